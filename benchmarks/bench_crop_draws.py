"""One window, many crop draws: how much of a window's error is the luck of its crops.

A frame's crops are random (seeded by the crop seed and the frame's number), and the benchmark's
worst windows move a lot with them (docs/model.md). This estimates each named window once per crop
seed, for each run-time variant (benchmarks/variants.py) and crops per frame asked for, and gives
the spread of its error over the draws, with where the answers put the sun from the camera's
heading against where it was. A window whose error stays put whatever the crops is the model's
belief; one whose error ranges widely is a crop lottery, which more or better-placed crops narrow.

    python3 benchmarks/bench_crop_draws.py [--model DIR] [--window LOG:NEWEST_FRAME ...] [--crop-seeds 60]
                                           [--variants plain,tiled] [--crops 8,64]

A window is named by its log and its newest frame (counted from 0), and its frames are the ones
the live window policy picks up to there, as in bench_accuracy.py. The default windows are the
worst held-out and validation windows of the shipped model (make the drives with
bench_accuracy.py, or ``sunrig synth``, first).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import comma_list, machine, relative_azimuth_deg, run  # noqa: E402
from benchmarks.variants import VARIANTS, estimator_for  # noqa: E402
from rig.geometry import az_el_from_enu  # noqa: E402

DEFAULT_WINDOWS = ("data/heldout/drive_2000_0084.mcap:7", "data/val/drive_2500_0194.mcap:12")
OVER_DEG = 30.0


def window_arg(text: str) -> tuple[Path, int]:
    """``LOG:NEWEST_FRAME`` -> (path, index of the window's newest frame)."""
    path, sep, newest = text.rpartition(":")
    if not sep or not path or not newest.isdigit():
        raise argparse.ArgumentTypeError(f"expected LOG:NEWEST_FRAME (e.g. data/heldout/drive_2000_0084.mcap:7), "
                                         f"got {text!r}")
    return Path(path), int(newest)


def window_frames(frames: list, newest: int, n_frames: int) -> list:
    """The frames the live window policy picks for the window whose newest frame is ``frames[newest]``."""
    from types import SimpleNamespace

    from rig.window import SpreadWindowPolicy

    policy = SpreadWindowPolicy(n_frames=n_frames)  # the live policy's span, as bench_accuracy.py's
    # Each frame a view of its own at its own time, as every frame of a drive that never stands
    # (rig/window.py's ViewClock stamps no synthetic frame a repeat: docs/architecture.md).
    picked = policy.select([SimpleNamespace(frame=f, window_t_s=f.t_mono_s, view_key=f.seq)
                            for f in frames[: newest + 1]])
    return [c.frame for c in picked]


def draw_summary(errors_deg: list[float], answer_rel_az_deg: list[float], answer_el_deg: list[float]) -> dict:
    """The spread over the draws of one window's error, and of where its answers put the sun."""
    return {
        "n_draws": len(errors_deg),
        "mean_deg": statistics.fmean(errors_deg),
        "median_deg": statistics.median(errors_deg),
        "min_deg": min(errors_deg),
        "max_deg": max(errors_deg),
        f"over_{OVER_DEG:g}_deg": sum(e > OVER_DEG for e in errors_deg),
        "answer_rel_azimuth_deg": {"median": statistics.median(answer_rel_az_deg),
                                   "min": min(answer_rel_az_deg), "max": max(answer_rel_az_deg)},
        "answer_elevation_deg": {"median": statistics.median(answer_el_deg),
                                 "min": min(answer_el_deg), "max": max(answer_el_deg)},
    }


def _angles_deg(est) -> tuple[float, float, float]:
    """(error, answer azimuth from the heading clockwise, answer elevation) of one estimate, deg."""
    return math.degrees(est.error_rad), math.degrees(est.relative_bearing_rad), math.degrees(est.elevation_rad)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", help="model folder (default: the shipped model)")
    ap.add_argument("--window", dest="windows", type=window_arg, action="append",
                    help="a window as LOG:NEWEST_FRAME (repeat for more; default "
                         f"{' and '.join(DEFAULT_WINDOWS)})")
    ap.add_argument("--crop-seeds", type=int, default=60, help="crop draws per window: seeds 0..N-1 (default 60)")
    ap.add_argument("--variants", type=comma_list(str, f"names from {', '.join(VARIANTS)}",
                                                  lambda xs: all(x in VARIANTS for x in xs)),
                    default=["plain", "tiled"], help="run-time variants (benchmarks/variants.py; default plain,tiled)")
    ap.add_argument("--crops", type=comma_list(int, "positive integers", lambda xs: all(x > 0 for x in xs)),
                    default=[8], help="crops per frame, one run each (default 8)")
    args = ap.parse_args()
    if args.crop_seeds < 1:
        ap.error(f"--crop-seeds: expected at least 1, got {args.crop_seeds}")
    windows = args.windows or [window_arg(w) for w in DEFAULT_WINDOWS]
    missing = [str(p) for p, _ in windows if not p.is_file()]
    if missing:
        ap.error(f"no log at {', '.join(missing)}; make the drives first (python3 benchmarks/bench_accuracy.py "
                 "makes data/heldout; sunrig synth data/val --drives 300 --frames 24 --seed 2500 makes data/val)")

    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel
    from replay.sources import open_frames

    model = OnnxModel.load(resolve_model_dir(args.model))
    n_frames = int(model.contract.frames_per_window)
    out = []
    for path, newest in windows:
        log_frames = list(open_frames(path))
        if newest >= len(log_frames):
            ap.error(f"{path} has {len(log_frames)} frames (0 to {len(log_frames) - 1}); pick a newest frame in them")
        frames = window_frames(log_frames, newest, n_frames)
        if len(frames) < n_frames:
            ap.error(f"{path} has no full window of {n_frames} frames ending at frame {newest}; "
                     f"pick a newest frame from {n_frames - 1} to the log's last")
        runs = []
        for variant in args.variants:
            for crops in args.crops:
                angles = []
                for seed in range(args.crop_seeds):
                    estimator = estimator_for(variant)(model, seed=seed, crops_per_frame=crops)
                    angles.append(_angles_deg(estimator.estimate(estimator.encode_batch(frames))))
                err, rel_az, el = (list(col) for col in zip(*angles, strict=True))
                runs.append({"variant": variant, "crops_per_frame": crops, **draw_summary(err, rel_az, el)})
                print(f"{path.name}:{newest} {variant} x{crops}: mean {runs[-1]['mean_deg']:.1f} deg, "
                      f"{runs[-1]['min_deg']:.1f}-{runs[-1]['max_deg']:.1f}", file=sys.stderr)
        truth = frames[-1]  # the window's newest frame, whose heading the answers are relative to
        taz, tel = az_el_from_enu(truth.sun_enu_truth)
        out.append({"log": str(path), "newest_frame": newest, "frames_seq": [f.seq for f in frames],
                    "truth": {"rel_azimuth_deg": relative_azimuth_deg(taz, truth.attitude.heading_rad),
                              "elevation_deg": math.degrees(tel)},
                    "runs": runs})
    print(json.dumps({"benchmark": "crop_draws", "model": {"dir": str(model.model_dir), "id": model.model_id},
                      "crop_seeds": args.crop_seeds, "windows": out, "machine": machine()}, indent=2))


if __name__ == "__main__":
    run(main)
