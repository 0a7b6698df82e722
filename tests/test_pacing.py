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


def deliveries(pacer, stamps, stall_at=None, stall_s=0.0, read_s=0.0):
    """When each frame is handed on: the clock moves by each wait, by ``read_s`` per frame read,
    and by ``stall_s`` once, before frame ``stall_at`` (the machine stopped: a page-out, SIGSTOP)."""
    now, out = 0.0, []
    for seq, t in enumerate(stamps):
        if seq == stall_at:
            now += stall_s
        now += read_s
        now += pacer.delay_s(frame(seq, t), now_s=now)
        out.append(now)
    return np.array(out)


def test_a_live_replay_that_stalled_paces_on_from_where_it_is_instead_of_rushing():
    # A 3 s stall at 10 Hz: the replay once handed on the 30 frames it was behind at once (each
    # 0.1-2.9 s older than the schedule, a burst of stale estimates after it) and only then went on
    # at 10 Hz. Behind by more than max_behind_s, it paces from the frame it is at, as a camera
    # keeps its rate through a stall of its host.
    p = Pacer(max_jump_s=10.0, max_behind_s=0.5)
    at = deliveries(p, [0.1 * i for i in range(80)], stall_at=40, stall_s=3.0)
    assert np.diff(at[40:]) == pytest.approx(np.full(39, 0.1))
    assert at[40] == pytest.approx(6.9)  # the frame due at 4.0, handed on when the stall ended
    assert p.reanchors == 1


def test_a_replay_slower_than_its_recording_stays_within_max_behind_s_and_says_so_once_a_minute(caplog):
    # Each frame takes 0.12 s to read in a 10 Hz recording: the replay falls behind by 0.02 s a frame.
    p = Pacer(max_jump_s=10.0, max_behind_s=0.5)
    with caplog.at_level("INFO", logger="rig.pacing"):
        at = deliveries(p, [0.1 * i for i in range(1000)], read_s=0.12)  # 120 s
    # Behind the schedule of its last anchor by at most max_behind_s (+ one frame's read): re-anchored
    # about every 25 frames, not left to fall 10 s behind.
    assert 35 <= p.reanchors <= 45
    assert at[-1] == pytest.approx(0.12 * 1000)
    said = [r.getMessage() for r in caplog.records]
    assert 2 <= len(said) <= 3, said  # the first, then once a minute with the count: not 40 lines
    assert "fell behind" in said[0]
    assert "re-anchored" in said[1]


def test_max_behind_s_must_be_positive():
    with pytest.raises(ValueError, match="Pacer"):
        Pacer(10.0, max_behind_s=0.0)


def test_due_s_is_when_the_frame_was_due_by_the_schedule_it_was_paced_on():
    # The live rig counts a paced frame's latency from here: a frame handed on late (the source read
    # slowly, or the host stalled in the wait) was a camera's frame that long ago.
    p = Pacer(max_jump_s=10.0, max_behind_s=1.0)
    p.delay_s(frame(0, 5.0), now_s=100.0)
    assert p.due_s == 100.0
    assert p.delay_s(frame(1, 5.1), now_s=100.05) == pytest.approx(0.05) and p.due_s == pytest.approx(100.1)
    assert p.delay_s(frame(2, 5.2), now_s=100.6) == 0.0 and p.due_s == pytest.approx(100.2)  # 0.4 s late
    assert p.delay_s(frame(3, 5.3), now_s=103.0) == 0.0 and p.due_s == 103.0  # re-anchored: due now
