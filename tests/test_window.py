"""The window policy: spread over time, newest always in, what there is while filling."""

import numpy as np
import pytest

from rig.errors import ValidationError
from rig.types import Attitude, Frame, FrameFeatures, HeadingRef, Intrinsics
from rig.window import SpreadWindowPolicy

INTR = Intrinsics(fx=20.0, fy=20.0, cx=8.0, cy=8.0, width=16, height=16)
IMG = np.zeros((16, 16, 3), np.uint8)


def feats(seq, t, heading=True):
    att = Attitude(0.1 * seq, HeadingRef.TRUE) if heading else None
    frame = Frame(t_mono_s=t, seq=seq, image_bgr=IMG, intrinsics=INTR, attitude=att)
    return FrameFeatures(frame, np.zeros((1, 4)), np.zeros((1, 2)), np.zeros((1, 2), np.float32), "m")


def test_filling_takes_all_frames_in_span():
    ring = [feats(i, i * 0.1) for i in range(3)]
    assert [f.frame.seq for f in SpreadWindowPolicy(8, 4.0).select(ring)] == [0, 1, 2]


def test_spread_over_span_not_last_n():
    ring = [feats(i, i * 0.1) for i in range(100)]  # 10 s at 10 Hz
    chosen = SpreadWindowPolicy(8, 3.5).select(ring)
    t = [f.frame.t_mono_s for f in chosen]
    assert len(chosen) == 8 and chosen[-1] is ring[-1]
    assert t == sorted(t)
    assert t[0] == pytest.approx(9.9 - 3.5, abs=0.051)
    np.testing.assert_allclose(np.diff(t), 0.5, atol=0.051)  # evenly spread, not consecutive


def test_frames_without_heading_are_never_chosen():
    ring = [feats(i, i * 0.1, heading=i % 2 == 0) for i in range(40)]
    assert all(f.frame.attitude is not None for f in SpreadWindowPolicy(8, 4.0).select(ring))
    assert SpreadWindowPolicy().select([feats(0, 0.0, heading=False)]) == []


def test_distinct_frames_even_when_sparse():
    ring = [feats(i, t) for i, t in enumerate([0.0, 0.1, 0.2, 3.9, 3.95, 4.0, 4.05, 4.1, 4.2, 4.3])]
    chosen = SpreadWindowPolicy(8, 4.3).select(ring)  # 10 frames in span, most bunched at the end
    assert len({id(f) for f in chosen}) == len(chosen) == 8
    assert chosen[0] is ring[0] and chosen[-1] is ring[-1]


def test_bad_policy():
    with pytest.raises(ValidationError):
        SpreadWindowPolicy(0, 1.0)
    with pytest.raises(ValidationError):
        SpreadWindowPolicy(8, 0.0)
