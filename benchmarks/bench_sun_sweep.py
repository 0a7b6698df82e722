"""One synthetic drive rendered again with only the sun's azimuth turned: the model's error for each.

The worst held-out windows come from a few drives (docs/model.md, "Known limits"). This asks of one
of them whether the street hides where the sun is or whether the model fails to read it: the same
street, road, camera, sky and sun elevation, with the sun at each azimuth relative to the camera's
first heading (0 ahead, 90 to the right, 180 behind). For each it gives the transformer's error
over the drive's full windows (the live window policy, as bench_accuracy) and the brightness of the
image's top band in thirds (left, centre, right) of one frame: where that band is sky, its
left-right difference is the sky's own pointer to the sun's side, whatever casts a shadow or not.

    python3 benchmarks/bench_sun_sweep.py [--model DIR] [--drive-seed 2000] [--index 0]
                                          [--relative-az-deg 0,30,...] [--frame 8] [--crop-seed 0]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import check_frames, comma_list, int_in, machine, run, transformer_errors_deg  # noqa: E402

DEFAULT_RELATIVE_AZ_DEG = (0, 60, 90, 120, 150, 180, 210, 240, 270, 300)
TOP_BAND_ROWS = (0.01, 0.16)  # of the image height: above the horizon of a level KITTI camera
_degrees = comma_list(float, "finite degrees", lambda degs: all(math.isfinite(d) for d in degs))


def top_band_thirds(image_bgr) -> list[float]:
    """Mean grey level of the image's top band, in its left, centre and right thirds."""
    h, w = image_bgr.shape[:2]
    band = image_bgr[int(TOP_BAND_ROWS[0] * h) : int(TOP_BAND_ROWS[1] * h)].mean(axis=2)
    return [round(float(band[:, a * w // 3 : (a + 1) * w // 3].mean()), 1) for a in range(3)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", help="model folder (default: the shipped model)")
    ap.add_argument("--drive-seed", type=int, default=2000, help="seed of the drive set (default 2000, held out)")
    ap.add_argument("--index", type=int_in(0), default=0, help="which drive of the set (default 0: drive_2000_0000)")
    ap.add_argument("--frames", type=int_in(1, 5000), default=24,
                    help="frames of the drive (at least the model's window)")
    ap.add_argument("--relative-az-deg", type=_degrees, default=list(DEFAULT_RELATIVE_AZ_DEG),
                    help="sun azimuths from the first frame's heading, clockwise (default "
                         f"{','.join(str(a) for a in DEFAULT_RELATIVE_AZ_DEG)})")
    ap.add_argument("--frame", type=int, default=8, help="the frame whose top band is measured (default 8)")
    ap.add_argument("--crop-seed", type=int, default=0)
    args = ap.parse_args()
    if not 0 <= args.frame < args.frames:
        ap.error(f"--frame: expected 0..{args.frames - 1}, got {args.frame}")

    import numpy as np

    from estimator.estimator import SunEstimator
    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel
    from replay.synthetic import drive_seed
    from replay.synthetic.drive import Drive, plan_drive

    model = OnnxModel.load(resolve_model_dir(args.model))
    check_frames(args.frames, model)
    estimator = SunEstimator(model, seed=args.crop_seed)
    seed = drive_seed(args.drive_seed, args.index)
    plan = plan_drive(seed, args.frames)
    heading0 = plan.poses[0].heading_rad
    rows = []
    for rel in args.relative_az_deg:
        az = (heading0 + math.radians(rel)) % (2 * math.pi)
        drive = Drive(seed, args.frames, sun_azimuth_rad=az)
        frames = list(drive.frames())
        err, elev = map(np.asarray, transformer_errors_deg(frames, estimator))
        rows.append({"relative_az_deg": rel, "sun_azimuth_deg": round(math.degrees(az), 2),
                     "n_windows": int(err.size), "mean_deg": float(err.mean()), "max_deg": float(err.max()),
                     "answer_elevation_deg_mean": float(elev.mean()),
                     "top_band_lcr": top_band_thirds(frames[args.frame].image_bgr)})
        print(f"sun {rel:+7.1f} deg from the heading: mean {err.mean():5.1f}, max {err.max():5.1f} deg; "
              f"top band L/C/R {rows[-1]['top_band_lcr']}", file=sys.stderr)
    print(json.dumps({
        "benchmark": "sun_sweep",
        "drive": {"drive_seed": args.drive_seed, "index": args.index, "seed": seed, "frames": args.frames,
                  "sun_elevation_deg": round(math.degrees(plan.params.sun_elevation_rad), 2),
                  "first_heading_deg": round(math.degrees(heading0), 2),
                  "true_relative_az_deg": round(math.degrees(plan.params.sun_azimuth_rad - heading0) % 360.0, 2)},
        "crop_seed": args.crop_seed,
        "model": {"dir": str(model.model_dir), "id": model.model_id},
        "sweep": rows,
        "machine": machine(),
    }, indent=2))


if __name__ == "__main__":
    run(main)
