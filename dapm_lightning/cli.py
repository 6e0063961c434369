"""The ``dapm-lightning`` command: LightningCLI subcommands plus the tools synth, doctor, collect-carla, export.

Every subcommand runs with short error messages (:mod:`dapm_lightning.tools.errors`).
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Sequence

TOOLS = {
    "synth": ("dapm_lightning.tools.synth", "synth_main", "render a synthetic data set in UAPD layout and naming"),
    "doctor": ("dapm_lightning.tools.doctor", "doctor_main", "check a UAPD-format data set against its poses"),
    "export": ("dapm_lightning.tools.export", "export_main", "export a checkpoint to ONNX, checked with onnxruntime"),
    "collect-carla": ("dapm_lightning.tools.carla_collect", "collect_main",
                      "collect UAPD-format images from a running CARLA server"),
}
"""Subcommands beside LightningCLI's: ``name -> (module, function, one-line help)``."""

LIGHTNING_SUBCOMMANDS = {"fit": "train (and validate) a model", "validate": "validate a checkpoint",
                         "test": "test a checkpoint (metrics, viewpoint figure)",
                         "predict": "depth, pose, camera and metric 3D for images, folders, globs or videos"}


def usage() -> str:
    """Top-level help: every subcommand with one line."""
    rows = [*LIGHTNING_SUBCOMMANDS.items(), *((name, tool[2]) for name, tool in TOOLS.items())]
    lines = ["usage: dapm-lightning SUBCOMMAND [--help] ...   (dapm-lightning --version: the version)", "",
             "DAPM: metric depth and camera pose (height, pitch, roll, FoV) from one UAV image.", "",
             "subcommands:"] + [f"  {name:<15}{text}" for name, text in rows]
    lines += ["", "`dapm-lightning SUBCOMMAND --help` lists every setting of one subcommand; errors show a",
              "short message, and the Python traceback with --debug (or DAPM_DEBUG=1)."]
    return "\n".join(lines)


def packaged_configs(args: Sequence[str]) -> list[str]:
    """``--config configs/NAME.yaml`` that is not there reads the package's own config of that name.

    For an installed package or another working directory: ``dapm_lightning/configs/NAME.yaml``, when there
    is one.
    """
    from pathlib import Path

    packaged = Path(__file__).resolve().parent / "configs"
    result = list(args)
    for k, value in enumerate(result):
        name = value.split("=", 1)[1] if value.startswith("--config=") else value
        if (k > 0 and result[k - 1] == "--config") or value.startswith("--config="):
            path = Path(name)
            if not path.exists() and (packaged / path.name).is_file():
                shipped = str(packaged / path.name)
                result[k] = f"--config={shipped}" if value.startswith("--config=") else shipped
    return result


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of ``dapm-lightning``.

    User errors (bad paths, data, checkpoints, settings) end in a short message and exit status 1;
    ``--debug`` anywhere on the command line (or ``DAPM_DEBUG=1``) shows the traceback instead.
    """
    from dapm_lightning.tools.errors import debug_requested, run_reporting_errors

    debug, args = debug_requested(sys.argv[1:] if argv is None else argv)
    if not args or args[0] in ("-h", "--help"):
        print(usage())
        return
    if args[0] in ("--version", "-V", "version"):
        from dapm_lightning import __version__

        print(f"dapm-lightning {__version__}")
        return
    if args[0] in TOOLS:
        module_name, function, _ = TOOLS[args[0]]
        entry = getattr(importlib.import_module(module_name), function)
        result = run_reporting_errors(lambda: entry(args[1:]), debug)
        if isinstance(result, int):
            raise SystemExit(result)
        return
    if args[0] not in LIGHTNING_SUBCOMMANDS and not args[0].startswith("-"):
        import difflib

        close = difflib.get_close_matches(args[0], [*LIGHTNING_SUBCOMMANDS, *TOOLS], n=1)
        hint = f" (did you mean {close[0]}?)" if close else ""
        print(f"error: unknown subcommand {args[0]!r}{hint}\n\n{usage()}", file=sys.stderr)
        raise SystemExit(2)
    if args[0] == "predict":
        from dapm_lightning.tools.predict import is_lightning_form, predict_main

        if not is_lightning_form(args[1:]):  # the one-line form: SOURCE --ckpt_path CKPT [--out DIR] ...
            run_reporting_errors(lambda: predict_main(args[1:]), debug)
            return
        import dapm_lightning.inference.datamodule  # noqa: F401  (--data PredictDataModule by its short name)
        from dapm_lightning.tools.progress import show_progress

        if not show_progress() and not any(a.startswith("--trainer.enable_progress_bar") for a in args):
            args = [args[0], "--trainer.enable_progress_bar=false", *args[1:]]  # no bar into a file or a pipe
    args = packaged_configs(args)
    from dapm_lightning.training.lightning_cli import run_lightning_cli

    if argv is None:  # LightningCLI reads sys.argv itself (and warns when given both): without --debug
        sys.argv = [sys.argv[0], *args]
    run_reporting_errors(lambda: run_lightning_cli(None if argv is None else args), debug)
