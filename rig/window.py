"""Which frames form a window. Pure logic: takes the candidates, returns the chosen ones.

Consecutive frames at 10-30 Hz are nearly identical, so "the last 8" would show the network one
view eight times. The policy instead picks frames that differ: the newest frame always, then,
greedily, the candidate farthest from every frame chosen so far (farthest-point sampling), where
two frames' distance combines their time apart (in units of the span) and their headings apart
(in units of ``yaw_scale_rad``). On a straight road that spreads the window over the span; in a
turn it takes more of the frames that look in new directions, which is where the paper's
spatio-temporal aggregation gains most.

Candidates are the frames with a heading from the last ``span_s`` seconds. While fewer than
``n_frames`` are there (the ring is filling, or the source is slow), the window is all of them:
an estimate from fewer frames now (reported in ``n_frames``) beats none.

A window's frames share one heading zero: the newest frame's reference and epoch, and no heading
jump between them. A heading that changes between two frames by more than ``MIN_JUMP_RAD`` faster
than ``max_yaw_rate_rad_s`` is not a turn the camera made (a compass glitch, a source whose zero
moved unsaid), and the picture did not turn with it. The farthest-point rule would take such a
frame first, as the most different view, into every window for a whole span. So a frame that jumps
away from both its neighbours while they agree (one glitched heading) is left out, and otherwise
the window starts again from the jump, as after a new epoch: until the next frame says which it
was, a newest frame that jumped is a window of its own.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from rig.errors import ValidationError
from rig.geometry import wrap_pi
from rig.types import FrameFeatures

T = TypeVar("T", bound=FrameFeatures)

# Faster than a vehicle turns its camera: a car rarely turns 40 deg/s. The synthetic drives turn at
# most 17.4 deg a frame (173.5 deg/s at their 10 frames a second, over the 100 held-out drives), under
# MIN_JUMP_RAD a frame at any frame rate, so no synthetic frame is ever taken for a jump.
DEFAULT_MAX_YAW_RATE_RAD_S = math.radians(180.0)
# A smaller change is never a jump, however close the frames' stamps: a compass's noise (a few
# degrees) between frames stamped together (a burst, a frozen clock) is an impossible rate too.
MIN_JUMP_RAD = math.radians(45.0)


@dataclass(frozen=True)
class SpreadWindowPolicy:
    """Up to ``n_frames`` frames from the last ``span_s`` seconds, diverse in time and yaw."""

    n_frames: int = 8
    span_s: float = 4.0
    yaw_scale_rad: float = math.radians(45.0)
    max_yaw_rate_rad_s: float = DEFAULT_MAX_YAW_RATE_RAD_S

    def __post_init__(self) -> None:
        if self.n_frames < 1:
            raise ValidationError(f"window n_frames: expected >= 1, got {self.n_frames}")
        if not self.span_s > 0:
            raise ValidationError(f"window span_s: expected > 0 s, got {self.span_s}")
        if not self.yaw_scale_rad > 0:
            raise ValidationError(f"window yaw_scale_rad: expected > 0, got {self.yaw_scale_rad}")
        if not self.max_yaw_rate_rad_s > 0:
            raise ValidationError(f"window max_yaw_rate_rad_s: expected > 0 rad/s, got {self.max_yaw_rate_rad_s}")

    def select(self, candidates: Sequence[T]) -> list[T]:
        """Chosen frames, oldest first. ``candidates`` must be ordered by time, oldest first.

        Only frames whose heading shares the newest heading's zero are candidates
        (:meth:`same_zero`): the same reference and, for relative headings, the same epoch (after
        a source lost its zero, the window starts again from the frames after it), and no heading
        jump between them."""
        usable = self.same_zero(candidates)
        t_s = np.array([c.frame.t_mono_s for c in usable])
        # Every one has an attitude (same_zero); the test only tells the type checker so.
        heading_rad = np.array([c.frame.attitude.heading_rad for c in usable if c.frame.attitude is not None])
        return [usable[i] for i in self.select_indices(t_s, heading_rad)] if usable else []

    def same_zero(self, candidates: Sequence[T]) -> list[T]:
        """The candidates (in order) whose heading shares the newest heading's zero: the same
        reference and epoch, after the last heading jump (:meth:`_jumps`), less any frame whose
        heading alone jumped away and back. The frames a window can be made of."""
        with_attitude = [(c, c.frame.attitude) for c in candidates if c.frame.attitude is not None]
        if not with_attitude:
            return []
        newest = with_attitude[-1][1]
        usable = [c for c, a in with_attitude if (a.reference, a.epoch) == (newest.reference, newest.epoch)]
        t_s = np.array([c.frame.t_mono_s for c in usable])
        heading_rad = np.array([a.heading_rad for c in usable if (a := c.frame.attitude) is not None])
        # A heading off both its neighbours, which agree with each other: a glitch of that frame alone.
        into = self._jumps(t_s[:-1], heading_rad[:-1], t_s[1:], heading_rad[1:])  # into frame i + 1 from i
        glitch = np.zeros(len(usable), bool)
        glitch[1:-1] = into[:-1] & into[1:] & ~self._jumps(t_s[:-2], heading_rad[:-2], t_s[2:], heading_rad[2:])
        kept = np.flatnonzero(~glitch)
        # Any other jump is where the heading's zero moved: the window starts again from the last one.
        t_s, heading_rad = t_s[kept], heading_rad[kept]
        into = np.flatnonzero(self._jumps(t_s[:-1], heading_rad[:-1], t_s[1:], heading_rad[1:]))
        start = int(into[-1]) + 1 if len(into) else 0
        return [usable[i] for i in kept[start:]]

    def _jumps(self, t_from_s: np.ndarray, heading_from_rad: np.ndarray, t_to_s: np.ndarray,
               heading_to_rad: np.ndarray) -> np.ndarray:
        """Whether the heading changed between each pair of frames by more than ``MIN_JUMP_RAD``,
        faster than ``max_yaw_rate_rad_s``: more than a vehicle turns its camera."""
        turn_rad = np.abs(wrap_pi(heading_to_rad - heading_from_rad))
        dt_s = np.abs(t_to_s - t_from_s)
        return (turn_rad > MIN_JUMP_RAD) & (turn_rad > self.max_yaw_rate_rad_s * dt_s)

    def pool_start(self, t_s: np.ndarray, newest: int | np.ndarray = -1) -> np.ndarray:
        """Of frames at times ``t_s`` (ascending): the index of the oldest within the span of the
        frame ``newest`` (an index, or an array of them), where a window ending there may start."""
        return np.searchsorted(t_s, t_s[newest] - self.span_s, side="left")

    def select_indices(self, t_s: np.ndarray, heading_rad: np.ndarray) -> list[int]:
        """The window of frames at times ``t_s`` (ascending, the last the newest) with headings
        ``heading_rad`` in one reference: their indices, ascending. The rule of :meth:`select`, on
        arrays, for training to draw its windows as the rig does (``estimator/train.py``)."""
        first = int(self.pool_start(t_s))
        n_pool = len(t_s) - first
        if n_pool <= self.n_frames:
            return list(range(first, len(t_s)))
        t = t_s[first:] / self.span_s
        yaw = heading_rad[first:]
        dist = np.hypot(t[:, None] - t[None, :], wrap_pi(yaw[:, None] - yaw[None, :]) / self.yaw_scale_rad)
        chosen = [n_pool - 1]  # the newest frame is always in
        nearest = dist[-1].copy()
        # A chosen frame is never chosen again, even where frames share a time and a heading (a
        # coarse or frozen clock while the vehicle stands): every distance is then 0, and the
        # argmax would take the newest frame again and again.
        nearest[n_pool - 1] = -np.inf
        for _ in range(self.n_frames - 1):
            # Ties (e.g. equal distances) go to the newer frame: argmax of the reversed array.
            best = n_pool - 1 - int(np.argmax(nearest[::-1]))
            chosen.append(best)
            nearest = np.minimum(nearest, dist[best])
            nearest[best] = -np.inf
        return [first + i for i in sorted(chosen)]
