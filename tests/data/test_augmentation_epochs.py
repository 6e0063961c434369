"""Each epoch augments every image differently, whatever the loader workers, and two runs augment alike."""

import hashlib

import pytest
from torch.utils.data import DataLoader

from dapm_lightning.data import UAPDDataset
from dapm_lightning.data.datamodules import UAPDDataModule
from dapm_lightning.data.transforms import Augmentation, train_transform
from tests.conftest import write_pair

GROUND = Augmentation(ground_pattern_p=1.0, ground_recolour_p=1.0)
"""Every transform of the pipeline on, the ground's too (they draw from the same per-sample generator)."""


def epoch_digests(root, workers, persistent, epochs=3, augmentation=Augmentation()):  # noqa: B008 (frozen)
    dm = UAPDDataModule(root=str(root), batch_size=2, num_workers=workers, persistent_workers=persistent,
                        augment=True, seed=4, augmentation=augmentation)
    dm.setup("fit")
    loader = dm.train_dataloader()  # one loader for the whole run, as Lightning keeps it
    seen = []
    for epoch in range(epochs):
        loader.sampler.set_epoch(epoch)  # what Lightning does before every epoch
        digests = {}
        for batch in loader:
            for name, image in zip(batch["name"], batch["image"]):
                digests[name] = hashlib.sha1(image.numpy().tobytes()).hexdigest()
        seen.append(digests)
    return seen


@pytest.mark.parametrize(("workers", "persistent", "augmentation"),
                         [(0, False, Augmentation()), (1, False, Augmentation()), (1, True, Augmentation()),
                          (2, True, Augmentation()), (2, True, GROUND)])
def test_augmentation_differs_between_epochs_and_repeats_between_runs(tiny_uapd, workers, persistent, augmentation):
    first = epoch_digests(tiny_uapd, workers, persistent, augmentation=augmentation)
    names = set(first[0]) & set(first[1]) & set(first[2])
    assert names
    changed = sum(len({first[e][n] for e in range(3)}) > 1 for n in names)
    assert changed == len(names), f"{len(names) - changed} image(s) augmented identically in every epoch"
    assert epoch_digests(tiny_uapd, workers, persistent, augmentation=augmentation) == first
    if workers:  # and the same as in the main process
        assert epoch_digests(tiny_uapd, 0, False, augmentation=augmentation) == first


def test_a_data_set_without_augment_seed_augments_apart_in_each_worker_and_epoch(tmp_path):
    """``UAPDDataset(root, split, transform)`` in a user's own loader: each worker and each epoch draws its own."""
    for k in range(8):  # one picture under eight names: any two equal outputs are equal augmentations
        write_pair(tmp_path, "train", f"T{k}_z_40_pitch_-50_roll_5_fov_80.png", (40.0, -50.0, 5.0, 80.0), seed=3)
    dataset = UAPDDataset(tmp_path, "train", train_transform(Augmentation(color_jitter_p=1.0, noise_p=1.0)))

    def epoch() -> list[str]:
        loader = DataLoader(dataset, batch_size=2, num_workers=2, collate_fn=list)
        return [hashlib.sha1(s["image"].numpy().tobytes()).hexdigest() for batch in loader for s in batch]

    first, second = epoch(), epoch()
    assert len(set(first)) == 8, "two workers augmented alike"
    assert not set(first) & set(second), "the next epoch's workers repeated the augmentations"
