"""From the network's outputs to per-image predictions at each input's own size.

:func:`batch_predictions` is the one post-processing step: the Lightning prediction writer and the Python API
(PyTorch or onnxruntime alike) call it with a batch's :class:`~dapm_lightning.models.dapm.InferenceOutput` and
its :class:`~dapm_lightning.data.unlabelled.PredictBatch`. It applies the batch's pose prior as its mode says
(:mod:`dapm_lightning.inference.prior`), resizes depth in the log space without mixing sky into the ground,
keeps the sky exactly at the depth limit where the model sees sky (``sky_prob > 0.5``) and strictly below it
elsewhere, and derives the intrinsics and the camera-to-world transform of the pose at the input's size.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from dapm_lightning.data.unlabelled import PredictBatch
from dapm_lightning.geometry.camera import intrinsics_matrix
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_KEYS, SKY_PROBABILITY_THRESHOLD, pose_field
from dapm_lightning.geometry.depth_codec import decode_log_depth, encode_log_depth, sky_at_limit
from dapm_lightning.geometry.igd import DepthKind, IGDSpec
from dapm_lightning.geometry.pointcloud import camera_to_world, depth_to_points, valid_points
from dapm_lightning.inference.ply import write_ply
from dapm_lightning.inference.prior import apply_pose_prior, bound_by_ground
from dapm_lightning.models.dapm import InferenceOutput


def _resize(values: Tensor, size: tuple[int, int]) -> Tensor:
    """``[N, C, h, w]`` bilinearly to ``size`` (unchanged when already there)."""
    if tuple(values.shape[-2:]) == size:
        return values
    return F.interpolate(values, size=size, mode="bilinear", align_corners=False)


def resize_depth(depth_m: Tensor, size: Sequence[int], max_depth: float = MAX_DEPTH_M,
                 sky: Tensor | None = None) -> Tensor:
    """``[1, h, w]`` metres to ``[1, H, W]``, interpolated in the log space from non-sky pixels only.

    ``sky``: ``[1, h, w]`` bool at the network size (default: ``depth_m >= max_depth``). Sky pixels take no part
    in the interpolation, so no point half-way to the sky appears along a skyline; where only sky is near, the
    plain interpolation is kept (the caller's sky mask decides those pixels).
    """
    size = (int(size[0]), int(size[1]))
    if tuple(depth_m.shape[-2:]) == size:
        return depth_m
    sky = depth_m >= max_depth if sky is None else sky
    norm = encode_log_depth(depth_m[None].float(), max_depth)
    ground = (~sky[None]).float()
    weight = _resize(ground, size)
    mixed = _resize(norm * ground, size) / weight.clamp_min(1e-6)
    plain = _resize(norm, size)
    return decode_log_depth(torch.where(weight > 1e-3, mixed, plain), max_depth)[0]


_FIELD_KEYS = {pose_field(k): k for k in POSE_KEYS}
"""The files' pose names (``height_m``, ...) -> the API's (``height``, ...)."""


@dataclass(frozen=True, eq=False)  # eq from Mapping: equal to a dict of the same values
class CameraPose(Mapping[str, float]):
    """A pose in physical units: ``height`` m, ``pitch``, ``roll``, ``fov`` deg (docs/conventions.md).

    Read as attributes (``pose.pitch``) or as a mapping in :data:`POSE_KEYS` order (``pose["pitch"]``,
    ``dict(pose)``, ``pose.items()``); the files' names with units work too (``pose["pitch_deg"]``), and
    :meth:`fields` gives the pose as the files and the telemetry CSV name it.
    """

    height: float
    pitch: float
    roll: float
    fov: float

    @classmethod
    def from_tensor(cls, pose: Tensor) -> CameraPose:
        """From a ``[4]`` tensor in :data:`POSE_KEYS` order."""
        height, pitch, roll, fov = (float(v) for v in pose.detach().double().cpu())
        return cls(height, pitch, roll, fov)

    def __getitem__(self, key: str) -> float:
        key = _FIELD_KEYS.get(key, key)
        if key not in POSE_KEYS:
            raise KeyError(key)
        return float(getattr(self, key))

    def fields(self) -> dict[str, float]:
        """``{"height_m": ..., "pitch_deg": ..., "roll_deg": ..., "fov_deg": ...}``: the files' names and units."""
        return {pose_field(k): self[k] for k in POSE_KEYS}

    def __iter__(self) -> Iterator[str]:
        return iter(POSE_KEYS)

    def __len__(self) -> int:
        return len(POSE_KEYS)


@dataclass
class PointCloud:
    """Points ``xyz`` ``[N, 3]`` float32 metres in the world frame, optional colours ``rgb`` ``[N, 3]`` uint8."""

    xyz: np.ndarray
    rgb: np.ndarray | None = None

    def write_ply(self, path: str | Path) -> Path:
        """Binary PLY (opens in MeshLab, CloudCompare, Open3D, trimesh)."""
        return write_ply(path, self.xyz, self.rgb)


@dataclass
class Prediction:
    """One image's prediction at the input's size.

    Attributes:
        depth_m: ``[H, W]`` float32 metres: exactly ``max_depth`` on sky, below it elsewhere; None for DAPM(P).
        sky: ``[H, W]`` bool: ``sky_prob > 0.5`` (models without a sky stage: depth at the limit).
        pose: the :class:`CameraPose` (m, deg) used for K, the transform and the points; None for DAPM(D).
        sky_prob: ``[H, W]`` float32 probability of "beyond max depth", None without a sky stage.
        K: ``[3, 3]`` intrinsics for the input's size from the FoV (pixel ``(i, j)`` centre at
            ``(j + 0.5, i + 0.5)``), None without a pose.
        camera_to_world: ``[4, 4]`` camera (x right, y down, z forward) to world (origin on the ground
            under the camera, Z up), None without a pose.
        depth_kind: ``"range"`` or ``"planar"``: what ``depth_m`` measures (the model's setting).
        max_depth: the model's depth limit (sky).
        name: what its files are called.
        size: ``(H, W)`` of the input image.
        pose_network: the network's own estimate per component (equal to ``pose`` without a prior).
        pose_source: per component, where ``pose`` comes from: ``"network"``, ``"telemetry"`` or ``"fused"``
            (all ``"network"`` without telemetry; None without a pose).
        pose_provenance: per component given by telemetry (``telemetry`` or ``fused``), the file and the place in it
            (``"flight.csv line 12"``, ``"DJI_0001.JPG XMP drone-dji:RelativeAltitude"``,
            ``"DJI_0005.SRT subtitle 215 rel_alt"``, ``"Python API prior"``).
        scale_from: how the telemetry scale fit found its factor: ``ground``, ``height`` or ``none``.
        rgb: the input's ``[H, W, 3]`` uint8 pixels, when the loader was asked to keep them.
        time_s: a video frame's time in the video (seconds); None for an image.
        network_size: ``(h, w)`` the network saw the image at; None where not known.
    """

    depth_m: np.ndarray | None
    sky: np.ndarray | None
    pose: CameraPose | None
    sky_prob: np.ndarray | None = None
    K: np.ndarray | None = None
    camera_to_world: np.ndarray | None = None
    depth_kind: DepthKind = "range"
    max_depth: float = MAX_DEPTH_M
    name: str = ""
    size: tuple[int, int] = (0, 0)
    pose_network: CameraPose | None = None
    pose_source: dict[str, str] | None = None
    pose_provenance: dict[str, str] | None = None
    scale_from: str = "none"
    rgb: np.ndarray | None = None
    time_s: float | None = None
    network_size: tuple[int, int] | None = None

    def auto_stride(self) -> int:
        """The point-cloud stride that gives about the network's resolution (1 where not known or larger)."""
        if self.network_size is None:
            return 1
        ratio = (self.size[0] * self.size[1]) / max(1, self.network_size[0] * self.network_size[1])
        return max(1, round(math.sqrt(ratio)))

    def points(self, stride: int = 1, max_depth: float | None = None, rgb: np.ndarray | None = None) -> PointCloud:
        """Metric point cloud of the non-sky pixels, every ``stride``-th row and column, in the world frame.

        Args:
            stride: subsampling step in pixels. max_depth: drop points farther than this (metres).
            rgb: ``[H, W, 3]`` uint8 image of the input's size to colour the points.
        """
        if self.depth_m is None or self.pose is None:
            raise ValueError("a point cloud needs depth and pose: DAPM(D) and DAPM(P) models predict only one")
        if stride < 1:
            raise ValueError(f"stride must be >= 1, got {stride}")
        depth = torch.from_numpy(np.ascontiguousarray(self.depth_m, np.float32))[None, None]
        pose = torch.tensor([[self.pose[k] for k in POSE_KEYS]], dtype=torch.float64)
        xyz = depth_to_points(depth.double(), pose, depth_kind=self.depth_kind, stride=stride)[0]
        keep = valid_points(depth, min(self.max_depth, max_depth or math.inf))[0]
        if self.sky is not None:
            keep &= ~torch.from_numpy(self.sky)
        keep = keep[::stride, ::stride]
        colours = None
        if rgb is not None:
            if rgb.shape[:2] != self.depth_m.shape:
                raise ValueError(f"rgb is {rgb.shape[:2]}, depth {self.depth_m.shape}: give the input image")
            colours = np.asarray(rgb)[::stride, ::stride][keep.numpy()].astype(np.uint8)
        return PointCloud(xyz[keep].float().numpy(), colours)

    def camera_dict(self) -> dict[str, Any]:
        """What ``NAME_camera.json`` holds: image size, K, camera-to-world, pose per component, conventions.

        Per pose component (``pose``): its value, its source (``network``, ``telemetry``, ``fused``) and the
        network's own value; beside it (``pose_provenance``), per component, the file and the place in it the
        telemetry came from (None where the network's value is used).
        """
        height, width = self.size
        pose = provenance = None
        if self.pose is not None:
            network = self.pose_network or self.pose
            sources, given = self.pose_source or {}, self.pose_provenance or {}
            pose = {pose_field(k): {"value": pose_value_text(v), "source": sources.get(k, "network"),
                                    "network": pose_value_text(network.get(k))} for k, v in self.pose.items()}
            provenance = {pose_field(k): given.get(k) for k in self.pose}
        return {"name": self.name, **({} if self.time_s is None else {"time_s": round(self.time_s, 3)}),
                "width": int(width), "height": int(height),
                "K": None if self.K is None else self.K.tolist(),
                "camera_to_world": None if self.camera_to_world is None else self.camera_to_world.tolist(),
                "pose": pose, "pose_provenance": provenance, "depth_kind": self.depth_kind,
                "max_depth_m": self.max_depth,
                "conventions": "pixel (i, j) centre at (j + 0.5, i + 0.5); camera x right, y down, z forward; world "
                               "origin on the ground under the camera, X horizontal along the optical axis, Y left, "
                               "Z up (docs/conventions.md)"}


def pose_value_text(value: float | None) -> float | None:
    """A pose value for ``camera.json``, to 1e-5 m or degree: below that is float32's arithmetic noise.

    An SRT's -42.0 pitch, carried in float32 through the network's normalised pose and back, is -42.0, not
    -42.000003814697266.
    """
    return None if value is None else round(float(value), 5)


def _camera_pose(pose: Tensor | None) -> CameraPose | None:
    return None if pose is None else CameraPose.from_tensor(pose)


def make_prediction(name: str, size: Sequence[int], depth_m: Tensor | None, sky_prob: Tensor | None,
                    pose: Tensor | None, spec: IGDSpec | None = None, *, pose_network: Tensor | None = None,
                    pose_source: Mapping[str, str] | None = None,
                    pose_provenance: Mapping[str, str] | None = None) -> Prediction:
    """One image's :class:`Prediction` at the input size ``(H, W)`` from the network's outputs for it.

    Args:
        depth_m: ``[1, h, w]`` metres at the network size. sky_prob: ``[1, h, w]``. pose: ``[4]`` physical, the
            one used (telemetry or fused, when there is a prior). spec: the model's IGD settings (depth limit
            and kind). pose_network: ``[4]`` the network's own estimate. pose_source: per component.
        pose_provenance: per component given by telemetry, where its value came from.
    """
    spec = spec or IGDSpec()
    size = (int(size[0]), int(size[1]))
    depth = sky = prob = None
    if sky_prob is not None:
        prob_t = _resize(sky_prob.detach().float().cpu()[None], size)[0].clamp(0, 1)
        prob = prob_t[0].numpy()
        sky_t = prob_t > SKY_PROBABILITY_THRESHOLD
        sky_net = sky_prob.detach().float().cpu() > SKY_PROBABILITY_THRESHOLD
    elif depth_m is not None:
        sky_net = depth_m.detach().float().cpu() >= spec.max_depth
        sky_t = _resize(sky_net[None].float(), size)[0] > SKY_PROBABILITY_THRESHOLD
    if depth_m is not None:
        resized = resize_depth(depth_m.detach().float().cpu(), size, spec.max_depth, sky_net)
        depth_t = sky_at_limit(resized, sky_t, spec.max_depth)
        depth, sky = depth_t[0].numpy(), sky_t[0].numpy()
    pose_used = _camera_pose(pose)
    k = c2w = None
    if pose is not None:
        pose64 = pose.detach().double().cpu()[None]
        k = intrinsics_matrix(pose64[:, 3], size)[0].numpy()
        c2w = camera_to_world(pose64)[0].numpy()
    return Prediction(depth, sky, pose_used, prob, k, c2w, spec.depth_kind, spec.max_depth, name, size,
                      _camera_pose(pose_network) or pose_used,
                      dict(pose_source) if pose_source else _network_sources(pose_used),
                      dict(pose_provenance) if pose_provenance else None)


def _network_sources(pose: CameraPose | None) -> dict[str, str] | None:
    """Without telemetry every component is the network's (None without a pose)."""
    return None if pose is None else {k: "network" for k in POSE_KEYS}


def predictions_from_outputs(output: InferenceOutput, names: Sequence[str], sizes: Sequence[Sequence[int]],
                             spec: IGDSpec | None = None, *,
                             pose_sources: Sequence[Mapping[str, str]] | None = None,
                             provenance: Sequence[Mapping[str, str]] | None = None) -> list[Prediction]:
    """A batch's :class:`Prediction` per image, each at its input size (no prior applied here).

    Args:
        output: at the network size; ``pose`` the pose used, ``pose_network`` the network's own where they differ.
        names, sizes: per image, its name and ``(H, W)``. spec: the model's IGD settings.
        pose_sources: per image, per component, where the pose used comes from.
        provenance: per image, per component given by telemetry, where its value came from.
    """
    def row(value: Tensor | None, k: int) -> Tensor | None:
        return None if value is None else value[k]

    return [make_prediction(names[k], sizes[k], row(output.depth_m, k), row(output.sky_prob, k),
                            row(output.pose, k), spec, pose_network=row(output.pose_network, k),
                            pose_source=None if pose_sources is None else pose_sources[k],
                            pose_provenance=None if provenance is None else provenance[k])
            for k in range(len(names))]


def batch_predictions(output: InferenceOutput, batch: PredictBatch, spec: IGDSpec) -> list[Prediction]:
    """The predictions of one predict batch: its network output, its pose prior applied as its mode says.

    The one step from a network output to :class:`Prediction`: the Lightning writer and
    :class:`~dapm_lightning.inference.predictor.DAPMPredictor` (any runtime) both call it. With the batch's
    ``igd_bound``, the depth is then capped by the ground of the pose used (:func:`bound_by_ground`).
    """
    applied = apply_pose_prior(output, batch.prior, batch.mode, spec)
    if batch.igd_bound is not None:
        applied = applied._replace(output=bound_by_ground(applied.output, batch.prior, spec, batch.igd_bound))
    provenance = None
    if batch.prior is not None:
        given = batch.provenance or [("",) * len(POSE_KEYS)] * len(batch)
        provenance = [{k: where for k, where in zip(POSE_KEYS, wheres) if where and sources[k] != "network"}
                      for wheres, sources in zip(given, applied.sources)]
    predictions = predictions_from_outputs(applied.output, batch.names, batch.sizes, spec,
                                           pose_sources=applied.sources if batch.prior is not None else None,
                                           provenance=provenance)
    for prediction, scale_from, rgb, time_s in zip(predictions, applied.scale_from, batch.rgb or [None] * len(batch),
                                                   batch.times or [None] * len(batch)):
        prediction.scale_from, prediction.rgb, prediction.time_s = scale_from, rgb, time_s
        prediction.network_size = (int(batch.images.shape[-2]), int(batch.images.shape[-1]))
    return predictions
