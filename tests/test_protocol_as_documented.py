"""The serial output as a controller's engineer meets it: decoders written from docs/protocol.md alone.

Everything below the "decoder from the page" line was written from the page, not from
rig/protocol.py: the byte order, sizes, scaling, checksum and CRC, COBS, flag bits, status rule,
reserved bits, versioning and the readers' resynchronisation and counters. The tests feed these
decoders what rig/protocol.py emits for a range of estimates (valid, invalid, relative with epochs,
a sun below the horizon, azimuths near 0/360, extreme values) and the page's own examples, and run
the page's readers beside the rig's on the same damaged streams. A disagreement is a fault of the
code or of the page (docs/protocol.md: "If the code and this page disagree, treat it as a bug").
"""

from __future__ import annotations

import math
import random
import re
import struct
from typing import Any

import numpy as np
import pytest

import rig.protocol as rig_protocol
from rig.geometry import enu_from_az_el
from rig.protocol import (
    BinaryFrameReader,
    NmeaLineReader,
    StatusRule,
    decode_binary,
    decode_nmea,
    encode_binary,
    encode_nmea,
)
from rig.types import HeadingRef, SunEstimate

# ---------------------------------------------------------------------------------------------
# The decoder from the page (docs/protocol.md), as a controller's engineer would write it.
# ---------------------------------------------------------------------------------------------

NMEA_MAX_LEN = 82  # "$" to LF, CR and LF included
BINARY_FRAME_LEN = 65  # two delimiters and 63 COBS bytes
MAX_RUN = 256  # the most a binary reader keeps between delimiters
PAYLOAD = struct.Struct("<BBBBIdq3f5fHH")  # little-endian, no padding: 60 bytes

VALID, HAS_UTC, PARTIAL_WINDOW, SPREAD_HIGH, ABOVE_TRAINED = 0x01, 0x02, 0x04, 0x08, 0x10
ZERO_SHIFT, ZERO_MASK, RESERVED = 5, 0x60, 0x80
REFS = {"T": "true", "M": "magnetic", "R": "relative"}


class Dropped(Exception):
    """A message the page says to drop; ``counter`` is the reader counter it goes in."""

    def __init__(self, counter: str, why: str) -> None:
        super().__init__(f"{counter}: {why}")
        self.counter = counter


def xor_checksum(body: bytes) -> int:
    out = 0
    for b in body:
        out ^= b
    return out


def crc16_ccitt_false(data: bytes) -> int:
    """Bit by bit (the rig's is table-driven): poly 0x1021, init 0xFFFF, no reflection, no final XOR."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def cobs_encode(data: bytes) -> bytes:
    out = bytearray()
    block = bytearray()
    for b in data:
        if b == 0:
            out += bytes([len(block) + 1]) + block
            block = bytearray()
        else:
            block.append(b)
            if len(block) == 254:
                out += b"\xff" + block
                block = bytearray()
    out += bytes([len(block) + 1]) + block
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    out = bytearray()
    i = 0
    while i < len(data):
        code = data[i]
        block = data[i + 1:i + code]
        if code == 0 or len(block) != code - 1 or 0 in block:
            raise Dropped("malformed", "not COBS")
        out += block
        i += code
        if code < 0xFF and i < len(data):  # the last block's zero is not data
            out.append(0)
    return bytes(out)


_NMEA_SHAPES = {  # the field formats of the page's table ("no leading zeros" is said of the integers)
    "utc": r"(\d{6}\.\d{2})?",
    "seq": r"0|[1-9]\d{0,4}",
    "angle": r"-?\d{1,3}\.\d",
    "unit": r"-?\d\.\d{3}",
    "frames": r"[1-9]\d?",
}


def _shaped(text: str, shape: str) -> str:
    if not re.fullmatch(_NMEA_SHAPES[shape], text):
        raise Dropped("malformed", f"{text!r} is not {shape}")
    return text


def _ranged(text: str, shape: str, lo: float, hi: float) -> float:
    value = float(_shaped(text, shape))
    if not lo <= value <= hi:
        raise Dropped("malformed", f"{text} outside [{lo}, {hi}]")
    return value


def page_decode_nmea(line: bytes) -> dict[str, Any]:
    """One sentence from `$` to its line end (CR LF or LF), checked in the page's order:
    checksum, address, version, field count, then each field against the table."""
    body = line[:-2] if line.endswith(b"\r\n") else line[:-1] if line.endswith(b"\n") else line
    m = re.fullmatch(rb"\$([\x20-\x7e]*)\*([0-9A-Fa-f]{2})", body)  # the rig writes uppercase
    if not m or b"$" in m.group(1) or b"*" in m.group(1):
        raise Dropped("malformed", "no *HH")
    if xor_checksum(m.group(1)) != int(m.group(2), 16):
        raise Dropped("bad_checksum", "XOR mismatch")
    fields = m.group(1).decode("ascii").split(",")
    if fields[0] != "PSRGS":
        raise Dropped("foreign", fields[0])
    if len(fields) < 2 or fields[1] != "1":
        raise Dropped("unknown_version", fields[1] if len(fields) > 1 else "")
    if len(fields) != 14:
        raise Dropped("malformed", f"{len(fields)} fields")
    _, _, utc, seq, az, el, e, n, u, brg, spread, frames, ref, status = fields
    utc_s = None
    if _shaped(utc, "utc"):
        hh, mm, ss = int(utc[:2]), int(utc[2:4]), float(utc[4:])
        if hh > 23 or mm > 59 or ss >= 61.0:
            raise Dropped("malformed", f"time {utc}")
        utc_s = hh * 3600 + mm * 60 + ss
    if ref not in REFS or status not in ("A", "V"):
        raise Dropped("malformed", f"ref {ref!r}, status {status!r}")
    return {
        "version": 1,
        "utc_s_of_day": utc_s,
        "seq": int(_shaped(seq, "seq")),
        "azimuth_deg": _ranged(az, "angle", 0.0, 359.9),
        "elevation_deg": _ranged(el, "angle", -90.0, 90.0),
        "sun_enu": tuple(_ranged(c, "unit", -1.0, 1.0) for c in (e, n, u)),
        "relative_bearing_deg": _ranged(brg, "angle", -180.0, 179.9),
        "spread_deg": _ranged(spread, "angle", 0.0, 180.0),
        "n_frames": int(_ranged(frames, "frames", 1, 99)),
        "heading_ref": REFS[ref],
        "valid": status == "A",
    }


def page_decode_binary_payload(decoded: bytes) -> dict[str, Any]:
    """COBS-decoded bytes of one frame: length, CRC, version and type, length, then the fields."""
    if len(decoded) < 4:
        raise Dropped("malformed", "fewer than 4 bytes")
    body, (crc,) = decoded[:-2], struct.unpack("<H", decoded[-2:])
    if crc16_ccitt_false(body) != crc:
        raise Dropped("bad_crc", "CRC mismatch")
    if body[0] != 1 or body[1] != 1:
        raise Dropped("unknown_version", f"version {body[0]}, type {body[1]}")
    if len(body) != PAYLOAD.size:
        raise Dropped("malformed", f"{len(body)} payload bytes")
    (_, _, flags, ref, seq, t_mono_s, utc_ns, east, north, up, az, el, brg, heading, spread,
     n_frames, n_tokens) = PAYLOAD.unpack(body)
    ranges = {"azimuth_deg": (az, 0.0, 360.0, False), "elevation_deg": (el, -90.0, 90.0, True),
              "relative_bearing_deg": (brg, -180.0, 180.0, False), "heading_deg": (heading, 0.0, 360.0, False),
              "spread_deg": (spread, 0.0, 180.0, True), "east": (east, -1.0, 1.0, True),
              "north": (north, -1.0, 1.0, True), "up": (up, -1.0, 1.0, True)}
    for name, (value, lo, hi, closed) in ranges.items():
        if not (lo <= value <= hi if closed else lo <= value < hi):
            raise Dropped("malformed", f"{name} {value}")
    if chr(ref) not in REFS or not math.isfinite(t_mono_s):
        raise Dropped("malformed", f"ref {ref:#x}, t_mono_s {t_mono_s}")
    return {  # bit 7 is reserved: a version-1 reader ignores it
        "version": 1, "msg_type": 1, "flags": flags, "valid": bool(flags & VALID),
        "partial_window": bool(flags & PARTIAL_WINDOW), "spread_high": bool(flags & SPREAD_HIGH),
        "above_trained": bool(flags & ABOVE_TRAINED), "heading_zero": (flags & ZERO_MASK) >> ZERO_SHIFT,
        "seq": seq, "t_mono_s": t_mono_s, "utc_ns": utc_ns if flags & HAS_UTC else None,
        "sun_enu": (east, north, up), "azimuth_deg": az, "elevation_deg": el,
        "relative_bearing_deg": brg, "heading_deg": heading, "spread_deg": spread,
        "n_frames": n_frames, "n_tokens": n_tokens, "heading_ref": REFS[chr(ref)],
    }


def page_decode_binary(frame: bytes) -> dict[str, Any]:
    """One whole frame, 0x00 | COBS(payload | CRC LE) | 0x00."""
    if len(frame) < 2 or frame[0] != 0 or frame[-1] != 0 or 0 in frame[1:-1]:
        raise Dropped("malformed", "not delimited")
    return page_decode_binary_payload(cobs_decode(frame[1:-1]))


class PageNmeaReader:
    """Resynchronises on every `$`; counts what it drops (the page's table, NMEA column)."""

    def __init__(self) -> None:
        self.line: bytearray | None = None  # from `$`, or None outside a sentence
        self.counts = dict.fromkeys(
            ("messages", "bad_checksum", "malformed", "unknown_version", "foreign", "garbage_bytes"), 0)

    def _garbage(self, data: bytes | bytearray) -> None:
        self.counts["garbage_bytes"] += sum(b not in b"\r\n" for b in data)

    def feed(self, chunk: bytes) -> list[dict[str, Any]]:
        out = []
        for b in chunk:
            if b == ord("$"):
                if self.line is not None:  # a sentence cut short by the next `$`
                    self._garbage(self.line)
                self.line = bytearray(b"$")
            elif self.line is None:
                self._garbage(bytes([b]))
            else:
                self.line.append(b)
                if b == ord("\n"):
                    line, self.line = bytes(self.line), None
                    try:
                        out.append(page_decode_nmea(line))
                        self.counts["messages"] += 1
                    except Dropped as exc:
                        self.counts[exc.counter] += 1
                elif len(self.line) >= NMEA_MAX_LEN:  # 82 bytes after a `$` with no LF among them
                    self._garbage(self.line)
                    self.line = None
        return out


class PageBinaryReader:
    """Resynchronises on every 0x00; counts what it drops (the page's table, binary column)."""

    def __init__(self) -> None:
        self.run = bytearray()
        self.counts = dict.fromkeys(("messages", "bad_crc", "malformed", "unknown_version", "garbage_bytes"), 0)

    def feed(self, chunk: bytes) -> list[dict[str, Any]]:
        out = []
        for b in chunk:
            if b != 0:
                self.run.append(b)
                continue
            run, self.run = bytes(self.run), bytearray()
            if not run:
                continue  # empty frames are ignored
            if len(run) > MAX_RUN:
                self.counts["garbage_bytes"] += len(run)
                continue
            try:
                out.append(page_decode_binary_payload(cobs_decode(run)))
                self.counts["messages"] += 1
            except Dropped as exc:
                self.counts[exc.counter] += 1
        return out


# ---------------------------------------------------------------------------------------------
# What the page says each field holds, from the estimate.
# ---------------------------------------------------------------------------------------------


def circular_diff_deg(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def truth(est: SunEstimate) -> dict[str, float]:
    e, n, u = (float(x) for x in est.sun_enu)
    az = math.degrees(math.atan2(e, n)) % 360.0
    heading = math.degrees(est.heading_rad) % 360.0
    return {"az": az, "el": math.degrees(math.atan2(u, math.hypot(e, n))), "e": e, "n": n, "u": u,
            "heading": heading, "brg": (az - heading + 180.0) % 360.0 - 180.0,
            "spread": math.degrees(est.spread_rad)}


def page_flags(est: SunEstimate, rule: StatusRule) -> int:
    t = truth(est)
    flags = HAS_UTC if est.utc_ns is not None else 0
    flags |= PARTIAL_WINDOW if est.n_frames < rule.full_window else 0
    flags |= SPREAD_HIGH if t["spread"] > rule.max_spread_deg else 0
    flags |= ABOVE_TRAINED if t["el"] > rule.max_elevation_deg else 0
    flags |= 0 if flags & (PARTIAL_WINDOW | SPREAD_HIGH | ABOVE_TRAINED) else VALID
    ref = est.heading_ref.value
    return flags | ((est.heading_epoch % 4) << ZERO_SHIFT if ref == "relative" else 0)


def page_utc_text(utc_ns: int) -> str:
    centis = (utc_ns % (86_400 * 10**9)) // 10**7  # truncated, in days of 86 400 s
    s, cs = divmod(centis, 100)
    return f"{s // 3600:02d}{s // 60 % 60:02d}{s % 60:02d}.{cs:02d}"


def check_nmea(line: bytes, est: SunEstimate, rule: StatusRule) -> dict[str, Any]:
    """``line`` as the page describes the sentence for ``est``; returns the page's decoding."""
    assert line.startswith(b"$PSRGS,") and line.endswith(b"\r\n") and len(line) <= NMEA_MAX_LEN, line
    assert all(0x20 <= b < 0x7F for b in line[:-2]), line
    msg = page_decode_nmea(line)
    t = truth(est)
    fields = line[:-5].decode("ascii").split(",")
    assert not any(f.startswith("-") and float(f) == 0.0 for f in fields[4:11]), f"a negative zero in {line!r}"
    assert all(re.fullmatch(r"-?(0|[1-9]\d*)\.\d+", f) for f in fields[4:11]), f"a leading zero in {line!r}"
    assert re.fullmatch(rb"[0-9A-F]{2}", line[-4:-2]), line
    assert fields[2] == ("" if est.utc_ns is None else page_utc_text(est.utc_ns)), line
    assert msg["seq"] == est.seq % 100_000
    half = 0.05 + 1e-9
    assert circular_diff_deg(msg["azimuth_deg"], t["az"]) <= half, (line, t)
    assert abs(msg["elevation_deg"] - t["el"]) <= half, (line, t)
    for got, want in zip(msg["sun_enu"], (t["e"], t["n"], t["u"]), strict=True):
        assert abs(got - want) <= 0.0005 + 1e-12, (line, t)
    assert abs(math.sqrt(sum(c * c for c in msg["sun_enu"])) - 1.0) <= 0.0009, line
    assert circular_diff_deg(msg["relative_bearing_deg"], t["brg"]) <= half, (line, t)
    heading_from_wire = (msg["azimuth_deg"] - msg["relative_bearing_deg"]) % 360.0
    assert circular_diff_deg(heading_from_wire, t["heading"]) <= 0.1 + 1e-9, (line, t)
    assert abs(msg["spread_deg"] - t["spread"]) <= half, (line, t)
    assert msg["n_frames"] == min(est.n_frames, 99)
    assert msg["heading_ref"] == est.heading_ref.value
    assert msg["valid"] == bool(page_flags(est, rule) & VALID), (line, t, rule)
    return msg


def check_binary(frame: bytes, est: SunEstimate, rule: StatusRule) -> dict[str, Any]:
    """``frame`` as the page describes the binary frame for ``est``; returns the page's decoding."""
    assert len(frame) == BINARY_FRAME_LEN, frame.hex(" ")
    msg = page_decode_binary(frame)
    assert cobs_encode(cobs_decode(frame[1:-1])) == frame[1:-1], "not the canonical COBS"
    payload = cobs_decode(frame[1:-1])[:-2]
    assert payload[3] == ord(est.heading_ref.value[0].upper())
    t = truth(est)
    assert msg["flags"] & RESERVED == 0
    assert msg["flags"] == page_flags(est, rule), (msg, t, rule)
    assert msg["seq"] == est.seq % 2**32
    assert msg["t_mono_s"] == est.t_mono_s
    assert msg["utc_ns"] == est.utc_ns
    assert struct.unpack_from("<q", payload, 16)[0] == (est.utc_ns or 0)  # 0 when HAS_UTC is clear
    for got, want in zip(msg["sun_enu"], (t["e"], t["n"], t["u"]), strict=True):
        assert got == pytest.approx(want, abs=1e-7), t
    assert circular_diff_deg(msg["azimuth_deg"], t["az"]) <= 1e-4, (msg, t)
    assert msg["elevation_deg"] == pytest.approx(t["el"], abs=1e-4)
    assert circular_diff_deg(msg["relative_bearing_deg"], t["brg"]) <= 1e-4, (msg, t)
    assert circular_diff_deg(msg["heading_deg"], t["heading"]) <= 1e-4, (msg, t)
    assert msg["spread_deg"] == pytest.approx(t["spread"], abs=1e-4)
    assert msg["n_frames"] == min(est.n_frames, 65535) and msg["n_tokens"] == min(est.n_tokens, 65535)
    assert msg["heading_ref"] == est.heading_ref.value
    return msg


def estimate(az_deg: float = 123.4, el_deg: float = 35.6, *, heading_deg: float = 100.0, spread_deg: float = 5.2,
             n_frames: int = 8, n_tokens: int = 32, seq: int = 1234, utc_ns: int | None = 1317042145964389000,
             ref: str = "true", epoch: int = 0, t_mono_s: float = 12.5, sun_enu: Any = None) -> SunEstimate:
    if sun_enu is None:
        sun_enu = enu_from_az_el(math.radians(az_deg), math.radians(el_deg))
    return SunEstimate(t_mono_s=t_mono_s, seq=seq, sun_enu=np.asarray(sun_enu, dtype=np.float64),
                       heading_rad=math.radians(heading_deg), heading_ref=HeadingRef(ref),
                       spread_rad=math.radians(spread_deg), n_frames=n_frames, n_tokens=n_tokens,
                       aggregator="transformer", utc_ns=utc_ns, heading_epoch=epoch)


DEFAULT_RULE = StatusRule()
SHIPPED_RULE = StatusRule(full_window=8, max_spread_deg=30.0, max_elevation_deg=79.9)
RULES = [DEFAULT_RULE, SHIPPED_RULE, StatusRule(full_window=3, max_spread_deg=10.0, max_elevation_deg=40.0)]


def check_both(est: SunEstimate, rule: StatusRule = DEFAULT_RULE) -> tuple[dict[str, Any], dict[str, Any]]:
    return check_nmea(encode_nmea(est, rule), est, rule), check_binary(encode_binary(est, rule), est, rule)


# ---------------------------------------------------------------------------------------------
# The page's own statements and examples, against the page's decoder.
# ---------------------------------------------------------------------------------------------


def test_the_page_decoder_reproduces_the_pages_check_values():
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    assert cobs_encode(bytes.fromhex("11220033")) == bytes.fromhex("0311220233")
    assert cobs_decode(bytes.fromhex("0311220233")) == bytes.fromhex("11220033")
    for data, enc in [("00", "0101"), ("0000", "010101"), ("11220033", "0311220233"),
                      ("11223344", "0511223344"), ("11000000", "0211010101")]:  # Wikipedia's vectors
        assert cobs_encode(bytes.fromhex(data)) == bytes.fromhex(enc)
        assert cobs_decode(bytes.fromhex(enc)) == bytes.fromhex(data)
    long = bytes(range(1, 256))
    assert cobs_encode(long) == b"\xff" + long[:254] + b"\x02" + long[254:]
    assert PAYLOAD.size == 60


PAGE_NMEA_EXAMPLES = [
    b"$PSRGS,1,130225.96,1234,123.4,35.6,0.679,-0.448,0.582,23.4,5.2,8,T,A*5D\r\n",
    b"$PSRGS,1,,23456,10.0,5.0,0.173,0.981,0.087,20.0,12.0,3,R,V*48\r\n",
    b"$PSRGS,1,144905.96,99999,200.0,-45.0,-0.242,-0.664,-0.707,-150.0,180.0,99,R,V*74\r\n",
]
PAGE_BINARY_EXAMPLE = bytes.fromhex(
    "00 07 01 01 03 54 d2 04 01 01 01 01 01 01 01 23 29 40 88 f2 6c 90 da 12 47 12 d9 c6 2d 3f"
    "58 2b e5 be 03 06 15 3f cd cc f6 42 66 66 0e 42 33 33 bb 41 01 08 c8 42 66 66 a6 40 08 02"
    "20 03 64 67 00")


def test_the_pages_examples_decode_by_the_page_and_come_from_the_rig():
    msgs = [page_decode_nmea(line) for line in PAGE_NMEA_EXAMPLES]
    assert len(PAGE_NMEA_EXAMPLES[2]) == 82
    assert msgs[0]["utc_s_of_day"] == pytest.approx(13 * 3600 + 2 * 60 + 25.96)
    assert msgs[1]["seq"] == 23456 and msgs[1]["heading_ref"] == "relative" and not msgs[1]["valid"]
    # the heading is azimuth - bearing, to within 0.1 deg
    assert (msgs[0]["azimuth_deg"] - msgs[0]["relative_bearing_deg"]) % 360 == pytest.approx(100.0, abs=0.1)
    for msg, line in zip(msgs, PAGE_NMEA_EXAMPLES, strict=True):
        assert decode_nmea(line) == msg

    est = estimate()
    assert encode_nmea(est) == PAGE_NMEA_EXAMPLES[0]
    check_nmea(PAGE_NMEA_EXAMPLES[0], est, StatusRule())
    est2 = estimate(10.0, 5.0, heading_deg=350.0, spread_deg=12.0, n_frames=3, seq=123456, utc_ns=None,
                    ref="relative")
    assert encode_nmea(est2) == PAGE_NMEA_EXAMPLES[1]
    worst = estimate(200.0, -45.0, heading_deg=350.0, spread_deg=180.0, n_frames=150, seq=99_999,
                     utc_ns=1317048545964389000, ref="relative")
    assert encode_nmea(worst) == PAGE_NMEA_EXAMPLES[2]

    assert len(PAGE_BINARY_EXAMPLE) == BINARY_FRAME_LEN
    assert encode_binary(est) == PAGE_BINARY_EXAMPLE
    msg = check_binary(PAGE_BINARY_EXAMPLE, est, StatusRule())
    assert msg["flags"] == VALID | HAS_UTC and msg["seq"] == 1234 and msg["heading_ref"] == "true"
    assert PAGE_BINARY_EXAMPLE[-3:-1] == bytes.fromhex("6467")  # CRC 0x6764, little-endian
    assert decode_binary(PAGE_BINARY_EXAMPLE) == msg


# ---------------------------------------------------------------------------------------------
# What the rig emits, against the page's decoder.
# ---------------------------------------------------------------------------------------------

CASES = {
    "valid": estimate(),
    "partial window": estimate(n_frames=3),
    "spread high": estimate(spread_deg=45.0),
    "all three reasons": estimate(80.0, 85.0, spread_deg=31.0, n_frames=1),
    "no utc": estimate(utc_ns=None),
    "magnetic": estimate(ref="magnetic"),
    "relative epoch 0": estimate(ref="relative"),
    "relative epoch 1": estimate(ref="relative", epoch=1),
    "relative epoch 2": estimate(ref="relative", epoch=2),
    "relative epoch 3 partial": estimate(ref="relative", epoch=3, n_frames=2),
    "relative epoch 6": estimate(ref="relative", epoch=6),
    "relative epoch 2**40+3": estimate(ref="relative", epoch=2**40 + 3),
    "sun below the horizon": estimate(250.0, -12.0),
    "nadir": estimate(sun_enu=[0.0, 0.0, -1.0]),
    "zenith": estimate(sun_enu=[0.0, 0.0, 1.0]),
    "zenith, north -0.0": estimate(sun_enu=[0.0, -0.0, 1.0]),
    "zenith, east -0.0": estimate(sun_enu=[-0.0, 0.0, 1.0]),
    "azimuth 359.96 wraps to 0.0": estimate(359.96, 20.0),
    "azimuth 359.94": estimate(359.94, 20.0),
    "azimuth a hair under 360": estimate(sun_enu=[-1e-12, 1.0, 0.0]),
    "azimuth a hair over 0": estimate(sun_enu=[1e-12, 1.0, 0.0]),
    "azimuth 0.04": estimate(0.04, 20.0),
    "bearing at -180.04 wraps to +179.96, sent as -180.0": estimate(10.0, 20.0, heading_deg=190.04),
    "bearing at -179.96": estimate(10.0, 20.0, heading_deg=189.96),
    "bearing -180 exactly": estimate(10.0, 20.0, heading_deg=190.0),
    "heading a hair under 360": estimate(heading_deg=360.0 - 1e-12),
    "heading -0.04": estimate(30.0, 20.0, heading_deg=-0.04),
    "tiny negative vector components": estimate(sun_enu=[-0.0004, 0.9999998, -0.0004]),
    "spread 0": estimate(spread_deg=0.0),
    "spread 180": estimate(spread_deg=180.0),
    "spread 30.04 (V, sent as 30.0)": estimate(spread_deg=30.04),
    "spread 29.96 (A, sent as 30.0)": estimate(spread_deg=29.96),
    "n_frames 99": estimate(n_frames=99),
    "n_frames 100, tokens 2**16": estimate(n_frames=100, n_tokens=2**16),
    "n_frames 2**20": estimate(n_frames=2**20, n_tokens=2**20 + 7),
    "seq 0": estimate(seq=0),
    "seq 99999": estimate(seq=99_999),
    "seq 100000": estimate(seq=100_000),
    "seq 2**32 + 5": estimate(seq=2**32 + 5),
    "seq 2**62": estimate(seq=2**62),
    "utc 23:59:59.999 stays on its day": estimate(utc_ns=1317081599999999999),
    "utc at the epoch": estimate(utc_ns=0),
    "utc 1 ns before the epoch": estimate(utc_ns=-1),
    "utc at int64 max": estimate(utc_ns=2**63 - 1),
    "utc at int64 min": estimate(utc_ns=-(2**63)),
    "t_mono_s negative": estimate(t_mono_s=-3.25),
    "t_mono_s huge": estimate(t_mono_s=1e300),
    "worst case width": estimate(200.0, -45.0, heading_deg=350.0, spread_deg=180.0, n_frames=150, seq=99_999,
                                 utc_ns=1317048545964389000, ref="relative",
                                 sun_enu=[-0.2424, -0.6644, -0.7071]),
}


@pytest.mark.parametrize("rule", RULES, ids=["default", "shipped", "strict"])
@pytest.mark.parametrize("name", list(CASES))
def test_the_rig_emits_what_the_page_describes(name, rule):
    nmea, binary = check_both(CASES[name], rule)
    assert nmea["valid"] == binary["valid"]


def test_the_pages_named_boundaries():
    """The cases the page spells out, with the text it promises."""
    def fields(est: SunEstimate, rule: StatusRule = DEFAULT_RULE) -> list[str]:
        return encode_nmea(est, rule)[:-5].decode("ascii").split(",")

    assert fields(CASES["azimuth 359.96 wraps to 0.0"])[4] == "0.0"
    assert fields(CASES["zenith"])[4] == "0.0"
    assert fields(CASES["zenith, north -0.0"])[4] == "180.0"
    assert fields(CASES["zenith, east -0.0"])[4] == "0.0"
    assert fields(CASES["bearing at -180.04 wraps to +179.96, sent as -180.0"])[9] == "-180.0"
    assert fields(CASES["tiny negative vector components"])[6:9] == ["0.000", "1.000", "0.000"]
    assert fields(CASES["spread 30.04 (V, sent as 30.0)"])[10::3] == ["30.0", "V"]
    assert fields(CASES["spread 29.96 (A, sent as 30.0)"])[10::3] == ["30.0", "A"]
    assert fields(estimate(el_deg=79.94), SHIPPED_RULE)[5::8] == ["79.9", "V"]
    assert fields(estimate(el_deg=79.86), SHIPPED_RULE)[5::8] == ["79.9", "A"]
    assert fields(CASES["utc 23:59:59.999 stays on its day"])[2] == "235959.99"
    assert fields(CASES["n_frames 100, tokens 2**16"])[11] == "99"
    assert fields(CASES["sun below the horizon"])[13] == "A"  # the status rule has no lower bound
    assert len(encode_nmea(CASES["worst case width"])) == 82


def test_the_zero_bits_follow_the_epoch_and_leave_the_status_alone():
    for epoch in range(9):
        msg = page_decode_binary(encode_binary(estimate(ref="relative", epoch=epoch)))
        assert msg["heading_zero"] == epoch % 4
        assert msg["flags"] & ~ZERO_MASK == VALID | HAS_UTC
    for ref in ("true", "magnetic"):
        assert page_decode_binary(encode_binary(estimate(ref=ref)))["heading_zero"] == 0


def random_estimate(rng: random.Random) -> SunEstimate:
    v = np.array([rng.gauss(0, 1) for _ in range(3)])
    if rng.random() < 0.2:  # near the wrap of the azimuth, or a pole
        v = np.array([rng.choice([-1, 1]) * rng.random() * 1e-3, 1.0, rng.gauss(0, 1)])
    if rng.random() < 0.05:
        v = np.array([rng.random() * 1e-9, rng.random() * 1e-9, rng.choice([-1.0, 1.0])])
    ref = rng.choice(["true", "magnetic", "relative"])
    return SunEstimate(
        t_mono_s=rng.uniform(-1e6, 1e9), seq=rng.choice([rng.randrange(200_000), rng.randrange(2**64)]),
        sun_enu=v / np.linalg.norm(v), heading_rad=rng.uniform(-10, 10), heading_ref=HeadingRef(ref),
        spread_rad=rng.choice([rng.uniform(0, math.pi), rng.uniform(0, 0.7), math.pi]),
        n_frames=rng.choice([rng.randrange(1, 20), rng.randrange(1, 2**20)]),
        n_tokens=rng.choice([rng.randrange(1, 200), rng.randrange(1, 2**20)]), aggregator="mean",
        utc_ns=rng.choice([None, rng.randrange(-(2**63), 2**63), rng.randrange(0, 4 * 10**18)]),
        heading_epoch=rng.randrange(50) if ref == "relative" else 0)


def test_500_seeded_random_estimates_agree_with_the_page():
    rng = random.Random(20240611)
    for _ in range(500):
        est = random_estimate(rng)
        rule = rng.choice(RULES)
        t = truth(est)
        if (min(abs(t["spread"] - rule.max_spread_deg), abs(t["el"] - rule.max_elevation_deg)) < 1e-9):
            continue  # a threshold to the last bit: either computation may win
        check_both(est, rule)


# ---------------------------------------------------------------------------------------------
# The rig's decoders and readers, against the page's.
# ---------------------------------------------------------------------------------------------


def test_the_rigs_decoders_return_what_the_page_decodes():
    rng = random.Random(7)
    for est in [*CASES.values(), *(random_estimate(rng) for _ in range(200))]:
        line, frame = encode_nmea(est), encode_binary(est)
        assert decode_nmea(line) == page_decode_nmea(line)
        assert decode_binary(frame) == page_decode_binary(frame)


def reframe(payload: bytes) -> bytes:
    """A frame of any payload, with its CRC, as another encoder would send it."""
    return b"\x00" + cobs_encode(payload + struct.pack("<H", crc16_ccitt_false(payload))) + b"\x00"


def test_the_rigs_crc_and_cobs_are_the_pages():
    rng = random.Random(11)
    for n in [0, 1, 2, 62, 253, 254, 255, 508, 600]:
        data = rng.randbytes(n) if n % 2 else bytes(rng.choice([0, 0, rng.randrange(256)]) for _ in range(n))
        assert rig_protocol.crc16_ccitt_false(data) == crc16_ccitt_false(data)
        assert rig_protocol.cobs_encode(data) == cobs_encode(data)
        assert rig_protocol.cobs_decode(cobs_encode(data)) == data


def test_decode_nmea_takes_a_leap_second_from_another_encoder_and_nothing_past_it():
    line = PAGE_NMEA_EXAMPLES[0].replace(b"130225.96", b"235960.99")
    line = line[:-4] + b"%02X\r\n" % xor_checksum(line[1:-5])
    assert decode_nmea(line)["utc_s_of_day"] == page_decode_nmea(line)["utc_s_of_day"] == pytest.approx(86_400.99)
    past = line.replace(b"235960.99", b"235961.00")
    past = past[:-4] + b"%02X\r\n" % xor_checksum(past[1:-5])
    with pytest.raises(Dropped, match="malformed"):
        page_decode_nmea(past)
    with pytest.raises(ValueError):
        decode_nmea(past)


def test_a_version_1_reader_ignores_the_reserved_flag_bit():
    payload = cobs_decode(encode_binary(estimate())[1:-1])[:-2]
    with_bit7 = reframe(payload[:2] + bytes([payload[2] | RESERVED]) + payload[3:])
    assert page_decode_binary(with_bit7)["valid"]
    msg = decode_binary(with_bit7)
    assert msg["valid"] and msg["heading_zero"] == 0
    reader = BinaryFrameReader()
    assert len(reader.feed(with_bit7)) == 1 and reader.counts["messages"] == 1


def test_later_versions_and_types_are_counted_as_unknown_whatever_their_length():
    payload = cobs_decode(encode_binary(estimate())[1:-1])[:-2]
    later = [reframe(bytes([2, 1]) + payload[2:] + b"\x05" * 40), reframe(bytes([1, 2]) + payload[2:10]),
             reframe(bytes([9, 9])), reframe(bytes([2]) + b"\x01" * 200)]
    nmea_later = b"$PSRGS,2,anything,at,all"
    nmea_later += b"*%02X\r\n" % xor_checksum(nmea_later[1:])
    for frame in later:
        with pytest.raises(Dropped) as exc:
            page_decode_binary(frame)
        assert exc.value.counter == "unknown_version"
        reader = BinaryFrameReader()
        assert reader.feed(frame) == [] and reader.counts["unknown_version"] == 1, reader.counts
    nmea_reader = NmeaLineReader()
    assert nmea_reader.feed(nmea_later) == [] and nmea_reader.counts["unknown_version"] == 1, nmea_reader.counts


def messages_for_streams(rng: random.Random, n: int) -> list[SunEstimate]:
    return [random_estimate(rng) for _ in range(n)]


def damaged_stream(rng: random.Random, messages: list[bytes], kind: str) -> bytes:
    """Messages with the damage a line brings: noise, cut-short messages, flipped bits, others' traffic."""
    out = bytearray(rng.randbytes(rng.randrange(0, 90)))  # a reader started mid-stream
    for msg in messages:
        r = rng.random()
        if r < 0.15:
            out += rng.randbytes(rng.randrange(1, 300))
        elif r < 0.3:
            out += msg[:rng.randrange(1, len(msg))]  # cut short by a write timeout
        elif r < 0.4:
            i = rng.randrange(len(msg))
            out += msg[:i] + bytes([msg[i] ^ (1 << rng.randrange(8))]) + msg[i + 1:]
        elif r < 0.45 and kind == "nmea":
            gga = b"GPGGA,123519,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,"
            out += b"$" + gga + b"*%02X\r\n" % xor_checksum(gga)
        elif r < 0.5 and kind == "nmea":
            out += msg[:-5] + b"\r\n"  # no *HH
        elif r < 0.55:
            out += rng.choice([b"\r\n", b"\n", b"$", b"\x00", b"\x00\x00"]) * rng.randrange(1, 4)
        out += msg
    return bytes(out)


@pytest.mark.parametrize("kind", ["nmea", "binary"])
def test_the_rigs_readers_count_damaged_streams_as_the_page_does(kind):
    rng = random.Random(kind)
    for _ in range(120):
        ests = messages_for_streams(rng, rng.randrange(1, 12))
        encode = encode_nmea if kind == "nmea" else encode_binary
        stream = damaged_stream(rng, [encode(est) for est in ests], kind)
        page: Any = PageNmeaReader() if kind == "nmea" else PageBinaryReader()
        rig: Any = NmeaLineReader() if kind == "nmea" else BinaryFrameReader()
        got_page, got_rig = page.feed(stream), []
        i = 0
        while i < len(stream):  # the rig's reader in chunks of any size
            step = rng.randrange(1, 100)
            got_rig += rig.feed(stream[i:i + step])
            i += step
        assert got_rig == got_page
        assert rig.counts == page.counts, stream
        # every undamaged message gets through: the last one always is
        assert got_page and got_page[-1]["seq"] == (ests[-1].seq % (100_000 if kind == "nmea" else 2**32))


def test_the_page_readers_edge_cases_agree_with_the_rigs():
    line = encode_nmea(estimate())
    frame = encode_binary(estimate())
    nmea_streams = [
        b"tail of a sentence\r\n" + line,
        line[:30] + line,  # cut short by the next `$`
        b"$" + b"x" * 81 + b"\r\n" + line,  # 82 bytes after a `$` with no LF
        b"$" + b"x" * 79 + b"\r\n" + line,  # a line of 82 bytes: not garbage, malformed
        b"$" + b"x" * 80 + b"\n" + line,  # LF only: 82 bytes
        b"$" + b"x" * 81 + b"\n" + line,  # 83 bytes
        line[:-2] + b"\n" + line,  # LF only
        line[:-2] + b"\r\r\n" + line,
        b"\r\n\r\n\n" + line,
    ]
    for stream in nmea_streams:
        page, rig = PageNmeaReader(), NmeaLineReader()
        assert rig.feed(stream) == page.feed(stream)
        assert rig.counts == page.counts, stream
    run = bytes(range(1, 256)) + b"\x01"
    binary_streams = [
        frame[1:],  # started mid-stream: only the trailing delimiter left... and the frame
        frame[-1:] + frame,
        frame[20:] + frame,  # the bytes before the first 0x00 are a frame
        frame[:30] + frame,  # cut short by a write timeout
        b"\x00" + run + b"\x00" + frame,  # 256 bytes between delimiters: decoded, not garbage
        b"\x00" + run + b"\x01" + b"\x00" + frame,  # 257: garbage
        b"\x00" + run * 3 + b"\x00" + frame,
        b"\x00\x00\x00" + frame + frame,
        b"\x00\x01\x00\x02\x05\x00\x03\x01\x02\x00" + frame,  # fewer than 4 bytes, or not COBS
    ]
    for stream in binary_streams:
        page_b, rig_b = PageBinaryReader(), BinaryFrameReader()
        assert rig_b.feed(stream) == page_b.feed(stream)
        assert rig_b.counts == page_b.counts, stream


def test_a_third_party_nmea_parser_reads_the_rigs_sentences():
    pynmea2 = pytest.importorskip("pynmea2", reason="the dev extra's pynmea2 is the third-party NMEA parser")
    rng = random.Random(3)
    for est in [*CASES.values(), *(random_estimate(rng) for _ in range(100))]:
        line = encode_nmea(est)
        msg = pynmea2.parse(line.decode("ascii"), check=True)  # raises on a checksum mismatch
        assert isinstance(msg, pynmea2.ProprietarySentence) and msg.manufacturer == "SRG"
        assert msg.data == ["S", *line[7:-5].decode("ascii").split(",")]
        page = page_decode_nmea(line)
        assert int(msg.data[3]) == page["seq"] and float(msg.data[4]) == page["azimuth_deg"]
    assert pynmea2.parse(PAGE_NMEA_EXAMPLES[0].decode("ascii"), check=True).data[:5] == [
        "S", "1", "130225.96", "1234", "123.4"]
    with pytest.raises(pynmea2.ChecksumError):
        pynmea2.parse(PAGE_NMEA_EXAMPLES[0].decode("ascii").replace("*5D", "*5E"), check=True)


BAD_FIELDS: dict[int, list[float]] = {  # payload field index: values outside the page's table
    3: [0x74, 0x00, 0x41], 5: [math.nan, math.inf], 7: [math.nan, 1.01, -1.5], 9: [math.nan, math.inf],
    10: [360.0, -0.001, math.nan], 11: [90.01, -90.5], 12: [180.0, -180.01], 13: [360.0, -1.0],
    14: [-0.01, 180.01, math.nan],
}


def test_a_frame_with_a_field_outside_the_table_is_malformed_for_both_decoders():
    fields = list(PAYLOAD.unpack(cobs_decode(encode_binary(estimate())[1:-1])[:-2]))
    for index, values in BAD_FIELDS.items():
        for value in values:
            bad = reframe(PAYLOAD.pack(*fields[:index], value, *fields[index + 1:]))
            with pytest.raises(Dropped, match="malformed"):
                page_decode_binary(bad)
            with pytest.raises(ValueError):
                decode_binary(bad)
            reader = BinaryFrameReader()
            assert reader.feed(bad) == [] and reader.counts["malformed"] == 1, (index, value)


def mutated(rng: random.Random, data: bytes, alphabet: bytes) -> bytearray:
    out = bytearray(data)
    for _ in range(rng.randrange(1, 4)):
        op, j = rng.random(), rng.randrange(len(out))
        if op < 0.5:
            out[j] = rng.choice(alphabet)
        elif op < 0.75:
            del out[j]
        else:
            out.insert(j, rng.choice(alphabet))
    return out


def test_sentences_damaged_under_a_good_checksum_are_judged_as_the_page_says():
    # Another encoder's sentences, or noise the checksum missed: each field against the table.
    rng = random.Random(1)
    for _ in range(3000):
        body = mutated(rng, encode_nmea(random_estimate(rng))[1:-5], b"0123456789.-,+ ABEFMRTVZ*$\x7f\x80\x01e")
        line = b"$" + body + b"*" + (rng.choice(["%02X", "%02x"]) % xor_checksum(bytes(body))).encode()
        line += rng.choice([b"\r\n", b"\n"])
        page, rig = PageNmeaReader(), NmeaLineReader()
        assert rig.feed(line) == page.feed(line)
        assert rig.counts == page.counts, line


def test_frames_damaged_under_a_good_crc_are_judged_as_the_page_says():
    rng = random.Random(2)
    for _ in range(3000):
        payload = cobs_decode(encode_binary(random_estimate(rng))[1:-1])[:-2]
        frame = reframe(bytes(mutated(rng, payload, bytes(range(256)))))
        page, rig = PageBinaryReader(), BinaryFrameReader()
        assert rig.feed(frame) == page.feed(frame)
        assert rig.counts == page.counts, frame.hex(" ")
