"""Each epoch augments every image differently, whatever the loader workers, and two runs augment alike."""

import hashlib

import pytest

from dapm_lightning.data.datamodules import UAPDDataModule
from dapm_lightning.data.transforms import Augmentation

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
