"""Render a predicted metric point cloud beside its image (the README's 3D figure).

``python -m dapm_lightning.tools.render_pointcloud --ckpt_path CKPT --image FRAME.png --out view.png``
predicts depth and pose for the image, lifts the depth into the gravity-aligned world frame (origin on
the ground under the camera, Z up) and draws the coloured points from an oblique viewpoint, with the
camera and its predicted height, pitch, roll and FoV. Uses its own matplotlib figure (no global state).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def view_box(xyz: np.ndarray, height: float) -> tuple[np.ndarray, np.ndarray, float]:
    """The plotted square: (x/y low corner, x/y high corner, side in metres).

    It frames the central 96 % of the points in x and y and the camera (origin, ``height`` up): a few
    far points near the horizon would otherwise shrink the scene into a corner of the plot.
    """
    low = np.minimum(np.percentile(xyz[:, :2], 2, axis=0), 0.0)
    high = np.maximum(np.percentile(xyz[:, :2], 98, axis=0), 0.0)
    span = max(float((high - low).max()), height, 1.0)
    centre = (low + high) / 2
    return centre - span / 2, centre + span / 2, span


def draw_cloud(ax: Any, image_rgb: np.ndarray, prediction: Any, label: str, *, stride: int = 1,
               max_depth: float | None = None) -> None:
    """One prediction's coloured point cloud, the camera and its pose on a 3D matplotlib axis."""
    cloud = prediction.points(stride=stride, max_depth=max_depth, rgb=image_rgb)
    pose = prediction.pose
    height = pose["height"]
    box_low, box_high, span = view_box(cloud.xyz, height)
    inside = np.all((cloud.xyz[:, :2] >= box_low) & (cloud.xyz[:, :2] <= box_high), axis=1) & (
        cloud.xyz[:, 2] <= span)
    xyz = cloud.xyz[inside]
    ax.scatter(xyz[:, 0], xyz[:, 1], xyz[:, 2], c=cloud.rgb[inside] / 255.0, s=2.0, depthshade=False, linewidths=0)
    ax.scatter([0], [0], [height], c="red", s=30, marker="^")
    ax.plot([0, 0], [0, 0], [0, height], color="red", linewidth=1)
    forward = prediction.camera_to_world[:3, 2] * max(5.0, 0.3 * height)
    ax.quiver(0, 0, height, *forward, color="red", linewidth=1.5)
    ax.set_xlim(box_low[0], box_high[0])
    ax.set_ylim(box_low[1], box_high[1])
    ax.set_zlim(min(0.0, float(xyz[:, 2].min(initial=0.0))), span)
    ax.set_box_aspect((1, 1, 1))
    ax.view_init(elev=28, azim=-140)
    ax.set_xlabel("X (m, forward)")
    ax.set_ylabel("Y (m, left)")
    ax.set_zlabel("Z (m, up)")
    ax.set_title(f"{label} ({len(xyz)} of {len(cloud.xyz)} points shown)\n"
                 f"height {height:.1f} m, pitch "
                 f"{pose['pitch']:.1f}, roll {pose['roll']:.1f}, FoV {pose['fov']:.1f} deg", fontsize=9)


def render(image_rgb: np.ndarray, prediction: Any, out: str | Path, *, stride: int = 1,
           max_depth: float | None = None, title: str | None = None, with_telemetry: Any = None) -> Path:
    """Draw ``image_rgb`` (``[H, W, 3]`` uint8) and ``prediction``'s point cloud side by side into ``out``.

    ``with_telemetry``: a second prediction of the same image, given telemetry, drawn as a third panel.
    """
    from matplotlib.figure import Figure

    panels = 2 if with_telemetry is None else 3
    figure = Figure(figsize=(5.5 * panels, 4.6), dpi=110)
    left = figure.add_subplot(1, panels, 1)
    left.imshow(image_rgb)
    title = title or "input image"
    left.set_title(title if len(title) <= 48 else title[:45] + "...", fontsize=9)
    left.axis("off")
    draw_cloud(figure.add_subplot(1, panels, 2, projection="3d"), image_rgb, prediction,
               "predicted metric point cloud" if with_telemetry is None else "without telemetry",
               stride=stride, max_depth=max_depth)
    if with_telemetry is not None:
        draw_cloud(figure.add_subplot(1, panels, 3, projection="3d"), image_rgb, with_telemetry,
                   "with telemetry", stride=stride, max_depth=max_depth)
    figure.tight_layout()
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out)
    return out


def render_main(ckpt_path: Path, image: Path, out: Path = Path("pointcloud.png"), image_width: int | None = None,
                stride: int = 1, max_depth: float | None = None, ply: Path | None = None,
                telemetry: list[float] | None = None) -> Path:
    """Predict one image and render its point cloud beside it.

    Args:
        ckpt_path: a full DAPM checkpoint (depth and pose).
        image: the image file.
        out: the PNG to write.
        image_width: network input width (default: the checkpoint's training size).
        stride: keep every stride-th pixel in the point cloud.
        max_depth: leave out points farther than this (metres).
        ply: also write the point cloud to this PLY file.
        telemetry: the image's known pose (height m, pitch, roll, fov deg; NaN where unknown): a third panel
            shows the cloud predicted with it.
    """
    from dapm_lightning.inference.inputs import read_image
    from dapm_lightning.inference.predictor import DAPMPredictor

    image = Path(image)
    if not image.is_file():  # read_image reports a missing file as one it cannot decode
        raise FileNotFoundError(f"--image {image}: no such image file" if not image.exists() else
                                f"--image {image}: a folder, not an image file (this tool draws one image)")
    rgb = read_image(image)
    predictor = DAPMPredictor.from_checkpoint(ckpt_path, image_width=image_width)
    prediction = predictor(rgb)
    if prediction.pose is None or prediction.depth_m is None:
        kind = "DAPM(D), depth only: no pose branch" if prediction.pose is None else "DAPM(P), pose only: no depth"
        raise ValueError(f"--ckpt_path {ckpt_path}: a {kind}; a point cloud needs both depth and pose.\n"
                         "Fix: pass a full DAPM checkpoint (depth and pose); `dapm-lightning predict` writes what "
                         "this model predicts alone.")
    given = predictor(rgb, prior=np.asarray(telemetry, dtype=np.float64)) if telemetry is not None else None
    if ply is not None:
        prediction.points(stride, max_depth, rgb).write_ply(ply)
    written = render(rgb, prediction, out, stride=stride, max_depth=max_depth, title=Path(image).name,
                     with_telemetry=given)
    print(f"wrote {written}")
    return written


def main(argv: Sequence[str] | None = None) -> None:
    """Command line of :func:`render_main`."""
    import sys

    from jsonargparse import auto_cli

    from dapm_lightning.tools.errors import debug_requested, run_reporting_errors

    debug, args = debug_requested(sys.argv[1:] if argv is None else argv)
    run_reporting_errors(lambda: auto_cli(render_main, args=args, as_positional=False,
                                          prog="python -m dapm_lightning.tools.render_pointcloud",
                                          description=__doc__), debug)


if __name__ == "__main__":
    main()
