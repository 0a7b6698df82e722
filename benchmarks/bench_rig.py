"""The live rig on this machine: frame-to-publish latency, update rate, drops and memory.

Runs the bundled drive (looped to a longer source) through `RigPipeline` with the given model:
paced at 10 Hz (a camera's rate, ``--frames`` frames) and unpaced (frames made as fast as possible
for the same duration: a source far faster than the estimator), publishing NMEA to a real
pseudo-terminal that nobody reads. Its kernel buffer (about 16 KB on Linux) fills after a few
hundred messages, so the serial publisher's drop path is exercised too: expect a write timeout and
a reopen even in the paced run (300 frames: 298 written, 1 timeout, 1 reopen). Also times single
`SerialPublisher.publish` calls against that stalled reader. Prints JSON.

    python3 benchmarks/bench_rig.py [--model DIR] [--frames 400]
    python3 benchmarks/bench_rig.py --preset paper [--int8]     # the paper's architecture, random weights
    python3 benchmarks/bench_rig.py --resolution 1920x1080      # memory at a camera's size

``--preset`` runs an untrained model of that network preset (speed does not depend on the weights;
needs the train extra), ``--int8`` the model with its backbone quantized (``sunrig quantize``,
calibrated on the bundled drive's frames). ``--ort-spinning`` lets ONNX Runtime's threads
spin between ops, its default, which the rig turns off (docs/model.md, "int8 backbones").
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import machine  # noqa: E402


def at_resolution(frames, width: int, height: int) -> list:
    """The drive's frames resized to ``width`` x ``height``, their intrinsics scaled with them."""
    from dataclasses import replace

    import cv2

    from replay.kitti import scaled_intrinsics

    return [replace(f, image_bgr=cv2.resize(f.image_bgr, (width, height), interpolation=cv2.INTER_LINEAR),
                    intrinsics=scaled_intrinsics(f.intrinsics, width, height)) for f in frames]


def handed_out(frame, t_mono_s: float, seq: int, own_image: bool):
    """``frame`` renumbered and restamped; with ``own_image``, in an image buffer of its own, as a
    camera fills a new one for every frame (a looped drive's frames otherwise share its 40 images,
    which hides what holding frames costs)."""
    from dataclasses import replace

    if own_image:
        return replace(frame, t_mono_s=t_mono_s, seq=seq, image_bgr=frame.image_bgr.copy())
    return replace(frame, t_mono_s=t_mono_s, seq=seq)


def looped(frames, n: int, dt: float, own_images: bool = False):
    """``n`` frames from a drive played over and over, renumbered, ``dt`` apart."""
    for i in range(n):
        yield handed_out(frames[i % len(frames)], i * dt, i, own_images)


def flood(frames, seconds: float, own_images: bool = False):
    """Frames as fast as they can be made for ``seconds``, stamped with the monotonic clock: a
    source far faster than the estimator, for the sustained (overloaded) update rate."""
    end = time.monotonic() + seconds
    i = 0
    while time.monotonic() < end:
        yield handed_out(frames[i % len(frames)], time.monotonic(), i, own_images)
        i += 1


def resolution(text: str) -> tuple[int, int]:
    width, sep, height = text.partition("x")
    if not (sep and width.isdigit() and height.isdigit() and 64 <= int(width) <= 8192 and 64 <= int(height) <= 8192):
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, each 64..8192 px (e.g. 1920x1080), got {text!r}")
    return int(width), int(height)


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", help="model folder (default: the shipped model)")
    ap.add_argument("--frames", type=int, default=400)
    ap.add_argument("--preset", help="an untrained model of this network preset instead (fast, light, paper)")
    ap.add_argument("--int8", action="store_true", help="quantize the model's backbone first")
    ap.add_argument("--ort-spinning", action="store_true",
                    help="ONNX Runtime's threads spin between ops (its default, not the rig's), to compare")
    ap.add_argument("--resolution", type=resolution, metavar="WxH",
                    help="the drive's frames resized to this size, each frame in an image buffer of its own as "
                         "a camera's: what the rig's memory holds at that size (max_rss_mb)")
    args = ap.parse_args()

    from estimator.estimator import SunEstimator
    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel
    from replay.sources import DEMO_LOG, open_frames
    from rig.pipeline import RigConfig, RigPipeline
    from rig.publishers import SerialPublisher
    from rig.window import SpreadWindowPolicy

    drive = list(open_frames(DEMO_LOG))
    if args.resolution:
        drive = at_resolution(drive, *args.resolution)
    tmp = tempfile.TemporaryDirectory()
    if args.preset:
        from estimator.export import build_random_model
        from estimator.nets import PRESETS

        model_dir = build_random_model(Path(tmp.name) / "float", PRESETS[args.preset], seed=0)
    else:
        model_dir = resolve_model_dir(args.model)
    model = OnnxModel.load(model_dir, spin_wait=args.ort_spinning)
    if args.int8:
        from estimator.quantize import calibration_crops, quantize_model

        calibration = calibration_crops(SunEstimator(model), [drive], n_crops=512)
        model = OnnxModel.load(quantize_model(model, calibration, Path(tmp.name) / "int8"),
                               spin_wait=args.ort_spinning)
    results = {}
    for name, realtime in (("paced_10hz", True), ("unpaced", False)):
        master, slave = os.openpty()
        pub = SerialPublisher(os.ttyname(slave), format="nmea")
        est = SunEstimator(model)
        rss_before = rss_mb()
        own = args.resolution is not None
        source = looped(drive, args.frames, 0.1, own) if realtime else flood(drive, args.frames / 10.0, own)
        pipe = RigPipeline(source, est, SpreadWindowPolicy(), [pub], config=RigConfig(realtime=realtime))
        t0 = time.monotonic()
        stats = pipe.run()
        wall = time.monotonic() - t0
        pub.close()
        # The serial writer may still have been writing when run() took its statistics: read
        # them again after the close, as the CLI's exit report does.
        pipe.collect_publisher_stats()
        os.close(master)
        os.close(slave)
        d = stats.as_dict()
        results[name] = {
            "frames": d["frames_captured"], "wall_s": wall, "update_hz": d["update_hz"], "latency": d["latency"],
            "frames_dropped_queue": d["frames_dropped_queue"], "windows_skipped": d["windows_skipped"],
            "estimates": d["estimates"], "serial": d["publishers"].get("SerialPublisher", {}),
            "max_rss_mb_before": rss_before, "max_rss_mb_after": rss_mb(),
        }

    # One publish() call while the reader has stopped: the estimator's cost of a stalled link.
    master, slave = os.openpty()
    pub = SerialPublisher(os.ttyname(slave), format="nmea")
    est = SunEstimator(model)
    sample = est.estimate(est.encode_batch(drive[:8]))
    calls = []
    for _ in range(5000):
        t = time.perf_counter()
        pub.publish(sample)
        calls.append((time.perf_counter() - t) * 1e3)
    pub_stats = pub.stats()
    pub.close()
    os.close(master)
    os.close(slave)
    calls.sort()
    results["publish_call_stalled_reader"] = {
        "calls": len(calls), "p50_ms": calls[len(calls) // 2], "p99_ms": calls[int(len(calls) * 0.99)],
        "max_ms": calls[-1], "serial": pub_stats,
    }
    size = args.resolution or (drive[0].intrinsics.width, drive[0].intrinsics.height)
    print(json.dumps({"benchmark": "rig", "model": model.model_id, "preset": args.preset, "int8": args.int8,
                      "resolution": f"{size[0]}x{size[1]}", "own_images": args.resolution is not None,
                      "ort_spinning": args.ort_spinning,
                      "trained": bool(model.contract.training.get("trained", True)), "results": results,
                      "machine": machine()}, indent=2))
    tmp.cleanup()


if __name__ == "__main__":
    main()
