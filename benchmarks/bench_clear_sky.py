"""Synthetic drives rendered again under a clearer sky: whether a drive's clouds make its misses.

The worst validation windows come from drives with clouds in the sky or a sun dimmed by them
(docs/model.md, "Known limits"). This renders each named drive four times, changing nothing but the
sky: as recorded, without the cloud layer, with the direct sun at full strength, and both (a clear
day). Street, camera, noise and sun stay as they were. If a drive's error falls under a clear sky,
its clouds made the miss; if not, the street and where the sun stands relative to it did. For each
drive and sky it gives the transformer's error over the drive's full windows (the live window
policy, as bench_accuracy.py), pooled over the crop seeds, and where the sun stood from the camera.

    python3 benchmarks/bench_clear_sky.py [--model DIR] [--drive-seed 2500] [--indices 194,98,231]
                                          [--frames 24] [--crop-seeds 0,1,2]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import (  # noqa: E402
    VALIDATION_SEED,
    check_frames,
    comma_list,
    int_in,
    machine,
    relative_azimuth_deg,
    run,
    transformer_errors_deg,
)

# Each sky: the DriveParams fields it overrides (replay/synthetic/drive.py).
SKIES: dict[str, dict[str, float]] = {
    "recorded": {},
    "no_clouds": {"cloud_cover": 0.0},
    "full_sun": {"sun_visibility": 1.0},
    "clear": {"cloud_cover": 0.0, "sun_visibility": 1.0},
}
# The validation drives with estimates over 30 deg for the shipped model (docs/model.md).
DEFAULT_INDICES = (194, 98, 231, 13, 45)
OVER_DEG = 30.0
_indices = comma_list(int, "drive indices >= 0", lambda xs: all(x >= 0 for x in xs))


def summarise(errors_deg: list[float]) -> dict:
    n = len(errors_deg)
    return {"n_estimates": n, "mean_deg": sum(errors_deg) / n, "max_deg": max(errors_deg),
            f"over_{OVER_DEG:g}_deg": sum(e > OVER_DEG for e in errors_deg)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", help="model folder (default: the shipped model)")
    ap.add_argument("--drive-seed", type=int, default=VALIDATION_SEED,
                    help=f"seed of the drive set (default {VALIDATION_SEED}, the validation drives)")
    ap.add_argument("--indices", type=_indices, default=list(DEFAULT_INDICES),
                    help=f"which drives of the set (default {','.join(map(str, DEFAULT_INDICES))})")
    ap.add_argument("--frames", type=int_in(1, 5000), default=24,
                    help="frames of each drive (at least the model's window)")
    ap.add_argument("--crop-seeds", type=comma_list(int, "integers"), default=[0, 1, 2])
    args = ap.parse_args()

    from estimator.estimator import SunEstimator
    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel
    from replay.synthetic import drive_seed
    from replay.synthetic.drive import Drive, plan_drive

    model = OnnxModel.load(resolve_model_dir(args.model))
    check_frames(args.frames, model)
    drives = []
    for index in args.indices:
        seed = drive_seed(args.drive_seed, index)
        plan = plan_drive(seed, args.frames)
        p = plan.params
        rel = [relative_azimuth_deg(p.sun_azimuth_rad, pose.heading_rad) for pose in plan.poses]
        skies = {}
        for sky, overrides in SKIES.items():
            frames = list(Drive(seed, args.frames, **overrides).frames())
            errors: list[float] = []
            for crop_seed in args.crop_seeds:
                errors += transformer_errors_deg(frames, SunEstimator(model, seed=crop_seed))[0]
            skies[sky] = summarise(errors)
            print(f"drive {index} {sky:>9}: mean {skies[sky]['mean_deg']:5.1f}, max {skies[sky]['max_deg']:5.1f} "
                  f"deg, {skies[sky][f'over_{OVER_DEG:g}_deg']} over {OVER_DEG:g}", file=sys.stderr)
        drives.append({
            "index": index, "seed": seed,
            "sun_elevation_deg": round(math.degrees(p.sun_elevation_rad), 2),
            "sun_from_heading_deg": {"first": round(rel[0], 1), "last": round(rel[-1], 1)},
            "sun_visibility": round(p.sun_visibility, 3), "cloud_cover": round(p.cloud_cover, 3),
            "skies": skies,
        })
    print(json.dumps({
        "benchmark": "clear_sky",
        "drive_seed": args.drive_seed, "frames": args.frames, "crop_seeds": args.crop_seeds,
        "model": {"dir": str(model.model_dir), "id": model.model_id},
        "skies": SKIES,
        "drives": drives,
        "machine": machine(),
    }, indent=2))


if __name__ == "__main__":
    run(main)
