"""Whether a confidence learnt from what a window already computes could flag the model's misses.

The shipped model's misses are sure and wrong: no one figure the rig computes per window flags
them (``bench_spread.py``: the spread, the answer's place, the mirror gap, the crops' own answer).
This asks whether a learnt mix of those figures does. A linear probe (ridge regression on the log
of the window's error, its inputs standardised) over FEATURES is fitted on the full windows of one
drive set (default: the 300 drives of seed 4000, never used by anything else, crop seeds 0 and 1)
and judged on others with crop seed 0 (default: validation, held-out and fresh): its rank AUC for
the windows over 20 and 30 deg, and what a flag on the windows of the largest 1, 2, 5 and 10 % of
its scores would catch and the worst window it would leave. The model's weights are frozen, and
the probe is not part of the rig: it measures whether a learnt flag (a confidence output) is worth
building, not one to ship.

    python3 benchmarks/bench_confidence.py [--model DIR]    # about 25 minutes on 2 idle cores
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.bench_spread import RunRecordingEstimator, gap_flags  # noqa: E402
from benchmarks.common import comma_list, machine, run  # noqa: E402

# Per full window: what the rig computes for it anyway, or could with one more aggregator run.
FEATURES = (
    "spread_deg",  # the transformer's tokens around its answer (both runs)
    "plain_spread_deg", "mirrored_spread_deg",  # each run's own
    "mirror_gap_deg",  # between the as-seen and mirrored answers
    "crop_gap_deg",  # between the answer and the crops' own (the mean aggregator's)
    "crop_spread_deg",  # the crops' own answers around their mean
    "plain_norm_mean", "plain_norm_std", "mirrored_norm_mean", "mirrored_norm_std",  # token vector lengths
    "heading_span_deg", "heading_offset_deg",  # the frames' headings: range, mean |from the newest|
    "window_s",  # from the oldest frame to the newest
    "elevation_deg", "azimuth_sin", "azimuth_cos",  # the answer, from the newest frame's heading
    "luma_mean", "luma_std",  # of the newest frame
)
# On standardised inputs. 1, 30 and 300 catch the same windows over 30 deg on the default sets,
# and within 2 the same over 20 (session 33).
RIDGE = 30.0


Predictor = Callable[[np.ndarray], np.ndarray]


def fit_ridge(x: np.ndarray, y: np.ndarray, ridge: float = RIDGE) -> tuple[Predictor, np.ndarray]:
    """Least squares of ``y`` on the columns of ``x`` (standardised) plus an unpenalised intercept,
    with ``ridge`` times the squared weights added. Returns the predictor and the weights of the
    standardised columns (how much each feature moves the prediction per standard deviation)."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    mu, sd = x.mean(axis=0), x.std(axis=0)
    sd = np.where(sd > 0, sd, 1.0)  # a constant column: zeros after centring, and weight 0
    z = np.column_stack([(x - mu) / sd, np.ones(len(x))])
    # The ridge as extra rows (sqrt(ridge) * I, target 0), solved by least squares: the minimum-norm
    # answer also when a column is constant and there is no ridge.
    penalty = math.sqrt(ridge) * np.eye(z.shape[1])[:-1]
    w = np.linalg.lstsq(np.vstack([z, penalty]), np.concatenate([y, np.zeros(len(penalty))]), rcond=None)[0]

    def predict(x_new: np.ndarray) -> np.ndarray:
        return np.column_stack([(np.asarray(x_new, dtype=np.float64) - mu) / sd, np.ones(len(x_new))]) @ w

    return predict, w[:-1]


def window_features(paths: list[Path], estimator: RunRecordingEstimator) -> tuple[np.ndarray, np.ndarray]:
    """FEATURES (N, F) and the transformer's error (N,), deg, of every full window of the drives."""
    from estimator.calibration import mean_direction
    from replay.sources import open_frames
    from rig.exposure import luminance_stats
    from rig.geometry import angle_between, az_el_from_enu, wrap_pi
    from rig.offline import estimate_stream
    from rig.window import SpreadWindowPolicy

    policy = SpreadWindowPolicy(n_frames=estimator.frames_per_window, span_s=4.0)
    rows, errors = [], []
    for path in paths:
        luma: dict[int, tuple[float, float]] = {}

        def measured(frames, luma=luma):
            for frame in frames:
                luma[frame.seq] = luminance_stats(frame.image_bgr)
                yield frame

        for result in estimate_stream(measured(open_frames(path)), estimator, policy,
                                      aggregators=["transformer", "mean"]):
            est, crops = result["transformer"], result["mean"]
            if est.n_frames != policy.n_frames or est.error_rad is None:
                continue
            assert estimator.runs is not None
            plain, mirrored = estimator.runs
            plain_spread, mirrored_spread = mean_direction(plain)[1], mean_direction(mirrored)[1]
            frames = [f.frame for f in estimator.window]
            rel_yaw = wrap_pi(np.array([f.attitude.heading_rad for f in frames]) - est.heading_rad)
            window_s = max(f.t_mono_s for f in frames) - min(f.t_mono_s for f in frames)
            az, el = az_el_from_enu(est.sun_enu)
            az_from_heading = float(wrap_pi(az - est.heading_rad))
            norms_plain, norms_mirrored = np.linalg.norm(plain, axis=1), np.linalg.norm(mirrored, axis=1)
            rows.append([
                math.degrees(est.spread_rad), math.degrees(plain_spread), math.degrees(mirrored_spread),
                estimator.mirror_gap_deg(),
                math.degrees(float(angle_between(est.sun_enu, crops.sun_enu))), math.degrees(crops.spread_rad),
                norms_plain.mean(), norms_plain.std(), norms_mirrored.mean(), norms_mirrored.std(),
                math.degrees(float(np.ptp(rel_yaw))), math.degrees(float(np.abs(rel_yaw).mean())),
                window_s, math.degrees(float(el)), math.sin(az_from_heading), math.cos(az_from_heading),
                *luma[est.seq],
            ])
            errors.append(math.degrees(est.error_rad))
    return np.asarray(rows, dtype=np.float64), np.asarray(errors)


def drive_set(text: str) -> tuple[str, int, int]:
    """``DIR:DRIVES:SEED``, e.g. ``data/val:300:2500`` (1 to MAX_DRIVES drives)."""
    from replay.synthetic import MAX_DRIVES

    try:
        folder, drives, seed = text.rsplit(":", 2)
        if folder and 1 <= int(drives) <= MAX_DRIVES:
            return folder, int(drives), int(seed)
    except ValueError:
        pass
    raise argparse.ArgumentTypeError(f"expected DIR:DRIVES:SEED with 1 to {MAX_DRIVES} drives "
                                     f"(e.g. data/val:300:2500), got {text!r}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", help="model folder (default: the shipped model)")
    ap.add_argument("--fit", type=drive_set, default=("data/probe", 300, 4000),
                    help="DIR:DRIVES:SEED the probe is fitted on (made if missing; default data/probe:300:4000)")
    ap.add_argument("--fit-seeds", type=comma_list(int, "crop seeds"), default=[0, 1],
                    help="crop seeds of the fit windows (default 0,1)")
    ap.add_argument("--test", type=drive_set, nargs="+",
                    default=[("data/val", 300, 2500), ("data/heldout", 100, 2000), ("data/fresh", 300, 3000)],
                    help="DIR:DRIVES:SEED sets it is judged on, crop seed 0 (default validation, held-out, fresh)")
    args = ap.parse_args()

    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel
    from replay.synthetic import write_synthetic_logs

    model = OnnxModel.load(resolve_model_dir(args.model))
    if not model.contract.mirror_windows:
        sys.exit("bench_confidence: the model does not run windows mirrored, and the probe's inputs need both runs")

    def features(folder: str, drives: int, seed: int, crop_seed: int) -> tuple[np.ndarray, np.ndarray]:
        paths = write_synthetic_logs(folder, drives=drives, frames=24, seed=seed, progress=sys.stderr.isatty(), jobs=2)
        print(f"bench_confidence: {folder}, crop seed {crop_seed}", file=sys.stderr)
        return window_features(paths, RunRecordingEstimator(model, seed=crop_seed))

    fit = [features(*args.fit, s) for s in args.fit_seeds]
    x_fit, err_fit = np.concatenate([f[0] for f in fit]), np.concatenate([f[1] for f in fit])
    target = np.log1p(err_fit)
    predict, weights = fit_ridge(x_fit, target)
    residual = target - predict(x_fit)
    tests = {}
    for folder, drives, seed in args.test:
        x, err = features(folder, drives, seed, 0)
        flags = gap_flags(predict(x), err, unit="score")
        tests[f"{folder} (seed {seed})"] = {
            "windows": len(err), "max_deg": float(err.max()),
            **{k: v for k, v in flags.items() if k.startswith(("windows_", "auc_", "flag_"))}}
    print(json.dumps({
        "benchmark": "confidence",
        "model": {"dir": str(model.model_dir), "id": model.model_id},
        "probe": {"fit": {"data": args.fit[0], "drives": args.fit[1], "seed": args.fit[2], "crop_seeds": args.fit_seeds,
                          "windows": len(err_fit), "over_30_deg": int((err_fit > 30).sum()),
                          "r2": float(1.0 - residual.var() / target.var())},
                  "target": "log(1 + error_deg)", "ridge": RIDGE,
                  "weights": dict(sorted(zip(FEATURES, weights.tolist(), strict=True), key=lambda kv: -abs(kv[1])))},
        "tests": tests,
        "machine": machine(),
    }, indent=2))


if __name__ == "__main__":
    run(main)
