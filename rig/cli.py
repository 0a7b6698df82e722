"""The `sunrig` command line. A thin shell: parse, open sources, call the library, report.

Errors a user can fix (any :class:`rig.errors.SunrigError`) print one line and exit 2; anything
else is a bug: one line and exit 1, with the traceback only under ``--debug``.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from pathlib import Path
from typing import TextIO

from rig.errors import SunrigError

EXIT_USER_ERROR = 2
EXIT_BUG = 1


class Progress:
    """A one-line progress counter on stderr, only when stderr is a terminal (logs stay clean)."""

    def __init__(self, label: str, stream: TextIO = sys.stderr, enabled: bool | None = None) -> None:
        self.label = label
        self.stream = stream
        self.enabled = stream.isatty() if enabled is None else enabled
        self.start = time.monotonic()
        self.last = 0.0

    def update(self, done: int, extra: str = "") -> None:
        now = time.monotonic()
        if not self.enabled or now - self.last < 0.2:
            return
        self.last = now
        rate = done / max(now - self.start, 1e-9)
        self.stream.write(f"\r{self.label}: {done} ({rate:.1f}/s) {extra}\033[K")
        self.stream.flush()

    def close(self, summary: str) -> None:
        if self.enabled:
            self.stream.write("\r\033[K")
        self.stream.write(f"{self.label}: {summary}\n")
        self.stream.flush()


def _open_jsonl(target: str) -> TextIO:
    if target == "-":
        return sys.stdout
    try:
        return open(target, "w", encoding="utf-8")  # noqa: SIM115 - closed by the caller
    except OSError as exc:
        raise SunrigError(f"cannot write JSONL to {target}: {exc.strerror}; pass a writable path or -") from None


def _load_model(model_dir: str | None):
    from estimator.models import resolve_model_dir
    from estimator.runtime import OnnxModel

    return OnnxModel.load(resolve_model_dir(model_dir))


def cmd_replay(args: argparse.Namespace) -> int:
    from estimator.estimator import SunEstimator
    from replay.native import open_log
    from rig.offline import OfflineStats, estimate_stream
    from rig.window import SpreadWindowPolicy

    # The log is checked before the model is loaded: a wrong path should fail in milliseconds.
    source = open_log(Path(args.log))
    model = _load_model(args.model)
    estimator = SunEstimator(model, aggregator=args.aggregator, seed=args.seed)
    policy = SpreadWindowPolicy(n_frames=estimator.frames_per_window, span_s=args.window_span_s)
    out = _open_jsonl(args.jsonl) if args.jsonl else None
    stats = OfflineStats()
    progress = Progress(f"replay {Path(args.log).name}", enabled=None if not args.quiet else False)
    errors = []
    try:
        for n, results in enumerate(estimate_stream(source, estimator, policy, stats=stats), start=1):
            est = results[args.aggregator]
            if est.error_rad is not None:
                errors.append(est.error_rad)
            if out is not None:
                out.write(json.dumps(est.to_json_dict()) + "\n")
            progress.update(n, f"frames {stats.frames}")
    finally:
        if out is not None and out is not sys.stdout:
            out.close()
        elif out is not None:
            out.flush()
    summary = f"{stats.frames} frames, {stats.windows - stats.windows_failed} estimates"
    if stats.frames_without_heading:
        summary += f", {stats.frames_without_heading} frames without heading skipped"
    if stats.windows_failed:
        summary += f", {stats.windows_failed} windows failed"
    if errors:
        import math

        summary += f", mean error {math.degrees(sum(errors) / len(errors)):.2f} deg"
    if getattr(source, "truncated", False):
        summary += " (log truncated: replayed up to its last complete chunk)"
    if not args.quiet:
        progress.close(summary)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sunrig", description="Estimate the sun direction from a camera rig's images and heading."
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("replay", help="run a recorded log through the estimator")
    p.add_argument("log", help="a native sunrig log (.mcap)")
    p.add_argument("--jsonl", metavar="PATH|-", help="write one JSON object per estimate here (- for stdout)")
    p.add_argument("--model", metavar="DIR", help="model folder (backbone.onnx + aggregator.onnx)")
    p.add_argument("--aggregator", default="transformer", choices=["transformer", "mean", "meanshift", "single"])
    p.add_argument("--seed", type=int, default=0, help="crop sampling seed (default 0)")
    p.add_argument("--window-span-s", type=float, default=4.0, metavar="S",
                   help="spread each window's frames over the last S seconds (default 4)")
    p.add_argument("--quiet", action="store_true", help="no progress or summary on stderr")
    p.set_defaults(func=cmd_replay)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.debug else logging.WARNING,
        format="sunrig: %(levelname)s: %(message)s",
    )
    try:
        return args.func(args)
    except SunrigError as exc:
        if args.debug:
            raise
        print(f"sunrig: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader of our stdout went away (e.g. `| head`): not an error of ours.
        return 0
    except Exception as exc:  # noqa: BLE001 - the last line of defence prints one line
        if args.debug:
            raise
        print(f"sunrig: internal error: {type(exc).__name__}: {exc} (rerun with --debug for a traceback)",
              file=sys.stderr)
        return EXIT_BUG


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
