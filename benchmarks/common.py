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
from typing import Any, NoReturn

from rig.errors import SunrigError

# The seed of the validation drives, on which runs are compared (docs/model.md, "How a run is
# chosen"); held-out drives are 2000 (bench_accuracy.py) and training drives 1000.
VALIDATION_SEED = 2500


def run(main: Callable[[], object]) -> NoReturn:
    """Run a benchmark's ``main`` as a command. A user's mistake (any :class:`SunrigError`: a
    missing model, a folder that cannot be written, drives kept with other frames) ends it in one
    line and exit 2, as argparse's usage errors and the ``sunrig`` CLI do, and a Ctrl-C that
    ``main`` did not turn into a report ends it in one line and exit 130; both printed a traceback
    over the line that said what to do. Anything else is a bug and keeps its traceback."""
    prog = Path(sys.argv[0]).stem
    try:
        code = main()
    except SunrigError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print(f"{prog}: interrupted (Ctrl-C); nothing was measured to the end, so no JSON is printed",
              file=sys.stderr)
        sys.exit(130)
    sys.exit(code if isinstance(code, int) else 0)


def int_in(lo: int, hi: int | None = None) -> Callable[[str], int]:
    """An argparse type: an integer from ``lo`` to ``hi`` (no upper bound when None)."""
    what = f"an integer from {lo} to {hi}" if hi is not None else f"an integer >= {lo}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from None
        if value < lo or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return value

    return parse


def float_in(lo: float, hi: float = math.inf, *, lo_included: bool = False) -> Callable[[str], float]:
    """An argparse type: a finite number above ``lo`` (or from it, ``lo_included``) and at most
    ``hi`` (nan and inf are typos)."""
    what = (f"a finite number {'from' if lo_included else 'above'} {lo:g}"
            + (f" {'to' if lo_included else 'and at most'} {hi:g}" if hi < math.inf else ""))

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and (lo <= value if lo_included else lo < value) and value <= hi):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return value

    return parse


def machine() -> dict:
    info: dict[str, object] = {
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


# The quality the synthetic logs' frames are written at (replay.native.LogWriter.write_frame), so
# that a benchmark that renders its own frames shows the model what it was trained and measured on.
SYNTH_JPEG_QUALITY = 90


def through_jpeg(image_bgr: Any, quality: int = SYNTH_JPEG_QUALITY) -> Any:
    """``image_bgr`` encoded as JPEG at ``quality`` and decoded again, as a log's frame comes back."""
    import cv2

    ok, data = cv2.imencode(".jpg", image_bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    decoded = cv2.imdecode(data, cv2.IMREAD_COLOR) if ok else None
    assert decoded is not None, "OpenCV could not JPEG-encode and decode a rendered frame"
    return decoded


def comma_list(convert: Callable[[str], Any], what: str, valid: Callable[[list], bool] = bool) -> Callable:
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
    from replay.synthetic import MAX_DRIVES, MAX_FRAMES

    ap.add_argument("--model", help="model folder (default: the shipped model)")
    ap.add_argument("--data", default=data, help="where the drives are (made if missing)")
    # The synthetic writer's own bounds, checked here so that a typo is a usage error at once.
    ap.add_argument("--drives", type=int_in(1, MAX_DRIVES), default=drives)
    ap.add_argument("--frames", type=int_in(1, MAX_FRAMES), default=24,
                    help="frames per drive (default 24; at least the model's window)")
    ap.add_argument("--drive-seed", type=int, default=drive_seed, help=drive_seed_help)


def check_frames(frames: int, model, option: str = "--frames") -> None:
    """Refuse drives of ``frames`` frames that hold no full window of ``model``: every figure
    would be of no window at all."""
    need = int(model.contract.frames_per_window)
    if frames < need:
        raise SunrigError(f"{option} {frames}: a drive needs at least {need} frames (the model's window) for one "
                          f"window to be graded; pass {option} {need} or more")


def drives_and_model(args: argparse.Namespace) -> tuple[list[Path], Any]:
    """The model and the drives :func:`add_drive_args` names (written first if they are not there).
    The model is loaded and the frames checked against its window first, so that a wrong
    ``--model`` or too few ``--frames`` is said before minutes of drives are rendered."""
    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel
    from replay.synthetic import write_synthetic_logs

    model = OnnxModel.load(resolve_model_dir(args.model))
    check_frames(args.frames, model)
    paths = write_synthetic_logs(args.data, drives=args.drives, frames=args.frames, seed=args.drive_seed,
                                 progress=sys.stderr.isatty(), jobs=2)
    return paths, model


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
