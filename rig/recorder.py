"""The MCAP recorder as a rig publisher: estimates (and frames, when asked) into a native log.

Disk writes happen on the recorder's own thread behind a bounded queue. When the disk cannot keep
up, the oldest waiting items are dropped and counted rather than stalling capture or the estimator.
"""

from __future__ import annotations

import logging
import os
from datetime import datetime
from pathlib import Path
from typing import TYPE_CHECKING

from rig.errors import PublishError, SunrigError
from rig.publishers import QueuedWriter
from rig.types import Frame, SunEstimate

if TYPE_CHECKING:
    from replay.native import LogWriter

log = logging.getLogger(__name__)

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


def discard_if_empty(writer: LogWriter) -> bool:
    """Remove a closed recording that holds no frame and no estimate; True when it was removed.

    Made by this run and holding nothing, it would only fail a replay of it and be warned about and
    left out by every later eval or train of its folder. (With ``overwrite``, the file it replaced
    was already gone when it opened.)
    """
    if not writer.closed or writer.frames_written or writer.estimates_written or writer.path is None:
        return False
    # Only a file: an --out that is a device (/dev/null with --overwrite, as root) was unlinked,
    # removing the device node itself from the system.
    if not writer.path.is_file():
        return False
    writer.path.unlink(missing_ok=True)
    return True


class RecorderPublisher:
    """Writes what it is given to a native log on a writer thread; ``close`` finishes the file.

    ``writer``: the log, made by :func:`open_recording` (which never replaces a file by accident).
    The thread is a :class:`~rig.publishers.QueuedWriter`: when the disk cannot keep up, the
    oldest of ``queue_size`` waiting items are dropped and counted, and a failed write (a full
    disk) is counted, not raised. ``close`` waits up to ``join_timeout_s`` for the queue to be
    written, so a recording keeps its last seconds; a write stuck longer (a disk that stopped
    answering) is left behind, and the thread finishes the file when that write returns.
    """

    def __init__(self, writer: LogWriter, *, record_frames: bool = False, queue_size: int = 64,
                 join_timeout_s: float = 10.0) -> None:
        self._writer = writer
        self.path = writer.path
        self.record_frames = record_frames
        self.join_timeout_s = join_timeout_s
        self._worker: QueuedWriter[Frame | SunEstimate] = QueuedWriter(
            self._write, writer.close, what=f"recorder {self.path}", max_pending=queue_size)

    def record_frame(self, frame: Frame) -> None:
        if self.record_frames:
            self._worker.put(frame)  # (nothing, once closed)

    def publish(self, est: SunEstimate) -> None:
        if not self._worker.put(est):  # closed: said, so that the pipeline counts it, as any output's
            raise PublishError(f"publish() on the closed recorder of {self.path}; make a new one")

    def _write(self, item: Frame | SunEstimate) -> None:
        if isinstance(item, Frame):
            self._writer.write_frame(item)
        else:
            self._writer.write_estimate(item)

    def stats(self) -> dict:
        return {"written": self._worker.written, **self._worker.stats()}

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
