"""Gyro-integrated heading (drivers/imu_heading.py, ``imu_mode gyro``) on a SIMULATED BMI270.

There is no device here: every figure is of a simulation, which models what the BMI270 datasheet
(BST-BMI270-DS000) states and what a vehicle plausibly does; nothing in it was recorded.

The IMU (``SimImu``), at ``--rate-hz`` (oak.py asks ``imu_rate_hz``, default 100; both sensors):

- gyro: the true body rate + a constant bias (``--bias-deg-s`` on each axis, random signs, so the
  rate about up, which turns the heading, is that much on any axis-aligned mount; the datasheet's
  zero-rate offset is +-0.5 deg/s typical, 1 sigma) + a random walk (``--bias-walk``, deg/s per
  sqrt s; the datasheet gives no figure: an assumption) + white noise at ``--gyro-noise`` (7 mdps
  per sqrt Hz, the datasheet's performance mode) over the Nyquist band, quantised to the +-2000
  deg/s range's LSB (which range DepthAI sets is not known here);
- accelerometer: the true specific force + white noise (160 ug per sqrt Hz) and the translational
  vibration below.

The vehicle (``plan_drive`` / ``plan_curve``), the camera (an OAK-D mount, ``CAM_FROM_IMU_OAK_D``)
looking forward, pitched 2 deg down and rolled 1 deg on its mount:

- ``drive``: ``--boot-still-s`` standing at boot, then driving, with a ``--stop-s`` stop every
  ``--stop-every-s`` (slowing down over 5 s, standing, speeding up over 6 s). Driving is a random
  sequence of straight stretches, gentle curves (1-5 deg/s for 10-30 s) and 90 deg turns at
  intersections (slowed to 5 m/s, 20 deg/s); cruising 10-15 m/s.
- ``curve``: the case a stillness test can mistake for a bias: cruising at 20 m/s around one long
  curve at a constant 1-3 deg/s (drawn per drive, or ``--curve-deg-s``) from the first report to
  the last, no stop.

The engine runs throughout: vibration of ``--idle-gyro-deg-s`` (rate amplitude about each axis,
at 20-40 Hz, zero mean) and ``--idle-accel-m-s2``. While moving, the road moves the body
(``--road-scale`` times: pitch and roll rates of 0.5 deg/s RMS at 0.8-3 Hz, heave 0.3 m/s² RMS
at 1-3 Hz, wheel vibration 0.5 m/s² and 1 deg/s at 10-15 Hz, and speed changes of 0.1 m/s² RMS
at 0.1-0.5 Hz); a smooth road is a smaller scale. These figures are assumptions, not measured.

The tracker (``AttitudeTracker`` in ``gyro`` mode, as oak.py makes it) gets each report as oak.py
hands it over (accelerometer, then gyro, of one packet); a 10 Hz camera asks for the heading at
each frame. The error is the tracker's relative heading minus the true heading change since its
first report, wrapped to [-180, 180). Per drive: the error at 1, 5 and 10 minutes (the frame
nearest), its largest magnitude, the largest change of the error across ``--span-s`` (what one
window sees: the window compares frames up to a span apart), the largest pitch and roll errors,
and the integrator's counts. The summary gives the median and max over drives. ``cost`` is the
wall time of one drive's first 20 s of reports through the tracker (``time_ms``, warm-up, repeats)
per gyro report. ``--gyro-bias off`` runs the integrator without learning the bias (as it was
before it learned it); the summary counts the still stretches learned from and refused.

    python3 benchmarks/bench_gyro.py [--scenario drive|curve] [--drives 5] [--seed 0] [--minutes 10]
                                     [--rate-hz 100] [--bias-deg-s 0.5] [--bias-walk 0.002]
                                     [--idle-gyro-deg-s 3] [--idle-accel-m-s2 0.3] [--road-scale 1]
                                     [--boot-still-s 30] [--stop-every-s 120] [--stop-s 20]
                                     [--curve-deg-s R] [--span-s 4] [--repeats 3] [--gyro-bias on|off]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks.common import float_in, int_in, machine, run, time_ms  # noqa: E402

G = 9.80665
DEG = math.pi / 180.0
# BMI270 datasheet (BST-BMI270-DS000): gyro noise density 7 mdps/sqrt(Hz) in performance mode,
# accelerometer 160 ug/sqrt(Hz); the LSB is that of the +-2000 dps range (16 bit).
GYRO_NOISE_DPS_SQRT_HZ = 0.007
ACCEL_NOISE_UG_SQRT_HZ = 160.0
GYRO_LSB_DEG_S = 2000.0 / 32768.0
MOUNT_PITCH_DEG, MOUNT_ROLL_DEG = -2.0, 1.0
FRAME_HZ = 10.0
_DIFF_S = 1e-4  # central difference of the true attitude for the body rate


@dataclass(frozen=True)
class SimConfig:
    scenario: str = "drive"
    minutes: float = 10.0
    rate_hz: float = 100.0
    bias_deg_s: float = 0.5
    bias_walk: float = 0.002  # deg/s per sqrt(s)
    gyro_noise: float = GYRO_NOISE_DPS_SQRT_HZ
    gyro_lsb_deg_s: float = GYRO_LSB_DEG_S  # 0: not quantised
    idle_gyro_deg_s: float = 3.0
    idle_accel_m_s2: float = 0.3
    road_scale: float = 1.0
    boot_still_s: float = 30.0
    stop_every_s: float = 120.0
    stop_s: float = 20.0
    curve_deg_s: float | None = None  # the curve's rate; None: drawn from 1-3 deg/s per drive


class PiecewiseLinear:
    """A function linear between knots (t, value), constant outside them, with its exact integral."""

    def __init__(self, t: list[float], v: list[float]) -> None:
        self.t = np.asarray(t, dtype=np.float64)
        self.v = np.asarray(v, dtype=np.float64)
        seg = np.diff(self.t) * 0.5 * (self.v[1:] + self.v[:-1])
        self._cum = np.concatenate([[0.0], np.cumsum(seg)])

    def __call__(self, t) -> np.ndarray:
        return np.interp(t, self.t, self.v)

    def slope(self, t) -> np.ndarray:
        k = np.clip(np.searchsorted(self.t, t, side="right") - 1, 0, len(self.t) - 2)
        d = np.diff(self.t)[k]
        s = np.where(d > 0, (self.v[k + 1] - self.v[k]) / np.where(d > 0, d, 1.0), 0.0)
        inside = (t >= self.t[0]) & (t < self.t[-1])
        return np.where(inside, s, 0.0)

    def integral(self, t) -> np.ndarray:
        """The integral from the first knot to t (before it: 0; after the last: constant value)."""
        t = np.asarray(t, dtype=np.float64)
        tc = np.clip(t, self.t[0], self.t[-1])
        k = np.clip(np.searchsorted(self.t, tc, side="right") - 1, 0, len(self.t) - 2)
        dt = tc - self.t[k]
        vk = self.v[k]
        vt = np.interp(tc, self.t, self.v)
        return self._cum[k] + dt * 0.5 * (vk + vt) + np.maximum(t - self.t[-1], 0.0) * self.v[-1]


@dataclass
class Plan:
    """Speed (m/s) and yaw rate (rad/s, clockwise seen from above positive) over time."""

    speed: PiecewiseLinear
    yaw_rate: PiecewiseLinear
    duration_s: float


def plan_drive(cfg: SimConfig, rng: np.random.Generator) -> Plan:
    """Boot standstill, then driving with a stop every ``stop_every_s`` (see the module doc)."""
    end = cfg.minutes * 60.0
    kt, kv, kr = [0.0], [0.0], [0.0]

    def knot(dt: float, v: float, r: float) -> None:
        kt.append(kt[-1] + dt)
        kv.append(v)
        kr.append(r)

    knot(cfg.boot_still_s, 0.0, 0.0)
    while kt[-1] < end:
        cruise = float(rng.uniform(10.0, 15.0))
        leg_end = kt[-1] + cfg.stop_every_s
        knot(6.0, cruise, 0.0)
        while kt[-1] < leg_end - 25.0:
            kind = rng.choice(["straight", "curve", "turn"], p=[0.4, 0.35, 0.25])
            if kind == "straight":
                knot(float(rng.uniform(5.0, 20.0)), cruise, 0.0)
            elif kind == "curve":
                r = float(rng.uniform(1.0, 5.0)) * DEG * rng.choice([-1.0, 1.0])
                knot(2.0, cruise, r)
                knot(float(rng.uniform(10.0, 30.0)), cruise, r)
                knot(2.0, cruise, 0.0)
            else:  # 90 deg at an intersection: 1 s ramps in and out (10 deg) and 3.5 s at 20 deg/s
                r = 20.0 * DEG * rng.choice([-1.0, 1.0])
                knot(3.0, 5.0, 0.0)
                knot(1.0, 5.0, r)
                knot(3.5, 5.0, r)
                knot(1.0, 5.0, 0.0)
                knot(4.0, cruise, 0.0)
        knot(5.0, 0.0, 0.0)  # slowing down to the stop
        knot(cfg.stop_s, 0.0, 0.0)
    return Plan(PiecewiseLinear(kt, kv), PiecewiseLinear(kt, kr), end)


def plan_curve(cfg: SimConfig, rng: np.random.Generator) -> Plan:
    """Cruising one long curve at a constant rate from the start: what a bias looks like."""
    end = cfg.minutes * 60.0
    rate = float(rng.uniform(1.0, 3.0)) if cfg.curve_deg_s is None else cfg.curve_deg_s
    r = rate * DEG * rng.choice([-1.0, 1.0])
    return Plan(PiecewiseLinear([0.0, end], [20.0, 20.0]), PiecewiseLinear([0.0, end], [r, r]), end)


class Sines:
    """A sum of sinusoids of random frequency and phase; ``rms`` is the RMS of its derivative
    (``rate=True``: the angle whose rate has that RMS) or of itself."""

    def __init__(self, rng, n: int, f_lo: float, f_hi: float, rms: float, rate: bool = False) -> None:
        self.f = rng.uniform(f_lo, f_hi, n)
        self.ph = rng.uniform(0.0, 2 * np.pi, n)
        amp = rms * math.sqrt(2.0 / n)  # each sinusoid's amplitude: n of them give that RMS
        self.a = amp / (2 * np.pi * self.f) if rate else np.full(n, amp)

    def __call__(self, t) -> np.ndarray:
        t = np.asarray(t, dtype=np.float64)
        return np.sum(self.a * np.sin(2 * np.pi * self.f * t[..., None] + self.ph), axis=-1)


class Vehicle:
    """The true attitude and specific force of the camera (and IMU) over a plan."""

    def __init__(self, plan: Plan, cfg: SimConfig, rng: np.random.Generator) -> None:
        self.plan = plan
        s = cfg.road_scale
        # Engine vibration (always on), one frequency per axis: zero-mean rates of amplitude A.
        amp = cfg.idle_gyro_deg_s * DEG
        self.engine = [Sines(rng, 1, 20.0, 40.0, amp / math.sqrt(2.0), rate=True) for _ in range(3)]
        self.engine_acc = [Sines(rng, 1, 20.0, 40.0, cfg.idle_accel_m_s2 / math.sqrt(2.0)) for _ in range(3)]
        # The road, scaled by how far the vehicle is from standing (full from 3 m/s on).
        self.road_pitch = Sines(rng, 4, 0.8, 3.0, 0.5 * DEG * s, rate=True)
        self.road_roll = Sines(rng, 4, 0.8, 3.0, 0.5 * DEG * s, rate=True)
        self.wheel_pitch = Sines(rng, 3, 10.0, 15.0, 1.0 * DEG * s / math.sqrt(2.0), rate=True)
        self.heave = Sines(rng, 4, 1.0, 3.0, 0.3 * s)
        self.wheel_acc = [Sines(rng, 3, 10.0, 15.0, 0.5 * s / math.sqrt(3.0)) for _ in range(3)]
        self.surge = Sines(rng, 4, 0.1, 0.5, 0.1 * s)

    def moving(self, t) -> np.ndarray:
        return np.minimum(1.0, self.plan.speed(t) / 3.0)

    def angles(self, t) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Camera heading (clockwise from north, radians, unwrapped), pitch and roll."""
        m = self.moving(t)
        heading = self.plan.yaw_rate.integral(t) + self.engine[2](t)
        pitch = MOUNT_PITCH_DEG * DEG + self.engine[0](t) + m * (self.road_pitch(t) + self.wheel_pitch(t))
        roll = MOUNT_ROLL_DEG * DEG + self.engine[1](t) + m * self.road_roll(t)
        return heading, pitch, roll

    def world_from_imu(self, t, cam_from_imu) -> np.ndarray:
        from drivers.imu_heading import world_from_cam

        h, p, r = self.angles(t)
        return world_from_cam(h, p, r) @ cam_from_imu

    def body_rate_imu(self, t, cam_from_imu) -> np.ndarray:
        """The true angular rate in IMU axes (rad/s): R(t - d)^T R(t + d) over 2 d."""
        a = self.world_from_imu(t - _DIFF_S, cam_from_imu)
        b = self.world_from_imu(t + _DIFF_S, cam_from_imu)
        m = np.swapaxes(a, -1, -2) @ b
        return np.stack([m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0],
                         m[..., 1, 0] - m[..., 0, 1]], axis=-1) / (4.0 * _DIFF_S)

    def specific_force_imu(self, t, cam_from_imu) -> np.ndarray:
        """What an ideal accelerometer reads (m/s², IMU axes): acceleration minus gravity."""
        m = self.moving(t)
        yaw = self.plan.yaw_rate.integral(t)
        fwd = np.stack([np.sin(yaw), np.cos(yaw), np.zeros_like(yaw)], axis=-1)
        right = np.stack([np.cos(yaw), -np.sin(yaw), np.zeros_like(yaw)], axis=-1)
        along = self.plan.speed.slope(t) + m * self.surge(t)
        centripetal = self.plan.speed(t) * self.plan.yaw_rate(t)  # clockwise: towards the right
        up = G + m * self.heave(t)
        f_world = along[..., None] * fwd + centripetal[..., None] * right
        f_world[..., 2] += up
        r = self.world_from_imu(t, cam_from_imu)
        f = np.einsum("...ji,...j->...i", r, f_world)
        vib = np.stack([e(t) for e in self.engine_acc], axis=-1)
        wheel = np.stack([w(t) for w in self.wheel_acc], axis=-1)
        return f + vib + m[..., None] * wheel


@dataclass
class Reports:
    t: np.ndarray  # (n,) seconds
    gyro: np.ndarray  # (n, 3) rad/s, IMU axes
    accel: np.ndarray  # (n, 3) m/s², IMU axes
    bias: np.ndarray  # (n, 3) rad/s: the simulated gyro bias at each report


def simulate(vehicle: Vehicle, cfg: SimConfig, rng: np.random.Generator, cam_from_imu) -> Reports:
    """The BMI270's reports at ``cfg.rate_hz`` over the plan (SIMULATED)."""
    n = int(vehicle.plan.duration_s * cfg.rate_hz) + 1
    t = np.arange(n) / cfg.rate_hz
    dt = 1.0 / cfg.rate_hz
    b0 = cfg.bias_deg_s * DEG * rng.choice([-1.0, 1.0], 3)
    walk = np.cumsum(rng.normal(0.0, cfg.bias_walk * DEG * math.sqrt(dt), (n, 3)), axis=0)
    bias = b0 + walk
    nyquist = cfg.rate_hz / 2.0
    gyro_sigma = cfg.gyro_noise * DEG * math.sqrt(nyquist)
    accel_sigma = ACCEL_NOISE_UG_SQRT_HZ * 1e-6 * G * math.sqrt(nyquist)
    gyro = vehicle.body_rate_imu(t, cam_from_imu) + bias + rng.normal(0.0, gyro_sigma, (n, 3))
    if cfg.gyro_lsb_deg_s > 0:
        lsb = cfg.gyro_lsb_deg_s * DEG
        gyro = np.round(gyro / lsb) * lsb
    accel = vehicle.specific_force_imu(t, cam_from_imu) + rng.normal(0.0, accel_sigma, (n, 3))
    return Reports(t, gyro, accel, bias)


def wrap_deg(x):
    return (np.asarray(x) + 180.0) % 360.0 - 180.0


def span_error_deg(t: np.ndarray, err_deg: np.ndarray, span_s: float) -> float:
    """The largest change of the heading error between two frames at most ``span_s`` apart."""
    worst = 0.0
    j = 0
    for i in range(len(t)):  # frames in time order; the window [t_i - span, t_i]
        while t[i] - t[j] > span_s + 1e-9:
            j += 1
        seg = err_deg[j:i + 1]
        worst = max(worst, float(np.max(seg) - np.min(seg)))
    return worst


def make_tracker(**kw):
    from drivers.imu_heading import CAM_FROM_IMU_OAK_D, AttitudeTracker, ImuMode

    return AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D, **kw)


def feed(tracker, rep: Reports, frame_hz: float = FRAME_HZ, upto: int | None = None):
    """Every report through the tracker, as oak.py does; the attitude at each frame time (a
    frame is asked for once the report at or after it came). Returns (frame_t, attitudes)."""
    n = len(rep.t) if upto is None else upto
    times, atts = [], []
    next_frame = 0.0
    gyro, accel, ts = rep.gyro.tolist(), rep.accel.tolist(), rep.t.tolist()
    for k in range(n):
        t = ts[k]
        tracker.add_accelerometer(t, accel[k])
        tracker.add_gyro(t, gyro[k])
        while next_frame <= t:
            att, _ = tracker.attitude_at(next_frame)
            times.append(next_frame)
            atts.append(att)
            next_frame = round(next_frame + 1.0 / frame_hz, 9)
    return np.array(times), atts


def errors(vehicle: Vehicle, times: np.ndarray, atts: list, t0: float) -> dict:
    """Heading, pitch and roll errors (deg) of the frames with an attitude."""
    ok = np.array([a is not None for a in atts])
    tt = times[ok]
    h, p, r = vehicle.angles(tt)
    h0 = vehicle.angles(np.array([t0]))[0][0]
    est_h = np.array([a.heading_rad for a in atts if a is not None])
    est_p = np.array([a.pitch_rad for a in atts if a is not None])
    est_r = np.array([a.roll_rad for a in atts if a is not None])
    # Unwrapped: a drift past half a turn is that much error, not a small one of the other sign.
    heading = np.degrees(np.unwrap(np.radians(wrap_deg(np.degrees(est_h - (h - h0))))))
    return {"t": tt, "heading": heading, "pitch": np.degrees(est_p - p),
            "roll": wrap_deg(np.degrees(est_r - r)), "frames_without": int(np.sum(~ok))}


def run_drive(cfg: SimConfig, seed: int, span_s: float, tracker_kw: dict | None = None) -> dict:
    from drivers.imu_heading import CAM_FROM_IMU_OAK_D

    rng = np.random.default_rng(seed)
    plan = plan_curve(cfg, rng) if cfg.scenario == "curve" else plan_drive(cfg, rng)
    vehicle = Vehicle(plan, cfg, rng)
    rep = simulate(vehicle, cfg, rng, CAM_FROM_IMU_OAK_D)
    tracker = make_tracker(**(tracker_kw or {}))
    times, atts = feed(tracker, rep)
    e = errors(vehicle, times, atts, float(rep.t[0]))
    at = {}
    for minute in (1, 5, 10):
        if minute * 60.0 <= e["t"][-1] + 1e-9:
            k = int(np.argmin(np.abs(e["t"] - minute * 60.0)))
            at[f"{minute}min"] = round(float(e["heading"][k]), 2)
    counts = dict(tracker.gyro.counts)
    standing = plan.speed(e["t"]) == 0.0
    return {
        "seed": seed,
        "heading_error_deg": at,
        "max_abs_heading_error_deg": round(float(np.max(np.abs(e["heading"]))), 2),
        "max_span_error_deg": round(span_error_deg(e["t"], e["heading"], span_s), 3),
        "max_abs_pitch_error_deg": round(float(np.max(np.abs(e["pitch"]))), 2),
        "max_abs_roll_error_deg": round(float(np.max(np.abs(e["roll"]))), 2),
        "heading_drift_deg_s_true": round(float(-np.degrees(rep.bias[0] @ up_imu(vehicle, rep))), 3),
        "standing_share": round(float(np.mean(standing)), 3),
        "frames_without_heading": e["frames_without"],
        "counts": {k: (round(v, 4) if isinstance(v, float) else v) for k, v in counts.items()},
    }


def up_imu(vehicle: Vehicle, rep: Reports) -> np.ndarray:
    """World up in IMU axes at the first report (the mount is fixed, so nearly always)."""
    from drivers.imu_heading import CAM_FROM_IMU_OAK_D

    return vehicle.world_from_imu(rep.t[:1], CAM_FROM_IMU_OAK_D)[0].T @ np.array([0.0, 0.0, 1.0])


def summarize(drives: list[dict]) -> dict:
    out: dict = {}
    for key in ("1min", "5min", "10min"):
        vals = [abs(d["heading_error_deg"][key]) for d in drives if key in d["heading_error_deg"]]
        if vals:
            out[f"abs_heading_error_{key}_deg"] = {"median": round(statistics.median(vals), 2),
                                                  "max": round(max(vals), 2)}
    for key in ("max_abs_heading_error_deg", "max_span_error_deg", "max_abs_pitch_error_deg",
                "max_abs_roll_error_deg"):
        vals = [d[key] for d in drives]
        out[key] = {"median": round(statistics.median(vals), 3), "max": round(max(vals), 3)}
    for key in ("gyro_bias_learned", "gyro_bias_refused"):
        out[key] = sum(int(d["counts"].get(key, 0)) for d in drives)
    return out


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", choices=("drive", "curve"), default="drive",
                    help="drive: stops and turns; curve: one long constant-rate curve, no stop")
    ap.add_argument("--drives", type=int_in(1), default=5, help="simulated drives (seeds seed .. seed + n - 1)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--minutes", type=float_in(0.0, 120.0), default=10.0)
    ap.add_argument("--rate-hz", type=float_in(20.0, 1000.0, lo_included=True), default=100.0,
                    help="IMU report rate (oak.py's imu_rate_hz; at least its 20 Hz)")
    ap.add_argument("--bias-deg-s", type=float_in(0.0, 20.0, lo_included=True), default=0.5)
    ap.add_argument("--bias-walk", type=float_in(0.0, 1.0, lo_included=True), default=0.002,
                    help="bias random walk, deg/s per sqrt(s)")
    ap.add_argument("--idle-gyro-deg-s", type=float_in(0.0, 100.0, lo_included=True), default=3.0)
    ap.add_argument("--idle-accel-m-s2", type=float_in(0.0, 20.0, lo_included=True), default=0.3)
    ap.add_argument("--road-scale", type=float_in(0.0, 10.0, lo_included=True), default=1.0)
    ap.add_argument("--boot-still-s", type=float_in(0.0, 600.0, lo_included=True), default=30.0)
    ap.add_argument("--stop-every-s", type=float_in(40.0, 3600.0, lo_included=True), default=120.0)
    ap.add_argument("--stop-s", type=float_in(0.0, 600.0, lo_included=True), default=20.0)
    ap.add_argument("--curve-deg-s", type=float_in(0.0, 30.0), default=None,
                    help="the curve scenario's rate (default: drawn from 1-3 deg/s per drive)")
    ap.add_argument("--span-s", type=float_in(0.0, 60.0), default=4.0, help="the window's span")
    ap.add_argument("--gyro-bias", choices=("on", "off"), default="on",
                    help="learn the gyro bias while still (on, the driver's default) or not (off: as before)")
    ap.add_argument("--repeats", type=int_in(1), default=3, help="timed runs for the cost (after one warm-up)")
    return ap.parse_args(argv)


def main() -> None:
    args = parse_args()
    cfg = SimConfig(scenario=args.scenario, minutes=args.minutes, rate_hz=args.rate_hz, bias_deg_s=args.bias_deg_s,
                    bias_walk=args.bias_walk, idle_gyro_deg_s=args.idle_gyro_deg_s,
                    idle_accel_m_s2=args.idle_accel_m_s2, road_scale=args.road_scale,
                    boot_still_s=args.boot_still_s, stop_every_s=args.stop_every_s, stop_s=args.stop_s,
                    curve_deg_s=args.curve_deg_s)
    tracker_kw = {"gyro_bias": args.gyro_bias == "on"}
    drives = []
    for i in range(args.drives):
        d = run_drive(cfg, args.seed + i, args.span_s, tracker_kw)
        drives.append(d)
        print(f"drive {i + 1}/{args.drives}: seed {d['seed']}, error {d['heading_error_deg']}, "
              f"max {d['max_abs_heading_error_deg']} deg", file=sys.stderr)
    from drivers.imu_heading import CAM_FROM_IMU_OAK_D

    rng = np.random.default_rng(args.seed)
    plan = plan_curve(cfg, rng) if cfg.scenario == "curve" else plan_drive(cfg, rng)
    vehicle = Vehicle(plan, cfg, rng)
    rep = simulate(vehicle, cfg, rng, CAM_FROM_IMU_OAK_D)
    upto = min(len(rep.t), int(20.0 * cfg.rate_hz))
    timing = time_ms(lambda: feed(make_tracker(**tracker_kw), rep, upto=upto), repeats=args.repeats, warmup=1)
    result = {
        "benchmark": "gyro_heading",
        "simulated": "a simulated BMI270 and vehicle, no device: see the module doc for every assumption",
        "config": {**cfg.__dict__, "drives": args.drives, "seed": args.seed, "span_s": args.span_s,
                   "gyro_bias": args.gyro_bias,
                   "mount": "OAK-D", "frame_hz": FRAME_HZ},
        "summary": summarize(drives),
        "cost_us_per_report": {"median": round(timing["median_ms"] * 1e3 / upto, 1),
                               "p10": round(timing["p10_ms"] * 1e3 / upto, 1),
                               "p90": round(timing["p90_ms"] * 1e3 / upto, 1)},
        "drives": drives,
        "machine": machine(),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    run(main)
