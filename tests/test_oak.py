"""The OAK driver (drivers/oak.py) through the real depthai library, without a device.

Host-only pipelines (``dai.Pipeline(False)``) with a ``dai.node.ThreadedHostNode`` that sends real
``dai.ImgFrame`` and ``dai.IMUData`` messages drive the same code a device feeds: output queues,
:class:`OakMessageHandler`, the reader thread, loss and reconnection. Only
:func:`open_device_session` (Camera and IMU nodes on a device) needs hardware: the tests marked
``hardware`` (``pytest --hardware``). docs/oak.md is the specification.
"""

from __future__ import annotations

import logging
import math
import subprocess
import sys
import threading
import time
import traceback
from datetime import timedelta
from typing import Any

import numpy as np
import pytest

from drivers.imu_heading import (
    CAM_FROM_IMU_OAK_D,
    CAM_FROM_IMU_OAK_D_PRO,
    AttitudeTracker,
    ImuMode,
    quat_from_rotation,
    world_from_cam,
)
from drivers.oak import (
    FRAME_TYPES_BGR,
    NO_DEVICE_MESSAGE,
    OakCamera,
    OakConfig,
    OakError,
    OakMessageHandler,
    OakSession,
    intrinsics_from_matrix,
    mid_exposure_s,
    read_cam_from_imu,
    read_intrinsics,
)
from rig.errors import ValidationError
from rig.types import HeadingRef, Intrinsics

dai = pytest.importorskip("depthai")

HANG_GUARD_S = 10.0  # every wait here ends by this, so a bug fails instead of hanging
HEADING_DEG = 1e-3  # the IMU report carries float32 quaternion components
TIME_S = 1e-6  # DepthAI timestamps are microseconds on the host
W, H = 32, 24
INTR = Intrinsics(fx=30.0, fy=30.0, cx=16.0, cy=12.0, width=W, height=H)
MOUNT = CAM_FROM_IMU_OAK_D_PRO
BASE_S = 1000.0  # message times (monotonic seconds): any value works, the driver only compares them


# --- real depthai messages ------------------------------------------------------------------


def ts(t_s: float):
    stamp = dai.Timestamp()
    stamp.sec = int(math.floor(t_s))
    stamp.nsec = int(round((t_s - math.floor(t_s)) * 1e9))
    return stamp


def image(seq: int) -> np.ndarray:
    return np.random.default_rng(seq).integers(0, 256, (H, W, 3), dtype=np.uint8)


def img_frame(seq: int, t_end_s: float, exposure_us: int = 10_000, img: np.ndarray | None = None):
    f = dai.ImgFrame()
    f.setCvFrame(image(seq) if img is None else img, dai.ImgFrame.Type.BGR888i)
    f.setTimestamp(timedelta(seconds=t_end_s))
    f.setSequenceNum(seq)
    cam = f.cam
    cam.exposureTimeUs = exposure_us
    f.cam = cam
    return f


def q_level(h_deg: float, mount=MOUNT) -> np.ndarray:
    """Rotation vector (ENU from IMU) of a level camera at heading h."""
    return quat_from_rotation(world_from_cam(math.radians(h_deg)) @ mount)


def imu_rv(t_s: float, q, accuracy_rad: float = 0.05, accel=(-9.81, 0.0, 0.0)):
    """IMUData with one packet: a rotation vector and (same time) an accelerometer report."""
    rv = dai.IMUReportRotationVectorWAcc()
    rv.real, rv.i, rv.j, rv.k = (float(x) for x in q)
    rv.rotationVectorAccuracy = accuracy_rad
    rv.timestamp = ts(t_s)
    acc = dai.IMUReportAccelerometer()
    acc.x, acc.y, acc.z = accel
    acc.timestamp = ts(t_s)
    packet = dai.IMUPacket()
    packet.rotationVector = rv
    packet.acceleroMeter = acc
    data = dai.IMUData()
    data.packets = [packet]
    return data


def imu_gyro(t_s: float, gyro, accel):
    g = dai.IMUReportGyroscope()
    g.x, g.y, g.z = (float(v) for v in gyro)
    g.timestamp = ts(t_s)
    a = dai.IMUReportAccelerometer()
    a.x, a.y, a.z = (float(v) for v in accel)
    a.timestamp = ts(t_s)
    packet = dai.IMUPacket()
    packet.gyroscope = g
    packet.acceleroMeter = a
    data = dai.IMUData()
    data.packets = [packet]
    return data


def ramp_deg(t_s: float) -> float:
    """The scripted magnetic heading: 10 deg, turning clockwise at 50 deg/s."""
    return 10.0 + 50.0 * (t_s - BASE_S)


def script(n_frames: int, first_seq: int = 0, fps: float = 50.0, exposure_us: int = 10_000,
           imu_hz: float = 100.0) -> list[tuple[float, str, Any]]:
    """Frames (end-of-exposure stamps) and rotation vectors covering them, in message-time order."""
    out = []
    t_end = [BASE_S + 0.1 + k / fps for k in range(n_frames)]
    for k, t in enumerate(t_end):
        out.append((t, "video", img_frame(first_seq + k, t, exposure_us)))
    n_imu = int((t_end[-1] + 0.05 - BASE_S) * imu_hz)
    for i in range(n_imu):
        t = BASE_S + i / imu_hz
        out.append((t, "imu", imu_rv(t, q_level(ramp_deg(t)))))
    out.sort(key=lambda m: (m[0], m[1] == "video"))
    return out


# --- a host-only source ---------------------------------------------------------------------


class ScriptedSource(dai.node.ThreadedHostNode):  # type: ignore[name-defined]  # dai comes from importorskip
    """Sends its script's messages on ``video`` and ``imu``; then stops the pipeline (a lost
    device) or idles (a stalled one). An exception escaping run() aborts the whole process in
    depthai 3.12, so none may."""

    def __init__(self) -> None:
        super().__init__()
        self.video = self.createOutput()
        self.imu = self.createOutput()
        self.messages: list = []
        self.pause_s = 0.002
        self.then = "idle"  # or "stop"

    def run(self) -> None:
        try:
            for _, kind, msg in self.messages:
                if not self.mainLoop():
                    return
                (self.video if kind == "video" else self.imu).send(msg)
                time.sleep(self.pause_s)
            if self.then == "stop":
                self.stopPipeline()
                return
            while self.mainLoop():
                time.sleep(0.01)
        except Exception:  # noqa: BLE001 - see the docstring
            traceback.print_exc()


def host_sessions(*scripts, then=("idle",), imu_mode=ImuMode.ROTATION_VECTOR, mount=MOUNT, imu_name="BNO086"):
    """An ``open_session`` that builds one host-only pipeline per script, in order; past the last
    it raises OakError like a machine with nothing plugged in."""
    pending = list(scripts)
    thens = list(then) + [then[-1]] * len(scripts)
    opened: list[Any] = []

    def open_session(config: OakConfig) -> OakSession:
        if not pending:
            raise OakError(NO_DEVICE_MESSAGE)
        p = dai.Pipeline(False)
        src = p.create(ScriptedSource)
        src.messages = pending.pop(0)
        src.then = thens[len(opened)]
        opened.append(src)
        return OakSession(pipeline=p, video=src.video, imu=src.imu, intrinsics=INTR, imu_mode=imu_mode,
                          cam_from_imu=None if imu_mode is None else mount, cam_from_imu_source="test",
                          imu_name=imu_name, description=f"host-{len(opened)}")

    open_session.opened = opened  # type: ignore[attr-defined]  # the sources, for the tests to look at
    return open_session


def collect(cam: OakCamera, n: int, timeout_s: float = HANG_GUARD_S) -> list:
    frames: list[Any] = []
    deadline = time.monotonic() + timeout_s
    while len(frames) < n and time.monotonic() < deadline:
        f = cam.get(0.1)
        if f is not None:
            frames.append(f)
    return frames


FAST: dict[str, Any] = dict(queue_size=32, backoff_s=(0.05, 0.1), poll_s=0.02, imu_wait_s=0.3, declination_deg=5.0,
            width=W, height=H)


# --- timestamps and calibration ----------------------------------------------------------------


def test_mid_exposure_is_depthais_middle_offset():
    f = img_frame(3, 12.5, exposure_us=8000)
    assert f.getTimestamp() == timedelta(seconds=12.5)  # the stamp marks the END of exposure
    assert mid_exposure_s(f) == pytest.approx(12.496, abs=TIME_S)
    assert mid_exposure_s(f) == f.getTimestamp(dai.CameraExposureOffset.MIDDLE).total_seconds()


def calibration(with_imu: bool):
    calib = dai.CalibrationHandler()
    calib.setCameraIntrinsics(dai.CameraBoardSocket.CAM_A, [[1000.0, 0, 960.0], [0, 1000.0, 540.0], [0, 0, 1]],
                              dai.Size2f(1920, 1080))
    if with_imu:
        calib.setImuExtrinsics(dai.CameraBoardSocket.CAM_A, CAM_FROM_IMU_OAK_D.tolist(), [1.0, -1.5, 0.0],
                               [0.0, 0.0, 0.0])
    return calib


def test_intrinsics_from_the_calibration_at_the_output_size():
    calib = calibration(with_imu=False)
    intr = read_intrinsics(calib, dai.CameraBoardSocket.CAM_A, 640, 360)
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == pytest.approx((1000 / 3, 1000 / 3, 320.0, 180.0), rel=1e-6)
    intr = read_intrinsics(calib, dai.CameraBoardSocket.CAM_A, 640, 480)  # 4:3 out of 16:9: centre crop
    assert (intr.fx, intr.fy, intr.cx, intr.cy, intr.width) == pytest.approx((1000 / 3, 1000 / 3, 320, 240, 640))
    with pytest.raises(OakError, match="no intrinsics for .*CAM_B.*OakConfig.intrinsics"):
        read_intrinsics(calib, dai.CameraBoardSocket.CAM_B, 640, 400)
    with pytest.raises(ValidationError):
        intrinsics_from_matrix(np.eye(2), 4, 4)


def test_imu_to_camera_rotation_from_the_calibration_or_the_default():
    r, source = read_cam_from_imu(calibration(with_imu=True), dai.CameraBoardSocket.CAM_A, "OAK-D-PRO")
    np.testing.assert_array_equal(r, CAM_FROM_IMU_OAK_D)  # the calibration wins over the product table
    assert source == "calibration"
    r, source = read_cam_from_imu(calibration(with_imu=False), dai.CameraBoardSocket.CAM_A, "OAK-D-PRO")
    np.testing.assert_array_equal(r, CAM_FROM_IMU_OAK_D_PRO)
    assert source.startswith("default for OAK-D-PRO; calibration has none")
    # getCameraToImuExtrinsics is the inverse: the rotation read is IMU -> camera, as documented
    calib = calibration(with_imu=True)
    inv = np.asarray(calib.getCameraToImuExtrinsics(dai.CameraBoardSocket.CAM_A))[:3, :3]
    np.testing.assert_array_equal(inv, CAM_FROM_IMU_OAK_D.T)


# --- the shared message handling, message by message ---------------------------------------------


def test_handler_frames_wait_for_the_imu_then_get_the_interpolated_heading():
    tracker = AttitudeTracker(ImuMode.ROTATION_VECTOR, MOUNT, declination_rad=math.radians(5.0))
    h = OakMessageHandler(INTR, tracker, imu_wait_s=0.5, first_seq=100)
    h.on_imu(imu_rv(BASE_S + 0.00, q_level(ramp_deg(BASE_S))))
    h.on_frame(img_frame(7, BASE_S + 0.015, exposure_us=10_000), now_s=50.0)  # mid-exposure at +0.010
    assert h.ready(50.1) == []  # the IMU report after +0.010 is not in yet: the frame waits
    h.on_imu(imu_rv(BASE_S + 0.02, q_level(ramp_deg(BASE_S + 0.02))))
    [frame] = h.ready(50.2)
    assert frame.seq == 100 and frame.t_mono_s == pytest.approx(BASE_S + 0.010, abs=TIME_S)
    np.testing.assert_array_equal(frame.image_bgr, image(7))
    assert frame.attitude is not None and frame.attitude.reference is HeadingRef.TRUE
    assert math.degrees(frame.attitude.heading_rad) == pytest.approx(ramp_deg(BASE_S + 0.01) + 5.0, abs=HEADING_DEG)
    assert frame.attitude.pitch_rad == pytest.approx(0.0, abs=1e-5)

    h.on_frame(img_frame(9, BASE_S + 0.5), now_s=51.0)  # device seq 8 never came; no IMU covers it
    assert h.ready(51.4) == []
    [late] = h.ready(51.6)  # waited imu_wait_s: it goes without a heading, never extrapolated
    assert late.seq == 102 and late.attitude is None
    h.on_frame(img_frame(9, BASE_S + 0.6), now_s=52.0)  # a repeated device seq number
    h.on_frame(img_frame(10, BASE_S + 0.7, img=np.zeros((H, W + 2, 3), np.uint8)), now_s=52.0)  # wrong size
    h.on_imu("not IMUData")
    assert h.drain() == []
    c = h.counts
    assert (c["frames_in"], c["frames_out"], c["frames_with_heading"]) == (4, 2, 1)
    assert (c["frames_dropped_device"], c["seq_backwards"], c["bad_frames"], c["bad_imu"]) == (1, 1, 1, 1)
    assert c["no_heading_imu_pending"] == 1 and c["imu_reports"] == 4  # 2 rotation vectors + 2 accelerometers


def test_handler_one_bad_report_costs_only_itself_not_the_rest_of_its_batch():
    """An IMUData carries up to 10 packets (setMaxBatchReports), more after a USB hiccup. A zero
    quaternion among them is counted bad; the packets after it were dropped with it, a 0.1 s hole
    at 100 Hz in which frames had no heading (imu_gap)."""
    tracker = AttitudeTracker(ImuMode.ROTATION_VECTOR, MOUNT)
    h = OakMessageHandler(INTR, tracker)
    times = [BASE_S + k * 0.01 for k in range(10)]
    packets = [imu_rv(t, q_level(ramp_deg(t))).packets[0] for t in times]
    packets[1].rotationVector = imu_rv(times[1], (0.0, 0.0, 0.0, 0.0)).packets[0].rotationVector
    batch = dai.IMUData()
    batch.packets = packets
    h.on_imu(batch)
    assert h.counts["bad_imu"] == 1 and h.counts["imu_reports"] == 10 + 9  # every accelerometer, 9 of 10 vectors
    att, reason = tracker.attitude_at(BASE_S + 0.085)
    assert reason == "ok" and att is not None
    assert math.degrees(att.heading_rad) == pytest.approx(ramp_deg(BASE_S + 0.085), abs=HEADING_DEG)


def test_handler_a_frame_of_the_wrong_size_is_bad_not_also_dropped_by_the_device():
    # It was left out of the sequence, so the next frame counted it as never sent too: 4 device
    # frames accounted for where the device sent 3.
    h = OakMessageHandler(INTR, None)
    h.on_frame(img_frame(0, BASE_S), now_s=0.0)
    h.on_frame(img_frame(1, BASE_S + 0.1, img=np.zeros((H, W + 2, 3), np.uint8)), now_s=0.0)
    h.on_frame(img_frame(2, BASE_S + 0.2), now_s=0.0)
    assert [f.seq for f in h.drain()] == [0, 2]
    c = h.counts
    assert (c["frames_in"], c["frames_out"], c["bad_frames"], c["frames_dropped_device"]) == (3, 2, 1, 0)


def test_handler_a_frame_before_the_first_imu_report_waits_for_it():
    # docs/oak.md: a frame that arrives before its IMU reports waits up to imu_wait_s. Before the
    # session's first report it went out at once, without a heading.
    h = OakMessageHandler(INTR, AttitudeTracker(ImuMode.ROTATION_VECTOR, MOUNT), imu_wait_s=0.15)
    h.on_frame(img_frame(0, BASE_S + 0.015), now_s=10.0)  # mid-exposure at +0.010
    assert h.ready(10.0) == []
    h.on_imu(imu_rv(BASE_S, q_level(40.0)))
    h.on_imu(imu_rv(BASE_S + 0.02, q_level(40.0)))
    [frame] = h.ready(10.005)
    assert frame.attitude is not None and math.degrees(frame.attitude.heading_rad) == pytest.approx(40.0, abs=0.01)
    # An IMU that never reports: the wait is bounded.
    no_tracker_yet = OakMessageHandler(INTR, AttitudeTracker(ImuMode.ROTATION_VECTOR, MOUNT), imu_wait_s=0.15)
    no_tracker_yet.on_frame(img_frame(0, BASE_S), now_s=20.0)
    assert no_tracker_yet.ready(20.1) == []
    [alone] = no_tracker_yet.ready(20.2)
    assert alone.attitude is None and no_tracker_yet.counts["no_heading_no_imu_yet"] == 1


def test_handler_a_frame_covered_by_inaccurate_rotation_vectors_goes_at_once_counted_as_such():
    # It waited imu_wait_s for reports that had come (and been refused), then was counted
    # no_heading_imu_pending: 150 ms of latency per frame, and a reason that hid the magnetometer.
    h = OakMessageHandler(INTR, AttitudeTracker(ImuMode.ROTATION_VECTOR, MOUNT), imu_wait_s=0.15)
    h.on_imu(imu_rv(BASE_S, q_level(40.0)))
    for k in range(1, 10):
        h.on_imu(imu_rv(BASE_S + 0.01 * k, q_level(40.0), accuracy_rad=math.pi))
    h.on_frame(img_frame(0, BASE_S + 0.055), now_s=10.0)  # mid-exposure at +0.050
    [frame] = h.ready(10.0)
    assert frame.attitude is None
    assert h.counts["no_heading_inaccurate"] == 1 and h.counts["no_heading_imu_pending"] == 0


def test_a_rotation_vector_that_turns_inaccurate_mid_run_is_said(caplog):
    """The warning came only when no report had ever been accurate: a magnetometer disturbed after
    a good start left frames without heading and the log silent."""
    msgs = [m for m in script(20) if m[1] == "video"]
    for i in range(int(0.6 * 100)):
        t = BASE_S + i / 100
        msgs.append((t, "imu", imu_rv(t, q_level(40.0), accuracy_rad=0.05 if t < BASE_S + 0.2 else math.pi)))
    msgs.sort(key=lambda m: (m[0], m[1] == "video"))
    with caplog.at_level(logging.WARNING, logger="drivers.oak"), \
            OakCamera(OakConfig(**FAST), open_session=host_sessions(msgs)) as cam:
        frames = collect(cam, 20)
        stats = cam.stats()
    assert len(frames) == 20 and stats["frames_with_heading"] >= 1 and stats["no_heading_inaccurate"] >= 10, stats
    said = [r.getMessage() for r in caplog.records if "not accurate" in r.getMessage()]
    assert len(said) == 1 and "figure-eight" in said[0] and "45" in said[0], said


def test_a_rotation_vector_inaccurate_twice_is_said_each_time_and_when_it_recovers(caplog):
    """Said once a run, a second disturbance (a truck beside the camera after a bridge) went unsaid,
    and so did the recovery between them."""
    msgs = [m for m in script(60) if m[1] == "video"]  # 1.2 s of frames at 50 fps
    bad = [(0.2, 0.5), (0.8, 1.0)]  # seconds after BASE_S while the rotation vector is inaccurate
    for i in range(int(1.3 * 100)):
        t = BASE_S + i / 100
        inaccurate = any(a <= t - BASE_S < b for a, b in bad)
        msgs.append((t, "imu", imu_rv(t, q_level(40.0), accuracy_rad=math.pi if inaccurate else 0.05)))
    msgs.sort(key=lambda m: (m[0], m[1] == "video"))
    with caplog.at_level(logging.INFO, logger="drivers.oak"), \
            OakCamera(OakConfig(**FAST), open_session=host_sessions(msgs)) as cam:
        frames = collect(cam, 60)
    assert len(frames) == 60
    said = [r.getMessage() for r in caplog.records if "accurate" in r.getMessage()]
    assert [("not accurate" in m, "accurate again" in m) for m in said] == [(True, False), (False, True),
                                                                             (True, False), (False, True)], said


def test_handler_gyro_mode_from_imudata_gyroscope_reports():
    """A BMI270-like IMU: gyro + accelerometer reports, integrated on the host, relative heading."""
    tracker = AttitudeTracker(ImuMode.GYRO, MOUNT)
    h = OakMessageHandler(INTR, tracker, imu_wait_s=0.0)
    rate = math.radians(20.0)
    for k in range(101):  # 1 s at 100 Hz, turning clockwise at 20 deg/s from heading 123
        t = BASE_S + k * 0.01
        r = world_from_cam(math.radians(123.0) + rate * k * 0.01) @ MOUNT
        h.on_imu(imu_gyro(t, r.T @ np.array([0.0, 0.0, -rate]), r.T @ np.array([0.0, 0.0, 9.81])))
    h.on_frame(img_frame(0, BASE_S + 0.505, exposure_us=10_000), now_s=0.0)
    [frame] = h.ready(0.0)
    assert frame.attitude is not None and frame.attitude.reference is HeadingRef.RELATIVE
    assert math.degrees(frame.attitude.heading_rad) == pytest.approx(10.0, abs=0.05)


def test_handler_without_imu_passes_frames_through():
    h = OakMessageHandler(INTR, None)
    h.on_frame(img_frame(0, 5.0), now_s=0.0)
    [frame] = h.ready(0.0)
    assert frame.attitude is None and h.counts["no_heading_no_imu"] == 1


# --- the whole driver over host-only pipelines -----------------------------------------------------


def test_host_pipeline_frames_and_headings_match_what_was_sent():
    n = 20
    msgs = script(n)
    sent = {m.getSequenceNum(): m for _, kind, m in msgs if kind == "video"}
    with OakCamera(OakConfig(**FAST), open_session=host_sessions(msgs)) as cam:
        frames = collect(cam, n)
        stats = cam.stats()
    assert [f.seq for f in frames] == list(range(n))
    for f in frames:
        m = sent[f.seq]
        np.testing.assert_array_equal(f.image_bgr, image(f.seq))
        assert f.t_mono_s == pytest.approx(m.getTimestamp(dai.CameraExposureOffset.MIDDLE).total_seconds(), abs=TIME_S)
        assert f.intrinsics == INTR
        assert f.attitude.reference is HeadingRef.TRUE
        want = (ramp_deg(f.t_mono_s) + 5.0) % 360.0
        assert math.degrees(f.attitude.heading_rad) == pytest.approx(want, abs=HEADING_DEG), f.seq
        assert abs(f.attitude.pitch_rad) < 1e-5 and abs(f.attitude.roll_rad) < 1e-5
    assert stats["frames_out"] == stats["frames_with_heading"] == n
    assert stats["heading_ref"] == "true" and stats["imu_mode"] == "rotation_vector"
    assert stats["device_lost"] == 0 and stats["sessions"] == 1
    assert stats["gravity_mismatch_deg"] == pytest.approx(0.0, abs=0.01)
    assert stats["imu_counts"]["added"] == stats["imu_counts"]["rotation_vectors"] > n


def test_device_loss_is_reported_and_reconnected_and_seq_continues():
    first, second = script(5), script(6, first_seq=40)
    opener = host_sessions(first, second, then=("stop", "idle"))
    with OakCamera(OakConfig(**FAST), open_session=opener) as cam:
        frames = collect(cam, 11)
        stats = cam.stats()
    assert len(frames) == 11 and len(opener.opened) == 2
    seqs = [f.seq for f in frames]
    assert seqs == sorted(set(seqs)) and seqs[:5] == [0, 1, 2, 3, 4] and seqs[5] == 5  # continues, no repeats
    np.testing.assert_array_equal(frames[5].image_bgr, image(40))
    assert stats["device_lost"] == 1 and stats["reconnects"] == 1 and stats["sessions"] == 2
    assert "pipeline stopped" in stats["last_error"] or "closed" in stats["last_error"]


def test_a_reconnect_starts_a_new_heading_epoch_only_for_relative_headings():
    """A game-rotation-vector heading restarts at 0 when the device comes back: its frames carry
    the session's epoch so no window mixes the two zeros. A true heading keeps epoch 0."""
    for mode, want in ((ImuMode.GAME_ROTATION_VECTOR, [0] * 5 + [1] * 6), (ImuMode.ROTATION_VECTOR, [0] * 11)):
        opener = host_sessions(script(5), script(6, first_seq=40), then=("stop", "idle"), imu_mode=mode)
        with OakCamera(OakConfig(**FAST), open_session=opener) as cam:
            frames = collect(cam, 11)
        assert len(frames) == 11 and [f.attitude.epoch for f in frames] == want, mode
        if mode is ImuMode.GAME_ROTATION_VECTOR:
            assert frames[0].attitude.reference is HeadingRef.RELATIVE


def test_a_reconnect_to_the_same_oak_keeps_its_gyro_bias_and_another_oak_does_not():
    """imu_mode gyro learns the gyro's bias standing still (docs/oak.md). A reconnect made a new
    tracker, and the heading drifted at the whole bias until the next 2 s stop; the same device
    (product and id) keeps it, another device's bias is its own."""
    import dataclasses

    def nothing_plugged(config):
        raise OakError(NO_DEVICE_MESSAGE)

    session = host_sessions(script(1), imu_mode=ImuMode.GYRO)(OakConfig(**FAST))
    try:
        with OakCamera(OakConfig(**FAST), open_session=nothing_plugged, wait_for_device=True) as cam:
            first = cam._tracker(session)
            assert first is not None and first.gyro is not None and first.gyro.bias is not None
            first.gyro.bias.bias_rad_s, first.gyro.bias.learned = np.radians([0.5, 0.0, 0.0]), True
            same = cam._tracker(session)
            assert same is not None and same.gyro is not None and same.gyro.bias is not None
            assert same.gyro.bias.learned and same.gyro.bias.bias_rad_s == pytest.approx(np.radians([0.5, 0, 0]))
            other = cam._tracker(dataclasses.replace(session, description="OAK-D 19443010A1B2C3D4"))
            assert other is not None and other.gyro is not None and other.gyro.bias is not None
            assert not other.gyro.bias.learned
    finally:
        session.close()


@pytest.mark.parametrize(
    ("mode", "declination_deg", "warned"),
    [
        (ImuMode.GAME_ROTATION_VECTOR, 5.0, True),
        (ImuMode.GYRO, 5.0, True),
        (ImuMode.ROTATION_VECTOR, 5.0, False),  # applied: the headings are true
        (ImuMode.GAME_ROTATION_VECTOR, None, False),  # nothing asked for, nothing dropped
        (ImuMode.GYRO, None, False),
    ],
)
def test_a_declination_a_relative_imu_mode_cannot_use_is_said_once(mode, declination_deg, warned, caplog):
    """docs/oak.md, Declination: it was dropped without a word in the relative modes, while whoever
    passed --declination-deg believed the headings were true. Said once, not again at a reconnect."""
    opener = host_sessions(script(3), script(3, first_seq=10), then=("stop", "idle"), imu_mode=mode)
    cfg = OakConfig(**{**FAST, "declination_deg": declination_deg})
    with caplog.at_level(logging.WARNING, logger="drivers.oak"), OakCamera(cfg, open_session=opener) as cam:
        frames = collect(cam, 6)
        stats = cam.stats()
    assert len(frames) == 6 and stats["sessions"] == 2  # the second session did not say it again
    said = [r.getMessage() for r in caplog.records if "declination" in r.getMessage()]
    if not warned:
        assert said == []
        return
    assert len(said) == 1, said
    message = said[0]
    assert stats["heading_ref"] == "relative"
    for part in ("declination_deg 5 is not applied", f"imu_mode {mode.value}", "heading_ref relative",
                 "imu_mode rotation_vector", "--heading nmea:PORT"):
        assert part in message, (part, message)


def test_a_usb2_link_too_slow_for_the_stream_is_said_at_open():
    """An OAK on a USB2 port or cable (dai.UsbSpeed.HIGH, 480 Mbit/s) cannot carry a large colour
    stream: the device drops frames, which showed only as frames_dropped_device, with no why."""
    from drivers.oak import usb_bandwidth_warning  # here: a module without it fails this test only

    message = usb_bandwidth_warning("HIGH", 1920, 1080, 30.0)  # NV12: 1920 * 1080 * 1.5 * 30 = 93 MB/s
    assert message is not None and "\n" not in message
    for part in ("USB2", "1920x1080 at 30 fps", "93 MB/s", "frames_dropped_device", "USB3"):
        assert part in message, (part, message)
    assert "USB1" in (usb_bandwidth_warning("FULL", 640, 400, 15.0) or "")  # 12 Mbit/s: 5.8 MB/s is too much
    assert usb_bandwidth_warning("HIGH", 640, 400, 15.0) is None  # 5.8 MB/s: USB2 carries it
    for speed in ("SUPER", "SUPER_PLUS", "UNKNOWN", ""):  # USB3; a PoE device has no USB speed
        assert usb_bandwidth_warning(speed, 1920, 1080, 30.0) is None
    # The session's link speed is in stats (set here as open_device_session reads it from the device).
    opener = host_sessions(script(2))

    def on_usb2(config: OakConfig) -> OakSession:
        session = opener(config)
        session.usb_speed = "HIGH"
        return session

    with OakCamera(OakConfig(**FAST), open_session=on_usb2) as cam:
        assert len(collect(cam, 2)) == 2
        assert cam.stats()["usb_speed"] == "HIGH"


def test_a_magnetic_heading_without_a_declination_is_said_once(caplog):
    """`--heading oak-imu` on a BNO08x without --declination-deg: every estimate is in a
    magnetic-north world, off true north by the site's declination (tens of degrees in places),
    and nothing said so but the 'M' in the output."""
    cfg = OakConfig(**{**FAST, "declination_deg": None})
    opener = host_sessions(script(3), script(3, first_seq=10), then=("stop", "idle"))
    with caplog.at_level(logging.WARNING, logger="drivers.oak"), OakCamera(cfg, open_session=opener) as cam:
        frames = collect(cam, 6)
    assert len(frames) == 6 and all(f.attitude.reference is HeadingRef.MAGNETIC for f in frames)
    said = [r.getMessage() for r in caplog.records if "magnetic north" in r.getMessage()]
    assert len(said) == 1 and "--declination-deg" in said[0] and "east positive" in said[0], said
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="drivers.oak"), \
            OakCamera(OakConfig(**FAST), open_session=host_sessions(script(3))) as cam:  # declination 5
        assert len(collect(cam, 3)) == 3
    assert not [r for r in caplog.records if "magnetic north" in r.getMessage()]


def test_the_unused_declination_advice_fits_the_imu():
    from drivers.oak import unused_declination_warning  # here, not at the top: a module without it fails this test only

    # A chip without a magnetometer cannot be switched to the rotation vector: another IMU or GNSS.
    for name in ("BMI270", "LSM6DSV"):
        mode = ImuMode.GYRO if name == "BMI270" else ImuMode.GAME_ROTATION_VECTOR
        message = unused_declination_warning(-3.5, mode, name)
        assert message is not None and f"The {name} has no magnetometer" in message and "BNO085/086" in message
        assert "declination_deg -3.5 is not applied" in message and "--heading nmea:PORT" in message
    assert "set imu_mode rotation_vector" in (unused_declination_warning(2.0, ImuMode.GYRO, "BNO086") or "")
    assert unused_declination_warning(2.0, ImuMode.ROTATION_VECTOR, "BNO086") is None
    assert unused_declination_warning(None, ImuMode.GYRO, "BMI270") is None


def test_a_stalled_device_counts_as_lost():
    opener = host_sessions(script(2), script(2, first_seq=10))
    cfg = OakConfig(**{**FAST, "stall_timeout_s": 0.3})
    with OakCamera(cfg, open_session=opener) as cam:
        frames = collect(cam, 4)
        deadline = time.monotonic() + HANG_GUARD_S
        while cam.stats()["device_lost"] < 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        stats = cam.stats()
    assert len(frames) == 4 and stats["device_lost"] >= 1 and "no frame for" in stats["last_error"]


def _lost_to_the_imu_then_reconnected(first: list, caplog) -> str:
    """Run ``first`` (100 frames at 50 Hz, IMU broken after 0.3 s) paced at 10 ms a message, so
    its frames go on for 1.8 s past the break, longer than stall_timeout_s 0.5; then a good
    session. Returns the first loss said."""
    opener = host_sessions(first, script(3, first_seq=200))

    def paced(config):
        session = opener(config)
        opener.opened[-1].pause_s = 0.01
        return session

    cfg = OakConfig(**{**FAST, "stall_timeout_s": 0.5})
    with caplog.at_level(logging.WARNING, logger="drivers.oak"), OakCamera(cfg, open_session=paced) as cam:
        deadline = time.monotonic() + HANG_GUARD_S
        got_second = False
        while not got_second and time.monotonic() < deadline:
            f = cam.get(0.1)
            got_second = f is not None and np.array_equal(f.image_bgr, image(200))
        stats = cam.stats()
    assert got_second and stats["device_lost"] >= 1 and stats["reconnects"] >= 1
    lost = [r.getMessage() for r in caplog.records if "lost" in r.getMessage()]
    assert lost
    return lost[0]


def test_an_imu_that_goes_quiet_while_frames_come_counts_as_a_lost_device(caplog):
    """An OAK's IMU can stop sending while its camera goes on (depthai-python #354). Each frame
    then waited imu_wait_s and went without heading, which the rig skips: no estimate, and not a
    word until the exit summary. The IMU is part of the device: no frame covered by its reports
    for stall_timeout_s is a loss, said and reconnected, as a camera stall is."""
    first = [m for m in script(100) if m[1] == "video" or m[0] < BASE_S + 0.3]
    assert "no frame covered by the IMU's reports for" in _lost_to_the_imu_then_reconnected(first, caplog)


def test_imu_stamps_that_jump_off_the_cameras_count_as_a_lost_device(caplog):
    """The IMU's stamps can step while the camera's do not: an IMU clock that wraps at 2^32 us
    (depthai-core #965; depthai-ros #736, the IMU gone for exactly 71.6 min). Its reports still
    came, each refused as out of order, and every frame went without heading for 71.6 minutes."""
    wrap_s = 2.0**32 / 1e6
    first = [(t, kind, imu_rv(t - wrap_s, q_level(ramp_deg(t))) if kind == "imu" and t >= BASE_S + 0.3 else msg)
             for t, kind, msg in script(100)]
    assert "no frame covered by the IMU's reports for" in _lost_to_the_imu_then_reconnected(first, caplog)


def test_no_imu_session_gives_frames_without_attitude():
    msgs = [m for m in script(3) if m[1] == "video"]
    with OakCamera(OakConfig(**FAST), open_session=host_sessions(msgs, imu_mode=None)) as cam:
        frames = collect(cam, 3)
        stats = cam.stats()
    assert [f.attitude for f in frames] == [None] * 3 and stats["no_heading_no_imu"] == 3


def test_no_device_fails_at_once_with_what_to_do():
    if dai.Device.getAllAvailableDevices():
        pytest.skip("an OAK is plugged in: this test is for a machine without one")
    t0 = time.monotonic()
    with pytest.raises(OakError) as err:
        OakCamera(OakConfig())
    assert str(err.value) == NO_DEVICE_MESSAGE
    assert time.monotonic() - t0 < 5.0  # no 10 s device search


def device_info(device_id: str, name: str, state):
    return dai.DeviceInfo(name, device_id, state, dai.XLinkProtocol.X_LINK_USB_VSC,
                          dai.XLinkPlatform.X_LINK_MYRIAD_X, dai.XLinkError_t.X_LINK_SUCCESS)


class FakeDeviceList:
    """FAKE: depthai's device search (``dai.Device.getAllConnectedDevices``) with devices in the
    states a real search reports. Needed because no OAK is attached here; the DeviceInfo objects
    and the state enum are depthai's own. (DepthAI's getAllAvailableDevices() is this search
    without the devices in X_LINK_BOOTED, depthai-core DeviceBase.cpp: a device another program
    holds is connected, not available.)"""

    XLinkDeviceState = dai.XLinkDeviceState

    def __init__(self, *infos) -> None:
        self.Device = self
        self._infos = list(infos)

    def getAllConnectedDevices(self):  # noqa: N802 - depthai's name
        return list(self._infos)


def test_a_device_in_use_by_another_program_is_named_as_such():
    """It was 'no OAK device found; check the USB cable and permissions': the search for available
    devices leaves out one that another program (a second sunrig, a viewer) has booted."""
    from drivers.oak import _find_device

    busy = device_info("18443010A1B2C3D4E5", "1.3", dai.XLinkDeviceState.X_LINK_BOOTED)
    free = device_info("1844301011F0E1D2C3", "1.4", dai.XLinkDeviceState.X_LINK_UNBOOTED)
    for device_id in (None, "18443010A1B2C3D4E5", "1.3"):
        with pytest.raises(OakError) as err:
            _find_device(FakeDeviceList(busy), device_id)
        message = str(err.value)
        assert "\n" not in message and "18443010A1B2C3D4E5" in message, message
        assert "in use by another program" in message and "close" in message, message
        assert "USB cable" not in message, message
    assert _find_device(FakeDeviceList(busy, free), None).getDeviceId() == "1844301011F0E1D2C3"
    with pytest.raises(OakError, match="in use by another program"):
        _find_device(FakeDeviceList(busy, free), "18443010A1B2C3D4E5")
    with pytest.raises(OakError) as err:
        _find_device(FakeDeviceList(), None)
    assert str(err.value) == NO_DEVICE_MESSAGE
    with pytest.raises(OakError, match=r"no OAK device 'X1' found \(available: 1844301011F0E1D2C3 \(1.4\)\)"):
        _find_device(FakeDeviceList(busy, free), "X1")


def test_waiting_for_a_device_never_hangs_and_close_is_idempotent():
    opener = host_sessions()  # nothing to open, ever
    cam = OakCamera(OakConfig(**FAST), open_session=opener, wait_for_device=True)
    assert cam.get(0.2) is None
    deadline = time.monotonic() + HANG_GUARD_S
    while cam.stats()["open_failures"] < 2 and time.monotonic() < deadline:
        time.sleep(0.02)
    assert cam.stats()["open_failures"] >= 2 and cam.stats()["last_error"] == NO_DEVICE_MESSAGE
    t0 = time.monotonic()
    cam.close()
    cam.close()
    assert time.monotonic() - t0 < 2.0 and cam.finished and not cam.stats()["reader_alive"]
    assert list(cam) == []  # iterating a closed camera ends at once


def test_iteration_ends_on_close_from_another_thread():
    cam = OakCamera(OakConfig(**FAST), open_session=host_sessions(script(3)))
    got: list = []
    t = threading.Thread(target=lambda: got.extend(cam), daemon=True)
    t.start()
    deadline = time.monotonic() + HANG_GUARD_S
    while len(got) < 3 and time.monotonic() < deadline:
        time.sleep(0.02)
    cam.close()
    t.join(HANG_GUARD_S)
    assert not t.is_alive() and len(got) == 3


def test_a_bug_in_the_reader_surfaces_as_an_error():
    def broken(config):
        raise ZeroDivisionError("a bug")

    cam = OakCamera(OakConfig(**FAST), open_session=broken, wait_for_device=True)
    with pytest.raises(OakError, match="OAK reader failed: ZeroDivisionError: a bug"):
        list(cam)
    cam.close()


def test_slow_consumer_drops_oldest_and_counts():
    n = 12
    with OakCamera(OakConfig(**FAST), open_session=host_sessions(script(n)), output_queue=4) as cam:
        deadline = time.monotonic() + HANG_GUARD_S
        while cam.stats()["frames_out"] < n and time.monotonic() < deadline:
            time.sleep(0.02)
        frames = collect(cam, 4, timeout_s=1.0)
        stats = cam.stats()
    assert [f.seq for f in frames] == list(range(n - 4, n))
    assert stats["frames_dropped_consumer"] == n - 4


@pytest.mark.parametrize(
    ("kw", "match"),
    [
        ({"fps": 0}, "fps"),
        ({"width": -1}, "width"),
        ({"imu_mode": "magnetic"}, "imu_mode"),
        ({"declination_deg": 200}, "declination"),
        ({"backoff_s": (2.0, 1.0)}, "backoff"),
        ({"sensor_world": "nue"}, "sensor_world"),
        ({"cam_from_imu": ((1, 0, 0), (0, 1, 0), (0, 0, -1))}, "proper rotation"),
        ({"intrinsics": INTR}, "match the output size"),
    ],
)
def test_config_is_validated(kw, match):
    with pytest.raises(ValidationError, match=match):
        OakConfig(**kw)


def test_import_needs_no_depthai():
    """``import drivers.oak`` stays cheap and free of side effects: depthai loads on first use."""
    import subprocess
    import sys

    code = "import sys, drivers.oak, drivers.imu_heading; sys.exit('depthai' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], timeout=60).returncode == 0


def test_host_only_pipelines_cannot_hold_the_device_nodes():
    """What stays behind the hardware marker, and why: depthai refuses Camera and IMU nodes in a
    host-only pipeline, so only open_device_session needs an OAK."""
    p = dai.Pipeline(False)
    with pytest.raises(RuntimeError, match="host only"):
        p.create(dai.node.Camera)
    with pytest.raises(RuntimeError, match="host only"):
        p.create(dai.node.IMU)


# --- on a real device --------------------------------------------------------------------------


@pytest.mark.hardware
def test_real_oak_frames_and_attitude():
    """An OAK with an IMU, standing upright on a level surface: frames at the configured size,
    calibrated intrinsics, and an attitude close to level (this checks the IMU-to-camera rotation's
    down axis and the rotation vector's world frame; the heading's sign needs the north check)."""
    cfg = OakConfig(width=640, height=400, fps=10)
    with OakCamera(cfg) as cam:
        frames = collect(cam, 20, timeout_s=20.0)
        stats = cam.stats()
    assert len(frames) == 20, stats
    f = frames[-1]
    assert f.image_bgr.shape == (400, 640, 3) and 200 < f.intrinsics.fx < 2000
    assert all(b.t_mono_s > a.t_mono_s for a, b in zip(frames, frames[1:], strict=False))
    assert abs(f.t_mono_s - time.monotonic()) < 2.0  # DepthAI's host clock is time.monotonic()
    if stats["imu_mode"] is not None:
        assert f.attitude is not None, stats
        assert abs(math.degrees(f.attitude.pitch_rad)) < 20 and abs(math.degrees(f.attitude.roll_rad)) < 20, stats


@pytest.mark.hardware
def test_real_oak_heading_against_a_compass():
    """Point the camera at a known true heading and set SUNRIG_OAK_EXPECT_HEADING_DEG and
    SUNRIG_DECLINATION_DEG; the rotation vector's heading must agree within 15 deg."""
    import os

    want = os.environ.get("SUNRIG_OAK_EXPECT_HEADING_DEG")
    if want is None:
        pytest.skip("set SUNRIG_OAK_EXPECT_HEADING_DEG (and SUNRIG_DECLINATION_DEG) to run the compass check")
    cfg = OakConfig(imu_mode="rotation_vector", declination_deg=float(os.environ.get("SUNRIG_DECLINATION_DEG", 0)))
    with OakCamera(cfg) as cam:
        frames = [f for f in collect(cam, 30, timeout_s=20.0) if f.attitude is not None]
    assert frames, "no frame carried a heading: is the magnetometer calibrated (move in a figure-eight)?"
    got = math.degrees(frames[-1].attitude.heading_rad)
    assert abs((got - float(want) + 180) % 360 - 180) < 15, got


def test_importing_depthai_leaves_stdout_to_the_estimates():
    # depthai's C++ logger prints import-time warnings (here: "USB protocol not available", as in
    # any container without /dev/bus/usb) on stdout, where `sunrig run --jsonl -` writes JSON.
    bare = subprocess.run([sys.executable, "-c", "import depthai"], capture_output=True, text=True, timeout=120)
    if not bare.stdout:
        pytest.skip("depthai prints nothing on import here: nothing to keep off stdout")
    code = "from drivers.oak import _dai; _dai(); print('{}')"
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout == "{}\n"  # only what the program itself printed


def test_stdout_is_swapped_for_the_first_depthai_import_only(monkeypatch):
    # fd 1 is the whole process's: a reconnect's _dai() while `--jsonl -` streams must not swap it.
    import contextlib

    import drivers.oak as oak

    oak._dai()
    swaps: list[int] = []

    def counted() -> contextlib.nullcontext:
        swaps.append(1)
        return contextlib.nullcontext()

    monkeypatch.setattr(oak, "_stdout_to_stderr", counted)
    oak._dai()
    assert swaps == []


def test_an_imu_rate_too_slow_for_the_gap_it_may_bridge_is_refused():
    """At 10 Hz the reports are max_imu_gap_s (0.1 s) apart: with any jitter, about every other
    frame went without heading (imu_gap) and gyro integration restarted with a new epoch whenever
    a step came out longer. Two report intervals must fit in the gap: one late or lost is bridged."""
    with pytest.raises(ValidationError, match=r"^OakConfig.imu_rate_hz: 10 Hz .* at least 20 Hz") as err:
        OakConfig(imu_rate_hz=10)
    assert "\n" not in str(err.value)
    assert OakConfig(imu_rate_hz=20).imu_rate_hz == 20
    assert OakConfig(imu_rate_hz=8, max_imu_gap_s=0.3).imu_rate_hz == 8
    assert OakConfig(imu_rate_hz=1, imu_mode="none").imu_rate_hz == 1  # no IMU: nothing to bridge


def test_a_frame_type_that_is_not_a_colour_image_is_refused_at_once():
    """OakConfig.frame_type names a dai.ImgFrame.Type. One whose getCvFrame() is not BGR uint8
    (GRAY8, RAW10, ...) made every frame a bad_frame with nothing said, and a name that is no type
    at all ('BGR') was an AttributeError after the device was opened, which left it open."""
    for bad in ("GRAY8", "RAW10", "BGR", "nv12"):
        with pytest.raises(ValidationError, match=rf"^OakConfig.frame_type: expected one of .*NV12.*, got '{bad}'$"):
            OakConfig(frame_type=bad)
    colour = np.random.default_rng(0).integers(0, 256, (H, W, 3), dtype=np.uint8)
    for name in FRAME_TYPES_BGR:  # each accepted type reads back as a BGR colour image
        OakConfig(frame_type=name)
        f = dai.ImgFrame()
        f.setCvFrame(colour, getattr(dai.ImgFrame.Type, name))
        out = f.getCvFrame()
        assert out.shape == (H, W, 3) and out.dtype == np.uint8, name
