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


# --- the tracker --------------------------------------------------------------------------------


def test_tracker_rotation_vector_magnetic_then_true():
    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO)
    tr.add_rotation_vector(1.00, q_heading(80.0), 0.1)
    tr.add_rotation_vector(1.01, q_heading(82.0), 0.1)
    att, reason = tr.attitude_at(1.005)
    assert reason == OK and att.reference is HeadingRef.MAGNETIC
    assert deg(att.heading_rad) == pytest.approx(81.0, abs=1e-6)
    assert att.pitch_rad == pytest.approx(0.0, abs=1e-9) and att.roll_rad == pytest.approx(0.0, abs=1e-9)

    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, declination_rad=math.radians(-3.0))
    tr.add_rotation_vector(1.00, q_heading(1.0))
    att, _ = tr.attitude_at(1.00)
    assert att.reference is HeadingRef.TRUE and deg(att.heading_rad) == pytest.approx(358.0, abs=1e-6)


def test_tracker_skips_inaccurate_rotation_vectors():
    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, max_accuracy_rad=math.radians(30))
    assert not tr.add_rotation_vector(1.0, q_heading(0.0), accuracy_rad=math.pi)  # BNO: "uncalibrated"
    assert tr.counts["inaccurate"] == 1 and tr.attitude_at(1.0) == (None, NO_IMU_YET)


def test_tracker_game_rotation_vector_is_relative_to_its_first_report():
    tr = AttitudeTracker(ImuMode.GAME_ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO, declination_rad=0.2)
    tr.add_rotation_vector(5.0, q_heading(200.0))
    tr.add_rotation_vector(5.1, q_heading(230.0))
    att, _ = tr.attitude_at(5.0)
    assert att.reference is HeadingRef.RELATIVE and deg(att.heading_rad) == pytest.approx(0.0, abs=1e-6)
    att, _ = tr.attitude_at(5.1)
    assert deg(att.heading_rad) == pytest.approx(30.0, abs=1e-6)  # the declination means nothing here
    tr.reset()
    assert tr.attitude_at(5.1) == (None, NO_IMU_YET)


def test_tracker_vertical_optical_axis_has_no_heading():
    tr = AttitudeTracker(ImuMode.ROTATION_VECTOR, CAM_FROM_IMU_OAK_D_PRO)
    tr.add_rotation_vector(0.0, quat_from_rotation(world_from_cam(0.3, math.radians(89.9)) @ CAM_FROM_IMU_OAK_D_PRO))
    assert tr.attitude_at(0.0) == (None, VERTICAL)


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
        assert reason == OK and att.reference is HeadingRef.RELATIVE
        assert ang_diff(att.heading_rad, math.radians(want)) < GYRO_RAD, (t, deg(att.heading_rad))
        assert abs(att.pitch_rad) < TILT_RAD and abs(att.roll_rad) < TILT_RAD
    assert tr.gyro.counts["gyro_steps"] == 300


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


def test_gyro_counts_gaps_and_ignores_old_samples():
    integ = GyroIntegrator(CAM_FROM_IMU_OAK_D_PRO)
    integ.update(1.0, np.zeros(3))
    assert integ.update(1.0, np.zeros(3)) is None
    integ.update(1.5, np.zeros(3))
    assert integ.counts == {"gyro_steps": 1, "gyro_gaps": 1, "gyro_out_of_order": 1}
