"""Pick and open a live source from two specs: which camera, and where its heading comes from.

    --camera  oak | oak:DEVICE_ID             an OAK (DepthAI) colour camera        (drivers.oak)
              opencv:0                        a device index                         (drivers.opencv_camera)
              opencv:rtsp://HOST/PATH         a network stream (rtsp, http, ...)
              opencv:FILE                     a video file
              file:LOG                        a sunrig native log (replay.native), through the live path
    --heading oak-imu                         the OAK's own IMU (only with --camera oak)
              nmea:PORT                       a GNSS compass / INS on a serial port, pyserial URL or capture
                                              file, interpolated to each frame's time (drivers.pairing)
              visual                          visual odometry from the images: relative to the start
              none                            no heading (frames are counted and skipped by the rig)
              log                             the heading recorded in the log (only with --camera file:)

:func:`parse_camera` / :func:`parse_heading` / :func:`check_pair` are pure (a bad spec or a
combination that cannot work is a one-line :class:`SourceError` that says what to pass);
:func:`open_source` opens the devices and returns a :class:`LiveSource`: iterate it for Frames,
close it (a context manager) to release them. Device drivers are imported only when asked for.
"""

from __future__ import annotations

import dataclasses
import importlib
import logging
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from rig.errors import SourceError, SunrigError
from rig.types import Frame

log = logging.getLogger(__name__)

CAMERA_KINDS = ("oak", "opencv", "file")
HEADING_KINDS = ("oak-imu", "nmea", "visual", "none", "log")
CAMERA_HELP = "oak, oak:DEVICE_ID, opencv:0, opencv:rtsp://..., opencv:VIDEO_FILE or file:LOG"
HEADING_HELP = "oak-imu, nmea:PORT, visual, none or log"


@dataclass(frozen=True)
class CameraSpec:
    kind: str  # one of CAMERA_KINDS
    target: str = ""  # device index / URL / file for opencv, the log for file, a device id for oak

    def __str__(self) -> str:
        return f"{self.kind}:{self.target}" if self.target else self.kind


@dataclass(frozen=True)
class HeadingSpec:
    kind: str  # one of HEADING_KINDS
    target: str = ""  # the port for nmea

    def __str__(self) -> str:
        return f"{self.kind}:{self.target}" if self.target else self.kind


def parse_camera(spec: str) -> CameraSpec:
    """``--camera``: see the module docstring."""
    spec = (spec or "").strip()
    if not spec:
        raise SourceError(f"no camera given: pass --camera {CAMERA_HELP} (or set [source] camera in --config)")
    kind, sep, rest = spec.partition(":")
    if kind == "oak":
        return CameraSpec("oak", rest)
    if kind in ("opencv", "file"):
        if not rest:
            raise SourceError(f"--camera {spec}: say what to open after '{kind}:', e.g. "
                              + ("opencv:0 or opencv:rtsp://HOST/PATH" if kind == "opencv" else "file:drive.mcap"))
        return CameraSpec(kind, rest)
    raise SourceError(f"--camera {spec}: unknown camera {kind!r}; pass {CAMERA_HELP}")


def parse_heading(spec: str) -> HeadingSpec:
    """``--heading``: see the module docstring."""
    spec = (spec or "").strip()
    if not spec:
        raise SourceError(f"no heading given: pass --heading {HEADING_HELP}")
    kind, sep, rest = spec.partition(":")
    if kind == "nmea":
        if not rest:
            raise SourceError("--heading nmea: name the port, e.g. nmea:/dev/ttyUSB0, nmea:socket://HOST:PORT "
                              "or nmea:CAPTURE_FILE")
        return HeadingSpec("nmea", rest)
    if kind in ("oak-imu", "visual", "none", "log") and not rest:
        return HeadingSpec(kind)
    raise SourceError(f"--heading {spec}: unknown heading source; pass {HEADING_HELP}")


def check_pair(camera: CameraSpec, heading: HeadingSpec) -> None:
    """Refuse the combinations that cannot work, saying what to pass instead."""
    if heading.kind == "oak-imu" and camera.kind != "oak":
        raise SourceError(f"--heading oak-imu is the OAK's own IMU: use it with --camera oak, or pass "
                          f"--heading {_headings_for(camera)} for --camera {camera}")
    if heading.kind == "log" and camera.kind != "file":
        # The default heading: a config that sets only [source] camera to a live one comes here.
        raise SourceError(f"--heading log is a log's recorded heading: --camera {camera} has none; pass "
                          f"--heading {_headings_for(camera)} (or set [source] heading in --config)")
    if heading.kind == "nmea" and (camera.kind == "file" or _is_video_file(camera)):
        # A recording's frames carry the times of the session (or file) that made them: a
        # compass read now cannot be matched to them.
        raise SourceError(f"--camera {camera} replays a recording; a live --heading nmea: cannot be matched to "
                          f"its times; use --heading {_headings_for(camera)}")
    if heading.kind == "nmea" and Path(heading.target).is_file():
        # A capture is read to its end as the source opens, so every frame of a live camera comes
        # after its last sample: each would be counted "after" and none estimated.
        raise SourceError(f"--heading nmea:{heading.target} is a capture file, read to its end before the "
                          f"first frame of --camera {camera}; pass the live port (nmea:/dev/ttyUSB0 or "
                          "nmea:socket://HOST:PORT), or replay the capture with `sunrig gnss`")


def _headings_for(camera: CameraSpec) -> str:
    """The headings that work with ``camera``, as a refusal suggests them: the OAK's IMU only on an
    OAK, a log's heading only from a log, a live port only with a live camera."""
    names = ["oak-imu"] if camera.kind == "oak" else []
    if camera.kind == "file":
        names.append("log")
    elif not _is_video_file(camera):
        names.append("nmea:PORT")
    names.append("visual")
    return ", ".join(names) + " or none"


def is_recording(camera: CameraSpec) -> bool:
    """A ``file:`` log or an ``opencv:`` video file: its frames come as fast as they are read,
    stamped with the recording's own time (so that, not the wall clock, says how long it ran)."""
    return camera.kind == "file" or _is_video_file(camera)


def _is_video_file(camera: CameraSpec) -> bool:
    if camera.kind != "opencv":
        return False
    from drivers.opencv_camera import parse_target

    return parse_target(camera.target).kind == "file"


@dataclass(frozen=True)
class SourceOptions:
    """Options of the sources (the CLI's ``run``/``record`` flags). Degrees only at this interface."""

    calibration: str | None = None  # OpenCV calibration file (opencv, and overrides the OAK's own)
    hfov_deg: float | None = None  # or the horizontal field of view (opencv)
    width: int | None = None  # requested frame size and rate (opencv devices; the OAK's output)
    height: int | None = None
    fps: float | None = None
    baud: int = 115200  # nmea serial ports
    max_gap_s: float = 1.5  # pairing: see drivers.pairing
    max_age_s: float = 1.5
    heading_latency_s: float = 0.0  # pairing: the heading device's output latency
    declination_deg: float | None = None  # oak-imu: east positive, makes the rotation vector true north


class LiveSource:
    """Frames from the opened devices, with the heading attached. Iterate it once; close it (or
    use ``with``) to release the devices. ``stats()`` gathers every part's counters;
    ``gnss`` is the GNSS reader when the heading is ``nmea:``."""

    def __init__(self, camera: CameraSpec, heading: HeadingSpec, frames: Iterable[Frame],
                 parts: dict[str, Any], gnss: Any = None) -> None:
        self.camera = camera
        self.heading = heading
        self._frames = frames
        self._parts = parts  # name -> object with stats() and/or close()
        self.gnss = gnss
        self._closed = False

    def __iter__(self) -> Iterator[Frame]:
        return iter(self._frames)

    @property
    def truncated(self) -> bool:
        """A ``file:`` log that was cut off (replayed up to its last complete chunk)."""
        return any(getattr(p, "truncated", False) for p in self._parts.values())

    def stats(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for name, part in self._parts.items():
            stats = getattr(part, "stats", None)
            if callable(stats):
                out[name] = stats()
            elif isinstance(stats, dict):
                out[name] = dict(stats)
            elif dataclasses.is_dataclass(stats) and not isinstance(stats, type):
                out[name] = dataclasses.asdict(stats)
            elif hasattr(part, "as_dict"):
                out[name] = part.as_dict()
        return out

    def stop(self) -> None:
        """End the iteration from another thread (the rig stopping) even while no frame comes: the
        camera's ``stop()``, when it has one. Not its ``close()``: the rig's capture thread may be
        inside the device's calls, and the devices are closed by whoever opened them, after."""
        stop = getattr(self._parts.get("camera"), "stop", None)
        if callable(stop):
            stop()

    def describe(self) -> str:
        return f"camera {self.camera}, heading {self.heading}"

    def close(self) -> None:
        """Release every device. Idempotent."""
        if self._closed:
            return
        self._closed = True
        for name, part in reversed(list(self._parts.items())):
            close = getattr(part, "close", None)
            if callable(close):
                try:
                    close()
                except Exception as exc:  # noqa: BLE001 - one part failing to close must not keep the others open
                    log.warning("closing the %s source failed: %s", name, exc)

    def __enter__(self) -> LiveSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_source(camera: str, heading: str, *, options: SourceOptions | None = None,
                clock: Callable[[], float] | None = None) -> LiveSource:
    """Open ``--camera`` with ``--heading`` (see the module docstring). Every spec is checked
    before any device is opened, and a device that cannot be opened is a one-line SunrigError."""
    cam, head = parse_camera(camera), parse_heading(heading)
    check_pair(cam, head)
    opts = options or SourceOptions()
    parts: dict[str, Any] = {}
    try:
        if cam.kind == "file":
            _warn_unused_for_a_log(cam, opts)
            return _file_source(cam, head, parts)
        # The heading device first when it is separate: a wrong serial port fails before the camera starts.
        reader = _open_gnss(head, opts, clock) if head.kind == "nmea" else None
        if reader is not None:
            parts["gnss"] = reader
        if cam.kind == "oak":
            camera_src = _open_oak(cam, head, opts)
        else:
            camera_src = _open_opencv(cam, opts)
        parts["camera"] = camera_src
        frames: Iterable[Frame] = camera_src
        if head.kind == "nmea":
            from drivers.pairing import HeadingInterpolator, PairingStats, with_heading

            interp = HeadingInterpolator(opts.max_gap_s, opts.max_age_s, opts.heading_latency_s)
            pairing = PairingStats(interp)
            parts["pairing"] = pairing
            extra: dict[str, Any] = {"clock": clock} if clock is not None else {}  # else the default
            frames = with_heading(frames, reader, interp, stats=pairing, **extra)
        elif head.kind == "visual":
            frames = _visual(frames, parts)
        elif head.kind == "none":
            frames = _without_heading(frames)
        return LiveSource(cam, head, frames, parts, gnss=reader)
    except BaseException:
        LiveSource(cam, head, (), parts).close()
        raise


def _warn_unused_for_a_log(cam: CameraSpec, opts: SourceOptions) -> None:
    """A log carries its own intrinsics and frame size: say that a camera model passed with it is
    not used, where it would otherwise be dropped without a word (a rig's configuration file may
    well set one and be run on a log: a warning, not a refusal)."""
    unused = [flag for flag, value in (("--calibration", opts.calibration), ("--hfov-deg", opts.hfov_deg),
                                       ("--width", opts.width), ("--height", opts.height), ("--fps", opts.fps))
              if value]
    if unused:
        log.warning("%s not used with --camera file:%s: a log replays with the intrinsics, size and rate "
                    "it was recorded with", " and ".join(unused), cam.target)


def _file_source(cam: CameraSpec, head: HeadingSpec, parts: dict[str, Any]) -> LiveSource:
    from replay.sources import open_frames

    log_src = open_frames(cam.target)
    parts["log"] = log_src
    frames: Iterable[Frame] = log_src
    if head.kind == "visual":
        frames = _visual(frames, parts)
    elif head.kind == "none":
        frames = _without_heading(frames)
    return LiveSource(cam, head, frames, parts)


def _visual(frames: Iterable[Frame], parts: dict[str, Any]) -> Iterable[Frame]:
    from drivers.visual_odometry import VisualOdometry, with_visual_heading

    vo = VisualOdometry()
    parts["visual_odometry"] = vo
    return _Reiterable(lambda: with_visual_heading(frames, vo))


def _without_heading(frames: Iterable[Frame]) -> Iterable[Frame]:
    return _Reiterable(lambda: (dataclasses.replace(f, attitude=None) if f.attitude is not None else f
                                for f in frames))


class _Reiterable:
    """An iterable that makes a fresh generator per iteration (a log replays from its start)."""

    def __init__(self, make: Callable[[], Iterator[Frame]]) -> None:
        self._make = make

    def __iter__(self) -> Iterator[Frame]:
        return self._make()


def _open_gnss(head: HeadingSpec, opts: SourceOptions, clock: Callable[[], float] | None) -> Any:
    from drivers.gnss import GnssReader

    extra: dict[str, Any] = {"clock": clock} if clock is not None else {}  # else the default
    return GnssReader(head.target, baudrate=opts.baud, **extra)


def _open_opencv(cam: CameraSpec, opts: SourceOptions) -> Any:
    from drivers.opencv_camera import OpenCvCamera

    if opts.calibration is None and opts.hfov_deg is None:
        raise SourceError(f"--camera {cam} needs intrinsics: pass --calibration FILE (an OpenCV calibration) "
                          "or --hfov-deg DEG (its horizontal field of view)")
    if opts.calibration is not None and opts.hfov_deg is not None:
        raise SourceError("pass either --calibration or --hfov-deg, not both")
    return OpenCvCamera(cam.target, calibration=opts.calibration, hfov_deg=opts.hfov_deg, width=opts.width,
                        height=opts.height, fps=opts.fps)


def _open_oak(cam: CameraSpec, head: HeadingSpec, opts: SourceOptions) -> Any:
    """``drivers.oak.OakCamera``, imported here: the module (or DepthAI) may be missing."""
    try:
        oak = importlib.import_module("drivers.oak")
    except ImportError as exc:
        raise SourceError(f"--camera oak: the OAK driver cannot be loaded ({exc}); install DepthAI "
                          "(pip install 'depthai>=3') or use --camera opencv:N") from None
    fields: dict[str, Any] = {"imu_mode": "auto" if head.kind == "oak-imu" else "none"}
    if cam.target:
        fields["device_id"] = cam.target
    for name in ("width", "height", "fps", "declination_deg"):
        value = getattr(opts, name)
        if value is not None:
            fields[name] = value
    if opts.calibration is not None:
        from drivers.opencv_camera import fit_intrinsics, load_calibration

        defaults = oak.OakConfig()
        size = (fields.get("width", defaults.width), fields.get("height", defaults.height))
        fields["intrinsics"] = fit_intrinsics(*size, calibration=load_calibration(opts.calibration))
    elif opts.hfov_deg is not None:
        log.warning("--hfov-deg is ignored for an OAK: it reads its intrinsics from its own calibration")
    try:
        config = oak.OakConfig(**fields)
        return oak.OakCamera(config)
    except SunrigError:
        raise
    except Exception as exc:  # noqa: BLE001 - DepthAI raises RuntimeError for a missing device
        raise SourceError(f"--camera {cam}: cannot open the OAK: {type(exc).__name__}: {exc}; check the USB "
                          "cable and udev rules, or use --camera opencv:N") from None

