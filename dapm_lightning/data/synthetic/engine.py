"""Ray casting with Intel Embree (``embreex``) over triangle meshes built from a scene's objects.

Only the objects a camera can see are meshed: each object's bounding sphere is tested against the
view frustum (widened, so that shadows cast from just outside the picture still fall) and against
the pixel size (an object smaller than ``LOD_PIXELS`` of a pixel at its distance is left out). The
mesh is built in camera-centred coordinates so that float32 keeps millimetres near the camera.
The ground plane is not meshed: it is intersected analytically in float64 by the renderer, which
keeps ground depth exactly the ideal ground depth of docs/conventions.md ("Ideal Ground Depth").
"""

from __future__ import annotations

import math

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from dapm_lightning.data.synthetic.objects import BLOB, BOX, CONE, GABLE_X, GABLE_Y, Objects

LOD_PIXELS = 0.5
"""Objects whose angular radius is below this share of a pixel are not meshed."""
SHADOW_MARGIN_DEG = 20.0
"""The culling frustum is this much wider than the picture on each side (shadows from outside the frame)."""
REACH_M = 1300.0
"""Objects farther than this are not meshed (depth beyond 1000 m is sky in the encoding; haze hides the rest)."""

_BOX_FACES = np.array([[4, 5, 7], [4, 7, 6], [0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5], [0, 1, 5], [0, 5, 4],
                       [2, 6, 7], [2, 7, 3]])  # corners: bit 0 -> x, bit 1 -> y, bit 2 -> z; no floor
_GABLE_FACES = np.array([[0, 4, 6], [0, 6, 2], [1, 3, 7], [1, 7, 5], [0, 1, 5], [0, 5, 4], [2, 6, 7], [2, 7, 3],
                         [4, 6, 8], [5, 7, 9], [4, 5, 9], [4, 9, 8], [6, 7, 9], [6, 9, 8]])
_RING = 6
_BLOB_FACES = np.array([[0, 2 + k, 2 + (k + 1) % _RING] for k in range(_RING)]
                       + [[1, 2 + (k + 1) % _RING, 2 + k] for k in range(_RING)])  # 0 top, 1 bottom, ring
_CONE_FACES = np.array([[0, 1 + k, 1 + (k + 1) % _RING] for k in range(_RING)])  # 0 apex, ring
_ANGLES = np.arange(_RING) * (2 * math.pi / _RING)


def _box_vertices(lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    bits = np.array([[i & 1, (i >> 1) & 1, (i >> 2) & 1] for i in range(8)], bool)
    return np.where(bits[None], hi[:, None], lo[:, None])  # [N, 8, 3]


def _gable_vertices(lo: np.ndarray, hi: np.ndarray, eave: np.ndarray) -> np.ndarray:
    """Walls to the eaves and a ridge along x at mid-y: 4 floor, 4 eave, 2 ridge corners."""
    corners = _box_vertices(lo, np.concatenate([hi[:, :2], eave[:, None]], 1))
    mid_y = (lo[:, 1] + hi[:, 1]) / 2
    ridge = np.stack([np.stack([lo[:, 0], mid_y, hi[:, 2]], -1), np.stack([hi[:, 0], mid_y, hi[:, 2]], -1)], 1)
    return np.concatenate([corners, ridge], 1)


def _ring_vertices(lo: np.ndarray, hi: np.ndarray, ring_z: np.ndarray) -> np.ndarray:
    centre = (lo + hi) / 2
    radius = (hi - lo)[:, :2] / 2
    ring = np.stack([centre[:, None, 0] + radius[:, None, 0] * np.cos(_ANGLES),
                     centre[:, None, 1] + radius[:, None, 1] * np.sin(_ANGLES),
                     np.broadcast_to(ring_z[:, None], (len(lo), _RING))], -1)
    return ring


def triangulate(objects: Objects) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vertices ``[V, 3]``, triangles ``[T, 3]`` (int32) and the object row of each triangle ``[T]``."""
    verts, faces, owners = [], [], []
    count = 0
    for prim in (BOX, GABLE_X, GABLE_Y, BLOB, CONE):
        rows = np.flatnonzero(objects.prim == prim)
        if not len(rows):
            continue
        lo, hi = objects.lo[rows], objects.hi[rows]
        if prim == BOX:
            v, f = _box_vertices(lo, hi), _BOX_FACES
        elif prim == GABLE_X:
            v, f = _gable_vertices(lo, hi, objects.eave[rows]), _GABLE_FACES
        elif prim == GABLE_Y:  # build along x in swapped axes, then swap back
            swap = [1, 0, 2]
            v = _gable_vertices(lo[:, swap], hi[:, swap], objects.eave[rows])[..., swap]
            f = _GABLE_FACES
        elif prim == BLOB:
            centre = (lo + hi) / 2
            top = np.concatenate([centre[:, None, :2], hi[:, None, 2:]], -1)
            bottom = np.concatenate([centre[:, None, :2], lo[:, None, 2:]], -1)
            ring = _ring_vertices(lo, hi, lo[:, 2] + 0.45 * (hi[:, 2] - lo[:, 2]))
            v, f = np.concatenate([top, bottom, ring], 1), _BLOB_FACES
        else:
            centre = (lo + hi) / 2
            apex = np.concatenate([centre[:, None, :2], hi[:, None, 2:]], -1)
            v, f = np.concatenate([apex, _ring_vertices(lo, hi, lo[:, 2])], 1), _CONE_FACES
        per = v.shape[1]
        verts.append(v.reshape(-1, 3))
        faces.append((f[None] + (count + per * np.arange(len(rows)))[:, None, None]).reshape(-1, 3))
        owners.append(np.repeat(rows, len(f)))
        count += per * len(rows)
    if not verts:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int32), np.zeros(0, np.int64)
    return np.concatenate(verts), np.concatenate(faces).astype(np.int32), np.concatenate(owners)


def visible(objects: Objects, origin: np.ndarray, forward: np.ndarray, right: np.ndarray, down: np.ndarray,
            fov_deg: float, size: tuple[int, int]) -> np.ndarray:
    """Rows of ``objects`` worth meshing for this camera (frustum, distance and pixel-size culling)."""
    if not len(objects):
        return np.zeros(0, np.int64)
    centre = (objects.lo + objects.hi) / 2 - origin
    radius = np.linalg.norm(objects.hi - objects.lo, axis=1) / 2
    z = centre @ forward
    x = centre @ right
    y = centre @ down
    half = math.radians(min(fov_deg / 2 + SHADOW_MARGIN_DEG, 89.0))
    tan_h = math.tan(half)
    tan_v = math.tan(min(math.atan(math.tan(math.radians(fov_deg) / 2) * size[0] / size[1])
                         + math.radians(SHADOW_MARGIN_DEG), math.radians(89.0)))
    dist = np.linalg.norm(centre, axis=1)
    pixel = 2 * math.tan(math.radians(fov_deg) / 2) / size[1]  # radians per pixel at the centre
    keep = ((z > -radius) & (np.abs(x) <= z * tan_h + radius * math.sqrt(1 + tan_h ** 2))
            & (np.abs(y) <= z * tan_v + radius * math.sqrt(1 + tan_v ** 2))
            & (dist - radius < REACH_M) & (radius >= LOD_PIXELS * pixel * dist))
    return np.flatnonzero(keep)


def clear_of_camera(objects: Objects, origin: np.ndarray) -> np.ndarray:
    """Rows that leave the camera in the open: nothing taller than the camera within 8 m of it horizontally."""
    dx = np.maximum(np.maximum(objects.lo[:, 0] - origin[0], origin[0] - objects.hi[:, 0]), 0)
    dy = np.maximum(np.maximum(objects.lo[:, 1] - origin[1], origin[1] - objects.hi[:, 1]), 0)
    return ~((np.hypot(dx, dy) < 8.0) & (objects.hi[:, 2] > origin[2] - 3.0))


def facing(objects: Objects, verts: np.ndarray, faces: np.ndarray, owner: np.ndarray, origin: np.ndarray,
           sun: np.ndarray | None) -> np.ndarray:
    """Triangles that face the camera or the sun (outward normals; every shape here is convex).

    The nearest hit of a camera ray on a convex object is on a face turned towards the camera, and a
    shadow ray towards the sun leaves an object through a face turned towards the sun, so the other
    faces change neither the picture nor the shadows (about 40 % fewer triangles to hand to Embree).
    """
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    normal = np.cross(b - a, c - a)
    centre = (objects.lo[owner] + objects.hi[owner]) / 2
    flip = (((a + b + c) / 3 - centre) * normal).sum(1) < 0
    normal[flip] *= -1
    keep = ((origin - a) * normal).sum(1) > 0
    if sun is not None and sun[2] > 0:
        keep |= normal @ sun > 0
    return keep


class RayCaster:
    """Embree scene of one camera's visible objects (camera-centred coordinates).

    With ``sun`` given, only the triangles facing the camera or the sun are meshed (:func:`facing`);
    :meth:`occluded` must then be asked towards that sun only.
    """

    def __init__(self, objects: Objects, origin: np.ndarray, sun: np.ndarray | None = None) -> None:
        verts, faces, self.owner = triangulate(objects)
        if len(faces):
            keep = facing(objects, verts, faces, self.owner, origin, sun)
            faces, self.owner = faces[keep], self.owner[keep]
            used = np.zeros(len(verts), bool)
            used[faces.ravel()] = True
            remap = np.cumsum(used) - 1
            verts, faces = verts[used], remap[faces].astype(np.int32)
        self.empty = len(faces) == 0
        if not self.empty:
            self.scene = rtcore_scene.EmbreeScene()
            TriangleMesh(self.scene, np.ascontiguousarray(verts - origin, np.float32), faces)

    def intersect(self, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Nearest hit of rays from the camera: distance along unit ``dirs`` (inf: none), object row, unit normal."""
        n = len(dirs)
        if self.empty:
            return np.full(n, np.inf), np.full(n, -1), np.zeros((n, 3))
        result = self.scene.run(np.zeros((n, 3), np.float32), np.ascontiguousarray(dirs, np.float32), output=1)
        prim = result["primID"]
        hit = prim >= 0
        t = np.where(hit, result["tfar"].astype(np.float64), np.inf)
        row = np.where(hit, self.owner[np.where(hit, prim, 0)], -1)
        normal = result["Ng"].astype(np.float64)
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
        normal *= np.where((normal * dirs).sum(1) > 0, -1.0, 1.0)[:, None]  # facing the camera
        return t, row, normal

    def occluded(self, points: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Whether a ray from each camera-relative point towards ``direction`` hits an object."""
        if self.empty or not len(points):
            return np.zeros(len(points), bool)
        dirs = np.broadcast_to(np.asarray(direction, np.float32), points.shape)
        return self.scene.run(np.ascontiguousarray(points, np.float32), np.ascontiguousarray(dirs),
                              query="OCCLUDED") >= 0
