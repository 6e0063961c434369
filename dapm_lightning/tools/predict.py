"""dapm-lightning predict SOURCE --ckpt_path CKPT: depth, sky, camera and metric 3D for images, folders or videos.

SOURCE is one or more of: a folder of images (sub-folders included), a glob pattern ('flight/**/*.jpg'; .JPG
matches too), an image, a video file, a .txt list of paths (one a line); images of any sizes and aspects. The
network runs at the checkpoint's training size (the same pixel count in each image's aspect) unless
--image_width says otherwise. The Lightning form (``--config configs/predict.yaml``, every trainer setting,
several GPUs) is the same command with a config instead of SOURCE.
"""

from __future__ import annotations

import argparse
import difflib
import math
import signal
import sys
import warnings
from collections.abc import Callable, Sequence

from dapm_lightning.options import (  # nothing heavy until the command line is parsed: --help answers at once
    DEFAULT_BATCH_SIZE,
    DEFAULT_OUTPUTS,
    EXACT_SIGMA,
    IGD_BOUND_MARGIN,
    OUTPUT_KINDS,
    PRECISIONS,
    PRIOR_MODES,
    check_outputs,
)
from dapm_lightning.tools.argv import whole_number

LIGHTNING_OPTIONS = ("--config", "--data", "--trainer", "--model", "--print_config", "--seed_everything")
"""Options that select the Lightning form of ``predict``."""
EXIT_SIGTERM = 128 + signal.SIGTERM
"""Exit status of a run stopped by SIGTERM (143, as a process killed by it): a job script tells it from 0."""


def _stop_on_sigterm(signum: int, frame: object) -> None:
    raise SystemExit(EXIT_SIGTERM)


def is_lightning_form(args: Sequence[str]) -> bool:
    """Whether ``predict``'s arguments are the LightningCLI form (a config or dotted settings, no SOURCE)."""
    return any(a == option or a.startswith((option + ".", option + "=")) for a in args for option in LIGHTNING_OPTIONS)


class _Parser(argparse.ArgumentParser):
    """argparse without abbreviations, whose unknown-option error suggests the closest option in two lines."""

    argv: Sequence[str] = ()
    """The arguments being parsed (:func:`parse`), for what a missing SOURCE most likely means."""

    def error(self, message: str) -> None:  # type: ignore[override]
        if "required: SOURCE" in message and (taken := _sources_taken_as_outputs(self.argv)):
            message += (f" ({', '.join(map(repr, taken))} was read as an --outputs kind: put SOURCE before "
                        "--outputs, or give the kinds with commas, --outputs depth_npy,camera)")
        self.exit(2, f"{self.prog}: error: {message}\nSee `{self.prog} --help`.\n")


def _sources_taken_as_outputs(argv: Sequence[str]) -> list[str]:
    """The words after ``--outputs`` that are not output kinds (nor ``all``): SOURCEs that ``nargs="+"`` took."""
    taken: list[str] = []
    for index, word in enumerate(argv):
        if word == "--outputs":
            for value in argv[index + 1:]:
                if value.startswith("-"):
                    break
                taken += [part for part in value.split(",") if part and part not in (*OUTPUT_KINDS, "all")]
    return taken


positive, not_negative = whole_number(1), whole_number(0)


def number_in(low: float, high: float, what: str, *, high_included: bool = True) -> Callable[[str], float]:
    """An argparse type: a finite number from ``low`` to ``high`` (``what`` it is), or an error saying so."""

    def check(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number ({what})") from None
        if not (low <= value and (value <= high if high_included else value < high)):
            bound = f"[{low:g}, {high:g}{']' if high_included else ')'}"
            raise argparse.ArgumentTypeError(f"must be {what} in {bound}, got {text}")
        return value

    return check


def positive_metres(text: str) -> float:
    """An argparse type: a distance in metres above 0 (``inf`` allowed), or an error saying so."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of metres") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be a distance above 0 m, got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The one-line form's options."""
    parser = _Parser(prog="dapm-lightning predict", allow_abbrev=False, description=__doc__,
                     usage="%(prog)s SOURCE [SOURCE ...] --ckpt_path CKPT [--out DIR] [--device cpu|cuda|auto] "
                           "[--outputs KIND ...] [--telemetry FILE] [options]",
                     formatter_class=argparse.RawDescriptionHelpFormatter,
                     epilog="Every Lightning setting (devices, precision, DDP): "
                            "dapm-lightning predict --config configs/predict.yaml --help")
    parser.add_argument("source", nargs="+", metavar="SOURCE",
                        help="folder of images (sub-folders included), glob pattern, image, video or .txt list")
    parser.add_argument("--ckpt_path", "--ckpt", required=True,
                        help="a dapm-lightning checkpoint (.ckpt), or a model exported from one (.onnx: float32, fp16 "
                             "or int8; runs in onnxruntime on the CPU)")
    parser.add_argument("--out", default=None,
                        help="output folder (default: a new one per run: runs/predict, runs/predict2, ...)")
    parser.add_argument("--exist_ok", action="store_true",
                        help="add to an --out that holds files (its images' files are rewritten together)")
    parser.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto (default: %(default)s)")
    parser.add_argument("--outputs", nargs="+", default=list(DEFAULT_OUTPUTS), metavar="KIND",
                        help=f"per-image files, any of {', '.join(OUTPUT_KINDS)}, or all; spaces or commas "
                             f"(default: {','.join(DEFAULT_OUTPUTS)}; poses.csv/json and contact_sheet.png per run)")
    parser.add_argument("--image_width", type=positive, default=None,
                        help="network input width (default: the checkpoint's training size)")
    parser.add_argument("--batch_size", type=positive, default=DEFAULT_BATCH_SIZE,
                        help="images per forward pass (default: %(default)s)")
    parser.add_argument("--precision", choices=PRECISIONS, default="32", help="(default: %(default)s)")
    parser.add_argument("--frame_step", type=positive, default=1, help="videos: every N-th frame (default: 1)")
    parser.add_argument("--max_frames", type=positive, default=None, help="videos: stop after this many frames")
    parser.add_argument("--contact_sheet", type=not_negative, default=8,
                        help="contact_sheet.png of the first N images (at most 64); 0: none (default: %(default)s)")
    parser.add_argument("--depth_range", type=float, nargs=2, default=None, metavar=("MIN_M", "MAX_M"),
                        help="colour depth maps in this range of metres, the same for every image (maps to compare; "
                             "default: each map its own 2nd-98th percentile)")
    parser.add_argument("--points_stride", type=positive, default=None,
                        help="point clouds: every N-th row and column (default: about the network's resolution)")
    parser.add_argument("--points_max_depth", type=positive_metres, default=None,
                        help="point clouds: drop points farther than this (metres; sky is always dropped)")
    parser.add_argument("--channels_last", action="store_true", help="channels-last memory (NHWC convolutions)")
    parser.add_argument("--compile", action="store_true",
                        help="torch.compile the network (minutes to start; pays off on long videos)")
    parser.add_argument("--num_workers", type=not_negative, default=0, help="decoding processes (default: 0)")
    parser.add_argument("--quiet", "-q", action="store_true",
                        help="no progress bar and no notes (the bar shows only at a terminal anyway)")
    flight = parser.add_argument_group("telemetry (docs/predict.md): the pose the drone knows, for metric depth")
    flight.add_argument("--telemetry", default=None, metavar="FILE",
                        help="CSV name,height_m,pitch_deg,roll_deg,fov_deg (empty cell: unknown), or a video's SRT")
    flight.add_argument("--no_metadata", action="store_true",
                        help="ignore the images' DJI XMP / EXIF and a video's own .SRT")
    flight.add_argument("--sensor_width_mm", type=number_in(1e-3, 1e3, "a sensor width in mm"), default=None,
                        help="sensor width in mm (of the area the images cover): each image's EXIF FocalLength then "
                             "gives its FoV, before its 35 mm equivalent")
    flight.add_argument("--strict_telemetry", action="store_true",
                        help="stop when an image's XMP/EXIF or a video's SRT cannot be read (default: that image or "
                             "video falls back to the network's pose, with a warning)")
    flight.add_argument("--telemetry_mode", choices=PRIOR_MODES, default="condition",
                        help="into the network's IGD (condition), depth fitted afterwards (scale), or both "
                             "(default: %(default)s)")
    flight.add_argument("--telemetry_sigma", type=number_in(0.0, math.inf, "a standard deviation"), nargs=4,
                        default=EXACT_SIGMA,
                        metavar=("HEIGHT_M", "PITCH", "ROLL", "FOV"),
                        help="telemetry uncertainty; 0 replaces the network's value (default: 0 0 0 0)")
    flight.add_argument("--igd_bound", type=number_in(0.0, 10.0, "a margin", high_included=False),
                        default=IGD_BOUND_MARGIN, metavar="MARGIN",
                        help="images whose telemetry gives the height: each pixel's depth capped at (1 + MARGIN) x the "
                             "flat ground of the pose used (default: %(default)s; docs/predict.md)")
    flight.add_argument("--no_igd_bound", dest="igd_bound", action="store_const", const=None,
                        help="no IGD bound (ground far below the take-off level: a valley, the sea from a cliff)")
    return parser


def parse(argv: Sequence[str]) -> argparse.Namespace:
    """Parse the one-line form; an unknown option is named with the closest valid one."""
    parser = build_parser()
    parser.argv = list(argv)
    args, unknown = parser.parse_known_intermixed_args(list(argv))  # SOURCE ... before, between or after options
    if unknown:
        options = [o for action in parser._actions for o in action.option_strings]
        flag = unknown[0].split("=")[0]
        close = difflib.get_close_matches(flag, options, n=2)
        hint = f" (did you mean {' or '.join(close)}?)" if close else ""
        parser.error(f"unknown option {unknown[0]!r}{hint}")
    try:
        args.outputs = check_outputs(args.outputs)
    except ValueError as error:
        parser.error(str(error))
    return args


def _short_warning(message: Warning | str, category: type[Warning], filename: str, lineno: int,
                   line: str | None = None) -> str:
    return f"warning: {message}\n"


def check_not_lightning_word(ckpt_path: str) -> None:
    """Refuse Lightning's ``--ckpt_path`` words (``last``, ``best``...), which name a file only in its form."""
    from pathlib import Path

    from dapm_lightning.training.checkpoint_files import is_lightning_checkpoint_word

    if is_lightning_checkpoint_word(ckpt_path) and not Path(ckpt_path).exists():
        raise ValueError(f"--ckpt_path {ckpt_path}: no such file; this form of predict takes a checkpoint file, not "
                         "Lightning's words for one (last, best): `--ckpt_path last` works in predict's Lightning "
                         "form, whose configuration names the run's folder (docs/long_jobs.md).\nFix: give the "
                         "checkpoint file, e.g. --ckpt_path outputs/RUN/tensorboard/version_0/checkpoints/last.ckpt")


def predict_main(argv: Sequence[str]) -> None:
    """``dapm-lightning predict SOURCE --ckpt_path CKPT [--out DIR] [--device cpu|cuda|auto] [--outputs ...]``."""
    args = parse(argv)
    from dapm_lightning.inference.inputs import PredictSource
    from dapm_lightning.inference.predictor import DAPMPredictor
    from dapm_lightning.inference.run_folder import run_folder
    from dapm_lightning.inference.runtime import check_device
    from dapm_lightning.inference.sources import resolve_sources
    from dapm_lightning.inference.writers import PredictionFiles, check_output_outside_source
    from dapm_lightning.tools.progress import progress_bar, quiet_notes

    quiet_notes(args.quiet)
    check_not_lightning_word(args.ckpt_path)
    check_device(args.device, args.precision)  # before the model loads: gpu for cuda, 16 on the CPU
    warnings.formatwarning = _short_warning  # "warning: MESSAGE", not the source line that raised it
    # what can be found wrong without the model is found before it loads (seconds): a missing source, an
    # output folder inside it (its files would be read back as images) or one that cannot be written
    resolve_sources(args.source)
    check_output_outside_source(run_folder(None) if args.out is None else args.out, args.source, "--out")
    out = run_folder(args.out, args.exist_ok)
    files = PredictionFiles(out, args.outputs, args.points_stride, args.points_max_depth,
                            contact_sheet=args.contact_sheet, option="--out", depth_range=args.depth_range)
    predictor = DAPMPredictor.from_checkpoint(args.ckpt_path, args.image_width, args.device,
                                              precision=args.precision, batch_size=args.batch_size,
                                              channels_last=args.channels_last, compile=args.compile,
                                              telemetry_mode=args.telemetry_mode,
                                              telemetry_sigma=args.telemetry_sigma, igd_bound=args.igd_bound)
    source = PredictSource(tuple(args.source), args.frame_step, args.max_frames, args.telemetry, not args.no_metadata,
                           args.sensor_width_mm, args.strict_telemetry)
    # the pixels ride along (the points' colours, the contact sheet, a video's preview): one batch at a time
    loader = predictor.loader(source, keep_rgb=True, num_workers=args.num_workers)
    previous = signal.signal(signal.SIGTERM, _stop_on_sigterm)  # as Ctrl-C: the tables take the images written
    try:
        with files, progress_bar(loader.expected_images(), args.quiet) as bar:  # no folder if nothing was written
            for batch in loader:
                for prediction in predictor.predict_batch(batch):
                    files.add(prediction)
                    bar.update(1)
            bar.close()
            print(files.finish(), file=sys.stdout, flush=True)
    except BaseException as error:  # a damaged image, Ctrl-C, SIGTERM, a failed write: the tables were brought
        sigterm = isinstance(error, SystemExit) and error.code == EXIT_SIGTERM  # up to date on closing
        if sigterm:
            print(f"\nstopped by SIGTERM{f': {files.kept}' if files.kept else ''}", file=sys.stderr, flush=True)
        elif files.kept:
            print(f"stopped early by the error below: {files.kept}", file=sys.stderr, flush=True)
        raise
    finally:
        signal.signal(signal.SIGTERM, previous)
