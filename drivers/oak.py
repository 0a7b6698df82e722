"""OAK colour camera + IMU as a Frame source (DepthAI v3): the I/O shell.

Three layers, so that everything but device creation runs without a device, through the real
depthai library (``docs/oak.md`` is the specification, ``tests/test_oak.py`` the tests):

- :func:`open_device_session` is the only device-specific part: it opens a device, reads its
  calibration and IMU type, and builds a pipeline with a ``dai.node.Camera`` colour output and a
  ``dai.node.IMU``. It returns an :class:`OakSession`: a pipeline and its two outputs. A test
  hands :class:`OakCamera` a factory returning a host-only pipeline instead (a
  ``dai.node.ThreadedHostNode`` sending real ``dai.ImgFrame`` / ``dai.IMUData`` messages).
- :class:`OakMessageHandler` turns ``dai.ImgFrame`` and ``dai.IMUData`` messages into
  :class:`rig.types.Frame`: image, mid-exposure time, sequence number, and the attitude
  interpolated from the IMU at that time (:class:`drivers.imu_heading.AttitudeTracker`). No I/O
  and no clock: the time of arrival is an argument.
- :class:`OakCamera` owns one reader thread that starts a session's pipeline, drains its output
  queues with bounded waits, hands messages to the handler and queues the Frames for the caller
  (drop-oldest). A lost device (an exception from depthai, a stopped pipeline, no frame for
  ``stall_timeout_s``) is counted and logged, the session is torn down, and a new one is opened
  with a backoff that doubles up to ``backoff_s[1]``. ``close()`` is idempotent and bounded.

depthai is imported lazily (:func:`_dai`), so ``import drivers.oak`` works and costs nothing on a
machine without it.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Any

import numpy as np

from drivers.imu_heading import (
    ENU_FROM_SENSOR_WORLD,
    IMU_PENDING,
    INACCURATE,
    NO_IMU_YET,
    OK,
    VERTICAL,
    WANTS,
    AttitudeTracker,
    ImuMode,
    cam_from_imu_default,
    choose_imu_mode,
    imu_caps,
    imu_sensors,
    validate_rotation,
)
from rig.errors import OakError, ValidationError
from rig.lasting import LastingCondition
from rig.portio import Backoff, begin_stop, join_worker
from rig.types import Frame, Intrinsics

log = logging.getLogger(__name__)

NO_DEVICE_MESSAGE = (
    "no OAK device found; check the USB cable and permissions (udev rules), or use --camera opencv:N"
)
_HEADING_REASONS = ("no_imu", "no_imu_yet", "too_old", "imu_pending", "imu_gap", "vertical", "inaccurate")
HANDLER_COUNTS = (
    "frames_in",  # ImgFrames received
    "frames_out",  # Frames made
    "frames_with_heading",  # ... of which carry an attitude
    "bad_frames",  # an ImgFrame that is not a BGR image of the configured size: dropped
    "frames_dropped_device",  # gaps in the device's sequence numbers (frames it never sent us)
    "seq_backwards",  # a device sequence number not above the previous one: dropped
    "pending_overflow",  # frames released without waiting for the IMU because too many waited
    "imu_messages",  # IMUData received
    "imu_reports",  # reports in them that were used
    "bad_imu",  # IMU messages, or reports in them, that could not be read
    *(f"no_heading_{r}" for r in _HEADING_REASONS),  # frames without attitude, by reason
)
CAMERA_COUNTS = (
    "frames_dropped_consumer",  # Frames dropped because the caller did not take them in time
    "sessions",  # pipelines started
    "open_failures",  # attempts to open a device that failed
    "device_lost",  # sessions that ended by an error, a stopped pipeline or a stall
    "reconnects",  # sessions started after a lost one
)


def _dai():
    """depthai, imported on first use, with an error that says what to install."""
    dai = sys.modules.get("depthai")
    if dai is None:
        try:
            # Only the first import prints. fd 1 is the whole process's: swapping it again at every
            # session (reconnects while `--jsonl -` streams) would send those estimates to stderr.
            with _stdout_to_stderr():
                import depthai
        except ImportError as exc:  # pragma: no cover - depends on the environment
            raise OakError("the OAK driver needs DepthAI v3: pip install 'depthai>=3'") from exc
        dai = depthai
    if not hasattr(dai.node, "Camera") or not hasattr(dai.node, "ThreadedHostNode"):  # pragma: no cover
        raise OakError(f"the OAK driver needs DepthAI v3, found depthai {dai.__version__}: pip install 'depthai>=3'")
    return dai


@contextlib.contextmanager
def _stdout_to_stderr() -> Iterator[None]:
    """File descriptor 1 goes to 2 for the block. depthai's C++ logger prints its import-time
    warnings (e.g. "USB protocol not available") on stdout, where `sunrig run --jsonl -` writes
    estimates: a JSON reader would choke on the first line."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        os.dup2(saved, 1)
        os.close(saved)


# ---------------------------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------------------------

# The dai.ImgFrame.Type names whose getCvFrame() is a BGR uint8 colour image, and their bytes a
# pixel on the link. Any other type (GRAY8, RAW10, ...) would make every frame a bad one.
FRAME_TYPES_BGR = {"NV12": 1.5, "NV21": 1.5, "YUV420p": 1.5, "YUV422i": 2.0,
                   "BGR888i": 3.0, "BGR888p": 3.0, "RGB888i": 3.0, "RGB888p": 3.0}


@dataclass(frozen=True)
class OakConfig:
    """What to open and how. Degrees only here, at the interface (``declination_deg``)."""

    width: int = 640
    height: int = 400
    fps: float = 15.0
    socket: str = "CAM_A"  # dai.CameraBoardSocket name of the colour camera
    frame_type: str | None = None  # dai.ImgFrame.Type name; None: the device's choice (converted to BGR)
    device_id: str | None = None  # device id / name / IP; None: the first one found
    imu_mode: str = "auto"  # auto | rotation_vector | game_rotation_vector | gyro | none
    imu_rate_hz: int = 100
    declination_deg: float | None = None  # east positive; with the rotation vector gives true heading
    sensor_world: str = "enu"  # the rotation vector's world frame (enu per the BNO08x datasheet)
    cam_from_imu: tuple | None = None  # 3x3 override; else the calibration; else a per-product default
    intrinsics: Intrinsics | None = None  # override for a device without a colour calibration
    max_rv_accuracy_deg: float = 45.0  # rotation vectors less accurate than this are not used
    imu_history_s: float = 2.0  # how far back IMU orientations are kept
    max_imu_gap_s: float = 0.1  # no interpolation across a longer gap between IMU reports
    imu_wait_s: float = 0.15  # how long a frame waits for the IMU reports that bracket it
    queue_size: int = 4  # device -> host frame queue (non-blocking: the device drops the oldest)
    poll_s: float = 0.05  # the longest single wait of the reader thread
    startup_timeout_s: float = 15.0  # no first frame within this: the session failed
    stall_timeout_s: float = 3.0  # no frame for this long after the first: the device is lost
    backoff_s: tuple[float, float] = (0.5, 8.0)  # reconnect backoff: first and longest wait

    def __post_init__(self) -> None:
        for name in ("width", "height", "imu_rate_hz", "queue_size"):
            v = getattr(self, name)
            if not isinstance(v, int | np.integer) or isinstance(v, bool) or v <= 0:
                raise ValidationError(f"OakConfig.{name}: expected a positive integer, got {v!r}")
        for name in ("fps", "max_rv_accuracy_deg", "imu_history_s", "max_imu_gap_s", "poll_s",
                     "startup_timeout_s", "stall_timeout_s"):
            v = getattr(self, name)
            if not isinstance(v, int | float) or not math.isfinite(v) or v <= 0:
                raise ValidationError(f"OakConfig.{name}: expected a finite number > 0, got {v!r}")
        if not (isinstance(self.imu_wait_s, int | float) and 0 <= self.imu_wait_s < 10):
            raise ValidationError(f"OakConfig.imu_wait_s: expected seconds in [0, 10), got {self.imu_wait_s!r}")
        if self.frame_type is not None and self.frame_type not in FRAME_TYPES_BGR:
            raise ValidationError(f"OakConfig.frame_type: expected one of {', '.join(FRAME_TYPES_BGR)} "
                                  f"(a colour image), or None for the device's choice, got {self.frame_type!r}")
        if self.sensor_world not in ENU_FROM_SENSOR_WORLD:
            raise ValidationError(
                f"OakConfig.sensor_world: expected one of {', '.join(ENU_FROM_SENSOR_WORLD)}, got {self.sensor_world!r}"
            )
        if self.imu_mode not in WANTS:
            raise ValidationError(f"OakConfig.imu_mode: expected one of {', '.join(WANTS)}, got {self.imu_mode!r}")
        # Two report intervals within the gap the tracker bridges, so one late or lost report is
        # bridged; at one interval per gap, jitter alone leaves frames without heading (imu_gap)
        # and restarts gyro integration (a new zero and epoch) over and over.
        min_rate_hz = math.ceil(2.0 / self.max_imu_gap_s - 1e-9)
        if self.imu_mode != "none" and self.imu_rate_hz < min_rate_hz:
            raise ValidationError(
                f"OakConfig.imu_rate_hz: {self.imu_rate_hz} Hz puts the IMU reports {1.0 / self.imu_rate_hz:.3g} s "
                f"apart, too far for max_imu_gap_s {self.max_imu_gap_s:g} s to bridge a late or lost one, and "
                f"frames would go without heading (imu_gap); use at least {min_rate_hz} Hz, or raise max_imu_gap_s"
            )
        d = self.declination_deg
        if d is not None and not (isinstance(d, int | float) and math.isfinite(d) and -180 <= d <= 180):
            raise ValidationError(f"OakConfig.declination_deg: expected within [-180, 180] (east +), got {d!r}")
        Backoff(self.backoff_s, lambda msg: ValidationError(f"OakConfig.{msg}"))  # validates
        if self.cam_from_imu is not None:
            validate_rotation("OakConfig.cam_from_imu", self.cam_from_imu)
        if self.intrinsics is not None and (self.intrinsics.width, self.intrinsics.height) != (self.width, self.height):
            raise ValidationError(
                f"OakConfig.intrinsics: expected {self.width}x{self.height} to match the output size, "
                f"got {self.intrinsics.width}x{self.intrinsics.height}"
            )

    @property
    def declination_rad(self) -> float | None:
        return None if self.declination_deg is None else math.radians(self.declination_deg)


def unused_declination_warning(declination_deg: float | None, mode: ImuMode, imu_name: str) -> str | None:
    """What to tell a user whose declination the IMU mode cannot use, or None when it applies.

    A declination turns a magnetic heading into a true one; the game rotation vector and gyro
    integration give a heading relative to the session's start, so the tracker drops it. Said, not
    silent: whoever passed it believes the estimates are referenced to true north.
    """
    if declination_deg is None or mode is ImuMode.ROTATION_VECTOR:
        return None
    caps = imu_caps(imu_name)
    imu = imu_name or "IMU"
    if caps is not None and caps.rotation_vector:  # the chip has it: this mode was asked for
        fix = f"For a true heading set imu_mode rotation_vector (or auto) to use the {imu}'s magnetometer"
    else:
        fix = (f"The {imu} has no magnetometer: for a true heading use an OAK whose IMU has one "
               "(BNO085/086, imu_mode rotation_vector)")
    return (f"declination_deg {declination_deg:g} is not applied: the IMU gives a heading relative to its "
            f"start in imu_mode {mode.value}, so estimates carry heading_ref relative, not true. {fix}, or use a "
            "GNSS compass (--heading nmea:PORT); or drop --declination-deg")


# What a USB link carries of an OAK's stream in practice, bytes/s, by dai.UsbSpeed name: about half
# the bus rate (protocol and XLink overhead, other devices on the hub). USB3 (SUPER, SUPER_PLUS)
# and PoE (UNKNOWN) carry any colour stream this driver asks for.
_USB_BYTES_S = {"LOW": 0.1e6, "FULL": 0.7e6, "HIGH": 30e6}
_USB_NAMES = {"LOW": "USB1 (low speed, 1.5 Mbit/s)", "FULL": "USB1 (full speed, 12 Mbit/s)",
              "HIGH": "USB2 (480 Mbit/s)"}


def usb_bandwidth_warning(usb_speed: str, width: int, height: int, fps: float,
                          bytes_per_px: float = 1.5) -> str | None:
    """What to tell a user whose USB link (``dai.UsbSpeed`` name) cannot carry the colour stream
    (NV12: 1.5 bytes a pixel), or None. Too slow a link makes the device drop frames, which
    otherwise show only as ``frames_dropped_device``."""
    budget = _USB_BYTES_S.get((usb_speed or "").upper())
    need = width * height * bytes_per_px * fps
    if budget is None or need <= budget:
        return None
    return (f"the OAK is connected over {_USB_NAMES[usb_speed.upper()]}: {width}x{height} at {fps:g} fps needs "
            f"about {need / 1e6:.0f} MB/s, more than the about {budget / 1e6:g} MB/s it carries, so the device "
            "will drop frames (frames_dropped_device); plug it into a USB3 port with a USB3 cable, or lower "
            "--width/--height/--fps")


# ---------------------------------------------------------------------------------------------
# Calibration (real dai.CalibrationHandler objects; no device needed)
# ---------------------------------------------------------------------------------------------


def intrinsics_from_matrix(k, width: int, height: int) -> Intrinsics:
    """Intrinsics of a 3x3 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] for an image size."""
    m = np.asarray(k, dtype=np.float64)
    if m.shape != (3, 3):
        raise ValidationError(f"camera matrix: expected shape (3, 3), got {m.shape}")
    return Intrinsics(fx=m[0, 0], fy=m[1, 1], cx=m[0, 2], cy=m[1, 2], width=width, height=height)


def read_intrinsics(calib: Any, socket: Any, width: int, height: int) -> Intrinsics:
    """The colour camera's intrinsics at the output size from a ``dai.CalibrationHandler``.

    ``keepAspectRatio=True`` (depthai's default) scales and centre-crops like the Camera node's
    ``ImgResizeMode.CROP``, which :func:`open_device_session` asks for.
    """
    try:
        k = calib.getCameraIntrinsics(socket, width, height)
    except RuntimeError as exc:
        raise OakError(
            f"the OAK calibration has no intrinsics for {socket}: {exc}; "
            "recalibrate the device or pass OakConfig.intrinsics"
        ) from None
    return intrinsics_from_matrix(k, width, height)


def read_cam_from_imu(calib: Any, socket: Any, product_name: str = "") -> tuple[np.ndarray, str]:
    """Rotation taking IMU axes to the colour camera's (OpenCV) axes, and where it came from.

    ``getImuToCameraExtrinsics(socket)`` is the 4x4 transform p_cam = R p_imu + t; its rotation is
    used when the calibration has one that is a proper rotation. Otherwise (many devices carry
    no IMU extrinsics, or an all-zero matrix) the per-product default of
    :func:`drivers.imu_heading.cam_from_imu_default`.
    """
    try:
        t = np.asarray(calib.getImuToCameraExtrinsics(socket), dtype=np.float64)
        return validate_rotation("imu extrinsics", t[:3, :3]), "calibration"
    except (RuntimeError, ValidationError, IndexError, ValueError) as exc:
        r, source = cam_from_imu_default(product_name)
        return r, f"{source}; calibration has none ({str(exc).splitlines()[0][:80]})"


# ---------------------------------------------------------------------------------------------
# Messages -> Frames (shared by the device and by host-only pipelines)
# ---------------------------------------------------------------------------------------------


def _stamped(report: Any) -> bool:
    """A report the device filled in: an unused report in an IMUPacket keeps timestamp 0."""
    return report.getTimestamp() != timedelta(0)


def mid_exposure_s(msg: Any) -> float:
    """Monotonic seconds at mid-exposure of an ImgFrame. DepthAI's ``getTimestamp()`` marks the
    END of exposure (``getTimestamp(CameraExposureOffset.MIDDLE)`` is ``ts - exposure / 2``)."""
    return (msg.getTimestamp() - msg.getExposureTime() / 2).total_seconds()


class OakMessageHandler:
    """``dai.IMUData`` and ``dai.ImgFrame`` in, :class:`Frame` out. No I/O, no clock.

    A frame waits (up to ``imu_wait_s`` after it arrived, at most ``max_pending`` frames) until
    the IMU reports that bracket its mid-exposure time are in; then it gets the interpolated
    attitude, or none with the reason counted (``no_heading_<reason>``). Frame sequence numbers
    are the device's plus an offset that makes them continue from ``first_seq``, so a frame the
    device dropped leaves a gap, and a new session never repeats a number.
    """

    def __init__(
        self,
        intrinsics: Intrinsics,
        tracker: AttitudeTracker | None,
        *,
        imu_wait_s: float = 0.15,
        max_pending: int = 16,
        first_seq: int = 0,
        counts: dict[str, int] | None = None,
    ) -> None:
        self.intrinsics = intrinsics
        self.tracker = tracker
        self.imu_wait_s = float(imu_wait_s)
        self.max_pending = int(max_pending)
        self.next_seq = int(first_seq)
        self._offset: int | None = None
        self._last_dev_seq: int | None = None
        self._pending: deque[tuple[float, int, np.ndarray, float]] = deque()
        self.counts = counts if counts is not None else dict.fromkeys(HANDLER_COUNTS, 0)
        # When (the ready() time) a frame last found IMU reports around it, with a heading or not
        # for a reason of its own (inaccurate, vertical): None before the first.
        self.covered_s: float | None = None

    # -- IMU --------------------------------------------------------------------------------
    def on_imu(self, msg: Any) -> None:
        tr = self.tracker
        self.counts["imu_messages"] += 1
        if tr is None:
            return
        try:
            packets = list(msg.packets)
        except (AttributeError, TypeError) as exc:  # not IMUData
            self.counts["bad_imu"] += 1
            log.debug("unusable IMU message: %s", exc)
            return
        for packet in packets:
            # Report by report: a bad one (a zero quaternion) costs itself, not the rest of a batch
            # of up to 10 packets, whose loss would leave a hole of imu_gap frames.
            self._on_report(tr, packet, "acceleroMeter")
            self._on_report(tr, packet, "gyroscope" if tr.mode is ImuMode.GYRO else "rotationVector")

    def _on_report(self, tr: AttitudeTracker, packet: Any, kind: str) -> None:
        try:
            r = getattr(packet, kind)
            if not _stamped(r):
                return
            t = r.getTimestamp().total_seconds()
            if kind == "acceleroMeter":
                tr.add_accelerometer(t, (r.x, r.y, r.z))
                used = True
            elif kind == "gyroscope":
                used = tr.add_gyro(t, (r.x, r.y, r.z))
            else:  # DepthAI puts every rotation-vector kind here
                used = tr.add_rotation_vector(t, (r.real, r.i, r.j, r.k), r.rotationVectorAccuracy)
        except (AttributeError, TypeError, ValueError) as exc:  # not an IMUPacket, or a zero quaternion
            self.counts["bad_imu"] += 1
            log.debug("unusable IMU report: %s", exc)
            return
        if used:
            self.counts["imu_reports"] += 1

    # -- frames -----------------------------------------------------------------------------
    def on_frame(self, msg: Any, now_s: float) -> None:
        """Take an ImgFrame that arrived at monotonic ``now_s``; :meth:`ready` hands it out."""
        self.counts["frames_in"] += 1
        try:
            img = msg.getCvFrame()
            t_mid = mid_exposure_s(msg)
            dev_seq = int(msg.getSequenceNum())
        except (AttributeError, TypeError, RuntimeError) as exc:
            self.counts["bad_frames"] += 1
            log.debug("unusable frame message: %s", exc)
            return
        if self._last_dev_seq is not None:
            if dev_seq <= self._last_dev_seq:
                self.counts["seq_backwards"] += 1
                return
            self.counts["frames_dropped_device"] += dev_seq - self._last_dev_seq - 1
        if self._offset is None:
            self._offset = self.next_seq - dev_seq
        # Before the size check: a frame of the wrong size was sent, and counted as bad; left out
        # of the sequence, the next frame counted it as dropped by the device too.
        self._last_dev_seq = dev_seq
        want = (self.intrinsics.height, self.intrinsics.width, 3)
        if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.shape != want:
            self.counts["bad_frames"] += 1
            log.debug("frame is %s %s, expected uint8 %s", getattr(img, "dtype", None), getattr(img, "shape", None),
                      want)
            return
        if not img.flags.owndata:
            img = img.copy()  # the message's buffer is not ours to keep
        self._pending.append((t_mid, dev_seq + self._offset, img, float(now_s)))

    def ready(self, now_s: float) -> list[Frame]:
        """Frames whose attitude is settled at monotonic ``now_s``, in order."""
        out: list[Frame] = []
        while self._pending:
            t_mid, seq, img, arrived = self._pending[0]
            if self.tracker is None:
                att, reason = None, "no_imu"
            else:
                att, reason = self.tracker.attitude_at(t_mid)
                # A frame before the session's first IMU report waits for it too (docs/oak.md).
                if reason in (IMU_PENDING, NO_IMU_YET) and now_s - arrived < self.imu_wait_s:
                    if len(self._pending) <= self.max_pending:
                        break
                    self.counts["pending_overflow"] += 1
            self._pending.popleft()
            if reason in (OK, INACCURATE, VERTICAL) and math.isfinite(now_s):
                self.covered_s = now_s
            frame = self._make(t_mid, seq, img, att, reason)
            if frame is not None:
                out.append(frame)
        return out

    def drain(self) -> list[Frame]:
        """Every waiting frame, settled now (a session is ending: no more IMU will come)."""
        return self.ready(math.inf)

    def _make(self, t_mid: float, seq: int, img: np.ndarray, att: Any, reason: str) -> Frame | None:
        try:
            frame = Frame(t_mono_s=t_mid, seq=seq, image_bgr=img, intrinsics=self.intrinsics, attitude=att)
        except ValidationError as exc:
            self.counts["bad_frames"] += 1
            log.debug("frame rejected: %s", exc)
            return None
        self.next_seq = seq + 1
        self.counts["frames_out"] += 1
        if att is not None:
            self.counts["frames_with_heading"] += 1
        elif reason != OK:
            self.counts[f"no_heading_{reason}"] += 1
        return frame


# ---------------------------------------------------------------------------------------------
# Sessions: the device-specific part
# ---------------------------------------------------------------------------------------------


@dataclass
class OakSession:
    """A built (not yet started) pipeline and what the shared code needs to read it."""

    pipeline: Any  # dai.Pipeline
    video: Any  # dai.Node.Output of ImgFrames
    imu: Any | None  # dai.Node.Output of IMUData, or None (no IMU, imu_mode none)
    intrinsics: Intrinsics
    imu_mode: ImuMode | None
    cam_from_imu: np.ndarray | None
    cam_from_imu_source: str = ""
    imu_name: str = ""
    description: str = "OAK"
    usb_speed: str = ""  # dai.UsbSpeed name of the link (HIGH is USB2, SUPER USB3; UNKNOWN for PoE)
    on_close: list[Callable[[], None]] = field(default_factory=list)  # e.g. device.close

    def close(self) -> None:
        """Stop the pipeline and release the device (may block inside depthai: call it bounded).

        ``wait()`` after ``stop()`` matters: it joins the pipeline's host-node threads with the GIL
        released. Without it the last reference to the pipeline, dropped anywhere, runs a destructor
        that joins them while holding the GIL, and a Python host node can never finish (deadlock).
        """
        for step in [self.pipeline.stop, self.pipeline.wait, *self.on_close]:
            try:
                step()
            except Exception as exc:  # noqa: BLE001 - a dead device fails in many ways; keep tearing down
                log.debug("OAK teardown step failed: %s", exc)


def _in_use_error(info: Any) -> OakError:
    return OakError(f"OAK {info.getDeviceId()} ({info.name}) is in use by another program (state {info.state.name}): "
                    "close it (another sunrig, a DepthAI viewer) or wait a few seconds after it exits, then try again")


def _find_device(dai: Any, device_id: str | None) -> Any:
    """The DeviceInfo to open, found without DepthAI's ~10 s search when nothing is connected.

    DepthAI's available devices are its connected ones less those already booted: a device that
    another program holds is connected but not available, and is named as in use, not as missing.
    One search (about 0.5 s) serves both: getAllAvailableDevices() is the same search, filtered."""
    connected = dai.Device.getAllConnectedDevices()
    infos = [i for i in connected if i.state != dai.XLinkDeviceState.X_LINK_BOOTED]
    wanted = [i for i in infos if device_id is None or device_id in (i.getDeviceId(), i.name)]
    if wanted:
        return wanted[0]
    busy = [i for i in connected if device_id is None or device_id in (i.getDeviceId(), i.name)]
    if busy:
        raise _in_use_error(busy[0])
    if device_id is None:
        raise OakError(NO_DEVICE_MESSAGE)
    found = ", ".join(f"{i.getDeviceId()} ({i.name})" for i in infos) or "none"
    raise OakError(f"no OAK device {device_id!r} found (available: {found}); check the id and the cable")


def open_device_session(config: OakConfig) -> OakSession:
    """Open an OAK and build its pipeline: ``Camera`` colour output and ``IMU`` in the chosen mode."""
    dai = _dai()
    info = _find_device(dai, config.device_id)
    try:
        device = dai.Device(info)
    except RuntimeError as exc:
        raise OakError(f"cannot open OAK {info.getDeviceId()}: {exc}; it may be in use by another process, "
                       "or unplug and replug it") from None
    try:
        # This driver reconnects itself (with backoff, counted, logged); depthai's own attempts
        # would hide the loss and block the reader thread meanwhile.
        device.setMaxReconnectionAttempts(0)
        try:
            socket = getattr(dai.CameraBoardSocket, config.socket)
        except AttributeError:
            raise OakError(f"OakConfig.socket {config.socket!r} is not a dai.CameraBoardSocket; use CAM_A") from None
        calib = device.readCalibration()
        try:
            product = device.getProductName()
        except RuntimeError:  # older EEPROMs carry no product name: the default mount then applies
            product = ""
        imu_name = device.getConnectedIMU()
        try:
            usb_speed = device.getUsbSpeed().name
        except RuntimeError:  # not a USB device
            usb_speed = "UNKNOWN"
        intrinsics = config.intrinsics or read_intrinsics(calib, socket, config.width, config.height)
        mode = choose_imu_mode(imu_name, config.imu_mode)
        cam_from_imu, source = None, ""
        if mode is not None:
            if config.cam_from_imu is not None:
                cam_from_imu, source = validate_rotation("cam_from_imu", config.cam_from_imu), "config"
            else:
                cam_from_imu, source = read_cam_from_imu(calib, socket, product)
        pipeline = dai.Pipeline(device)
        cam = pipeline.create(dai.node.Camera).build(socket)
        ftype = getattr(dai.ImgFrame.Type, config.frame_type) if config.frame_type else None
        video = cam.requestOutput((config.width, config.height), type=ftype, resizeMode=dai.ImgResizeMode.CROP,
                                  fps=float(config.fps))
        imu_out = None
        if mode is not None:
            imu = pipeline.create(dai.node.IMU)
            imu.enableIMUSensor([getattr(dai.IMUSensor, s) for s in imu_sensors(mode, imu_name)],
                                int(config.imu_rate_hz))
            imu.setBatchReportThreshold(1)  # send every report at once: latency over USB efficiency
            imu.setMaxBatchReports(10)
            imu_out = imu.out
    except (ValidationError, OakError):
        device.close()
        raise
    except RuntimeError as exc:
        device.close()
        raise OakError(f"cannot set up OAK {info.getDeviceId()}: {exc}") from None
    return OakSession(pipeline=pipeline, video=video, imu=imu_out, intrinsics=intrinsics, imu_mode=mode,
                      cam_from_imu=cam_from_imu, cam_from_imu_source=source, imu_name=imu_name,
                      description=f"{product or 'OAK'} {info.getDeviceId()}", usb_speed=usb_speed,
                      on_close=[device.close])


# ---------------------------------------------------------------------------------------------
# The shell
# ---------------------------------------------------------------------------------------------


class _DeviceLost(Exception):
    """The session's device stopped delivering (a stopped pipeline, a stall)."""


class OakCamera:
    """Frames from an OAK's colour camera with the IMU's attitude at each frame's mid-exposure.

    Iterate it (or call :meth:`get`) for :class:`rig.types.Frame`; use it as a context manager.
    The constructor opens the device at once and raises :class:`OakError` with what to do when
    it cannot (``wait_for_device=True`` instead keeps trying in the background). ``open_session``
    replaces :func:`open_device_session`, e.g. by a host-only pipeline in tests.

    Frames wait for the caller in a queue of ``output_queue``; when it is full the oldest is
    dropped and counted (``frames_dropped_consumer``): a slow caller sees fresh frames, never
    a growing lag.
    """

    def __init__(
        self,
        config: OakConfig | None = None,
        *,
        open_session: Callable[[OakConfig], OakSession] | None = None,
        wait_for_device: bool = False,
        output_queue: int = 8,
        clock: Callable[[], float] = time.monotonic,
        join_timeout_s: float = 3.0,
    ) -> None:
        self.config = config or OakConfig()
        self._open = open_session or open_device_session
        self._clock = clock
        self._join_timeout_s = float(join_timeout_s)
        self._out_max = int(output_queue)
        self._cond = threading.Condition()  # guards everything below
        self._frames: deque[Frame] = deque()
        self._counts = dict.fromkeys(HANDLER_COUNTS, 0)
        self._counts.update(dict.fromkeys(CAMERA_COUNTS, 0))
        self._info: dict[str, Any] = {"device": None, "usb_speed": None, "imu": None, "imu_mode": None,
                                      "heading_ref": None, "cam_from_imu_source": None,
                                      "gravity_mismatch_deg": None, "imu_counts": {}}
        self._last_error: str | None = None
        self._failure: str | None = None
        self._next_seq = 0
        self._stop = threading.Event()
        self._finished = threading.Event()
        self._warned: set[str] = set()
        # Whether the rotation vector is too inaccurate for a heading: said when that starts and ends,
        # each time (a magnetometer disturbed mid-run, then clear again), not once a run.
        self._accuracy = LastingCondition(None)
        self._seen_inaccurate = self._seen_with_heading = 0
        self._got_frame = False  # the current session has delivered a frame (resets the backoff)
        self._last_tracker: AttitudeTracker | None = None  # the last session's: its epoch is taken
        self._last_description: str | None = None  # and its device (product and id), whose gyro bias is kept
        first = None if wait_for_device else self._open(self.config)
        self._thread = threading.Thread(target=self._run, args=(first,), name="sunrig-oak", daemon=True)
        self._thread.start()

    # --- the caller's side ------------------------------------------------------------------
    def get(self, timeout_s: float = 0.5) -> Frame | None:
        """The oldest queued Frame, waiting at most ``timeout_s``; None if none came."""
        with self._cond:
            if not self._frames and not self._finished.is_set():
                self._cond.wait(timeout_s)
            return self._frames.popleft() if self._frames else None

    def __iter__(self) -> Iterator[Frame]:
        """Frames until :meth:`close`; raises :class:`OakError` if the reader thread died of a bug."""
        while True:
            frame = self.get(0.2)
            if frame is not None:
                yield frame
                continue
            if self._stop.is_set() or self._finished.is_set():
                if self._failure is not None:
                    raise OakError(f"OAK reader failed: {self._failure}")
                return

    def stats(self) -> dict[str, Any]:
        """Counters (HANDLER_COUNTS, CAMERA_COUNTS) and state: device, imu, imu_mode, heading_ref, ..."""
        with self._cond:
            out: dict[str, Any] = {**self._counts, **self._info}
            out["last_error"] = self._last_error
            out["failure"] = self._failure
            out["queued"] = len(self._frames)
            out["reader_alive"] = self._thread.is_alive()
        return out

    @property
    def finished(self) -> bool:
        return self._finished.is_set()

    def close(self) -> None:
        """Stop the reader and release the device. Idempotent; returns within about ``join_timeout_s``."""
        if not begin_stop(self._cond, self._stop):
            return
        join_worker(self._thread, self._join_timeout_s, None, log, "OAK reader")

    def __enter__(self) -> OakCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the reader thread: all depthai I/O happens here --------------------------------------
    def _warn_once(self, key: str, msg: str, *args: Any) -> None:
        if key not in self._warned:
            self._warned.add(key)
            log.warning(msg, *args)

    def _run(self, session: OakSession | None) -> None:
        backoff = Backoff(self.config.backoff_s, ValidationError)
        had_session = False
        loss_errors = _loss_errors()
        try:
            while not self._stop.is_set():
                if session is None:
                    try:
                        session = self._open(self.config)
                    except OakError as exc:
                        with self._cond:
                            self._counts["open_failures"] += 1
                            self._last_error = str(exc)
                        self._warn_once("open", "OAK: %s; retrying every %.1f-%.0f s", exc,
                                        backoff.first_s, backoff.longest_s)
                        backoff.wait(self._stop)
                        continue
                if had_session:
                    with self._cond:
                        self._counts["reconnects"] += 1
                    log.info("OAK %s reconnected", session.description)
                had_session = True
                self._warned.discard("open")
                self._got_frame = False
                try:
                    self._serve(session)
                except loss_errors as exc:
                    message = f"{type(exc).__name__}: {exc}"
                    with self._cond:
                        self._counts["device_lost"] += 1
                        self._last_error = message
                    log.warning("OAK %s lost (%s); reconnecting with backoff", session.description, message)
                finally:
                    self._close_session(session)
                    session = None
                if self._got_frame:
                    backoff.reset()  # it worked for a while: a new outage starts the backoff again
                backoff.wait(self._stop)
        except BaseException as exc:  # a bug: report it rather than die silently
            with self._cond:
                self._failure = f"{type(exc).__name__}: {exc}"
                self._last_error = f"reader thread failed: {self._failure}"
            log.exception("OAK reader failed")
        finally:
            if session is not None:
                self._close_session(session)
            with self._cond:
                self._finished.set()
                self._cond.notify_all()

    def _tracker(self, session: OakSession) -> AttitudeTracker | None:
        cfg = self.config
        if session.imu is None or session.imu_mode is None:
            self._warn_once("no_imu", "OAK %s: no IMU heading (IMU %r, imu_mode %s): frames carry no attitude",
                            session.description, session.imu_name, cfg.imu_mode)
            return None
        if session.cam_from_imu_source.startswith("default"):
            self._warn_once("mount", "OAK %s: IMU-to-camera rotation is the %s: check it (docs/oak.md) or set "
                            "cam_from_imu", session.description, session.cam_from_imu_source)
        if session.imu_mode is ImuMode.ROTATION_VECTOR and cfg.declination_deg is None:
            # Said, not silent: the estimates' world is then turned by the site's declination.
            self._warn_once("magnetic", "OAK %s: headings are referenced to magnetic north (no declination_deg): "
                            "estimates carry heading_ref magnetic and are off true north by the site's declination; "
                            "pass --declination-deg (east positive, from a geomagnetic model such as NOAA's) for "
                            "true north", session.description)
        unused = unused_declination_warning(cfg.declination_deg, session.imu_mode, session.imu_name)
        if unused is not None:
            # Keyed by mode: a reconnect in the same mode says nothing new, another device's may.
            self._warn_once(f"declination_{session.imu_mode.value}", "OAK %s: %s", session.description, unused)
        # Each session re-zeroes a relative heading: its session number is the heading epoch, or
        # one past the last tracker's, which moves on by itself after a gap in gyro reports.
        with self._cond:
            epoch = self._counts["sessions"]
        if self._last_tracker is not None:
            epoch = max(epoch, self._last_tracker.epoch + 1)
        tracker = AttitudeTracker(session.imu_mode, session.cam_from_imu, declination_rad=cfg.declination_rad,
                                  sensor_world=cfg.sensor_world, history_s=cfg.imu_history_s,
                                  max_gap_s=cfg.max_imu_gap_s, max_accuracy_rad=math.radians(cfg.max_rv_accuracy_deg),
                                  epoch=epoch)
        if self._last_tracker is not None and session.description == self._last_description:
            tracker.keep_gyro_bias(self._last_tracker)  # the same device again: its gyro's bias is as learned
        self._last_tracker, self._last_description = tracker, session.description
        return tracker

    def _serve(self, session: OakSession) -> None:
        """Run one session until close() (returns) or a loss (raises)."""
        dai = _dai()
        cfg = self.config
        tracker = self._tracker(session)
        bpp = FRAME_TYPES_BGR[cfg.frame_type] if cfg.frame_type else 1.5  # the device's choice: NV12
        usb = usb_bandwidth_warning(session.usb_speed, cfg.width, cfg.height, cfg.fps, bpp)
        if usb is not None:
            self._warn_once(f"usb_{session.usb_speed}", "OAK %s: %s", session.description, usb)
        handler = OakMessageHandler(session.intrinsics, tracker, imu_wait_s=cfg.imu_wait_s,
                                    first_seq=self._next_seq, counts=self._counts)
        with self._cond:
            self._counts["sessions"] += 1
            self._info.update(device=session.description, usb_speed=session.usb_speed or None, imu=session.imu_name,
                              imu_mode=None if tracker is None else tracker.mode.value,
                              heading_ref=None if tracker is None else tracker.heading_ref.value,
                              cam_from_imu_source=session.cam_from_imu_source or None)
        qv = session.video.createOutputQueue(maxSize=cfg.queue_size, blocking=False)
        qi = None if session.imu is None else session.imu.createOutputQueue(maxSize=64, blocking=False)
        queues = [q for q in (qv, qi) if q is not None]
        wait = timedelta(seconds=cfg.poll_s)
        session.pipeline.start()
        started = self._clock()
        last_frame: float | None = None
        try:
            while not self._stop.is_set():
                dai.MessageQueue.waitAny(queues, wait)  # bounded: returns at the timeout or on close
                if qi is not None:
                    for msg in qi.tryGetAll():
                        handler.on_imu(msg)
                now = self._clock()
                for msg in qv.tryGetAll():
                    handler.on_frame(msg, now)
                    last_frame = now
                    self._got_frame = True
                self._publish(handler.ready(self._clock()))
                self._check_tracker(tracker)
                if not session.pipeline.isRunning():
                    raise _DeviceLost("the pipeline stopped")
                quiet = now - (started if last_frame is None else last_frame)
                limit = cfg.startup_timeout_s if last_frame is None else cfg.stall_timeout_s
                if quiet > limit:
                    raise _DeviceLost(f"no frame for {quiet:.1f} s")
                # An IMU that stops while the camera goes on (depthai-python #354), or whose stamps
                # step away from the camera's (an IMU clock wrapping at 2^32 us, depthai-core #965),
                # leaves every frame without heading, which the rig skips: as lost as no frames.
                covered = handler.covered_s
                quiet_imu = now - (started if covered is None else covered)
                limit_imu = cfg.startup_timeout_s if covered is None else cfg.stall_timeout_s
                if tracker is not None and quiet_imu > limit_imu:
                    raise _DeviceLost(f"no frame covered by the IMU's reports for {quiet_imu:.1f} s while frames "
                                      "came (the IMU quiet, or its stamps off the camera's)")
        finally:
            self._publish(handler.drain())
            self._next_seq = handler.next_seq

    def _check_tracker(self, tracker: AttitudeTracker | None) -> None:
        if tracker is None:
            return
        imu_counts = {**tracker.counts, **tracker.buffer.counts, **(tracker.gyro.counts if tracker.gyro else {})}
        with self._cond:
            self._info["imu_counts"] = imu_counts
        g = tracker.gravity_mismatch_rad
        if g is not None and math.isfinite(g):
            with self._cond:
                self._info["gravity_mismatch_deg"] = math.degrees(g)
            if g > math.radians(20.0):
                self._warn_once("gravity", "OAK: the rotation vector's up and the accelerometer's disagree by "
                                "%.0f deg: its world frame is not %s (set sensor_world; docs/oak.md)",
                                math.degrees(g), tracker.sensor_world)
        with self._cond:
            inaccurate, with_heading = self._counts["no_heading_inaccurate"], self._counts["frames_with_heading"]
        lost, kept = inaccurate - self._seen_inaccurate, with_heading - self._seen_with_heading
        self._seen_inaccurate, self._seen_with_heading = inaccurate, with_heading
        if not (lost or kept):
            return  # no frame since: nothing to judge by
        # At the start (not calibrated yet) or mid-run (disturbed): said when it costs frames.
        said = self._accuracy.update("inaccurate" if lost else None, self._clock())
        if said is None:
            return
        if said.kind == "change" and said.changes == 1 and lost:
            log.warning("OAK: the IMU's rotation vector is not accurate (its own estimate worse than "
                        "max_rv_accuracy_deg %g: magnetometer not calibrated, or disturbed by steel or currents "
                        "nearby): frames go without heading until it is (no_heading_inaccurate); move the camera in "
                        "a figure-eight, or use imu_mode game_rotation_vector", self.config.max_rv_accuracy_deg)
        elif said.kind == "change" and said.changes == 1:
            log.info("OAK: the IMU's rotation vector is accurate again, after %.1f s in which frames went without "
                     "heading", self._clock() - said.since_s)
        else:
            log.warning("OAK: the IMU's rotation vector goes between accurate and not: %d changes in %.0f s; %s now",
                        said.changes, self._clock() - said.since_s, "not accurate" if lost else "accurate")

    def _publish(self, frames: list[Frame]) -> None:
        if not frames:
            return
        with self._cond:
            for f in frames:
                if len(self._frames) >= self._out_max:
                    self._frames.popleft()
                    self._counts["frames_dropped_consumer"] += 1
                self._frames.append(f)
            self._cond.notify_all()

    def _close_session(self, session: OakSession) -> None:
        """session.close() in a helper thread, waited on for at most join_timeout_s: a dead
        device can block inside depthai, and the reader must stay responsive to close()."""
        t = threading.Thread(target=session.close, name="sunrig-oak-close", daemon=True)
        t.start()
        t.join(self._join_timeout_s)
        if t.is_alive():
            log.warning("OAK %s: teardown did not finish within %.1f s; leaving it", session.description,
                        self._join_timeout_s)


def _loss_errors() -> tuple[type[BaseException], ...]:
    """What a failing device raises: depthai's RuntimeErrors (XLink), a closed queue, a stall."""
    errors: list[type[BaseException]] = [_DeviceLost, RuntimeError, OakError]
    try:
        import depthai as dai

        errors.append(dai.MessageQueue.QueueException)
    except (ImportError, AttributeError):  # pragma: no cover - depends on the environment
        pass
    return tuple(errors)
