"""Errors that name the files at fault."""

from __future__ import annotations

from collections.abc import Sequence


class DatasetError(ValueError):
    """A data set has problems; ``problems`` lists every one as ``"<file>: <what is wrong>"``."""

    def __init__(self, root: object, problems: Sequence[str], *, shown: int = 50) -> None:
        self.problems = list(problems)
        listed = "\n  ".join(self.problems[:shown])
        more = f"\n  ... and {len(self.problems) - shown} more" if len(self.problems) > shown else ""
        super().__init__(f"{root}: {len(self.problems)} problem(s) found:\n  {listed}{more}")
