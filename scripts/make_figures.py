"""Render the figures of docs/ that need no trained model, with the project's code: python scripts/make_figures.py."""

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


LAYERS = [("cli", "dapm-lightning: subcommands and tools, one line each"),
          ("tools", "predict (one-line form), export, doctor, synth, quickstart"),
          ("inference", "inputs, runtime, postprocess, prior, writers, telemetry/"),
          ("training", "DAPMModule, DAPMLoss, callbacks, checkpoints, DAPMCLI"),
          ("data", "samples, UAPD / Potsdam / synthetic, PredictBatch"),
          ("models | metrics", "DAPMNet, PQB, IGD feature, PosePrior | torchmetrics"),
          ("geometry | options.py", "pose, camera, IGD, depth codec, bins, point clouds | the options' values")]
FLOW = [("SOURCE: folder, glob, image, video", "inputs.resolve_source"),
        ("PredictInput per image\n(network size, name, size, prior)", "ImageFilesDataset / VideoFramesDataset"),
        ("PredictBatch\n(one size; PosePrior + mode)", "inputs.predict_loader"),
        ("InferenceOutput\n(depth, sky, pose, spread)", "runtime: TorchRuntime | OnnxRuntime"),
        ("Prediction per image\n(input size; K, pose, sources)", "postprocess.batch_predictions"),
        ("files: depth, sky, camera, PLY;\nposes.csv, contact sheet", "writers.PredictionFiles")]


def architecture() -> None:
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 6.2), gridspec_kw={"width_ratios": [1, 1.1]})
    for ax in (left, right):
        ax.set_xlim(0, 1)
        ax.axis("off")
    left.set_ylim(0, len(LAYERS))
    left.set_title("layers: a module imports its own and those below")
    for row, (name, what) in enumerate(LAYERS):
        y = len(LAYERS) - 1 - row
        left.add_patch(plt.Rectangle((0.02, y + 0.1), 0.96, 0.8, facecolor=plt.cm.Blues(0.25 + 0.09 * row),
                                     edgecolor="black"))
        left.text(0.05, y + 0.58, name, fontsize=11, weight="bold", va="center")
        left.text(0.05, y + 0.3, what, fontsize=8.5, va="center")
    right.set_ylim(0, len(FLOW))
    right.set_title("predict: the one path from a source to files")
    for row, (data, _) in enumerate(FLOW):
        y = len(FLOW) - 1 - row
        right.add_patch(plt.Rectangle((0.02, y + 0.2), 0.5, 0.65, facecolor="#fff3d6", edgecolor="black"))
        right.text(0.27, y + 0.52, data, fontsize=8.5, ha="center", va="center")
        if row:
            right.annotate("", xy=(0.27, y + 0.86), xytext=(0.27, y + 1.2),
                           arrowprops={"arrowstyle": "->", "lw": 1.4})
            right.text(0.3, y + 1.03, FLOW[row][1], fontsize=8, va="center", style="italic", color="#333")
        else:
            right.text(0.55, y + 0.52, "DAPMPredictor, predict SOURCE,\npredict --config (PredictDataModule)",
                       fontsize=8, va="center", color="#333")
    fig.tight_layout()
    fig.savefig(OUT / "architecture.png", dpi=70)
    plt.close(fig)


def predict_pictures() -> None:
    """The predict writers' depth picture and contact sheet, drawn from synthetic frames' true depth and pose."""
    import cv2

    from dapm_lightning.data.pictures import depth_picture
    from dapm_lightning.data.synthetic.generate import image_seed, sample_pose
    from dapm_lightning.data.synthetic.render import render_scene
    from dapm_lightning.data.synthetic.scene import sample_scene
    from dapm_lightning.inference.contact_sheet import contact_sheet, contact_tiles
    from dapm_lightning.inference.postprocess import make_prediction

    rows, first = [], None
    for index, size in ((3, (240, 320)), (11, (240, 320)), (5, (180, 320))):
        rng = image_seed(77, "val", index)
        pose = sample_pose(rng)
        rgb, depth, _ = render_scene(pose, size, sample_scene(rng))
        depth = np.where(np.isfinite(depth) & (depth < 1000), depth, 1000.0).astype(np.float32)
        sky = torch.from_numpy((depth >= 1000).astype(np.float32))[None]
        prediction = make_prediction(f"synth_{index:03d}", size, torch.from_numpy(depth)[None], sky,
                                     torch.tensor(pose, dtype=torch.float32))
        prediction.rgb = rgb
        rows.append(contact_tiles(prediction))
        if first is None:
            first = depth_picture(prediction.depth_m, prediction.sky)
    assert first is not None
    cv2.imwrite(str(OUT / "predict_depth_color.png"), cv2.cvtColor(first, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(OUT / "predict_contact_sheet.png"), cv2.cvtColor(contact_sheet(rows), cv2.COLOR_RGB2BGR))


if __name__ == "__main__":
    OUT.mkdir(parents=True, exist_ok=True)
    igd_grid()
    pinhole_vs_paper()
    architecture()
    predict_pictures()
    print(f"wrote figures to {OUT}; the synthetic samples figure: python -m benchmarks.bench_synth figure")
