"""What the per-token spread says about a model's windows: the spread figures in docs/protocol.md.

The status rule (``rig/protocol.py``) calls a window valid when its tokens agree (spread under
30 deg). This prints, as JSON, the transformer's spread over every full window of the drives
(percentiles, and on the windows more than 30 deg off), and on windows with nothing to see:
eight frames of a drive made black, white, mid-grey or pure noise, with the elevation the model
answers. Those are estimated directly, as if the exposure gate (``rig/exposure.py``) were off.
It also gives the range of the drives' frame luma that the gate's thresholds are placed against,
and the windows grouped by where the answer puts the sun from the camera (ahead, to the side,
behind; low, mid, high): whether the answer's own place could flag the windows far off. For a
model that runs every window mirrored too (``mirror_windows``), it gives the angle between the
window's as-seen and mirrored answers, and how many of the windows far off a flag on that gap
would catch: whether the two runs disagree where the model is wrong. The same for the angle
between the transformer's answer and its crops' own (the ``mean`` aggregator: each crop run alone,
their answers averaged): whether the window's joint answer strays from what its crops say where
the model is wrong.

    python3 benchmarks/bench_spread.py [--model DIR] [--data data/val --drives 300 --drive-seed 2500]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import VALIDATION_SEED, add_drive_args, drives_and_model, machine, run  # noqa: E402
from estimator.calibration import mean_direction  # noqa: E402
from estimator.estimator import SunEstimator, mirrored_joint_runs, window_tokens  # noqa: E402
from rig.geometry import angle_between  # noqa: E402

TAIL_DEG = 30.0
# Where an answer puts the sun from the camera: |azimuth from the heading| and elevation bands, deg.
AZIMUTH_BANDS_DEG = (("ahead", 0.0, 60.0), ("side", 60.0, 120.0), ("behind", 120.0, 180.1))
ELEVATION_BANDS_DEG = (("low", -90.0, 30.0), ("mid", 30.0, 60.0), ("high", 60.0, 90.1))
BLANK_IMAGES = {
    "black": lambda img, rng: np.zeros_like(img),
    "white": lambda img, rng: np.full_like(img, 255),
    "grey": lambda img, rng: np.full_like(img, 128),
    "noise": lambda img, rng: rng.integers(0, 256, img.shape, dtype=np.uint8),
}


# Shares of the windows a flag (on the mirror gap, the crop gap or any score) is tried at.
FLAG_SHARES = (0.01, 0.02, 0.05, 0.10)


PLACES = [f"{az} {el}" for az, _, _ in AZIMUTH_BANDS_DEG for el, _, _ in ELEVATION_BANDS_DEG]


def answer_place(azimuth_from_heading_deg: float, elevation_deg: float) -> str:
    """The band of PLACES (e.g. ``behind high``) that holds an answer ``azimuth_from_heading_deg``
    (either side, in [-180, 180]) from the camera's heading and ``elevation_deg`` up."""
    a = abs(azimuth_from_heading_deg)
    az = next(i for i, (_, lo, hi) in enumerate(AZIMUTH_BANDS_DEG) if lo <= a < hi)
    el = next(i for i, (_, lo, hi) in enumerate(ELEVATION_BANDS_DEG) if lo <= elevation_deg < hi)
    return PLACES[az * len(ELEVATION_BANDS_DEG) + el]


def by_answer_place(places: list[str], errors_deg: list[float]) -> dict[str, dict]:
    """For each band: its share of the windows, their mean error and how many are over TAIL_DEG."""
    grouped: dict[str, list[float]] = {place: [] for place in PLACES}
    for place, err in zip(places, errors_deg, strict=True):
        grouped[place].append(err)
    out = {}
    for place, errs in grouped.items():
        e = np.asarray(errs)
        out[place] = {"share": e.size / len(places), "mean_deg": float(e.mean()) if e.size else None,
                      f"over_{TAIL_DEG:.0f}_deg": int((e > TAIL_DEG).sum())}
    return out


def rank_auc(score: np.ndarray, positive: np.ndarray) -> float | None:
    """The chance that a positive window scores above a negative one (ties count half): the area
    under the ROC curve of flagging by ``score``. None when either class is empty."""
    score, positive = np.asarray(score, dtype=np.float64), np.asarray(positive, dtype=bool)
    if positive.all() or not positive.any():
        return None
    # Every (positive, negative) pair: a few hundred thousand for the 5100 windows of a run.
    diff = score[positive][:, None] - score[~positive][None, :]
    return float(np.mean((diff > 0) + 0.5 * (diff == 0)))


def gap_flags(gap_deg: np.ndarray, error_deg: np.ndarray, shares=FLAG_SHARES, unit: str = "deg") -> dict:
    """What a flag on the windows of the largest ``gap_deg`` would catch: for each share of the
    windows flagged, its threshold, how many of the windows over 20 and over TAIL_DEG it holds, the
    worst window it leaves and how good the windows it takes are; and the rank AUC of the gap for each.
    ``unit`` names the gap's unit in the threshold's key (``threshold_deg``); any score will do."""
    gap_deg, error_deg = np.asarray(gap_deg, dtype=np.float64), np.asarray(error_deg, dtype=np.float64)
    out: dict = {"median": float(np.median(gap_deg)), "p99": float(np.percentile(gap_deg, 99))}
    for limit in (20.0, TAIL_DEG):
        far = error_deg > limit
        out[f"windows_over_{limit:.0f}_deg"] = int(far.sum())
        out[f"auc_over_{limit:.0f}_deg"] = rank_auc(gap_deg, far)
    tail = gap_deg[error_deg > TAIL_DEG]
    out[f"on_windows_over_{TAIL_DEG:.0f}_deg"] = (
        {"min": float(tail.min()), "median": float(np.median(tail)), "max": float(tail.max())} if tail.size else None)
    out["flag_largest"] = []
    for share in shares:
        threshold = float(np.quantile(gap_deg, 1.0 - share))
        flagged = gap_deg > threshold
        out["flag_largest"].append({
            "share": share, f"threshold_{unit}": threshold, "flagged": int(flagged.sum()),
            **{f"caught_over_{limit:.0f}_deg": int((flagged & (error_deg > limit)).sum())
               for limit in (20.0, TAIL_DEG)},
            "max_deg_left": float(error_deg[~flagged].max()) if (~flagged).any() else None,
            # What the flag costs: how good the windows it would take away are.
            "mean_deg_flagged": float(error_deg[flagged].mean()) if flagged.any() else None,
            "flagged_under_10_deg": int((flagged & (error_deg < 10.0)).sum())})
    return out


class RunRecordingEstimator(SunEstimator):
    """The estimator every command uses, which also keeps the last window's as-seen and mirrored
    runs (world vectors, (T, 3) each) of a model run mirrored (``mirror_windows``): the aggregator
    runs once more, on the crops' embeddings already made. ``window`` is the last window's frames."""

    runs: tuple[np.ndarray, np.ndarray] | None = None
    window: tuple = ()

    def estimate_many(self, window, aggregators):
        self.window = tuple(window)
        if self.mirror_windows:
            self.runs = mirrored_joint_runs(self.model, window_tokens(window), window)
        return super().estimate_many(window, aggregators)

    def mirror_gap_deg(self) -> float | None:
        """The angle between the last window's as-seen and mirrored answers, deg."""
        if self.runs is None:
            return None
        plain, mirrored = self.runs
        return math.degrees(float(angle_between(mean_direction(plain)[0], mean_direction(mirrored)[0])))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_drive_args(ap, data="data/val", drives=300, drive_seed=VALIDATION_SEED,
                   drive_seed_help=f"seed of the drives (default {VALIDATION_SEED}: validation)")
    ap.add_argument("--seed", type=int, default=0, help="crop seed (default 0)")
    args = ap.parse_args()

    from replay.sources import open_frames
    from rig.exposure import luminance_stats
    from rig.geometry import az_el_from_enu, wrap_pi
    from rig.offline import estimate_stream
    from rig.window import SpreadWindowPolicy

    paths, model = drives_and_model(args)
    estimator = RunRecordingEstimator(model, seed=args.seed)
    policy = SpreadWindowPolicy(n_frames=estimator.frames_per_window, span_s=4.0)

    spread, error, luma, places, gaps, crop_gaps = [], [], [], [], [], []
    # The crops' own answer rides along: the mean aggregator reuses the window's embeddings.
    aggregators = [estimator.aggregator] + (["mean"] if estimator.aggregator == "transformer" else [])

    def measured(frames):
        for frame in frames:
            luma.append(luminance_stats(frame.image_bgr))
            yield frame

    for path in paths:
        for result in estimate_stream(measured(open_frames(path)), estimator, policy, aggregators=aggregators):
            est = result[estimator.aggregator]
            if est.n_frames == policy.n_frames and est.error_rad is not None:
                spread.append(math.degrees(est.spread_rad))
                error.append(math.degrees(est.error_rad))
                az, el = az_el_from_enu(est.sun_enu)
                places.append(answer_place(math.degrees(float(wrap_pi(az - est.heading_rad))), math.degrees(float(el))))
                gaps.append(estimator.mirror_gap_deg())
                if "mean" in result:
                    crop_gaps.append(math.degrees(float(angle_between(est.sun_enu, result["mean"].sun_enu))))
    spread_a, error_a = np.asarray(spread), np.asarray(error)
    tail = spread_a[error_a > TAIL_DEG]
    luma_a = np.asarray(luma)

    frames = list(open_frames(paths[0]))[: estimator.frames_per_window]
    rng = np.random.default_rng(0)
    blank = {}
    for name, make in BLANK_IMAGES.items():
        feats = estimator.encode_batch([dataclasses.replace(f, image_bgr=make(f.image_bgr, rng)) for f in frames])
        est = estimator.estimate(feats)
        blank[name] = {"spread_deg": math.degrees(est.spread_rad), "elevation_deg": math.degrees(est.elevation_rad)}

    print(json.dumps({
        "benchmark": "spread",
        "data": {"seed": args.drive_seed, "drives": args.drives, "frames_per_drive": args.frames},
        "crop_seed": args.seed,
        "model": {"dir": str(model.model_dir), "id": model.model_id},
        "windows": len(spread),
        "spread_deg": {"p5": float(np.percentile(spread_a, 5)), "median": float(np.median(spread_a)),
                       "p99": float(np.percentile(spread_a, 99)), "max": float(spread_a.max())},
        f"windows_over_{TAIL_DEG:.0f}_deg": int(tail.size),
        f"spread_deg_on_windows_over_{TAIL_DEG:.0f}_deg": (
            {"min": float(tail.min()), "max": float(tail.max())} if tail.size else None),
        "by_answer_place": by_answer_place(places, error),
        "mirror_gap_deg": gap_flags(np.asarray(gaps), error_a) if estimator.mirror_windows else None,
        "crop_gap_deg": gap_flags(np.asarray(crop_gaps), error_a) if crop_gaps else None,
        "blank_windows": blank,
        "frame_luma": {"frames": len(luma_a), "mean_min": float(luma_a[:, 0].min()),
                       "mean_max": float(luma_a[:, 0].max()), "std_min": float(luma_a[:, 1].min())},
        "machine": machine(),
    }, indent=2))


if __name__ == "__main__":
    run(main)
