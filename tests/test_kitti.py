"""KITTI raw drives as a frame source (replay/kitti.py), on the real text files of one drive.

The shared fixture (../shared/fixtures/kitti_raw_meta) holds drive 2011_09_26_drive_0001 without
its images and with only OXTS frame 0. Each test copies it into tmp_path and fills the gaps there:
small PNGs (414 x 125, a third of the real 1242 x 375, so the reader scales the intrinsics) named
0000000000.png ..., and OXTS frames 1..107 as copies of frame 0 (the vehicle then stands still at
frame 0's pose while the timestamps run on: enough for the reader, whose per-frame values are
tested on frame 0). The eval test builds a drive of its own and needs no fixture.
"""

from __future__ import annotations

import calendar
import json
import logging
import math
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import cv2
import numpy as np
import pytest

import replay.kitti as kitti
from replay.kitti import (
    OXTS_FIELDS,
    KittiDrive,
    attitude_from_oxts,
    intrinsics_from_calib,
    longest_increasing,
    open_kitti,
    parse_calib,
    parse_dataformat,
    parse_timestamps_ns,
)
from replay.sources import open_frames
from rig.errors import LogError
from rig.geometry import az_el_from_enu
from rig.solar import standard_pressure_hpa, sun_position
from rig.types import HeadingRef
from tests.tolerances import EXACT_F64

SHARED = Path(__file__).resolve().parents[2] / "shared"
FIXTURE = SHARED / "fixtures" / "kitti_raw_meta"
DATE = "2011_09_26"
DRIVE = "2011_09_26_drive_0001_sync"
N_FRAMES = 108
SMALL = (414, 125)  # width, height: the real size / 3


def _need_fixture() -> None:
    if not FIXTURE.is_dir():
        pytest.skip(f"needs the real KITTI text files at {FIXTURE} (an outside checkout has no ../shared)")


def _writable_copy(src: Path, dst: Path) -> None:
    shutil.copytree(src, dst)
    for root, _dirs, files in os.walk(dst):  # the shared tree is read-only, and copytree keeps modes
        os.chmod(root, 0o755)
        for f in files:
            os.chmod(Path(root) / f, 0o644)


def _fill_drive(drive: Path, n: int, size=SMALL, seed: int = 0) -> None:
    """Images 0..n-1 (smooth noise, small PNGs) and OXTS records 1..n-1 copied from record 0."""
    (drive / "image_02" / "data").mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    w, h = size
    base = cv2.resize(rng.integers(0, 256, (8, 24, 3), dtype=np.uint8), (w, h), interpolation=cv2.INTER_LINEAR)
    for i in range(n):
        cv2.imwrite(str(drive / "image_02" / "data" / f"{i:010d}.png"), np.roll(base, i, axis=1))
    record0 = (drive / "oxts" / "data" / "0000000000.txt").read_text()
    for i in range(1, n):
        (drive / "oxts" / "data" / f"{i:010d}.txt").write_text(record0)


@pytest.fixture
def kitti_date(tmp_path) -> Path:
    _need_fixture()
    root = tmp_path / "kitti"
    _writable_copy(FIXTURE, root)
    _fill_drive(root / DATE / DRIVE, N_FRAMES)
    return root / DATE


@pytest.fixture(autouse=True)
def _fresh_warning_state(monkeypatch):
    # The default-offset warning is once per process; each test starts as a fresh process would.
    monkeypatch.setattr(kitti, "_warned_default_offset", False)


def _timestamp_ns(line: str) -> int:
    """Reference parse with plain integers: the wall clock as ns since the epoch."""
    date, clock = line.split()
    y, mo, d = (int(v) for v in date.split("-"))
    hms, frac = clock.split(".")
    h, mi, s = (int(v) for v in hms.split(":"))
    return calendar.timegm((y, mo, d, h, mi, s)) * 1_000_000_000 + int(frac.ljust(9, "0"))


# --- pure parsers ----------------------------------------------------------------------------


def test_timestamps_parse_to_the_nanosecond():
    _need_fixture()
    for stream in ("image_02", "oxts", "velodyne_points"):
        text = (FIXTURE / DATE / DRIVE / stream / "timestamps.txt").read_text()
        lines = [ln for ln in text.splitlines() if ln.strip()]
        assert all(len(ln.split(".")[1]) == 9 for ln in lines)  # the files really carry 9 digits
        got = parse_timestamps_ns(text)
        assert got.dtype == np.int64 and len(got) == N_FRAMES
        assert got.tolist() == [_timestamp_ns(ln) for ln in lines]
    first = parse_timestamps_ns("2011-09-26 13:02:25.961661696\n")[0]
    assert first % 1_000_000_000 == 961_661_696  # no float on the way: every digit survives


def test_timestamps_exact_for_random_nanoseconds():
    rng = np.random.default_rng(1)
    secs = rng.integers(0, 2**31, 200)
    nanos = rng.integers(0, 10**9, 200)
    pairs = list(zip(secs.tolist(), nanos.tolist(), strict=True))
    lines = [f"{np.datetime64(s, 's').astype(str).replace('T', ' ')}.{ns:09d}" for s, ns in pairs]
    got = parse_timestamps_ns("\n".join(lines))
    assert got.tolist() == [s * 10**9 + ns for s, ns in pairs]


@pytest.mark.parametrize("bad", ["2011-09-26 13:02", "2011/09/26 13:02:25.1", "2011-09-26 13:02:25.1234567890",
                                 "2011-19-26 13:02:25.1"])
def test_bad_timestamp_is_a_one_line_log_error(bad):
    with pytest.raises(LogError) as err:
        parse_timestamps_ns(f"2011-09-26 13:02:25.000000000\n{bad}\n", "x/timestamps.txt")
    assert "\n" not in str(err.value) and "x/timestamps.txt" in str(err.value)


def test_dataformat_typo_is_tolerated():
    _need_fixture()
    text = (FIXTURE / DATE / DRIVE / "oxts" / "dataformat.txt").read_text()
    assert text.splitlines()[13].startswith("ay:")  # the real typo: line 14 names az "ay"
    assert parse_dataformat(text) == list(OXTS_FIELDS)


def test_oxts_attitude_conventions():
    # OXTS: yaw 0 = east, counter-clockwise positive; pitch positive front down; roll positive left up.
    heading, pitch, roll = attitude_from_oxts(np.array([0.1, 0.0]), np.array([0.05, 0.0]),
                                              np.array([0.0, math.pi / 2]))
    assert heading == pytest.approx([math.pi / 2, 0.0])  # east, north
    assert pitch[0] == pytest.approx(-0.05)  # front down = nose down = negative in sunrig
    assert roll[0] == pytest.approx(0.1)  # left side up = right side down = positive in sunrig


# --- the drive ---------------------------------------------------------------------------------


def test_drive_frames(kitti_date):
    src = open_frames(kitti_date, utc_offset_h=2.0)
    assert isinstance(src, KittiDrive) and len(src) == N_FRAMES
    frames = list(src)
    assert [f.seq for f in frames] == list(range(N_FRAMES))
    f0 = frames[0]
    # Heading of frame 0 from its OXTS yaw (-2.6087 rad): 90 deg - yaw.
    assert math.degrees(f0.attitude.heading_rad) == pytest.approx(239.47, abs=0.01)
    assert f0.attitude.reference == HeadingRef.TRUE
    assert f0.attitude.pitch_rad == pytest.approx(-0.00903)
    assert f0.attitude.roll_rad == pytest.approx(0.035752)
    # Field of view from P_rect_02 / S_rect_02, kept by the intrinsics scaled to the small images.
    hfov, vfov = src.field_of_view_deg
    assert (hfov, vfov) == (pytest.approx(81.43, abs=0.01), pytest.approx(29.12, abs=0.01))
    assert src.intrinsics.fx == pytest.approx(721.5377) and (src.intrinsics.width, src.intrinsics.height) == (1242, 375)
    k = f0.intrinsics
    assert (k.width, k.height) == SMALL and f0.image_bgr.shape == (SMALL[1], SMALL[0], 3)
    assert math.degrees(k.hfov_rad) == pytest.approx(81.43, abs=0.01)
    assert math.degrees(k.vfov_rad) == pytest.approx(29.12, abs=0.01)
    # Times: UTC = local - 2 h, to the nanosecond; monotonic from the first image.
    lines = (kitti_date / DRIVE / "image_02" / "timestamps.txt").read_text().split("\n")
    assert f0.utc_ns == _timestamp_ns(lines[0]) - 2 * 3600 * 10**9
    assert frames[-1].utc_ns == _timestamp_ns(lines[N_FRAMES - 1]) - 2 * 3600 * 10**9
    assert f0.t_mono_s == 0.0
    assert frames[-1].t_mono_s == (_timestamp_ns(lines[N_FRAMES - 1]) - _timestamp_ns(lines[0])) / 1e9
    assert all(b.t_mono_s > a.t_mono_s for a, b in zip(frames, frames[1:], strict=False))
    # GNSS fix from OXTS at the OXTS time.
    oxts_line = (kitti_date / DRIVE / "oxts" / "timestamps.txt").read_text().split("\n")[0]
    assert f0.gnss.utc_ns == _timestamp_ns(oxts_line) - 2 * 3600 * 10**9
    assert (f0.gnss.lat_deg, f0.gnss.lon_deg, f0.gnss.alt_m) == pytest.approx((49.015003823272, 8.4342971002335,
                                                                                116.43032836914))


def test_drive_ground_truth_is_the_ephemeris(kitti_date):
    f0 = next(iter(open_frames(kitti_date, utc_offset_h=2.0)))
    want = sun_position(np.int64(f0.utc_ns), f0.gnss.lat_deg, f0.gnss.lon_deg, f0.gnss.alt_m,
                        pressure_hpa=standard_pressure_hpa(f0.gnss.alt_m))
    np.testing.assert_allclose(f0.sun_enu_truth, want.enu, atol=EXACT_F64)
    az, el = (math.degrees(v) for v in az_el_from_enu(f0.sun_enu_truth))
    assert (az, el) == (pytest.approx(175.0, abs=0.5), pytest.approx(39.7, abs=0.5))  # 11:02 UTC, Karlsruhe
    # Read as UTC instead, the same timestamp is two hours later: the sun ~37 deg further west.
    g0 = next(iter(open_frames(kitti_date, utc_offset_h=0.0)))
    assert g0.utc_ns - f0.utc_ns == 2 * 3600 * 10**9
    az_utc = math.degrees(az_el_from_enu(g0.sun_enu_truth)[0])
    assert az_utc == pytest.approx(212.5, abs=0.5)


def test_default_offset_warns_once(kitti_date, caplog):
    with caplog.at_level(logging.WARNING, logger="replay.kitti"):
        a = open_kitti(kitti_date)
        b = open_kitti(kitti_date / DRIVE)
    warnings = [r for r in caplog.records if "time zone" in r.getMessage()]
    assert len(warnings) == 1 and "--utc-offset" in warnings[0].getMessage()
    assert a.utc_offset_h == b.utc_offset_h == kitti.DEFAULT_UTC_OFFSET_H
    caplog.clear()
    kitti._warned_default_offset = False
    with caplog.at_level(logging.WARNING, logger="replay.kitti"):
        open_kitti(kitti_date, utc_offset_h=0.0)
    assert not [r for r in caplog.records if "time zone" in r.getMessage()]


def test_offset_default_for_code_that_opens_logs_itself(kitti_date):
    from replay.sources import utc_offset_default

    with utc_offset_default(0.0):  # how `sunrig train --utc-offset 0` reaches the logs train() opens
        inner = open_frames(kitti_date)
        explicit = open_frames(kitti_date, utc_offset_h=1.0)
    assert inner.utc_offset_h == 0.0 and explicit.utc_offset_h == 1.0
    assert open_frames(kitti_date).utc_offset_h == kitti.DEFAULT_UTC_OFFSET_H


def test_drive_folder_and_date_folder_agree(kitti_date):
    a = open_kitti(kitti_date, utc_offset_h=2.0)
    b = open_kitti(kitti_date / DRIVE, utc_offset_h=2.0)
    assert a.path.resolve() == b.path.resolve() and a.date_dir.resolve() == b.date_dir.resolve()
    np.testing.assert_array_equal(a.utc_ns, b.utc_ns)
    np.testing.assert_array_equal(a.sun_enu, b.sun_enu)


def _one_line_log_error(path, needle: str) -> str:
    with pytest.raises(LogError) as err:
        open_frames(path, utc_offset_h=2.0)
    text = str(err.value)
    assert "\n" not in text and needle in text, text
    return text


def test_not_a_kitti_folder(tmp_path):
    (tmp_path / "notes.txt").write_text("hello")
    _one_line_log_error(tmp_path, "not a KITTI raw drive")


def test_a_folder_of_recordings_given_for_one_log_says_to_pass_one_of_them(tmp_path):
    # replay and run --camera file: read one log; a folder of them was "not a KITTI raw drive".
    for name in ("b.mcap", "a.mcap"):
        (tmp_path / name).write_bytes(b"")
    text = _one_line_log_error(tmp_path, "a folder of 2 native logs, where one log is read")
    assert f"(e.g. {tmp_path / 'a.mcap'})" in text and "sunrig eval / train" in text


def test_missing_calibration(kitti_date):
    (kitti_date / "calib_cam_to_cam.txt").unlink()
    text = _one_line_log_error(kitti_date, "calib_cam_to_cam.txt")
    assert "2011_09_26_calib.zip" in text
    _one_line_log_error(kitti_date / DRIVE, "calib_cam_to_cam.txt")


def _calib_zip(folder: Path) -> Path:
    """KITTI's 2011_09_26_calib.zip as the dataset ships it: its files under the date's folder
    (2011_09_26/calib_cam_to_cam.txt ...), as the drive zips hold 2011_09_26/*_sync/."""
    z = folder / f"{DATE}_calib.zip"
    with zipfile.ZipFile(z, "w") as out:
        for f in sorted((FIXTURE / DATE).glob("calib_*.txt")):
            out.write(f, f"{DATE}/{f.name}")
    return z


def test_missing_calibration_says_where_to_unzip_it_and_that_works(kitti_date, tmp_path):
    # The zip holds 2011_09_26/calib_*.txt: unzipped in the date folder, as the message said, it
    # made 2011_09_26/2011_09_26/calib_cam_to_cam.txt and the same error again.
    for f in kitti_date.glob("calib_*.txt"):
        f.unlink()
    text = _one_line_log_error(kitti_date / DRIVE, f"unzip {DATE}_calib.zip in {kitti_date.resolve().parent}")
    with zipfile.ZipFile(_calib_zip(tmp_path)) as z:
        z.extractall(kitti_date.parent)
    assert len(open_kitti(kitti_date / DRIVE, utc_offset_h=2.0)) == N_FRAMES, text


def test_calibration_unzipped_one_folder_too_deep_says_to_move_it_up(kitti_date, tmp_path):
    for f in kitti_date.glob("calib_*.txt"):
        f.unlink()
    with zipfile.ZipFile(_calib_zip(tmp_path)) as z:
        z.extractall(kitti_date)  # the old message's advice: unzip it in the date folder
    deep = kitti_date.resolve() / DATE
    _one_line_log_error(kitti_date / DRIVE, f"{deep / 'calib_cam_to_cam.txt'} is one folder too deep; "
                                            f"move {deep}/calib_*.txt up into {kitti_date.resolve()}")
    for f in deep.glob("calib_*.txt"):
        f.rename(kitti_date / f.name)
    assert len(open_kitti(kitti_date / DRIVE, utc_offset_h=2.0)) == N_FRAMES


def test_image_and_oxts_counts_disagree(kitti_date):
    (kitti_date / DRIVE / "oxts" / "data" / f"{N_FRAMES - 1:010d}.txt").unlink()
    text = _one_line_log_error(kitti_date, "107 OXTS records")
    assert "108 images" in text


def test_date_folder_with_several_drives(kitti_date):
    _writable_copy(kitti_date / DRIVE, kitti_date / "2011_09_26_drive_0002_sync")
    _one_line_log_error(kitti_date, "holds 2 KITTI drives")
    assert len(open_kitti(kitti_date / DRIVE, utc_offset_h=2.0)) == N_FRAMES  # each drive still opens


def test_bad_calibration(kitti_date):
    (kitti_date / "calib_cam_to_cam.txt").write_text("calib_time: today\nP_rect_00: 1 2 3\n")
    _one_line_log_error(kitti_date, "P_rect_02")


def test_corrupt_oxts_record_costs_only_its_frame(kitti_date, caplog):
    (kitti_date / DRIVE / "oxts" / "data" / "0000000005.txt").write_text("garbage\n")
    with caplog.at_level(logging.WARNING, logger="replay.kitti"):
        frames = list(open_frames(kitti_date, utc_offset_h=2.0))
    assert len(frames) == N_FRAMES
    assert frames[5].attitude is None and frames[5].gnss is None and frames[5].sun_enu_truth is None
    assert frames[6].attitude is not None and frames[6].sun_enu_truth is not None
    assert any("0000000005.txt" in r.getMessage() for r in caplog.records)


def test_unreadable_image_is_skipped(kitti_date):
    (kitti_date / DRIVE / "image_02" / "data" / "0000000003.png").write_bytes(b"not a png")
    frames = list(open_frames(kitti_date, utc_offset_h=2.0))
    assert len(frames) == N_FRAMES - 1 and 3 not in [f.seq for f in frames]


def test_cli_error_for_a_broken_drive_is_one_line(kitti_date):
    (kitti_date / "calib_cam_to_cam.txt").unlink()
    res = subprocess.run([sys.executable, "-m", "rig.cli", "replay", str(kitti_date), "--utc-offset", "2"],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("sunrig: error: ") and "calib_cam_to_cam.txt" in lines[0]


# --- eval on a KITTI drive -----------------------------------------------------------------------

_CALIB = """calib_time: 09-Jan-2012 13:57:47
S_rect_02: 1.242000e+03 3.750000e+02
P_rect_02: 7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0.000000e+00 7.215377e+02 1.728540e+02 \
2.163791e-01 0.000000e+00 0.000000e+00 1.000000e+00 2.745884e-03
"""


@pytest.mark.parametrize(("line", "needle"), [
    # round() of these raised ValueError / OverflowError: internal errors, naming no file.
    ("S_rect_02: nan 3.750000e+02", "S_rect_02 nan 375 is no image size"),
    ("S_rect_02: 1e400 3.750000e+02", "S_rect_02 inf 375 is no image size"),
    ("S_rect_02: 0 3.750000e+02", "S_rect_02 0 375 is no image size"),
])
def test_a_damaged_calibration_size_is_named_with_its_file(line, needle):
    text = _CALIB.replace("S_rect_02: 1.242000e+03 3.750000e+02", line)
    with pytest.raises(LogError) as info:
        intrinsics_from_calib(parse_calib(text), name="calib_cam_to_cam.txt")
    assert str(info.value).startswith(f"calib_cam_to_cam.txt: {needle}; is the file damaged?")


def test_a_damaged_projection_is_named_with_its_file():
    text = _CALIB.replace("P_rect_02: 7.215377e+02", "P_rect_02: nan")
    with pytest.raises(LogError, match=r"^calib_cam_to_cam.txt: P_rect_02: fx: expected a finite number, got nan"):
        intrinsics_from_calib(parse_calib(text), name="calib_cam_to_cam.txt")


@pytest.mark.parametrize(("old", "new", "needle"), [
    ("P_rect_02: 7.215377e+02", "P_rect_02: 1e308", "fx: expected at most"),
    ("0.000000e+00 7.215377e+02 1.728540e+02", "0.000000e+00 1e308 1.728540e+02", "fy: expected at most"),
])
def test_a_focal_length_no_camera_has_fails_its_drive_naming_the_file(tmp_path, old, new, needle):
    # fx = 1e308 was taken: the crops' side, fx * tan(angle), was inf, and replay and eval of the
    # drive ended in an internal OverflowError that named no file.
    date = make_drive(tmp_path, 3)
    calib = date / "calib_cam_to_cam.txt"
    calib.write_text(_CALIB.replace(old, new))
    with pytest.raises(LogError) as err:
        open_kitti(date, utc_offset_h=2.0)
    message = str(err.value)
    assert message.startswith(f"{calib}: P_rect_02: Intrinsics.{needle}") and "\n" not in message
    assert message.endswith("Compare it with the date's calib_cam_to_cam.txt from KITTI")


def _write_oxts(date, index, pose):
    """Frame ``index``'s OXTS record: ``pose`` (lat lon alt roll pitch yaw) and 24 zeros after it."""
    rest = " ".join(["0"] * 24)
    (date / DRIVE / "oxts" / "data" / f"{index:010d}.txt").write_text(f"{pose} {rest}\n")


def make_drive(root: Path, n: int, size=(138, 42), seed: int = 0) -> Path:
    """A KITTI date folder with one generated drive of ``n`` frames at 10 Hz, turning 5 deg a frame
    (no fixture needed): real calibration values, images at 1/9 of the real size."""
    date = root / DATE
    drive = date / DRIVE
    (drive / "oxts" / "data").mkdir(parents=True)
    (date / "calib_cam_to_cam.txt").write_text(_CALIB)
    stamps = "".join(f"2011-09-26 13:02:{25 + i // 10:02d}.{(i % 10) * 100_000_000 + 1234567:09d}\n" for i in range(n))
    (drive / "image_02").mkdir()
    (drive / "image_02" / "timestamps.txt").write_text(stamps)
    (drive / "oxts" / "timestamps.txt").write_text(stamps)
    for i in range(n):
        _write_oxts(date, i, f"49.015 8.4343 116.4 0.01 0.005 {-2.6 + math.radians(5.0 * i)}")
    (drive / "image_02" / "data").mkdir()
    rng = np.random.default_rng(seed)
    w, h = size
    for i in range(n):
        cv2.imwrite(str(drive / "image_02" / "data" / f"{i:010d}.png"), rng.integers(0, 256, (h, w, 3), np.uint8))
    return date


def test_generated_drive_reads(tmp_path):
    date = make_drive(tmp_path, 12)
    frames = list(open_frames(date, utc_offset_h=2.0))
    assert len(frames) == 12 and all(f.sun_enu_truth is not None for f in frames)
    assert frames[1].t_mono_s == pytest.approx(0.1)


@pytest.mark.torch
def test_eval_runs_on_a_kitti_drive(tmp_path, tiny_model_dir):
    date = make_drive(tmp_path / "kitti", 12)
    out, png = tmp_path / "eval.json", tmp_path / "eval.png"
    res = subprocess.run([sys.executable, "-m", "rig.cli", "eval", str(date / DRIVE), "--model", str(tiny_model_dir),
                          "--json", str(out), "--plot", str(png), "--quiet", "--utc-offset", "2"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    summary = json.loads(out.read_text())
    assert set(summary["aggregators"]) == {"transformer", "mean", "meanshift", "single"}
    for s in summary["aggregators"].values():
        assert s["n_windows"] == 5  # 12 frames, windows full from the 8th frame on
        assert 0.0 <= s["median_deg"] <= s["max_deg"] <= 180.0
    assert summary["windows_without_truth"] == 0
    assert png.stat().st_size > 10_000 and (tmp_path / "eval-tokens.png").stat().st_size > 10_000


@pytest.mark.torch
def test_training_reads_a_kitti_drive(tmp_path):
    pytest.importorskip("torch", reason="estimator.train needs the train extra: pip install 'sunrig[train]'")
    from estimator.train import load_drives
    from replay.sources import utc_offset_default

    date = make_drive(tmp_path, 12)
    with utc_offset_default(2.0):
        (drive,) = load_drives([date / DRIVE], crop_size=32, crop_fov_rad=math.radians(40.0))
    assert drive.images.shape[0] == 12 and drive.sun_enu.shape == (12, 3)
    want = list(open_frames(date, utc_offset_h=2.0))
    np.testing.assert_allclose(drive.sun_enu, [f.sun_enu_truth for f in want])
    np.testing.assert_allclose(drive.yaw_rad, [f.heading_rad for f in want])


def test_frames_whose_timestamp_does_not_increase_are_skipped(tmp_path):
    # Downstream the clock must increase: the frames kept are the longest run of increasing
    # stamps, the others skipped and counted. Seconds 0, .1, .4 (ahead), .2, .4, .5: the .4 ahead
    # is the one out of line.
    date = make_drive(tmp_path, 6)
    stamps = "".join(f"2011-09-26 13:02:25.{t:09d}\n"
                     for t in (0, 100_000_000, 400_000_000, 200_000_000, 400_000_000, 500_000_000))
    (date / DRIVE / "image_02" / "timestamps.txt").write_text(stamps)
    drive = open_kitti(date, utc_offset_h=2.0)
    assert [f.seq for f in drive] == [0, 1, 3, 4, 5]
    assert drive.corrupt_skipped == 1


def test_one_timestamp_far_ahead_costs_only_its_own_frame(tmp_path):
    # Frame 4 stamped 8 hours ahead (a night sun for its truth): against a running maximum every
    # frame after it was "not after the previous one" and dropped, and frame 4 was kept and graded.
    date = make_drive(tmp_path, 12)
    path = date / DRIVE / "image_02" / "timestamps.txt"
    lines = path.read_text().splitlines()
    lines[4] = "2011-09-26 21:02:25.000000000"
    path.write_text("\n".join(lines) + "\n")
    drive = open_kitti(date, utc_offset_h=2.0)
    assert [f.seq for f in drive] == [i for i in range(12) if i != 4]
    assert drive.corrupt_skipped == 1


def test_more_skips_than_warnings_end_with_the_total(tmp_path, caplog):
    # The warnings stop after the first few so a broken drive cannot flood the log; the total was
    # then said nowhere (native logs say theirs).
    date = make_drive(tmp_path, 12)
    for i in range(8):
        (date / DRIVE / "image_02" / "data" / f"{i:010d}.png").write_bytes(b"not a png")
    with caplog.at_level(logging.WARNING, logger="replay.kitti"):
        frames = list(open_kitti(date, utc_offset_h=2.0))
    assert len(frames) == 4
    said = [r.getMessage() for r in caplog.records]
    assert sum("is missing or not an image" in m for m in said) == 5
    assert said[-1].endswith("8 frames or records skipped or left without pose in all")


def test_longest_increasing_keeps_a_longest_strictly_increasing_run():
    assert longest_increasing(np.array([1, 2, 3, 100, 5, 6, 7])) == [0, 1, 2, 4, 5, 6]
    assert longest_increasing(np.array([5, 1, 2, 3])) == [1, 2, 3]
    assert len(longest_increasing(np.array([1, 2, 2, 3]))) == 3
    assert longest_increasing(np.array([], dtype=np.int64)) == []
    rng = np.random.default_rng(0)
    for _ in range(50):  # against the O(n^2) definition
        v = rng.integers(0, 20, rng.integers(1, 30))
        best = [1] * len(v)
        for i in range(len(v)):
            best[i] = 1 + max([best[j] for j in range(i) if v[j] < v[i]], default=0)
        got = longest_increasing(v)
        assert len(got) == max(best) and all(v[a] < v[b] for a, b in zip(got, got[1:], strict=False))


def test_oxts_records_out_of_range_or_not_finite_cost_only_their_frame(tmp_path):
    # A latitude of 95 deg, a NaN yaw or a pitch of 4 rad (a logger glitch) must not end the replay (a GnssFix of
    # lat 95 would raise) nor pass for a pose: the frame goes without heading, fix and truth, counted.
    date = make_drive(tmp_path, 6)
    _write_oxts(date, 2, "95.0 8.4343 116.4 0.01 0.005 0.3")
    _write_oxts(date, 3, "49.015 8.4343 116.4 0.01 0.005 nan")
    _write_oxts(date, 4, "49.015 8.4343 116.4 0.01 4.0 0.3")  # pitch past pi
    drive = open_kitti(date, utc_offset_h=2.0)
    frames = list(drive)
    assert [f.attitude is None and f.gnss is None and f.sun_enu_truth is None for f in frames] == [
        False, False, True, True, True, False]
    assert drive.corrupt_skipped == 3


@pytest.mark.parametrize("pose", ["49.015 8.4343 1e9 0.01 0.005 0.3",  # altitude past what the ephemeris takes
                                  "49.015 8.4343 -7e6 0.01 0.005 0.3",  # deeper than the Earth's centre
                                  "49.015 8.4343 116.4 0.01 0.005 1e300"])  # yaw wrapped to some angle
def test_an_out_of_range_altitude_or_yaw_costs_only_its_frame(tmp_path, caplog, pose):
    # An altitude of 1e9 m ended the whole drive (and an eval over several) in the ephemeris's
    # "elevation: expected within ..." with no file named, where a bad latitude cost its frame.
    date = make_drive(tmp_path, 6)
    _write_oxts(date, 2, pose)
    with caplog.at_level(logging.WARNING, logger="replay.kitti"):
        drive = open_kitti(date, utc_offset_h=2.0)
        frames = list(drive)
    assert [f.attitude is None and f.gnss is None and f.sun_enu_truth is None for f in frames] == [
        False, False, True, False, False, False]
    assert drive.corrupt_skipped == 1
    assert any("0000000002.txt" in r.getMessage() and "frame 2 has no heading" in r.getMessage()
               for r in caplog.records)


@pytest.mark.parametrize("stamp", ["2300-01-01 00:00:00.000000000", "9999-12-31 23:59:59.999999999",
                                   "1600-01-01 00:00:00.000000000", "1677-09-21 00:12:43.145224192"])
def test_a_timestamp_past_what_ns_hold_is_a_one_line_log_error(stamp):
    # Parsed to datetime64[ns], 2300 wrapped to 1715, 9999 to 1816 and 1600 to 2184 without a word:
    # the sun was then computed for another date. (The last is NaT's own value, one ns too early.)
    with pytest.raises(LogError, match=r"^x/timestamps.txt line 2: .* outside the years 1678\.\.2262"):
        parse_timestamps_ns(f"2011-09-26 13:02:25.000000000\n{stamp}\n", "x/timestamps.txt")
    # the limits themselves are times
    assert parse_timestamps_ns("1677-09-21 00:12:43.145224193\n2262-04-11 23:47:16.854775807\n").tolist() == [
        -(2**63) + 1, 2**63 - 1]


def _stamp(date: Path, stream: str, index: int, stamp: str) -> None:
    path = date / DRIVE / stream / "timestamps.txt"
    lines = path.read_text().splitlines()
    lines[index] = stamp
    path.write_text("\n".join(lines) + "\n")


def test_image_timestamps_past_what_ns_hold_cost_only_their_frames(tmp_path, caplog):
    # 2300 wrapped to 1715 (frame 0, then first in time) and 1600 to 2184 (the last frame, then
    # after the others): both replayed, graded against the sun of a wrong date, with exit 0.
    date = make_drive(tmp_path, 6)
    _stamp(date, "image_02", 0, "2300-01-01 00:00:00.000000000")
    _stamp(date, "image_02", 5, "1600-01-01 00:00:00.000000000")
    with caplog.at_level(logging.WARNING, logger="replay.kitti"):
        drive = open_kitti(date, utc_offset_h=2.0)
        frames = list(drive)
    assert [f.seq for f in frames] == [1, 2, 3, 4]
    assert all(str(np.datetime64(f.utc_ns, "ns")).startswith("2011-09-26T11:02:25") for f in frames)
    assert all(f.sun_enu_truth is not None for f in frames)
    assert frames[0].t_mono_s == 0.0 and frames[1].t_mono_s == pytest.approx(0.1)
    assert drive.corrupt_skipped == 2
    said = [r.getMessage() for r in caplog.records]
    assert any("frame 0" in m and "2300-01-01" in m and "1678..2262" in m and "frame skipped" in m for m in said)
    assert any("frame 5" in m and "1600-01-01" in m for m in said)


def test_a_drive_stamped_wholly_past_what_ns_hold_yields_no_frame_of_a_wrong_date(tmp_path):
    date = make_drive(tmp_path, 4)
    (date / DRIVE / "image_02" / "timestamps.txt").write_text(
        "".join(f"9999-01-01 00:00:0{i}.000000000\n" for i in range(4)))
    drive = open_kitti(date, utc_offset_h=2.0)
    assert list(drive) == [] and drive.corrupt_skipped == 4


def test_a_utc_past_what_ns_hold_after_the_offset_costs_its_frame(tmp_path):
    # 23:00 local on the last day ns hold is within them, but at UTC-2 its UTC (01:00 the next day)
    # is not: int64 arithmetic wrapped it to 1677. East of Greenwich the same stamps are times.
    date = make_drive(tmp_path, 3)
    stamps = "".join(f"2262-04-11 23:00:0{i}.000000000\n" for i in range(3))
    for stream in ("image_02", "oxts"):
        (date / DRIVE / stream / "timestamps.txt").write_text(stamps)
    west = open_kitti(date, utc_offset_h=-2.0)
    assert list(west) == [] and west.corrupt_skipped == 3 + 3  # each frame's image and OXTS stamps
    east = list(open_kitti(date, utc_offset_h=2.0))
    assert [str(np.datetime64(f.utc_ns, "ns"))[:19] for f in east] == [f"2262-04-11T21:00:0{i}" for i in range(3)]


def test_frames_centuries_apart_within_what_ns_hold_keep_their_order(tmp_path):
    # 1678 to 2262 is more ns than int64 holds: the seconds since the first frame must not wrap.
    date = make_drive(tmp_path, 3)
    (date / DRIVE / "image_02" / "timestamps.txt").write_text(
        "1678-01-01 12:00:00.000000000\n2262-01-01 12:00:00.000000000\n2262-01-01 12:00:00.100000000\n")
    frames = list(open_kitti(date, utc_offset_h=2.0))
    assert [f.seq for f in frames] == [0, 1, 2]
    assert frames[1].t_mono_s == (_timestamp_ns("2262-01-01 12:00:00.0") - _timestamp_ns("1678-01-01 12:00:00.0")) / 1e9
    assert frames[2].t_mono_s > frames[1].t_mono_s > 0


def test_an_oxts_timestamp_past_what_ns_hold_costs_that_frame_its_pose(tmp_path, caplog):
    # The fix's time wrapped the same way (a GnssFix of 1715); the image's own time still holds.
    date = make_drive(tmp_path, 4)
    _stamp(date, "oxts", 2, "2300-01-01 00:00:00.000000000")
    with caplog.at_level(logging.WARNING, logger="replay.kitti"):
        drive = open_kitti(date, utc_offset_h=2.0)
        frames = list(drive)
    assert [f.seq for f in frames] == [0, 1, 2, 3]
    assert [f.attitude is None and f.gnss is None and f.sun_enu_truth is None for f in frames] == [
        False, False, True, False]
    assert drive.corrupt_skipped == 1
    assert any("oxts/timestamps.txt" in r.getMessage() and "frame 2 has no heading" in r.getMessage()
               for r in caplog.records)


def test_utc_offset_beyond_any_time_zone_is_refused():
    # Time zones run from -12 to +14 h: anything past 14 is a typo (minutes? a date?), and each hour
    # moves the sun ~15 deg.
    assert kitti.utc_offset_ns(5.5) == 19_800 * 10**9
    for bad in (14.5, -15.0, 20):
        with pytest.raises(LogError, match="UTC offset"):
            kitti.utc_offset_ns(bad)


def test_intrinsics_scale_each_axis_by_its_own_factor():
    # A copy resized to another aspect (half the width, a third of the height): x values scale by
    # 1/2, y values by 1/3, so the view angles of every pixel stay the calibration's.
    k = kitti.Intrinsics(fx=721.5377, fy=721.5377, cx=609.5593, cy=172.854, width=1242, height=375)
    s = kitti.scaled_intrinsics(k, 621, 125)
    assert (s.fx, s.cx) == pytest.approx((721.5377 / 2, 609.5593 / 2))
    assert (s.fy, s.cy) == pytest.approx((721.5377 / 3, 172.854 / 3))
    assert math.degrees(s.vfov_rad) == pytest.approx(math.degrees(k.vfov_rad))


def test_oxts_records_numbered_unlike_the_images_are_refused(tmp_path):
    # Record i is frame i's pose: OXTS files numbered otherwise (a gap, a partial re-extract) would
    # pair images with the wrong poses, so the drive is refused, as when the counts differ.
    date = make_drive(tmp_path, 5)
    data = date / DRIVE / "oxts" / "data"
    (data / "0000000004.txt").rename(data / "0000000009.txt")
    with pytest.raises(LogError, match="not numbered"):
        open_kitti(date, utc_offset_h=2.0)


def test_a_date_folder_with_another_folder_beside_its_drive_still_opens(tmp_path):
    # Only *_drive_NNNN_sync folders are drives: a notes/ or an unzipped calib/ folder beside the
    # one drive must not make the date folder look like it holds two.
    date = make_drive(tmp_path, 3)
    (date / "notes").mkdir()
    (date / "2011_09_26_drive_0002_extract").mkdir()  # the unsynced variant is not a sync drive
    drive = open_kitti(date, utc_offset_h=2.0)
    assert drive.path.name == DRIVE and len(drive) == 3


def test_an_unsynced_extract_drive_is_refused_naming_the_sync_zip(tmp_path):
    # An *_extract drive holds unrectified images (1392 x 512, distorted) and OXTS at 100 Hz: read
    # with P_rect_02 it was graded with the wrong intrinsics when its counts happened to agree,
    # and told to "re-extract the drive" when they did not.
    date = make_drive(tmp_path, 3)
    extract = date / "2011_09_26_drive_0001_extract"
    (date / DRIVE).rename(extract)
    want = "download 2011_09_26_drive_0001_sync.zip and pass its 2011_09_26_drive_0001_sync folder"
    _one_line_log_error(extract, want)
    _one_line_log_error(date, want)  # the date folder holding only that drive


@pytest.mark.parametrize("where", [".", "image_02/.."])
def test_a_drive_given_as_dot_is_named_by_its_folder(tmp_path, monkeypatch, where):
    # `cd drive && sunrig replay .`: Path(".").name is "", and every message about the drive began
    # ": 5 images, ..." with nothing to say which drive.
    date = make_drive(tmp_path, 5)
    monkeypatch.chdir(date / DRIVE)
    assert open_kitti(where, utc_offset_h=2.0).path.name == DRIVE
    (date / DRIVE / "oxts" / "data" / "0000000004.txt").unlink()
    text = _one_line_log_error(where, "4 OXTS records")
    assert text.startswith(f"{DRIVE}: 5 images"), text


@pytest.mark.parametrize("sub", ["image_03", "image_02", "image_02/data", "oxts"])
def test_a_folder_inside_a_drive_says_to_pass_the_drive(tmp_path, sub):
    # A user after the right colour camera passes drive/image_03: it was "not a KITTI raw drive
    # ... pass a .mcap file, a KITTI date folder YYYY_MM_DD/ or one of its drive folders", which
    # neither named the drive nor said which camera is read.
    date = make_drive(tmp_path, 3)
    (date / DRIVE / "image_03" / "data").mkdir(parents=True)
    text = _one_line_log_error(date / DRIVE / sub, f"is inside the KITTI drive {date / DRIVE}; pass that drive folder")
    assert "image_02 (the left colour camera" in text


def test_a_drive_folder_under_another_name_opens_by_its_contents(tmp_path):
    # A drive folder copied under a name of one's own still has oxts/ and image_02/: it is a drive,
    # and its date folder (with the calibration) is its parent.
    date = make_drive(tmp_path, 3)
    (date / DRIVE).rename(date / "my_drive")
    drive = open_kitti(date / "my_drive", utc_offset_h=2.0)
    assert drive.path.name == "my_drive" and len(drive) == 3
    assert drive.date_dir.resolve() == date.resolve()


def test_a_dataformat_with_other_fields_is_refused(tmp_path):
    # dataformat.txt, when present, must list lat, lon, alt, roll, pitch, yaw first: records in
    # another order would be read as the wrong pose without a word.
    date = make_drive(tmp_path, 3)
    fields = ["lon", "lat", *OXTS_FIELDS[2:]]  # latitude and longitude swapped
    (date / DRIVE / "oxts" / "dataformat.txt").write_text("".join(f"{f}: something\n" for f in fields))
    with pytest.raises(LogError, match="not a KITTI OXTS format"):
        open_kitti(date, utc_offset_h=2.0)
    # The devkit's own field list (as the fixture's file has it, typo aside) opens.
    (date / DRIVE / "oxts" / "dataformat.txt").write_text("".join(f"{f}: something\n" for f in OXTS_FIELDS))
    assert len(open_kitti(date, utc_offset_h=2.0)) == 3


def test_a_position_just_past_the_poles_or_the_date_line_costs_only_its_frame(tmp_path):
    # Latitude 90.5 or longitude 180.5 is no place on Earth: the record is out of range, so its
    # frame goes without pose (a GnssFix of lat 90.5 would end the replay), however slight the excess.
    date = make_drive(tmp_path, 4)
    _write_oxts(date, 1, "90.5 8.4343 116.4 0.01 0.005 0.3")
    _write_oxts(date, 2, "49.015 180.5 116.4 0.01 0.005 0.3")
    drive = open_kitti(date, utc_offset_h=2.0)
    frames = list(drive)
    assert [f.gnss is None and f.attitude is None for f in frames] == [False, True, True, False]
    assert drive.corrupt_skipped == 2


def test_oxts_record_with_a_number_missing_or_extra_is_refused():
    # A record cut short (or two run together) is a damaged file even when its first six numbers
    # look like a pose: the count is checked, and the message says what was expected.
    good = [49.015, 8.4343, 116.4, 0.01, 0.005, 0.3] + [0.0] * 24
    assert kitti.parse_oxts(" ".join(map(str, good))).tolist() == good
    for values, count in ((good[:-1], 29), (good + [1.0], 31)):
        with pytest.raises(LogError, match=f"r/0001.txt: expected 30 numbers, got {count}"):
            kitti.parse_oxts(" ".join(map(str, values)), "r/0001.txt")


def test_dataformat_lines_naming_no_field_are_skipped():
    # Only ``name: description`` lines name a field: a title line, a blank one or a line with an
    # empty name before its colon must not shift the field order the drive is checked against.
    text = "OXTS data format\n\n" + "".join(f"{f}: description\n" for f in OXTS_FIELDS[:3]) + ": orphan\n" + \
        "".join(f"{f}: description\n" for f in OXTS_FIELDS[3:])
    assert parse_dataformat(text) == list(OXTS_FIELDS)


def test_blank_lines_in_a_timestamps_file_are_skipped():
    # An extra newline at the end (or a blank line an editor left) is not a frame and not an error.
    text = "2011-09-26 13:02:25.000000001\n\n   \n2011-09-26 13:02:25.100000002\n\n"
    assert parse_timestamps_ns(text).tolist() == [_timestamp_ns("2011-09-26 13:02:25.000000001"),
                                                  _timestamp_ns("2011-09-26 13:02:25.100000002")]


def test_utc_offset_limits_themselves_are_allowed():
    # Kiribati's +14 h is a real time zone: the limits are inclusive, as the message's [-14, 14] says.
    assert kitti.utc_offset_ns(14) == 14 * 3600 * 10**9
    assert kitti.utc_offset_ns(-14.0) == -14 * 3600 * 10**9


def test_oxts_record_with_a_non_finite_velocity_keeps_its_pose():
    # Only the pose (lat, lon, alt, roll, pitch, yaw) is used and must be finite: a NaN in an
    # unused field (here vn, the 7th) must not cost the frame its heading and truth.
    values = [49.015, 8.4343, 116.4, 0.01, 0.005, 0.3, float("nan")] + [0.0] * 23
    got = kitti.parse_oxts(" ".join(map(str, values)))
    assert got[:6].tolist() == values[:6] and math.isnan(got[6])
    with pytest.raises(LogError, match="not finite"):
        kitti.parse_oxts(" ".join(map(str, [*values[:5], float("nan"), *values[6:]])))


def test_bad_timestamp_message_names_its_line_number():
    # "line 2" is the file's own numbering (from 1), so an editor's go-to-line finds it.
    with pytest.raises(LogError, match=r"x/timestamps.txt line 2: expected"):
        parse_timestamps_ns("2011-09-26 13:02:25.000000000\n2011-09-26 13:02\n", "x/timestamps.txt")


def test_a_missing_or_unreadable_timestamps_file_is_a_log_error(tmp_path):
    date = make_drive(tmp_path, 3)
    (date / DRIVE / "image_02" / "timestamps.txt").unlink()
    with pytest.raises(LogError, match=r"timestamps.txt: missing \(image timestamps\)"):
        open_kitti(date, utc_offset_h=2.0)
    date2 = make_drive(tmp_path / "b", 3)
    stamps = date2 / DRIVE / "oxts" / "timestamps.txt"
    stamps.unlink()
    stamps.mkdir()  # a folder where the file should be: readable by no one, root included
    with pytest.raises(LogError, match="cannot read OXTS timestamps"):
        open_kitti(date2, utc_offset_h=2.0)


def test_a_file_given_for_the_drive_is_refused_as_not_a_folder(tmp_path):
    path = tmp_path / "2011_09_26_drive_0001_sync"
    path.write_text("not a folder")
    with pytest.raises(LogError, match="not a folder"):
        open_kitti(path, utc_offset_h=2.0)


def test_a_fresh_process_warns_about_the_default_offset(tmp_path):
    # The other tests reset the once-per-process flag; here a real process starts as users' do,
    # and its first drive opened without --utc-offset says which offset it assumed.
    date = make_drive(tmp_path, 3)
    code = ("import logging, replay.kitti as k; logging.basicConfig(level=logging.WARNING); "
            f"k.open_kitti({str(date)!r}); k.open_kitti({str(date)!r})")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stderr.count("carry no time zone") == 1 and "--utc-offset 0" in res.stderr


def test_resized_images_warn_only_when_their_aspect_ratio_differs(tmp_path, caplog):
    # A copy resized by 1/9 (138 x 42: 41.67 rounded) keeps the calibration's aspect: scaled quietly.
    # One stretched to 138 x 80 does not: the intrinsics are still scaled, with a warning to check.
    for size, warns in (((138, 42), False), ((138, 80), True)):
        caplog.clear()
        date = make_drive(tmp_path / f"{size[0]}x{size[1]}", 2, size=size)
        with caplog.at_level(logging.INFO, logger="replay.kitti"):
            f0 = next(iter(open_kitti(date, utc_offset_h=2.0)))
        assert (f0.intrinsics.width, f0.intrinsics.height) == size
        warned = [r for r in caplog.records if "aspect ratio differs" in r.getMessage()]
        assert bool(warned) == warns and all(r.levelno == logging.WARNING for r in warned)


def test_a_drive_without_its_oxts_folder_is_called_incomplete(tmp_path):
    # Half an unzip: the drive folder is there, its oxts/ is not. The message says so, rather than
    # leaving the user to work it out from a count of 0 OXTS records.
    date = make_drive(tmp_path, 3)
    shutil.rmtree(date / DRIVE / "oxts")
    with pytest.raises(LogError, match=r"no oxts/ folder; is it a complete \*_sync drive"):
        open_kitti(date, utc_offset_h=2.0)


def test_the_default_offset_reads_the_timestamps_as_cest(tmp_path):
    # Opened without an offset, a drive is read as UTC+2 (CEST, docs/ground-truth.md): each hour
    # off would move the true sun ~15 deg, so the default itself is checked, not just its name.
    date = make_drive(tmp_path, 2)
    line = (date / DRIVE / "image_02" / "timestamps.txt").read_text().splitlines()[0]
    drive = open_kitti(date)
    assert drive.utc_offset_h == 2.0
    assert int(drive.utc_ns[0]) == _timestamp_ns(line) - 2 * 3600 * 10**9


def test_oxts_headings_are_within_one_turn():
    # heading = 90 deg - yaw, in [0, 2 pi): yaw 135 deg (north-west) is heading 315 deg, not -45 or 495.
    yaw = np.radians([135.0, 90.0, -90.0, 180.0])
    heading, _, _ = attitude_from_oxts(np.zeros(4), np.zeros(4), yaw)
    assert np.degrees(heading) == pytest.approx([315.0, 0.0, 180.0, 270.0])


def test_an_unreadable_image_is_counted_and_warned(kitti_date, caplog):
    (kitti_date / DRIVE / "image_02" / "data" / "0000000003.png").write_bytes(b"not a png")
    drive = open_kitti(kitti_date, utc_offset_h=2.0)
    with caplog.at_level(logging.WARNING, logger="replay.kitti"):
        assert len(list(drive)) == N_FRAMES - 1
    assert drive.corrupt_skipped == 1
    assert any("0000000003.png is missing or not an image" in r.getMessage() for r in caplog.records)


def test_a_last_image_stamped_hours_off_gets_no_truth_of_another_instant(tmp_path, caplog):
    # Still in increasing order, the last frame was kept and graded against the sun 8 h later
    # (below the horizon): its image and OXTS stamps now disagree, so it has no pose or truth.
    date = make_drive(tmp_path, 12)
    _stamp(date, "image_02", 11, "2011-09-26 21:02:26.101234567")
    drive = open_kitti(date, utc_offset_h=2.0)
    frames = list(drive)
    assert len(frames) == 12 and frames[-1].sun_enu_truth is None and frames[-1].attitude is None
    assert all(f.sun_enu_truth is not None for f in frames[:-1]) and drive.corrupt_skipped == 1
    assert "frame 11's image and OXTS timestamps are 28800 s apart" in caplog.text


def test_times_count_from_the_first_frame_kept(tmp_path):
    # A first stamp an hour ahead is skipped, and the times once counted from it: every frame an
    # hour below 0, which `record --camera file:` then refused.
    date = make_drive(tmp_path, 12)
    for stream in ("image_02", "oxts"):
        _stamp(date, stream, 0, "2011-09-26 14:02:25.001234567")
    frames = list(open_kitti(date, utc_offset_h=2.0))
    assert [f.seq for f in frames] == list(range(1, 12))
    assert frames[0].t_mono_s == 0.0 and frames[1].t_mono_s == pytest.approx(0.1)


@pytest.mark.torch
def test_replay_of_a_drive_from_inside_it_names_the_drive(kitti_date, tiny_model_dir, monkeypatch, capsys):
    # `cd drive && sunrig replay .`: the summary said "replay : 30 frames", the name of "." being "".
    from rig.cli import main

    monkeypatch.chdir(kitti_date / DRIVE)
    assert main(["replay", ".", "--utc-offset", "2", "--model", str(tiny_model_dir)]) == 0
    said = capsys.readouterr().err.strip().splitlines()[-1]
    assert said.startswith(f"replay {DRIVE}: "), said
