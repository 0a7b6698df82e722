"""Bounded buffers between the rig's stages. Each states its overflow policy and counts drops.

- :class:`DropOldestQueue`: between capture and encoding. ``put`` never blocks: when full, the
  oldest waiting item is dropped (a live estimate wants the newest frame, not a backlog).
- :class:`FrameRing`: the encoded frames (frame + crop embeddings) the window policy chooses from.
  Bounded by count and by age; what falls out is counted as evicted, which is normal operation,
  not a loss.

Both are thread-safe; every wait takes a timeout so no stage can hang on them.
"""

from __future__ import annotations

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
# The oldest frame a ring keeps behind the newest (the live rig's [rig] ring_max_age_s); a frame
# further behind is a clock that jumped, and the ring starts again from it.
DEFAULT_MAX_AGE_S = 10.0


class FrameRing:
    """The last encoded frames, oldest first, at most ``capacity`` and at most ``max_age_s`` older
    than the newest one."""

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

    def push(self, feats: FrameFeatures) -> bool:
        """Add the newest frame; a frame older than the newest held is refused (and counted):
        windows assume time order, and a late frame adds nothing to a live estimate.

        A frame more than ``max_age_s`` older than the newest is not late: the clock jumped (one
        frame stamped far ahead, or a source that restarted its clock). Refusing it would refuse
        every frame from then on, so the ring starts again from it (counted in ``restarts``)."""
        with self._lock:
            if self._frames and feats.frame.t_mono_s < self._frames[-1].frame.t_mono_s:
                if self._frames[-1].frame.t_mono_s - feats.frame.t_mono_s <= self.max_age_s:
                    self.out_of_order += 1
                    return False
                self.evicted += len(self._frames)
                self._frames.clear()
                self.restarts += 1
            self._frames.append(feats)
            newest = feats.frame.t_mono_s
            while len(self._frames) > self.capacity or newest - self._frames[0].frame.t_mono_s > self.max_age_s:
                self._frames.popleft()
                self.evicted += 1
            return True

    def snapshot(self) -> list[FrameFeatures]:
        """A copy of the held frames, oldest first, for the window policy to choose from."""
        with self._lock:
            return list(self._frames)

    def __len__(self) -> int:
        with self._lock:
            return len(self._frames)
