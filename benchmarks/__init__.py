"""Benchmarks beside the package, not in the wheel; run from the repository root.

``python -m benchmarks.bench`` (``make bench``), ``benchmarks.bench_synth``, ``benchmarks.bench_predict``,
``benchmarks.bench_gpu`` (``make bench-gpu``). They use the package's public API; nothing in ``dapm_lightning``
imports them.
"""
