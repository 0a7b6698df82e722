"""Pairing a camera with a heading source (drivers/pairing.py): golden interpolation (across north
too), every reason a frame gets no heading, the counters, and the stream wrapper with a heading
source that is still arriving (an injected clock: no sleeps)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from drivers.nmea import HeadingSample
from drivers.pairing import FINAL, HeadingInterpolator, PairingStats, interpolate, with_heading
from rig.errors import ValidationError
from rig.types import Frame, GnssFix, HeadingRef, Intrinsics
from tests.tolerances import ANGLE_RAD_F64

INTR = Intrinsics.from_hfov(8, 6, math.radians(60.0))


def sample(t: float, heading_deg: float, ref=HeadingRef.TRUE, pitch_deg=None, roll_deg=None) -> HeadingSample:
    rad = None if pitch_deg is None else math.radians(pitch_deg)
    roll = None if roll_deg is None else math.radians(roll_deg)
    return HeadingSample(t, math.radians(heading_deg), ref, rad, roll, "HDT", None)


def frame(t: float, seq: int) -> Frame:
    return Frame(t, seq, INTR, image_bgr=np.zeros((6, 8, 3), np.uint8))


def deg(attitude) -> float:
    return math.degrees(attitude.heading_rad)


# --- the pure interpolator -----------------------------------------------------------------------


@pytest.mark.parametrize(("h0", "h1", "w", "expected"), [
    (359.0, 1.0, 0.5, 0.0),  # across north the short way, not through 180
    (359.0, 1.0, 0.25, 359.5),
    (1.0, 359.0, 0.75, 359.5),
    (10.0, 20.0, 0.3, 13.0),
    (170.0, 190.0, 0.5, 180.0),
    (90.0, 270.0 - 1e-9, 0.5, 180.0),  # just under half a turn: the clockwise arc
])
def test_golden_interpolation(h0, h1, w, expected):
    att = interpolate(sample(0.0, h0), sample(1.0, h1), w)
    assert math.radians(deg(att)) == pytest.approx(math.radians(expected % 360.0), abs=1e-6)


def test_interpolates_between_the_samples_around_the_frame():
    interp = HeadingInterpolator(max_gap_s=1.5, max_age_s=1.0)
    samples = [sample(10.0, 358.0), sample(11.0, 2.0), sample(12.0, 6.0)]
    assert deg(interp.at(samples, 10.5)) == pytest.approx(0.0, abs=1e-9)
    assert deg(interp.at(samples, 11.75)) == pytest.approx(5.0, abs=1e-9)
    assert interp.at(samples, 11.0).heading_rad == pytest.approx(math.radians(2.0), abs=ANGLE_RAD_F64)
    assert interp.counts["interpolated"] == 2 and interp.counts["exact"] == 1


def test_the_weight_is_the_fraction_of_the_samples_interval():
    # A 10 Hz heading source: a frame 25 ms after a sample is a quarter of the way to the next.
    interp = HeadingInterpolator(max_gap_s=0.5, max_age_s=1.0)
    samples = [sample(20.0, 40.0), sample(20.1, 44.0), sample(20.2, 48.0)]
    assert deg(interp.at(samples, 20.025)) == pytest.approx(41.0, abs=1e-6)
    assert deg(interp.at(samples, 20.175)) == pytest.approx(47.0, abs=1e-6)


def test_pitch_and_roll_are_interpolated_only_when_both_samples_have_them():
    att = interpolate(sample(0, 0, pitch_deg=2.0, roll_deg=-4.0), sample(1, 0, pitch_deg=4.0, roll_deg=0.0), 0.5)
    assert math.degrees(att.pitch_rad) == pytest.approx(3.0) and math.degrees(att.roll_rad) == pytest.approx(-2.0)
    att = interpolate(sample(0, 0, pitch_deg=2.0), sample(1, 0), 0.5)
    assert att.pitch_rad is None and att.roll_rad is None


def test_out_of_range_frames_get_no_heading():
    interp = HeadingInterpolator()
    samples = [sample(10.0, 5.0), sample(11.0, 6.0)]
    assert interp.lookup(samples, 9.99).status == "before"
    assert interp.lookup(samples, 11.01).status == "after"  # no extrapolation past the newest
    assert interp.lookup([], 10.0).status == "before"
    assert interp.at(samples, 12.0) is None


def test_a_gap_is_not_interpolated_across():
    interp = HeadingInterpolator(max_gap_s=1.5)
    samples = [sample(10.0, 0.0), sample(12.0, 90.0)]
    result = interp.lookup(samples, 11.0)
    assert result.attitude is None and result.status == "gap"


def test_no_heading_is_interpolated_across_a_suspend_of_the_host():
    # CLOCK_MONOTONIC stands still while the host is suspended: a sample read just before an hour's
    # suspend (10.0) and the first after it (10.6) look 0.6 s apart, and a frame between them was
    # given a heading half-way between the vehicle's heading then and an hour later. Each sample
    # carries CLOCK_BOOTTIME - CLOCK_MONOTONIC when it was read (boot_offset_s), which grows by the
    # time suspended; two samples around a frame that differ in it are a gap, however close they look.
    from drivers.nmea import SUSPEND_TOLERANCE_S

    def at(t, heading_deg, boot):
        return dataclasses.replace(sample(t, heading_deg), boot_offset_s=boot)

    interp = HeadingInterpolator(max_gap_s=1.5, max_age_s=1.5)
    samples = [at(9.6, 0.0, 2.0), at(10.0, 4.0, 2.0), at(10.6, 90.0, 3602.0), at(11.0, 94.0, 3602.0)]
    for t in (10.1, 10.5):  # a frame from just before the suspend, and one from just after it
        result = interp.lookup(samples, t)
        assert result.attitude is None and result.status == "gap", t
    assert deg(interp.at(samples, 9.8)) == pytest.approx(2.0)  # both samples before the suspend
    assert deg(interp.at(samples, 10.8)) == pytest.approx(92.0)  # both after it
    assert interp.at(samples, 10.6) is not None  # a frame at a sample's own time is that sample
    # Live: a frame after the last sample from before the suspend waits (the monotonic clock has not
    # moved on), and the sample that then comes from after the suspend does not give it a heading.
    assert interp.lookup(samples[:2], 10.1, now_s=10.3).status == "pending"
    assert interp.lookup(samples[:3], 10.1, now_s=10.6).status == "gap"
    # Two clock reads a moment apart are not a suspend; a sample without the offset (not Linux, a
    # recorded sequence, visual odometry) is paired by the monotonic clock alone, as before.
    near = [at(10.0, 4.0, 2.0), at(10.6, 10.0, 2.0 + SUSPEND_TOLERANCE_S / 2)]
    assert deg(interp.at(near, 10.3)) == pytest.approx(7.0)
    unknown = [at(10.0, 4.0, 2.0), sample(10.6, 10.0)]
    assert deg(interp.at(unknown, 10.3)) == pytest.approx(7.0)


def test_stale_while_live():
    interp = HeadingInterpolator(max_gap_s=1.5, max_age_s=0.5)
    samples = [sample(10.0, 0.0), sample(11.0, 10.0)]
    assert interp.lookup(samples, 11.2, now_s=11.4).status == "pending"  # the next sample may come
    assert interp.lookup(samples, 11.2, now_s=11.8).status == "stale"  # waited longer than max_age_s
    # The newest sample is so old that whatever comes next is more than max_gap_s after it.
    assert HeadingInterpolator(max_gap_s=1.0, max_age_s=5.0).lookup(samples, 11.2, now_s=12.1).status == "gap"


def test_the_wait_for_a_late_compass_counts_from_its_own_clock():
    # A 1 Hz compass 1 s late: the sample after a frame at 11.2 (its 12.0) arrives at 13.0. The
    # wait was counted on the host's clock, so at the default 1.5 s the frame went stale at 12.7,
    # a third of all frames (196 of 599 in the review's simulation).
    interp = HeadingInterpolator(max_gap_s=1.5, max_age_s=1.5, latency_s=1.0)
    arrived = [sample(11.0, 0.0), sample(12.0, 10.0)]  # stamped on arrival: the compass's 10.0 and 11.0
    assert interp.lookup(arrived, 11.2, now_s=12.9).status == "pending"
    assert interp.lookup([*arrived, sample(13.0, 20.0)], 11.2, now_s=13.0).attitude is not None
    assert interp.lookup(arrived, 11.2, now_s=13.8).status == "stale"  # 1.5 s past its time on the compass's clock


def test_a_frame_stamped_after_it_arrived_gets_no_heading():
    # Its stamp is not the host's clock (a device clock that stepped, a replayed file): the
    # samples at its stamp were measured after the frame was taken, so none is matched to it.
    interp = HeadingInterpolator(max_gap_s=1.5, max_age_s=1.5)
    samples = [sample(10.0, 0.0), sample(11.0, 10.0)]
    assert interp.lookup(samples, 10.5, now_s=11.0, arrived_s=10.2).status == "ahead"
    assert interp.lookup(samples, 10.5, arrived_s=10.2).status == "ahead"  # the source has ended: the same
    assert interp.lookup(samples, 10.5, now_s=11.0, arrived_s=10.5).status == "interpolated"  # stamped on arrival
    assert interp.lookup(samples, 10.5, now_s=11.0).status == "interpolated"  # no arrival given: by its stamp
    assert interp.counts["ahead"] == 2


def test_mixed_references_are_not_interpolated():
    interp = HeadingInterpolator()
    samples = [sample(0.0, 10.0, HeadingRef.TRUE), sample(1.0, 12.0, HeadingRef.MAGNETIC)]
    assert interp.lookup(samples, 0.5).status == "mixed"
    assert interp.at(samples, 1.0).reference is HeadingRef.MAGNETIC


def test_interleaved_references_give_each_frame_the_best_one_around_it():
    # HDT and an HDG without variation from one receiver, 20 ms apart at 10 Hz: every pair of
    # samples around a frame was mixed, and no frame got a heading.
    samples = []
    for k in range(10):
        samples += [sample(0.1 * k, 90.0 + k, HeadingRef.TRUE), sample(0.1 * k + 0.02, 80.0 + k, HeadingRef.MAGNETIC)]
    interp = HeadingInterpolator()
    got = [interp.at(samples, 0.05 + 0.1 * i) for i in range(9)]
    assert all(a is not None and a.reference is HeadingRef.TRUE for a in got)
    assert math.degrees(got[3].heading_rad) == pytest.approx(93.5)  # between the true samples, 3.05 s
    # Live: a frame after the newest true sample waits for the next one, though a magnetic
    # sample after it is already there.
    assert interp.lookup(samples, 0.91, now_s=0.95).status == "pending"
    # Magnetic where true has nothing: a compass before its GNSS heading came up.
    switching = [sample(0.0, 10.0, HeadingRef.MAGNETIC), sample(1.0, 12.0, HeadingRef.MAGNETIC),
                 sample(2.0, 30.0, HeadingRef.TRUE), sample(3.0, 32.0, HeadingRef.TRUE)]
    assert interp.at(switching, 0.5).reference is HeadingRef.MAGNETIC
    assert interp.at(switching, 2.5).reference is HeadingRef.TRUE
    assert interp.lookup(switching, 1.5).status == "mixed"


def test_latency_moves_the_samples_earlier():
    interp = HeadingInterpolator(latency_s=0.2)
    samples = [sample(10.2, 0.0), sample(11.2, 10.0)]
    assert deg(interp.at(samples, 10.5)) == pytest.approx(5.0)


def test_latency_is_allowed_for_while_waiting_for_the_next_sample():
    # A live frame after the newest sample waits while the next one can still be close enough to
    # it. With 0.5 s latency the next sample, arriving now, is dated now - 0.5 s: at now = 11.3 it
    # would be 0.8 s after the newest (dated 10.0), within max_gap_s = 1.0, so the frame waits
    # (without the latency it would look 1.3 s away and the frame would be lost as a gap).
    interp = HeadingInterpolator(max_gap_s=1.0, max_age_s=2.0, latency_s=0.5)
    samples = [sample(10.5, 0.0)]  # stamped 10.5, measured at 10.0
    assert interp.lookup(samples, 10.2, now_s=11.3).status == "pending"
    assert interp.lookup(samples, 10.2, now_s=11.6).status == "gap"  # 1.1 s: too far now
    assert deg(interp.at(samples + [sample(11.5, 10.0)], 10.2)) == pytest.approx(2.0)


def test_counters_count_final_results_only():
    interp = HeadingInterpolator(max_gap_s=1.5, max_age_s=0.5)
    samples = [sample(10.0, 0.0), sample(11.0, 10.0), sample(14.0, 10.0)]
    for t in (9.0, 10.0, 10.5, 12.0):
        interp.lookup(samples, t)
    interp.lookup(samples, 14.1, now_s=14.2)  # pending: not counted
    interp.lookup(samples, 10.5, count=False)
    assert interp.counts == dict.fromkeys(FINAL, 0) | {"before": 1, "exact": 1, "interpolated": 1, "gap": 1}


@pytest.mark.parametrize("kwargs", [{"max_gap_s": 0}, {"max_age_s": -1}, {"max_gap_s": math.inf},
                                    {"latency_s": -0.1}, {"max_age_s": None}])
def test_bad_limits_are_refused(kwargs):
    with pytest.raises(ValidationError):
        HeadingInterpolator(**kwargs)


# --- the stream wrapper --------------------------------------------------------------------------


class ArrivingHeadings:
    """A heading source whose samples arrive as the (injected) clock passes their time, like a
    GnssReader's history; ``utc_at``/``latest_fix`` as the reader answers them."""

    def __init__(self, samples, clock, utc0_ns=None, fix=None):
        self.samples, self.clock, self.utc0_ns, self.fix = samples, clock, utc0_ns, fix

    def heading_history(self):
        now = self.clock()
        return [s for s in self.samples if s.t_mono_s <= now]

    def utc_at(self, now_s, max_age_s=10.0):
        return None if self.utc0_ns is None else self.utc0_ns + round(now_s * 1e9)

    def latest_fix(self, now_s, max_age_s=1.5):
        return self.fix


class Clock:
    def __init__(self, t=0.0):
        self.t = t

    def __call__(self):
        return self.t


def camera(clock: Clock, times):
    """Frames that arrive at their own time (the clock follows them), as from a live camera."""
    for seq, t in enumerate(times):
        clock.t = t
        yield frame(t, seq)


def test_live_frames_wait_for_the_heading_after_them():
    clock = Clock()
    samples = [sample(t, 10.0 * t) for t in (0.0, 1.0, 2.0, 3.0)]
    source = ArrivingHeadings(samples, clock)
    times = [0.25 * k for k in range(1, 14)]  # 0.25 .. 3.25 s
    out = list(with_heading(camera(clock, times), source, HeadingInterpolator(max_gap_s=1.5, max_age_s=1.5),
                            clock=clock))
    assert [f.seq for f in out] == list(range(len(times)))  # every frame, in order
    assert [deg(f.attitude) for f in out[:-1]] == pytest.approx([10.0 * t for t in times[:-1]])
    assert out[-1].attitude is None  # after the last sample, when the camera stopped: never extrapolated


def test_a_stalled_heading_source_leaves_frames_without_heading():
    clock = Clock()
    samples = [sample(0.0, 0.0), sample(1.0, 10.0)]  # then the compass goes quiet
    stats = PairingStats(HeadingInterpolator(max_gap_s=1.5, max_age_s=0.5))
    times = [0.5, 1.2, 1.4, 1.6, 2.0, 2.5, 3.0]
    out = list(with_heading(camera(clock, times), ArrivingHeadings(samples, clock), stats.interpolator,
                            clock=clock, stats=stats))
    assert [f.attitude is not None for f in out] == [True] + [False] * 6
    counts = stats.as_dict()
    assert counts["frames"] == 7 and counts["interpolated"] == 1
    assert counts["stale"] + counts["gap"] + counts["after"] == 6


def test_the_wait_buffer_is_bounded():
    clock = Clock()
    stats = PairingStats(HeadingInterpolator(max_gap_s=100.0, max_age_s=100.0))
    source = ArrivingHeadings([sample(0.0, 0.0)], clock)
    out = list(with_heading(camera(clock, [0.1 * k for k in range(1, 11)]), source, stats.interpolator,
                            clock=clock, stats=stats, max_pending=3))
    assert len(out) == 10 and all(f.attitude is None for f in out)
    assert stats.overflow == 10 - 3  # all but the last max_pending were let go early


def test_a_frame_stamped_far_ahead_does_not_hold_the_frames_behind_it():
    # A frame stamped 100 s ahead of the clock waited until the clock reached its stamp (plus
    # max_age_s), and every frame behind it with it, until 256 piled up: 8.5 s of a 30 Hz camera
    # with no output. Now each frame waits at most max_age_s (beyond the latency) after it arrived.
    clock = Clock()
    max_age_s, latency_s, dt = 0.5, 0.2, 1 / 30
    samples = [sample(0.1 * k + latency_s, float(k)) for k in range(101)]  # 10 Hz, stamped on arrival
    stats = PairingStats(HeadingInterpolator(max_gap_s=0.5, max_age_s=max_age_s, latency_s=latency_s))
    arrived = {}

    def frames():
        for seq in range(270):  # 9 s: more than max_pending frames behind the one stamped ahead
            clock.t = 0.5 + seq * dt
            arrived[seq] = clock.t
            yield frame(clock.t + (100.0 if seq == 3 else 0.0), seq)

    out = []
    for f in with_heading(frames(), ArrivingHeadings(samples, clock), stats.interpolator, clock=clock, stats=stats):
        out.append(f)
        if f.seq < 260:  # the last ones come out when the camera stops
            assert clock.t - arrived[f.seq] <= max_age_s + latency_s + dt, f.seq
    assert [f.seq for f in out] == list(range(270))
    assert out[3].attitude is None  # its samples would come 100 s after it was taken
    # Every other frame gets its heading, as before (but the last few: the camera stopped first).
    assert all(f.attitude is not None for f in out[:260] if f.seq != 3)
    counts = stats.as_dict()
    assert counts["ahead"] == 1 and counts["overflow"] == 0 and counts["stale"] == 0


def test_a_frame_stamped_a_little_ahead_gets_no_heading_though_samples_come_for_its_stamp():
    # 0.3 s ahead of the clock, within max_age_s: the samples around its stamp do arrive in
    # time, but they were measured 0.3 s after the frame was taken; no heading is matched to it.
    clock = Clock()
    samples = [sample(0.1 * k, float(k)) for k in range(31)]
    stats = PairingStats(HeadingInterpolator(max_gap_s=0.5, max_age_s=1.0))

    def frames():
        for seq, t in enumerate((1.0, 1.1, 1.2, 1.3, 1.4, 1.5)):
            clock.t = t
            yield frame(t + (0.3 if seq == 1 else 0.0), seq)

    out = list(with_heading(frames(), ArrivingHeadings(samples, clock), stats.interpolator, clock=clock, stats=stats))
    assert [f.attitude is not None for f in out] == [True, False, True, True, True, True]
    assert stats.as_dict()["ahead"] == 1


def test_gnss_utc_and_fix_are_attached():
    clock = Clock()
    fix = GnssFix(utc_ns=1_700_000_000 * 10**9, lat_deg=48.1, lon_deg=11.5)
    source = ArrivingHeadings([sample(0.0, 0.0), sample(1.0, 10.0), sample(2.0, 20.0)], clock,
                              utc0_ns=1_700_000_000 * 10**9, fix=fix)
    out = list(with_heading(camera(clock, [0.5, 1.5]), source, clock=clock))
    assert [f.utc_ns for f in out] == [1_700_000_000 * 10**9 + 500_000_000, 1_700_000_000 * 10**9 + 1_500_000_000]
    assert all(f.gnss == fix for f in out)


def test_a_frame_stamped_ahead_gets_no_utc():
    # Its stamp is not the host's clock: the UTC carried from now to it was extrapolated to a time
    # that had not come (100 s ahead here), beyond the reader's own limits. Its neighbours get theirs.
    clock = Clock()
    utc0 = 1_700_000_000 * 10**9
    fix = GnssFix(utc_ns=utc0, lat_deg=48.1, lon_deg=11.5)
    samples = [sample(0.1 * k, float(k)) for k in range(31)]
    stats = PairingStats(HeadingInterpolator(max_gap_s=0.5, max_age_s=1.0))

    def frames():
        for seq, t in enumerate((1.0, 1.1, 1.2)):
            clock.t = t
            yield frame(t + (100.0 if seq == 1 else 0.0), seq)

    out = list(with_heading(frames(), ArrivingHeadings(samples, clock, utc0_ns=utc0, fix=fix), stats.interpolator,
                            clock=clock, stats=stats))
    assert stats.as_dict()["ahead"] == 1
    assert [f.utc_ns for f in out] == [utc0 + 1_000_000_000, None, utc0 + 1_200_000_000]
    assert all(f.gnss == fix for f in out)  # the newest position is as near to it as to any frame


def test_a_recorded_sequence_of_samples():
    samples = [sample(0.0, 350.0), sample(1.0, 10.0)]
    out = list(with_heading([frame(0.5, 0), frame(1.5, 1)], samples, live=False))
    assert deg(out[0].attitude) == pytest.approx(0.0, abs=1e-9) and out[1].attitude is None


def test_an_unusable_heading_source_is_refused():
    with pytest.raises(ValidationError, match="heading_history"):
        list(with_heading([frame(0.0, 0)], object()))


def test_frames_after_an_ended_source_do_not_wait():
    clock = Clock()
    source = ArrivingHeadings([sample(0.0, 0.0), sample(1.0, 10.0)], Clock(10.0))  # all read already
    source.finished = True  # a capture file read to its end
    stats = PairingStats(HeadingInterpolator())
    out = []
    for f in with_heading(camera(clock, [0.5, 1.2, 1.3]), source, stats.interpolator, clock=clock, stats=stats):
        out.append((f.seq, clock.t))
    assert out == [(0, 0.5), (1, 1.2), (2, 1.3)]  # each released as it came, not held back
    assert stats.interpolator.counts["after"] == 2


# --- a heading sample that glitches (one sentence off: multipath) ---------------------------------


def compass_1hz(glitch_at: dict[int, float], n: int = 7, rate_deg_s: float = 5.0) -> list[HeadingSample]:
    """A 1 Hz compass on a vehicle turning at ``rate_deg_s`` from 10 deg, its samples ``k`` replaced
    by ``glitch_at[k]`` degrees."""
    return [sample(float(k), glitch_at.get(k, 10.0 + rate_deg_s * k)) for k in range(n)]


def off_deg(attitude, expected_deg: float) -> float:
    return abs(math.degrees(math.remainder(attitude.heading_rad - math.radians(expected_deg), math.tau)))


def test_a_glitched_sample_of_a_1hz_compass_is_not_interpolated_into_a_ramp():
    # One HDT half a turn off (a dual-antenna compass's multipath): interpolated, it made a 2 s ramp
    # out to 180 deg and back across 20 frames, each frame step under the window's jump rule, so it
    # passed for a turn and poisoned every window for seconds. Left out, the frames around it are
    # interpolated between the samples on either side (with a max_gap_s that spans the two intervals).
    samples = compass_1hz({3: 10.0 + 5.0 * 3 + 180.0})
    interp = HeadingInterpolator(max_gap_s=2.5, max_age_s=1.5)
    for k in range(21, 40):  # 2.1 .. 3.9 s
        t = k / 10
        assert off_deg(interp.at(samples, t), 10.0 + 5.0 * t) < 1e-6, t
    assert interp.glitches == 1
    # At the default max_gap_s the samples left around it are too far apart: no heading, not a wrong one.
    default = PairingStats(HeadingInterpolator())
    assert all(default.interpolator.at(samples, k / 10) is None for k in range(21, 40))
    assert default.as_dict()["glitch"] == 1 and default.as_dict()["gap"] == 19


def headings_at(interp, samples, times) -> list:
    return [None if (a := interp.at(samples, t)) is None else deg(a) % 360.0 for t in times]


@pytest.mark.parametrize(("headings", "glitches"), [
    ([10.0, 100.0, 190.0, 280.0], 0),  # a steady turn at 90 deg/s: no sample off the line between its neighbours
    ([10.0, 10.0, 100.0, 100.0], 0),  # 90 deg in a second, then straight on: it stays
    ([10.0, 55.0, 10.0, 10.0], 0),  # out 45 deg and back: at the jump floor, a swerve
    ([10.0, 55.5, 10.0, 10.0], 1),  # just beyond it both ways: no vehicle turns so
])
def test_a_real_turn_at_the_limit_is_kept(headings, glitches):
    samples = [sample(float(k), h) for k, h in enumerate(headings)]
    interp = HeadingInterpolator(max_gap_s=2.5)
    times = [0.5, 1.0, 1.5, 2.5]
    got = headings_at(interp, samples, times)
    assert interp.glitches == glitches
    if not glitches:  # as interpolated without the check
        assert got == pytest.approx([deg(interpolate(samples[int(t)], samples[int(t) + 1], t % 1.0)) % 360.0
                                     if t % 1.0 else headings[int(t)] for t in times])
    # The window's own limit at a 10 Hz compass: 18 deg a sample, 180 deg/s, kept whatever its heading.
    fast = [sample(0.1 * k, 18.0 * k) for k in range(30)]
    interp = HeadingInterpolator()
    assert headings_at(interp, fast, [0.05 + 0.1 * k for k in range(29)]) == pytest.approx(
        [(9.0 + 18.0 * k) % 360.0 for k in range(29)])
    assert interp.glitches == 0


def test_a_zero_that_moved_passes_through_unchanged():
    # A source whose zero moved (the heading stays at the new value): no sample is left out, and the
    # frames get what they got without the check (the window's jump rule starts its windows again).
    samples = [sample(float(k), 10.0 if k < 3 else 160.0) for k in range(6)]
    interp = HeadingInterpolator(max_gap_s=1.5)
    times = [0.1 * k for k in range(51)]
    plain = [None if (r := interp.lookup(samples, t)).attitude is None else deg(r.attitude) % 360.0 for t in times]
    assert interp.glitches == 0
    assert plain[20:31:5] == pytest.approx([10.0, 85.0, 160.0]) and plain[45] == pytest.approx(160.0)
    # Live as well: each frame waits for the samples after the jump's, then goes as before. Until
    # the third sample after 2 s (at 5 s) the jump may be a glitch of two samples, and the frames
    # after 2 s that cannot wait for it within max_age_s go without heading (1.4 s of them).
    clock = Clock()
    stats = PairingStats(HeadingInterpolator(max_gap_s=1.5, max_age_s=1.5))
    out = list(with_heading(camera(clock, times[1:]), ArrivingHeadings(samples, clock), stats.interpolator,
                            clock=clock, stats=stats))
    unconfirmed = set(range(21, 35))
    assert [None if f.attitude is None else deg(f.attitude) % 360.0 for f in out] == pytest.approx(
        [None if k in unconfirmed else plain[k] for k in range(1, 51)])
    assert (stats.as_dict()["glitch"], stats.as_dict()["unconfirmed"]) == (0, 14)


def test_two_glitches_in_a_row():
    # Two different wild values: each is off both its neighbours (the first's after is the second),
    # and both are left out.
    samples = [sample(0.1 * k, h) for k, h in enumerate([10.0, 10.0, 190.0, 100.0, 10.0, 10.0])]
    interp = HeadingInterpolator()
    assert headings_at(interp, samples, [0.15, 0.25, 0.35, 0.45]) == pytest.approx([10.0] * 4)
    assert interp.glitches == 2
    # The same value twice: each agrees with one neighbour, so neither is a glitch alone; the two
    # went out and came back together, as no vehicle turns, and are left out as one glitch of two
    # samples. (They were kept: a 1 Hz compass's multipath over two sentences gave 3 s of ramps and
    # headings half a turn off, each frame step a turn to the window.)
    held = [sample(0.1 * k, h) for k, h in enumerate([10.0, 10.0, 190.0, 190.0, 10.0, 10.0])]
    interp = HeadingInterpolator()
    assert headings_at(interp, held, [0.15, 0.2, 0.25, 0.3, 0.35]) == pytest.approx([10.0] * 5)
    assert interp.glitches == 2


def test_a_run_of_glitched_samples_is_left_out_when_it_comes_back_within_3_s():
    # Two sentences of a 1 Hz compass half a turn off: out and back within 3 s (2 to 5 s).
    samples = compass_1hz({3: 195.0, 4: 200.0}, n=9)
    interp = HeadingInterpolator(max_gap_s=3.5)
    assert headings_at(interp, samples, [k / 10 for k in range(21, 50)]) == pytest.approx(
        [10.0 + 0.5 * k for k in range(21, 50)])
    assert interp.glitches == 2
    # Three of a 2 Hz compass, 85-100 deg off: out and back within 2 s.
    fast = [sample(0.5 * k, {6: 110.0, 7: 130.0, 8: 120.0}.get(k, 10.0 + 2.5 * k)) for k in range(14)]
    interp = HeadingInterpolator(max_gap_s=2.5)
    assert headings_at(interp, fast, [k / 10 for k in range(26, 45)]) == pytest.approx(
        [10.0 + 0.5 * k for k in range(26, 45)])
    assert interp.glitches == 3
    # Three of a 1 Hz compass span 4 s from the sample before to the one after: that long out and
    # back may be a vehicle's, and is kept as it is.
    slow = compass_1hz({3: 110.0, 4: 130.0, 5: 120.0}, n=9)
    interp = HeadingInterpolator(max_gap_s=4.5)
    assert headings_at(interp, slow, [3.0, 4.0, 5.0]) == pytest.approx([110.0, 130.0, 120.0])
    assert interp.glitches == 0


def test_a_real_turn_out_and_back_over_two_samples_is_kept():
    # Out 40 deg over two samples and back (a swerve): no sample is more than 45 deg off the line.
    samples = [sample(float(k), h) for k, h in enumerate([10.0, 10.0, 40.0, 50.0, 10.0, 10.0])]
    interp = HeadingInterpolator(max_gap_s=2.5)
    assert headings_at(interp, samples, [2.0, 3.0]) == pytest.approx([40.0, 50.0])
    assert interp.glitches == 0
    # A zero that moved for good over three samples, at a 10 Hz compass: kept, as one of one sample.
    moved = [sample(0.1 * k, 10.0 if k < 3 else 160.0) for k in range(8)]
    interp = HeadingInterpolator()
    assert headings_at(interp, moved, [0.3, 0.5, 0.7]) == pytest.approx([160.0] * 3)
    assert interp.glitches == 0


def test_live_frames_wait_for_a_run_of_glitched_samples_to_end():
    # A 1 Hz compass glitched at 3 and 4 s, a 10 Hz camera, max_age_s long enough to wait for 5 s's
    # sample: no frame gets a glitched heading or a ramp to one.
    clock = Clock()
    samples = compass_1hz({3: 195.0, 4: 200.0}, n=8)
    stats = PairingStats(HeadingInterpolator(max_gap_s=3.5, max_age_s=3.5))
    times = [0.1 * k for k in range(1, 71)]
    out = list(with_heading(camera(clock, times), ArrivingHeadings(samples, clock), stats.interpolator,
                            clock=clock, stats=stats))
    assert all(off_deg(f.attitude, 10.0 + 5.0 * f.t_mono_s) < 1e-6 for f in out[:-1]), \
        [(f.t_mono_s, None if f.attitude is None else deg(f.attitude)) for f in out]
    assert stats.as_dict()["glitch"] == 2
    # At the default max_age_s the frames that cannot wait for the verdict go without heading.
    clock = Clock()
    stats = PairingStats(HeadingInterpolator())
    out = list(with_heading(camera(clock, times), ArrivingHeadings(samples, clock), stats.interpolator,
                            clock=clock, stats=stats))
    wrong = [(f.t_mono_s, deg(f.attitude)) for f in out[:-1]
             if f.attitude is not None and off_deg(f.attitude, 10.0 + 5.0 * f.t_mono_s) > 1e-6]
    assert not wrong, wrong


def test_a_glitch_at_the_start_or_the_end_of_a_stream_is_kept():
    # The first sample has none before it, the last none after it: each looks as a zero that moved
    # there (or from there) does, and is taken as it is, as before.
    first = [sample(float(k), 180.0 if k == 0 else 10.0) for k in range(4)]
    interp = HeadingInterpolator()
    assert headings_at(interp, first, [0.0, 0.5, 1.5]) == pytest.approx([180.0, 95.0, 10.0])
    last = [sample(float(k), 180.0 if k == 3 else 10.0) for k in range(4)]
    assert headings_at(interp, last, [1.5, 2.5, 3.0]) == pytest.approx([10.0, 95.0, 180.0])
    assert interp.glitches == 0
    # Live, the frames before the last sample waited for the one after it, which never came: when the
    # source ends they go as they would have.
    clock = Clock()
    source = ArrivingHeadings(last, clock)
    out = list(with_heading(camera(clock, [2.5, 3.2]), source, HeadingInterpolator(), clock=clock))
    assert deg(out[0].attitude) == pytest.approx(95.0) and out[1].attitude is None


@pytest.mark.parametrize(("headings", "glitches", "at_2s"), [
    ([170.0, 175.0, -5.0, -175.0, -170.0], 1, 180.0),  # half a turn off just past +-180: left out
    ([170.0, 175.0, -175.0, -165.0, -155.0], 0, 185.0),  # a turn across +-180: kept
    ([-175.0, 175.0, 85.0, 175.0, -175.0], 1, 175.0),  # out 90 deg and back from 175, across -180 on both sides
])
def test_glitches_across_plus_minus_180(headings, glitches, at_2s):
    samples = [sample(float(k), h) for k, h in enumerate(headings)]
    interp = HeadingInterpolator(max_gap_s=2.5)
    got = headings_at(interp, samples, [1.5, 2.0, 2.5])
    assert interp.glitches == glitches
    assert got[1] == pytest.approx(at_2s)  # left out: half-way from the sample before it to the one after
    assert abs(got[0] - got[1]) < 10.0 and abs(got[2] - got[1]) < 10.0  # no frame goes the long way round


def test_live_frames_wait_one_more_sample_to_tell_a_glitch():
    # A 1 Hz compass glitched at 3 s, a 10 Hz camera: the frames whose heading comes from the sample
    # at 3 s wait for the one at 4 s, which says it was a glitch. No frame waits longer than max_age_s.
    clock = Clock()
    samples = compass_1hz({3: 10.0 + 5.0 * 3 + 180.0})
    stats = PairingStats(HeadingInterpolator(max_gap_s=2.5, max_age_s=2.5))
    times = [0.1 * k for k in range(1, 61)]
    out, waited = [], []
    for f in with_heading(camera(clock, times), ArrivingHeadings(samples, clock), stats.interpolator,
                          clock=clock, stats=stats):
        out.append(f)
        waited.append(clock.t - f.t_mono_s)
    assert [f.seq for f in out] == list(range(60))
    assert all(off_deg(f.attitude, 10.0 + 5.0 * f.t_mono_s) < 1e-6 for f in out[:-1]), \
        [(f.t_mono_s, deg(f.attitude)) for f in out]
    assert max(waited[:-1]) <= 2.0 + 1e-9  # the frame just after 2 s waited for 4 s's sample
    assert stats.as_dict()["glitch"] == 1
    # A steady compass: frames wait for the sample after them only, as before (one heading interval).
    clock = Clock()
    steady, waited = compass_1hz({}), []
    for f in with_heading(camera(clock, times), ArrivingHeadings(steady, clock), HeadingInterpolator(), clock=clock):
        waited.append(clock.t - f.t_mono_s)
    assert max(waited[:-1]) <= 1.0 + 1e-9


def test_a_frame_waits_for_a_glitchs_verdict_no_longer_than_max_age():
    # At the default max_age_s (1.5 s) the first frames after the sample at 2 s cannot wait for the
    # one at 4 s (each is let go when the frame after max_age_s comes). They went as they would
    # without the check, the way to the glitch: 18, 36 and 54 deg off, each frame step within the
    # window's jump rule. Now they go without heading ('unconfirmed');
    # those after it get none either (the samples at 2 and 4 s are more than max_gap_s apart).
    clock = Clock()
    samples = compass_1hz({3: 10.0 + 5.0 * 3 + 180.0})
    stats = PairingStats(HeadingInterpolator(max_gap_s=1.5, max_age_s=1.5))
    times = [0.1 * k for k in range(1, 61)]
    got = {}
    for f in with_heading(camera(clock, times), ArrivingHeadings(samples, clock), stats.interpolator,
                          clock=clock, stats=stats):
        assert clock.t - f.t_mono_s <= 1.5 + 0.1 + 1e-9, f.seq
        got[round(f.t_mono_s, 1)] = f.attitude
    assert all(got[round(0.1 * k, 1)] is None for k in range(21, 40))
    assert all(got[round(0.1 * k, 1)] is not None for k in range(1, 20))
    assert stats.as_dict()["glitch"] == 1
    assert stats.as_dict()["unconfirmed"] == 3 and stats.as_dict()["gap"] == 16


def test_glitches_are_said_once_then_summed_up_once_a_minute(caplog):
    # A compass glitching every 5 s for 3 minutes: the first is said, then one line a minute.
    glitched = {k: 10.0 + 170.0 for k in range(5, 180, 5)}
    samples = [sample(float(k), glitched.get(k, 10.0)) for k in range(181)]
    clock = Clock()
    stats = PairingStats(HeadingInterpolator(max_gap_s=2.5, max_age_s=2.5))
    with caplog.at_level("WARNING", logger="drivers.pairing"):
        out = list(with_heading(camera(clock, [0.5 * k for k in range(1, 361)]), ArrivingHeadings(samples, clock),
                                stats.interpolator, clock=clock, stats=stats))
    assert len(out) == 360 and stats.as_dict()["glitch"] == len(glitched) == 35
    lines = [r.getMessage() for r in caplog.records if r.name == "drivers.pairing"]
    assert len(lines) == 3, lines  # at 5 s, then at 65 s and 125 s (12 glitches each)
    assert lines[0].startswith("heading sample at 5.00 s left out: it turned +170 deg in 1.00 s")
    assert lines[1].startswith("12 heading samples left out as glitches in 60 s, the last at 65.00 s")
