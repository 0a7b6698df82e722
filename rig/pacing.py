"""When each frame of a recording is due, so that a replay runs at the recording's own pace.

Pure logic with an injected clock reading; the loops that sleep are :func:`rig.cli.paced`
(``sunrig replay --realtime``) and the live rig's capture stage (``RigConfig.realtime``).
"""

from __future__ import annotations

import logging

from rig.types import Frame

log = logging.getLogger(__name__)


class Pacer:
    """The wait before each frame: its time since the first frame, scaled by ``speed``, against
    the wall clock since then.

    A frame more than ``max_jump_s`` off that schedule re-anchors it at the frame: a recording
    whose clock jumps ahead is not slept through (one glitched stamp could freeze a replay for an
    hour), and a replay that fell that far behind (a slow source, a suspended machine) does not
    then rush every later frame. No window spans such a jump anyway. ``reanchors`` counts them.
    """

    def __init__(self, max_jump_s: float, speed: float = 1.0) -> None:
        if not (max_jump_s > 0 and speed > 0):
            raise ValueError(f"Pacer: expected max_jump_s > 0 and speed > 0, got {max_jump_s} and {speed}")
        self.max_jump_s = max_jump_s
        self.speed = speed
        self.reanchors = 0
        self._start_s: float | None = None
        self._first_t_s = 0.0
        self._last_t_s = 0.0

    def delay_s(self, frame: Frame, now_s: float) -> float:
        """Seconds to wait before ``frame`` (0 when it is due or late)."""
        t, last = frame.t_mono_s, self._last_t_s
        self._last_t_s = t
        if self._start_s is None:
            self._start_s, self._first_t_s = now_s, t
            return 0.0
        delay = self._start_s + (t - self._first_t_s) / self.speed - now_s
        if abs(delay) <= self.max_jump_s:
            return max(delay, 0.0)
        # Off schedule: the recording's own clock jumped between two frames (either way), or the
        # replay fell behind a recording that did not.
        step = t - last
        if abs(step) > self.max_jump_s:
            log.info("seq %d is stamped %+.1f s from the frame before it (the recording's clock jumped): "
                     "pacing from it", frame.seq, step)
        else:
            log.info("the replay is %.1f s off the recording's schedule at seq %d (it fell behind): "
                     "pacing from here, not rushing", -delay, frame.seq)
        self.reanchors += 1
        self._start_s, self._first_t_s = now_s, t
        return 0.0
