"""Progress bars: drawn on a terminal, never in a log or a pipe, never with --quiet."""

import io
import sys

import pytest

from dapm_lightning.tools.progress import progress_bar
from dapm_lightning.tools.synth import synth_main


class Terminal(io.StringIO):
    def isatty(self):
        return True


@pytest.mark.parametrize("terminal,quiet,drawn", [(True, False, True), (True, True, False), (False, False, False)])
def test_synth_draws_a_bar_on_a_terminal_only(terminal, quiet, drawn, tmp_path, monkeypatch, capsys):
    stream = Terminal() if terminal else io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    monkeypatch.setattr(sys.stdout, "isatty", lambda: terminal, raising=False)
    synth_main(["--out", str(tmp_path / "d"), "--train", "5", "--val", "1", "--size", "16", "--workers", "1",
                *(["--quiet"] if quiet else [])])
    assert "wrote 5 train + 1 val images" in capsys.readouterr().out  # the result line, always
    bar = stream.getvalue()
    assert ("rendering:" in bar and "/6 [" in bar and "image/s" in bar) == drawn, bar


def test_an_undrawn_bar_takes_the_same_calls(monkeypatch):
    stream = io.StringIO()
    monkeypatch.setattr(sys, "stderr", stream)
    with progress_bar(3, what="x") as bar:
        bar.update(2)
        bar.set_postfix_str("y")
    assert stream.getvalue() == ""


def test_doctor_draws_a_bar_per_split_on_a_terminal(tmp_path, monkeypatch, capsys):
    from dapm_lightning.data.synthetic import generate_uapd
    from dapm_lightning.tools.doctor import doctor_main

    root = generate_uapd(tmp_path / "d", train=3, val=2, size=16, workers=1)
    stream = Terminal()
    monkeypatch.setattr(sys, "stderr", stream)
    monkeypatch.setattr(sys.stdout, "isatty", lambda: True, raising=False)
    assert doctor_main([str(root)]) == 0
    assert "checking train:" in stream.getvalue() and "checking val:" in stream.getvalue()
    stream.truncate(0)
    for quiet in (["--quiet"], ["--quiet", "true"], ["--quiet=yes"]):
        assert doctor_main([str(root), *quiet]) == 0
        assert "checking" not in stream.getvalue(), quiet
    assert doctor_main([str(root), "--no_quiet"]) == 0
    assert "checking train:" in stream.getvalue()
