"""File checks cheap enough for every file of a data set, so that a broken file is reported at start-up.

A data set checks each of its files when it is built, not when training reaches it. :func:`read_png_info` reads
the whole PNG and walks its chunks: the signature, the IHDR header, every chunk's length and CRC (``zlib.crc32``:
damage anywhere in the file, image data included, changes its chunk's CRC), at least one IDAT chunk, and the IEND
chunk at the very end. It does not inflate the image data: a file whose CRCs were computed over wrong data (a
broken writer) passes; decoding it (``dapm-lightning doctor``) finds that. :func:`read_npy_header` checks a
``.npy`` file's header and length. :func:`scan_files` runs a check over many files in threads.
"""

from __future__ import annotations

import os
import struct
import zlib
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import numpy as np

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
COLOR_TYPES = {0: "grey", 2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}
SCAN_THREADS = min(8, os.cpu_count() or 1)
"""Threads of a start-up scan (reading a file and zlib's CRC release the GIL; a network file system gains most)."""
_CHUNK_HEAD, _U32 = struct.Struct(">I4s"), struct.Struct(">I")
_Item = TypeVar("_Item")
_Result = TypeVar("_Result")


@dataclass(frozen=True)
class PngInfo:
    """What the IHDR chunk of a PNG says."""

    width: int
    height: int
    bit_depth: int
    color_type: int

    @property
    def color(self) -> str:
        """The colour type by name (``grey``, ``RGB``, ``palette``, ``grey+alpha``, ``RGBA``)."""
        return COLOR_TYPES.get(self.color_type, f"color type {self.color_type}")


def read_file(path: Path) -> bytes:
    """The bytes of a data set's file.

    Raises:
        ValueError: naming the file: missing, or it cannot be read (and why).
    """
    try:
        return path.read_bytes()
    except FileNotFoundError as error:
        raise ValueError(f"{path}: missing") from error
    except OSError as error:
        raise ValueError(f"{path}: cannot be read ({error.strerror or error})") from error


def _name(kind: bytes) -> str:
    """A chunk type as text, e.g. ``'IDAT'``."""
    return repr(kind.decode("latin-1"))


def read_png_info(path: Path) -> PngInfo:
    """Check a PNG's structure and every chunk's CRC, and return what its header says.

    Raises:
        ValueError: naming the file, if it is missing or unreadable, not a PNG, truncated, damaged (a chunk
            whose CRC does not match its bytes), without image data, or followed by bytes after its IEND chunk.
    """
    data = read_file(path)
    size = len(data)
    if size < 33 or data[:8] != _SIGNATURE or data[12:16] != b"IHDR" or data[8:12] != b"\x00\x00\x00\x0d":
        raise ValueError(f"{path}: not a PNG file (bad signature or header, {size} bytes)")
    width, height, bit_depth, color_type = struct.unpack_from(">IIBB", data, 16)
    view, crc32, chunk_head, u32 = memoryview(data), zlib.crc32, _CHUNK_HEAD.unpack_from, _U32.unpack_from
    position, image_data = 8, False
    while True:  # every chunk: length, type, data, CRC of type and data
        if position + 12 > size:
            raise ValueError(f"{path}: truncated PNG (it ends {size - position} bytes into the header of a chunk at "
                             f"byte {position}; no IEND chunk at the end of its {size} bytes)")
        length, kind = chunk_head(data, position)
        end = position + 12 + length
        if end > size:
            raise ValueError(f"{path}: truncated PNG (its {_name(kind)} chunk at byte {position} holds {length} "
                             f"bytes, the file ends {size - position - 12} bytes into it; no IEND chunk at the end "
                             f"of its {size} bytes)")
        if crc32(view[position + 4:end - 4]) != u32(data, end - 4)[0]:
            raise ValueError(f"{path}: damaged PNG (the CRC of its {_name(kind)} chunk at byte {position} does not "
                             "match its bytes: the file changed after it was written)")
        if kind == b"IEND":
            break
        image_data = image_data or kind == b"IDAT"
        position = end
    if not image_data:
        raise ValueError(f"{path}: damaged PNG (no IDAT chunk: no image data)")
    if end != size:
        raise ValueError(f"{path}: damaged PNG ({size - end} bytes after its IEND chunk, which ends the image)")
    return PngInfo(width, height, bit_depth, color_type)


def read_npy_header(path: Path) -> tuple[tuple[int, ...], np.dtype]:
    """Check a ``.npy`` file's header and length, without reading its array.

    Returns:
        ``(shape, dtype)``.

    Raises:
        ValueError: naming the file, if it is missing or unreadable, not a ``.npy`` file, or truncated.
    """
    try:
        with path.open("rb") as handle:
            version = np.lib.format.read_magic(handle)
            read_header = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                np.lib.format.read_array_header_2_0
            shape, _, dtype = read_header(handle)
            start, size = handle.tell(), os.fstat(handle.fileno()).st_size
    except FileNotFoundError as error:
        raise ValueError(f"{path}: missing") from error
    except OSError as error:
        raise ValueError(f"{path}: cannot be read ({error.strerror or error})") from error
    except ValueError as error:
        raise ValueError(f"{path}: not a .npy file ({error})") from error
    expected = start + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if size != expected:
        raise ValueError(f"{path}: {'truncated' if size < expected else 'damaged'} .npy file ({size} bytes, its "
                         f"header says {expected} for a {dtype} array of shape {shape})")
    return tuple(shape), dtype


def scan_files(check: Callable[[_Item], _Result], items: Sequence[_Item]) -> list[_Result]:
    """``[check(item) for item in items]``, in :data:`SCAN_THREADS` threads when there are many items."""
    if len(items) < 64 or SCAN_THREADS < 2:
        return [check(item) for item in items]
    with ThreadPoolExecutor(SCAN_THREADS) as pool:
        return list(pool.map(check, items))
