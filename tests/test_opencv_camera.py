"""The OpenCV camera (drivers/opencv_camera.py) through the real OpenCV: a video written with
cv2.VideoWriter and read back, calibration files written with cv2.FileStorage, devices and
streams that do not exist. Only a device that disappears mid-run is played by a fake capture
(``DisappearingCapture``, clearly a fake): no test machine has a camera to unplug."""

from __future__ import annotations

import contextlib
import math
import os
import socket
import stat
import sys
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import pytest

from drivers.opencv_camera import (
    CameraError,
    CameraTarget,
    OpenCvCamera,
    as_bgr,
    calibration_from_mapping,
    fit_intrinsics,
    load_calibration,
    parse_target,
)
from rig.types import MIN_FOV_DEG, Intrinsics
from tests.tolerances import EXACT_F64

HANG_GUARD_S = 5.0  # every wait here ends by this, so a bug fails instead of hanging
MJPG_MEAN_ABS = 8.0  # mean abs pixel difference after an MJPG round trip of the smooth test images
W, H, FPS, N = 64, 48, 10.0, 12


def clip_image(k: int) -> np.ndarray:
    """Frame k: a smooth gradient with a bright square that moves 3 px per frame."""
    yy, xx = np.mgrid[0:H, 0:W]
    img = np.stack([xx * 3, yy * 4, np.full_like(xx, 40 + 10 * k)], axis=-1).astype(np.uint8)
    img[10:22, 3 * k:3 * k + 12] = 250
    return img


@pytest.fixture
def video(tmp_path):
    path = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), FPS, (W, H))
    assert writer.isOpened()
    for k in range(N):
        writer.write(clip_image(k))
    writer.release()
    return path


def collect(camera: OpenCvCamera, limit: int = 1000) -> list:
    """Frames until the source ends or ``limit``; the camera is stopped after HANG_GUARD_S."""
    out = []
    guard = threading.Timer(HANG_GUARD_S, camera.stop)
    guard.start()
    try:
        for frame in camera:
            out.append(frame)
            if len(out) >= limit:
                break
    finally:
        guard.cancel()
    return out


# --- pure parts ----------------------------------------------------------------------------------


@pytest.mark.parametrize(("text", "kind", "value"), [
    ("0", "device", 0), ("12", "device", 12), (3, "device", 3),
    ("rtsp://cam.local:554/stream1", "url", "rtsp://cam.local:554/stream1"),
    ("HTTP://host/mjpg", "url", "HTTP://host/mjpg"),
    ("videotestsrc ! videoconvert ! appsink", "gstreamer", "videotestsrc ! videoconvert ! appsink"),
    ("/data/drive.mp4", "file", "/data/drive.mp4"),
    # A device by path is live, not a recording (which a live --heading nmea: was refused for).
    ("/dev/video0", "device", "/dev/video0"),
    ("/dev/v4l/by-id/usb-cam-video-index0", "device", "/dev/v4l/by-id/usb-cam-video-index0"),
])
def test_parse_target(text, kind, value):
    assert parse_target(text) == CameraTarget(kind, value)


@pytest.mark.parametrize("text", ["2147483648", "9" * 400, "9" * 5000, 2**31],
                         ids=["2147483648", "400-digits", "5000-digits", "int-2**31"])
def test_a_device_index_beyond_a_c_int_is_one_clear_error(text):
    # OpenCV takes the index as a C int: 2147483648 reached cv2.VideoCapture, whose "Overload
    # resolution failed" and six lines after it were an internal error of run and record.
    with pytest.raises(CameraError, match=r"^camera index [0-9.]+( \(\d+ digits\))?: expected at most 2147483647"
                       ) as info:
        parse_target(text)
    message = str(info.value)
    assert "\n" not in message and "pass the index of the device" in message and len(message) < 200
    assert parse_target("2147483647") == CameraTarget("device", 2**31 - 1)


def test_parse_target_refuses_nothing():
    with pytest.raises(CameraError, match="device index"):
        parse_target("  ")


def test_intrinsics_from_hfov():
    intr = fit_intrinsics(640, 480, hfov_rad=math.radians(90.0))
    assert intr == Intrinsics.from_hfov(640, 480, math.radians(90.0))
    assert intr.fx == pytest.approx(320.0)


def test_a_calibration_is_scaled_to_the_stream():
    cal = calibration_from_mapping({"K": [[800.0, 0, 640.0], [0, 810.0, 360.0], [0, 0, 1]], "width": 1280,
                                    "height": 720})
    intr = fit_intrinsics(640, 360, calibration=cal)
    assert (intr.fx, intr.fy, intr.cx, intr.cy) == pytest.approx((400.0, 405.0, 320.0, 180.0), abs=EXACT_F64)
    assert fit_intrinsics(1280, 720, calibration=cal).fx == 800.0
    with pytest.raises(CameraError, match="aspect ratio"):
        fit_intrinsics(640, 480, calibration=cal)


@pytest.mark.parametrize(("values", "match"), [
    ({"width": 10, "height": 10}, "no camera matrix"),
    ({"camera_matrix": np.eye(3) * 100}, "no image size"),
    ({"camera_matrix": [1, 2, 3], "image_width": 4, "image_height": 4}, "3x3"),
    ({"camera_matrix": -np.eye(3), "image_width": 4, "image_height": 4}, "positive"),
    ({"camera_matrix": np.diag([100.0, -100.0, 1.0]), "image_width": 4, "image_height": 4}, "positive fx, fy"),
    ({"camera_matrix": np.eye(3) * 100, "image_width": 4, "image_height": 4, "D": [0.1, float("nan")]}, "finite"),
    # A count of coefficients no OpenCV model has: its assertion, five lines, at the first frame.
    ({"camera_matrix": np.eye(3) * 100, "image_width": 4, "image_height": 4, "D": [0.1, 0.2, 0.3]},
     r"distortion: expected 4, 5, 8, 12 or 14 coefficients \(k1, k2, p1, p2\[, k3\[, \.\.\.\]\]\), .* got 3;"),
    # As a TOML file gives them: a ragged matrix, words for numbers (a ValueError's traceback).
    ({"camera_matrix": [[100, 0, 2], [0, 100], [0, 0, 1]], "image_width": 4, "image_height": 4}, "not 3x3 numbers"),
    ({"camera_matrix": np.eye(3) * 100, "image_width": 4, "image_height": 4, "D": ["k1"]}, "not a list of numbers"),
])
def test_bad_calibrations_say_what_is_missing(values, match):
    with pytest.raises(CameraError, match=match):
        calibration_from_mapping(values)


def test_image_size_pair_and_null_entries():
    # calibration_from_mapping: an ``image_size`` pair is (width, height), and fills in whichever
    # of image_width / image_height is missing; a key whose value is None (a JSON null) is skipped
    # for the next name, as its docstring's "first of the common key names" implies.
    k = [[800.0, 0, 640.0], [0, 800.0, 360.0], [0, 0, 1]]
    cal = calibration_from_mapping({"camera_matrix": k, "image_size": [1280, 720]})
    assert (cal.width, cal.height) == (1280, 720)
    cal = calibration_from_mapping({"camera_matrix": k, "image_width": 1280, "image_size": [1280, 720]})
    assert (cal.width, cal.height) == (1280, 720)
    cal = calibration_from_mapping({"camera_matrix": None, "K": k, "width": 1280, "height": None,
                                    "image_height": 720})
    assert cal.k[0, 0] == 800.0 and (cal.width, cal.height) == (1280, 720)


def test_an_aspect_ratio_off_by_more_than_one_percent_is_refused():
    # fit_intrinsics allows 1 % between the x and y scales: 1920x1080 -> 1920x1088 (an encoder's
    # 16-row padding, 0.74 %) is scaled; 1280x720 -> 1280x704 (2.2 %, a crop) is refused.
    cal = calibration_from_mapping({"K": np.diag([1000.0, 1000.0, 1.0]), "width": 1920, "height": 1080})
    assert fit_intrinsics(1920, 1088, calibration=cal).fy == pytest.approx(1000.0 * 1088 / 1080)
    cal = calibration_from_mapping({"K": np.diag([800.0, 800.0, 1.0]), "width": 1280, "height": 720})
    with pytest.raises(CameraError, match="aspect ratio"):
        fit_intrinsics(1280, 704, calibration=cal)


@pytest.mark.parametrize("hfov_deg", [0.0, -10.0, 180.0, 200.0, float("nan"), float("inf")])
def test_a_field_of_view_outside_0_to_180_deg_is_refused(hfov_deg):
    # A pinhole camera's horizontal field of view is strictly below 180 deg (fx = W / 2 / tan(hfov / 2)).
    with pytest.raises(CameraError, match="between 0 and 180 deg"):
        fit_intrinsics(64, 48, hfov_rad=math.radians(hfov_deg))


@pytest.mark.parametrize("hfov_deg", [1e-300, 5e-5])
def test_a_field_of_view_narrower_than_any_camera_is_refused_before_the_camera_opens(video, hfov_deg):
    # --hfov-deg 1e-300 made fx 1e302 px: numpy warned of overflow in the crops' view angles, and a
    # calibration of the same focal length ended the run in round(inf).
    with pytest.raises(CameraError, match=r"^horizontal field of view: expected at least 0.0001 deg"):
        fit_intrinsics(W, H, hfov_rad=math.radians(hfov_deg))
    with pytest.raises(CameraError, match=r"^horizontal field of view: expected at least 0.0001 deg"):
        OpenCvCamera(str(video), hfov_deg=hfov_deg)
    # The bound itself is a camera, on the widest image OpenCV makes too.
    for width in (W, 2**31 - 1):
        assert math.degrees(fit_intrinsics(width, H, hfov_rad=math.radians(MIN_FOV_DEG)).hfov_rad) == pytest.approx(
            MIN_FOV_DEG)


def test_no_intrinsics_is_one_clear_error(video):
    with pytest.raises(CameraError, match="--calibration FILE.*--hfov-deg"):
        fit_intrinsics(64, 48)
    with pytest.raises(CameraError, match="--hfov-deg"):
        OpenCvCamera(str(video))
    with pytest.raises(CameraError, match="not both"):
        OpenCvCamera(str(video), hfov_deg=60.0, calibration=calibration_from_mapping(
            {"K": np.eye(3), "width": 64, "height": 48}))


def test_as_bgr():
    assert as_bgr(np.zeros((4, 5), np.uint8)).shape == (4, 5, 3)
    assert as_bgr(np.zeros((4, 5, 4), np.uint8)).shape == (4, 5, 3)
    assert as_bgr(np.full((4, 5), 65535, np.uint16)).max() == 255
    # A 16-bit camera is scaled to 8 bits (x 255 / 65535), not clipped: 25600 -> 99.6 -> 100.
    assert (as_bgr(np.full((4, 5), 25600, np.uint16)) == 100).all()


# --- calibration files written by cv2.FileStorage ------------------------------------------------


def write_calibration(path, k, width, height, dist=None, keys=("camera_matrix", "image_width", "image_height")):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write(keys[0], np.asarray(k, dtype=np.float64))
    fs.write(keys[1], width)
    fs.write(keys[2], height)
    if dist is not None:
        fs.write("distortion_coefficients", np.asarray(dist, dtype=np.float64).reshape(1, -1))
    fs.release()


@pytest.mark.parametrize(("name", "keys"), [
    ("calib.yaml", ("camera_matrix", "image_width", "image_height")),
    ("calib.json", ("K", "width", "height")),
    ("calib.xml", ("cameraMatrix", "image_width", "image_height")),
])
def test_load_calibration_file(tmp_path, name, keys):
    k: list[list[float]] = [[500.0, 0, 320.5], [0, 502.0, 240.25], [0, 0, 1]]
    write_calibration(tmp_path / name, k, 640, 480, keys=keys)
    cal = load_calibration(tmp_path / name)
    assert cal.width == 640 and cal.height == 480 and not cal.distorted
    assert np.allclose(cal.k, k)


# The file ROS camera_calibration writes (its ost.yaml): matrices as rows, cols and data, no dt.
_ROS_CAMERA_INFO = """image_width: 1280
image_height: 720
camera_name: narrow_stereo
camera_matrix:
  rows: 3
  cols: 3
  data: [910.2, 0.0, 641.7, 0.0, 909.8, 362.4, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.31, 0.11, 0.0, 0.0, 0.0]
"""


@pytest.mark.parametrize(("name", "text"), [
    ("ost.yaml", _ROS_CAMERA_INFO),
    ("nested.json", '{"image_width": 1280, "image_height": 720, "camera_matrix": [[910.2, 0, 641.7], '
                    '[0, 909.8, 362.4], [0, 0, 1]], "distortion_coefficients": [-0.31, 0.11, 0, 0, 0]}'),
    # TOML, as sunrig's own configuration is written: cv2.FileStorage read it as YAML and said
    # "line 1: Only collections as YAML streams are supported by this parser".
    ("cam.toml", "image_width = 1280\nimage_height = 720\ncamera_matrix = [[910.2, 0, 641.7], [0, 909.8, 362.4], "
                 "[0, 0, 1]]\ndistortion_coefficients = [-0.31, 0.11, 0, 0, 0]\n"),
])
def test_load_a_ros_or_nested_list_calibration(tmp_path, name, text):
    # Both were an OpenCV assertion ("internal error" at the CLI): node.mat() wants a dt.
    (tmp_path / name).write_text(text)
    cal = load_calibration(tmp_path / name)
    assert (cal.width, cal.height) == (1280, 720)
    np.testing.assert_array_equal(cal.k, [[910.2, 0, 641.7], [0, 909.8, 362.4], [0, 0, 1]])
    np.testing.assert_array_equal(cal.distortion, [-0.31, 0.11, 0, 0, 0])


@pytest.mark.parametrize("matrix", ["{rows: 3, cols: 3, data: [1, 2]}", "{foo: 1}", "[[1, 2, 3], [4, 5]]",
                                    "[a, b, c]"])
def test_a_matrix_of_no_known_shape_is_one_line_naming_its_key(tmp_path, matrix):
    path = tmp_path / "odd.yaml"
    path.write_text(f"%YAML:1.0\n---\nimage_width: 640\nimage_height: 480\ncamera_matrix: {matrix}\n")
    with pytest.raises(CameraError, match=r"odd.yaml: camera_matrix is not a matrix OpenCV or ROS writes") as err:
        load_calibration(path)
    assert "\n" not in str(err.value)


def test_calibration_file_errors(tmp_path):
    with pytest.raises(CameraError, match="does not exist"):
        load_calibration(tmp_path / "none.yaml")
    with pytest.raises(CameraError, match="is a folder"):
        load_calibration(tmp_path)
    (tmp_path / "empty.yaml").write_bytes(b"")
    with pytest.raises(CameraError, match=r"is empty \(0 bytes\)"):
        load_calibration(tmp_path / "empty.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("%YAML:1.0\n---\nK: [1, 2\n")
    # The file's line and OpenCV's reason, without OpenCV's own source path and function.
    with pytest.raises(CameraError, match=r"bad.yaml is not .*: line 3: Missing , between the elements; pass") as err:
        load_calibration(bad)
    assert ".cpp" not in str(err.value) and "OpenCV(" not in str(err.value)
    bad.write_text("this is not: [a calibration\n")
    with pytest.raises(CameraError, match="--hfov-deg instead"):
        load_calibration(bad)
    partial = tmp_path / "partial.yaml"
    fs = cv2.FileStorage(str(partial), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.eye(3) * 300)
    fs.release()
    with pytest.raises(CameraError, match="image_width"):
        load_calibration(partial)


_K = [[60.0, 0, 32.0], [0, 60.0, 24.0], [0, 0, 1]]


@pytest.mark.parametrize(("k", "size", "needle"), [
    # Loaded, then the live rig's encode stage died in round(inf) (the crop side fx * tan(angle)),
    # and a recording made with it failed replay, eval and quantize as an internal error.
    ([[1e308, 0, 32.0], [0, 1e308, 24.0], [0, 0, 1]], (W, H), "fx: expected at most 3.66693e+07 pixels"),
    ([[60.0, 0, 32.0], [0, 1e308, 24.0], [0, 0, 1]], (W, H), "fy: expected at most"),
    # Loaded, then the camera reader divided by it: a traceback without --debug, and the run ended.
    (_K, (0, 0), "width: expected a positive integer, got 0"),
    (_K, (W, 0), "height: expected a positive integer, got 0"),
    # Loaded, and failed only once capture started.
    (_K, (-W, -H), "width: expected a positive integer, got -64"),
    # Truncated to 64 without a word.
    (_K, (W + 0.5, H), "width: expected a positive integer, got 64.5"),
    ([[60.0, 0, 650.0], [0, 60.0, 24.0], [0, 0, 1]], (W, H), "cx: expected within [0, 64] pixels, got 650"),
    (_K, (3.2e9, 2.4e9), "width: expected at most 2147483647 pixels"),
])
def test_a_calibration_that_is_no_camera_is_refused_as_it_loads(tmp_path, video, k, size, needle):
    path = tmp_path / "cam.yaml"
    write_calibration(path, k, *size)
    with pytest.raises(CameraError) as info:
        load_calibration(path)
    message = str(info.value)
    assert message.startswith(f"calibration file {path}: the camera matrix and image size are no camera: ")
    assert needle in message and message.endswith("; recalibrate, or pass --hfov-deg instead") and "\n" not in message
    with pytest.raises(CameraError, match="are no camera"):  # before the video opens, not at its first frame
        OpenCvCamera(str(video), calibration=path)


# --- a real video file through cv2.VideoCapture --------------------------------------------------


def test_video_file_round_trip(video):
    with OpenCvCamera(str(video), hfov_deg=60.0) as cam:
        frames = collect(cam)
        stats = cam.stats()
    assert len(frames) == N and [f.seq for f in frames] == list(range(N))
    assert all(f.attitude is None for f in frames)  # a camera has no heading of its own
    assert frames[0].intrinsics == Intrinsics.from_hfov(W, H, math.radians(60.0))
    for k, f in enumerate(frames):
        assert f.image_bgr.dtype == np.uint8 and f.image_bgr.shape == (H, W, 3)
        assert np.abs(f.image_bgr.astype(int) - clip_image(k)).mean() < MJPG_MEAN_ABS
    # File time: the container's timestamps, k / fps from 0.
    assert [f.t_mono_s for f in frames] == pytest.approx([k / FPS for k in range(N)], abs=1e-3)
    assert stats["frames"] == N and stats["dropped"] == 0 and stats["read_failures"] == 0


def test_video_file_with_a_calibration_at_twice_the_size(video, tmp_path):
    path = tmp_path / "cam.yaml"
    write_calibration(path, [[100.0, 0, 64.0], [0, 100.0, 48.0], [0, 0, 1]], 2 * W, 2 * H)
    with OpenCvCamera(str(video), calibration=path) as cam:
        frames = collect(cam, limit=2)
    assert frames[0].intrinsics == Intrinsics(fx=50.0, fy=50.0, cx=32.0, cy=24.0, width=W, height=H)


def test_a_distorted_calibration_undistorts_the_frames(video, tmp_path):
    path = tmp_path / "cam.yaml"
    write_calibration(path, [[60.0, 0, 32.0], [0, 60.0, 24.0], [0, 0, 1]], W, H, dist=[-0.3, 0.1, 0, 0, 0])
    with OpenCvCamera(str(video), calibration=path) as cam:
        undistorted = collect(cam, limit=1)[0]
    with OpenCvCamera(str(video), hfov_deg=60.0) as cam:
        raw = collect(cam, limit=1)[0]
    assert undistorted.intrinsics.fx == 60.0
    assert np.abs(undistorted.image_bgr.astype(int) - raw.image_bgr).mean() > 1.0  # the lens bending is removed


def test_stop_and_close_end_a_file_read_early_and_close_is_idempotent(video):
    cam = OpenCvCamera(str(video), hfov_deg=60.0)
    it = iter(cam)
    next(it)
    cam.stop()
    assert list(it) == []
    cam.close()
    cam.close()
    assert cam.stats()["read_failures"] == 0


# --- what does not exist -------------------------------------------------------------------------


def test_a_folder_is_not_called_missing(tmp_path):
    with pytest.raises(CameraError, match="is a folder, not a video file"):
        OpenCvCamera(str(tmp_path), hfov_deg=60.0)  # the driver takes what follows opencv:


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="needs /dev/zero")
def test_a_device_file_is_not_called_missing():
    # Under /dev a path is a device, opened as one: /dev/zero is no camera, and is there, so the
    # error says what it is, not "check it is plugged in".
    with pytest.raises(CameraError, match=r"^no camera at /dev/zero: it is not a video device \(V4L2\); pass ") as info:
        OpenCvCamera("/dev/zero", hfov_deg=60.0)
    assert "plugged in" not in str(info.value) and "\n" not in str(info.value)


@pytest.mark.skipif(not hasattr(os, "mknod") or os.geteuid() != 0 or not sys.platform.startswith("linux"),
                    reason="makes a device node: root on Linux")
def test_a_video_device_node_without_its_device_is_called_gone(tmp_path):
    # A real V4L2 node (major 81) whose camera is not there, as /dev/videoN is for a moment after
    # an unplug or with a stale by-id link: the kernel answers ENXIO; the error says so.
    node = tmp_path / "video250"
    os.mknod(node, stat.S_IFCHR | 0o660, os.makedev(81, 250))
    with pytest.raises(CameraError, match=rf"^no camera at {node}: the device behind it is gone \(unplugged\?\)"):
        OpenCvCamera(CameraTarget("device", str(node)), hfov_deg=60.0)  # as opencv:/dev/... names one


def test_a_missing_file_is_one_clear_error(tmp_path):
    with pytest.raises(CameraError, match="does not exist") as info:
        OpenCvCamera(str(tmp_path / "nope.avi"), hfov_deg=60.0)
    assert "\n" not in str(info.value)


def test_a_file_that_is_not_a_video(tmp_path):
    junk = tmp_path / "junk.avi"
    junk.write_bytes(b"not a video" * 100)
    with pytest.raises(CameraError, match="cannot read the video file"):
        OpenCvCamera(str(junk), hfov_deg=60.0)


def test_a_missing_device_index_is_one_clear_error():
    with pytest.raises(CameraError, match="no camera at index 63") as info:
        OpenCvCamera(63, hfov_deg=60.0)
    assert "\n" not in str(info.value)


def test_a_missing_device_path_is_one_clear_error(tmp_path):
    with pytest.raises(CameraError, match=r"^no camera at /dev/video-none-63: check it is plugged in") as info:
        OpenCvCamera("/dev/video-none-63", hfov_deg=60.0)
    assert "\n" not in str(info.value)


def test_a_bad_url_is_one_clear_error():
    t0 = time.monotonic()
    with pytest.raises(CameraError, match="cannot open the stream rtsp://127.0.0.1:1/none"):
        OpenCvCamera("rtsp://127.0.0.1:1/none", hfov_deg=60.0)
    assert time.monotonic() - t0 < HANG_GUARD_S + 1


# --- a device that disappears: a FAKE capture (no real device can be unplugged here) -------------


class DisappearingCapture:
    """FAKE cv2.VideoCapture: gives ``frames`` frames, then every read fails, as an unplugged USB
    camera's does. ``opens`` says which later opens fail (False) or succeed (True)."""

    FRAME_PERIOD_S = 0.002  # a real read blocks until the next frame; the consumer keeps up with this

    def __init__(self, frames: int, opened: bool = True):
        self.left = frames
        self.opened = opened
        self.released = False

    def isOpened(self):  # noqa: N802 - the cv2.VideoCapture interface
        return self.opened and not self.released

    def read(self):
        if self.left <= 0 or self.released:
            return False, None
        self.left -= 1
        time.sleep(self.FRAME_PERIOD_S)
        return True, np.full((H, W, 3), 100, np.uint8)

    def get(self, prop):
        return 0.0

    def release(self):
        self.released = True


class FakeFactory:
    """Opens DisappearingCaptures: the first gives 3 frames, then one open fails, then 4 frames."""

    def __init__(self, plan):
        self.plan = list(plan)
        self.opens = 0
        self.lock = threading.Lock()

    def __call__(self, target):
        with self.lock:
            self.opens += 1
            frames = self.plan.pop(0) if self.plan else None
        return DisappearingCapture(0, opened=False) if frames is None else DisappearingCapture(frames)


def test_a_lost_device_is_reported_and_reopened():
    factory = FakeFactory([3, None, 4])
    cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=factory, backoff_s=(0.01, 0.02), poll_s=0.01)
    got = collect(cam, limit=7)
    stats = cam.stats()
    cam.close()
    # 3 frames, the device is lost, one reopen fails, 4 frames from the reopened device. (A slow
    # machine may drop one: the live queue keeps the newest.)
    assert len(got) + stats["dropped"] == 7 and [f.seq for f in got] == sorted({f.seq for f in got})
    assert stats["read_failures"] >= 1 and stats["reconnects"] == 1 and stats["open_failures"] >= 1
    assert "read failed" in stats["last_error"]


def test_a_device_that_never_comes_back_does_not_hang():
    factory = FakeFactory([2])
    cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=factory, backoff_s=(0.01, 0.02), poll_s=0.01)
    it = iter(cam)
    assert next(it).seq == 0 and next(it).seq == 1
    stopper = threading.Timer(0.3, cam.stop)  # the rig's stop event, from another thread
    stopper.start()
    t0 = time.monotonic()
    assert list(it) == []
    assert time.monotonic() - t0 < HANG_GUARD_S
    cam.close()
    assert cam.stats()["open_failures"] >= 2  # it kept trying until stopped


def test_max_outage_turns_a_lost_device_into_an_error():
    cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=FakeFactory([1]), backoff_s=(0.01, 0.02),
                       poll_s=0.01, max_outage_s=0.1)
    t0 = time.monotonic()
    # "camera 0", as the other messages name it (it was "camera camera 0").
    with pytest.raises(CameraError, match=r"^camera 0 lost for more than 0.1 s \(read failed"):
        collect(cam)
    assert time.monotonic() - t0 < HANG_GUARD_S
    cam.close()


def test_a_zero_backoff_is_refused():
    # A zero wait between reconnects would spin on a lost device (OpenCvCamera: 0 < min <= max).
    with pytest.raises(CameraError, match="backoff_s"):
        OpenCvCamera(0, hfov_deg=60.0, capture_factory=FakeFactory([1]), backoff_s=(0.0, 1.0))


def test_live_frames_are_stamped_at_read_time_minus_the_latency_never_below_zero():
    # A live frame: clock() when read() returns, moved back by latency_s (the module docstring),
    # and clamped at 0 (Frame times are not negative).
    for now, want in ((100.0, 99.95), (0.01, 0.0)):
        def clock(now: float = now) -> float:
            return now

        cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=FakeFactory([3]), poll_s=0.01, reconnect=False,
                           latency_s=0.05, clock=clock)
        got = collect(cam)
        cam.close()
        assert got and all(f.t_mono_s == pytest.approx(want, abs=EXACT_F64) for f in got)


def test_a_file_without_timestamps_or_frame_rate_is_stamped_at_30_fps():
    # _file_time: no CAP_PROP_POS_MSEC (the fake's get() says 0) and no CAP_PROP_FPS: index / 30 s.
    cam = OpenCvCamera(CameraTarget("file", "clip.avi"), hfov_deg=60.0,
                       capture_factory=lambda _: DisappearingCapture(4), poll_s=0.01)
    got = collect(cam)
    cam.close()
    assert [f.t_mono_s for f in got] == pytest.approx([0.0, 1 / 30, 2 / 30, 3 / 30], abs=EXACT_F64)


def test_an_outage_is_timed_from_its_first_failed_read():
    # max_outage_s counts from the first failed read of an outage, not from the latest retry: a
    # stream that reopens fine but whose every read fails (a dead RTSP feed) is still an outage.
    # One frame, then every reopen succeeds and its first read fails.
    factory = FakeFactory([1] + [0] * 10_000)
    cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=factory, backoff_s=(0.01, 0.02), poll_s=0.01,
                       max_outage_s=0.2)
    t0 = time.monotonic()
    with pytest.raises(CameraError, match="lost for more than 0.2 s"):
        collect(cam)
    assert time.monotonic() - t0 < HANG_GUARD_S
    assert cam.stats()["read_failures"] >= 2 and cam.stats()["reconnects"] >= 1  # reopened, read failed again
    cam.close()


class OddFramesCapture(DisappearingCapture):
    """FAKE cv2.VideoCapture: ``frames`` frames, those at the indexes in ``odd`` of another size
    (a resolution renegotiated under a fixed calibration) or empty, as ``odd`` says."""

    def __init__(self, frames: int, odd: dict[int, str]):
        super().__init__(frames)
        self.odd, self.n = odd, 0

    def read(self):
        ok, image = super().read()
        kind, self.n = self.odd.get(self.n), self.n + 1
        if ok and kind == "resized":
            image = np.full((H // 2, W, 3), 100, np.uint8)
        elif ok and kind == "empty":
            image = np.zeros((0, 0, 3), np.uint8)
        return ok, image


def test_odd_frames_after_the_first_are_counted_not_fatal(caplog):
    intr = Intrinsics(fx=500.0, fy=500.0, cx=W / 2, cy=H / 2, width=W, height=H)
    odd = {3: "resized", 4: "resized", 6: "empty"}
    cam = OpenCvCamera(0, intrinsics=intr, capture_factory=lambda _: OddFramesCapture(10, odd), poll_s=0.01,
                       reconnect=False)
    with caplog.at_level("WARNING", logger="drivers.opencv_camera"):
        got = collect(cam)
    cam.close()
    stats = cam.stats()
    # The camera went on after them: 7 good frames (seq 0-6), taken or dropped as a live camera's are.
    assert stats["bad_frames"] == 3 and stats["frames"] == 7 and len(got) + stats["dropped"] == 7
    assert got[-1].seq == 6 and all(f.image_bgr.shape == (H, W, 3) for f in got)
    # One warning per kind of bad frame: the two resized frames say it once.
    warned = [r.getMessage() for r in caplog.records if "bad_frames" in r.getMessage()]
    assert len(warned) == 2 and f"gives {W}x{H // 2}" in warned[0]


def test_a_first_frame_of_the_wrong_size_is_one_clear_error():
    intr = Intrinsics(fx=500.0, fy=500.0, cx=W / 2, cy=H / 2, width=W, height=H)
    cam = OpenCvCamera(0, intrinsics=intr, capture_factory=lambda _: OddFramesCapture(5, {0: "resized"}),
                       poll_s=0.01, reconnect=False)
    with pytest.raises(CameraError, match="pass intrinsics for this size"):
        collect(cam)
    cam.close()


def test_a_live_camera_drops_frames_the_consumer_does_not_take():
    cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=FakeFactory([50]), poll_s=0.01, reconnect=False)
    it = iter(cam)
    first = next(it)
    deadline = time.monotonic() + HANG_GUARD_S
    while cam.stats()["frames"] < 50 and time.monotonic() < deadline:
        time.sleep(0.01)  # let the reader run ahead of a slow consumer
    rest = list(it)
    cam.close()
    stats = cam.stats()
    assert len(rest) <= 2 and stats["dropped"] >= 45 and stats["dropped"] + 1 + len(rest) == 50
    assert rest[-1].seq == 49 and first.seq < rest[0].seq  # the newest is kept, the order too


@pytest.mark.hardware
def test_a_real_camera_at_index_0():
    """`pytest --hardware` with a USB camera plugged in: a few frames, live times, no drops needed."""
    with OpenCvCamera(0, hfov_deg=70.0) as cam:
        frames = collect(cam, limit=5)
    assert len(frames) == 5 and [f.seq for f in frames] == list(range(5))
    assert all(b.t_mono_s > a.t_mono_s for a, b in zip(frames, frames[1:], strict=False))
    assert abs(frames[-1].t_mono_s - time.monotonic()) < HANG_GUARD_S  # stamped on the monotonic clock


# --- a video file refused as it opens ------------------------------------------------------------


def test_a_video_file_without_one_frame_is_refused_as_it_opens(tmp_path):
    # A container with no frame (a dashcam's file cut at its start) opens in OpenCV: it was taken,
    # and the run ended with "the source gave no frame ... check the camera and its cable".
    path = tmp_path / "empty.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter.fourcc(*"MJPG"), FPS, (W, H))
    writer.release()
    with pytest.raises(CameraError, match=r"^video file .*empty\.avi has no frame OpenCV can decode") as info:
        OpenCvCamera(str(path), hfov_deg=60.0)
    assert "\n" not in str(info.value) and "convert it" in str(info.value)


def test_a_calibration_of_another_aspect_ratio_is_refused_as_a_video_file_opens(video, tmp_path):
    # A file's first frame is read as it opens: a calibration that cannot fit it is the open's
    # one-line error, not the capture stage's failure once the run started.
    path = tmp_path / "cam.yaml"
    write_calibration(path, [[100.0, 0, 64.0], [0, 100.0, 36.0], [0, 0, 1]], 128, 72)
    with pytest.raises(CameraError, match=f"the calibration is for 128x72 but the stream is {W}x{H}"):
        OpenCvCamera(str(video), calibration=path)


def test_a_file_opencv_cannot_open_leaves_only_the_error_on_stderr(tmp_path, video, capfd):
    # OpenCV's own "[ERROR:0@0.01] global cap_ffmpeg_impl.hpp:1412 open Could not find decoder"
    # and FFmpeg's "[mov,mp4,... @ 0x55...] moov atom not found" were printed above the one line
    # that says what to do.
    junk = tmp_path / "junk.mp4"
    junk.write_bytes(b"not a video")
    unknown_codec = tmp_path / "codec.avi"  # an AVI whose codec no decoder knows
    unknown_codec.write_bytes(video.read_bytes().replace(b"MJPG", b"QQQQ"))
    capfd.readouterr()
    for path in (junk, unknown_codec):
        with pytest.raises(CameraError, match="cannot read the video file"):
            OpenCvCamera(str(path), hfov_deg=60.0)
    assert capfd.readouterr().err == ""



# --- a camera whose read stops returning: a FAKE capture (no real stream can be made to stall) ----


class StallingCapture(DisappearingCapture):
    """FAKE cv2.VideoCapture: ``frames`` frames, then a read that does not return until ``resume``
    is set (a stream whose decoder waits for data that does not come), then frames again."""

    def __init__(self, frames: int):
        super().__init__(frames + 1000)
        self.before_stall = frames
        self.resume = threading.Event()

    def read(self):
        if self.before_stall == 0:
            self.resume.wait(HANG_GUARD_S)
        self.before_stall -= 1
        return super().read()

    def release(self):
        self.resume.set()  # as OpenCV's release ends a read waiting on the capture
        super().release()


def test_a_stalled_read_is_said_and_counted_and_its_end_too(caplog):
    capture = StallingCapture(2)
    cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=lambda _: capture, poll_s=0.01, stall_s=0.05)
    it = iter(cam)
    with caplog.at_level("INFO", logger="drivers.opencv_camera"):
        assert [next(it).seq, next(it).seq] == [0, 1]
        # The consumer waits for the next frame; the reader's read has not returned.
        waiter = threading.Thread(target=lambda: next(it), daemon=True)
        waiter.start()
        deadline = time.monotonic() + HANG_GUARD_S
        while cam.stats()["stalls"] == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        stats = cam.stats()
        assert stats["stalls"] == 1 and "read() has not returned for 0.05 s" in stats["last_error"]
        capture.resume.set()
        waiter.join(HANG_GUARD_S)
    cam.close()
    said = [r.getMessage() for r in caplog.records]
    assert sum("has not returned" in m for m in said) == 1  # once per stall, not once per poll
    assert any("camera 0: its read() returned after" in m for m in said)
    assert cam.stats()["stalls"] == 1


def test_a_read_stalled_longer_than_max_outage_is_the_consumers_error():
    capture = StallingCapture(1)
    cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=lambda _: capture, poll_s=0.01, stall_s=0.02,
                       max_outage_s=0.1, join_timeout_s=0.1)
    with pytest.raises(CameraError, match=r"^camera 0 lost for more than 0.1 s \(read\(\) has not returned"):
        collect(cam)
    cam.close()


# --- a camera that gives the same frame again: a FAKE capture (no real camera freezes on cue) -----


class RepeatingCapture(DisappearingCapture):
    """FAKE cv2.VideoCapture: each read gives the next image of ``images`` (a list of arrays),
    as a frozen driver or IP camera gives its last buffer again; then the end."""

    def __init__(self, images: list):
        super().__init__(len(images))
        self.images = list(images)

    def read(self):
        ok, _ = super().read()
        return (True, self.images.pop(0).copy()) if ok else (False, None)


def test_a_live_frame_identical_to_the_one_before_is_dropped_and_counted(caplog):
    # Two exposures of a real sensor never match byte for byte: the same image again is an old
    # view stamped with a new read time, which a live compass's heading would be paired with.
    a, b = (np.random.default_rng(k).integers(0, 255, (H, W, 3), dtype=np.uint8) for k in (1, 2))
    black = np.zeros((H, W, 3), np.uint8)  # a dark scene's frames are all alike: left to the rig
    images = [a, a, a, b, b, a, black, black]
    cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=lambda _: RepeatingCapture(images), poll_s=0.01,
                       reconnect=False)
    with caplog.at_level("WARNING", logger="drivers.opencv_camera"):
        got = collect(cam)
    cam.close()
    stats = cam.stats()
    assert stats["repeated"] == 3 and stats["frames"] == 5
    # Taken or dropped as a live camera's are (a slow machine may drop one for lag), in order.
    kept = [a, b, a, black, black]
    assert len(got) + stats["dropped"] == 5
    assert [f.image_bgr.tobytes() for f in got] == [kept[f.seq].tobytes() for f in got]
    assert sum("identical to the one before" in r.getMessage() for r in caplog.records) == 1


# --- a requested mode: said when it is not what comes ---------------------------------------------


def test_a_requested_size_a_video_file_cannot_take_is_said(video, caplog):
    # --width/--height/--fps are requests to a device; of a file they were dropped without a word.
    with caplog.at_level("WARNING", logger="drivers.opencv_camera"):
        with OpenCvCamera(str(video), hfov_deg=60.0, width=1280, height=720, fps=30.0) as cam:
            frames = collect(cam, limit=2)
    assert frames[0].image_bgr.shape == (H, W, 3)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and f"{video} is a video file: it keeps its own {W}x{H} at {FPS:g} fps" in said[0]
    assert "--width/--height/--fps" in said[0]


def test_a_device_that_keeps_another_size_than_asked_is_said_once(caplog):
    # A camera that cannot do the requested mode keeps its own (FAKE capture: the request is
    # OpenCV's to pass on, and no device is here): the frames say which, and so does the log.
    cam = OpenCvCamera(0, hfov_deg=60.0, width=1280, height=720, capture_factory=FakeFactory([4]), poll_s=0.01,
                       reconnect=False)
    with caplog.at_level("WARNING", logger="drivers.opencv_camera"):
        frames = collect(cam)
    cam.close()
    assert frames and frames[0].image_bgr.shape == (H, W, 3)
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and f"camera 0 gives {W}x{H}, not the 1280x720 asked for" in said[0]


def test_reopens_slower_than_stall_s_in_an_outage_are_not_each_a_stall(caplog):
    # Reopening an unreachable stream takes OpenCV's open timeout (5 s) each time: in an outage
    # already said, each attempt was said and counted again as a stall, one warning per attempt.
    def slow_failing_open(_target, opens=[0]):  # noqa: B006 - the count of opens, kept across calls
        opens[0] += 1
        if opens[0] == 1:
            return DisappearingCapture(1)
        time.sleep(0.05)  # FAKE: an open that waits for its timeout
        return DisappearingCapture(0, opened=False)

    cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=slow_failing_open, backoff_s=(0.01, 0.01), poll_s=0.01,
                       stall_s=0.02)
    it = iter(cam)
    with caplog.at_level("WARNING", logger="drivers.opencv_camera"):
        assert next(it).seq == 0
        waiter = threading.Thread(target=lambda: next(it, None), daemon=True)  # the consumer waits on
        waiter.start()
        deadline = time.monotonic() + HANG_GUARD_S
        while cam.stats()["open_failures"] < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        cam.stop()
        waiter.join(HANG_GUARD_S)
    cam.close()
    said = [r.getMessage() for r in caplog.records]
    assert cam.stats()["stalls"] == 0 and not any("has not returned" in m for m in said)
    assert sum("read failed" in m for m in said) == 1  # the outage, said once


def test_a_read_that_fails_after_stop_says_no_reconnect(caplog):
    # A stalled read that fails (its timeout) after the rig stopped: the reader said "read failed;
    # reconnecting with backoff" below the run's summary, of a camera nobody reads any more.
    capture = StallingCapture(1)
    cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=lambda _: capture, poll_s=0.01, join_timeout_s=0.01)
    it = iter(cam)
    assert next(it).seq == 0
    deadline = time.monotonic() + HANG_GUARD_S
    while cam._busy is None and time.monotonic() < deadline:  # the reader is in its stalled read
        time.sleep(0.01)
    with caplog.at_level("WARNING", logger="drivers.opencv_camera"):
        cam.stop()
        assert list(it) == []
        capture.left = 0  # the read, when it returns, fails
        capture.resume.set()
        reader = cam._thread
        assert reader is not None
        reader.join(HANG_GUARD_S)
    cam.close()
    assert not any("read failed" in r.getMessage() for r in caplog.records)
    assert cam.stats()["read_failures"] == 0


# --- a real stream through FFmpeg: a local MJPEG-over-HTTP server that stops sending --------------


class StallingMjpegServer:
    """A real HTTP server on 127.0.0.1 that sends ``frames`` MJPEG frames, then holds the
    connection open and sends nothing (a camera whose stream stalled) until closed."""

    def __init__(self, frames: int):
        self.frames = frames
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}/stream.mjpg"
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self):
        self.sock.settimeout(HANG_GUARD_S)
        with contextlib.suppress(OSError):
            conn, _ = self.sock.accept()
            with conn:
                conn.recv(4096)
                conn.sendall(b"HTTP/1.0 200 OK\r\nContent-Type: multipart/x-mixed-replace; boundary=frame\r\n\r\n")
                for k in range(self.frames):
                    jpeg = cv2.imencode(".jpg", clip_image(k))[1].tobytes()
                    conn.sendall(b"--frame\r\nContent-Type: image/jpeg\r\nContent-Length: %d\r\n\r\n" % len(jpeg)
                                 + jpeg + b"\r\n")
                self.done.wait(HANG_GUARD_S)

    def close(self):
        self.done.set()
        self.sock.close()
        self.thread.join(HANG_GUARD_S)


def test_a_stalled_stream_leaves_only_sunrigs_own_lines_on_stderr(monkeypatch, capfd):
    # FFmpeg's read timeout ends the stalled read (0.5 s here, 5 s as shipped); OpenCV printed
    # "[ WARN:0@6.95] global cap_ffmpeg_impl.hpp:435 _opencv_ffmpeg_interrupt_callback Stream
    # timeout triggered after 5006 ms" beside the camera's own "read failed" warning.
    monkeypatch.setattr("drivers.opencv_camera._READ_TIMEOUT_MS", 500)
    server = StallingMjpegServer(frames=3)
    try:
        cam = OpenCvCamera(server.url, hfov_deg=60.0, poll_s=0.01, backoff_s=(HANG_GUARD_S, HANG_GUARD_S))
        capfd.readouterr()
        assert len(collect(cam, limit=3)) == 3
        deadline = time.monotonic() + HANG_GUARD_S
        while cam.stats()["read_failures"] == 0 and time.monotonic() < deadline:
            time.sleep(0.01)  # the stalled read's timeout
        cam.close()
    finally:
        server.close()
    assert cam.stats()["read_failures"] == 1
    assert "WARN" not in capfd.readouterr().err


# --- a distortion model other than OpenCV's standard one ------------------------------------------


@pytest.mark.parametrize("model", ["equidistant", "fisheye"])
def test_a_fisheye_calibration_is_refused_not_undistorted_as_another_model(tmp_path, model):
    # ROS camera_calibration --fisheye (and Kalibr) write distortion_model: equidistant with 4
    # coefficients k1..k4: read as k1, k2, p1, p2 of the standard model, every frame was bent the
    # wrong way without a word.
    path = tmp_path / "ost.yaml"
    path.write_text(_ROS_CAMERA_INFO.replace("plumb_bob", model).replace("cols: 5", "cols: 4")
                    .replace("[-0.31, 0.11, 0.0, 0.0, 0.0]", "[0.02, -0.01, 0.003, -0.001]"))
    with pytest.raises(CameraError, match=rf"distortion_model {model}: sunrig undistorts OpenCV's standard model"):
        load_calibration(path)
    table = tmp_path / "cam.toml"
    table.write_text(f'distortion_model = "{model}"\nimage_width = 1280\nimage_height = 720\n'
                     'camera_matrix = [[910.2, 0, 641.7], [0, 909.8, 362.4], [0, 0, 1]]\n'
                     'D = [0.02, -0.01, 0.003, -0.001]\n')
    with pytest.raises(CameraError, match=f"distortion_model {model}"):
        load_calibration(table)


def test_the_standard_distortion_models_by_name_are_read(tmp_path):
    path = tmp_path / "ost.yaml"
    path.write_text(_ROS_CAMERA_INFO.replace("plumb_bob", "rational_polynomial"))
    assert load_calibration(path).distorted


def test_a_camera_that_opens_but_never_gives_a_frame_says_what_that_may_be(caplog):
    # FAKE capture: opens, every read fails, as a V4L2 camera busy in another program, or a
    # stream that accepts and sends nothing. "read failed (stream lost?)" spoke of a loss.
    cam = OpenCvCamera(0, hfov_deg=60.0, capture_factory=FakeFactory([0, None]), backoff_s=(0.01, 0.01),
                       poll_s=0.01)
    got: list = []
    with caplog.at_level("WARNING", logger="drivers.opencv_camera"):
        waiter = threading.Thread(target=lambda: got.extend(cam), daemon=True)  # the consumer waits on
        waiter.start()
        deadline = time.monotonic() + HANG_GUARD_S
        while cam.stats()["read_failures"] == 0 and time.monotonic() < deadline:
            time.sleep(0.01)
        cam.stop()
        waiter.join(HANG_GUARD_S)
    cam.close()
    assert got == []
    said = [r.getMessage() for r in caplog.records if "read failed" in r.getMessage()]
    assert said == ["camera 0: read failed before its first frame (busy in another program? a stream that sends "
                    "nothing?); reconnecting with backoff"]
    assert "before its first frame" in cam.stats()["last_error"]
