"""The int8 verdict: an int8 model against its float32 model on held-out renders, as ``export --int8`` prints it.

Both models run the same renders (images the calibration did not see), alternating image by image so a busy
machine slows them alike. Accuracy is the toolbox d1 of the depth (metres, sky excluded) and the median error of
each pose component against the rendered truth; the int8 model passes when its d1 is at most
:data:`D1_TOLERANCE` below the float model's and no pose median is more than :data:`POSE_TOLERANCE` (m or deg)
above it.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from dapm_lightning.geometry.constants import POSE_KEYS, POSE_UNITS
from dapm_lightning.inference.onnx import onnx_feed
from dapm_lightning.inference.quantize import Render

D1_TOLERANCE = 0.01
"""The largest drop of depth d1 an int8 model may have against its float32 model."""
POSE_TOLERANCE = 0.5
"""The largest growth of a pose median (height m; pitch, roll, fov deg) an int8 model may have."""


@dataclass
class Scores:
    """One model on the held-out renders: d1 (None without depth), pose medians (empty without pose), latencies."""

    d1: float | None = None
    pose_median: dict[str, float] = field(default_factory=dict)
    seconds: list[float] = field(default_factory=list)

    @property
    def median_ms(self) -> float:
        """Median latency of one image, ms."""
        return 1000 * statistics.median(self.seconds) if self.seconds else float("nan")


@dataclass
class Int8Verdict:
    """The int8 model against the float32 one (:func:`compare_int8`)."""

    size: tuple[int, int]
    images: int
    float32: Scores
    int8: Scores
    threads: int | None = None

    @property
    def d1_change(self) -> float | None:
        """int8 d1 minus float32 d1 (negative: worse)."""
        if self.float32.d1 is None or self.int8.d1 is None:
            return None
        return self.int8.d1 - self.float32.d1

    @property
    def pose_changes(self) -> dict[str, float]:
        """Per pose component, int8 median error minus float32 median error (positive: worse)."""
        return {k: self.int8.pose_median[k] - self.float32.pose_median[k] for k in self.float32.pose_median}

    @property
    def speedup(self) -> float:
        """float32 latency / int8 latency."""
        return self.float32.median_ms / self.int8.median_ms

    @property
    def failures(self) -> list[str]:
        """What exceeds the tolerances, one phrase each (empty: it passes)."""
        found = []
        change = self.d1_change
        if change is not None and (change < -D1_TOLERANCE or not np.isfinite(change)):
            found.append(f"d1 drops by {-change:.3f} (> {D1_TOLERANCE})")
        for key, growth in self.pose_changes.items():
            if growth > POSE_TOLERANCE or not np.isfinite(growth):
                found.append(f"the {key} median grows by {growth:.2f} {POSE_UNITS[key]} (> {POSE_TOLERANCE})")
        return found

    @property
    def passed(self) -> bool:
        """Whether the int8 model keeps the float model's accuracy within the tolerances."""
        return not self.failures

    def lines(self) -> list[str]:
        """The verdict as printed: accuracy changes, speed, and PASS or FAIL with what failed."""
        out = [f"int8 vs float32 on {self.images} held-out renders at {self.size[0]}x{self.size[1]} "
               "(images the calibration did not see):"]
        if self.d1_change is not None:
            out.append(f"  depth d1 {self.float32.d1:.3f} -> {self.int8.d1:.3f} ({self.d1_change:+.3f}; "
                       f"allowed -{D1_TOLERANCE})")
        for key, growth in self.pose_changes.items():
            out.append(f"  {key} median {self.float32.pose_median[key]:.2f} -> {self.int8.pose_median[key]:.2f} "
                       f"{POSE_UNITS[key]} ({growth:+.2f}; allowed +{POSE_TOLERANCE})")
        out.append(f"  speed: {self.float32.median_ms:.1f} ms -> {self.int8.median_ms:.1f} ms per image "
                   f"({self.speedup:.2f}x float32, batch 1, "
                   f"{self.threads or 'default'} thread{'s' if self.threads != 1 else ''})")
        out.append("  verdict: PASS" if self.passed else "  verdict: FAIL: " + "; ".join(self.failures))
        return out

    def as_dict(self) -> dict[str, Any]:
        """The figures as plain numbers (for benchmarks and logs)."""
        return {"size": list(self.size), "images": self.images, "d1_float32": self.float32.d1,
                "d1_int8": self.int8.d1, "d1_change": self.d1_change, "pose_changes": self.pose_changes,
                "ms_float32": self.float32.median_ms, "ms_int8": self.int8.median_ms, "speedup": self.speedup,
                "passed": self.passed}


def ort_session(path: str | Path, threads: int | None = None) -> Any:
    """An onnxruntime CPU session of ``path`` (``threads``: intra-op threads; default onnxruntime's)."""
    import onnxruntime

    options = onnxruntime.SessionOptions()
    if threads:
        options.intra_op_num_threads = threads
    return onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def run_session(session: Any, image: np.ndarray) -> dict[str, np.ndarray]:
    """One forward pass of an exported model (no telemetry): its outputs by name."""
    names = [o.name for o in session.get_outputs()]
    feed = onnx_feed(image, [i.name for i in session.get_inputs()])
    return dict(zip(names, session.run(None, feed)))


def score(outputs: Sequence[dict[str, np.ndarray]], renders: Sequence[Render]) -> tuple[float | None,
                                                                                        dict[str, float]]:
    """Toolbox d1 of ``depth_m`` and the pose medians of ``pose`` against the renders' truth."""
    from dapm_lightning.metrics import DepthMetrics, PoseMetrics

    depth, pose = DepthMetrics(), PoseMetrics()
    has_depth, has_pose = "depth_m" in outputs[0], "pose" in outputs[0]
    for out, render in zip(outputs, renders):
        if has_depth:
            depth.update(torch.from_numpy(out["depth_m"]), torch.from_numpy(render.depth_m))
        if has_pose:
            pose.update(torch.from_numpy(out["pose"]), torch.from_numpy(render.pose[None]))
    d1 = float(depth.compute()["d1"]) if has_depth else None
    medians = {k: float(v) for k, v in pose.compute().items() if k.endswith("_median")} if has_pose else {}
    return d1, {k: medians[f"{k}_median"] for k in POSE_KEYS if f"{k}_median" in medians}


Runner = Callable[[np.ndarray], dict[str, np.ndarray]]
"""One forward pass: ``[1, 3, H, W]`` float32 image -> outputs by name (``depth_m``, ``pose``, ...)."""


def compare_runners(runners: dict[str, Runner], renders: Sequence[Render]) -> dict[str, Scores]:
    """Every runner on every render, alternating per image after one warm-up pass each: their scores."""
    outputs: dict[str, list[dict[str, np.ndarray]]] = {name: [] for name in runners}
    seconds: dict[str, list[float]] = {name: [] for name in runners}
    for run in runners.values():
        run(renders[0].image)
    for render in renders:
        for name, run in runners.items():
            start = time.perf_counter()
            outputs[name].append(run(render.image))
            seconds[name].append(time.perf_counter() - start)
    return {name: Scores(*score(outputs[name], renders), seconds=seconds[name]) for name in runners}


def session_runner(session: Any) -> Runner:
    """:func:`run_session` of ``session``."""
    return lambda image: run_session(session, image)


def compare_int8(float_path: str | Path, int8_path: str | Path, renders: Sequence[Render],
                 threads: int | None = None) -> Int8Verdict:
    """The int8 model against the float32 model on ``renders`` (:func:`~.quantize.render_set`)."""
    scores = compare_runners({"float32": session_runner(ort_session(float_path, threads)),
                              "int8": session_runner(ort_session(int8_path, threads))}, renders)
    size = (int(renders[0].image.shape[-2]), int(renders[0].image.shape[-1]))
    return Int8Verdict(size, len(renders), scores["float32"], scores["int8"], threads)
