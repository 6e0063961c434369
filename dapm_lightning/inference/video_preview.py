"""``STEM_depth.mp4``: a video source's frames beside their depth, written as the frames come (OpenCV's writer).

The frame rate is the kept frames' own (the video's, over ``frame_step``), from their times in the video; the
preview is at most :data:`PREVIEW_HEIGHT` pixels high. It is written to a hidden file and renamed once read back
whole (OpenCV's writer reports no failed write: a full disk leaves a file no player opens).
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from dapm_lightning.data.files import WriteError
from dapm_lightning.inference.postprocess import Prediction

PREVIEW_HEIGHT = 720
"""The most pixels high a preview is (frames are shrunk to it)."""
FRAME_NAME = re.compile(r"(?P<video>.+)_f(?P<frame>\d{6,})")
"""A video frame's output name: ``STEM_f<frame number>``."""


def _even(value: int) -> int:
    return max(2, value - value % 2)


class _Preview:
    """One video's preview: the first frame waits for the second, whose time gives the frame rate."""

    def __init__(self, path: Path) -> None:
        self.path, self.partial = path, path.with_name(f".{path.stem}.partial{path.suffix}")
        self.pending: tuple[np.ndarray, float] | None = None
        self.writer: Any = None
        self.size: tuple[int, int] | None = None
        self.frames = 0

    def _open(self, fps: float, frame: np.ndarray) -> None:
        self.size = (frame.shape[1], frame.shape[0])
        fourcc = cv2.VideoWriter_fourcc(*"mp4v")  # type: ignore[attr-defined]
        self.writer = cv2.VideoWriter(str(self.partial), fourcc, fps, self.size)
        if not self.writer.isOpened():
            self.partial.unlink(missing_ok=True)
            raise WriteError(self.path, "OpenCV cannot write an mp4 here: its FFmpeg lacks the mp4v encoder, or the "
                             "folder refuses the file", "leave videos out of the run, or write to another folder")

    def _write(self, frame: np.ndarray) -> None:
        assert self.size is not None
        if (frame.shape[1], frame.shape[0]) != self.size:
            frame = cv2.resize(frame, self.size, interpolation=cv2.INTER_AREA)
        self.writer.write(cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
        self.frames += 1

    def add(self, frame: np.ndarray, time_s: float) -> None:
        if self.writer is None and self.pending is None:
            self.pending = (frame, time_s)
            return
        if self.writer is None:
            assert self.pending is not None
            first, start = self.pending
            self._open(1.0 / (time_s - start) if time_s > start else 25.0, first)
            self._write(first)
            self.pending = None
        self._write(frame)

    def close(self) -> Path:
        if self.pending is not None:  # a single frame: one second of it
            self._open(1.0, self.pending[0])
            self._write(self.pending[0])
        self.writer.release()
        read = _frames_readable(self.partial)  # the writer's failures are silent: the file is checked
        if read != self.frames:
            self.partial.unlink(missing_ok=True)
            raise WriteError(self.path, f"{read} of its {self.frames} frames read back: a full disk?",
                             "free space on that disk, or write to another folder")
        os.replace(self.partial, self.path)
        return self.path

    def abandon(self) -> None:
        if self.writer is not None:
            self.writer.release()
        self.partial.unlink(missing_ok=True)


def _frames_readable(path: Path) -> int:
    """How many frames a video file says it holds (0 when it does not open: an mp4 without its index)."""
    capture = cv2.VideoCapture(str(path))
    try:
        return int(capture.get(cv2.CAP_PROP_FRAME_COUNT)) if capture.isOpened() else 0
    finally:
        capture.release()


def preview_frame(rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """The input frame beside its depth picture, both at one height (at most :data:`PREVIEW_HEIGHT`), even sizes."""
    height = _even(min(PREVIEW_HEIGHT, rgb.shape[0]))
    parts = [cv2.resize(p, (max(1, round(p.shape[1] * height / p.shape[0])), height), interpolation=cv2.INTER_AREA)
             for p in (rgb, depth)]
    frame = np.concatenate(parts, axis=1)
    return frame[:, :_even(frame.shape[1])]


class VideoPreviews:
    """Every video's preview of a run, one open at a time in the order the frames come."""

    def __init__(self) -> None:
        self.open: dict[str, _Preview] = {}
        self.written: list[Path] = []

    def add(self, out: Path, prediction: Prediction, depth: np.ndarray | None) -> None:
        """Add a prediction's frame to its video's preview (nothing for an image, or without pixels or depth)."""
        match = FRAME_NAME.fullmatch(prediction.name)
        if prediction.time_s is None or match is None or prediction.rgb is None or depth is None:
            return
        video = match.group("video")
        if video not in self.open:
            for other in list(self.open):  # the previous video is complete: images come in order
                self.written.append(self.open.pop(other).close())
            self.open[video] = _Preview(out / f"{video}_depth.mp4")
        self.open[video].add(preview_frame(prediction.rgb, depth), prediction.time_s)

    def finish(self) -> list[Path]:
        """Close the open preview; returns every preview written."""
        for video in list(self.open):
            self.written.append(self.open.pop(video).close())
        return self.written

    def abandon(self) -> None:
        """After a failure: the preview being written goes (those complete stay)."""
        for video in list(self.open):
            self.open.pop(video).abandon()
