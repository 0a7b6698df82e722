"""Visual odometry (drivers/visual_odometry.py) on synthetic drives: heading drift and frame cost.

The drift is the heading error against the truth, per 100 m driven.

Each drive (``drive_seed(seed, i)``, i < drives) is rendered once at ``--scale`` of KITTI's image
size; the odometry then runs over its frames. Per drive: the heading error (odometry minus the
true heading change since its epoch's zero: the first frame, or the frame where a loss with no
rough turn started a new zero) at the last frame with a heading, its maximum, the RMS over
frames, and the drift per 100 m = the accumulated error (the sum of each epoch's |last error|) /
distance driven * 100, the distance from the drive's planned trajectory (``plan_drive``). Frames
without a heading are counted. The
cost is timed with ``benchmarks.common.time_ms`` (warm-up, repeats) over a whole drive and
divided by its frames; rendering is not timed. OpenCV runs on ``--threads`` threads.

The drives are seeds the odometry was not tuned on (it was tuned on plan seeds 0-10): the figure
is a fair one for this synthetic world, which is harder than a real street in one way (flat
shaded surfaces, fog, 2-5 m per frame at 10 fps) and easier in others (no rolling shutter, no
motion blur to speak of, no other moving traffic than parked cars).

``--substeps K`` renders the same streets at K times the frame rate (1/K of the motion per
frame): the synthetic corners turn up to 12 deg per frame at 10 fps (over 100 deg/s), far beyond
what 10 fps tracking handles well, and K = 3 shows what a 30 fps camera would see.

    python3 benchmarks/bench_vo.py [--drives 8] [--frames 40] [--seed 1000] [--scale 0.5] [--repeats 3] [--substeps 1]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import float_in, int_in, machine, run, time_ms  # noqa: E402
from rig.errors import SunrigError  # noqa: E402


def _quantile(samples: list[float], q: float) -> float:
    s = sorted(samples)
    return s[min(len(s) - 1, max(0, round(q * (len(s) - 1))))]


def heading_errors_deg(truth_rad: list[float], estimate_rad: list[float | None],
                       zero_index: list[int] | None = None) -> list[float | None]:
    """Estimate minus the true heading change since its epoch's zero (``zero_index[k]``: the frame
    frame k's epoch started at; the first frame for all when None), wrapped to [-180, 180)."""
    out: list[float | None] = []
    for k, (truth, est) in enumerate(zip(truth_rad, estimate_rad, strict=True)):
        if est is None:
            out.append(None)
            continue
        zero = truth_rad[zero_index[k] if zero_index is not None else 0]
        err = (est - (truth - zero) + math.pi) % (2 * math.pi) - math.pi
        out.append(math.degrees(err))
    return out


def epoch_zeros(epochs: list[int]) -> list[int]:
    """For each frame, the index of the frame its epoch started at (the odometry's epoch after
    each frame: a new zero starts at the first frame that has the new epoch)."""
    first: dict[int, int] = {}
    return [first.setdefault(e, k) for k, e in enumerate(epochs)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--drives", type=int_in(1), default=8, help="synthetic drives")
    # Two frames at least: a drive's drift is over the distance between its first and last.
    ap.add_argument("--frames", type=int_in(2, 5000), default=40, help="frames per drive (10 fps)")
    ap.add_argument("--seed", type=int, default=1000, help="drive i is drive_seed(seed, i)")
    ap.add_argument("--scale", type=float_in(0.0, 2.0), default=0.5,
                    help="image size as a fraction of KITTI 1242x375")
    ap.add_argument("--repeats", type=int_in(1), default=3, help="timed runs over each drive (after one warm-up)")
    ap.add_argument("--threads", type=int_in(0), default=1, help="OpenCV threads")
    ap.add_argument("--substeps", type=int_in(1, 10), default=1,
                    help="render each drive with K times the frames, 1/K the motion per frame, at K x 10 fps")
    ap.add_argument("--out", help="also write the JSON here")
    args = ap.parse_args()
    out = Path(args.out) if args.out else None
    if out is not None and (out.is_dir() or not os.access(out.parent, os.W_OK)):
        # Said now, not after minutes of rendering and tracking.
        raise SunrigError(f"--out {out}: cannot write there; check the folder exists and is writable")

    import cv2
    import numpy as np

    from drivers.visual_odometry import VisualOdometry
    from replay.synthetic import Drive, drive_seed, kitti_intrinsics, plan_drive
    from replay.synthetic.camera import Camera

    cv2.setNumThreads(args.threads)
    intr = kitti_intrinsics(args.scale)
    drives = []
    for i in range(args.drives):
        seed = drive_seed(args.seed, i)
        n_frames = args.frames * args.substeps
        if args.substeps == 1:
            drive = Drive(seed, n_frames, intrinsics=intr)
        else:
            # The same street and speed, seen K times as often: what a faster camera sees.
            step_m = plan_drive(seed, args.frames).params.metres_per_frame / args.substeps
            drive = Drive(seed, n_frames, intrinsics=intr, fps=10.0 * args.substeps, metres_per_frame=step_m)
        camera = Camera(drive.params.effects, intr.width, intr.height, seed=seed)
        images = [drive.render_frame(k, camera) for k in range(n_frames)]
        times = [k / drive.fps for k in range(n_frames)]
        truth = list(np.unwrap([p.heading_rad for p in drive.poses]))
        positions = np.array([p.position[:2] for p in drive.poses])
        distance_m = float(np.sum(np.linalg.norm(np.diff(positions, axis=0), axis=1)))

        def run(images=images, times=times) -> tuple[list[float | None], list[int], dict]:
            vo = VisualOdometry()
            est, epochs = [], []
            for t, img in zip(times, images, strict=True):
                s = vo.update(t, img, intr)
                est.append(None if s is None else s.heading_rad)
                epochs.append(vo.epoch)
            return est, epochs, vo.stats

        est, epochs, stats = run()
        est_unwrapped: list[float | None] = []
        last = 0.0
        for e in est:  # unwrap the estimate the same way as the truth
            if e is None:
                est_unwrapped.append(None)
                continue
            last = last + (e - last + math.pi) % (2 * math.pi) - math.pi
            est_unwrapped.append(last)
        # A new epoch (a loss with no rough turn to carry) starts again at 0 from the truth there:
        # the error accumulated before it is each earlier epoch's last, and adds to the drift.
        zeros = epoch_zeros(epochs)
        errors = heading_errors_deg(truth, est_unwrapped, zeros)
        valid = [e for e in errors if e is not None]
        last_of_epoch = {zeros[k]: e for k, e in enumerate(errors) if e is not None}
        final = next(e for e in reversed(errors) if e is not None)
        accumulated = sum(abs(e) for e in last_of_epoch.values())
        timing = time_ms(lambda run=run: run(), repeats=args.repeats, warmup=1)
        drives.append({
            "seed": seed,
            "distance_m": round(distance_m, 1),
            "turn_deg": round(math.degrees(truth[-1] - truth[0]), 1),
            "final_error_deg": round(final, 2),
            "epochs": len(set(epochs)),
            "accumulated_error_deg": round(accumulated, 2),
            "max_abs_error_deg": round(max(abs(e) for e in valid), 2),
            "rms_error_deg": round(math.sqrt(statistics.fmean(e * e for e in valid)), 2),
            "drift_deg_per_100m": round(accumulated / distance_m * 100.0, 2),
            "frames_without_heading": sum(e is None for e in errors),
            "ms_per_frame": round(timing["median_ms"] / n_frames, 2),
            "stats": stats,
        })
        print(f"drive {i + 1}/{args.drives}: seed {seed}, {distance_m:.0f} m, turn {drives[-1]['turn_deg']} deg, "
              f"final error {final:+.2f} deg, {drives[-1]['ms_per_frame']} ms/frame", file=sys.stderr)

    drift = [d["drift_deg_per_100m"] for d in drives]
    ms = [d["ms_per_frame"] for d in drives]
    total_m = sum(d["distance_m"] for d in drives)
    result = {
        "benchmark": "visual_odometry",
        "config": {"drives": args.drives, "frames": args.frames * args.substeps, "seed": args.seed,
                   "fps": 10.0 * args.substeps,
                   "image": [intr.width, intr.height], "hfov_deg": round(math.degrees(intr.hfov_rad), 1),
                   "opencv_threads": args.threads, "repeats": args.repeats},
        "summary": {
            "drift_deg_per_100m": {"median": _quantile(drift, 0.5), "mean": round(statistics.fmean(drift), 2),
                                   "p90": _quantile(drift, 0.9), "max": max(drift)},
            "drift_deg_per_100m_pooled": round(
                math.sqrt(sum(d["accumulated_error_deg"] ** 2 for d in drives) / len(drives))
                / (total_m / len(drives)) * 100.0, 2),
            "max_abs_error_deg": max(d["max_abs_error_deg"] for d in drives),
            "frames_without_heading": sum(d["frames_without_heading"] for d in drives),
            "frames": args.drives * args.frames * args.substeps,
            "distance_m": round(total_m, 1),
            "ms_per_frame": {"median": _quantile(ms, 0.5), "p10": _quantile(ms, 0.1), "p90": _quantile(ms, 0.9)},
        },
        "drives": drives,
        "machine": machine(),
    }
    text = json.dumps(result, indent=2)
    if out is not None:
        out.write_text(text + "\n", encoding="utf-8")
    print(text)


if __name__ == "__main__":
    run(main)
