"""The ``dapm-lightning`` command: LightningCLI subcommands plus the tools synth, doctor, collect-carla, export."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path



def synth_main(argv: Sequence[str]) -> None:
    """``dapm-lightning synth``: write a synthetic UAPD-format data set."""
    from dapm_lightning.data.synthetic import generate_uapd

    parser = argparse.ArgumentParser(
        prog="dapm-lightning synth",
        description="Render a synthetic data set in UAPD layout and naming: OUT/{train,val}/{rgb,depth}/NAME.png "
                    "(depth: range in metres, 8-bit log encoded, grey 255 = sky).")
    parser.add_argument("--out", type=Path, required=True, help="output root folder")
    parser.add_argument("--train", type=int, default=200, help="training images (default 200)")
    parser.add_argument("--val", type=int, default=50, help="validation images (default 50)")
    parser.add_argument("--size", type=int, nargs="+", default=[128], metavar="S",
                        help="S for SxS images, or H W (default 128)")
    parser.add_argument("--seed", type=int, default=0, help="same seed, same bytes (default 0)")
    parser.add_argument("--workers", type=int, default=None, help="processes (default: CPU count, max 8)")
    args = parser.parse_args(list(argv))
    if len(args.size) not in (1, 2) or min(args.size) < 1:
        parser.error(f"--size takes S or H W (positive), got {args.size}")
    size = args.size[0] if len(args.size) == 1 else (args.size[0], args.size[1])
    out = generate_uapd(args.out, train=args.train, val=args.val, size=size, seed=args.seed, workers=args.workers)
    print(f"wrote {args.train} train + {args.val} val images to {out}")


def main(argv: Sequence[str] | None = None) -> None:
    """Entry point of ``dapm-lightning``."""
    args = list(sys.argv[1:] if argv is None else argv)
    if args and args[0] == "synth":
        synth_main(args[1:])
        return
    if args and args[0] == "doctor":
        from dapm_lightning.doctor import doctor_main

        raise SystemExit(doctor_main(args[1:]))
    if args and args[0] == "collect-carla":
        from dapm_lightning.carla_collect import collect_main

        collect_main(args[1:])
        return
    if args and args[0] == "export":
        from dapm_lightning.export import export_main

        export_main(args[1:])
        return
    from dapm_lightning.lightning_cli import run_lightning_cli

    run_lightning_cli(None if argv is None else args)
