"""The core value types every source, the estimator and every publisher share.

All are frozen dataclasses validated once, when made, with messages that give expected vs actual.
Arrays handed to them are made read-only, so a cached frame cannot change under the estimator.
Radians inside; ``_deg`` only in the JSON views for humans and wires.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from datetime import UTC, datetime

import numpy as np

from rig.errors import ValidationError
from rig.geometry import angle_between, az_el_from_enu, wrap_2pi, wrap_pi, wrapped_deg

_UNIT_TOL = 1e-3
_UNIT_ROUNDING = 1e-12  # a norm this close to 1 is a unit vector's, rounded

# What a camera is, bounded where it enters (a calibration file, --hfov-deg, a KITTI calibration,
# a recorded log, a device): beyond these a number is damaged, not a lens.
#
# OpenCV keeps an image's rows and columns in C ints, so no source yields a larger side (and a
# 400-digit one overflowed the float arithmetic of the field of view).
MAX_IMAGE_SIDE_PX = 2**31 - 1
# The narrowest field of view, across the image's longer side. The narrowest imagers built,
# adaptive-optics cameras behind 8-10 m telescopes, see about 10 arcsec across; 1e-4 deg (0.36 arcsec)
# is far below them. A longer focal length (1e308 px in a damaged calibration) is no camera, and
# its crops' sides, fx * tan(angle), overflowed to inf. With sides up to MAX_IMAGE_SIDE_PX it keeps
# fx and fy below 1.3e15 px. Over the longer side, so the one row of a line-scan camera is no fault.
MIN_FOV_DEG = 1e-4
# The shortest focal length: at a millionth of a pixel every pixel but the central one sits within
# 0.0001 deg of 90 deg off axis, which no rectified pinhole image does (179 deg, the widest
# --hfov-deg, on a one-pixel-wide image is 0.004 px); far shorter ones overflowed (u - cx) / fx.
MIN_FOCAL_PX = 1e-6


class HeadingRef(enum.StrEnum):
    """What a heading of 0 points at."""

    TRUE = "true"  # true (geographic) north
    MAGNETIC = "magnetic"  # magnetic north; needs a declination to become true
    RELATIVE = "relative"  # the source's own start heading (gyro, game rotation vector, VO)


def _finite(name: str, value: float) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise ValidationError(f"{name}: expected a real number, got {value!r}") from None
    if not math.isfinite(value):
        raise ValidationError(f"{name}: expected a finite number, got {value}")
    return value


def _vector3(name: str, value, unit: bool) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,):
        raise ValidationError(f"{name}: expected shape (3,), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValidationError(f"{name}: expected finite values, got {arr.tolist()}")
    if unit and abs(np.linalg.norm(arr) - 1.0) > _UNIT_TOL:
        raise ValidationError(
            f"{name}: expected a unit vector (norm 1 +- {_UNIT_TOL}), got norm {np.linalg.norm(arr):.6f}"
        )
    # Within the tolerance, made unit: the wire promises 1 +- 0.0009 after its 3-decimal rounding,
    # which a vector 0.9991 long that passed the check above would not keep. One unit to rounding
    # is kept bit for bit (a log's round trip gives back the vector it was given).
    norm = float(np.linalg.norm(arr))
    arr = arr / norm if unit and abs(norm - 1.0) > _UNIT_ROUNDING else arr.copy()
    arr.setflags(write=False)
    return arr


# UTC instants are int64 ns since the epoch (numpy's datetime64[ns], the binary frame's field).
_INT64 = (-(2**63), 2**63 - 1)


def _seq(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < 0:
        raise ValidationError(f"{name}: expected a non-negative integer, got {value!r}")
    return int(value)


def _utc_ns(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or not _INT64[0] <= value <= _INT64[1]:
        raise ValidationError(f"{name}: expected integer ns since the epoch (int64), got {value!r}")
    return int(value)


@dataclass(frozen=True)
class Intrinsics:
    """Pinhole intrinsics in pixels of the image they describe (no distortion: rectified images)."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        for name in ("width", "height"):
            v = getattr(self, name)
            try:
                whole = int(v) == v
            except (TypeError, ValueError, OverflowError):  # None, "64", nan, inf
                whole = False
            if not whole or v <= 0:
                raise ValidationError(f"Intrinsics.{name}: expected a positive integer, got {v!r}")
            if v > MAX_IMAGE_SIDE_PX:
                raise ValidationError(f"Intrinsics.{name}: expected at most {MAX_IMAGE_SIDE_PX} pixels, got {v!r}")
            object.__setattr__(self, name, int(v))
        side = max(self.width, self.height)
        longest = (side / 2.0) / math.tan(math.radians(MIN_FOV_DEG) / 2.0)  # as from_hfov makes it
        for name in ("fx", "fy"):
            v = _finite(name, getattr(self, name))
            if v <= 0:
                raise ValidationError(f"Intrinsics.{name}: expected > 0 pixels, got {v}")
            if v < MIN_FOCAL_PX:
                raise ValidationError(f"Intrinsics.{name}: expected at least {MIN_FOCAL_PX:g} pixels, got {v}")
            if v > longest:
                raise ValidationError(
                    f"Intrinsics.{name}: expected at most {longest:.6g} pixels (a field of view of at least "
                    f"{MIN_FOV_DEG:g} deg across the image's {side} px), got {v}"
                )
            object.__setattr__(self, name, v)
        for name, limit in (("cx", self.width), ("cy", self.height)):
            v = _finite(name, getattr(self, name))
            if not 0.0 <= v <= limit:
                raise ValidationError(f"Intrinsics.{name}: expected within [0, {limit}] pixels, got {v}")
            object.__setattr__(self, name, v)

    @property
    def hfov_rad(self) -> float:
        """Horizontal field of view, edge to edge."""
        return math.atan(self.cx / self.fx) + math.atan((self.width - self.cx) / self.fx)

    @property
    def vfov_rad(self) -> float:
        """Vertical field of view, edge to edge."""
        return math.atan(self.cy / self.fy) + math.atan((self.height - self.cy) / self.fy)

    @classmethod
    def from_hfov(cls, width: int, height: int, hfov_rad: float) -> Intrinsics:
        """Square pixels, principal point at the centre, focal length from a horizontal FOV."""
        fx = (width / 2.0) / math.tan(hfov_rad / 2.0)
        return cls(fx=fx, fy=fx, cx=width / 2.0, cy=height / 2.0, width=width, height=height)


@dataclass(frozen=True)
class Attitude:
    """Camera heading (yaw, clockwise from the reference's north) and, where known, pitch/roll.

    ``epoch`` tells apart the zeros of a relative heading: a source that loses its zero (an IMU
    that reconnects and starts again at 0, visual odometry that restarts) counts up, and headings
    of different epochs are never put in one window. Absolute references keep epoch 0.
    """

    heading_rad: float
    reference: HeadingRef
    pitch_rad: float | None = None
    roll_rad: float | None = None
    epoch: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "heading_rad", float(wrap_2pi(_finite("heading_rad", self.heading_rad))))
        try:
            object.__setattr__(self, "reference", HeadingRef(self.reference))
        except ValueError:
            raise ValidationError(
                f"Attitude.reference: expected one of {[r.value for r in HeadingRef]}, got {self.reference!r}"
            ) from None
        if isinstance(self.epoch, bool) or not isinstance(self.epoch, int | np.integer) or self.epoch < 0:
            raise ValidationError(f"Attitude.epoch: expected an integer >= 0, got {self.epoch!r}")
        object.__setattr__(self, "epoch", int(self.epoch))
        for name in ("pitch_rad", "roll_rad"):
            v = getattr(self, name)
            if v is not None:
                v = _finite(name, v)
                if abs(v) > math.pi:
                    raise ValidationError(f"Attitude.{name}: expected within [-pi, pi] rad, got {v}")
                object.__setattr__(self, name, v)


@dataclass(frozen=True)
class GnssFix:
    """A position fix with its UTC time (ns since the Unix epoch)."""

    utc_ns: int
    lat_deg: float
    lon_deg: float
    alt_m: float | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "utc_ns", _utc_ns("GnssFix.utc_ns", self.utc_ns))
        lat = _finite("lat_deg", self.lat_deg)
        lon = _finite("lon_deg", self.lon_deg)
        if not -90.0 <= lat <= 90.0:
            raise ValidationError(f"GnssFix.lat_deg: expected within [-90, 90] deg, got {lat}")
        if not -180.0 <= lon <= 360.0:
            raise ValidationError(f"GnssFix.lon_deg: expected within [-180, 360] deg, got {lon}")
        object.__setattr__(self, "lat_deg", lat)
        object.__setattr__(self, "lon_deg", lon)
        if self.alt_m is not None:
            object.__setattr__(self, "alt_m", _finite("alt_m", self.alt_m))


@dataclass(frozen=True, eq=False)
class FrameMeta:
    """Everything known about a camera frame but its pixels: its time, sequence number, camera,
    heading, UTC, position and true sun. A :class:`Frame` is one with its image.

    Once the backbone has encoded a frame's crops nothing downstream reads its pixels, and the ring
    keeps a few seconds of frames: 128 frames of a 1920 x 1080 camera are 800 MB of images, which a
    small computer does not have to spare (``benchmarks/bench_rig.py --resolution``). So features
    keep this (:meth:`Frame.meta`), not the frame.

    ``t_mono_s`` is the monotonic pipeline clock (``time.monotonic()``, DepthAI's host clock) at
    mid-exposure; ``seq`` counts frames from the source, strictly increasing.
    """

    t_mono_s: float
    seq: int
    intrinsics: Intrinsics
    attitude: Attitude | None = None
    utc_ns: int | None = None
    gnss: GnssFix | None = None
    sun_enu_truth: np.ndarray | None = None

    def __post_init__(self) -> None:
        cls = type(self).__name__  # errors name the type the caller made: Frame.seq, FrameMeta.seq
        object.__setattr__(self, "t_mono_s", _finite("t_mono_s", self.t_mono_s))
        object.__setattr__(self, "seq", _seq(f"{cls}.seq", self.seq))
        if not isinstance(self.intrinsics, Intrinsics):
            raise ValidationError(f"{cls}.intrinsics: expected Intrinsics, got {type(self.intrinsics).__name__}")
        if self.attitude is not None and not isinstance(self.attitude, Attitude):
            raise ValidationError(f"{cls}.attitude: expected Attitude or None, got {type(self.attitude).__name__}")
        if self.gnss is not None and not isinstance(self.gnss, GnssFix):
            raise ValidationError(f"{cls}.gnss: expected GnssFix or None, got {type(self.gnss).__name__}")
        if self.utc_ns is not None:
            object.__setattr__(self, "utc_ns", _utc_ns(f"{cls}.utc_ns", self.utc_ns))
        if self.sun_enu_truth is not None:
            object.__setattr__(self, "sun_enu_truth", _vector3(f"{cls}.sun_enu_truth", self.sun_enu_truth, unit=True))

    @property
    def heading_rad(self) -> float | None:
        return None if self.attitude is None else self.attitude.heading_rad


@dataclass(frozen=True, eq=False)
class Frame(FrameMeta):
    """One camera frame with everything known about it at capture. The one type every source yields.

    The fields of :class:`FrameMeta`, and ``image_bgr`` (H, W, 3) uint8 BGR, read-only, of the
    intrinsics' size: a keyword argument, as a subclass's field comes after its base's defaults.
    """

    image_bgr: np.ndarray = field(kw_only=True)

    def __post_init__(self) -> None:
        super().__post_init__()
        img = self.image_bgr
        if not isinstance(img, np.ndarray):
            raise ValidationError(f"Frame.image_bgr: expected a numpy array, got {type(img).__name__}")
        if img.dtype != np.uint8:
            raise ValidationError(f"Frame.image_bgr: expected dtype uint8, got {img.dtype}")
        if img.ndim != 3 or img.shape[2] != 3:
            raise ValidationError(f"Frame.image_bgr: expected shape (H, W, 3) BGR, got {img.shape}")
        if img.shape[:2] != (self.intrinsics.height, self.intrinsics.width):
            raise ValidationError(
                "Frame.image_bgr: expected shape "
                f"({self.intrinsics.height}, {self.intrinsics.width}, 3) to match the intrinsics, got {img.shape}"
            )
        if img.flags.writeable:
            img = img.view()
            img.setflags(write=False)
            object.__setattr__(self, "image_bgr", img)

    def meta(self) -> FrameMeta:
        """Everything about this frame but its pixels (what the ring keeps once they are encoded)."""
        return FrameMeta(self.t_mono_s, self.seq, self.intrinsics, self.attitude, self.utc_ns, self.gnss,
                         self.sun_enu_truth)


@dataclass(frozen=True, eq=False)
class FrameFeatures:
    """A frame with its crops' view angles and backbone embeddings, computed once when it arrives.

    ``frame`` is the frame without its pixels (:class:`FrameMeta`); a :class:`Frame` given is kept
    as its ``meta()``, so that nothing holding features (the ring, a replay's window) holds images.

    ``crop_boxes_px`` rows are (x0, y0, side_x, side_y) in image pixels; ``crop_angles_rad`` rows are
    (horizontal, vertical) view angles of the crop centres; ``embeddings`` rows are the backbone's
    output per crop. ``model_id`` names the backbone that made them, so a cache never mixes models.
    ``embeddings_mirrored``, for a model run mirrored (its contract's ``mirror_windows``), are the
    same crops' embeddings flipped left to right, row for row; None otherwise.

    ``view_signature`` is the frame's image shrunk to 12 x 32 cells, with its slopes along x and
    y in two more planes (``rig.window.view_signature``), to tell a new view
    from the same one again (a vehicle standing: ``rig.window.ViewClock``), which then stamps
    ``t_view_s`` (the frame's time with the time stood still before it taken out) and
    ``view_seq`` (the seq of the first frame of its view). None where nothing measured or stamped
    them: the frame is then a view of its own, at its own time.
    """

    frame: FrameMeta
    crop_boxes_px: np.ndarray
    crop_angles_rad: np.ndarray
    embeddings: np.ndarray
    model_id: str
    embeddings_mirrored: np.ndarray | None = None
    view_signature: np.ndarray | None = None
    t_view_s: float | None = None
    view_seq: int | None = None

    def __post_init__(self) -> None:
        if isinstance(self.frame, Frame):
            object.__setattr__(self, "frame", self.frame.meta())
        elif not isinstance(self.frame, FrameMeta):
            raise ValidationError(f"FrameFeatures.frame: expected Frame or FrameMeta, got {type(self.frame).__name__}")
        n = len(self.crop_boxes_px)
        checks = (
            ("crop_boxes_px", self.crop_boxes_px, (n, 4)),
            ("crop_angles_rad", self.crop_angles_rad, (n, 2)),
        )
        for name, arr, shape in checks:
            if np.shape(arr) != shape:
                raise ValidationError(f"FrameFeatures.{name}: expected shape {shape}, got {np.shape(arr)}")
        emb = self.embeddings
        if not isinstance(emb, np.ndarray) or emb.ndim != 2 or emb.shape[0] != n:
            raise ValidationError(f"FrameFeatures.embeddings: expected shape ({n}, D), got {np.shape(emb)}")
        if emb.dtype != np.float32:
            raise ValidationError(f"FrameFeatures.embeddings: expected dtype float32, got {emb.dtype}")
        mirrored = self.embeddings_mirrored
        if mirrored is not None and (not isinstance(mirrored, np.ndarray) or mirrored.shape != emb.shape
                                     or mirrored.dtype != np.float32):
            got = getattr(mirrored, "dtype", type(mirrored).__name__)
            raise ValidationError(f"FrameFeatures.embeddings_mirrored: expected float32 of shape {emb.shape}, "
                                  f"got {got} of shape {np.shape(mirrored)}")
        names = ["crop_boxes_px", "crop_angles_rad", "embeddings"]
        if mirrored is not None:
            names.append("embeddings_mirrored")
        for name in names:
            arr = np.array(getattr(self, name), copy=True)
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)

    @property
    def n_crops(self) -> int:
        return len(self.crop_boxes_px)

    @property
    def window_t_s(self) -> float:
        """The time a window's span is measured in: ``t_view_s`` where stamped, else the frame's."""
        return self.frame.t_mono_s if self.t_view_s is None else self.t_view_s

    @property
    def view_key(self) -> int:
        """Which view the frame shows: the seq of the view's first frame (its own when new)."""
        return self.frame.seq if self.view_seq is None else self.view_seq


@dataclass(frozen=True, eq=False)
class SunEstimate:
    """The sun direction estimated from one window of frames.

    ``sun_enu`` is a unit vector in the world frame of the window's heading reference (true north,
    or the start heading when ``heading_ref`` is relative). ``t_mono_s``/``seq``/``heading_rad``
    are those of the newest frame in the window. ``spread_rad`` is the RMS angle of the per-token
    world vectors around the estimate: small when the tokens agree. ``heading_epoch`` is the
    window's :attr:`Attitude.epoch`: which zero a relative heading counts from (0 otherwise).
    """

    t_mono_s: float
    seq: int
    sun_enu: np.ndarray
    heading_rad: float
    heading_ref: HeadingRef
    spread_rad: float
    n_frames: int
    n_tokens: int
    aggregator: str
    utc_ns: int | None = None
    truth_enu: np.ndarray | None = None
    token_enu: np.ndarray | None = field(default=None, repr=False)
    heading_epoch: int = 0

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_mono_s", _finite("t_mono_s", self.t_mono_s))
        # Checked here, not only in Frame: an estimate also comes from a log's estimate channel or
        # a library caller, and the encoders format seq and utc_ns as integers of fixed width.
        object.__setattr__(self, "seq", _seq("SunEstimate.seq", self.seq))
        if self.utc_ns is not None:
            object.__setattr__(self, "utc_ns", _utc_ns("SunEstimate.utc_ns", self.utc_ns))
        object.__setattr__(self, "sun_enu", _vector3("SunEstimate.sun_enu", self.sun_enu, unit=True))
        object.__setattr__(self, "heading_rad", float(wrap_2pi(_finite("heading_rad", self.heading_rad))))
        object.__setattr__(self, "heading_ref", HeadingRef(self.heading_ref))
        epoch = self.heading_epoch
        if isinstance(epoch, bool) or not isinstance(epoch, int | np.integer) or epoch < 0:
            raise ValidationError(f"SunEstimate.heading_epoch: expected an integer >= 0, got {epoch!r}")
        if epoch and self.heading_ref is not HeadingRef.RELATIVE:
            raise ValidationError(f"SunEstimate.heading_epoch: {epoch} with a {self.heading_ref.value} heading, "
                                  "whose zero never changes: expected 0")
        object.__setattr__(self, "heading_epoch", int(epoch))
        spread = _finite("spread_rad", self.spread_rad)
        if not 0.0 <= spread <= math.pi:
            raise ValidationError(f"SunEstimate.spread_rad: expected within [0, pi] rad, got {spread}")
        for name in ("n_frames", "n_tokens"):
            object.__setattr__(self, name, _seq(f"SunEstimate.{name}", getattr(self, name)))
        if self.n_frames < 1 or self.n_tokens < 1:
            raise ValidationError(
                "SunEstimate: expected at least one frame and token, "
                f"got {self.n_frames} frames, {self.n_tokens} tokens"
            )
        if self.truth_enu is not None:
            object.__setattr__(self, "truth_enu", _vector3("SunEstimate.truth_enu", self.truth_enu, unit=True))
        if self.token_enu is not None:
            tok = np.array(self.token_enu, dtype=np.float64)
            if tok.shape != (self.n_tokens, 3):
                raise ValidationError(f"SunEstimate.token_enu: expected shape ({self.n_tokens}, 3), got {tok.shape}")
            tok.setflags(write=False)
            object.__setattr__(self, "token_enu", tok)

    @property
    def azimuth_rad(self) -> float:
        return float(az_el_from_enu(self.sun_enu)[0])

    @property
    def elevation_rad(self) -> float:
        return float(az_el_from_enu(self.sun_enu)[1])

    @property
    def relative_bearing_rad(self) -> float:
        """Sun azimuth relative to the newest frame's heading, in [-pi, pi): positive to the right."""
        return float(wrap_pi(self.azimuth_rad - self.heading_rad))

    @property
    def error_rad(self) -> float | None:
        if self.truth_enu is None:
            return None
        return float(angle_between(self.sun_enu, self.truth_enu))

    def to_json_dict(self) -> dict:
        """The JSONL view: degrees, plain lists, ``truth_enu``/``error_deg`` only when known,
        ``heading_epoch`` only for a relative heading."""
        out = {
            "t": self.t_mono_s,
            "seq": self.seq,
            "sun_enu": [round(float(x), 7) for x in self.sun_enu],
            "azimuth_deg": wrapped_deg(self.azimuth_rad),
            "elevation_deg": math.degrees(self.elevation_rad),
            "heading_deg": wrapped_deg(self.heading_rad),
            "heading_ref": self.heading_ref.value,
            "relative_bearing_deg": wrapped_deg(self.relative_bearing_rad, -180.0),
            "spread_deg": math.degrees(self.spread_rad),
            "n_frames": self.n_frames,
            "n_tokens": self.n_tokens,
            "aggregator": self.aggregator,
        }
        if self.heading_ref is HeadingRef.RELATIVE:
            out["heading_epoch"] = self.heading_epoch
        if self.utc_ns is not None:
            out["utc"] = utc_iso(self.utc_ns)
        error_rad = self.error_rad  # None exactly when truth_enu is
        if self.truth_enu is not None and error_rad is not None:
            out["truth_enu"] = [round(float(x), 7) for x in self.truth_enu]
            out["error_deg"] = math.degrees(error_rad)
        return out


def utc_iso(utc_ns: int) -> str:
    """ISO 8601 UTC with microseconds and a Z, e.g. ``2011-09-26T13:02:25.964389Z``."""
    dt = datetime.fromtimestamp(utc_ns // 1_000_000_000, tz=UTC).replace(microsecond=(utc_ns % 1_000_000_000) // 1000)
    return dt.strftime("%Y-%m-%dT%H:%M:%S.%fZ")
