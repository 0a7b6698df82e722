"""Camera attitude from an IMU: quaternions -> heading/pitch/roll, gyro integration, a buffer of
orientations interpolated at a frame's mid-exposure time, and magnetic declination.

Pure: numpy arrays, floats and timestamps in, values out; no depthai, no I/O, no clock. The OAK
driver (``drivers/oak.py``) turns DepthAI messages into calls on :class:`AttitudeTracker`;
``docs/oak.md`` is the specification and ``tests/test_imu_heading.py`` tests it.

Frames (``docs/conventions.md`` has the project's table):

- ``enu``: world, x east, y north, z up.
- ``sensor world``: the world frame the IMU's fusion reports in. The BNO08x follows Android's
  definition (x east, y north, z up: ENU), so by default it is ``enu``; ``ned`` and ``nwu`` are
  selectable in case a unit disagrees (see docs/oak.md, "Assumptions").
- ``imu``: the IMU's body axes, the frame of its accelerometer, gyroscope and rotation vector.
- ``cam``: OpenCV camera frame of the colour camera (x right, y down, z forward).

A rotation vector (Android, BNO08x) is the unit quaternion ``q`` with ``v_world = R(q) v_imu``,
i.e. ``sensor_world_from_imu``. Quaternions here are arrays ``[w, x, y, z]`` (DepthAI's
``real, i, j, k``).
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from rig.errors import ValidationError
from rig.geometry import wrap_2pi
from rig.types import Attitude, HeadingRef

GRAVITY_M_S2 = 9.80665

# The sensor world frames a rotation vector may be expressed in, as enu_from_<frame>.
ENU_FROM_SENSOR_WORLD = {
    "enu": np.eye(3),  # Android / BNO08x datasheet: x east, y north, z up
    "ned": np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]),  # x north, y east, z down
    "nwu": np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),  # x north, y west, z up
}

# IMU mounting in OAK devices, as cam_from_imu (columns: the IMU's x, y, z axes in the colour
# camera's OpenCV frame). From Luxonis' depthai-ros URDF (depthai_descriptions base_macro.urdf.xacro,
# IMU joint rpy relative to the camera's x-forward/y-left/z-up frame): OAK-D rpy (0, pi/2, 0) gives
# IMU x down, y left, z forward; OAK-D-PRO and OAK-D-POE rpy (pi, pi/2, 0) give x down, y right,
# z backward (the same as Luxonis' forum answer quoted in Monado's DepthAI driver). Used only when
# the device calibration has no IMU extrinsics.
CAM_FROM_IMU_OAK_D = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
CAM_FROM_IMU_OAK_D_PRO = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
CAM_FROM_IMU_BY_PRODUCT = {
    "OAK-D": CAM_FROM_IMU_OAK_D,
    "OAK-D-PRO": CAM_FROM_IMU_OAK_D_PRO,
    "OAK-D-POE": CAM_FROM_IMU_OAK_D_PRO,
}
CAM_FROM_IMU_DEFAULT = CAM_FROM_IMU_OAK_D_PRO  # unknown product: the current OAK-D Pro layout

_ROTATION_TOL = 1e-3  # how far a calibration matrix may be from a proper rotation
_MISMATCH_SMOOTHING = 0.05  # exponential smoothing of the gravity check (about 20 reports)
_VERTICAL_SIN = math.sin(math.radians(1.0))  # optical axis within 1 deg of vertical: no heading
# Lookup results (AttitudeTracker.attitude_at reasons). Only "ok" carries an attitude.
OK, NO_IMU_YET, TOO_OLD, IMU_PENDING, IMU_GAP, VERTICAL, INACCURATE = (
    "ok", "no_imu_yet", "too_old", "imu_pending", "imu_gap", "vertical", "inaccurate")
_MAX_INACCURATE_RUNS = 64  # stretches of refused rotation vectors remembered (within history_s)


# ---------------------------------------------------------------------------------------------
# Quaternions and rotations
# ---------------------------------------------------------------------------------------------


def quat_normalize(q) -> np.ndarray:
    """Unit quaternion(s) [w, x, y, z]; a zero quaternion is a ValidationError (no orientation)."""
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q, axis=-1, keepdims=True)
    if q.shape[-1] != 4 or np.any(~np.isfinite(q)) or np.any(n < 1e-9):
        raise ValidationError(f"quaternion: expected finite [w, x, y, z] with norm > 0, got {q.tolist()}")
    return q / n


def rotation_from_quat(q_wxyz) -> np.ndarray:
    """Rotation matrix (..., 3, 3) of unit quaternion(s) (..., 4) [w, x, y, z]: v' = R v."""
    q = quat_normalize(q_wxyz)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], axis=-1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], axis=-1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], axis=-1),
    ]
    return np.stack(rows, axis=-2)


def quat_from_rotation(r) -> np.ndarray:
    """Unit quaternion [w, x, y, z] (w >= 0) of a 3x3 rotation matrix (Shepperd's method)."""
    m = np.asarray(r, dtype=np.float64)
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2])
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = 2.0 * math.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2])
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1])
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q_wxyz = np.array(q)
    return quat_normalize(-q_wxyz if q_wxyz[0] < 0 else q_wxyz)


def quat_multiply(a, b) -> np.ndarray:
    """Hamilton product a (x) b: the rotation b, then a."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array([
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    ])


def quat_from_rotvec(v) -> np.ndarray:
    """Quaternion of a rotation vector (axis times angle, radians)."""
    v = np.asarray(v, dtype=np.float64)
    angle = float(np.linalg.norm(v))
    if angle < 1e-12:
        return np.array([1.0, 0.5 * v[0], 0.5 * v[1], 0.5 * v[2]])  # first order; normalised by the caller
    s = math.sin(angle / 2.0) / angle
    return np.array([math.cos(angle / 2.0), v[0] * s, v[1] * s, v[2] * s])


def slerp(q0, q1, f: float) -> np.ndarray:
    """Spherical interpolation from q0 (f = 0) to q1 (f = 1) along the shorter arc (q and -q are
    the same rotation, so q1 is flipped when they lie in opposite hemispheres)."""
    q0 = quat_normalize(q0)
    q1 = quat_normalize(q1)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 0.9995:  # nearly equal: the linear form is exact to float precision and avoids 0/0
        return quat_normalize(q0 + f * (q1 - q0))
    theta = math.acos(min(d, 1.0))
    s = math.sin(theta)
    return (math.sin((1.0 - f) * theta) / s) * q0 + (math.sin(f * theta) / s) * q1


def validate_rotation(name: str, r) -> np.ndarray:
    """A 3x3 proper rotation (orthonormal, det +1 within 1e-3) as float64, or ValidationError."""
    try:
        m = np.asarray(r, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValidationError(f"{name}: expected a 3x3 rotation matrix, got {r!r}") from None
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        raise ValidationError(f"{name}: expected a finite 3x3 rotation matrix, got shape {m.shape}")
    err = float(np.max(np.abs(m @ m.T - np.eye(3))))
    if err > _ROTATION_TOL or abs(np.linalg.det(m) - 1.0) > _ROTATION_TOL:
        raise ValidationError(
            f"{name}: expected a proper rotation (R R^T = I, det +1), got max |R R^T - I| = {err:.2g}, "
            f"det = {np.linalg.det(m):.4f}"
        )
    return m


# ---------------------------------------------------------------------------------------------
# Attitude of the optical axis
# ---------------------------------------------------------------------------------------------


def world_from_cam(heading_rad, pitch_rad=0.0, roll_rad=0.0) -> np.ndarray:
    """ENU from OpenCV camera (..., 3, 3) for heading (clockwise from north), pitch (nose up) and
    roll (right side down), applied yaw, then pitch about the right axis, then roll about the
    optical axis (docs/conventions.md). Columns: the camera's x (right), y (down), z (forward)."""
    h, p, r = (np.asarray(a, dtype=np.float64) for a in (heading_rad, pitch_rad, roll_rad))
    h, p, r = np.broadcast_arrays(h, p, r)
    sh, ch, sp, cp, sr, cr = np.sin(h), np.cos(h), np.sin(p), np.cos(p), np.sin(r), np.cos(r)
    fwd0 = np.stack([sh, ch, np.zeros_like(h)], axis=-1)  # level forward after the yaw
    right0 = np.stack([ch, -sh, np.zeros_like(h)], axis=-1)
    up0 = np.stack([np.zeros_like(h), np.zeros_like(h), np.ones_like(h)], axis=-1)
    fwd = cp[..., None] * fwd0 + sp[..., None] * up0  # pitch about the right axis
    up1 = -sp[..., None] * fwd0 + cp[..., None] * up0
    right = cr[..., None] * right0 - sr[..., None] * up1  # roll about the optical axis
    up = sr[..., None] * right0 + cr[..., None] * up1
    return np.stack([right, -up, fwd], axis=-1)


def attitude_from_world_from_cam(r) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(heading in [0, 2 pi), pitch, roll) of ENU-from-camera rotation(s) (..., 3, 3).

    Heading is the azimuth of the optical axis projected onto the horizontal plane; pitch its
    elevation; roll the angle the right axis dips below the horizontal plane, measured about the
    optical axis. Inverse of :func:`world_from_cam` for |pitch| < pi/2.
    """
    m = np.asarray(r, dtype=np.float64)
    fwd = m[..., :, 2]
    right_up = m[..., 2, 0]
    up_up = -m[..., 2, 1]  # the camera's up is its -y
    heading = wrap_2pi(np.arctan2(fwd[..., 0], fwd[..., 1]))
    pitch = np.arctan2(fwd[..., 2], np.hypot(fwd[..., 0], fwd[..., 1]))
    roll = np.arctan2(-right_up, up_up)
    return heading, pitch, roll


def world_from_cam_of_imu(q_world_from_imu, cam_from_imu, enu_from_sensor_world=None) -> np.ndarray:
    """ENU-from-camera rotation for an IMU orientation quaternion (sensor world from IMU)."""
    r = rotation_from_quat(q_world_from_imu) @ np.asarray(cam_from_imu, dtype=np.float64).T
    if enu_from_sensor_world is not None:
        r = np.asarray(enu_from_sensor_world, dtype=np.float64) @ r
    return r


def magnetic_to_true(heading_rad: float, declination_rad: float) -> float:
    """True heading from a magnetic one: declination is east-positive (true = magnetic + declination)."""
    return float(wrap_2pi(heading_rad + declination_rad))


def gravity_mismatch_rad(q_world_from_imu, accel_imu, enu_from_sensor_world=None) -> float:
    """Angle between "up" as the rotation vector sees it in the IMU frame and the accelerometer's
    reading (at rest an accelerometer measures +g along up). Near 0 when the rotation vector's
    world frame has z up and shares the accelerometer's axes; near pi for a z-down (NED) world."""
    r = rotation_from_quat(q_world_from_imu)
    if enu_from_sensor_world is not None:
        r = np.asarray(enu_from_sensor_world, dtype=np.float64) @ r
    up_imu = r.T @ np.array([0.0, 0.0, 1.0])
    a = np.asarray(accel_imu, dtype=np.float64)
    n = float(np.linalg.norm(a))
    if n < 1e-9:
        return math.nan
    return float(math.acos(max(-1.0, min(1.0, float(up_imu @ a) / n))))


# ---------------------------------------------------------------------------------------------
# IMU types and modes
# ---------------------------------------------------------------------------------------------


class ImuMode(enum.StrEnum):
    """Where the heading comes from."""

    ROTATION_VECTOR = "rotation_vector"  # on-chip fusion with the magnetometer: magnetic north
    GAME_ROTATION_VECTOR = "game_rotation_vector"  # on-chip fusion without it: relative
    GYRO = "gyro"  # host-side gyro integration (IMUs without fusion): relative


@dataclass(frozen=True)
class ImuCaps:
    rotation_vector: bool  # on-chip fusion with a magnetometer
    game_rotation_vector: bool  # on-chip fusion without one


# What DepthAI's getConnectedIMU() names. BNO08x: 9-axis sensor hub with fusion; BMI270: 6-axis,
# no fusion; LSM6DSV (RVC4): game rotation vector on chip, no magnetometer in the chip itself.
IMU_CAPS = {
    "BNO080": ImuCaps(True, True),
    "BNO085": ImuCaps(True, True),
    "BNO086": ImuCaps(True, True),
    "BNO08X": ImuCaps(True, True),
    "BMI270": ImuCaps(False, False),
    "LSM6DSV": ImuCaps(False, True),
}
_NO_IMU = ("", "NONE", "NO_IMU", "UNKNOWN_NONE")
WANTS = ("auto", "rotation_vector", "game_rotation_vector", "gyro", "none")


def imu_caps(imu_name: str) -> ImuCaps | None:
    """Capabilities of an IMU by the name DepthAI reports; None when there is no IMU. An unknown
    name is treated as a plain accelerometer + gyroscope (no fusion), which every IMU offers."""
    name = (imu_name or "").strip().upper()
    if name in _NO_IMU:
        return None
    return IMU_CAPS.get(name, ImuCaps(False, False))


def choose_imu_mode(imu_name: str, want: str = "auto") -> ImuMode | None:
    """The heading source for an IMU (``device.getConnectedIMU()``) and a wish.

    ``auto``: the rotation vector when the chip has fusion with a magnetometer, else its game
    rotation vector, else gyro integration. ``none`` or no IMU: None (frames carry no heading).
    Asking for a fusion output the chip does not have is a ValidationError saying what to use.
    """
    want = (want or "auto").strip().lower()
    if want not in WANTS:
        raise ValidationError(f"imu_mode: expected one of {', '.join(WANTS)}, got {want!r}")
    caps = imu_caps(imu_name)
    if want == "none" or caps is None:
        return None
    if want == "auto":
        if caps.rotation_vector:
            return ImuMode.ROTATION_VECTOR
        return ImuMode.GAME_ROTATION_VECTOR if caps.game_rotation_vector else ImuMode.GYRO
    mode = ImuMode(want)
    has = {ImuMode.ROTATION_VECTOR: caps.rotation_vector, ImuMode.GAME_ROTATION_VECTOR: caps.game_rotation_vector}
    if not has.get(mode, True):
        raise ValidationError(
            f"imu_mode {want}: the {imu_name} IMU has no on-chip {want.replace('_', ' ')}; "
            "use imu_mode 'gyro' or 'auto'"
        )
    return mode


def imu_sensors(mode: ImuMode, imu_name: str) -> tuple[str, ...]:
    """Names of the ``dai.IMUSensor`` outputs a mode needs. The accelerometer gives gravity: the
    tilt for gyro integration, and a check of the rotation vector's frame in the fusion modes."""
    if mode is ImuMode.ROTATION_VECTOR:
        return ("ROTATION_VECTOR", "ACCELEROMETER")
    if mode is ImuMode.GAME_ROTATION_VECTOR:
        return ("GAME_ROTATION_VECTOR", "ACCELEROMETER")
    if (imu_name or "").strip().upper() == "BMI270":
        return ("GYROSCOPE_RAW", "ACCELEROMETER_RAW")  # what DepthAI offers for the BMI270 (SI units)
    return ("GYROSCOPE_CALIBRATED", "ACCELEROMETER")


def heading_ref_for(mode: ImuMode, declination_rad: float | None) -> HeadingRef:
    """The reference of the headings a mode gives: true north needs a magnetometer and a declination."""
    if mode is ImuMode.ROTATION_VECTOR:
        return HeadingRef.MAGNETIC if declination_rad is None else HeadingRef.TRUE
    return HeadingRef.RELATIVE


def cam_from_imu_default(product_name: str) -> tuple[np.ndarray, str]:
    """The documented IMU mounting for a product (``readCalibration().getEepromData().productName``
    or ``device.getProductName()``) and where it came from, for when the calibration has none."""
    key = (product_name or "").strip().upper()
    if key in CAM_FROM_IMU_BY_PRODUCT:
        return CAM_FROM_IMU_BY_PRODUCT[key].copy(), f"default for {key}"
    return CAM_FROM_IMU_DEFAULT.copy(), f"default (OAK-D-PRO layout; product {product_name!r} not in the table)"


# ---------------------------------------------------------------------------------------------
# Orientation buffer
# ---------------------------------------------------------------------------------------------


class OrientationBuffer:
    """IMU orientations (monotonic time, quaternion), oldest first, interpolated by slerp.

    Bounded two ways: samples older than ``history_s`` before the newest are pruned, and at most
    ``capacity`` are kept (the oldest goes, counted in ``overflow``). A sample not newer than the
    newest is dropped (``out_of_order``). Lookups never extrapolate: a time before the oldest
    sample is ``too_old``, after the newest ``imu_pending`` (its reports may still be on the
    way), and between two samples further apart than ``max_gap_s`` ``imu_gap``.
    """

    def __init__(self, history_s: float = 2.0, capacity: int = 4096, max_gap_s: float = 0.1) -> None:
        if not (history_s > 0 and capacity >= 2 and max_gap_s > 0):
            raise ValidationError(
                f"OrientationBuffer: expected history_s > 0, capacity >= 2, max_gap_s > 0, "
                f"got {history_s}, {capacity}, {max_gap_s}"
            )
        self.history_s = float(history_s)
        self.max_gap_s = float(max_gap_s)
        self._t: deque[float] = deque(maxlen=capacity)
        self._q: deque[np.ndarray] = deque(maxlen=capacity)
        self.counts = {"added": 0, "out_of_order": 0, "overflow": 0}

    def __len__(self) -> int:
        return len(self._t)

    @property
    def newest_t(self) -> float | None:
        return self._t[-1] if self._t else None

    @property
    def oldest_t(self) -> float | None:
        return self._t[0] if self._t else None

    def add(self, t_s: float, q_wxyz) -> bool:
        t_s = float(t_s)
        if not math.isfinite(t_s) or (self._t and t_s <= self._t[-1]):
            self.counts["out_of_order"] += 1
            return False
        if len(self._t) == self._t.maxlen:
            self.counts["overflow"] += 1
        self._t.append(t_s)
        self._q.append(quat_normalize(q_wxyz))
        self.counts["added"] += 1
        while self._t and self._t[0] < t_s - self.history_s:
            self._t.popleft()
            self._q.popleft()
        return True

    def clear(self) -> None:
        self._t.clear()
        self._q.clear()

    def at(self, t_s: float) -> tuple[np.ndarray | None, str]:
        """(quaternion, "ok") at ``t_s``, or (None, reason)."""
        if not self._t:
            return None, NO_IMU_YET
        if t_s < self._t[0]:
            return None, TOO_OLD
        if t_s > self._t[-1]:
            return None, IMU_PENDING
        ts = self._t
        lo, hi = 0, len(ts) - 1  # binary search for ts[i] <= t_s <= ts[i + 1]
        while hi - lo > 1:
            mid = (lo + hi) // 2
            if ts[mid] <= t_s:
                lo = mid
            else:
                hi = mid
        if ts[lo] == t_s:
            return self._q[lo].copy(), OK
        if ts[hi] == t_s:
            return self._q[hi].copy(), OK
        if ts[hi] - ts[lo] > self.max_gap_s:
            return None, IMU_GAP
        f = (t_s - ts[lo]) / (ts[hi] - ts[lo])
        return slerp(self._q[lo], self._q[hi], f), OK


# ---------------------------------------------------------------------------------------------
# Gyro integration (IMUs without fusion)
# ---------------------------------------------------------------------------------------------

# The gyro bias, learned while the IMU is certainly still (docs/oak.md, "Gyro bias"). A BMI270's
# zero-rate offset is +-0.5 deg/s typical (datasheet, 1 sigma): 30 deg of heading a minute.
GYRO_BIAS_STILL_S = 2.0  # how long the IMU must be quiet before its mean rate is taken for the bias
_BIAS_BLOCK_S = 0.25  # the quiet test's time step; the newest block is never learned from (below)
# The quiet test low-passes rates and accelerations (two first-order stages at 1 Hz): an idling
# engine's 20-40 Hz vibration (a few deg/s, zero mean) is cut 400-1600 fold, the body's pitching
# and heaving on a road (1-3 Hz) hardly at all.
_STILL_LOWPASS_HZ = 1.0
# Quiet: over GYRO_BIAS_STILL_S the low-passed rate moves by at most this on every axis (standing
# with the engine idling, simulated: at most 0.07 deg/s) and the low-passed acceleration by at most
# STILL_ACCEL_SPREAD_M_S2 (at most 0.011); its mean is within STILL_GRAVITY_TOL of g.
STILL_RATE_SPREAD_RAD_S = math.radians(0.1)
STILL_ACCEL_SPREAD_M_S2 = 0.02
STILL_GRAVITY_TOL = 0.03
# A quiet stretch whose mean rate is larger is not a bias (the datasheet's offset is 0.5 deg/s at
# 1 sigma, this is 3 sigma) but, most likely, a long smooth curve: refused, and counted.
MAX_GYRO_BIAS_RAD_S = math.radians(1.5)


class GyroBiasEstimator:
    """The gyro's bias (rad/s, IMU axes): its mean rate over a stretch in which the IMU is still.

    Still means quiet for at least ``still_s``: the rates and accelerations, low-passed, each stay
    within a narrow band (an idling engine's fast vibration passes, a body pitching on its springs
    or a speed change does not), and the acceleration is g. Each quiet stretch's mean rate (all
    but its newest ``_BIAS_BLOCK_S``, where a start may hide behind the low-pass' delay) becomes
    the bias, unless it exceeds ``max_bias_rad_s``. A constant turn on a road so smooth that
    nothing else moves is as quiet as standing: it is learned as a bias when below that limit.

    Pure and cheap: a few vector operations a report; the times are the reports'.
    """

    def __init__(self, *, still_s: float = GYRO_BIAS_STILL_S, max_bias_rad_s: float = MAX_GYRO_BIAS_RAD_S,
                 rate_spread_rad_s: float = STILL_RATE_SPREAD_RAD_S,
                 accel_spread_m_s2: float = STILL_ACCEL_SPREAD_M_S2) -> None:
        self.n_blocks = max(2, int(round(still_s / _BIAS_BLOCK_S)))
        self.max_bias_rad_s = float(max_bias_rad_s)
        self._spread = np.array([rate_spread_rad_s] * 3 + [accel_spread_m_s2] * 3)
        self.bias_rad_s = np.zeros(3)
        self.learned = False  # a bias has been learned (bias_rad_s is no longer zero by default)
        self.counts = {"gyro_bias_learned": 0, "gyro_bias_refused": 0}
        self.restart()

    def restart(self) -> None:
        """Forget the stretch in progress (a gap in the reports, one without an accelerometer):
        quiet must be seen again from here. The learned bias stays."""
        self._t: float | None = None
        self._lp1: np.ndarray | None = None
        self._lp2: np.ndarray | None = None
        self._block: list | None = None  # [t0, n, sum_w, sum_a, low, high]
        self._blocks: deque[list] = deque(maxlen=self.n_blocks)
        self._stretch: list | None = None  # [n, sum_w, learned, refused]

    def take_over(self, other: GyroBiasEstimator) -> None:
        """The bias ``other`` learned, if any, with its counts: the same chip in a new session."""
        if other.learned:
            self.bias_rad_s, self.learned = other.bias_rad_s.copy(), True
            self.counts.update(other.counts)

    def add(self, t_s: float, gyro_imu_rad_s: np.ndarray, accel_imu_m_s2) -> bool:
        """One report (in time order); True when it changed the bias."""
        if accel_imu_m_s2 is None:
            self.restart()  # stillness cannot be checked without the accelerometer
            return False
        a = np.asarray(accel_imu_m_s2, dtype=np.float64)
        x = np.concatenate([gyro_imu_rad_s, a])
        if not np.all(np.isfinite(x)):
            self.restart()
            return False
        if self._lp1 is None or self._lp2 is None or self._t is None:
            self._lp1, self._lp2 = x.copy(), x.copy()
        else:
            k = 1.0 - math.exp(-2.0 * math.pi * _STILL_LOWPASS_HZ * (t_s - self._t))
            self._lp1 += k * (x - self._lp1)
            self._lp2 += k * (self._lp1 - self._lp2)
        self._t = t_s
        b = self._block
        if b is None:
            self._block = [t_s, 1, x[:3].copy(), a.copy(), self._lp2.copy(), self._lp2.copy()]
            return False
        b[1] += 1
        b[2] += x[:3]
        b[3] += a
        np.minimum(b[4], self._lp2, out=b[4])
        np.maximum(b[5], self._lp2, out=b[5])
        if t_s - b[0] < _BIAS_BLOCK_S:
            return False
        self._blocks.append(b)
        self._block = None
        return self._judge()

    def _judge(self) -> bool:
        blocks = self._blocks
        if len(blocks) < self.n_blocks:
            return False
        low = np.min([b[4] for b in blocks], axis=0)
        high = np.max([b[5] for b in blocks], axis=0)
        n = sum(b[1] for b in blocks)
        g = float(np.linalg.norm(sum(b[3] for b in blocks) / n))
        if np.any(high - low > self._spread) or abs(g / GRAVITY_M_S2 - 1.0) > STILL_GRAVITY_TOL:
            self._stretch = None  # moving (or shaken): the stretch, if any, ends here
            return False
        st = self._stretch
        if st is None:  # a new quiet stretch: every block but the newest
            older = list(blocks)[:-1]
            st = self._stretch = [sum(b[1] for b in older), sum(b[2] for b in older), False, False]
        else:
            st[0] += blocks[-2][1]
            st[1] += blocks[-2][2]
        mean = st[1] / st[0]
        if float(np.linalg.norm(mean)) > self.max_bias_rad_s:
            if not st[3]:
                st[3] = True
                self.counts["gyro_bias_refused"] += 1
            return False
        if not st[2]:
            st[2] = True
            self.counts["gyro_bias_learned"] += 1
        self.bias_rad_s = mean
        self.learned = True
        return True


class GyroIntegrator:
    """Orientation (world from IMU) from gyro rates, with the tilt held by the accelerometer.

    The world frame is z up and its "north" is the camera's heading at the first sample, so the
    headings it gives are relative to the start. Each step integrates the mean of two consecutive
    rates; a complementary (Mahony proportional) term pulls the estimated up towards the
    accelerometer's while its magnitude is within 10% of g, so the tilt does not drift. That term
    cannot correct the heading: nothing in a 6-axis IMU can, and gyro bias makes it drift.

    It starts (and starts again after a gap) only at a report that comes with an accelerometer
    reading: without one there is no up to start from, and a guessed one can be half a turn off
    (a camera mounted upside down), where the tilt term is zero and never pulls it back.

    With ``gyro_bias`` (the default) a :class:`GyroBiasEstimator` learns the gyro's bias whenever
    the IMU stands still and it is subtracted from every rate after; ``counts`` say how often
    (``gyro_bias_learned``, ``gyro_bias_refused``), and the bias (``gyro_bias_deg_s``, its size)
    and the heading drift it caused (``gyro_bias_heading_deg_s``, clockwise positive), in deg/s.
    """

    def __init__(self, cam_from_imu, *, tilt_gain: float = 0.5, max_step_s: float = 0.1,
                 gyro_bias: bool = True) -> None:
        c = validate_rotation("cam_from_imu", cam_from_imu)
        self._forward_imu = c.T @ np.array([0.0, 0.0, 1.0])  # optical axis in IMU axes
        self.tilt_gain = float(tilt_gain)
        self.max_step_s = float(max_step_s)
        self._q: np.ndarray | None = None
        self._t: float | None = None
        self._w: np.ndarray | None = None
        self.bias = GyroBiasEstimator() if gyro_bias else None
        self.counts: dict[str, float] = {"gyro_steps": 0, "gyro_gaps": 0, "gyro_out_of_order": 0,
                                         "gyro_no_gravity": 0}
        if self.bias is not None:
            self.counts.update(self.bias.counts, gyro_bias_deg_s=0.0, gyro_bias_heading_deg_s=0.0)

    @property
    def initialized(self) -> bool:
        return self._q is not None

    def _initial(self, up_imu: np.ndarray) -> np.ndarray:
        up = up_imu / np.linalg.norm(up_imu)
        fwd = self._forward_imu - (self._forward_imu @ up) * up
        if np.linalg.norm(fwd) < 1e-3:  # camera looking straight up or down: any heading will do
            fwd = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
        north = fwd / np.linalg.norm(fwd)
        east = np.cross(north, up)
        imu_from_world = np.stack([east, north, up], axis=-1)  # columns: world axes in IMU axes
        return quat_from_rotation(imu_from_world.T)

    def update(self, t_s: float, gyro_imu_rad_s, accel_imu=None) -> np.ndarray | None:
        """Advance to ``t_s`` with the rate measured then; returns world-from-IMU, or None for a
        sample that is not newer than the previous one, or that would start the integration
        (the first, or the first after a gap) without an accelerometer reading to give up."""
        w = np.asarray(gyro_imu_rad_s, dtype=np.float64)
        if self._q is not None:
            assert self._t is not None and self._w is not None  # set with _q
            dt = float(t_s) - self._t
            if not dt > 0:
                self.counts["gyro_out_of_order"] += 1
                return None
            if dt <= self.max_step_s:
                return self._step(float(t_s), dt, self._unbiased(float(t_s), w, accel_imu), accel_imu)
            # Reports lost: the rotation meanwhile is unknown, and integrating across the gap would
            # invent one (the mean of the rates at its ends times its length). Start again from the
            # accelerometer, with a new zero; the tracker gives its headings a new epoch.
            self.counts["gyro_gaps"] += 1
            self._q = self._t = self._w = None
            if self.bias is not None:
                self.bias.restart()  # the same chip: its bias is kept, but quiet is seen anew
        up = None if accel_imu is None else np.asarray(accel_imu, dtype=np.float64)
        if up is None or not np.all(np.isfinite(up)) or float(np.linalg.norm(up)) < 1e-3:
            self.counts["gyro_no_gravity"] += 1  # no up to start from: wait for the accelerometer
            return None
        self._q, self._t = self._initial(up), float(t_s)
        self._w = self._unbiased(float(t_s), w, up)
        return self._q.copy()

    def keep_bias(self, other: GyroIntegrator) -> None:
        """Go on subtracting the bias ``other`` learned (the same chip, a new session), until a
        stop learns it again."""
        if self.bias is None or other.bias is None or not other.bias.learned:
            return
        self.bias.take_over(other.bias)
        self.counts.update({k: v for k, v in other.counts.items() if k.startswith("gyro_bias_")})

    def _unbiased(self, t_s: float, w: np.ndarray, accel_imu) -> np.ndarray:
        """The rate less the bias learned so far (this report included)."""
        est = self.bias
        if est is None:
            return w
        if est.add(t_s, w, accel_imu):
            self.counts.update(est.counts)
            b = est.bias_rad_s
            self.counts["gyro_bias_deg_s"] = round(math.degrees(float(np.linalg.norm(b))), 4)
            if self._q is not None:
                # The part about up turned the heading: anticlockwise about up is a falling heading.
                up_imu = rotation_from_quat(self._q).T @ np.array([0.0, 0.0, 1.0])
                self.counts["gyro_bias_heading_deg_s"] = round(-math.degrees(float(b @ up_imu)), 4)
        elif est.counts["gyro_bias_refused"] != self.counts["gyro_bias_refused"]:
            self.counts.update(est.counts)
        return w - est.bias_rad_s

    def _step(self, t_s: float, dt: float, w: np.ndarray, accel_imu) -> np.ndarray:
        assert self._q is not None and self._w is not None
        rate = 0.5 * (w + self._w)
        if accel_imu is not None and self.tilt_gain > 0:
            a = np.asarray(accel_imu, dtype=np.float64)
            n = float(np.linalg.norm(a))
            if abs(n - GRAVITY_M_S2) < 0.1 * GRAVITY_M_S2:  # not while accelerating hard
                up_est = rotation_from_quat(self._q).T @ np.array([0.0, 0.0, 1.0])
                rate = rate + self.tilt_gain * np.cross(a / n, up_est)
        self._q = quat_normalize(quat_multiply(self._q, quat_from_rotvec(rate * dt)))
        self._t, self._w = t_s, w
        self.counts["gyro_steps"] += 1
        return self._q.copy()


# ---------------------------------------------------------------------------------------------
# The tracker: reports in, attitude at a time out
# ---------------------------------------------------------------------------------------------


class AttitudeTracker:
    """IMU reports in, the camera's :class:`~rig.types.Attitude` at any recent time out.

    - ``rotation_vector``: quaternions referenced to magnetic north; the heading is magnetic, or
      true when ``declination_rad`` (east positive) is given. Reports whose own accuracy estimate
      is worse than ``max_accuracy_rad`` (the BNO08x says pi until its magnetometer is
      calibrated) are not used (``inaccurate``).
    - ``game_rotation_vector`` and ``gyro``: relative; the heading is zeroed at the first report,
      so 0 is the optical axis' direction when the tracker started.

    ``cam_from_imu`` maps IMU axes to the colour camera's; ``sensor_world`` names the frame the
    rotation vector is referenced to (``enu`` per the BNO08x datasheet).
    """

    def __init__(
        self,
        mode: ImuMode,
        cam_from_imu,
        *,
        declination_rad: float | None = None,
        sensor_world: str = "enu",
        history_s: float = 2.0,
        capacity: int = 4096,
        max_gap_s: float = 0.1,
        max_accuracy_rad: float = math.radians(45.0),
        tilt_gain: float = 0.5,
        gyro_bias: bool = True,
        epoch: int = 0,
    ) -> None:
        self.mode = ImuMode(mode)
        self.cam_from_imu = validate_rotation("cam_from_imu", cam_from_imu)
        if sensor_world not in ENU_FROM_SENSOR_WORLD:
            raise ValidationError(
                f"sensor_world: expected one of {', '.join(ENU_FROM_SENSOR_WORLD)}, got {sensor_world!r}"
            )
        self.sensor_world = sensor_world
        self._enu_from_sensor = ENU_FROM_SENSOR_WORLD[sensor_world] if self.mode is not ImuMode.GYRO else np.eye(3)
        if declination_rad is not None and not (math.isfinite(declination_rad) and abs(declination_rad) <= math.pi):
            raise ValidationError(f"declination: expected within [-180, 180] deg, got {math.degrees(declination_rad)}")
        # A declination turns magnetic into true; it means nothing for a relative heading.
        self.declination_rad = declination_rad if self.mode is ImuMode.ROTATION_VECTOR else None
        self.heading_ref = heading_ref_for(self.mode, self.declination_rad)
        # Carried by every Attitude. A relative heading's zero is this tracker's first sample, so
        # a new tracker (a reconnected device) must come with a new epoch; absolute ones keep 0.
        self.epoch = int(epoch) if self.heading_ref is HeadingRef.RELATIVE else 0
        self.max_accuracy_rad = float(max_accuracy_rad)
        self.buffer = OrientationBuffer(history_s=history_s, capacity=capacity, max_gap_s=max_gap_s)
        # The same gap for both: a gap the buffer would interpolate across is no reason to restart
        # the integration (with a new zero and epoch), nor the reverse.
        self.gyro = (GyroIntegrator(self.cam_from_imu, tilt_gain=tilt_gain, max_step_s=max_gap_s,
                                    gyro_bias=gyro_bias)
                     if self.mode is ImuMode.GYRO else None)
        self._accel: tuple[float, np.ndarray] | None = None
        self._zero_rad: float | None = None
        self.gravity_mismatch_rad: float | None = None  # smoothed check, at rest only (fusion modes)
        # Stretches [first_t, last_t] of rotation vectors refused as inaccurate, oldest first: a
        # frame among them has no heading because of them, and waiting for more reports is no use.
        self._inaccurate_runs: deque[list[float]] = deque(maxlen=_MAX_INACCURATE_RUNS)
        self._in_inaccurate_run = False
        self.counts = {"rotation_vectors": 0, "gyro_reports": 0, "accel_reports": 0, "inaccurate": 0,
                       "ignored": 0}

    def _heading_of(self, q) -> float:
        r = world_from_cam_of_imu(q, self.cam_from_imu, self._enu_from_sensor)
        return float(attitude_from_world_from_cam(r)[0])

    def _store(self, t_s: float, q) -> bool:
        if not self.buffer.add(t_s, q):
            return False
        if self._zero_rad is None:
            self._zero_rad = self._heading_of(q) if self.heading_ref is HeadingRef.RELATIVE else 0.0
        return True

    def add_rotation_vector(self, t_s: float, q_wxyz, accuracy_rad: float = 0.0) -> bool:
        """A rotation vector or game rotation vector report; True when it was buffered."""
        if self.mode is ImuMode.GYRO:
            self.counts["ignored"] += 1
            return False
        self.counts["rotation_vectors"] += 1
        if self.mode is ImuMode.ROTATION_VECTOR and accuracy_rad > self.max_accuracy_rad:
            self.counts["inaccurate"] += 1
            self._note_inaccurate(float(t_s))
            return False
        q = quat_normalize(q_wxyz)
        if self._accel is not None and abs(self._accel[0] - t_s) < 0.05:
            a = self._accel[1]
            if abs(float(np.linalg.norm(a)) - GRAVITY_M_S2) < 0.05 * GRAVITY_M_S2:  # only near rest
                g = gravity_mismatch_rad(q, a, self._enu_from_sensor)
                # Smoothed: one jolt must not look like a wrong frame; a wrong frame is there always.
                old = self.gravity_mismatch_rad
                self.gravity_mismatch_rad = g if old is None else old + _MISMATCH_SMOOTHING * (g - old)
        stored = self._store(t_s, q)
        if stored:
            self._in_inaccurate_run = False
        return stored

    def _note_inaccurate(self, t_s: float) -> None:
        runs = self._inaccurate_runs
        if self._in_inaccurate_run and runs and t_s > runs[-1][1]:
            runs[-1][1] = t_s
        elif not runs or t_s > runs[-1][1]:
            runs.append([t_s, t_s])
        self._in_inaccurate_run = True
        while runs and runs[0][1] < t_s - self.buffer.history_s:
            runs.popleft()

    def _among_inaccurate(self, t_s: float) -> bool:
        """Whether ``t_s`` lies inside a stretch of refused reports, or up to max_gap_s before one."""
        return any(first - self.buffer.max_gap_s <= t_s <= last for first, last in self._inaccurate_runs)

    def add_accelerometer(self, t_s: float, accel_imu_m_s2) -> None:
        self.counts["accel_reports"] += 1
        self._accel = (float(t_s), np.asarray(accel_imu_m_s2, dtype=np.float64))

    def add_gyro(self, t_s: float, gyro_imu_rad_s) -> bool:
        """A gyroscope report (rad/s, IMU axes); True when it advanced the integrated orientation."""
        if self.gyro is None:
            self.counts["ignored"] += 1
            return False
        self.counts["gyro_reports"] += 1
        accel = None
        if self._accel is not None and abs(self._accel[0] - t_s) < 0.1:
            accel = self._accel[1]
        gaps = self.gyro.counts["gyro_gaps"]
        q = self.gyro.update(t_s, gyro_imu_rad_s, accel)
        if self.gyro.counts["gyro_gaps"] != gaps:
            self._new_zero()  # the integrator started again after a gap in its reports
        return q is not None and self._store(t_s, q)

    def attitude_at(self, t_s: float) -> tuple[Attitude | None, str]:
        """The camera's attitude at monotonic ``t_s`` (interpolated, never extrapolated), or
        (None, reason): ``no_imu_yet``, ``too_old``, ``imu_pending``, ``imu_gap``, ``vertical``, or
        ``inaccurate`` where rotation vectors came but were refused as too inaccurate."""
        q, reason = self.buffer.at(t_s)
        if q is None:
            if reason in (NO_IMU_YET, IMU_PENDING, IMU_GAP) and self._among_inaccurate(t_s):
                return None, INACCURATE  # the IMU reported there, too inaccurately to use
            return None, reason
        r = world_from_cam_of_imu(q, self.cam_from_imu, self._enu_from_sensor)
        if math.hypot(r[0, 2], r[1, 2]) < _VERTICAL_SIN:
            return None, VERTICAL  # the optical axis has no horizontal direction to speak of
        heading, pitch, roll = (float(a) for a in attitude_from_world_from_cam(r))
        heading -= self._zero_rad or 0.0
        if self.declination_rad is not None:
            heading = magnetic_to_true(heading, self.declination_rad)
        return Attitude(heading, self.heading_ref, pitch, roll, epoch=self.epoch), OK

    def reset(self) -> None:
        """Forget everything (a new device session): relative headings restart from a new zero,
        in a new epoch."""
        self._accel = None
        self._inaccurate_runs.clear()
        self._in_inaccurate_run = False
        self._new_zero()
        if self.gyro is not None:
            g = self.gyro
            self.gyro = GyroIntegrator(self.cam_from_imu, tilt_gain=g.tilt_gain, max_step_s=g.max_step_s,
                                       gyro_bias=g.bias is not None)
            self.gyro.keep_bias(g)  # a new session of the same chip: its bias is as it was

    def keep_gyro_bias(self, previous: AttitudeTracker) -> None:
        """Take the gyro bias ``previous`` (the last session's tracker of the same device) learned:
        a reconnect starts a new zero, but the chip's bias is what it was."""
        if self.gyro is not None and previous.gyro is not None:
            self.gyro.keep_bias(previous.gyro)

    def _new_zero(self) -> None:
        """Orientations from here on have another zero: none before is kept to interpolate with,
        and a relative heading counts in the next epoch, so no window mixes the two zeros."""
        self.buffer.clear()
        self._zero_rad = None
        if self.heading_ref is HeadingRef.RELATIVE:
            self.epoch += 1
