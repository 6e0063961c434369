"""Turn a training checkpoint into a model folder to ship: float16 weights, the hyper-parameters and the training
image size (no optimizer state, no callbacks' state), split into parts of at most 15 MiB with a card.

    python scripts/ship_model.py RUN/last.ckpt models/NAME --card card.json

Every command that takes a checkpoint takes the folder (``read_checkpoint`` joins and checks the parts); so does
``fit --model.init_weights`` (docs/gpu.md, "The shipped model").
"""

from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import torch

from dapm_lightning.training.checkpoint_files import (
    check_dapm_checkpoint,
    inference_checkpoint,
    read_checkpoint,
    split_checkpoint,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", help="a checkpoint written by `dapm-lightning fit`")
    parser.add_argument("folder", type=Path, help="the model folder to write (parts + parts.json)")
    parser.add_argument("--card", type=Path, help="a JSON file of plain values describing the model")
    args = parser.parse_args()
    checkpoint = read_checkpoint(args.checkpoint)
    check_dapm_checkpoint(checkpoint, args.checkpoint)
    card = json.loads(args.card.read_text()) if args.card else {}
    card.setdefault("steps", checkpoint.get("global_step"))
    card.setdefault("image_size", (checkpoint.get("dapm_train_image_size") or [None])[0])
    with tempfile.TemporaryDirectory() as work:
        whole = Path(work) / "model.ckpt"
        torch.save(inference_checkpoint(checkpoint), whole)
        files = split_checkpoint(whole, args.folder, card=card)
    read_checkpoint(args.folder)  # the parts join to the file written, or this fails naming the part
    print(f"wrote {args.folder}: {len(files) - 1} part(s), {sum(f.stat().st_size for f in files[:-1]) / 1e6:.1f} MB")


if __name__ == "__main__":
    main()
