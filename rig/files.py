"""Output folders: made when missing, refused in one line when they cannot be."""

from __future__ import annotations

import os
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
