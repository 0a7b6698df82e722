"""The MCAP recorder as a rig publisher: estimates (and frames, when asked) into a native log.

Disk writes happen on the recorder's own thread behind a bounded queue. When the disk cannot keep
up, the oldest waiting items are dropped and counted rather than stalling capture or the estimator.
A disk that fills ends the recording at its last complete chunk (:class:`Recording`).
"""

from __future__ import annotations

import errno
import logging
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING

from rig.errors import PublishError, SunrigError
from rig.publishers import QueuedWriter
from rig.types import Frame, SunEstimate

if TYPE_CHECKING:
    from replay.native import LogWriter

log = logging.getLogger(__name__)

# A write the disk has no room for: a full disk, a quota, a file size limit.
DISK_FULL_ERRNOS = frozenset((errno.ENOSPC, errno.EDQUOT, errno.EFBIG))
# A chunk ends at the latest once its oldest item waited this long. A log's own bound is 1 MiB,
# which an estimates-only recording fills in about 5 minutes at 10 Hz: held in memory that long,
# they were all lost at a power cut or a full disk, and a full disk was found (and said) only then.
CHUNK_EVERY_S = 10.0
START_FIELD = "{start}"
MAX_SAME_START = 100  # NAME, NAME-1 .. NAME-99: more starts in one second than any boot loop makes


class RecordingRefused(SunrigError):
    """A recording may not go where it was asked to. ``why``: ``"exists"`` (and may not be
    replaced), ``"folder"`` (the path is a folder), ``"no folder"`` (its folder does not exist),
    ``"stdout"`` (``-``: a log is a file), ``"taken"`` (every ``{start}`` variant exists). The
    command that asked words the way out in its own options (``rig/cli.py``)."""

    def __init__(self, path: Path, why: str) -> None:
        self.path, self.why = path, why
        super().__init__(f"{path}: recording refused ({why})")


def _stamp(start_utc: datetime) -> str:
    return start_utc.strftime("%Y%m%dT%H%M%SZ")


def check_recording_path(template: str | Path, *, overwrite: bool = False) -> None:
    """Refuse, before minutes of opening devices (and before other outputs are opened and
    truncated), what :func:`open_recording` would refuse later."""
    name = str(template)
    if name == "-":
        raise RecordingRefused(Path(name), "stdout")
    path = Path(name)
    if START_FIELD not in str(path.parent) and not path.parent.is_dir():
        raise RecordingRefused(path, "no folder")
    if START_FIELD in path.name:
        return  # a free name is found when the file is made
    if path.is_dir():
        raise RecordingRefused(path, "folder")
    if os.path.lexists(path) and not overwrite:  # lexists: a dangling link is taken too
        raise RecordingRefused(path, "exists")
    if overwrite and path.is_symlink():
        # Replacing writes through the link: to a file in a folder that may not exist, found only
        # once the devices were open. Named by where it points, which is what the user must make.
        target = Path(os.path.realpath(path))
        if not target.parent.is_dir():
            raise RecordingRefused(target, "no folder")


def open_recording(template: str | Path, *, start_utc: datetime, overwrite: bool = False) -> LogWriter:
    """The recording's log, its file made now.

    A drive cannot be recorded again, so an existing file is never replaced by accident (rosbag2
    refuses an existing output the same way): the file is created exclusively, which also keeps a
    file made since :func:`check_recording_path` looked. ``overwrite`` replaces it instead.
    ``{start}`` in the name becomes the UTC start time (``20261123T031500Z``), so a rig that
    records at every boot from one configuration writes a new file each time; a name already taken
    (a restart within the second, or a board whose clock repeats a boot time before it syncs)
    gets ``-1``, ``-2``, ... after the time rather than stopping the rig.
    """
    from replay.native import LogWriter

    check_recording_path(template, overwrite=overwrite)
    name = str(template)
    stamp = _stamp(start_utc)
    path = Path(name.replace(START_FIELD, stamp))
    if path.is_dir():
        raise RecordingRefused(path, "folder")
    if overwrite:
        return LogWriter(path)
    candidates = [path]
    if START_FIELD in name:
        candidates += [Path(name.replace(START_FIELD, f"{stamp}-{k}")) for k in range(1, MAX_SAME_START)]
    for candidate in candidates:
        try:
            return LogWriter(candidate, exclusive=True)
        except FileExistsError:
            continue
    raise RecordingRefused(path, "taken" if START_FIELD in name else "exists")


def written_file(path: Path | None) -> Path | None:
    """The regular file a log at ``path`` was written into: through a link (``--overwrite`` of a
    link, which writes where it points), the file it points to; None for a device or a stream.
    That file is what an empty recording leaves behind, and its folder is on the disk that fills."""
    if path is None:
        return None
    real = Path(os.path.realpath(path))
    # Only a file: a device (--out /dev/null with --overwrite, as root) unlinked would remove the
    # device node itself from the system.
    return real if real.is_file() else None


def recording_folder(path: Path) -> Path:
    """The folder a recording at ``path`` is written into, on the disk that may fill: through a
    link, the folder it points into (the link's own may be on another disk)."""
    return Path(os.path.realpath(path)).parent


def recording_name(path: Path | None) -> str:
    """``path`` as said to the user; through a link, the file it points to, which is the one kept
    or removed (:func:`discard_if_empty`), named with the link the user gave."""
    if path is None:
        return "the recording"
    return f"{os.path.realpath(path)} (where {path} points)" if path.is_symlink() else str(path)


def discard_if_empty(writer: LogWriter) -> bool:
    """Remove a closed recording that holds no frame and no estimate; True when it was removed.

    Made by this run and holding nothing, it would only fail a replay of it and be warned about and
    left out by every later eval or train of its folder. (With ``overwrite``, the file it replaced
    was already gone when it opened. Made through a link, the file it points to is removed and the
    link, the user's, is kept: removing the link left the emptied file behind.)
    """
    if not writer.closed or writer.frames_written or writer.estimates_written:
        return False
    made = written_file(writer.path)
    if made is None:
        return False
    made.unlink(missing_ok=True)
    return True


@dataclass(frozen=True)
class DiskFull:
    """What a full disk cost a recording. It holds what came before ``since_utc`` (its complete
    chunks: ``frames_recorded``, ``estimates_recorded``); from then on nothing was recorded
    (``frames_lost``, ``estimates_lost``). ``removed``: it held nothing, and its file is gone.
    ``errno``: ENOSPC, EDQUOT or EFBIG (:data:`DISK_FULL_ERRNOS`)."""

    errno: int
    since_utc: datetime
    frames_recorded: int
    estimates_recorded: int
    frames_lost: int
    estimates_lost: int
    removed: bool

    @property
    def cause(self) -> str:
        """What filled, in the OS's words too: "its disk is full (No space left on device)"."""
        reason = os.strerror(self.errno)
        if self.errno == errno.EFBIG:
            # A FAT32 stick's 4 GiB: about 2.5 hours of 1242 x 375 frames at 10 Hz. Space is not what it lacks.
            return f"its file is as large as its file system allows ({reason})"
        return f"its disk quota is used up ({reason})" if self.errno == errno.EDQUOT else f"its disk is full ({reason})"

    def remedy(self, folder: Path | str) -> str:
        """What to do about it, for a recording in ``folder``."""
        if self.errno == errno.EFBIG:
            return f"record to a file system that allows larger files than that of {folder} (ext4 or exFAT, not FAT32)"
        return f"free space in {folder}"


class Recording:
    """A recording's log, and how much of it is on the disk (``writer.on_disk``).

    A full disk ends the recording. The write that did not fit left part of a chunk in the file,
    and a log cannot go on past that: what was written after it once space was freed replays as a
    damaged record (and filled the freed disk again with it). So from the first write the disk
    has no room for, nothing more is written: that item, those since the last complete chunk (held
    in memory until the chunk ends) and every later one are counted as lost, and :meth:`close`
    abandons the log (``LogWriter.abandon``: the file cut back to the end of that chunk, a log
    cut off there that replays whole), and removes the file when it holds no chunk (an empty log
    would only be refused by every replay).

    ``chunk_every_s``: end the chunk in progress, besides at the log's own size bound, once its
    oldest item waited this long (``monotonic`` seconds); None: at the size bound only. The log
    says when a chunk is on the disk (``on_disk`` moves), of a device or a stream too, whose size
    says nothing.
    """

    def __init__(self, writer: LogWriter, *, chunk_every_s: float | None = None,
                 clock: Callable[[], datetime] = lambda: datetime.now(UTC),
                 monotonic: Callable[[], float] = time.monotonic) -> None:
        self.writer = writer
        self.path = writer.path
        self.chunk_every_s = chunk_every_s
        self._clock, self._monotonic = clock, monotonic
        self._given = [0, 0]  # frames, estimates handed to the log, lost ones too
        self._seen_on_disk = writer.on_disk  # as last seen: when it moves, a chunk has ended
        self._pending_since: datetime | None = None  # the first item not yet in a complete chunk
        self._pending_since_s = 0.0  # the same, in `monotonic` seconds
        self._full: tuple[int, datetime] | None = None  # (errno, since) once the disk is full
        self._removed = False

    @property
    def disk_full(self) -> DiskFull | None:
        """None while every write fit (and after a close that fit)."""
        if self._full is None:
            return None
        code, since = self._full
        kept = self.writer.on_disk  # (one read: the writer thread may move it)
        return DiskFull(code, since, kept.frames, kept.estimates, self._given[0] - kept.frames,
                        self._given[1] - kept.estimates, self._removed)

    def write_frame(self, frame: Frame, *, jpeg_quality: int = 90) -> bool:
        """False: not recorded, the disk is full (:attr:`disk_full`)."""
        return self._write(0, lambda: self.writer.write_frame(frame, jpeg_quality=jpeg_quality))

    def write_estimate(self, est: SunEstimate) -> bool:
        """False: not recorded, the disk is full (:attr:`disk_full`)."""
        return self._write(1, lambda: self.writer.write_estimate(est))

    def _write(self, kind: int, write: Callable[[], None]) -> bool:
        if self._full is not None:
            self._given[kind] += 1
            return False
        if self._pending_since is None:
            self._pending_since, self._pending_since_s = self._clock(), self._monotonic()
        try:
            write()
        except OSError as exc:
            if exc.errno not in DISK_FULL_ERRNOS:
                raise
            self._given[kind] += 1  # the item the disk had no room for
            self._filled(exc)
            return False
        self._given[kind] += 1
        self._note_chunk_end()
        if (self._pending_since is not None and self.chunk_every_s is not None
                and self._monotonic() - self._pending_since_s >= self.chunk_every_s):
            try:
                self.writer.flush()
            except OSError as exc:
                if exc.errno not in DISK_FULL_ERRNOS:
                    raise
                self._filled(exc)
                return False
            self._note_chunk_end()
        return True

    def _note_chunk_end(self) -> None:
        on_disk = self.writer.on_disk
        if on_disk != self._seen_on_disk:  # a chunk ended: chunks end between items, so nothing waits
            self._seen_on_disk = on_disk
            self._pending_since = None

    def _filled(self, exc: OSError) -> None:
        self._full = (exc.errno or errno.ENOSPC, self._pending_since or self._clock())

    def close(self) -> None:
        """Finish the log: its summary and index. After a full disk, abandon it instead
        (``LogWriter.abandon``: cut back to its last complete chunk); a close the disk has no room
        for leaves it so too. Either way a file that holds no chunk is removed."""
        if self._full is not None:
            self.writer.abandon()
        else:
            try:
                self.writer.close()
            except OSError as exc:
                if exc.errno not in DISK_FULL_ERRNOS:
                    raise
                self._filled(exc)  # the writer cut it back to its last complete chunk
        if self._full is None or self.writer.on_disk.size_bytes:
            return
        # A device (--out /dev/full with --overwrite, as root) is left as it is; through a link,
        # the file it points to goes (discard_if_empty).
        if (made := written_file(self.path)) is not None:
            made.unlink(missing_ok=True)
            self._removed = True


class RecorderPublisher:
    """Writes what it is given to a native log on a writer thread; ``close`` finishes the file.

    ``writer``: the log, made by :func:`open_recording` (which never replaces a file by accident).
    The thread is a :class:`~rig.publishers.QueuedWriter`: when the disk cannot keep up, the
    oldest of ``queue_size`` waiting items are dropped and counted, and a failed write is counted,
    not raised. A full disk ends the recording at its last complete chunk (:class:`Recording`),
    said once as it happens, and each item not recorded since is counted in ``errors`` (the status
    line's publish errors); :attr:`disk_full` says what it cost. A chunk ends at least every
    ``chunk_every_s`` (:data:`CHUNK_EVERY_S`). ``close`` waits up to
    ``join_timeout_s`` for the queue to be written, so a recording keeps its last seconds; a
    write stuck longer (a disk that stopped answering) is left behind, and the thread finishes the
    file when that write returns.
    """

    def __init__(self, writer: LogWriter, *, record_frames: bool = False, queue_size: int = 64,
                 join_timeout_s: float = 10.0, chunk_every_s: float = CHUNK_EVERY_S) -> None:
        self._writer = writer
        self._recording = Recording(writer, chunk_every_s=chunk_every_s)
        self.path = writer.path
        self.record_frames = record_frames
        self.join_timeout_s = join_timeout_s
        self._worker: QueuedWriter[Frame | SunEstimate] = QueuedWriter(
            self._write, self._finish, what=f"recorder {self.path}", max_pending=queue_size)

    def record_frame(self, frame: Frame) -> None:
        if self.record_frames:
            self._worker.put(frame)  # (nothing, once closed)

    def publish(self, est: SunEstimate) -> None:
        if not self._worker.put(est):  # closed: said, so that the pipeline counts it, as any output's
            raise PublishError(f"publish() on the closed recorder of {self.path}; make a new one")

    def _write(self, item: Frame | SunEstimate) -> None:
        was_full = self._recording.disk_full is not None
        if isinstance(item, Frame):
            self._recording.write_frame(item)
        else:
            self._recording.write_estimate(item)
        if not was_full:
            self._say_if_full()

    def _finish(self) -> None:
        was_full = self._recording.disk_full is not None
        self._recording.close()
        if not was_full:
            self._say_if_full()  # the disk had no room for the last chunk and the summary

    def _say_if_full(self) -> None:
        """Once, as the disk fills: the journal's line of when, what the recording keeps, what to do."""
        full = self._recording.disk_full
        if full is None:
            return
        log.warning("recording %s: %s: the recording ends at %s; what comes later is not recorded (counted in the "
                    "status line's publish errors), and the other outputs go on; %s, and the next start records "
                    "again", self.path, full.cause, f"{full.since_utc:%H:%M:%S} UTC", full.remedy(self.folder))

    @property
    def folder(self) -> Path | str:
        """The folder the recording is written into, on the disk that may fill: through a link,
        where it points (the link's own folder may be on another disk)."""
        return recording_folder(self.path) if self.path is not None else "its folder"

    @property
    def disk_full(self) -> DiskFull | None:
        """What a full disk cost the recording (:class:`DiskFull`); None while every write fit."""
        return self._recording.disk_full

    def stats(self) -> dict:
        stats = {"written": self._worker.written, **self._worker.stats()}
        full = self._recording.disk_full
        if full is not None:  # taken by the log, then lost with the chunk the disk had no room for
            lost = full.frames_lost + full.estimates_lost
            stats["written"] = full.frames_recorded + full.estimates_recorded
            stats["errors"] += lost
            stats["last_error"] = stats["last_error"] or f"OSError: {os.strerror(full.errno)}"
        return stats

    @property
    def finished(self) -> bool:
        """The log is complete (summary and index): closed, and its writer was not left stuck."""
        return self._worker.finished

    @property
    def stuck(self) -> bool:
        """close() gave up on a write that has not returned (the log is finished if it ever does)."""
        return self._worker.left_behind

    def discard_if_empty(self) -> bool:
        """Once finished: remove the log if nothing was written to it (:func:`discard_if_empty`)."""
        return self.finished and discard_if_empty(self._writer)

    def close(self) -> None:
        self._worker.close(self.join_timeout_s)
