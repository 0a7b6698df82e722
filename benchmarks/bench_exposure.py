"""What the exposure gate lets through of a covered lens, a night or a sun metered dark, and how the model reads it.

The gate is rig/exposure.py. These are the things a road camera shows that a luma mean and
standard deviation do not: a lens partly covered (a cap slid over, a hand, a sun visor close to
the lens), dusk or night brightened by auto exposure into noise, and the sun in view with the
rest of the frame metered dark.

Fresh synthetic drives (``drive_seed(--drive-seed, i)``, named ``drive_SEED_IIII`` as elsewhere)
are rendered once per pose. Each impairment acts on the light that reaches the sensor (the
rendered radiance), before the drive's camera (auto-exposure, noise, tone curve) and JPEG at the
synthetic logs' quality, so that the camera's exposure reacts to a covered lens as a real one
would: it brightens what the cover leaves. On ``--drives`` drives:

- ``none``: the drive as rendered (the control);
- ``cap_lower_half`` / ``cap_left_half``: that half of the frame black (a lens cap slid over);
- ``blob_30`` / ``blob_60``: a dark, flat, soft-edged blob over 30 % / 60 % of the frame (a hand
  from the lower right, a sun visor from the top), out of focus as anything at the lens is;
- ``night_4`` / ``night_6`` / ``night_8``: dusk or night, the light 4 / 6 / 8 stops down, which
  the camera's auto exposure makes up in gain, and the sensor's noise grown with that gain as
  photon noise does (2^(stops/2) in the camera's sqrt-exposure units; the synthetic camera keeps
  its noise fixed whatever the exposure, so the benchmark applies it: ``night_camera``). Only the
  photon noise: a real sensor's read noise, which the camera does not model, adds to it in the
  shadows.

On ``--sun-drives`` drives of the same set whose sun is in view and not hidden (half its disk
showing or more) in at least half the frames (found in order by their plan, then by their render):

- ``sun_none``: the drive as rendered (the control);
- ``sun_metered``: each frame that shows the sun exposed so that its mean luma is ``--metered-mean``
  (a meter that protects the highlights), its sun disk still saturated.

Each drive runs through the offline rig loop of ``sunrig replay`` (rig/offline.estimate_stream:
the rig's ring, SpreadWindowPolicy with the default span, SunEstimator with the model's aggregator
and crop seed ``--crop-seed``) and the model's status rule: one estimate per frame, partial windows
included, as the live rig sends. Per impairment, once with the exposure gate as shipped
(``gate_on``) and once without (``gate_off``: what the model makes of every frame): windows, angular
error (mean, median, p90, max), the share flagged valid (FLAG_VALID), the valid windows' mean error
and how many of them are over 30 deg; the frames the gate rejects, by reason, and the share of the
frames the gate's cover measure finds covered (rig/exposure.covered_share; of the frames the
impairment changed, or of every frame of a control), and their ``fine_share``, a noise measure the
gate does not use (neighbouring pixels' luma differences against the frame's spread).

``gate_us`` is what the gate costs a frame (median over the control frames, microseconds).
``--count-gate DIR`` instead counts the gate's verdicts on every frame of the logs in DIR (e.g. the
held-out drives, data/heldout), as shipped and with only the mean and standard deviation checks:
how many frames a measure added to the gate newly rejects there, their covered and fine shares.

    python3 benchmarks/bench_exposure.py [--model DIR] [--drives 16] [--sun-drives 6] [--drive-seed 3000]
                                         [--frames 24] [--metered-mean 10] [--crop-seed 0]
    python3 benchmarks/bench_exposure.py --count-gate data/heldout
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import (  # noqa: E402
    SYNTH_JPEG_QUALITY,
    check_frames,
    float_in,
    int_in,
    machine,
    run,
    through_jpeg,
    time_ms,
)
from rig.protocol import FLAG_VALID  # noqa: E402

if TYPE_CHECKING:
    from replay.synthetic.drive import Drive

# The fresh set (bench_standstill.py): never trained on (1000) nor chosen by (2500, 2000).
DEFAULT_DRIVE_SEED = 3000
TRAINING_DRIVE_SEED = 1000
IMPAIRMENTS = ("none", "cap_lower_half", "cap_left_half", "blob_30", "blob_60")
# Dusk and night: the light cut by that many stops, which the drive's auto exposure makes up in gain.
NIGHT_IMPAIRMENTS = ("night_4", "night_6", "night_8")
SUN_IMPAIRMENTS = ("sun_none", "sun_metered")
# A blob's centre (x, y as shares of the width and height) and its edge's softness (a share of the
# width): a hand comes up from the lower right, a visor down from the top; both out of focus.
BLOBS = {"blob_30": (0.30, (0.8, 1.0)), "blob_60": (0.60, (0.5, 0.0))}
BLOB_SOFTNESS = 0.06
# A blob's radiance, a share of the frame's median: a hand or a visor in the shade of the car.
BLOB_LEVEL = 0.03
# Half the sun's disk showing or more makes a frame "in view" (the renderer's sun_visible).
SUN_VISIBLE = 0.5
# How many drives of the set are looked at for sun-in-view ones before giving up.
SUN_SCAN_LIMIT = 4000
TAIL_DEG = 30.0


def cover_mask(height: int, width: int, kind: str) -> np.ndarray:
    """How much of the light a cover takes at each pixel (0-1, float32 (height, width))."""
    mask = np.zeros((height, width), np.float32)
    if kind == "cap_lower_half":
        mask[height // 2:] = 1.0
    elif kind == "cap_left_half":
        mask[:, : width // 2] = 1.0
    elif kind in BLOBS:
        share, (cx, cy) = BLOBS[kind]
        yy, xx = np.mgrid[0:height, 0:width].astype(np.float32)
        # An ellipse as wide, for its height, as the frame: distance in widths, rows stretched.
        dist = np.hypot((xx + 0.5) / width - cx, ((yy + 0.5) / height - cy) * height / width)
        radius = float(np.quantile(dist, share))  # the blob's middle of the edge holds `share` of the pixels
        mask = (1.0 / (1.0 + np.exp((dist - radius) / (BLOB_SOFTNESS / 4.0)))).astype(np.float32)
    elif kind != "none":
        raise ValueError(f"cover_mask: unknown impairment {kind!r}; expected one of {IMPAIRMENTS}")
    return mask


def impaired_radiance(radiance: np.ndarray, kind: str) -> np.ndarray:
    """``radiance`` (h, w, 3) with the cover ``kind`` in front of the lens: a cap takes all the
    light, a blob replaces it by its own flat, dark radiance."""
    if kind == "none":
        return radiance
    height, width = radiance.shape[:2]
    mask = cover_mask(height, width, kind)[..., None]
    level = BLOB_LEVEL * float(np.median(radiance)) if kind in BLOBS else 0.0
    return (radiance * (1.0 - mask) + level * mask).astype(np.float32)


def night_stops(kind: str) -> int:
    """How many stops of light the night impairment ``kind`` ("night_N") takes."""
    if kind not in NIGHT_IMPAIRMENTS:
        raise ValueError(f"night_stops: unknown impairment {kind!r}; expected one of {NIGHT_IMPAIRMENTS}")
    return int(kind.removeprefix("night_"))


def night_camera(effects, width: int, height: int, seed: int, stops: int):
    """The drive's camera (``effects``) for a scene ``stops`` darker, with the noise of the gain
    its auto exposure then applies. The synthetic camera adds a fixed noise in sqrt-exposure units
    whatever the exposure, so light cut by 2^stops and made up by the exposure came out as clean as
    by day; a real sensor's photon (shot) noise at 2^stops the gain is 2^(stops/2) as large in
    those units (sqrt(g * N) electrons' spread against g * N, read through a square root)."""
    from dataclasses import replace

    from replay.synthetic.camera import Camera

    noisy = replace(effects, noise_sqrt=effects.noise_sqrt * 2.0 ** (stops / 2.0))
    return Camera(noisy, width, height, seed=seed)


def fine_share(image_bgr: np.ndarray) -> float:
    """A noise measure the gate does not use: the mean square luma difference between the gate's
    sampled pixels and their right-hand neighbours (left-hand in the last column), over twice the
    sample's luma variance; about 1 for white noise, near 0 for a smooth scene."""
    from rig.exposure import _LUMA_BGR, _luma_sample, _sample_flat

    height, width = image_bgr.shape[:2]
    flat = _sample_flat(height, width)
    beside = np.where(flat % width == width - 1, flat - 1, flat + 1) if width > 1 else flat
    luma = _luma_sample(image_bgr)
    neighbour = (np.ascontiguousarray(image_bgr).reshape(-1, 3).take(beside, axis=0).astype(np.float32)
                 @ _LUMA_BGR).astype(np.float64)
    variance = float(luma.var())
    return float(np.mean((luma - neighbour) ** 2)) / (2.0 * variance) if variance > 0 else 0.0


def luma_mean(image_bgr: np.ndarray) -> float:
    """Mean BT.601 luma of a whole 8-bit BGR image."""
    return float((image_bgr.reshape(-1, 3).astype(np.float32) @ np.array([0.114, 0.587, 0.299], np.float32)).mean())


def capture_metered(camera, radiance: np.ndarray, rng_key: list[int], target_mean: float) -> np.ndarray:
    """``radiance`` through ``camera`` (one without auto-exposure, the drive's sensor otherwise) at
    the exposure that gives a mean luma of ``target_mean``, bisected in log exposure with the noise
    drawn from ``rng_key`` each time: a meter that darkens the frame for the sun in it."""
    from dataclasses import replace

    lo, hi = math.log(1e-6), math.log(1e3)
    image = None
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        camera.effects = replace(camera.effects, auto_exposure=False, fixed_exposure=math.exp(mid))
        image = camera.capture(radiance, np.random.default_rng(rng_key))
        mean = luma_mean(image)
        if abs(mean - target_mean) < 0.25:
            break
        lo, hi = (mid, hi) if mean < target_mean else (lo, mid)
    assert image is not None
    return image


@dataclass
class Rendered:
    """A drive rendered once: each pose's radiance and how much of the sun's disk it shows."""

    drive: Drive
    radiance: list[np.ndarray]
    sun_visible: list[float]


def render(drive: Drive) -> Rendered:
    radiance, sun_visible = [], []
    for pose in drive.poses:
        out = drive.renderer.render(pose)
        radiance.append(out.radiance.copy())  # a copy now: the renderer draws every pose into the same buffers
        sun_visible.append(float(out.sun_visible))
    return Rendered(drive, radiance, sun_visible)


def frames_of(r: Rendered, kind: str, metered_mean: float, impaired: list[int]) -> Iterator:
    """The Frames of drive ``r`` under impairment ``kind``, through one camera (its exposure
    carried over) and JPEG; appends to ``impaired`` the seqs of the frames the impairment changed."""
    from replay.synthetic.camera import Camera
    from rig.types import Attitude, Frame, HeadingRef

    drive = r.drive
    width, height = drive.intrinsics.width, drive.intrinsics.height
    night = night_stops(kind) if kind in NIGHT_IMPAIRMENTS else 0
    camera = (night_camera(drive.params.effects, width, height, drive.seed, night) if night
              else Camera(drive.params.effects, width, height, seed=drive.seed))
    # The same sensor (noise bank, gain), exposed by the benchmark: its auto-exposure left as it was.
    metered = Camera(drive.params.effects, drive.intrinsics.width, drive.intrinsics.height, seed=drive.seed)
    for k, pose in enumerate(drive.poses):
        key = [drive.seed, 3, k]
        if kind == "sun_metered" and r.sun_visible[k] >= SUN_VISIBLE:
            image = capture_metered(metered, r.radiance[k], key, metered_mean)
            impaired.append(k)
        elif night:
            image = camera.capture(r.radiance[k] * np.float32(2.0 ** -night), np.random.default_rng(key))
            impaired.append(k)
        else:
            light = impaired_radiance(r.radiance[k], "none" if kind.startswith("sun_") else kind)
            image = camera.capture(light, np.random.default_rng(key))
            if not kind.startswith("sun_") and kind != "none":
                impaired.append(k)
        t_s = k / drive.fps
        yield Frame(t_mono_s=t_s, seq=k, image_bgr=through_jpeg(image), intrinsics=drive.intrinsics,
                    attitude=Attitude(pose.heading_rad, HeadingRef.TRUE, pose.pitch_rad, pose.roll_rad),
                    utc_ns=drive.params.utc_start_ns + int(round(t_s * 1e9)), gnss=None,
                    sun_enu_truth=drive.sun_enu)


@dataclass
class Counts:
    """An impairment's frames, those it changed, the gate's verdicts and the changed frames' mean luma."""

    frames: int = 0
    frames_impaired: int = 0
    gate: Counter = field(default_factory=Counter)
    impaired_luma_mean: list[float] = field(default_factory=list)
    covered_share: list[float] = field(default_factory=list)
    fine_share: list[float] = field(default_factory=list)


@dataclass
class Windows:
    """Each window's error (deg) and whether it was flagged valid."""

    error_deg: list[float] = field(default_factory=list)
    valid: list[bool] = field(default_factory=list)

    def summary(self) -> dict:
        e = np.asarray(self.error_deg, dtype=np.float64)
        v = np.asarray(self.valid, dtype=bool)
        some = e.size > 0
        return {
            "windows": int(e.size),
            "mean_deg": float(e.mean()) if some else None,
            "median_deg": float(np.median(e)) if some else None,
            "p90_deg": float(np.percentile(e, 90)) if some else None,
            "max_deg": float(e.max()) if some else None,
            "valid_share": float(v.mean()) if some else None,
            "valid_mean_deg": float(e[v].mean()) if v.any() else None,
            f"valid_over_{TAIL_DEG:.0f}_deg": int((v & (e > TAIL_DEG)).sum()),
        }


def run_stream(frames: list, estimator, rule, span_s: float, gate, out: Windows) -> None:
    """Every window of ``frames`` through the rig's offline loop with ``gate`` (None: none), into ``out``."""
    from rig.offline import estimate_stream
    from rig.window import SpreadWindowPolicy

    policy = SpreadWindowPolicy(n_frames=estimator.frames_per_window, span_s=span_s)
    for results in estimate_stream(iter(frames), estimator, policy, exposure_gate=gate):
        est = results[estimator.aggregator]
        assert est.error_rad is not None  # every synthetic frame carries its true sun
        out.error_deg.append(math.degrees(est.error_rad))
        out.valid.append(bool(rule.flags(est) & FLAG_VALID))


def sun_drives(set_seed: int, n_frames: int, fps: float, want: int, skip: set[int]) -> Iterator[tuple[int, Rendered]]:
    """Drives of the set (index, rendered) whose sun shows in at least half the frames: by their
    plan first (the sun on the image, cheap), then by their render (not hidden by the street)."""
    from replay.synthetic import drive_seed, plan_drive
    from replay.synthetic.drive import KITTI_INTRINSICS, Drive
    from replay.synthetic.render import project_direction

    found = 0
    for index in range(SUN_SCAN_LIMIT):
        if found == want:
            return
        if index in skip:
            continue
        seed = drive_seed(set_seed, index)
        plan = plan_drive(seed, n_frames)
        on_image = 0
        for pose in plan.poses:
            uv, z = project_direction(plan.params.sun_enu, pose, KITTI_INTRINSICS)
            on_image += bool(z > 0 and 0 <= uv[0] < KITTI_INTRINSICS.width and 0 <= uv[1] < KITTI_INTRINSICS.height)
        if 2 * on_image < n_frames:
            continue
        r = render(Drive(seed, n_frames, fps=fps))
        if 2 * sum(v >= SUN_VISIBLE for v in r.sun_visible) >= n_frames:
            found += 1
            yield index, r


def _spread(values: list[float]) -> dict | None:
    return ({"min": float(np.min(values)), "median": float(np.median(values)), "max": float(np.max(values))}
            if values else None)


def count_gate(folder: str) -> dict:
    """The gate's verdicts on every frame of the logs in ``folder``: as shipped, and with only its
    mean and standard deviation checks (the gate before any other measure)."""
    from replay.sources import open_frames
    from rig.errors import SunrigError
    from rig.exposure import DEFAULT_EXPOSURE_GATE, covered_share, luminance_stats

    paths = sorted(Path(folder).glob("*.mcap"))
    if not paths:
        raise SunrigError(f"--count-gate {folder}: no .mcap logs there; pass a folder of drives, e.g. data/heldout")
    g = DEFAULT_EXPOSURE_GATE
    shipped: Counter = Counter()
    plain: Counter = Counter()
    newly: list[str] = []
    shares: list[float] = []
    fine: list[float] = []
    frames = 0
    for path in paths:
        for frame in open_frames(path):
            frames += 1
            reason = g.rejects(frame.image_bgr)
            mean, std = luminance_stats(frame.image_bgr)
            shares.append(covered_share(frame.image_bgr))
            fine.append(fine_share(frame.image_bgr))
            before = ("dark" if mean < g.min_mean else "bright" if mean > g.max_mean
                      else "flat" if std < g.min_std else None)
            shipped[reason or "passed"] += 1
            plain[before or "passed"] += 1
            if reason and not before:
                newly.append(f"{path.stem} seq {frame.seq} ({reason})")
    return {"folder": folder, "logs": len(paths), "frames": frames, "shipped_gate": dict(shipped),
            "mean_std_only": dict(plain), "newly_rejected": len(newly), "newly_rejected_frames": newly[:20],
            "covered_share": _spread(shares), "fine_share": _spread(fine)}


def main() -> None:
    from replay.synthetic import MAX_DRIVES, MAX_FRAMES

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", help="model folder (default: the shipped model)")
    ap.add_argument("--drives", type=int_in(0, MAX_DRIVES), default=16, help="drives for the covers (default 16)")
    ap.add_argument("--sun-drives", type=int_in(0, MAX_DRIVES), default=6,
                    help="drives with the sun in view, for the metering (default 6)")
    ap.add_argument("--drive-seed", type=int, default=DEFAULT_DRIVE_SEED,
                    help=f"seed of the drive set (default {DEFAULT_DRIVE_SEED}; not {TRAINING_DRIVE_SEED}, "
                         "the training drives)")
    ap.add_argument("--frames", type=int_in(1, MAX_FRAMES), default=24,
                    help="frames per drive (default 24; at least the model's window)")
    ap.add_argument("--metered-mean", type=float_in(0.0, 255.0), default=10.0,
                    help="mean luma of a frame metered for the sun in it (default 10)")
    ap.add_argument("--crop-seed", type=int, default=0, help="the estimator's crop seed (default 0, the rig's)")
    ap.add_argument("--count-gate", metavar="DIR",
                    help="only count the gate's verdicts on the logs in DIR (e.g. data/heldout) and exit")
    args = ap.parse_args()
    if args.count_gate is not None:
        started = time.perf_counter()
        print(json.dumps({"benchmark": "exposure_gate_count", **count_gate(args.count_gate),
                          "runtime_s": round(time.perf_counter() - started, 1), "machine": machine()}, indent=2))
        return
    if args.drive_seed == TRAINING_DRIVE_SEED:
        ap.error(f"--drive-seed {TRAINING_DRIVE_SEED}: the training drives say nothing of a model's error; "
                 f"pass another set's seed, e.g. {DEFAULT_DRIVE_SEED}")
    if args.drives + args.sun_drives == 0:
        ap.error("--drives 0 --sun-drives 0: nothing to measure; pass at least one drive")

    from estimator.estimator import SunEstimator
    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel
    from replay.synthetic import drive_seed
    from replay.synthetic.drive import Drive
    from rig.config import DEFAULTS
    from rig.exposure import DEFAULT_EXPOSURE_GATE, covered_share

    started = time.perf_counter()
    model = OnnxModel.load(resolve_model_dir(args.model))
    check_frames(args.frames, model)
    estimator = SunEstimator(model, seed=args.crop_seed)
    rule = estimator.status_rule()
    span_s = float(DEFAULTS["window"]["span_s"])
    fps = 10.0
    gate = DEFAULT_EXPOSURE_GATE

    results: dict[str, dict] = {}
    windows = {kind: (Windows(), Windows()) for kind in (*IMPAIRMENTS, *NIGHT_IMPAIRMENTS, *SUN_IMPAIRMENTS)}
    counts = {kind: Counts() for kind in windows}
    gate_cost: list[Callable[[], object]] = []

    def measure(r: Rendered, kind: str) -> None:
        impaired: list[int] = []
        frames = list(frames_of(r, kind, args.metered_mean, impaired))
        c = counts[kind]
        c.frames += len(frames)
        c.frames_impaired += len(impaired)
        for f in frames:
            c.gate[gate.rejects(f.image_bgr) or "passed"] += 1
        c.impaired_luma_mean += [luma_mean(frames[k].image_bgr) for k in impaired]
        c.covered_share += [covered_share(frames[k].image_bgr) for k in (impaired or range(len(frames)))]
        c.fine_share += [fine_share(frames[k].image_bgr) for k in (impaired or range(len(frames)))]
        if kind == "none" and not gate_cost:
            image = frames[0].image_bgr
            gate_cost.append(lambda: gate.rejects(image))
        on, off = windows[kind]
        run_stream(frames, estimator, rule, span_s, gate, on)
        run_stream(frames, estimator, rule, span_s, None, off)

    covers = []
    for index in range(args.drives):
        r = render(Drive(drive_seed(args.drive_seed, index), args.frames, fps=fps))
        covers.append(index)
        for kind in (*IMPAIRMENTS, *NIGHT_IMPAIRMENTS):
            measure(r, kind)
        print(f"drive_{args.drive_seed}_{index:04d}: covers and night done", file=sys.stderr)
    sunny = []
    for index, r in sun_drives(args.drive_seed, args.frames, fps, args.sun_drives, skip=set(covers)):
        sunny.append(f"drive_{args.drive_seed}_{index:04d}")
        for kind in SUN_IMPAIRMENTS:
            measure(r, kind)
        print(f"{sunny[-1]}: sun in view in {sum(v >= SUN_VISIBLE for v in r.sun_visible)} frames, done",
              file=sys.stderr)
    for kind, (on, off) in windows.items():
        c = counts[kind]
        if not c.frames:
            continue
        results[kind] = {
            "frames": c.frames, "frames_impaired": c.frames_impaired,
            "impaired_luma_mean": _spread(c.impaired_luma_mean),
            "covered_share": _spread(c.covered_share),
            "fine_share": _spread(c.fine_share),
            "gate": dict(c.gate),
            "gate_on": on.summary(), "gate_off": off.summary()}
    cost = time_ms(gate_cost[0], repeats=200, warmup=20) if gate_cost else None
    print(json.dumps({
        "benchmark": "exposure",
        "drives": {"drive_seed": args.drive_seed, "covers": args.drives, "sun_in_view": sunny,
                   "frames": args.frames, "fps": fps, "jpeg_quality": SYNTH_JPEG_QUALITY,
                   "metered_mean": args.metered_mean},
        "window": {"n_frames": estimator.frames_per_window, "span_s": span_s},
        "crop_seed": args.crop_seed,
        "model": {"dir": str(model.model_dir), "id": model.model_id},
        "exposure_gate": {k: v for k, v in vars(gate).items()},
        "gate_us": None if cost is None else {"median": cost["median_ms"] * 1e3, "p90": cost["p90_ms"] * 1e3},
        "impairments": results,
        "runtime_s": round(time.perf_counter() - started, 1),
        "machine": machine(),
    }, indent=2))


if __name__ == "__main__":
    run(main)
