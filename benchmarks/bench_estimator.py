"""Per-frame and per-window cost of the estimator on this machine, per network preset.

Random weights (speed does not depend on them), fp32, ONNX Runtime on the CPU. Per frame: 4 crops
cut and resized plus one backbone run (done once, when a frame arrives). Per window: one
aggregator run over 32 cached tokens plus the calibration. Needs the train extra to build models.
With ``--int8`` each preset is measured again with its backbone quantized (``estimator.quantize``,
calibrated on the benchmark's own random frames: speed only, no accuracy).

    python3 benchmarks/bench_estimator.py [--presets fast,light,paper] [--threads N] [--int8]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import comma_list, int_in, machine, run, time_ms  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", type=comma_list(str, "preset names"), default="fast,light,paper",
                    help="network presets (estimator/nets.py; default fast,light,paper)")
    ap.add_argument("--threads", type=int_in(0), default=0, help="ONNX Runtime intra-op threads (0: default)")
    ap.add_argument("--repeats", type=int_in(1), default=20, help="timed runs of each, after 3 warm-up runs")
    ap.add_argument("--int8", action="store_true", help="also measure each preset with an int8 backbone")
    args = ap.parse_args()

    from estimator import nets

    unknown = [name for name in args.presets if name not in nets.PRESETS]
    if unknown:
        ap.error(f"argument --presets: no preset {', '.join(map(repr, unknown))}; pick from {', '.join(nets.PRESETS)}")
    from estimator.estimator import SunEstimator
    from estimator.export import export_model
    from estimator.quantize import calibration_crops, quantize_model
    from estimator.runtime import OnnxModel
    from rig.types import Attitude, Frame, HeadingRef, Intrinsics

    k = Intrinsics(fx=721.5377, fy=721.5377, cx=609.5593, cy=172.854, width=1242, height=375)
    rng = np.random.default_rng(0)
    frames = [Frame(t_mono_s=0.1 * i, seq=i, image_bgr=rng.integers(0, 256, (375, 1242, 3), dtype=np.uint8),
                    intrinsics=k, attitude=Attitude(math.radians(5.0 * i), HeadingRef.TRUE)) for i in range(8)]
    def measure(model) -> dict:
        est = SunEstimator(model)
        window = est.encode_batch(frames)
        i = iter(range(10**9))
        per_frame = time_ms(lambda e=est, i=i: e.encode(frames[next(i) % 8]), repeats=args.repeats)
        per_window = {agg: time_ms(lambda e=est, w=window, a=agg: e.estimate(w, a), repeats=args.repeats)
                      for agg in ("transformer", "mean", "meanshift", "single")}
        return {"frame_encode": per_frame, "window": per_window}

    results = {}
    for name in args.presets:
        cfg = nets.PRESETS[name]
        with tempfile.TemporaryDirectory() as tmp:
            backbone, aggregator = cfg.build(seed=0)
            export_model(backbone, aggregator, cfg.contract(training={"trained": False}), Path(tmp) / "fp32")
            model = OnnxModel.load(Path(tmp) / "fp32", intra_op_threads=args.threads or None)
            results[name] = {"crop_size_px": cfg.crop_size, "base_width": cfg.base_width, **measure(model)}
            if args.int8:
                calibration = calibration_crops(SunEstimator(model), [frames], n_crops=256)
                quantize_model(model, calibration, Path(tmp) / "int8")
                results[name]["int8"] = measure(OnnxModel.load(Path(tmp) / "int8",
                                                                intra_op_threads=args.threads or None))
    print(json.dumps({"benchmark": "estimator", "image": [1242, 375], "crops_per_frame": 4,
                      "tokens_per_window": 32, "intra_op_threads": args.threads or None, "repeats": args.repeats,
                      "int8": args.int8, "results": results, "machine": machine()}, indent=2))


if __name__ == "__main__":
    run(main)
