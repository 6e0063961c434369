"""Point clouds as PLY files (binary little-endian; x, y, z float32 metres, optional red, green, blue uint8)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

PLY_COMMENT = ("dapm-lightning point cloud: metres, gravity-aligned world frame (origin on the ground under the "
               "camera, X horizontal along the optical axis, Y left, Z up; ground at z = 0)")
_TYPES = {"char": "i1", "uchar": "u1", "short": "<i2", "ushort": "<u2", "int": "<i4", "uint": "<u4",
          "float": "<f4", "double": "<f8", "int8": "i1", "uint8": "u1", "int16": "<i2", "uint16": "<u2",
          "int32": "<i4", "uint32": "<u4", "float32": "<f4", "float64": "<f8"}


def write_ply(path: str | Path, xyz: np.ndarray, rgb: np.ndarray | None = None, comment: str = PLY_COMMENT) -> Path:
    """Write ``xyz`` ``[N, 3]`` (and ``rgb`` ``[N, 3]`` uint8) as a binary little-endian PLY; returns the path.

    Opens in MeshLab, CloudCompare, Open3D (``o3d.io.read_point_cloud``) and trimesh.
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
    with path.open("wb") as handle:
        handle.write(("\n".join(header) + "\n").encode("ascii"))
        handle.write(vertices.tobytes())
    return path


def read_ply(path: str | Path) -> dict[str, np.ndarray]:
    """Vertices of a PLY point cloud (ascii or binary little-endian) as ``{property: [N] array}``.

    Only the ``vertex`` element is returned; scalar properties only (no lists), as point clouds use.
    """
    path = Path(path)
    data = path.read_bytes()
    end = data.find(b"end_header")
    if not data.startswith(b"ply") or end < 0:
        raise ValueError(f"{path}: not a PLY file (no 'ply' magic or no 'end_header')")
    body_start = data.index(b"\n", end) + 1
    lines = data[:end].decode("ascii").splitlines()
    fmt = ""
    elements: list[tuple[str, int, list[tuple[str, str]]]] = []  # (name, count, [(property, dtype)])
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1]
        elif words[0] == "element":
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property":
            if words[1] == "list":
                raise ValueError(f"{path}: list properties are not supported by this reader")
            if words[1] not in _TYPES:
                raise ValueError(f"{path}: unknown property type {words[1]!r}")
            elements[-1][2].append((words[2], _TYPES[words[1]]))
    if fmt not in ("ascii", "binary_little_endian"):
        raise ValueError(f"{path}: PLY format {fmt!r} not supported (ascii or binary_little_endian)")
    offset, text_rows = body_start, data[body_start:].decode("ascii").split("\n") if fmt == "ascii" else []
    row = 0
    for name, count, props in elements:
        dtype = np.dtype(props)
        if fmt == "ascii":
            values = np.array([r.split() for r in text_rows[row:row + count]], dtype=np.float64).reshape(count, -1)
            row += count
            table = np.empty(count, dtype)
            for k, (prop, _) in enumerate(props):
                table[prop] = values[:, k]
        else:
            table = np.frombuffer(data, dtype, count=count, offset=offset)
            offset += dtype.itemsize * count
        if name == "vertex":
            return {prop: np.array(table[prop]) for prop, _ in props}
    raise ValueError(f"{path}: no vertex element")
