"""The `sunrig` command line. A thin shell: parse, open sources, call the library, report.

Errors a user can fix (any :class:`rig.errors.SunrigError`) print one line and exit 2; anything
else is a bug: one line and exit 1, with the traceback only under ``--debug``.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import itertools
import json
import logging
import math
import os
import re
import sys
import threading
import time
from collections.abc import Iterable
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from rig.errors import SunrigError
from rig.progress import Progress, StatusRow, end_row
from rig.stopping import StopSignals

if TYPE_CHECKING:
    from rig.recorder import DiskFull, RecorderPublisher
    from rig.types import Frame

EXIT_USER_ERROR = 2
EXIT_BUG = 1
# A full disk (or quota, or file size limit) while writing: the user's to fix, not a bug.
_DISK_FULL = (errno.ENOSPC, errno.EFBIG, errno.EDQUOT)
# OS errors that the machine, not sunrig, causes: a path that cannot be read or written, a full
# disk, a failing device. With a file name, any OS error is one of these.
_MACHINE_ERRNOS = frozenset((*_DISK_FULL, errno.EACCES, errno.EPERM, errno.EROFS, errno.ENOENT, errno.ENOTDIR,
                             errno.EISDIR, errno.EIO))


# sunrig's own folders: a file of ours that cannot be read is a broken install or a bug, not a
# path the user gave.
_OWN_FOLDERS = tuple(Path(__file__).resolve().parent.parent / name
                     for name in ("rig", "estimator", "replay", "drivers"))


def _machine_error(exc: BaseException) -> str | None:
    """The one line for an OS error that is the machine's to fix (a path that cannot be written, a
    full disk, a failing device), or None for one that is a bug of ours."""
    if not isinstance(exc, OSError) or exc.errno not in _MACHINE_ERRNOS:
        return None
    if exc.filename is not None:
        path = Path(os.fsdecode(exc.filename)).resolve()
        if any(path.is_relative_to(own) for own in _OWN_FOLDERS):
            return None
    if exc.errno in _DISK_FULL:
        hint = "free space on that disk, or write elsewhere"
    elif exc.errno == errno.EIO:
        hint = "check the disk or device"
    else:
        hint = "check the path is right and writable"
    where = f"{os.fsdecode(exc.filename)}: " if exc.filename is not None else ""
    return f"{where}{exc.strerror or exc}; {hint}"


def _int_in(lo: int, hi: int | None = None):
    """An argparse type: an integer from ``lo`` (to ``hi``; at most rig.config.INT_MAX, beyond
    which no count or size here means anything)."""
    from rig.config import INT_MAX, shown_value

    if hi is not None:
        what = f"an integer from {lo} to {hi}"
    else:
        what = "a positive integer" if lo == 1 else f"an integer >= {lo}"

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            value = None
        shown = shown_value(text)
        if value is None or value < lo or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"expected {what}, got {shown}")
        if value > INT_MAX:
            raise argparse.ArgumentTypeError(f"expected {what} up to {INT_MAX}, got {shown}")
        return value
    return parse


def _float_in(lo: float, hi: float = math.inf, *, lo_included: bool = False):
    """An argparse type: a finite number in (``lo``, ``hi``] (``[lo, hi]`` with ``lo_included``).
    nan and inf are typos here, never meant (a nan budget never ends)."""
    from rig.config import describe_range, in_range

    what = f"a finite number {describe_range(lo, hi, lo_included)}"

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not in_range(value, lo, hi, lo_included):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return value
    return parse


def _crop_fovs(text: str) -> float | tuple[float, ...]:
    """``--crop-fov``: one angle (``17.6``) or one per crop scale (``17.6,26``), each in (0, 180)."""
    try:
        fovs = tuple(float(part) for part in text.split(","))
    except ValueError:
        fovs = (math.nan,)
    from estimator.contract import is_crop_fov_deg

    if not all(is_crop_fov_deg(f) for f in fovs):
        raise argparse.ArgumentTypeError(
            f"expected an angle in (0, 180) deg or a comma-separated list of them, got {text!r}")
    return fovs[0] if len(fovs) == 1 else fovs


def _config_type(section: str, key: str):
    """An argparse type for a flag that sets a config option: the option's own type and range
    (rig/config.py), so a flag and a file accept the same values, 0 for "unset" included."""
    from rig.config import DEFAULTS, ConfigError, check_option

    convert = type(DEFAULTS[section][key])

    def parse(text: str):
        try:
            return check_option(section, key, convert(text))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {convert.__name__}, got {text!r}") from None
        except ConfigError as exc:
            raise argparse.ArgumentTypeError(str(exc).split(": ", 1)[1]) from None
    return parse


def _path(text: str) -> str:
    """An argparse type for every path (and port) a command takes: not empty. ``""`` is what an
    unset shell variable gives (``--out "$OUT"``), and was taken as the current folder (quantize
    --out, synth wrote there), as no output at all (eval --plot, run --record), or as a folder to
    read (gnss)."""
    if not text:
        raise argparse.ArgumentTypeError("expected a path, got an empty string")
    return text


def _source_spec(text: str) -> str:
    """An argparse type for --camera and --heading: not empty. ``""`` (``--camera "$CAMERA"`` with the
    variable unset) replaced the config file's [source] option, and the error then said to set it
    there, where it was set."""
    if not text.strip():
        raise argparse.ArgumentTypeError("expected a source, got an empty string (leave the flag out to use "
                                         "the config's)")
    return text


_positive_int = _int_in(1)
_nonneg_int = _int_in(0)
_positive_float = _float_in(0.0)
_share = _float_in(0.0, 1.0, lo_included=True)


def _synth_frames(text: str) -> int:
    """--frames of synth: at most replay.synthetic.MAX_FRAMES, whose comment says why."""
    from replay.synthetic import MAX_FRAMES

    try:
        return _int_in(1, MAX_FRAMES)(text)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"{exc} (a longer drive's route takes gigabytes to lay out)") from None


def _synth_drives(text: str) -> int:
    """--drives of synth: at most replay.synthetic.MAX_DRIVES, whose comment says why."""
    from replay.synthetic import MAX_DRIVES

    try:
        return _int_in(1, MAX_DRIVES)(text)
    except argparse.ArgumentTypeError as exc:
        raise argparse.ArgumentTypeError(f"{exc} (a bigger set: more folders, each with its own --seed)") from None


def _synth_fps(text: str) -> float:
    """--fps of synth: at least 1 frame in 1000 s and at most replay.synthetic.MAX_FPS, since a
    drive's timestamps are int64 nanoseconds."""
    from replay.synthetic import MAX_FPS

    return _float_in(1e-3, MAX_FPS, lo_included=True)(text)


def _utc_offset_type(text: str) -> float:
    from replay.kitti import UTC_OFFSET_LIMIT_H

    return _float_in(-UTC_OFFSET_LIMIT_H, UTC_OFFSET_LIMIT_H, lo_included=True)(text)


def _load_model(model_dir: str | None, stop: StopSignals):
    from estimator.models import resolve_model_dir

    # A stop landing inside onnxruntime's import is turned by it into "ImportError: initialization
    # failed", an internal error (exit 1, a failed unit at a service's stop): the import is a block
    # a stop must not cut, and a stop held meanwhile is taken right after it.
    with stop.finishing():
        from estimator.runtime import OnnxModel
    if stop.requested:
        raise KeyboardInterrupt
    return OnnxModel.load(resolve_model_dir(model_dir or None))


def _publishers(*, serial: str | None, baud: int, fmt: str, jsonl: str | None, rule, stop: StopSignals,
                record: str | None = None, record_overwrite: bool = False, record_frames: bool = False,
                nmea_stdout: bool = False, live: bool = False) -> list:
    """The outputs a command asked for. Opened before any work, so a bad port fails at once.
    ``stop``: the command's stop signals, which closing the outputs must not be cut by.

    ``live``: the stream outputs (JSONL, NMEA on stdout) write in threads of their own, so a
    reader that stops reading cannot stall the rig; offline they write in the caller's thread,
    where waiting for a slow reader loses nothing. Offline the serial port likewise waits for its
    writer rather than replace an unsent estimate (newest wins only live)."""
    from rig.publishers import BackgroundPublisher, JsonlPublisher, SentencePublisher, SerialPublisher

    def stream(p):
        return BackgroundPublisher(p) if live else p

    pubs: list = []
    try:
        if serial:
            pubs.append(SerialPublisher(serial, format=fmt, baudrate=baud, status_rule=rule, wait_for_writer=not live))
        elif nmea_stdout:
            pubs.append(stream(SentencePublisher(sys.stdout, status_rule=rule)))
        if jsonl:
            pubs.append(stream(JsonlPublisher(jsonl, status_rule=rule)))
        if record:
            from rig.recorder import RecorderPublisher, open_recording

            # Last: an output that fails to open leaves no empty recording behind.
            writer = open_recording(record, start_utc=datetime.now(UTC), overwrite=record_overwrite)
            try:
                pubs.append(RecorderPublisher(writer, record_frames=record_frames))
            except BaseException:
                writer.close()
                if not record_overwrite and writer.path is not None:  # (open_recording's writer has one)
                    writer.path.unlink(missing_ok=True)  # made by this run, and holds nothing
                raise
    except BaseException:
        _close_all(pubs, stop)
        raise
    return pubs


@contextlib.contextmanager
def _recording_refusals(option: str, replace: str):
    """A refused recording (rig.recorder.RecordingRefused) in the words of the command that
    asked: ``option`` is where its path came from, ``replace`` how to allow replacing a file."""
    from rig.recorder import MAX_SAME_START, START_FIELD, RecordingRefused

    try:
        yield
    except RecordingRefused as exc:
        path = exc.path
        msg = {
            "exists": f"exists: a recording is not replaced by accident; pass another path, put {START_FIELD} "
                      f"in the name for a new file per run, or {replace} to replace it",
            "folder": f"is a folder: name a file in it, e.g. {path / (START_FIELD + '.mcap')}",
            "no folder": (f"is in {path.parent}, which is a file, not a folder: pass another path"
                          if path.parent.exists() else
                          f"is in a folder that does not exist ({path.parent}): make it, or pass another path"),
            "stdout": "is stdout, but a recording is a file: pass a file name",
            "taken": f"and its -1 to -{MAX_SAME_START - 1} variants exist already: pass a name in another folder",
        }[exc.why]
        raise SunrigError(f"{option} {path} {msg}") from None


def _close_all(pubs: list, stop: StopSignals) -> None:
    # A stop signal now must not leave an output half closed (a recording without its summary).
    with stop.finishing():
        for p in pubs:
            try:
                p.close()
            except Exception as exc:  # noqa: BLE001 - closing one output must not hide the others
                logging.getLogger(__name__).warning("closing %s failed: %s", type(p).__name__, exc)


def paced(frames, speed: float = 1.0, clock=time.monotonic, sleep=time.sleep, max_jump_s: float = 10.0):
    """Yield frames no faster than their timestamps say (``--realtime``); a jump of more than
    ``max_jump_s`` in the recording's clock re-anchors the pace (rig/pacing.Pacer)."""
    from rig.pacing import Pacer

    pacer = Pacer(max_jump_s, speed)
    for frame in frames:
        delay = pacer.delay_s(frame, clock())
        if delay > 0:
            sleep(delay)
        yield frame


def cmd_replay(args: argparse.Namespace) -> int:
    from estimator.estimator import SunEstimator
    from replay.sources import demo_log, open_frames
    from rig.exposure import ExposureGate
    from rig.offline import OfflineStats, estimate_stream
    from rig.window import SpreadWindowPolicy

    log_path = args.log or str(demo_log())
    # The log is checked before the model is loaded: a wrong path should fail in milliseconds.
    source = open_frames(log_path, utc_offset_h=args.utc_offset)
    _refuse_overwriting([Path(log_path)], jsonl=args.jsonl)
    model = _load_model(args.model, args.stop)
    estimator = SunEstimator(model, aggregator=args.aggregator, seed=args.seed)
    policy = SpreadWindowPolicy(n_frames=estimator.frames_per_window, span_s=args.window_span_s)
    pubs = _publishers(serial=args.serial, baud=args.baud, fmt=args.format, jsonl=args.jsonl,
                       rule=estimator.status_rule(), stop=args.stop)
    stats = OfflineStats()
    # resolve(): a KITTI drive is often replayed from inside it (`sunrig replay .`), whose name is "".
    progress = Progress(f"replay {Path(log_path).resolve().name}", enabled=None if not args.quiet else False)
    frames = paced(source) if args.realtime else source
    errors = []
    interrupted = False
    try:
        # Paced, each frame is estimated as it arrives; unpaced, frames are encoded in batches.
        batch = 1 if args.realtime else 8
        gate = ExposureGate(max_covered_share=args.max_covered_share)
        for n, results in enumerate(estimate_stream(frames, estimator, policy, stats=stats, encode_batch=batch,
                                                    exposure_gate=gate), 1):
            est = results[args.aggregator]
            if est.error_rad is not None:
                errors.append(est.error_rad)
            for p in pubs:
                p.publish(est)
            progress.update(n, f"frames {stats.frames}")
    except KeyboardInterrupt:
        interrupted = True  # what was replayed is written: say how far it got, as eval does
    finally:
        _close_all(pubs, args.stop)
    summary = f"{stats.frames} frames, {stats.windows - stats.windows_failed} estimates"
    if interrupted:
        summary = f"interrupted after {summary}"
    if stats.frames_without_heading:
        summary += f", {stats.frames_without_heading} frames without heading skipped"
    if stats.frames_bad_exposure:
        summary += f", {stats.frames_bad_exposure} frames too dark, bright, flat or covered to show the sun skipped"
    if stats.frames_out_of_order:
        summary += f", {stats.frames_out_of_order} frames older than the one before skipped"
    if stats.clock_jumps:
        summary += f", {stats.clock_jumps} clock jumps (windows started again)"
    if stats.windows_failed:
        summary += f", {stats.windows_failed} windows failed"
    if errors:
        summary += f", mean error {math.degrees(sum(errors) / len(errors)):.2f} deg"
    if getattr(source, "truncated", False):
        summary += " (log truncated: replayed up to its last complete chunk)"
    if not args.quiet:
        progress.close(summary)
    from rig.publishers import publisher_name

    lost = _report_output_losses({publisher_name(p): p.stats() for p in pubs})  # below the progress line
    if interrupted:
        return args.stop.exit_code()  # as for any Ctrl-C, with the work so far written
    if not stats.frames:  # every image corrupt, or none recorded: not a replay that worked
        print(f"sunrig: error: {log_path}: no frame of it could be read (the warnings above say why); "
              "replay another log, or re-record this one", file=sys.stderr)
        return EXIT_USER_ERROR
    if stats.windows and stats.windows_failed == stats.windows:  # frames, yet not one answer
        print(f"sunrig: error: {log_path}: every one of its {stats.windows} windows failed (the warnings above "
              "say why); check the model (--model) or replay another log", file=sys.stderr)
        return EXIT_USER_ERROR
    if not stats.windows:  # frames, yet none fit for a window: say which kind of frame it lacks
        why = (f"{stats.frames_without_heading} of its {stats.frames} frames have no heading; record with "
               "a heading source (--heading)" if stats.frames_without_heading else
               f"{stats.frames_bad_exposure} of its {stats.frames} frames are too dark, bright, flat or covered "
               "to show the sun" if stats.frames_bad_exposure else f"none of its {stats.frames} frames made a window")
        print(f"sunrig: error: {log_path}: no estimate: {why}", file=sys.stderr)
        return EXIT_USER_ERROR
    return lost


def _effective_config(args: argparse.Namespace) -> dict:
    from rig.config import load_config, override

    cfg = load_config(args.config)
    flags = {
        "source.camera": getattr(args, "camera", None),
        "source.heading": getattr(args, "heading", None),
        "estimator.model": getattr(args, "model", None),
        "estimator.aggregator": getattr(args, "aggregator", None),
        "output.serial": getattr(args, "serial", None),
        "output.baud": getattr(args, "baud", None),
        "output.format": getattr(args, "format", None),
        "output.jsonl": getattr(args, "jsonl", None),
        "output.record": getattr(args, "record", None),
        "output.record_frames": True if getattr(args, "record_frames", False) else None,
        "output.record_overwrite": True if getattr(args, "record_overwrite", False) else None,
        "rig.realtime": False if getattr(args, "fast", False) else None,
        **{f"source.{name}": getattr(args, name, None)
           for name in ("calibration", "hfov_deg", "width", "height", "fps", "max_gap_s", "max_age_s",
                        "heading_latency_s", "declination_deg")},
        "source.baud": getattr(args, "source_baud", None),
    }
    return override(cfg, flags)


def _source_options(cfg: dict):
    """The [source] options of the effective configuration as drivers.sources.SourceOptions;
    zero, empty and nan mean "not set" (TOML has no null)."""

    from drivers.sources import SourceOptions

    src = cfg["source"]
    fields = {name: src[name] for name in ("calibration", "hfov_deg", "width", "height", "fps", "baud",
                                            "max_gap_s", "max_age_s", "heading_latency_s", "declination_deg")}
    unset = [k for k, v in fields.items()
             if k in ("calibration", "hfov_deg", "width", "height", "fps", "declination_deg")
             and (v in ("", 0, 0.0) or (isinstance(v, float) and math.isnan(v)))]
    for k in unset:
        del fields[k]
    return SourceOptions(**fields)


def _spec_files(camera: str, heading: str) -> list[Path]:
    """The local files that the sources read (``file:LOG``, ``opencv:VIDEO``, ``nmea:CAPTURE``)."""
    from drivers.sources import parse_camera, parse_heading

    specs = (parse_camera(camera), parse_heading(heading))  # a bad spec fails here as it would at the open
    return [Path(s.target) for s in specs if s.kind in ("file", "opencv", "nmea") and Path(s.target).is_file()]


def _refuse_overwriting(inputs: list[Path], **outputs: str | None) -> None:
    """An output that is one of the inputs would be truncated before a frame of it is read, and
    two outputs on one path would leave only the one written last."""
    seen: dict[str, str] = {}
    for flag, out in outputs.items():
        if not out or out == "-":
            continue
        where = os.path.realpath(out)
        if where in seen:
            raise SunrigError(f"--{seen[where].replace('_', '-')} and --{flag.replace('_', '-')} are both {out}; "
                              "one would overwrite the other: pass two paths")
        seen[where] = flag
    for flag, out in outputs.items():
        if not out or out == "-" or not Path(out).exists():
            continue
        for src in inputs:
            if src.exists() and os.path.samefile(out, src):
                raise SunrigError(f"--{flag.replace('_', '-')} {out} is the input being read; writing it would "
                                  "destroy it: pass another path")


def _check_writable(flag: str, path: str | None, suffixes: tuple[str, ...] = ()) -> None:
    """Fail before minutes of work, not after, when an output cannot be written there."""
    if not path or path == "-":
        return
    out = Path(path)
    if suffixes and out.suffix.lower() not in suffixes:
        raise SunrigError(f"{flag} {path}: expected a {' or '.join(suffixes)} file name")
    folder = out.parent
    if out.is_dir() or not folder.is_dir() or not os.access(folder, os.W_OK):
        raise SunrigError(f"{flag} {path}: cannot write there; check the folder exists and is writable")
    from rig.files import check_can_write

    try:  # by writing: os.access says yes to root for any folder, /proc too
        check_can_write(out)
    except OSError as exc:
        raise SunrigError(f"{flag} {path}: cannot write there ({exc.strerror}); check the folder exists and is "
                          "writable") from None


def _open_camera(spec: str, heading: str, options=None):
    """A live source from ``--camera`` and ``--heading`` (drivers.sources; docs/drivers.md)."""
    from drivers.sources import open_source

    return open_source(spec, heading, options=options)


# How a live command's recording errors name its options: the path came from --record, or from
# the config file ([output] record), which demo reads too.
_RECORD_FLAG_WORDS = ("--record", "--record-overwrite")
_RECORD_CONFIG_WORDS = ("[output] record", "set [output] record_overwrite = true")


def _check_live_outputs(cfg: dict, inputs: list[Path], record_words: tuple[str, str]) -> None:
    """Before any device opens or the model loads: no output may write over an input it reads
    (``inputs``), nor a recording over an existing file."""
    out = cfg["output"]
    _refuse_overwriting(inputs, jsonl=out["jsonl"], record=out["record"])
    if out["record"]:
        from rig.recorder import check_recording_path

        with _recording_refusals(*record_words):
            check_recording_path(out["record"], overwrite=out["record_overwrite"])


def _rig_config(r: dict, *, live_camera: bool):
    """The pipeline's RigConfig from the ``[rig]`` table. A live camera is never paced (``realtime``
    paces a recording: a camera's frame that came late once made the pace start again from it,
    and hold every later frame as late, for the rest of the run), and its frames are as old as
    their stamps on the rig's clock say (``live_clock``)."""
    from rig.exposure import ExposureGate
    from rig.pipeline import RigConfig

    return RigConfig(queue_size=r["queue_size"], ring_capacity=r["ring_capacity"],
                     ring_max_age_s=r["ring_max_age_s"], status_every_s=r["status_every_s"],
                     max_latency_s=r["max_latency_s"], realtime=r["realtime"] and not live_camera,
                     live_clock=live_camera, exposure_gate=ExposureGate(max_covered_share=r["max_covered_share"]))


def _live(cfg: dict, source, *, stop: StopSignals, nmea_stdout: bool, quiet: bool, live_camera: bool,
          record_words: tuple[str, str] = _RECORD_CONFIG_WORDS) -> int:
    """The live rig on ``source``; its outputs were checked (:func:`_check_live_outputs`).
    ``stop``: the command's stop signals; ``live_camera``: a camera, not a recording (a ``file:``
    log or a video file); ``record_words``: how errors name the recording's options, as there."""
    from estimator.estimator import SunEstimator
    from rig.config import check_window_fits
    from rig.pipeline import RigPipeline
    from rig.window import SpreadWindowPolicy

    model = _load_model(cfg["estimator"]["model"], stop)
    estimator = SunEstimator(model, aggregator=cfg["estimator"]["aggregator"], seed=cfg["estimator"]["seed"])
    check_window_fits(cfg, estimator.frames_per_window)
    policy = SpreadWindowPolicy(n_frames=estimator.frames_per_window, span_s=cfg["window"]["span_s"],
                                yaw_scale_rad=math.radians(cfg["window"]["yaw_scale_deg"]))
    # Checked before the outputs open: opening truncates an existing JSONL file or recording.
    rig_cfg = _rig_config(cfg["rig"], live_camera=live_camera)
    from rig.recorder import RecorderPublisher

    status_row = StatusRow(sys.stderr)  # on a terminal one row rewritten in place; in a log, a line each time

    def status(line: str) -> None:
        if not quiet:
            status_row.show(_status_text(line, source))

    out = cfg["output"]
    recorder: RecorderPublisher | None = None
    with _recording_refusals(*record_words):  # the file is made now: one may have appeared since the check
        pubs = _publishers(serial=out["serial"] or None, baud=out["baud"], fmt=out["format"],
                           jsonl=out["jsonl"] or None, rule=estimator.status_rule(),
                           record=out["record"] or None, record_overwrite=out["record_overwrite"],
                           record_frames=out["record_frames"], nmea_stdout=nmea_stdout, live=True, stop=stop)
    # From here every output is open: a stop at any point after closes them (a SIGTERM while the
    # pipeline was being built once left a 0-byte recording, never finished nor discarded).
    ran = False
    try:
        recorder = next((p for p in pubs if isinstance(p, RecorderPublisher)), None)
        pipe = RigPipeline(source, estimator, policy, pubs, config=rig_cfg, on_status=status,
                           on_frame=recorder.record_frame if recorder is not None else None)
        stats = pipe.run()  # ends by itself when every output's reader has gone (`| head`)
        ran = True
    finally:
        try:
            _close_all(pubs, stop)
        except KeyboardInterrupt:  # quit at once (rig/stopping.py): say what that cost
            if recorder is not None and not recorder.finished:
                print(f"sunrig: quit before the recording {recorder.path} was finished; its complete chunks "
                      "still replay", file=sys.stderr)
            raise
        if not ran:  # stopped (or failed) before the pipeline ran: no empty recording left behind
            _discard_empty_recording(recorder)
    # What the outputs wrote once closed: a background writer still at work when the run ended
    # was reported "0 written" (exit 2, "wrote none") of a file that held estimates.
    pipe.collect_publisher_stats()
    if not quiet:
        status_row.end()
        print(f"sunrig: done: {stats.status_line(stats.ended_s)}", file=sys.stderr)
        # The status line counts frames without heading, not why. (demo's source is a log: no devices.)
        source_stats = getattr(source, "stats", None)
        details = _source_summary(source_stats()) if callable(source_stats) else ""
        if details:
            print(f"sunrig: source: {details}", file=sys.stderr)
    full = recorder.disk_full if recorder is not None else None
    if (recorder is not None and recorder.finished and full is None and not _discard_empty_recording(recorder)
            and not quiet):
        print(f"sunrig: recorded to {recorder.path}", file=sys.stderr)  # {start} made its name
    if stats.frames_captured == 0 and not stop.requested:
        # The source ended without one frame (a log none of whose frames could be read, a camera
        # that gave up at once): not a run that worked, as replay and record say of it too.
        raise SunrigError("the source gave no frame (the warnings above say why); check the camera and its "
                          "cable, or the video file or log (docs/drivers.md)")
    if recorder is not None and not recorder.finished:
        why = (f"a write to its disk did not return in {recorder.join_timeout_s:g} s: a disk that stopped answering?"
               if recorder.stuck else "closing it failed, as said above")
        print(f"sunrig: error: the recording {recorder.path} is unfinished ({why}); its complete chunks "
              f"still replay (sunrig replay {recorder.path})", file=sys.stderr)
        return EXIT_USER_ERROR
    if recorder is not None and full is not None:
        from rig.publishers import publisher_name

        # Its own words for its losses: when, what it holds, what to do; and frames, not "estimates".
        others = {k: v for k, v in stats.publishers.items() if k != publisher_name(recorder)}
        return max(_report_disk_full(recorder, full), _report_output_losses(others))
    return _report_output_losses(stats.publishers)


def _n(k: int, what: str) -> str:
    return f"{k} {what}" + ("" if k == 1 else "s")


def _counted(frames: int, estimates: int, with_frames: bool) -> str:
    return f"{_n(frames, 'frame')} and {_n(estimates, 'estimate')}" if with_frames else _n(estimates, "estimate")


def _report_disk_full(recorder: RecorderPublisher, full: DiskFull) -> int:
    """The end of a run whose recording's disk filled. The serial output, the rig's job, went on
    (docs/deploy.md, "On the road"): a recording that keeps part of the run is a warning, and the
    run exits 0 as it would have; one that got nothing is exit 2, as any output that wrote nothing
    (:func:`_report_output_losses`), and no file is left of it."""
    with_frames = recorder.record_frames
    lost = _counted(full.frames_lost, full.estimates_lost, with_frames)
    again = f"{full.remedy(recorder.folder)}, and the next start records again"
    if full.removed:
        lost_too = f", and {lost} were not recorded" if full.frames_lost or full.estimates_lost else ""
        print(f"sunrig: error: nothing could be recorded to {recorder.path}: {full.cause}, so no file is "
              f"kept{lost_too}; {again}", file=sys.stderr)
        return EXIT_USER_ERROR
    kept = _counted(full.frames_recorded, full.estimates_recorded, with_frames)
    logging.getLogger(__name__).warning(
        "the recording %s ends at %s: %s; it keeps the %s before, and %s from then on were not recorded; %s",
        recorder.path, f"{full.since_utc:%H:%M:%S} UTC", full.cause, kept, lost, again)
    return 0


def _discard_empty_recording(recorder: RecorderPublisher | None) -> bool:
    """Remove a finished recording that got nothing, saying so; True when it was removed."""
    from rig.recorder import recording_name

    if recorder is None or not recorder.discard_if_empty():
        return False
    print(f"sunrig: nothing was recorded, so {recording_name(recorder.path)} is not kept", file=sys.stderr)
    return True


def _report_output_losses(publishers: dict[str, dict]) -> int:
    """One line per output that failed to write estimates or dropped some (by name, its
    ``stats()``); exit 2 if one wrote none at all (a full disk, a dead link): the run went on for
    the other outputs, but its user must know."""
    from rig.pipeline import publisher_losses

    code = 0
    for name, st in publishers.items():
        dropped, failed = publisher_losses([st])  # as the status line counts them
        if not failed and not dropped:
            continue
        written = int(st.get("written") or 0)
        # Still waiting when the output closed (its port gone): counted, so the line adds up to
        # what was published.
        unsent = int(st.get("pending") or 0) + int(st.get("in_flight") or 0)
        tail = f"{written} written" + (f", {unsent} unsent at the end" if unsent else "")
        if failed:
            print(f"sunrig: {name}: {failed} estimates failed to write, {tail} "
                  f"(last error: {st.get('last_error') or 'see the log above'})", file=sys.stderr)
        if dropped:
            # A port that failed (unplugged, or closed at the end) drops as a stalled reader does;
            # the counters cannot tell which drop was which, so a controller's engineer is not sent
            # to debug a read loop when the cable was out.
            port_trouble = failed or st.get("reopens") or st.get("port_open") is False
            why = "while its port was failing or its reader did not keep up" if port_trouble else \
                "because its reader did not keep up"
            print(f"sunrig: {name}: {dropped} estimates dropped {why}, {tail}", file=sys.stderr)
        if written == 0:
            code = EXIT_USER_ERROR
    return code


def cmd_run(args: argparse.Namespace) -> int:
    from drivers.sources import is_recording

    cfg = _effective_config(args)
    words = _RECORD_FLAG_WORDS if args.record is not None else _RECORD_CONFIG_WORDS
    _check_live_outputs(cfg, _spec_files(cfg["source"]["camera"], cfg["source"]["heading"]), words)
    source = _open_camera(cfg["source"]["camera"], cfg["source"]["heading"], _source_options(cfg))
    if not (cfg["output"]["serial"] or cfg["output"]["jsonl"] or cfg["output"]["record"]):
        # Fine for bring-up (the status line shows camera, heading and rate), but a rig whose
        # config lost its [output] would otherwise run for hours telling no one. Said once the
        # sources are open, so that a bad source stays a one-line error.
        logging.getLogger(__name__).warning("no output: estimates are made and dropped; pass --serial PORT, "
                                            "--jsonl PATH|- or --record OUT.mcap (or set [output] in --config)")
    try:
        return _live(cfg, source, stop=args.stop, nmea_stdout=False, quiet=args.quiet,
                     live_camera=not is_recording(source.camera), record_words=words)
    finally:
        source.close()  # release the devices: the rig only iterates its source


def cmd_record(args: argparse.Namespace) -> int:
    """Live sources to a native log: frames with heading, GNSS fix and UTC (nmea:), intrinsics.

    Ctrl-C (or SIGTERM, SIGHUP) ends the recording, and the log is finished (summary and index);
    one while a frame (or the summary) is being written lets that write finish first (rig.stopping).
    """
    from drivers.sources import is_recording
    from rig.recorder import (
        CHUNK_EVERY_S,
        Recording,
        check_recording_path,
        discard_if_empty,
        open_recording,
        recording_folder,
        recording_name,
    )

    cfg = _effective_config(args)
    _refuse_overwriting(_spec_files(cfg["source"]["camera"], cfg["source"]["heading"]), out=args.out)
    with _recording_refusals("--out", "--overwrite"):
        check_recording_path(args.out, overwrite=args.overwrite)
    # The sources first: a wrong camera or port fails before the output file is created.
    source = _open_camera(cfg["source"]["camera"], cfg["source"]["heading"], _source_options(cfg))
    stop = args.stop
    quiet = args.quiet
    status_row = StatusRow(sys.stderr)  # on a terminal one row rewritten in place; in a log, a line each 5 s
    n = n_heading = 0
    start = time.monotonic()
    next_status = start + 5.0
    interrupted = False
    # A log or a video file is read as fast as it can be: its own time, not the wall clock, says how
    # much of it --seconds keeps, and no wall-clock backstop cuts a slow re-recording (visual
    # odometry) short.
    replayed = is_recording(source.camera)
    first_t_s: float | None = None
    # A backstop for --seconds: a camera that stops sending frames must not keep the recording open.
    deadline = (threading.Timer(args.seconds + 2.0, source.stop)
                if args.seconds is not None and not replayed else None)
    if deadline is not None:
        deadline.daemon = True
        deadline.start()
    writer = None
    try:
        with _recording_refusals("--out", "--overwrite"):
            # Made now, after the sources: a wrong camera or port leaves no file.
            writer = open_recording(args.out, start_utc=datetime.now(UTC), overwrite=args.overwrite)
        out = writer.path
        # A full disk ends it at its last complete chunk; a slow camera's chunk ends within CHUNK_EVERY_S.
        recording = Recording(writer, chunk_every_s=CHUNK_EVERY_S)
        try:
            for frame in source:
                if replayed and args.seconds is not None:
                    first_t_s = frame.t_mono_s if first_t_s is None else first_t_s
                    if frame.t_mono_s - first_t_s > args.seconds:
                        break
                with stop.finishing():  # a frame is written whole or not at all
                    if not recording.write_frame(frame, jpeg_quality=args.jpeg_quality):
                        break  # the disk is full: said below
                n += 1
                n_heading += frame.attitude is not None
                now = time.monotonic()
                if not quiet and (status_row.tty or now >= next_status):
                    status_row.show(f"record: {n} frames ({n_heading} with heading) in {now - start:.1f} s")
                    if not status_row.tty:
                        next_status = now + 5.0
                if stop.requested:  # held while the frame was written
                    break
                if (args.frames is not None and n >= args.frames) or (
                        args.seconds is not None and not replayed and now - start >= args.seconds):
                    break
        except KeyboardInterrupt:
            interrupted = True  # Ctrl-C (or SIGTERM from a service manager) is how a live recording ends
        finally:
            with stop.finishing():  # a stop signal now must not cut the summary short
                recording.close()
    except Exception:
        # The source failed before its first frame (a calibration of another resolution, found on
        # that frame): its error says what to do, and an empty log left behind would refuse the
        # corrected command as a recording that exists.
        if writer is not None and discard_if_empty(writer):
            print(f"sunrig: nothing was recorded, so {recording_name(writer.path)} is not kept", file=sys.stderr)
        raise
    finally:
        if deadline is not None:
            deadline.cancel()
        source.close()
    full = recording.disk_full
    if full is not None:
        status_row.end()  # below the progress line, not over it
        lost = _n(full.frames_lost, "frame")
        folder = recording_folder(out) if out is not None else "its folder"  # (open_recording's writer has a path)
        if full.removed:
            lost_too = f", and its {lost} were not recorded" if full.frames_lost else ""
            raise SunrigError(f"record: nothing could be recorded to {out}: {full.cause}, so no file is "
                              f"kept{lost_too}; {full.remedy(folder)} or pass another --out")
        raise SunrigError(f"record: {out} ends at {full.since_utc:%H:%M:%S} UTC: {full.cause}; it keeps the "
                          f"{_n(full.frames_recorded, 'frame')} before (sunrig replay {out}), and {lost} from then "
                          f"on were not recorded; {full.remedy(folder)} or pass another --out")
    if discard_if_empty(writer):
        said = f"record: no frame came in {time.monotonic() - start:.1f} s, so {recording_name(out)} is not kept"
        if interrupted or stop.requested:  # stopped as a service is: not a failure of the command
            print(f"{said} (stopped by {stop.by or 'Ctrl-C'})", file=sys.stderr)
            return 0
        raise SunrigError(f"{said}; check the camera and its cable (docs/drivers.md)")
    if not quiet:
        status_row.end()
        summary = f"{n} frames ({n_heading} with heading) in {time.monotonic() - start:.1f} s to {out}"
        if interrupted or stop.requested:
            summary += f" (stopped by {stop.by or 'Ctrl-C'}; the log is complete)"
        details = _source_summary(source.stats())
        if details:
            summary += f"; {details}"
        print(f"record: {summary}", file=sys.stderr)
    return 0


def _status_text(line: str, source: object) -> str:
    """The rig's status line with its source's losses so far (camera drops and reconnects, frames
    without heading and why), which the pipeline's own counters do not see."""
    source_stats = getattr(source, "stats", None)
    details = _source_summary(source_stats()) if callable(source_stats) else ""
    return f"sunrig: {line} | source: {details}" if details else f"sunrig: {line}"


def _source_summary(stats: dict) -> str:
    """The counters worth a user's attention: drops, read failures, frames without heading and why."""
    parts = []
    camera = stats.get("camera") or {}
    for key in ("dropped", "frames_dropped_consumer", "frames_dropped_device", "read_failures", "reconnects",
                "device_lost", "bad_frames", "open_failures", "stalls"):
        if camera.get(key):
            parts.append(f"camera {key.replace('_', ' ')} {camera[key]}")
    if camera.get("repeated"):  # an OpenCV camera's frozen driver: its repeats are dropped, not used
        parts.append(f"camera repeated frames dropped {camera['repeated']}")
    # An OAK attaches its own IMU's heading: the frames it gave none, by why (drivers/oak.py).
    for key, n in camera.items():
        if key.startswith("no_heading_") and n:
            parts.append(f"camera frames without heading ({key.removeprefix('no_heading_').replace('_', ' ')}) {n}")
    # imu_mode gyro: the bias learned while standing still holds the heading (docs/oak.md); none
    # learned, it drifts by the gyro's whole bias.
    imu = camera.get("imu_counts") or {}
    if imu.get("gyro_bias_learned"):
        parts.append(f"gyro bias learned {_n(imu['gyro_bias_learned'], 'time')} "
                     f"({imu.get('gyro_bias_heading_deg_s', 0.0):+.2f} deg/s of heading)")
    if imu.get("gyro_bias_refused"):
        parts.append(f"gyro still stretches refused as too fast a bias {imu['gyro_bias_refused']}")
    pairing = stats.get("pairing") or {}
    for key in ("gap", "before", "after", "stale", "mixed", "ahead", "unconfirmed", "overflow"):
        if pairing.get(key):
            parts.append(f"heading {key} {pairing[key]}")
    if pairing.get("glitch"):  # samples, not frames (drivers/pairing.py): their frames count under gap
        parts.append(f"heading samples left out as glitches {pairing['glitch']}")
    gnss = stats.get("gnss") or {}  # why a heading port gave no headings: its bytes, as the framer saw them
    for key in ("bad_checksum", "truncated", "overlong", "malformed", "garbage_bytes", "bad_fields", "no_data",
                "read_errors", "reopens", "suspends", "stale_bytes"):
        if gnss.get(key):
            parts.append(f"heading port {key.replace('_', ' ')} {gnss[key]}")
    vo = stats.get("visual_odometry") or {}
    if vo.get("lost"):
        parts.append(f"visual odometry lost {vo['lost']} of {vo['frames']} frames")
    # Each new zero (docs/drivers.md) refills the windows: what a user sees as a stretch of partial ones.
    new_zeros = sum(vo.get(key, 0) for key in ("gaps", "uncarried", "restarts"))
    if new_zeros:
        parts.append(f"visual odometry started {new_zeros} new heading zero{'s' if new_zeros > 1 else ''}")
    if vo.get("repeated"):
        parts.append(f"camera repeated {vo['repeated']} frames")
    return ", ".join(parts)


def cmd_demo(args: argparse.Namespace) -> int:
    from replay.sources import demo_log, open_frames

    cfg = _effective_config(args)  # --fast, when given, unsets [rig] realtime there; not given, the file's stands
    cfg["rig"]["status_every_s"] = min(cfg["rig"]["status_every_s"], 1.0)
    out = cfg["output"]
    if not out["serial"]:  # stdout carries the NMEA text
        if out["format"] != "nmea":
            raise SunrigError(f"--format {out['format']} needs --serial PORT: without a port the sentences go to "
                              "stdout as NMEA text")
        if out["jsonl"] == "-":
            raise SunrigError("--jsonl - would mix JSON lines into the NMEA text on stdout: pass --jsonl FILE, "
                              "or --serial PORT")
    log_path = demo_log()
    _check_live_outputs(cfg, [log_path], _RECORD_CONFIG_WORDS)
    return _live(cfg, open_frames(log_path), stop=args.stop, nmea_stdout=not cfg["output"]["serial"],
                 quiet=args.quiet, live_camera=False)


def cmd_config(args: argparse.Namespace) -> int:
    from drivers.sources import check_pair, parse_camera, parse_heading
    from rig.config import ConfigError, dump_toml

    cfg = _effective_config(args)
    camera, heading = cfg["source"]["camera"], cfg["source"]["heading"]
    if camera:  # unset: `run` asks for one
        # Needs no device, so checked here as boot would: a live camera left with the default
        # heading (a log's) is the usual first mistake in a service's config.
        try:
            check_pair(parse_camera(camera), parse_heading(heading))
        except SunrigError as exc:
            where = f"{args.config}: " if args.config else ""
            raise ConfigError(f"{where}[source] camera {camera} with heading {heading}: {exc}") from None
    print(dump_toml(cfg), end="")
    return 0


def _expand_logs(command: str, items: list[str]) -> list[Path]:
    """Log arguments: files, or folders whose *.mcap files are taken in name order. A folder
    with none is taken as a KITTI drive, unless it is none (:func:`_refuse_folder_without_logs`).
    A log named again (a folder and a log in it, overlapping globs, another spelling of its path)
    is taken once, with a warning: read twice, its windows weighed double in eval's every figure
    and in training."""
    paths: list[Path] = []
    for item in items:
        p = Path(item)
        logs = sorted(p.glob("*.mcap")) if p.is_dir() else []
        if logs:
            paths.extend(logs)
        else:
            if p.is_dir():
                _refuse_folder_without_logs(p)
            paths.append(p)
    first_by_file: dict[Path, Path] = {}
    for path in paths:
        first = first_by_file.setdefault(path.resolve(), path)
        if first is not path:
            again = "" if first == path else f" as {first}"
            logging.getLogger(__name__).warning("%s: %s: named before%s; read once", command, path, again)
    return list(first_by_file.values())


def _refuse_folder_without_logs(folder: Path) -> None:
    """Raise LogError for a folder given as logs that holds no .mcap log and is not a KITTI drive
    (nor a date folder of drives), saying what it holds instead: a recordings folder still empty
    was told it is "not a KITTI raw drive". A KITTI folder is left to its reader, whose errors
    name what a drive lacks."""
    # The reader's own test of a drive, so that the two cannot disagree.
    from replay.kitti import drive_folders, looks_like_drive
    from rig.errors import LogError

    if looks_like_drive(folder) or drive_folders(folder):
        return
    entries = sorted(folder.iterdir())
    if not entries:
        raise LogError(f"{folder}: no .mcap logs in this folder (it is empty); record or copy logs into it, "
                       "or pass another folder")
    nested = [e for e in entries if e.is_dir() and any(e.glob("*.mcap"))]
    if len(nested) == 1:
        raise LogError(f"{folder}: no .mcap logs in this folder, only in its subfolder {nested[0]}; "
                       "pass that folder")
    if nested:
        raise LogError(f"{folder}: no .mcap logs in this folder, only in its {len(nested)} subfolders "
                       f"({nested[0]} ...); pass those folders")
    names = [e.name + ("/" if e.is_dir() else "") for e in entries]
    held = ", ".join(names) if len(names) <= 3 else f"{len(names)} others: {', '.join(names[:3])}, ..."
    raise LogError(f"{folder}: no .mcap logs in this folder (only {held}) and not a KITTI drive; "
                   "pass .mcap logs, folders of them, or KITTI drive folders")


def _open_logs(command: str, paths: list[Path],
               utc_offset_h: float | None) -> tuple[list[tuple[Path, Iterable[Frame]]], list[str]]:
    """The logs at ``paths`` (as :func:`_expand_logs` gives them), each opened now so that a bad
    one fails before any work is done.

    A log that holds no frames (a recording cut off before its first frame, as a power cut at
    start-up leaves one) is left out with a warning: there is nothing in it to lose, and one such
    file must not stop the evaluation or training of a fleet's folder. Every other bad log is an
    error, and so are logs none of which holds frames. Returns the opened logs and the names of
    those left out."""
    from replay.sources import open_frames
    from rig.errors import EmptyLogError, LogError

    opened: list[tuple[Path, Iterable[Frame]]] = []
    empty: list[EmptyLogError] = []
    for path in paths:
        try:
            opened.append((path, open_frames(path, utc_offset_h=utc_offset_h)))
        except EmptyLogError as exc:
            empty.append(exc)
    if empty and not opened:
        if len(empty) == 1:
            raise empty[0]
        raise LogError(f"none of the {len(empty)} logs holds frames ({empty[0].name}: {empty[0].reason}, ...); "
                       "record again or pass other logs")
    for skipped in empty:
        logging.getLogger(__name__).warning("%s: left out %s: it holds no frames (%s)", command, skipped.name,
                                            skipped.reason)
    return opened, [skipped.name for skipped in empty]


def _aggregator_list(text: str) -> list[str]:
    """An argparse type: eval's comma-separated aggregators, each one the estimator has. Checked
    here, so that a typo names the flag before the logs are opened and the model loaded."""
    from estimator.estimator import AGGREGATORS

    names = text.split(",")
    unknown = [name for name in names if name not in AGGREGATORS]
    if unknown:
        listed = ", ".join(repr(name) for name in unknown)
        raise argparse.ArgumentTypeError(f"no aggregator{'s' if len(unknown) > 1 else ''} {listed}: pass a "
                                         f"comma-separated subset of {', '.join(AGGREGATORS)}")
    return list(dict.fromkeys(names))  # each once: "mean,mean" is the mean


def cmd_eval(args: argparse.Namespace) -> int:
    from estimator.estimator import AGGREGATORS, SunEstimator
    from estimator.evaluate import TAIL_DEG, TAIL_KEY, evaluate, plot_eval
    from rig.exposure import ExposureGate
    from rig.files import write_replacing
    from rig.window import SpreadWindowPolicy

    _check_writable("--json", args.json)
    _check_writable("--plot", args.plot, (".png", ".pdf", ".svg"))
    paths = _expand_logs("eval", args.logs)
    _refuse_overwriting(paths, json=args.json, plot=args.plot)  # first: it says the log is being read
    if args.json and Path(args.json).suffix.lower() == ".mcap":
        # `eval --json drives/*.mcap` took the first log for the JSON's path and wrote over it.
        raise SunrigError(f"--json {args.json}: that is a log's name (.mcap), not a JSON file's; pass the JSON "
                          "file's own path after --json (or - for stdout)")
    opened, left_out = _open_logs("eval", paths, args.utc_offset)
    sources = [(str(p), frames) for p, frames in opened]
    model = _load_model(args.model, args.stop)
    estimator = SunEstimator(model, seed=args.seed)
    policy = SpreadWindowPolicy(n_frames=estimator.frames_per_window, span_s=args.window_span_s)
    aggregators = args.aggregators or list(AGGREGATORS)
    # Logs are the unit with a known total (windows per log are known only once read): rate and time left.
    progress = Progress("eval", total=len(sources), unit="logs", enabled=None if not args.quiet else False)
    result = evaluate(sources, estimator, policy, aggregators=aggregators,
                      progress=lambda windows, logs: progress.update(logs, f"{windows} windows"),
                      exposure_gate=ExposureGate(max_covered_share=args.max_covered_share))
    summary = result.summary()
    summary["model"] = {"dir": str(model.model_dir), "id": model.model_id}
    summary["logs_left_out"] = left_out  # they hold no frames (warned about above)
    text = json.dumps(summary, indent=2)
    with args.stop.finishing():  # the work is done: a stop signal now must not lose its record
        if args.json and args.json != "-":
            # Whole or not at all: a full disk left an empty JSON where the results were to go.
            write_replacing(args.json, lambda tmp: tmp.write_text(text + "\n", encoding="utf-8"))
        else:
            print(text)
        # A chart of no window is no figure: the error below says why nothing was graded.
        if args.plot and result.window_logs:
            plot_eval(result, Path(args.plot))
    lines = [f"{name}: mean {s['mean_deg']:.2f} deg, median {s['median_deg']:.2f}, max {s['max_deg']:.1f}, "
             f"{s[TAIL_KEY]} of {s['n_windows']} windows over {TAIL_DEG:g} deg"
             for name, s in summary["aggregators"].items() if s["n_windows"]]
    if result.interrupted and not result.window_logs:
        lines.insert(0, "interrupted before any window was graded; the JSON holds what was counted, and no figure "
                        "was drawn")
    elif result.interrupted:
        lines.insert(0, f"interrupted after {len(result.window_logs)} windows in {len(result.logs)} logs begun; "
                        "the JSON and figures hold those")
    if not args.quiet:
        progress.close()  # the counter cleared, so that the warnings below start a line of their own
    if result.window_logs:  # (with none graded, the error below says why in one line)
        for log, why in result.logs_not_graded.items():
            logging.getLogger(__name__).warning("eval: %s: no window graded (%s); the figures are of the other logs",
                                                log, why)
    if not args.quiet and lines:
        print(f"eval: {'; '.join(lines)}", file=sys.stderr)
    if result.interrupted:
        return args.stop.exit_code()  # as for any Ctrl-C, but with the work so far written
    if not lines:  # an error, so said even with --quiet (which silences progress, not errors)
        if not result.frames:  # every image corrupt, or none recorded: no span or log length would help
            which = (f"{sources[0][0]}: no frame of it could be read" if len(sources) == 1 else
                     f"no frame of the {len(sources)} logs could be read")
            again = "another log, or re-record this one" if len(sources) == 1 else "other logs, or re-record these"
            print(f"sunrig: error: eval graded nothing: {which} (the warnings above say why); evaluate {again}",
                  file=sys.stderr)
            return EXIT_USER_ERROR
        if result.windows_failed:  # first: the warnings above say what the model did with the windows
            print(f"sunrig: error: eval graded nothing: {result.windows_failed} windows failed and none was "
                  "estimated (the warnings above say why); check the model (--model)", file=sys.stderr)
            return EXIT_USER_ERROR
        if result.frames_without_heading:  # frames with truth but no heading make no window to grade
            why = f"{result.frames_without_heading} of the {result.frames} frames have no heading"
        elif result.windows_without_truth:
            why = f"{result.windows_without_truth} windows had no true sun"
        elif result.frames_bad_exposure:
            why = f"{result.frames_bad_exposure} of the {result.frames} frames too dark, bright, flat or covered to use"
        else:  # short logs, or frames too far apart (a slow camera) for the span: not a log without truth
            print(f"sunrig: error: eval graded nothing: no log has {policy.n_frames} frames within "
                  f"--window-span-s {policy.span_s:g} s ({result.frames} frames in all); give longer logs, or "
                  "raise --window-span-s for a camera slower than "
                  f"{(policy.n_frames - 1) / policy.span_s:g} frames a second", file=sys.stderr)
            return EXIT_USER_ERROR
        print(f"sunrig: error: eval graded nothing: no full window with ground truth in these logs ({why}); "
              "evaluate logs from `sunrig synth`, KITTI drives, or recordings with GNSS time and position "
              "(docs/ground-truth.md)", file=sys.stderr)
        return EXIT_USER_ERROR
    return 0


def cmd_train(args: argparse.Namespace) -> int:
    from rig.errors import require_torch

    require_torch()
    if args.quiet:  # its INFO lines ("loaded 40 drives ...", "training in float32") are progress
        logging.getLogger("estimator").setLevel(logging.WARNING)
    from estimator.models import resolve_init_dir
    from estimator.recipe import command_line, data_fingerprint
    from estimator.train import TrainConfig, train

    if args.export_only:
        from estimator.train import export_checkpoint

        # Logs beside --export-only: a checkpoint from before training recorded its data's sun
        # elevations takes them from its logs (checked to be the run's by their fingerprint).
        opened, _ = _open_logs("train", _expand_logs("train", args.logs), args.utc_offset) if args.logs else ([], [])
        logs = [p for p, _ in opened]
        mirror = args.mirror_windows
        out = export_checkpoint(Path(args.out), Path(args.export_only), run_crops_per_frame=args.crops or 0,
                                export_command=command_line() if args.crops or logs or args.data_note
                                or mirror is not None else "",
                                log_paths=logs, data_note=args.data_note or "", run_mirror_windows=mirror)
        if not args.quiet:
            print(f"train: exported the checkpoint in {args.out} to {out}", file=sys.stderr)
        return 0
    if not args.logs:
        raise SunrigError("train: no logs given; pass native logs or folders of them")
    if args.mirror_windows is not None:
        raise SunrigError("train: --mirror-windows sets how an exported model runs; pass it with --export-only "
                          "once the run is done (a fine-tune keeps its --init model's)")
    # Opened now, so that a bad log fails before minutes of loading the others.
    opened, _ = _open_logs("train", _expand_logs("train", args.logs), args.utc_offset)
    paths = [p for p, _ in opened]
    cfg = TrainConfig(preset=args.preset, layers=args.layers, minutes=args.minutes, max_steps=args.steps,
                      batch_windows=args.batch, crops_per_frame=args.crops or 0, lr=args.lr,
                      crop_fov_deg=args.crop_fov,
                      hard_share=args.hard_share, mirror_share=args.mirror_share,
                      live_share=args.live_share, precision=args.precision,
                      tail_weight=args.tail_weight, tail_margin_deg=args.tail_margin,
                      ema_decay=args.ema_decay,
                      init=str(resolve_init_dir(args.init)) if args.init else "",
                      seed=args.seed, threads=args.threads,
                      command=command_line(),
                      data={"logs": len(paths), "fingerprint": data_fingerprint(paths),
                            "source": args.data_note or ""})
    enabled = None if not args.quiet else False
    loading = Progress("train: loading", unit="logs", enabled=enabled)
    steps: Progress | None = None

    finished = False

    def on_progress(p: dict) -> None:
        nonlocal steps, finished
        if p["phase"] == "resume":
            # The same command resumes a run (by design: a killed run loses nothing); say so, as
            # it continues a run rather than start one.
            if not args.quiet:
                print(f"train: resuming the run in {args.out} at step {p['step']} ({p['minutes']:.1f} min "
                      "trained); for a new run pass another --out", file=sys.stderr)
            return
        if p["phase"] == "finished":
            finished = True
            return
        if p["phase"] == "load":
            loading.total = p["total"]
            loading.update(p["done"])
            return
        if steps is None:
            # Created when the first step ends, so minutes of loading and a resumed run's earlier
            # steps stay out of the rate and the time left.
            loading.close()
            steps = Progress("train", unit="steps", enabled=enabled)
            steps.skip(p["start_step"])
        steps.total = p["total"]  # None until train() has timed enough steps to know
        budget = f" [{p['elapsed_s'] / 60:.0f}/{p['budget_s'] / 60:.0f} min]" if p["budget_s"] else ""
        steps.update(p["step"], f"loss {p['loss']:.3f} err {p['err_deg']:.1f} deg{budget}")

    from replay.sources import utc_offset_default

    with utc_offset_default(args.utc_offset):  # train() opens the logs itself
        out = train(paths, Path(args.out), cfg, progress=on_progress)
    (steps or loading).close()
    if not args.quiet:
        if finished:
            more = "--steps" if args.steps else "--minutes"
            print(f"train: the run in {out} already reached its end; nothing to train (pass a larger {more} to "
                  "train it further)", file=sys.stderr)
        else:
            print(f"train: model written to {out}", file=sys.stderr)
    return 0


def cmd_quantize(args: argparse.Namespace) -> int:
    from estimator.quantize import quantize_logs_model
    from estimator.recipe import command_line

    model = _load_model(args.model, args.stop)
    # Calibration reads images only: a KITTI drive's UTC offset (its true sun) does not matter here.
    opened, _ = _open_logs("quantize", _expand_logs("quantize", args.logs), 0.0)
    # Frames are the unit while the logs are read: how many they hold is known only once read.
    # Then ONNX Runtime runs the backbone over the crops (20 s for the paper's architecture on 2
    # cores), a line of its own that starts as the reading ends.
    enabled = None if not args.quiet else False
    reading = Progress("quantize: reading frames", unit="frames", enabled=enabled)
    running: Progress | None = None

    def backbone_runs(crops_done: int, crops: int) -> None:
        nonlocal running
        if running is None:
            reading.close()
            running = Progress("quantize: running the backbone", total=crops, unit="crops", enabled=enabled)
        running.update(crops_done)

    try:
        out = quantize_logs_model(model, opened, Path(args.out), n_crops=args.calibration_crops, seed=args.seed,
                                  command=command_line(), progress=reading.update,
                                  calibration_progress=backbone_runs)
    finally:
        reading.close()
        if running is not None:
            running.close()
    if not args.quiet:
        print(f"quantize: int8 model written to {out}; measure it with `sunrig eval LOG... --model {out}` before "
              "using it (docs/model.md, int8)", file=sys.stderr)
    return 0


def cmd_synth(args: argparse.Namespace) -> int:
    from replay.synthetic import write_synthetic_logs

    kept = 0

    def say_kept(n_kept: int) -> None:
        # Said before the render, which can take hours: a user who meant a fresh set (a reused
        # folder) learns at once that it is a resume, and how much of it is left.
        nonlocal kept
        kept = n_kept
        if kept and not args.quiet:
            print(f"synth: {kept} of the {args.drives} drives are in {args.out} from an earlier run: kept, "
                  f"rendering {args.drives - kept}", file=sys.stderr)

    paths = write_synthetic_logs(args.out, drives=args.drives, frames=args.frames, seed=args.seed,
                                 progress=not args.quiet, fps=args.fps, jobs=args.jobs,
                                 render_scale=args.render_scale, on_kept=say_kept)
    if not args.quiet:
        print(f"synth: {len(paths)} logs of {args.frames} frames in {args.out}"
              + (f" ({kept} kept from an earlier run)" if kept else ""), file=sys.stderr)
    return 0


def cmd_gnss(args: argparse.Namespace) -> int:
    """Bring-up of a GNSS compass / INS: print what it decodes, one JSON object per sentence."""
    from drivers.gnss import GnssReader
    from rig.publishers import JsonlPublisher

    _refuse_overwriting([Path(args.source)], jsonl=args.jsonl)  # a capture file read and written at once
    # The source first: a wrong path fails before an output file is created.
    reader = GnssReader(args.source, baudrate=args.baud, events=4096, require_checksum=args.require_checksum)
    out = None
    # A capture file is read to its end, as replay reads a log: one cut short by a stop is an
    # interrupted command (128 + the signal), where a live port's session ends that way (exit 0).
    capture = Path(args.source).is_file()
    interrupted = False
    try:
        out = JsonlPublisher(args.jsonl or "-")  # the same lines, flushes and write errors as replay's
        while True:
            done = reader.finished  # read first: every update queued before it is taken below
            updates = reader.get_events(timeout_s=0.5)
            for update in updates:
                out.publish(update)
            if done and not updates:
                break
    except KeyboardInterrupt:
        interrupted = capture  # Ctrl-C is how a live port session ends
    finally:
        reader.close()
        if out is not None:
            out.close()
    # None: Ctrl-C came while the output opened (a FIFO's open waits for its reader), so none was written.
    n_lines = out.stats()["written"] if out is not None else 0
    if reader.failure:
        raise RuntimeError(f"the GNSS reader thread failed: {reader.failure}")
    stats = reader.stats()
    if not args.quiet:
        dropped = {k: stats[k] for k in ("bad_checksum", "no_checksum", "truncated", "overlong", "malformed",
                                         "bad_fields", "no_data", "undated", "read_errors", "events_dropped",
                                         "suspends", "stale_bytes")
                   if stats[k]}
        summary = (f"{n_lines} updates from {stats['sentences']} sentences ({stats['headings']} headings, "
                   f"{stats['fixes']} fixes)")
        if dropped:
            summary += "; " + ", ".join(f"{k} {v}" for k, v in dropped.items())
        if stats["last_error"]:
            summary += f"; last error: {stats['last_error']}"
        if interrupted:
            summary += f" (stopped by {args.stop.by or 'Ctrl-C'} before the end of {args.source})"
        print(f"gnss: {summary}", file=sys.stderr)
    if interrupted:
        return args.stop.exit_code()
    if not stats["sentences"] and stats["bad_checksum"]:
        # Sentences came, all damaged: a noisy line or a wrong baud that happens to frame, not a wrong file.
        raise SunrigError(f"gnss: every sentence from {args.source} failed its checksum ({stats['bad_checksum']}); "
                          "check the wiring and the --baud rate, or the capture's integrity")
    if not stats["sentences"]:
        # Nothing that even looked like NMEA: the wrong file, baud rate or device, not a quiet success.
        raise SunrigError(f"gnss: no NMEA sentence from {args.source}; check it is the GNSS device or a "
                          "capture of its output (text lines starting with $), and the --baud rate")
    return 0


_MAX_CSV_LINE = 2**20  # characters: a row is a time and a few numbers


def _csv_lines(f, name: str):
    """The lines of ``f``, each read with a bound: a file that never ends a line (/dev/zero) was
    read whole into memory until the machine ran out of it."""
    for n in itertools.count(1):
        line = f.readline(_MAX_CSV_LINE + 1)
        if not line:
            return
        if len(line) > _MAX_CSV_LINE:
            raise SunrigError(f"{name} line {n}: over {_MAX_CSV_LINE // 2**20} MiB without a line end, which no row "
                              "time,lat,lon is; pass a CSV file of rows time,lat,lon with a header")
        yield line


def _csv_row_error(name: str, rows: list[list[str]], places: list[int], exc) -> SunrigError:
    """A rig.solar.RangeError about one row of a CSV, as one line naming the row (by its line)."""
    n = places[exc.index]
    return SunrigError(f"{name} line {n}: {exc} (row {','.join(rows[n - 1])[:60]!r})")


def cmd_sun(args: argparse.Namespace) -> int:
    """The sun's position by NREL's SPA for one time and place, or for each row of a CSV."""
    import csv

    import numpy as np

    from rig.solar import RangeError, parse_utc_iso, standard_pressure_hpa, sun_position, utc_column

    rows: list[list[str]] = []
    places: list[int] = []  # each time's line in the CSV
    if args.csv:
        if args.time or args.lat is not None or args.lon is not None:
            raise SunrigError("sun: give either --csv or --time/--lat/--lon, not both")
        name = "stdin" if args.csv == "-" else args.csv
        try:
            # utf-8-sig: "CSV UTF-8" from Excel starts with a byte order mark, which read as UTF-8
            # is a character before "time" that no message could show.
            f = sys.stdin if args.csv == "-" else open(args.csv, newline="", encoding="utf-8-sig")  # closed below
        except OSError as exc:
            raise SunrigError(f"sun: cannot read {args.csv}: {exc.strerror or exc}; pass a CSV file of rows "
                              "time,lat,lon with a header, or - for stdin") from None
        try:
            with f:
                rows = list(csv.reader(_csv_lines(f, name)))
        except UnicodeDecodeError as exc:
            raise SunrigError(f"{name}: not UTF-8 text (byte {exc.start}); save it as UTF-8 CSV") from None
        except (OSError, csv.Error) as exc:
            raise SunrigError(f"sun: cannot read {name} as CSV: {exc}") from None
        if rows and rows[0]:
            rows[0][0] = rows[0][0].removeprefix("\ufeff")  # stdin's, which no encoding argument reaches
        header = [h.strip().lower() for h in rows[0]] if rows else []
        if not {"time", "lat", "lon"} <= set(header):
            got = ",".join(header)
            raise SunrigError(f"{name} line 1: expected a header row with time,lat,lon (and optionally "
                              f"elevation_m), got {(got if got.isprintable() else repr(got)) or 'nothing'}")
        col = {h: i for i, h in enumerate(header)}

        def number(cells: dict[str, str], key: str) -> float:
            try:
                return float(cells[key])
            except ValueError:
                raise ValueError(f"{key}: expected a number, got {cells[key][:40]!r}") from None

        times, lat, lon, elev = [], [], [], []
        for n, row in enumerate(rows[1:], 2):
            if not any(cell.strip() for cell in row):
                continue
            try:
                cells = {h: row[i].strip() for h, i in col.items() if i < len(row)}
                times.append(parse_utc_iso(cells.get("time", "")))
                la, lo = number(cells, "lat"), number(cells, "lon")
                el = number(cells, "elevation_m") if cells.get("elevation_m") else args.elevation_m
            except KeyError as exc:  # a short row: say which column, not KeyError's repr
                raise SunrigError(f"{name} line {n}: no {exc.args[0]} column in this row "
                                  f"(row {','.join(row)[:60]!r}); give every row time,lat,lon") from None
            except (ValueError, SunrigError) as exc:
                raise SunrigError(f"{name} line {n}: {exc} (row {','.join(row)[:60]!r})") from None
            lat.append(la)
            lon.append(lo)
            elev.append(el)
            places.append(n)
        if not times:
            raise SunrigError(f"{name}: no rows after the header")
        try:
            utc = utc_column(times, [f"line {n}" for n in places])  # numpy promotes to the finest unit written
        except RangeError as exc:
            raise _csv_row_error(name, rows, places, exc) from None
    else:
        if not args.time or args.lat is None or args.lon is None:
            raise SunrigError("sun: give --time, --lat and --lon (or --csv FILE)")
        utc = np.array([parse_utc_iso(args.time)])
        lat, lon, elev = [args.lat], [args.lon], [args.elevation_m]
    if np.datetime_data(utc.dtype)[0] in ("D", "h", "m"):
        utc = utc.astype("datetime64[s]")  # so that the output says seconds and Z
    elev_arr = np.asarray(elev, dtype=np.float64)
    pressure = standard_pressure_hpa(elev_arr) if args.pressure_hpa is None else args.pressure_hpa
    try:
        pos = sun_position(utc, np.asarray(lat), np.asarray(lon), elev_arr, pressure_hpa=pressure,
                           temperature_c=args.temperature_c, delta_t_s=args.delta_t_s)
    except RangeError as exc:  # checked for all rows at once: say which row
        if not args.csv or exc.index is None:
            raise
        raise _csv_row_error(args.csv if args.csv != "-" else "stdin", rows, places, exc) from None
    iso = np.datetime_as_string(utc, timezone="UTC")
    for i in range(len(utc)):
        print(json.dumps({
            "utc": str(iso[i]), "lat_deg": float(lat[i]), "lon_deg": float(lon[i]), "elevation_m": float(elev[i]),
            "azimuth_deg": float(np.degrees(pos.azimuth_rad[i])),
            "elevation_deg": float(np.degrees(pos.elevation_rad[i])),
            "zenith_deg": float(np.degrees(pos.zenith_rad[i])),
            "enu": [round(float(x), 9) for x in pos.enu[i]],
            "delta_t_s": float(pos.delta_t_s[i]),
        }))
    return 0


def _source_flags(p: argparse.ArgumentParser) -> None:
    """--camera / --heading and the options of the sources (docs/drivers.md)."""
    p.add_argument("--camera", type=_source_spec, metavar="SOURCE",
                   help="oak[:ID], opencv:N, opencv:rtsp://..., opencv:VIDEO or file:LOG (a log through the live path)")
    p.add_argument("--heading", type=_source_spec, metavar="SOURCE",
                   help="oak-imu, nmea:PORT (GNSS compass / INS), visual (from the images, relative), none, "
                        "or log (a file: camera's own)")
    g = p.add_argument_group("source options")
    g.add_argument("--calibration", type=_path, metavar="FILE",
                   help="OpenCV calibration (YAML/JSON/XML: camera_matrix, image_width, image_height)")
    # Each flag takes its [source] option's type and range: 0 is "unset" as in the file, so a
    # flag can unset what a file set.
    g.add_argument("--hfov-deg", type=_config_type("source", "hfov_deg"), metavar="DEG",
                   help="or the camera's horizontal field of view (0: unset)")
    g.add_argument("--width", type=_config_type("source", "width"),
                   help="requested frame width (opencv device, oak; 0: its own)")
    g.add_argument("--height", type=_config_type("source", "height"),
                   help="requested frame height (opencv device, oak; 0: its own)")
    g.add_argument("--fps", type=_config_type("source", "fps"),
                   help="requested frame rate (opencv device, oak; 0: its own)")
    g.add_argument("--source-baud", type=_config_type("source", "baud"), metavar="BAUD",
                   help="baud rate of an nmea: port (default 115200)")
    g.add_argument("--max-gap-s", type=_config_type("source", "max_gap_s"), metavar="S",
                   help="nmea: no heading interpolated across a longer gap between samples (default 1.5)")
    g.add_argument("--max-age-s", type=_config_type("source", "max_age_s"), metavar="S",
                   help="nmea: a frame waits at most this long for the heading after it (default 1.5)")
    g.add_argument("--heading-latency-s", type=_config_type("source", "heading_latency_s"), metavar="S",
                   help="nmea: the heading device's output latency, subtracted from its times (default 0)")
    g.add_argument("--declination-deg", type=_config_type("source", "declination_deg"), metavar="DEG",
                   help="oak-imu: magnetic declination, east positive (makes the heading true north)")


def _output_flags(p: argparse.ArgumentParser, defaults: bool = True) -> None:
    p.add_argument("--serial", type=_path, metavar="PORT",
                   help="serial port or pyserial URL (socket://, loop://, spy://)")
    p.add_argument("--baud", type=_positive_int, default=115200 if defaults else None,
                   help="baud rate (default 115200)")
    p.add_argument("--format", choices=["nmea", "binary"], default="nmea" if defaults else None,
                   help="serial format (default nmea; see docs/protocol.md)")
    if not defaults:
        p.add_argument("--jsonl", type=_path, metavar="PATH|-", help="also write one JSON object per estimate here")


class _Parser(argparse.ArgumentParser):
    """argparse, with its errors in one line like every other error here: the usage block it
    prints first (5-12 lines) buried the line that says what is wrong. The subcommands' parsers
    are of this class too (argparse makes them of the main parser's)."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        # What argparse takes for a value although it starts with "-": it takes only plain negative
        # numbers (-5, -.5), so "--elevation-m -1e9" or "--time -1000-01-01T00:00Z" was "expected
        # one argument" (Python 3.14 takes -1e9 too). No option here starts with a minus and a
        # digit, so every such argument is a value. (An argparse attribute without a public way to
        # set it; tests/test_solar.py fails if a Python renames it.)
        self._negative_number_matcher = re.compile(r"^-\.?\d")

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    from rig.config import DEFAULTS

    parser = _Parser(
        prog="sunrig", description="Estimate the sun direction from a camera rig's images and heading."
    )
    parser.add_argument("--debug", action="store_true", help="show tracebacks and debug logs")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    # --debug after the subcommand too (`sunrig replay X --debug`), where people add it when an
    # error says "rerun with --debug"; SUPPRESS keeps a subcommand from resetting the main flag.
    debug = _Parser(add_help=False)
    debug.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS)

    p = sub.add_parser("replay", parents=[debug], help="run a recorded log through the estimator")
    p.add_argument("log", nargs="?", type=_path,
                   help="a native sunrig log (.mcap) or a KITTI raw drive folder; default: the bundled demo drive")
    p.add_argument("--jsonl", type=_path, metavar="PATH|-",
                   help="write one JSON object per estimate here (- for stdout)")
    p.add_argument("--model", type=_path, metavar="DIR", help="model folder (default: the shipped model)")
    p.add_argument("--aggregator", default="transformer", choices=["transformer", "mean", "meanshift", "single"],
                   help="how a window's crops become one answer (default transformer, the paper's)")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="crop sampling seed (default 0)")
    p.add_argument("--window-span-s", type=_positive_float, default=4.0, metavar="S",
                   help="choose each window's frames from the last S seconds (default 4)")
    p.add_argument("--max-covered-share", type=_share, default=DEFAULTS["rig"]["max_covered_share"], metavar="SHARE",
                   help="leave out frames more than this share of which is dark and flat, as behind a cap or a "
                        "visor (default %(default)s; 1: never; raise it for a camera that sees its own hood)")
    _output_flags(p)
    p.add_argument("--realtime", action="store_true", help="pace by the log's timestamps instead of full speed")
    p.add_argument("--utc-offset", type=_utc_offset_type, metavar="HOURS",
                   help="KITTI drives: hours their timestamps are ahead of UTC (default +2, CEST, with a warning); "
                        "native logs carry UTC and ignore it")
    p.add_argument("--quiet", action="store_true", help="no progress or summary on stderr")
    p.set_defaults(func=cmd_replay)

    p = sub.add_parser("run", parents=[debug], help="the live rig: camera and heading in, sun direction out")
    _source_flags(p)
    p.add_argument("--config", type=_path, metavar="FILE.toml", help="configuration file; flags override it")
    p.add_argument("--model", type=_path, metavar="DIR", help="model folder (default: the shipped model)")
    p.add_argument("--aggregator", choices=["transformer", "mean", "meanshift", "single"],
                   help="how a window's crops become one answer (default transformer, the paper's)")
    _output_flags(p, defaults=False)
    p.add_argument("--record", type=_path, metavar="OUT.mcap",
                   help="record estimates (and frames with --record-frames)")
    p.add_argument("--record-frames", action="store_true",
                   help="record the frames too (most of a log's size): a log that replays and trains")
    p.add_argument("--record-overwrite", action="store_true",
                   help="replace an existing --record file (by default it is refused; {start} in its name is "
                        "the UTC start time, for a new file per run)")
    p.add_argument("--fast", action="store_true",
                   help="do not pace a file: camera by its timestamps; as live, frames the estimator cannot keep "
                        "up with are dropped (sunrig replay estimates every frame)")
    p.add_argument("--quiet", action="store_true", help="no status lines on stderr")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("record", parents=[debug],
                       help="record live sources (frames, heading, GNSS, intrinsics) to a native log")
    _source_flags(p)
    p.add_argument("--out", required=True, type=_path, metavar="OUT.mcap",
                   help="the native log to write; {start} in the name is the UTC start time (20261123T031500Z). "
                        "An existing file is refused unless --overwrite")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--seconds", type=_positive_float, metavar="N",
                   help="stop after N seconds, of the recording's own time for a log or video file (default: Ctrl-C "
                        "or the end)")
    p.add_argument("--frames", type=_positive_int, metavar="N", help="stop after N frames")
    p.add_argument("--jpeg-quality", type=_int_in(1, 100), default=90, metavar="Q",
                   help="JPEG quality of the images, 1-100 (default 90)")
    p.add_argument("--config", type=_path, metavar="FILE.toml", help="configuration file ([source] camera, heading)")
    p.add_argument("--quiet", action="store_true", help="no progress or summary on stderr")
    p.set_defaults(func=cmd_record)

    p = sub.add_parser("demo", parents=[debug], help="the bundled drive through the live rig, in real time")
    p.add_argument("--config", type=_path, metavar="FILE.toml",
                   help="configuration file ([output], [rig], [estimator])")
    p.add_argument("--model", type=_path, metavar="DIR", help="model folder (default: the shipped model)")
    _output_flags(p, defaults=False)
    p.add_argument("--fast", action="store_true",
                   help="as fast as possible instead of real time (frames the estimator cannot keep up with "
                        "are dropped, as live)")
    p.add_argument("--quiet", action="store_true", help="no status lines on stderr")
    p.set_defaults(func=cmd_demo)

    p = sub.add_parser("config", parents=[debug], help="show the effective configuration")
    p.add_argument("--print", action="store_true", required=True, help="print it as TOML")
    p.add_argument("--config", type=_path, metavar="FILE.toml",
                   help="configuration file (default: the built-in defaults)")
    p.set_defaults(func=cmd_config)

    p = sub.add_parser("eval", parents=[debug], help="angular error of every aggregator over logs with ground truth")
    p.add_argument("logs", nargs="+", type=_path,
                   help="native logs (.mcap), folders of them, or KITTI raw drive folders")
    p.add_argument("--json", type=_path, metavar="OUT", help="write the summary here (default: stdout)")
    p.add_argument("--plot", type=_path, metavar="OUT.png", help="cumulative error curves (and OUT-tokens.png)")
    p.add_argument("--model", type=_path, metavar="DIR", help="model folder (default: the shipped model)")
    p.add_argument("--aggregators", type=_aggregator_list, metavar="A,B",
                   help="comma-separated subset (default: all)")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="crop sampling seed (default 0)")
    p.add_argument("--window-span-s", type=_positive_float, default=4.0, metavar="S",
                   help="choose each window's frames from the last S seconds (default 4)")
    p.add_argument("--max-covered-share", type=_share, default=DEFAULTS["rig"]["max_covered_share"], metavar="SHARE",
                   help="leave out frames more than this share of which is dark and flat, as behind a cap or a "
                        "visor (default %(default)s; 1: never; raise it for a camera that sees its own hood)")
    p.add_argument("--utc-offset", type=_utc_offset_type, metavar="HOURS",
                   help="KITTI drives: hours their timestamps are ahead of UTC (default +2, CEST, with a warning); "
                        "native logs carry UTC and ignore it")
    p.add_argument("--quiet", action="store_true", help="no progress or summary on stderr")
    p.set_defaults(func=cmd_eval)

    p = sub.add_parser("quantize", parents=[debug],
                       help="a model with an int8 backbone, calibrated on logs (needs sunrig[train])")
    p.add_argument("logs", nargs="+", type=_path,
                   help="native logs (.mcap), folders of them, or KITTI raw drive folders, "
                                           "like those the model will see; no ground truth needed")
    p.add_argument("--out", required=True, type=_path, metavar="MODEL_DIR", help="the int8 model's folder (a new one)")
    p.add_argument("--model", type=_path, metavar="DIR", help="the model to quantize (default: the shipped model)")
    p.add_argument("--calibration-crops", type=_positive_int, default=1024, metavar="N",
                   help="crops to calibrate the activations on, drawn evenly from the logs' frames (default 1024)")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="crop and frame sampling seed (default 0)")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_quantize)

    from estimator.contract import PAPER_CROP_FOV_DEG
    from estimator.recipe import TrainConfig  # no torch: the defaults below are the library's own

    recipe = TrainConfig()
    p = sub.add_parser("train", parents=[debug], help="train a model on logs with ground truth (needs sunrig[train])")
    p.add_argument("logs", nargs="*", type=_path,
                   help="native logs (.mcap), folders of them, or KITTI raw drive folders")
    p.add_argument("--out", required=True, type=_path, metavar="MODEL_DIR",
                   help="model folder; holds checkpoint.pt, and a run resumes from it")
    p.add_argument("--preset", default=recipe.preset,
                   help="network preset: fast (default, the 2-core CPU recipe of docs/model.md), light, "
                        "paper (ResNet18 at 224 px), tiny (for tests)")
    p.add_argument("--layers", type=_positive_int, default=recipe.layers, metavar="N",
                   help="transformer layers (default: the preset's, 4 for fast and the paper's); recorded in the "
                        "contract, so a fine-tune of such a model passes it too")
    p.add_argument("--minutes", type=_positive_float, default=recipe.minutes,
                   help=f"training time budget (default {recipe.minutes:g})")
    p.add_argument("--steps", type=_positive_int, default=0,
                   help="stop after this many steps instead of at the time budget")
    p.add_argument("--batch", type=_positive_int, default=recipe.batch_windows,
                   help=f"windows per step (default {recipe.batch_windows})")
    p.add_argument("--crops", type=_positive_int, metavar="N",
                   help="crops per frame, recorded in the contract and used at run time (default 4, the paper's; "
                        "a resume keeps its run's). With --export-only: the run-time count of the exported model")
    p.add_argument("--lr", type=_positive_float, default=recipe.lr, help=f"peak learning rate (default {recipe.lr:g})")
    p.add_argument("--crop-fov", type=_crop_fovs, default=recipe.crop_fov_deg, metavar="DEG[,DEG]",
                   help="horizontal angle a crop spans, recorded in the contract and used at run time; several "
                        "(e.g. 17.6,26) share each frame's crops among the angles (default: the --init model's, "
                        f"else the paper's {PAPER_CROP_FOV_DEG:.1f}; a resume keeps its run's)")
    p.add_argument("--hard-share", type=_float_in(0.0, 1.0, lo_included=True), default=recipe.hard_share,
                   help="share of windows drawn from drives in proportion to their running error "
                        f"(default {recipe.hard_share:g})")
    p.add_argument("--mirror-share", type=_float_in(0.0, 1.0, lo_included=True), default=recipe.mirror_share,
                   help="share of windows mirrored left to right, the sun's east and every heading with them "
                        f"(default {recipe.mirror_share:g}; 0 for the recipe before, which a run begun then "
                        "resumes with)")
    p.add_argument("--live-share", type=_float_in(0.0, 1.0, lo_included=True), default=recipe.live_share,
                   help="share of windows whose frames are those the rig would pick: the newest anywhere in the "
                        "drive, the others by the live window policy; the rest are random frames of the whole "
                        f"drive (default {recipe.live_share:g})")
    p.add_argument("--tail-weight", type=_float_in(0.0, math.inf, lo_included=True), default=recipe.tail_weight,
                   help="weight of an extra loss on each full window's estimate, the squared angle (rad) by which "
                        "it misses beyond --tail-margin; it aims training at the worst windows "
                        f"(default {recipe.tail_weight:g}: the paper's loss alone)")
    p.add_argument("--tail-margin", type=_float_in(0.0, 180.0, lo_included=True), default=recipe.tail_margin_deg,
                   metavar="DEG",
                   help=f"miss in deg beyond which --tail-weight counts (default {recipe.tail_margin_deg:g})")
    p.add_argument("--ema-decay", type=_float_in(0.0, 0.99999, lo_included=True), default=recipe.ema_decay,
                   metavar="DECAY",
                   help="export a moving average of the weights, each step weighing the old average by DECAY "
                        "(e.g. 0.9995: about the last 2000 steps), instead of the last step's weights "
                        f"(default {recipe.ema_decay:g}: the last step's)")
    p.add_argument("--precision", choices=("auto", "bf16", "fp32"), default=recipe.precision,
                   help="auto (default): bf16 autocast where the CPU computes bf16 natively, else fp32")
    p.add_argument("--seed", type=_nonneg_int, default=recipe.seed,
                   help=f"initialisation and sampling seed (default {recipe.seed})")
    p.add_argument("--threads", type=_positive_int, default=recipe.threads, help="torch threads (default: all cores)")
    p.add_argument("--data-note", help="what the logs are, recorded in the model's contract (with --export-only "
                   "and the run's logs: for a run started without one)")
    p.add_argument("--utc-offset", type=_utc_offset_type, metavar="HOURS",
                   help="KITTI drives: hours their timestamps are ahead of UTC (default +2, CEST, with a warning); "
                        "native logs carry UTC and ignore it")
    p.add_argument("--init", type=_path, metavar="MODEL_DIR",
                   help="fine-tune: start from this model's weights instead of random ones "
                        "('shipped': the model installed with sunrig)")
    p.add_argument("--export-only", type=_path, metavar="DIR",
                   help="export the checkpoint in --out as it stands to DIR, without training (e.g. mid-run); "
                        "with the run's logs, a checkpoint that predates it also records their sun elevations")
    p.add_argument("--mirror-windows", action=argparse.BooleanOptionalAction, default=None,
                   help="with --export-only: the exported model also runs every window mirrored left to right "
                        "and averages the two answers (twice the work a frame; docs/model.md). Default: as the "
                        "--init model ran (the shipped model: mirrored), else not")
    p.add_argument("--quiet", action="store_true", help="no progress on stderr")
    p.set_defaults(func=cmd_train)

    p = sub.add_parser("synth", parents=[debug], help="write procedural street drives with the true sun as native logs")
    p.add_argument("out", type=_path, help="output folder (drives already there are kept: a run resumes)")
    p.add_argument("--drives", type=_synth_drives, default=10, help="how many drives (default 10, at most 100000)")
    p.add_argument("--frames", type=_synth_frames, default=40, help="frames per drive (default 40, at most 5000)")
    p.add_argument("--seed", type=_nonneg_int, default=0, help="drive i of seed S is always the same drive")
    p.add_argument("--fps", type=_synth_fps, default=10.0, help="frame rate of the drives (default 10, at most 1000)")
    p.add_argument("--jobs", type=_positive_int, default=1, help="drives rendered in parallel (default 1)")
    p.add_argument("--render-scale", type=_float_in(0.0, 1.0), default=0.5,
                   help="internal render size relative to the output (default 0.5, upsampled)")
    p.add_argument("--quiet", action="store_true", help="no progress or summary on stderr")
    p.set_defaults(func=cmd_synth)

    p = sub.add_parser("sun", parents=[debug], help="the sun's position for a time and place (NREL SPA), as JSON")
    p.add_argument("--time", metavar="ISO8601",
                   help="UTC time, e.g. 2011-09-26T11:02:26Z (no offset: UTC); years -2000..6000, signed below 0: "
                        "-1000-03-21T12:00Z")
    p.add_argument("--lat", type=float, metavar="DEG", help="latitude, north positive")
    p.add_argument("--lon", type=float, metavar="DEG", help="longitude, east positive")
    p.add_argument("--csv", type=_path, metavar="IN|-",
                   help="rows time,lat,lon[,elevation_m] with a header: one JSON line each")
    p.add_argument("--elevation-m", type=float, default=0.0, metavar="M", help="height above sea level (default 0)")
    p.add_argument("--pressure-hpa", type=float, metavar="P",
                   help="for refraction (default: the standard atmosphere at the elevation, 1013.25 at 0 m)")
    p.add_argument("--temperature-c", type=float, default=12.0, metavar="C", help="for refraction (default 12)")
    p.add_argument("--delta-t-s", type=float, metavar="S",
                   help="TT - UT1 in seconds (default: the Espenak & Meeus approximation, 67 s for 2011)")
    p.set_defaults(func=cmd_sun)

    p = sub.add_parser("gnss", parents=[debug], help="read a GNSS compass / INS (NMEA 0183) and print what it decodes")
    p.add_argument("source", type=_path, metavar="PORT_OR_FILE",
                   help="serial device, pyserial URL (socket://HOST:PORT) or an NMEA capture file")
    p.add_argument("--jsonl", type=_path, metavar="PATH|-", default="-",
                   help="one JSON object per sentence that gives a heading, fix or time (default: - stdout)")
    p.add_argument("--baud", type=_positive_int, default=115200,
                   help="baud rate of a serial device (default 115200)")
    p.add_argument("--require-checksum", action="store_true",
                   help="drop sentences without *HH instead of accepting them")
    p.add_argument("--quiet", action="store_true", help="no summary on stderr")
    p.set_defaults(func=cmd_gnss)
    return parser


def _below_drawn_row(record: logging.LogRecord) -> bool:
    """A logging filter that lets every record through, once below any row drawn in place."""
    end_row()
    return True


def main(argv: list[str] | None = None, *, late_signals: str = "restore") -> int:
    """The command line. ``late_signals``: what a stop signal does once the command has returned
    (:meth:`rig.stopping.StopSignals.installed`): "restore" the handlers before it (a library
    caller, tests), or "ignore" it (the ``sunrig`` console command, which is about to exit)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.debug else logging.WARNING,
        format="sunrig: %(levelname)s: %(message)s",
    )
    for handler in logging.getLogger().handlers:
        # Below a status or progress row drawn in place on the terminal, not run on after its text.
        handler.addFilter(_below_drawn_row)
    if not args.debug:
        # The rig's own INFO lines are its events, rare and each said once: an outage that ended (a
        # serial port writing again, a GNSS or camera back), a stretch of failed windows over. At
        # WARNING a journal said when the GNSS stopped and never that it came back. Other
        # libraries' INFO stays out.
        for package in ("rig", "drivers", "estimator"):
            logging.getLogger(package).setLevel(logging.INFO)
    # How this command is being stopped (rig/stopping.py): Ctrl-C, SIGTERM and SIGHUP. One per
    # call, so that commands run one after another in a process (tests), or a library caller's
    # command in a thread of its own (which signals never reach), share no stop state.
    stop = args.stop = StopSignals()
    try:
        with stop.installed(after=late_signals):
            return args.func(args)
    except SunrigError as exc:
        if args.debug:
            raise
        print(f"sunrig: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        return stop.exit_code()  # the shell's code for death by that signal
    except BrokenPipeError:
        # The reader of our stdout went away (e.g. `| head`): not an error of ours.
        return 0
    except Exception as exc:  # noqa: BLE001 - the last line of defence prints one line
        if args.debug:
            raise
        machine = _machine_error(exc)  # e.g. an output path found unwritable only when written
        if machine is not None:
            print(f"sunrig: error: {machine}", file=sys.stderr)
            return EXIT_USER_ERROR
        print(f"sunrig: internal error: {type(exc).__name__}: {exc} (rerun with --debug for a traceback)",
              file=sys.stderr)
        return EXIT_BUG


def console_main() -> int:
    """The ``sunrig`` command: :func:`main`, with a stop signal after the command has returned
    ignored. GNU timeout signals the command and then its process group; the second signal came
    once the work was done and killed the finished command with the default action (exit 143 for
    a recording that was complete)."""
    return main(late_signals="ignore")


if __name__ == "__main__":  # pragma: no cover
    sys.exit(console_main())
