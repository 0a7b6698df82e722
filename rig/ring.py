"""Bounded buffers between the rig's stages. Each states its overflow policy and counts drops.

- :class:`DropOldestQueue`: between capture and encoding. ``put`` never blocks: when full, the
  oldest waiting item is dropped (a live estimate wants the newest frame, not a backlog).
- :class:`FrameRing`: the encoded frames (frame + crop embeddings) the window policy chooses from.
  Bounded by count and by age; what falls out is counted as evicted, which is normal operation,
  not a loss.

Both are thread-safe; every wait takes a timeout so no stage can hang on them.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from typing import Generic, TypeVar

from rig.errors import ValidationError
from rig.types import FrameFeatures

T = TypeVar("T")


class DropOldestQueue(Generic[T]):
    """A bounded FIFO whose ``put`` drops the oldest item instead of blocking when full."""

    def __init__(self, maxsize: int) -> None:
        if maxsize < 1:
            raise ValidationError(f"queue size: expected >= 1, got {maxsize}")
        self.maxsize = maxsize
        self._items: deque[T] = deque()
        self._cond = threading.Condition()
        self.put_count = 0
        self.dropped = 0
        self._closed = False

    def put(self, item: T) -> bool:
        """Add ``item``; returns False when an older item had to be dropped to make room."""
        with self._cond:
            self.put_count += 1
            dropped = len(self._items) >= self.maxsize
            if dropped:
                self._items.popleft()
                self.dropped += 1
            self._items.append(item)
            self._cond.notify()
            return not dropped

    def get(self, timeout: float) -> T | None:
        """The oldest item, or None after ``timeout`` seconds (or at once when closed and empty)."""
        with self._cond:
            if not self._items and not self._closed:
                self._cond.wait(timeout)
            return self._items.popleft() if self._items else None

    def close(self) -> None:
        """Wake every waiter; later ``get`` calls return what is left, then None without waiting."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


# Frames a ring holds at most (the live rig's [rig] ring_capacity, and a replay's): 4 s of a
# 30 fps camera, the window policy's default span.
DEFAULT_RING_CAPACITY = 128
# The oldest frame a ring keeps behind the newest (the live rig's [rig] ring_max_age_s).
DEFAULT_MAX_AGE_S = 10.0
# The longest a frame is held behind the newest on the frames' own clock, however long the vehicle
# stands (the max age counts view time, which stands still with it: rig/window.py): the sun moves
# at most 0.25 deg a minute, 0.5 deg in this time, and a window older than that is stale anyway.
MAX_HOLD_S = 120.0
# How far behind the newest held a frame may be stamped and still be late (refused) rather than a
# clock that stepped back (the ring starts again from it). A late frame is a few frames late: tens
# of ms at 30 fps, a few hundred at 5 fps. Refusing a step back costs every frame until the stamps
# catch up, no estimate at all for that long; starting again costs a refill, estimates from fewer
# frames. Beyond a second the refill is the smaller loss. Not tied to max_age_s: the live ring
# (10 s) refused 5 s of frames after a 5 s step where a replay's (the 4 s window span) restarted.
LATE_FRAME_TOLERANCE_S = 1.0
# How far the UTC between a frame and the newest held may disagree with their monotonic stamps
# before it is a clock jump: CLOCK_MONOTONIC stands still while the host is suspended and UTC does
# not, so after a resume the held frames are as old as the suspend, not a moment. Honest clocks
# disagree by far less: a UTC carried by the monotonic clock from the newest GNSS sentence moves by
# the sentences' latency (tens of ms), an NTP slew by 0.5 ms a second, a leap second by 1 s. Missed
# disagreements are harmless: a window mixes frames at most this much further apart than it thinks,
# and the sun moves at most ~0.25 deg a minute, 0.02 deg in 5 s.
UTC_DISAGREEMENT_TOLERANCE_S = 5.0


def ring_too_short(ring: FrameRing, span_s: float) -> str | None:
    """What to say when ``ring``, full by count, holds less than a window's ``span_s``: a camera
    faster than ``capacity`` frames a span (128 frames are 2.1 s at 60 fps, half the 4 s span)
    narrows every window, in time and so in the headings it sees, with nothing else to show it.
    None while it holds enough."""
    held_s = ring.crowded_span_s
    if held_s is None or held_s <= 0 or held_s >= span_s:
        return None
    fps = (ring.capacity - 1) / held_s
    return (f"[rig] ring_capacity {ring.capacity} holds only {held_s:.1f} s of this camera's frames ({fps:.0f} fps), "
            f"less than [window] span_s {span_s:g} s: windows span less than they should; set ring_capacity to "
            f"{math.ceil(round(fps * span_s, 6))} or more")


class FrameRing:
    """The last encoded frames, oldest first, at most ``capacity`` and at most ``max_age_s`` older
    than the newest one in view time (``FrameFeatures.window_t_s``: time stood still left out),
    and at most ``MAX_HOLD_S`` on the frames' clock. Of the repeats of one view (a vehicle
    standing) it keeps the newest two: the newest, and the one before it, which the estimator may
    still be about to take its window for; so a stop fills no room."""

    def __init__(self, capacity: int = DEFAULT_RING_CAPACITY, max_age_s: float = DEFAULT_MAX_AGE_S) -> None:
        if capacity < 1:
            raise ValidationError(f"ring capacity: expected >= 1 frames, got {capacity}")
        if not max_age_s > 0:
            raise ValidationError(f"ring max age: expected > 0 s, got {max_age_s}")
        self.capacity = capacity
        self.max_age_s = max_age_s
        self._frames: deque[FrameFeatures] = deque()
        self._lock = threading.Lock()
        self.evicted = 0
        self.out_of_order = 0
        self.restarts = 0
        self.last_restart = ""  # why the ring last started again, worded to follow "seq N "
        # The seconds the ring held (newest minus oldest) when it last let a frame go for room, not
        # for age: a camera fast enough to fill ``capacity`` sooner than a window's span (None: never).
        self.crowded_span_s: float | None = None

    def push(self, feats: FrameFeatures) -> bool:
        """Add the newest frame; a frame older than the newest held is refused (and counted):
        windows assume time order, and a late frame adds nothing to a live estimate.

        The ring starts again from the frame (counted in ``restarts``, the reason in
        ``last_restart``) when its clock jumped: it is more than ``LATE_FRAME_TOLERANCE_S`` older
        than the newest (one frame stamped far ahead, or a source whose clock stepped back or
        restarted; refusing it would refuse every frame until the stamps caught up, or from then on),
        or it and the newest both carry UTC and their UTC difference disagrees with their monotonic
        one by more than ``UTC_DISAGREEMENT_TOLERANCE_S`` (a suspend, which the monotonic clock does
        not count: the held frames are older than they look)."""
        frame = feats.frame
        with self._lock:
            if self._frames:
                newest = self._frames[-1].frame
                behind_s = newest.t_mono_s - frame.t_mono_s
                if behind_s > LATE_FRAME_TOLERANCE_S:
                    self._restart(f"is {behind_s:.1f} s older than the frame before it")
                elif behind_s > 0:
                    self.out_of_order += 1
                    return False
                elif newest.utc_ns is not None and frame.utc_ns is not None:
                    utc_s, mono_s = (frame.utc_ns - newest.utc_ns) / 1e9, frame.t_mono_s - newest.t_mono_s
                    if abs(utc_s - mono_s) > UTC_DISAGREEMENT_TOLERANCE_S:
                        self._restart(f"is {utc_s:.1f} s after the frame before it in UTC but {mono_s:.1f} s "
                                      "on the monotonic clock (a suspend and resume, or a clock set)")
            self._frames.append(feats)
            if feats.view_key != frame.seq:
                self._drop_older_repeats(feats.view_key)
            newest_s, newest_view_s = frame.t_mono_s, feats.window_t_s
            while (len(self._frames) > self.capacity or newest_view_s - self._frames[0].window_t_s > self.max_age_s
                   or newest_s - self._frames[0].frame.t_mono_s > MAX_HOLD_S):
                oldest = self._frames[0]
                crowded = (newest_view_s - oldest.window_t_s <= self.max_age_s
                           and newest_s - oldest.frame.t_mono_s <= MAX_HOLD_S)  # let go for room, not age
                self._frames.popleft()
                self.evicted += 1
                if crowded:
                    self.crowded_span_s = newest_view_s - self._frames[0].window_t_s
            return True

    def _drop_older_repeats(self, view_key: int) -> None:
        """Called under the lock, a repeat of view ``view_key`` just added: let go of the repeats of
        that view before the newest two (the view's first frame stays, a frame of its own time)."""
        repeats = [i for i in range(len(self._frames) - 1, -1, -1)
                   if self._frames[i].view_key == view_key and self._frames[i].frame.seq != view_key]
        for i in repeats[2:]:  # from the newest down: indices stay valid
            del self._frames[i]
            self.evicted += 1

    def _restart(self, why: str) -> None:
        """Called under the lock: drop every held frame (counted as evicted) and say why."""
        self.evicted += len(self._frames)
        self._frames.clear()
        self.restarts += 1
        self.last_restart = why

    def snapshot(self) -> list[FrameFeatures]:
        """A copy of the held frames, oldest first, for the window policy to choose from."""
        with self._lock:
            return list(self._frames)

    def __len__(self) -> int:
        with self._lock:
            return len(self._frames)
