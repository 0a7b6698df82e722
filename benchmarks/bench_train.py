"""Training speed: seconds per step of a preset in float32 and under bf16 autocast, the real loop.

Makes a few small synthetic drives in a temporary folder, then runs ``sunrig``'s training loop
for ``--steps`` steps per precision and reads the step times from its metrics file (every 50
steps), leaving out the first 50 (warm-up). Needs the train extra.

    python3 benchmarks/bench_train.py [--preset fast] [--layers N] [--steps 200] [--drives 12]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import int_in, machine, run  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="fast", help="network preset (estimator/nets.py; default fast)")
    ap.add_argument("--layers", type=int_in(0), default=0, help="transformer layers (default: the preset's)")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--drives", type=int_in(1, 1000), default=12, help="synthetic drives of 24 frames to train on")
    args = ap.parse_args()
    if args.steps < 100:
        ap.error("--steps: at least 100 (the first 50 are warm-up)")

    from estimator import nets
    from estimator.train import METRICS, TrainConfig, train, use_bf16

    # Said now: train() says it too, but only after the drives are rendered.
    if args.preset not in nets.PRESETS:
        ap.error(f"argument --preset: no preset {args.preset!r}; pick from {', '.join(nets.PRESETS)}")
    from replay.synthetic import write_synthetic_logs

    results = {}
    with tempfile.TemporaryDirectory() as tmp:
        logs = write_synthetic_logs(Path(tmp) / "logs", drives=args.drives, frames=24, seed=7, progress=False, jobs=2)
        for precision in ("fp32", "bf16"):
            out = Path(tmp) / precision
            train(logs, out, TrainConfig(preset=args.preset, layers=args.layers, max_steps=args.steps,
                                                     precision=precision))
            rows = [json.loads(line) for line in (out / METRICS).read_text().splitlines()]
            first, last = rows[0], rows[-1]
            results[precision] = {
                "s_per_step": round((last["elapsed_s"] - first["elapsed_s"]) / (last["step"] - first["step"]), 4),
                "steps_timed": last["step"] - first["step"],
            }
    print(json.dumps({
        "benchmark": "train_step",
        "preset": args.preset,
        "layers": args.layers or None,
        "steps": args.steps,
        "drives": args.drives,
        "batch_windows": TrainConfig().batch_windows,
        "native_bf16": use_bf16("auto"),
        "results": results,
        "bf16_speedup": round(results["fp32"]["s_per_step"] / results["bf16"]["s_per_step"], 2),
        "machine": machine(),
    }, indent=2))


if __name__ == "__main__":
    run(main)
