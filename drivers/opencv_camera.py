"""Any camera OpenCV can open: a device index (V4L2, USB/UVC), a video file, or a network stream
(RTSP/HTTP URL, or a GStreamer pipeline when OpenCV is built with GStreamer).

The shell is :class:`OpenCvCamera`: one reader thread owns the ``cv2.VideoCapture``, the
consumer iterates Frames. The pure parts are :func:`parse_target`, :func:`load_calibration` /
:func:`calibration_from_mapping` and :func:`fit_intrinsics`.

- **Intrinsics** come from a calibration file (OpenCV YAML/JSON/XML as ``cv2.FileStorage``
  writes it, e.g. from ``calibrateCamera``, or a ``.toml`` file with the same keys:
  ``camera_matrix`` or ``K``, ``image_width`` / ``image_height``, optional
  ``distortion_coefficients``) or from a horizontal field of view.
  A calibration made at another resolution with the same aspect ratio is scaled to the stream. A
  calibration with distortion is applied: frames are undistorted (same K), since every Frame is a
  rectified pinhole image.
- **Time**: a live frame is stamped with the monotonic clock when ``read()`` returns, which is
  later than mid-exposure by half the exposure plus transfer and decoding (a few to tens of ms;
  pass ``latency_s`` to move it back when it is known). A video file has no live clock: its
  frames are stamped with ``CAP_PROP_POS_MSEC`` (the file's own timestamps, starting near 0), or
  ``index / fps`` where the container does not say.
- **Lost streams**: a live source whose ``read()`` fails (unplugged, network gone) is released,
  counted, logged once per outage and reopened with a backoff that doubles up to
  ``backoff_s[1]``; it never raises for that, unless ``max_outage_s`` is set and passes. A video
  file ends at its end; its first frame is read as it opens, so a file with no frame OpenCV can
  decode, or one the intrinsics cannot fit, is refused then.
- **Repeated frames**: a live image identical to the one before (a frozen driver or stream
  giving its last buffer again) is no new exposure: dropped and counted (``repeated``).
- **Bounded waits**: the consumer waits at most ``poll_s`` at a time and sees :meth:`stop` /
  :meth:`close` within that; a live frame the consumer has not taken is dropped when a newer one
  arrives (counted), a file waits for the consumer instead (nothing is lost by replaying
  slower). OpenCV's own open and read are bounded by ``CAP_PROP_OPEN_TIMEOUT_MSEC`` /
  ``CAP_PROP_READ_TIMEOUT_MSEC`` on network streams; a read or reopen that has not returned for
  ``stall_s`` (3 s) is said once and counted (``stalls``), and past ``max_outage_s`` is the
  consumer's error; a read stuck below Python is abandoned with its daemon thread after
  ``join_timeout_s``.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import math
import os
import re
import stat
import sys
import threading
import time
import tomllib
from collections import deque
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from rig.errors import CameraError, SunrigError, ValidationError
from rig.lasting import EventThrottle
from rig.types import MIN_FOV_DEG, Frame, Intrinsics

log = logging.getLogger(__name__)

# FFmpeg prints its own reason for a failed open ("moov atom not found", "Connection refused") on
# stderr, above the one line that says what to do, and again at every reconnect of a lost stream
# (every few seconds of an outage). OpenCV reads this once, as FFmpeg is first used: quiet unless
# the user set it (e.g. OPENCV_FFMPEG_LOGLEVEL=16 to see FFmpeg's errors again).
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET

_URL_SCHEMES = ("rtsp://", "rtsps://", "rtmp://", "http://", "https://", "udp://", "tcp://", "srt://")
_OPEN_TIMEOUT_MS = 5000
_READ_TIMEOUT_MS = 5000
_CV_INT_MAX = 2**31 - 1  # cv2.VideoCapture(index) takes a C int


# --- pure parts ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class CameraTarget:
    """What ``--camera opencv:...`` names. ``kind``: device, file, url or gstreamer."""

    kind: str
    value: int | str

    @property
    def live(self) -> bool:
        return self.kind != "file"

    def __str__(self) -> str:
        return f"camera {self.value}" if self.kind == "device" else str(self.value)


def parse_target(text: str | int) -> CameraTarget:
    """A device index (``0``) or path (``/dev/video0``), a stream URL (``rtsp://...``), a GStreamer
    pipeline (contains ``!``) or a video file path."""
    if isinstance(text, int):
        return CameraTarget("device", _device_index(text))
    text = text.strip()
    if not text:
        raise CameraError("empty camera: pass a device index (opencv:0), a video file or an rtsp:// URL")
    if text.isascii() and text.isdigit():
        # A 5000-digit index is more than int() converts: it is too large either way.
        return CameraTarget("device", _device_index(int(text) if len(text) <= 20 else text))
    if text.startswith("/dev/"):
        # A device by path, such as the stable /dev/v4l/by-id/... names of a rig with several
        # cameras: live, like an index, not a recording to replay.
        return CameraTarget("device", text)
    if text.lower().startswith(_URL_SCHEMES):
        return CameraTarget("url", text)
    if "!" in text:
        return CameraTarget("gstreamer", text)
    return CameraTarget("file", text)


def _device_index(index: int | str) -> int:
    """A device index as OpenCV takes it: a C int (a str stands for one too long to convert)."""
    if isinstance(index, str) or not -_CV_INT_MAX - 1 <= index <= _CV_INT_MAX:
        shown = str(index) if len(str(index)) <= 20 else f"{str(index)[:12]}... ({len(str(index))} digits)"
        raise CameraError(f"camera index {shown}: expected at most {_CV_INT_MAX} (OpenCV takes a C int); "
                          "pass the index of the device, e.g. opencv:0 for /dev/video0")
    return index


_DISTORTION_COUNTS = (0, 4, 5, 8, 12, 14)  # what cv2.initUndistortRectifyMap takes


@dataclass(frozen=True)
class Calibration:
    """A camera matrix for a given image size, with its distortion coefficients (may be empty)."""

    k: np.ndarray  # 3x3
    width: int
    height: int
    distortion: np.ndarray  # (n,), zeros or empty when none

    def __post_init__(self) -> None:
        k = np.asarray(self.k, dtype=np.float64)
        if k.shape != (3, 3):
            raise ValidationError(f"camera matrix: expected 3x3 values, got shape {k.shape}")
        d = np.asarray(self.distortion, dtype=np.float64).ravel()
        if not (np.all(np.isfinite(k)) and k[0, 0] > 0 and k[1, 1] > 0 and np.all(np.isfinite(d))):
            raise ValidationError(f"expected a finite camera matrix with positive fx, fy, got {k.tolist()}")
        if d.size not in _DISTORTION_COUNTS and np.any(d != 0.0):  # zeros of any count are no distortion
            raise ValidationError(f"distortion: expected 4, 5, 8, 12 or 14 coefficients (k1, k2, p1, p2[, k3[, ...]]), "
                                  f"as OpenCV's model has, got {d.size}")
        try:
            # The same bounds as every frame's (a focal length no camera has, a size of 0), checked
            # now: as the file loads, not when the first frame comes, or never for the wrong size.
            at_size = Intrinsics(fx=k[0, 0], fy=k[1, 1], cx=k[0, 2], cy=k[1, 2], width=self.width,
                                 height=self.height)
        except ValidationError as exc:
            raise ValidationError(f"the camera matrix and image size are no camera: {exc}") from None
        object.__setattr__(self, "k", k)
        object.__setattr__(self, "distortion", d)
        object.__setattr__(self, "width", at_size.width)
        object.__setattr__(self, "height", at_size.height)

    @property
    def distorted(self) -> bool:
        return bool(np.any(self.distortion != 0.0))


_K_KEYS = ("camera_matrix", "K", "cameraMatrix", "intrinsic_matrix", "M")
_D_KEYS = ("distortion_coefficients", "dist_coeffs", "D", "distCoeffs", "distortion")
_W_KEYS = ("image_width", "width", "imageWidth")
_H_KEYS = ("image_height", "height", "imageHeight")
# The names (ROS, Kalibr) of the model cv2.undistort applies: k1, k2, p1, p2[, k3[, k4, k5, k6]].
_STANDARD_MODELS = ("plumb_bob", "rational_polynomial", "radtan", "radial-tangential", "none", "")


def calibration_from_mapping(values: Mapping[str, Any], name: str = "calibration") -> Calibration:
    """A :class:`Calibration` from named values (the common key names of OpenCV calibration files:
    ``camera_matrix``/``K``, ``image_width``/``width``, ``image_height``/``height``,
    ``distortion_coefficients``/``D``). A ``image_size`` pair may stand for width and height."""

    def first(keys: tuple[str, ...]) -> Any:
        return next((values[k] for k in keys if k in values and values[k] is not None), None)

    k = first(_K_KEYS)
    if k is None:
        raise CameraError(f"{name}: no camera matrix (expected one of {', '.join(_K_KEYS)}); "
                          "pass a cv2.FileStorage calibration file, or --hfov-deg instead")
    try:  # a file's values (TOML, or a mapping built by hand): a ragged or non-numeric list
        k = np.asarray(k, dtype=np.float64)
    except (ValueError, TypeError):
        raise CameraError(f"{name}: the camera matrix is not 3x3 numbers; pass it as [[fx, 0, cx], [0, fy, cy], "
                          "[0, 0, 1]]") from None
    if k.size != 9:
        raise CameraError(f"{name}: camera matrix: expected 3x3 values, got shape {k.shape}")
    k = k.reshape(3, 3)
    width, height = first(_W_KEYS), first(_H_KEYS)
    size = values.get("image_size")
    if (width is None or height is None) and size is not None and np.size(size) == 2:
        width, height = np.asarray(size).ravel().tolist()
    if width is None or height is None:
        raise CameraError(f"{name}: no image size (expected image_width and image_height); "
                          "add them, since the camera matrix is only valid at its own resolution")
    model = values.get("distortion_model")
    if model is not None and str(model).strip().lower() not in _STANDARD_MODELS:
        # A fisheye's k1..k4 read as k1, k2, p1, p2 would bend every frame the wrong way.
        raise CameraError(f"{name}: distortion_model {model}: sunrig undistorts OpenCV's standard model (plumb_bob, "
                          "rational_polynomial) only; recalibrate with cv2.calibrateCamera, or undistort the frames "
                          "before sunrig and pass --hfov-deg")
    d = first(_D_KEYS)
    try:
        d = np.zeros(0) if d is None else np.asarray(d, dtype=np.float64).ravel()
    except (ValueError, TypeError):
        raise CameraError(f"{name}: the distortion coefficients are not a list of numbers; pass them as "
                          "[k1, k2, p1, p2, k3]") from None
    try:
        return Calibration(k=k, width=width, height=height, distortion=d)
    except ValidationError as exc:
        raise CameraError(f"{name}: {exc}; recalibrate, or pass --hfov-deg instead") from None


# OpenCV's parse error names its own source file and function before the reason, e.g.
# "OpenCV(5.1.0) /io/.../persistence_yml.cpp:871: error: (-212:Parsing error) parse in function
# '/x.yaml(1): Only collections ...'". The user needs the file's line and the reason only.
_CV_PARSE_REASON = re.compile(r"in function '.*?\((\d+)\): (.*?)'?$")


def _parse_reason(message: str) -> str:
    last = (message.strip().splitlines() or [""])[-1]
    m = _CV_PARSE_REASON.search(last)
    return f"line {m.group(1)}: {m.group(2)}" if m else last


def load_calibration(path: str | os.PathLike[str]) -> Calibration:
    """Read an OpenCV calibration file (YAML, JSON or XML, as ``cv2.FileStorage`` writes it), or a
    ``.toml`` file with the same keys (top level)."""
    p = Path(path)
    remedy = "pass the file calibrateCamera's results were saved to, or --hfov-deg instead"
    if p.is_dir():
        raise CameraError(f"calibration file {p} is a folder; {remedy}")
    if not p.exists():
        raise CameraError(f"calibration file {p} does not exist; {remedy}")
    if not p.is_file():  # /dev/zero, a FIFO (whose open would wait for a writer without a word)
        raise CameraError(f"calibration file {p} is not a regular file (a FIFO or device); save the calibration "
                          "to a file and pass that, or --hfov-deg instead")
    if p.stat().st_size == 0:  # OpenCV says only "Assertion failed: buf"
        raise CameraError(f"calibration file {p} is empty (0 bytes); {remedy}")
    if p.suffix.lower() == ".toml":  # as sunrig's own configuration: cv2.FileStorage would read it as YAML
        try:
            with p.open("rb") as f:
                table = tomllib.load(f)
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise CameraError(f"calibration file {p} is not valid TOML: {exc}; {remedy}") from None
        return calibration_from_mapping(table, f"calibration file {p}")
    try:
        fs = cv2.FileStorage(str(p), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as exc:  # OpenCV 5 wraps its parse error in a SystemError
        reason = _parse_reason(str(exc.__cause__ or exc))
        raise CameraError(f"calibration file {p} is not an OpenCV FileStorage file (YAML/JSON/XML): "
                          f"{reason}; {remedy}") from None
    try:
        if not fs.isOpened():
            raise CameraError(f"calibration file {p} cannot be read by cv2.FileStorage (YAML, JSON or XML); {remedy}")
        values: dict[str, Any] = {}
        for key in (*_K_KEYS, *_D_KEYS, *_W_KEYS, *_H_KEYS, "image_size"):
            node = fs.getNode(key)
            if node.empty() or node.isNone():
                continue
            if node.isMap() or node.isSeq():
                try:
                    values[key] = _node_array(node)
                except (cv2.error, ValueError) as exc:
                    reason = _parse_reason(str(exc)) if isinstance(exc, cv2.error) else str(exc)
                    raise CameraError(f"calibration file {p}: {key} is not a matrix OpenCV or ROS writes "
                                      f"({reason}); {remedy}") from None
            elif node.isInt():
                values[key] = int(node.real())  # as the file has it: "width 0", not "0.0"
            elif node.isReal():
                values[key] = node.real()
        model = fs.getNode("distortion_model")
        if model.isString():
            values["distortion_model"] = model.string()
        return calibration_from_mapping(values, f"calibration file {p}")
    finally:
        fs.release()


def _node_array(node: Any) -> np.ndarray:
    """A matrix node as an array: an ``opencv-matrix`` (``rows``, ``cols``, ``dt``, ``data``),
    the same without ``dt`` as ROS ``camera_calibration`` writes it, or a list, flat or nested
    (JSON). Raises ValueError (or cv2.error) for anything else."""
    if node.isMap() and node.getNode("dt").empty():
        rows, cols, data = (node.getNode(k) for k in ("rows", "cols", "data"))
        if rows.empty() or cols.empty() or not data.isSeq():
            raise ValueError("a map without rows, cols and data")
        values = _node_array(data).ravel()
        if values.size != int(rows.real()) * int(cols.real()):
            raise ValueError(f"{values.size} values for {int(rows.real())} x {int(cols.real())}")
        return values.reshape(int(rows.real()), int(cols.real()))
    if node.isSeq():
        items = [node.at(i) for i in range(node.size())]
        if items and all(item.isSeq() for item in items):
            return np.array([_node_array(item) for item in items])  # ragged rows: ValueError
        if not all(item.isInt() or item.isReal() for item in items):
            raise ValueError("a list of other than numbers")
        return np.array([item.real() for item in items])
    return node.mat()


def fit_intrinsics(width: int, height: int, *, calibration: Calibration | None = None,
                   hfov_rad: float | None = None) -> Intrinsics:
    """Intrinsics of a ``width`` x ``height`` stream: the calibration, scaled when the stream is
    another size of the same aspect ratio; or square pixels with the given horizontal FOV."""
    if calibration is not None:
        c = calibration
        sx, sy = width / c.width, height / c.height
        if abs(sx - sy) > 0.01 * max(sx, sy):
            raise CameraError(f"the calibration is for {c.width}x{c.height} but the stream is {width}x{height}, "
                              "another aspect ratio (cropped?); calibrate at this resolution")
        k = c.k
        # Pixel centres: a continuous coordinate u scales as u * s (edges at 0 and W), as Intrinsics uses.
        return Intrinsics(fx=k[0, 0] * sx, fy=k[1, 1] * sy, cx=k[0, 2] * sx, cy=k[1, 2] * sy, width=width,
                          height=height)
    if hfov_rad is None:
        raise CameraError("the camera needs intrinsics: pass a calibration file (--calibration FILE) "
                          "or its horizontal field of view (--hfov-deg DEG)")
    if not (math.isfinite(hfov_rad) and 0.0 < hfov_rad < math.pi):
        raise CameraError(f"horizontal field of view: expected between 0 and 180 deg, got {math.degrees(hfov_rad)}")
    if hfov_rad < math.radians(MIN_FOV_DEG):  # the focal length would be no camera's (rig/types.py)
        raise CameraError(f"horizontal field of view: expected at least {MIN_FOV_DEG:g} deg, as any camera has, "
                          f"got {math.degrees(hfov_rad):g}; pass the field of view in degrees")
    return Intrinsics.from_hfov(width, height, hfov_rad)


def as_bgr(image: np.ndarray) -> np.ndarray:
    """A capture's image as BGR uint8: grey and BGRA cameras exist."""
    if image.dtype == np.uint16:
        image = cv2.convertScaleAbs(image, alpha=255.0 / 65535.0)
    elif image.dtype != np.uint8:
        image = image.astype(np.uint8)
    if image.ndim == 2:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    if image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    if image.shape[2] == 1:
        return cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    return image


# --- the I/O shell -------------------------------------------------------------------------------


class _OpenCvQuiet:
    """OpenCV prints WARN and ERROR lines for every failed open ("Could not find decoder") and
    for a read that times out ("Stream timeout triggered after 5006 ms", V4L2's "select()
    timeout"); the camera says each in its own words, once. OpenCV's log level is one for the
    process: it stays silent while any camera is inside an open or read (threads overlap), and
    is put back as the last one leaves."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._inside = 0
        self._level = 0

    @contextlib.contextmanager
    def __call__(self) -> Iterator[None]:
        with self._lock:
            if self._inside == 0:
                self._level = cv2.utils.logging.getLogLevel()
                cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
            self._inside += 1
        try:
            yield
        finally:
            with self._lock:
                self._inside -= 1
                if self._inside == 0:
                    cv2.utils.logging.setLogLevel(self._level)


_opencv_quiet = _OpenCvQuiet()


def open_capture(target: CameraTarget, width: int | None = None, height: int | None = None,
                 fps: float | None = None) -> Any:
    """A ``cv2.VideoCapture`` for ``target`` (maybe not opened: check ``isOpened()``)."""
    with _opencv_quiet():
        if target.kind == "url":
            cap = cv2.VideoCapture(target.value, cv2.CAP_FFMPEG,
                                   [cv2.CAP_PROP_OPEN_TIMEOUT_MSEC, _OPEN_TIMEOUT_MS,
                                    cv2.CAP_PROP_READ_TIMEOUT_MSEC, _READ_TIMEOUT_MS])
        elif target.kind == "gstreamer":
            cap = cv2.VideoCapture(target.value, cv2.CAP_GSTREAMER)
        elif target.kind == "device" and isinstance(target.value, str):
            cap = cv2.VideoCapture(target.value, cv2.CAP_V4L2)  # a path: only V4L2 opens one as a device
        else:
            cap = cv2.VideoCapture(target.value)
    if cap.isOpened() and target.kind == "device":
        # Requests; a camera that cannot do them keeps its own mode (the frames say which).
        if width:
            cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
        if height:
            cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        if fps:
            cap.set(cv2.CAP_PROP_FPS, fps)
        cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)  # the newest frame, not one queued in the driver
    return cap


def _open_failure(target: CameraTarget) -> CameraError:
    if target.kind == "device":
        where = f"index {target.value}" if isinstance(target.value, int) else str(target.value)
        return CameraError(f"no camera at {where}: {_why_no_v4l2_device(target.value)}")
    if target.kind == "gstreamer" and "NO" in _build_line("GStreamer"):
        return CameraError("this OpenCV has no GStreamer support; pass an rtsp:// URL or a device index instead")
    if target.kind == "file":
        return CameraError(f"OpenCV cannot read the video file {target.value}: not a video, or a codec this "
                           "OpenCV build lacks; convert it (e.g. to MJPG .avi or H.264 .mp4)")
    return CameraError(f"cannot open the stream {target.value}: check the URL, credentials and network "
                       "(OpenCV waited up to 5 s)")


_V4L2_MAJOR = 81  # the Linux device number of every /dev/videoN (Documentation/admin-guide/devices.txt)


def _why_no_v4l2_device(device: int | str) -> str:
    """Why OpenCV could not open a device, as far as Linux tells: no such node, a node that is no
    camera (/dev/null), no permission, a camera gone behind its node, or one OpenCV cannot use
    (busy, or a UVC camera's metadata node). Elsewhere, what to check."""
    generic = "check it is plugged in (ls /dev/video*), that the user is in the 'video' group, and the index or path"
    if not sys.platform.startswith("linux"):
        return generic
    path = Path(f"/dev/video{device}" if isinstance(device, int) else device)
    if not path.exists():
        return f"check it is plugged in (there is no {path}; ls /dev/video*), and the index or path"
    info = path.stat()
    if not stat.S_ISCHR(info.st_mode) or os.major(info.st_rdev) != _V4L2_MAJOR:
        return ("it is not a video device (V4L2); pass a camera's /dev/videoN or /dev/v4l/by-id/... path, or its "
                "index (opencv:0)")
    try:
        os.close(os.open(path, os.O_RDWR | os.O_NONBLOCK))
    except OSError as exc:
        if exc.errno in (errno.ENXIO, errno.ENODEV, errno.ENOENT):
            return "the device behind it is gone (unplugged?); plug it in again, or pick another (ls /dev/video*)"
        if exc.errno in (errno.EACCES, errno.EPERM):
            return (f"no permission to open {path}; add the user to the 'video' group "
                    "(sudo usermod -aG video $USER, then log in again)")
        if exc.errno == errno.EBUSY:
            return f"{path} is busy; close the program using it (fuser -v {path})"
        return f"{path}: {exc.strerror}; check the camera and its cable"
    return (f"OpenCV cannot capture from {path}: busy in another program (fuser -v {path}), or not a capture node "
            "(a USB camera's second /dev/video node carries metadata only: v4l2-ctl --list-devices)")


def _build_line(name: str) -> str:
    return next((line for line in cv2.getBuildInformation().splitlines() if line.strip().startswith(name + ":")), "")


class OpenCvCamera:
    """Frames from a device index, video file or stream URL through ``cv2.VideoCapture``.

    ``source``: a device index, a path or URL, or a :class:`CameraTarget`. Intrinsics: exactly
    one of ``intrinsics`` (used as is; must match the stream size), ``calibration`` (a file or a
    :class:`Calibration`) or ``hfov_deg``. ``width``/``height``/``fps`` are requests to a device
    (a size it does not give is said once; a file or stream takes none, said as it opens).
    ``reconnect``: retry a failed read (default: yes for live sources, never for files).
    ``capture_factory(target)`` opens a capture (tests pass a fake for the one thing no test
    machine has: a device that disappears). Iterate it for Frames; a context manager.
    """

    def __init__(self, source: int | str | CameraTarget, *, intrinsics: Intrinsics | None = None,
                 calibration: str | os.PathLike[str] | Calibration | None = None, hfov_deg: float | None = None,
                 width: int | None = None, height: int | None = None, fps: float | None = None,
                 reconnect: bool | None = None, backoff_s: tuple[float, float] = (0.2, 5.0),
                 max_outage_s: float | None = None, latency_s: float = 0.0, poll_s: float = 0.1,
                 join_timeout_s: float = 2.0, stall_s: float = 3.0, clock: Callable[[], float] = time.monotonic,
                 capture_factory: Callable[[CameraTarget], Any] | None = None) -> None:
        self.target = source if isinstance(source, CameraTarget) else parse_target(source)
        given = sum(x is not None for x in (intrinsics, calibration, hfov_deg))
        if given == 0:
            fit_intrinsics(0, 0)  # raises the one error that says what to pass
        if given > 1:
            raise CameraError("pass one source of intrinsics: a calibration file (--calibration FILE), "
                              "a horizontal field of view (--hfov-deg DEG) or Intrinsics, not both")
        lo, hi = backoff_s
        if not 0 < lo <= hi:
            raise CameraError(f"backoff_s: expected 0 < min <= max seconds, got {backoff_s!r}")
        if isinstance(calibration, str | os.PathLike):
            calibration = load_calibration(calibration)
        self._calibration = calibration
        self._fixed = intrinsics
        self._hfov = None if hfov_deg is None else math.radians(float(hfov_deg))
        if self._hfov is not None:
            fit_intrinsics(16, 9, hfov_rad=self._hfov)  # check the angle now, before opening anything
        self.live = self.target.live
        self._reconnect = self.live if reconnect is None else bool(reconnect)
        self._backoff = (float(lo), float(hi))
        self._max_outage_s = max_outage_s
        self._latency_s = float(latency_s)
        self._poll_s = float(poll_s)
        self._join_timeout_s = float(join_timeout_s)
        self._stall_s = float(stall_s)
        self._clock = clock
        self._factory = capture_factory or (lambda t: open_capture(t, width, height, fps))

        if self.target.kind == "file" and capture_factory is None and not Path(str(self.target.value)).is_file():
            path = Path(str(self.target.value))
            what = ("is a folder, not a video file" if path.is_dir() else
                    "is a device or special file, not a video file" if path.exists() else "does not exist")
            raise CameraError(f"video file {self.target.value} {what}; pass an existing file, "
                              "a device index (opencv:0) or an rtsp:// URL")
        cap = self._factory(self.target)
        if not cap.isOpened():
            cap.release()
            raise _open_failure(self.target)
        self._cap: Any = cap
        self._fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)

        self._lock = threading.Condition()
        self._queue: deque[Frame] = deque()
        self._queue_max = 2 if self.live else 8
        self._stats = dict.fromkeys(("frames", "dropped", "bad_frames", "read_failures", "reconnects",
                                     "open_failures", "stalls", "repeated"), 0)
        self._last_error: str | None = None
        self._failure: BaseException | None = None
        self._ended = False  # the reader will put nothing more (end of file, gave up, or a bug)
        # Since when the reader has been inside the capture's read() or open, and which: a call
        # that does not return (a stream or driver waiting for data that does not come) is seen by
        # the consumer, the one side still running.
        self._busy: tuple[float, str, bool] | None = None
        self._stalled = False
        self._last_image: np.ndarray | None = None  # a live source's last raw image (see _repeats)
        self._repeats_said = EventThrottle(60.0)  # said at most once a minute
        self._stop = threading.Event()
        self._closed = False
        self._thread: threading.Thread | None = None
        self._seq = 0
        self._last_file_t: float | None = None
        self._intr: Intrinsics | None = None
        self._undistort: tuple[np.ndarray, np.ndarray] | None = None
        self._undistort_size: tuple[int, int] | None = None
        # A device keeps its own mode when it cannot do the one asked for: said at its first frame.
        self._asked = (width or None, height or None) if self.target.kind == "device" else (None, None)
        self._said_sizes: set[tuple[int, int]] = set()
        # A file's first frame is read now: a file with no frame OpenCV can decode, or one the
        # intrinsics cannot fit, is refused as it opens, not once the run has started.
        self._first: Frame | None = None if self.live else self._read_first_frame()
        if self.target.kind != "device" and (width or height or fps):
            if self._first is not None:
                intr = self._first.intrinsics
                rate = f" at {self._fps:g} fps" if self._fps > 0 else ""
                what = f"is a video file: it keeps its own {intr.width}x{intr.height}{rate}"
            else:
                what = "is a stream: it keeps the mode its sender chose"
            log.warning("%s %s; --width/--height/--fps are requests to a camera device, left unused", self.target, what)

    # --- the consumer's side ---------------------------------------------------------------------

    def __iter__(self) -> Iterator[Frame]:
        return self.frames()

    def frames(self) -> Iterator[Frame]:
        """Frames until the file ends, :meth:`stop`/:meth:`close`, or (with ``max_outage_s``) a
        live source stays lost too long (CameraError). Each wait is at most ``poll_s``."""
        self._start()
        while True:
            with self._lock:
                while not self._queue and not self._ended and not self._stop.is_set():
                    self._lock.wait(self._poll_s)
                    self._check_stall()
                if self._stop.is_set():
                    return
                if self._queue:
                    frame = self._queue.popleft()
                    self._lock.notify_all()  # a file's reader may be waiting for room
                elif self._failure is not None:
                    raise self._failure
                else:
                    return
            yield frame

    def stop(self) -> None:
        """Ask the reader to stop; iteration ends within ``poll_s``."""
        self._stop.set()
        with self._lock:
            self._lock.notify_all()

    def stats(self) -> dict[str, Any]:
        with self._lock:
            return {**self._stats, "last_error": self._last_error, "source": str(self.target),
                    "intrinsics": self._intr}

    @property
    def _named(self) -> str:
        """The source as messages name it: "camera 0" (not "camera camera 0"), "camera rtsp://..."."""
        text = str(self.target)
        return text if text.startswith("camera ") else f"camera {text}"

    @property
    def intrinsics(self) -> Intrinsics | None:
        """The intrinsics of the frames (known from the first frame on)."""
        return self._intr

    def close(self) -> None:
        """Stop the reader and release the capture. Idempotent; returns within ``join_timeout_s``."""
        if self._closed:
            return
        self._closed = True
        self.stop()
        thread = self._thread
        if thread is not None:
            thread.join(self._join_timeout_s)
            if thread.is_alive():
                log.warning("camera reader for %s did not stop within %.1f s; it releases the capture when its "
                            "read returns", self.target, self._join_timeout_s)
                return
        self._release()

    def __enter__(self) -> OpenCvCamera:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the reader thread: all capture I/O happens here -----------------------------------------

    def _start(self) -> None:
        with self._lock:
            if self._thread is not None or self._closed:
                return
            self._thread = threading.Thread(target=self._run, name=f"sunrig-camera {self.target}", daemon=True)
            self._thread.start()

    def _run(self) -> None:
        backoff = self._backoff[0]
        outage_since: float | None = None
        try:
            if self._first is not None:  # read as the file opened
                self._put(self._first)
                self._first = None
            while not self._stop.is_set():
                if self._cap is None:
                    if not self._busy_with("reopen", self._reopen, in_outage=True):
                        outage_since = self._check_outage(outage_since)
                        self._stop.wait(backoff)
                        backoff = min(2.0 * backoff, self._backoff[1])
                        continue
                try:
                    with _opencv_quiet():
                        ok, image = self._busy_with("read()", self._cap.read, in_outage=outage_since is not None)
                except cv2.error as exc:
                    ok, image = False, None
                    self._note_error(f"read raised: {str(exc).strip().splitlines()[-1]}")
                now = self._clock()
                if self._stop.is_set():
                    break  # stopped while reading: nobody takes what the read gave, nor hears of its failure
                if not ok or image is None:
                    if not self._reconnect:
                        break  # the end of a file (or of a source we were told not to retry)
                    outage_since = self._read_failed(outage_since, now)
                    self._stop.wait(backoff)
                    backoff = min(2.0 * backoff, self._backoff[1])
                    continue
                if outage_since is not None:
                    log.info("%s is back after %.1f s", self._named, now - outage_since)
                outage_since = None
                backoff = self._backoff[0]
                if self.live and self._repeats(image, now):
                    continue
                try:
                    frame = self._make_frame(image, now)
                except (SunrigError, ValueError, cv2.error) as exc:
                    if self._seq == 0:
                        raise  # the first frame: a wrong setup (e.g. a calibration for another size) fails at once
                    # Later, one odd frame (a resolution renegotiated under a fixed calibration, an
                    # empty or 2-channel image) is dropped and counted, not the end of the camera.
                    self._bad_frame(exc)
                    continue
                self._put(frame)
        except BaseException as exc:  # a bug, or max_outage_s passed: the consumer re-raises it
            with self._lock:
                self._failure = exc if isinstance(exc, SunrigError) else CameraError(
                    f"the camera reader for {self.target} failed: {type(exc).__name__}: {exc}")
            if not isinstance(exc, SunrigError):
                log.exception("camera reader for %s failed", self.target)
        finally:
            self._release()
            with self._lock:
                self._ended = True
                self._lock.notify_all()

    def _read_first_frame(self) -> Frame:
        try:
            try:
                with _opencv_quiet():
                    ok, image = self._cap.read()
            except cv2.error:
                ok, image = False, None
            if not ok or image is None:
                raise CameraError(f"video file {self.target.value} has no frame OpenCV can decode (none in it, or a "
                                  "codec this OpenCV build lacks); convert it (e.g. to MJPG .avi or H.264 .mp4)")
            try:
                return self._make_frame(image, self._clock())
            except (ValueError, cv2.error) as exc:
                raise CameraError(f"video file {self.target.value}: its first frame cannot be used: {exc}") from None
        except BaseException:
            self._release()
            raise

    def _busy_with(self, what: str, call: Callable[[], Any], *, in_outage: bool) -> Any:
        """``call()`` (a read or open), marked as under way for :meth:`_check_stall`. In an
        outage already said, a slow call (an open waiting for its timeout, every few seconds) is
        no news: it is not said or counted as a stall, only held to ``max_outage_s``."""
        with self._lock:
            self._busy = (self._clock(), what, in_outage)
        try:
            return call()
        finally:
            with self._lock:
                since = self._busy[0] if self._busy else 0.0
                self._busy = None
                stalled, self._stalled = self._stalled, False
            if stalled:
                log.info("%s: its %s returned after %.1f s", self._named, what, self._clock() - since)

    def _check_stall(self) -> None:
        """The consumer's side (lock held): a read or open that has not returned for ``stall_s``
        is said once and counted (``stalls``); past ``max_outage_s`` it is the consumer's error.
        The reader cannot be woken from inside OpenCV; a network stream's own timeouts (5 s) or
        V4L2's (10 s) end most such calls as a failure, which reconnects."""
        if self._busy is None:
            return
        since, what, in_outage = self._busy
        waited_s = self._clock() - since
        if waited_s >= self._stall_s and not self._stalled and not in_outage:
            self._stalled = True
            self._stats["stalls"] += 1
            self._last_error = f"{what} has not returned for {self._stall_s:g} s (a stalled camera or stream)"
            log.warning("%s: %s; waiting for it (counted in stalls)", self._named, self._last_error)
        if self._max_outage_s is not None and waited_s > self._max_outage_s:
            raise CameraError(f"{self._named} lost for more than {self._max_outage_s:g} s ({self._last_error}); "
                              "check the cable or network")

    def _repeats(self, image: np.ndarray, now: float) -> bool:
        """A live image identical to the one before, byte for byte, is the driver's or stream's
        last buffer again (a frozen camera, an IP camera repeating its last picture), not a new
        exposure: two exposures of a real sensor differ by its noise at least. Stamped with this
        read's time it would be an older view paired with a newer heading, so it is dropped and
        counted (``repeated``), said at most once a minute. (A low-bitrate stream of a still scene
        may decode to the same bytes too: it then gives fewer frames, never an old one as new.) A
        uniform image (black, saturated) is kept: a dark scene's frames are all alike, and the
        rig's exposure check says so."""
        last, self._last_image = self._last_image, image
        if last is None or last.shape != image.shape or last.dtype != image.dtype:
            return False
        # A few rows first: two different images almost always differ there, so the whole
        # comparison runs for repeats only.
        if not np.array_equal(last[::16], image[::16]) or not np.array_equal(last, image):
            return False
        if image.size == 0 or image.min() == image.max():
            return False
        with self._lock:
            self._stats["repeated"] += 1
            self._last_error = "frames identical to the one before (a frozen camera or stream?)"
        if self._repeats_said.note(now) is not None:
            log.warning("%s: a frame identical to the one before (a frozen camera or stream?); dropping such frames "
                        "(counted in repeated)", self._named)
        return True

    def _make_frame(self, image: np.ndarray, now: float) -> Frame:
        image = as_bgr(image)
        h, w = image.shape[:2]
        if self._intr is None or (self._intr.width, self._intr.height) != (w, h):
            self._intr = self._intrinsics_for(w, h)
            self._say_unasked_size(w, h)
        if self._undistort is not None:
            image = cv2.remap(image, *self._undistort, interpolation=cv2.INTER_LINEAR)
        if self.live:
            t = now - self._latency_s
        else:
            t = self._file_time()
        frame = Frame(t_mono_s=max(t, 0.0), seq=self._seq, image_bgr=image, intrinsics=self._intr)
        self._seq += 1
        return frame

    def _say_unasked_size(self, w: int, h: int) -> None:
        asked_w, asked_h = self._asked
        if (asked_w is None or asked_w == w) and (asked_h is None or asked_h == h) or (w, h) in self._said_sizes:
            return
        self._said_sizes.add((w, h))
        asked = f"{asked_w or '(its own)'}x{asked_h or '(its own)'}"
        log.warning("%s gives %dx%d, not the %s asked for (--width/--height): it cannot do that mode; its "
                    "intrinsics follow what it gives", self._named, w, h, asked)

    def _file_time(self) -> float:
        """The file's own timestamp of the frame just read, or index / fps where it has none."""
        pos = self._cap.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
        fallback = self._seq / (self._fps if self._fps > 0 else 30.0)
        last = self._last_file_t
        t = pos if (math.isfinite(pos) and pos >= 0 and (last is None or pos > last)) else fallback
        if last is not None and t <= last:
            t = last + 1.0 / (self._fps if self._fps > 0 else 30.0)  # strictly increasing, whatever the file says
        self._last_file_t = t
        return t

    def _intrinsics_for(self, w: int, h: int) -> Intrinsics:
        if self._fixed is not None:
            if (self._fixed.width, self._fixed.height) != (w, h):
                raise CameraError(f"the intrinsics are for {self._fixed.width}x{self._fixed.height} but the camera "
                                  f"gives {w}x{h}; pass intrinsics for this size")
            return self._fixed
        intr = fit_intrinsics(w, h, calibration=self._calibration, hfov_rad=self._hfov)
        cal = self._calibration
        if cal is not None and cal.distorted:
            k = np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1.0]])
            # Undistort onto the same K: the frame keeps the calibrated geometry, minus the lens bending.
            self._undistort = cv2.initUndistortRectifyMap(k, cal.distortion, None, k, (w, h), cv2.CV_16SC2)
        return intr

    def _put(self, frame: Frame) -> None:
        with self._lock:
            if self.live:
                if len(self._queue) >= self._queue_max:
                    self._queue.popleft()  # live: the newest frame matters, never block the camera
                    self._stats["dropped"] += 1
            else:
                while len(self._queue) >= self._queue_max and not self._stop.is_set():
                    self._lock.wait(self._poll_s)  # a file waits for the consumer: nothing is lost
            self._queue.append(frame)
            self._stats["frames"] += 1
            self._lock.notify_all()

    def _read_failed(self, outage_since: float | None, now: float) -> float:
        with self._lock:
            self._stats["read_failures"] += 1
        if outage_since is None:  # once per outage, not once per retry
            if self._seq == 0:  # it opened but never gave a frame: nothing was lost
                self._note_error("read failed before its first frame (busy in another program? a stream that sends "
                                 "nothing?)")
                log.warning("%s: %s; reconnecting with backoff", self._named, self._last_error)
            else:
                self._note_error("read failed (stream lost?)")
                log.warning("%s: read failed; reconnecting with backoff", self._named)
            outage_since = now
        self._release()
        return self._check_outage(outage_since)

    def _check_outage(self, outage_since: float | None) -> float:
        now = self._clock()
        since = now if outage_since is None else outage_since
        if self._max_outage_s is not None and now - since > self._max_outage_s:
            raise CameraError(f"{self._named} lost for more than {self._max_outage_s:g} s "
                              f"({self._last_error}); check the cable or network")
        return since

    def _reopen(self) -> bool:
        try:
            cap = self._factory(self.target)
        except (cv2.error, OSError) as exc:
            self._note_error(f"reopen failed: {exc}")
            cap = None
        if cap is None or not cap.isOpened():
            if cap is not None:
                cap.release()
            with self._lock:
                self._stats["open_failures"] += 1
            return False
        self._cap = cap
        with self._lock:
            self._stats["reconnects"] += 1
        log.info("%s reopened", self._named)
        return True

    def _bad_frame(self, exc: BaseException) -> None:
        message = f"bad frame: {exc}"
        with self._lock:
            self._stats["bad_frames"] += 1
            repeated = message == self._last_error
            self._last_error = message
        if not repeated:  # once per kind of bad frame, not once per frame
            log.warning("%s: %s; dropping such frames (counted in bad_frames)", self._named, exc)

    def _note_error(self, message: str) -> None:
        with self._lock:
            self._last_error = message

    def _release(self) -> None:
        cap, self._cap = self._cap, None
        if cap is not None:
            with contextlib.suppress(cv2.error):
                cap.release()
