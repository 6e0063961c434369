"""Cheap PNG header checks, so that a broken file is reported when a data set is built, not mid-training."""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_IEND = b"\x00\x00\x00\x00IEND\xaeB`\x82"
COLOR_TYPES = {0: "grey", 2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}


@dataclass(frozen=True)
class PngInfo:
    """What the IHDR chunk of a PNG says."""

    width: int
    height: int
    bit_depth: int
    color_type: int

    @property
    def color(self) -> str:
        return COLOR_TYPES.get(self.color_type, f"color type {self.color_type}")


def read_png_info(path: Path) -> PngInfo:
    """Read the header of a PNG and check that the file ends with its IEND chunk.

    Raises:
        ValueError: naming the file, if it is not a PNG, its header is damaged or it is truncated.
    """
    try:
        with path.open("rb") as handle:
            head = handle.read(33)
            handle.seek(0, 2)
            size = handle.tell()
            handle.seek(max(size - len(_IEND), 0))
            tail = handle.read()
    except OSError as error:
        raise ValueError(f"{path}: cannot be read ({error})") from error
    if len(head) < 33 or head[:8] != _SIGNATURE or head[12:16] != b"IHDR":
        raise ValueError(f"{path}: not a PNG file (bad signature or header, {size} bytes)")
    width, height, bit_depth, color_type = struct.unpack(">IIBB", head[16:26])
    if tail != _IEND:
        raise ValueError(f"{path}: truncated PNG (no IEND chunk at the end of its {size} bytes)")
    return PngInfo(width, height, bit_depth, color_type)
