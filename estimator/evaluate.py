"""Evaluation: angular error of every aggregator over the windows of logs that carry the true sun.

The windows are the ones the live rig would form (the spread window policy, one per frame), minus
those formed while a log's buffer is still filling (fewer frames than a full window), so every
aggregator is scored on the same full windows. Pure numbers here; plotting is in
:func:`plot_eval`, which imports matplotlib only when called.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimator.estimator import AGGREGATORS, SunEstimator
from replay.sources import corrupt_skipped
from rig.exposure import DEFAULT_EXPOSURE_GATE, ExposureGate
from rig.geometry import az_el_from_enu
from rig.offline import OfflineStats, estimate_stream
from rig.protocol import FLAG_ABOVE_TRAINED, FLAG_SPREAD_HIGH, FLAG_VALID, StatusRule
from rig.types import Frame, HeadingRef, SunEstimate
from rig.window import SpreadWindowPolicy

THRESHOLDS_DEG = (5.0, 10.0, 20.0)
# The model's target for its worst window (issue #3). The max alone is one estimate of thousands
# and moves with the crop draw, so the summary also counts the windows past it and gives the p99.
TAIL_DEG = 30.0
TAIL_KEY = f"windows_over_{TAIL_DEG:g}_deg"
# Logs listed in a summary's ``worst_logs``, per aggregator: a tail usually comes from a few drives,
# and which ones is the first thing to know about it.
WORST_LOGS = 5
LOG_KEYS = ("n_windows", "mean_deg", "max_deg", TAIL_KEY)  # of error_summary, per log
SEQ_KEYS = ("n_windows", "mean_deg", "p99_deg", "max_deg", TAIL_KEY)  # of error_summary, per newest frame


@dataclass
class TruthTally:
    """Why a log's frames have no true sun, counted as they pass (:meth:`counted`), so that a log
    left out of ``sunrig eval`` or ``sunrig train`` is named with what its frames lack and what to
    record: "no true sun" alone did not tell a drive recorded without GNSS from one recorded with
    a relative heading."""

    frames: int = 0
    no_fix: int = 0  # a TRUE heading, and no true sun: no GNSS fix within reach (replay.groundtruth)
    not_true: dict[str, int] = field(default_factory=dict)  # by heading reference (relative, magnetic)
    no_heading: int = 0

    def add(self, frame: Frame) -> None:
        self.frames += 1
        att = frame.attitude
        if att is None:
            self.no_heading += 1
        elif att.reference != HeadingRef.TRUE:
            self.not_true[att.reference.value] = self.not_true.get(att.reference.value, 0) + 1
        elif frame.sun_enu_truth is None:
            self.no_fix += 1

    def counted(self, frames: Iterable[Frame]) -> Iterator[Frame]:
        for frame in frames:
            self.add(frame)
            yield frame

    def why(self) -> str:
        """What the frames lack for a true sun, each with what to record."""
        m = self.frames
        if not m:
            return "it holds no frames"
        counts: list[int] = []

        def of(n: int) -> str:  # "4 of its 10 frames" the first time, "3" after
            counts.append(n)
            return f"{n} of its {m} frames" if len(counts) == 1 else str(n)

        def have(n: int) -> str:
            return "has" if n == 1 else "have"

        parts = []
        if self.no_fix:
            parts.append(f"{of(self.no_fix)} {have(self.no_fix)} a TRUE heading and no GNSS fix (the true sun "
                         "needs the place and UTC: record with a GNSS, docs/ground-truth.md)")
        if self.not_true:
            refs = sorted(self.not_true.items(), key=lambda kv: (-kv[1], kv[0]))
            said = [f"{of(n)} {have(n)} a {ref} heading" if i == 0 else f"{of(n)} a {ref} one"
                    for i, (ref, n) in enumerate(refs)]
            parts.append(" and ".join(said) + " (the true sun needs a TRUE heading: a GNSS compass or INS)")
        if self.no_heading:
            parts.append(f"{of(self.no_heading)} {have(self.no_heading)} no heading")
        return "; ".join(parts)


def error_summary(errors_deg: Sequence[float]) -> dict[str, float | int | None]:
    """Mean, median, p99, max, the share of windows under 5, 10 and 20 degrees and the number
    of windows over :data:`TAIL_DEG`. Of no window, the same keys, None for the figures there are
    none of: a reader of the JSON finds the shape it was promised."""
    e = np.asarray(errors_deg, dtype=np.float64)
    if e.size == 0:
        return {"mean_deg": None, "median_deg": None, "p99_deg": None, "max_deg": None, "n_windows": 0,
                **{f"under_{th:g}_deg": None for th in THRESHOLDS_DEG}, TAIL_KEY: 0}
    out: dict[str, float | int | None] = {
        "mean_deg": float(e.mean()),
        "median_deg": float(np.median(e)),
        "p99_deg": float(np.percentile(e, 99)),
        "max_deg": float(e.max()),
        "n_windows": int(e.size),
    }
    for th in THRESHOLDS_DEG:
        out[f"under_{th:g}_deg"] = float((e < th).mean())
    out[TAIL_KEY] = int((e > TAIL_DEG).sum())
    return out


def status_summary(flags: Sequence[int], errors_deg: Sequence[float]) -> dict[str, float | int | None]:
    """What a controller would have been told of these windows (their status flags, in the same
    order as their errors): how many it could trust, why the others not, and how wrong the
    trusted ones were at worst. The error figures of :func:`error_summary` stay over every window."""
    f = np.asarray(flags, dtype=np.int64)
    e = np.asarray(errors_deg, dtype=np.float64)
    valid = (f & FLAG_VALID) != 0
    return {
        "valid_windows": int(valid.sum()),
        "above_trained": int(((f & FLAG_ABOVE_TRAINED) != 0).sum()),
        "spread_high": int(((f & FLAG_SPREAD_HIGH) != 0).sum()),
        f"{TAIL_KEY}_not_valid": int((~valid & (e > TAIL_DEG)).sum()),
        "valid_max_deg": float(e[valid].max()) if valid.any() else None,
    }


@dataclass
class EvalResult:
    errors_deg: dict[str, list[float]] = field(default_factory=dict)
    # Per aggregator, in the order of errors_deg: the status flags a controller would get
    # (rig/protocol.StatusRule) and the answer's elevation; then each window's true elevation.
    flags: dict[str, list[int]] = field(default_factory=dict)
    elevation_deg: dict[str, list[float]] = field(default_factory=dict)
    truth_elevation_deg: list[float] = field(default_factory=list)
    # A few windows for the plots, each with its log (named in its title).
    samples: list[tuple[str, dict[str, SunEstimate]]] = field(default_factory=list)
    logs: list[str] = field(default_factory=list)
    # Each window's newest frame (its seq in the log), then its log, in the order of every errors_deg list.
    window_seqs: list[int] = field(default_factory=list)
    window_logs: list[str] = field(default_factory=list)
    frames: int = 0
    frames_without_heading: int = 0  # left out of windows, as in a replay
    frames_bad_exposure: int = 0  # too dark, bright, flat or covered to show the sun (rig/exposure.py)
    # Frames older than the one before (left out, as live: windows assume time order) and clock
    # jumps (windows start again): a figure over a log whose clock misbehaved says so.
    frames_out_of_order: int = 0
    clock_jumps: int = 0
    windows_skipped_filling: int = 0
    windows_failed: int = 0
    windows_without_truth: int = 0
    # Damaged records the log readers skipped (replay.sources.corrupt_skipped), per log: a figure
    # computed over a damaged log says so, and the frames it lost are in no other count.
    records_skipped_corrupt_by_log: dict[str, int] = field(default_factory=dict)
    interrupted: bool = False  # Ctrl-C: the figures are of the windows evaluated until then
    # Logs read to their end of which no window was graded, each with why: among graded logs the
    # figures are not theirs, and only this says so (the counts above are pooled over all logs).
    logs_not_graded: dict[str, str] = field(default_factory=dict)

    # The counters above: pooled by addition and reported as they are, in this order.
    COUNTS = ("frames", "frames_without_heading", "frames_bad_exposure", "frames_out_of_order", "clock_jumps",
              "windows_skipped_filling", "windows_failed", "windows_without_truth")
    # Those that estimate_stream counts per log (the others are counted here, per window).
    STREAM_COUNTS = ("frames", "frames_without_heading", "frames_bad_exposure", "frames_out_of_order",
                     "clock_jumps", "windows_failed")

    def extend(self, other: EvalResult) -> None:
        """Pool another evaluation of the same logs into this one (e.g. with other crop seeds):
        its windows' errors and counts (per log too) are added; the logs, those not graded and the sample
        windows stay this one's."""
        for per_agg in ("errors_deg", "flags", "elevation_deg"):
            for name, values in getattr(other, per_agg).items():
                getattr(self, per_agg).setdefault(name, []).extend(values)
        self.truth_elevation_deg.extend(other.truth_elevation_deg)
        self.window_seqs.extend(other.window_seqs)
        self.window_logs.extend(other.window_logs)
        self.interrupted |= other.interrupted  # pooled with a cut-short run: so is the pool
        for name in self.COUNTS:
            setattr(self, name, getattr(self, name) + getattr(other, name))
        for log, n in other.records_skipped_corrupt_by_log.items():
            self.records_skipped_corrupt_by_log[log] = self.records_skipped_corrupt_by_log.get(log, 0) + n

    @property
    def records_skipped_corrupt(self) -> int:
        """Damaged records skipped over all logs (the per-log counts, summed)."""
        return sum(self.records_skipped_corrupt_by_log.values())

    def trim_to_whole_windows(self) -> None:
        """After an interruption: drop what a window cut short left in some lists but not others
        (``window_logs`` is appended last, so its length is the number of whole windows)."""
        n = len(self.window_logs)
        for per_agg in (self.errors_deg, self.flags, self.elevation_deg):
            for values in per_agg.values():
                del values[n:]
        del self.truth_elevation_deg[n:]
        del self.window_seqs[n:]

    def _grouped(self, aggregator: str, keys: list, what: str, fields: tuple[str, ...]) -> list[tuple]:
        """One aggregator's windows grouped by ``keys`` (one per window, in the order of its errors):
        (key, the ``fields`` of its windows' error_summary), keys in first-seen order."""
        errs = np.asarray(self.errors_deg[aggregator], dtype=np.float64)
        if len(keys) != errs.size:
            raise ValueError(f"{aggregator}: {errs.size} window errors but {len(keys)} window {what}")
        per_window = np.asarray(keys)
        out = []
        for key in dict.fromkeys(keys):
            s = error_summary(errs[per_window == key])
            out.append((key, {k: s[k] for k in fields}))
        return out

    def by_log(self, aggregator: str) -> list[dict[str, float | int | str]]:
        """One aggregator's windows log by log (pooled evaluations of a log count together):
        windows, mean, max, windows over :data:`TAIL_DEG` and the damaged records its reader
        skipped, the worst max first."""
        # Grouped in first-seen order, so ties stay in log order.
        rows = [{"log": name, **s, "records_skipped_corrupt": self.records_skipped_corrupt_by_log.get(name, 0)}
                for name, s in self._grouped(aggregator, self.window_logs, "logs", LOG_KEYS)]
        return sorted(rows, key=lambda r: -float(r["max_deg"]))

    def by_newest_frame(self, aggregator: str) -> list[dict[str, float | int]]:
        """One aggregator's windows grouped by their newest frame's seq, ascending: how the error
        changes as a log's windows gather frames (the first full window of a drive is its first 8
        frames back to back; later ones spread over the policy's span and the road's turns)."""
        rows = [{"newest_seq": int(seq), **s}
                for seq, s in self._grouped(aggregator, self.window_seqs, "seqs", SEQ_KEYS)]
        return sorted(rows, key=lambda r: r["newest_seq"])

    def summary(self) -> dict:
        return {
            "aggregators": {name: error_summary(e) for name, e in self.errors_deg.items()},
            "status": {name: status_summary(self.flags[name], e) for name, e in self.errors_deg.items()},
            "worst_logs": {name: self.by_log(name)[:WORST_LOGS] for name in self.errors_deg},
            "logs": self.logs,
            "logs_not_graded": self.logs_not_graded,
            **{name: getattr(self, name) for name in self.COUNTS},
            "records_skipped_corrupt": self.records_skipped_corrupt,
            **({"interrupted": True} if self.interrupted else {}),
        }


def evaluate(sources: Iterable[tuple[str, Iterable[Frame]]], estimator: SunEstimator, policy: SpreadWindowPolicy,
             aggregators: Sequence[str] = AGGREGATORS, n_samples: int = 6,
             progress: Callable[[int, int], None] | None = None,
             status_rule: StatusRule | None = None,
             exposure_gate: ExposureGate | None = DEFAULT_EXPOSURE_GATE) -> EvalResult:
    """Every full window of every source, estimated by each aggregator on the same crops.

    ``progress(windows_done, logs_done)`` is called after each window and each log.
    ``status_rule``: what decides each window's status flags (default: the estimator's model's,
    as the rig's outputs use). ``exposure_gate``: which frames are left out as unable to show the
    sun (``rig/exposure.py``; None keeps every frame). A Ctrl-C ends the evaluation early, not the result: it comes back
    with ``interrupted`` set and the windows evaluated until then, so minutes of work are kept."""
    rule = status_rule or estimator.status_rule()
    result = EvalResult(errors_deg={a: [] for a in aggregators}, flags={a: [] for a in aggregators},
                        elevation_deg={a: [] for a in aggregators})
    try:
        for n_logs, (name, frames) in enumerate(sources, 1):
            result.logs.append(name)
            stats = OfflineStats()
            graded_before, without_truth_before = len(result.window_logs), result.windows_without_truth
            tally = TruthTally()
            try:
                _evaluate_log(result, name, tally.counted(frames), estimator, policy, aggregators, n_samples, rule,
                              stats, progress, n_logs - 1, exposure_gate)
                if len(result.window_logs) == graded_before:
                    result.logs_not_graded[name] = _why_not_graded(
                        stats, result.windows_without_truth - without_truth_before, policy, tally)
            finally:  # an interrupted log's frames count too
                for key in EvalResult.STREAM_COUNTS:
                    setattr(result, key, getattr(result, key) + getattr(stats, key))
                # Asked of the reader once its pass has ended: the log is not read again for it.
                by_log = result.records_skipped_corrupt_by_log
                by_log[name] = by_log.get(name, 0) + corrupt_skipped(frames)
            if progress:
                progress(len(result.window_logs), n_logs)
    except KeyboardInterrupt:
        result.interrupted = True
        result.trim_to_whole_windows()
    return result


def _why_not_graded(stats: OfflineStats, windows_without_truth: int, policy: SpreadWindowPolicy,
                    tally: TruthTally | None = None) -> str:
    """Why a log read to its end gave no window to grade, from its own counts (in the order the
    CLI's error for a run that graded nothing gives them); ``tally``: what its frames lacked for
    a true sun."""
    n, m = policy.n_frames, stats.frames
    if not m:
        return "no frame of it could be read"
    if stats.windows_failed:
        return f"its {stats.windows_failed} windows failed"
    if windows_without_truth:
        lack = tally.why() if tally is not None and tally.frames else ""
        return f"its {windows_without_truth} full windows have no true sun" + (f": {lack}" if lack else "")
    if stats.frames_without_heading:
        return f"{stats.frames_without_heading} of its {m} frames have no heading"
    if stats.frames_bad_exposure:
        return f"{stats.frames_bad_exposure} of its {m} frames are too dark, bright, flat or covered to use"
    if m < n:
        return f"it has {m} frames, fewer than a window's {n}"
    return f"no {n} of its {m} frames are within {policy.span_s:g} s of each other"


def _evaluate_log(result: EvalResult, name: str, frames: Iterable[Frame], estimator: SunEstimator,
                  policy: SpreadWindowPolicy, aggregators: Sequence[str], n_samples: int, rule: StatusRule,
                  stats: OfflineStats, progress: Callable[[int, int], None] | None, logs_done: int,
                  exposure_gate: ExposureGate | None) -> None:
    sampled = False
    for estimates in estimate_stream(frames, estimator, policy, aggregators=aggregators, stats=stats,
                                     exposure_gate=exposure_gate):
        first = next(iter(estimates.values()))
        if first.n_frames < policy.n_frames:
            result.windows_skipped_filling += 1
            continue
        if first.truth_enu is None:
            result.windows_without_truth += 1
            continue
        for agg, est in estimates.items():
            error_rad = est.error_rad
            assert error_rad is not None  # one window, one truth: every aggregator's has first's
            result.errors_deg[agg].append(math.degrees(error_rad))
            result.flags[agg].append(rule.flags(est))
            result.elevation_deg[agg].append(math.degrees(est.elevation_rad))
        result.truth_elevation_deg.append(math.degrees(float(az_el_from_enu(first.truth_enu)[1])))
        result.window_seqs.append(first.seq)
        result.window_logs.append(name)  # last: it is what makes the window count (trim_to_whole_windows)
        # The first full window of each of the first logs, for the scatter figure: each log has its
        # own sun, so the figure shows different skies.
        if len(result.samples) < n_samples and not sampled:
            result.samples.append((name, estimates))
            sampled = True
        if progress:
            progress(len(result.window_logs), logs_done)


def plot_eval(result: EvalResult, out_png: Path, title: str = "") -> list[Path]:
    """Two figures: cumulative angular error per aggregator (``out_png``, as the paper's result
    figures) and per-token estimates with their aggregate for a few windows (``<stem>-tokens.png``,
    as the paper's calibration figure). Returns the paths written."""
    import matplotlib

    matplotlib.use("Agg")  # no display on a rig or in CI
    import matplotlib.pyplot as plt

    out_png = Path(out_png)
    written = []
    fig, ax = plt.subplots(figsize=(6.4, 4.4), dpi=120)
    for name, errs in result.errors_deg.items():
        if not errs:
            continue
        e = np.sort(np.asarray(errs))
        frac = np.arange(1, e.size + 1) / e.size
        ax.plot(e, frac, label=f"{name} (mean {e.mean():.2f}, max {e.max():.1f} deg)")
    ax.set_xlim(0, 60)
    ax.set_ylim(0, 1)
    ax.set_xlabel("angular error (deg)")
    ax.set_ylabel("share of windows")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
    n = max((len(v) for v in result.errors_deg.values()), default=0)
    title = title or f"cumulative angular error, {n} windows"
    if result.interrupted:  # as its JSON says: the figure is of the windows before a Ctrl-C, not of every log
        begun = len(result.logs)
        title += f" (interrupted: {begun} log{'' if begun == 1 else 's'} begun)"
    ax.set_title(title)
    fig.tight_layout()
    _save_whole(fig, out_png)
    written.append(out_png)

    if result.samples:
        tokens_png = out_png.with_name(out_png.stem + "-tokens" + out_png.suffix)
        first = result.samples[0][1]
        preferred: list[str] = [a for a in ("transformer", "meanshift") if a in first]
        shown = preferred or list(first)
        cols = len(result.samples)
        fig, axes = plt.subplots(len(shown), cols, figsize=(2.6 * cols, 2.8 * len(shown)), dpi=110,
                                 subplot_kw={"projection": "polar"}, squeeze=False)
        for r, agg in enumerate(shown):
            for c, (log, sample) in enumerate(result.samples):
                _polar_window(axes[r][c], sample[agg], Path(log).stem)
                if c == 0:
                    axes[r][c].set_ylabel(agg, labelpad=24)
        fig.suptitle("per-token (dots), aggregate (x), truth (*)\nazimuth clockwise from N; radius: zenith angle",
                     fontsize=9)
        fig.tight_layout()
        fig.subplots_adjust(hspace=0.3)
        _save_whole(fig, tokens_png)
        written.append(tokens_png)
    return written


def _save_whole(fig, path: Path) -> None:
    """Save ``fig`` at ``path`` whole or not at all, and close it: saved in place, a full disk left a
    torn image under the name asked for (read as the run's figure) and lost the one there before."""
    import matplotlib.pyplot as plt

    from rig.files import write_replacing

    try:
        write_replacing(path, fig.savefig)  # the sibling keeps the suffix, which picks the format
    finally:
        plt.close(fig)


def _polar_window(ax, est: SunEstimate, log: str) -> None:
    from rig.geometry import az_el_from_enu

    ax.set_theta_zero_location("N")
    ax.set_theta_direction(-1)  # clockwise azimuth, as the conventions
    if est.token_enu is not None:
        az, el = az_el_from_enu(est.token_enu)
        ax.scatter(az, 90.0 - np.degrees(el), s=8, alpha=0.35)
    az, el = az_el_from_enu(est.sun_enu)
    ax.scatter([az], [90.0 - math.degrees(el)], marker="x", s=60, color="k")
    if est.truth_enu is not None:
        az, el = az_el_from_enu(est.truth_enu)
        ax.scatter([az], [90.0 - math.degrees(el)], marker="*", s=90, color="tab:red")
    ax.set_ylim(0, 90)
    ax.set_yticklabels([])
    ax.set_xticklabels([])
    err = "" if est.error_rad is None else f"{math.degrees(est.error_rad):.1f} deg"
    ax.set_title(f"{log} seq {est.seq}\n{err}", fontsize=8)  # where to find the window again
