"""The live rig: capture -> encode -> ring -> estimate -> publish, each stage its own thread.

- **capture** pulls frames from the source (a driver, or a log paced in real time) and puts them
  in a small drop-oldest queue: a slow estimator makes the rig skip frames, never lag behind.
- **encode** runs the backbone once per frame as it enters the ring (``SunEstimator.encode``).
- **estimate** forms a window from the ring for the newest frame and runs the aggregator. It is
  woken through a one-slot mailbox: if estimating falls behind encoding, older "new frame"
  signals are overwritten (counted as skipped windows) so latency stays bounded. A window whose
  frame left the source more than ``max_latency_s`` ago (it waited through a stall: a page-out, a
  machine too busy) is skipped too, and so is an estimate that took that long: nothing on the wire
  says how old an estimate is (docs/protocol.md), and one seconds old has a relative bearing as
  old. Counted as stale, and said when it starts and when estimates are in time again.
- **publish**: every publisher's ``publish`` must return at once (the serial one hands the
  message to its own writer thread). A publisher that raises (a full disk under the JSONL file)
  loses that estimate, counted in ``publish_errors`` (and as ``raised`` in its statistics) and
  logged once per kind of error; the other outputs go on, because one broken output must not
  silence the controller. One that raises ``BrokenPipeError`` has ended (its reader, e.g.
  ``| head``, went away): it gets no more estimates, and when every output has ended the rig
  stops, as a command whose output is read by ``head`` does.

Every stage waits with a timeout and checks one stop event. A stage that raises stops all the
others, and :meth:`RigPipeline.run` re-raises it as :class:`PipelineError` naming the stage,
within a couple of seconds; a source that blocks forever is abandoned (its thread is a daemon),
never waited on without bound.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field

import numpy as np

from estimator.calibration import EstimationError
from estimator.estimator import SunEstimator
from rig.errors import SunrigError, ValidationError
from rig.exposure import DEFAULT_EXPOSURE_GATE, ExposureGate
from rig.lasting import EventThrottle, LastingCondition
from rig.pacing import Pacer
from rig.publishers import ErrorTally, Publisher, failed_writes, publisher_name
from rig.ring import DEFAULT_MAX_AGE_S, DEFAULT_RING_CAPACITY, DropOldestQueue, FrameRing, ring_too_short
from rig.types import Frame, FrameFeatures
from rig.window import MIN_JUMP_RAD, SpreadWindowPolicy, ViewClock

log = logging.getLogger(__name__)

_POLL_S = 0.05  # how often an idle stage re-checks the stop event
_JOIN_S = 2.0  # how long run() waits for a stage to end once stopped


class PipelineError(SunrigError):
    """A stage of the live pipeline failed; the message names the stage and the cause."""


@dataclass(frozen=True)
class RigConfig:
    queue_size: int = 2  # frames waiting for the backbone; more only adds latency
    ring_capacity: int = DEFAULT_RING_CAPACITY
    ring_max_age_s: float = DEFAULT_MAX_AGE_S
    status_every_s: float = 5.0
    realtime: bool = False  # pace a recorded source by its timestamps
    # The oldest an estimate may be sent: from its frame leaving the source to its publishing. Later
    # ones are skipped (stale); a paced replay that falls this far behind its schedule paces from
    # where it is (rig/pacing.py) rather than rushing out frames already this old.
    # 2 s: longer than a frame may wait for a compass's heading (drivers.pairing, max_age_s 1.5 s).
    max_latency_s: float = 2.0
    exposure_gate: ExposureGate | None = DEFAULT_EXPOSURE_GATE  # None: every frame joins windows
    # The frames are stamped on this pipeline's clock (a live camera): a frame is as old as its
    # stamp says, also when it reached the rig late (the pairing holds one for its heading, up to
    # max_age_s, and through a camera stall the last one). A recording's stamps are its own clock.
    live_clock: bool = False

    def __post_init__(self) -> None:
        for name in ("queue_size", "ring_capacity"):
            if not getattr(self, name) >= 1:
                raise ValidationError(f"[rig] {name}: expected >= 1, got {getattr(self, name)}")
        for name in ("ring_max_age_s", "status_every_s", "max_latency_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValidationError(f"[rig] {name}: expected a finite number of seconds > 0, got {v}")


@dataclass
class _Latency:
    samples: deque[float] = field(default_factory=lambda: deque(maxlen=2000))

    def add(self, seconds: float) -> None:
        self.samples.append(seconds)

    def summary_ms(self) -> dict[str, float]:
        if not self.samples:
            return {}
        a = np.fromiter(self.samples, dtype=np.float64) * 1e3
        return {"p50_ms": float(np.percentile(a, 50)), "p99_ms": float(np.percentile(a, 99)),
                "max_ms": float(a.max())}


@dataclass
class RigStats:
    """Counters of one run. ``latency`` is a frame leaving the source (capture; a paced replay's frame:
    when it was due) to the return of the last publisher's ``publish``; ``update_hz`` is estimates
    per second over the run.
    ``windows_skipped`` counts every window not sent because the estimator was behind: overwritten
    in the mailbox, or stale (later than ``RigConfig.max_latency_s``), which ``estimates_stale``
    counts apart, or whose frame the ring let go before its turn (it started again at a clock jump)."""

    frames_captured: int = 0
    frames_dropped_queue: int = 0
    frames_without_heading: int = 0
    frames_bad_exposure: int = 0
    frames_encoded: int = 0
    frames_out_of_order: int = 0
    # frames more than 1 s older than the one before (a clock stepped back), or whose UTC moved on
    # far more than their monotonic clock (a suspend): the ring started again from them
    clock_jumps: int = 0
    windows_skipped: int = 0
    estimates_stale: int = 0  # of windows_skipped: too late to send
    estimates: int = 0
    estimates_failed: int = 0
    publish_errors: int = 0  # estimates a publisher raised on, all outputs (each counts its own)
    status_errors: int = 0  # status lines on_status raised on (stderr on a full disk): not written, the rig goes on
    started_s: float = 0.0
    ended_s: float = 0.0
    latency: _Latency = field(default_factory=_Latency)
    publishers: dict[str, dict] = field(default_factory=dict)

    def as_dict(self) -> dict:
        """The counters as they are now, a copy: taken while the rig runs, it stays what it was."""
        d = {k: v for k, v in self.__dict__.items() if k not in ("latency", "started_s", "ended_s", "publishers")}
        # Copied: run() goes on replacing each publisher's statistics in this table.
        d["publishers"] = {name: dict(st) for name, st in self.publishers.items()}
        d["latency"] = self.latency.summary_ms()
        span = max(self.ended_s - self.started_s, 1e-9)
        d["update_hz"] = self.estimates / span
        d["duration_s"] = span
        return d

    def status_line(self, now_s: float) -> str:
        lat = self.latency.summary_ms()
        rate = self.estimates / max(now_s - self.started_s, 1e-9)
        lat_text = f"latency p50 {lat['p50_ms']:.0f} ms p99 {lat['p99_ms']:.0f} ms" if lat else "latency -"
        pub_drops, pub_errors = publisher_losses(self.publishers.values())
        # Each output that lost some, by name: a sum alone does not say which to look at.
        losses = {name: publisher_losses([st]) for name, st in self.publishers.items()}
        drops_by = ", ".join(f"{name} {d}" for name, (d, _) in losses.items() if d)
        errors_by = ", ".join(f"{name} {e}" for name, (_, e) in losses.items() if e)
        status = f" | status errors {self.status_errors}" if self.status_errors else ""
        stale = f" ({self.estimates_stale} of them too late to send)" if self.estimates_stale else ""
        return (f"frames {self.frames_captured} (dropped {self.frames_dropped_queue}, no heading "
                f"{self.frames_without_heading}, bad exposure {self.frames_bad_exposure}, out of order "
                f"{self.frames_out_of_order}, clock jumps {self.clock_jumps}) | estimates "
                f"{self.estimates} at {rate:.1f} Hz, skipped {self.windows_skipped}, failed "
                f"{self.estimates_failed}{stale} | {lat_text} | publish drops {pub_drops}"
                f"{f' ({drops_by})' if drops_by else ''}, errors {pub_errors}{f' ({errors_by})' if errors_by else ''}"
                f"{status}")


def publisher_losses(stats: Iterable[dict]) -> tuple[int, int]:
    """Estimates the publishers dropped (``dropped``, ``dropped_overwritten``, ``dropped_write_timeout``,
    ``dropped_unsent``: a slow or stalled link) and failed to write (``write_errors``, ``errors``: a broken one), summed
    over their ``stats()``: a serial link that goes down must show in the status line."""
    drops = errors = 0
    for s in stats:
        drops += sum(int(v) for k, v in s.items() if k.startswith("dropped") and isinstance(v, int))
        errors += failed_writes(s)
    return drops, errors


class RigPipeline:
    """Runs a source through the estimator to the publishers until the source ends or ``stop``."""

    def __init__(self, source: Iterable[Frame], estimator: SunEstimator, policy: SpreadWindowPolicy,
                 publishers: Sequence[Publisher] = (), *, config: RigConfig | None = None,
                 on_frame: Callable[[Frame], None] | None = None,
                 on_status: Callable[[str], None] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.source = source
        self.estimator = estimator
        self.policy = policy
        self.publishers = list(publishers)
        self.config = config or RigConfig()
        self.on_frame = on_frame  # e.g. a recorder; must not block
        self.on_status = on_status
        self.clock = clock
        self.stats = RigStats()
        self._stop = threading.Event()
        self._capture_done = threading.Event()
        self._encode_done = threading.Event()
        self._frames: DropOldestQueue[tuple[Frame, float]] = DropOldestQueue(self.config.queue_size)
        self._mailbox: DropOldestQueue[tuple[FrameFeatures, float]] = DropOldestQueue(1)
        self.ring = FrameRing(self.config.ring_capacity, self.config.ring_max_age_s)
        self._views = ViewClock()  # a vehicle standing keeps the views from before the stop (rig/window.py)
        self._failure: tuple[str, BaseException] | None = None
        self._failure_lock = threading.Lock()
        # Why frames fail the exposure gate (None: they pass), said when that changes; a verdict that
        # flips at every frame (a scene at a threshold, light through trees) is summed up once a minute.
        self._exposure = LastingCondition(None)
        # "sparse" while windows cannot fill (_log_sparse), "failing" while they fail (_log_failing):
        # each said when it changes; one that flips at every window is summed up once a minute.
        self._sparse = LastingCondition(None)
        self._failing = LastingCondition(None)
        # The frame a heading jump started the windows again from, said once; jumps said at most
        # once a minute (_log_heading_jump).
        self._jump_said_at: FrameFeatures | None = None
        self._jumps = EventThrottle(60.0)
        self._failing_since_seq = 0  # the window that began the stretch of failures last said
        # "stale" while windows come later than max_latency_s (_log_stale), said as the others are.
        self._stale = LastingCondition(None)
        self._stale_since_seq = 0
        self._ring_short_said = False  # _check_ring_span: said once a run
        self._last_failure = ""  # what the newest failed window raised
        self._status_error: str | None = None  # what the last status line that failed raised
        # Per publisher (by position): its name in the statistics (two of one class get #2, #3),
        # what its publish() raised on, and whether its reader is gone.
        self._names: list[str] = []
        for p in self.publishers:
            name = publisher_name(p)
            n = sum(1 for other in self._names if other.split("#")[0] == name)
            self._names.append(f"{name}#{n + 1}" if n else name)
        self._raised = [ErrorTally(log, name) for name in self._names]
        self._ended: set[int] = set()
        # Set when run() returns: from then on the caller owns the outputs (it closes them), and a
        # stage it abandoned publishes nothing more. The lock keeps a publish from straddling that.
        self._outputs_lock = threading.Lock()
        self._outputs_released = False

    # -- control -----------------------------------------------------------------------------
    def stop(self) -> None:
        self._stop.set()

    def _fail(self, stage: str, exc: BaseException) -> None:
        with self._failure_lock:
            if self._failure is None:
                self._failure = (stage, exc)
        self._stop.set()

    def _stage(self, name: str, body: Callable[[], None], done: threading.Event | None) -> threading.Thread:
        def run() -> None:
            try:
                body()
            except BaseException as exc:  # noqa: BLE001 - any failure must stop the whole rig
                log.debug("stage %s failed", name, exc_info=True)
                self._fail(name, exc)
            finally:
                if done is not None:
                    done.set()

        # Daemon: a source blocked inside a driver call must not keep the process alive.
        return threading.Thread(target=run, name=f"sunrig-{name}", daemon=True)

    def run(self, timeout_s: float | None = None) -> RigStats:
        """Run to the end of the source (or ``stop``, or ``timeout_s``); raise on a stage failure."""
        self.stats.started_s = self.clock()
        # Stages are waited for through their done events, never Thread.join: a join cut short by
        # Ctrl-C marks its thread as ended while it still runs (CPython 3.11), and the outputs
        # would then be closed under a stage still publishing.
        estimate_done = threading.Event()
        stages = {"capture": self._capture_done, "encode": self._encode_done, "estimate": estimate_done}
        threads = [
            self._stage("capture", self._capture, self._capture_done),
            self._stage("encode", self._encode, self._encode_done),
            self._stage("estimate", self._estimate, estimate_done),
        ]
        next_status = self.clock() + self.config.status_every_s
        deadline = None if timeout_s is None else self.clock() + timeout_s
        interrupted = False
        try:
            # Started inside the try: a Ctrl-C landing between two starts once left the started
            # stages running ONNX Runtime while the interpreter exited (SIGABRT, a core dump).
            for t in threads:
                t.start()
            while not all(done.is_set() for done in stages.values()):
                estimate_done.wait(_POLL_S)
                now = self.clock()
                if self.on_status and now >= next_status:
                    self.collect_publisher_stats()
                    self._report_status(self.on_status, self.stats.status_line(now))
                    next_status = now + self.config.status_every_s
                if deadline is not None and now >= deadline:
                    self._stop.set()
                if self._stop.is_set():
                    break
        except KeyboardInterrupt:
            interrupted = True
        finally:
            self._stop_stages(threads, stages, interrupted)
            # A stop (Ctrl-C, a timeout) leaves what was queued for a stage that has ended: counted
            # as dropped, so that every frame captured and every frame encoded is accounted for.
            if self._encode_done.is_set():
                self.stats.frames_dropped_queue += len(self._frames)
            if estimate_done.is_set():
                self.stats.windows_skipped += len(self._mailbox)
            self.stats.ended_s = self.clock()
            self.collect_publisher_stats()
            self._release_outputs()
        stuck = [f"sunrig-{name}" for name, done in stages.items() if not done.is_set()]
        if stuck:
            log.warning("abandoned stage(s) %s that did not stop within %.0f s", ", ".join(stuck), _JOIN_S)
        if self._failure is not None:
            stage, exc = self._failure
            # A SunrigError's words are for the user and say what to do; a bug's class is for its report.
            cause = str(exc) if isinstance(exc, SunrigError) else f"{type(exc).__name__}: {exc}"
            raise PipelineError(f"{stage} stage failed: {cause}") from exc
        return self.stats

    def _stop_stages(self, threads: list[threading.Thread], stages: dict[str, threading.Event],
                     interrupted: bool) -> None:
        """Stop every stage and wait for each to end, at most ``_JOIN_S`` in all.

        A stop signal (``KeyboardInterrupt``) landing in this wait, when the rig was already stopping
        for a reason of its own (its timeout, every output gone, a failed stage), asks for what is
        under way: it is held until the stages have ended, as one landing in the run is, so the
        outputs are never closed under a stage still publishing. It once escaped at once, with no
        statistics. Only another one after it (``interrupted``: the run already took one) means
        quit at once, and is let through."""
        end = time.monotonic() + _JOIN_S
        while True:
            try:
                self._stop.set()
                # A source waiting for its next frame (a camera in an outage) sees the stop only
                # when the next one comes; one that can be asked to stop ends its iteration now.
                stop_source = getattr(self.source, "stop", None)
                if callable(stop_source):
                    try:
                        stop_source()
                    except Exception:  # noqa: BLE001 - a source that fails to stop is left as one that does not
                        log.debug("the source's stop() raised", exc_info=True)
                self._frames.close()
                self._mailbox.close()
                for t, done in zip(threads, stages.values(), strict=True):
                    if t.ident is None:  # never started (the stop came first): nothing to wait for
                        done.set()
                for done in stages.values():
                    done.wait(max(0.0, end - time.monotonic()))
                return
            except KeyboardInterrupt:
                if interrupted:
                    raise
                interrupted = True  # and wait on, within the same bound: every step above can be repeated

    def _release_outputs(self) -> None:
        """From now on no stage publishes. Waits for a publish under way (each returns at once),
        at most ``_JOIN_S``: one stuck past that is left behind, as its stage is."""
        got = self._outputs_lock.acquire(timeout=_JOIN_S)
        self._outputs_released = True
        if got:
            self._outputs_lock.release()

    def _report_status(self, on_status: Callable[[str], None], line: str) -> None:
        # A status line is not an output: one that cannot be written (stderr on a full disk, a
        # terminal gone) is counted and said once per kind of error, and the outputs go on. Its
        # error once left run() and stopped the rig, the controller's serial output with it.
        try:
            on_status(line)
        except Exception as exc:  # noqa: BLE001 - a status line must never stop the rig
            self.stats.status_errors += 1
            text = f"{type(exc).__name__}: {exc}"
            if text != self._status_error:
                log.warning("the status line could not be written (%s): counted, and the rig goes on", text)
            self._status_error = text

    def collect_publisher_stats(self) -> None:
        """Take each output's statistics into ``stats.publishers``: at each status line, at the end
        of :meth:`run`, and again by the caller once it has closed the outputs, whose background
        writers may still have been writing (or dropping) when the run ended."""
        self.stats.publish_errors = sum(raised.count for raised in self._raised)
        for p, name, raised in zip(self.publishers, self._names, self._raised, strict=True):
            try:
                st = dict(p.stats())
            except Exception:  # noqa: BLE001 - statistics must never stop the rig
                st = {}  # its own counters are lost this time; the pipeline's count of its errors is not
            if raised.count:
                st["raised"] = raised.count
                st["last_error"] = st.get("last_error") or raised.last
            self.stats.publishers[name] = st

    # -- stages ------------------------------------------------------------------------------
    def _capture(self) -> None:
        # A jump longer than the ring holds re-anchors the pace: no window spans it anyway.
        # Behind by more than the latency bound, it paces from where it is: a camera keeps its rate
        # through a stall of its host, and the frames missed would only be skipped as stale.
        pacer = (Pacer(max_jump_s=self.config.ring_max_age_s, max_behind_s=self.config.max_latency_s)
                 if self.config.realtime else None)
        for frame in self.source:
            if self._stop.is_set():
                return
            if pacer is not None:
                delay = pacer.delay_s(frame, self.clock())
                if delay > 0 and self._stop.wait(delay):
                    return
            # Latency counts from here: the recorder and the exposure gate below are the controller's wait too.
            # A paced frame's from when it was due: a camera's frame is as old when the host stalled
            # in the wait (its estimate went out seconds late as a fresh one), or read it late.
            # A live camera's from its stamp: it may have waited before it reached the rig.
            now = self.clock()
            if pacer is not None:
                arrived = min(now, pacer.due_s)
            elif self.config.live_clock:
                arrived = min(now, frame.t_mono_s)
            else:
                arrived = now
            self.stats.frames_captured += 1
            if self.on_frame is not None:
                self.on_frame(frame)
            if frame.attitude is None:
                # A frame without heading can never join a window: skip the backbone for it.
                self.stats.frames_without_heading += 1
                continue
            gate = self.config.exposure_gate
            reason = gate.rejects(frame.image_bgr) if gate is not None else None
            self._log_exposure(frame, reason)
            if reason:
                # Too dark, bright, flat or covered to show the sun (rig/exposure.py): recorded, never estimated.
                self.stats.frames_bad_exposure += 1
                continue
            if not self._frames.put((frame, arrived)):
                self.stats.frames_dropped_queue += 1

    def _publish(self, est) -> None:
        for i, p in enumerate(self.publishers):
            if i in self._ended:
                continue
            try:
                p.publish(est)
            except BrokenPipeError:
                self._ended.add(i)
                log.info("%s: its reader went away; the other outputs go on", self._names[i])
                if len(self._ended) == len(self.publishers):
                    self._stop.set()  # nobody reads any output: done, as `cmd | head` is
            except Exception as exc:  # noqa: BLE001 - one broken output must not silence the others
                self._raised[i].add(exc, est.seq)

    def _log_sparse(self, same_zero: list[FrameFeatures], window: list[FrameFeatures],
                    newest: FrameFeatures) -> None:
        """Say when windows stop filling and when they fill again: a partial window whose frames come
        too sparsely to fill one (a slow camera, or frames dropped for a slow estimator), so every
        estimate goes out flagged partial, for as long as that lasts. A window still filling
        (:meth:`_still_filling`) changes nothing."""
        partial = len(window) < self.policy.n_frames
        if partial and self._still_filling(same_zero, window):
            return
        said = self._sparse.update("sparse" if partial else None, newest.frame.t_mono_s)
        if said is None:
            return
        if said.kind == "change" and said.changes == 1:
            if partial:
                log.warning("windows hold %d of the model's %d frames: fewer frames than that come in [window] "
                            "span_s (%g s), so every estimate goes out flagged as a partial window; raise span_s or "
                            "the camera's frame rate, or lighten the load that drops frames", len(window),
                            self.policy.n_frames, self.policy.span_s)
            else:
                log.info("from seq %d windows are full again", newest.frame.seq)
            return
        log.warning("windows are full and partial in turn: %d changes in %.0f s, %d of %d windows partial; from seq "
                    "%d %s (said once a minute while it goes on; the camera's frame rate is at the edge of [window] "
                    "span_s)", said.changes, newest.frame.t_mono_s - said.since_s, said.counts.get("sparse", 0),
                    sum(said.counts.values()), newest.frame.seq, "partial" if partial else "full")

    def _still_filling(self, same_zero: list[FrameFeatures], window: list[FrameFeatures]) -> bool:
        """Whether a partial ``window`` (then all the frames of its span) is partial only because its
        frames began less than a span ago: the ring holds none of the newest frame's heading zero
        (``same_zero``: the policy's candidates) from before the span (start-up, a new heading zero,
        a heading jump), or the window's frames come at least as
        densely as a full window's (8 frames in 7 intervals within the 4 s span: 0.571 s apart on
        average): after a gap (a tunnel whose frames the exposure gate refused, a camera's outage)
        they are refilling it, and the camera's rate is not at fault. A window of the newest frame
        alone shows no rate: the interval before the gap stands for it."""
        # In view time, as the window's span: a vehicle that stood still is no slow camera.
        newest_s = window[-1].window_t_s
        if not same_zero or newest_s - same_zero[0].window_t_s <= self.policy.span_s:
            return True
        full_interval_s = self.policy.span_s / max(self.policy.n_frames - 1, 1)
        if len(window) >= 2:
            mean_interval_s = (newest_s - window[0].window_t_s) / (len(window) - 1)
        else:
            before = [f.window_t_s for f in same_zero if f.window_t_s < newest_s][-2:]
            if len(before) < 2:
                return True  # nothing shows the rate yet
            mean_interval_s = before[1] - before[0]
        # The tolerance keeps a camera exactly at the full window's rate (1.75 fps) from flipping on rounding.
        return mean_interval_s <= full_interval_s * (1.0 + 1e-9)

    def _log_heading_jump(self, candidates: list[FrameFeatures], same_zero: list[FrameFeatures]) -> None:
        """Say when a heading jump (``rig/window.py``: faster than a camera turns) starts the windows
        again: its frames are then only those from the jump on (``same_zero``), fewer than the ring
        holds of that heading reference and epoch, and the estimates go out flagged partial until the
        windows refill. Once a jump (the windows after it show the same cut for a span), at most
        once a minute of the frames' clock: a compass that glitches every few frames is summed up."""
        if not same_zero:
            return
        first = same_zero[0]
        att = first.frame.attitude
        assert att is not None  # same_zero holds frames with a heading only
        zero = [c for c in candidates if (a := c.frame.attitude) is not None
                and (a.reference, a.epoch) == (att.reference, att.epoch)]
        if zero[0] is first or first is self._jump_said_at:
            return  # the windows reach back to the oldest such frame held; or this jump is said
        before = zero[next(i for i, c in enumerate(zero) if c is first) - 1]
        assert before.frame.attitude is not None
        if zero[-1].window_t_s - before.window_t_s > self.policy.span_s:
            # The frames cut off are older than any window reaches: no window lost them. (A glitch
            # that has become the ring's oldest frame, with no frame before it, looks like a jump.)
            return
        self._jump_said_at = first
        turn_deg = math.degrees(abs(math.remainder(att.heading_rad - before.frame.attitude.heading_rad, math.tau)))
        dt_s = first.frame.t_mono_s - before.frame.t_mono_s
        said = self._jumps.note(first.frame.t_mono_s)
        if said is None:
            return
        n, said_before_s = said
        turn = f"{turn_deg:.0f} deg from seq {before.frame.seq}'s in {dt_s:.2f} s"
        rate = (f"more than {math.degrees(MIN_JUMP_RAD):.0f} deg at over "
                f"{math.degrees(self.policy.max_yaw_rate_rad_s):.0f} deg/s")
        if said_before_s is None:
            log.warning("seq %d: its heading jumped %s, faster than a camera turns (%s): a compass glitch, or a "
                        "heading source whose zero moved unsaid. Windows start again from it, flagged partial "
                        "until they refill; if the next heading comes back, it alone is left out",
                        first.frame.seq, turn, rate)
        else:
            log.warning("the heading jumped %d times in %.0f s, the last at seq %d (%s), faster than a camera turns "
                        "(%s): windows start again from each jump (said once a minute while it goes on)", n,
                        first.frame.t_mono_s - said_before_s, first.frame.seq, turn, rate)

    def _log_failing(self, feats: FrameFeatures, exc: EstimationError | None) -> None:
        """Say when windows start failing and when estimates come again: a model answering NaN fails
        every window, said 10 times a second for as long as it lasted; one failing every other
        window is summed up once a minute."""
        seq = feats.frame.seq
        if exc is not None:
            self._last_failure = str(exc)
        said = self._failing.update(None if exc is None else "failing", feats.frame.t_mono_s)
        if said is None:
            return
        failed = said.counts.get("failing", 0)
        if said.kind == "change" and said.changes == 1:
            if exc is not None:
                self._failing_since_seq = seq
                log.warning("no estimate for seq %d: %s (the windows that fail after it are counted, and said "
                            "when estimates come again)", seq, exc)
            else:
                log.info("from seq %d estimates again: %d windows failed since seq %d", seq, failed,
                         self._failing_since_seq)
            return
        log.warning("windows fail and succeed in turn: %d changes in %.0f s, %d of %d windows failed (last: %s); "
                    "from seq %d %s (said once a minute while it goes on)", said.changes,
                    feats.frame.t_mono_s - said.since_s, failed, sum(said.counts.values()), self._last_failure, seq,
                    "failing" if exc is not None else "estimating")

    def _log_exposure(self, frame: Frame, reason: str | None) -> None:
        # Once per change, not per frame: a night is one message, not one per frame. By the frames'
        # clock, so a replay says the same as the drive did.
        said = self._exposure.update(reason, frame.t_mono_s)
        if said is None:
            return
        if said.kind == "change" and said.changes == 1:
            if reason == "covered":
                # Said with its remedy: a camera that always sees its own hood or dashboard would
                # otherwise send nothing all day.
                log.warning("from seq %d frames are partly covered (dark and flat over more than %.0f%% of the frame: "
                            "a cap, a visor or a hand over the lens?): left out of windows until that changes; if "
                            "it is the vehicle's own hood or dashboard, always in view, raise [rig] "
                            "max_covered_share (docs/deploy.md)", frame.seq,
                            100.0 * self._gate_share())
            elif reason:
                log.warning("from seq %d frames are too %s to show the sun: left out of windows until that changes",
                            frame.seq, reason)
            else:
                log.info("from seq %d frames show the scene again: windows refill", frame.seq)
            return
        left_out = sum(n for r, n in said.counts.items() if r is not None)
        log.warning("frames pass and fail the exposure gate in turn: %d changes in %.0f s, %d of %d frames left out "
                    "of windows; from seq %d %s (said once a minute while it goes on)", said.changes,
                    frame.t_mono_s - said.since_s, left_out, sum(said.counts.values()), frame.seq,
                    ("partly covered" if reason == "covered" else f"too {reason}") if reason else "showing the scene")

    def _gate_share(self) -> float:
        gate = self.config.exposure_gate
        return gate.max_covered_share if gate is not None else 1.0

    def _encode(self) -> None:
        while not self._stop.is_set():
            item = self._frames.get(_POLL_S)
            if item is None:
                if self._capture_done.is_set() and len(self._frames) == 0:
                    return
                continue
            frame, arrived = item
            feats = self._views.stamp(self.estimator.encode(frame))
            self.stats.frames_encoded += 1
            if not self.ring.push(feats):
                self.stats.frames_out_of_order += 1
                continue
            self._check_ring_span()
            if self.ring.restarts != self.stats.clock_jumps:  # the ring counts them; this one says so
                self.stats.clock_jumps = self.ring.restarts
                log.warning("seq %d %s: the clock jumped; windows start again from it",
                            frame.seq, self.ring.last_restart)
            if not self._mailbox.put((feats, arrived)):
                self.stats.windows_skipped += 1

    def _check_ring_span(self) -> None:
        """Say once a run when the ring holds less than a window's span (:func:`ring_too_short`)."""
        if self._ring_short_said:
            return
        short = ring_too_short(self.ring, self.policy.span_s)
        if short is not None:
            self._ring_short_said = True
            log.warning("%s", short)

    def _estimate(self) -> None:
        while not self._stop.is_set():
            item = self._mailbox.get(_POLL_S)
            if item is None:
                if self._encode_done.is_set() and len(self._mailbox) == 0:
                    return
                continue
            feats, arrived = item
            if self._too_late(feats, self.clock() - arrived):  # waited through a stall: not worth a run
                continue
            candidates = self._held_up_to(feats)
            if candidates is None:
                self.stats.windows_skipped += 1  # the ring let its frame go (a clock jump) before its turn
                continue
            same_zero = self.policy.same_zero(candidates)  # what the window is chosen among
            window = self.policy.select_same_zero(same_zero)
            self._log_heading_jump(candidates, same_zero)
            self._log_sparse(same_zero, window, feats)
            try:
                est = self.estimator.estimate(window)
            except EstimationError as exc:
                self.stats.estimates_failed += 1
                self._log_failing(feats, exc)
                continue
            self._log_failing(feats, None)
            if self._too_late(feats, self.clock() - arrived):  # the window itself stalled
                continue
            self._log_stale(feats, None)
            with self._outputs_lock:
                if self._outputs_released:
                    # run() gave up waiting for this stage (a window that stalled through the stop) and
                    # returned; its caller closes the outputs. Not sent, as a window skipped.
                    self.stats.windows_skipped += 1
                    return
                self._publish(est)
            self.stats.estimates += 1
            self.stats.latency.add(self.clock() - arrived)

    def _held_up_to(self, feats: FrameFeatures) -> list[FrameFeatures] | None:
        """The ring's frames up to ``feats`` by position, ``feats`` the newest: a window never holds a
        frame that came after its own. By stamp, a driver stamping two frames alike put the later
        one into the earlier one's window, as its newest, and its seq went out twice; and after the
        ring started again (a clock stepped back) the frames after the jump, stamped earlier, made
        up the window. None when the ring no longer holds ``feats``."""
        held = self.ring.snapshot()
        for i in range(len(held) - 1, -1, -1):  # the newest frames are the likeliest
            if held[i] is feats:
                return held[: i + 1]
        return None

    def _too_late(self, feats: FrameFeatures, age_s: float) -> bool:
        """Whether the window of ``feats``, its frame ``age_s`` out of the source, is too late to send:
        then it is counted (skipped, stale) and said."""
        if age_s <= self.config.max_latency_s:
            return False
        self.stats.windows_skipped += 1
        self.stats.estimates_stale += 1
        self._log_stale(feats, age_s)
        return True

    def _log_stale(self, feats: FrameFeatures, age_s: float | None) -> None:
        """Say when windows start coming too late to send (``age_s``) and when they are in time again
        (None); a machine at the edge of the bound is summed up once a minute."""
        seq = feats.frame.seq
        said = self._stale.update(None if age_s is None else "stale", feats.frame.t_mono_s)
        if said is None:
            return
        stale = said.counts.get("stale", 0)
        if said.kind == "change" and said.changes == 1:
            if age_s is not None:
                self._stale_since_seq = seq
                log.warning("seq %d: its estimate came %.1f s after its frame, over [rig] max_latency_s (%g s): not "
                            "sent, nor any later one as late (counted as stale; said when estimates are in time "
                            "again). The machine stalled or is too busy for the model", seq, age_s,
                            self.config.max_latency_s)
            else:
                log.info("from seq %d estimates are in time again: %d too late to send since seq %d", seq, stale,
                         self._stale_since_seq)
            return
        log.warning("estimates come in time and too late in turn: %d changes in %.0f s, %d of %d too late to send "
                    "(over [rig] max_latency_s %g s); from seq %d %s (said once a minute while it goes on)",
                    said.changes, feats.frame.t_mono_s - said.since_s, stale, sum(said.counts.values()),
                    self.config.max_latency_s, seq, "too late" if age_s is not None else "in time")
