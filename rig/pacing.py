"""When each frame of a recording is due, so that a replay runs at the recording's own pace.

Pure logic with an injected clock reading; the loops that sleep are :func:`rig.cli.paced`
(``sunrig replay --realtime``) and the live rig's capture stage (``RigConfig.realtime``).
"""

from __future__ import annotations

import logging

from rig.lasting import EventThrottle
from rig.types import Frame

log = logging.getLogger(__name__)

_BEHIND_SAID_EVERY_S = 60.0


class Pacer:
    """The wait before each frame: its time since the first frame, scaled by ``speed``, against
    the wall clock since then.

    A frame more than ``max_jump_s`` ahead of that schedule, or more than ``max_behind_s`` behind it
    (default ``max_jump_s``), re-anchors it at the frame: a recording whose clock jumps ahead is not
    slept through (one glitched stamp could freeze a replay for an hour), and a replay that fell
    behind (a slow source, a stalled or suspended machine) does not then rush every later frame.
    The live rig passes a ``max_behind_s`` of its latency bound: a replay there stands for a camera,
    which keeps its rate through a stall of its host; rushing the frames missed handed on a burst
    of frames each older than the last estimate's (seconds, after a 3 s page-out). ``reanchors``
    counts them; falling behind is said once, then once a minute with the count since. ``due_s`` is
    when the last frame was due on the clock of ``now_s`` (the live rig's latency starts there).
    """

    def __init__(self, max_jump_s: float, speed: float = 1.0, max_behind_s: float | None = None) -> None:
        max_behind_s = max_jump_s if max_behind_s is None else max_behind_s
        if not (max_jump_s > 0 and speed > 0 and max_behind_s > 0):
            raise ValueError(f"Pacer: expected max_jump_s > 0, speed > 0 and max_behind_s > 0, got {max_jump_s}, "
                             f"{speed} and {max_behind_s}")
        self.max_jump_s = max_jump_s
        self.max_behind_s = max_behind_s
        self.speed = speed
        self.reanchors = 0
        self._behind = EventThrottle(_BEHIND_SAID_EVERY_S)  # falling behind, said by now_s
        self._start_s: float | None = None
        self._first_t_s = 0.0
        self._last_t_s = 0.0
        self.due_s = 0.0

    def delay_s(self, frame: Frame, now_s: float) -> float:
        """Seconds to wait before ``frame`` (0 when it is due or late)."""
        t, last = frame.t_mono_s, self._last_t_s
        self._last_t_s = t
        if self._start_s is None:
            self._start_s, self._first_t_s, self.due_s = now_s, t, now_s
            return 0.0
        delay = self._start_s + (t - self._first_t_s) / self.speed - now_s
        if -self.max_behind_s <= delay <= self.max_jump_s:
            self.due_s = now_s + delay
            return max(delay, 0.0)
        # Off schedule: the recording's own clock jumped between two frames (either way), or the
        # replay fell behind a recording that did not.
        step = t - last
        if abs(step) > self.max_jump_s:
            log.info("seq %d is stamped %+.1f s from the frame before it (the recording's clock jumped): "
                     "pacing from it", frame.seq, step)
        else:
            self._say_behind(-delay, frame.seq, now_s)
        self.reanchors += 1
        self._start_s, self._first_t_s, self.due_s = now_s, t, now_s
        return 0.0

    def _say_behind(self, behind_s: float, seq: int, now_s: float) -> None:
        # A source slower than its recording falls behind again and again (every few seconds with a
        # small max_behind_s): said once, then once a minute, not at each re-anchor.
        said = self._behind.note(now_s)
        if said is None:
            return
        n, said_before_s = said
        if said_before_s is None:
            log.info("the replay is %.1f s off the recording's schedule at seq %d (it fell behind): "
                     "pacing from here, not rushing", behind_s, seq)
        else:
            log.info("the replay fell behind the recording's schedule and re-anchored %d times in %.0f s, the last "
                     "%.1f s behind at seq %d: a source slower than its recording (said once a minute while it "
                     "goes on)", n, now_s - said_before_s, behind_s, seq)
