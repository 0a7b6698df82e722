"""The MCAP recorder as a rig publisher: estimates (and frames, when asked) into a native log.

Disk writes happen on the recorder's own thread behind a bounded queue. When the disk cannot keep
up, the newest items are refused and counted rather than stalling capture or the estimator.
"""

from __future__ import annotations

import logging
import threading
from datetime import datetime
from pathlib import Path

from rig.errors import SunrigError
from rig.publishers import ErrorTally
from rig.ring import DropOldestQueue
from rig.types import Frame, SunEstimate

log = logging.getLogger(__name__)

START_FIELD = "{start}"


def recording_path(template: str | Path, *, start_utc: datetime, overwrite: bool = False,
                   flag: str = "--out", overwrite_flag: str = "--overwrite") -> Path:
    """The file a recording goes to, refused if it exists unless ``overwrite``.

    A drive cannot be recorded again, so an existing recording is never replaced by accident
    (rosbag2 refuses an existing output the same way). ``{start}`` in the name becomes the UTC
    start time (``20261123T031500Z``), so a rig that starts recording at every boot with the same
    configuration writes a new file each time instead of failing. ``flag`` and ``overwrite_flag``
    name the options in the error, as the command spells them.
    """
    name = str(template)
    path = Path(name.replace(START_FIELD, start_utc.strftime("%Y%m%dT%H%M%SZ")))
    if path.exists() and not overwrite:
        hint = f" or put {START_FIELD} in the name for a new file per run" if START_FIELD not in name else ""
        raise SunrigError(f"{flag} {path} exists: a recording is not replaced by accident; pass another path{hint}, "
                          f"or {overwrite_flag} to replace it")
    return path


class RecorderPublisher:
    """Writes what it is given to a native log on a writer thread; ``close`` finishes the file."""

    def __init__(self, path: str | Path, *, record_frames: bool = False, queue_size: int = 64) -> None:
        from replay.native import LogWriter

        self.path = Path(path)
        self.record_frames = record_frames
        self._writer = LogWriter(self.path)
        self._queue: DropOldestQueue[Frame | SunEstimate] = DropOldestQueue(queue_size)
        self._stop = threading.Event()
        self._closed = False
        self.written = 0
        self._errors = ErrorTally(log, f"recorder {self.path}")
        self._thread = threading.Thread(target=self._run, name="sunrig-recorder", daemon=True)
        self._thread.start()

    def record_frame(self, frame: Frame) -> None:
        if self.record_frames and not self._closed:
            self._queue.put(frame)

    def publish(self, est: SunEstimate) -> None:
        if not self._closed:
            self._queue.put(est)

    def _run(self) -> None:
        while True:
            item = self._queue.get(0.1)
            if item is None:
                if self._stop.is_set():
                    return
                continue
            try:
                if isinstance(item, Frame):
                    self._writer.write_frame(item)
                else:
                    self._writer.write_estimate(item)
                self.written += 1
            except Exception as exc:  # noqa: BLE001 - a full disk must not stop the rig
                self._errors.add(exc, item.seq)

    def stats(self) -> dict:
        return {"written": self.written, "dropped": self._queue.dropped, "errors": self._errors.count,
                "last_error": self._errors.last}

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._stop.set()
        self._queue.close()
        self._thread.join(10.0)  # drain what is queued: a recording should keep its last seconds
        self._writer.close()
