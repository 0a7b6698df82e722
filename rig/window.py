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


@dataclass(frozen=True)
class SpreadWindowPolicy:
    """Up to ``n_frames`` frames from the last ``span_s`` seconds, diverse in time and yaw."""

    n_frames: int = 8
    span_s: float = 4.0
    yaw_scale_rad: float = math.radians(45.0)

    def __post_init__(self) -> None:
        if self.n_frames < 1:
            raise ValidationError(f"window n_frames: expected >= 1, got {self.n_frames}")
        if not self.span_s > 0:
            raise ValidationError(f"window span_s: expected > 0 s, got {self.span_s}")
        if not self.yaw_scale_rad > 0:
            raise ValidationError(f"window yaw_scale_rad: expected > 0, got {self.yaw_scale_rad}")

    def select(self, candidates: Sequence[T]) -> list[T]:
        """Chosen frames, oldest first. ``candidates`` must be ordered by time, oldest first.

        Only frames whose heading shares the newest heading's zero are candidates: the same
        reference and, for relative headings, the same epoch (after a source lost its zero, the
        window starts again from the frames after it)."""
        usable = self.same_zero(candidates)
        t_s = np.array([c.frame.t_mono_s for c in usable])
        # Every one has an attitude (same_zero); the test only tells the type checker so.
        heading_rad = np.array([c.frame.attitude.heading_rad for c in usable if c.frame.attitude is not None])
        return [usable[i] for i in self.select_indices(t_s, heading_rad)] if usable else []

    @staticmethod
    def same_zero(candidates: Sequence[T]) -> list[T]:
        """The candidates (in order) whose heading shares the newest heading's zero: the same
        reference and epoch. The frames a window can be made of."""
        with_attitude = [(c, c.frame.attitude) for c in candidates if c.frame.attitude is not None]
        if not with_attitude:
            return []
        newest = with_attitude[-1][1]
        return [c for c, a in with_attitude if (a.reference, a.epoch) == (newest.reference, newest.epoch)]

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
