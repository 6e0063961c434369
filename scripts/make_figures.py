"""Render the figures of docs/ with the project's own code: python scripts/make_figures.py."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch

from dapm_lightning.geometry import ideal_ground_depth

OUT = Path(__file__).resolve().parents[1] / "docs" / "figures"


def igd_grid() -> None:
    poses = [(50, -90, 0, 60), (50, -45, 0, 60), (50, -10, 0, 60), (50, -45, 20, 60),
             (50, -45, 0, 110), (15, -45, 0, 60), (100, -45, 0, 60), (50, 5, -20, 90)]
    fig, axes = plt.subplots(2, 4, figsize=(12, 6.2), constrained_layout=True)
    for ax, pose in zip(axes.flat, poses):
        depth = ideal_ground_depth(torch.tensor(pose, dtype=torch.float64), (128, 128))[0, 0].numpy()
        image = ax.imshow(np.log2(depth + 1) / np.log2(1001), cmap="magma_r", vmin=0, vmax=1)
        ax.set_title(f"h {pose[0]} m, pitch {pose[1]}°\nroll {pose[2]}°, FoV {pose[3]}°", fontsize=9)
        ax.axis("off")
    fig.colorbar(image, ax=axes, shrink=0.7, label="log depth (0 = 0 m, 1 = 1000 m / sky)")
    fig.suptitle("Ideal Ground Depth (pinhole, range) for a few poses")
    fig.savefig(OUT / "igd_poses.png", dpi=70)
    plt.close(fig)


def pinhole_vs_paper() -> None:
    pose = torch.tensor([40.0, -30.0, 15.0, 110.0], dtype=torch.float64)
    pin = ideal_ground_depth(pose, (128, 128))[0, 0].numpy()
    paper = ideal_ground_depth(pose, (128, 128), model="paper")[0, 0].numpy()
    ground = (pin < 1000) & (paper < 1000)
    ratio = np.where(ground, paper / pin, np.nan)
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.6), constrained_layout=True)
    for ax, img, title in zip(axes, (pin, paper), ("pinhole (exact)", "paper model (Eq. 10-17)")):
        ax.imshow(np.log2(img + 1) / np.log2(1001), cmap="magma_r", vmin=0, vmax=1)
        ax.set_title(title)
        ax.axis("off")
    im = axes[2].imshow(ratio, cmap="coolwarm", vmin=0.6, vmax=1.4)
    axes[2].set_title("paper / pinhole")
    axes[2].axis("off")
    fig.colorbar(im, ax=axes[2], shrink=0.8)
    fig.suptitle("h 40 m, pitch -30°, roll 15°, FoV 110°")
    fig.savefig(OUT / "igd_pinhole_vs_paper.png", dpi=70)
    plt.close(fig)


if __name__ == "__main__":
    OUT.mkdir(parents=True, exist_ok=True)
    igd_grid()
    pinhole_vs_paper()
    print(f"wrote figures to {OUT}; the synthetic samples figure: python -m benchmarks.bench_synth figure")
