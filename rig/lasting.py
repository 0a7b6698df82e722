"""When to say a condition that lasts and changes: pure, by the caller's clock.

A rig runs for hours, and a condition it reports (an output whose writes fail, frames the exposure
gate refuses, windows that cannot fill or fail) may last that long, or flip at every event. Said at
every change, a flipping one wrote a line per frame into the journal; said once, a second stretch
hid behind the first. :class:`LastingCondition` says each change at once while a small budget
allows, then sums up the changes since the last change it said (counts that grow from one summary
to the next, with the seconds they took), and reminds of a bad state that lasts.
"""

from __future__ import annotations

import math
from collections.abc import Hashable
from dataclasses import dataclass


@dataclass(frozen=True)
class Said:
    """A line :class:`LastingCondition` has decided to say. ``kind`` "change": the state is now
    ``state``, no longer ``before``; "still": it is ``state`` as said before, and changes went unsaid
    in between (``changes`` > 0) or it has lasted long enough for a reminder. ``changes`` counts the
    changes of state, ``counts`` the events of each kind (this one included) since ``before`` was said,
    at ``since_s``; ``budget_spent``: changes are said once per refill from now on."""

    kind: str
    state: Hashable
    before: Hashable
    since_s: float
    changes: int
    counts: dict[Hashable, int]
    budget_spent: bool


class LastingCondition:
    """When to say a condition that lasts and changes (an exposure verdict, a port whose writes fail):
    each change when it happens, and counts in between, in a bounded number of lines.

    A change of state is said at once while a budget allows: ``burst`` changes, refilled one per
    ``refill_s``. A condition flipping on every event (a scene at a threshold, a link failing every
    other write) is then counted, not said: one line per ``refill_s`` sums up the changes since the
    last change said (cumulative: the next summary counts from the same point), with
    the state it is in. Two real changes, a lens covered and then uncovered, are each said at once.
    A state other than ``ok`` that lasts is said again after ``remind_s``, then after doubling
    intervals up to ``remind_max_s`` (None: never).

    Pure: the caller passes each event's state and time (its own clock, or a frame's), says the
    :class:`Said` returned, and keeps the exact counts in its statistics, as before."""

    def __init__(self, ok: Hashable = None, *, burst: int = 4, refill_s: float = 60.0,
                 remind_s: float | None = None, remind_max_s: float = 3600.0) -> None:
        self.ok = ok
        self._burst, self._refill_s = burst, refill_s
        self._remind_s, self._remind_max_s = remind_s, remind_max_s
        self._tokens = float(burst)
        self._at_s: float | None = None  # the time of the newest event
        self.said: Hashable = ok  # the state the log says the condition is in
        self.state: Hashable = ok  # the state it is in
        self._since_s: float | None = None  # when `said` was said (the first event, for the initial state)
        self._changes = 0  # since `said` was said
        self._unsaid = 0  # changes since the last line
        self._counts: dict[Hashable, int] = {}
        self._key: Hashable = None  # what the newest event was counted under
        self._remind_every_s = remind_s
        self._next_remind_s = math.inf

    def update(self, state: Hashable, now_s: float, event: Hashable = None) -> Said | None:
        """One event (a frame judged, a write tried) finding the condition in ``state`` at
        ``now_s``; counted under ``event`` (default: the state). The line to say, or None."""
        if self._at_s is None:
            self._at_s = self._since_s = now_s
        # Time that steps back (a replayed log's clock) refills nothing and delays no reminder.
        self._tokens = min(float(self._burst), self._tokens + max(0.0, now_s - self._at_s) / self._refill_s)
        if now_s < self._at_s and self._remind_every_s is not None:
            self._next_remind_s = min(self._next_remind_s, now_s + self._remind_every_s)
        self._at_s = now_s
        key = state if event is None else event
        self._counts[key] = self._counts.get(key, 0) + 1
        self._key = key
        if state != self.state:
            self.state = state
            self._changes += 1
            self._unsaid += 1
        if state != self.said:
            if self._tokens < 1.0:
                return None
            return self._say("change", now_s)
        if self._unsaid and self._tokens >= 1.0:
            return self._say("still", now_s)
        if state != self.ok and now_s >= self._next_remind_s:
            return self._say("still", now_s)
        return None

    def _say(self, kind: str, now_s: float) -> Said:
        if kind == "change" or self._unsaid:
            self._tokens -= 1.0
        assert self._since_s is not None
        said = Said(kind, self.state, self.said, self._since_s, self._changes, dict(self._counts),
                    budget_spent=self._tokens < 1.0)
        self._unsaid = 0
        if kind == "change":
            self.said, self._since_s, self._changes = self.state, now_s, 0
            self._counts = {self._key: 1}  # this event: the first of the new state's stretch
            self._remind_every_s = self._remind_s
        elif self._remind_every_s is not None:
            self._remind_every_s = min(2.0 * self._remind_every_s, self._remind_max_s)
        if self._remind_every_s is not None and self.state != self.ok:
            self._next_remind_s = now_s + self._remind_every_s
        else:
            self._next_remind_s = math.inf
        return said


class EventThrottle:
    """When to say an event that may repeat (a replay falling behind again, a camera repeating a
    frame): the first time, then at most once every ``every_s`` with how many came since. For
    events, not states: nothing says when they stop (:class:`LastingCondition` does, for states).

    Pure: :meth:`note` takes each event's time by the caller's clock."""

    def __init__(self, every_s: float = 60.0) -> None:
        self.every_s = every_s
        self._said_s: float | None = None  # when an event was last said
        self._unsaid = 0  # events since, this one included once noted

    def note(self, now_s: float) -> tuple[int, float | None] | None:
        """None: leave this event unsaid. Else say it: (events since the last one said, this one
        included; the time that one was said, None the first time)."""
        self._unsaid += 1
        before = self._said_s
        if before is not None and now_s - before < self.every_s:
            return None
        n, self._unsaid, self._said_s = self._unsaid, 0, now_s
        return n, before
