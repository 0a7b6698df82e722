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
    from replay.sources import open_frames
    from rig.offline import OfflineStats, estimate_stream
    from rig.window import SpreadWindowPolicy

    # The log is checked before the model is loaded: a wrong path should fail in milliseconds.
    if args.log is None:
        from replay.sources import DEMO_LOG

        args.log = str(DEMO_LOG)
    source = open_frames(args.log)
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


def _expand_logs(items: list[str]) -> list[Path]:
    """Log arguments: files, or folders whose *.mcap files are taken in name order."""
    paths: list[Path] = []
    for item in items:
        p = Path(item)
        if p.is_dir() and any(p.glob("*.mcap")):
            paths.extend(sorted(p.glob("*.mcap")))
        else:
            paths.append(p)
    return paths


def cmd_eval(args: argparse.Namespace) -> int:
    from estimator.estimator import AGGREGATORS, SunEstimator
    from estimator.evaluate import evaluate, plot_eval
    from replay.sources import open_frames
    from rig.window import SpreadWindowPolicy

    paths = _expand_logs(args.logs)
    sources = [(str(p), open_frames(p)) for p in paths]  # every log checked before any work
    model = _load_model(args.model)
    estimator = SunEstimator(model, seed=args.seed)
    policy = SpreadWindowPolicy(n_frames=estimator.frames_per_window, span_s=args.window_span_s)
    aggregators = args.aggregators.split(",") if args.aggregators else list(AGGREGATORS)
    progress = Progress("eval", enabled=None if not args.quiet else False)
    result = evaluate(sources, estimator, policy, aggregators=aggregators,
                      progress=lambda n: progress.update(n, "windows"))
    summary = result.summary()
    summary["model"] = {"dir": str(model.model_dir), "id": model.model_id}
    text = json.dumps(summary, indent=2)
    if args.json and args.json != "-":
        Path(args.json).write_text(text + "\n", encoding="utf-8")
    else:
        print(text)
    if args.plot:
        plot_eval(result, Path(args.plot))
    lines = [f"{name}: mean {s['mean_deg']:.2f} deg, median {s['median_deg']:.2f}, max {s['max_deg']:.1f} "
             f"over {s['n_windows']} windows" for name, s in summary["aggregators"].items() if s["n_windows"]]
    if not args.quiet:
        progress.close("; ".join(lines) if lines else "no full window with ground truth in these logs")
    if not lines:
        return EXIT_USER_ERROR
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from rig.errors import require_torch

    require_torch()
    from estimator.train import TrainConfig, command_line, data_fingerprint, train

    if args.export_only:
        from estimator.train import export_checkpoint

        out = export_checkpoint(Path(args.out), Path(args.export_only))
        if not args.quiet:
            print(f"train: exported the checkpoint in {args.out} to {out}", file=sys.stderr)
        return 0
    if not args.logs:
        raise SunrigError("train: no logs given; pass native logs or folders of them")
    paths = _expand_logs(args.logs)
    from replay.sources import open_frames

    for p in paths:  # fail on a bad log now, not after loading the others
        open_frames(p)
    cfg = TrainConfig(preset=args.preset, minutes=args.minutes, max_steps=args.steps,
                      batch_windows=args.batch, lr=args.lr, seed=args.seed, threads=args.threads,
                      command=command_line(),
                      data={"logs": len(paths), "fingerprint": data_fingerprint(paths),
                            "source": args.data_note or ""})
    bar = None
    if not args.quiet:
        try:
            from tqdm import tqdm

            bar = tqdm(total=0, unit="step", dynamic_ncols=True)
        except ImportError:  # pragma: no cover
            bar = None
    progress_line = Progress("train", enabled=None if not args.quiet and bar is None else False)

    def on_progress(p: dict) -> None:
        if bar is not None:
            bar.total = p["total"] if p["total"] < 10**9 else None
            bar.n = p["step"]
            bar.set_postfix(loss=f"{p['loss']:.3f}", err=f"{p['err_deg']:.1f}deg",
                            min=f"{p['elapsed_s'] / 60:.0f}/{p['budget_s'] / 60:.0f}", refresh=False)
            bar.refresh()
        else:
            progress_line.update(p["step"], f"loss {p['loss']:.3f} err {p['err_deg']:.1f} deg")

    out = train(paths, Path(args.out), cfg, progress=on_progress)
    if bar is not None:
        bar.close()
    if not args.quiet:
        progress_line.close(f"model written to {out}")
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from replay.synthetic import write_synthetic_logs

    paths = write_synthetic_logs(args.out, drives=args.drives, frames=args.frames, seed=args.seed,
                                 progress=not args.quiet, fps=args.fps, jobs=args.jobs,
                                 render_scale=args.render_scale)
    if not args.quiet:
        print(f"synth: {len(paths)} logs of {args.frames} frames in {args.out}", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="sunrig", description="Estimate the sun direction from a camera rig's images and heading."
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    p = sub.add_parser("replay", help="run a recorded log through the estimator")
    p.add_argument("log", nargs="?", help="a native sunrig log (.mcap); default: the bundled demo drive")
    p.add_argument("--jsonl", metavar="PATH|-", help="write one JSON object per estimate here (- for stdout)")
    p.add_argument("--model", metavar="DIR", help="model folder (backbone.onnx + aggregator.onnx)")
    p.add_argument("--aggregator", default="transformer", choices=["transformer", "mean", "meanshift", "single"])
    p.add_argument("--seed", type=int, default=0, help="crop sampling seed (default 0)")
    p.add_argument("--window-span-s", type=float, default=4.0, metavar="S",
                   help="spread each window's frames over the last S seconds (default 4)")
    p.add_argument("--quiet", action="store_true", help="no progress or summary on stderr")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("eval", help="angular error of every aggregator over logs with ground truth")
    p.add_argument("logs", nargs="+", help="native logs, or folders of them")
    p.add_argument("--json", metavar="OUT", help="write the summary here (default: stdout)")
    p.add_argument("--plot", metavar="OUT.png", help="cumulative error curves (and OUT-tokens.png)")
    p.add_argument("--model", metavar="DIR", help="model folder (default: the shipped model)")
    p.add_argument("--aggregators", metavar="A,B", help="comma-separated subset (default: all)")
    p.add_argument("--seed", type=int, default=0, help="crop sampling seed (default 0)")
    p.add_argument("--window-span-s", type=float, default=4.0, metavar="S")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("train", help="train a model on logs with ground truth (needs sunrig[train])")
    p.add_argument("logs", nargs="*", help="native logs, or folders of them")
    p.add_argument("--out", required=True, metavar="MODEL_DIR",
                   help="model folder; holds checkpoint.pt, and a run resumes from it")
    p.add_argument("--preset", default="fast",
                   help="network preset: fast (default, the 90-minute CPU recipe), light, paper (ResNet18 at 224 px)")
    p.add_argument("--minutes", type=float, default=80.0, help="training time budget (default 80)")
    p.add_argument("--steps", type=int, default=0, help="stop after this many steps instead")
    p.add_argument("--batch", type=int, default=6, help="windows per step (default 6)")
    p.add_argument("--lr", type=float, default=5e-4, help="peak learning rate (default 5e-4)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=0, help="torch threads (default: all cores)")
    p.add_argument("--data-note", help="what the logs are, recorded in the model's contract")
    p.add_argument("--export-only", metavar="DIR",
                   help="export the checkpoint in --out as it stands to DIR, without training (e.g. mid-run)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("synth", help="write procedural street drives with the true sun as native logs")
    p.add_argument("out", help="output folder (drives already there are kept: a run resumes)")
    p.add_argument("--drives", type=int, default=10)
    p.add_argument("--frames", type=int, default=40, help="frames per drive (default 40)")
    p.add_argument("--seed", type=int, default=0, help="drive i of seed S is always the same drive")
    p.add_argument("--fps", type=float, default=10.0, help="frame rate of the drives (default 10)")
    p.add_argument("--jobs", type=int, default=1, help="drives rendered in parallel (default 1)")
    p.add_argument("--render-scale", type=float, default=0.5,
                   help="internal render size relative to the output (default 0.5, upsampled)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=cmd_synth)
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
