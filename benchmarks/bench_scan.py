"""Speed of the start-up scan of a UAPD-format data set, beside a header-only check and a full decode.

``python -m benchmarks.bench_scan --pairs 2000 --size 512``: renders a few synthetic pairs at ``size`` (PNG files as
the generator writes them), copies them under ``pairs`` distinct names, and times, in files per second (an RGB and a
depth PNG per pair):

- ``scan``: building ``UAPDDataset`` (names parsed, every PNG's structure and chunk CRCs checked, in
  ``SCAN_THREADS`` threads), what ``fit`` and ``doctor`` do at start-up;
- ``scan, 1 thread``: the same in one thread;
- ``header only``: the check the scan did before (signature, IHDR, the IEND tail; 3 small reads a file);
- ``decode``: ``cv2.imread`` of every file, what finding damage by decoding would cost (``doctor`` does it).

The files were just written, so they are read from the page cache: a cold disk or a network file system adds its
reading time to the first three alike.
"""

from __future__ import annotations

import argparse
import shutil
import struct
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2

from dapm_lightning.data import pngcheck
from dapm_lightning.data.synthetic import generate_uapd
from dapm_lightning.data.uapd import UAPDDataset, format_uapd_filename, parse_uapd_filename, pose_from_parsed


def header_only(path: Path) -> None:
    """The scan's former check: the signature and IHDR at the start, the IEND chunk at the end."""
    with path.open("rb") as handle:
        head = handle.read(33)
        handle.seek(-12, 2)
        tail = handle.read()
    if head[:8] != b"\x89PNG\r\n\x1a\n" or head[12:16] != b"IHDR" or tail[4:8] != b"IEND":
        raise ValueError(f"{path}: bad PNG")
    struct.unpack(">IIBB", head[16:26])


def make_data(root: Path, pairs: int, size: int, rendered: int) -> list[Path]:
    """``pairs`` pairs under ``root/train``: copies of ``rendered`` synthetic pairs under distinct names."""
    source = generate_uapd(root / "source", train=rendered, val=0, size=size, seed=0, workers=1)
    names = sorted(p.name for p in (source / "train" / "rgb").iterdir())
    files = []
    for sub in ("rgb", "depth"):
        (root / "data" / "train" / sub).mkdir(parents=True)
    for k in range(pairs):
        name = names[k % len(names)]
        new = format_uapd_filename(["copy", f"{k:06d}"], pose_from_parsed(parse_uapd_filename(name)))
        for sub in ("rgb", "depth"):
            target = root / "data" / "train" / sub / new
            shutil.copyfile(source / "train" / sub / name, target)
            files.append(target)
    return files


def best_rate(count: int, run: Callable[[], Any], rounds: int) -> float:
    """``count`` divided by the best of ``rounds`` timings of ``run``."""
    best = float("inf")
    for _ in range(rounds):
        start = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - start)
    return count / best


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Print (and return) files/s of the scan, the former header-only check and a full decode."""
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pairs", type=int, default=2000, help="pairs in the data set (2 files each)")
    parser.add_argument("--size", type=int, default=512, help="image side in pixels")
    parser.add_argument("--rendered", type=int, default=16, help="distinct synthetic pairs rendered and copied")
    parser.add_argument("--rounds", type=int, default=3, help="timings per method (the best is kept)")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        files = make_data(Path(tmp), args.pairs, args.size, min(args.rendered, args.pairs))
        root = Path(tmp) / "data"
        megabytes = sum(f.stat().st_size for f in files) / 1e6
        threads = pngcheck.SCAN_THREADS

        def one_thread() -> None:
            pngcheck.SCAN_THREADS = 1
            try:
                UAPDDataset(root, "train")
            finally:
                pngcheck.SCAN_THREADS = threads

        rates = {
            f"scan ({threads} threads)": best_rate(len(files), lambda: UAPDDataset(root, "train"), args.rounds),
            "scan, 1 thread": best_rate(len(files), one_thread, args.rounds),
            "header only (before)": best_rate(len(files), lambda: [header_only(f) for f in files], args.rounds),
            "decode (cv2.imread)": best_rate(len(files), lambda: [cv2.imread(str(f), cv2.IMREAD_UNCHANGED)
                                                                  for f in files], max(1, args.rounds - 2)),
        }
    print(f"start-up scan: {args.pairs} pairs ({len(files)} PNG files, {megabytes:.0f} MB) at {args.size}x{args.size}, "
          f"page cache warm, best of {args.rounds}")
    print(f"{'method':<24}{'files/s':>10}{'MB/s':>9}")
    for method, rate in rates.items():
        print(f"{method:<24}{rate:>10.0f}{rate * megabytes / len(files):>9.0f}")
    return {"pairs": args.pairs, "size": args.size, "files": len(files), "megabytes": megabytes,
            "files_per_s": rates}


if __name__ == "__main__":
    main()
