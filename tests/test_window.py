"""The window policy: spread over time, newest always in, what there is while filling."""

import numpy as np
import pytest

from rig.errors import ValidationError
from rig.types import Attitude, Frame, FrameFeatures, HeadingRef, Intrinsics
from rig.window import SpreadWindowPolicy

INTR = Intrinsics(fx=20.0, fy=20.0, cx=8.0, cy=8.0, width=16, height=16)
IMG = np.zeros((16, 16, 3), np.uint8)


def feats(seq, t, heading=True, yaw=None, ref=HeadingRef.TRUE, epoch=0):
    att = Attitude(0.1 * seq if yaw is None else yaw, ref, epoch=epoch) if heading else None
    frame = Frame(t_mono_s=t, seq=seq, image_bgr=IMG, intrinsics=INTR, attitude=att)
    return FrameFeatures(frame, np.zeros((1, 4)), np.zeros((1, 2)), np.zeros((1, 2), np.float32), "m")


def test_filling_takes_all_frames_in_span():
    ring = [feats(i, i * 0.1) for i in range(3)]
    assert [f.frame.seq for f in SpreadWindowPolicy(8, 4.0).select(ring)] == [0, 1, 2]


def test_straight_road_spreads_over_the_span_not_last_n():
    ring = [feats(i, i * 0.1, yaw=1.0) for i in range(100)]  # 10 s at 10 Hz, constant heading
    chosen = SpreadWindowPolicy(8, 3.5).select(ring)
    t = np.array([f.frame.t_mono_s for f in chosen])
    assert len(chosen) == 8 and chosen[-1] is ring[-1]
    assert (np.diff(t) > 0).all()
    assert t[0] == pytest.approx(9.9 - 3.5, abs=0.051)  # reaches back over the whole span
    assert np.diff(t).min() >= 0.3  # no two near-identical neighbours (the last 8 would be 0.1 s apart)


def test_a_turn_draws_more_frames_than_the_straight():
    # 3 s straight (heading 0), then a 90 deg turn in the last 1 s, at 10 Hz.
    yaws = [0.0] * 30 + list(np.linspace(0.0, np.pi / 2, 11))
    ring = [feats(i, i * 0.1, yaw=y) for i, y in enumerate(yaws)]
    chosen = SpreadWindowPolicy(8, 4.0).select(ring)
    in_turn = sum(f.frame.t_mono_s >= 3.0 for f in chosen)
    assert in_turn > 8 * 1.0 / 4.0  # more than the turn's 1/4 share of the span
    assert chosen[0].frame.t_mono_s <= 0.5  # the straight is still represented


def test_time_apart_is_counted_in_spans():
    # The oldest frame is one span back at the same heading (distance 1); the middle one a quarter
    # span back but turned 90 deg, two yaw scales (distance ~2.02). In seconds the oldest would
    # look 4 apart and win.
    ring = [feats(0, 0.0, yaw=0.0), feats(1, 3.0, yaw=np.pi / 2), feats(2, 4.0, yaw=0.0)]
    assert [f.frame.seq for f in SpreadWindowPolicy(2, 4.0).select(ring)] == [1, 2]


def test_yaw_scale_is_the_turn_that_counts_as_much_as_one_span():
    # The oldest frame is one span back at the same heading (distance 1); the middle one a quarter
    # span back, turned 20 deg. At a 10 deg scale that turn is two spans (distance ~2.02) and wins;
    # at 45 deg it is 0.44 of a span (distance ~0.51) and the oldest wins.
    ring = [feats(0, 0.0, yaw=0.0), feats(1, 3.0, yaw=np.radians(20.0)), feats(2, 4.0, yaw=0.0)]

    def pick(scale_deg):
        return [f.frame.seq for f in SpreadWindowPolicy(2, 4.0, np.radians(scale_deg)).select(ring)]

    assert pick(10.0) == [1, 2]
    assert pick(45.0) == [0, 2]


def test_headings_apart_wrap_through_north():
    # 357.1 deg and 2.9 deg are 5.7 deg apart across north: the oldest frame nearly repeats the
    # newest, and the one turned to 34 deg is the more different view.
    ring = [feats(0, 2.9, yaw=2 * np.pi - 0.05), feats(1, 3.0, yaw=0.6), feats(2, 4.0, yaw=0.05)]
    assert [f.frame.seq for f in SpreadWindowPolicy(2, 4.0).select(ring)] == [1, 2]


def test_deterministic():
    ring = [feats(i, i * 0.1, yaw=0.05 * (i % 7)) for i in range(60)]
    a = SpreadWindowPolicy().select(ring)
    b = SpreadWindowPolicy().select(list(ring))
    assert [f.frame.seq for f in a] == [f.frame.seq for f in b]


def test_frames_without_heading_are_never_chosen():
    ring = [feats(i, i * 0.1, heading=i % 2 == 0) for i in range(40)]
    assert all(f.frame.attitude is not None for f in SpreadWindowPolicy(8, 4.0).select(ring))
    assert SpreadWindowPolicy().select([feats(0, 0.0, heading=False)]) == []


def test_only_frames_sharing_the_newest_headings_zero_are_chosen():
    # A relative heading source lost its zero at frame 20 (epoch 0 -> 1): the window starts again.
    ring = [feats(i, i * 0.1, ref=HeadingRef.RELATIVE, epoch=int(i >= 20)) for i in range(30)]
    chosen = SpreadWindowPolicy(8, 4.0).select(ring)
    assert len(chosen) == 8 and {f.frame.attitude.epoch for f in chosen} == {1}
    assert [f.frame.seq for f in SpreadWindowPolicy(8, 4.0).select(ring[:21])] == [20]  # just after the loss
    # A source that switched reference (GNSS heading back after a relative stretch) likewise.
    mixed = [feats(i, i * 0.1, ref=HeadingRef.RELATIVE if i < 25 else HeadingRef.TRUE) for i in range(30)]
    assert {f.frame.attitude.reference for f in SpreadWindowPolicy(8, 4.0).select(mixed)} == {HeadingRef.TRUE}


def test_distinct_frames_even_when_sparse():
    ring = [feats(i, t) for i, t in enumerate([0.0, 0.1, 0.2, 3.9, 3.95, 4.0, 4.05, 4.1, 4.2, 4.3])]
    chosen = SpreadWindowPolicy(8, 4.3).select(ring)  # 10 frames in span, most bunched at the end
    assert len({id(f) for f in chosen}) == len(chosen) == 8
    assert chosen[0] is ring[0] and chosen[-1] is ring[-1]


def test_frames_sharing_a_time_and_heading_are_each_chosen_once():
    # A coarse or frozen clock while the vehicle stands: 12 frames at 3 (time, heading) points, or
    # all at one. Every distance to a chosen frame is then 0, which once took the newest frame
    # again and again and sent one frame 8 times as a full window.
    policy = SpreadWindowPolicy(8, 4.0)
    for times in ([1.0 + 0.1 * (i // 4) for i in range(12)], [5.0] * 12):
        chosen = policy.select([feats(i, t, yaw=0.3) for i, t in enumerate(times)])
        seqs = [f.frame.seq for f in chosen]
        assert len(set(seqs)) == len(seqs) == 8 and seqs[-1] == 11, (times, seqs)
    # The earliest time point is still reached: spreading holds among the repeated stamps.
    chosen = policy.select([feats(i, 1.0 + 0.1 * (i // 4), yaw=0.3) for i in range(12)])
    assert chosen[0].frame.t_mono_s == 1.0


def test_bad_policy():
    with pytest.raises(ValidationError):
        SpreadWindowPolicy(0, 1.0)
    with pytest.raises(ValidationError):
        SpreadWindowPolicy(8, 0.0)
    with pytest.raises(ValidationError):
        SpreadWindowPolicy(8, 1.0, yaw_scale_rad=0.0)


def test_smallest_policy_is_the_newest_frame_alone():
    ring = [feats(i, i * 0.1) for i in range(5)]
    assert [f.frame.seq for f in SpreadWindowPolicy(1, 1.0).select(ring)] == [4]
