"""Writing synthetic UAPD-format data sets: per-image seeding, worker processes, shards, ``synth.json``."""

from __future__ import annotations

import json
import multiprocessing
import os
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from dapm_lightning.data.files import make_folder, remove_empty_folders, write_image
from dapm_lightning.data.synthetic.lens import distort, sample_lens
from dapm_lightning.data.synthetic.render import render_scene
from dapm_lightning.data.synthetic.scene import Scene, normalize_families, sample_scene
from dapm_lightning.data.synthetic.shading import camera_effects
from dapm_lightning.data.uapd import format_uapd_filename, is_uapd_image
from dapm_lightning.geometry.constants import MAX_DEPTH_M, POSE_KEYS, POSE_RANGES
from dapm_lightning.geometry.depth_codec import depth_to_grey

GENERATOR_VERSION = 5  # 5: version 4's pictures, the pose keys in file names in the published UAPD order
"""Bumped whenever the same settings would render different files, pictures or names (so caches re-render)."""
_SPLIT_IDS = {"train": 0, "val": 1, "test": 2}
MAX_IMAGE_SIDE = 8192
"""The largest image side rendered (the network's, ``inference.onnx.MAX_EXPORT_SIDE``)."""
_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def sample_pose(rng: np.random.Generator, ranges: dict[str, tuple[float, float]] = POSE_RANGES) -> np.ndarray:
    """A pose uniform in the given ranges, rounded to 2 decimals (as written in the file name)."""
    return np.array([round(float(rng.uniform(*ranges[key])), 2) for key in POSE_KEYS])


def image_seed(seed: int, split: str, index: int) -> np.random.Generator:
    """The random generator of one image: depends on (seed, split, index) only, not on worker count or shard."""
    return np.random.default_rng([seed, _SPLIT_IDS.get(split, 9), index])


def uapd_name(index: int, pose: np.ndarray, scene: Scene, lens: tuple[float, float] | None = None) -> str:
    """UAPD-style file name carrying the pose (x, y, yaw, lens k and kcube as metadata, the family as a token)."""
    x, y = scene.camera_xy
    distortion = {"lensk": lens[0], "lenskcube": lens[1]} if lens else None
    return format_uapd_filename(["synth", f"{index:06d}", scene.family], pose, x=x, y=y, yaw=scene.yaw_deg,
                                extra=distortion)


def render_sample(seed: int, split: str, index: int, size: tuple[int, int],
                  families: dict[str, float] | None = None, effects: bool = True, distortion: bool = False,
                  max_depth: float = MAX_DEPTH_M) -> tuple[str, np.ndarray, np.ndarray, np.ndarray]:
    """``(name, rgb uint8, depth grey uint8, hit map)`` of one image of a data set.

    The grey levels encode depth up to ``max_depth`` (grey 255: at or beyond it, sky included).

    With ``distortion``, lens coefficients are drawn from a stream of their own (the pose and scene
    stay those of the undistorted image) and image and depth are warped alike (:mod:`.lens`).
    """
    rng = image_seed(seed, split, index)
    pose = sample_pose(rng)
    scene = sample_scene(rng, families=families)
    lens = None
    if distortion:
        lens = sample_lens(np.random.default_rng([seed, _SPLIT_IDS.get(split, 9), index, 1]))
        rgb, depth_m, hit = render_scene(pose, size, scene, effects=False)
        rgb, depth_m, hit = distort(rgb, depth_m, hit, *lens)
        if effects:
            rgb = camera_effects(rgb / 255.0, scene.look, np.random.default_rng(scene.texture_seed))
    else:
        rgb, depth_m, hit = render_scene(pose, size, scene, effects=effects)
    grey = depth_to_grey(np.where(np.isfinite(depth_m), depth_m, max_depth), max_depth)
    return uapd_name(index, pose, scene, lens), rgb, grey, hit


def _render_one(job: tuple[Path, str, int, int, tuple[int, int], dict[str, float], bool, bool, float]) -> str:
    out, split, index, seed, size, families, effects, distortion, max_depth = job
    torch.set_num_threads(1)
    name, rgb, grey, _ = render_sample(seed, split, index, size, families, effects, distortion, max_depth)
    write_image(out / split / "rgb" / name, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    write_image(out / split / "depth" / name, grey)
    return name


def settings(*, train: int, val: int, size: int | tuple[int, int], seed: int,
             families: dict[str, float] | str | None = None, effects: bool = True,
             distortion: bool = False, max_depth: float = MAX_DEPTH_M) -> dict[str, Any]:
    """What ``synth.json`` records; two data sets with equal settings hold the same bytes."""
    hw = [size, size] if isinstance(size, int) else [int(s) for s in size]
    return {"train": int(train), "val": int(val), "size": hw, "seed": int(seed),
            "families": normalize_families(families), "effects": bool(effects),
            "distortion": bool(distortion), "depth_kind": "range",
            "max_depth": float(max_depth), "generator": "dapm_lightning.data.synthetic", "version": GENERATOR_VERSION}


def is_current(root: str | Path, **kwargs: Any) -> bool:
    """Whether ``root/synth.json`` records exactly these settings (see :func:`settings`)."""
    return settings_changes(root, **kwargs) == ""


def settings_changes(root: str | Path, **kwargs: Any) -> str:
    """What differs between ``root/synth.json`` and these settings, e.g. ``"train 8 -> 2000, val 4 -> 200"``.

    Empty when they agree; ``"no readable synth.json"`` when there is none to compare.
    """
    try:
        have = json.loads((Path(root) / "synth.json").read_text())
    except (json.JSONDecodeError, OSError):
        return "no readable synth.json"
    have.pop("cache", None)  # who rendered it, not what (is_cache)
    have.setdefault("distortion", False)  # written before the option existed: undistorted
    want = json.loads(json.dumps(settings(**kwargs)))
    absent = object()
    keys = [*want, *(key for key in have if key not in want)]
    return ", ".join(f"{key} {have.get(key)} -> {want.get(key)}" for key in keys
                     if have.get(key, absent) != want.get(key, absent))


def is_cache(root: str | Path) -> bool:
    """Whether ``root/synth.json`` marks the set a cache, one that other settings may replace.

    ``generate_uapd(cache=True)`` marks it, as ``SyntheticDataModule`` renders; ``dapm-lightning synth`` does not.
    """
    try:
        return json.loads((Path(root) / "synth.json").read_text()).get("cache") is True
    except (json.JSONDecodeError, OSError, AttributeError):
        return False


def shard_range(count: int, shard: tuple[int, int]) -> range:
    """Indices of shard ``k`` of ``n`` (0-based) among ``count`` jobs: contiguous, sizes differing by at most 1."""
    k, n = shard
    if n < 1 or not 0 <= k < n:
        raise ValueError(f"shard must be K/N with 0 <= K < N, got {k}/{n}")
    return range(count * k // n, count * (k + 1) // n)


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    """Cancel the images not started and end the worker processes now (``shutdown`` would let them finish)."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    # the pool's manager thread closes its wake-up pipe as it ends; Python's exit handler writes to that pipe
    # unlocked (CPython 3.11), and a close in between printed an OSError traceback (Bad file descriptor) at exit:
    # waited for below (shutdown forgets it)
    manager = getattr(pool, "_executor_manager_thread", None)  # not public
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        if process.is_alive():
            process.terminate()
    for process in processes:
        process.join(timeout=5)
    if manager is not None:
        manager.join(timeout=5)


class SynthFolderError(ValueError):
    """The output folder cannot take this render (it holds other images); the message names it and the fix."""


def _image_folders(out: Path) -> list[Path]:
    """The four folders a set's images go to: ``out/{train,val}/{rgb,depth}``."""
    return [out / split / sub for split in ("train", "val") for sub in ("rgb", "depth")]


def _refuse_foreign_images(out: Path) -> None:
    """Refuse a folder without ``synth.json`` that holds images of its own (a real UAPD set).

    The synthetic images would mix with them, and a later render of other settings would delete only its own.
    """
    foreign = next((path for folder in _image_folders(out) if folder.is_dir() for path in folder.iterdir()
                    if is_uapd_image(path) and not path.name.startswith("synth_")), None)
    if foreign is not None:
        raise SynthFolderError(f"{out}: holds images not rendered by the generator (e.g. {foreign}) and no "
                               "synth.json, so rendering there would mix synthetic images into that set.\nFix: "
                               "render into an empty folder (synth --out, or the synthetic data module's "
                               "data.init_args.root); to train on that set, use --data.class_path "
                               "dapm_lightning.data.datamodules.UAPDDataModule")


def generate_uapd(out: str | Path, *, train: int = 200, val: int = 50, size: int | tuple[int, int] = 128,
                  seed: int = 0, workers: int | None = None, families: dict[str, float] | str | None = None,
                  effects: bool = True, shard: tuple[int, int] = (0, 1), distortion: bool = False,
                  max_depth: float = MAX_DEPTH_M, progress: Callable[[int], object] | None = None,
                  cache: bool = False) -> Path:
    """Write a synthetic UAPD-format data set ``out/{train,val}/{rgb,depth}/NAME.png``.

    Args:
        out: root folder (created).
        train, val: image counts per split.
        size: ``S`` for ``S x S`` or ``(H, W)``.
        seed: same seed, same bytes, whatever the number of workers or shards.
        workers: processes (default: the CPU count, at most 8).
        families: weights of the scene families (``{"downtown": 2, "forest": 1}`` or ``"downtown=2,forest=1"``;
            default: every family equally).
        effects: camera processing (exposure, blur, noise, JPEG artefacts).
        distortion: radial lens distortion of random strength per image (:mod:`.lens`), applied to
            image and depth alike (the depth is then consistent with the image, not pinhole).
        shard: ``(k, n)``: render only the k-th (0-based) of n contiguous parts of the image list, for
            array jobs; the union of all shards is byte-identical to one run.
        max_depth: the depth limit of the log encoding (grey 255); the model's ``igd.max_depth`` must match.
        progress: called with the number of images rendered since its last call (a progress bar's ``update``).
        cache: mark the set a cache in ``synth.json`` (:func:`is_cache`): ``SyntheticDataModule`` replaces only
            its own caches when its settings change.

    Returns:
        ``out``; it also holds ``synth.json`` with the settings (:func:`settings`). A folder holding a
        data set of other settings, or the images of a render cut short (no ``synth.json``), is emptied of its
        images first (refused for a shard of a set of other settings; a shard keeps a cut-short render's images);
        one holding images the generator did not render (no ``synth.json``) is refused.
    """
    out = Path(out)
    hw = (size, size) if isinstance(size, int) else (int(size[0]), int(size[1]))
    if not all(1 <= side <= MAX_IMAGE_SIDE for side in hw):
        raise ValueError(f"size {hw[0]}x{hw[1]}: each side must be 1 to {MAX_IMAGE_SIDE} pixels")
    chosen = {"train": train, "val": val, "size": hw, "seed": seed, "families": families, "effects": effects,
              "distortion": distortion, "max_depth": max_depth}
    info = settings(**chosen)
    weights = info["families"]
    recorded = (out / "synth.json").is_file()
    if not recorded:
        _refuse_foreign_images(out)
    # a render cut short (images, no synth.json yet) may have had other settings: replaced like a stale set, except
    # by a shard, whose siblings may be writing those images now
    cut_short = not recorded and shard[1] == 1 and any(any(folder.glob("synth_*.png"))
                                                       for folder in _image_folders(out))
    stale = (recorded and not is_current(out, **chosen)) or cut_short
    if stale and shard[1] > 1:
        raise SynthFolderError(f"{out}: holds a data set rendered with other settings ({out / 'synth.json'}), "
                               "which shards cannot replace (each would delete the others' images).\n"
                               "Fix: remove that set, or render the shards into another folder")
    jobs = [(out, split, i, seed, hw, weights, effects, distortion, max_depth)
            for split, count in (("train", train), ("val", val)) for i in range(count)]
    jobs = [jobs[i] for i in shard_range(len(jobs), shard)]
    if stale:
        if jobs:  # one image rendered first: settings that cannot render (memory) fail with the old set still whole
            _, split, index, *_ = jobs[0]
            render_sample(seed, split, index, hw, weights, effects, distortion, max_depth)
        for folder in _image_folders(out):
            for path in folder.glob("synth_*.png"):
                path.unlink(missing_ok=True)  # each node of a multi-node run replaces a shared folder's set at once
    new_folders = [made for folder in _image_folders(out) for made in make_folder(folder)]  # --out's parents too
    try:
        _render_jobs(jobs, workers, out, shard, progress)
    except BaseException:  # a stop before the set is whole: no empty folder of this run left (a shard's may be shared)
        if shard[1] == 1:
            remove_empty_folders(new_folders)
        raise
    # last, so that a crashed run is not "current"; atomically, as shards of an array job finish side by side
    partial = out / f".synth.json.{os.getpid()}"
    partial.write_text(json.dumps({**info, "cache": True} if cache else info, indent=2) + "\n")
    os.replace(partial, out / "synth.json")
    return out


def _render_jobs(jobs: list[tuple], workers: int | None, out: Path, shard: tuple[int, int],
                 progress: Callable[[int], object] | None) -> None:
    """Render and write ``jobs`` in ``workers`` processes (one: in this one), telling ``progress`` of each image."""
    workers = workers or min(os.cpu_count() or 1, 8)
    if workers > 1 and len(jobs) > 1:
        saved = {k: os.environ.get(k) for k in _THREAD_VARS}
        os.environ.update({k: "1" for k in _THREAD_VARS})  # one thread per worker process: no oversubscription
        try:
            pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
            try:
                for _ in pool.map(_render_one, jobs, chunksize=max(1, min(16, len(jobs) // (workers * 4)))):
                    if progress is not None:
                        progress(1)
            except BaseException:  # a failed image, Ctrl-C, SIGTERM (synth): no worker renders on, none outlives us
                _stop_workers(pool)
                if shard[1] == 1:  # the temporary files of images cut off (a shard's siblings may be writing theirs)
                    for folder in _image_folders(out):
                        for path in folder.glob(".synth_*.tmp"):
                            path.unlink(missing_ok=True)
                raise
            pool.shutdown()
        finally:
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value
    else:
        for job in jobs:
            _render_one(job)
            if progress is not None:
                progress(1)
