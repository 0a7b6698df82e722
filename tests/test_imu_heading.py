"""The pure IMU attitude math (drivers/imu_heading.py): golden cases worked out by hand from the
Android/BNO08x rotation-vector definition and the OAK IMU mountings, round trips, scalar vs
batched, the interpolation buffer, gyro integration, declination and the mode choice.
docs/oak.md is the specification."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.imu_heading import (
    CAM_FROM_IMU_OAK_D,
    CAM_FROM_IMU_OAK_D_PRO,
    ENU_FROM_SENSOR_WORLD,
    IMU_GAP,
    IMU_PENDING,
    NO_IMU_YET,
    OK,
    TOO_OLD,
    VERTICAL,
    AttitudeTracker,
    GyroIntegrator,
    ImuMode,
    OrientationBuffer,
    attitude_from_world_from_cam,
    cam_from_imu_default,
    choose_imu_mode,
    gravity_mismatch_rad,
    heading_ref_for,
    imu_sensors,
    magnetic_to_true,
    quat_from_rotation,
    quat_multiply,
    rotation_from_quat,
    slerp,
    validate_rotation,
    world_from_cam,
    world_from_cam_of_imu,
)
from rig.errors import ValidationError
from rig.types import HeadingRef
from tests.tolerances import ANGLE_RAD_F64, DEG, EXACT_F64

# Tolerances of this file (one table): float64 trigonometry is exact to ~1e-9; the hand-made
# golden quaternions are printed to 5 decimals; gyro integration at 100 Hz is a discretisation.
GOLDEN_Q_RAD = 1e-4
GYRO_RAD = 0.05 * DEG
TILT_RAD = 0.2 * DEG

R2 = math.sqrt(0.5)


def deg(x) -> float:
    return math.degrees(float(x))


def ang_diff(a, b) -> float:
    return abs((float(a) - float(b) + math.pi) % (2 * math.pi) - math.pi)


# --- golden attitudes of the camera --------------------------------------------------------


@pytest.mark.parametrize(
    ("h_deg", "p_deg", "r_deg", "fwd", "right"),
    [
        (0, 0, 0, (0, 1, 0), (1, 0, 0)),  # level, looking north: right is east
        (90, 0, 0, (1, 0, 0), (0, -1, 0)),  # looking east: right is south
        (180, 0, 0, (0, -1, 0), (-1, 0, 0)),
        (270, 0, 0, (-1, 0, 0), (0, 1, 0)),
        (0, 30, 0, (0, math.cos(math.radians(30)), 0.5), (1, 0, 0)),  # nose up: forward rises
        (0, 0, 30, (0, 1, 0), (math.cos(math.radians(30)), 0, -0.5)),  # right side down
    ],
)
def test_world_from_cam_golden_axes(h_deg, p_deg, r_deg, fwd, right):
    r = world_from_cam(math.radians(h_deg), math.radians(p_deg), math.radians(r_deg))
    np.testing.assert_allclose(r[:, 2], fwd, atol=EXACT_F64)
    np.testing.assert_allclose(r[:, 0], right, atol=EXACT_F64)
    h, p, rr = attitude_from_world_from_cam(r)
    assert ang_diff(h, math.radians(h_deg)) < ANGLE_RAD_F64
    assert abs(p - math.radians(p_deg)) < ANGLE_RAD_F64
    assert abs(rr - math.radians(r_deg)) < ANGLE_RAD_F64


def test_world_from_cam_matches_the_synthetic_renderer():
    """The renderer (replay/synthetic/render.py) defines the project's attitude convention."""
    render = pytest.importorskip("replay.synthetic.render")
    rng = np.random.default_rng(0)
    for h, p, r in zip(rng.uniform(0, 2 * np.pi, 20), rng.uniform(-1.2, 1.2, 20), rng.uniform(-1, 1, 20),
                       strict=True):
        np.testing.assert_allclose(world_from_cam(h, p, r), render.world_from_cam(h, p, r), atol=EXACT_F64)


def test_attitude_round_trip_and_batched_equals_scalar():
    rng = np.random.default_rng(1)
    h = rng.uniform(0, 2 * np.pi, 50)
    p = rng.uniform(-1.5, 1.5, 50)
    r = rng.uniform(-3.0, 3.0, 50)
    mats = world_from_cam(h, p, r)
    hb, pb, rb = attitude_from_world_from_cam(mats)
    np.testing.assert_allclose(np.cos(hb - h), 1.0, atol=EXACT_F64)
    np.testing.assert_allclose(pb, p, atol=ANGLE_RAD_F64)
    np.testing.assert_allclose(rb, r, atol=ANGLE_RAD_F64)
    for k in range(len(h)):
        np.testing.assert_allclose(world_from_cam(h[k], p[k], r[k]), mats[k], atol=EXACT_F64)
        hs, ps, rs = attitude_from_world_from_cam(mats[k])
        assert (hs, ps, rs) == (hb[k], pb[k], rb[k])


def test_quaternion_round_trip_and_batched():
    rng = np.random.default_rng(2)
    qs = rng.normal(size=(40, 4))
    qs /= np.linalg.norm(qs, axis=1, keepdims=True)
    mats = rotation_from_quat(qs)
    for q, m in zip(qs, mats, strict=True):
        np.testing.assert_allclose(rotation_from_quat(q), m, atol=EXACT_F64)
        np.testing.assert_allclose(m @ m.T, np.eye(3), atol=EXACT_F64)
        q2 = quat_from_rotation(m)
        assert abs(abs(q2 @ q) - 1.0) < 1e-12  # the same rotation (q or -q)
    # Hamilton product composes rotations: R(a (x) b) = R(a) R(b)
    a, b = qs[0], qs[1]
    np.testing.assert_allclose(rotation_from_quat(quat_multiply(a, b)), mats[0] @ mats[1], atol=EXACT_F64)


def test_quat_from_rotation_half_turns_and_the_positive_real_part():
    """Half turns (trace -1) need Shepperd's other branches; whichever branch computes it, the
    result is the one of q and -q with w >= 0, as documented."""
    c100, s100 = math.cos(math.radians(100.0)), math.sin(math.radians(100.0))
    cases = [
        (0.0, 1.0, 0.0, 0.0),  # half turn about x: R = diag(1, -1, -1)
        (0.0, 0.0, 1.0, 0.0),  # about y: diag(-1, 1, -1)
        (0.0, 0.0, 0.0, 1.0),  # about z: diag(-1, -1, 1)
        (0.1, 1e-7, math.sqrt(0.99), 0.0),  # 168.5 deg about y, a hair off: dividing by 4|x| loses digits
        (0.25, 0.6, 0.0, -0.75),  # 150 deg about an axis in the x-z plane: y = 0, never divide by 4|y|
        (-0.25, 0.6, 0.0, -0.75),
        (c100, s100, 0.0, 0.0),  # 200 deg about x: w = cos 100 deg < 0, so -q comes back
        (c100, 0.0, s100, 0.0),
        (c100, 0.0, 0.0, s100),
        (0.8, 0.0, 0.6, 0.0),  # 73.7 deg about y: the trace branch
    ]
    for q in cases:
        q = np.array(q) / np.linalg.norm(q)
        got = quat_from_rotation(rotation_from_quat(q))
        want = -q if q[0] < 0 else q
        if q[0] == 0.0:  # a half turn: q and -q both have w = 0, either will do
            want = want if got @ want > 0 else -want
        assert got[0] >= 0.0, q
        np.testing.assert_allclose(got, want, atol=EXACT_F64)


# --- golden IMU quaternions (worked by hand) ----------------------------------------------------
# A rotation vector q is sensor_world_from_imu with the world ENU (BNO08x = Android convention).
# OAK-D Pro mount: IMU x = camera down, y = camera right, z = camera backward.
#   Camera level, looking north: IMU x = (0,0,-1), y = east (1,0,0), z = south (0,-1,0).
#   R = [[0,1,0],[0,0,-1],[-1,0,0]]: trace 0, w = 1/2, x = (R32-R23)/4w = 1/2, y = (R13-R31)/4w = 1/2,
#   z = (R21-R12)/4w = -1/2.
#   Turned clockwise to look east: q_z(-90 deg) (x) q = (0, sqrt(1/2), 0, -sqrt(1/2)): a half turn about
#   (1,0,-1)/sqrt2, R = [[0,0,-1],[0,-1,0],[-1,0,0]]: IMU x down, y south (right of east), z west.
# OAK-D mount: IMU x = camera down, y = camera left, z = camera forward.
#   Looking north, nose up 30 deg: x = (0, 1/2, -0.866), y = (-1,0,0), z = (0, 0.866, 1/2):
#   trace 1/2, w = sqrt(1.5)/2 = 0.61237, x = -0.866/(4w) = -0.35355, y = 0.35355, z = 1.5/(4w) = 0.61237.

GOLDEN_RV = [
    # (name, cam_from_imu, (real, i, j, k), heading, pitch, roll) in degrees
    ("pro north level", CAM_FROM_IMU_OAK_D_PRO, (0.5, 0.5, 0.5, -0.5), 0.0, 0.0, 0.0),
    ("pro east level", CAM_FROM_IMU_OAK_D_PRO, (0.0, R2, 0.0, -R2), 90.0, 0.0, 0.0),
    ("oak-d north pitched up 30", CAM_FROM_IMU_OAK_D, (0.61237, -0.35355, 0.35355, 0.61237), 0.0, 30.0, 0.0),
]


@pytest.mark.parametrize(("name", "mount", "q", "h", "p", "r"), GOLDEN_RV, ids=[g[0] for g in GOLDEN_RV])
def test_rotation_vector_golden(name, mount, q, h, p, r):
    m = world_from_cam_of_imu(q, mount)
    hh, pp, rr = attitude_from_world_from_cam(m)
    assert ang_diff(hh, math.radians(h)) < GOLDEN_Q_RAD, (name, deg(hh))
    assert abs(pp - math.radians(p)) < GOLDEN_Q_RAD, (name, deg(pp))
    assert abs(rr - math.radians(r)) < GOLDEN_Q_RAD, (name, deg(rr))


# The compass points and a 10 deg pitch and roll, as a user checks a rig, worked by hand for the
# default (OAK-D-PRO) mount. q_north = (1/2, 1/2, 1/2, -1/2) (above). Turning the camera clockwise
# by h is q_z(-h) (x) q_north with q_z(-h) = (cos h/2, 0, 0, -sin h/2); with c, s = cos h/2, sin h/2:
#   q = (c - s, c + s, c - s, -(c + s)) / 2.
#   south (c = 0, s = 1): (-1/2, 1/2, -1/2, -1/2), the same rotation as (1/2, -1/2, 1/2, 1/2):
#     R = [[0,-1,0],[0,0,1],[-1,0,0]]: IMU x down, y west (right of south), z north (behind).
#   west (c = -s = -sqrt 1/2): (-sqrt 1/2, 0, -sqrt 1/2, 0) = (sqrt 1/2, 0, sqrt 1/2, 0), 90 deg
#     about north: IMU x down, y north (right of west), z east (behind).
# Nose up by 10 deg is a turn about the camera's right axis, east when it looks north: q_x(+10) (x)
# q_north with c, s = cos 5, sin 5 deg gives (c - s, c + s, c + s, -(c - s)) / 2 =
#   (0.4545195, 0.5416752, 0.5416752, -0.4545195): IMU x (down) = (0, sin 10, -cos 10).
# Right side down by 10 deg is a turn about the optical axis, north: q_y(+10) (x) q_north =
#   (c - s, c - s, c + s, -(c + s)) / 2 = (0.4545195, 0.4545195, 0.5416752, -0.5416752):
#   R[0, 0] = 1 - 2 (y^2 + z^2) = -sin 10 (IMU x, down, leans west as the right side dips east).
GOLDEN_USER = [
    # (name, (real, i, j, k), heading, pitch, roll) in degrees, OAK-D-PRO mount
    ("north", (0.5, 0.5, 0.5, -0.5), 0.0, 0.0, 0.0),
    ("east", (0.0, R2, 0.0, -R2), 90.0, 0.0, 0.0),
    ("south", (0.5, -0.5, 0.5, 0.5), 180.0, 0.0, 0.0),
    ("west", (R2, 0.0, R2, 0.0), 270.0, 0.0, 0.0),
    ("south as DepthAI may send it (-q)", (-0.5, 0.5, -0.5, -0.5), 180.0, 0.0, 0.0),
    ("north, nose up 10", (0.4545195, 0.5416752, 0.5416752, -0.4545195), 0.0, 10.0, 0.0),
    ("north, right side down 10", (0.4545195, 0.4545195, 0.5416752, -0.5416752), 0.0, 0.0, 10.0),
]


@pytest.mark.parametrize(("name", "q", "h", "p", "r"), GOLDEN_USER, ids=[g[0] for g in GOLDEN_USER])
def test_rotation_vector_compass_points_pitch_and_roll_through_the_tracker(name, q, h, p, r):
    """What `--heading oak-imu` reports for a level camera at each compass point and for a 10 deg
    pitch or roll, per docs/conventions.md (heading clockwise from north, pitch nose up, roll
    right side down); a declination of +5 deg (east) moves only the heading, by +5."""
    for decl_deg, ref in ((None, HeadingRef.MAGNETIC), (5.0, HeadingRef.TRUE)):
        decl = None if decl_deg is None else math.radians(decl_deg)
        tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, declination_rad=decl)
        assert tr.add_rotation_vector(2.0, q, accuracy_rad=0.05)
        att, reason = tr.attitude_at(2.0)
        assert reason == OK and att is not None and att.pitch_rad is not None and att.roll_rad is not None
        assert att.reference is ref and att.epoch == 0
        want_h = math.radians(h + (decl_deg or 0.0))
        assert ang_diff(att.heading_rad, want_h) < GOLDEN_Q_RAD, (name, decl_deg, deg(att.heading_rad))
        assert abs(att.pitch_rad - math.radians(p)) < GOLDEN_Q_RAD, (name, deg(att.pitch_rad))
        assert abs(att.roll_rad - math.radians(r)) < GOLDEN_Q_RAD, (name, deg(att.roll_rad))


def test_the_same_rotation_vector_reads_half_a_turn_apart_on_the_two_mounts():
    """An OAK-D (IMU z forward) looking north sends what an OAK-D-PRO (IMU z backward) sends
    looking south: IMU x down, y west, z north. The mount decides the heading's sign of forward."""
    q = (0.5, -0.5, 0.5, 0.5)
    h_oak_d = attitude_from_world_from_cam(world_from_cam_of_imu(q, CAM_FROM_IMU_OAK_D))[0]
    h_pro = attitude_from_world_from_cam(world_from_cam_of_imu(q, CAM_FROM_IMU_OAK_D_PRO))[0]
    assert ang_diff(h_oak_d, 0.0) < EXACT_F64 and ang_diff(h_pro, math.pi) < EXACT_F64


def test_mounts_are_rotations_and_differ_by_a_half_turn_about_down():
    for m in (CAM_FROM_IMU_OAK_D, CAM_FROM_IMU_OAK_D_PRO):
        validate_rotation("mount", m)
    # Both put the IMU's x along the camera's down axis; y and z are flipped between them.
    flip = CAM_FROM_IMU_OAK_D_PRO @ CAM_FROM_IMU_OAK_D.T
    np.testing.assert_allclose(flip, np.diag([-1.0, 1.0, -1.0]), atol=EXACT_F64)


def test_sensor_world_frames():
    """The same physical orientation reported in NED or NWU gives the same heading once named."""
    cam = world_from_cam(math.radians(40), math.radians(10), math.radians(-5))
    world_from_imu = cam @ CAM_FROM_IMU_OAK_D_PRO  # ENU from IMU
    for name, enu_from in ENU_FROM_SENSOR_WORLD.items():
        validate_rotation(name, enu_from)
        q = quat_from_rotation(enu_from.T @ world_from_imu)  # what a sensor with that world reports
        h, p, r = attitude_from_world_from_cam(world_from_cam_of_imu(q, CAM_FROM_IMU_OAK_D_PRO, enu_from))
        assert ang_diff(h, math.radians(40)) < ANGLE_RAD_F64, name
        assert abs(p - math.radians(10)) < ANGLE_RAD_F64 and abs(r + math.radians(5)) < ANGLE_RAD_F64


def test_validate_rotation_rejects_non_rotations():
    for bad in (np.zeros((3, 3)), np.diag([1.0, 1.0, -1.0]), 2 * np.eye(3), np.eye(2), "x"):
        with pytest.raises(ValidationError, match="rotation"):
            validate_rotation("m", bad)


# --- declination, modes, references -----------------------------------------------------------


def test_declination_east_positive_and_wraps():
    assert deg(magnetic_to_true(math.radians(350), math.radians(15))) == pytest.approx(5.0)
    assert deg(magnetic_to_true(math.radians(10), math.radians(-15))) == pytest.approx(355.0)
    assert deg(magnetic_to_true(math.radians(90), 0.0)) == pytest.approx(90.0)


@pytest.mark.parametrize(
    ("imu", "want", "mode"),
    [
        ("BNO086", "auto", ImuMode.ROTATION_VECTOR),
        ("BNO085", "auto", ImuMode.ROTATION_VECTOR),
        ("BNO080", "auto", ImuMode.ROTATION_VECTOR),
        ("BNO08X", "auto", ImuMode.ROTATION_VECTOR),
        ("BNO080", "game_rotation_vector", ImuMode.GAME_ROTATION_VECTOR),  # every BNO08x has both
        ("BNO085", "game_rotation_vector", ImuMode.GAME_ROTATION_VECTOR),
        ("BNO08X", "game_rotation_vector", ImuMode.GAME_ROTATION_VECTOR),
        ("bno086", "game_rotation_vector", ImuMode.GAME_ROTATION_VECTOR),
        ("BNO086", "gyro", ImuMode.GYRO),
        ("BMI270", "auto", ImuMode.GYRO),
        ("BMI270", "gyro", ImuMode.GYRO),
        ("LSM6DSV", "auto", ImuMode.GAME_ROTATION_VECTOR),
        ("SOMETHING_NEW", "auto", ImuMode.GYRO),  # unknown: every IMU has a gyroscope
        ("NONE", "auto", None),
        ("", "auto", None),
        ("BNO086", "none", None),
    ],
)
def test_choose_imu_mode(imu, want, mode):
    assert choose_imu_mode(imu, want) is mode


def test_choose_imu_mode_refuses_fusion_the_chip_lacks():
    with pytest.raises(ValidationError, match="BMI270.*use imu_mode 'gyro' or 'auto'"):
        choose_imu_mode("BMI270", "rotation_vector")
    with pytest.raises(ValidationError, match="game rotation vector"):
        choose_imu_mode("BMI270", "game_rotation_vector")
    with pytest.raises(ValidationError, match="expected one of"):
        choose_imu_mode("BNO086", "magic")


def test_heading_refs_and_sensors():
    assert heading_ref_for(ImuMode.ROTATION_VECTOR, None) is HeadingRef.MAGNETIC
    assert heading_ref_for(ImuMode.ROTATION_VECTOR, 0.0) is HeadingRef.TRUE
    assert heading_ref_for(ImuMode.GAME_ROTATION_VECTOR, 0.1) is HeadingRef.RELATIVE
    assert heading_ref_for(ImuMode.GYRO, None) is HeadingRef.RELATIVE
    assert imu_sensors(ImuMode.ROTATION_VECTOR, "BNO086")[0] == "ROTATION_VECTOR"
    assert imu_sensors(ImuMode.GAME_ROTATION_VECTOR, "BNO086")[0] == "GAME_ROTATION_VECTOR"
    assert imu_sensors(ImuMode.GYRO, "BMI270") == ("GYROSCOPE_RAW", "ACCELEROMETER_RAW")
    assert imu_sensors(ImuMode.GYRO, "BNO086") == ("GYROSCOPE_CALIBRATED", "ACCELEROMETER")


def test_default_mount_by_product():
    m, src = cam_from_imu_default("OAK-D")
    np.testing.assert_array_equal(m, CAM_FROM_IMU_OAK_D)
    assert src == "default for OAK-D"
    m, src = cam_from_imu_default("oak-d-pro")
    np.testing.assert_array_equal(m, CAM_FROM_IMU_OAK_D_PRO)
    m, src = cam_from_imu_default("OAK-X-UNKNOWN")
    np.testing.assert_array_equal(m, CAM_FROM_IMU_OAK_D_PRO)
    assert "not in the table" in src


def test_gravity_mismatch_checks_the_world_frame():
    q = (0.5, 0.5, 0.5, -0.5)  # OAK-D Pro looking north, level: IMU x is down
    accel = (-9.81, 0.0, 0.0)  # at rest the accelerometer reads +g along up = -x
    assert gravity_mismatch_rad(q, accel) < 1e-9
    assert deg(gravity_mismatch_rad(q, accel, ENU_FROM_SENSOR_WORLD["ned"])) == pytest.approx(180.0)
    assert math.isnan(gravity_mismatch_rad(q, (0.0, 0.0, 0.0)))


def test_gravity_mismatch_is_the_angle_between_the_two_ups():
    """docs/oak.md, check 1, for any orientation: 0 when the rotation vector's up is the
    accelerometer's, 180 deg for a NED world, 0 for NWU (it differs only in yaw); in between, the
    angle between the two."""
    q = (0.5, 0.5, 0.5, -0.5)  # OAK-D Pro level, looking north: up is IMU -x, east is IMU +y
    c30, s30 = math.cos(math.radians(30.0)), math.sin(math.radians(30.0))
    assert deg(gravity_mismatch_rad(q, (-9.81 * c30, 9.81 * s30, 0.0))) == pytest.approx(30.0, abs=1e-9)
    rng = np.random.default_rng(3)
    for qr in rng.normal(size=(20, 4)):
        accel = 9.81 * rotation_from_quat(qr).T @ np.array([0.0, 0.0, 1.0])  # +g along up, IMU axes
        assert gravity_mismatch_rad(qr, accel) < 1e-6
        assert abs(gravity_mismatch_rad(qr, accel, ENU_FROM_SENSOR_WORLD["ned"]) - math.pi) < 1e-6
        assert gravity_mismatch_rad(qr, accel, ENU_FROM_SENSOR_WORLD["nwu"]) < 1e-6


def test_tracker_gravity_check_is_smoothed_and_only_at_rest():
    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, sensor_world="ned")
    q = (0.5, 0.5, 0.5, -0.5)  # read as NED, the up this implies is the accelerometer's down
    tr.add_accelerometer(0.0, (-9.81 * 1.5, 0.0, 0.0))  # a jolt: no check
    tr.add_rotation_vector(0.0, q)
    assert tr.gravity_mismatch_rad is None
    for k in range(1, 100):
        tr.add_accelerometer(k * 0.01, (-9.81, 0.0, 0.0))
        tr.add_rotation_vector(k * 0.01, q)
    assert deg(tr.gravity_mismatch_rad) == pytest.approx(180.0, abs=1e-6)
    tr.add_accelerometer(1.0, (0.0, 9.81, 0.0))  # one sample 90 deg off moves it by 5% of the way only
    tr.add_rotation_vector(1.0, q)
    assert deg(tr.gravity_mismatch_rad) == pytest.approx(175.5, abs=1e-6)
    # "At rest" allows for an accelerometer's scale error: 2% low is still checked (here: agrees).
    tr = AttitudeTracker(ImuMode.GAME_ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO)
    tr.add_accelerometer(0.0, (-0.98 * 9.80665, 0.0, 0.0))
    tr.add_rotation_vector(0.0, q)
    assert tr.gravity_mismatch_rad == pytest.approx(0.0, abs=1e-9)


# --- the buffer -------------------------------------------------------------------------------


def q_heading(h_deg: float, mount=CAM_FROM_IMU_OAK_D_PRO) -> np.ndarray:
    """The rotation vector of a level camera looking at heading h."""
    return quat_from_rotation(world_from_cam(math.radians(h_deg)) @ mount)


def heading_of(q, mount=CAM_FROM_IMU_OAK_D_PRO) -> float:
    return deg(attitude_from_world_from_cam(world_from_cam_of_imu(q, mount))[0])


def test_buffer_interpolates_across_north_and_never_extrapolates():
    buf = OrientationBuffer(history_s=2.0, max_gap_s=0.1)
    assert buf.at(1.0) == (None, NO_IMU_YET)
    buf.add(10.00, q_heading(350.0))
    buf.add(10.02, q_heading(10.0))
    buf.add(10.04, q_heading(30.0))
    q, reason = buf.at(10.01)
    h = heading_of(q)
    assert reason == OK and min(h, 360.0 - h) < 1e-6  # 0, not the 180 a naive average of 350 and 10 gives
    q, reason = buf.at(10.03)
    assert reason == OK and heading_of(q) == pytest.approx(20.0, abs=1e-6)
    q, reason = buf.at(10.02)  # exactly a sample
    assert reason == OK and heading_of(q) == pytest.approx(10.0, abs=1e-9)
    assert buf.at(9.99) == (None, TOO_OLD)
    assert buf.at(10.05) == (None, IMU_PENDING)
    buf.add(10.30, q_heading(40.0))  # 0.26 s after the previous one: a gap
    assert buf.at(10.2) == (None, IMU_GAP)


def test_buffer_hemisphere_and_order_and_bounds():
    buf = OrientationBuffer(history_s=1.0, capacity=4, max_gap_s=1.0)
    q0 = q_heading(100.0)
    buf.add(0.0, q0)
    buf.add(0.5, -q_heading(120.0))  # the same rotation as +q: slerp must take the short arc
    q, _ = buf.at(0.25)
    assert heading_of(q) == pytest.approx(110.0, abs=1e-6)
    assert not buf.add(0.5, q0) and not buf.add(0.4, q0) and not buf.add(float("nan"), q0)
    assert buf.counts["out_of_order"] == 3
    for t in (0.6, 0.7, 0.8):
        buf.add(t, q0)
    assert len(buf) == 4 and buf.counts["overflow"] == 1 and buf.oldest_t == 0.5
    buf.add(2.0, q0)  # prunes everything older than 1 s before the newest
    assert buf.oldest_t == 2.0 and len(buf) == 1
    with pytest.raises(ValidationError):
        buf.add(3.0, (0.0, 0.0, 0.0, 0.0))


def test_slerp_endpoints_and_midpoint():
    a, b = q_heading(0.0), q_heading(90.0)
    np.testing.assert_allclose(slerp(a, b, 0.0), a, atol=EXACT_F64)
    assert heading_of(slerp(a, b, 1.0)) == pytest.approx(90.0, abs=1e-9)
    assert heading_of(slerp(a, b, 0.5)) == pytest.approx(45.0, abs=1e-9)


def test_slerp_follows_the_arc_at_every_fraction():
    """Not only the midpoint: a quarter of the way from heading 0 to 90 is 22.5, also when q1 comes
    in the other hemisphere; two equal orientations (an IMU at rest) interpolate to themselves."""
    a, b = q_heading(0.0), q_heading(90.0)
    for q1 in (b, -b):
        for f, want in ((0.25, 22.5), (0.75, 67.5)):
            q = slerp(a, q1, f)
            assert np.linalg.norm(q) == pytest.approx(1.0, abs=EXACT_F64)
            assert heading_of(q) == pytest.approx(want, abs=1e-9)
    rest = np.array([0.5, 0.5, 0.5, -0.5])  # exactly unit: q . q = 1
    np.testing.assert_allclose(slerp(rest, rest, 0.3), rest, atol=EXACT_F64)


def test_buffer_refuses_bounds_that_cannot_hold_a_bracket():
    OrientationBuffer(history_s=0.5, capacity=2, max_gap_s=0.01)  # two samples bracket a time
    for kwargs in ({"history_s": 0.0}, {"capacity": 1}, {"max_gap_s": 0.0}):
        with pytest.raises(ValidationError, match="OrientationBuffer"):
            OrientationBuffer(**kwargs)


def test_buffer_limits_are_inclusive():
    """Pruned are samples *older* than history_s before the newest, refused are brackets *more*
    than max_gap_s apart (docs/oak.md): exactly at either limit is kept and interpolated."""
    buf = OrientationBuffer(history_s=1.0, max_gap_s=1.0)
    assert buf.newest_t is None and buf.oldest_t is None
    assert buf.add(3.0, q_heading(10.0)) is True
    assert buf.add(4.0, q_heading(30.0)) is True
    assert (buf.oldest_t, buf.newest_t, len(buf)) == (3.0, 4.0, 2)
    q, reason = buf.at(3.5)
    assert reason == OK and heading_of(q) == pytest.approx(20.0, abs=1e-6)
    assert buf.add(4.0, q_heading(30.0)) is False  # not newer than the newest
    buf.add(4.25, q_heading(30.0))
    buf.add(4.5, q_heading(30.0))  # 3.0 is now 1.5 s older than the newest: pruned
    assert (buf.oldest_t, buf.newest_t, len(buf)) == (4.0, 4.5, 3)


def test_buffer_interpolates_between_the_two_samples_around_the_time():
    """Among many samples the lookup uses the pair that brackets the time, never a wider one:
    headings that zigzag would show it."""
    hs = [100.0, 140.0, 110.0, 150.0, 120.0, 160.0, 130.0, 170.0, 140.0]
    ts = [10.0 + 0.01 * k for k in range(len(hs))]
    buf = OrientationBuffer()
    for t, h in zip(ts, hs, strict=True):
        buf.add(t, q_heading(h))
    for k in range(len(hs) - 1):
        q, reason = buf.at(0.5 * (ts[k] + ts[k + 1]))
        assert reason == OK and heading_of(q) == pytest.approx(0.5 * (hs[k] + hs[k + 1]), abs=1e-6), k
        q, reason = buf.at(ts[k])
        assert reason == OK and heading_of(q) == pytest.approx(hs[k], abs=1e-9), k


# --- the tracker --------------------------------------------------------------------------------


def test_tracker_rotation_vector_magnetic_then_true():
    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO)
    tr.add_rotation_vector(1.00, q_heading(80.0), 0.1)
    tr.add_rotation_vector(1.01, q_heading(82.0), 0.1)
    att, reason = tr.attitude_at(1.005)
    assert att is not None and att.pitch_rad is not None and att.roll_rad is not None
    assert reason == OK and att.reference is HeadingRef.MAGNETIC
    assert deg(att.heading_rad) == pytest.approx(81.0, abs=1e-6)
    assert att.pitch_rad == pytest.approx(0.0, abs=1e-9) and att.roll_rad == pytest.approx(0.0, abs=1e-9)

    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, declination_rad=math.radians(-3.0))
    tr.add_rotation_vector(1.00, q_heading(1.0))
    att, _ = tr.attitude_at(1.00)
    assert att is not None
    assert att.reference is HeadingRef.TRUE and deg(att.heading_rad) == pytest.approx(358.0, abs=1e-6)


def test_tracker_skips_inaccurate_rotation_vectors():
    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, max_accuracy_rad=math.radians(30))
    assert tr.add_rotation_vector(1.0, q_heading(0.0), accuracy_rad=math.pi) is False  # BNO: "uncalibrated"
    assert tr.counts["inaccurate"] == 1 and tr.attitude_at(1.0) == (None, "inaccurate")
    # Only reports *worse* than the limit are refused: one exactly at it is used.
    assert tr.add_rotation_vector(2.0, q_heading(0.0), accuracy_rad=math.radians(30)) is True
    assert tr.counts["inaccurate"] == 1 and tr.attitude_at(2.0)[1] == OK


def test_a_frame_whose_rotation_vectors_were_too_inaccurate_says_so():
    """The magnetometer disturbed mid-run (a vehicle's steel, a passing truck): the BNO's accuracy
    estimate goes past the limit and its reports are not used. A frame they cover has no heading
    because of that, said as 'inaccurate', not 'imu_pending' (its reports came, and waiting for
    more does not help) nor 'imu_gap' nor 'no_imu_yet'."""
    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, max_accuracy_rad=math.radians(30))
    for k in range(3):  # accurate at 1.00 .. 1.02
        assert tr.add_rotation_vector(1.0 + 0.01 * k, q_heading(40.0), accuracy_rad=0.1)
    for k in range(3, 40):  # inaccurate from 1.03 to 1.39
        assert not tr.add_rotation_vector(1.0 + 0.01 * k, q_heading(40.0), accuracy_rad=math.pi)
    assert tr.attitude_at(1.01)[1] == OK  # before it turned inaccurate: interpolated as ever
    assert tr.attitude_at(1.025)[1] == "inaccurate"  # bracketed by an accurate and an inaccurate report
    assert tr.attitude_at(1.2) == (None, "inaccurate")  # was imu_pending
    assert tr.attitude_at(1.5) == (None, IMU_PENDING)  # after the newest report: its reports may yet come
    for k in range(50, 53):  # accurate again from 1.50: the stretch between is not a gap in the reports
        assert tr.add_rotation_vector(1.0 + 0.01 * k, q_heading(40.0), accuracy_rad=0.1)
    assert tr.attitude_at(1.2) == (None, "inaccurate")  # was imu_gap
    assert tr.attitude_at(1.45) == (None, IMU_GAP)  # 1.39 to 1.50: no report at all
    assert tr.attitude_at(1.51)[1] == OK
    # Inaccurate from the first report: was no_imu_yet.
    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO)
    tr.add_rotation_vector(1.0, q_heading(0.0), accuracy_rad=math.pi)
    tr.add_rotation_vector(1.1, q_heading(0.0), accuracy_rad=math.pi)
    assert tr.attitude_at(1.05) == (None, "inaccurate") and tr.attitude_at(1.2) == (None, NO_IMU_YET)
    tr.reset()  # a new session: the old session's reports say nothing of its frames
    assert tr.attitude_at(1.05) == (None, NO_IMU_YET)


def test_tracker_game_rotation_vector_is_relative_to_its_first_report():
    tr = AttitudeTracker(ImuMode.GAME_ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, declination_rad=0.2)
    tr.add_rotation_vector(5.0, q_heading(200.0))
    tr.add_rotation_vector(5.1, q_heading(230.0))
    att, _ = tr.attitude_at(5.0)
    assert att is not None
    assert att.reference is HeadingRef.RELATIVE and deg(att.heading_rad) == pytest.approx(0.0, abs=1e-6)
    att, _ = tr.attitude_at(5.1)
    assert att is not None
    assert deg(att.heading_rad) == pytest.approx(30.0, abs=1e-6)  # the declination means nothing here
    tr.reset()
    assert tr.attitude_at(5.1) == (None, NO_IMU_YET)


def test_tracker_vertical_optical_axis_has_no_heading():
    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO)
    tr.add_rotation_vector(0.0, quat_from_rotation(world_from_cam(0.3, math.radians(89.9)) @ CAM_FROM_IMU_OAK_D_PRO))
    assert tr.attitude_at(0.0) == (None, VERTICAL)
    # docs/oak.md: "within 1 deg of vertical" has none; 1.5 deg off vertical still has one.
    tr.add_rotation_vector(1.0, quat_from_rotation(world_from_cam(0.3, math.radians(89.5)) @ CAM_FROM_IMU_OAK_D_PRO))
    assert tr.attitude_at(1.0) == (None, VERTICAL)
    tr.add_rotation_vector(2.0, quat_from_rotation(world_from_cam(0.3, math.radians(88.5)) @ CAM_FROM_IMU_OAK_D_PRO))
    att, reason = tr.attitude_at(2.0)
    assert att is not None and att.pitch_rad is not None and att.roll_rad is not None
    assert reason == OK and att.heading_rad == pytest.approx(0.3, abs=1e-9)
    assert deg(att.pitch_rad) == pytest.approx(88.5, abs=1e-9)


def test_tracker_keeps_at_most_4096_imu_samples():
    """docs/oak.md: the orientation buffer holds at most 4096 samples, the oldest dropped and counted."""
    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, history_s=10.0)
    q = q_heading(45.0)
    for k in range(4097):  # 1 kHz for 4.1 s, all within the history
        tr.add_rotation_vector(k * 0.001, q)
    assert len(tr.buffer) == 4096 and tr.buffer.counts["overflow"] == 1 and tr.buffer.oldest_t == 0.001


def test_tracker_declination_is_within_half_a_turn():
    for ok in (math.pi, -math.pi, 0.0):
        AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, declination_rad=ok)
    for bad in (4.0, -4.0, math.nan, math.inf):
        with pytest.raises(ValidationError, match="declination"):
            AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, declination_rad=bad)


def test_tracker_counts_every_report_and_ignores_the_other_kind():
    """What stats()["imu_counts"] shows; the add_* methods say whether the report was used."""
    q = q_heading(10.0)
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D_PRO)
    assert tr.add_rotation_vector(0.0, q) is False  # gyro mode: no rotation vectors
    tr.add_accelerometer(0.0, (-9.81, 0.0, 0.0))
    assert tr.add_gyro(0.0, np.zeros(3)) is True
    assert tr.add_gyro(0.0, np.zeros(3)) is False  # not newer
    assert tr.counts == {"rotation_vectors": 0, "gyro_reports": 2, "accel_reports": 1, "inaccurate": 0,
                         "ignored": 1}
    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO)
    assert tr.add_gyro(0.0, np.zeros(3)) is False  # fusion mode: no gyro
    tr.add_accelerometer(1.0, (-9.81, 0.0, 0.0))
    tr.add_accelerometer(1.01, (-9.81, 0.0, 0.0))
    assert tr.add_rotation_vector(1.0, q) is True
    assert tr.add_rotation_vector(1.0, q) is False  # not newer: dropped by the buffer
    assert tr.add_rotation_vector(1.1, q, accuracy_rad=math.pi) is False
    assert tr.counts == {"rotation_vectors": 3, "gyro_reports": 0, "accel_reports": 2, "inaccurate": 1,
                         "ignored": 1}
    assert tr.buffer.counts == {"added": 1, "out_of_order": 1, "overflow": 0}


# --- gyro integration ----------------------------------------------------------------------------


def level_pro_imu(h_rad: float) -> np.ndarray:
    """ENU from IMU for a level OAK-D Pro at heading h."""
    return world_from_cam(h_rad) @ CAM_FROM_IMU_OAK_D_PRO


def test_gyro_integration_turns_clockwise_and_keeps_level():
    """A level camera turning clockwise at 30 deg/s for 3 s: +90 deg, relative to its start."""
    rate = math.radians(30.0)
    w_world = np.array([0.0, 0.0, -rate])  # clockwise seen from above is negative about up
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D_PRO, history_s=5.0)
    t0 = 100.0
    for k in range(301):
        t = t0 + k * 0.01
        r = level_pro_imu(math.radians(37.0) + rate * (t - t0))  # it started at 37 deg: relative gives 0
        tr.add_accelerometer(t, r.T @ np.array([0.0, 0.0, 9.81]))  # +g along up, in IMU axes
        tr.add_gyro(t, r.T @ w_world)
    for t, want in ((t0, 0.0), (t0 + 1.005, 30.15), (t0 + 3.0, 90.0)):
        att, reason = tr.attitude_at(t)
        assert att is not None and att.pitch_rad is not None and att.roll_rad is not None
        assert reason == OK and att.reference is HeadingRef.RELATIVE
        assert ang_diff(att.heading_rad, math.radians(want)) < GYRO_RAD, (t, deg(att.heading_rad))
        assert abs(att.pitch_rad) < TILT_RAD and abs(att.roll_rad) < TILT_RAD
    assert tr.gyro is not None and tr.gyro.counts["gyro_steps"] == 300


def test_gyro_tilt_follows_the_accelerometer():
    """Started level, then the accelerometer says 10 deg nose up: the tilt converges, the heading stays."""
    integ = GyroIntegrator(CAM_FROM_IMU_OAK_D_PRO, tilt_gain=1.0)
    level = level_pro_imu(0.0)
    integ.update(0.0, np.zeros(3), level.T @ np.array([0.0, 0.0, 9.81]))
    pitched = world_from_cam(0.0, math.radians(10.0)) @ CAM_FROM_IMU_OAK_D_PRO
    q = None
    for k in range(1, 1001):  # 10 s at 100 Hz, time constant 1 s
        q = integ.update(k * 0.01, np.zeros(3), pitched.T @ np.array([0.0, 0.0, 9.81]))
    h, p, r = attitude_from_world_from_cam(world_from_cam_of_imu(q, CAM_FROM_IMU_OAK_D_PRO))
    assert abs(p - math.radians(10.0)) < TILT_RAD and abs(r) < TILT_RAD and ang_diff(h, 0.0) < TILT_RAD


UP_PRO_LEVEL = level_pro_imu(0.0).T @ np.array([0.0, 0.0, 9.81])  # accelerometer of a level OAK-D Pro


def _step_counts(integ) -> dict:
    """The integrator's counts of steps and of reports it did not step with (not the bias')."""
    return {k: v for k, v in integ.counts.items() if not k.startswith("gyro_bias")}


def test_gyro_counts_gaps_and_ignores_old_samples():
    integ = GyroIntegrator(CAM_FROM_IMU_OAK_D_PRO)
    integ.update(1.0, np.zeros(3), UP_PRO_LEVEL)
    assert integ.update(1.0, np.zeros(3), UP_PRO_LEVEL) is None
    integ.update(1.5, np.zeros(3), UP_PRO_LEVEL)  # a gap: the integrator starts again, no step across it
    assert _step_counts(integ) == {"gyro_steps": 0, "gyro_gaps": 1, "gyro_out_of_order": 1, "gyro_no_gravity": 0}


def test_gyro_gap_is_a_step_longer_than_a_tenth_of_a_second():
    """docs/oak.md: a gap *longer* than 0.1 s between gyro reports is counted."""
    integ = GyroIntegrator(CAM_FROM_IMU_OAK_D_PRO)
    for t in (0.0, 0.1, 0.22):  # steps of 0.1 s (not a gap) and 0.12 s (a gap)
        integ.update(t, np.zeros(3), UP_PRO_LEVEL)
    assert _step_counts(integ) == {"gyro_steps": 1, "gyro_gaps": 1, "gyro_out_of_order": 0, "gyro_no_gravity": 0}


def _gyro_report(tracker, t, heading_deg, rate_deg_s):
    """A level camera at ``heading_deg`` turning clockwise at ``rate_deg_s``: its accelerometer
    and gyro reports (IMU axes) at ``t``."""
    imu_to_world = world_from_cam(math.radians(heading_deg)) @ CAM_FROM_IMU_OAK_D_PRO
    tracker.add_accelerometer(t, imu_to_world.T @ [0.0, 0.0, 9.81])
    tracker.add_gyro(t, imu_to_world.T @ [0.0, 0.0, -math.radians(rate_deg_s)])  # clockwise: -z


def test_a_gap_in_gyro_reports_starts_a_new_zero_in_a_new_epoch():
    # 30 deg/s clockwise for 0.5 s (0 -> 15 deg), then still, with no reports from 0.5 to 1.5 s.
    # Integrated across the gap, the mean of the rates at its ends (15 deg/s) over 1 s invented a
    # turn: 30 deg in the same epoch, where the truth is 15 and the turn meanwhile is unknown.
    tracker = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D_PRO, epoch=3)
    for k in range(51):
        _gyro_report(tracker, k * 0.01, 30.0 * k * 0.01, 30.0)
    before, _ = tracker.attitude_at(0.2)
    assert before is not None and before.epoch == 3 and math.degrees(before.heading_rad) == pytest.approx(6.0, abs=0.1)
    for k in range(51):
        _gyro_report(tracker, 1.5 + k * 0.01, 15.0, 0.0)
    after, _ = tracker.attitude_at(1.8)
    assert after is not None and after.epoch == 4 and ang_diff(after.heading_rad, 0.0) < TILT_RAD  # a new zero
    assert tracker.attitude_at(0.2)[0] is None  # nothing of the old zero is kept to interpolate with
    assert tracker.gyro is not None and tracker.gyro.counts["gyro_gaps"] == 1


def test_reset_starts_a_relative_heading_in_a_new_epoch():
    tracker = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D_PRO, epoch=3)
    tracker.reset()
    assert tracker.epoch == 4
    absolute = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, declination_rad=0.1)
    absolute.reset()
    assert absolute.epoch == 0  # absolute headings keep epoch 0


@pytest.mark.parametrize(
    ("w_cam", "want_deg"),
    [
        ((0.0, 1.0, 0.0), (30.0, 0.0, 0.0)),  # about the camera's down axis: clockwise, heading grows
        ((1.0, 0.0, 0.0), (0.0, 30.0, 0.0)),  # about its right axis: nose up
        ((0.0, 0.0, 1.0), (0.0, 0.0, 30.0)),  # about the optical axis: right side down
    ],
)
def test_tracker_gyro_integrates_body_rates_about_each_axis(w_cam, want_deg):
    """Gyro rates are body rates in IMU axes; on the OAK-D (IMU x down, y left, z forward) the
    three camera axes are three different IMU axes. Started level (the first accelerometer
    report) and looking at its own north (relative 0), with no tilt term, a constant rate about a
    fixed body axis integrates exactly, even in 1.5 deg steps (20 Hz)."""
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D, tilt_gain=0.0)
    assert tr.gyro is not None and not tr.gyro.initialized
    tr.add_accelerometer(0.0, CAM_FROM_IMU_OAK_D.T @ np.array([0.0, -9.81, 0.0]))  # +g along the camera's up
    w_imu = CAM_FROM_IMU_OAK_D.T @ (math.radians(30.0) * np.array(w_cam))
    for k in range(21):  # 1 s
        assert tr.add_gyro(k * 0.05, w_imu) is True
        assert tr.gyro.initialized
    att, reason = tr.attitude_at(1.0)
    assert att is not None and att.pitch_rad is not None and att.roll_rad is not None
    assert reason == OK and tr.counts["gyro_reports"] == 21
    assert ang_diff(att.heading_rad, math.radians(want_deg[0])) < ANGLE_RAD_F64
    assert abs(att.pitch_rad - math.radians(want_deg[1])) < ANGLE_RAD_F64
    assert abs(att.roll_rad - math.radians(want_deg[2])) < ANGLE_RAD_F64


def test_gyro_first_sample_looks_north_with_the_tilt_of_gravity():
    """GyroIntegrator's world is z up from the accelerometer, and its north is where the optical
    axis points at the first sample: the first orientation is heading 0 with the true pitch and roll."""
    for mount in (CAM_FROM_IMU_OAK_D, CAM_FROM_IMU_OAK_D_PRO):
        world_from_imu = world_from_cam(math.radians(123.0), math.radians(20.0), math.radians(-10.0)) @ mount
        accel = world_from_imu.T @ np.array([0.0, 0.0, 9.81])
        q = GyroIntegrator(mount).update(0.0, np.zeros(3), accel)
        np.testing.assert_allclose(world_from_cam_of_imu(q, mount),
                                   world_from_cam(0.0, math.radians(20.0), math.radians(-10.0)), atol=1e-9)


def test_gyro_starts_even_when_the_camera_looks_straight_up_or_down():
    """A vertical optical axis has no heading to call north; any will do, but it must be a rotation.
    Also for an IMU whose x axis is the optical axis."""
    x_forward = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # IMU x fwd, y right, z down
    for mount in (CAM_FROM_IMU_OAK_D, CAM_FROM_IMU_OAK_D_PRO, x_forward):
        for sign in (1.0, -1.0):  # looking up: gravity's up is the optical axis; looking down: minus it
            accel = sign * 9.81 * (mount.T @ np.array([0.0, 0.0, 1.0]))
            q = GyroIntegrator(mount).update(0.0, np.zeros(3), accel)
            assert q is not None
            _, p, _ = attitude_from_world_from_cam(world_from_cam_of_imu(q, mount))
            assert np.all(np.isfinite(q)) and p == pytest.approx(sign * math.pi / 2, abs=1e-9)


def test_tracker_gyro_tilt_converges_at_the_documented_gain():
    """docs/oak.md: a Mahony proportional term of gain 0.5/s pulls the estimated up towards the
    accelerometer's. With a tilt error e it turns the estimate at 0.5 sin(e) rad/s, so
    tan(e/2) = tan(e0/2) exp(-0.5 t): started level, with the accelerometer saying 10 deg nose up,
    after 2 s the pitch is 10 deg - 2 atan(tan(5 deg) / e). The heading does not move."""
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D_PRO)  # the driver's gain: the default
    g_up = np.array([0.0, 0.0, 9.81])
    tr.add_accelerometer(0.0, level_pro_imu(0.0).T @ g_up)
    tr.add_gyro(0.0, np.zeros(3))
    pitched = world_from_cam(0.0, math.radians(10.0)) @ CAM_FROM_IMU_OAK_D_PRO
    for k in range(1, 201):  # 2 s at 100 Hz
        tr.add_accelerometer(k * 0.01, pitched.T @ g_up)
        tr.add_gyro(k * 0.01, np.zeros(3))
    att, _ = tr.attitude_at(2.0)
    assert att is not None and att.pitch_rad is not None and att.roll_rad is not None
    want = math.radians(10.0) - 2.0 * math.atan(math.tan(math.radians(5.0)) * math.exp(-1.0))
    assert abs(att.pitch_rad - want) < GYRO_RAD, deg(att.pitch_rad)
    assert ang_diff(att.heading_rad, 0.0) < GYRO_RAD and abs(att.roll_rad) < GYRO_RAD


def test_gyro_tilt_correction_only_within_ten_percent_of_g():
    """docs/oak.md: the accelerometer holds the tilt only while its magnitude is within 10% of g
    (not while accelerating hard): 8% low still pulls, 12% high does not."""
    level = level_pro_imu(0.0)
    pitched = world_from_cam(0.0, math.radians(10.0)) @ CAM_FROM_IMU_OAK_D_PRO
    g_up = np.array([0.0, 0.0, 9.80665])
    for scale, moves in ((0.92, True), (1.12, False)):
        integ = GyroIntegrator(CAM_FROM_IMU_OAK_D_PRO, tilt_gain=1.0)
        integ.update(0.0, np.zeros(3), level.T @ g_up)
        for k in range(1, 101):
            q = integ.update(k * 0.01, np.zeros(3), scale * (pitched.T @ g_up))
        _, p, _ = attitude_from_world_from_cam(world_from_cam_of_imu(q, CAM_FROM_IMU_OAK_D_PRO))
        assert (deg(p) > 5.0) if moves else (abs(p) < EXACT_F64), (scale, deg(p))


def test_gyro_waits_for_gravity_so_an_upside_down_camera_turns_the_right_way():
    """The integrator's world is z up from the accelerometer: a gyro report before the first
    accelerometer report (or the first after a gap) has no up to start from. Assumed upright, an
    OAK mounted upside down starts with up half a turn off, where the tilt term (a x up) is zero
    and cannot pull it back: a clockwise turn read as anticlockwise, roll 0 for 180, all run."""
    rate = math.radians(30.0)
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D_PRO, history_s=5.0)
    for k in range(301):
        t = 100.0 + k * 0.01
        imu_to_world = world_from_cam(rate * k * 0.01, 0.0, math.pi) @ CAM_FROM_IMU_OAK_D_PRO  # upside down
        if k > 0:  # the first packet carries a gyro report only
            tr.add_accelerometer(t, imu_to_world.T @ np.array([0.0, 0.0, 9.81]))
        assert tr.add_gyro(t, imu_to_world.T @ np.array([0.0, 0.0, -rate])) is (k > 0)
    assert tr.attitude_at(100.0) == (None, "too_old")  # nothing before gravity was known
    att, reason = tr.attitude_at(103.0)
    assert reason == OK and att is not None and att.roll_rad is not None
    assert ang_diff(att.heading_rad, math.radians(90.0 - 0.3)) < GYRO_RAD, deg(att.heading_rad)  # zero at 0.01 s
    assert ang_diff(att.roll_rad, math.pi) < TILT_RAD, deg(att.roll_rad)
    assert tr.gyro is not None and tr.gyro.counts["gyro_no_gravity"] == 1


def test_gyro_after_a_gap_waits_for_gravity_too():
    integ = GyroIntegrator(CAM_FROM_IMU_OAK_D_PRO)
    up_imu = level_pro_imu(0.0).T @ np.array([0.0, 0.0, 9.81])
    assert integ.update(0.0, np.zeros(3), up_imu) is not None
    assert integ.update(0.5, np.zeros(3)) is None  # a gap, and no up to start again from
    assert not integ.initialized
    assert integ.update(0.51, np.zeros(3), up_imu) is not None
    assert _step_counts(integ) == {"gyro_steps": 0, "gyro_gaps": 1, "gyro_out_of_order": 0, "gyro_no_gravity": 1}


def test_gyro_gap_is_the_trackers_max_gap():
    """max_gap_s is what the tracker calls a gap between reports, for interpolation and for the
    integrator alike. At 8 Hz with max_gap_s 0.3 the rotation vector modes interpolate, and gyro
    integration restarted at every report (the integrator's own 0.1 s): a new epoch each time."""
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D_PRO, max_gap_s=0.3, epoch=2)
    for k in range(17):  # 2 s at 8 Hz, 30 deg/s clockwise
        _gyro_report(tr, k / 8.0, 30.0 * k / 8.0, 30.0)
    att, reason = tr.attitude_at(2.0)
    assert reason == OK and att is not None and att.epoch == 2
    assert ang_diff(att.heading_rad, math.radians(60.0)) < GYRO_RAD, deg(att.heading_rad)
    assert tr.gyro is not None and tr.gyro.counts["gyro_gaps"] == 0


# --- gyro bias learned while still ---------------------------------------------------------------
# A BMI270's zero-rate offset is +-0.5 deg/s typical (datasheet, 1 sigma): integrated, 30 deg of
# heading a minute. Standing still (a light, a jam, parked at boot) the gyro measures it directly.

G_STD = 9.80665
BIAS_DEG_S = 0.02  # a bias learned from a few seconds of a still, noisy, vibrating IMU


def _vehicle_reports(tracker, t0, seconds, *, bias_deg_s=(0.0, 0.0, 0.0), yaw_deg_s=0.0, speed_m_s=0.0,
                     heading0_deg=0.0, road=0.0, engine_deg_s=0.0, accel_scale=1.0, seed=0, hz=100.0):
    """An OAK-D (BMI270) on a vehicle, its reports at ``hz`` from ``t0`` for ``seconds``: a level
    camera turning clockwise at ``yaw_deg_s`` at ``speed_m_s`` (centripetal acceleration to the
    right), the engine's vibration (``engine_deg_s`` about each axis at 23-31 Hz, zero mean), the
    road's pitching and heaving (``road``: 1 is 0.5 deg/s RMS at 1.3 Hz and 0.3 m/s² at 2.1 Hz),
    a gyro bias in IMU axes and the datasheet's white noise (7 mdps/sqrt Hz). Returns the true
    heading at the end (deg)."""
    rng = np.random.default_rng(seed)
    mount = CAM_FROM_IMU_OAK_D
    f_eng = np.array([27.0, 31.0, 23.0])
    a_eng = math.radians(engine_deg_s) / (2 * np.pi * f_eng)  # angle amplitude of that rate
    a_road = math.radians(0.5 * math.sqrt(2.0) * road) / (2 * np.pi * 1.3)

    def angles(t):
        h = math.radians(heading0_deg + yaw_deg_s * (t - t0)) + a_eng[0] * math.sin(2 * np.pi * f_eng[0] * t)
        p = a_eng[1] * math.sin(2 * np.pi * f_eng[1] * t) + a_road * math.sin(2 * np.pi * 1.3 * t)
        r = a_eng[2] * math.sin(2 * np.pi * f_eng[2] * t)
        return h, p, r

    def world_from_imu(t):
        return world_from_cam(*angles(t)) @ mount

    bias = np.radians(np.asarray(bias_deg_s, dtype=np.float64))
    d = 1e-4
    n = int(round(seconds * hz))
    for k in range(n):
        t = t0 + k / hz
        m = world_from_imu(t - d).T @ world_from_imu(t + d)
        w = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1]]) / (4 * d)
        h = angles(t)[0]
        right = np.array([math.cos(h), -math.sin(h), 0.0])
        f_world = np.array([0.0, 0.0, G_STD + 0.3 * math.sqrt(2.0) * road * math.sin(2 * np.pi * 2.1 * t)])
        f_world = accel_scale * f_world + speed_m_s * math.radians(yaw_deg_s) * right
        tracker.add_accelerometer(t, world_from_imu(t).T @ f_world + rng.normal(0.0, 0.011, 3))
        tracker.add_gyro(t, w + bias + rng.normal(0.0, math.radians(0.05), 3))
    return heading0_deg + yaw_deg_s * (n - 1) / hz


def _heading_deg(tracker, t):
    att, reason = tracker.attitude_at(t)
    assert reason == OK and att is not None, reason
    return deg(att.heading_rad)


def test_a_still_imu_learns_its_gyro_bias_and_the_heading_stops_drifting():
    """Parked at boot with the engine idling: the heading turned at the bias' rate about up
    (0.5 deg/s, 30 deg a minute). After 2 s still, the mean rate is the bias; subtracted, the
    heading holds, and counts say that a bias was learned and how fast it turned the heading."""
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D, history_s=5.0)
    _vehicle_reports(tr, 0.0, 5.0, bias_deg_s=(0.5, -0.5, 0.5), engine_deg_s=3.0)
    assert tr.gyro is not None and tr.gyro.counts["gyro_bias_learned"] == 1
    # The OAK-D's IMU x is the camera's down: level, the rate about up is -x, -0.5 deg/s (anticlockwise),
    # so the heading drifted clockwise by +0.5 deg/s.
    assert tr.gyro.counts["gyro_bias_heading_deg_s"] == pytest.approx(0.5, abs=BIAS_DEG_S)
    assert tr.gyro.counts["gyro_bias_deg_s"] == pytest.approx(0.5 * math.sqrt(3.0), abs=2 * BIAS_DEG_S)
    before = math.radians(_heading_deg(tr, 5.0 - 0.01))
    _vehicle_reports(tr, 5.0, 60.0, bias_deg_s=(0.5, -0.5, 0.5), engine_deg_s=3.0, seed=1)
    assert deg(ang_diff(math.radians(_heading_deg(tr, 65.0 - 0.01)), before)) < 60.0 * BIAS_DEG_S  # not 30 deg
    assert tr.gyro.counts["gyro_bias_learned"] == 1  # one still stretch


def test_a_stop_shorter_than_two_seconds_teaches_nothing():
    """Quiet for 1.9 s at boot, then driving; and a 1.5 s stop between turns: neither is still
    for long enough."""
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D)
    end = _vehicle_reports(tr, 0.0, 1.9, bias_deg_s=(0.5, 0.5, 0.5))
    end = _vehicle_reports(tr, 1.9, 3.0, bias_deg_s=(0.5, 0.5, 0.5), yaw_deg_s=10.0, speed_m_s=5.0, road=1.0,
                           heading0_deg=end)
    end = _vehicle_reports(tr, 4.9, 1.5, bias_deg_s=(0.5, 0.5, 0.5), heading0_deg=end, engine_deg_s=3.0)
    _vehicle_reports(tr, 6.4, 3.0, bias_deg_s=(0.5, 0.5, 0.5), yaw_deg_s=-10.0, speed_m_s=5.0, heading0_deg=end,
                     road=1.0)
    assert tr.gyro is not None and tr.gyro.counts["gyro_bias_learned"] == 0
    assert tr.gyro.bias is not None and not tr.gyro.bias.learned


def test_a_slow_curve_on_a_road_is_not_taken_for_a_bias():
    """At 20 m/s around a 1 deg/s curve the gyro reads a steady 1 deg/s, as a bias would. The
    road moves the body: at a quarter of the simulated road's motion (docs/oak.md) it is no longer
    quiet, so the curve is not learned, and the heading turns with it."""
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D)
    end = _vehicle_reports(tr, 0.0, 20.0, yaw_deg_s=1.0, speed_m_s=20.0, road=0.25, engine_deg_s=3.0)
    assert tr.gyro is not None and tr.gyro.counts["gyro_bias_learned"] == 0
    assert abs(_heading_deg(tr, 19.99) - end) < 0.2


def test_a_perfectly_smooth_curve_is_a_bias_below_the_limit_and_refused_above():
    """Nothing a 6-axis IMU measures tells a constant turn on a road that moves nothing else from
    standing with a bias of that rate (the centripetal acceleration is constant too, a tilt). Above
    1.5 deg/s (three times the datasheet's typical offset) it is refused and counted; below, it
    is learned: the limit of the method (docs/oak.md)."""
    for rate, learned in ((2.0, False), (1.0, True)):
        tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D)
        _vehicle_reports(tr, 0.0, 4.0, yaw_deg_s=rate, speed_m_s=20.0)
        assert tr.gyro is not None
        assert tr.gyro.counts["gyro_bias_learned"] == int(learned), rate
        assert tr.gyro.counts["gyro_bias_refused"] == int(not learned), rate
        if learned:
            assert tr.gyro.counts["gyro_bias_heading_deg_s"] == pytest.approx(rate, abs=BIAS_DEG_S)


def test_an_accelerometer_off_g_is_not_still():
    """Standing, the accelerometer reads g; 5 % more is a vehicle accelerating (or a bad scale)."""
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D)
    _vehicle_reports(tr, 0.0, 4.0, bias_deg_s=(0.3, 0.3, 0.3), accel_scale=1.05)
    assert tr.gyro is not None and tr.gyro.counts["gyro_bias_learned"] == 0


def test_the_bias_outlives_a_gap_and_each_stop_learns_it_again():
    """A gap restarts the integration (a new zero) but it is the same chip: the bias stays. It
    drifts with temperature, so the next stop's replaces it."""
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D)
    _vehicle_reports(tr, 0.0, 3.0, bias_deg_s=(0.5, 0.0, 0.0))
    assert tr.gyro is not None and tr.gyro.counts["gyro_bias_heading_deg_s"] == pytest.approx(0.5, abs=BIAS_DEG_S)
    _vehicle_reports(tr, 3.5, 1.0, bias_deg_s=(0.5, 0.0, 0.0))  # after a gap of 0.5 s
    assert tr.gyro.counts["gyro_gaps"] == 1 and tr.epoch == 1
    turned = ang_diff(math.radians(_heading_deg(tr, 4.49)), math.radians(_heading_deg(tr, 3.5)))
    assert deg(turned) < BIAS_DEG_S  # still subtracted: not 0.5 deg
    _vehicle_reports(tr, 4.5, 3.0, bias_deg_s=(0.2, 0.0, 0.0))
    assert tr.gyro.counts["gyro_bias_learned"] == 2
    assert tr.gyro.counts["gyro_bias_heading_deg_s"] == pytest.approx(0.2, abs=BIAS_DEG_S)


def test_without_bias_learning_the_heading_drifts_at_the_bias():
    """gyro_bias=False: the integrator as it was, which the benchmark compares with."""
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D, gyro_bias=False)
    _vehicle_reports(tr, 0.0, 10.0, bias_deg_s=(0.5, 0.0, 0.0))
    assert _heading_deg(tr, 9.99) == pytest.approx(0.5 * 9.99, abs=0.1)
    assert tr.gyro is not None and tr.gyro.bias is None and "gyro_bias_learned" not in tr.gyro.counts
    tr.reset()
    assert tr.gyro is not None and tr.gyro.bias is None  # a new session keeps the choice


def test_a_new_session_of_the_same_chip_keeps_the_bias_learned():
    """A reconnect (a new tracker, or reset()) starts a new zero, but the chip is the same: its
    bias stays subtracted until the next stop learns it again. Dropped, the heading drifted at the
    whole bias from every reconnect until the vehicle next stood for 2 s."""
    tr = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D)
    _vehicle_reports(tr, 0.0, 3.0, bias_deg_s=(0.5, 0.0, 0.0))
    again = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D, epoch=1)
    again.keep_gyro_bias(tr)
    tr.reset()
    for new in (again, tr):
        assert new.gyro is not None and new.gyro.bias is not None and new.gyro.bias.learned
        assert new.gyro.counts["gyro_bias_learned"] == 1  # counted once, as the status line reads it
        assert new.gyro.counts["gyro_bias_heading_deg_s"] == pytest.approx(0.5, abs=BIAS_DEG_S)
        _vehicle_reports(new, 10.0, 10.0, bias_deg_s=(0.5, 0.0, 0.0), yaw_deg_s=10.0, speed_m_s=5.0, road=1.0)
        assert _heading_deg(new, 19.99) == pytest.approx(99.9, abs=1.0)  # not 5 deg more: the bias over 10 s
    # None learned: nothing is taken.
    fresh = AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D)
    fresh.keep_gyro_bias(AttitudeTracker(ImuMode.GYRO, CAM_FROM_IMU_OAK_D))
    assert fresh.gyro is not None and fresh.gyro.bias is not None and not fresh.gyro.bias.learned
