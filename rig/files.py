"""Output folders: made when missing, refused in one line when they cannot be, held by one process
at a time; output files replaced whole or not at all; stream files touched only by their first write."""

from __future__ import annotations

import contextlib
import errno
import logging
import os
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO, Any

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


log = logging.getLogger(__name__)


@contextlib.contextmanager
def folder_lock(folder: Path, *, name: str, command: str, flag: str) -> Iterator[bool]:
    """Hold ``folder`` for one process: another process asking for it while it is held (a second
    ``command`` on the same folder, started twice or resumed while the first runs) is refused in
    one line naming ``flag`` (how the command names the folder) and the holder's pid, instead of
    doing the same work into the same files through the same temporary names.

    The folder is made if missing (the lock lives in it, in a hidden file ``name``) and removed
    again, with the parents made for it, if the holder leaves nothing in it (one refused or stopped
    early). The lock is the kernel's (``flock``), so a holder killed by any means frees the folder
    with it; the lock file holds the holder's pid, for the refusal to name, and is removed at the
    end. Yields whether the folder is held: where the OS or the file system has no ``flock``
    (Windows; some network mounts), False, and processes go unguarded, with a warning on such a
    mount."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - Windows
        yield False
        return
    made = []
    where = folder
    while not where.exists() and where != where.parent:
        made.append(where)
        where = where.parent
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    try:
        fd = _take_lock(path, fcntl, command=command, flag=flag)
        try:
            yield fd is not None
        finally:
            if fd is not None:
                path.unlink(missing_ok=True)  # before the lock goes: whoever opens the path next makes a new file
                os.close(fd)
    finally:
        for made_folder in made:  # innermost first; one that holds anything stays
            try:
                made_folder.rmdir()
            except OSError:
                break


def _take_lock(path: Path, fcntl: Any, *, command: str, flag: str) -> int | None:
    """The open, locked ``path`` (see :func:`folder_lock`); None where the file system has no locks."""
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
            os.close(fd)
            pid = f" (pid {holder})" if holder.isdigit() else ""
            raise ValidationError(
                f"{flag} {path.parent} is in use by another {command}{pid}; "
                f"wait for it to end (or stop it) and run the command again, or pass another {flag}") from None
        except OSError as exc:
            if exc.errno not in (errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS):
                os.close(fd)
                raise
            log.warning("%s: this file system has no file locks; make sure no other %s uses this folder",
                        path.parent, command)
            os.close(fd)
            return None
        # A holder that ended between our open and our lock removed the file we hold: a lock on it
        # guards nothing, so take the one at the path as it is now.
        try:
            held, now = os.fstat(fd), os.stat(path)
            if (held.st_dev, held.st_ino) == (now.st_dev, now.st_ino):
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode("ascii"))
    return fd


def sync_to_disk(path: Path) -> None:
    """Flush a file's data, or a folder's entries, to the disk: a file before it is renamed into
    place, its folder after, so that a power loss leaves the old file or the new one whole. A
    folder cannot be opened for that on Windows, and some file systems refuse to sync one (EINVAL):
    its rename is then as lasting as the file system makes it."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except (IsADirectoryError, PermissionError):
        return  # Windows opens no folder
    try:
        os.fsync(fd)
    except OSError as exc:
        if not (path.is_dir() and exc.errno in (errno.EINVAL, errno.EBADF, errno.ENOTSUP)):
            raise
    finally:
        os.close(fd)


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


def nearest_existing_folder(path: Path) -> Path:
    """``path``, or the nearest folder above it that exists: the one a mkdir of ``path`` writes in,
    and whose disk its files take room on."""
    where = path
    while not where.exists() and where != where.parent:
        where = where.parent
    return where


def check_folder_writable(out: Path, *, flag: str) -> None:
    """Refuse (ValidationError naming ``flag``), before minutes of work, an output folder ``out``
    that cannot be written: a mkdir found it only after the work, or a folder the user may not
    write by the first file written into it. Probed by making a hidden folder and removing it in
    ``out`` or the nearest folder above it that exists (the one mkdir writes in): os.access says
    yes to root for /proc or a read-only mount. Hidden, so one a kill leaves behind does not make
    the folder "hold files"."""
    where = nearest_existing_folder(out)
    try:
        if not where.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(where))
        os.rmdir(tempfile.mkdtemp(prefix=".sunrig-probe-", dir=where))
    except OSError as exc:
        raise ValidationError(f"{flag} {out}: cannot write there ({exc.strerror}: {where}); pass a folder you "
                              "can write to") from None


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
