"""Pair a camera with a heading from another device: interpolate the heading to each frame's time.

A camera and a GNSS compass (or any heading source) run on their own clocks' schedules; both
are stamped on the host's monotonic clock when their data arrive. A frame at ``t`` gets the
heading interpolated between the two heading samples around ``t`` (the yaw along the shorter
arc, so 359 deg and 1 deg meet at 0, not at 180). Nothing is extrapolated and nothing stale is
used: a frame gets no attitude (``None``, counted) when

- ``gap``: the two samples around it are more than ``max_gap_s`` apart (a dropout: a turn
  during it would be invisible), or the host was suspended between them (the monotonic clock
  stands still meanwhile, so they look as close as ever; the vehicle may have turned any way):
  each sample carries the boot offset it was read under (``HeadingSample.boot_offset_s``);
- ``before``: it is older than the oldest sample kept;
- ``stale``: no sample after it arrived within ``max_age_s`` of it (a live source stalled), or
  ``after``: the heading source has ended before it;
- ``mixed``: the samples around it have different references (true vs magnetic), and neither
  reference's own samples give it a heading. A source that interleaves references (HDT beside an
  HDG without variation) gives each frame the best one that brackets it: true, then magnetic;
- ``ahead``: live, it is stamped after it arrived, so its stamp is not the host's clock (a device
  clock that stepped, a replayed file): the samples at its stamp were measured after it was taken;
- ``unconfirmed``: live, its heading would come from the newest sample, which jumped, and the
  sample that tells whether that one is a glitch (below) did not come within ``max_age_s``.

A heading sample that is impossible given its neighbours (a glitch: a dual-antenna compass's
multipath puts one sentence half a turn off, or any wild value) is left out, counted in
``glitches`` (samples, not frames): one that is more than ``rig.window.MIN_JUMP_RAD`` from the
sample kept before it and from the sample after it, and by more than that farther from the line
between them than they are from each other (the heading went out and came back). Up to
``MAX_GLITCH_RUN`` samples in a row that each are so against the sample before them and the
first after them are one glitch, when those two are at most ``MAX_GLITCH_RUN_S`` apart.
Interpolated, a 1 Hz compass's glitch was a 2 s ramp out and back whose every frame step passed
the window's jump rule for a turn.
Whether samples are one needs the sample after them, so live, a frame whose heading depends on
the newest samples, when they jumped, waits for the next (still at most ``max_age_s``; then it
goes without heading, ``unconfirmed``). A sample with no sample kept before it or none after it (a
stream's first and last) cannot be told from a heading whose zero moved, and is kept, as is a
jump that stays (a zero that moved).

Live, the sample after a frame arrives after the frame, so the stream wrapper holds each frame
until its heading is known (in a bounded buffer): this delays frames by up to one heading
interval. The wait is counted from the frame's stamp, which is no later than its arrival (a
frame stamped later is ``ahead`` and does not wait), so no frame waits more than ``max_age_s``
(beyond ``latency_s``) after it arrived, and neither do the frames behind it. ``latency_s``
moves the samples earlier by the heading device's known output latency (a sample is stamped
when its sentence ends, after the measurement).

:class:`HeadingInterpolator` is pure (samples and times in, an Attitude out); :func:`with_heading`
is the stream wrapper, and the only place that reads the clock.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import math
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

from drivers.nmea import HeadingSample, suspended_between
from rig.errors import ValidationError
from rig.geometry import wrap_pi
from rig.lasting import EventThrottle
from rig.types import Attitude, Frame, HeadingRef
from rig.window import MIN_JUMP_RAD

log = logging.getLogger(__name__)

# The default gap covers a 1 Hz GNSS compass that misses one sentence now and then; the default
# age lets a frame wait for the next of those sentences (plus its transmit time and jitter).
DEFAULT_MAX_GAP_S = 1.5
DEFAULT_MAX_AGE_S = 1.5

FINAL = ("interpolated", "exact", "gap", "before", "after", "stale", "mixed", "ahead", "unconfirmed")
# A glitch may last several samples (multipath over two sentences of a 1 Hz compass): up to this
# many in a row that went out and came back together are one, when the sample after them comes
# within MAX_GLITCH_RUN_S of the sample before them. Longer, or slower, an excursion may be a
# vehicle's (out 45 deg and back in 3 s is 30 deg/s each way, a hard swerve), and is kept.
MAX_GLITCH_RUN = 3
MAX_GLITCH_RUN_S = 3.0
# How many samples before a frame's are judged again for glitches at each lookup: a glitch's
# verdict depends on the sample kept before it, so on the verdicts before. A frame inside the
# longest run must still see the sample before the run; the history (512) is not judged each frame.
_GLITCH_LOOKBACK = MAX_GLITCH_RUN + 1
# Which heading a frame takes where a source gives several references (HeadingRef.RELATIVE last:
# its zero is the source's start, not north).
_PREFERENCE = (HeadingRef.TRUE, HeadingRef.MAGNETIC, HeadingRef.RELATIVE)


@dataclass(frozen=True)
class Glitch:
    """A heading sample left out: the sample (``t_mono_s`` on its own stamp), its turn away from the
    sample kept before it (rad, signed) and the time between them (s)."""

    t_mono_s: float
    turn_rad: float
    dt_s: float


@dataclass(frozen=True)
class Lookup:
    """The heading of one frame time: ``attitude`` (None unless ``status`` is interpolated or
    exact) and ``status``, one of :data:`FINAL` or ``pending`` (the sample after it may still come)."""

    attitude: Attitude | None
    status: str


class HeadingInterpolator:
    """Headings at frame times from a sequence of :class:`HeadingSample` (oldest first).

    ``max_gap_s``: the two samples around a frame may be at most this far apart.
    ``max_age_s``: how long after a frame the sample following it may arrive, beyond the
    latency; older frames without one are stale. ``latency_s``: subtracted from every sample time
    (and so from the time a frame has waited).
    ``counts``: how many lookups ended in each status of :data:`FINAL` (``count=False`` lookups
    and pending ones are not counted). ``glitches``: how many samples were left out as glitches
    (each once, whatever lookups judged it), the newest ``last_glitch``.
    """

    def __init__(self, max_gap_s: float = DEFAULT_MAX_GAP_S, max_age_s: float = DEFAULT_MAX_AGE_S,
                 latency_s: float = 0.0) -> None:
        for name, value in (("max_gap_s", max_gap_s), ("max_age_s", max_age_s)):
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValidationError(f"HeadingInterpolator.{name}: expected a finite number of seconds > 0, "
                                      f"got {value!r}")
        if not (isinstance(latency_s, int | float) and math.isfinite(latency_s) and latency_s >= 0):
            raise ValidationError(f"HeadingInterpolator.latency_s: expected seconds >= 0, got {latency_s!r}")
        self.max_gap_s = float(max_gap_s)
        self.max_age_s = float(max_age_s)
        self.latency_s = float(latency_s)
        self.counts = dict.fromkeys(FINAL, 0)
        self.glitches = 0
        self.last_glitch: Glitch | None = None
        self._newest_glitch_s: dict[HeadingRef, float] = {}  # of each reference: counted up to this stamp

    def lookup(self, samples: Sequence[HeadingSample], t_mono_s: float, now_s: float | None = None, *,
               arrived_s: float | None = None, count: bool = True) -> Lookup:
        """The heading at ``t_mono_s``. ``now_s``: the current monotonic time while more samples
        may come (a frame after the newest sample is then ``pending`` until ``max_age_s``);
        None when no more will come (the source has ended, or a recorded sequence).
        ``arrived_s``: when the frame arrived, on the clock of ``now_s``; a frame stamped after
        it is ``ahead`` (None: not known, the stamp is trusted)."""
        if arrived_s is not None and t_mono_s > arrived_s:
            # Not the host's clock, so no sample time can be matched to it; and waiting for its
            # stamp held it (and every frame behind it) until the clock got there.
            result = Lookup(None, "ahead")
        else:
            result = self._lookup(samples, t_mono_s, now_s)
        if count and result.status != "pending":
            self.counts[result.status] += 1
        return result

    def at(self, samples: Sequence[HeadingSample], t_mono_s: float) -> Attitude | None:
        """The interpolated attitude at ``t_mono_s`` from a finished sequence of samples, or None."""
        return self.lookup(samples, t_mono_s).attitude

    def _lookup(self, samples: Sequence[HeadingSample], t: float, now_s: float | None) -> Lookup:
        references = {s.reference for s in samples}
        if len(references) < 2:
            return self._lookup_one(samples, t, now_s)
        # A receiver that sends both HDT and an HDG without variation interleaves true and magnetic
        # samples, so the two around a frame were nearly always mixed and no frame got a heading.
        # Each reference is looked up among its own samples, the best first: true, then magnetic.
        # A better one still pending is waited for; a worse one is taken only where the better
        # has nothing (before it began, after it ended, across its gap).
        for ref in _PREFERENCE:
            if ref not in references:
                continue
            found = self._lookup_one([s for s in samples if s.reference is ref], t, now_s)
            if found.attitude is not None or found.status == "pending":
                return found
        # None gives a heading. Say "mixed" where that is why (the samples around t differ in
        # reference), otherwise what the whole sequence says (before all of them, a gap, ...). It
        # has no heading either: two samples around t of one reference are neighbours in that
        # reference's own samples too.
        return self._lookup_one(samples, t, now_s)

    def _lookup_one(self, samples: Sequence[HeadingSample], t: float, now_s: float | None) -> Lookup:
        times = [s.t_mono_s - self.latency_s for s in samples]
        if not times or t < times[0]:
            return Lookup(None, "before")
        i = bisect.bisect_left(times, t)
        samples, times, doubtful_after_s = self._without_glitches(samples, times, i, now_s)
        i = bisect.bisect_left(times, t)
        if doubtful_after_s is not None and t > doubtful_after_s and i < len(times) and now_s is not None:
            # Its heading comes from the newest samples, which jumped: a glitch if the next comes back.
            # Waited for up to max_age_s as for any sample after a frame. After that it goes without
            # heading: taken as it is, a 1 Hz compass's glitch gave the first frames after the
            # sample before it 18-54 deg of the way out to it, each frame step a turn to the window.
            # A real turn of more than 45 deg between samples (45 deg/s at 1 Hz) costs the same.
            if (now_s - self.latency_s) - t <= self.max_age_s:
                return Lookup(None, "pending")
            return Lookup(None, "unconfirmed")
        if i < len(times) and times[i] == t:
            return Lookup(samples[i].attitude(), "exact")
        if i == len(times):
            # After the newest sample: wait for the next one while it can still arrive in time.
            if now_s is None:
                return Lookup(None, "after")
            # On the compass's clock, as the gap below: its sample after t arrives latency_s late by
            # nature, so a 1 Hz compass with 1 s latency left a third of the frames stale at 1.5 s.
            if (now_s - self.latency_s) - t > self.max_age_s:
                return Lookup(None, "stale")
            if (now_s - self.latency_s) - times[-1] > self.max_gap_s:
                return Lookup(None, "gap")  # whatever comes next is too far from the newest
            return Lookup(None, "pending")
        s0, s1 = samples[i - 1], samples[i]
        t0, t1 = times[i - 1], times[i]
        if t1 - t0 > self.max_gap_s or suspended_between(s0.boot_offset_s, s1.boot_offset_s):
            return Lookup(None, "gap")
        if s0.reference != s1.reference:
            return Lookup(None, "mixed")
        return Lookup(interpolate(s0, s1, (t - t0) / (t1 - t0)), "interpolated")

    def _without_glitches(self, samples: Sequence[HeadingSample], times: list[float], i: int,
                          now_s: float | None) -> tuple[Sequence[HeadingSample], list[float], float | None]:
        """``samples`` (with their ``times``) less the glitches among those around index ``i`` (from
        ``_GLITCH_LOOKBACK`` before it to a run's length after it), and, live, the time of the
        sample after which the newest samples may still turn out to be one (they jumped from it,
        and the next may come back), or None."""
        start, end = max(0, i - _GLITCH_LOOKBACK), min(len(samples), i + MAX_GLITCH_RUN + 2)
        kept: list[int] = []  # of those judged; the samples before start and from end on stay as they are
        doubtful_after_s = None
        j = start
        while j < end:
            if not kept:
                kept.append(j)  # nothing judged before it: taken as it is
                j += 1
                continue
            p = kept[-1]
            if run := self._glitch_run(samples, times, p, j):
                for g in range(j, j + run):
                    self._count_glitch(samples[g], samples[p], times[g] - times[p])
                j += run
                continue
            if doubtful_after_s is None and now_s is not None and self._may_be_open_run(samples, times, p, j, now_s):
                doubtful_after_s = times[p]
            kept.append(j)
            j += 1
        if len(kept) == j - start:
            return samples, times, doubtful_after_s  # none left out: as they were
        kept = [*range(start), *kept, *range(j, len(samples))]
        return [samples[k] for k in kept], [times[k] for k in kept], doubtful_after_s

    def _glitch_run(self, samples: Sequence[HeadingSample], times: list[float], p: int, j: int) -> int:
        """How many samples from ``j`` on are a glitch (:meth:`_out_and_back` each, judged against the
        sample ``p`` kept before them and the first after them that came back), 0 if none."""
        if not self._neighbours(samples, times, p, j):
            return 0
        for k in range(1, MAX_GLITCH_RUN + 1):
            n = j + k
            if n >= len(samples) or not self._neighbours(samples, times, n - 1, n):
                return 0
            if k > 1 and times[n] - times[p] > MAX_GLITCH_RUN_S:
                return 0
            if all(self._out_and_back(samples, times, p, g, n) for g in range(j, n)):
                return k
            if not self._jumped(samples, times, p, n, chained=True):
                return 0  # it came back, but not every sample before it went out
        return 0

    def _may_be_open_run(self, samples: Sequence[HeadingSample], times: list[float], p: int, j: int,
                         now_s: float) -> bool:
        """Live: whether the samples from ``j`` to the newest may still be a glitch. Each jumped
        from ``p``, they are no more than a run, and the sample that would end them can still
        come: within ``max_gap_s`` of the newest and, for a run, ``MAX_GLITCH_RUN_S`` of ``p``."""
        last = len(samples) - 1
        if last - j + 1 > MAX_GLITCH_RUN or not self._jumped(samples, times, p, j):
            return False
        if not all(self._jumped(samples, times, p, g, chained=True) for g in range(j + 1, last + 1)):
            return False
        now = now_s - self.latency_s
        return now - times[last] <= self.max_gap_s and (last == j or now - times[p] <= MAX_GLITCH_RUN_S)

    def _neighbours(self, samples: Sequence[HeadingSample], times: list[float], a: int, b: int) -> bool:
        """Whether samples ``a`` and ``b`` (a before b) are neighbours the interpolation would pair:
        one reference, at most ``max_gap_s`` apart, and no suspend of the host between them."""
        sa, sb = samples[a], samples[b]
        return (sa.reference is sb.reference and times[b] - times[a] <= self.max_gap_s
                and not suspended_between(sa.boot_offset_s, sb.boot_offset_s))

    def _jumped(self, samples: Sequence[HeadingSample], times: list[float], p: int, g: int, *,
                chained: bool = False) -> bool:
        """Whether sample ``g`` turned more than ``MIN_JUMP_RAD`` from the sample ``p`` kept before
        it, its neighbour (``chained``: or through the samples between, each the next's): it may be
        a glitch, told by the samples after it."""
        turn_rad = abs(math.remainder(samples[g].heading_rad - samples[p].heading_rad, math.tau))
        near = (all(self._neighbours(samples, times, a, a + 1) for a in range(p, g)) if chained
                else self._neighbours(samples, times, p, g))
        return near and turn_rad > MIN_JUMP_RAD

    def _out_and_back(self, samples: Sequence[HeadingSample], times: list[float], p: int, g: int, n: int) -> bool:
        """Whether sample ``g`` is impossible given the sample ``p`` kept before it and the sample
        ``n`` after it (the caller checks they are neighbours, through the samples between): more
        than ``MIN_JUMP_RAD`` from each, and more than that farther from the line between them (their
        headings interpolated to its time) than they are from each other.

        The window's rate (``rig.window.DEFAULT_MAX_YAW_RATE_RAD_S``, 180 deg/s) cannot tell here:
        between samples a second apart it allows half a turn, more than two headings can differ, so
        a 1 Hz compass's glitch would always pass for a turn. What tells is the shape: out and back,
        each by more than the jump floor, no turn keeps on so. On the 401 synthetic drives (held-out,
        val and demo), every 1st to 15th frame's heading taken as a compass's (10 to 0.67 Hz), one of
        23332 samples is one (a swerve 68 deg out and 54 back in 2 s, which no car turns; the next
        closest 29 deg by this rule); a sample half a turn off is one while the vehicle turns under
        67 deg/s."""
        h_p, h_g, h_n = samples[p].heading_rad, samples[g].heading_rad, samples[n].heading_rad
        apart_rad = math.remainder(h_n - h_p, math.tau)
        span_s = times[n] - times[p]
        w = (times[g] - times[p]) / span_s if span_s > 0 else 0.5  # two stamped alike: half-way
        off_rad = abs(math.remainder(h_g - (h_p + w * apart_rad), math.tau))
        out_rad = abs(math.remainder(h_g - h_p, math.tau))
        back_rad = abs(math.remainder(h_n - h_g, math.tau))
        # The margin over their distance apart also leaves alone a turn whose neighbours are half a
        # turn apart (90 deg/s at 1 Hz), where the line between them goes either way round.
        return min(out_rad, back_rad, off_rad - abs(apart_rad)) > MIN_JUMP_RAD

    def _count_glitch(self, glitch: HeadingSample, before: HeadingSample, dt_s: float) -> None:
        """Count a glitch once, however many lookups judge it (each reference's in stamp order)."""
        if glitch.t_mono_s <= self._newest_glitch_s.get(glitch.reference, -math.inf):
            return
        self._newest_glitch_s[glitch.reference] = glitch.t_mono_s
        self.glitches += 1
        self.last_glitch = Glitch(glitch.t_mono_s, math.remainder(glitch.heading_rad - before.heading_rad, math.tau),
                                  dt_s)


def interpolate(s0: HeadingSample, s1: HeadingSample, w: float) -> Attitude:
    """The attitude a fraction ``w`` of the way from ``s0`` to ``s1``: the yaw along the shorter
    arc; pitch and roll linearly, when both samples have them (else None)."""
    heading = s0.heading_rad + w * float(wrap_pi(s1.heading_rad - s0.heading_rad))

    def lerp(a: float | None, b: float | None) -> float | None:
        return None if a is None or b is None else a + w * (b - a)

    return Attitude(heading, s0.reference, pitch_rad=lerp(s0.pitch_rad, s1.pitch_rad),
                    roll_rad=lerp(s0.roll_rad, s1.roll_rad))


def _samples_of(source: Any) -> Callable[[], Sequence[HeadingSample]]:
    """How to read a heading source: its ``heading_history()`` (GnssReader), or a fixed sequence."""
    history = getattr(source, "heading_history", None)
    if callable(history):
        return history
    if isinstance(source, Sequence):
        fixed = list(source)
        return lambda: fixed
    raise ValidationError(f"heading source: expected an object with heading_history() or a sequence of "
                          f"HeadingSample, got {type(source).__name__}")


def _gnss_extras(source: Any, t_frame: float, now_s: float, status: str) -> dict[str, Any]:
    """UTC and position for a frame from a source that has them (GnssReader), else nothing.

    UTC is carried from now back to the frame by the monotonic clock; a fix is the newest one
    (positions change slowly next to what the sun needs: a kilometre moves it by 0.01 deg).
    A frame ``ahead`` gets no UTC: its stamp is not the host's clock, and carried to it the UTC
    would be extrapolated to a time that has not come. A frame stamped before the source's latest
    resume (``resumed_at_s``) gets neither: it may have been taken before the suspend, which the
    monotonic clock did not count, so the UTC carried back to it would be late by the whole suspend,
    and the position is from after it.
    """
    out: dict[str, Any] = {}
    utc_at = getattr(source, "utc_at", None)
    utc = utc_at(now_s) if callable(utc_at) else None
    latest_fix = getattr(source, "latest_fix", None)
    fix = latest_fix(now_s) if callable(latest_fix) else None
    # Asked after them: a UTC or fix read after a resume was kept after the reader saw the resume.
    resumed_at_s = getattr(source, "resumed_at_s", None)
    if isinstance(resumed_at_s, int | float) and t_frame < resumed_at_s:
        return out
    if utc is not None and status != "ahead":
        out["utc_ns"] = utc - round((now_s - t_frame) * 1e9)
    if fix is not None:
        out["gnss"] = fix
    return out


class PairingStats:
    """What :func:`with_heading` did: the interpolator's counts plus frames forced out of a full buffer,
    and the heading samples left out as glitches (``glitch``: samples, not frames)."""

    def __init__(self, interpolator: HeadingInterpolator) -> None:
        self.interpolator = interpolator
        self.overflow = 0
        self.frames = 0

    def as_dict(self) -> dict[str, int]:
        return {"frames": self.frames, **self.interpolator.counts, "overflow": self.overflow,
                "glitch": self.interpolator.glitches}


def with_heading(frames: Iterable[Frame], heading_source: Any, interpolator: HeadingInterpolator | None = None,
                 *, clock: Callable[[], float] = time.monotonic, max_pending: int = 256,
                 stats: PairingStats | None = None, live: bool = True) -> Iterator[Frame]:
    """The frames, in order, each with the heading interpolated to its time (or None, counted).

    ``heading_source``: an object with ``heading_history()`` (a :class:`drivers.gnss.GnssReader`),
    or a sequence of samples. When it also has ``utc_at``/``latest_fix`` (a GNSS receiver), the
    frames get UTC and the position too (not a UTC for a frame ``ahead``; neither for a frame
    stamped before the source's latest resume from a suspend). A heading the frames carried is replaced.

    ``live``: samples are still arriving, so a frame newer than the newest sample waits (checked
    again as each next frame arrives) until its heading comes, or ``max_age_s`` passes, or
    ``max_pending`` frames wait (then the oldest is let go without heading, counted ``overflow``).
    A frame stamped after it arrived (by ``clock``) does not wait: it is ``ahead``, without heading.
    At the end of the frames, what still waits is resolved with the samples there are.
    A heading sample left out as a glitch is said as a warning, the first at once, then at most
    once a minute (by the samples' clock) with how many came since.
    """
    interp = interpolator or HeadingInterpolator()
    stats = stats if stats is not None else PairingStats(interp)
    read = _samples_of(heading_source)
    pending: deque[tuple[Frame, float | None]] = deque()  # each frame with when it arrived (live)
    glitches_said = interp.glitches
    throttle = EventThrottle(60.0)

    def say_glitches() -> None:
        nonlocal glitches_said
        glitch = interp.last_glitch
        if interp.glitches == glitches_said or glitch is None:
            return
        new, glitches_said = interp.glitches - glitches_said, interp.glitches
        said = None
        for _ in range(new):  # several judged by one lookup: the first said, the rest in the next summary
            said = throttle.note(glitch.t_mono_s) or said
        if said is None:
            return
        n, before_s = said
        turn = f"{math.degrees(glitch.turn_rad):+.0f} deg in {glitch.dt_s:.2f} s"
        if before_s is None:
            log.warning("heading sample at %.2f s left out: it turned %s from the sample kept before it, and a "
                        "later one came back, which no vehicle turns (a compass glitch: multipath at its antennas?); "
                        "the frames around it take the samples on either side (counted in the pairing's glitch)",
                        glitch.t_mono_s, turn)
        else:
            log.warning("%d heading samples left out as glitches in %.0f s, the last at %.2f s (%s): frequent ones "
                        "mean the compass's antennas see reflections; give them a clear view of the sky (said once "
                        "a minute while it goes on)", n, glitch.t_mono_s - before_s, glitch.t_mono_s, turn)

    def release(final: bool) -> Iterator[Frame]:
        # A source that has ended (a capture file read to its end) will send nothing more: no waiting.
        ended = final or not live or getattr(heading_source, "finished", False) is True
        samples = read()
        now = clock()
        while pending:
            frame, arrived = pending[0]
            result = interp.lookup(samples, frame.t_mono_s, None if ended else now, arrived_s=arrived)
            if result.status == "pending":
                if len(pending) <= max_pending:
                    return
                stats.overflow += 1  # the buffer is full: let the oldest go without heading
            pending.popleft()
            say_glitches()
            extras = _gnss_extras(heading_source, frame.t_mono_s, now, result.status) if live else {}
            yield dataclasses.replace(frame, attitude=result.attitude, **extras)

    for frame in frames:
        stats.frames += 1
        pending.append((frame, clock() if live else None))  # not live: no clock, the stamps are all there is
        yield from release(final=False)
    yield from release(final=True)
