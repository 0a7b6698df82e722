"""drivers/nmea.py at its edges: the limits and defaults docs/gnss.md states (line lengths, printable
ASCII, addresses, line ends, field ranges, the years 1980-2079, the 12-hour dating rule, staleness),
each pinned on both sides. The sentences are real ones (rst39.log, skytraq-PX1172RH_DS.log) or
built from them, with checksums from the project's helper. Split from test_gnss_nmea.py, whose
helpers these tests reuse.
"""

from __future__ import annotations

import math

import pytest

from drivers.nmea import (
    HeadingSample,
    NmeaFramer,
    NmeaStream,
    Pashr,
    Rmc,
    decode_sentence,
    newest_heading,
    parse_sentence,
)
from rig.errors import ProtocolError, ValidationError
from rig.types import HeadingRef
from tests.test_gnss_nmea import GGA, HDT_10, RMC, feed_chunks, headings_deg, nmea, updates_of

# rst39.log's first PASHR (OxTS), as in test_pashr_layout_and_signs
PASHR_FIELDS = "204132.000,010.51,T,+00.39,-00.79,-00.84,0.151,0.075,0.555,1"


def decode(body: str):
    return decode_sentence(parse_sentence(nmea(body)))


def utcs(updates) -> list[str]:
    return [u.to_json_dict()["utc"] for u in updates]


# --- framing ---------------------------------------------------------------------------------


def test_a_sentence_without_checksum_is_accepted_by_default_at_every_entry_point():
    line = b"$HEHDT,12.50,T"
    [sentence] = NmeaFramer().feed(line + b"\r\n")
    assert sentence.kind == "HDT" and sentence.checksum is False
    assert parse_sentence(line).checksum is False
    with pytest.raises(ProtocolError, match="no_checksum"):
        parse_sentence(line, require_checksum=True)


def test_max_len_must_hold_a_standard_sentence():
    # 82 characters with '$' and CRLF: 80 from '$' to before the line end is the least max_len.
    assert NmeaFramer(max_len=80).feed(HDT_10)[0].kind == "HDT"
    with pytest.raises(ValidationError, match=">= 80 characters, got 79"):
        NmeaFramer(max_len=79)


def test_a_line_of_160_characters_is_decoded_and_161_is_overlong():
    at_limit = nmea("GPHDT,10." + "0" * 145 + ",T")  # a heading with many decimals
    over = nmea("GPHDT,10." + "0" * 146 + ",T")
    assert len(at_limit.rstrip(b"\r\n")) == 160 and len(over.rstrip(b"\r\n")) == 161
    # whole (the line end comes with it) and byte by byte (the line end comes after 160 bytes)
    for sizes in ([10_000], [1] * 400):
        out, counts = feed_chunks(at_limit + over + HDT_10, sizes)
        assert headings_deg(out) == [10.0, 10.0]
        assert counts["overlong"] == 1 and counts["long_lines"] == 1 and counts["sentences"] == 2


def test_a_long_line_is_one_over_the_standards_82_characters():
    # rst39.log's GGA with its geoid separation filled in: 82 characters with CRLF, then 83.
    standard = nmea("GPGGA,204132.10,4205.733715,N,08802.040978,W,2,08,1.0,221.9,M,-33.8,M,3,0138")
    longer = nmea("GPGGA,204132.10,4205.733715,N,08802.040978,W,2,08,1.0,221.92,M,-33.8,M,3,0138")
    assert (len(standard), len(longer)) == (82, 83)
    _, counts = feed_chunks(standard, [1000])
    assert counts["sentences"] == 1 and counts["long_lines"] == 0
    _, counts = feed_chunks(longer, [1000])
    assert counts["sentences"] == 1 and counts["long_lines"] == 1


def test_lf_only_and_cr_only_line_ends_lose_no_sentence():
    lines = [nmea(f"GPHDT,{h}.00,T").rstrip(b"\r\n") for h in (10, 20, 30)]
    for end in (b"\n", b"\r"):
        data = end.join(lines) + end
        for sizes in ([1000], [1] * 200):
            out, counts = feed_chunks(data, sizes)
            assert headings_deg(out) == [10.0, 20.0, 30.0] and counts["garbage_bytes"] == 0


def test_a_lone_dollar_before_a_sentence_is_truncated_and_the_sentence_kept():
    for sizes in ([1000], [1] * 100):
        out, counts = feed_chunks(b"$" + HDT_10, sizes)
        assert headings_deg(out) == [10.0] and counts["truncated"] == 1 and counts["bad_checksum"] == 0


def test_an_address_must_be_talker_and_formatter_or_proprietary():
    # Standard addresses are 5 upper-case characters; a proprietary one (P...) may be shorter or longer.
    bad = [nmea("GPHDTX,10.00,T"), nmea("gphdt,10.00,T"), nmea("GPHD,10.00,T")]
    psti = b"$PSTI,036,003832.000,290322,244.28,2.77,0.00,R*5D\r\n"  # skytraq-PX1172RH_DS.log
    out, counts = feed_chunks(b"".join(bad) + psti + HDT_10, [1000])
    assert headings_deg(out) == [10.0]
    assert counts["malformed"] == 3 and counts["sentences"] == 2 and counts["ignored"] == 1


def test_printable_ascii_is_space_to_tilde():
    out, counts = feed_chunks(
        nmea("GPTXT,01,01,02,ANTENNA OK")  # u-blox's text sentence: a space is printable
        + nmea("GPTXT,01,01,02,A~B")
        + nmea("GPTXT,01,01,02,A\x7fB"),  # DEL is not
        [1000],
    )
    assert out == [] and counts["ignored"] == 2 and counts["malformed"] == 1


def test_after_a_reset_framing_starts_afresh():
    framer = NmeaFramer()
    framer.feed(b"$GPHDT," + b"1" * 200)  # overlong, no line end yet: its rest would be dropped
    framer.reset()  # the port was reopened: what comes next is not that line's rest
    assert [s.kind for s in framer.feed(b"tail\r\n" + HDT_10)] == ["HDT"]
    assert framer.counts["garbage_bytes"] == 4 and framer.counts["truncated"] == 0
    framer.feed(b"$GPHDT,1")
    framer.reset()
    assert framer.counts["truncated"] == 1 and framer.feed(HDT_10)[0].fields == ("10.00", "T")


# --- fields ----------------------------------------------------------------------------------


def test_time_of_day_up_to_a_leap_second_and_whole_seconds_are_exact():
    assert decode("GPZDA,204133,19,02,2014,,").time_of_day_ns == (20 * 3600 + 41 * 60 + 33) * 10**9
    assert decode("GPZDA,235960.00,31,12,2016,,").time_of_day_ns == 86_400 * 10**9  # the leap second
    for bad_time in ("235961.00", "236000.00"):
        with pytest.raises(ProtocolError, match="time"):
            decode(f"GPZDA,{bad_time},31,12,2016,,")


def test_dates_from_1980_to_2079_and_two_digit_years():
    gps_epoch_ns = 315_964_800 * 10**9  # 1980-01-06T00:00:00Z
    out, counts = updates_of(
        nmea("GPRMC,000000.00,A,4205.733476,N,08802.041110,W,0.0,0.0,060180,,,A"),  # 80 -> 1980
        nmea("GPRMC,235959.00,A,4205.733476,N,08802.041110,W,0.0,0.0,311279,,,A"),  # 79 -> 2079, December
        nmea("GPZDA,000000.00,06,01,1980,00,00"),
        nmea("GPZDA,235959.00,31,12,2079,00,00"),
        nmea("GPZDA,235959.00,31,12,1979,00,00"),  # before GPS
    )
    assert out[0].utc_ns == gps_epoch_ns and out[2].utc_ns == gps_epoch_ns
    assert utcs(out) == ["1980-01-06T00:00:00.000000Z", "2079-12-31T23:59:59.000000Z",
                         "1980-01-06T00:00:00.000000Z", "2079-12-31T23:59:59.000000Z"]
    assert counts["bad_fields"] == 1


def test_latitude_and_longitude_reach_the_poles_and_the_antimeridian_and_no_further():
    gga = decode("GPGGA,204132.10,9000.0000,N,18000.0000,W,2,08,1.0,221.921,M,,,3,0138")
    assert (gga.lat_deg, gga.lon_deg) == (90.0, -180.0)
    rmc = decode("GPRMC,204132.00,A,9000.0000,S,18000.0000,E,9.415,21.404,190214,,,D")
    assert (rmc.lat_deg, rmc.lon_deg) == (-90.0, 180.0)
    _, counts = updates_of(
        nmea("GPGGA,204132.10,9000.0001,N,08802.040978,W,2,08,1.0,221.921,M,,,3,0138"),
        nmea("GPGGA,204132.10,4205.733715,N,18000.0001,W,2,08,1.0,221.921,M,,,3,0138"),
        nmea("GPRMC,204132.00,A,9000.0001,S,08802.041110,W,9.415,21.404,190214,,,D"),
        nmea("GPRMC,204132.00,A,4205.733476,N,18000.0001,E,9.415,21.404,190214,,,D"),
    )
    assert counts["bad_fields"] == 4


def test_a_position_missing_its_number_or_hemisphere_is_no_position_not_a_bad_field():
    out, counts = updates_of(
        nmea("GPRMC,204133.00,A,4205.735585,N,,,8.904,41.865,190214,,,D"),  # no longitude
        nmea("GPGGA,204133.10,4205.735766,,08802.039145,W,2,09,0.9,221.871,M,,,4,0138"),  # no N/S
        nmea("GPGGA,204133.10,,N,08802.039145,W,2,09,0.9,221.871,M,,,4,0138"),  # no latitude
    )
    # The RMC still gives its UTC; neither gives a fix.
    assert utcs(out) == ["2014-02-19T20:41:33.000000Z"] and out[0].fix is None
    assert counts["fixes"] == 0 and counts["no_data"] == 2 and counts["bad_fields"] == 0


def test_the_optional_last_fields_may_be_absent():
    # RMC before NMEA 2.3 has no FAA mode (11 fields); PASHR without the IMU flag has 10.
    rmc = decode("GPRMC,204132.00,A,4205.733476,N,08802.041110,W,9.415,21.404,190214,,")
    assert isinstance(rmc, Rmc) and rmc.valid and rmc.mode is None and rmc.date == (2014, 2, 19)
    assert decode("GPRMC,204132.00,A,4205.733476,N,08802.041110,W,9.415,21.404,190214,,,").mode is None
    pashr = decode(f"PASHR,{PASHR_FIELDS}")
    assert isinstance(pashr, Pashr) and pashr.imu_status is None and pashr.gnss_quality == 1
    out, counts = updates_of(nmea("GPRMC,204132.00,A,4205.733476,N,08802.041110,W,9.415,21.404,190214,,"),
                             nmea(f"PASHR,{PASHR_FIELDS}"))
    assert [u.sentence for u in out] == ["RMC", "PASHR"] and counts["fixes"] == 1 and counts["headings"] == 1


def test_angle_ranges_and_letters():
    # The NMEA manual's HDG example: deviation 0.0 is a deviation, variation 12.6 W.
    hdg = decode("HCHDG,98.3,0.0,E,12.6,W")
    assert hdg.deviation_rad == 0.0 and hdg.variation_rad == pytest.approx(math.radians(-12.6))
    out, counts = updates_of(
        nmea("HCHDG,98.3,0.0,E,180.5,W"),  # a variation beyond 180 deg
        nmea("HCHDG,98.3,+0.5,E,12.6,W"),  # the direction is the letter, not a sign
        nmea("GPHDT,+10.00,T"),  # a heading has no sign
        nmea("PASHR,204132.000,010.51,T,+180.50,-00.79,-00.84,0.151,0.075,0.555,1,0"),  # roll beyond 180
        nmea("GPHDT,10.00,M"),  # HDT is true heading by definition
    )
    assert out == [] and counts["bad_fields"] == 5
    with pytest.raises(ProtocolError, match="HDT reference: 'M'"):
        decode("GPHDT,10.00,M")
    with pytest.raises(ProtocolError, match="RMC status: 'X'"):
        decode("GPRMC,204133.00,X,4205.735585,N,08802.039368,W,8.904,41.865,190214,,,D")


def test_zda_without_its_whole_date_is_no_data_and_a_date_that_is_not_numbers_is_bad():
    out, counts = updates_of(
        nmea("GNZDA,003832.000,29,03,2022,00,00"),  # skytraq-PX1172RH_DS.log
        nmea("GPZDA,204133.000,,,,,"),  # a receiver without a date yet
        nmea("GPZDA,204133.000,19,02,,,"),
        nmea("GPZDA,204133.000,19,Feb,2014,,"),
    )
    assert utcs(out) == ["2022-03-29T00:38:32.000000Z"]
    assert counts["decoded"] == 3 and counts["no_data"] == 2 and counts["bad_fields"] == 1


# --- tracking --------------------------------------------------------------------------------


def test_a_time_of_day_is_dated_within_12_hours_of_the_newest_utc():
    # docs/gnss.md: "on whichever day puts them within 12 hours of it"; exactly 12 hours is within.
    morning = nmea("GPRMC,060000.00,A,4807.038,N,01131.000,E,0.0,0.0,010124,,,A")
    evening = nmea("GPRMC,180000.00,A,4807.038,N,01131.000,E,0.0,0.0,010124,,,A")

    def gga(hhmmss: str) -> bytes:
        return nmea(f"GPGGA,{hhmmss},4807.038,N,01131.000,E,1,08,0.9,545.4,M,46.9,M,,")

    cases = [
        (morning, "180000.00", "2024-01-01T18:00:00.000000Z"),  # 12 h later: same day
        (morning, "180000.10", "2023-12-31T18:00:00.100000Z"),  # 12 h 0.1 s later: the day before
        (evening, "060000.00", "2024-01-01T06:00:00.000000Z"),  # 12 h earlier: same day
        (evening, "055959.90", "2024-01-02T05:59:59.900000Z"),  # 12 h 0.1 s earlier: the day after
    ]
    for rmc, hhmmss, expected in cases:
        out, _ = updates_of(rmc, gga(hhmmss))
        assert utcs(out)[1] == expected, hhmmss


def test_a_pashr_without_its_t_flag_is_no_data_not_undated():
    # Before any date: no heading (its reference is unknown), so nothing waits for a date.
    out, counts = updates_of(nmea("PASHR,204132.000,010.51,,+00.39,-00.79,-00.84,0.151,0.075,0.555,1,0"))
    assert out == [] and counts["no_data"] == 1 and counts["undated"] == 0
    out, counts = updates_of(nmea(f"PASHR,{PASHR_FIELDS},0"))
    assert out[0].heading.utc_ns is None and counts["undated"] == 1


def test_only_gga_has_an_altitude_and_decoded_counts_every_message():
    out, counts = updates_of(RMC, nmea("GPGSV,1,1,04,25,70,260,50"), GGA)
    rmc, gga = (u.to_json_dict() for u in out)
    assert "alt_m" not in rmc and gga["alt_m"] == 221.871
    assert counts["decoded"] == 2 and counts["ignored"] == 1


def test_newest_heading_at_now_and_at_max_age_is_used():
    # "received at or before now_s", "None when ... older than max_age_s": both ends included.
    samples = [HeadingSample(t, math.radians(t), HeadingRef.TRUE, None, None, "HDT", None) for t in (1.0, 2.0, 3.0)]
    reading = newest_heading(samples, now_s=2.0, max_age_s=1.0)
    assert reading.sample is samples[1] and reading.age_s == 0.0
    reading = newest_heading(samples, now_s=4.0, max_age_s=1.0)
    assert reading.sample is samples[2] and reading.age_s == 1.0
    assert reading.attitude() == samples[2].attitude()


def test_a_heading_sample_needs_a_finite_time_and_heading():
    for t, heading in ((1.0, math.nan), (math.inf, 0.0)):
        with pytest.raises(ValidationError, match="finite"):
            HeadingSample(t, heading, HeadingRef.TRUE, None, None, "HDT", None)


def test_a_pashr_before_its_receiver_knows_the_time_still_gives_the_heading():
    # An INS sends an empty time field until GNSS gives it one. That is not Ashtech's PASHR,POS
    # family (whose field 1 is a word), so the heading is kept, without UTC.
    stream = NmeaStream()
    (update,) = stream.feed(nmea("PASHR,," + PASHR_FIELDS.split(",", 1)[1]), 0.0)
    assert update.heading.heading_rad == pytest.approx(math.radians(10.51)) and update.utc_ns is None
    assert stream.counts["headings"] == 1 and stream.counts["ignored"] == 0
    assert decode("PASHR,POS,0,10,204132.00") is None  # the family itself is still left alone
