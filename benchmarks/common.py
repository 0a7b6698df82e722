"""Shared by the benchmarks: timing with warm-up and repeats, and the machine record.

Every benchmark prints one JSON object: what was measured, median and spread over repeats after a
warm-up, and the machine and library versions it ran on.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

# The seed of the validation drives, on which runs are compared (docs/model.md, "How a run is
# chosen"); held-out drives are 2000 (bench_accuracy.py) and training drives 1000.
VALIDATION_SEED = 2500


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
    # "inclusive": within the samples; the default ("exclusive") extrapolates past them on a few
    # repeats (3 runs of 10, 20 and 30 ms gave a p10 of 4 ms).
    q = statistics.quantiles(samples, n=10, method="inclusive") if len(samples) >= 2 else samples * 9
    return {"median_ms": statistics.median(samples), "p10_ms": q[0], "p90_ms": q[-1], "min_ms": samples[0],
            "repeats": repeats}


def comma_list(convert: Callable[[str], float], what: str, valid: Callable[[list], bool] = bool) -> Callable:
    """An argparse type for a comma-separated list of ``what`` (e.g. ``0,1,2``), each made by
    ``convert`` and the list accepted by ``valid`` (default: not empty)."""

    def parse(text: str) -> list:
        try:
            values = [convert(s) for s in text.split(",") if s.strip()]
        except ValueError:
            values = []
        if not values or not valid(values):
            raise argparse.ArgumentTypeError(f"expected comma-separated {what}, got {text!r}")
        return values

    return parse


def add_drive_args(ap: argparse.ArgumentParser, *, data: str, drives: int, drive_seed: int,
                   drive_seed_help: str) -> None:
    """The options of a benchmark over synthetic drives: the model, and which drives (made if missing)."""
    ap.add_argument("--model", help="model folder (default: the shipped model)")
    ap.add_argument("--data", default=data, help="where the drives are (made if missing)")
    ap.add_argument("--drives", type=int, default=drives)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--drive-seed", type=int, default=drive_seed, help=drive_seed_help)


def drives_and_model(args: argparse.Namespace) -> tuple[list[Path], object]:
    """The drives :func:`add_drive_args` names (written first if they are not there) and the model."""
    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel
    from replay.synthetic import write_synthetic_logs

    paths = write_synthetic_logs(args.data, drives=args.drives, frames=args.frames, seed=args.drive_seed,
                                 progress=sys.stderr.isatty(), jobs=2)
    return paths, OnnxModel.load(resolve_model_dir(args.model))


def transformer_errors_deg(frames: list, estimator) -> tuple[list[float], list[float]]:
    """The transformer's angular error and answer elevation (degrees) on each full window of one
    drive's frames, with the live window policy (as bench_accuracy.py)."""
    from estimator.evaluate import evaluate
    from rig.window import SpreadWindowPolicy

    policy = SpreadWindowPolicy(n_frames=estimator.frames_per_window)
    result = evaluate([("drive", iter(frames))], estimator, policy, aggregators=["transformer"])
    return list(result.errors_deg["transformer"]), list(result.elevation_deg["transformer"])


def relative_azimuth_deg(sun_azimuth_rad: float, heading_rad: float) -> float:
    """Where the sun stands from the camera's heading, clockwise in [-180, 180) (0 ahead, 90 right)."""
    from rig.geometry import wrap_pi

    return math.degrees(float(wrap_pi(sun_azimuth_rad - heading_rad)))
