"""Per-viewpoint breakdown (paper's viewpoint figure): depth d1 and pose error per bin of each pose component."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from dapm_lightning.geometry.constants import POSE_KEYS, POSE_RANGES, POSE_UNITS


def viewpoint_table(records: Tensor, bins: int = 5) -> list[dict[str, Any]]:
    """Bin test images by each true pose component (uniform bins over the UAPD range).

    Args:
        records: ``[N, 9]``: true pose (4), per-image d1 (1), absolute pose errors (4).
        bins: bins per component.

    Returns:
        Rows ``{component, bin, low, high, count, d1 (mean), error (median of that component's error)}``.
    """
    rows = []
    for k, key in enumerate(POSE_KEYS):
        lo, hi = POSE_RANGES[key]
        edges = torch.linspace(lo, hi, bins + 1)
        which = torch.bucketize(records[:, k].clamp(lo, hi), edges[1:-1], right=True)
        for b in range(bins):
            chosen = records[which == b]
            d1 = chosen[:, 4][torch.isfinite(chosen[:, 4])]
            err = chosen[:, 5 + k][torch.isfinite(chosen[:, 5 + k])]
            rows.append({"component": key, "bin": b, "low": float(edges[b]), "high": float(edges[b + 1]),
                         "count": int(chosen.shape[0]),
                         "d1": float(d1.mean()) if d1.numel() else math.nan,
                         "error": float(err.median()) if err.numel() else math.nan})
    return rows


def plot_viewpoints(rows: list[dict[str, Any]], path: str | Path) -> Path:
    """Save a 1x4 figure (pitch, height, roll, fov): d1 and median pose error per bin."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 4, figsize=(16, 3.6), constrained_layout=True)
    for ax, key in zip(axes, ("pitch", "height", "roll", "fov")):
        sel = [r for r in rows if r["component"] == key]
        centres = [(r["low"] + r["high"]) / 2 for r in sel]
        ax.plot(centres, [r["d1"] for r in sel], "o-", color="tab:blue", label="depth δ1")
        ax.set_ylim(0, 1.02)
        ax.set_xlabel(f"true {key} [{POSE_UNITS[key]}]")
        ax.set_ylabel("δ1", color="tab:blue")
        twin = ax.twinx()
        twin.plot(centres, [r["error"] for r in sel], "s--", color="tab:red", label=f"{key} error")
        twin.set_ylabel(f"median {key} error [{POSE_UNITS[key]}]", color="tab:red")
        for c, r in zip(centres, sel):
            ax.annotate(f"n={r['count']}", (c, 0.03), ha="center", fontsize=7)
    fig.suptitle("Accuracy per viewpoint (test set)")
    path = Path(path)
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
