"""The native log: sunrig recordings as MCAP, the container of rosbag2 and Foxglove.

``docs/log-format.md`` is the specification; this module is its only writer and reader.

Shape: pure encoders/decoders (values <-> message bytes) and a pure :class:`_FrameAssembler`
(message stream -> Frames) inside a thin I/O shell (:class:`LogWriter`, :class:`NativeLogSource`).

Two choices carry the robustness:

- The writer cuts chunks itself, only between frames, flushes each finished chunk to the OS and
  repeats the camera calibration at the start of every chunk. A process killed mid-write
  therefore leaves whole frames in whole chunks, and any chunk decodes without the ones before it
  (apart from the schema and channel records, which MCAP stores once, in the first chunk).
- The reader streams records front to back and never seeks, so a file without its summary and
  footer (the usual state of a killed recording) replays up to its last complete chunk. A chunk
  that fails its CRC or does not decompress is skipped and counted; a damaged record header, after
  which nothing can be framed, ends the replay like a truncation. Each record is parsed from its
  own bytes, so a damaged field inside one cannot read past it (:func:`_framed_records`).
"""

from __future__ import annotations

import dataclasses
import errno
import io
import json
import logging
import math
import os
import stat
import struct
import sys
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import IO, Any, cast

import cv2
import numpy as np
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from google.protobuf.message import DecodeError
from google.protobuf.timestamp_pb2 import Timestamp
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile, McapError, RecordLengthLimitExceeded
from mcap.opcode import Opcode
from mcap.reader import SeekingReader
from mcap.records import Channel, Chunk, DataEnd, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import StreamReader, breakup_chunk, read_magic
from mcap.writer import LIBRARY_IDENTIFIER as MCAP_LIBRARY
from mcap.writer import CompressionType
from mcap.writer import Writer as McapWriter
from mcap_protobuf.schema import build_file_descriptor_set

from rig.errors import EmptyLogError, LogError, ValidationError
from rig.files import sync_to_disk
from rig.solar import UTC_NS_MAX
from rig.types import Attitude, Frame, GnssFix, HeadingRef, Intrinsics, SunEstimate, utc_iso

try:  # mcap depends on zstandard; kept optional here only so the error tuple can name it
    from zstandard import ZstdError as _ZstdError
except ImportError:  # pragma: no cover - depends on the environment
    _ZstdError = McapError  # type: ignore[misc,assignment]

logger = logging.getLogger(__name__)

FORMAT_VERSION = "1"
PROFILE = "sunrig"
METADATA_NAME = "sunrig"
MCAP_MAGIC = b"\x89MCAP0\r\n"

TOPIC_IMAGE = "/camera/image"
TOPIC_CALIBRATION = "/camera/calibration"
TOPIC_HEADING = "/heading"
TOPIC_GNSS = "/gnss/fix"
TOPIC_UTC = "/time/utc"
TOPIC_SUN_TRUTH = "/sun/truth"
TOPIC_ESTIMATE = "/sun/estimate"

CAMERA_FRAME_ID = "camera"
GNSS_FRAME_ID = "gnss"
DEFAULT_CHUNK_SIZE = 1 << 20  # ~10-20 JPEG frames of 640x480: at most about a second lost on a kill
_MAX_SEQ = 1 << 32  # MCAP's message sequence is a uint32
_MESSAGE_OVERHEAD = 31  # opcode, length, channel id, sequence, two times: bytes per message record
_MAX_WARNINGS = 5  # per replay; the rest are only counted, so a damaged log cannot flood the log

_COMPRESSION = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}

# What a damaged or cut-off byte stream makes mcap, struct, zstandard and lz4 raise. lz4.frame
# reports bad input as RuntimeError, so it is here, caught only around decoding calls.
_DECODE_ERRORS: tuple[type[BaseException], ...] = (
    McapError,
    ValueError,  # includes CRC mismatches and bad UTF-8
    struct.error,
    EOFError,
    _ZstdError,
    RuntimeError,
    # A length field damaged into a huge number: the reader's slice or allocation of it fails
    # before any CRC could.
    OverflowError,
    MemoryError,
)
# What reading a log's summary can raise: a damaged summary section also fails its lookups. (A
# named tuple, not a starred one in the except: mypy does not accept a starred except tuple.)
_SUMMARY_ERRORS: tuple[type[BaseException], ...] = (*_DECODE_ERRORS, OSError, KeyError, IndexError)
# What a damaged message payload makes the decoders below raise.
_MESSAGE_ERRORS = (DecodeError, ValueError, KeyError, TypeError, IndexError, cv2.error)


def _sunrig_version() -> str:
    try:
        return version("sunrig")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "0+unknown"


# ---------------------------------------------------------------------------------------------
# Schemas


def _json_schema(title: str, description: str, properties: dict, required: list[str]) -> bytes:
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        "title": title,
        "description": description,
        "type": "object",
        "properties": properties,
        "required": required,
    }
    return json.dumps(schema, indent=1).encode()


_SEQ = {"type": "integer", "minimum": 0, "description": "Frame.seq of the frame it belongs to"}
_VEC3 = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}

_ATTITUDE_SCHEMA = _json_schema(
    "sunrig.Attitude",
    "Camera heading (yaw) clockwise from the reference's north, and pitch/roll where known.",
    {
        "heading_deg": {"type": "number", "description": "clockwise from north, [0, 360)"},
        "reference": {"type": "string", "enum": [r.value for r in HeadingRef]},
        "pitch_deg": {"type": ["number", "null"], "description": "null when unknown"},
        "roll_deg": {"type": ["number", "null"], "description": "null when unknown"},
        "epoch": {"type": "integer", "minimum": 0,
                  "description": "which zero a relative heading counts from; absent in older logs (0)"},
        "seq": _SEQ,
    },
    ["heading_deg", "reference", "pitch_deg", "roll_deg", "seq"],
)
_UTC_SCHEMA = _json_schema(
    "sunrig.UtcTime",
    "UTC time of the frame's mid-exposure; utc.sec/utc.nsec are exact, utc_iso is for humans.",
    {
        "utc": {
            "type": "object",
            "properties": {
                "sec": {"type": "integer", "description": "seconds since the Unix epoch"},
                "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
            },
            "required": ["sec", "nsec"],
        },
        "utc_iso": {"type": "string", "description": "ISO 8601, microseconds, Z"},
        "seq": _SEQ,
    },
    ["utc", "seq"],
)
_SUN_TRUTH_SCHEMA = _json_schema(
    "sunrig.SunTruth",
    "Ground-truth sun direction: unit vector in East-North-Up, azimuth clockwise from north.",
    {
        "sun_enu": _VEC3,
        "azimuth_deg": {"type": "number"},
        "elevation_deg": {"type": "number"},
        "seq": _SEQ,
    },
    ["sun_enu", "seq"],
)
_ESTIMATE_SCHEMA = _json_schema(
    "sunrig.SunEstimate",
    "One sun estimate, as SunEstimate.to_json_dict() plus utc_ns and token_enu when known.",
    {
        "t": {"type": "number", "description": "monotonic time (s) of the newest frame"},
        "seq": _SEQ,
        "sun_enu": _VEC3,
        "azimuth_deg": {"type": "number"},
        "elevation_deg": {"type": "number"},
        "heading_deg": {"type": "number"},
        "heading_ref": {"type": "string", "enum": [r.value for r in HeadingRef]},
        "heading_epoch": {"type": "integer", "minimum": 0,
                          "description": "which zero a relative heading counts from; absent otherwise"},
        "relative_bearing_deg": {"type": "number"},
        "spread_deg": {"type": "number"},
        "n_frames": {"type": "integer"},
        "n_tokens": {"type": "integer"},
        "aggregator": {"type": "string"},
        "utc": {"type": "string"},
        "utc_ns": {"type": "integer", "description": "exact UTC ns since the epoch"},
        "truth_enu": _VEC3,
        "error_deg": {"type": "number"},
        "token_enu": {"type": "array", "items": _VEC3},
    },
    [
        "t",
        "seq",
        "sun_enu",
        "heading_deg",
        "heading_ref",
        "spread_deg",
        "n_frames",
        "n_tokens",
        "aggregator",
    ],
)


@dataclass(frozen=True)
class _ChannelSpec:
    schema_name: str
    schema_encoding: str  # "protobuf" | "jsonschema"
    message_encoding: str  # "protobuf" | "json"
    schema_data: Any  # protobuf message class or JSON Schema bytes

    def schema_bytes(self) -> bytes:
        if self.schema_encoding == "protobuf":
            return build_file_descriptor_set(self.schema_data).SerializeToString()
        return self.schema_data


def _proto(cls: Any) -> _ChannelSpec:
    return _ChannelSpec(cls.DESCRIPTOR.full_name, "protobuf", "protobuf", cls)


def _jsonspec(data: bytes) -> _ChannelSpec:
    return _ChannelSpec(json.loads(data)["title"], "jsonschema", "json", data)


# The channels of a frame's messages, in the order a frame writes them (the image last).
_FRAME_TOPICS = (TOPIC_CALIBRATION, TOPIC_HEADING, TOPIC_GNSS, TOPIC_UTC, TOPIC_SUN_TRUTH, TOPIC_IMAGE)

CHANNELS: dict[str, _ChannelSpec] = {
    TOPIC_IMAGE: _proto(CompressedImage),
    TOPIC_CALIBRATION: _proto(CameraCalibration),
    TOPIC_HEADING: _jsonspec(_ATTITUDE_SCHEMA),
    TOPIC_GNSS: _proto(LocationFix),
    TOPIC_UTC: _jsonspec(_UTC_SCHEMA),
    TOPIC_SUN_TRUTH: _jsonspec(_SUN_TRUTH_SCHEMA),
    TOPIC_ESTIMATE: _jsonspec(_ESTIMATE_SCHEMA),
}


# ---------------------------------------------------------------------------------------------
# Pure encoders and decoders: values <-> message bytes


def ns_from_s(t_s: float) -> int:
    """Monotonic seconds to MCAP's unsigned integer nanoseconds."""
    ns = round(t_s * 1e9)
    if ns < 0:
        raise ValidationError(f"time: expected >= 0 s for an MCAP log time, got {t_s} s")
    return ns


def _timestamp(ns: int) -> Timestamp:
    sec, nsec = divmod(int(ns), 1_000_000_000)
    return Timestamp(seconds=sec, nanos=nsec)


def _ns_from_timestamp(ts: Timestamp) -> int:
    return int(ts.seconds) * 1_000_000_000 + int(ts.nanos)


def _dumps(obj: dict) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def _loads(data: bytes) -> dict:
    try:
        obj = json.loads(data)
    except RecursionError:  # a payload nested thousands deep ([[[[...]]]]): damaged or crafted
        raise ValueError("JSON nested too deep to decode") from None
    if not isinstance(obj, dict):
        raise ValueError(f"expected a JSON object, got {type(obj).__name__}")
    return obj


def _deg(rad: float | None) -> float | None:
    return None if rad is None else math.degrees(rad)


def _rad(deg: float | None) -> float | None:
    return None if deg is None else math.radians(float(deg))


def encode_image(image_bgr: np.ndarray, t_ns: int, jpeg_quality: int) -> bytes:
    ok, jpeg = cv2.imencode(".jpg", image_bgr, [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)])
    if not ok:  # cannot happen for a validated Frame image; kept so a failure is not silent
        raise LogError(f"OpenCV could not JPEG-encode an image of shape {image_bgr.shape}")
    msg = CompressedImage(
        timestamp=_timestamp(t_ns), frame_id=CAMERA_FRAME_ID, data=jpeg.tobytes(), format="jpeg"
    )
    return msg.SerializeToString()


def decode_image(data: bytes) -> np.ndarray:
    msg = CompressedImage.FromString(data)
    buf = np.frombuffer(msg.data, dtype=np.uint8)
    image = cv2.imdecode(buf, cv2.IMREAD_COLOR) if buf.size else None
    if image is None:
        raise ValueError(f"image ({msg.format or 'no format'}, {buf.size} bytes) does not decode")
    return image


def encode_calibration(intr: Intrinsics, t_ns: int) -> bytes:
    fx, fy, cx, cy = intr.fx, intr.fy, intr.cx, intr.cy
    msg = CameraCalibration(
        timestamp=_timestamp(t_ns),
        frame_id=CAMERA_FRAME_ID,
        width=intr.width,
        height=intr.height,
        # Frames are rectified pinhole images: zero distortion, R = I, P = [K | 0].
        distortion_model="plumb_bob",
        D=[0.0] * 5,
        K=[fx, 0.0, cx, 0.0, fy, cy, 0.0, 0.0, 1.0],
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=[fx, 0.0, cx, 0.0, 0.0, fy, cy, 0.0, 0.0, 0.0, 1.0, 0.0],
    )
    return msg.SerializeToString()


def decode_calibration(data: bytes) -> Intrinsics:
    msg = CameraCalibration.FromString(data)
    if len(msg.K) != 9:
        raise ValueError(f"calibration K: expected 9 values, got {len(msg.K)}")
    if any(d != 0.0 for d in msg.D):
        # sunrig frames are rectified; a distorted calibration would need undistorting first.
        raise ValueError(f"calibration D: expected zero distortion, got {list(msg.D)}")
    k = msg.K
    return Intrinsics(fx=k[0], fy=k[4], cx=k[2], cy=k[5], width=msg.width, height=msg.height)


def encode_attitude(att: Attitude, seq: int) -> bytes:
    return _dumps(
        {
            "heading_deg": math.degrees(att.heading_rad),
            "reference": att.reference.value,
            "pitch_deg": _deg(att.pitch_rad),
            "roll_deg": _deg(att.roll_rad),
            "epoch": att.epoch,
            "seq": seq,
        }
    )


def decode_attitude(data: bytes) -> Attitude:
    d = _loads(data)
    heading = d["heading_deg"]
    # The writer gives [0, 360); a heading beyond a turn either way is a damaged number (1e308 wrapped
    # to some angle and was graded as one), so the message is skipped as corrupt.
    if isinstance(heading, int | float) and not isinstance(heading, bool) and not -360.0 <= heading <= 360.0:
        raise ValueError(f"heading_deg: expected an angle within [-360, 360], got {heading}")
    return Attitude(
        # A null heading_deg (a damaged payload) reaches Attitude's own check, a ValidationError.
        heading_rad=_rad(d["heading_deg"]),  # type: ignore[arg-type]
        reference=d["reference"],
        pitch_rad=_rad(d.get("pitch_deg")),
        roll_rad=_rad(d.get("roll_deg")),
        epoch=d.get("epoch", 0),
    )


def encode_gnss(fix: GnssFix) -> bytes:
    msg = LocationFix(
        timestamp=_timestamp(fix.utc_ns),
        frame_id=GNSS_FRAME_ID,
        latitude=fix.lat_deg,
        longitude=fix.lon_deg,
        # NaN for an unknown altitude, as ROS NavSatFix does; Foxglove's map ignores altitude.
        altitude=math.nan if fix.alt_m is None else fix.alt_m,
        position_covariance_type=LocationFix.PositionCovarianceType.UNKNOWN,
    )
    return msg.SerializeToString()


def decode_gnss(data: bytes) -> GnssFix:
    msg = LocationFix.FromString(data)
    if not msg.HasField("timestamp"):
        raise ValueError("location fix without its UTC timestamp")
    alt = None if math.isnan(msg.altitude) else msg.altitude
    return GnssFix(
        utc_ns=_utc_ns_held("location fix", msg.timestamp.seconds, _ns_from_timestamp(msg.timestamp)),
        lat_deg=msg.latitude,
        lon_deg=msg.longitude,
        alt_m=alt,
    )


def encode_utc(utc_ns: int, seq: int) -> bytes:
    sec, nsec = divmod(int(utc_ns), 1_000_000_000)
    # sec/nsec rather than one ns integer: exact in JavaScript (Foxglove) too, where a 64-bit
    # integer loses its last digits; Foxglove also shows a {sec, nsec} object as a time.
    return _dumps({"utc": {"sec": sec, "nsec": nsec}, "utc_iso": utc_iso(int(utc_ns)), "seq": seq})


def decode_utc(data: bytes) -> int:
    utc = _loads(data)["utc"]
    sec, nsec = utc["sec"], utc["nsec"]
    if not (isinstance(sec, int) and isinstance(nsec, int) and 0 <= nsec < 1_000_000_000):
        raise ValueError(f"utc: expected integer sec and nsec in [0, 1e9), got {utc!r}")
    return _utc_ns_held("utc", sec, sec * 1_000_000_000 + nsec)


def _utc_ns_held(what: str, sec: int, utc_ns: int) -> int:
    """``utc_ns`` if it is a time from 1970 to 2262, else a ValueError (the message is then
    skipped as corrupt): a date no clock meant, which past int64 ns (2262) the ephemeris cannot
    take and numpy wraps round to another date."""
    if not 0 <= utc_ns <= UTC_NS_MAX:
        raise ValueError(f"{what}: expected a time from 1970 to 2262 (what ns since 1970 hold), got sec {sec}")
    return utc_ns


def encode_sun_truth(sun_enu: np.ndarray, seq: int) -> bytes:
    x, y, z = (float(v) for v in sun_enu)
    return _dumps(
        {
            "sun_enu": [x, y, z],
            "azimuth_deg": math.degrees(math.atan2(x, y)) % 360.0,
            "elevation_deg": math.degrees(math.atan2(z, math.hypot(x, y))),
            "seq": seq,
        }
    )


def decode_sun_truth(data: bytes) -> np.ndarray:
    vec = np.asarray(_loads(data)["sun_enu"], dtype=np.float64)
    if vec.shape != (3,):
        raise ValueError(f"sun_enu: expected 3 numbers, got shape {vec.shape}")
    return vec


def encode_estimate(est: SunEstimate) -> bytes:
    d = est.to_json_dict()
    # to_json_dict keeps only microseconds of UTC and drops the per-token vectors; add them so
    # estimate_from_dict rebuilds the estimate.
    if est.utc_ns is not None:
        d["utc_ns"] = est.utc_ns
    if est.token_enu is not None:
        d["token_enu"] = est.token_enu.tolist()
    return _dumps(d)


def estimate_from_dict(d: dict) -> SunEstimate:
    """Rebuild a :class:`SunEstimate` from a ``/sun/estimate`` message (``sun_enu`` to 1e-7)."""
    try:
        return SunEstimate(
            t_mono_s=d["t"],
            seq=int(d["seq"]),
            sun_enu=d["sun_enu"],
            heading_rad=math.radians(d["heading_deg"]),
            heading_ref=HeadingRef(d["heading_ref"]),
            # degrees and back can land one ulp past pi
            spread_rad=min(math.radians(d["spread_deg"]), math.pi),
            n_frames=int(d["n_frames"]),
            n_tokens=int(d["n_tokens"]),
            aggregator=str(d["aggregator"]),
            utc_ns=d.get("utc_ns"),
            truth_enu=d.get("truth_enu"),
            token_enu=d.get("token_enu"),
            heading_epoch=d.get("heading_epoch", 0),  # absent: an absolute heading, or an older log
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise ValidationError(
            f"/sun/estimate message: cannot rebuild a SunEstimate: {exc}"
        ) from exc


# ---------------------------------------------------------------------------------------------
# Writer


@dataclass(frozen=True)
class LogOnDisk:
    """How much of a log is on the disk: its first ``size_bytes`` bytes, which end with its last
    finished chunk (or, once closed, its footer) and replay as ``frames`` frames and ``estimates``
    estimates. ``size_bytes`` 0: no chunk has been finished yet, the log holds nothing.

    "On the disk" is synced (``fsync``) in a file the writer opened; handed to the OS in one that
    cannot sync (a device); flushed to the stream for a stream handed in, which its owner syncs.
    """

    size_bytes: int
    frames: int
    estimates: int


class LogWriter:
    """Writes Frames and SunEstimates to a native (MCAP) log. A context manager; ``close()`` is
    idempotent and writes the summary that makes the file indexed. A writer never closed (a killed
    process) still leaves a log that replays up to its last finished chunk; so does a power cut,
    as each finished chunk of a file it opened is synced to the disk. :attr:`on_disk` says how far
    that is; after a write that raised (a full disk), :meth:`abandon` closes the log at that point
    instead of ``close()``.

    ``target`` is a path or a binary stream with ``write``/``tell``/``flush`` (left open on close).
    ``chunk_size`` is the uncompressed bytes per chunk: the most a kill can lose. ``exclusive``:
    a path that exists raises ``FileExistsError`` instead of being replaced. ``metadata``: more
    entries for the ``sunrig`` metadata record, facts about how the log was made (a synthetic
    drive's ``render_scale``); the format's own keys cannot be replaced.
    """

    def __init__(
        self,
        target: str | os.PathLike[str] | IO[bytes],
        *,
        chunk_size: int = DEFAULT_CHUNK_SIZE,
        compression: str = "zstd",
        exclusive: bool = False,
        metadata: Mapping[str, str] | None = None,
    ) -> None:
        own = {
            "format_version": FORMAT_VERSION,
            "sunrig_version": _sunrig_version(),
            "log_time": "monotonic clock (time.monotonic) in ns at mid-exposure",
            "image_encoding": "jpeg",
        }
        extra = dict(metadata or {})
        if not all(isinstance(k, str) and isinstance(v, str) for k, v in extra.items()):
            raise ValidationError(f"LogWriter.metadata: expected str keys and values, got {extra!r}")
        if clash := sorted(own.keys() & extra.keys()):
            raise ValidationError(
                f"LogWriter.metadata: {', '.join(clash)} belong to the log format and cannot be replaced; "
                "name the entry otherwise"
            )
        if not isinstance(chunk_size, int) or chunk_size <= 0:
            raise ValidationError(
                f"LogWriter.chunk_size: expected a positive integer, got {chunk_size!r}"
            )
        if compression not in _COMPRESSION:
            raise ValidationError(
                f"LogWriter.compression: expected one of {sorted(_COMPRESSION)}, "
                f"got {compression!r}"
            )
        self._owns_file = isinstance(target, str | os.PathLike)
        self._sync_file = self._owns_file
        self._folder_synced = False  # the folder's entry for a file this writer made
        self._detach = False
        if isinstance(target, str | os.PathLike):  # (_owns_file, spelled out so mypy narrows target)
            try:
                # "xb": a file that exists raises FileExistsError, for the caller to decide.
                self._file: IO[bytes] = open(target, "xb" if exclusive else "wb")  # noqa: SIM115 - closed in close()
            except FileExistsError:
                raise
            except OSError as exc:
                raise LogError(
                    f"cannot create log {_show(target)}: {exc.strerror}; "
                    "check the folder exists and is writable"
                ) from exc
            self.path: Path | None = Path(target)
        else:
            if not hasattr(target, "write") or not hasattr(target, "tell"):
                raise ValidationError(
                    "LogWriter.target: expected a path or a binary stream, "
                    f"got {type(target).__name__}"
                )
            # mcap would buffer a raw stream in a writer of its own that close() cannot flush.
            if isinstance(target, io.RawIOBase):
                self._file, self._detach = io.BufferedWriter(target), True
            else:
                self._file = target
            self.path = None
        # The mcap writer never cuts a chunk itself (chunk_size = max): we cut between frames.
        self._mcap = McapWriter(
            self._file, chunk_size=sys.maxsize, compression=_COMPRESSION[compression]
        )
        self._mcap.start(profile=PROFILE, library=f"sunrig/{_sunrig_version()} {MCAP_LIBRARY}")
        # Metadata sits before the first chunk, so even a truncated log says what wrote it.
        self._mcap.add_metadata(METADATA_NAME, {**own, **extra})
        self._chunk_size = chunk_size
        self._chunk_bytes = 0
        self._channel_ids: dict[str, int] = {}
        self._last_intrinsics: Intrinsics | None = None
        self._calibration_in_chunk = False
        self._closed = False
        self.frames_written = 0  # handed to the writer, those in the chunk in progress too
        self.estimates_written = 0
        self._on_disk = LogOnDisk(0, 0, 0)

    # -- public

    def write_frame(self, frame: Frame, *, jpeg_quality: int = 90) -> None:
        """Write one frame: its calibration (when new or first in a chunk), heading, GNSS, UTC and
        truth messages, then the image; all at ``log_time = frame.t_mono_s``, sequence ``seq``.
        """
        self._check_open()
        if not isinstance(frame, Frame):
            raise ValidationError(f"write_frame: expected a Frame, got {type(frame).__name__}")
        if not isinstance(jpeg_quality, int) or not 1 <= jpeg_quality <= 100:
            raise ValidationError(
                f"write_frame.jpeg_quality: expected an integer in [1, 100], got {jpeg_quality!r}"
            )
        seq = self._check_seq(frame.seq)
        t_ns = ns_from_s(frame.t_mono_s)
        # Encode the image first: if that fails, no orphan per-frame messages are left behind.
        image = encode_image(frame.image_bgr, t_ns, jpeg_quality)
        if not self.frames_written:
            # Every per-frame channel is declared in the first frame's chunk, the image's last,
            # even those with no message yet. Declared where first used (a heading from frame 5
            # on, once a compass had its fix), a channel lost with a later damaged chunk took
            # every later message on it along, in a log cut off before its summary.
            for topic in _FRAME_TOPICS:
                self._channel(topic)
        if frame.intrinsics != self._last_intrinsics or not self._calibration_in_chunk:
            self._add(TOPIC_CALIBRATION, t_ns, seq, encode_calibration(frame.intrinsics, t_ns))
            self._last_intrinsics = frame.intrinsics
            self._calibration_in_chunk = True
        if frame.attitude is not None:
            self._add(TOPIC_HEADING, t_ns, seq, encode_attitude(frame.attitude, seq))
        if frame.gnss is not None:
            self._add(TOPIC_GNSS, t_ns, seq, encode_gnss(frame.gnss))
        if frame.utc_ns is not None:
            self._add(TOPIC_UTC, t_ns, seq, encode_utc(frame.utc_ns, seq))
        if frame.sun_enu_truth is not None:
            self._add(TOPIC_SUN_TRUTH, t_ns, seq, encode_sun_truth(frame.sun_enu_truth, seq))
        self._add(TOPIC_IMAGE, t_ns, seq, image)
        self.frames_written += 1
        self._maybe_end_chunk()

    def write_estimate(self, est: SunEstimate) -> None:
        """Write one estimate on ``/sun/estimate`` at ``log_time = est.t_mono_s``."""
        self._check_open()
        if not isinstance(est, SunEstimate):
            raise ValidationError(
                f"write_estimate: expected a SunEstimate, got {type(est).__name__}"
            )
        seq = self._check_seq(est.seq)
        t_ns = ns_from_s(est.t_mono_s)
        self._add(TOPIC_ESTIMATE, t_ns, seq, encode_estimate(est))
        self.estimates_written += 1
        self._maybe_end_chunk()

    def flush(self) -> None:
        """End the chunk in progress and hand it to the OS: what a crash can no longer lose."""
        self._check_open()
        self._end_chunk()

    def close(self) -> None:
        """Write the chunk in progress, the summary and the footer, and sync them. One the disk
        has no room for (or any write error) raises, and leaves the log as :meth:`abandon` does:
        cut back to its last synced chunk, not to the part of a record that fitted."""
        if self._closed:
            return
        try:
            self._mcap.finish()
            self._file.flush()
            self._sync()
        except OSError:
            self.abandon()
            raise
        except BaseException:
            self._closed = True
            self._release_file()
            raise
        self._closed = True
        self._on_disk = LogOnDisk(self._file.tell(), self.frames_written, self.estimates_written)
        self._release_file()

    def _release_file(self) -> None:
        if self._owns_file:
            self._file.close()
        elif self._detach:
            self._file.detach()  # type: ignore[attr-defined] # leave the caller's stream open

    def abandon(self) -> None:
        """Close the log without its summary and footer, keeping what :attr:`on_disk` counts and
        nothing after it: for after a write that raised (a full disk). That write left part of a
        chunk in the file, which a summary cannot index, and a summary written behind it once space
        was freed replays as a damaged record. A file the writer opened is cut back to
        ``on_disk.size_bytes`` and synced (to 0 bytes when no chunk was finished: removing it is the
        caller's choice); a stream handed in is left as it is, for its owner to cut back. The log
        then replays as one not closed. Idempotent; after :meth:`close`, nothing to do."""
        if self._closed:
            return
        self._closed = True
        if not self._owns_file:
            if self._detach:
                try:
                    self._file.detach()  # type: ignore[attr-defined] # leave the caller's stream open
                except OSError:
                    pass  # its buffer did not fit either: the stream has what it took
            return
        # A second descriptor, to cut the file back after closing the first: closing writes out
        # what its buffer still holds (or fails to, on a full disk), and that goes too.
        fd = os.dup(self._file.fileno())
        try:
            try:
                self._file.close()
            except OSError:
                pass  # the disk had no room for the buffer: it is cut off with the rest
            if stat.S_ISREG(os.fstat(fd).st_mode):  # a device (/dev/full) has nothing to cut
                os.ftruncate(fd, self._on_disk.size_bytes)
                if self._sync_file:
                    _fsync(fd)
        finally:
            os.close(fd)

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def on_disk(self) -> LogOnDisk:
        """What of the log is on the disk: where its last finished and synced chunk ends and the
        frames and estimates up to there. A write that raised (a full disk) leaves it as it was: a
        file cut back to ``on_disk.size_bytes`` replays what it counts."""
        return self._on_disk

    def __enter__(self) -> LogWriter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    # -- internals

    def _check_open(self) -> None:
        if self._closed:
            raise LogError(
                f"the log writer for {self.path or 'a stream'} is closed; open a new LogWriter"
            )

    @staticmethod
    def _check_seq(seq: int) -> int:
        if not 0 <= seq < _MAX_SEQ:
            raise ValidationError(
                f"seq: expected within [0, 2**32) for an MCAP sequence, got {seq}"
            )
        return int(seq)

    def _channel(self, topic: str) -> int:
        cid = self._channel_ids.get(topic)
        if cid is None:
            spec = CHANNELS[topic]
            sid = self._mcap.register_schema(
                spec.schema_name, spec.schema_encoding, spec.schema_bytes()
            )
            cid = self._mcap.register_channel(topic, spec.message_encoding, sid)
            self._channel_ids[topic] = cid
        return cid

    def _add(self, topic: str, t_ns: int, seq: int, data: bytes) -> None:
        self._mcap.add_message(
            self._channel(topic), log_time=t_ns, data=data, publish_time=t_ns, sequence=seq
        )
        self._chunk_bytes += len(data) + _MESSAGE_OVERHEAD

    def _maybe_end_chunk(self) -> None:
        if self._chunk_bytes >= self._chunk_size:
            self._end_chunk()

    def _end_chunk(self) -> None:
        chunk = self._chunk_bytes > 0  # mcap writes no chunk without messages
        self._mcap.flush()  # finishes the chunk, writes it and its index, flushes the stream
        self._sync()
        if chunk:
            # Chunks end only between items, so every item handed in so far is in one.
            self._on_disk = LogOnDisk(self._file.tell(), self.frames_written, self.estimates_written)
        self._chunk_bytes = 0
        self._calibration_in_chunk = False

    def _sync(self) -> None:
        """Have the OS write what it was handed to the disk. A power cut (a rig's ignition) loses
        what the OS had not written back, on Linux up to half a minute of chunks; synced, only the
        chunk in progress, as a killed process. Only a file this writer opened: a stream handed in
        may be a pipe or a buffer, which its owner syncs if it can."""
        if not self._sync_file:
            return
        if not _fsync(self._file.fileno()):
            self._sync_file = False
            return
        if not self._folder_synced and self.path is not None:
            # The file's name lives in its folder: until that is synced too, a power cut in the
            # first seconds of a recording can lose the file, its synced chunks with it. Once.
            self._folder_synced = True
            sync_to_disk(self.path.absolute().parent)


def _fsync(fd: int) -> bool:
    """Sync a file to the disk; False when it cannot be synced. A device or pipe (--out /dev/null)
    and some file systems cannot: nothing to keep there. A disk that failed to write (EIO) is
    raised as any write error."""
    try:
        os.fsync(fd)
    except OSError as exc:
        if exc.errno not in (errno.EINVAL, errno.EOPNOTSUPP, errno.ENOTSUP):
            raise
        return False
    return True


# ---------------------------------------------------------------------------------------------
# Reader: pure assembly


class _CorruptMessage(LogError):
    """One message could not be decoded; the replay skips it."""


@dataclass
class LogStats:
    """Counters of one pass over a log (reset when a new pass starts)."""

    frames_read: int = 0
    corrupt_skipped: int = 0  # messages and chunks that did not decode
    truncated: bool = False  # the log ended early: cut off mid-write, or unframeable after a point
    bytes_read: int = 0  # where the pass stopped
    bytes_total: int = 0
    zeros_from: int | None = None  # where the zeros it ended in begin (data never written: a power cut)


_AUX_DECODERS = {
    TOPIC_HEADING: decode_attitude,
    TOPIC_GNSS: decode_gnss,
    TOPIC_UTC: decode_utc,
    TOPIC_SUN_TRUTH: decode_sun_truth,
}


_AUX_FIELDS = {
    TOPIC_HEADING: "attitude",
    TOPIC_GNSS: "gnss",
    TOPIC_UTC: "utc_ns",
    TOPIC_SUN_TRUTH: "sun_enu_truth",
}


class _FrameAssembler:
    """Turns one log's messages, in file order, into Frames. Pure: no I/O, no clock.

    A per-frame message (the calibration too) belongs to the image with the same MCAP log time and
    sequence, whether it comes before the image (sunrig's writer) or after it (another writer's).
    The sequence alone cannot tell: a writer that leaves every sequence 0 made each heading written
    after its image the next image's. So a frame is held from its image until the next image (or a
    gap, or the end) for the messages that follow it; take :meth:`take` after each call. An image
    with no calibration yet waits the same way for one of its own. A message that matches no image
    belonged to a frame whose image was lost, or was stamped otherwise than its image, and is
    dropped and counted in :attr:`unmatched`. One repeating the log time and sequence of one
    before it on its channel is a duplicate, dropped and counted in :attr:`duplicates`. The
    calibration holds until the next.
    """

    def __init__(self) -> None:
        self.intrinsics: Intrinsics | None = None
        # topic -> ((sequence, log time), value) of the message waiting for its image
        self._pending: dict[str, tuple[tuple[int, int], Any]] = {}
        self._held: Frame | None = None  # the newest frame, open to messages written after its image
        self._held_key: tuple[int, int] | None = None
        # An image that came with no calibration before it: (key, image bytes, its per-frame values),
        # until the next message tells whether its calibration follows it.
        self._uncalibrated: tuple[tuple[int, int], bytes, dict[str, Any]] | None = None
        self._ready: list[Frame] = []
        self._skipped: list[tuple[int, str]] = []  # (sequence, why) of images found unusable late
        # Per-frame messages dropped for a sequence and log time no image had, by topic: empty for
        # a sunrig log that lost nothing; in another writer's, the sign of a layout sunrig cannot
        # pair (a heading stamped with a time of its own, or a sequence counted per channel).
        self.unmatched: dict[str, int] = {}
        # Messages dropped as copies of one before them on their channel, by topic (a writer that
        # wrote twice, or a log merged with itself): each frame replays once.
        self.duplicates: dict[str, int] = {}

    def take(self) -> list[Frame]:
        """The frames complete since the last call, in order."""
        ready, self._ready = self._ready, []
        return ready

    def take_skipped(self) -> list[tuple[int, str]]:
        """(sequence, why) of each image skipped since the last call for want of a calibration: one
        is known to have none only at the message after it, so it is not raised as it comes."""
        skipped, self._skipped = self._skipped, []
        return skipped

    def gap(self) -> None:
        """Messages were lost (a skipped chunk): forget state that may no longer be current."""
        self._release()
        self.intrinsics = None
        self._pending.clear()

    def end(self) -> None:
        """The log ended: the held frame is complete; messages still waiting had no image."""
        self._release()
        for topic in self._pending:
            self._count_unmatched(topic)
        self._pending = {}

    def _release(self) -> None:
        if self._held is not None:
            self._ready.append(self._held)
        self._held, self._held_key = None, None
        if self._uncalibrated is not None:  # its calibration did not follow it
            self._skipped.append((self._uncalibrated[0][0], "image without a valid calibration before it"))
            self._uncalibrated = None

    def _count_unmatched(self, topic: str) -> None:
        self.unmatched[topic] = self.unmatched.get(topic, 0) + 1

    def _count_duplicate(self, topic: str) -> None:
        self.duplicates[topic] = self.duplicates.get(topic, 0) + 1

    def _hold(self, key: tuple[int, int], data: bytes, aux: dict[str, Any], intrinsics: Intrinsics) -> None:
        try:
            image = decode_image(data)
            self._held = Frame(t_mono_s=key[1] / 1e9, seq=key[0], image_bgr=image, intrinsics=intrinsics, **aux)
        except _MESSAGE_ERRORS as exc:  # ValidationError is a ValueError
            raise _CorruptMessage(f"image: {exc}") from exc
        self._held_key = key

    def feed(self, topic: str, seq: int, log_time_ns: int, data: bytes) -> None:
        """One message; raises :class:`_CorruptMessage` for one that does not decode."""
        key = (seq, log_time_ns)
        if topic == TOPIC_CALIBRATION:
            try:
                self.intrinsics = decode_calibration(data)
            except _MESSAGE_ERRORS as exc:
                # Better no frames until the next calibration than frames with wrong intrinsics.
                self.intrinsics = None
                raise _CorruptMessage(f"calibration: {exc}") from exc
            if self._uncalibrated is not None and self._uncalibrated[0] == key:  # written after its image
                _, image, aux = self._uncalibrated
                self._uncalibrated = None
                self._hold(key, image, aux, self.intrinsics)
            elif self._held is not None and key == self._held_key and self._held.intrinsics != self.intrinsics:
                try:  # a change, written after its image: the held frame's too
                    self._held = dataclasses.replace(self._held, intrinsics=self.intrinsics)
                except _MESSAGE_ERRORS as exc:
                    raise _CorruptMessage(f"calibration: {exc}") from exc
            return
        decoder = _AUX_DECODERS.get(topic)
        if decoder is not None:
            try:
                value = decoder(data)
            except _MESSAGE_ERRORS as exc:
                raise _CorruptMessage(f"{topic}: {exc}") from exc
            name = _AUX_FIELDS[topic]
            if self._held is not None and key == self._held_key:  # written after its image: the held frame's
                if getattr(self._held, name) is not None:
                    self._count_duplicate(topic)
                    return
                try:
                    change: dict[str, Any] = {name: value}
                    self._held = dataclasses.replace(self._held, **change)
                except _MESSAGE_ERRORS as exc:
                    raise _CorruptMessage(f"{topic}: {exc}") from exc
                return
            if self._uncalibrated is not None and key == self._uncalibrated[0]:
                waiting = self._uncalibrated[2]
                if name in waiting:
                    self._count_duplicate(topic)
                else:
                    waiting[name] = value
                return
            if topic in self._pending:
                if self._pending[topic][0] == key:  # the same frame's again: keep the first
                    self._count_duplicate(topic)
                    return
                self._count_unmatched(topic)  # a second one before any image: the first matched none
            self._pending[topic] = (key, value)
            return
        if topic != TOPIC_IMAGE:
            return
        if key in (self._held_key, self._uncalibrated and self._uncalibrated[0]):  # the same image again
            self._count_duplicate(topic)
            return
        self._release()  # the next image: the frame before it is complete
        pending, self._pending = self._pending, {}
        for t, (k, _) in pending.items():
            if k != key:
                self._count_unmatched(t)
        aux = {_AUX_FIELDS[t]: v for t, (k, v) in pending.items() if k == key}
        if self.intrinsics is None:
            # Its calibration may follow it (another writer's layout): known at the next message.
            self._uncalibrated = (key, data, aux)
            return
        self._hold(key, data, aux, self.intrinsics)


# ---------------------------------------------------------------------------------------------
# Reader: I/O shell


def _show(path: str | os.PathLike[str]) -> str:
    """The path for a one-line message."""
    return str(path).replace("\n", "\\n").replace("\r", "\\r")


_HINT = "pass a file written by sunrig record/synth"
_SIGNATURES = (
    (b"\x89PNG\r\n\x1a\n", "a PNG signature"),
    (b"\xff\xd8\xff", "a JPEG signature"),
    (b"#ROSBAG", "a ROS 1 bag header; convert it with `mcap convert` first"),
    (
        b"SQLite format 3\x00",
        "an SQLite header, perhaps a rosbag2 .db3; convert it with `mcap convert` first",
    ),
    (b"\x1f\x8b", "a gzip signature; decompress it first"),
    (b"PK\x03\x04", "a ZIP signature; extract it first"),
    (b"(\xb5/\xfd", "a zstd signature; decompress it first"),
)


def _open_log_file(path: Path) -> tuple[IO[bytes], int]:
    """Open ``path`` and check the MCAP magic; one-line LogError for anything that is not a log."""
    name = _show(path)
    if not path.exists():
        raise LogError(f"{name} does not exist; check the path and {_HINT}")
    if path.is_dir():
        raise LogError(f"{name} is a directory, not an MCAP log; pass the .mcap file itself")
    if not path.is_file():
        # A pipe (<(cat log.mcap)), a FIFO or a device: a log is read by seeking to its summary,
        # which none of them can; a FIFO's open would also wait for a writer without a word.
        raise LogError(f"{name} is not a regular file (a pipe, FIFO or device), and a log is read by seeking; "
                       "save it to a file and pass that")
    try:
        f = open(path, "rb")  # noqa: SIM115 - returned to the caller, who closes it
    except OSError as exc:
        raise LogError(f"cannot read {name}: {exc.strerror}; check its permissions") from exc
    try:
        size = os.fstat(f.fileno()).st_size
        head = f.read(16)
        f.seek(0)
    except OSError as exc:
        f.close()
        raise LogError(f"cannot read {name}: {exc.strerror}; check the file and the disk") from exc
    if head[:8] != MCAP_MAGIC:
        zeros = _zeros_from(f, size) if size and not head.strip(b"\0") else None
        f.close()
        if size == 0:
            # The writer's first write to the file is its first chunk (the header waits for it).
            raise EmptyLogError(name, "it is empty, 0 bytes: a recording stopped, or its power cut, before its "
                                      "first chunk was written")
        if zeros == 0:
            raise EmptyLogError(name, f"it is {size} bytes of zeros: a recording whose file system had made room "
                                      "for its data but never wrote it, as at a power cut")
        if MCAP_MAGIC.startswith(head):
            raise EmptyLogError(name, f"it is cut off inside the MCAP magic, {size} bytes")
        what = next((desc for sig, desc in _SIGNATURES if head.startswith(sig)), None)
        if what is None:
            what = f"bytes {head[:8].hex(' ')} where the MCAP magic {MCAP_MAGIC.hex(' ')} belongs"
        raise LogError(f"{name} is not an MCAP log (it starts with {what}); {_HINT}")
    return f, size


@dataclass
class _LogInfo:
    profile: str = ""
    library: str = ""
    metadata: dict[str, str] = field(default_factory=dict)


class _BoundedReads:
    """A log file whose reads stop at its end. mcap reads a record's fields straight from the
    file, and a file object allocates the bytes it is asked for before it reads them: one damaged
    length field inside a record would ask for up to 2**64 bytes (a MemoryError, or on a small
    board the OOM killer) where the file has only megabytes left."""

    def __init__(self, f: IO[bytes], size: int) -> None:
        self._f, self._size = f, size

    def read(self, n: int | None = -1) -> bytes:
        left = max(self._size - self._f.tell(), 0)
        return self._f.read(left if n is None or n < 0 else min(n, left))

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        return self._f.seek(offset, whence)

    def tell(self) -> int:
        return self._f.tell()


def _summary(f: IO[bytes], size: int) -> Any:
    """A finished log's summary (with its channels), or None when it has none (truncated)."""
    try:
        summary = SeekingReader(cast(IO[bytes], _BoundedReads(f, size)), record_size_limit=size).get_summary()
    except _SUMMARY_ERRORS:
        return None
    finally:
        f.seek(0)
    return summary if summary is not None and summary.channels else None


@dataclass(frozen=True)
class _ChannelFacts:
    """What a log says of one of its channels: its schema's name ("" when schemaless) and the
    encoding of its messages."""

    schema: str
    encoding: str


def _summary_topics(summary: Any) -> dict[str, _ChannelFacts] | None:
    """Topic -> its channel's facts from a summary (None: no summary)."""
    if summary is None:
        return None
    return {
        c.topic: _ChannelFacts(
            summary.schemas[c.schema_id].name if c.schema_id in summary.schemas else "", c.message_encoding
        )
        for c in summary.channels.values()
    }


def _check_image_channel(name: str, topics: dict[str, _ChannelFacts]) -> None:
    spec = CHANNELS[TOPIC_IMAGE]
    expected = spec.schema_name
    if TOPIC_IMAGE not in topics:
        listed = ", ".join(sorted(topics)) or "none"
        if TOPIC_ESTIMATE in topics:  # sunrig's own: a `run --record` without --record-frames
            raise LogError(
                f"{name} holds estimates only (recorded without --record-frames), no frames to replay; "
                "read them with replay.native.read_estimates, or record with --record-frames"
            )
        raise LogError(
            f"{name} is an MCAP log but not a sunrig log: it has no {TOPIC_IMAGE} channel "
            f"(channels: {listed}); {_HINT}"
        )
    image = topics[TOPIC_IMAGE]
    if image.schema != expected:
        raise LogError(
            f"{name} has {TOPIC_IMAGE} as {image.schema or 'schemaless'}, "
            f"expected {expected}; {_HINT}"
        )
    if image.encoding != spec.message_encoding:
        # Foxglove's schemas also come in JSON and other encodings; the reader passes over a
        # channel in an encoding it cannot decode, so without this every image went unread.
        raise LogError(
            f"{name} has {TOPIC_IMAGE} as {expected} in {image.encoding or 'no'} encoding, and sunrig "
            f"reads it in {spec.message_encoding} encoding; write its images as {spec.message_encoding} "
            f"(Foxglove's protobuf schemas), or {_HINT}"
        )


def _check_calibration_channel(name: str, topics: dict[str, _ChannelFacts]) -> None:
    """Every image needs the intrinsics before it: without a calibration sunrig can decode, each
    would be skipped as corrupt, and a whole camera recording blamed on damage."""
    spec = CHANNELS[TOPIC_CALIBRATION]
    need = (f"sunrig needs the camera intrinsics for its images: write a {spec.schema_name} message "
            f"({spec.message_encoding}) on {TOPIC_CALIBRATION} before the first image "
            f"(docs/log-format.md), or {_HINT}")
    calibration = topics.get(TOPIC_CALIBRATION)
    if calibration is None:
        raise LogError(f"{name} has no {TOPIC_CALIBRATION} channel, and {need}")
    if (calibration.schema, calibration.encoding) != (spec.schema_name, spec.message_encoding):
        raise LogError(
            f"{name} has {TOPIC_CALIBRATION} as {calibration.schema or 'schemaless'} in "
            f"{calibration.encoding or 'no'} encoding, and {need}"
        )


def _check_channels(name: str, topics: dict[str, _ChannelFacts]) -> None:
    _check_image_channel(name, topics)
    _check_calibration_channel(name, topics)


def _inspect(path: Path) -> _LogInfo:
    """Eager checks, cheap on a sunrig log: magic, format version, the camera's channels and an
    image on them (in a sunrig log, all in its first chunk)."""
    name = _show(path)
    f, size = _open_log_file(path)
    info = _LogInfo()
    with f:
        # A finished log lists its channels at the end: reject a foreign MCAP without decoding
        # its data. A truncated one has no summary; the scan below then decides.
        summary = _summary(f, size)
        topics = _summary_topics(summary)
        if topics is not None:
            _check_channels(name, topics)
        checked = topics is not None
        # The channels images come on: a summary names them all, a data section as it goes.
        image_ids = {c.id for c in summary.channels.values() if c.topic == TOPIC_IMAGE} if summary else set()
        images = False
        schemas: dict[int, str] = {}
        seen: dict[str, _ChannelFacts] = {}
        stats = LogStats(bytes_total=size)
        for record in _records(f, stats, name, warn=False):
            if isinstance(record, Header):
                info.profile, info.library = record.profile, record.library
            elif isinstance(record, Metadata) and record.name == METADATA_NAME:
                info.metadata = dict(record.metadata)
                found = info.metadata.get("format_version")
                if found is None:
                    # The key itself damaged (one flipped bit, and the metadata has no CRC of its
                    # own): the data may be whole. Read it as this version; the channel checks
                    # below still refuse what is not a sunrig log.
                    logger.warning("%s: its sunrig metadata has no format_version (damaged?); read as version %s",
                                   name, FORMAT_VERSION)
                elif found != FORMAT_VERSION:
                    raise LogError(
                        f"{name} is in sunrig log format version {found}; this sunrig reads "
                        f"version {FORMAT_VERSION}: use the sunrig that wrote it or upgrade"
                    )
            elif isinstance(record, Schema):
                schemas[record.id] = record.name
            elif isinstance(record, Channel):
                seen[record.topic] = _ChannelFacts(schemas.get(record.schema_id, ""), record.message_encoding)
                if record.topic == TOPIC_IMAGE:
                    _check_image_channel(name, seen)
                    image_ids.add(record.id)
                if not checked and TOPIC_IMAGE in seen and TOPIC_CALIBRATION in seen:
                    # sunrig's writer declares the calibration before the image; another writer
                    # may declare it later.
                    _check_calibration_channel(name, seen)
                    checked = True
                    if images:
                        return info
            elif isinstance(record, Message) and record.channel_id in image_ids:
                images = True
                if checked:
                    # A sunrig log's first chunk declares its channels, then holds the first
                    # frame: no need to read further.
                    return info
        if stats.truncated and not seen:
            if stats.zeros_from is not None:
                raise EmptyLogError(name, f"an MCAP log that ends in {size - stats.zeros_from} bytes of zeros from "
                                          f"byte {stats.zeros_from}, before its first complete chunk: data its file "
                                          "system never wrote, as at a power cut")
            raise EmptyLogError(name, "an MCAP log cut off before its first complete chunk")
        if topics is None:  # no summary vouched for the channels: the data section must have
            if not seen and info.metadata:  # sunrig's own log, closed before its first frame came
                raise EmptyLogError(name, "a sunrig log whose recording stopped before the first frame came")
            _check_channels(name, seen)
        if not images and not stats.truncated and not stats.corrupt_skipped:
            # Read whole and undamaged: its replay would end with no frame and no warning to say
            # why (a recorder declared the camera's channels, and the camera sent nothing).
            raise EmptyLogError(name, f"an MCAP log with no message on its {TOPIC_IMAGE} channel")
    return info  # a damaged chunk: the summary named the channels, the later chunks replay


# The records sunrig reads from a data section; others (message indexes, attachments, ...) are
# framed and passed over.
_RECORD_TYPES: dict[int, Any] = {Opcode.HEADER: Header, Opcode.SCHEMA: Schema, Opcode.CHANNEL: Channel,
                                 Opcode.MESSAGE: Message, Opcode.METADATA: Metadata, Opcode.CHUNK: Chunk,
                                 Opcode.DATA_END: DataEnd, Opcode.FOOTER: Footer}


def _framed_records(f: IO[bytes], size: int) -> Iterator[Any]:
    """The records of an MCAP byte stream, each parsed from its own body's bytes.

    mcap's StreamReader parses a record's fields straight from the file, so a damaged length
    inside one (a chunk's data length, say) reads past the record, asks the file for up to 2**64
    bytes and loses the framing of every record after it. Here a record's outer length frames it:
    a field that overruns the body fails that record alone (a chunk then is skipped as corrupt),
    and the next record is found where its length says. The outer length itself cannot exceed the
    file (a damaged one ends the stream, as the module docstring says).
    """
    read_magic(ReadDataStream(f))
    while True:
        head = f.read(9)
        if not head:
            raise _EndAfterRecord()  # no DataEnd, and no part of a record: a log never closed
        if len(head) < 9:
            raise EndOfFile()  # no DataEnd: the log was cut off
        opcode, length = struct.unpack("<BQ", head)
        if opcode == 0:  # reserved by MCAP: no record has it (zeros, most likely)
            raise McapError(f"opcode 0x00, which no MCAP record has, at byte {f.tell() - 9}")
        if length > max(size, 1):
            raise RecordLengthLimitExceeded(opcode, length, size)
        body = f.read(length)
        if len(body) < length:
            raise EndOfFile()
        kind = _RECORD_TYPES.get(opcode)
        if kind is Message:
            yield Message.read(ReadDataStream(io.BytesIO(body)), length)
        elif kind is Chunk:
            yield _ChunkBody(body)  # parsed by _records, where a bad one is skipped
        elif kind is not None:
            yield kind.read(ReadDataStream(io.BytesIO(body)))


class _EndAfterRecord(EndOfFile):
    """The bytes end where a record ends, before the data section's end: a log not closed."""


@dataclass(frozen=True)
class _ChunkBody:
    body: bytes

    def chunk(self) -> Chunk:
        return Chunk.read(ReadDataStream(io.BytesIO(self.body)))


# The shortest run of zeros at a log's end taken for data a file system never wrote. Longer than any
# run in sunrig's own records (a calibration's five zero distortion doubles, 40 bytes, in a chunk
# stored uncompressed), so a log merely cut off where its bytes happen to be zeros is not called so.
_MIN_ZERO_TAIL = 64


def _zeros_from(f: IO[bytes], size: int) -> int | None:
    """Where the run of zero bytes that ends the first ``size`` bytes begins, when it is at least
    :data:`_MIN_ZERO_TAIL` long, else None. A power cut leaves such a run where a file system had
    made a file longer (its size on the disk) but never wrote the data there (ext4, XFS). Restores
    the file's position."""
    at = f.tell()
    start = size
    try:
        while start > 0:
            n = min(start, 1 << 16)
            f.seek(start - n)
            block = f.read(n)
            if len(block) < n:  # shrank under us: no answer
                return None
            kept = block.rstrip(b"\0")
            start -= n - len(kept)
            if kept:
                break
    finally:
        f.seek(at)
    return start if size - start >= _MIN_ZERO_TAIL else None


def _warn_zeros(name: str, size: int, zeros_from: int) -> None:
    logger.warning("%s: the log ends in %d bytes of zeros from byte %d: data its file system had made room for but "
                   "never wrote, as at a power cut while it was recorded; replayed the complete chunks before them",
                   name, size - zeros_from, zeros_from)


def _warn_cut(f: IO[bytes], size: int, name: str, what: str | None) -> None:
    """Say that a log ends early: in a record cut short (``what`` says which), after a complete
    record without its summary (``what`` None: a recording not closed), or because it is still
    being written (it has grown since it was opened: a recording in progress)."""
    try:
        now = os.fstat(f.fileno()).st_size
    except (OSError, AttributeError, io.UnsupportedOperation):  # not a file: cannot grow under us
        now = size
    if now > size:
        logger.warning("%s: the log is still being written (it grew from %d bytes while it was read); replayed "
                       "the complete chunks of its first %d bytes: replay it again when the recording has ended",
                       name, size, size)
    elif what is None:
        logger.warning("%s: the log ends after a complete record, at byte %d, without its summary: a recording "
                       "that was not closed (killed, its power cut, or cut back after a full disk); replayed all "
                       "it holds", name, size)
    else:
        logger.warning("%s: the log is cut off mid-write (%s, at byte %d); replayed what came before",
                       name, what, size)


def _records(f: IO[bytes], stats: LogStats, name: str, *, warn: bool = True) -> Iterator[Any]:
    """Every record of the data section in file order, chunks opened; never seeks.

    Stops at DataEnd (what follows repeats the data section's schemas and channels and indexes
    it), at the end of the bytes (a truncated log: ``stats.truncated``) or at a record it cannot
    frame. A chunk that fails its CRC or does not decompress is skipped, counted, and reported as
    ``None`` so consumers can drop state that chunk may have changed.
    """
    size = stats.bytes_total
    # Only the bytes the file held when opened: a log still being written grows while it is read,
    # and what it held is what the checks on opening saw and what bytes_total counts.
    records = _framed_records(cast(IO[bytes], _BoundedReads(f, size)), size)
    while True:
        try:
            record = next(records)
        except StopIteration:
            break
        except _DECODE_ERRORS as exc:
            stats.truncated = True
            stats.bytes_read = f.tell()
            zeros = _zeros_from(f, size)
            if zeros is not None and stats.bytes_read > zeros:  # stopped in them
                stats.zeros_from = zeros
                if warn:
                    _warn_zeros(name, size, zeros)
            elif warn:
                if isinstance(exc, _EndAfterRecord):
                    _warn_cut(f, size, name, None)
                elif stats.bytes_read >= size:  # the reader stopped at the file's end: in a cut record
                    _warn_cut(f, size, name, "its last record is incomplete")
                else:
                    logger.warning("%s: the log ends early at byte %d of %d (a damaged record: %s); replayed "
                                   "what came before", name, stats.bytes_read, size, exc)
            return
        if isinstance(record, _ChunkBody):
            try:
                inner = breakup_chunk(record.chunk(), validate_crc=True)
            except _DECODE_ERRORS as exc:
                zeros = _zeros_from(f, size)
                if zeros is not None and f.tell() > zeros:  # the last chunk, its end never written
                    stats.truncated, stats.zeros_from = True, zeros
                    stats.bytes_read = f.tell()
                    if warn:
                        _warn_zeros(name, size, zeros)
                    return
                if f.tell() >= size:  # the last chunk, partly written: a truncation
                    stats.truncated = True
                    stats.bytes_read = f.tell()
                    if warn:
                        _warn_cut(f, size, name, "its last chunk is incomplete")
                    return
                stats.corrupt_skipped += 1
                if warn:
                    logger.warning(
                        "%s: skipped a corrupt chunk before byte %d: %s", name, f.tell(), exc
                    )
                yield None
                continue
            yield from inner
        elif isinstance(record, DataEnd | Footer):
            break
        else:
            yield record
    stats.bytes_read = f.tell()


def _messages(f: IO[bytes], stats: LogStats, name: str) -> Iterator[tuple[str, Message] | None]:
    """(topic, message) in file order; None where a chunk was lost."""
    topics: dict[int, str] = {}
    ignored: set[int] = set()
    # sunrig's topics in an encoding it cannot decode (another recorder's /gnss/fix in JSON, say):
    # topic -> that encoding. Passed over like another tool's channel, but said, or a log with a
    # heading on such a channel is told to record with a heading source.
    unread: dict[str, str] = {}

    def declare(channel: Channel) -> None:
        spec = CHANNELS.get(channel.topic)
        # Only channels with sunrig's encoding; another tool's channels are left alone.
        if spec is not None and channel.message_encoding == spec.message_encoding:
            topics[channel.id] = channel.topic
        else:
            ignored.add(channel.id)
            if spec is not None:
                unread[channel.topic] = channel.message_encoding

    # A finished log's summary repeats every channel: with it, a damaged first chunk (where the
    # data section declares them) loses its own messages only, not every later chunk's.
    summary = _summary(f, stats.bytes_total)
    for channel in summary.channels.values() if summary is not None else ():
        declare(channel)
    for record in _records(f, stats, name):
        if isinstance(record, Message):
            topic = topics.get(record.channel_id)
            if topic is not None:
                yield topic, record
            elif record.channel_id not in ignored:
                stats.corrupt_skipped += 1  # its channel record was in a lost chunk
        elif isinstance(record, Channel):
            declare(record)
        elif record is None:
            yield None
    if unread:
        logger.warning(
            "%s: passed over every message on %s; write them in the encoding docs/log-format.md gives",
            name,
            ", ".join(f"{topic} in {encoding or 'no'} encoding (sunrig reads {CHANNELS[topic].message_encoding})"
                      for topic, encoding in sorted(unread.items())),
        )


class NativeLogSource:
    """A native log as a frame source, like any camera driver: iterate it for Frames in order.

    Checks the file when made (raises :class:`LogError` with one line if it is not a sunrig log),
    so a CLI fails before it loads a model. Each iteration replays the log from the start and
    resets :attr:`stats`; a truncated log yields its complete frames and sets :attr:`truncated`.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.info = _inspect(self.path)
        self.stats = LogStats()

    @property
    def truncated(self) -> bool:
        return self.stats.truncated

    def __iter__(self) -> Iterator[Frame]:
        return self._frames()

    def _frames(self) -> Iterator[Frame]:
        name = _show(self.path)
        f, size = _open_log_file(self.path)
        stats = self.stats = LogStats(bytes_total=size)
        assembler = _FrameAssembler()
        warned = 0

        def skipped(seq: int, why: object) -> None:
            nonlocal warned
            stats.corrupt_skipped += 1
            if warned < _MAX_WARNINGS:
                warned += 1
                logger.warning("%s: skipped a corrupt message at seq %d: %s", name, seq, why)

        with f:
            for item in _messages(f, stats, name):
                if item is None:
                    assembler.gap()
                else:
                    topic, msg = item
                    try:
                        assembler.feed(topic, msg.sequence, msg.log_time, msg.data)
                    except _CorruptMessage as exc:
                        for seq, why in assembler.take_skipped():  # the images before it, first
                            skipped(seq, why)
                        skipped(msg.sequence, exc)
                for seq, why in assembler.take_skipped():
                    skipped(seq, why)
                for frame in assembler.take():
                    stats.frames_read += 1
                    yield frame
            assembler.end()
            for seq, why in assembler.take_skipped():
                skipped(seq, why)
            for frame in assembler.take():
                stats.frames_read += 1
                yield frame
        if assembler.unmatched:
            logger.warning(
                "%s: dropped %s that matched no image, and its frames replay without them: the writer must "
                "give each of a frame's messages its image's MCAP log time and sequence (docs/log-format.md)",
                name,
                ", ".join(f"{n} {topic} messages" for topic, n in sorted(assembler.unmatched.items())),
            )
        if assembler.duplicates:
            logger.warning(
                "%s: dropped %s, each a duplicate of the one before it on its channel (the same log time and "
                "sequence); every frame replays once",
                name,
                ", ".join(f"{n} {topic} messages" for topic, n in sorted(assembler.duplicates.items())),
            )
        if stats.corrupt_skipped > warned:
            logger.warning(
                "%s: %d corrupt messages or chunks skipped in all", name, stats.corrupt_skipped
            )

    def __repr__(self) -> str:
        return f"NativeLogSource({str(self.path)!r})"


def open_log(path: str | os.PathLike[str]) -> NativeLogSource:
    """Check ``path`` is a sunrig native log now, and return it as a frame source."""
    return NativeLogSource(path)


def read_frames(path: str | os.PathLike[str]) -> Iterator[Frame]:
    """Frames of a native log in order (a generator; see :class:`NativeLogSource`)."""
    yield from open_log(path)


@dataclass(frozen=True)
class LogFigures:
    """What a finished log's summary says of it: its frame count, the seconds from its first
    message to its last, and its ``sunrig`` metadata record (empty when it has none)."""

    frames: int
    span_s: float
    metadata: dict[str, str]


def _indexed_metadata(f: IO[bytes], size: int, summary: Any) -> dict[str, str]:
    """The ``sunrig`` metadata record a summary indexes; empty when there is none or it does not
    parse (metadata has no CRC: what a damaged one said is unknown, not an error of the log)."""
    for index in summary.metadata_indexes:
        if index.name != METADATA_NAME:
            continue
        try:
            f.seek(index.offset)
            reader = StreamReader(cast(IO[bytes], _BoundedReads(f, size)), skip_magic=True, record_size_limit=size)
            record = next(iter(reader.records), None)
        except _SUMMARY_ERRORS:
            return {}
        return dict(record.metadata) if isinstance(record, Metadata) else {}
    return {}


def log_figures(path: str | os.PathLike[str]) -> LogFigures | None:
    """A finished log's :class:`LogFigures`, from its summary and the metadata it indexes (no chunk
    is read); None when it has no summary (a log cut off mid-write) or no image channel."""
    f, size = _open_log_file(Path(path))
    with f:
        summary = _summary(f, size)
        if summary is None or summary.statistics is None:
            return None
        stats = summary.statistics
        ids = [cid for cid, c in summary.channels.items() if c.topic == TOPIC_IMAGE]
        if not ids:
            return None
        frames = sum(stats.channel_message_counts.get(cid, 0) for cid in ids)
        span_s = (stats.message_end_time - stats.message_start_time) / 1e9
        return LogFigures(frames, span_s, _indexed_metadata(f, size, summary))


def frame_count(path: str | os.PathLike[str]) -> int | None:
    """How many frames a finished log holds (:func:`log_figures`), or None."""
    figures = log_figures(path)
    return None if figures is None else figures.frames


def read_estimates(path: str | os.PathLike[str]) -> Iterator[dict]:
    """The ``/sun/estimate`` messages as dicts (rebuild with :func:`estimate_from_dict`).

    Needs only an MCAP file: a log with no estimates yields nothing. Corrupt ones are skipped.
    """
    p = Path(path)
    name = _show(p)
    f, size = _open_log_file(p)
    stats = LogStats(bytes_total=size)
    with f:
        for item in _messages(f, stats, name):
            if item is None or item[0] != TOPIC_ESTIMATE:
                continue
            try:
                d = _loads(item[1].data)
            except ValueError as exc:
                logger.warning(
                    "%s: skipped a corrupt estimate at seq %d: %s", name, item[1].sequence, exc
                )
                continue
            yield d
