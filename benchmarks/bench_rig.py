"""The live rig on this machine: frame-to-publish latency, update rate, drops and memory.

Runs the bundled drive (looped to a longer source) through `RigPipeline` with the given model:
paced at 10 Hz (a camera's rate, ``--frames`` frames) and unpaced (frames made as fast as possible
for the same duration: a source far faster than the estimator), publishing NMEA to a real
pseudo-terminal that nobody reads. Its kernel buffer (about 16 KB on Linux) fills after a few
hundred messages, so the serial publisher's drop path is exercised too: expect a write timeout and
a reopen even in the paced run (300 frames: 298 written, 1 timeout, 1 reopen). Also times single
`SerialPublisher.publish` calls against that stalled reader. Prints JSON.

Every frame is stamped on the monotonic clock, as a camera's, so each run also reports ``age``: an
estimate's age when the last output returned, from its newest frame's time (``latency`` is the
rig's own figure, from the frame leaving the source or, paced, from when it was due). Two more runs
at the paced rate: ``stall`` (one window takes ``--stall-s`` seconds, a page-out: the estimates
after it must not be stale, and the stalled one is not sent, as ``estimates_stale``), and
``stop_mid_window`` (``stop()`` while that window is stalled: how long ``run()`` takes to return).
``--load N`` runs them all beside N busy processes at the same nice level, a busy computer.

    python3 benchmarks/bench_rig.py [--model DIR] [--frames 400] [--fps 10] [--load 0] [--stall-s 3]
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
    """``n`` frames from a drive played over and over, renumbered, ``dt`` apart, stamped on the
    monotonic clock from the first (paced, the pacer then hands each on at its stamp)."""
    t0 = time.monotonic()
    for i in range(n):
        yield handed_out(frames[i % len(frames)], t0 + i * dt, i, own_images)


class AgeProbe:
    """The last output: each estimate's age as it returns, from its newest frame's time (this
    benchmark's sources stamp frames on the monotonic clock, as a camera does)."""

    def __init__(self) -> None:
        self.ages_s: list[float] = []

    def publish(self, est) -> None:
        self.ages_s.append(time.monotonic() - est.t_mono_s)

    def close(self) -> None:
        pass

    def stats(self) -> dict:
        return {}

    def summary(self, bound_s: float) -> dict:
        if not self.ages_s:
            return {}
        a = sorted(self.ages_s)
        return {"p50_ms": a[len(a) // 2] * 1e3, "p99_ms": a[int(len(a) * 0.99)] * 1e3, "max_ms": a[-1] * 1e3,
                "over_bound": sum(1 for x in a if x > bound_s)}


def stalling(estimator_cls, stall_at: int, stall_s: float, stalled=None):
    """``estimator_cls`` whose ``stall_at``-th window takes ``stall_s`` longer (a page-out);
    ``stalled`` (an Event) is set as the stall begins."""

    class Stalls(estimator_cls):
        windows = 0

        def estimate(self, window, aggregator=None):
            type(self).windows += 1
            if type(self).windows == stall_at:
                if stalled is not None:
                    stalled.set()
                time.sleep(stall_s)
            return super().estimate(window, aggregator)

    return Stalls


def busy_processes(n: int) -> list:
    """``n`` processes that spin at the same nice level, each ending when this one does (even killed)."""
    import subprocess

    code = "import os\np = os.getppid()\nwhile os.getppid() == p: pass"
    return [subprocess.Popen([sys.executable, "-c", code]) for _ in range(n)]


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
    ap.add_argument("--fps", type=float, default=10.0, help="the paced runs' frame rate (default 10)")
    ap.add_argument("--load", type=int, default=0, help="busy processes beside the rig (default 0)")
    ap.add_argument("--stall-s", type=float, default=3.0, help="how long the stall run's one window takes")
    ap.add_argument("--preset", help="an untrained model of this network preset instead (fast, light, paper)")
    ap.add_argument("--int8", action="store_true", help="quantize the model's backbone first")
    ap.add_argument("--ort-spinning", action="store_true",
                    help="ONNX Runtime's threads spin between ops (its default, not the rig's), to compare")
    ap.add_argument("--resolution", type=resolution, metavar="WxH",
                    help="the drive's frames resized to this size, each frame in an image buffer of its own as "
                         "a camera's: what the rig's memory holds at that size (max_rss_mb)")
    args = ap.parse_args()
    if not (args.fps > 0 and args.load >= 0 and args.stall_s > 0 and args.frames >= 50):
        ap.error("expected --fps > 0, --load >= 0, --stall-s > 0 and --frames >= 50")

    from estimator.estimator import SunEstimator
    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel
    from replay.sources import DEMO_LOG, open_frames

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
    results: dict[str, dict] = {}
    dt = 1.0 / args.fps
    load = busy_processes(args.load)
    try:
        _runs(args, drive, model, dt, results)
    finally:
        for proc in load:
            proc.kill()
            proc.wait()
    size = args.resolution or (drive[0].intrinsics.width, drive[0].intrinsics.height)
    print(json.dumps({"benchmark": "rig", "model": model.model_id, "preset": args.preset, "int8": args.int8,
                      "resolution": f"{size[0]}x{size[1]}", "own_images": args.resolution is not None,
                      "ort_spinning": args.ort_spinning, "fps": args.fps, "load_processes": args.load,
                      "stall_s": args.stall_s,
                      "trained": bool(model.contract.training.get("trained", True)), "results": results,
                      "machine": machine()}, indent=2))
    tmp.cleanup()


def _runs(args, drive, model, dt: float, results: dict) -> None:
    import threading

    from estimator.estimator import SunEstimator
    from rig.pipeline import RigConfig, RigPipeline
    from rig.publishers import SerialPublisher
    from rig.window import SpreadWindowPolicy

    bound_s = RigConfig().max_latency_s
    paced_name = f"paced_{args.fps:g}hz"
    for name, realtime in ((paced_name, True), ("unpaced", False)):
        master, slave = os.openpty()
        pub = SerialPublisher(os.ttyname(slave), format="nmea")
        est = SunEstimator(model)
        rss_before = rss_mb()
        own = args.resolution is not None
        source = looped(drive, args.frames, dt, own) if realtime else flood(drive, args.frames * dt, own)
        probe = AgeProbe()
        pipe = RigPipeline(source, est, SpreadWindowPolicy(), [pub, probe], config=RigConfig(realtime=realtime))
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
            "age": probe.summary(bound_s), "frames_dropped_queue": d["frames_dropped_queue"],
            "windows_skipped": d["windows_skipped"], "estimates_stale": d["estimates_stale"],
            "estimates": d["estimates"], "serial": d["publishers"].get("SerialPublisher", {}),
            "max_rss_mb_before": rss_before, "max_rss_mb_after": rss_mb(),
        }

    # One window takes stall_s (its 30th), paced: the rig goes on from the newest frame after it.
    probe = AgeProbe()
    n = max(50, int(round((args.stall_s + 6.0) / dt)))
    est = stalling(SunEstimator, 30, args.stall_s)(model)
    pipe = RigPipeline(looped(drive, n, dt), est, SpreadWindowPolicy(), [probe], config=RigConfig(realtime=True))
    d = pipe.run().as_dict()
    results["stall"] = {"frames": d["frames_captured"], "estimates": d["estimates"], "latency": d["latency"],
                        "age": probe.summary(bound_s), "estimates_stale": d["estimates_stale"],
                        "windows_skipped": d["windows_skipped"], "frames_dropped_queue": d["frames_dropped_queue"]}

    # stop() 0.3 s into that stalled window: run() returns within its bound on the stages (2 s).
    stalled = threading.Event()
    est = stalling(SunEstimator, 30, args.stall_s, stalled)(model)
    pipe = RigPipeline(looped(drive, n, dt), est, SpreadWindowPolicy(), [AgeProbe()], config=RigConfig(realtime=True))
    stopped_at: list[float] = []

    def stop_in_the_stall() -> None:
        if stalled.wait(60.0):
            time.sleep(0.3)
            stopped_at.append(time.monotonic())
            pipe.stop()

    threading.Thread(target=stop_in_the_stall, daemon=True).start()
    d = pipe.run().as_dict()
    returned = time.monotonic()
    results["stop_mid_window"] = {
        "stop_to_return_s": returned - stopped_at[0] if stopped_at else None,
        "frames": d["frames_captured"], "estimates": d["estimates"],
        "accounted": d["frames_captured"] == (d["frames_encoded"] + d["frames_dropped_queue"]
                                              + d["frames_without_heading"] + d["frames_bad_exposure"]),
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


if __name__ == "__main__":
    main()
