"""KITTI raw drives as a frame source: the paper's real benchmark, read straight from the files.

Layout (as the dataset ships it)::

    YYYY_MM_DD/                       the date folder
        calib_cam_to_cam.txt          P_rect_02 and S_rect_02 of the left colour camera
        YYYY_MM_DD_drive_NNNN_sync/   a drive ("synced + rectified"): one OXTS record per image
            image_02/timestamps.txt   one line per frame, 9 fractional digits
            image_02/data/0000000000.png ...
            oxts/timestamps.txt, oxts/dataformat.txt, oxts/data/0000000000.txt ...

Either the date folder (holding exactly one drive) or a drive folder can be given; the date
folder is then the drive's parent.

Choices, all stated in ``docs/ground-truth.md``:

- **Camera**: ``image_02`` (left colour), the paper's. Intrinsics from ``P_rect_02`` (fx, fy, cx,
  cy) and the image size from ``S_rect_02``: 721.5377 px, 1242 x 375, 81.43 x 29.12 deg for
  2011_09_26. Images of another size (resized copies) get intrinsics scaled to them, so the field
  of view stays the calibration's.
- **Time**: the timestamps are wall-clock text without a time zone. They are parsed to the
  nanosecond with integer arithmetic, and UTC = timestamp - ``utc_offset_h``. The default is
  :data:`DEFAULT_UTC_OFFSET_H` = +2 h (CEST, in force in Karlsruhe for every KITTI raw date,
  2011-09-26 .. 2011-10-03): we read the timestamps as the recording PC's local clock. That is a
  belief, not a documented fact (KITTI does not say), so leaving the offset to the default logs a
  warning once; pass ``--utc-offset 0`` if you hold them to be UTC. Each hour moves the sun by
  ~15 deg in azimuth. ``t_mono_s`` is seconds since the drive's first image timestamp. A time
  that int64 ns cannot hold (outside the years 1678..2262), as written or as UTC, is a damaged
  record, not a date numpy wraps round to another.
- **Attitude**: OXTS (``dataformat.txt``): yaw 0 = east, counter-clockwise positive; pitch
  positive = front down; roll positive = left side up (a forward-left-up body frame). In sunrig's
  conventions: heading = 90 deg - yaw (clockwise from true north, so the reference is TRUE);
  pitch = -OXTS pitch (positive nose up); roll = +OXTS roll (left side up is right side down,
  sunrig's positive). These are the vehicle's angles: the camera's optical axis is within ~0.5 deg
  of the IMU's forward axis (calib_imu_to_velo + calib_velo_to_cam: 0.06 deg in yaw for
  2011_09_26), below what the estimator can resolve, so it is not applied (the paper neither).
- **Ground truth**: the sun for each frame's UTC time and OXTS position, by NREL's SPA
  (:mod:`rig.solar`), computed for the whole drive when it is opened.
- ``dataformat.txt`` is only a check of the field order: its real typo (line 14 says ``ay``
  where ``az`` is meant) is recognised and taken as ``az``.
"""

from __future__ import annotations

import bisect
import logging
import math
import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from replay.groundtruth import sun_truth_enu
from rig.errors import LogError, ValidationError
from rig.solar import ELEVATION_RANGE_M, NS_YEARS, UTC_NS_MAX, UTC_NS_MIN
from rig.types import Attitude, Frame, GnssFix, HeadingRef, Intrinsics

logger = logging.getLogger(__name__)

DEFAULT_UTC_OFFSET_H = 2.0
CAMERA = "image_02"
CALIB_FILE = "calib_cam_to_cam.txt"
_DRIVE_RE = re.compile(r"^(\d{4}_\d{2}_\d{2})_drive_(\d{4})_sync$")
_EXTRACT_RE = re.compile(r"^(\d{4}_\d{2}_\d{2}_drive_\d{4})_extract$")
_DATE_RE = re.compile(r"^\d{4}_\d{2}_\d{2}$")
_TIMESTAMP_RE = re.compile(r"^\d{4}-\d{2}-\d{2} \d{2}:\d{2}:\d{2}(\.\d{1,9})?$")
_MAX_WARNINGS = 5
# A synced drive's image and OXTS record of one frame are stamped within a few ms (13 ms at most in
# the fixture drive 2011_09_26_0001); a second apart, one of the stamps is damaged.
MAX_IMAGE_OXTS_SKEW_NS = 1_000_000_000

# The 30 OXTS fields in the order of the KITTI devkit's dataformat.txt.
OXTS_FIELDS = (
    "lat", "lon", "alt", "roll", "pitch", "yaw", "vn", "ve", "vf", "vl", "vu", "ax", "ay", "az",
    "af", "al", "au", "wx", "wy", "wz", "wf", "wl", "wu", "pos_accuracy", "vel_accuracy",
    "navstat", "numsats", "posmode", "velmode", "orimode",
)
_USED = ("lat", "lon", "alt", "roll", "pitch", "yaw")
_POSE_RANGE = ((-90.0, 90.0), (-180.0, 180.0), ELEVATION_RANGE_M, (-math.pi, math.pi), (-math.pi, math.pi),
               (-2.0 * math.pi, 2.0 * math.pi))

_warned_default_offset = False


# ------------------------------------------------------------------------------------------
# Pure parsers: text in, arrays out


def parse_timestamps(text: str, name: str = "timestamps.txt") -> list[tuple[int, int]]:
    """Timestamp lines ``YYYY-MM-DD HH:MM:SS.fffffffff`` -> (line number, ns since 1970-01-01 of that
    wall clock) as Python integers, exact for any year written (no time zone applied, no float on
    the way). Whether a time fits in int64 ns is the caller's to check (:func:`in_ns_range`).

    Raises :class:`LogError` naming the first bad line. Blank lines (a trailing newline) are skipped.
    """
    rows, fractions = [], []
    for i, ln in enumerate((ln.strip() for ln in text.splitlines()), 1):
        if not ln:
            continue
        if not _TIMESTAMP_RE.match(ln):
            raise LogError(f"{name} line {i}: expected 'YYYY-MM-DD HH:MM:SS.fffffffff', got {ln[:40]!r}")
        whole, _, fraction = ln.partition(".")
        rows.append((i, whole.replace(" ", "T")))
        fractions.append(int(fraction.ljust(9, "0")))
    try:
        # Whole seconds: datetime64[s] holds every four-digit year, where [ns] wraps past 1678..2262.
        seconds = np.array([r for _, r in rows], dtype="datetime64[s]").view(np.int64).tolist()
    except ValueError as exc:  # a well-formed but impossible date, e.g. month 13
        raise LogError(f"{name}: not a valid date/time: {exc}") from None
    return [(i, sec * 1_000_000_000 + frac) for (i, _), sec, frac in zip(rows, seconds, fractions, strict=True)]


def in_ns_range(t_ns: int) -> bool:
    """Whether a time (int ns since the epoch) fits in int64 ns, as the ephemeris takes it."""
    return UTC_NS_MIN <= t_ns <= UTC_NS_MAX


def show_ns(t_ns: int) -> str:
    """A time of any year (int ns since the epoch) as ISO text to the second, for a message."""
    return str(np.datetime64(t_ns // 1_000_000_000, "s"))


def parse_timestamps_ns(text: str, name: str = "timestamps.txt") -> np.ndarray:
    """:func:`parse_timestamps` as int64 ns, refusing (:class:`LogError` naming the line) a time that
    int64 ns cannot hold (the years 1678..2262) rather than a date wrapped around to another."""
    out = []
    for i, t in parse_timestamps(text, name):
        if not in_ns_range(t):
            raise LogError(f"{name} line {i}: {show_ns(t)} is outside the years {NS_YEARS} that ns since 1970 hold; "
                           "is the file damaged?")
        out.append(t)
    return np.array(out, dtype=np.int64)


UTC_OFFSET_LIMIT_H = 14  # the widest of the world's time zones (Kiribati, +14)


def longest_increasing(values: np.ndarray) -> list[int]:
    """Indices, ascending, of a longest strictly increasing subsequence of ``values`` (one of them
    where several are as long). O(n log n): patience sorting, then back along the predecessors."""
    tails: list[int] = []  # tails[k]: index of the smallest last value of an increasing run of k + 1
    tail_values: list[float] = []
    before = [-1] * len(values)
    for i, v in enumerate(values.tolist()):
        k = bisect.bisect_left(tail_values, v)
        if k:
            before[i] = tails[k - 1]
        if k == len(tails):
            tails.append(i)
            tail_values.append(v)
        else:
            tails[k], tail_values[k] = i, v
    out = []
    i = tails[-1] if tails else -1
    while i >= 0:
        out.append(i)
        i = before[i]
    return out[::-1]


def utc_offset_ns(utc_offset_h: float) -> int:
    """An offset in hours as integer ns (fractional hours allowed: India is +5.5)."""
    lim = UTC_OFFSET_LIMIT_H
    if not (isinstance(utc_offset_h, int | float) and math.isfinite(utc_offset_h) and -lim <= utc_offset_h <= lim):
        raise LogError(f"UTC offset: expected hours within [-{lim}, {lim}], got {utc_offset_h!r}")
    return round(utc_offset_h * 3600) * 1_000_000_000


def parse_dataformat(text: str) -> list[str]:
    """Field names of ``oxts/dataformat.txt``, one per line, in order.

    The real file names field 14 ``ay`` (twice); a name that repeats an earlier one where the
    devkit's order has another name is taken as that name (so its ``ay`` is ``az``).
    """
    names: list[str] = []
    for line in text.splitlines():
        head, sep, _ = line.partition(":")
        if not sep or not head.strip():
            continue
        name = head.strip()
        k = len(names)
        if name in names and k < len(OXTS_FIELDS) and OXTS_FIELDS[k] not in names:
            name = OXTS_FIELDS[k]  # the known typo, or one like it
        names.append(name)
    return names


def parse_oxts(text: str, name: str = "oxts") -> np.ndarray:
    """One OXTS record: 30 numbers on a line -> float64 (30,). Raises :class:`LogError`."""
    try:
        values = np.array([float(v) for v in text.split()], dtype=np.float64)
    except ValueError:
        raise LogError(f"{name}: expected 30 numbers, got {text.strip()[:60]!r}") from None
    if values.shape != (len(OXTS_FIELDS),):
        raise LogError(f"{name}: expected {len(OXTS_FIELDS)} numbers, got {values.size}")
    if not np.all(np.isfinite(values[:6])):
        raise LogError(f"{name}: position or attitude is not finite: {values[:6].tolist()}")
    return values


def oxts_in_range(pose: np.ndarray) -> np.ndarray:
    """Which of lat, lon, alt, roll, pitch, yaw (rows of 6) are in range, as bools of the same shape.

    A place on Earth, an altitude the ephemeris takes (:data:`rig.solar.ELEVATION_RANGE_M`; 1e9 m
    ended the whole drive there), roll and pitch within a half turn, yaw within a turn either way
    (the devkit gives -pi..pi: a yaw of 1e300 would wrap to some heading and be graded as one).
    NaN is out of range.
    """
    lo, hi = np.array(_POSE_RANGE).T
    return (pose >= lo) & (pose <= hi)


def parse_calib(text: str) -> dict[str, np.ndarray]:
    """``key: numbers`` lines of a KITTI calibration file; non-numeric ones (calib_time) are left out."""
    out: dict[str, np.ndarray] = {}
    for line in text.splitlines():
        key, sep, rest = line.partition(":")
        if not sep:
            continue
        try:
            out[key.strip()] = np.array([float(v) for v in rest.split()], dtype=np.float64)
        except ValueError:
            continue
    return out


def intrinsics_from_calib(calib: dict[str, np.ndarray], camera: str = "02", name: str = CALIB_FILE) -> Intrinsics:
    """Rectified intrinsics of camera ``camera``: fx, fy, cx, cy from ``P_rect_XX`` (3 x 4), size
    from ``S_rect_XX`` (width, height)."""
    p, s = calib.get(f"P_rect_{camera}"), calib.get(f"S_rect_{camera}")
    if p is None or p.size != 12 or s is None or s.size != 2:
        raise LogError(f"{name}: no P_rect_{camera} (12 numbers) and S_rect_{camera} (2 numbers); "
                       "is it the date's calib_cam_to_cam.txt?")
    p = p.reshape(3, 4)
    # round() of nan or 1e400 raised ValueError / OverflowError: an internal error, not this file's.
    if not (np.isfinite(s).all() and (s >= 1).all() and (s <= 1e6).all()):
        raise LogError(f"{name}: S_rect_{camera} {' '.join(f'{v:g}' for v in s)} is no image size; "
                       "is the file damaged? Compare it with the date's calib_cam_to_cam.txt from KITTI")
    try:
        return Intrinsics(fx=p[0, 0], fy=p[1, 1], cx=p[0, 2], cy=p[1, 2], width=round(s[0]), height=round(s[1]))
    except ValidationError as exc:  # nan or 0 in P_rect: say which file, not only which number
        raise LogError(f"{name}: P_rect_{camera}: {exc}; is the file damaged? Compare it with the date's "
                       "calib_cam_to_cam.txt from KITTI") from None


def attitude_from_oxts(roll_rad, pitch_rad, yaw_rad) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """OXTS (forward-left-up, yaw 0 = east counter-clockwise) -> sunrig heading, pitch, roll (rad).

    heading = 90 deg - yaw in [0, 2 pi); pitch = -pitch (OXTS front down -> sunrig nose up);
    roll = roll (OXTS left side up = sunrig right side down).
    """
    heading = np.mod(np.pi / 2.0 - np.asarray(yaw_rad, dtype=np.float64), 2.0 * np.pi)
    return heading, -np.asarray(pitch_rad, dtype=np.float64), np.asarray(roll_rad, dtype=np.float64)


def scaled_intrinsics(k: Intrinsics, width: int, height: int) -> Intrinsics:
    """``k`` for the same camera at another image size (about the pixel grid's corner)."""
    sx, sy = width / k.width, height / k.height
    return Intrinsics(fx=k.fx * sx, fy=k.fy * sy, cx=k.cx * sx, cy=k.cy * sy, width=width, height=height)


# ------------------------------------------------------------------------------------------
# Finding the files


def _read_text(path: Path, what: str) -> str:
    try:
        return path.read_text(encoding="utf-8", errors="replace")
    except FileNotFoundError:
        raise LogError(f"{path}: missing ({what})") from None
    except OSError as exc:
        raise LogError(f"{path}: cannot read {what}: {exc.strerror or exc}") from None


def drive_folders(date_dir: Path) -> list[Path]:
    """The ``*_drive_NNNN_sync`` folders of a date folder, in name order."""
    return sorted(p for p in Path(date_dir).iterdir() if p.is_dir() and _DRIVE_RE.match(p.name))


def looks_like_drive(path: Path) -> bool:
    """Whether ``path`` is a drive folder (by its name, or by its image and OXTS folders)."""
    return bool(_DRIVE_RE.match(path.name)) or ((path / "oxts").is_dir() and (path / CAMERA).is_dir())


def drive_files(date_dir: Path, drive_dir: Path) -> list[Path]:
    """The files :class:`KittiDrive` reads of a drive, in a fixed order: the date's calibration,
    then the camera's timestamps and images and the OXTS timestamps, records and data format (not
    the drive's other cameras or velodyne points)."""
    cam_dir, oxts_dir = drive_dir / CAMERA, drive_dir / "oxts"
    used = [date_dir / CALIB_FILE, cam_dir / "timestamps.txt", *sorted((cam_dir / "data").glob("*.png")),
            oxts_dir / "timestamps.txt", *sorted((oxts_dir / "data").glob("*.txt"))]
    if (oxts_dir / "dataformat.txt").is_file():
        used.append(oxts_dir / "dataformat.txt")
    return used


def _missing_calib_message(date_dir: Path, drive_dir: Path) -> str:
    """What to do when the date folder lacks its calibration. KITTI's YYYY_MM_DD_calib.zip holds
    its files under the date (YYYY_MM_DD/calib_cam_to_cam.txt ...), as the drive zips hold
    YYYY_MM_DD/*_sync/: it is unzipped in the date folder's parent, and unzipped in the date
    folder itself it puts them one folder too deep (which the advice "unzip it there" did)."""
    match = _DRIVE_RE.match(drive_dir.name)
    date = match.group(1) if match else date_dir.name if _DATE_RE.match(date_dir.name) else "YYYY_MM_DD"
    for deep in (date_dir / date / CALIB_FILE, *sorted(date_dir.glob(f"*/{CALIB_FILE}"))):
        if deep.is_file() and deep.parent != drive_dir:
            return f"{drive_dir}: {deep} is one folder too deep; move {deep.parent}/calib_*.txt up into {date_dir}"
    head = f"{drive_dir}: no {CALIB_FILE} in its date folder {date_dir}"
    if date_dir.name == date:
        return f"{head}; unzip {date}_calib.zip in {date_dir.parent} (it holds {date}/calib_*.txt)"
    return (f"{head}; take the calib_*.txt files out of the drive's {date}_calib.zip (under its {date}/) "
            "and put them there")


def _unsynced_message(folder: Path, drive: str) -> str:
    """An *_extract drive ("unsynced+unrectified data") has distorted images, which P_rect does not
    describe, and OXTS records at 100 Hz, not one per image: only its _sync twin can be read."""
    return (f"{folder}: an unsynced, unrectified KITTI drive (its images are not rectified, its OXTS runs at "
            f"100 Hz); sunrig reads synced+rectified data: download {drive}_sync.zip and pass its {drive}_sync folder")


def find_drive(path: str | Path) -> tuple[Path, Path]:
    """(date folder, drive folder) for a date folder holding one drive, or a drive folder."""
    p = Path(path)
    if not p.is_dir():
        raise LogError(f"{p}: not a folder; a KITTI drive is a YYYY_MM_DD/ folder or one of its *_drive_NNNN_sync/")
    extract = _EXTRACT_RE.match(p.name)
    if extract:
        raise LogError(_unsynced_message(p, extract.group(1)))
    drive_above = next((q for q in (p.parent, p.parent.parent) if looks_like_drive(q)), None) \
        if not looks_like_drive(p) and p.name != ".." else None
    if drive_above is not None:  # drive/image_03, drive/image_02/data, drive/oxts
        drive_above = drive_above if drive_above.name not in ("", "..") else drive_above.resolve()
        raise LogError(f"{p}: is inside the KITTI drive {drive_above}; pass that drive folder (its image_02 (the left "
                       "colour camera, the paper's) is read; no other camera can be chosen)")
    if looks_like_drive(p):
        # A drive given as "." or "..", whose name is "" or "..", is named by its folder's own name:
        # every message about the drive begins with that name.
        date_dir, drive_dir = p.resolve().parent, p if p.name not in ("", "..") else p.resolve()
    else:
        drives = drive_folders(p)
        logs = [] if drives else sorted(p.glob("*.mcap"))
        if logs:  # a folder of recordings, given where one log is read
            raise LogError(f"{p}: a folder of {len(logs)} native logs, where one log is read; pass one of them "
                           f"(e.g. {logs[0]}), or the folder to sunrig eval / train")
        extracts = [] if drives or logs else sorted(q for q in p.iterdir() if _EXTRACT_RE.match(q.name))
        if extracts:
            match = _EXTRACT_RE.match(extracts[0].name)
            assert match is not None  # as filtered just above
            raise LogError(_unsynced_message(extracts[0], match.group(1)))
        if not drives:
            raise LogError(
                f"{p}: not a KITTI raw drive (no *_drive_NNNN_sync/ folder in it, and it is not one) and not a "
                "native log; pass a .mcap file, a KITTI date folder YYYY_MM_DD/ or one of its drive folders")
        if len(drives) > 1:
            raise LogError(
                f"{p}: holds {len(drives)} KITTI drives ({drives[0].name} ... {drives[-1].name}); pass the drive "
                f"folders (e.g. {p}/*_sync) so that each drive is a log of its own")
        date_dir, drive_dir = p, drives[0]
    if not (date_dir / CALIB_FILE).is_file():
        raise LogError(_missing_calib_message(date_dir, drive_dir))
    for sub in (CAMERA, "oxts"):
        if not (drive_dir / sub).is_dir():
            raise LogError(f"{drive_dir}: no {sub}/ folder; is it a complete *_sync drive?")
    return date_dir, drive_dir


# ------------------------------------------------------------------------------------------
# The source


def _times_in_ns(stamps: list[tuple[int, int]], offset_ns: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(wall clock, UTC) as int64 ns and whether both fit, for :func:`parse_timestamps` output;
    0 where they do not (checked in Python integers, which do not wrap)."""
    held = np.array([in_ns_range(t) and in_ns_range(t - offset_ns) for _, t in stamps], dtype=bool)
    local = np.array([t if ok else 0 for (_, t), ok in zip(stamps, held, strict=True)], dtype=np.int64)
    utc = np.array([t - offset_ns if ok else 0 for (_, t), ok in zip(stamps, held, strict=True)], dtype=np.int64)
    return local, utc, held


def _show_times(t_ns: int, offset_ns: int) -> str:
    return show_ns(t_ns) + (f" (UTC {show_ns(t_ns - offset_ns)})" if offset_ns else "")


class KittiDrive:
    """A KITTI raw drive as a frame source: iterate it for Frames (re-iterable; images are read
    lazily, everything else when it is opened, so a bad drive fails before any work).

    Frames carry the rectified ``image_02``, its intrinsics, a TRUE heading with pitch and roll,
    UTC time, the OXTS fix and the sun from SPA as ``sun_enu_truth``.

    ``corrupt_skipped`` counts the damaged records of the latest pass: OXTS records that do not
    parse or are out of range and OXTS timestamps outside the years int64 ns hold (their frame
    comes without pose), and image timestamps out of order or outside those years and images that
    do not decode (their frame is skipped).
    """

    def __init__(self, path: str | Path, utc_offset_h: float | None = None) -> None:
        global _warned_default_offset
        self.date_dir, self.path = find_drive(path)
        if utc_offset_h is None:
            utc_offset_h = DEFAULT_UTC_OFFSET_H
            if not _warned_default_offset:
                _warned_default_offset = True
                logger.warning(
                    "KITTI timestamps carry no time zone: taking them as UTC%+g h (CEST); if they are UTC, pass "
                    "--utc-offset 0 (each hour moves the sun ~15 deg). See docs/ground-truth.md",
                    DEFAULT_UTC_OFFSET_H)
        self.utc_offset_h = float(utc_offset_h)
        offset_ns = utc_offset_ns(self.utc_offset_h)
        name = self.path.name
        self.corrupt_skipped = 0

        self.intrinsics = intrinsics_from_calib(parse_calib(_read_text(self.date_dir / CALIB_FILE, "calibration")),
                                                CAMERA[-2:], str(self.date_dir / CALIB_FILE))
        cam_dir, oxts_dir = self.path / CAMERA, self.path / "oxts"
        self.images = sorted((cam_dir / "data").glob("*.png"))
        oxts_files = sorted((oxts_dir / "data").glob("*.txt"))
        image_stamps = parse_timestamps(_read_text(cam_dir / "timestamps.txt", "image timestamps"),
                                        f"{name}/{CAMERA}/timestamps.txt")
        oxts_stamps = parse_timestamps(_read_text(oxts_dir / "timestamps.txt", "OXTS timestamps"),
                                       f"{name}/oxts/timestamps.txt")
        counts = {"images": len(self.images), "image timestamps": len(image_stamps),
                  "OXTS records": len(oxts_files), "OXTS timestamps": len(oxts_stamps)}
        if len(set(counts.values())) != 1 or not self.images:
            raise LogError(f"{name}: " + ", ".join(f"{v} {k}" for k, v in counts.items())
                           + "; a sync drive has one of each per frame (re-extract the drive)")
        stems = [p.stem for p in self.images]
        if stems != [f"{i:010d}" for i in range(len(stems))] or [p.stem for p in oxts_files] != stems:
            raise LogError(f"{name}: image and OXTS files are not numbered 0000000000 ... {len(stems) - 1:010d} "
                           "alike; re-extract the drive")

        fmt = oxts_dir / "dataformat.txt"
        if fmt.is_file():
            fields = parse_dataformat(_read_text(fmt, "OXTS data format"))
            if tuple(fields[:6]) != _USED:
                raise LogError(f"{fmt}: fields start {fields[:6]}, expected {list(_USED)}; not a KITTI OXTS format")

        n = len(self.images)
        oxts = np.full((n, 6), np.nan)
        for i, f in enumerate(oxts_files):
            try:
                oxts[i] = parse_oxts(_read_text(f, "OXTS record"), f"{name}/oxts/data/{f.name}")[:6]
            except LogError as exc:  # one bad record costs that frame its pose, not the drive
                self._warn(f"{exc}; frame {i} has no heading, position or truth")
        lat, lon, alt, roll, pitch, yaw = oxts.T
        self.heading_rad, self.pitch_rad, self.roll_rad = attitude_from_oxts(roll, pitch, yaw)
        self.lat_deg, self.lon_deg, self.alt_m = lat, lon, alt
        # A time that int64 ns cannot hold, as written or as UTC, is a damaged record: numpy would
        # wrap it around to another date (2300 to 1715) and the sun be computed for that one.
        image_ns, self.utc_ns, image_time_held = _times_in_ns(image_stamps, offset_ns)
        _, self.oxts_utc_ns, oxts_time_held = _times_in_ns(oxts_stamps, offset_ns)
        for i in np.flatnonzero(~image_time_held).tolist():
            self._warn(f"{name}/{CAMERA}/timestamps.txt line {image_stamps[i][0]}: frame {i}'s time "
                       f"{_show_times(image_stamps[i][1], offset_ns)} is outside the years {NS_YEARS} that ns "
                       "since 1970 hold; frame skipped")
        for i in np.flatnonzero(~oxts_time_held).tolist():
            self._warn(f"{name}/oxts/timestamps.txt line {oxts_stamps[i][0]}: OXTS time "
                       f"{_show_times(oxts_stamps[i][1], offset_ns)} is outside the years {NS_YEARS} that ns "
                       f"since 1970 hold; frame {i} has no heading, position or truth")
        with np.errstate(invalid="ignore"):  # NaN rows (bad records) compare False, as they should
            in_range = oxts_in_range(oxts)
        for i in np.flatnonzero(~np.all(in_range, axis=1) & np.all(np.isfinite(oxts), axis=1)).tolist():
            bad = ", ".join(f"{_USED[k]} {oxts[i, k]:g}" for k in np.flatnonzero(~in_range[i]).tolist())
            self._warn(f"{name}/oxts/data/{oxts_files[i].name}: out of range: {bad}; "
                       f"frame {i} has no heading, position or truth")
        self.pose_ok = np.all(in_range, axis=1) & oxts_time_held
        # The timestamps must increase: a step back would break the monotonic clock downstream.
        # The frames kept are the longest run of increasing times, so that one stamp far ahead
        # costs its own frame, not every frame after it (which a running maximum dropped).
        held = np.flatnonzero(image_time_held)
        self.time_ok = np.zeros(n, dtype=bool)
        self.time_ok[held[longest_increasing(image_ns[held])]] = True
        for i in np.flatnonzero(~self.time_ok & image_time_held).tolist():
            self._warn(f"{name}: frame {i}'s timestamp is out of order with the frames around it; frame skipped")
        # Seconds from the first frame kept, by an exact difference of Python integers (1678 to
        # 2262 is more ns than int64 holds). From a first stamp that was skipped instead, every
        # frame's time was an hour below 0 and `record --camera file:` refused the drive.
        t0 = int(image_ns[np.argmax(self.time_ok)]) if self.time_ok.any() else 0
        self.t_mono_s = np.array([(t - t0) / 1e9 if ok else np.nan
                                  for t, ok in zip(image_ns.tolist(), self.time_ok.tolist(), strict=True)])
        # A synced drive stamps a frame's image and its OXTS record within a few ms of each other.
        # Where they are further apart, one of the two is damaged, and which one is unknown: the
        # truth would be the sun of another instant (a stamp 8 h ahead at a drive's end was kept,
        # being still in increasing order, and graded against a sun below the horizon).
        # In Python integers: two stamps of 1678..2262 can be more ns apart than int64 holds.
        skew_ns = np.array([abs(a - b) for a, b in zip(self.utc_ns.tolist(), self.oxts_utc_ns.tolist(), strict=True)],
                           dtype=np.float64)
        apart = image_time_held & oxts_time_held & (skew_ns > MAX_IMAGE_OXTS_SKEW_NS)
        for i in np.flatnonzero(apart & self.pose_ok & self.time_ok).tolist():  # skipped frames are said once
            self._warn(f"{name}: frame {i}'s image and OXTS timestamps are {skew_ns[i] / 1e9:g} s apart; "
                       f"frame {i} has no heading, position or truth")
        self.pose_ok &= ~apart
        self.sun_enu = np.full((n, 3), np.nan)
        ok = self.pose_ok & self.time_ok
        if np.any(ok):
            self.sun_enu[ok] = sun_truth_enu(self.utc_ns[ok], lat[ok], lon[ok], alt[ok])
        self._intrinsics_by_size: dict[tuple[int, int], Intrinsics] = {}
        # Each pass starts from the damage found here and adds the images it cannot read: one
        # pass's count, as a native log's stats are, so that passes pooled (an evaluation per crop
        # seed) do not count the first pass's images again in the second.
        self._skipped_when_opened = self.corrupt_skipped

    def _warn(self, message: str) -> None:
        self.corrupt_skipped += 1
        if self.corrupt_skipped <= _MAX_WARNINGS:
            logger.warning("%s", message)

    def __len__(self) -> int:
        return len(self.images)

    @property
    def field_of_view_deg(self) -> tuple[float, float]:
        return math.degrees(self.intrinsics.hfov_rad), math.degrees(self.intrinsics.vfov_rad)

    def _intrinsics_for(self, width: int, height: int) -> Intrinsics:
        key = (width, height)
        k = self._intrinsics_by_size.get(key)
        if k is None:
            k = self.intrinsics
            if key != (k.width, k.height):
                # Resized copies keep the aspect ratio up to the rounding of each side to whole pixels.
                off_aspect = abs(height - k.height * width / k.width) > 1.0
                log = logger.warning if off_aspect else logger.info
                log("%s: images are %dx%d, the calibration's %dx%d; intrinsics scaled to them%s", self.path.name,
                    width, height, k.width, k.height,
                    " (the aspect ratio differs: check the calibration)" if off_aspect else "")
                k = scaled_intrinsics(k, width, height)
            self._intrinsics_by_size[key] = k
        return k

    def frame(self, i: int, image_bgr: np.ndarray) -> Frame:
        """Frame ``i`` of the drive around an image (pure: no file access)."""
        attitude = gnss = truth = None
        if self.pose_ok[i]:
            attitude = Attitude(self.heading_rad[i], HeadingRef.TRUE, self.pitch_rad[i], self.roll_rad[i])
            gnss = GnssFix(int(self.oxts_utc_ns[i]), self.lat_deg[i], self.lon_deg[i], self.alt_m[i])
            truth = self.sun_enu[i]
        h, w = image_bgr.shape[:2]
        return Frame(t_mono_s=float(self.t_mono_s[i]), seq=i, image_bgr=image_bgr,
                     intrinsics=self._intrinsics_for(w, h), attitude=attitude, utc_ns=int(self.utc_ns[i]),
                     gnss=gnss, sun_enu_truth=truth)

    def __iter__(self) -> Iterator[Frame]:
        self.corrupt_skipped = self._skipped_when_opened
        for i, path in enumerate(self.images):
            if not self.time_ok[i]:
                continue
            image = cv2.imread(str(path), cv2.IMREAD_COLOR)
            if image is None:
                self._warn(f"{self.path.name}: {path.name} is missing or not an image; frame {i} skipped")
                continue
            yield self.frame(i, image)
        if self.corrupt_skipped > _MAX_WARNINGS:  # the warnings stopped at the first few: say the total
            logger.warning("%s: %d frames or records skipped or left without pose in all", self.path.name,
                           self.corrupt_skipped)

    def __repr__(self) -> str:
        return f"KittiDrive({str(self.path)!r}, utc_offset_h={self.utc_offset_h:+g})"


def open_kitti(path: str | Path, utc_offset_h: float | None = None) -> KittiDrive:
    """Check ``path`` is a KITTI raw drive (or its date folder holding one) and open it."""
    return KittiDrive(path, utc_offset_h=utc_offset_h)
