"""Procedural street drives with a known sun: training and test data no download can give here.

Each drive is a random street (road with markings, sidewalks, buildings with windows, trees,
poles, signs, walls, cars) under a Preetham sky with the sun at a random azimuth and an
elevation of 5-75 deg, seen by a KITTI-like camera on a vehicle that drives straights, bends and
corners. Lambertian shading (sun plus sky and ground ambient) and cast shadows (onto the ground
and onto other objects) follow exactly the sun in ``Frame.sun_enu_truth``.

    from replay.synthetic import synth_drive, write_synthetic_logs
    for frame in synth_drive(seed=3, n_frames=40): ...
    write_synthetic_logs("data/synth", drives=100, frames=40, seed=0)

Modules: ``scene`` (road path, ground map, solids, random layout), ``sky`` (Preetham sky, sun,
ambient), ``render`` (rasteriser, shading, shadows), ``camera`` (exposure, noise, tone curve),
``drive`` (parameters, trajectory, the Frame stream).
"""

from __future__ import annotations

import math
import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn

import numpy as np

from replay.synthetic.camera import CameraEffects
from replay.synthetic.drive import KITTI_INTRINSICS, Drive, DriveParams, kitti_intrinsics, plan_drive, synth_drive
from rig.errors import SunrigError, ValidationError
from rig.files import folder_lock, make_output_folder, sync_to_disk
from rig.progress import Progress
from rig.types import Intrinsics

__all__ = [
    "KITTI_INTRINSICS",
    "MAX_DRIVES",
    "MAX_FPS",
    "MAX_FRAMES",
    "CameraEffects",
    "Drive",
    "DriveParams",
    "drive_seed",
    "kitti_intrinsics",
    "plan_drive",
    "synth_drive",
    "write_synthetic_logs",
]


# The key of a synthetic drive's render scale in its log's ``sunrig`` metadata (docs/log-format.md).
RENDER_SCALE_KEY = "render_scale"
# The longest drive write_synthetic_logs (and sunrig synth --frames) takes. A drive's whole route
# is laid out before its first frame, in occupancy grids over its bounding box, so its memory grows
# with the square of its length: seed 0's drives peaked at 0.5-3.4 GB at 5000 frames and up to
# 8.4 GB at 10 000 (its drive 5), where a frame also took up to 0.2 s. KITTI's longest drive is
# about 5000 frames.
MAX_FRAMES = 5000
# The most drives one set takes: their names are listed and checked for an earlier run's before the
# first frame, a minute and 4 GB at 10 million (a few zeros too many), and 100 000 drives of 24
# frames are days of rendering here. A bigger set is several folders with other seeds (drive_seed
# keeps them apart).
MAX_DRIVES = 100_000
# The fastest frame rate of a drive: frames are stamped in int64 nanoseconds, and above 1 GHz they
# shared a stamp without a word. No camera this rig reads runs faster than 1 kHz.
MAX_FPS = 1000.0
# The lock file of a folder being written (rig.files.folder_lock): hidden, and no *.mcap a reader takes.
SYNTH_LOCK = ".synth.lock"


def drive_seed(seed: int, index: int) -> int:
    """The seed of drive ``index`` of a set made with ``seed``: independent streams per drive."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1, dtype=np.uint32)[0])


def _write_one(job: tuple[Path, int, int, Intrinsics | None, float, float],
               on_frame: Callable[[], None] | None = None) -> tuple[Path, int]:
    """Render one drive into ``path`` via a temporary name, so an existing file is always whole;
    ``on_frame`` is called as each frame is written (the progress counter)."""
    from replay.native import LogWriter

    path, dseed, frames, intrinsics, render_scale, fps = job
    tmp = path.with_name(path.name + ".part")
    drive = Drive(dseed, frames, intrinsics=intrinsics, render_scale=render_scale, fps=fps)
    # repr: the float back exactly, so a resumed run compares it with --render-scale as given.
    try:
        with LogWriter(tmp, metadata={RENDER_SCALE_KEY: repr(float(render_scale))}) as writer:
            for frame in drive.frames():
                writer.write_frame(frame)
                if on_frame is not None:
                    on_frame()
        # On the disk before it takes the drive's name, and the name on the disk after: renamed
        # with its data still in memory, a power loss could leave the name on an empty or cut
        # drive, which a resume refuses (_kept) until it is deleted by hand.
        sync_to_disk(tmp)
        os.replace(tmp, path)
    except BaseException as exc:
        # A drive cut short (a full disk, Ctrl-C, a worker stopped) would only hold its space.
        tmp.unlink(missing_ok=True)
        # The log writer's errors (a full disk) name no file, and OUT may be on any disk: the
        # drive's, not its .part, which the user never named.
        if isinstance(exc, OSError) and exc.filename is None and exc.errno is not None:
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
    sync_to_disk(path.parent)
    return path, frames


# How often a worker looks whether the run that started it is still there (_watch_parent).
PARENT_POLL_S = 0.2
# How often a ``jobs`` run redraws its progress from its workers' frame count between drives.
PROGRESS_POLL_S = 0.2
# A worker's count of the frames it wrote, shared with the run (_start_worker).
_frames_written: Any = None
# The signal that stopped this worker (_exit_on_signal), 0 while none has.
_stop_signal = 0


def _count_frame() -> None:
    with _frames_written.get_lock():
        _frames_written.value += 1


def _write_in_worker(job: tuple[Path, int, int, Intrinsics | None, float, float]) -> tuple[Path, int]:
    try:
        return _write_one(job, _count_frame)
    finally:
        # A stop's SystemExit can be replaced on its way out by an error of the clean-up (the
        # log's close on a full disk), which the pool sends back as the drive's result: the worker
        # then waited for work with SIGTERM ignored, and the run waited in the pool's join forever.
        if _stop_signal:
            raise SystemExit(128 + _stop_signal)


def _start_worker(parent_pid: int, frames_written: Any, workers_started: Any) -> None:
    """The initializer of a ``jobs`` worker of :func:`write_synthetic_logs`: it renders only while
    the run that started it (``parent_pid``) runs, and a drive it is stopped in leaves no .part.
    It adds each frame it writes to ``frames_written``, the run's progress, which otherwise moved
    only as whole drives came back (minutes apart for long drives), and counts itself in
    ``workers_started``: more than ``jobs`` means the pool replaced a worker that died."""
    global _frames_written
    _frames_written = frames_written
    with workers_started.get_lock():
        workers_started.value += 1
    # The pool stops its workers with SIGTERM (terminate, on the run's Ctrl-C or SIGTERM), whose
    # default action ended a worker at once with its .part left: an exception instead, which
    # _write_one cleans up after.
    signal.signal(signal.SIGTERM, _exit_on_signal)
    # Ctrl-C reaches the whole process group and a hang-up the session: the run stops its workers
    # itself (above), rather than each worker printing a KeyboardInterrupt traceback of its own.
    for name in ("SIGINT", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_IGN)
    threading.Thread(target=_watch_parent, args=(parent_pid,), name="synth-parent", daemon=True).start()


def _exit_on_signal(signum: int, frame: FrameType | None) -> NoReturn:
    global _stop_signal
    signal.signal(signum, signal.SIG_IGN)  # once: a second signal must not cut the clean-up short
    _stop_signal = signum
    # SystemExit ends a multiprocessing worker without a traceback; Exception would be sent back.
    raise SystemExit(128 + signum)


def _watch_parent(parent_pid: int) -> None:
    """Stop this worker (as the pool would, SIGTERM) once its parent is gone: a run killed with -9
    cannot stop its workers, which rendered their drives to the end (the CPU taken for minutes,
    and a rerun, the folder free again, rendering the same drives into the same .part files) and
    then died on a traceback sending their result. A daemon: it ends with its worker."""
    while os.getppid() == parent_pid:  # a parent that dies gives its children another
        time.sleep(PARENT_POLL_S)
    os.kill(os.getpid(), signal.SIGTERM)


def _float_or_nan(text: str) -> float:
    """``text`` as a float, NaN when it is none (equal to nothing, so a damaged value is a mismatch)."""
    try:
        return float(text)
    except ValueError:
        return math.nan


def _kept(paths: list[Path], frames: int, fps: float, render_scale: float) -> set[Path]:
    """The drives kept from an earlier run. Each must be the drive asked for: the name fixes the
    seed, and the frame count, rate and render scale are checked (a set asked for with 20 frames at
    1 fps and scale 1 must not be 10-frame drives, nor 10 fps ones, nor ones rendered at 0.5)."""
    from replay.native import log_figures

    kept = {path for path in paths if path.exists()}
    for path in sorted(kept):
        figures = log_figures(path)
        if figures is None:  # drives are written whole (_write_one): this one was damaged since
            raise ValidationError(f"{path} is kept from an earlier run but is not a whole log (cut short or "
                                  "damaged): delete it, and this command makes it again")
        found, span = figures.frames, figures.span_s
        if found != frames:
            raise ValidationError(
                f"{path} is kept from an earlier run but holds {found} frames, not the {frames} asked for: "
                "pass another folder, or delete the folder's drives to make them again"
            )
        want = (frames - 1) / fps  # the frames are 1 / fps apart, the first at 0
        if frames > 1 and abs(span - want) > 1e-3:
            raise ValidationError(
                f"{path} is kept from an earlier run but its frames are {span / (frames - 1):g} s apart, not the "
                f"{1 / fps:g} s of --fps {fps:g}: pass another folder, or delete the folder's drives to make them again"
            )
        scale = figures.metadata.get(RENDER_SCALE_KEY)
        # No scale: a drive written before it was recorded. Kept unchecked, so that folders made
        # then still resume instead of being refused whole (their drives cannot say their scale).
        if scale is not None and _float_or_nan(scale) != render_scale:
            raise ValidationError(
                f"{path} is kept from an earlier run but was rendered at --render-scale {scale}, not the "
                f"{render_scale:g} asked for: pass another folder, or delete the folder's drives to make them again"
            )
    return kept


def write_synthetic_logs(out_dir: str | os.PathLike[str], *, drives: int, frames: int, seed: int,
                         intrinsics: Intrinsics | None = None, progress: bool = True,
                         render_scale: float = 0.5, fps: float = 10.0, jobs: int = 1,
                         on_kept: Callable[[int], None] | None = None) -> list[Path]:
    """Write ``drives`` native logs of ``frames`` frames each, ``drive_{seed}_{i:04d}.mcap``.

    Drive i uses :func:`drive_seed` (seed, i), so any one log can be remade alone, and a drive
    whose log already exists is not rendered again: an interrupted run resumes (one whose
    frame count, rate or render scale differs is refused). While it runs, the process holds
    ``out_dir``: a second one on it is refused naming this one's pid. ``jobs`` drives
    render in parallel processes, which stop with this one (:func:`_start_worker`), even killed
    with -9, and leave no .part. ``on_kept`` is told how many drives are kept, once they are
    checked and before any is rendered. Returns the paths in order. Images go through the log
    writer's JPEG encoder.
    """
    if not 0 <= drives <= MAX_DRIVES or not 1 <= frames <= MAX_FRAMES or jobs < 1 or not 0 < fps <= MAX_FPS:
        raise ValidationError(
            f"synthetic logs: expected drives from 0 to {MAX_DRIVES} (more: another folder and seed), frames from 1 "
            f"to {MAX_FRAMES} (longer routes take gigabytes to lay out), jobs >= 1 and fps above 0 to {MAX_FPS:g}, "
            f"got {drives}, {frames}, {jobs}, {fps:g}"
        )
    out = make_output_folder(out_dir, what="folder", holds="OUT is the folder the drives are written to")
    # Held to the end: a second synth on the folder (started twice, or resumed while the first
    # runs) rendered the same drives into the same .part files, where a kill of either left the
    # other's drive damaged under its whole name, or deleted its .part.
    with folder_lock(out, name=SYNTH_LOCK, command="sunrig synth", flag="OUT"):
        return _write_held(out, drives=drives, frames=frames, seed=seed, intrinsics=intrinsics, progress=progress,
                           render_scale=render_scale, fps=fps, jobs=jobs, on_kept=on_kept)


def _write_held(out: Path, *, drives: int, frames: int, seed: int, intrinsics: Intrinsics | None, progress: bool,
                render_scale: float, fps: float, jobs: int, on_kept: Callable[[int], None] | None) -> list[Path]:
    """:func:`write_synthetic_logs` into ``out``, which this process holds (:func:`folder_lock`)."""
    paths = [out / f"drive_{seed}_{i:04d}.mcap" for i in range(drives)]
    kept = _kept(paths, frames, fps, render_scale)
    if on_kept is not None:
        on_kept(len(kept))
    todo = [(p, drive_seed(seed, i), frames, intrinsics, render_scale, fps)
            for i, p in enumerate(paths) if p not in kept]
    bar = Progress("synth", total=drives * frames, unit="frames", enabled=None if progress else False)
    kept_frames = (drives - len(todo)) * frames
    bar.skip(kept_frames)  # kept from an earlier run: not part of the rate
    try:
        if jobs == 1 or len(todo) <= 1:
            for job in todo:
                _write_one(job, bar.advance)  # frame by frame: a long drive takes minutes
        else:
            import multiprocessing

            context = multiprocessing.get_context("spawn")
            written, started = context.Value("q", 0), context.Value("i", 0)
            try:
                with context.Pool(jobs, _start_worker, (os.getpid(), written, started)) as pool:
                    results, left = pool.imap_unordered(_write_in_worker, todo), len(todo)
                    while left:
                        try:
                            results.next(timeout=PROGRESS_POLL_S)
                            left -= 1
                        except multiprocessing.TimeoutError:
                            pass  # no drive finished yet: redraw the frames written within drives
                        bar.update(kept_frames + written.value)
                        # The pool replaces a worker that died (killed alone, as the out-of-memory
                        # killer does) but never hands its drive out again: the run waited forever.
                        if started.value > jobs:
                            raise SunrigError(
                                "synth: a --jobs worker died while rendering (killed, perhaps for want of memory); run "
                                "the command again to resume, with fewer --jobs if it happens again")
                    # Let the workers leave on the pool's sentinel: the with's terminate would SIGTERM
                    # those still exiting, and one caught in its atexit handlers printed a traceback.
                    # Left only on an error or a signal, terminate stops workers that are rendering.
                    pool.close()
                    pool.join()
            except BaseException:
                # The pool is stopped: a worker killed with its drive left that drive's .part.
                for job in todo:
                    job[0].with_name(job[0].name + ".part").unlink(missing_ok=True)
                raise
    finally:
        bar.close()
    return paths
