"""Augmentation strengths as settings; the authors' values (train.py) by their effect on pixels."""

import numpy as np
import pytest

from dapm_lightning.data.datamodules import UAPDDataModule
from dapm_lightning.data.transforms import AUTHORS_AUGMENTATION, Augmentation, train_transform

POSE = np.array([40.0, -30.0, 5.0, 70.0], np.float32)
ONLY = {"brightness": 0.0, "contrast": 0.0, "saturation": 0.0, "color_jitter_p": 0.0, "noise_p": 0.0, "flip_p": 0.0}


def draws(augmentation, image, count=300):
    pipeline = train_transform(augmentation)
    outputs = []
    for seed in range(count):
        pipeline.set_random_seed(seed)
        outputs.append(pipeline(image=image, mask=image[..., 0], pose=POSE)["image"].astype(np.float64))
    return outputs


@pytest.mark.parametrize("strength", [0.2, 0.5])
def test_brightness_factor_spans_one_plus_minus_the_strength(strength):
    grey = np.full((8, 8, 3), 100, np.uint8)
    factors = np.array([out.mean() / 100 for out in
                        draws(Augmentation(**{**ONLY, "brightness": strength, "color_jitter_p": 1.0}), grey)])
    assert factors.min() >= 1 - strength - 0.01 and factors.max() <= 1 + strength + 0.01
    assert factors.min() < 1 - 0.8 * strength and factors.max() > 1 + 0.8 * strength


def test_the_authors_jitter_is_on_every_image_and_the_default_on_four_in_five():
    grey = np.full((8, 8, 3), 100, np.uint8)

    def changed(augmentation):
        return np.mean([not np.array_equal(out, grey) for out in draws(augmentation, grey)])

    # a factor within 0.005 of 1 leaves grey 100 as it is: 1 % of the draws at strength 0.5, 2.5 % at 0.2
    authors = Augmentation(**{**ONLY, "brightness": 0.5, "color_jitter_p": AUTHORS_AUGMENTATION.color_jitter_p})
    assert changed(authors) >= 0.97
    assert changed(Augmentation(**{**ONLY, "brightness": 0.2, "color_jitter_p": 0.8})) == pytest.approx(0.78, abs=0.07)


def test_noise_sigma_is_a_share_of_the_intensity_range_and_its_probability():
    grey = np.full((32, 32, 3), 128, np.uint8)
    sigma = AUTHORS_AUGMENTATION.noise_std[0]
    noisy = draws(Augmentation(**{**ONLY, "noise_std": (sigma, sigma), "noise_p": 1.0}), grey, count=20)
    assert np.mean([np.std(out - 128) for out in noisy]) == pytest.approx(0.05 * 255, rel=0.05)  # 12.75 levels
    sometimes = draws(Augmentation(**{**ONLY, "noise_std": (sigma, sigma), "noise_p": AUTHORS_AUGMENTATION.noise_p}),
                      grey)
    assert np.mean([not np.array_equal(out, grey) for out in sometimes]) == pytest.approx(0.5, abs=0.07)


def test_the_data_module_uses_its_augmentation_on_the_training_split_only(tiny_uapd):
    module = UAPDDataModule(root=str(tiny_uapd), augmentation=AUTHORS_AUGMENTATION)
    jitter, noise, flip = module.split_transform(True).transforms
    assert (jitter.p, noise.p, flip.p) == (1.0, 0.5, 0.5) and tuple(noise.std_range) == (0.05, 0.05)
    assert module.split_transform(False) is None
    assert UAPDDataModule(root=str(tiny_uapd), augment=False, augmentation=AUTHORS_AUGMENTATION).split_transform(
        True) is None
    from_mapping = UAPDDataModule(root=str(tiny_uapd), augmentation={"noise_p": 0.5, "noise_std": [0.05, 0.05]})
    assert from_mapping.augmentation == Augmentation(noise_p=0.5, noise_std=(0.05, 0.05))
    assert UAPDDataModule(root=str(tiny_uapd)).augmentation == Augmentation()  # today's light augmentation


@pytest.mark.parametrize(("changes", "message"), [({"noise_std": (0.05, 0.01)}, "noise_std"),
                                                  ({"noise_p": 1.5}, "noise_p must be a probability"),
                                                  ({"brightness": -0.1}, "brightness must be >= 0")])
def test_bad_strengths_are_refused(changes, message):
    with pytest.raises(ValueError, match=message):
        Augmentation(**changes)
