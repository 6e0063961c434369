"""Point clouds as PLY files (binary little-endian; x, y, z float32 metres, optional red, green, blue uint8)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dapm_lightning.data.files import open_atomic

PLY_COMMENT = ("dapm-lightning point cloud: metres, gravity-aligned world frame (origin on the ground under the "
               "camera, X horizontal along the optical axis, Y left, Z up; ground at z = 0)")


def write_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray | None = None, comment: str = PLY_COMMENT) -> Path:
    """Write ``xyz`` ``[N, 3]`` (and ``rgb`` ``[N, 3]`` uint8) as a binary little-endian PLY; returns the path.

    Opens in MeshLab, CloudCompare, Open3D (``o3d.io.read_point_cloud``) and trimesh. Written whole or not at
    all (:func:`~dapm_lightning.data.files.open_atomic`).

    Raises:
        WriteError: the file could not be written (a full disk, a read-only or missing folder).
    """
    xyz = np.asarray(xyz, np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if rgb is not None:
        rgb = np.asarray(rgb).reshape(-1, 3)
        if rgb.shape[0] != xyz.shape[0]:
            raise ValueError(f"rgb has {rgb.shape[0]} points, xyz {xyz.shape[0]}")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vertices = np.empty(xyz.shape[0], dtype=fields)
    vertices["x"], vertices["y"], vertices["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    if rgb is not None:
        vertices["red"], vertices["green"], vertices["blue"] = rgb[:, 0], rgb[:, 1], rgb[:, 2]
    header = ["ply", "format binary_little_endian 1.0", f"comment {comment}", f"element vertex {xyz.shape[0]}",
              *(f"property {'float' if kind == '<f4' else 'uchar'} {name}" for name, kind in fields), "end_header"]
    path = Path(path)
    with open_atomic(path) as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        handle.write(vertices.tobytes())
    return path
