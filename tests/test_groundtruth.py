"""Ground truth from GNSS time + position (replay/groundtruth.py) and its wiring into open_frames."""

from __future__ import annotations

import dataclasses
import logging
import math

import numpy as np
import pytest

from replay.groundtruth import GroundTruthSource, frame_with_truth, sun_truth_enu, with_ground_truth
from replay.native import LogWriter, open_log
from replay.sources import DEMO_LOG, open_frames
from rig.solar import standard_pressure_hpa, sun_position
from rig.types import Attitude, Frame, GnssFix, HeadingRef, Intrinsics
from tests.tolerances import EXACT_F64

K = Intrinsics(fx=100.0, fy=100.0, cx=32.0, cy=20.0, width=64, height=40)
T0_NS = 1_317_034_945_961_661_696  # 2011-09-26T11:02:25.96Z
FIX = GnssFix(T0_NS, 49.015, 8.4343, 116.4)


def _frame(i=0, *, ref=HeadingRef.TRUE, gnss=FIX, utc=True, truth=None, attitude=True) -> Frame:
    return Frame(
        t_mono_s=0.1 * i, seq=i, image_bgr=np.zeros((40, 64, 3), np.uint8), intrinsics=K,
        attitude=Attitude(math.radians(30.0), ref) if attitude else None,
        utc_ns=T0_NS + i * 100_000_000 if utc else None, gnss=gnss, sun_enu_truth=truth,
    )


def _expected(t_ns: int, fix: GnssFix) -> np.ndarray:
    return sun_position(np.int64(t_ns), fix.lat_deg, fix.lon_deg, fix.alt_m,
                        pressure_hpa=standard_pressure_hpa(fix.alt_m)).enu


def test_truth_is_the_ephemeris_at_the_frame_time():
    f = frame_with_truth(_frame(3))
    np.testing.assert_allclose(f.sun_enu_truth, _expected(T0_NS + 300_000_000, FIX), atol=EXACT_F64)
    # No frame time: the fix's own time.
    g = frame_with_truth(_frame(3, utc=False))
    np.testing.assert_allclose(g.sun_enu_truth, _expected(T0_NS, FIX), atol=EXACT_F64)


def test_vectorised_matches_per_frame():
    t = T0_NS + np.arange(5) * 60 * 10**9
    lat, lon, alt = np.full(5, 49.0), np.linspace(8.0, 9.0, 5), np.full(5, 100.0)
    batch = sun_truth_enu(t, lat, lon, alt)
    for i in range(5):
        np.testing.assert_allclose(batch[i], sun_truth_enu(np.int64(t[i]), lat[i], lon[i], alt[i]), atol=EXACT_F64)


@pytest.mark.parametrize("ref", [HeadingRef.MAGNETIC, HeadingRef.RELATIVE])
def test_no_truth_for_magnetic_or_relative_heading(ref):
    f = _frame(ref=ref)
    assert frame_with_truth(f) is f and f.sun_enu_truth is None


def test_truth_without_heading_and_kept_when_present():
    assert frame_with_truth(_frame(attitude=False)).sun_enu_truth is not None
    own = [0.0, 0.6, 0.8]
    f = _frame(truth=own)
    assert frame_with_truth(f) is f
    assert frame_with_truth(_frame(gnss=None)).sun_enu_truth is None


def test_source_holds_the_last_fix_and_counts(caplog):
    frames = [
        _frame(0),  # own fix
        _frame(1, gnss=None),  # 0.1 s after the last fix: uses it
        _frame(2, gnss=None, utc=False),  # no time at all
        _frame(3, ref=HeadingRef.MAGNETIC),
        _frame(4, ref=HeadingRef.MAGNETIC),
        _frame(5, truth=[1.0, 0.0, 0.0]),
        Frame(t_mono_s=100.0, seq=6, image_bgr=np.zeros((40, 64, 3), np.uint8), intrinsics=K,
              attitude=Attitude(0.0, HeadingRef.TRUE), utc_ns=T0_NS + 61 * 10**9),  # fix too old
    ]
    src = GroundTruthSource(frames)
    with caplog.at_level(logging.WARNING, logger="replay.groundtruth"):
        out = list(src)
    assert [f.sun_enu_truth is not None for f in out] == [True, True, False, False, False, True, False]
    np.testing.assert_allclose(out[1].sun_enu_truth, _expected(T0_NS + 100_000_000, FIX), atol=EXACT_F64)
    s = src.truth_stats
    assert (s.frames, s.truth_added, s.had_truth, s.no_fix, s.heading_not_true) == (7, 2, 1, 2, 2)
    warnings = [r for r in caplog.records if "magnetic" in r.getMessage()]
    assert len(warnings) == 1  # once per pass, not per frame
    assert len(list(src)) == 7  # re-iterable
    assert src.truth_stats.frames == 7  # counted afresh each pass, not added to the last


def test_a_fix_is_not_held_for_frames_long_before_it():
    # The held fix's age is a distance in time either way: a frame 61 s before the fix (a
    # recording whose UTC stepped back) is as far from it as one 61 s after.
    early = Frame(t_mono_s=0.2, seq=1, image_bgr=np.zeros((40, 64, 3), np.uint8), intrinsics=K,
                  attitude=Attitude(0.0, HeadingRef.TRUE), utc_ns=T0_NS - 61 * 10**9)
    src = GroundTruthSource([_frame(0), early])
    out = list(src)
    assert out[1].sun_enu_truth is None and src.truth_stats.no_fix == 1


def test_wrapper_stands_in_for_the_source(tmp_path):
    src = with_ground_truth(open_log(DEMO_LOG))
    assert src.truncated is False and src.path == DEMO_LOG  # the native source's attributes
    assert with_ground_truth(src) is src


def test_open_frames_adds_truth_to_a_native_log_with_gnss(tmp_path):
    path = tmp_path / "drive.mcap"
    with LogWriter(path) as w:
        for i in range(6):
            w.write_frame(_frame(i, gnss=FIX if i % 3 == 0 else None,
                                 ref=HeadingRef.RELATIVE if i == 5 else HeadingRef.TRUE))
    plain = list(open_frames(path, ground_truth=False))
    assert all(f.sun_enu_truth is None for f in plain)
    frames = list(open_frames(path))
    assert [f.sun_enu_truth is not None for f in frames] == [True, True, True, True, True, False]
    np.testing.assert_allclose(frames[4].sun_enu_truth, _expected(T0_NS + 400_000_000, FIX), atol=EXACT_F64)


def test_open_frames_keeps_a_logs_own_truth():
    own = list(open_log(DEMO_LOG))
    wrapped = list(open_frames(DEMO_LOG))
    assert len(own) == len(wrapped) > 0
    for a, b in zip(own, wrapped, strict=True):
        np.testing.assert_array_equal(a.sun_enu_truth, b.sun_enu_truth)


def test_a_frames_own_truth_is_dropped_with_a_magnetic_or_relative_heading(caplog):
    # A log recorded with another heading (visual odometry over the demo drive) still carries the
    # drive's true-north truth: it would grade estimates made in a magnetic or start-heading world.
    own = [0.0, 0.6, 0.8]
    frames = [_frame(0, truth=own), _frame(1, ref=HeadingRef.RELATIVE, truth=own),
              _frame(2, ref=HeadingRef.RELATIVE, truth=own), _frame(3, ref=HeadingRef.MAGNETIC, truth=own),
              _frame(4, attitude=False, truth=own)]
    src = GroundTruthSource(frames)
    with caplog.at_level(logging.WARNING, logger="replay.groundtruth"):
        out = list(src)
    assert [f.sun_enu_truth is not None for f in out] == [True, False, False, False, True]
    assert [f.attitude is not None and f.attitude.reference for f in out[1:4]] == [
        HeadingRef.RELATIVE, HeadingRef.RELATIVE, HeadingRef.MAGNETIC]  # only the truth changes
    s = src.truth_stats
    assert (s.frames, s.had_truth, s.heading_not_true, s.truth_added) == (5, 2, 3, 0)
    warned = [r.getMessage() for r in caplog.records if "get no ground truth" in r.getMessage()]
    assert len(warned) == 2 and "relative" in warned[0] and "magnetic" in warned[1]  # once per reference


def test_open_frames_drops_the_truth_of_a_log_recorded_with_a_relative_heading(tmp_path, caplog):
    path = tmp_path / "visual.mcap"
    with LogWriter(path) as w:
        for f in list(open_log(DEMO_LOG))[:4]:
            w.write_frame(dataclasses.replace(f, attitude=Attitude(0.1 * f.seq, HeadingRef.RELATIVE)))
    assert all(f.sun_enu_truth is not None for f in open_frames(path, ground_truth=False))
    with caplog.at_level(logging.WARNING, logger="replay.groundtruth"):
        assert all(f.sun_enu_truth is None for f in open_frames(path))
    assert [r.getMessage().split(": ")[0] for r in caplog.records] == [str(path)]  # which log, when many are read
