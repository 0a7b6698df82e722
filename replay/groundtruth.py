"""Ground truth for any log that knows where and when: the sun from GNSS position + UTC (NREL SPA).

The paper's ground truth is exactly this (GPS + UTC through SPA), so a user's own recordings
become training and evaluation data the moment they carry a GNSS fix and UTC time. The shape is a
pure function per frame (:func:`frame_with_truth`) inside a thin wrapper over any frame source
(:class:`GroundTruthSource`), which ``replay.sources.open_frames`` puts around every native log.

What gets a truth, and why:

- A frame that already carries ``sun_enu_truth`` (synthetic drives, KITTI) keeps it, unless its
  heading is MAGNETIC or RELATIVE (see the heading reference below): then it is dropped.
- Time: the frame's own ``utc_ns`` (its mid-exposure), else its GNSS fix's ``utc_ns`` (a fix
  can be up to a second older than the frame: the sun moves ~0.004 deg in a second).
- Place: the frame's fix, else the last fix seen within :data:`MAX_FIX_AGE_S` of the frame's
  time (fixes come at 1-10 Hz, frames at 10-30 Hz; a minute at highway speed is ~2 km, which
  moves the sun by ~0.02 deg). No fix: no truth.
- Heading reference: the truth is in true-north ENU. It can grade or train only estimates made
  in the same frame, i.e. with a TRUE heading (or frames without a heading, which the estimator
  skips anyway). Frames with a MAGNETIC heading get no truth: their estimates live in a
  magnetic-north world, off by the local declination (up to tens of degrees), and sunrig carries
  no magnetic model to correct it. Frames with a RELATIVE heading get no truth: their world's
  "north" is wherever the source started. A warning says so once per pass.
- Atmosphere: pressure from the fix's altitude (standard atmosphere), 12 C, Delta T from the
  Espenak & Meeus approximation (``rig.solar``); together worth < 0.03 deg above 5 deg elevation.
"""

from __future__ import annotations

import dataclasses
import logging
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from rig.solar import standard_pressure_hpa, sun_position
from rig.types import Frame, GnssFix, HeadingRef

logger = logging.getLogger(__name__)

MAX_FIX_AGE_S = 60.0


def sun_truth_enu(utc, lat_deg, lon_deg, alt_m=None) -> np.ndarray:
    """The apparent sun as ENU unit vectors (..., 3) for UTC times (ns or datetime64) and places.

    Vectorised: a whole drive in one call. ``alt_m`` None means sea level.
    """
    alt = np.zeros(np.shape(lat_deg)) if alt_m is None else np.asarray(alt_m, dtype=np.float64)
    return sun_position(utc, lat_deg, lon_deg, alt, pressure_hpa=standard_pressure_hpa(alt)).enu


def frame_time_ns(frame: Frame) -> int | None:
    """The UTC time a truth should be computed for: the frame's own, else its fix's."""
    if frame.utc_ns is not None:
        return frame.utc_ns
    if frame.gnss is not None:
        return frame.gnss.utc_ns
    return None


def truth_allowed(frame: Frame) -> bool:
    """A truth in true-north ENU fits only frames with a TRUE heading, or with none."""
    return frame.attitude is None or frame.attitude.reference == HeadingRef.TRUE


def frame_with_truth(frame: Frame, fix: GnssFix | None = None) -> Frame:
    """``frame`` with ``sun_enu_truth`` from ``fix`` (default: its own ``gnss``) when it can have
    one (see the module notes); otherwise ``frame`` itself, unchanged."""
    fix = fix if fix is not None else frame.gnss
    t_ns = frame_time_ns(frame)
    if frame.sun_enu_truth is not None or fix is None or t_ns is None or not truth_allowed(frame):
        return frame
    alt = 0.0 if fix.alt_m is None else fix.alt_m
    truth = sun_truth_enu(np.int64(t_ns), fix.lat_deg, fix.lon_deg, alt)
    return dataclasses.replace(frame, sun_enu_truth=truth)


@dataclass
class GroundTruthStats:
    frames: int = 0
    had_truth: int = 0  # the source's own truth, kept (a TRUE heading or none)
    truth_added: int = 0
    no_fix: int = 0  # no time, or no fix within MAX_FIX_AGE_S
    heading_not_true: int = 0  # magnetic or relative heading: no truth on purpose (an own one dropped)


class GroundTruthSource:
    """A frame source whose frames get the true sun from their GNSS fix and UTC time.

    Re-iterable when the wrapped source is; every other attribute (``truncated``, ``stats`` of a
    native log, ``path``) is the wrapped source's, so it stands in for it anywhere.
    """

    def __init__(self, source: Iterable[Frame], max_fix_age_s: float = MAX_FIX_AGE_S) -> None:
        self.source = source
        self.max_fix_age_ns = int(max_fix_age_s * 1e9)
        self.truth_stats = GroundTruthStats()

    def __getattr__(self, name: str):
        # Only called for attributes this wrapper does not have itself.
        if name == "source":  # not yet set (e.g. during unpickling): do not recurse
            raise AttributeError(name)
        return getattr(self.source, name)

    def __iter__(self) -> Iterator[Frame]:
        return self._frames()

    def _frames(self) -> Iterator[Frame]:
        stats = self.truth_stats = GroundTruthStats()
        last_fix: GnssFix | None = None
        warned: set[HeadingRef] = set()
        for frame in self.source:
            stats.frames += 1
            if frame.gnss is not None:
                last_fix = frame.gnss
            if not truth_allowed(frame):
                # Before the source's own truth: a log recorded with another heading (e.g. visual
                # odometry over a synthetic drive) can still carry its true-north truth.
                stats.heading_not_true += 1
                assert frame.attitude is not None  # truth_allowed() passes every frame without one
                ref = frame.attitude.reference
                if ref not in warned:
                    warned.add(ref)
                    logger.warning(
                        "%s: frames with a %s heading get no ground truth: the sun's true-north direction cannot "
                        "grade or train estimates in a %s world frame (record a TRUE heading for that)",
                        getattr(self.source, "path", None) or "the log", ref.value,
                        "magnetic-north" if ref == HeadingRef.MAGNETIC else "start-heading")
                yield frame if frame.sun_enu_truth is None else dataclasses.replace(frame, sun_enu_truth=None)
                continue
            if frame.sun_enu_truth is not None:
                stats.had_truth += 1
                yield frame
                continue
            t_ns = frame_time_ns(frame)
            fix = frame.gnss
            if fix is None and last_fix is not None and t_ns is not None \
                    and abs(t_ns - last_fix.utc_ns) <= self.max_fix_age_ns:
                fix = last_fix
            if fix is None or t_ns is None:
                stats.no_fix += 1
                yield frame
                continue
            stats.truth_added += 1
            yield frame_with_truth(frame, fix)

    def __repr__(self) -> str:
        return f"GroundTruthSource({self.source!r})"


def with_ground_truth(source: Iterable[Frame]) -> GroundTruthSource:
    """Wrap ``source`` so frames with GNSS time and position get ``sun_enu_truth``."""
    return source if isinstance(source, GroundTruthSource) else GroundTruthSource(source)
