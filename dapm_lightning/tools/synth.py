"""``dapm-lightning synth``: render a synthetic UAPD-format data set, whole or one shard of it."""

from __future__ import annotations

import argparse
import math
import re
import signal
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from dapm_lightning.data.files import WriteError, check_folder_writable
from dapm_lightning.data.synthetic import (
    FAMILIES,
    SynthFolderError,
    generate_uapd,
    is_current,
    normalize_families,
    settings_changes,
    shard_range,
)
from dapm_lightning.geometry.constants import MAX_DEPTH_M, MIN_DEPTH_LIMIT_M
from dapm_lightning.tools.progress import progress_bar


def parse_shard(text: str) -> tuple[int, int]:
    """``"K/N"`` (0-based K, as ``$SLURM_ARRAY_TASK_ID`` with ``--array=0-(N-1)``) to ``(K, N)``."""
    match = re.fullmatch(r"\s*(\d+)\s*/\s*(\d+)\s*", text)
    if not match:
        raise argparse.ArgumentTypeError(f"--shard takes K/N (e.g. 3/16), got {text!r}")
    k, n = int(match.group(1)), int(match.group(2))
    if n < 1 or k >= n:
        raise argparse.ArgumentTypeError(f"--shard K/N needs 0 <= K < N, got {text!r}")
    return k, n


def parse_families(text: str) -> dict[str, float]:
    """``"downtown=2,suburb=1"`` (a name alone weighs 1) to normalised weights."""
    try:
        return normalize_families(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``dapm-lightning synth``."""
    parser = argparse.ArgumentParser(
        prog="dapm-lightning synth",
        description="Render a synthetic data set in UAPD layout and naming: OUT/{train,val}/{rgb,depth}/NAME.png "
                    "(depth: range in metres, 8-bit log encoded, grey 255 = at or beyond 1000 m). Scene families: "
                    f"{', '.join(FAMILIES)}. The settings go to OUT/synth.json; a folder holding a set of other "
                    "settings is refused unless --replace is given. See docs/synthetic.md.")
    parser.add_argument("--out", type=Path, required=True, help="output root folder")
    parser.add_argument("--train", type=int, default=200, help="training images (default 200)")
    parser.add_argument("--val", type=int, default=50, help="validation images (default 50)")
    parser.add_argument("--size", type=int, nargs="+", default=[128], metavar="S",
                        help="S for SxS images, or H W (default 128)")
    parser.add_argument("--seed", type=int, default=0, help="same seed, same bytes (default 0)")
    parser.add_argument("--workers", type=int, default=None, help="processes (default: CPU count, max 8)")
    parser.add_argument("--families", type=parse_families, default=None, metavar="NAME=W,...",
                        help="weights of the scene families, e.g. 'downtown=2,suburb=1,water=0.5' "
                             "(families left out are not rendered; default: all equally)")
    parser.add_argument("--shard", type=parse_shard, default=(0, 1), metavar="K/N",
                        help="render only part K of N (0-based) of the image list, e.g. $SLURM_ARRAY_TASK_ID/16; "
                             "all N parts together are byte-identical to one run")
    parser.add_argument("--distortion", action="store_true",
                        help="random radial lens distortion per image (k in [-0.5, 0.5], kcube in [-0.2, 0.2], "
                             "written into the name), applied to image and depth alike")
    parser.add_argument("--max_depth", type=float, default=MAX_DEPTH_M, metavar="M",
                        help=f"depth limit of the log encoding, grey 255 (default {MAX_DEPTH_M:g}, UAPD's); train "
                             "with the same model.net.igd.max_depth and data.init_args.max_depth")
    parser.add_argument("--replace", action="store_true",
                        help="render over a set of other settings in OUT (its images are deleted)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar (there is none off a terminal)")
    parser.add_argument("--no-effects", dest="effects", action="store_false",
                        help="no camera processing (exposure, white balance, blur, noise, JPEG artefacts)")
    return parser


EXIT_SIGTERM = 128 + signal.SIGTERM
"""Exit status of a render stopped by SIGTERM (143, as a process killed by it): a job script tells it from 0."""


def _stop_on_sigterm(signum: int, frame: object) -> None:
    raise SystemExit(EXIT_SIGTERM)  # what was rendered is told after the stop (synth_main), not from the handler


def synth_main(argv: Sequence[str]) -> None:
    """Entry point of ``dapm-lightning synth``."""
    parser = build_parser()
    args = parser.parse_args(list(argv))
    if len(args.size) not in (1, 2) or min(args.size) < 1:
        parser.error(f"--size takes S or H W (positive), got {args.size}")
    if not (math.isfinite(args.max_depth) and args.max_depth > MIN_DEPTH_LIMIT_M):
        parser.error(f"--max_depth must be > {MIN_DEPTH_LIMIT_M:g} m, got {args.max_depth}")
    if args.train < 0 or args.val < 0:
        parser.error("--train and --val must be >= 0")
    if args.train + args.val == 0:
        parser.error("nothing to render: --train and --val are both 0 (give either a number of images)")
    if args.workers is not None and args.workers < 1:
        parser.error(f"--workers must be at least 1 (omit it for the CPU count, at most 8), got {args.workers}")
    size = args.size[0] if len(args.size) == 1 else (args.size[0], args.size[1])
    part = shard_range(args.train + args.val, args.shard)
    check_folder_writable(args.out, "--out")
    chosen = dict(train=args.train, val=args.val, size=size, seed=args.seed, families=args.families,
                  effects=args.effects, distortion=args.distortion, max_depth=args.max_depth)
    changes = settings_changes(args.out, **chosen)
    if (args.out / "synth.json").is_file() and changes and not args.replace and args.shard[1] == 1:
        raise SynthFolderError(f"{args.out}: holds a data set of other settings ({changes}), whose images this "
                               "render would delete.\nFix: add --replace to render over it, or give another --out")
    start = time.perf_counter()
    previous = signal.signal(signal.SIGTERM, _stop_on_sigterm)  # as Ctrl-C: the worker processes end with the run
    try:
        with progress_bar(len(part), quiet=args.quiet, what="rendering") as bar:
            out = generate_uapd(args.out, train=args.train, val=args.val, size=size, seed=args.seed,
                                workers=args.workers, families=args.families, effects=args.effects, shard=args.shard,
                                distortion=args.distortion, max_depth=args.max_depth, progress=bar.update)
    except (SystemExit, KeyboardInterrupt) as stop:
        if isinstance(stop, KeyboardInterrupt) or stop.code == EXIT_SIGTERM:  # synth.json may have been written
            done = is_current(args.out, **chosen) and args.shard[1] == 1  # just before the stop came
            print(f"\nstopped by {'Ctrl-C' if isinstance(stop, KeyboardInterrupt) else 'SIGTERM'}: "
                  + ("the set was complete (synth.json written)" if done else
                     "no synth.json written; rerun the same command to render the set"), file=sys.stderr, flush=True)
        raise
    except SynthFolderError:
        raise  # a folder problem, not a wrong option: its message and fix, without the usage
    except WriteError as error:  # a full or read-only disk mid-render: the set is not whole
        unfinished = ("this shard's images are unfinished; rerun this shard" if args.shard[1] > 1 else
                      "no synth.json written (the set is unfinished, as `dapm-lightning doctor` reports); rerun the "
                      "same command")
        print(f"stopped by the error below: {unfinished} once the error is fixed", file=sys.stderr, flush=True)
        if "--out" in error.fix:
            raise
        raise WriteError(error.path, error.reason, f"{error.fix} (--out)") from error
    except ValueError as error:
        parser.error(str(error))
    finally:
        signal.signal(signal.SIGTERM, previous)
    seconds = time.perf_counter() - start
    what = (f"images {part.start}..{part.stop - 1} (shard {args.shard[0]}/{args.shard[1]}) of "
            if args.shard[1] > 1 else "")
    print(f"wrote {what}{args.train} train + {args.val} val images to {out} "
          f"({len(part) / max(seconds, 1e-9):.1f} images/s)")


if __name__ == "__main__":
    import sys

    synth_main(sys.argv[1:])
