"""Accuracy of a model on held-out synthetic drives: the numbers in docs/model.md.

Makes the held-out drives if they are not there yet (seed 2000: never used in training, whose
drives come from seed 1000), runs every aggregator over every full window, prints the JSON summary
and writes the figures.

    python3 benchmarks/bench_accuracy.py [--model DIR] [--data DIR] [--drives 100] [--plot OUT.png]
                                         [--crop-layout spread|uniform]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import machine  # noqa: E402

HELD_OUT_SEED = 2000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", help="model folder (default: the shipped model)")
    ap.add_argument("--data", default="data/heldout", help="where the held-out drives are (made if missing)")
    ap.add_argument("--drives", type=int, default=100)
    ap.add_argument("--frames", type=int, default=24)
    ap.add_argument("--plot", default="data/heldout-eval.png")
    ap.add_argument("--crop-layout", default="spread", choices=("spread", "uniform"),
                    help="where each frame's crops go (default spread, as every command; uniform: the paper's draws)")
    args = ap.parse_args()

    from estimator.estimator import SunEstimator
    from estimator.evaluate import evaluate, plot_eval
    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel
    from replay.sources import open_frames
    from replay.synthetic import write_synthetic_logs
    from rig.window import SpreadWindowPolicy

    paths = write_synthetic_logs(args.data, drives=args.drives, frames=args.frames, seed=HELD_OUT_SEED,
                                 progress=sys.stderr.isatty(), jobs=2)
    model = OnnxModel.load(resolve_model_dir(args.model))
    estimator = SunEstimator(model, crop_layout=args.crop_layout)
    policy = SpreadWindowPolicy(n_frames=estimator.frames_per_window, span_s=4.0)
    result = evaluate([(str(p), open_frames(p)) for p in paths], estimator, policy)
    Path(args.plot).parent.mkdir(parents=True, exist_ok=True)
    plot_eval(result, Path(args.plot))
    summary = result.summary()
    summary.pop("logs")
    print(json.dumps({
        "benchmark": "accuracy",
        "data": {"held_out_seed": HELD_OUT_SEED, "drives": args.drives, "frames_per_drive": args.frames},
        "crop_layout": args.crop_layout,
        "model": {"dir": str(model.model_dir), "id": model.model_id,
                  "training_command": model.contract.training.get("command")},
        **summary,
        "machine": machine(),
    }, indent=2))


if __name__ == "__main__":
    main()
