"""Lightning data modules: UAPD, synthetic UAPD-format (generated on first use) and Potsdam."""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any, Literal

import albumentations as A
import lightning as L
import torch
from lightning.pytorch.trainer.states import TrainerFn
from torch.utils.data import DataLoader, Dataset
from torch.utils.data._utils.collate import default_collate

from dapm_lightning.data.depth_kind import sampled_mismatch
from dapm_lightning.data.errors import SkippedFile
from dapm_lightning.data.potsdam import PotsdamCrops, PotsdamDataset
from dapm_lightning.data.sample import Sample
from dapm_lightning.data.samplers import EpochShuffleSampler
from dapm_lightning.data.synthetic import SynthFolderError, generate_uapd, is_cache, settings_changes
from dapm_lightning.data.transforms import Augmentation, train_transform
from dapm_lightning.data.uapd import UAPDDataset, read_depth_grey
from dapm_lightning.data.workers import loader_context, loader_workers
from dapm_lightning.geometry.constants import MAX_DEPTH_M
from dapm_lightning.geometry.depth_codec import check_depth_limit


def collate_samples(items: list[Sample | SkippedFile]) -> dict[str, Any]:
    """Stack the tensors of a list of samples; ``name`` and ``meta`` stay lists.

    Samples left out because their file failed (:class:`~dapm_lightning.data.errors.SkippedFile`, with
    ``on_bad_file="skip"``) are dropped; ``skipped`` lists their problems (empty when none was), and
    :meth:`DAPMDataModule.on_before_batch_transfer` takes it out of the batch and warns once per file.
    """
    samples = [s for s in items if not isinstance(s, SkippedFile)]
    batch: dict[str, Any] = {k: default_collate([s[k] for s in samples])  # type: ignore[literal-required]
                             for k in samples[0] if k not in ("name", "meta")}
    batch["name"] = [s["name"] for s in samples]
    batch["meta"] = [s.get("meta", {}) for s in samples]
    batch["skipped"] = [s.problem for s in items if isinstance(s, SkippedFile)]
    return batch


class DAPMDataModule(L.LightningDataModule):
    """Loaders shared by every data set: batch size, workers, pinned memory, augmentation.

    Args:
        batch_size: per process (the global batch is ``batch_size x devices x nodes``).
        num_workers, pin_memory, persistent_workers: ``DataLoader`` settings.
        worker_start_method: how loader workers start: ``forkserver`` (default: from a single-threaded server
            process, immune to locks held by this process's threads), ``fork`` (PyTorch's default on Linux: data sets
            that cannot be pickled) or ``spawn`` (:func:`~dapm_lightning.data.workers.loader_context`).
        prepare_data_per_node: where the data is prepared (the synthetic set rendered, Potsdam's crops cut): true,
            once on each node (Lightning's default: a root on each node's own disk); false, once in the whole job,
            by its first process while the others wait (a root on a file system the nodes share).
        augment: augment the training split (colour jitter, noise, pose-aware flip).
        augmentation: its strengths (:class:`~dapm_lightning.data.transforms.Augmentation`; the defaults are
            this project's light augmentation, the paper configs set the authors' stronger one).
        image_dtype: ``"uint8"`` ships 4x fewer bytes per sample; the model normalises on the device.
        eval_batch_size: batch size of validation/test/predict (default: ``batch_size``).
        seed: a whole number >= 0; the training order is a permutation drawn from (seed, epoch) and the augmentation of
            each sample is seeded by (seed, epoch, index), so runs repeat exactly, with any number of
            workers, persistent or not, and under DDP; a run resumed from a mid-epoch checkpoint
            continues with the batches the uninterrupted run would see.
    """

    serves_prediction = False
    """Whether ``predict`` batches are images to predict (``PredictBatch``): only ``PredictDataModule``'s are; the
    other modules' are labelled samples, which ``dapm-lightning predict`` refuses."""

    def __init__(self, batch_size: int = 8, num_workers: int = 2, pin_memory: bool = False,
                 persistent_workers: bool = False, augment: bool = True,
                 image_dtype: Literal["float32", "uint8"] = "uint8", eval_batch_size: int | None = None,
                 seed: int = 0, augmentation: Augmentation = Augmentation(),  # noqa: B008 (frozen)
                 worker_start_method: Literal["forkserver", "fork", "spawn"] = "forkserver",
                 prepare_data_per_node: bool = True) -> None:
        super().__init__()
        self.prepare_data_per_node = prepare_data_per_node  # read by Lightning
        counts = (("batch_size", batch_size, 1, 8), ("eval_batch_size", eval_batch_size, 1, 8),
                  ("num_workers", num_workers, 0, 2), ("seed", seed, 0, 0))  # seeds of numpy's SeedSequence: >= 0
        for name, value, least, example in counts:
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < least):
                raise ValueError(f"data.init_args.{name}: {value!r}, but it must be a whole number of at least "
                                 f"{least}.\nFix: e.g. --data.init_args.{name} {example}")
        self.batch_size, self.num_workers = batch_size, num_workers
        self.pin_memory, self.persistent_workers = pin_memory, persistent_workers and num_workers > 0
        self.augment, self.image_dtype = augment, image_dtype
        self.augmentation = Augmentation(**augmentation) if isinstance(augmentation, dict) else augmentation
        self.eval_batch_size = eval_batch_size or batch_size
        self.seed = seed
        loader_context(worker_start_method)  # refused here, not at the first loader
        self.worker_start_method = worker_start_method
        self._resume_position: dict[str, int] | None = None
        self.resumed_at: tuple[int, int] | None = None
        """``(epoch, batches)``: the training loader resumes ``epoch`` after its first ``batches`` batches (of this
        run's processes), when restored from a checkpoint; else None (:meth:`_loader`; read when training starts)."""
        self.datasets: dict[str, Dataset[Sample]] = {}
        self._read_early: dict[tuple[str, bool], Dataset[Sample]] = {}
        self.skipped_while_loading: list[str] = []
        """Files that failed after the scan and were left out (``on_bad_file: skip``), in this process, once each."""

    def make_dataset(self, split: str, train: bool) -> Dataset[Sample]:
        """The data set of one split (``train`` says whether to augment)."""
        raise NotImplementedError

    def split_transform(self, train: bool) -> A.Compose | None:
        """The augmentation of a split: only the training split's, only with ``augment``."""
        if not (train and self.augment):
            return None
        # the UAPD modules know what their depth files hold; the ground recolour's flat ground is of that kind
        return train_transform(self.augmentation, getattr(self, "depth_kind", "range"),
                               getattr(self, "max_depth", MAX_DEPTH_M))

    def _stage_splits(self, stage: str | None) -> list[tuple[str, str, bool]]:
        """``(key in datasets, folder split, augmented)`` of each data set a stage uses."""
        splits = [("train", "train", True, ("fit",)), ("val", "val", False, ("fit", "validate")),
                  ("test", self.test_split, False, ("test",)), ("predict", self.test_split, False, ("predict",))]
        return [(key, split, train) for key, split, train, stages in splits if stage is None or stage in stages]

    def setup(self, stage: str | None = None) -> None:
        for key, split, train in self._stage_splits(stage):
            early = self._read_early.pop((split, train), None)
            self.datasets[key] = early if early is not None else self.make_dataset(split, train)

    def read_early(self, stage: str) -> None:
        """Scan the data sets of ``stage`` now (their problems raised now), for :meth:`setup` to use.

        The command line calls it before the trainer starts, so a wrong data root or a broken file stops the run
        before the loggers create their version folders (an empty ``version_0`` left behind would send the next run
        to ``version_1``). Only the project's own modules are read early (UAPD): one whose :meth:`prepare_data` makes
        its data (the synthetic set, Potsdam's crops, a subclass's download) or a subclass with its own
        :meth:`setup` or :meth:`make_dataset` is read in :meth:`setup`, as Lightning does.
        """
        cls = type(self)
        if cls.prepare_data is not L.LightningDataModule.prepare_data:  # it makes the data, after this
            return
        if cls.setup.__module__ != __name__ or cls.make_dataset.__module__ != __name__:
            return  # a subclass's own setup or data sets may depend on what setup or the trainer sets: read there
        for _, split, train in self._stage_splits(stage):
            self._read_early[(split, train)] = self.make_dataset(split, train)

    test_split = "val"

    def _processes(self) -> tuple[int, int]:
        trainer = self.trainer
        return (trainer.world_size, trainer.global_rank) if trainer is not None else (1, 0)

    def _loader(self, split: str, train: bool = False) -> DataLoader[dict[str, Any]]:
        """A split's loader; the training one resumes the restored position, in whole batches of all processes.

        The position is rounded down to a multiple of the global batch (batch size x processes), so that it is a
        whole number of this run's batches (:attr:`resumed_at`) also when the checkpoint was saved by another number
        of processes (or batch size): fewer than one global batch of samples is then trained twice. An epoch keeps
        at least its last batch, the last of this run's epoch (:meth:`_epoch_batches`: ``limit_train_batches``
        counts each process's batches, so an epoch holds another number of samples on another number of processes).
        """
        dataset = self.datasets[split]
        world_size, rank = self._processes()
        sampler = EpochShuffleSampler(len(dataset), self.seed, num_replicas=world_size, rank=rank,  # type: ignore[arg-type]
                                      shuffle=train, drop_last=train)
        batch_size = self.batch_size if train else self.eval_batch_size
        loader = DataLoader(dataset, batch_size=batch_size, sampler=sampler,
                            pin_memory=self.pin_memory, persistent_workers=self.persistent_workers,
                            collate_fn=collate_samples, drop_last=train and len(sampler) > batch_size,
                            **loader_workers(self.num_workers, rank, self.worker_start_method, dataset),  # SIGTERM
                            generator=torch.Generator().manual_seed(self.seed))  # worker seeds: not the global RNG
        if train:
            self.resumed_at = None
            if self._resume_position is not None:  # restored from a checkpoint
                epoch, samples = self._resume_position["epoch"], self._resume_position["samples_seen"]
                batches = min(samples // (batch_size * world_size), max(self._epoch_batches(len(loader)) - 1, 0))
                sampler.resume(epoch, batches * batch_size * world_size)
                self.resumed_at, self._resume_position = (epoch, batches), None
        return loader

    def _epoch_batches(self, loader_batches: int) -> int:
        """Training batches in an epoch of this run: the loader's, cut by ``limit_train_batches`` as Lightning does."""
        limit = self.trainer.limit_train_batches if self.trainer is not None else 1.0
        if isinstance(limit, int):
            return min(loader_batches, limit)
        return int(loader_batches * limit)

    def train_dataloader(self) -> DataLoader[dict[str, Any]]:
        return self._loader("train", train=True)

    def state_dict(self) -> dict[str, Any]:
        """Where training stands in the epoch, saved in every checkpoint of a fit (for an exact mid-epoch resume).

        The position of the next training batch: ``epoch`` and ``samples_seen``, the samples of that epoch
        already trained on by all processes together (the global position). Right for a checkpoint taken at any
        point of a fit: after a training batch, during or after a validation (``trainer.training`` is then False),
        at the end of an epoch (the next epoch, from its start) and when training ends, also when ``max_steps``
        ended it mid-epoch (Lightning has then already counted the epoch as done: the epoch is the one the
        batches were drawn from, not ``trainer.current_epoch``); before the first training batch of a resumed
        run, the position it was restored to. Empty outside a fit.
        """
        trainer = self.trainer
        if trainer is None or trainer.state.fn != TrainerFn.FITTING:
            return {}
        if self._resume_position is not None:  # restored, and no training batch drawn yet (the sanity check)
            return dict(self._resume_position)
        loop = trainer.fit_loop
        batches = loop.epoch_loop.batch_progress.current.processed
        epoch = max(0, loop.epoch_progress.current.started - 1)  # the epoch the processed batches belong to
        if batches >= trainer.num_training_batches:  # that epoch is over: the next starts from its beginning
            epoch, batches = epoch + 1, 0
        return {"epoch": epoch, "samples_seen": batches * self.batch_size * trainer.world_size}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        self._resume_position = dict(state_dict) if state_dict else None

    def on_before_batch_transfer(self, batch: Any, dataloader_idx: int) -> Any:
        """Warn once per file about samples left out of a batch because their file failed (``on_bad_file: skip``)."""
        if isinstance(batch, dict):
            for problem in batch.pop("skipped", []):
                if problem not in self.skipped_while_loading:
                    self.skipped_while_loading.append(problem)
                    warnings.warn(problem, UserWarning, stacklevel=2)
        return batch

    def val_dataloader(self) -> DataLoader[dict[str, Any]]:
        return self._loader("val")

    def test_dataloader(self) -> DataLoader[dict[str, Any]]:
        return self._loader("test")

    def predict_dataloader(self) -> DataLoader[dict[str, Any]]:
        return self._loader("predict")


class UAPDDataModule(DAPMDataModule):
    """UAPD-format data: ``root/{train,val}/{rgb,depth}/NAME.png`` with the pose in NAME.

    Args:
        root: data set root.
        test_split: folder used by ``test`` and ``predict`` (UAPD publishes train and val only).
        on_bad_file: ``"raise"`` lists every broken file at start-up; ``"skip"`` leaves them out, and leaves out of
            its batch a sample whose file fails later (missing, or damaged after the scan), with a warning naming
            the file once.
        depth_kind: what the depth PNGs hold ("range" for synthetic data; check real data with the
            doctor); the model's ``depth_kind`` must match.
        max_depth: metres that grey 255 means, the log encoding's limit (UAPD: 1000; above 1 m, refused
            otherwise); the model's ``igd.max_depth`` must match (checked when training or testing starts).
    """

    def __init__(self, root: str = "data/uapd", test_split: str = "val",
                 on_bad_file: Literal["raise", "skip"] = "raise", depth_kind: Literal["range", "planar"] = "range",
                 max_depth: float = MAX_DEPTH_M, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.root, self.test_split, self.on_bad_file, self.depth_kind = Path(root), test_split, on_bad_file, depth_kind
        self.max_depth = check_depth_limit(max_depth, "data.init_args.max_depth")

    def make_dataset(self, split: str, train: bool) -> Dataset[Sample]:
        return UAPDDataset(self.root, split, self.split_transform(train), max_depth=self.max_depth,
                           image_dtype=self.image_dtype, on_bad_file=self.on_bad_file, augment_seed=self.seed)

    def setup(self, stage: str | None = None) -> None:
        """As every data module; when fitting, warn if the training depth looks of the kind ``depth_kind`` is not.

        :func:`~dapm_lightning.data.depth_kind.sampled_mismatch` over 32 training files (range or planar).
        """
        super().setup(stage)
        train = self.datasets.get("train")
        if stage in (None, "fit") and isinstance(train, UAPDDataset) and self._processes()[1] == 0:  # one reader
            folder = train.root / train.split / train.depth_dir
            problem = sampled_mismatch(lambda index: read_depth_grey(folder / train.names[index]), train.poses,
                                       self.depth_kind, max_depth=self.max_depth)
            if problem:
                warnings.warn(f"{folder}: {problem}", stacklevel=2)


class SyntheticDataModule(UAPDDataModule):
    """Synthetic UAPD-format data, rendered into ``root`` on first use (and re-rendered if any setting changes).

    A set it rendered is marked a cache in ``root/synth.json``; it replaces no other set (one ``dapm-lightning synth``
    rendered, of other settings, stops it with an error naming the folder).

    Args:
        root: cache folder.
        train_size, val_size: image counts.
        image_size: square side in pixels.
        render_seed: seed of the generator (the scenes and poses); ``seed`` is the loaders'.
        render_workers: processes for the generator (default: CPU count, at most 8).
        families: scene families and their weights, e.g. ``{downtown: 2, suburb: 1}``; None: all alike
            (docs/synthetic.md).
        effects: camera effects (exposure, blur, noise, JPEG artefacts).
        distortion: the lens distortion UAPD randomised (image and depth warped alike).
    """

    def __init__(self, root: str = "data/synthetic", train_size: int = 1000, val_size: int = 200,
                 image_size: int = 64, render_seed: int = 0, render_workers: int | None = None,
                 families: dict[str, float] | None = None, effects: bool = True, distortion: bool = False,
                 **kwargs: Any) -> None:
        super().__init__(root=root, **kwargs)
        self.render_settings: dict[str, Any] = {
            "train": train_size, "val": val_size, "size": image_size, "seed": render_seed,
            "families": families, "effects": effects, "distortion": distortion, "max_depth": self.max_depth}
        self.render_workers = render_workers

    def prepare_data(self) -> None:
        settings = self.render_settings
        changes = settings_changes(self.root, **settings)  # synth.json records every setting and the version
        if not changes:
            return
        what = f"{settings['train']} + {settings['val']} synthetic images at {settings['size']} px"
        if (Path(self.root) / "synth.json").is_file():
            if not is_cache(self.root):  # made with `dapm-lightning synth` (or before caches were marked): kept
                raise SynthFolderError(
                    f"{self.root}: holds a synthetic set of other settings ({changes}), not one this module "
                    "rendered, so it is not replaced.\nFix: give data.init_args.root another folder, give the data "
                    f"module the set's settings ({Path(self.root) / 'synth.json'}), or remove the folder to have "
                    "it rendered anew")
            warnings.warn(f"{self.root}: rendering it again ({what}): it holds a synthetic set of other settings "
                          f"({changes}), whose images are replaced. To keep a set, give this run another "
                          "data.init_args.root.", stacklevel=2)
        else:
            print(f"{self.root}: rendering {what}", flush=True)
        generate_uapd(self.root, workers=self.render_workers, cache=True, **settings)


class PotsdamDataModule(DAPMDataModule):
    """ISPRS Potsdam, depth only (train DAPM(D)).

    ``root`` is the unpacked ISPRS download, no renaming: ``2_Ortho_RGB/`` beside
    ``1_DSM_normalisation/`` (``product: ndsm``, the default) or ``1_DSM/`` (``product: dsm``); the older
    ``rgb/`` + ``height/`` layout also works. Tiles are cut into ``crop_size`` crops on first use and
    split 8:2 with a fixed seed. ``ndsm_scale``: how the 8-bit nDSM becomes metres
    (:class:`~dapm_lightning.data.potsdam.PotsdamCrops`). ``on_bad_file``: ``"raise"`` lists every broken tile and crop
    at start-up; ``"skip"`` leaves them out (and, later, any crop whose file fails).
    """

    def __init__(self, root: str = "data/potsdam", crop_size: int = 512, val_fraction: float = 0.2,
                 split_seed: int = 0, product: Literal["ndsm", "dsm"] = "ndsm", ndsm_scale: float | None = None,
                 on_bad_file: Literal["raise", "skip"] = "raise", **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.root, self.crop_size, self.val_fraction, self.split_seed = Path(root), crop_size, val_fraction, split_seed
        self.product, self.ndsm_scale, self.on_bad_file = product, ndsm_scale, on_bad_file

    def prepare_data(self) -> None:
        PotsdamCrops(self.root, crop_size=self.crop_size, product=self.product, ndsm_scale=self.ndsm_scale,
                     on_bad_file=self.on_bad_file).prepare()

    def make_dataset(self, split: str, train: bool) -> Dataset[Sample]:
        return PotsdamDataset(self.root, "train" if split == "train" else "val",
                              self.split_transform(train), crop_size=self.crop_size,
                              val_fraction=self.val_fraction, seed=self.split_seed, image_dtype=self.image_dtype,
                              augment_seed=self.seed, product=self.product, ndsm_scale=self.ndsm_scale,
                              on_bad_file=self.on_bad_file)


__all__ = ["DAPMDataModule", "PotsdamDataModule", "SyntheticDataModule", "UAPDDataModule", "collate_samples"]
