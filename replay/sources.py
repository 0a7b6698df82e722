"""Open a recorded source by path: the one place that knows which reader fits which file.

Every command that takes a log (`replay`, `eval`, `train`) comes through here, so a new format
is added once. Today: a native log (.mcap), whose frames with GNSS time and position but no
truth get the true sun (``replay.groundtruth``), and a KITTI raw drive (a folder,
``replay.kitti``), whose timestamps need a UTC offset.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

from rig.errors import REINSTALL, LogError
from rig.types import Frame

# A 40-frame synthetic street drive (`sunrig synth OUT --drives 1 --frames 40 --seed 3000`, which
# makes it byte for byte), shipped so the quick start runs without any download. Remade with the
# writer of the day when the layout changes: it is the log users copy. Its /gnss/fix is empty, as
# in any log without GNSS: a synthetic drive has its sun (/sun/truth) and UTC, but no place.
DEMO_LOG = Path(__file__).resolve().parent / "data" / "demo.mcap"


def demo_log() -> Path:
    """:data:`DEMO_LOG`, or a LogError that says to reinstall: the user named no path, so "check
    the path" is no remedy for a demo log missing from the install."""
    if not DEMO_LOG.is_file():
        raise LogError(f"the demo log installed with sunrig ({DEMO_LOG}) is missing; {REINSTALL}, or pass a log")
    return DEMO_LOG

# The UTC offset for sources without a time zone when a caller does not pass one: set by
# `utc_offset_default` around code that opens logs itself (training opens its logs deep inside).
_UTC_OFFSET_H: ContextVar[float | None] = ContextVar("sunrig_utc_offset_h", default=None)


@contextmanager
def utc_offset_default(utc_offset_h: float | None) -> Iterator[None]:
    """Within the block, ``open_frames`` without ``utc_offset_h`` uses this one (None: the reader's
    own default, with its warning)."""
    token = _UTC_OFFSET_H.set(utc_offset_h)
    try:
        yield
    finally:
        _UTC_OFFSET_H.reset(token)


def open_frames(path: str | Path, *, utc_offset_h: float | None = None, ground_truth: bool = True) -> Iterable[Frame]:
    """A re-iterable source of Frames for ``path``; raises :class:`rig.errors.LogError` with a
    one-line message when the path is not a log it can read.

    - a folder: a KITTI raw drive (its date folder holding one drive, or the drive folder);
      ``utc_offset_h`` is the hours its timestamps are ahead of UTC (None: the context's
      :func:`utc_offset_default`, else KITTI's default of +2 h with a warning).
    - a file: a native log. Its timestamps are UTC already, so ``utc_offset_h`` does not apply.
      With ``ground_truth``, frames with GNSS time and position but no ``sun_enu_truth`` get it
      (TRUE or no heading only; see ``replay.groundtruth``).
    """
    p = Path(path)
    if p.is_dir():
        from replay.kitti import open_kitti

        if utc_offset_h is None:
            utc_offset_h = _UTC_OFFSET_H.get()
        return open_kitti(p, utc_offset_h=utc_offset_h)
    from replay.native import open_log

    source = open_log(p)
    if not ground_truth:
        return source
    from replay.groundtruth import with_ground_truth

    return with_ground_truth(source)


def corrupt_skipped(source: Iterable[Frame]) -> int:
    """How many damaged records the reader of ``source`` skipped in its latest pass (read it once
    the pass has ended): 0 for a source that counts none (a device, a list of frames).

    A record is what the reader decodes as one piece; a damaged one costs a frame, several, or only
    part of one, so this is not a count of frames:

    - a native log (``NativeLogSource.stats``): messages and chunks that did not decode. A chunk
      holds many frames; a bad heading, fix or truth message leaves its frame without that field.
    - a KITTI drive (``KittiDrive.corrupt_skipped``): images that did not decode and timestamps
      out of order (each skips its frame), and OXTS records that did not parse or were out of
      range (each leaves its frame without pose or truth).
    """
    count = getattr(source, "corrupt_skipped", None)  # a KITTI drive
    if count is None:
        # A native log, bare or inside its GroundTruthSource (which passes its attributes through).
        # A camera driver's ``stats`` is a method, with no such field: 0.
        count = getattr(getattr(source, "stats", None), "corrupt_skipped", None)
    return int(count or 0)
