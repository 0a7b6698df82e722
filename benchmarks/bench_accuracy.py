"""Accuracy of a model on held-out synthetic drives: the numbers in docs/model.md.

Makes the held-out drives if they are not there yet (seed 2000: never used in training, whose
drives come from seed 1000), runs every aggregator over every full window, prints the JSON summary
and writes the figures.

The crops of a frame are random (seeded by ``--seeds`` and the frame's number), and one model's
worst window moves a lot with them: on the session-2 model, crop seeds 0, 1 and 2 gave a maximum
of 35, 85 and 80 deg on the same windows. So every window is estimated once per crop seed and the
headline numbers pool all of them (3 x 1700 estimates by default); ``per_seed`` gives each seed's,
with the drives of its worst windows (``worst_logs``).

``by_newest_frame`` groups the windows by their newest frame: a drive's first windows, eight frames
back to back, are its hardest (docs/model.md).

``status`` says what a controller would have been told of those windows (the model's status rule,
docs/protocol.md), and ``elevation`` how far above the truth the answers for the highest training
suns go: the margin the rule allows above them (rig/protocol.ELEVATION_MARGIN_DEG).

    python3 benchmarks/bench_accuracy.py [--model DIR] [--data DIR] [--drives 100] [--plot OUT.png]
                                         [--seeds 0,1,2] [--crop-layout spread|uniform] [--drive-seed 2000]
                                         [--crops N] [--mirror-windows on|off] [--variant NAME]

The figures go beside the drives (``data/heldout-eval.png`` and ``-tokens.png`` for
``data/heldout``), unless ``--plot`` says where; the JSON names both (``data_dir``, ``plot``).
``--mirror-windows`` runs the model mirrored or not whatever its contract says (the shipped model's
says mirrored); ``--variant`` measures a run-time change that was tried and not adopted
(benchmarks/variants.py).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import add_drive_args, comma_list, drives_and_model, machine, run  # noqa: E402
from benchmarks.variants import VARIANTS, estimator_for  # noqa: E402

HELD_OUT_SEED = 2000
_seeds = comma_list(int, "distinct integers", lambda seeds: len(set(seeds)) == len(seeds))


def _positive(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return n


def default_plot(data: str) -> Path:
    """Where the figures of the drives in ``data`` go unless ``--plot`` says: beside the folder,
    named after it (``data/heldout`` -> ``data/heldout-eval.png``), so that the validation run's
    figures do not replace the held-out ones'."""
    folder = Path(data)
    return folder.parent / f"{folder.name or 'drives'}-eval.png"


def check_plot(plot: Path) -> None:
    """Refuse a ``--plot`` that cannot be written, making its folder."""
    from rig.errors import SunrigError

    try:
        plot.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SunrigError(f"--plot {plot}: cannot make its folder ({exc.strerror}); pass another path") from None
    if plot.is_dir() or not os.access(plot.parent, os.W_OK):
        raise SunrigError(f"--plot {plot}: cannot write there; pass another path")


def elevation_excess(result, trained_max_deg: float | None, band_deg: float = 5.0) -> dict | None:
    """For windows whose true sun is within ``band_deg`` of the highest training sun: how far the
    transformer's answer lies above the truth (p99 and max)."""
    import numpy as np

    if trained_max_deg is None:
        return None
    truth = np.asarray(result.truth_elevation_deg)
    excess = np.asarray(result.elevation_deg["transformer"]) - truth
    top = truth >= trained_max_deg - band_deg
    return {"trained_max_deg": trained_max_deg, "truth_from_deg": trained_max_deg - band_deg,
            "n_windows": int(top.sum()),
            "excess_p99_deg": float(np.percentile(excess[top], 99)) if top.any() else None,
            "excess_max_deg": float(excess[top].max()) if top.any() else None}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_drive_args(ap, data="data/heldout", drives=100, drive_seed=HELD_OUT_SEED,
                   drive_seed_help=f"seed of the drives (default {HELD_OUT_SEED}; the validation set is 2500; "
                                   "training used 1000, whose drives say nothing about held-out accuracy)")
    ap.add_argument("--plot", metavar="OUT.png",
                    help="the cumulative error figure, and OUT-tokens.png beside it (default: beside the drives, "
                         "DATA-eval.png)")
    ap.add_argument("--seeds", type=_seeds, default=[0, 1, 2],
                    help="crop seeds; every window is estimated once per seed (default 0,1,2)")
    ap.add_argument("--crop-layout", default="spread", choices=("spread", "uniform"),
                    help="where each frame's crops go (default spread, as every command; uniform: the paper's draws)")
    ap.add_argument("--crops", type=_positive, default=0, metavar="N",
                    help="crops per frame instead of the model's (its contract's; more costs backbone time per frame)")
    ap.add_argument("--mirror-windows", choices=("on", "off"),
                    help="run every window mirrored too, or not (default: as the model's contract says)")
    ap.add_argument("--variant", default="plain", choices=VARIANTS,
                    help="a run-time change tried and not adopted (benchmarks/variants.py; default plain)")
    args = ap.parse_args()
    plot = Path(args.plot) if args.plot else default_plot(args.data)
    check_plot(plot)  # before the drives and the evaluation: a plot that fails at the end loses minutes

    from estimator.evaluate import WORST_LOGS, error_summary, evaluate, plot_eval
    from replay.sources import open_frames
    from rig.window import SpreadWindowPolicy

    paths, model = drives_and_model(args)
    pooled, per_seed = None, {}
    make_estimator = estimator_for(args.variant)
    for seed in args.seeds:
        estimator = make_estimator(model, seed=seed, crop_layout=args.crop_layout, crops_per_frame=args.crops or None,
                                   mirror_windows=None if args.mirror_windows is None else args.mirror_windows == "on")
        policy = SpreadWindowPolicy(n_frames=estimator.frames_per_window, span_s=4.0)
        result = evaluate([(p.name, open_frames(p)) for p in paths], estimator, policy)
        per_seed[str(seed)] = {**error_summary(result.errors_deg["transformer"]),
                               "worst_logs": result.by_log("transformer")[:WORST_LOGS]}
        print(f"crop seed {seed}: transformer mean {per_seed[str(seed)]['mean_deg']:.2f} deg, "
              f"max {per_seed[str(seed)]['max_deg']:.2f} deg", file=sys.stderr)
        if pooled is None:
            pooled = result
        else:
            pooled.extend(result)
        if result.interrupted:
            break  # Ctrl-C: report what was done (marked interrupted), not go on with the next seed
    plot_eval(pooled, plot)
    summary = pooled.summary()
    summary.pop("logs")
    trained = model.contract.trained_sun_elevation_deg
    print(json.dumps({
        "benchmark": "accuracy",
        "data": {"held_out_seed": args.drive_seed, "drives": args.drives, "frames_per_drive": args.frames},
        "data_dir": args.data,
        "plot": str(plot),
        "crop_layout": args.crop_layout,
        "variant": args.variant,
        "mirror_windows": estimator.mirror_windows,
        "crop_seeds": args.seeds,
        "crops_per_frame": args.crops or model.contract.crops_per_frame,
        "model": {"dir": str(model.model_dir), "id": model.model_id,
                  "training_command": model.contract.training.get("command")},
        **summary,
        "status_rule": {"max_elevation_deg": estimator.status_rule().max_elevation_deg},
        "elevation": elevation_excess(pooled, None if trained is None else trained[1]),
        "by_newest_frame": {"transformer": pooled.by_newest_frame("transformer")},
        "per_seed": {"transformer": per_seed},
        "machine": machine(),
    }, indent=2))


if __name__ == "__main__":
    run(main)
