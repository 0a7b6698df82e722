"""Shared by the benchmarks: timing with warm-up and repeats, and the machine record.

Every benchmark prints one JSON object: what was measured, median and spread over repeats after a
warm-up, and the machine and library versions it ran on.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from importlib import metadata


def machine() -> dict:
    info = {
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
    }
    versions = {}
    for pkg in ("numpy", "onnxruntime", "opencv-contrib-python-headless", "torch", "sunrig"):
        try:
            versions[pkg] = metadata.version(pkg)
        except metadata.PackageNotFoundError:
            pass
    info["versions"] = versions
    return info


def time_ms(fn: Callable[[], object], repeats: int = 20, warmup: int = 3) -> dict:
    """Median, p10, p90 and min of ``fn``'s wall time in milliseconds."""
    for _ in range(warmup):
        fn()
    samples = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        samples.append((time.perf_counter() - t0) * 1e3)
    samples.sort()
    q = statistics.quantiles(samples, n=10) if len(samples) >= 2 else samples * 9
    return {"median_ms": statistics.median(samples), "p10_ms": q[0], "p90_ms": q[-1], "min_ms": samples[0],
            "repeats": repeats}
