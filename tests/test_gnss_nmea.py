"""NMEA 0183 heading / fix / UTC input: the pure framer, decoder and tracker (drivers/nmea.py),
checked against gpsd's decodings of three real captures, and the reader shell (drivers/gnss.py)
over a real pseudo-terminal, loop://, a capture file and ports that fail. docs/gnss.md is the spec.
"""

from __future__ import annotations

import json
import math
import os
import random
import re
import threading
import time
import tty
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
import serial

from drivers.gnss import GnssReader
from drivers.nmea import (
    DAY_NS,
    Gga,
    Hdg,
    HeadingSample,
    NmeaFramer,
    NmeaStream,
    Pashr,
    decode_sentence,
    newest_heading,
    parse_sentence,
)
from rig.errors import GnssError, ProtocolError
from rig.protocol import nmea_checksum
from rig.types import HeadingRef

SHARED = Path(__file__).resolve().parents[2] / "shared"
FIXTURES = SHARED / "fixtures" / "nmea"
needs_fixtures = pytest.mark.skipif(
    not FIXTURES.is_dir(), reason=f"the gpsd NMEA captures are not here: {FIXTURES} (the project's shared folder)"
)

HANG_GUARD_S = 5.0  # every wait in these tests ends by this, so a bug fails instead of hanging
GPSD_DEG = 5e-4  # gpsd prints headings with 3 decimals; the sentences carry 2
GPSD_LATLON_DEG = 5e-9  # gpsd prints lat/lon with 9 decimals


def nmea(body: str, checksum: bool = True) -> bytes:
    """A sentence with its checksum and CRLF, built with the project's one checksum helper."""
    if not checksum:
        return f"${body}\r\n".encode()
    return f"${body}*{nmea_checksum(body.encode()):02X}\r\n".encode()


def headings_deg(updates) -> list[float]:
    return [round(math.degrees(u.heading.heading_rad), 9) for u in updates if u.heading is not None]


def without_t(updates) -> list[dict]:
    return [{k: v for k, v in u.to_json_dict().items() if k != "t"} for u in updates]


def feed_chunks(data: bytes, sizes) -> tuple[list, dict]:
    stream = NmeaStream()
    out, i = [], 0
    for size in sizes:
        if i >= len(data):
            break
        out += stream.feed(data[i : i + size], 0.0)
        i += size
    out += stream.feed(data[i:], 0.0)
    out += stream.flush(0.0)
    return out, stream.counts


def angle_diff_deg(a: float, b: float) -> float:
    return abs((a - b + 180.0) % 360.0 - 180.0)


def wait_until(predicate, timeout_s: float = HANG_GUARD_S) -> bool:
    """Poll a condition of another thread with a deadline (the result is asserted, never assumed)."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            return False
        threading.Event().wait(0.01)
    return True


def collect(reader: GnssReader, predicate, timeout_s: float = HANG_GUARD_S) -> list:
    """Updates from ``reader.get_events`` until ``predicate(updates)`` holds or the deadline passes."""
    out: list = []
    deadline = time.monotonic() + timeout_s
    while not predicate(out) and time.monotonic() < deadline:
        out += reader.get_events(timeout_s=0.05)
    return out


# --- framing: chunked, leading garbage, truncated, checksums, long lines, noise ---------------

HDT_10 = nmea("GPHDT,10.00,T")
RMC = nmea("GPRMC,204133.00,A,4205.735585,N,08802.039368,W,8.904,41.865,190214,,,D")
GGA = nmea("GPGGA,204133.10,4205.735766,N,08802.039145,W,2,09,0.9,221.871,M,,,4,0138")
STREAM = RMC + HDT_10 + GGA + nmea("INHDT,20.00,T") + nmea("GNTHS,30.00,A")


def test_byte_by_byte_and_random_chunks_give_the_same_updates():
    whole, counts = feed_chunks(STREAM, [len(STREAM)])
    assert headings_deg(whole) == [10.0, 20.0, 30.0] and counts["fixes"] == 2
    rng = random.Random(5)
    for sizes in ([1] * len(STREAM), [rng.randint(1, 17) for _ in range(len(STREAM))]):
        chunked, chunk_counts = feed_chunks(STREAM, sizes)
        assert without_t(chunked) == without_t(whole)
        assert chunk_counts == counts


def test_leading_garbage_is_skipped_and_counted():
    garbage = b"\x00\xff\xb5b\x01\x07 junk, half a line: 133.00,A,4205*1C\r\n"
    for sizes in ([10_000], [1] * 200):
        out, counts = feed_chunks(garbage + STREAM, sizes)
        assert headings_deg(out) == [10.0, 20.0, 30.0]
        assert counts["garbage_bytes"] == len(garbage) - 2  # its CR LF is a line end, not garbage


def test_a_sentence_cut_short_by_the_next_is_dropped_as_truncated():
    cut = HDT_10[:9]  # "$GPHDT,10" and no line end
    out, counts = feed_chunks(cut + nmea("GPHDT,45.00,T"), [1] * 40)
    assert headings_deg(out) == [45.0] and counts["truncated"] == 1
    # ... and one cut off by the end of the stream
    out, counts = feed_chunks(HDT_10 + cut, [4] * 20)
    assert headings_deg(out) == [10.0] and counts["truncated"] == 1


def test_a_truncated_line_that_still_got_its_line_end_fails_the_field_count():
    # No checksum, so only the field count stands between this and a half-read latitude.
    out, counts = feed_chunks(b"$GPRMC,204133.00,A,4205.7355\r\n", [100])
    assert out == [] and counts["bad_fields"] == 1 and counts["no_checksum"] == 1


def test_a_capture_without_a_final_newline_keeps_its_last_sentence():
    out, counts = feed_chunks(HDT_10 + HDT_10.rstrip(b"\r\n"), [100])
    assert headings_deg(out) == [10.0, 10.0] and counts["truncated"] == 0


def test_bad_checksums_are_dropped_and_counted():
    corrupt = HDT_10.replace(b"10.00", b"19.00")  # the XOR no longer matches
    lower = f"$GPHDT,11.50,T*{nmea_checksum(b'GPHDT,11.50,T'):02x}\r\n".encode()  # lower-case hex is fine
    out, counts = feed_chunks(corrupt + lower + corrupt + nmea("GPHDT,11.00,T"), [7] * 20)
    assert headings_deg(out) == [11.5, 11.0]
    assert counts["bad_checksum"] == 2 and counts["sentences"] == 2


def test_sentences_without_a_checksum_are_accepted_and_counted_unless_required():
    data = nmea("HEHDT,12.50,T", checksum=False)
    out, counts = feed_chunks(data, [100])
    assert headings_deg(out) == [12.5] and counts["no_checksum"] == 1
    framer = NmeaFramer(require_checksum=True)
    assert framer.feed(data) == [] and framer.counts["no_checksum"] == 1


def test_a_checksum_that_is_not_two_hex_digits_is_malformed():
    out, counts = feed_chunks(b"$GPHDT,10.00,T*1\r\n$GPHDT,10.00,T*XY\r\n", [100])
    assert out == [] and counts["malformed"] == 2


def test_lines_over_82_characters():
    long_gga = nmea("GNGGA,132819.60,4134.49795459,N,09345.03431408,W,2,10,0.9,278.161,M,-31.442,M,6.6,0133")
    assert len(long_gga) == 92  # Trimble's GGA, as in nmea-rtk.log: over the standard's 82, decoded
    overlong = b"$GPHDT," + b"1" * 300 + b",T*00\r\n"
    for sizes in ([10_000], [1] * 1000, [33] * 100):
        out, counts = feed_chunks(RMC + long_gga + overlong + HDT_10, sizes)
        assert [u.sentence for u in out] == ["RMC", "GGA", "HDT"]
        assert counts["long_lines"] == 1 and counts["overlong"] == 1
        assert counts["garbage_bytes"] == 0  # the overlong line is counted once, as overlong
    # Past the limit a line is dropped at once, without waiting for a line end that may never come.
    framer = NmeaFramer()
    framer.feed(b"$GPHDT," + b"1" * 200)
    assert framer.counts["overlong"] == 1


def test_binary_noise_between_sentences_loses_no_sentence():
    rng = random.Random(11)
    parts, expected = [], []
    for i in range(40):
        parts.append(bytes(rng.randrange(256) for _ in range(rng.randint(0, 60))))  # '$', CR, LF included
        heading = f"{(i * 7.25) % 360:.2f}"
        parts.append(b"\r\n" + nmea(f"GPHDT,{heading},T"))
        expected.append(float(heading))
    data = b"".join(parts)
    for sizes in ([len(data)], [rng.randint(1, 50) for _ in range(len(data))]):
        out, counts = feed_chunks(data, sizes)
        assert headings_deg(out) == expected
        assert counts["garbage_bytes"] > 0


def test_a_run_of_dollars_is_framed_in_one_pass(monkeypatch):
    # Each '$' cut the one before short, and the framer looked for a line end through the whole
    # rest of the buffer before finding it: 4096 '$' read about 8 MB (0.1 MB/s of noise on 2 cores).
    # Counted as the bytes its searches read, not timed.
    import drivers.nmea

    class Counting:
        def __init__(self, pattern):
            self.pattern, self.read = pattern, 0

        def search(self, buf, pos=0, *rest):
            match = self.pattern.search(buf, pos, *rest)
            self.read += (match.end() if match else len(buf)) - pos
            return match

    proxies = {}
    for name in ("_LINE_END", "_LINE_END_OR_START"):  # the framer's searches, then and now
        if hasattr(drivers.nmea, name):
            proxies[name] = Counting(getattr(drivers.nmea, name))
            monkeypatch.setattr(drivers.nmea, name, proxies[name])
    framer = NmeaFramer()
    assert framer.feed(b"$" * 4096 + HDT_10) != []
    assert framer.counts["truncated"] == 4096
    assert sum(p.read for p in proxies.values()) < 3 * (4096 + len(HDT_10))


def test_non_printable_bytes_inside_a_line_make_it_malformed():
    out, counts = feed_chunks(b"$GPHDT,1\x0000,T\r\n", [100])
    assert out == [] and counts["malformed"] == 1


def test_parse_sentence_names_the_problem():
    assert parse_sentence(HDT_10).kind == "HDT" and parse_sentence(HDT_10).talker == "GP"
    assert parse_sentence(nmea("PASHR,204132.000,010.51,T")).talker == "P"  # proprietary: no talker
    with pytest.raises(ProtocolError, match="bad_checksum"):
        parse_sentence(HDT_10.replace(b"10.00", b"19.00"))
    with pytest.raises(ProtocolError, match="no \\$"):
        parse_sentence(b"GPHDT,10.00,T")


# --- decoding and validity -------------------------------------------------------------------


def updates_of(*sentences: bytes, t: float = 0.0):
    stream = NmeaStream()
    return stream.feed(b"".join(sentences), t), stream.counts


@pytest.mark.parametrize("talker", ["GP", "GN", "HE", "IN", "HC", "GL", "GA"])
def test_any_talker_id(talker):
    out, _ = updates_of(nmea(f"{talker}HDT,77.70,T"))
    assert headings_deg(out) == [77.7] and out[0].heading.reference == HeadingRef.TRUE


@pytest.mark.parametrize(
    "body",
    ["GPHDT,,T", "GNTHS,123.40,V", "GNTHS,123.40,", "GNTHS,,A", "HCHDG,,,,,", "PASHR,204132.000,,T,+00.39,-00.79,"
     "-00.84,0.151,0.075,0.555,1,0", "PASHR,204132.000,010.51,,+00.39,-00.79,-00.84,0.151,0.075,0.555,1,0"],
)
def test_empty_or_invalid_headings_give_no_heading(body):
    out, counts = updates_of(nmea(body))
    assert out == [] and counts["no_data"] == 1 and counts["headings"] == 0


@pytest.mark.parametrize("mode", ["A", "E", "M", "S"])
def test_ths_modes_other_than_v_give_a_true_heading(mode):
    out, _ = updates_of(nmea(f"GNTHS,359.99,{mode}"))
    assert headings_deg(out) == [359.99] and out[0].sentence == "THS"


def test_heading_360_wraps_to_0_and_out_of_range_is_a_bad_field():
    out, counts = updates_of(nmea("GPHDT,360.00,T"), nmea("GPHDT,361.00,T"), nmea("GPHDT,-1.0,T"))
    assert headings_deg(out) == [0.0] and counts["bad_fields"] == 2


@pytest.mark.parametrize(
    ("body", "expected_deg", "reference"),
    [
        ("HCHDG,100.0,2.0,E,10.0,W", 92.0, HeadingRef.TRUE),  # 100 + 2 - 10
        ("HCHDG,100.0,2.0,W,10.0,E", 108.0, HeadingRef.TRUE),  # 100 - 2 + 10
        ("HCHDG,355.0,,,10.0,E", 5.0, HeadingRef.TRUE),  # no deviation: 0; wraps past north
        ("HCHDG,100.0,2.0,E,,", 102.0, HeadingRef.MAGNETIC),  # no variation: magnetic, and says so
        ("HCHDG,100.0,2.0,E,10.0,", 102.0, HeadingRef.MAGNETIC),  # a variation without E/W is no variation
    ],
)
def test_hdg_true_is_magnetic_plus_deviation_plus_variation(body, expected_deg, reference):
    out, _ = updates_of(nmea(body))
    assert len(out) == 1 and out[0].sentence == "HDG"
    assert math.degrees(out[0].heading.heading_rad) == pytest.approx(expected_deg, abs=1e-9)
    assert out[0].heading.reference == reference


def test_pashr_layout_and_signs():
    # rst39.log's first line: time, heading, T, roll, pitch, heave, roll/pitch/heading sigma, GNSS flag, IMU flag.
    line = b"$PASHR,204132.000,010.51,T,+00.39,-00.79,-00.84,0.151,0.075,0.555,1,0*03\r\n"
    msg = decode_sentence(parse_sentence(line))
    assert isinstance(msg, Pashr) and msg.time_of_day_ns == (20 * 3600 + 41 * 60 + 32) * 10**9
    assert math.degrees(msg.roll_rad) == pytest.approx(0.39) and math.degrees(msg.pitch_rad) == pytest.approx(-0.79)
    assert msg.heave_m == pytest.approx(-0.84) and (msg.gnss_quality, msg.imu_status) == (1, 0)
    # The vendors' roll is positive right (starboard) side down and pitch positive bow up: ours too
    # (docs/conventions.md), so the values pass through with their signs.
    out, counts = updates_of(RMC, line)
    sample = out[-1].heading
    assert (sample.source_sentence, sample.reference) == ("PASHR", HeadingRef.TRUE)
    assert math.degrees(sample.roll_rad) == pytest.approx(0.39)
    assert math.degrees(sample.pitch_rad) == pytest.approx(-0.79)
    att = sample.attitude()
    assert att.roll_rad == sample.roll_rad and att.pitch_rad == sample.pitch_rad
    # dated by the RMC before it: 2014-02-19 (the RMC is 20:41:33, the PASHR 20:41:32, same day)
    assert sample.utc_ns == round(datetime.fromisoformat("2014-02-19T20:41:32+00:00").timestamp()) * 10**9
    # before any date the heading still counts, without UTC
    out, counts = updates_of(line)
    assert out[0].heading.utc_ns is None and counts["undated"] == 1


def test_ashtech_pashr_subtypes_are_another_sentence():
    out, counts = updates_of(nmea("PASHR,POS,0,09,204132.00,4205.733476,N,08802.041110,W,221.9,,21.4,9.4,0.0,1.0,"
                                  "1.0,1.0,1.0,0000"))
    assert out == [] and counts["ignored"] == 1


def test_rmc_status_v_and_gga_quality_0_give_no_fix():
    out, counts = updates_of(
        nmea("GPRMC,204133.00,V,4205.735585,N,08802.039368,W,8.904,41.865,190214,,,N"),
        nmea("GPGGA,204133.10,4205.735766,N,08802.039145,W,0,09,0.9,221.871,M,,,4,0138"),
        nmea("GPRMC,204133.00,A,4205.735585,N,08802.039368,W,8.904,41.865,190214,,,N"),  # FAA mode N: not valid
    )
    assert out == [] and counts["no_data"] == 3


def test_gga_takes_its_date_from_the_latest_rmc_or_zda():
    gga = nmea("GPGGA,204133.10,4205.735766,N,08802.039145,W,2,09,0.9,221.871,M,,,4,0138")
    out, counts = updates_of(gga)  # no date yet: no fix, counted
    assert out == [] and counts["undated"] == 1
    out, _ = updates_of(nmea("GPZDA,204133.000,19,02,2014,,"), gga)
    assert [u.sentence for u in out] == ["ZDA", "GGA"]
    assert out[1].to_json_dict()["utc"] == "2014-02-19T20:41:33.100000Z"
    assert out[1].fix.lat_deg == pytest.approx(42 + 5.735766 / 60, abs=1e-12)
    assert out[1].fix.lon_deg == pytest.approx(-(88 + 2.039145 / 60), abs=1e-12)
    assert out[1].fix.alt_m == pytest.approx(221.871)


def test_gga_across_midnight_lands_on_the_right_day():
    before = nmea("GPRMC,235959.90,A,4205.735585,N,08802.039368,W,0,0,190214,,,A")
    after = nmea("GPGGA,000000.10,4205.735766,N,08802.039145,W,1,09,0.9,221.871,M,,,,")
    late = nmea("GPGGA,235959.95,4205.735766,N,08802.039145,W,1,09,0.9,221.871,M,,,,")
    out, _ = updates_of(before, after, late)
    assert [u.to_json_dict()["utc"] for u in out] == [
        "2014-02-19T23:59:59.900000Z", "2014-02-20T00:00:00.100000Z", "2014-02-19T23:59:59.950000Z"]


def test_a_gga_only_stream_keeps_its_date_hour_after_hour():
    # One RMC, then only GGA (time of day, no date) every hour for 26 hours: each GGA is dated
    # from the one before it, so the day advances at each midnight, also more than half a day
    # after the RMC (13 h after 08:00 is 21:00 the same day, not 21:00 the day before).
    rmc = nmea("GPRMC,080000.00,A,4807.038,N,01131.000,E,0.0,0.0,010124,,,A")
    ggas = [nmea(f"GPGGA,{(8 + k) % 24:02d}0000.00,4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,")
            for k in range(1, 27)]
    out, _ = updates_of(rmc, *ggas)
    assert [u.utc_ns - out[0].utc_ns for u in out] == [k * 3600 * 10**9 for k in range(27)]


def test_bad_fields_are_counted_not_raised():
    out, counts = updates_of(
        nmea("GPGGA,204133.10,4261.735766,N,08802.039145,W,2,09,0.9,221.871,M,,,4,0138"),  # 61 minutes
        nmea("GPRMC,204133.00,A,4205.735585,X,08802.039368,W,8.904,41.865,190214,,,D"),  # hemisphere X
        nmea("GPRMC,256133.00,A,4205.735585,N,08802.039368,W,8.904,41.865,190214,,,D"),  # hour 25
        nmea("GPRMC,204133.00,A,4205.735585,N,08802.039368,W,8.904,41.865,310214,,,D"),  # 31 February
        nmea("GPZDA,204133.000,19,02,14,,"),  # two-digit ZDA year
        nmea("GPZDA,204133.000,19,02,2080,,"),  # a calendar date, past the last year a receiver reports
        nmea("GPHDT,1e2,T"),
        nmea("GPHDT,10.0"),  # too few fields
        # one field just past its range, the rest of the sentence valid
        nmea("GPRMC,240000.00,A,4205.735585,N,08802.039368,W,8.904,41.865,190214,,,D"),  # hour 24
        nmea("GPGGA,204133.10,4260.000000,N,08802.039145,W,2,09,0.9,221.871,M,,,4,0138"),  # 60 minutes
        nmea("PASHR,204132.000,010.51,T,+00.39,+95.00,-00.84,0.151,0.075,0.555,1,0"),  # pitch 95 deg
    )
    assert out == [] and counts["bad_fields"] == 11
    with pytest.raises(ProtocolError):
        decode_sentence(parse_sentence(nmea("GPHDT,abc,T")))


def test_other_sentences_are_ignored():
    out, counts = updates_of(nmea("GPGSV,1,1,04,25,70,260,50"), nmea("GNVTG,171.0,T,,M,000.0,N,000.0,K,D"))
    assert out == [] and counts["ignored"] == 2 and counts["decoded"] == 0


def test_newest_heading_age_staleness_and_no_peeking_ahead():
    samples = [HeadingSample(t, math.radians(t), HeadingRef.TRUE, None, None, "HDT", None) for t in (1.0, 2.0, 3.0)]
    reading = newest_heading(samples, now_s=2.5, max_age_s=1.0)
    assert reading.sample.t_mono_s == 2.0 and reading.age_s == pytest.approx(0.5)
    assert newest_heading(samples, now_s=4.5, max_age_s=1.0) is None  # stale: never used silently
    assert newest_heading(samples, now_s=0.5, max_age_s=1.0) is None  # all of them arrived later
    assert newest_heading([], now_s=1.0, max_age_s=1.0) is None


# --- the gpsd captures -----------------------------------------------------------------------
#
# Each .chk file is gpsd's regression output: the capture's sentences, each followed by the JSON
# reports gpsd made after reading it. An ATT report gives the heading gpsd holds at that point, so
# it is compared with the newest heading this decoder has made from the sentences before it.


def replay_chk(name: str):
    """Walk ``name``.chk: feed each sentence, and at every JSON report yield (report, newest heading
    update, newest fix, newest UTC-only update) as this decoder has them at that point."""
    stream = NmeaStream()
    heading = fix = utc = None
    for i, line in enumerate((FIXTURES / f"{name}.chk").read_text(encoding="ascii").splitlines()):
        if line.startswith("$"):
            for u in stream.feed(line.encode() + b"\r\n", float(i)):
                if u.heading is not None:
                    heading = u
                if u.fix is not None:
                    fix = u.fix
                if u.utc_ns is not None and u.heading is None:
                    utc = u.utc_ns
        elif line.startswith("{"):
            yield json.loads(line), heading, fix, utc


def iso_ns(text: str) -> int:
    dt = datetime.fromisoformat(text.replace("Z", "+00:00"))
    return round(dt.timestamp() * 1000) * 10**6


@needs_fixtures
@pytest.mark.parametrize(("name", "n_att"), [("skytraq-PX1172RH_DS.log", 11), ("rst39.log", 4)])
def test_headings_agree_with_gpsd(name, n_att):
    """Every ATT record gpsd made is matched; none is skipped.

    skytraq: gpsd reports ATT after HDT, and in the first cycle also after PSTI,035 and PSTI,036
    (Skytraq's own heading sentences, which this decoder does not use: they repeat the cycle's
    HDT/THS heading, and PSTI,036's pitch is where gpsd's ATT pitch comes from, so pitch is not
    compared). From the second cycle gpsd holds its reports to the end of the cycle (after
    PSTI,036) and adds the cycle's time, which is checked against our UTC of the same cycle.
    rst39: gpsd reports ATT only for HDT. It parses the OxTS PASHR but does not report it
    ("mask |= ATTITUDE_SET; confuses cycle order" in gpsd's driver_nmea0183.c), so the 100 PASHR
    headings have no gpsd counterpart; test_pashr_agrees_with_hdt_of_the_same_epoch covers them.
    """
    compared, worst = 0, 0.0
    for report, heading, _, utc in replay_chk(name):
        if report["class"] != "ATT":
            continue
        assert heading is not None, f"gpsd reported heading {report['heading']} before we had one"
        diff = angle_diff_deg(math.degrees(heading.heading.heading_rad), report["heading"])
        assert diff <= GPSD_DEG, (report, heading)
        assert heading.heading.reference == HeadingRef.TRUE
        if "time" in report:
            assert utc == iso_ns(report["time"]), "the heading is not from the cycle gpsd reported"
        worst = max(worst, diff)
        compared += 1
    assert compared == n_att
    print(f"{name}: {compared} gpsd headings compared, max difference {worst:.2e} deg")


@needs_fixtures
def test_pashr_agrees_with_hdt_of_the_same_epoch():
    """In rst39 each HDT is followed by the PASHR of the same whole second: same heading."""
    out, _ = feed_chunks((FIXTURES / "rst39.log").read_bytes(), [1 << 20])
    hdt = [u.heading.heading_rad for u in out if u.sentence == "HDT"]
    pashr_on_second = {}
    for u in out:
        if u.sentence == "PASHR" and u.utc_ns is not None and u.utc_ns % 10**9 == 0:
            pashr_on_second[u.utc_ns] = u.heading.heading_rad
    after_hdt = [pashr_on_second[t] for t in sorted(pashr_on_second)][-3:]  # 20:41:33, :34, :35
    assert len(hdt) == 4 and len(after_hdt) == 3  # the capture ends before the fourth HDT's PASHR
    for a, b in zip(hdt[:3], after_hdt, strict=True):
        assert angle_diff_deg(math.degrees(a), math.degrees(b)) < 1e-9
    n_pashr = sum(u.sentence == "PASHR" for u in out)
    assert n_pashr == 100  # every PASHR line of the capture gives a heading (with roll and pitch)


@needs_fixtures
@pytest.mark.parametrize(("name", "week_rollovers"), [("skytraq-PX1172RH_DS.log", 0), ("rst39.log", 1)])
def test_fixes_and_time_agree_with_gpsd(name, week_rollovers):
    """Every gpsd TPV with a time and position matches our newest fix: same time of day, lat/lon
    within gpsd's 9 decimals. The date differs in rst39 by one GPS week rollover (1024 weeks):
    gpsd dates its RMC 190214 as 2033-10-05, since it assumes a receiver older than gpsd's build
    lost a rollover. The ZDA in the same capture says 2014-02-19, as we do."""
    compared = 0
    for report, _, fix, _ in replay_chk(name):
        if report["class"] != "TPV" or "time" not in report or "lat" not in report:
            continue
        assert fix is not None
        assert iso_ns(report["time"]) - fix.utc_ns == week_rollovers * 1024 * 7 * DAY_NS
        assert abs(report["lat"] - fix.lat_deg) <= GPSD_LATLON_DEG
        assert abs(report["lon"] - fix.lon_deg) <= GPSD_LATLON_DEG
        compared += 1
    assert compared >= 10


@needs_fixtures
def test_nmea_rtk_fixes_and_time_agree_with_pynmea2():
    """nmea-rtk.log has no .chk: every RMC and GGA is checked against pynmea2, a decoder written
    independently, and each GGA's UTC against the RMC of the same epoch."""
    pynmea2 = pytest.importorskip("pynmea2", reason="the dev extra's pynmea2 cross-checks nmea-rtk.log")
    data = (FIXTURES / "nmea-rtk.log").read_bytes()
    out, counts = feed_chunks(data, [1 << 20])
    lines = [ln for ln in data.decode("ascii").splitlines() if ln.startswith("$")]
    assert counts["sentences"] == len(lines) == 244 and counts["bad_checksum"] == 0
    assert counts["long_lines"] == 244  # Trimble's 8-decimal minutes: every line is over 82 characters
    # The capture opens with a GGA before any date: that one fix is undated; the other 243 are fixes.
    assert counts["undated"] == 1 and len(out) == 243 and all(u.fix is not None for u in out)
    theirs = [pynmea2.parse(ln) for ln in lines[1:]]
    rmc_utc = {}
    for u, ref in zip(out, theirs, strict=True):
        assert u.sentence == ref.sentence_type
        assert u.fix.lat_deg == pytest.approx(float(ref.latitude), abs=1e-12)
        assert u.fix.lon_deg == pytest.approx(float(ref.longitude), abs=1e-12)
        tod = u.utc_ns % DAY_NS
        t = ref.timestamp
        assert tod == ((t.hour * 60 + t.minute) * 60 + t.second) * 10**9 + t.microsecond * 1000
        if u.sentence == "RMC":
            assert u.utc_ns // DAY_NS == (ref.datestamp.toordinal() - datetime(1970, 1, 1).toordinal())
            rmc_utc[tod] = u.utc_ns
        else:
            assert u.fix.alt_m == pytest.approx(float(ref.altitude))
    for u in out:
        if u.sentence == "GGA" and u.utc_ns % DAY_NS in rmc_utc:
            assert u.utc_ns == rmc_utc[u.utc_ns % DAY_NS]


@needs_fixtures
@pytest.mark.parametrize("name", ["skytraq-PX1172RH_DS.log", "rst39.log", "nmea-rtk.log"])
def test_captures_decode_the_same_in_any_chunks(name):
    """The raw captures, with their comment lines and gpsd's JSON in the Skytraq one (garbage to a
    framer), byte by byte and in random chunks, give what the whole file gives."""
    data = (FIXTURES / name).read_bytes()
    whole, counts = feed_chunks(data, [len(data)])
    assert counts["bad_checksum"] == counts["truncated"] == counts["malformed"] == counts["bad_fields"] == 0
    rng = random.Random(name)
    for sizes in ([1] * len(data), [rng.randint(1, 300) for _ in range(len(data))]):
        chunked, chunk_counts = feed_chunks(data, sizes)
        assert without_t(chunked) == without_t(whole) and chunk_counts == counts


# --- the reader shell ------------------------------------------------------------------------


class FakeClock:
    def __init__(self, start: float = 100.0) -> None:
        self.now = start

    def __call__(self) -> float:
        return self.now


def test_reader_over_loop_url_with_an_injected_clock():
    port = serial.serial_for_url("loop://", timeout=0.05)
    clock = FakeClock(100.0)
    with GnssReader(port, clock=clock, events=16, timeout_s=0.05) as reader:
        port.write(RMC + nmea("HEHDT,123.45,T"))
        got = collect(reader, lambda us: any(u.heading for u in us))
        assert [u.sentence for u in got] == ["RMC", "HDT"]
        assert got[1].t_mono_s == 100.0  # the reader's clock, not the wall
        reading = reader.latest_heading(100.4, max_age_s=0.5)
        assert reading is not None and reading.age_s == pytest.approx(0.4)
        assert math.degrees(reading.heading_rad) == pytest.approx(123.45) and reading.reference == HeadingRef.TRUE
        assert reader.latest_heading(100.6, max_age_s=0.5) is None  # stale
        assert reader.latest_heading(99.0) is None  # received after that moment
        fix = reader.latest_fix(100.1)
        assert fix is not None and fix.lat_deg == pytest.approx(42 + 5.735585 / 60)
        utc = reader.utc_at(101.0)
        assert utc == round(datetime.fromisoformat("2014-02-19T20:41:34+00:00").timestamp()) * 10**9
        assert len(reader.heading_history()) == 1
        stats = reader.stats()
        assert stats["headings"] == 1 and stats["fixes"] == 1 and stats["port"] == "loop://"
    assert not port.is_open and reader.finished
    reader.close()  # idempotent


def test_an_old_fix_or_utc_is_not_handed_out():
    # A fix or a UTC time from long ago would put a frame at a stale place or time: past its
    # max_age_s each is None, as a stale heading is. RMC carries both; it arrives at clock 100.0.
    port = serial.serial_for_url("loop://", timeout=0.05)
    with GnssReader(port, clock=FakeClock(100.0), events=4, timeout_s=0.05) as reader:
        port.write(RMC)
        assert collect(reader, lambda us: len(us) == 1)
        assert reader.latest_fix(101.0, max_age_s=1.5) is not None
        assert reader.latest_fix(102.0, max_age_s=1.5) is None  # 2 s old
        assert reader.latest_fix(99.0) is None  # received after that moment
        assert reader.utc_at(105.0, max_age_s=10.0) is not None
        assert reader.utc_at(111.0, max_age_s=10.0) is None  # 11 s old
        assert reader.utc_at(99.0) is None


def test_the_newest_fix_replaces_the_one_before():
    # A moving rig: each fix replaces the last, so a frame gets where the rig is now (GGA's
    # position, 0.000181' north of RMC's), not where the first fix put it.
    port = serial.serial_for_url("loop://", timeout=0.05)
    clock = FakeClock(100.0)
    with GnssReader(port, clock=clock, events=4, timeout_s=0.05) as reader:
        port.write(RMC)
        assert collect(reader, lambda us: len(us) == 1)
        clock.now = 101.0
        port.write(GGA)
        assert collect(reader, lambda us: len(us) == 1)
        fix = reader.latest_fix(101.5, max_age_s=1.0)
        assert fix is not None and fix.lat_deg == pytest.approx(42 + 5.735766 / 60, abs=1e-9)


def utc_ns_of(iso: str) -> int:
    return round(datetime.fromisoformat(iso).timestamp()) * 10**9


def test_a_fix_utc_or_heading_from_before_a_suspend_is_not_handed_out_after_it():
    # CLOCK_MONOTONIC stands still while the host is suspended: after an hour's suspend the RMC read
    # at 100.0 looked 0.5 s old at 100.5, and utc_at carried its UTC on to frames an hour late. The
    # injected boot offset stands for CLOCK_BOOTTIME - CLOCK_MONOTONIC, which grows by the time
    # suspended: nothing stamped before a suspend is handed out after it (no UTC rather than a wrong one).
    from drivers.nmea import SUSPEND_TOLERANCE_S

    port = serial.serial_for_url("loop://", timeout=0.05)
    clock, boot = FakeClock(100.0), FakeClock(0.0)
    with GnssReader(port, clock=clock, boot_offset=boot, events=4, timeout_s=0.05) as reader:
        port.write(RMC + nmea("HEHDT,123.45,T"))
        assert len(collect(reader, lambda us: len(us) == 2)) == 2
        boot.now = SUSPEND_TOLERANCE_S / 2  # the two clocks read a moment apart: not a suspend
        assert reader.utc_at(100.5) == utc_ns_of("2014-02-19T20:41:33+00:00") + 500_000_000
        assert reader.latest_fix(100.5) is not None and reader.latest_heading(100.5) is not None
        boot.now = 3600.0  # suspended for an hour, and resumed
        assert reader.utc_at(100.5) is None
        assert reader.latest_fix(100.5) is None
        assert reader.latest_heading(100.5) is None
        # The first sentences after the resume are fresh, and what they say is handed out again.
        # (Once the reader has seen the resume: what its first read after one finds is dropped.)
        assert wait_until(lambda: reader.stats()["suspends"] == 1)
        clock.now = 101.0
        port.write(nmea("GPRMC,214133.00,A,4205.735585,N,08802.039368,W,8.904,41.865,190214,,,D")
                   + nmea("HEHDT,200.0,T"))
        assert len(collect(reader, lambda us: len(us) == 2)) == 2
        assert reader.utc_at(101.5) == utc_ns_of("2014-02-19T21:41:33+00:00") + 500_000_000
        assert reader.latest_fix(101.5) is not None
        reading = reader.latest_heading(101.5)
        assert reading is not None and math.degrees(reading.heading_rad) == pytest.approx(200.0)
        # Asked of a moment before the resume, the heading from before the suspend is still not
        # handed out: it is judged by the clocks now, and the frame asking is as old as the suspend.
        assert reader.latest_heading(100.5) is None


def test_heading_samples_carry_the_boot_offset_so_pairing_does_not_bridge_a_suspend():
    # heading_history() kept every sample, and by its monotonic stamp alone one from before an hour's
    # suspend and one from after it looked 0.6 s apart: drivers/pairing.py interpolated between them.
    from drivers.pairing import HeadingInterpolator

    port = serial.serial_for_url("loop://", timeout=0.05)
    clock, boot = FakeClock(100.0), FakeClock(2.0)
    with GnssReader(port, clock=clock, boot_offset=boot, events=4, timeout_s=0.05) as reader:
        port.write(nmea("HEHDT,10.0,T"))
        assert len(collect(reader, lambda us: len(us) == 1)) == 1
        clock.now, boot.now = 100.6, 3602.0  # suspended for an hour, and resumed
        assert wait_until(lambda: reader.stats()["suspends"] == 1)  # the reader's first read after it
        port.write(nmea("HEHDT,100.0,T"))
        assert len(collect(reader, lambda us: len(us) == 1)) == 1
        history = reader.heading_history()
    assert [s.boot_offset_s for s in history] == [2.0, 3602.0]
    assert HeadingInterpolator().lookup(history, 100.3).status == "gap"


class SuspendablePort:
    """FAKE serial port (no host can be suspended under a test): its bytes wait in a buffer until
    read, as in the kernel's tty buffer. ``freeze()`` parks the reader's next read until ``thaw()``,
    as the host's suspend freezes the thread in it; that read then returns one byte (a read(1) that
    was waiting), and the rest waits for the next."""

    def __init__(self) -> None:
        self.is_open = True
        self.timeout = 0.05
        self.port = "suspendable://test"
        self._cond = threading.Condition()
        self._buf = bytearray()
        self._frozen = False
        self._cancelled = False
        self.parked = threading.Event()  # the reader is in a read that waits for thaw()

    @property
    def in_waiting(self) -> int:
        with self._cond:
            return 0 if self._frozen else len(self._buf)

    def write(self, data: bytes) -> None:
        with self._cond:
            self._buf += data

    def freeze(self) -> None:
        with self._cond:
            self._frozen = True

    def thaw(self) -> None:
        with self._cond:
            self._frozen = False
            self._cond.notify_all()

    def read(self, size: int = 1) -> bytes:
        with self._cond:
            if self._frozen:
                self.parked.set()
                self._cond.wait_for(lambda: not self._frozen or self._cancelled, HANG_GUARD_S)
                size = 1
            data = bytes(self._buf[:size])
            del self._buf[:size]
            if not data and not self._cancelled:
                self._cond.wait(self.timeout)
        return data

    def cancel_read(self) -> None:
        with self._cond:
            self._cancelled = True
            self._cond.notify_all()

    def open(self) -> None:
        self.is_open = True

    def close(self) -> None:
        self.is_open = False


def test_bytes_that_waited_through_a_suspend_are_dropped_not_stamped_fresh():
    # The device's sentences from before a suspend wait in the kernel's buffer (and a partial line in
    # the framer's) while the reader's thread is frozen; after the resume they were read, stamped
    # with the monotonic time and boot offset of then, and an hour-old heading, fix and UTC were
    # handed out as current. What the first read after a resume finds waiting is dropped and counted.
    port = SuspendablePort()
    clock, boot = FakeClock(100.0), FakeClock(0.0)
    hdt_77 = nmea("HEHDT,77.0,T")
    before = RMC + HDT_10 + hdt_77[:10]  # the last sentence's tail is still on the wire
    with GnssReader(port, clock=clock, boot_offset=boot, events=16, timeout_s=0.05) as reader:
        port.write(before)
        assert wait_until(lambda: reader.stats()["bytes"] == len(before))
        assert len(collect(reader, lambda us: len(us) == 2)) == 2
        port.freeze()
        assert port.parked.wait(HANG_GUARD_S)
        stale = hdt_77[10:] + nmea("GPRMC,204134.00,A,4205.735585,N,08802.039368,W,8.904,41.865,190214,,,D") \
            + nmea("HEHDT,50.0,T")
        port.write(stale)  # in the kernel's buffer as the host suspends
        clock.now, boot.now = 100.3, 3600.0  # suspended for an hour, and resumed
        port.thaw()
        assert wait_until(lambda: reader.stats()["bytes"] == len(before) + len(stale))
        assert reader.get_events(timeout_s=0.01) == []
        assert reader.latest_heading(100.4) is None
        assert reader.utc_at(100.4) is None and reader.latest_fix(100.4) is None
        stats = reader.stats()
        assert stats["suspends"] == 1 and stats["stale_bytes"] == len(stale)
        assert stats["truncated"] == 1  # the partial line kept from before the suspend
        # What comes after the resume is fresh, and handed out.
        clock.now = 100.5
        port.write(nmea("GPRMC,214133.00,A,4205.735585,N,08802.039368,W,8.904,41.865,190214,,,D")
                   + nmea("HEHDT,200.0,T"))
        assert len(collect(reader, lambda us: len(us) == 2)) == 2
        reading = reader.latest_heading(100.6)
        assert reading is not None and math.degrees(reading.heading_rad) == pytest.approx(200.0)
        assert reader.utc_at(100.6) == utc_ns_of("2014-02-19T21:41:33+00:00") + 100_000_000
        assert reader.stats()["suspends"] == 1


def test_a_frame_from_before_a_suspend_gets_no_utc_or_fix_from_after_it():
    # The pairing carried the UTC read after a resume back to a frame by the monotonic clock, which
    # stood still through the suspend: a frame taken before an hour's suspend (waiting for its
    # heading through it, or delivered by the camera after it) got a UTC an hour late.
    from drivers.pairing import HeadingInterpolator, PairingStats, with_heading
    from rig.types import Frame, Intrinsics

    intrinsics = Intrinsics.from_hfov(8, 6, math.radians(60.0))
    port = serial.serial_for_url("loop://", timeout=0.05)
    clock, boot = FakeClock(100.0), FakeClock(0.0)
    with GnssReader(port, clock=clock, boot_offset=boot, events=16, timeout_s=0.05) as reader:

        def frames():
            port.write(RMC + HDT_10)
            assert len(collect(reader, lambda us: len(us) == 2)) == 2
            clock.now = 100.2
            yield Frame(100.2, 0, intrinsics, image_bgr=np.zeros((6, 8, 3), np.uint8))  # waits for its heading
            clock.now, boot.now = 100.3, 3600.0  # suspended for an hour, and resumed
            assert wait_until(lambda: reader.stats()["suspends"] == 1)
            clock.now = 100.4
            port.write(nmea("GPRMC,214133.00,A,4205.735585,N,08802.039368,W,8.904,41.865,190214,,,D")
                       + nmea("HEHDT,200.0,T"))
            assert len(collect(reader, lambda us: len(us) == 2)) == 2
            clock.now = 100.5
            yield Frame(100.25, 1, intrinsics, image_bgr=np.zeros((6, 8, 3), np.uint8))  # taken before, come after
            clock.now = 100.6
            yield Frame(100.55, 2, intrinsics, image_bgr=np.zeros((6, 8, 3), np.uint8))  # taken after the resume

        stats = PairingStats(HeadingInterpolator())
        out = list(with_heading(frames(), reader, stats.interpolator, clock=clock, stats=stats))
    assert [f.seq for f in out] == [0, 1, 2]
    assert [(f.attitude, f.utc_ns, f.gnss) for f in out[:2]] == [(None, None, None)] * 2
    assert out[2].utc_ns == utc_ns_of("2014-02-19T21:41:33+00:00") + 150_000_000
    assert out[2].gnss is not None


def test_a_gga_after_a_night_suspended_gets_the_date_of_after_it():
    # GGA carries only the time of day, dated by the newest UTC (within 12 h of it). After a host
    # suspended overnight (20 h), the RMC's date from before it put a GGA at 16:41 on the day before:
    # the date is moved on by the time suspended, which the monotonic clock does not count.
    port = serial.serial_for_url("loop://", timeout=0.05)
    clock, boot = FakeClock(100.0), FakeClock(0.0)
    with GnssReader(port, clock=clock, boot_offset=boot, events=4, timeout_s=0.05) as reader:
        port.write(RMC)  # 2014-02-19 20:41:33
        assert len(collect(reader, lambda us: len(us) == 1)) == 1
        clock.now, boot.now = 100.5, 20 * 3600.0
        assert wait_until(lambda: reader.stats()["suspends"] == 1)
        port.write(nmea("GPGGA,164133.10,4205.735766,N,08802.039145,W,2,09,0.9,221.871,M,,,4,0138"))
        got = collect(reader, lambda us: len(us) == 1)
    assert [u.utc_ns for u in got] == [utc_ns_of("2014-02-20T16:41:33+00:00") + 100_000_000]
    assert got[0].fix is not None and got[0].fix.utc_ns == got[0].utc_ns


def test_without_clock_boottime_a_suspend_goes_unseen_as_before(monkeypatch):
    # Not Linux: no CLOCK_BOOTTIME, so nothing tells a suspend; the reader works by the monotonic
    # clock alone, as it did.
    from drivers.gnss import boottime_offset_s

    first, second = boottime_offset_s(), boottime_offset_s()
    if hasattr(time, "CLOCK_BOOTTIME"):  # the host's time suspended so far (to the µs between two reads)
        assert first is not None and second is not None and first > -0.01 and abs(second - first) < 0.01
    monkeypatch.delattr(time, "CLOCK_BOOTTIME", raising=False)
    assert boottime_offset_s() is None
    port = serial.serial_for_url("loop://", timeout=0.05)
    with GnssReader(port, clock=FakeClock(100.0), boot_offset=lambda: None, events=4, timeout_s=0.05) as reader:
        port.write(RMC)
        assert len(collect(reader, lambda us: len(us) == 1)) == 1
        assert reader.utc_at(100.5) == utc_ns_of("2014-02-19T20:41:33+00:00") + 500_000_000
        assert reader.latest_fix(100.5) is not None


def test_live_events_drop_the_oldest_and_count_it():
    # A live port never waits for its consumer: with room for 2, five headings leave the newest two
    # and 3 counted drops; `updates` counts every one decoded (docs/gnss.md's counters). The heading
    # history is a ring too (3 here): a reader running for days keeps a bounded memory.
    port = serial.serial_for_url("loop://", timeout=0.05)
    with GnssReader(port, events=2, history=3, timeout_s=0.05) as reader:
        port.write(b"".join(nmea(f"HEHDT,{h}.00,T") for h in (10, 20, 30, 40, 50)))
        assert wait_until(lambda: reader.stats()["updates"] == 5)
        stats = reader.stats()
        assert stats["events_dropped"] == 3 and stats["history"] == 3
        assert [math.degrees(s.heading_rad) for s in reader.heading_history()] == pytest.approx([30.0, 40.0, 50.0])
        assert headings_deg(reader.get_events(timeout_s=0.01)) == pytest.approx([40.0, 50.0])


def test_a_reader_that_keeps_no_headings_is_refused():
    # history=0 would keep no sample: every frame would go without a heading, silently.
    with pytest.raises(GnssError, match="history"):
        GnssReader(serial.serial_for_url("loop://"), history=0)


@pytest.fixture
def pty_pair():
    master, slave = os.openpty()
    tty.setraw(slave)  # no echo, no CR/LF translation: bytes pass as written
    fds = {"master": master, "slave": slave}
    yield fds, os.ttyname(slave)
    for fd in fds.values():
        if fd >= 0:
            os.close(fd)


def test_reader_on_a_pseudo_terminal_and_its_device_disappearing(pty_pair):
    fds, name = pty_pair
    reader = GnssReader(name, timeout_s=0.05, events=64, backoff_s=(0.02, 0.1))
    try:
        os.write(fds["master"], b"\xff\x00noise" + RMC[:20])
        os.write(fds["master"], RMC[20:] + nmea("GNTHS,200.00,A"))
        got = collect(reader, lambda us: any(u.heading for u in us))
        assert [u.sentence for u in got] == ["RMC", "THS"]
        assert reader.latest_heading(time.monotonic()).heading_rad == pytest.approx(math.radians(200.0))
        os.close(fds["master"])  # the device goes away
        fds["master"] = -1
        assert wait_until(lambda: reader.stats()["read_errors"] >= 1)
        stats = reader.stats()
        assert stats["last_error"] and stats["reader_alive"]  # reported, and still trying
    finally:
        started = time.monotonic()
        reader.close()
        assert time.monotonic() - started < 3.0  # bounded join, even while it retries
    assert not reader.stats()["reader_alive"]


class FlakyPort:
    """A port-like object that plays a script of reads (bytes or an exception), fails ``fail_opens``
    reopens, and records when each open was tried."""

    def __init__(self, script, fail_opens: int = 0) -> None:
        self.script = list(script)
        self.fail_opens = fail_opens
        self.open_times: list[float] = []
        self.is_open = True
        self.timeout = None
        self.port = "flaky://test"
        self._cancel = threading.Event()

    in_waiting = 0

    def read(self, size: int = 1) -> bytes:
        if not self.is_open:
            raise serial.PortNotOpenError()
        if self.script:
            item = self.script.pop(0)
            if isinstance(item, BaseException):
                raise item
            return item
        self._cancel.wait(self.timeout)
        return b""

    def open(self) -> None:
        self.open_times.append(time.monotonic())
        if self.fail_opens > 0:
            self.fail_opens -= 1
            raise serial.SerialException(2, "could not open port flaky://test: no such device")
        self.is_open = True

    def close(self) -> None:
        self.is_open = False

    def cancel_read(self) -> None:
        self._cancel.set()


def test_a_failing_port_is_reopened_with_backoff_and_recovers():
    lo = 0.02
    port = FlakyPort([HDT_10[:10], serial.SerialException("device reports readiness to read but returned no data"),
                      nmea("GPHDT,33.00,T")], fail_opens=2)
    with GnssReader(port, timeout_s=0.05, events=8, backoff_s=(lo, 1.0)) as reader:
        got = collect(reader, lambda us: any(u.heading for u in us))
        assert headings_deg(got) == [33.0]
        stats = reader.stats()
        assert stats["read_errors"] == 1 and stats["reopens"] == 1 and stats["truncated"] == 1
        assert "readiness" in stats["last_error"] or "reopen failed" in stats["last_error"]
    # read error -> wait lo -> open fails -> wait 2 lo -> open fails -> wait 4 lo -> open works
    gaps = [b - a for a, b in zip(port.open_times, port.open_times[1:], strict=False)]
    assert len(port.open_times) == 3 and gaps[0] >= 2 * lo * 0.99 and gaps[1] >= 4 * lo * 0.99


def test_a_port_that_never_comes_back_does_not_spin_or_hang():
    port = FlakyPort([HDT_10[:10], serial.SerialException("gone")], fail_opens=10**6)
    reader = GnssReader(port, timeout_s=0.05, backoff_s=(0.01, 0.04))
    assert wait_until(lambda: len(port.open_times) >= 4)
    # The sentence the unplug cut short shows at once, not only once the device sends again.
    assert reader.stats()["truncated"] == 1
    started = time.monotonic()
    reader.close()
    assert time.monotonic() - started < 3.0 and reader.finished
    span = port.open_times[-1] - port.open_times[0]
    assert span >= 0.02 + 0.04 * (len(port.open_times) - 3) - 1e-3  # backoff doubled to its cap, no spinning


@needs_fixtures
def test_reader_replays_a_capture_file_to_its_end():
    path = FIXTURES / "rst39.log"
    expected, _ = feed_chunks(path.read_bytes(), [1 << 20])
    with GnssReader(path, events=8) as reader:  # a small queue: the file waits for the consumer
        got = collect(reader, lambda us: reader.finished and len(us) >= len(expected))
        assert reader.wait_finished(HANG_GUARD_S)
        got += reader.get_events(timeout_s=0.01)
        stats = reader.stats()
    assert without_t(got) == without_t(expected)
    assert stats["events_dropped"] == 0 and stats["bytes"] == path.stat().st_size


def test_opening_errors_are_one_clear_line(tmp_path):
    with pytest.raises(GnssError, match="no such file or device"):
        GnssReader(tmp_path / "nope.log")
    with pytest.raises(GnssError, match="directory"):
        GnssReader(tmp_path)
    with pytest.raises(GnssError, match="cannot open GNSS source"):
        GnssReader("socket://127.0.0.1:1")  # nothing listens on port 1
    with pytest.raises(GnssError, match="timeout_s"):
        GnssReader(serial.serial_for_url("loop://"), timeout_s=0)


# --- the CLI ---------------------------------------------------------------------------------


def test_cli_prints_one_json_object_per_useful_sentence(tmp_path, capsys):
    from rig.cli import main

    capture = tmp_path / "capture.nmea"
    capture.write_bytes(b"garbage\r\n" + nmea("GPHDT,,T") + RMC + GGA + nmea("HEHDT,45.50,T") + b"$GPHDT,1")
    assert main(["gnss", str(capture), "--jsonl", "-", "--baud", "4800"]) == 0
    captured = capsys.readouterr()
    rows = [json.loads(line) for line in captured.out.splitlines()]
    assert [r["sentence"] for r in rows] == ["RMC", "GGA", "HDT"]
    assert all(isinstance(r["t"], float) for r in rows)
    assert rows[0]["utc"] == "2014-02-19T20:41:33.000000Z" and rows[0]["lat"] == pytest.approx(42.09559308)
    assert rows[1]["lon"] == pytest.approx(-(88 + 2.039145 / 60)) and rows[1]["utc"].endswith("33.100000Z")
    assert rows[2]["heading_deg"] == 45.5 and rows[2]["heading_ref"] == "true" and "lat" not in rows[2]
    assert "truncated 1" in captured.err and "no_data 1" in captured.err


def test_cli_on_a_missing_path_says_so_in_one_line(tmp_path, capsys):
    from rig.cli import main

    assert main(["gnss", str(tmp_path / "nope.log"), "--jsonl", "-"]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("sunrig: error: cannot open GNSS source") and captured.out == ""


def test_cli_on_a_file_with_no_nmea_fails_and_says_what_to_check(tmp_path, capsys):
    from rig.cli import main

    not_nmea = tmp_path / "drive.mcap"
    not_nmea.write_bytes(bytes(range(256)) * 40)  # e.g. a video or a log passed by mistake
    assert main(["gnss", str(not_nmea), "--jsonl", "-"]) == 2
    err = capsys.readouterr().err
    assert "0 updates from 0 sentences" in err and "no NMEA sentence from" in err and "--baud" in err


def test_cli_on_a_full_disk_says_so_in_one_line(tmp_path, capsys):
    # The JSONL output is replay's JsonlPublisher: a failed write is a one-line error, exit 2,
    # not an internal error from the lines still buffered when the file closes.
    from rig.cli import main

    capture = tmp_path / "capture.nmea"
    capture.write_bytes(RMC + GGA)
    assert main(["gnss", str(capture), "--jsonl", "/dev/full"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "cannot write JSONL to /dev/full: No space left" in lines[0], lines


def test_decoder_types_for_direct_use():
    gga = decode_sentence(parse_sentence(GGA))
    assert isinstance(gga, Gga) and gga.quality == 2 and gga.talker == "GP"
    hdg = decode_sentence(parse_sentence(nmea("HCHDG,100.0,2.0,E,10.0,W")))
    assert isinstance(hdg, Hdg) and hdg.variation_rad == pytest.approx(math.radians(-10.0))


def test_a_port_that_sends_bytes_and_no_nmea_is_said_once_live_and_its_return(caplog):
    # A GNSS at another baud rate (or a port that is not the GNSS) sent garbage for as long as the
    # rig ran, and the run said nothing: only "no heading N" in the status line, and the garbage
    # bytes at exit. Said once after a few seconds of bytes without a sentence, and when sentences come.
    import logging

    rng = np.random.default_rng(3)
    garbage = bytes(b for b in rng.integers(0x80, 0x100, 600, dtype=np.uint8))  # no '$', no line end
    port = serial.serial_for_url("loop://", timeout=0.05)
    clock = FakeClock(100.0)
    with caplog.at_level(logging.INFO, logger="drivers.gnss"), \
            GnssReader(port, clock=clock, events=16, timeout_s=0.05) as reader:
        port.write(garbage)
        assert wait_until(lambda: reader.stats()["bytes"] >= 600)
        assert "no NMEA" not in caplog.text  # a moment of noise is no wrong baud
        clock.now = 106.0
        port.write(garbage)
        assert wait_until(lambda: reader.stats()["bytes"] >= 1200)
        clock.now = 107.0
        port.write(garbage)
        assert wait_until(lambda: reader.stats()["bytes"] >= 1800)
        said = [r.getMessage() for r in caplog.records if "no NMEA" in r.getMessage()]
        # Said once, as the bytes of the sixth second come (how many of them, the reads' sizes decide).
        assert len(said) == 1 and re.fullmatch(
            r"GNSS port loop://: (60[1-9]|6[1-9]\d|1[01]\d\d|1200) bytes in 6 s and no NMEA sentence in them; check "
            rf"that it is the GNSS's NMEA output and its baud rate \(--baud, now {port.baudrate}\)", said[0]), said
        port.write(RMC)
        assert wait_until(lambda: "NMEA sentences again" in caplog.text)
