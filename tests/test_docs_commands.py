"""Every training command shown in README.md and docs/ parses as written (placeholders filled).

Each ``dapm-lightning fit|validate|test ...`` line of a fenced code block (continuation lines joined) runs
through the real entry point with ``--print_config`` appended: LightningCLI resolves every config and option
and prints the configuration without training, so a documented option that does not exist, or a data setting
without its data module, fails here as it would for a reader.
"""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest

from dapm_lightning.cli import main

REPO = Path(__file__).resolve().parents[1]
DOCUMENTS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
COMMAND = re.compile(r"^(?:srun\s+)?(?:\.venv/bin/)?dapm-lightning\s+(fit|validate|test)\b")
PLACEHOLDERS = {"/data/UAPD": "DATA", "/data/Potsdam": "DATA", "PATH": "CKPT", "CKPT": "CKPT"}


def documented_commands() -> list[tuple[str, list[str]]]:
    """``(where, argv)`` of each documented fit/validate/test command (not ``--help`` ones, nor ``...`` elisions)."""
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
                if "..." not in words and "--help" not in words and "--print_config" not in words:
                    found.append((f"{document.relative_to(REPO)}:{start + 1}", words))
            k += 1
    return found


COMMANDS = documented_commands()


def test_the_docs_show_training_commands():
    assert len(COMMANDS) >= 8, COMMANDS  # the extraction finds them (README, training, long jobs)


@pytest.mark.parametrize("where,argv", COMMANDS, ids=[where for where, _ in COMMANDS])
def test_a_documented_command_parses_as_written(where, argv, tiny_uapd, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(REPO)
    filled = {"DATA": str(tiny_uapd), "CKPT": str(tmp_path / "model.ckpt")}
    argv = [filled.get(PLACEHOLDERS.get(word, ""), word) for word in argv]
    with pytest.raises(SystemExit) as stopped:
        main([*argv, "--print_config"])
    said = capsys.readouterr()
    assert stopped.value.code in (0, None), f"{where}: {' '.join(argv)}\n{said.err[-2000:]}"
    assert "trainer:" in said.out, f"{where}: no configuration printed\n{said.err[-2000:]}"
