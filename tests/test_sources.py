"""Source selection (drivers/sources.py): the --camera / --heading specs, the combinations that
cannot work, and real sources opened through it: the bundled log, a video file written here,
missing devices and ports."""

from __future__ import annotations

import math
import sys
import time

import cv2
import numpy as np
import pytest

import drivers.sources as drivers_sources
from drivers.sources import (
    CameraSpec,
    HeadingSpec,
    SourceError,
    SourceOptions,
    check_pair,
    open_source,
    parse_camera,
    parse_heading,
)
from replay.sources import DEMO_LOG
from rig.errors import SunrigError
from rig.types import HeadingRef

# --- the specs -----------------------------------------------------------------------------------


@pytest.mark.parametrize(("spec", "expected"), [
    ("oak", CameraSpec("oak")),
    ("oak:14442C10D13EABCE00", CameraSpec("oak", "14442C10D13EABCE00")),
    ("opencv:0", CameraSpec("opencv", "0")),
    ("opencv:rtsp://10.0.0.5:554/h264", CameraSpec("opencv", "rtsp://10.0.0.5:554/h264")),
    ("opencv:/data/clip.mp4", CameraSpec("opencv", "/data/clip.mp4")),
    ("file:drive.mcap", CameraSpec("file", "drive.mcap")),
    ("file:C:/logs/drive.mcap", CameraSpec("file", "C:/logs/drive.mcap")),
])
def test_parse_camera(spec, expected):
    assert parse_camera(spec) == expected


@pytest.mark.parametrize(("spec", "expected"), [
    ("oak-imu", HeadingSpec("oak-imu")),
    ("nmea:/dev/ttyUSB0", HeadingSpec("nmea", "/dev/ttyUSB0")),
    ("nmea:socket://192.168.1.20:5017", HeadingSpec("nmea", "socket://192.168.1.20:5017")),
    ("visual", HeadingSpec("visual")),
    ("none", HeadingSpec("none")),
    ("log", HeadingSpec("log")),
])
def test_parse_heading(spec, expected):
    assert parse_heading(spec) == expected


@pytest.mark.parametrize(("spec", "match"), [
    ("", "no camera given"), ("usb:0", "unknown camera 'usb'"), ("opencv:", "after 'opencv:'"),
    ("file:", "file:drive.mcap"), ("webcam", "unknown camera"),
])
def test_bad_camera_specs_say_what_to_pass(spec, match):
    with pytest.raises(SourceError, match=match) as info:
        parse_camera(spec)
    assert "opencv:0" in str(info.value) or "file:" in str(info.value)


@pytest.mark.parametrize(("spec", "match"), [
    ("", "no heading given"), ("gps", "unknown heading"), ("nmea", "name the port"), ("visual:x", "unknown"),
    ("imu", "unknown heading"),
])
def test_bad_heading_specs_say_what_to_pass(spec, match):
    with pytest.raises(SourceError, match=match):
        parse_heading(spec)


@pytest.mark.parametrize(("camera", "heading", "match"), [
    ("opencv:0", "oak-imu", "use it with --camera oak"),
    ("file:x.mcap", "oak-imu", "use it with --camera oak"),
    ("opencv:0", "log", "has none"),
    ("oak", "log", "--heading oak-imu"),
    ("file:x.mcap", "nmea:/dev/ttyUSB0", "cannot be matched"),
    ("opencv:clip.avi", "nmea:/dev/ttyUSB0", "cannot be matched"),
])
def test_combinations_that_cannot_work(camera, heading, match):
    with pytest.raises(SourceError, match=match):
        check_pair(parse_camera(camera), parse_heading(heading))


@pytest.mark.parametrize(("camera", "heading"), [
    ("opencv:0", "oak-imu"), ("file:x.mcap", "oak-imu"), ("opencv:clip.avi", "oak-imu"),
    ("opencv:0", "log"), ("oak", "log"), ("opencv:clip.avi", "log"), ("file:x.mcap", "nmea:/dev/ttyUSB0"),
    ("opencv:clip.avi", "nmea:COM3"),
])
def test_every_heading_a_refusal_suggests_works_with_that_camera(camera, heading):
    # The way out must be a way out: a refusal for a file: camera once suggested nmea:PORT, which
    # is refused for it too, and left out log, the one that fits.
    import re

    with pytest.raises(SourceError) as info:
        check_pair(parse_camera(camera), parse_heading(heading))
    suggested = re.search(r"(?:pass|use) --heading (.+?)(?: for --camera| \(or set \[source\]|$)",
                          str(info.value)).group(1)
    names = [n.strip() for n in re.split(r",| or ", suggested) if n.strip()]
    assert names, str(info.value)
    for name in names:
        check_pair(parse_camera(camera), parse_heading(name.replace("PORT", "/dev/ttyUSB0")))


@pytest.mark.parametrize(("camera", "heading"), [
    ("oak", "oak-imu"), ("oak", "nmea:/dev/ttyUSB0"), ("oak", "visual"), ("opencv:0", "nmea:COM3"),
    ("opencv:rtsp://h/p", "visual"), ("opencv:clip.avi", "visual"), ("file:x.mcap", "log"),
    # A network stream is live (its frames carry the time they arrive), so a compass pairs with it:
    # only a video *file* is refused with nmea (parse_target: url and gstreamer are not files).
    ("opencv:rtsp://h/p", "nmea:/dev/ttyUSB0"), ("opencv:videotestsrc ! appsink", "nmea:COM3"),
    ("file:x.mcap", "visual"), ("file:x.mcap", "none"),
])
def test_combinations_that_work(camera, heading):
    check_pair(parse_camera(camera), parse_heading(heading))


def test_a_live_camera_with_an_nmea_capture_file_is_refused(tmp_path):
    # The capture is read to its end as it opens: every live frame came after its last sample,
    # was counted "after", and the run exited 0 having estimated nothing.
    capture = tmp_path / "compass.nmea"
    capture.write_bytes(b"$GPHDT,10.0,T*0A\r\n")
    for camera in ("opencv:0", "opencv:rtsp://h/p", "opencv:/dev/video0", "oak"):
        with pytest.raises(SourceError, match=r"is a capture file, read to its end before the first frame.*"
                                              r"nmea:/dev/ttyUSB0"):
            check_pair(parse_camera(camera), parse_heading(f"nmea:{capture}"))
    check_pair(parse_camera("opencv:0"), parse_heading(f"nmea:{tmp_path / 'ttyNOPE'}"))  # a port: its open says


# --- LiveSource: closing, stopping, truncation (fake parts: only the bookkeeping is under test) ----


class _Part:
    """FAKE source part: records its close() in ``log``; ``fail`` makes close() raise."""

    def __init__(self, name, log, fail=False, truncated=False):
        self.name, self.log, self.fail, self.truncated = name, log, fail, truncated

    def close(self):
        self.log.append(self.name)
        if self.fail:
            raise OSError(f"{self.name} would not close")


def test_close_releases_every_part_newest_first_once_even_when_one_fails():
    # LiveSource.close: the camera was opened after the heading port, so it is released first;
    # a part that fails to close must not keep the others open; a second close does nothing.
    closed = []
    src = drivers_sources.LiveSource(parse_camera("opencv:0"), parse_heading("nmea:COM3"), (),
                                     {"gnss": _Part("gnss", closed), "camera": _Part("camera", closed, fail=True)})
    src.close()
    assert closed == ["camera", "gnss"]
    src.close()
    assert closed == ["camera", "gnss"]


def test_one_truncated_part_makes_the_source_truncated():
    parts = {"log": _Part("log", [], truncated=True), "visual_odometry": _Part("vo", [])}
    assert drivers_sources.LiveSource(CameraSpec("file", "x"), HeadingSpec("visual"), (), parts).truncated
    parts["log"].truncated = False
    assert not drivers_sources.LiveSource(CameraSpec("file", "x"), HeadingSpec("visual"), (), parts).truncated


def test_stop_asks_the_camera_to_stop_and_never_closes_it():
    # The rig calls stop() from its own thread while its capture thread may be inside the
    # camera's calls (an OAK's): closing the device under it is not a stop. Whoever opened the
    # devices closes them, after the rig has returned.
    class Stoppable(_Part):
        def stop(self):
            self.log.append(f"{self.name} stop")

    calls: list[str] = []
    parts = {"camera": Stoppable("cam", calls), "gnss": _Part("gnss", calls)}
    drivers_sources.LiveSource(CameraSpec("opencv", "0"), HeadingSpec("nmea", "x"), (), parts).stop()
    assert calls == ["cam stop"]
    drivers_sources.LiveSource(CameraSpec("file", "x"), HeadingSpec("log"), (), {"camera": _Part("cam", calls)}).stop()
    assert calls == ["cam stop"]  # a camera without stop() is left as it is


def test_a_camera_that_fails_to_open_closes_the_heading_port_opened_before_it(monkeypatch):
    # open_source opens the nmea port first; when the camera then fails, the port must not be
    # left open (the except branch closes every part opened so far).
    closed = []
    monkeypatch.setattr(drivers_sources, "_open_gnss", lambda head, opts, clock: _Part("gnss", closed))
    with pytest.raises(SunrigError, match="no camera at index 63"):
        open_source("opencv:63", "nmea:COM3", options=SourceOptions(hfov_deg=60.0))
    assert closed == ["gnss"]


# --- the OAK's settings, through a stand-in for drivers.oak (no OAK on a test machine) -----------


class _FakeOakConfig:
    """FAKE drivers.oak.OakConfig (no OAK here): keeps the fields it is given."""

    from drivers.oak import OakConfig as _Real

    width, height = _Real.width, _Real.height  # the real defaults, which _open_oak reads
    del _Real

    def __init__(self, **fields):
        self.fields = fields


@pytest.fixture
def fake_oak(monkeypatch):
    """FAKE OAK driver (no OAK device can run here): installs a drivers.oak whose OakCamera
    records the OakConfig fields it was given (its stats()), or raises ``fake.error`` when set."""
    import types

    module = types.ModuleType("drivers.oak")
    module.error = None

    class FakeOakCamera:
        def __init__(self, config):
            if module.error is not None:
                raise module.error
            self.config = config

        def stats(self):
            return dict(self.config.fields)

    module.OakConfig, module.OakCamera = _FakeOakConfig, FakeOakCamera
    monkeypatch.setitem(sys.modules, "drivers.oak", module)
    return module


def oak_fields(camera, heading, **options):
    with open_source(camera, heading, options=SourceOptions(**options)) as src:
        return src.stats()["camera"]


def test_oak_options_reach_its_config(fake_oak):
    # The OAK's own IMU is read only when it is the heading source; every option given is passed.
    assert oak_fields("oak:14442C10D13EABCE00", "oak-imu", fps=10.0, declination_deg=3.5) == {
        "imu_mode": "auto", "device_id": "14442C10D13EABCE00", "fps": 10.0, "declination_deg": 3.5}
    assert oak_fields("oak", "visual", width=320, height=200) == {"imu_mode": "none", "width": 320, "height": 200}


def test_an_oak_calibration_file_is_fitted_to_the_oak_output_size(fake_oak, tmp_path):
    # A calibration at 1280x800 (fx = fy = 1000, centre 640, 400) scaled to the output size:
    # the default 640x400 halves it, a requested 320x200 quarters it.
    path = tmp_path / "oak.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("camera_matrix", np.array([[1000.0, 0, 640.0], [0, 1000.0, 400.0], [0, 0, 1]]))
    fs.write("image_width", 1280)
    fs.write("image_height", 800)
    fs.release()
    intr = oak_fields("oak", "oak-imu", calibration=str(path))["intrinsics"]
    assert (intr.width, intr.height, intr.fx, intr.cx, intr.cy) == (640, 400, 500.0, 320.0, 200.0)
    intr = oak_fields("oak", "oak-imu", calibration=str(path), width=320, height=200)["intrinsics"]
    assert (intr.width, intr.height, intr.fx) == (320, 200, 250.0)


def test_oak_driver_errors_keep_their_message_and_others_become_one_line(fake_oak):
    from rig.errors import CameraError

    fake_oak.error = CameraError("no OAK with id 1844301")
    with pytest.raises(CameraError, match="^no OAK with id 1844301$"):
        open_source("oak", "visual")
    fake_oak.error = RuntimeError("X_LINK_DEVICE_NOT_FOUND")
    with pytest.raises(SourceError, match="cannot open the OAK: RuntimeError: X_LINK_DEVICE_NOT_FOUND"):
        open_source("oak", "visual")


# --- opening real sources ------------------------------------------------------------------------


def test_file_log_with_its_own_heading():
    with open_source(f"file:{DEMO_LOG}", "log") as src:
        frames = list(src)
    assert len(frames) == 40 and all(f.attitude.reference is HeadingRef.TRUE for f in frames)
    assert src.stats()["log"] is not None


def test_a_camera_model_passed_with_a_log_is_said_to_be_unused(caplog, tmp_path):
    # It was dropped without a word, even a calibration file that does not exist.
    opts = SourceOptions(calibration=str(tmp_path / "nope.yaml"), fps=30.0)
    with caplog.at_level("WARNING", logger="drivers.sources"), open_source(f"file:{DEMO_LOG}", "log",
                                                                          options=opts) as src:
        frames = list(src)
    assert len(frames) == 40 and frames[0].intrinsics.width == 1242  # the log's own
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and said[0].startswith("--calibration and --fps not used with --camera file:"), said
    caplog.clear()
    with caplog.at_level("WARNING", logger="drivers.sources"), open_source(f"file:{DEMO_LOG}", "log") as src:
        next(iter(src))
    assert not caplog.records


def test_file_log_with_visual_heading_replaces_the_recorded_one():
    with open_source(f"file:{DEMO_LOG}", "visual") as src:
        frames = list(src)
        stats = src.stats()["visual_odometry"]
    assert len(frames) == 40 and stats["frames"] == 40
    with_heading = [f for f in frames if f.attitude is not None]
    assert len(with_heading) >= 35 and all(f.attitude.reference is HeadingRef.RELATIVE for f in with_heading)
    assert frames[0].attitude.heading_rad == 0.0


def test_file_log_without_heading():
    with open_source(f"file:{DEMO_LOG}", "none") as src:
        assert all(f.attitude is None for f in src)


def test_a_missing_log_is_one_line(tmp_path):
    with pytest.raises(SunrigError) as info:
        open_source(f"file:{tmp_path / 'nope.mcap'}", "log")
    assert "\n" not in str(info.value)


@pytest.fixture
def video(tmp_path):
    """A small pan to the right over a textured strip: an MJPG video written with cv2.VideoWriter."""
    rng = np.random.default_rng(0)
    strip = cv2.resize(rng.integers(0, 256, (30, 200), dtype=np.uint8), (800, 120), interpolation=cv2.INTER_NEAREST)
    strip = cv2.cvtColor(cv2.GaussianBlur(strip, (3, 3), 0), cv2.COLOR_GRAY2BGR)
    path = tmp_path / "pan.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (160, 120))
    for k in range(8):
        writer.write(np.ascontiguousarray(strip[:, 4 * k:4 * k + 160]))
    writer.release()
    return path


def test_opencv_video_with_visual_heading(video):
    with open_source(f"opencv:{video}", "visual", options=SourceOptions(hfov_deg=60.0)) as src:
        frames = list(src)
    assert len(frames) == 8 and [f.seq for f in frames] == list(range(8))
    assert all(f.attitude is not None and f.attitude.reference is HeadingRef.RELATIVE for f in frames)
    # The view slides left across the strip: the camera turned right, so the heading grows.
    turn = math.remainder(frames[-1].attitude.heading_rad, 2 * math.pi)
    assert turn > 0


def test_opencv_needs_intrinsics(video):
    with pytest.raises(SourceError, match="--calibration FILE.*--hfov-deg"):
        open_source(f"opencv:{video}", "visual")
    with pytest.raises(SourceError, match="not both"):
        open_source(f"opencv:{video}", "visual", options=SourceOptions(hfov_deg=60.0, calibration="x.yaml"))


def test_missing_devices_are_one_line_errors(tmp_path):
    for camera, heading in (("opencv:63", "none"), (f"opencv:{tmp_path / 'none.avi'}", "visual"),
                            ("opencv:0", f"nmea:{tmp_path / 'no-port'}")):
        with pytest.raises(SunrigError) as info:
            open_source(camera, heading, options=SourceOptions(hfov_deg=60.0))
        assert "\n" not in str(info.value), camera


def test_the_heading_port_is_opened_before_the_camera(tmp_path):
    # The GNSS port fails first, so its error is the one reported even with a camera that is missing too.
    with pytest.raises(SunrigError, match="GNSS source"):
        open_source("opencv:63", f"nmea:{tmp_path / 'no-port'}", options=SourceOptions(hfov_deg=60.0))


def test_oak_without_its_driver_is_one_clear_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "drivers.oak", None)  # as if the module or DepthAI were not installed
    with pytest.raises(SourceError, match="OAK driver cannot be loaded.*opencv:N"):
        open_source("oak", "oak-imu")


def test_oak_without_a_device_is_one_clear_error():
    pytest.importorskip("depthai")
    with pytest.raises(SunrigError) as info:
        open_source("oak", "visual")
    assert "\n" not in str(info.value) and "OAK" in str(info.value)


# --- sunrig record -------------------------------------------------------------------------------


def record(*args: str) -> int:
    from rig.cli import main

    return main(["record", *args])


def test_record_a_video_with_visual_heading_and_replay_it(video, tmp_path, capsys):
    from replay.native import read_frames

    out = tmp_path / "rec.mcap"
    assert record("--camera", f"opencv:{video}", "--heading", "visual", "--hfov-deg", "60", "--out", str(out)) == 0
    assert "record: 8 frames (8 with heading)" in capsys.readouterr().err
    frames = list(read_frames(out))
    assert [f.seq for f in frames] == list(range(8))
    assert frames[0].intrinsics.width == 160 and math.degrees(frames[0].intrinsics.hfov_rad) == pytest.approx(60.0)
    assert all(f.attitude.reference is HeadingRef.RELATIVE for f in frames)
    assert [f.t_mono_s for f in frames] == pytest.approx([k / 10.0 for k in range(8)], abs=1e-3)


def test_record_a_log_with_its_heading_and_a_frame_limit(tmp_path):
    from replay.native import read_frames

    out = tmp_path / "rec.mcap"
    assert record("--camera", f"file:{DEMO_LOG}", "--heading", "log", "--frames", "10", "--out", str(out),
                  "--quiet") == 0
    got = list(read_frames(out))
    original = list(read_frames(DEMO_LOG))[:10]
    assert len(got) == 10
    for a, b in zip(got, original, strict=True):
        assert a.seq == b.seq and a.t_mono_s == b.t_mono_s and a.utc_ns == b.utc_ns
        assert a.attitude.heading_rad == pytest.approx(b.attitude.heading_rad, abs=1e-9)
        assert np.allclose(a.sun_enu_truth, b.sun_enu_truth)


def test_record_a_bad_source_creates_no_file(tmp_path, capsys):
    out = tmp_path / "rec.mcap"
    assert record("--camera", "opencv:63", "--heading", "none", "--hfov-deg", "60", "--out", str(out)) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no camera at index 63" in err[0]
    assert not out.exists()


class InterruptedSource:
    """The demo log's frames, with a real signal (SIGINT: Ctrl-C) raised after ``after`` frames."""

    def __init__(self, after: int, signame: str = "SIGINT"):
        self.after, self.signame = after, signame
        self.closed = False
        self.camera = parse_camera(f"file:{DEMO_LOG}")  # what it stands in for (LiveSource.camera)

    def __iter__(self):
        import signal

        from replay.native import read_frames

        for k, frame in enumerate(read_frames(DEMO_LOG)):
            if k == self.after:
                signal.raise_signal(getattr(signal, self.signame))
            yield frame

    def stats(self):
        return {}

    def stop(self):
        pass

    def close(self):
        self.closed = True


# SIGTERM is how systemd and docker stop a service, SIGHUP what a dropped ssh session sends: both
# stop a recording as Ctrl-C does. Their default action would end the process with nothing flushed.
@pytest.mark.parametrize(("signame", "said"), [("SIGINT", "Ctrl-C"), ("SIGTERM", "SIGTERM"), ("SIGHUP", "SIGHUP")])
def test_ctrl_c_while_waiting_for_a_frame_finishes_the_log(tmp_path, monkeypatch, capsys, signame, said):
    import drivers.sources
    from replay.native import open_log

    source = InterruptedSource(after=5, signame=signame)
    monkeypatch.setattr(drivers.sources, "open_source", lambda *a, **k: source)
    out = tmp_path / "rec.mcap"
    assert record("--camera", f"file:{DEMO_LOG}", "--heading", "log", "--out", str(out)) == 0
    assert f"stopped by {said}; the log is complete" in capsys.readouterr().err
    log = open_log(out)
    assert len(list(log)) == 5 and not log.truncated and source.closed


@pytest.mark.parametrize("signame", ["SIGINT", "SIGTERM"])
def test_ctrl_c_while_writing_a_frame_lets_it_finish(tmp_path, monkeypatch, signame):
    import signal

    from replay.native import LogWriter, read_frames

    real_write = LogWriter.write_frame

    def write_then_interrupt(self, frame, **kw):
        if frame.seq == 2:
            signal.raise_signal(getattr(signal, signame))  # arrives mid-write: must not cut the frame in half
        real_write(self, frame, **kw)

    monkeypatch.setattr(LogWriter, "write_frame", write_then_interrupt)
    out = tmp_path / "rec.mcap"
    assert record("--camera", f"file:{DEMO_LOG}", "--heading", "log", "--out", str(out), "--quiet") == 0
    assert [f.seq for f in read_frames(out)] == [0, 1, 2]


def test_a_signal_after_the_wait_message_quits_a_record_whose_write_hangs(tmp_path, monkeypatch):
    # A first signal mid-write is held so the frame is written whole, and says to signal once
    # more; a disk that never returns must not make the recording unstoppable short of SIGKILL.
    import signal

    import rig.stopping
    from replay.native import LogWriter, read_frames

    # A person's second signal, after the wait message: not one burst with the first, though
    # raised microseconds after it here (rig.stopping.BURST_S).
    monkeypatch.setattr(rig.stopping, "BURST_S", 0.0)
    real_write = LogWriter.write_frame
    slept = []

    def hanging_write(self, frame, **kw):
        if frame.seq == 2:
            for _ in range(2):
                signal.raise_signal(signal.SIGTERM)  # the second raises here, inside the write
            time.sleep(5.0)  # a disk that does not answer: never reached
            slept.append(True)
        real_write(self, frame, **kw)

    monkeypatch.setattr(LogWriter, "write_frame", hanging_write)
    out = tmp_path / "rec.mcap"
    assert record("--camera", f"file:{DEMO_LOG}", "--heading", "log", "--out", str(out), "--quiet") == 0
    assert slept == [] and [f.seq for f in read_frames(out)] == [0, 1]  # closed properly, frame 2 not begun


@pytest.mark.torch
def test_run_a_video_with_visual_heading(video, tmp_path, tiny_model_dir):
    import json

    from rig.cli import main

    out = tmp_path / "est.jsonl"
    assert main(["run", "--camera", f"opencv:{video}", "--heading", "visual", "--hfov-deg", "60", "--model",
                 str(tiny_model_dir), "--jsonl", str(out), "--fast", "--quiet"]) == 0
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert rows and all(r["heading_ref"] == "relative" for r in rows)


def test_a_live_camera_left_with_the_default_heading_is_told_where_to_set_one():
    # A service's config that sets only [source] camera gets the default heading, a log's: the
    # refusal named only the flag, which a service never passes.
    with pytest.raises(SourceError) as err:
        check_pair(parse_camera("opencv:0"), parse_heading("log"))
    assert str(err.value).endswith("pass --heading nmea:PORT, visual or none (or set [source] heading in --config)")
