"""NMEA 0183 input from a GNSS compass or INS: bytes -> sentences -> messages -> heading, fix, UTC.

Pure: bytes and timestamps in, values out; no I/O, no clock. ``drivers/gnss.py`` is the I/O
shell around it and ``docs/gnss.md`` the specification (if they disagree, it is a bug).

Three stages, each usable and tested alone:

- :class:`NmeaFramer`: bytes in any chunks -> :class:`Sentence` (checksum checked). It
  resynchronises on every ``$`` and counts what it drops: ``garbage_bytes``, ``truncated``,
  ``overlong``, ``malformed``, ``bad_checksum``; ``no_checksum`` sentences are accepted and counted.
- :func:`decode_sentence`: a sentence -> one typed message (:class:`Hdt`, :class:`Ths`,
  :class:`Hdg`, :class:`Pashr`, :class:`Rmc`, :class:`Gga`, :class:`Zda`), any talker, or None
  for sentences it does not use. Angles become radians here; an empty field becomes None.
- :class:`GnssTracker`: messages + the monotonic time they arrived -> :class:`GnssUpdate`
  (a :class:`HeadingSample`, a :class:`~rig.types.GnssFix` and/or a UTC time), applying the
  validity rules and giving GGA and PASHR times their date.

:class:`NmeaStream` chains the three with one set of counters.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import date
from typing import Any

from rig.errors import ProtocolError, ValidationError
from rig.protocol import NMEA_MAX_LEN, nmea_checksum
from rig.types import Attitude, GnssFix, HeadingRef, utc_iso

TWO_PI = 2.0 * math.pi
DAY_NS = 86_400 * 10**9
_EPOCH_ORDINAL = date(1970, 1, 1).toordinal()

# The standard allows 82 characters with '$' and CRLF, but real receivers exceed it: Trimble's GGA
# with 8-decimal minutes is 92 (nmea-rtk.log), Skytraq's PSTI,030 is 104. Lines up to this length
# are decoded (and counted in ``long_lines``); a longer one is noise or two sentences run together.
MAX_SENTENCE_LEN = 160

FRAMER_COUNTS = (
    "sentences",  # lines handed on (checksum good, or absent and accepted)
    "no_checksum",  # sentences without *HH (accepted unless require_checksum)
    "bad_checksum",  # *HH present and wrong: dropped
    "truncated",  # a sentence cut short by the next '$' (or by the end of the stream): dropped
    "overlong",  # longer than max_len without a line end: dropped
    "long_lines",  # longer than the standard's 82 characters but within max_len: decoded anyway
    "malformed",  # a line that is not a sentence (bad bytes, bad address, '*' not followed by HH)
    "garbage_bytes",  # bytes outside any sentence (line ends between sentences do not count)
)
STREAM_COUNTS = (
    "decoded",  # sentences turned into a message
    "ignored",  # valid sentences of a type this decoder does not use (GSV, GSA, VTG, PSTI, ...)
    "bad_fields",  # a sentence of a known type whose fields are wrong (too few, out of range, bad text)
    "no_data",  # a valid sentence that says "no data": $GPHDT,,T, THS mode V, RMC status V, GGA quality 0
    "undated",  # a GGA/PASHR time before any RMC/ZDA gave the date: kept without UTC (or, GGA, no fix)
    "headings",  # HeadingSamples made
    "fixes",  # GnssFixes made
)

_LINE_END_OR_START = re.compile(rb"[\r\n$]")
_ADDRESS = re.compile(r"[A-Z][A-Z0-9]{2,9}")
_HEX2 = re.compile(rb"[0-9A-Fa-f]{2}")


def _not_separators(chunk: bytes | bytearray) -> int:
    """Bytes of ``chunk`` that are neither CR nor LF: line ends between sentences are not garbage."""
    return len(chunk) - chunk.count(b"\r") - chunk.count(b"\n")


# ---------------------------------------------------------------------------------------------
# Framing: bytes -> sentences
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Sentence:
    """One framed sentence. ``kind`` is the sentence formatter (``HDT``) for a standard sentence,
    or the whole address (``PASHR``) for a proprietary one; ``talker`` is ``GP``, ``GN``, ``HE``,
    ``IN``, ... or ``P``. ``fields`` are the comma-separated fields after the address."""

    talker: str
    kind: str
    fields: tuple[str, ...]
    checksum: bool


class NmeaFramer:
    """Feed it bytes as they arrive, in any chunks; it returns the sentences completed.

    A sentence starts at ``$`` and ends at CR or LF. A new ``$`` before the line end means the
    sentence was cut short (a lost byte, a reconnect): it is dropped as ``truncated`` and framing
    restarts there. ``require_checksum=True`` drops sentences without ``*HH`` instead of accepting
    them (they are counted in ``no_checksum`` either way).
    """

    def __init__(self, *, max_len: int = MAX_SENTENCE_LEN, require_checksum: bool = False) -> None:
        if max_len < NMEA_MAX_LEN - 2:
            raise ValidationError(f"NmeaFramer.max_len: expected >= {NMEA_MAX_LEN - 2} characters, got {max_len}")
        self._buf = bytearray()
        self._max_len = max_len
        self._require_checksum = require_checksum
        self._discarding = False  # inside an overlong line: drop bytes up to its end (or the next '$')
        self.counts = dict.fromkeys(FRAMER_COUNTS, 0)

    def feed(self, data: bytes) -> list[Sentence]:
        buf = self._buf
        buf += data
        out: list[Sentence] = []
        while buf:
            if self._discarding:
                match = _LINE_END_OR_START.search(buf)
                if match is None:
                    buf.clear()
                    break
                del buf[: match.start()]
                self._discarding = False
                continue
            if buf[0] != 0x24:  # not '$': skip to the next sentence start
                start = buf.find(b"$")
                self.counts["garbage_bytes"] += _not_separators(buf if start < 0 else buf[:start])
                if start < 0:
                    buf.clear()
                    break
                del buf[:start]
            # The sentence ends at the first line end or '$' after its own: searching for the two at
            # once reads each byte once. (A line end first, then a '$' before it, read the rest of
            # the buffer once per '$': a run of them on a noisy line was quadratic.)
            match = _LINE_END_OR_START.search(buf, 1)
            if match is not None and buf[match.start()] == 0x24:
                self.counts["truncated"] += 1
                del buf[: match.start()]
                continue
            if match is None:
                if len(buf) > self._max_len:
                    self.counts["overlong"] += 1
                    buf.clear()
                    self._discarding = True
                break
            end = match.start()
            line = bytes(buf[:end])
            del buf[: end + 1]
            sentence = self._parse(line)
            if sentence is not None:
                out.append(sentence)
        return out

    def flush(self) -> list[Sentence]:
        """The end of the stream: a last sentence without its line end is decoded if its checksum
        is there (captures often lack the final newline), else counted as truncated."""
        pending, self._buf = bytes(self._buf), bytearray()
        discarding, self._discarding = self._discarding, False
        if not pending or discarding:
            return []
        if len(pending) >= 4 and pending[-3:-2] == b"*" and _HEX2.fullmatch(pending[-2:]):
            sentence = self._parse(pending)
            return [] if sentence is None else [sentence]
        self.counts["truncated"] += 1
        return []

    def reset(self) -> None:
        """Forget a partial sentence (the port was reopened: its tail will never come)."""
        if self._buf.startswith(b"$"):
            self.counts["truncated"] += 1
        self._buf.clear()
        self._discarding = False

    def _parse(self, line: bytes) -> Sentence | None:
        """One line from '$' to before its line end -> a Sentence, or None (counted)."""
        if len(line) > self._max_len:
            self.counts["overlong"] += 1
            return None
        # NMEA is printable ASCII; anything else is line noise or binary (a UBX frame, a wrong baud).
        if not all(0x20 <= b <= 0x7E for b in line):
            self.counts["malformed"] += 1
            return None
        star = line.rfind(b"*")
        if star >= 0:
            if len(line) - star != 3 or not _HEX2.fullmatch(line[star + 1 :]):
                self.counts["malformed"] += 1
                return None
            body = line[1:star]
            if nmea_checksum(body) != int(line[star + 1 :], 16):
                self.counts["bad_checksum"] += 1
                return None
        else:
            body = line[1:]
        fields = body.decode("ascii").split(",")
        address = fields[0]
        if not _ADDRESS.fullmatch(address) or (address[0] != "P" and len(address) != 5):
            self.counts["malformed"] += 1
            return None
        if star < 0:
            self.counts["no_checksum"] += 1
            if self._require_checksum:
                return None
        if address[0] == "P":  # proprietary: P + maker code + type, no talker
            talker, kind = "P", address
        else:
            talker, kind = address[:2], address[2:]
        self.counts["sentences"] += 1
        if len(line) + 2 > NMEA_MAX_LEN:
            self.counts["long_lines"] += 1
        return Sentence(talker=talker, kind=kind, fields=tuple(fields[1:]), checksum=star >= 0)


def parse_sentence(line: bytes | str, *, require_checksum: bool = False) -> Sentence:
    """One complete sentence (with or without its line end) -> Sentence; ProtocolError if it is not one."""
    if isinstance(line, str):
        line = line.encode("ascii", "replace")
    framer = NmeaFramer(require_checksum=require_checksum)
    out = framer.feed(line.rstrip(b"\r\n") + b"\r\n")
    if len(out) != 1:
        why = [k for k in ("bad_checksum", "no_checksum", "truncated", "overlong", "malformed") if framer.counts[k]]
        raise ProtocolError(f"not an NMEA sentence ({', '.join(why) or 'no $'}): {line[:40]!r}", "framing")
    return out[0]


# ---------------------------------------------------------------------------------------------
# Decoding: sentence -> typed message
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Hdt:
    """HDT: true heading. ``heading_rad`` None: the field was empty (no heading)."""

    talker: str
    heading_rad: float | None


@dataclass(frozen=True, slots=True)
class Ths:
    """THS: true heading and its mode: A autonomous, E estimated (dead reckoning), M manual input,
    S simulator, V not valid."""

    talker: str
    heading_rad: float | None
    mode: str


@dataclass(frozen=True, slots=True)
class Hdg:
    """HDG: magnetic sensor heading, deviation and variation (east positive, west negative)."""

    talker: str
    magnetic_rad: float | None
    deviation_rad: float | None
    variation_rad: float | None


@dataclass(frozen=True, slots=True)
class Pashr:
    """PASHR (the OxTS / Applanix / Trimble / NovAtel attitude form, not Ashtech's PASHR,xxx):
    UTC time of day, heading (true when ``true_north``), roll, pitch, heave and quality flags.
    Roll positive right side down, pitch positive nose up: the vendors' Tait-Bryan convention,
    which is ours (docs/conventions.md), so no sign changes."""

    time_of_day_ns: int | None
    heading_rad: float | None
    true_north: bool
    roll_rad: float | None
    pitch_rad: float | None
    heave_m: float | None
    gnss_quality: int | None
    imu_status: int | None


@dataclass(frozen=True, slots=True)
class Rmc:
    """RMC: time, status (A valid), position, date (year, month, day) and FAA mode (NMEA 2.3+)."""

    talker: str
    time_of_day_ns: int | None
    valid: bool
    lat_deg: float | None
    lon_deg: float | None
    date: tuple[int, int, int] | None
    mode: str | None


@dataclass(frozen=True, slots=True)
class Gga:
    """GGA: time of day (no date), position, fix quality (0 = no fix), altitude above mean sea level."""

    talker: str
    time_of_day_ns: int | None
    lat_deg: float | None
    lon_deg: float | None
    quality: int | None
    alt_msl_m: float | None


@dataclass(frozen=True, slots=True)
class Zda:
    """ZDA: UTC time of day and date (4-digit year)."""

    talker: str
    time_of_day_ns: int | None
    date: tuple[int, int, int] | None


Message = Hdt | Ths | Hdg | Pashr | Rmc | Gga | Zda

# Fewest fields (after the address) each sentence must have. Without a checksum, a line cut short
# but still ended by CRLF would otherwise decode a partial last number as if it were whole.
_MIN_FIELDS = {"HDT": 2, "THS": 2, "HDG": 5, "PASHR": 10, "RMC": 11, "GGA": 14, "ZDA": 6}

_UNSIGNED = re.compile(r"\d+(\.\d*)?|\.\d+")
_SIGNED = re.compile(r"[+-]?(\d+(\.\d*)?|\.\d+)")
_TIME = re.compile(r"(\d{2})(\d{2})(\d{2})(?:\.(\d{1,9}))?")
_LATLON = re.compile(r"(\d{1,3})(\d{2}(?:\.\d+)?)")


def _bad(name: str, text: str, expected: str) -> ProtocolError:
    return ProtocolError(f"NMEA field {name}: {text!r}, expected {expected}", "field")


def _angle_deg(name: str, text: str, lo: float, hi: float, signed: bool = False) -> float | None:
    if not text:
        return None
    if not (_SIGNED if signed else _UNSIGNED).fullmatch(text):
        raise _bad(name, text, "a number of degrees")
    value = float(text)
    if not lo <= value <= hi:
        raise _bad(name, text, f"within [{lo:g}, {hi:g}] deg")
    return value


def _heading_rad(name: str, text: str) -> float | None:
    value = _angle_deg(name, text, 0.0, 360.0)
    return None if value is None else math.radians(value) % TWO_PI


def _signed_rad(name: str, text: str, limit_deg: float) -> float | None:
    value = _angle_deg(name, text, -limit_deg, limit_deg, signed=True)
    return None if value is None else math.radians(value)


def _east_positive(name: str, value_text: str, hemi: str) -> float | None:
    """A deviation or variation with its E/W letter as signed radians (east positive)."""
    value = _angle_deg(name, value_text, 0.0, 180.0)
    if value is None or not hemi:
        return None  # an angle without its direction is not usable
    if hemi not in ("E", "W"):
        raise _bad(f"{name} direction", hemi, "E or W")
    return math.radians(value if hemi == "E" else -value)


def _time_of_day_ns(text: str) -> int | None:
    """``hhmmss[.s...]`` -> ns since midnight, in integers so 20:41:32.040 stays exact."""
    if not text:
        return None
    match = _TIME.fullmatch(text)
    if match is None:
        raise _bad("time", text, "hhmmss.ss")
    h, m, s, frac = match.groups()
    if int(h) > 23 or int(m) > 59 or int(s) > 60:  # 60: a leap second
        raise _bad("time", text, "a time of day")
    ns = ((int(h) * 60 + int(m)) * 60 + int(s)) * 10**9
    return ns + (int(frac.ljust(9, "0")) if frac else 0)


# The years a receiver can report: GPS began in 1980, and RMC's two-digit years end in 2079.
_FIRST_YEAR, _LAST_YEAR = 1980, 2079


def _checked_date(name: str, text: str, year: int, month: int, day: int) -> tuple[int, int, int]:
    if not _FIRST_YEAR <= year <= _LAST_YEAR:
        # A glitched year would pass as a calendar date and overflow the int64 nanoseconds that
        # UTC travels in downstream (they end in 2262).
        raise _bad(name, text, f"a date in {_FIRST_YEAR}-{_LAST_YEAR}")
    try:
        date(year, month, day)
    except ValueError:
        raise _bad(name, text, "a calendar date") from None
    return year, month, day


def _ddmmyy(text: str) -> tuple[int, int, int] | None:
    if not text:
        return None
    if not re.fullmatch(r"\d{6}", text):
        raise _bad("date", text, "ddmmyy")
    yy = int(text[4:6])
    # Two-digit years: 80-99 are 1980-1999 (GPS began in 1980), 00-79 are 2000-2079.
    year = 1900 + yy if yy >= _FIRST_YEAR % 100 else 2000 + yy
    return _checked_date("date", text, year, int(text[2:4]), int(text[0:2]))


def _coordinate(name: str, value: str, hemi: str, positive: str, negative: str, limit: float) -> float | None:
    """``dddmm.mmmm`` + hemisphere -> signed degrees; None when either field is empty."""
    if not value or not hemi:
        return None
    match = _LATLON.fullmatch(value)
    if match is None:
        raise _bad(name, value, "dddmm.mmmm")
    degrees, minutes = int(match.group(1)), float(match.group(2))
    if minutes >= 60.0:
        raise _bad(name, value, "minutes below 60")
    result = degrees + minutes / 60.0
    if result > limit:
        raise _bad(name, value, f"at most {limit:g} deg")
    if hemi not in (positive, negative):
        raise _bad(f"{name} hemisphere", hemi, f"{positive} or {negative}")
    return -result if hemi == negative else result


def _int(name: str, text: str) -> int | None:
    if not text:
        return None
    if not text.isdigit():
        raise _bad(name, text, "an integer")
    return int(text)


def _float(name: str, text: str) -> float | None:
    if not text:
        return None
    if not _SIGNED.fullmatch(text):
        raise _bad(name, text, "a number")
    return float(text)


def decode_sentence(sentence: Sentence) -> Message | None:
    """The typed message of a sentence this decoder uses, or None for any other sentence.

    Raises :class:`ProtocolError` (``reason="field"``) when a known sentence has too few fields
    or a field that cannot be what it claims (out of range, not a number, bad hemisphere).
    """
    kind, f = sentence.kind, sentence.fields
    if kind == "PASHR" and f and f[0] and not f[0][:1].isdigit():
        return None  # Ashtech's own PASHR,POS / PASHR,ATT / ... family: another sentence entirely
    need = _MIN_FIELDS.get(kind)
    if need is None:
        return None
    if len(f) < need:
        raise ProtocolError(f"{kind}: expected at least {need} fields, got {len(f)}; the sentence is cut short",
                            "field")
    t = sentence.talker
    if kind == "HDT":
        if f[1] not in ("T", ""):
            raise _bad("HDT reference", f[1], "T")
        return Hdt(t, _heading_rad("heading", f[0]))
    if kind == "THS":
        return Ths(t, _heading_rad("heading", f[0]), f[1])
    if kind == "HDG":
        return Hdg(
            t,
            _heading_rad("magnetic heading", f[0]),
            _east_positive("deviation", f[1], f[2]),
            _east_positive("variation", f[3], f[4]),
        )
    if kind == "PASHR":
        return Pashr(
            time_of_day_ns=_time_of_day_ns(f[0]),
            heading_rad=_heading_rad("heading", f[1]),
            true_north=f[2] == "T",
            roll_rad=_signed_rad("roll", f[3], 180.0),
            pitch_rad=_signed_rad("pitch", f[4], 90.0),
            heave_m=_float("heave", f[5]),
            gnss_quality=_int("quality", f[9]),
            imu_status=_int("IMU status", f[10]) if len(f) > 10 else None,
        )
    if kind == "RMC":
        if f[1] not in ("A", "V"):
            raise _bad("RMC status", f[1], "A or V")
        return Rmc(
            t,
            _time_of_day_ns(f[0]),
            f[1] == "A",
            _coordinate("latitude", f[2], f[3], "N", "S", 90.0),
            _coordinate("longitude", f[4], f[5], "E", "W", 180.0),
            _ddmmyy(f[8]),
            f[11] if len(f) > 11 and f[11] else None,
        )
    if kind == "GGA":
        return Gga(
            t,
            _time_of_day_ns(f[0]),
            _coordinate("latitude", f[1], f[2], "N", "S", 90.0),
            _coordinate("longitude", f[3], f[4], "E", "W", 180.0),
            _int("quality", f[5]),
            _float("altitude", f[8]),
        )
    # ZDA
    day, month, year = f[1], f[2], f[3]
    zda_date = None
    if day and month and year:
        if not (day.isdigit() and month.isdigit() and re.fullmatch(r"\d{4}", year)):
            raise _bad("ZDA date", f"{day},{month},{year}", "dd,mm,yyyy")
        zda_date = _checked_date("ZDA date", f"{day},{month},{year}", int(year), int(month), int(day))
    return Zda(t, _time_of_day_ns(f[0]), zda_date)


# ---------------------------------------------------------------------------------------------
# Tracking: messages + arrival times -> heading, fix and UTC
# ---------------------------------------------------------------------------------------------


# How far CLOCK_BOOTTIME - CLOCK_MONOTONIC may move between two reads before the host was suspended
# between them. The difference grows by exactly the time spent suspended (NTP slews both clocks
# alike), but it is two clock reads one after the other, so a thread preempted between them sees it
# move by the preemption (ms on a busy host). A suspend shorter than this goes unseen: it leaves a
# UTC at most this late (0.002 deg of sun), and bridges samples at most this much further apart.
SUSPEND_TOLERANCE_S = 0.5


def suspended_between(then_s: float | None, now_s: float | None) -> bool:
    """Whether the host was suspended between two reads of CLOCK_BOOTTIME - CLOCK_MONOTONIC
    (``drivers.gnss.boottime_offset_s``, ``HeadingSample.boot_offset_s``); False when either is unknown."""
    return then_s is not None and now_s is not None and abs(now_s - then_s) > SUSPEND_TOLERANCE_S


@dataclass(frozen=True, slots=True)
class HeadingSample:
    """A valid heading as it arrived. ``t_mono_s``: the monotonic time its line end was read
    (so it lags the measurement by the transmit time and the device's own latency);
    ``utc_ns``: the measurement's UTC when the sentence carries a time (PASHR), else None.
    ``boot_offset_s``: CLOCK_BOOTTIME - CLOCK_MONOTONIC when it was read (the time the host had spent
    suspended so far; the reader sets it), or None where unknown. The monotonic clock stands still
    while the host is suspended, so two samples around a suspend look as close as their stamps say:
    this tells them apart (:func:`suspended_between`)."""

    t_mono_s: float
    heading_rad: float
    reference: HeadingRef
    pitch_rad: float | None
    roll_rad: float | None
    source_sentence: str
    utc_ns: int | None
    # Which zero a relative heading counts from (Attitude.epoch): visual odometry starts a new one
    # where it cannot carry its heading over (a gap in the frames, a new camera mode). 0 otherwise.
    epoch: int = 0
    boot_offset_s: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.t_mono_s) and math.isfinite(self.heading_rad)):
            raise ValidationError(f"HeadingSample: expected finite time and heading, got {self.t_mono_s}, "
                                  f"{self.heading_rad}")
        if self.boot_offset_s is not None and not math.isfinite(self.boot_offset_s):
            raise ValidationError(f"HeadingSample.boot_offset_s: expected finite seconds or None, got "
                                  f"{self.boot_offset_s}")
        object.__setattr__(self, "heading_rad", self.heading_rad % TWO_PI)
        object.__setattr__(self, "reference", HeadingRef(self.reference))

    def attitude(self) -> Attitude:
        return Attitude(self.heading_rad, self.reference, pitch_rad=self.pitch_rad, roll_rad=self.roll_rad,
                        epoch=self.epoch)


@dataclass(frozen=True, slots=True)
class HeadingReading:
    """The newest heading at a moment and how old it was then (see :func:`newest_heading`)."""

    sample: HeadingSample
    age_s: float

    @property
    def heading_rad(self) -> float:
        return self.sample.heading_rad

    @property
    def reference(self) -> HeadingRef:
        return self.sample.reference

    def attitude(self) -> Attitude:
        return self.sample.attitude()


@dataclass(frozen=True, slots=True)
class GnssUpdate:
    """What one sentence contributed: a heading, a fix and/or a UTC time (at least one is set)."""

    t_mono_s: float
    sentence: str
    heading: HeadingSample | None = None
    fix: GnssFix | None = None
    utc_ns: int | None = None

    def to_json_dict(self) -> dict[str, Any]:
        """The ``sunrig gnss --jsonl`` view: degrees; keys only for what the sentence gave."""
        out: dict[str, Any] = {"t": self.t_mono_s, "sentence": self.sentence}
        if self.heading is not None:
            out["heading_deg"] = round(math.degrees(self.heading.heading_rad), 6)
            out["heading_ref"] = self.heading.reference.value
            if self.heading.pitch_rad is not None:
                out["pitch_deg"] = round(math.degrees(self.heading.pitch_rad), 6)
            if self.heading.roll_rad is not None:
                out["roll_deg"] = round(math.degrees(self.heading.roll_rad), 6)
        if self.utc_ns is not None:
            out["utc"] = utc_iso(self.utc_ns)
        if self.fix is not None:
            out["lat"] = round(self.fix.lat_deg, 10)
            out["lon"] = round(self.fix.lon_deg, 10)
            if self.fix.alt_m is not None:
                out["alt_m"] = self.fix.alt_m
        return out


def utc_ns_from_date(ymd: tuple[int, int, int], time_of_day_ns: int) -> int:
    return (date(*ymd).toordinal() - _EPOCH_ORDINAL) * DAY_NS + time_of_day_ns


THS_VALID_MODES = frozenset("AEMS")  # V (not valid), an empty or an unknown mode: no heading


class GnssTracker:
    """Turns messages into updates, one per sentence that gives something. Holds one piece of
    state: the newest full UTC, which dates the GGA and PASHR times of day that follow.

    Validity: see docs/gnss.md. Counts ``no_data``, ``undated``, ``headings`` and ``fixes``.
    """

    def __init__(self) -> None:
        self._anchor_utc_ns: int | None = None  # newest UTC known with its date
        self.counts = dict.fromkeys(("no_data", "undated", "headings", "fixes"), 0)

    def update(self, msg: Message, t_mono_s: float) -> GnssUpdate | None:
        if isinstance(msg, Hdt | Ths | Hdg | Pashr):
            heading = self._heading(msg, t_mono_s)
            if heading is None:
                self.counts["no_data"] += 1
                return None
            self.counts["headings"] += 1
            return GnssUpdate(t_mono_s, heading.source_sentence, heading=heading, utc_ns=heading.utc_ns)
        if isinstance(msg, Rmc):
            if not msg.valid or msg.mode == "N" or msg.time_of_day_ns is None or msg.date is None:
                self.counts["no_data"] += 1
                return None
            utc = self._set_anchor(utc_ns_from_date(msg.date, msg.time_of_day_ns))
            return GnssUpdate(t_mono_s, "RMC", fix=self._fix(utc, msg.lat_deg, msg.lon_deg, None), utc_ns=utc)
        if isinstance(msg, Gga):
            if not msg.quality or msg.lat_deg is None or msg.lon_deg is None or msg.time_of_day_ns is None:
                self.counts["no_data"] += 1
                return None
            utc_ns = self._dated(msg.time_of_day_ns)
            if utc_ns is None:
                self.counts["undated"] += 1
                return None
            return GnssUpdate(t_mono_s, "GGA", fix=self._fix(utc_ns, msg.lat_deg, msg.lon_deg, msg.alt_msl_m),
                              utc_ns=utc_ns)
        if isinstance(msg, Zda):
            if msg.time_of_day_ns is None or msg.date is None:
                self.counts["no_data"] += 1
                return None
            return GnssUpdate(t_mono_s, "ZDA", utc_ns=self._set_anchor(utc_ns_from_date(msg.date, msg.time_of_day_ns)))
        raise TypeError(f"GnssTracker.update: not a message: {type(msg).__name__}")

    def _heading(self, msg: Hdt | Ths | Hdg | Pashr, t_mono_s: float) -> HeadingSample | None:
        pitch = roll = None
        utc = None
        reference = HeadingRef.TRUE
        if isinstance(msg, Hdt):
            name, heading = "HDT", msg.heading_rad
        elif isinstance(msg, Ths):
            name, heading = "THS", msg.heading_rad if msg.mode in THS_VALID_MODES else None
        elif isinstance(msg, Hdg):
            name, heading = "HDG", msg.magnetic_rad
            if heading is not None:
                # true = magnetic sensor heading + deviation + variation (east positive). A missing
                # deviation means the sensor applied its own (or has none); a missing variation
                # leaves a magnetic heading, which says so rather than pass for true.
                heading += msg.deviation_rad or 0.0
                if msg.variation_rad is None:
                    reference = HeadingRef.MAGNETIC
                else:
                    heading += msg.variation_rad
        else:
            name = "PASHR"
            # Without the T flag the heading's reference is unknown: no heading rather than a guess.
            heading = msg.heading_rad if msg.true_north else None
            pitch, roll = msg.pitch_rad, msg.roll_rad
            if heading is not None and msg.time_of_day_ns is not None:
                utc = self._dated(msg.time_of_day_ns)
                if utc is None:
                    self.counts["undated"] += 1
        if heading is None:
            return None
        return HeadingSample(t_mono_s, heading, reference, pitch, roll, name, utc)

    def suspended(self, duration_s: float) -> None:
        """The host was suspended for ``duration_s``, which the arrival times do not count: the
        newest UTC, which dates the next GGA and PASHR times of day, moves on by it. (Left where it
        was, after a night suspended a GGA at 16:41 took the date before the suspend.)"""
        if self._anchor_utc_ns is not None:
            self._anchor_utc_ns += round(duration_s * 1e9)

    def _fix(self, utc_ns: int, lat: float | None, lon: float | None, alt: float | None) -> GnssFix | None:
        if lat is None or lon is None:
            return None
        self.counts["fixes"] += 1
        return GnssFix(utc_ns=utc_ns, lat_deg=lat, lon_deg=lon, alt_m=alt)

    def _set_anchor(self, utc_ns: int) -> int:
        self._anchor_utc_ns = utc_ns
        return utc_ns

    def _dated(self, time_of_day_ns: int) -> int | None:
        """A time of day on the day nearest the newest known UTC: a GGA at 00:00:00.1 after an RMC
        at 23:59:59.9 belongs to the next day, a late GGA at 23:59:59.9 after midnight to the one before."""
        anchor = self._anchor_utc_ns
        if anchor is None:
            return None
        utc = anchor - anchor % DAY_NS + time_of_day_ns
        if utc - anchor > DAY_NS // 2:
            utc -= DAY_NS
        elif anchor - utc > DAY_NS // 2:
            utc += DAY_NS
        return self._set_anchor(utc)


# ---------------------------------------------------------------------------------------------
# The chain, and what a reader asks of what it kept
# ---------------------------------------------------------------------------------------------


class NmeaStream:
    """Framer, decoder and tracker in one: ``feed(bytes, t_mono_s)`` -> updates. ``counts`` joins
    the three stages' counters (FRAMER_COUNTS + STREAM_COUNTS)."""

    def __init__(self, *, max_len: int = MAX_SENTENCE_LEN, require_checksum: bool = False) -> None:
        self.framer = NmeaFramer(max_len=max_len, require_checksum=require_checksum)
        self.tracker = GnssTracker()
        self._counts = dict.fromkeys(("decoded", "ignored", "bad_fields"), 0)

    def feed(self, data: bytes, t_mono_s: float) -> list[GnssUpdate]:
        """Every sentence completed by ``data`` is stamped ``t_mono_s``: when its line end arrived."""
        return self._track(self.framer.feed(data), t_mono_s)

    def flush(self, t_mono_s: float) -> list[GnssUpdate]:
        """End of the stream (end of a capture file)."""
        return self._track(self.framer.flush(), t_mono_s)

    def reset(self) -> None:
        """The byte stream was broken (a reopened port): drop a partial sentence."""
        self.framer.reset()

    def suspended(self, duration_s: float) -> None:
        """The host was suspended for ``duration_s`` (the reader saw CLOCK_BOOTTIME - CLOCK_MONOTONIC
        move): drop a partial sentence, which may be from before it, and move the date on by it."""
        self.framer.reset()
        self.tracker.suspended(duration_s)

    @property
    def counts(self) -> dict[str, int]:
        return {**self.framer.counts, **self._counts, **self.tracker.counts}

    def _track(self, sentences: Iterable[Sentence], t_mono_s: float) -> list[GnssUpdate]:
        out = []
        for sentence in sentences:
            try:
                msg = decode_sentence(sentence)
            except ProtocolError:
                self._counts["bad_fields"] += 1
                continue
            if msg is None:
                self._counts["ignored"] += 1
                continue
            self._counts["decoded"] += 1
            update = self.tracker.update(msg, t_mono_s)
            if update is not None:
                out.append(update)
        return out


def newest_heading(samples: Iterable[HeadingSample], now_s: float, max_age_s: float) -> HeadingReading | None:
    """The newest sample received at or before ``now_s``, with its age, or None if it is older
    than ``max_age_s`` (or there is none). Samples received after ``now_s`` are not used: a frame
    exposed at ``now_s`` must not take a heading from its future. ``samples``: oldest first."""
    for sample in reversed(list(samples)):
        if sample.t_mono_s <= now_s:
            age = now_s - sample.t_mono_s
            return HeadingReading(sample, age) if age <= max_age_s else None
    return None
