"""Speed of the synthetic drive generator: frames per second end to end, and per-frame cost.

Each repeat builds one drive (scene layout, ground map, shadow map) and renders all its frames
to 8-bit images, as ``write_synthetic_logs`` does minus the JPEG/MCAP writing. ``frames_per_s``
counts the build; ``render_ms`` is per frame without it. OpenCV runs on one thread unless told
otherwise, so the figure is per core (generate drives in parallel processes for more).

    python3 benchmarks/bench_synth.py [--frames 40] [--repeats 5] [--render-scale 0.5] [--scale 1.0]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import float_in, int_in, machine, run  # noqa: E402


def _quantile(samples: list[float], q: float) -> float:
    s = sorted(samples)
    return s[min(len(s) - 1, max(0, round(q * (len(s) - 1))))]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    # The bounds of `sunrig synth` (--frames, --render-scale), and a size of at least a few pixels.
    ap.add_argument("--frames", type=int_in(1, 5000), default=40, help="frames per drive")
    ap.add_argument("--repeats", type=int_in(1), default=5, help="drives timed (seeds 0..repeats-1)")
    ap.add_argument("--render-scale", type=float_in(0.0, 1.0), default=0.5, help="internal render resolution factor")
    ap.add_argument("--scale", type=float_in(0.05, 4.0, lo_included=True), default=1.0,
                    help="output size as a fraction of KITTI 1242x375")
    ap.add_argument("--threads", type=int_in(0), default=1, help="OpenCV threads")
    args = ap.parse_args()

    import cv2

    from replay.synthetic import Drive, kitti_intrinsics
    from replay.synthetic.camera import Camera

    cv2.setNumThreads(args.threads)
    intr = kitti_intrinsics(args.scale)

    def run(seed: int) -> tuple[float, float, list[float]]:
        t0 = time.perf_counter()
        drive = Drive(seed, args.frames, intrinsics=intr, render_scale=args.render_scale)
        t1 = time.perf_counter()
        camera = Camera(drive.params.effects, intr.width, intr.height, seed=seed)
        per_frame = []
        for k in range(args.frames):
            ta = time.perf_counter()
            drive.render_frame(k, camera)
            per_frame.append((time.perf_counter() - ta) * 1e3)
        return (time.perf_counter() - t0), (t1 - t0) * 1e3, per_frame

    run(1000)  # warm-up: imports, first allocations
    fps, build_ms, frame_ms = [], [], []
    for seed in range(args.repeats):
        total_s, b_ms, f_ms = run(seed)
        fps.append(args.frames / total_s)
        build_ms.append(b_ms)
        frame_ms.extend(f_ms)
    print(json.dumps({
        "benchmark": "synthetic_drives",
        "resolution": [intr.width, intr.height],
        "render_scale": args.render_scale,
        "render_resolution": [round(intr.width * args.render_scale), round(intr.height * args.render_scale)],
        "frames_per_drive": args.frames,
        "repeats": args.repeats,
        "opencv_threads": args.threads,
        "frames_per_s": {"median": statistics.median(fps), "min": min(fps), "max": max(fps)},
        "render_ms": {"p50": _quantile(frame_ms, 0.5), "p90": _quantile(frame_ms, 0.9), "max": max(frame_ms)},
        "drive_build_ms": {"median": statistics.median(build_ms), "min": min(build_ms), "max": max(build_ms)},
        "machine": machine(),
    }, indent=2))


if __name__ == "__main__":
    run(main)
