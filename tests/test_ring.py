"""Bounded buffers: overflow policy, counters, and waits that always end."""

import threading

import numpy as np
import pytest

from rig.errors import ValidationError
from rig.ring import LATE_FRAME_TOLERANCE_S, UTC_DISAGREEMENT_TOLERANCE_S, DropOldestQueue, FrameRing
from rig.types import Attitude, Frame, FrameFeatures, HeadingRef, Intrinsics

INTR = Intrinsics(fx=20.0, fy=20.0, cx=8.0, cy=8.0, width=16, height=16)
IMG = np.zeros((16, 16, 3), np.uint8)


UTC0_NS = 1_700_000_000 * 10**9  # 2023-11-14: the UTC the stamps below count from


def feats(seq, t, utc_s=None):
    """A frame at monotonic ``t``, and at ``utc_s`` seconds after UTC0_NS when given."""
    utc_ns = None if utc_s is None else UTC0_NS + round(utc_s * 1e9)
    frame = Frame(t_mono_s=t, seq=seq, image_bgr=IMG, intrinsics=INTR, attitude=Attitude(0.0, HeadingRef.TRUE),
                  utc_ns=utc_ns)
    return FrameFeatures(frame, np.zeros((1, 4)), np.zeros((1, 2)), np.zeros((1, 2), np.float32), "m")


def test_queue_drops_oldest_and_counts():
    q = DropOldestQueue(3)
    results = [q.put(i) for i in range(5)]
    assert results == [True, True, True, False, False]
    assert q.dropped == 2 and q.put_count == 5
    assert [q.get(0.0) for _ in range(4)] == [2, 3, 4, None]


def test_queue_get_times_out_and_close_wakes_waiters():
    q = DropOldestQueue(1)
    # An empty get waits for its timeout: one that returned at once would make the consumer spin
    # on an empty queue. Checked by the wait it asks for, not by a clock.
    waits = []
    real_wait = q._cond.wait
    q._cond.wait = lambda timeout=None: waits.append(timeout) or real_wait(timeout)
    assert q.get(0.2) is None and waits == [0.2]
    q._cond.wait = real_wait
    got = []
    waiter = threading.Thread(target=lambda: got.append(q.get(30.0)))
    waiter.start()
    q.close()
    waiter.join(5.0)
    assert not waiter.is_alive() and got == [None]


def test_queue_get_waits_only_when_empty_and_open():
    # An item waiting, or a closed queue, is answered at once: a get that waited out its timeout
    # there would stall every consumer (and a publisher's drain at shutdown) by a poll interval.
    q = DropOldestQueue(2)
    waits = []
    real_wait = q._cond.wait
    q._cond.wait = lambda timeout=None: waits.append(timeout) or real_wait(timeout)
    q.put("a")
    assert q.get(2.0) == "a" and waits == []
    q.put("b")
    q.close()
    assert q.get(2.0) == "b" and q.get(2.0) is None and waits == []


def test_queue_memory_is_flat_under_overload():
    q = DropOldestQueue(4)
    for i in range(10_000):
        q.put(i)
    assert len(q) == 4 and q.dropped == 10_000 - 4


def test_ring_bounded_by_count_and_age():
    ring = FrameRing(capacity=5, max_age_s=1.0)
    for i in range(8):
        ring.push(feats(i, 0.1 * i))
    assert [f.frame.seq for f in ring.snapshot()] == [3, 4, 5, 6, 7]
    assert ring.evicted == 3
    ring.push(feats(8, 5.0))  # a gap: everything older than 1 s goes
    assert [f.frame.seq for f in ring.snapshot()] == [8]


def test_ring_keeps_a_frame_exactly_max_age_older_than_the_newest():
    # "At most max_age_s older than the newest": the edge itself stays.
    ring = FrameRing(capacity=10, max_age_s=1.0)
    for i, t in enumerate([0.0, 0.5, 1.0]):
        ring.push(feats(i, t))
    assert [f.frame.seq for f in ring.snapshot()] == [0, 1, 2] and ring.evicted == 0
    ring.push(feats(3, 1.5))
    assert [f.frame.seq for f in ring.snapshot()] == [1, 2, 3] and ring.evicted == 1


def test_ring_of_one_holds_the_newest_frame():
    ring = FrameRing(capacity=1)
    assert ring.push(feats(0, 0.0)) and ring.push(feats(1, 0.1))
    assert [f.frame.seq for f in ring.snapshot()] == [1] and ring.evicted == 1


def test_ring_refuses_late_frames():
    ring = FrameRing()
    assert ring.push(feats(1, 1.0))
    assert not ring.push(feats(0, 0.5))
    assert ring.out_of_order == 1 and len(ring) == 1
    # The same time as the newest is not late (two frames on one coarse clock tick).
    assert ring.push(feats(2, 1.0))
    assert ring.out_of_order == 1 and len(ring) == 2


def test_ring_starts_again_after_a_clock_jump():
    # One frame stamped an hour ahead: the frames after it are not late, the clock jumped. The
    # ring starts again from the first of them instead of refusing every frame from then on.
    ring = FrameRing(capacity=10, max_age_s=4.0)
    for i in range(3):
        assert ring.push(feats(i, 0.1 * i))
    assert ring.push(feats(3, 3600.0))
    assert [f.frame.seq for f in ring.snapshot()] == [3]  # its age evicted the rest
    assert ring.push(feats(4, 0.4)) and ring.push(feats(5, 0.5))
    assert [f.frame.seq for f in ring.snapshot()] == [4, 5]
    assert ring.restarts == 1 and ring.out_of_order == 0
    assert ring.evicted == 4  # 3 by age when the jump came, then the one stamped ahead at the restart
    # A frame a few frames late is still refused, not a restart.
    assert not ring.push(feats(6, 0.45)) and ring.out_of_order == 1 and ring.restarts == 1


def test_ring_tells_a_late_frame_from_a_clock_jump_by_how_far_behind_the_newest_it_is():
    # Stamps as a monotonic clock gives them (seconds since boot), not near zero. How far behind a
    # late frame may be does not hang on how long the ring keeps frames (the live rig's 10 s here).
    ring = FrameRing(capacity=10, max_age_s=10.0)
    assert ring.push(feats(0, 1000.0))
    assert not ring.push(feats(1, 999.96))  # one frame late at 30 fps
    assert not ring.push(feats(2, 1000.0 - LATE_FRAME_TOLERANCE_S))  # exactly the tolerance: still late
    assert ring.out_of_order == 2 and ring.restarts == 0 and len(ring) == 1
    assert ring.push(feats(3, 1000.0 - LATE_FRAME_TOLERANCE_S - 0.25))  # further back: the clock stepped back
    assert ring.restarts == 1 and [f.frame.seq for f in ring.snapshot()] == [3]
    assert ring.last_restart == "is 1.2 s older than the frame before it"


@pytest.mark.parametrize("max_age_s", [4.0, 10.0])  # a replay's ring (the window span) and the live rig's
def test_a_clock_stepped_back_by_seconds_restarts_either_ring_at_once(max_age_s):
    # A source whose stamps step back 5 s: the live ring refused every frame for 5 s as late (no
    # estimates), while a replay's ring started again at once. Both start again now.
    ring = FrameRing(capacity=128, max_age_s=max_age_s)
    for i in range(4):
        assert ring.push(feats(i, 1000.0 + 0.25 * i))
    assert ring.push(feats(4, 1001.0 - 5.0))
    assert ring.restarts == 1 and ring.out_of_order == 0 and [f.frame.seq for f in ring.snapshot()] == [4]
    assert ring.push(feats(5, 996.25)) and [f.frame.seq for f in ring.snapshot()] == [4, 5]


def test_ring_starts_again_after_a_suspend_that_the_monotonic_clock_did_not_see():
    # A host suspended for an hour: CLOCK_MONOTONIC stood still, UTC did not. The frames from before
    # the suspend are an hour old (the sun moved ~15 deg since), not a moment: no window may mix
    # them with the frame after the resume. The live ring (max age 10 s), stamps as the clocks give.
    ring = FrameRing(capacity=128, max_age_s=10.0)
    for i in range(3):
        assert ring.push(feats(i, 1000.0 + 0.25 * i, 0.25 * i))
    assert ring.push(feats(3, 1000.75, 3600.75))  # 0.25 s on from seq 2 by one clock, an hour by the other
    assert [f.frame.seq for f in ring.snapshot()] == [3]
    assert ring.restarts == 1 and ring.evicted == 3 and ring.out_of_order == 0
    assert "UTC" in ring.last_restart  # what the live rig's log line says
    # The clocks agree again from there: the ring fills as usual.
    assert ring.push(feats(4, 1001.0, 3601.0))
    assert [f.frame.seq for f in ring.snapshot()] == [3, 4] and ring.restarts == 1


def test_ring_keeps_frames_whose_utc_and_monotonic_clock_disagree_by_no_more_than_the_tolerance():
    # A UTC carried by the monotonic clock from the newest GNSS sentence moves by the sentences'
    # latency (tens of ms) when the next one arrives, a leap second by 1 s: not a suspend. The edge
    # itself is kept; only frames that both carry UTC are compared.
    tol = UTC_DISAGREEMENT_TOLERANCE_S
    ring = FrameRing(capacity=10, max_age_s=10.0)
    assert ring.push(feats(0, 1000.0, 0.0))
    assert ring.push(feats(1, 1000.25, 0.25 + 0.05))
    assert ring.push(feats(2, 1000.5, 0.5 + 0.05 + 1.0))  # a leap second
    assert ring.push(feats(3, 1000.75, 0.75 + 0.05 + 1.0 + tol))
    assert ring.restarts == 0 and len(ring) == 4
    assert ring.push(feats(4, 1001.0))  # no UTC: nothing to compare it with
    assert ring.push(feats(5, 1001.25, 3600.0))  # the newest kept (seq 4) has none either
    assert ring.restarts == 0 and len(ring) == 6
    # Between two that carry it, a disagreement either way counts (a host clock set back).
    assert ring.push(feats(6, 1001.5, 3600.25 - tol - 0.5))
    assert ring.restarts == 1 and [f.frame.seq for f in ring.snapshot()] == [6]


def test_bad_sizes():
    with pytest.raises(ValidationError):
        DropOldestQueue(0)
    with pytest.raises(ValidationError):
        FrameRing(capacity=0)
    for max_age_s in (0.0, -1.0, float("nan")):
        with pytest.raises(ValidationError):
            FrameRing(max_age_s=max_age_s)


def test_a_ring_full_by_count_says_how_many_seconds_it_holds():
    # A 60 fps camera fills the default 128 frames in 2.1 s, less than a window's 4 s span: the
    # windows then spanned half what they should, with nothing said. The ring tells how many
    # seconds it held when it last let a frame go for room (not for age).
    ring = FrameRing(capacity=4, max_age_s=10.0)
    for i in range(4):
        ring.push(feats(i, i * 0.5))
    assert ring.crowded_span_s is None  # nothing let go yet
    ring.push(feats(4, 2.0))
    assert ring.crowded_span_s == pytest.approx(1.5)  # frames 1..4: 0.5 s to 2.0 s
    aged = FrameRing(capacity=4, max_age_s=1.0)
    for i in range(8):
        aged.push(feats(i, i * 0.5))
    assert aged.crowded_span_s is None and aged.evicted == 5  # let go for age only
