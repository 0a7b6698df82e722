"""The wire formats (rig/protocol.py, docs/protocol.md): golden bytes, round trips, budgets, framers.

Wire tolerances (kept here until they move to tests/tolerances.py): NMEA fields are rounded to
their last digit, so a round trip is exact to half of it; binary floats are float32.
"""

from __future__ import annotations

import math
import re
import struct
from pathlib import Path

import numpy as np
import pytest

from rig.errors import ProtocolError, ValidationError
from rig.geometry import enu_from_az_el
from rig.protocol import (
    BINARY_FRAME_LEN,
    BINARY_PAYLOAD_LEN,
    FLAG_ABOVE_TRAINED,
    FLAG_HAS_UTC,
    FLAG_PARTIAL_WINDOW,
    FLAG_SPREAD_HIGH,
    FLAG_VALID,
    NMEA_MAX_LEN,
    BinaryFrameReader,
    NmeaLineReader,
    StatusRule,
    cobs_decode,
    cobs_encode,
    crc16_ccitt_false,
    decode_binary,
    decode_nmea,
    encode_binary,
    encode_nmea,
    nmea_checksum,
    nmea_sentence,
)
from rig.types import HeadingRef, SunEstimate

NMEA_DEG = 0.05 + 1e-9  # half of the 0.1 deg last digit
NMEA_UNIT = 0.0005 + 1e-9  # half of the 0.001 last digit
F32_DEG = 1e-4  # float32 of an angle below 360 deg: 2^-24 * 360 ~ 2e-5
F32_UNIT = 1e-7
UTC_2011 = 1317042145964389000  # 2011-09-26T13:02:25.964389Z (a KITTI drive)


def make_estimate(
    az_deg: float,
    el_deg: float,
    heading_deg: float = 0.0,
    *,
    spread_deg: float = 5.0,
    n_frames: int = 8,
    seq: int = 1,
    utc_ns: int | None = UTC_2011,
    heading_ref: str = "true",
    t_mono_s: float = 100.0,
) -> SunEstimate:
    return SunEstimate(
        t_mono_s=t_mono_s,
        seq=seq,
        sun_enu=enu_from_az_el(math.radians(az_deg), math.radians(el_deg)),
        heading_rad=math.radians(heading_deg),
        heading_ref=heading_ref,
        spread_rad=math.radians(spread_deg),
        n_frames=n_frames,
        n_tokens=4 * n_frames,
        aggregator="transformer",
        utc_ns=utc_ns,
    )


def random_estimates(n: int, seed: int = 0) -> list[SunEstimate]:
    """Seeded estimates over every field's whole range, UTC and heading references mixed."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        out.append(
            make_estimate(
                az_deg=rng.uniform(0, 360),
                el_deg=math.degrees(math.asin(rng.uniform(-1, 1))),
                heading_deg=rng.uniform(0, 360),
                spread_deg=rng.uniform(0, 180),
                n_frames=int(rng.integers(1, 200)),
                seq=int(rng.integers(0, 2**40)),
                utc_ns=int(rng.integers(0, 4 * 10**18)) if rng.random() < 0.7 else None,
                heading_ref=str(rng.choice(["true", "magnetic", "relative"])),
                t_mono_s=float(rng.uniform(0, 1e6)),
            )
        )
    return out


def worst_case_estimates() -> list[SunEstimate]:
    """Every NMEA field at its widest at once: 3-digit azimuth, all of x, y, z, elevation and
    bearing negative, 3-digit bearing and spread, 5-digit seq, 2-digit frames, a time."""
    wide = dict(spread_deg=179.96, n_frames=120, seq=99999, utc_ns=UTC_2011 + 10**18)
    return [
        make_estimate(200.0, -45.0, heading_deg=350.0, heading_ref="relative", **wide),
        make_estimate(225.0, -89.94, heading_deg=45.04, **wide),  # bearing rounds to -180.0
        make_estimate(269.96, -10.0, heading_deg=90.0, **wide),  # vector (-0.985, -0.001, -0.174)
    ]


# --- checksums ------------------------------------------------------------------------------


def test_crc16_ccitt_false_check_value():
    # The catalogue's check value (CRC RevEng, CRC-16/IBM-3740 alias CCITT-FALSE).
    assert crc16_ccitt_false(b"123456789") == 0x29B1
    assert crc16_ccitt_false(b"") == 0xFFFF
    # Incremental use gives the same answer as one call.
    assert crc16_ccitt_false(b"6789", crc16_ccitt_false(b"12345")) == 0x29B1


def test_nmea_checksum_of_a_known_gga_sentence():
    # pynmea2's documentation example, checksum 6D.
    body = b"GPGGA,184353.07,1929.045,S,02410.506,E,1,04,2.6,100.00,M,-33.9,M,,0000"
    assert nmea_checksum(body) == 0x6D


# --- COBS -----------------------------------------------------------------------------------

COBS_VECTORS = [  # Wikipedia, "Consistent Overhead Byte Stuffing", encoding examples
    (b"", b"\x01"),
    (b"\x00", b"\x01\x01"),
    (b"\x00\x00", b"\x01\x01\x01"),
    (b"\x00\x11\x00", b"\x01\x02\x11\x01"),
    (b"\x11\x22\x00\x33", b"\x03\x11\x22\x02\x33"),
    (b"\x11\x22\x33\x44", b"\x05\x11\x22\x33\x44"),
    (b"\x11\x00\x00\x00", b"\x02\x11\x01\x01\x01"),
    (bytes(range(1, 255)), b"\xff" + bytes(range(1, 255))),
    (bytes(range(0, 255)), b"\x01\xff" + bytes(range(1, 255))),
    (bytes(range(1, 256)), b"\xff" + bytes(range(1, 255)) + b"\x02\xff"),
    (bytes(range(2, 256)) + b"\x00", b"\xff" + bytes(range(2, 256)) + b"\x01\x01"),
    (bytes(range(3, 256)) + b"\x00\x01", b"\xfe" + bytes(range(3, 256)) + b"\x02\x01"),
]


@pytest.mark.parametrize("raw, encoded", COBS_VECTORS, ids=range(len(COBS_VECTORS)))
def test_cobs_known_vectors(raw, encoded):
    assert cobs_encode(raw) == encoded
    assert cobs_decode(encoded) == raw


def test_cobs_round_trip_random_data_has_no_zero_and_bounded_overhead():
    rng = np.random.default_rng(1)
    for n in [0, 1, 2, 253, 254, 255, 256, 508, 509, 1000]:
        for zero_fraction in (0.0, 0.05, 0.5, 1.0):
            raw = rng.integers(1, 256, n, dtype=np.uint8)
            raw[rng.random(n) < zero_fraction] = 0
            raw = raw.tobytes()
            enc = cobs_encode(raw)
            assert 0 not in enc
            assert len(enc) <= len(raw) + 1 + len(raw) // 254
            assert cobs_decode(enc) == raw


@pytest.mark.parametrize("bad", [b"", b"\x03\x11", b"\x02\x00", b"\x03\x11\x00"])
def test_cobs_decode_refuses_bad_input(bad):
    with pytest.raises(ProtocolError) as info:
        cobs_decode(bad)
    assert info.value.reason == "framing"


# --- status ---------------------------------------------------------------------------------


def test_status_rule_flags():
    rule = StatusRule(full_window=8, max_spread_deg=30.0)
    assert rule.flags(make_estimate(100, 30)) == FLAG_VALID | FLAG_HAS_UTC
    assert rule.flags(make_estimate(100, 30, utc_ns=None)) == FLAG_VALID
    assert rule.flags(make_estimate(100, 30, n_frames=7)) == FLAG_PARTIAL_WINDOW | FLAG_HAS_UTC
    assert rule.flags(make_estimate(100, 30, spread_deg=30.5, utc_ns=None)) == FLAG_SPREAD_HIGH
    assert rule.flags(make_estimate(100, 30, spread_deg=30.0, n_frames=9, utc_ns=None)) == FLAG_VALID
    # A spread at the limit is still valid. 30 deg comes back from radians() as 29.999999999999996,
    # so the line above cannot tell; 45 deg comes back exactly 45.
    wide = StatusRule(full_window=8, max_spread_deg=45.0)
    assert wide.flags(make_estimate(100, 30, spread_deg=45.0, utc_ns=None)) == FLAG_VALID
    with pytest.raises(ValidationError, match="full_window"):
        StatusRule(full_window=0)
    with pytest.raises(ValidationError, match="max_spread_deg"):
        StatusRule(max_spread_deg=-1.0)


def test_status_rule_flags_a_sun_above_every_training_sun():
    # A model trained on suns up to 74.9 deg: its limit is 79.9 (the margin is 5 deg).
    rule = StatusRule.for_model(8, 74.9)
    assert rule.max_elevation_deg == pytest.approx(79.9)
    assert rule.flags(make_estimate(100, 79.8, utc_ns=None)) == FLAG_VALID
    assert rule.flags(make_estimate(100, 85.0, utc_ns=None)) == FLAG_ABOVE_TRAINED
    # With the other reasons, each bit says its own.
    assert rule.flags(make_estimate(100, 85.0, n_frames=3, spread_deg=40.0, utc_ns=None)) == (
        FLAG_ABOVE_TRAINED | FLAG_PARTIAL_WINDOW | FLAG_SPREAD_HIGH)
    got = decode_binary(encode_binary(make_estimate(100, 85.0), rule))
    assert got["above_trained"] and not got["valid"] and not got["spread_high"]
    assert decode_nmea(encode_nmea(make_estimate(100, 85.0), rule))["valid"] is False
    # Unknown training suns (an older contract): no elevation check; the limit never passes 90.
    assert StatusRule.for_model(8, None).max_elevation_deg == 90.0
    assert StatusRule.for_model(8, 88.0).max_elevation_deg == 90.0
    assert StatusRule().flags(make_estimate(100, 89.9, utc_ns=None)) == FLAG_VALID
    with pytest.raises(ValidationError, match="max_elevation_deg"):
        StatusRule(max_elevation_deg=91.0)


# --- NMEA -----------------------------------------------------------------------------------


def _hand_checksum(body: str) -> str:
    value = 0
    for ch in body:
        value ^= ord(ch)
    return f"{value:02X}"


def test_nmea_golden_sentence():
    est = make_estimate(123.4, 35.6, heading_deg=100.0, spread_deg=5.2, seq=1234)
    body = "PSRGS,1,130225.96,1234,123.4,35.6,0.679,-0.448,0.582,23.4,5.2,8,T,A"
    assert _hand_checksum(body) == "5D"  # the value docs/protocol.md shows
    assert encode_nmea(est) == f"${body}*5D\r\n".encode("ascii")


def test_nmea_golden_sentence_without_utc_partial_window_relative():
    est = make_estimate(10.0, 5.0, heading_deg=350.0, spread_deg=12.0, n_frames=3, seq=123456,
                        utc_ns=None, heading_ref="relative")
    body = "PSRGS,1,,23456,10.0,5.0,0.173,0.981,0.087,20.0,12.0,3,R,V"
    assert encode_nmea(est) == f"${body}*{_hand_checksum(body)}\r\n".encode("ascii")


def test_nmea_rounding_stays_in_range_and_never_prints_minus_zero():
    line = encode_nmea(make_estimate(359.96, 0.0001, heading_deg=179.98)).decode()
    fields = line.split("*")[0].split(",")  # $PSRGS, version, utc, seq, az, el, e, n, u, bearing, ...
    assert fields[4] == "0.0"  # azimuth 359.96 wraps to 0.0, never 360.0
    assert fields[5] == "0.0"
    assert fields[6:9] == ["-0.001", "1.000", "0.000"]  # up = 2e-6: no "-0.000" either way
    assert fields[9] == "-180.0"  # bearing 179.98 rounds to 180.0, which wraps into [-180, 180)
    line = encode_nmea(make_estimate(0.0, -89.97, heading_deg=0.0)).decode()
    assert line.split(",")[5] == "-90.0"


def test_nmea_status_judges_unrounded_values_so_a_field_at_a_threshold_can_read_either_way():
    # docs/protocol.md, status rule: a spread of 30.04 deg is sent as 30.0 and flagged.
    fields = encode_nmea(make_estimate(100, 30, spread_deg=30.04)).decode().split("*")[0].split(",")
    assert (fields[10], fields[13]) == ("30.0", "V")
    fields = encode_nmea(make_estimate(100, 30, spread_deg=29.96)).decode().split("*")[0].split(",")
    assert (fields[10], fields[13]) == ("30.0", "A")
    rule = StatusRule.for_model(8, 74.9)  # limit 79.9 deg
    assert encode_nmea(make_estimate(100, 79.94), rule).decode().split(",")[5] == "79.9"
    assert decode_nmea(encode_nmea(make_estimate(100, 79.94), rule))["valid"] is False


def test_exact_zenith_and_nadir_send_the_azimuth_of_atan2_of_zeros():
    # docs/protocol.md: no horizontal part, so the azimuth is 0.0, or 180.0 when north is -0.0.
    for enu, azimuth in (((0.0, 0.0, 1.0), 0.0), ((0.0, 0.0, -1.0), 0.0), ((0.0, -0.0, 1.0), 180.0)):
        est = SunEstimate(t_mono_s=1.0, seq=1, sun_enu=np.array(enu), heading_rad=0.0,
                          heading_ref=HeadingRef.TRUE, spread_rad=0.0, n_frames=8, n_tokens=1, aggregator="mean")
        assert decode_nmea(encode_nmea(est))["azimuth_deg"] == azimuth
        assert decode_binary(encode_binary(est))["azimuth_deg"] == azimuth
        assert decode_nmea(encode_nmea(est))["elevation_deg"] == math.copysign(90.0, enu[2])


def test_nmea_worst_case_is_exactly_82_characters():
    for est in worst_case_estimates():
        line = encode_nmea(est)
        assert len(line) == NMEA_MAX_LEN, line
        assert line.endswith(b"\r\n")


def test_nmea_random_estimates_fit_and_round_trip():
    rule = StatusRule()
    longest = 0
    for est in random_estimates(500, seed=2) + worst_case_estimates():
        line = encode_nmea(est, rule)
        longest = max(longest, len(line))
        assert len(line) <= NMEA_MAX_LEN and line.isascii()
        got = decode_nmea(line)
        az = math.degrees(est.azimuth_rad)
        assert abs((got["azimuth_deg"] - az + 180.0) % 360.0 - 180.0) <= NMEA_DEG
        assert got["elevation_deg"] == pytest.approx(math.degrees(est.elevation_rad), abs=NMEA_DEG)
        rb = math.degrees(est.relative_bearing_rad)
        assert abs((got["relative_bearing_deg"] - rb + 180.0) % 360.0 - 180.0) <= NMEA_DEG
        assert got["spread_deg"] == pytest.approx(math.degrees(est.spread_rad), abs=NMEA_DEG)
        np.testing.assert_allclose(got["sun_enu"], est.sun_enu, atol=NMEA_UNIT)
        assert got["seq"] == est.seq % 100_000
        assert got["n_frames"] == min(est.n_frames, 99)
        assert got["heading_ref"] == est.heading_ref.value
        assert got["valid"] == bool(rule.flags(est) & FLAG_VALID)
        if est.utc_ns is None:
            assert got["utc_s_of_day"] is None
        else:
            s_of_day = (est.utc_ns % 86_400_000_000_000) / 1e9
            assert 0.0 <= s_of_day - got["utc_s_of_day"] < 0.01 + 1e-6  # truncated to 1/100 s
    assert longest == NMEA_MAX_LEN  # the worst cases reach the budget


def _resigned(body: str) -> bytes:
    return nmea_sentence(body.split(",")[1:], address=body.split(",")[0])


@pytest.mark.parametrize(
    "line, reason",
    [
        (b"$PSRGS,1,,1,10.0,5.0,0.173,0.981,0.087,20.0,12.0,3,R,V*00\r\n", "checksum"),
        (b"PSRGS,1,,1,10.0*11\r\n", "framing"),
        (b"$PSRGS,1,,1,10.0\r\n", "framing"),
        (b"$GPGGA,184353.07,1929.045,S,02410.506,E,1,04,2.6,100.00,M,-33.9,M,,0000*6D\r\n", "foreign"),
        (_resigned("PSRGS,2,,1,10.0,5.0"), "version"),
        (_resigned("PSRGS,1,,1,10.0,5.0"), "framing"),
        (_resigned("PSRGS,1,,1,400.0,5.0,0.173,0.981,0.087,20.0,12.0,3,R,V"), "field"),
        (_resigned("PSRGS,1,,1,1e2,5.0,0.173,0.981,0.087,20.0,12.0,3,R,V"), "field"),
        (_resigned("PSRGS,1,256199.00,1,10.0,5.0,0.173,0.981,0.087,20.0,12.0,3,R,V"), "field"),
        (_resigned("PSRGS,1,240000.00,1,10.0,5.0,0.173,0.981,0.087,20.0,12.0,3,R,V"), "field"),  # hour 24 alone
        (_resigned("PSRGS,1,,1,10.0,5.0,0.173,0.981,0.087,20.0,12.0,3,X,V"), "field"),
        (_resigned("PSRGS,1,,1,10.0,5.0,0.173,0.981,0.087,20.0,12.0,3,R,Q"), "field"),
    ],
)
def test_decode_nmea_refuses_with_a_reason(line, reason):
    with pytest.raises(ProtocolError) as info:
        decode_nmea(line)
    assert info.value.reason == reason


# --- binary ---------------------------------------------------------------------------------

GOLDEN_FRAME_HEX = (
    "000701010354d2040101010101010123294088f26c90da124712d9c62d3f582be5be0306153f"
    "cdccf64266660e423333bb410108c8426666a64008022003646700"
)


def test_binary_golden_frame():
    est = make_estimate(123.4, 35.6, heading_deg=100.0, spread_deg=5.2, seq=1234, t_mono_s=12.5)
    frame = encode_binary(est)
    assert frame.hex() == GOLDEN_FRAME_HEX
    assert len(frame) == BINARY_FRAME_LEN == 65
    assert frame[0] == 0 and frame[-1] == 0 and 0 not in frame[1:-1]
    raw = cobs_decode(frame[1:-1])
    payload, crc = raw[:-2], raw[-2:]
    assert len(payload) == BINARY_PAYLOAD_LEN == 60
    assert struct.unpack("<H", crc)[0] == crc16_ccitt_false(payload)
    assert payload[:4] == bytes([1, 1, FLAG_VALID | FLAG_HAS_UTC, ord("T")])
    assert struct.unpack_from("<I", payload, 4)[0] == 1234
    assert struct.unpack_from("<d", payload, 8)[0] == 12.5
    assert struct.unpack_from("<q", payload, 16)[0] == UTC_2011


def test_binary_round_trip_within_float32():
    rule = StatusRule()
    for est in random_estimates(300, seed=3) + worst_case_estimates():
        got = decode_binary(encode_binary(est, rule))
        assert got["version"] == 1 and got["msg_type"] == 1
        assert got["seq"] == est.seq % 2**32
        assert got["t_mono_s"] == est.t_mono_s
        assert got["utc_ns"] == est.utc_ns
        np.testing.assert_allclose(got["sun_enu"], est.sun_enu, atol=F32_UNIT)
        for key, rad in (
            ("azimuth_deg", est.azimuth_rad),
            ("elevation_deg", est.elevation_rad),
            ("relative_bearing_deg", est.relative_bearing_rad),
            ("heading_deg", est.heading_rad),
            ("spread_deg", est.spread_rad),
        ):
            assert got[key] == pytest.approx(math.degrees(rad), abs=F32_DEG), key
        assert got["n_frames"] == est.n_frames and got["n_tokens"] == est.n_tokens
        assert got["heading_ref"] == est.heading_ref.value
        assert got["flags"] == rule.flags(est)
        assert got["valid"] == bool(rule.flags(est) & FLAG_VALID)


def test_binary_flags_carry_a_relative_headings_zero_counter_outside_the_status():
    # Bits 5-6 count a relative heading's zeros modulo 4: a controller that sees them change knows
    # the azimuth, vector and heading are in a new frame from there on (the NMEA sentence has no
    # field for it). They are not part of the status: valid or not, the counter is there.
    import dataclasses

    rule = StatusRule()
    base = make_estimate(123.4, 35.6, heading_ref="relative")
    for epoch in range(9):
        est = dataclasses.replace(base, heading_epoch=epoch)
        got = decode_binary(encode_binary(est, rule))
        assert got["heading_zero"] == epoch % 4 and got["flags"] & 0x60 == (epoch % 4) << 5
        assert got["flags"] & 0x1F == rule.flags(est) and got["valid"] and got["flags"] & 0x80 == 0
    assert decode_binary(encode_binary(make_estimate(123.4, 35.6)))["heading_zero"] == 0


def _frame(payload: bytes) -> bytes:
    return b"\x00" + cobs_encode(payload + struct.pack("<H", crc16_ccitt_false(payload))) + b"\x00"


def test_decode_binary_refuses_with_a_reason():
    good = encode_binary(make_estimate(50, 20))
    raw = bytearray(cobs_decode(good[1:-1]))
    payload = bytes(raw[:-2])
    flipped = bytearray(raw)
    flipped[20] ^= 0x40
    cases = [
        (b"\x00" + cobs_encode(bytes(flipped)) + b"\x00", "checksum"),
        (_frame(bytes([2]) + payload[1:]), "version"),
        (_frame(payload[:1] + bytes([7]) + payload[2:]), "version"),
        (_frame(payload + b"\x00"), "framing"),
        (_frame(b"\x01"), "framing"),
        (good[:-1] + b"\x05\x00", "framing"),
        (_frame(payload[:3] + b"X" + payload[4:]), "field"),
    ]
    for frame, reason in cases:
        with pytest.raises(ProtocolError) as info:
            decode_binary(frame)
        assert info.value.reason == reason, frame.hex()


def _payload_with(**fields) -> bytes:
    """A version-1 payload of a good estimate with some fields replaced (by BINARY_STRUCT name)."""
    names = ("version", "msg_type", "flags", "ref", "seq", "t_mono_s", "utc_ns", "east", "north", "up",
             "azimuth_deg", "elevation_deg", "relative_bearing_deg", "heading_deg", "spread_deg",
             "n_frames", "n_tokens")
    raw = cobs_decode(encode_binary(make_estimate(50, 20))[1:-1])[:-2]
    values = dict(zip(names, struct.unpack("<BBBBIdq8fHH", raw), strict=True))
    values.update(fields)
    return struct.pack("<BBBBIdq8fHH", *(values[name] for name in names))


@pytest.mark.parametrize(
    "field, value",
    [("azimuth_deg", math.nan), ("azimuth_deg", 360.0), ("azimuth_deg", -0.5), ("elevation_deg", 90.5),
     ("elevation_deg", -math.inf), ("relative_bearing_deg", 180.0), ("relative_bearing_deg", -180.5),
     ("heading_deg", 360.0), ("heading_deg", math.nan), ("spread_deg", -0.5), ("spread_deg", 180.5),
     ("spread_deg", math.inf), ("east", 1.5), ("north", math.nan), ("up", -1.5), ("t_mono_s", math.inf),
     ("t_mono_s", math.nan)],
)
def test_decode_binary_refuses_a_field_outside_its_documented_range(field, value):
    # The CRC passes (another encoder, or noise the CRC misses): the values the page promises never
    # reach the controller as NaN, inf or out of range; the frame is a bad field (counted malformed).
    frame = _frame(_payload_with(**{field: value}))
    with pytest.raises(ProtocolError, match=field) as info:
        decode_binary(frame)
    assert info.value.reason == "field"
    reader = BinaryFrameReader()
    assert reader.feed(frame) == [] and reader.counts["malformed"] == 1


def test_decode_binary_accepts_each_range_end():
    for fields in (dict(azimuth_deg=0.0, heading_deg=0.0, relative_bearing_deg=-180.0, spread_deg=0.0,
                        elevation_deg=-90.0, east=-1.0, north=0.0, up=0.0),
                   dict(azimuth_deg=float(np.nextafter(np.float32(360), np.float32(0))), elevation_deg=90.0,
                        relative_bearing_deg=float(np.nextafter(np.float32(180), np.float32(0))),
                        spread_deg=180.0, east=0.0, north=0.0, up=1.0)):
        got = decode_binary(_frame(_payload_with(**fields)))
        assert got["azimuth_deg"] == fields["azimuth_deg"] and got["spread_deg"] == fields["spread_deg"]


def test_the_examples_on_the_protocol_page_are_what_the_encoders_send():
    # A controller's author copies these: each sentence and the frame must be the encoders' bytes.
    page = (Path(__file__).resolve().parents[1] / "docs" / "protocol.md").read_text()
    sentences = re.findall(r"^\$PSRGS,[^\n]*\*[0-9A-F]{2}$", page, flags=re.MULTILINE)
    golden = make_estimate(123.4, 35.6, heading_deg=100.0, spread_deg=5.2, seq=1234)
    partial = make_estimate(10.0, 5.0, heading_deg=350.0, spread_deg=12.0, n_frames=3, seq=123456,
                            utc_ns=None, heading_ref="relative")
    assert [s.encode() + b"\r\n" for s in sentences] == [
        encode_nmea(golden), encode_nmea(partial), encode_nmea(worst_case_estimates()[0])]
    assert len(encode_nmea(worst_case_estimates()[0])) == NMEA_MAX_LEN
    block = page.split("(CRC 0x6764):", 1)[1].split("```")[1]
    assert bytes.fromhex(block) == bytes.fromhex(GOLDEN_FRAME_HEX)


# --- stream readers: chunked input, leading garbage, truncated messages ----------------------


def _chunks(data: bytes, rng: np.random.Generator) -> list[bytes]:
    cuts = np.sort(rng.integers(0, len(data), 40))
    return [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)], strict=True)]


@pytest.mark.parametrize("fmt", ["nmea", "binary"])
def test_reader_chunked_input_gives_the_same_messages(fmt):
    encode, reader_type = (encode_nmea, NmeaLineReader) if fmt == "nmea" else (encode_binary, BinaryFrameReader)
    estimates = random_estimates(30, seed=4)
    stream = b"".join(encode(e) for e in estimates)
    whole = reader_type().feed(stream)
    assert [m["seq"] for m in whole] == [e.seq % (100_000 if fmt == "nmea" else 2**32) for e in estimates]
    for chunking in ("bytewise", "random"):
        reader = reader_type()
        pieces = [stream[i : i + 1] for i in range(len(stream))] if chunking == "bytewise" else (
            _chunks(stream, np.random.default_rng(5))
        )
        got = [m for piece in pieces for m in reader.feed(piece)]
        assert got == whole
        assert reader.counts["messages"] == len(estimates)
        assert sum(v for k, v in reader.counts.items() if k != "messages") == 0


def test_nmea_reader_leading_garbage_and_foreign_sentences():
    estimates = random_estimates(5, seed=6)
    gga = b"$GPGGA,184353.07,1929.045,S,02410.506,E,1,04,2.6,100.00,M,-33.9,M,,0000*6D\r\n"
    garbage = bytes(np.random.default_rng(7).integers(0, 256, 500, dtype=np.uint8)).replace(b"$", b"#")
    garbage = garbage.replace(b"\r", b"r").replace(b"\n", b"n")
    stream = garbage + b"".join(encode_nmea(e) + gga for e in estimates)
    reader = NmeaLineReader()
    got = reader.feed(stream)
    assert [m["seq"] for m in got] == [e.seq % 100_000 for e in estimates]
    assert reader.counts["garbage_bytes"] == len(garbage)
    assert reader.counts["foreign"] == len(estimates)
    assert reader.counts["bad_checksum"] == reader.counts["malformed"] == 0


def test_nmea_reader_truncated_corrupt_and_overlong_lines():
    a, b, c = (encode_nmea(e) for e in random_estimates(3, seed=8))
    corrupt = bytearray(b)
    corrupt[20] ^= 0x01  # one flipped bit: the checksum catches it
    overlong = b"$" + b"X" * 100 + b"\r\n"
    reader = NmeaLineReader()
    got = reader.feed(a[:40] + b + bytes(corrupt) + overlong + a[:30] + b"\r\n" + c)
    assert [m["seq"] for m in got] == [decode_nmea(x)["seq"] for x in (b, c)]
    assert reader.counts["bad_checksum"] == 1
    assert reader.counts["garbage_bytes"] == 40 + 101  # the cut sentence and the over-long line
    assert reader.counts["malformed"] == 1  # the second cut sentence ends with a line end: no *HH
    # A sentence cut at the end of the stream waits, and completes when the rest arrives.
    reader = NmeaLineReader()
    assert reader.feed(c[:-5]) == []
    assert [m["seq"] for m in reader.feed(c[-5:])] == [decode_nmea(c)["seq"]]


def test_binary_reader_leading_garbage():
    estimates = random_estimates(5, seed=9)
    garbage = bytes(np.random.default_rng(10).integers(0, 256, 700, dtype=np.uint8))
    reader = BinaryFrameReader()
    got = reader.feed(garbage + b"".join(encode_binary(e) for e in estimates))
    assert [m["seq"] for m in got] == [e.seq % 2**32 for e in estimates]
    assert reader.counts["messages"] == len(estimates)
    assert reader.counts["bad_crc"] + reader.counts["malformed"] + reader.counts["garbage_bytes"] > 0


def test_binary_reader_truncated_and_overlong_frames():
    a, b, c = (encode_binary(e) for e in random_estimates(3, seed=11))
    overlong = b"\x00" + b"\x07" * 1000
    reader = BinaryFrameReader()
    got = reader.feed(a[:30] + b + overlong + c)
    # The leading delimiter of b ends the truncated a; the over-long run is dropped up to c's.
    assert [m["seq"] for m in got] == [decode_binary(x)["seq"] for x in (b, c)]
    assert reader.counts["malformed"] + reader.counts["bad_crc"] == 1
    assert reader.counts["garbage_bytes"] == 1000
    # Cut at the end of the stream: it waits for the rest.
    reader = BinaryFrameReader()
    assert reader.feed(c[:-10]) == []
    assert len(reader.feed(c[-10:])) == 1


def test_binary_leading_delimiter_saves_the_frame_after_a_truncated_one():
    a, b = (encode_binary(e) for e in random_estimates(2, seed=12))
    with_lead = BinaryFrameReader().feed(a[:30] + b)
    without_lead = BinaryFrameReader().feed(a[:30] + b[1:])
    assert len(with_lead) == 1 and len(without_lead) == 0


# --- documented boundaries: each limit on both sides ------------------------------------------


def test_status_rule_limits_are_inclusive():
    # full_window >= 1: a one-frame window is a legal rule, and one frame fills it.
    assert StatusRule(full_window=1).flags(make_estimate(100, 30, n_frames=1, utc_ns=None)) == FLAG_VALID
    # elevation <= max_elevation_deg is valid; 90 deg and 45 deg come back from radians() exactly.
    assert StatusRule().flags(make_estimate(100, 90.0, utc_ns=None)) == FLAG_VALID
    rule = StatusRule(max_elevation_deg=45.0)
    assert rule.flags(make_estimate(100, 45.0, utc_ns=None)) == FLAG_VALID
    assert rule.flags(make_estimate(100, 45.1, utc_ns=None)) == FLAG_ABOVE_TRAINED
    # The thresholds' own ranges, [0, 180] and [0, 90], include their ends.
    for ok in (dict(max_spread_deg=0.0), dict(max_spread_deg=180.0), dict(max_elevation_deg=0.0)):
        StatusRule(**ok)
    with pytest.raises(ValidationError, match="max_spread_deg"):
        StatusRule(max_spread_deg=180.5)
    with pytest.raises(ValidationError, match="max_elevation_deg"):
        StatusRule(max_elevation_deg=-0.5)


def test_nmea_spread_at_both_ends_of_its_range():
    fields = encode_nmea(make_estimate(100, 30, spread_deg=0.0)).decode().split("*")[0].split(",")
    assert fields[10] == "0.0"
    fields = encode_nmea(make_estimate(100, 30, spread_deg=180.0)).decode().split("*")[0].split(",")
    assert fields[10] == "180.0"


_V1_FIELDS = "1,,1,10.0,5.0,0.173,0.981,0.087,20.0,12.0,3,R,V".split(",")
_V1_INDEX = {"utc": 1, "seq": 2, "el": 4, "e": 5, "n": 6, "u": 7, "brg": 8, "spread": 9, "frames": 10}


def _v1_with(name: str, text: str) -> bytes:
    fields = list(_V1_FIELDS)
    fields[_V1_INDEX[name]] = text
    return nmea_sentence(fields)


@pytest.mark.parametrize(
    "name, text",
    [("utc", "125900.00"), ("utc", "235960.99"), ("el", "90.0"), ("el", "-90.0"),
     ("e", "1.000"), ("e", "-1.000"), ("n", "1.000"), ("n", "-1.000"), ("u", "1.000"), ("u", "-1.000"),
     ("brg", "179.9"), ("brg", "-180.0"), ("spread", "180.0"), ("spread", "0.0"), ("frames", "1"),
     ("frames", "99"), ("seq", "0"), ("seq", "99999")],
)
def test_decode_nmea_accepts_each_range_end(name, text):
    assert decode_nmea(_v1_with(name, text))  # a dict, no ProtocolError


@pytest.mark.parametrize(
    "name, text",
    [("utc", "126000.00"), ("utc", "235961.00"), ("el", "90.1"), ("el", "-90.1"),
     ("e", "1.001"), ("e", "-1.001"), ("n", "1.001"), ("n", "-1.001"), ("u", "1.001"), ("u", "-1.001"),
     ("brg", "180.0"), ("brg", "-180.1"), ("spread", "180.1"), ("frames", "0"), ("frames", "100"),
     ("frames", "07"), ("seq", "007"), ("seq", "100000")],
)
def test_decode_nmea_refuses_one_step_past_each_range_end(name, text):
    with pytest.raises(ProtocolError) as info:
        decode_nmea(_v1_with(name, text))
    assert info.value.reason == "field"


def test_decode_nmea_leap_second_and_version_field_edges():
    got = decode_nmea(_v1_with("utc", "235960.99"))
    assert got["utc_s_of_day"] == pytest.approx(23 * 3600 + 59 * 60 + 60.99)
    # No version field at all: a version error (reported as none), not a crash.
    with pytest.raises(ProtocolError, match="'none'") as info:
        decode_nmea(nmea_sentence([]))
    assert info.value.reason == "version"
    # Version 1 with nothing after it: our version, wrong field count.
    with pytest.raises(ProtocolError) as info:
        decode_nmea(nmea_sentence(["1"]))
    assert info.value.reason == "framing"
    # A later version, however short, says which version it found.
    with pytest.raises(ProtocolError, match="'2'") as info:
        decode_nmea(nmea_sentence(["2"]))
    assert info.value.reason == "version"


def test_decode_binary_four_bytes_is_the_shortest_frame():
    # 2 payload bytes + CRC: a later version passes the CRC and counts as a version, not malformed.
    with pytest.raises(ProtocolError) as info:
        decode_binary(_frame(bytes([2, 1])))
    assert info.value.reason == "version"
    with pytest.raises(ProtocolError) as info:  # 3 bytes: too short for a header and CRC
        decode_binary(_frame(bytes([2])))
    assert info.value.reason == "framing"


def test_binary_and_jsonl_angles_stay_below_the_top_of_their_ranges():
    # Within 2e-5 deg of the wrap a float32 field rounds onto 360.0 or +180.0, and a sun with a
    # vanishing west component once gave an azimuth of exactly 2 pi: both are sent as the bottom.
    est = make_estimate(359.99999, 10.0, heading_deg=359.99999)
    got = decode_binary(encode_binary(est))
    assert got["azimuth_deg"] == 0.0 and got["heading_deg"] == 0.0
    est = make_estimate(179.999999, 10.0, heading_deg=0.0)
    assert decode_binary(encode_binary(est))["relative_bearing_deg"] == -180.0
    due_north = SunEstimate(
        t_mono_s=1.0, seq=1, sun_enu=np.array([-1e-17, 1.0, 0.0]), heading_rad=0.0, heading_ref="true",
        spread_rad=0.0, n_frames=1, n_tokens=1, aggregator="mean",
    )
    assert due_north.to_json_dict()["azimuth_deg"] == 0.0
    assert decode_binary(encode_binary(due_north))["azimuth_deg"] == 0.0


def test_binary_payload_utc_zero_and_counts_clamped_to_u16():
    no_utc = cobs_decode(encode_binary(make_estimate(100, 30, utc_ns=None))[1:-1])
    assert no_utc[2] & FLAG_HAS_UTC == 0
    assert struct.unpack_from("<q", no_utc, 16)[0] == 0  # 0 when HAS_UTC is clear
    base = make_estimate(100, 30)
    for n_frames, n_tokens, expected in ((65535, 65535, (65535, 65535)), (65536, 10**6, (65535, 65535)),
                                         (65534, 3, (65534, 3))):
        est = SunEstimate(t_mono_s=1.0, seq=1, sun_enu=base.sun_enu, heading_rad=0.0, heading_ref="true",
                          spread_rad=0.1, n_frames=n_frames, n_tokens=n_tokens, aggregator="mean")
        got = decode_binary(encode_binary(est))
        assert (got["n_frames"], got["n_tokens"]) == expected


def test_nmea_reader_counts_garbage_without_any_sentence_start():
    reader = NmeaLineReader()
    assert reader.feed(b"abc\r\nxyz") == []
    assert reader.counts["garbage_bytes"] == 6  # CR and LF are never garbage
    # A lone '$' right before a sentence is a cut sentence of one byte.
    line = encode_nmea(make_estimate(100, 30, seq=77))
    got = reader.feed(b"$" + line)
    assert [m["seq"] for m in got] == [77]
    assert reader.counts["garbage_bytes"] == 7 and reader.counts["malformed"] == 0


def test_nmea_reader_drops_82_bytes_without_a_line_end_at_once():
    reader = NmeaLineReader()
    reader.feed(b"$" + b"X" * 80)  # 81 bytes: a sentence may still end with its LF
    assert reader.counts["garbage_bytes"] == 0
    reader.feed(b"X")  # 82 bytes and no LF: no valid sentence can be this
    assert reader.counts["garbage_bytes"] == 82
    line = encode_nmea(make_estimate(100, 30, seq=5))
    assert [m["seq"] for m in reader.feed(line)] == [5]
    assert reader.counts["garbage_bytes"] == 82


def test_binary_reader_run_limit_is_256_bytes():
    # Exactly 256 bytes without a delimiter are kept and judged as a frame (0xFF blocks cut short).
    reader = BinaryFrameReader()
    reader.feed(b"\xff" * 256)
    assert reader.counts["garbage_bytes"] == 0
    reader.feed(b"\x00")
    assert reader.counts["malformed"] == 1 and reader.counts["garbage_bytes"] == 0
    # 257 bytes are a run of more than 256: garbage at once, the rest dropped up to the next 0x00.
    reader = BinaryFrameReader()
    reader.feed(b"\xff" * 257)
    assert reader.counts["garbage_bytes"] == 257
    reader.feed(b"\xff" * 3 + encode_binary(make_estimate(100, 30, seq=9)))
    assert reader.counts["garbage_bytes"] == 260 and reader.counts["malformed"] == 0
    assert reader.counts["messages"] == 1


def test_binary_reader_started_mid_frame_counts_the_tail_once():
    a, b = (encode_binary(e) for e in random_estimates(2, seed=13))
    reader = BinaryFrameReader()
    assert len(reader.feed(a[1:])) == 1  # a frame without its leading delimiter still decodes
    reader = BinaryFrameReader()
    got = reader.feed(a[40:] + b)
    assert len(got) == 1
    assert reader.counts["malformed"] + reader.counts["bad_crc"] == 1
    assert reader.counts["garbage_bytes"] == 0


def test_nmea_vector_components_clamp_to_unit_range():
    # SunEstimate accepts a norm of 1 +- 0.001, so a component may round to 1.001: it is sent as 1.000,
    # inside the documented -1.000..1.000, and the decoder accepts the sentence.
    base = make_estimate(100, 30)
    for enu, expected in (((0.0, 0.0, 1.0009), ["0.000", "0.000", "1.000"]),
                          ((0.0, -1.0009, 0.0), ["0.000", "-1.000", "0.000"]),
                          ((-1.0009, 0.0, 0.0), ["-1.000", "0.000", "0.000"])):
        est = SunEstimate(t_mono_s=1.0, seq=1, sun_enu=enu, heading_rad=0.0, heading_ref="true",
                          spread_rad=base.spread_rad, n_frames=8, n_tokens=32, aggregator="mean")
        line = encode_nmea(est)
        assert line.decode().split(",")[6:9] == expected
        assert decode_nmea(line)["sun_enu"] == tuple(float(x) for x in expected)


def test_nmea_reader_lf_only_line_ends_are_not_garbage():
    # `sunrig demo` prints sentences with LF only; the reader takes both line ends.
    estimates = random_estimates(4, seed=14)
    stream = b"".join(encode_nmea(e)[:-2] + b"\n" for e in estimates)
    reader = NmeaLineReader()
    assert [m["seq"] for m in reader.feed(stream)] == [e.seq % 100_000 for e in estimates]
    assert reader.counts["garbage_bytes"] == 0 and reader.counts["messages"] == len(estimates)
