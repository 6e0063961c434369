"""dapm-lightning export: an ONNX model (image in; depth, sky probability and/or pose out), checked on the spot.

Any DAPM checkpoint exports: the full model (depth_m, sky_prob, pose, with the telemetry inputs prior, prior_known
and prior_sigma), DAPM(D) (depth_m, sky_prob) and DAPM(P) (pose). Batch, height and width are dynamic by default
(any size: the predict path feeds the same network size as PyTorch). The file carries the network's settings and
training size as metadata, so `dapm-lightning predict SOURCE --ckpt_path MODEL.onnx` needs nothing else.
After writing, onnxruntime and PyTorch run the same random inputs at two sizes and the largest difference of
each output is printed; beyond the tolerances (float32: 0.1 % of depth pixels off by more than 1 %, sky
probability 0.01, pose 0.05 m or deg; float16: 1 %, 0.15, 0.5) the file is removed and the export fails, unless
--force true. --fp16 true stores the weights and runs the network in half precision with float32
input and outputs. --int8 true also writes an int8 model for CPUs and edge boards (onnxruntime static QDQ
quantisation of the encoder, depth decoder and depth heads, per-channel weights; the pose branch and the
metric decoding stay float32), calibrated on synthetic renders at the training size (and some at the export
size), then measured against the float32 model on held-out renders: when its depth d1 drops by more than
0.01 or a pose median grows by more than 0.5 (m or deg), the export fails and keeps no int8 file unless
--force true. A large model's weights go beside the graph in NAME.onnx.data (keep both files together; the .onnx
records that name: to rename a model, export it again with --out NEW.onnx).
Settings can come from a YAML file (--config FILE; --print_config shows one).
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from dapm_lightning.data.files import (
    WRITE_ERRNOS,
    WriteError,
    check_folder_writable,
    is_full_disk,
    make_folder,
    remove_empty_folders,
    write_error,
)
from dapm_lightning.inference.inputs import SIZE_MULTIPLE, checkpoint_network_size, network_size
from dapm_lightning.inference.onnx import (
    CHECK_DRAW,
    DEPTH_SHARE_OFF,
    EXPORT_TOLERANCES,
    MAX_EXPORT_SIDE,
    export_metadata,
    export_mismatches,
    export_onnx,
    move_exported,
    weights_file,
    write_metadata,
)


class ExportMismatch(RuntimeError):
    """The exported model's outputs disagree with PyTorch's beyond :data:`EXPORT_TOLERANCES` (no file kept)."""

    explained = True


class Int8Refused(RuntimeError):
    """The int8 model loses too much accuracy against the float32 one (no int8 file kept)."""

    explained = True  # the message says what it is and the fix: printed as it is (tools/errors.py)


def export(ckpt_path: str | Path, out: Path | None = None, height: int | None = None, width: int | None = None,
           dynamic: bool = True, fp16: bool = False, checks: int = 2, int8: bool = False,
           calibration_images: int = 64, verdict_images: int = 256, force: bool = False,
           threads: int | None = 1) -> Path:
    """Export a DAPM checkpoint to ONNX and check it with onnxruntime against PyTorch.

    Args:
        ckpt_path: the checkpoint (any DAPM: full, DAPM(D), DAPM(P)); loaded with weights_only=True.
        out: the ONNX file (default: the checkpoint's path with .onnx, or _fp16.onnx, _int8.onnx).
        height: example input height (and the checked size). Default: the checkpoint's training size.
        width: example input width. Default: the checkpoint's training size.
        dynamic: dynamic batch, height and width (any size); false: fixed [1, 3, height, width].
        fp16: half-precision weights and arithmetic (float32 input and outputs); for GPUs and Jetsons.
        checks: random inputs compared with PyTorch at each checked size.
        int8: static int8 quantisation (QDQ, per-channel weights) of the float32 model, written as
            NAME_int8.onnx beside the float32 model NAME.onnx, if it keeps the float model's accuracy.
        calibration_images: synthetic renders at the training size that calibrate the int8 ranges (a quarter
            as many more at the export size when it differs).
        verdict_images: held-out renders at the export size on which int8 is measured against float32.
        force: keep the exported model even when it disagrees with PyTorch beyond
            :data:`~dapm_lightning.inference.onnx.EXPORT_TOLERANCES`, and the int8 model even when it fails the
            verdict.
        threads: onnxruntime threads for the verdict's timing (default 1: steady on a busy machine; 0: onnxruntime's).
    """
    from dapm_lightning.training.checkpoint_files import check_checkpoint_there, is_remote
    from dapm_lightning.training.checkpointing import load_dapm_module

    if is_remote(ckpt_path):  # before Path(), which would fold its "//"
        raise ValueError(f"{ckpt_path}: export reads a local checkpoint file (the model's metadata records its "
                         "SHA-256).\nFix: copy the checkpoint here first and export the copy")
    ckpt_path = Path(ckpt_path)
    if int8 and fp16:
        raise ValueError("--int8 quantises the float32 model: leave --fp16 out")
    check_export_size(height, width)
    check_export_counts(checks=checks, calibration_images=calibration_images, verdict_images=verdict_images)
    check_checkpoint_there(ckpt_path)  # before --out, whose default comes from the checkpoint's name
    check_not_onnx(ckpt_path)  # before --out, whose default from an .onnx name would be that name itself
    suffix = "_fp16" if fp16 else "_int8" if int8 else ""
    out = Path(out) if out else ckpt_path.with_name(ckpt_path.stem + suffix + ".onnx")
    check_export_path(out, ckpt_path)
    float_out = out.with_name(out.stem.removesuffix("_int8") + ".onnx") if int8 else out
    if float_out == out:
        float_out = out.with_name(out.stem + "_float32.onnx") if int8 else out
    module = load_dapm_module(ckpt_path, map_location="cpu")
    trained = checkpoint_network_size(module)
    if height is None or width is None:
        height, width = network_size(height or trained[0], width or trained[1], None)
    start = time.perf_counter()
    metadata = {**export_metadata(module.net, module.train_image_size, ckpt_path),
                "dapm.precision": "float16" if fp16 else "float32"}
    created = make_folder(float_out.parent)  # removed again if nothing is kept in them (a failure, Ctrl-C)
    # written beside the target first, moved into place once checked: a failed export leaves an earlier one whole
    try:
        staging = Path(tempfile.mkdtemp(prefix=f".{float_out.name}.", dir=float_out.parent))
    except OSError as error:  # a folder that looked writable but is not (/sys): named as --out, not the staging
        remove_empty_folders(created)
        raise _out_error(float_out, error) from error
    try:
        rows = export_onnx(module.net.eval(), staging / float_out.name, (height, width), checks=checks,
                           dynamic=dynamic, fp16=fp16, metadata=metadata)
        failures = export_mismatches(rows, fp16)
        kept = not failures or force
        if kept:
            move_exported(staging / float_out.name, float_out)
    except OSError as error:
        if isinstance(error, WriteError) or (error.errno not in WRITE_ERRNOS and not is_full_disk(error)):
            raise
        raise _out_error(float_out, error) from error  # a full disk while exporting: --out named, not the staging
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        remove_empty_folders(created)
    names = [k for k in rows[0] if k not in ("shape", CHECK_DRAW, DEPTH_SHARE_OFF)]
    shape = "[batch, 3, height, width]" if dynamic else f"[1, 3, {height}, {width}]"
    data = weights_file(float_out)
    weights = (f"; weights in {data.name}: keep it beside the .onnx file under this name, which the .onnx records"
               if data.is_file() and kept else "")
    precision = "float16 inside, float32 input and outputs" if fp16 else "float32"
    print(f"{'wrote' if kept else 'exported, not written:'} {float_out} ({precision}{weights}) in "
          f"{time.perf_counter() - start:.0f} s: input 'image' {shape} float RGB in [0, 1]; outputs {', '.join(names)}")
    for row in rows:
        draw, draws = row.get(CHECK_DRAW, (1, 1))
        print(f"  check {tuple(row['shape'])}" + (f", random input {draw} of {draws}" if draws > 1 else "")
              + ": max |onnxruntime - PyTorch fp32|: "
              + ", ".join(f"{n} {row[n]:.3g}" for n in names)
              + (f"; depth pixels off by > 1 %: {row[DEPTH_SHARE_OFF]:.2%}" if DEPTH_SHARE_OFF in row else ""))
    if not kept:
        earlier = f" (the earlier {float_out.name} there is left as it was)" if float_out.is_file() else ""
        raise ExportMismatch(
            f"{float_out}: onnxruntime's outputs disagree with PyTorch's ({'; '.join(failures)}; the limits: "
            f"{', '.join(f'{k} {v:g}' for k, v in EXPORT_TOLERANCES[fp16].items())}), so it was not written"
            f"{earlier}.\n"
            "Fix: this is a bug of the export (an operator exported with other semantics): report it with the "
            "sizes above; exporting at a fixed size (--dynamic false --height H --width W) may avoid it; "
            "--force true keeps the file anyway.")
    if failures:
        print(f"kept anyway (--force true): {float_out} disagrees with PyTorch ({'; '.join(failures)})")
    if int8:
        calibrated = trained if dynamic else (height, width)  # a fixed-size graph takes its own size alone
        _int8(float_out, out, calibrated, (height, width), calibration_images, verdict_images, force, threads,
              {**metadata, "dapm.precision": "int8"})
    return out if int8 else float_out


def _int8(float_out: Path, out: Path, trained: tuple[int, int], size: tuple[int, int], calibration: int,
          verdict_images: int, force: bool, threads: int | None, metadata: dict[str, str]) -> None:
    """Quantise ``float_out`` into ``out``, measure it against float32, and keep it if it passes (or ``force``)."""
    from dapm_lightning.inference.int8_check import compare_int8
    from dapm_lightning.inference.quantize import calibration_images, quantize_int8, render_set

    start = time.perf_counter()
    extra = max(1, calibration // 4) if tuple(size) != tuple(trained) else 0
    out.unlink(missing_ok=True)  # an int8 file from an earlier export is not this model's
    partial = out.with_name(out.stem + ".partial.onnx")
    try:
        quantize_int8(float_out, partial, calibration_images(trained, size, at_train=calibration, at_export=extra))
        write_metadata(partial, metadata)  # the int8 file runs on its own too
        verdict = compare_int8(float_out, partial, render_set(size, verdict_images), threads=threads)
        if verdict.passed or force:
            partial.replace(out)
    finally:
        partial.unlink(missing_ok=True)
    seconds = time.perf_counter() - start
    calibrated = f"{calibration} renders at {trained[0]}x{trained[1]}" + (
        f" + {extra} at {size[0]}x{size[1]}" if extra else "")
    if not out.is_file():
        print("\n".join(verdict.lines()))
        raise Int8Refused(
            f"int8 model not kept ({'; '.join(verdict.failures)}): {out} was not written.\n"
            f"Fix: use the float32 model {float_out} (written, exact), or export it with --fp16 true for GPUs; "
            "calibrating at the size you predict at (--height, --width) or a longer-trained checkpoint may "
            "quantise better; --force true keeps the int8 model anyway.")
    print(f"wrote {out} (int8: QDQ, int8 weights per output channel, uint8 activations; pose branch and metric "
          f"decoding float32; calibrated on {calibrated}) in {seconds:.0f} s; this model's own checks:")
    print("\n".join(verdict.lines()))
    if not verdict.passed:
        print(f"kept anyway (--force true): {out} is less accurate than {float_out}")


def check_export_size(height: int | None, width: int | None) -> None:
    """Refuse an example input smaller than the encoder's stride or larger than an exported graph takes."""
    for name, side in (("--height", height), ("--width", width)):
        if side is not None and not SIZE_MULTIPLE <= side <= MAX_EXPORT_SIDE:
            raise ValueError(f"{name} {side}: an exported model takes sides of {SIZE_MULTIPLE} to {MAX_EXPORT_SIDE} "
                             f"pixels (at least the encoder's stride).\nFix: give {name} in that range, or leave it "
                             "out for the checkpoint's training size.")


def check_export_counts(**counts: int) -> None:
    """Refuse a count below 1 (``--checks``, ``--calibration_images``, ``--verdict_images``) before the export."""
    for name, count in counts.items():
        if count < 1:
            raise ValueError(f"--{name} {count}: at least 1 (the export is checked on random inputs, an int8 model "
                             f"calibrated and measured on renders).\nFix: give --{name} 1 or more, or leave it out")


def check_not_onnx(ckpt_path: Path) -> None:
    """Refuse an exported model given as the checkpoint: a name ending in .onnx, or an ONNX file by its content."""
    from dapm_lightning.training.checkpoint_files import looks_like_onnx

    named = ckpt_path.suffix.lower() == ".onnx"
    if not named:
        try:
            with open(ckpt_path, "rb") as stream:
                if not looks_like_onnx(stream.read(16)):
                    return
        except OSError:  # unreadable: read_checkpoint names it
            return
    run = (f"dapm-lightning predict SOURCE --ckpt_path {ckpt_path}" if named else
           f"dapm-lightning predict SOURCE --ckpt_path {ckpt_path.with_suffix('.onnx')} (renamed to end in .onnx, "
           "which is how predict tells an ONNX model)")
    raise ValueError(f"{ckpt_path}: an exported ONNX model already, not a checkpoint: export takes the checkpoint "
                     "written by `dapm-lightning fit` (a .ckpt file, e.g. the run's last.ckpt).\nFix: export that "
                     f".ckpt; to run this ONNX model, give it to predict directly: {run}")


def check_export_path(out: Path, ckpt_path: Path) -> None:
    """Refuse an ``--out`` where no model can be written, before the export's minutes.

    A folder, a name not ending in .onnx, the checkpoint itself, a path under a file, a read-only or unwritable folder.
    """
    if out.is_dir():
        raise ValueError(f"--out {out} is a folder.\nFix: give the file to write, e.g. --out "
                         f"{out / (ckpt_path.stem + '.onnx')}")
    if out.suffix.lower() != ".onnx" or out.resolve() == ckpt_path.resolve():
        raise ValueError(f"--out {out}: an exported model is written to a file ending in .onnx (an existing one "
                         f"is replaced, and nothing else is).\nFix: --out {out.with_suffix('.onnx')}")
    check_folder_writable(out.parent, "--out")  # before the export's minutes, not after


def _out_error(out: Path, error: OSError) -> WriteError:
    """A failed write of the export (in its hidden staging folder beside ``out``, or the move) naming ``out``."""
    failed = write_error(out, error)
    return WriteError(out, failed.reason, f"{failed.fix} (--out)")


def export_main(argv: Sequence[str]) -> None:
    """``dapm-lightning export CKPT [--out FILE] [--height H --width W] [--fp16 | --int8 [--force]]``.

    The checkpoint positional or ``--ckpt_path CKPT``; booleans as flags (``--int8``) or with
    their value (``--int8 true``).
    """
    from jsonargparse import auto_cli

    from dapm_lightning.tools.argv import flag_options

    args = list(argv)
    if args and not args[0].startswith("-") and "--ckpt_path" not in args and not any(
            a.startswith("--ckpt_path=") for a in args):
        args = ["--ckpt_path", *args]
    args = flag_options(args, ["--int8", "--fp16", "--force", "--dynamic"])
    auto_cli(export, args=args, as_positional=False, prog="dapm-lightning export", description=__doc__)
