"""Bad files as a user meets them: damaged inside, deleted or damaged after the scan, a pose beyond float32."""

import re
import shutil
import struct
import warnings
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from dapm_lightning.data import DatasetError, PotsdamDataset, UAPDDataset, parse_uapd_filename
from dapm_lightning.data.datamodules import UAPDDataModule, collate_samples
from dapm_lightning.data.errors import EVERY_FILE_SKIPPED_FIX, BadFileError, SkippedFile
from dapm_lightning.data.pngcheck import read_npy_header, read_png_info
from dapm_lightning.tools.errors import describe
from dapm_lightning.training.lightning_cli import run_lightning_cli
from tests.conftest import QUICKSTART


def chunks(data: bytes) -> list[tuple[int, int, bytes]]:
    """``(offset, length, type)`` of each chunk of a PNG."""
    found, position = [], 8
    while position < len(data):
        length, kind = struct.unpack_from(">I4s", data, position)
        found.append((position, length, kind))
        position += 12 + length
    return found


def damage(path: Path, kind: bytes = b"IDAT", *, fix_crc: bool = False) -> None:
    """Overwrite 16 bytes in the middle of the first ``kind`` chunk's data (its CRC kept, or computed anew)."""
    data = bytearray(path.read_bytes())
    position, length, _ = next(c for c in chunks(bytes(data)) if c[2] == kind)
    middle = position + 8 + max(0, length // 2 - 8)
    data[middle:middle + min(16, length)] = bytes(255 - b for b in data[middle:middle + min(16, length)])
    if fix_crc:
        struct.pack_into(">I", data, position + 8 + length, zlib.crc32(bytes(data[position + 4:position + 8 + length])))
    path.write_bytes(bytes(data))


def first_name(root: Path) -> str:
    return sorted((root / "train" / "rgb").iterdir())[0].name


@pytest.mark.parametrize("folder", ["rgb", "depth"])
def test_a_damaged_idat_is_refused_at_the_scan_naming_the_file(uapd_copy, folder):
    path = uapd_copy / "train" / folder / first_name(uapd_copy)
    damage(path)
    offset = next(position for position, _, kind in chunks(path.read_bytes()) if kind == b"IDAT")
    with pytest.raises(DatasetError, match="damaged PNG") as info:
        UAPDDataset(uapd_copy, "train")
    assert info.value.problems == [f"{path}: damaged PNG (the CRC of its 'IDAT' chunk at byte {offset} does not "
                                   "match its bytes: the file changed after it was written)"]


@pytest.mark.parametrize("folder", ["rgb", "depth"])
def test_skip_leaves_a_damaged_file_out_naming_it(uapd_copy, folder):
    name = first_name(uapd_copy)
    damage(uapd_copy / "train" / folder / name)
    with pytest.warns(UserWarning, match=f"(?s)skipping 1 bad file.*{re.escape(name)}: damaged PNG"):
        dataset = UAPDDataset(uapd_copy, "train", on_bad_file="skip")
    assert name not in dataset.names and len(dataset) == 3
    assert len(dataset.skipped) == 1 and str(uapd_copy / "train" / folder / name) in dataset.skipped[0]
    for index in range(len(dataset)):  # the rest loads
        dataset[index]


def test_every_file_bad_with_skip_given_is_not_told_to_skip(uapd_copy, tiny_potsdam, tmp_path):
    """on_bad_file skip already given and every file bad: the fix is to mend the files, not to skip them."""
    skip_hint = "--data.init_args.on_bad_file skip"
    for path in (uapd_copy / "train" / "rgb").iterdir():
        damage(path)
    with pytest.warns(UserWarning, match="skipping"), pytest.raises(DatasetError) as info:
        UAPDDataset(uapd_copy, "train", on_bad_file="skip")
    message, expected = describe(info.value)
    assert expected and skip_hint not in message and message.splitlines()[-1] == EVERY_FILE_SKIPPED_FIX
    assert skip_hint in describe(DatasetError(uapd_copy, ["a: damaged"]))[0]  # not given: skipping is one way out
    for path in [*(uapd_copy / "val" / "rgb").iterdir(), *(uapd_copy / "val" / "depth").iterdir()]:
        path.unlink()  # no pair at all: where the pairs go
    with pytest.raises(DatasetError) as info:
        UAPDDataset(uapd_copy, "val", on_bad_file="skip")
    assert describe(info.value)[0].splitlines()[-1].startswith("Fix: put the val split's pairs in ROOT/val/")
    root = Path(shutil.copytree(tiny_potsdam, tmp_path / "p"))
    crops = PotsdamDataset(root, "train", crop_size=32).crops
    for path in (crops / "rgb").iterdir():
        damage(path)
    with pytest.warns(UserWarning, match="skipping"), pytest.raises(DatasetError) as info:
        PotsdamDataset(root, "train", crop_size=32, on_bad_file="skip")
    assert describe(info.value)[0].splitlines()[-1] == EVERY_FILE_SKIPPED_FIX


def test_both_files_of_a_pair_damaged_are_both_named(uapd_copy):
    name = first_name(uapd_copy)
    paths = [uapd_copy / "train" / folder / name for folder in ("rgb", "depth")]
    for path in paths:
        damage(path)
    with pytest.raises(DatasetError) as info:
        UAPDDataset(uapd_copy, "train")
    assert [p.split(": ")[0] for p in info.value.problems] == [str(path) for path in paths]


@pytest.mark.parametrize("kind", [b"IHDR", b"IEND"])
def test_damage_in_any_chunk_is_found(uapd_copy, kind):
    path = uapd_copy / "train" / "depth" / first_name(uapd_copy)
    data = bytearray(path.read_bytes())
    position, length, _ = next(c for c in chunks(bytes(data)) if c[2] == kind)
    data[position + 8 + length] ^= 1  # the CRC's own first byte
    path.write_bytes(bytes(data))
    with pytest.raises(DatasetError, match=f"{path.name}: damaged PNG .the CRC of its '{kind.decode()}' chunk"):
        UAPDDataset(uapd_copy, "train")


def test_bytes_after_iend_and_a_png_without_image_data_are_named(tmp_path, tiny_uapd):
    source = next((tiny_uapd / "train" / "rgb").iterdir()).read_bytes()
    after = tmp_path / "after.png"
    after.write_bytes(source + b"junk")
    with pytest.raises(ValueError, match="after.png: damaged PNG .4 bytes after its IEND chunk"):
        read_png_info(after)
    empty = tmp_path / "empty.png"
    empty.write_bytes(source[:8] + b"".join(source[p:p + 12 + n] for p, n, kind in chunks(source) if kind != b"IDAT"))
    with pytest.raises(ValueError, match="empty.png: damaged PNG .no IDAT chunk"):
        read_png_info(empty)
    assert read_png_info(next((tiny_uapd / "train" / "rgb").iterdir())).width == 40


def test_other_images_in_the_folders_are_named_not_ignored(uapd_copy):
    name = first_name(uapd_copy)
    jpg = uapd_copy / "train" / "rgb" / "Town01_000001_z_50_pitch_-45_roll_0_fov_90.jpg"
    cv2.imwrite(str(jpg), np.zeros((24, 40, 3), np.uint8))
    (uapd_copy / "train" / "rgb" / "notes.txt").write_text("not an image")  # not an image file: not ours to judge
    (uapd_copy / "train" / "rgb" / ".DS_Store").write_bytes(b"\x00\x00\x00\x01Bud1")  # hidden: skipped
    shutil.copy(jpg, uapd_copy / "train" / "rgb" / ".hidden.jpg")  # hidden, though an image: skipped
    shutil.copy(uapd_copy / "train" / "rgb" / name, uapd_copy / "train" / "rgb" / f"._{name}")  # macOS on FAT
    no_suffix = uapd_copy / "train" / "depth" / name.removesuffix(".png")  # a PNG by its bytes, not by its name
    (uapd_copy / "train" / "depth" / name).rename(no_suffix)
    array = uapd_copy / "train" / "depth" / "Town01_000001_z_50_pitch_-45_roll_0_fov_90.npy"
    np.save(array, np.zeros((24, 40), np.float32))
    (uapd_copy / "train" / "rgb" / "more").mkdir()
    with pytest.raises(DatasetError) as info:
        UAPDDataset(uapd_copy, "train")
    rgb = uapd_copy / "train" / "rgb"
    assert sorted(info.value.problems) == sorted([
        f"{jpg}: not a PNG image by its name: UAPD reads NAME.png pairs only, so this file is not read (convert it "
        "to NAME.png, or move it out of the folder)",
        f"{rgb / 'more'}: a folder: UAPD reads the NAME.png files directly in rgb/, so nothing in it is read (move "
        "its files up, or move it out)",
        f"{no_suffix}: not a PNG image by its name: UAPD reads NAME.png pairs only, so this file is not read, and "
        f"{rgb / name} has no pair (convert it to NAME.png, or move it out of the folder)",
        f"{array}: not a PNG image by its name: UAPD reads NAME.png pairs only, so this file is not read (convert "
        "it to NAME.png, or move it out of the folder)"])


def test_a_stray_copy_beside_a_whole_pair_is_named_without_calling_the_pair_unpaired(uapd_copy):
    name = first_name(uapd_copy)
    stray = uapd_copy / "train" / "depth" / name.replace(".png", ".jpg")
    cv2.imwrite(str(stray), np.zeros((24, 40, 3), np.uint8))
    with pytest.raises(DatasetError) as info:
        UAPDDataset(uapd_copy, "train")
    assert info.value.problems == [f"{stray}: not a PNG image by its name: UAPD reads NAME.png pairs only, so this "
                                   "file is not read (convert it to NAME.png, or move it out of the folder)"]


def overflowing(name: str) -> str:
    height = parse_uapd_filename(name)["height"]
    token = f"z_{height:.2f}"
    assert token in name
    return name.replace(token, "z_" + "9" * 40)


def test_a_height_beyond_float32_in_a_name_is_refused_at_the_scan(uapd_copy):
    name = first_name(uapd_copy)
    new = overflowing(name)
    for folder in ("rgb", "depth"):
        (uapd_copy / "train" / folder / name).rename(uapd_copy / "train" / folder / new)
    with pytest.raises(ValueError, match="overflows float32"):
        parse_uapd_filename(new)
    with pytest.raises(DatasetError) as info:
        UAPDDataset(uapd_copy, "train")
    assert info.value.problems == [f"{uapd_copy / 'train' / 'rgb' / new}: {new}: pose key 'z' value {'9' * 40} "
                                   "overflows float32, the pose's type (|value| must be at most 3.4e38)"]
    with pytest.warns(UserWarning, match="overflows float32"):
        dataset = UAPDDataset(uapd_copy, "train", on_bad_file="skip")
    assert len(dataset) == 3 and np.isfinite(dataset.poses).all()


def test_an_impossible_pose_in_a_name_is_refused_at_the_scan_or_skipped(uapd_copy):
    names = sorted((uapd_copy / "train" / "rgb").iterdir())[:2]
    renamed = []
    for path, (token, wrong) in zip(names, (("fov_", "fov_0"), ("z_", "z_-50.43"))):
        value = re.search(token + r"[-\d.]+(?=_|\.png$)", path.name)
        assert value is not None
        new = path.name.replace(value.group(0), wrong)
        for folder in ("rgb", "depth"):
            (uapd_copy / "train" / folder / path.name).rename(uapd_copy / "train" / folder / new)
        renamed.append(uapd_copy / "train" / "rgb" / new)
    with pytest.raises(DatasetError) as info:
        UAPDDataset(uapd_copy, "train")
    assert len(info.value.problems) == 2
    for problem in info.value.problems:
        assert any(problem.startswith(f"{path}: {path.name}: a pose no camera can have") for path in renamed), problem
    assert any("fov_0: fov must be within (0, 180) degrees" in p for p in info.value.problems)
    assert any("z_-50.43: height must be > 0 m" in p for p in info.value.problems)
    with pytest.warns(UserWarning, match="skipping 2 bad file"):
        dataset = UAPDDataset(uapd_copy, "train", on_bad_file="skip")
    assert len(dataset) == 2 and (dataset.poses[:, 0] > 0).all() and (dataset.poses[:, 3] > 0).all()


def test_a_value_at_float32s_limit_is_kept_and_a_number_beyond_float64_is_refused():
    limit = f"{np.finfo(np.float32).max:.0f}"
    assert parse_uapd_filename(f"a_z_{limit}_pitch_-50_roll_0_fov_80.png")["height"] == float(limit)
    with pytest.raises(ValueError, match="key 'x' value 9+ is not a finite number"):
        parse_uapd_filename("a_x_" + "9" * 400 + "_z_1_pitch_-50_roll_0_fov_80.png")


@pytest.mark.parametrize("folder", ["rgb", "depth"])
def test_a_file_deleted_after_the_scan_is_reported_missing(uapd_copy, folder):
    dataset = UAPDDataset(uapd_copy, "train")
    path = uapd_copy / "train" / folder / dataset.names[0]
    path.unlink()
    with pytest.raises(BadFileError) as info:
        dataset[0]
    assert str(info.value) == f"{path}: missing (deleted or moved after the data set was scanned)"
    assert info.value.missing and "cannot be decoded" not in str(info.value)


@pytest.mark.parametrize("folder", ["rgb", "depth"])
def test_a_file_damaged_after_the_scan_cannot_be_decoded(uapd_copy, folder):
    dataset = UAPDDataset(uapd_copy, "train")
    path = uapd_copy / "train" / folder / dataset.names[0]
    damage(path, fix_crc=True)  # damage the CRCs cannot see: only decoding finds it
    read_png_info(path)
    with pytest.raises(BadFileError, match="cannot be decoded as an image") as info:
        dataset[0]
    assert str(path) in str(info.value) and not info.value.missing


def test_the_loader_leaves_out_a_failing_sample_and_lists_it(uapd_copy):
    dataset = UAPDDataset(uapd_copy, "train", on_bad_file="skip")
    raising = UAPDDataset(uapd_copy, "train")
    (uapd_copy / "train" / "rgb" / dataset.names[1]).unlink()
    items = dataset.__getitems__([(0, 0), (0, 1), (0, 2)])
    assert isinstance(items[1], SkippedFile) and "missing" in items[1].problem
    batch = collate_samples(items)
    assert batch["image"].shape[0] == 2 and batch["name"] == [dataset[0]["name"], dataset[2]["name"]]
    assert batch["skipped"] == [f"{uapd_copy / 'train' / 'rgb' / dataset.names[1]}: missing (deleted or moved after "
                                "the data set was scanned); left out (on_bad_file: skip)"]
    assert collate_samples(dataset.__getitems__([(0, 0), (0, 2)]))["skipped"] == []
    with pytest.raises(BadFileError, match="missing"):  # raise (the default): the loader raises
        raising.__getitems__([(0, 0), (0, 1)])


def test_a_batch_whose_every_file_fails_gets_the_next_sample_that_loads(uapd_copy):
    dataset = UAPDDataset(uapd_copy, "train", on_bad_file="skip")
    for index in (0, 1, 2):
        (uapd_copy / "train" / "depth" / dataset.names[index]).unlink()
    batch = collate_samples(dataset.__getitems__([(0, 0), (0, 1)]))
    assert batch["name"] == [Path(dataset.names[3]).stem] and len(batch["skipped"]) == 3
    assert batch["skipped"][2] == (f"{Path(dataset.names[3]).stem}: stands in for a batch whose every file failed "
                                   "(on_bad_file: skip)")
    (uapd_copy / "train" / "rgb" / dataset.names[3]).unlink()
    with pytest.raises(DatasetError, match="no file of the data set loads any more") as info:
        dataset.__getitems__([(0, 0), (0, 1)])
    assert describe(info.value)[0].splitlines()[-1] == EVERY_FILE_SKIPPED_FIX  # skip is on already


TINY = ["--model.net.backbone", "mobilenetv3_small_050", "--model.net.decoder_channels", "16",
        "--model.net.head_channels", "8", "--model.net.pose_hidden", "32", "--data.init_args.batch_size", "2",
        "--data.init_args.num_workers", "0", "--trainer.enable_progress_bar", "false", "--trainer.logger", "false",
        "--trainer.enable_checkpointing", "false", "--trainer.callbacks", "[]"]


def test_training_goes_on_past_a_file_deleted_after_the_scan_and_names_it_once(uapd_copy, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cli = run_lightning_cli(["--config", str(QUICKSTART), "--data.class_path",
                             "dapm_lightning.data.datamodules.UAPDDataModule", "--data.init_args.root", str(uapd_copy),
                             "--data.init_args.on_bad_file", "skip", *TINY, "--trainer.max_epochs", "3",
                             "--trainer.limit_val_batches", "1"], run=False)
    datamodule = cli.datamodule
    assert isinstance(datamodule, UAPDDataModule)
    real_setup = datamodule.setup

    def setup_then_delete(stage=None):
        real_setup(stage)
        for split in ("train", "val"):  # the scan has passed: the files go now
            names = datamodule.datasets[split].names
            (uapd_copy / split / "rgb" / names[-1]).unlink()

    monkeypatch.setattr(datamodule, "setup", setup_then_delete)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cli.trainer.fit(cli.model, datamodule=datamodule)
    assert cli.trainer.global_step == 3 * 2 and cli.trainer.current_epoch == 3  # every epoch, every step
    assert torch.isfinite(cli.trainer.callback_metrics["train_loss_epoch"])
    missing = [str(uapd_copy / split / "rgb" / datamodule.datasets[split].names[-1]) for split in ("train", "val")]
    stand_in = Path(datamodule.datasets["val"].names[0]).stem  # the last validation batch held only that file
    assert sorted(datamodule.skipped_while_loading) == sorted(
        [f"{path}: missing (deleted or moved after the data set was scanned); left out (on_bad_file: skip)"
         for path in missing] + [f"{stand_in}: stands in for a batch whose every file failed (on_bad_file: skip)"])
    for path in missing:  # seen in each of the 3 epochs (and the sanity check), named once
        named = [w for w in caught if path in str(w.message)]
        assert len(named) == 1 and "missing" in str(named[0].message), [str(w.message) for w in named]
    assert not any("cannot be decoded" in str(w.message) for w in caught)


@pytest.fixture()
def potsdam_copy(tiny_potsdam, tmp_path):
    root = Path(shutil.copytree(tiny_potsdam, tmp_path / "potsdam", ignore=shutil.ignore_patterns("crops_*")))
    PotsdamDataset(root, "train", crop_size=32)
    return root


def test_potsdam_crops_damaged_or_truncated_are_named_at_the_scan(potsdam_copy):
    dataset = PotsdamDataset(potsdam_copy, "train", crop_size=32)
    crops = dataset.crops
    png, npy = crops / "rgb" / f"{dataset.names[0]}.png", crops / "height" / f"{dataset.names[1]}.npy"
    damage(png)
    npy.write_bytes(npy.read_bytes()[:-100])
    with pytest.raises(DatasetError) as info:
        PotsdamDataset(potsdam_copy, "train", crop_size=32)
    assert len(info.value.problems) == 2
    assert info.value.problems[0].startswith(f"{png}: damaged PNG (the CRC of its 'IDAT' chunk")
    assert info.value.problems[1] == (f"{npy}: truncated .npy file (4124 bytes, its header says 4224 for a float32 "
                                      "array of shape (32, 32))")
    with pytest.raises(ValueError, match="truncated .npy"):
        read_npy_header(npy)
    with pytest.warns(UserWarning, match="skipping 2 bad crop"):
        skipping = PotsdamDataset(potsdam_copy, "train", crop_size=32, on_bad_file="skip")
    assert skipping.names == dataset.names[2:] and len(skipping.skipped) == 2


def test_potsdam_crop_deleted_after_the_scan_is_missing_and_skippable(potsdam_copy):
    dataset = PotsdamDataset(potsdam_copy, "train", crop_size=32, on_bad_file="skip")
    path = dataset.crops / "height" / f"{dataset.names[0]}.npy"
    path.unlink()
    with pytest.raises(BadFileError, match="missing .deleted or moved after the data set was scanned"):
        dataset[0]
    batch = collate_samples(dataset.__getitems__([0, 1]))
    assert batch["name"] == [dataset.names[1]] and batch["skipped"][0].startswith(f"{path}: missing")


def test_every_undecodable_potsdam_tile_is_listed(tiny_potsdam, tmp_path):
    root = Path(shutil.copytree(tiny_potsdam, tmp_path / "p", ignore=shutil.ignore_patterns("crops_*")))
    rgb = sorted((root / "rgb").iterdir())[0]
    height = sorted((root / "height").iterdir())[1]
    rgb.write_bytes(b"not a tiff")
    height.write_bytes(height.read_bytes()[:50])
    with pytest.raises(DatasetError) as info:
        PotsdamDataset(root, "train", crop_size=32)
    assert info.value.problems == [f"{rgb}: cannot be decoded", f"{height}: cannot be decoded"]
    assert not any(root.glob("crops_*/crops.json"))


def test_without_skip_a_file_deleted_after_the_scan_stops_the_loader_as_missing_from_a_worker(uapd_copy):
    datamodule = UAPDDataModule(str(uapd_copy), batch_size=4, num_workers=1, augment=False)
    datamodule.setup("fit")
    path = uapd_copy / "train" / "depth" / datamodule.datasets["train"].names[2]
    path.unlink()
    with pytest.raises(BadFileError) as info:  # the worker's error keeps its type (a ValueError: a short CLI message)
        next(iter(datamodule.train_dataloader()))
    assert f"{path}: missing (deleted or moved after the data set was scanned)" in str(info.value)
    assert info.value.missing and "cannot be decoded" not in str(info.value)
