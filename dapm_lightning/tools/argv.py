"""Options as users type them: lists and boolean flags for the ``jsonargparse`` commands, counts for ``argparse``.

``jsonargparse`` reads a list option only as ``[train,val]`` (or one value per ``--splits+``), and a boolean only
with its value (``--quiet true``); ``--splits train val``, ``--splits train,val``, ``--splits=train``, ``--quiet``
and ``--no_quiet`` are rewritten to those forms before parsing.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterable, Sequence


def whole_number(least: int) -> Callable[[str], int]:
    """An argparse type: a whole number of at least ``least`` (sizes, counts), or an error saying so."""

    def check(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < least:
            raise argparse.ArgumentTypeError(f"must be {'at least 1' if least == 1 else f'{least} or more'}, "
                                             f"got {value}")
        return value

    return check


def list_options(argv: Sequence[str], names: Iterable[str]) -> list[str]:
    """``argv`` with each of ``names`` given as a space- or comma-separated list rewritten to ``--NAME=[a,b]``.

    A value already in brackets, ``--NAME+ value`` and everything else pass through unchanged.
    """
    names = set(names)
    result: list[str] = []
    k = 0
    while k < len(argv):
        word = argv[k]
        name, equals, value = word.partition("=")
        if name in names and not (equals and value.startswith("[")):
            values = [value] if equals else []
            k += 1
            while not equals and k < len(argv) and not argv[k].startswith("-"):
                values.append(argv[k])
                k += 1
            if not equals and values and values[0].startswith("["):
                result += [word, *values]
                continue
            items = [item for text in values for item in text.split(",") if item]
            result.append(f"{name}=[{','.join(items)}]" if items else word)
            continue
        result.append(word)
        k += 1
    return result


def flag_options(argv: Sequence[str], names: Iterable[str]) -> list[str]:
    """``argv`` with each boolean of ``names`` given bare (``--quiet``, ``--no_quiet``) as ``--quiet=true|false``.

    ``--quiet true`` / ``--quiet=false`` pass through unchanged.
    """
    names = set(names)
    values = ("true", "false", "yes", "no", "1", "0", "on", "off")
    result: list[str] = []
    for k, word in enumerate(argv):
        following = argv[k + 1].lower() if k + 1 < len(argv) else ""
        if word in names and following not in values:
            result.append(f"{word}=true")
        elif word.startswith("--no_") and f"--{word[5:]}" in names:
            result.append(f"--{word[5:]}=false")
        else:
            result.append(word)
    return result


__all__ = ["flag_options", "list_options"]
