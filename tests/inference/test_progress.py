"""Progress and quiet: a bar with images/s and the time left at a terminal; nothing foreign in the Lightning form."""

import sys
import warnings

import cv2
import numpy as np
import pytest

from dapm_lightning.cli import main
from dapm_lightning.tools.progress import quiet_lightning, show_progress


@pytest.fixture()
def six_images(tmp_path):
    folder = tmp_path / "imgs"
    folder.mkdir()
    for k in range(6):
        cv2.imwrite(str(folder / f"i{k}.png"), np.random.default_rng(k).integers(0, 255, (30, 40, 3), np.uint8))
    return folder


def as_terminal(monkeypatch, yes=True):
    monkeypatch.setattr(sys.stdout, "isatty", lambda: yes, raising=False)
    monkeypatch.setattr(sys.stderr, "isatty", lambda: yes, raising=False)


def test_a_progress_bar_at_a_terminal_and_none_when_quiet_or_piped(checkpoint, six_images, tmp_path, capsys,
                                                                   monkeypatch):
    base = ["predict", str(six_images), "--ckpt_path", str(checkpoint), "--device", "cpu", "--batch_size", "2",
            "--outputs", "camera", "--contact_sheet", "0"]
    as_terminal(monkeypatch)
    assert show_progress() and not show_progress(quiet=True)
    main([*base, "--out", str(tmp_path / "a")])
    captured = capsys.readouterr()
    assert "6/6" in captured.err and "image/s" in captured.err  # done of total, the rate (and the time left)
    assert captured.out.startswith("predicted 6 images")  # stdout: the closing line alone
    main([*base, "--out", str(tmp_path / "b"), "--quiet"])
    captured = capsys.readouterr()
    assert "image/s" not in captured.err and "telemetry:" not in captured.err
    as_terminal(monkeypatch, False)  # piped or in a file: no bar
    main([*base, "--out", str(tmp_path / "c")])
    assert "image/s" not in capsys.readouterr().err and not show_progress()


def test_the_lightning_form_shows_no_tips_and_no_foreign_warnings(checkpoint, six_images, tmp_path, capsys,
                                                                  monkeypatch, caplog):
    monkeypatch.chdir(tmp_path)
    main(["predict", "--config", "configs/predict.yaml", "--ckpt_path", str(checkpoint), "--data.init_args.source",
          str(six_images), "--data.init_args.num_workers", "0", "--trainer.callbacks.output_dir", str(tmp_path / "o")])
    captured = capsys.readouterr()
    shown = captured.out + captured.err + caplog.text
    assert "Tip" not in shown and "litlogger" not in shown and "Predicting" not in shown  # not a terminal: no bar
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        quiet_lightning()
        warnings.warn("Be aware ... Please add the following callbacks: ['ModelCheckpoint']", UserWarning, stacklevel=1)
        warnings.warn("`isinstance(treespec, LeafSpec)` is deprecated", DeprecationWarning, stacklevel=1)
        warnings.warn("a warning of the user's own", UserWarning, stacklevel=1)
    assert [str(w.message) for w in seen] == ["a warning of the user's own"]
