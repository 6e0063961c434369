"""Command-line list options as users type them: ``--splits train val``, ``--splits train,val``, ``--splits=train``.

``jsonargparse`` reads a list option only as ``[train,val]`` (or one value per ``--splits+``); these forms are
rewritten to it before parsing.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence


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


__all__ = ["list_options"]
