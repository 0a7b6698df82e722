"""Frames in, estimates out, as fast as the machine goes: the loop behind `sunrig replay` and eval.

The live rig (threads, ring, drops) does the same per-frame work; this is its single-threaded
form for logs, where nothing may be dropped. Frames are encoded in small batches because one
backbone call over several frames costs less than several calls.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field

from estimator.calibration import EstimationError
from estimator.estimator import SunEstimator
from rig.exposure import DEFAULT_EXPOSURE_GATE, ExposureGate
from rig.ring import DEFAULT_RING_CAPACITY, FrameRing
from rig.types import Frame, SunEstimate
from rig.window import SpreadWindowPolicy, ViewClock

log = logging.getLogger(__name__)


@dataclass
class OfflineStats:
    frames: int = 0
    frames_without_heading: int = 0
    frames_bad_exposure: int = 0
    frames_out_of_order: int = 0
    # frames more than 1 s older than the one before (a clock stepped back), or whose UTC moved on
    # far more than their monotonic clock (a suspend): windows start again from them
    clock_jumps: int = 0
    windows: int = 0
    windows_failed: int = 0
    failures: list[str] = field(default_factory=list)


def estimate_stream(frames: Iterable[Frame], estimator: SunEstimator, policy: SpreadWindowPolicy,
                    *, aggregators: Sequence[str] | None = None, encode_batch: int = 8,
                    stats: OfflineStats | None = None,
                    exposure_gate: ExposureGate | None = DEFAULT_EXPOSURE_GATE,
                    ring_capacity: int = DEFAULT_RING_CAPACITY) -> Iterator[dict[str, SunEstimate]]:
    """One window per frame with a heading, estimated with each aggregator.

    Yields ``{aggregator: SunEstimate}`` per window. Frames without heading are counted and left
    out of windows (a frame's heading is never guessed), and so are frames too dark, bright, flat
    or covered to show the sun (``rig/exposure.py``; ``exposure_gate=None`` keeps them). A window that
    cannot be estimated is counted, logged and skipped: one bad window does not end a replay.
    """
    aggregators = list(aggregators or [estimator.aggregator])
    stats = stats if stats is not None else OfflineStats()
    # The live rig's ring, bounded by the policy's span (older frames can never be chosen again)
    # and by the live rig's default count (``ring_capacity``): a replay chooses among the frames
    # the rig would have held. Every frame still gets its window; the count only bounds the
    # candidates, which with a frozen clock (every frame at one time, so none ever too old) once
    # grew without end: each window chose among all the frames before it, 3000 frames took 271 s.
    ring = FrameRing(capacity=ring_capacity, max_age_s=policy.span_s)
    views = ViewClock()  # as live: a vehicle standing keeps the views from before the stop
    jumps_before = stats.clock_jumps  # the ring counts this stream's; stats may pool several streams
    pending: list[Frame] = []

    def flush() -> Iterator[dict[str, SunEstimate]]:
        for feats in map(views.stamp, estimator.encode_batch(pending)):
            if not ring.push(feats):
                stats.frames_out_of_order += 1  # as live: windows assume time order
                continue
            stats.clock_jumps = jumps_before + ring.restarts
            window = policy.select(ring.snapshot())
            try:
                results = estimator.estimate_many(window, aggregators)
            except EstimationError as exc:
                stats.windows += 1
                stats.windows_failed += 1
                if len(stats.failures) < 20:
                    stats.failures.append(f"seq {feats.frame.seq}: {exc}")
                log.warning("window ending at seq %d skipped: %s", feats.frame.seq, exc)
                continue
            # Counted once answered: an interrupt inside estimate_many leaves no window counted
            # that no one received.
            stats.windows += 1
            yield results
        pending.clear()

    for frame in frames:
        stats.frames += 1
        if frame.attitude is None:
            stats.frames_without_heading += 1
            continue
        if exposure_gate is not None and exposure_gate.rejects(frame.image_bgr):
            stats.frames_bad_exposure += 1
            continue
        pending.append(frame)
        if len(pending) >= encode_batch:
            yield from flush()
    yield from flush()
