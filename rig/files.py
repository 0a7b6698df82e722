"""Output folders: made when missing, refused in one line when they cannot be; output files
replaced whole or not at all; stream files touched only by their first write."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path
from typing import IO

from rig.errors import ValidationError


def make_output_folder(path: str | os.PathLike[str], *, what: str, holds: str) -> Path:
    """``path`` as a folder, made with its parents if missing. A path that is a file, or one
    that cannot be made (a parent that is a file, no permission), is a :class:`ValidationError`
    naming ``what`` the folder is and what it ``holds``; mkdir's own errors were internal ones."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise ValidationError(f"{out} is a file; {holds}: pass a folder's path")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ValidationError(f"cannot make the {what} {out}: {exc.strerror}; pass another path") from None
    return out


def write_replacing(path: str | os.PathLike[str], write: Callable[[Path], object]) -> None:
    """``write`` a hidden sibling of ``path``, then rename it over ``path``: a kill or a full disk
    mid-write leaves the file that was there (or none), never a torn or empty one, and a sibling
    that failed is removed. The sibling keeps the suffix, which ``np.savez`` would otherwise append.

    A ``path`` that exists and is not a regular file (a FIFO, a terminal, /dev/full) is written in
    place: renamed over, the device itself would be replaced by a file."""
    path = Path(path)
    if path.exists() and not path.is_file():
        write(path)
        return
    tmp = _sibling(path)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)  # a torn copy would only hold a full disk full
        # Name the file the error is about: the user's, not the hidden sibling they never named.
        if isinstance(exc, OSError) and (exc.filename is None or os.fsdecode(exc.filename) == str(tmp)):
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise


def _sibling(path: Path) -> Path:
    return path.with_name(f".{path.stem}.tmp{path.suffix}")


def check_can_write(path: str | os.PathLike[str]) -> None:
    """Raise OSError (naming ``path``) if :func:`write_replacing` could not write ``path``: its
    hidden sibling is made and removed. Before minutes of work, not after; os.access is no such
    check, since it says yes to root for any folder (/proc, a read-only bind mount). A path that
    exists and is not a regular file is written in place, and its open may wait (a FIFO): taken."""
    path = Path(path)
    if path.exists() and not path.is_file():
        return
    tmp = _sibling(path)
    try:
        os.close(os.open(tmp, os.O_WRONLY | os.O_CREAT, 0o666))  # write_replacing replaces it anyway
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    tmp.unlink(missing_ok=True)


class StreamFile:
    """A text file written as a stream (a line at a time, flushed, read while it grows), which a
    run that writes nothing leaves as it was. A stream cannot be whole or not at all (its reader
    reads as it comes), but a run that failed before its first line (a log none of whose frames
    could be read) once emptied the file a run before had written, or left a new path at 0 bytes.

    So the path is checked now, and touched at the first write: an existing regular file is opened
    now without truncating (a path that cannot be written fails at once, as it did) and truncated
    at the first write; a new path is made now and removed at once (the same check, by the open
    itself, which os.access is not for root), then made again at the first write. A path that
    exists and is not a regular file (a FIFO, a terminal, /dev/full) is opened now and written in
    place, as :func:`write_replacing` does; a FIFO's open waits for its reader, as it did.

    Raises OSError (with the file name) where ``open`` would."""

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        self.name = str(path)
        self._file: IO[str] | None = None
        self._truncate = False  # an existing file, opened as it was: truncated at the first write
        if self.path.exists() and self.path.is_file():
            fd = os.open(self.path, os.O_WRONLY)
            self._file = open(fd, "w", encoding="utf-8")  # noqa: SIM115 - closed in close()
            self._truncate = True
        elif not self.path.exists():
            try:
                os.close(os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            except FileExistsError:  # made meanwhile, or a dangling link: written as it was before
                self._file = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 - closed in close()
            else:
                self.path.unlink()
        else:
            self._file = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 - closed in close()
        self._closed = False

    def write(self, text: str) -> int:
        if self._file is None:  # a new path: made now (in the writer's thread, live)
            self._file = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 - closed in close()
        elif self._truncate:
            self._file.truncate(0)
            self._truncate = False
        return self._file.write(text)

    def flush(self) -> None:
        if self._file is not None:
            self._file.flush()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if self._file is not None:
            self._file.close()
