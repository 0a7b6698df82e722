"""Which frames form a window. Pure logic: takes the candidates, returns the chosen ones.

Consecutive frames at 10-30 Hz are nearly identical, so "the last 8" would show the network one
view eight times. The policy spreads the window over the last ``span_s`` seconds instead: the
newest frame always, then the frames nearest to evenly spaced target times back to
``newest - span_s``. While the buffer still covers less than the span, it takes what there is
(an estimate from fewer frames, reported in ``n_frames``) rather than wait.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from rig.errors import ValidationError
from rig.types import FrameFeatures

T = TypeVar("T", bound=FrameFeatures)


@dataclass(frozen=True)
class SpreadWindowPolicy:
    """Up to ``n_frames`` frames spread evenly in time over the last ``span_s`` seconds."""

    n_frames: int = 8
    span_s: float = 4.0

    def __post_init__(self) -> None:
        if self.n_frames < 1:
            raise ValidationError(f"window n_frames: expected >= 1, got {self.n_frames}")
        if not self.span_s > 0:
            raise ValidationError(f"window span_s: expected > 0 s, got {self.span_s}")

    def select(self, candidates: Sequence[T]) -> list[T]:
        """Chosen frames, oldest first. ``candidates`` must be ordered by time, oldest first."""
        usable = [c for c in candidates if c.frame.attitude is not None]
        if not usable:
            return []
        t = np.array([c.frame.t_mono_s for c in usable])
        newest = t[-1]
        in_span = np.nonzero(t >= newest - self.span_s)[0]
        first = int(in_span[0])
        if len(in_span) <= self.n_frames:
            return list(usable[first:])
        targets = np.linspace(newest - self.span_s, newest, self.n_frames)
        chosen: list[int] = []
        pool = list(range(first, len(usable)))
        # Fill from the newest target backwards, each target taking the nearest unused frame.
        for target in targets[::-1]:
            best = min(pool, key=lambda i: abs(t[i] - target))
            chosen.append(best)
            pool.remove(best)
        return [usable[i] for i in sorted(chosen)]
