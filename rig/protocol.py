"""Wire formats for a :class:`~rig.types.SunEstimate`: an NMEA 0183 sentence and a binary frame.

Pure bytes in, bytes or dicts out: no I/O, no clock. ``docs/protocol.md`` is the specification;
if this file and that page disagree, it is a bug. The I/O shells are in ``rig/publishers.py``.

- NMEA: ``$PSRGS,...*HH<CR><LF>``, proprietary (``P`` + maker ``SRG`` + sentence ``S``), at most
  82 characters, XOR checksum. Any NMEA library reads it.
- Binary: a 60-byte little-endian payload + CRC-16/CCITT-FALSE, COBS-encoded, between 0x00
  delimiters.

Both carry ``PROTOCOL_VERSION``. Decoders refuse a version they do not know (``ProtocolError``
with ``reason="version"``) rather than guess at its fields.
"""

from __future__ import annotations

import math
import re
import struct
from dataclasses import dataclass
from typing import Any

from rig.errors import ProtocolError, ValidationError
from rig.geometry import wrapped_deg
from rig.types import HeadingRef, SunEstimate

PROTOCOL_VERSION = 1

# ---------------------------------------------------------------------------------------------
# Status: one rule for both formats
# ---------------------------------------------------------------------------------------------

FLAG_VALID = 0x01  # the estimate passes the StatusRule (NMEA status A)
FLAG_HAS_UTC = 0x02  # utc_ns is set (otherwise the binary field is 0 and the NMEA time is empty)
FLAG_PARTIAL_WINDOW = 0x04  # fewer frames than a full window (start-up, heading gaps)
FLAG_SPREAD_HIGH = 0x08  # the per-token estimates disagree by more than max_spread_deg
FLAG_ABOVE_TRAINED = 0x10  # the sun is higher than max_elevation_deg: the model's compromise, not a sighting
# Binary only, not a status: a relative heading's epoch modulo 4 (SunEstimate.heading_epoch) in
# bits 5-6. It changes with the heading's zero (an OAK reconnect, odometry that lost track), which
# a controller could otherwise only guess from PARTIAL_WINDOW; 2 bits, so that a message or two
# lost on the line does not hide a change. NMEA has no field for it (a new field is a new version).
ZERO_SHIFT = 5
ZERO_MASK = 0x60

# How far above the highest sun of its training data a model's answer may lie before it is
# flagged: the scatter of answers for the highest suns. For the shipped model's suns within 5 deg
# of its highest, answers lie up to 6.2 deg (validation drives) and 4.0 deg (held-out drives) above
# the truth at the 99th percentile (benchmarks/bench_accuracy.py JSON, ``elevation``; the table in
# docs/protocol.md): a 5-deg margin flags some high suns whose answers are only a few degrees too
# high, a conservative miss, and catches the hedges.
ELEVATION_MARGIN_DEG = 5.0


@dataclass(frozen=True)
class StatusRule:
    """When an estimate is reported valid (NMEA ``A``, binary ``FLAG_VALID``).

    Valid means: a full window (``n_frames >= full_window``), tokens that agree
    (``spread <= max_spread_deg``) and a sun no higher than ``max_elevation_deg``. A partial
    window happens at start-up and after heading gaps; a large spread means the crops disagree
    (an untrained or foreign model).

    ``max_elevation_deg`` catches a model's hedge. Trained with the paper's cosine loss, a model
    that cannot tell where the sun is answers with the mean of the directions it cannot tell
    apart, and the mean of directions spread in azimuth is higher than any of them: a sun 56.5 deg
    up behind the camera in an empty street comes out 77 deg up on average with the shipped model
    (above 80 deg with the one before session 22; docs/protocol.md). An answer above every sun of
    the training data (plus :data:`ELEVATION_MARGIN_DEG`) is such a compromise, not a sighting.
    90 turns the check off; :meth:`for_model` takes the limit from a model's contract.
    """

    full_window: int = 8
    max_spread_deg: float = 30.0
    max_elevation_deg: float = 90.0

    def __post_init__(self) -> None:
        if self.full_window < 1:
            raise ValidationError(f"StatusRule.full_window: expected >= 1 frames, got {self.full_window}")
        if not 0.0 <= self.max_spread_deg <= 180.0:
            raise ValidationError(f"StatusRule.max_spread_deg: expected within [0, 180] deg, got {self.max_spread_deg}")
        if not 0.0 <= self.max_elevation_deg <= 90.0:
            raise ValidationError(
                f"StatusRule.max_elevation_deg: expected within [0, 90] deg, got {self.max_elevation_deg}")

    @classmethod
    def for_model(cls, full_window: int, trained_max_elevation_deg: float | None) -> StatusRule:
        """The rule for a model whose training suns reached ``trained_max_elevation_deg``
        (None: unknown, e.g. a contract written before training recorded it; no elevation check)."""
        if trained_max_elevation_deg is None:
            return cls(full_window=full_window)
        return cls(full_window=full_window,
                   max_elevation_deg=min(90.0, trained_max_elevation_deg + ELEVATION_MARGIN_DEG))

    def flags(self, est: SunEstimate) -> int:
        """The status bits of ``est``: FLAG_VALID unless a check below sets a reason not to."""
        flags = FLAG_HAS_UTC if est.utc_ns is not None else 0
        if est.n_frames < self.full_window:
            flags |= FLAG_PARTIAL_WINDOW
        if math.degrees(est.spread_rad) > self.max_spread_deg:
            flags |= FLAG_SPREAD_HIGH
        if math.degrees(est.elevation_rad) > self.max_elevation_deg:
            flags |= FLAG_ABOVE_TRAINED
        if not flags & _NOT_VALID:
            flags |= FLAG_VALID
        return flags


_NOT_VALID = FLAG_PARTIAL_WINDOW | FLAG_SPREAD_HIGH | FLAG_ABOVE_TRAINED

_FLAG_NAMES = sorted({FLAG_VALID: "VALID", FLAG_HAS_UTC: "HAS_UTC", FLAG_PARTIAL_WINDOW: "PARTIAL_WINDOW",
                      FLAG_SPREAD_HIGH: "SPREAD_HIGH", FLAG_ABOVE_TRAINED: "ABOVE_TRAINED"}.items())


def flag_names(flags: int) -> list[str]:
    """The names of the set status bits, lowest first (docs/protocol.md), e.g. for JSONL."""
    return [name for bit, name in _FLAG_NAMES if flags & bit]


DEFAULT_STATUS_RULE = StatusRule()

_REF_CODE = {HeadingRef.TRUE: "T", HeadingRef.MAGNETIC: "M", HeadingRef.RELATIVE: "R"}
_REF_FROM_CODE = {code: ref for ref, code in _REF_CODE.items()}

# ---------------------------------------------------------------------------------------------
# NMEA 0183
# ---------------------------------------------------------------------------------------------

NMEA_ADDRESS = "PSRGS"  # P (proprietary) + SRG (maker: sunrig) + S (sentence: sun)
NMEA_MAX_LEN = 82  # NMEA 0183: at most 82 characters from '$' to <LF> inclusive
NMEA_FIELDS = 13  # data fields after the address in version 1
NMEA_SEQ_MODULUS = 100_000  # seq travels as 5 digits: enough to spot gaps, wraps after ~55 min at 30 Hz
NMEA_MAX_FRAMES = 99  # n_frames travels as 2 digits; 99 means "99 or more"


def nmea_checksum(body: bytes) -> int:
    """XOR of every byte between ``$`` and ``*`` (exclusive), as NMEA 0183 defines it."""
    value = 0
    for byte in body:
        value ^= byte
    return value


def _quantize(value: float, decimals: int) -> int:
    """``value`` in units of 10**-decimals, rounded to nearest (the wire's fixed-point integer)."""
    return round(value * 10**decimals)


def _fixed(q: int, decimals: int) -> str:
    """Fixed-point text of a quantized value, built from the integer so -0.0 cannot appear."""
    sign = "-" if q < 0 else ""
    whole, frac = divmod(abs(q), 10**decimals)
    return f"{sign}{whole}.{frac:0{decimals}d}"


def _clamp(q: int, lo: int, hi: int) -> int:
    return max(lo, min(hi, q))


def _utc_hhmmss(utc_ns: int) -> str:
    """UTC time of day as hhmmss.ss, truncated (not rounded) so 23:59:59.999 stays on its day."""
    cs = (utc_ns // 10_000_000) % 8_640_000
    s, cs = divmod(cs, 100)
    m, s = divmod(s, 60)
    h, m = divmod(m, 60)
    return f"{h:02d}{m:02d}{s:02d}.{cs:02d}"


def nmea_fields(est: SunEstimate, rule: StatusRule = DEFAULT_STATUS_RULE) -> list[str]:
    """The 13 data fields of the version-1 sentence, as text (see docs/protocol.md for the budget)."""
    az_q = _quantize(math.degrees(est.azimuth_rad), 1) % 3600  # 359.96 rounds to 0.0, not 360.0
    el_q = _clamp(_quantize(math.degrees(est.elevation_rad), 1), -900, 900)
    rb_q = (_quantize(math.degrees(est.relative_bearing_rad), 1) + 1800) % 3600 - 1800  # keeps [-180, 180)
    spread_q = _clamp(_quantize(math.degrees(est.spread_rad), 1), 0, 1800)
    enu_q = [_clamp(_quantize(float(c), 3), -1000, 1000) for c in est.sun_enu]
    valid = rule.flags(est) & FLAG_VALID
    return [
        str(PROTOCOL_VERSION),
        _utc_hhmmss(est.utc_ns) if est.utc_ns is not None else "",
        str(est.seq % NMEA_SEQ_MODULUS),
        _fixed(az_q, 1),
        _fixed(el_q, 1),
        *(_fixed(q, 3) for q in enu_q),
        _fixed(rb_q, 1),
        _fixed(spread_q, 1),
        str(min(est.n_frames, NMEA_MAX_FRAMES)),
        _REF_CODE[est.heading_ref],
        "A" if valid else "V",
    ]


def nmea_sentence(fields: list[str], address: str = NMEA_ADDRESS) -> bytes:
    """``$address,f1,...*HH<CR><LF>`` with its checksum; no length check (see :func:`encode_nmea`)."""
    body = ",".join([address, *fields]).encode("ascii")
    return b"$" + body + b"*%02X\r\n" % nmea_checksum(body)


def encode_nmea(est: SunEstimate, rule: StatusRule = DEFAULT_STATUS_RULE) -> bytes:
    """The ``$PSRGS`` sentence of ``est``: ASCII, CRLF-terminated, at most 82 bytes."""
    line = nmea_sentence(nmea_fields(est, rule))
    if len(line) > NMEA_MAX_LEN:  # the field budget makes this unreachable; guard the budget itself
        raise ProtocolError(f"NMEA sentence of {len(line)} characters exceeds {NMEA_MAX_LEN}: a field budget is wrong")
    return line


# NMEA reserves '$' and '*'; a body holds printable ASCII only.
_SENTENCE_RE = re.compile(rb"^\$([^$*\x00-\x1f\x7f-\xff]*)\*([0-9A-Fa-f]{2})\r?\n?$")
_FIELD_RE = {
    "time": re.compile(r"^\d{6}\.\d{2}$"),
    "int": re.compile(r"^(0|[1-9]\d{0,4})$"),  # no leading zeros (docs/protocol.md)
    "deg1": re.compile(r"^-?\d{1,3}\.\d$"),
    "unit3": re.compile(r"^-?\d\.\d{3}$"),
}


def _field(name: str, text: str, kind: str) -> str:
    if not _FIELD_RE[kind].match(text):
        raise ProtocolError(f"NMEA field {name}: {text!r} is not a {kind} field; the sentence is corrupt", "field")
    return text


def _in_range(name: str, value: float, lo: float, hi: float) -> float:
    if not lo <= value <= hi:
        raise ProtocolError(f"NMEA field {name}: {value} outside [{lo}, {hi}]; the sentence is corrupt", "field")
    return value


def _number(name: str, text: str, kind: str, lo: float, hi: float) -> float:
    """A fixed-point field: its exact shape first (the XOR checksum misses many corruptions), then its range."""
    return _in_range(name, float(_field(name, text, kind)), lo, hi)


def nmea_body(line: bytes) -> bytes:
    """The text between ``$`` and ``*`` of a sentence whose checksum matches; ProtocolError otherwise."""
    match = _SENTENCE_RE.match(line)
    if match is None:
        raise ProtocolError(f"not an NMEA sentence ($...*HH): {line[:40]!r}", "framing")
    body, given = match.group(1), int(match.group(2), 16)
    computed = nmea_checksum(body)
    if given != computed:
        raise ProtocolError(
            f"bad NMEA checksum: sentence says {given:02X}, computed {computed:02X}; check the line or the baud rate",
            "checksum",
        )
    return body


def decode_nmea(line: bytes) -> dict[str, Any]:
    """Decode one ``$PSRGS`` sentence (with or without CRLF) into a dict; see docs/protocol.md.

    Raises :class:`ProtocolError` whose ``reason`` is ``framing``, ``checksum``, ``foreign``
    (another sentence), ``version`` (a version this decoder does not know) or ``field``.
    """
    fields = nmea_body(line).decode("ascii").split(",")
    if fields[0] != NMEA_ADDRESS:
        raise ProtocolError(f"not a sunrig sentence: {fields[0]!r}, expected {NMEA_ADDRESS!r}", "foreign")
    if len(fields) < 2 or fields[1] != str(PROTOCOL_VERSION):
        found = fields[1] if len(fields) > 1 else "none"
        raise ProtocolError(
            f"{NMEA_ADDRESS} version {found!r}, this decoder knows {PROTOCOL_VERSION}; update the controller", "version"
        )
    data = fields[1:]
    if len(data) != NMEA_FIELDS:
        raise ProtocolError(f"{NMEA_ADDRESS} v1: expected {NMEA_FIELDS} fields, got {len(data)}", "framing")
    _, utc, seq, az, el, e, n, u, rb, spread, nf, ref, status = data
    utc_s: float | None = None
    if utc:
        _field("utc", utc, "time")
        utc_s = _in_range("utc hours", int(utc[0:2]), 0, 23) * 3600.0
        utc_s += _in_range("utc minutes", int(utc[2:4]), 0, 59) * 60.0
        utc_s += _in_range("utc seconds", float(utc[4:]), 0.0, 60.99)  # 60: a leap second
    if ref not in _REF_FROM_CODE:
        raise ProtocolError(f"NMEA field heading_ref: {ref!r}, expected T, M or R", "field")
    if status not in ("A", "V"):
        raise ProtocolError(f"NMEA field status: {status!r}, expected A or V", "field")
    return {
        "version": PROTOCOL_VERSION,
        "utc_s_of_day": utc_s,
        "seq": int(_field("seq", seq, "int")),
        "azimuth_deg": _number("azimuth", az, "deg1", 0.0, 359.9),
        "elevation_deg": _number("elevation", el, "deg1", -90.0, 90.0),
        "sun_enu": (
            _number("east", e, "unit3", -1.0, 1.0),
            _number("north", n, "unit3", -1.0, 1.0),
            _number("up", u, "unit3", -1.0, 1.0),
        ),
        "relative_bearing_deg": _number("relative_bearing", rb, "deg1", -180.0, 179.9),
        "spread_deg": _number("spread", spread, "deg1", 0.0, 180.0),
        "n_frames": int(_in_range("n_frames", int(_field("n_frames", nf, "int")), 1, 99)),
        "heading_ref": _REF_FROM_CODE[ref].value,
        "valid": status == "A",
    }


# ---------------------------------------------------------------------------------------------
# Binary: payload + CRC-16, COBS, 0x00 delimiters
# ---------------------------------------------------------------------------------------------

MSG_SUN_ESTIMATE = 1
# version, msg type, flags, heading ref (ASCII T/M/R), seq, t_mono_s, utc_ns,
# east, north, up, azimuth_deg, elevation_deg, relative_bearing_deg, heading_deg, spread_deg,
# n_frames, n_tokens. Little-endian, no padding.
BINARY_STRUCT = struct.Struct("<BBBBIdq8fHH")
BINARY_PAYLOAD_LEN = BINARY_STRUCT.size  # 60
BINARY_FRAME_LEN = 1 + (BINARY_PAYLOAD_LEN + 2 + 1) + 1  # delimiter, COBS(payload + CRC), delimiter: 65
# A reader keeps at most this many bytes waiting for a delimiter: room for a later, larger
# version (so it is counted as unknown rather than as garbage), small enough to resync quickly.
BINARY_MAX_ENCODED = 256


def _crc16_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
        table.append(crc & 0xFFFF)
    return tuple(table)


_CRC16_TABLE = _crc16_table()


def crc16_ccitt_false(data: bytes, crc: int = 0xFFFF) -> int:
    """CRC-16/CCITT-FALSE: poly 0x1021, init 0xFFFF, not reflected, xorout 0; check 0x29B1."""
    for byte in data:
        crc = ((crc << 8) & 0xFFFF) ^ _CRC16_TABLE[(crc >> 8) ^ byte]
    return crc


def cobs_encode(data: bytes) -> bytes:
    """Consistent Overhead Byte Stuffing (Cheshire & Baker 1999): the output has no 0x00 byte.

    Each block is a code byte (1 + the number of non-zero bytes that follow) and those bytes;
    a code below 0xFF stands for a zero after its block. A full 254-byte block at the very end
    gets no empty block after it (the canonical encoding, as on Wikipedia).
    """
    out = bytearray(b"\x00")
    code_at, code = 0, 1
    for i, byte in enumerate(data):
        if byte:
            out.append(byte)
            code += 1
        if not byte or code == 0xFF:
            out[code_at] = code
            code_at, code = len(out), 1
            if not byte or i + 1 < len(data):
                out.append(0)
    if code_at < len(out):  # else the data ended on a full block and no block is open
        out[code_at] = code
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Inverse of :func:`cobs_encode`; ProtocolError (framing) for a 0x00 or a block cut short."""
    if not data:
        raise ProtocolError("empty COBS frame", "framing")
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        if code == 0:
            raise ProtocolError(f"0x00 inside a COBS frame at byte {i}", "framing")
        end = i + code
        if end > n:
            raise ProtocolError(f"COBS block at byte {i} needs {code - 1} bytes, {n - i - 1} left", "framing")
        block = data[i + 1 : end]
        if 0 in block:
            raise ProtocolError(f"0x00 inside a COBS frame near byte {i}", "framing")
        out += block
        i = end
        if code != 0xFF and i < n:
            out.append(0)
    return bytes(out)


def binary_payload(est: SunEstimate, rule: StatusRule = DEFAULT_STATUS_RULE) -> bytes:
    """The 60-byte version-1 payload of ``est`` (no CRC, no framing)."""
    e, n, u = (float(c) for c in est.sun_enu)
    return BINARY_STRUCT.pack(
        PROTOCOL_VERSION,
        MSG_SUN_ESTIMATE,
        rule.flags(est) | (est.heading_epoch % 4) << ZERO_SHIFT,
        ord(_REF_CODE[est.heading_ref]),
        est.seq % 2**32,
        est.t_mono_s,
        est.utc_ns if est.utc_ns is not None else 0,
        e,
        n,
        u,
        # The float32 fields keep the wrapped ranges: 359.99999 deg would round to 360.0.
        wrapped_deg(est.azimuth_rad, float32=True),
        math.degrees(est.elevation_rad),
        wrapped_deg(est.relative_bearing_rad, -180.0, float32=True),
        wrapped_deg(est.heading_rad, float32=True),
        math.degrees(est.spread_rad),
        min(est.n_frames, 0xFFFF),
        min(est.n_tokens, 0xFFFF),
    )


def encode_binary(est: SunEstimate, rule: StatusRule = DEFAULT_STATUS_RULE) -> bytes:
    """``00 COBS(payload + CRC16 little-endian) 00``: 65 bytes for version 1.

    The leading 0x00 costs one byte and lets a reader resync at once after a frame was cut
    short (a write timeout or a reopened port), instead of losing the next frame too.
    """
    payload = binary_payload(est, rule)
    return b"\x00" + cobs_encode(payload + struct.pack("<H", crc16_ccitt_false(payload))) + b"\x00"


def decode_binary(frame: bytes) -> dict[str, Any]:
    """Decode one frame (delimiters optional) into a dict; see docs/protocol.md.

    Raises :class:`ProtocolError` whose ``reason`` is ``framing`` (bad COBS, wrong length),
    ``checksum`` (CRC), ``version`` (a version or message type this decoder does not know) or
    ``field`` (a heading ref other than T/M/R; a float that is NaN, infinite or outside its range).
    """
    raw = cobs_decode(bytes(frame).strip(b"\x00"))
    if len(raw) < 4:
        raise ProtocolError(f"binary frame of {len(raw)} bytes is too short for a header and CRC", "framing")
    payload, (given,) = raw[:-2], struct.unpack("<H", raw[-2:])
    computed = crc16_ccitt_false(payload)
    if given != computed:
        raise ProtocolError(
            f"bad CRC-16: frame says {given:04X}, computed {computed:04X}; check the line or the baud rate", "checksum"
        )
    version, msg_type = payload[0], payload[1]
    if version != PROTOCOL_VERSION or msg_type != MSG_SUN_ESTIMATE:
        raise ProtocolError(
            f"binary version {version} type {msg_type}; this decoder knows version {PROTOCOL_VERSION} "
            f"type {MSG_SUN_ESTIMATE}: update the controller",
            "version",
        )
    if len(payload) != BINARY_PAYLOAD_LEN:
        raise ProtocolError(f"binary v1 payload of {len(payload)} bytes, expected {BINARY_PAYLOAD_LEN}", "framing")
    (_, _, flags, ref, seq, t_mono_s, utc_ns, e, n, u, az, el, rb, heading, spread, n_frames, n_tokens) = (
        BINARY_STRUCT.unpack(payload)
    )
    if chr(ref) not in _REF_FROM_CODE:
        raise ProtocolError(f"binary heading_ref byte {ref:#04x}, expected ASCII T, M or R", "field")
    # As the NMEA decoder does: a frame the CRC passes can still come from another encoder or be
    # noise the CRC missed, and a NaN or an out-of-range angle must not reach a control loop.
    if not math.isfinite(t_mono_s):
        raise ProtocolError(f"binary field t_mono_s: {t_mono_s} is not finite; the frame is corrupt", "field")
    for name, value, lo, hi, top_open in (
        ("east", e, -1.0, 1.0, False), ("north", n, -1.0, 1.0, False), ("up", u, -1.0, 1.0, False),
        ("azimuth_deg", az, 0.0, 360.0, True), ("elevation_deg", el, -90.0, 90.0, False),
        ("relative_bearing_deg", rb, -180.0, 180.0, True), ("heading_deg", heading, 0.0, 360.0, True),
        ("spread_deg", spread, 0.0, 180.0, False),
    ):
        if not (lo <= value < hi if top_open else lo <= value <= hi):  # also false for NaN
            raise ProtocolError(
                f"binary field {name}: {value} outside [{lo}, {hi}{')' if top_open else ']'}; the frame is corrupt",
                "field")
    return {
        "version": version,
        "msg_type": msg_type,
        "flags": flags,
        "valid": bool(flags & FLAG_VALID),
        "partial_window": bool(flags & FLAG_PARTIAL_WINDOW),
        "spread_high": bool(flags & FLAG_SPREAD_HIGH),
        "above_trained": bool(flags & FLAG_ABOVE_TRAINED),
        "heading_zero": (flags & ZERO_MASK) >> ZERO_SHIFT,
        "seq": seq,
        "t_mono_s": t_mono_s,
        "utc_ns": utc_ns if flags & FLAG_HAS_UTC else None,
        "sun_enu": (e, n, u),
        "azimuth_deg": az,
        "elevation_deg": el,
        "relative_bearing_deg": rb,
        "heading_deg": heading,
        "spread_deg": spread,
        "n_frames": n_frames,
        "n_tokens": n_tokens,
        "heading_ref": _REF_FROM_CODE[chr(ref)].value,
    }


# ---------------------------------------------------------------------------------------------
# Stream readers (controller side, and for tests): bytes in, decoded messages out
# ---------------------------------------------------------------------------------------------


def _not_separators(chunk: bytes | bytearray) -> int:
    """Bytes of ``chunk`` that are neither CR nor LF: line ends between sentences are not garbage."""
    return len(chunk) - chunk.count(b"\r") - chunk.count(b"\n")


class NmeaLineReader:
    """Feed it bytes as they arrive, in any chunks; it returns the ``$PSRGS`` sentences decoded.

    It resynchronises on every ``$``: a sentence cut short by the next one (a truncated write)
    is dropped, as is a line longer than 82 characters. ``counts``: ``messages`` decoded,
    ``bad_checksum``, ``malformed`` (framing or fields), ``unknown_version``, ``foreign``
    (valid sentences of other talkers, skipped) and ``garbage_bytes`` (bytes in no sentence).
    """

    def __init__(self, max_len: int = NMEA_MAX_LEN) -> None:
        self._buf = bytearray()
        self._max_len = max_len
        self.counts = dict.fromkeys(
            ("messages", "bad_checksum", "malformed", "unknown_version", "foreign", "garbage_bytes"), 0
        )

    def feed(self, data: bytes) -> list[dict[str, Any]]:
        self._buf += data
        out: list[dict[str, Any]] = []
        while True:
            start = self._buf.find(b"$")
            if start < 0:
                self.counts["garbage_bytes"] += _not_separators(self._buf)
                self._buf.clear()
                return out
            if start:
                self.counts["garbage_bytes"] += _not_separators(self._buf[:start])
                del self._buf[:start]
            end = self._buf.find(b"\n")
            restart = self._buf.find(b"$", 1)
            if restart >= 0 and (end < 0 or restart < end):
                self.counts["garbage_bytes"] += _not_separators(self._buf[:restart])
                del self._buf[:restart]
                continue
            if end < 0:
                if len(self._buf) >= self._max_len:  # a valid line has its LF by byte 82
                    self.counts["garbage_bytes"] += _not_separators(self._buf)
                    self._buf.clear()
                return out
            line = bytes(self._buf[: end + 1])
            del self._buf[: end + 1]
            self._decode(line, out)

    def _decode(self, line: bytes, out: list[dict[str, Any]]) -> None:
        if len(line) > self._max_len:
            self.counts["garbage_bytes"] += _not_separators(line)
            return
        try:
            out.append(decode_nmea(line))
        except ProtocolError as exc:
            key = {"checksum": "bad_checksum", "version": "unknown_version", "foreign": "foreign"}
            self.counts[key.get(exc.reason, "malformed")] += 1
            return
        self.counts["messages"] += 1


class BinaryFrameReader:
    """Feed it bytes as they arrive, in any chunks; it returns the binary frames decoded.

    Frames end at each 0x00. ``counts``: ``messages`` decoded, ``bad_crc``, ``malformed`` (not
    COBS, wrong length or field), ``unknown_version`` (version or message type) and
    ``garbage_bytes`` (runs longer than ``max_encoded`` without a delimiter, dropped).
    """

    def __init__(self, max_encoded: int = BINARY_MAX_ENCODED) -> None:
        self._buf = bytearray()
        self._max = max_encoded
        self._discarding = False  # inside an over-long run: drop bytes up to the next 0x00
        self.counts = dict.fromkeys(("messages", "bad_crc", "malformed", "unknown_version", "garbage_bytes"), 0)

    def feed(self, data: bytes) -> list[dict[str, Any]]:
        self._buf += data
        out: list[dict[str, Any]] = []
        while True:
            end = self._buf.find(0)
            if end < 0:
                if len(self._buf) > self._max:
                    self.counts["garbage_bytes"] += len(self._buf)
                    self._buf.clear()
                    self._discarding = True
                return out
            frame = bytes(self._buf[:end])
            del self._buf[: end + 1]
            if self._discarding or len(frame) > self._max:  # counted alike however the bytes were chunked
                self.counts["garbage_bytes"] += len(frame)
                self._discarding = False
            elif frame:  # two delimiters in a row (the leading one of each frame) hold nothing
                self._decode(frame, out)

    def _decode(self, frame: bytes, out: list[dict[str, Any]]) -> None:
        try:
            out.append(decode_binary(frame))
        except ProtocolError as exc:
            key = {"checksum": "bad_crc", "version": "unknown_version"}
            self.counts[key.get(exc.reason, "malformed")] += 1
            return
        self.counts["messages"] += 1
