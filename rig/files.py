"""Output folders: made when missing, refused in one line when they cannot be; output files
replaced whole or not at all."""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

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
    tmp = path.with_name(f".{path.stem}.tmp{path.suffix}")
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)  # a torn copy would only hold a full disk full
        if isinstance(exc, OSError) and exc.filename is None:  # name the file the error is about
            raise OSError(exc.errno, exc.strerror, str(path)) from exc
        raise
