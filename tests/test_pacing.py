"""Pacing a recording in real time (rig/pacing.py, and the replay loop that sleeps on it)."""

import numpy as np
import pytest

from rig.cli import paced
from rig.pacing import Pacer
from rig.types import Frame, Intrinsics

INTR = Intrinsics(fx=100.0, fy=100.0, cx=32.0, cy=24.0, width=64, height=48)
IMG = np.zeros((48, 64, 3), np.uint8)


def frame(seq, t):
    return Frame(t_mono_s=t, seq=seq, image_bgr=IMG, intrinsics=INTR)


@pytest.mark.parametrize(("max_jump_s", "speed"), [(10.0, 0.0), (10.0, -1.0), (0.0, 1.0)])
def test_speed_and_jump_limit_must_be_positive(max_jump_s, speed):
    with pytest.raises(ValueError, match="Pacer"):
        Pacer(max_jump_s, speed=speed)


def test_frames_wait_for_their_time_scaled_by_speed():
    p = Pacer(max_jump_s=10.0, speed=2.0)
    assert p.delay_s(frame(0, 5.0), now_s=100.0) == 0.0  # the first frame anchors the schedule
    assert p.delay_s(frame(1, 6.0), now_s=100.1) == pytest.approx(0.4)  # due at 100.5 at 2x
    assert p.delay_s(frame(2, 7.0), now_s=102.0) == 0.0  # late: no wait, and not a jump
    assert p.reanchors == 0


def test_a_frame_exactly_the_jump_limit_off_schedule_keeps_the_schedule():
    # "More than max_jump_s" re-anchors; the limit itself does not. A sub-second limit is valid
    # (the live rig passes its ring_max_age_s, any positive number).
    p = Pacer(max_jump_s=0.5)
    assert p.delay_s(frame(0, 0.0), now_s=0.0) == 0.0
    assert p.delay_s(frame(1, 0.5), now_s=0.0) == 0.5  # due exactly the limit ahead: wait for it
    assert p.delay_s(frame(2, 0.75), now_s=1.25) == 0.0  # exactly the limit behind: late, no re-anchor
    assert p.delay_s(frame(3, 1.0), now_s=1.25) == 0.0  # still on the first schedule: late
    assert p.reanchors == 0


def test_a_jump_either_way_re_anchors_instead_of_sleeping_or_rushing(caplog):
    p = Pacer(max_jump_s=10.0)
    p.delay_s(frame(0, 0.0), now_s=0.0)
    with caplog.at_level("INFO", logger="rig.pacing"):
        assert p.delay_s(frame(1, 3600.0), now_s=0.1) == 0.0  # stamped an hour ahead
        assert p.delay_s(frame(2, 3600.1), now_s=0.2) == pytest.approx(0.0, abs=1e-9)  # paced from it
        assert p.delay_s(frame(3, 3600.2), now_s=0.25) == pytest.approx(0.05)
        assert p.delay_s(frame(4, 3600.3), now_s=30.0) == 0.0  # the replay fell 30 s behind
        assert p.delay_s(frame(5, 3600.4), now_s=30.0) == pytest.approx(0.1)  # no rush after it
    assert p.reanchors == 2
    messages = [r.getMessage() for r in caplog.records]
    assert "+3600.0 s from the frame before it" in messages[0]
    assert "the replay is 29.6 s off" in messages[1] and "fell behind" in messages[1]


def test_one_glitched_stamp_is_two_jumps_of_the_recording_not_a_replay_behind(caplog):
    p = Pacer(max_jump_s=10.0)
    with caplog.at_level("INFO", logger="rig.pacing"):
        for seq, (t, now) in enumerate([(0.0, 0.0), (0.1, 0.1), (3600.0, 0.2), (0.3, 0.3), (0.4, 0.4)]):
            p.delay_s(frame(seq, t), now_s=now)
    messages = [r.getMessage() for r in caplog.records]
    assert p.reanchors == 2 and all("the recording's clock jumped" in m for m in messages)
    assert "-3599.7 s" in messages[1]


def test_replay_realtime_does_not_sleep_through_a_glitched_stamp():
    now, slept = [0.0], []

    def sleep(s):
        slept.append(s)
        now[0] += s

    frames = [frame(i, 0.1 * i) for i in range(5)] + [frame(5, 3600.0)] + [frame(i, 0.1 * i) for i in range(6, 9)]
    out = list(paced(frames, clock=lambda: now[0], sleep=sleep))
    assert [f.seq for f in out] == list(range(9))
    assert max(slept) < 1.0 and sum(slept) < 2.0  # without re-anchoring: sleep(3599.5)
