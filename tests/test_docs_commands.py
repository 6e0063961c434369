"""Every command shown in README.md and docs/ parses as written (placeholders filled).

Each ``dapm-lightning SUBCOMMAND ...`` line of a fenced code block (continuation lines joined) is parsed by the
real parser without running: ``fit``/``validate``/``test``, the Lightning form of ``predict``, ``export`` and
``doctor`` through the entry point with ``--print_config`` appended (every config and option resolved, the
configuration printed), the one-line ``predict`` and ``synth`` by their argparse parsers. A documented option
that does not exist, or a data setting without its data module, fails here as it would for a reader. Lines that
show a grammar (``[--out DIR]``, ``SOURCE...``) are not commands and are left out.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from dapm_lightning.cli import main
from dapm_lightning.tools.predict import is_lightning_form
from dapm_lightning.tools.predict import parse as parse_predict
from dapm_lightning.tools.synth import build_parser as build_synth_parser

REPO = Path(__file__).resolve().parents[1]
DOCUMENTS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
COMMAND = re.compile(r"^(?:srun\s+)?(?:\.venv/bin/)?dapm-lightning\s+(fit|validate|test|predict|export|doctor|synth)\b")
PLACEHOLDERS = {"/data/UAPD": "DATA", "/data/Potsdam": "DATA", "PATH": "CKPT", "CKPT": "CKPT"}


def documented_commands() -> list[tuple[str, list[str]]]:
    """``(where, argv)`` of each documented command (not ``--help`` ones, nor grammars with ``...`` or ``[``)."""
    found = []
    for document in DOCUMENTS:
        lines = document.read_text(encoding="utf-8").splitlines()
        in_block, k = False, 0
        while k < len(lines):
            line = lines[k]
            if line.lstrip().startswith("```"):
                in_block = not in_block
            elif in_block and COMMAND.match(line.strip()):
                start, text = k, line.strip()
                while text.endswith("\\") and k + 1 < len(lines):
                    k += 1
                    text = text[:-1] + " " + lines[k].strip()
                words = shlex.split(text, comments=True)
                words = words[words.index(next(w for w in words if w.endswith("dapm-lightning"))) + 1:]
                grammar = any("..." in word or word.startswith("[") for word in words)
                if not grammar and "--help" not in words and "--print_config" not in words:
                    found.append((f"{document.relative_to(REPO)}:{start + 1}", words))
            k += 1
    return found


COMMANDS = documented_commands()


def test_the_docs_show_training_commands():
    assert len(COMMANDS) >= 30, COMMANDS  # the extraction finds them (README, training, predict, data, ...)
    assert {argv[0] for _, argv in COMMANDS} == {"fit", "validate", "test", "predict", "export", "doctor", "synth"}


@pytest.mark.parametrize("where,argv", COMMANDS, ids=[where for where, _ in COMMANDS])
def test_a_documented_command_parses_as_written(where, argv, tiny_uapd, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(REPO)
    filled = {"DATA": str(tiny_uapd), "CKPT": str(tmp_path / "model.ckpt")}
    argv = [filled.get(PLACEHOLDERS.get(word, ""), word) for word in argv]
    if argv[0] == "synth":
        build_synth_parser().parse_args(argv[1:])  # argparse: exits 2 on an unknown option
        return
    if argv[0] == "predict" and not is_lightning_form(argv[1:]):
        parse_predict(argv[1:])
        return
    with pytest.raises(SystemExit) as stopped:
        main([*argv, "--print_config"])
    said = capsys.readouterr()
    assert stopped.value.code in (0, None), f"{where}: {' '.join(argv)}\n{said.err[-2000:]}"
    assert said.out.strip(), f"{where}: no configuration printed\n{said.err[-2000:]}"
