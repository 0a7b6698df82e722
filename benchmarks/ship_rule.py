"""The model card's rule for replacing the shipped model (docs/model.md, "How a run is chosen"),
applied to two outputs of ``bench_accuracy.py`` on the validation drives.

A run replaces the shipped one when on the validation set it is better in mean, p99 and the
number of estimates over 30 deg (all pooled over the crop seeds) and in the median over crop
seeds of the max. Written down as code so that the decision comes from the same files as the
card's numbers, and so that a rule fixed before a run is not bent after seeing its results.

    python3 benchmarks/bench_accuracy.py --model RUN --data data/val --drives 300 --drive-seed 2500 > run.json
    python3 benchmarks/bench_accuracy.py --data data/val --drives 300 --drive-seed 2500 > shipped.json
    python3 benchmarks/ship_rule.py run.json shipped.json

Prints one JSON object: each criterion's two values and whether the run is better in it, and
``replaces``. Exit 0 whichever way it goes; 2, with one line, when a file is not such a JSON or
the two were not measured on the same windows.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import VALIDATION_SEED  # noqa: E402
from estimator.evaluate import TAIL_KEY  # noqa: E402

# Lower is better in each. The first three pool every crop seed's estimates; the last is the
# median over crop seeds of each seed's max, since the pooled max is one window and moved by
# 26 deg with nothing but the crop seed (docs/model.md).
CRITERIA = ("mean_deg", "p99_deg", TAIL_KEY, "median_by_seed_max_deg")
# What must match for two runs' numbers to be over the same windows.
SAME_MEASUREMENT = ("data", "crop_seeds", "crop_layout")


class RuleError(ValueError):
    """The files cannot be compared by the rule; the message says what to pass instead."""


def criteria(bench: dict) -> dict[str, float]:
    """The rule's four numbers from one ``bench_accuracy.py`` output."""
    try:
        pooled = bench["aggregators"]["transformer"]
        seed_max = [s["max_deg"] for s in bench["per_seed"]["transformer"].values()]
        values = {key: pooled[key] for key in CRITERIA[:3]}
    except (KeyError, TypeError, AttributeError) as exc:
        raise RuleError(f"no transformer figures ({exc}); pass the JSON that bench_accuracy.py prints") from None
    if not seed_max:
        raise RuleError("no crop seed's figures in per_seed; pass the JSON that bench_accuracy.py prints")
    return {**values, "median_by_seed_max_deg": float(statistics.median(seed_max))}


def decide(run: dict, shipped: dict) -> dict:
    """Whether ``run`` replaces ``shipped``, criterion by criterion (lower is better; a tie is not)."""
    for name, bench in (("run", run), ("shipped", shipped)):
        if bench.get("interrupted"):
            raise RuleError(f"the {name}'s benchmark was interrupted; run it to the end")
    differs = [key for key in SAME_MEASUREMENT if run.get(key) != shipped.get(key)]
    if differs:
        raise RuleError(f"the two were measured differently ({', '.join(differs)}); run bench_accuracy.py "
                        "with the same --data, --drives, --drive-seed, --seeds and --crop-layout for both")
    seed = (run.get("data") or {}).get("held_out_seed")
    if seed != VALIDATION_SEED:
        raise RuleError(f"these are drives of seed {seed}, not the validation drives; the rule compares runs on "
                        f"--data data/val --drives 300 --drive-seed {VALIDATION_SEED}")
    a, b = criteria(run), criteria(shipped)
    rows = {key: {"run": a[key], "shipped": b[key], "run_better": a[key] < b[key]} for key in CRITERIA}
    return {
        "rule": "docs/model.md, How a run is chosen",
        "run": run.get("model", {}).get("id"),
        "shipped": shipped.get("model", {}).get("id"),
        "data": run["data"],
        "criteria": rows,
        "replaces": all(r["run_better"] for r in rows.values()),
        "loses_on": [key for key, r in rows.items() if not r["run_better"]],
    }


def _load(path: str) -> dict:
    try:
        bench = json.loads(Path(path).read_text())
    except OSError as exc:
        raise RuleError(f"cannot read {path}: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise RuleError(f"{path} is not text; pass the JSON that bench_accuracy.py prints") from None
    except json.JSONDecodeError as exc:
        raise RuleError(f"{path} is not JSON ({exc.msg}, line {exc.lineno}); pass what bench_accuracy.py prints") \
            from None
    if not isinstance(bench, dict) or bench.get("benchmark") != "accuracy":
        raise RuleError(f"{path} is not an output of bench_accuracy.py")
    return bench


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description="Whether a run replaces the shipped model by the model card's rule.")
    ap.add_argument("run", help="bench_accuracy.py's JSON for the run, on the validation drives")
    ap.add_argument("shipped", help="the same for the shipped model")
    args = ap.parse_args(argv)
    try:
        verdict = decide(_load(args.run), _load(args.shipped))
    except RuleError as exc:
        print(f"ship_rule: error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(verdict, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
