"""The one sample schema shared by every data set, transform, collate and the Lightning module.

Also what every data set does the same way: build a sample, seed its augmentation by (seed, epoch,
index), and read the ``(epoch, index)`` keys the training sampler yields.
"""

from __future__ import annotations

import random
from collections.abc import Callable
from typing import Any, TypedDict

import numpy as np
import torch
from torch import Tensor

from dapm_lightning.geometry.constants import MAX_DEPTH_M


class Sample(TypedDict, total=False):
    """One image and its labels in physical units.

    Keys:
        image: ``[3, H, W]`` RGB, float32 in [0, 1] (or uint8 in [0, 255] when a data set is asked
            for ``uint8`` images, which the Lightning module normalises on the device).
        depth: ``[1, H, W]`` metres, float32; sky pixels (grey 255) hold exactly ``max_depth``, so the
            sky mask is ``depth >= max_depth`` and the valid mask ``isfinite(depth) & (depth > 0)``;
            both are derived on the device (:func:`depth_masks`), not shipped by the loader.
        pose: ``[4]`` (height m, pitch deg, roll deg, fov deg); NaN when the data set has no pose.
        has_pose: ``[]`` bool.
        name: file stem.
        meta: other tokens of the file name.
    """

    image: Tensor
    depth: Tensor
    pose: Tensor
    has_pose: Tensor
    name: str
    meta: dict[str, Any]


def depth_masks(depth_m: Tensor, max_depth: float = MAX_DEPTH_M) -> tuple[Tensor, Tensor]:
    """``(sky, valid)`` bool masks of a depth map in metres: at/beyond ``max_depth``; finite and positive."""
    return depth_m >= max_depth, torch.isfinite(depth_m) & (depth_m > 0)


Transform = Callable[..., dict[str, Any]]
"""An albumentations-style pipeline: ``transform(image=, mask=, pose=) -> dict`` with the same keys."""

SampleKey = int | tuple[int, int]
"""A data set index, or ``(epoch, index)`` from the training sampler (the epoch seeds the augmentation)."""


def split_key(key: SampleKey) -> tuple[int, int]:
    """``(epoch, index)`` of a sample key; a plain index is epoch 0."""
    if isinstance(key, tuple):
        return int(key[0]), int(key[1])
    return 0, int(key)


def _set_state(transform: Transform, state: int) -> None:
    """One generator of ``state`` shared by the pipeline's transforms (see :func:`seed_augmentation`)."""
    if hasattr(transform, "set_random_state"):
        transform.set_random_state(np.random.default_rng(state), random.Random(state))
    elif hasattr(transform, "set_random_seed"):
        transform.set_random_seed(state)


def seed_augmentation(transform: Transform, seed: int | None, epoch: int, index: int) -> None:
    """Seed an albumentations pipeline by (seed, epoch, index), so a sample's augmentation is reproducible.

    The pipeline's transforms share one generator and draw from it in turn. (``Compose.set_random_seed`` gives each
    transform a generator of the same seed: their first draws, which decide whether each applies, are then equal,
    so transforms of equal probability would apply together or not at all.)

    ``seed`` None (a data set built without ``augment_seed``): not reproducible, but in a loader worker the pipeline
    is seeded once from the worker's seed (``get_worker_info().seed``: another for each worker, and for each epoch's
    new workers) and draws on from there. Else every worker would start from the generator it was forked with, the
    same in each worker and again in every epoch: the same augmentations in every worker, repeated every epoch.
    """
    if seed is None:
        worker = torch.utils.data.get_worker_info()
        seedable = hasattr(transform, "set_random_state") or hasattr(transform, "set_random_seed")
        if seedable and worker is not None and getattr(transform, "_dapm_worker_seed", None) != worker.seed:
            _set_state(transform, worker.seed)
            transform._dapm_worker_seed = worker.seed  # type: ignore[attr-defined]
        return
    _set_state(transform, int(np.random.SeedSequence([seed, epoch, index]).generate_state(1)[0]))


def make_sample(rgb: np.ndarray, depth_m: np.ndarray, pose: np.ndarray | None, name: str, meta: dict[str, Any],
                *, image_dtype: str = "float32") -> Sample:
    """Build a :class:`Sample` from ``[H, W, 3]`` uint8 RGB, ``[H, W]`` metres and a pose (None: no pose)."""
    image = torch.from_numpy(np.ascontiguousarray(rgb.transpose(2, 0, 1)))
    if image_dtype == "float32":
        image = image.float().div_(255.0)
    depth = torch.from_numpy(np.ascontiguousarray(depth_m, dtype=np.float32))[None]
    has_pose = pose is not None
    pose_tensor = torch.from_numpy(np.asarray(pose, np.float32)) if has_pose else torch.full((4,), float("nan"))
    return Sample(image=image, depth=depth, pose=pose_tensor, has_pose=torch.tensor(has_pose), name=name, meta=meta)
