"""Open a recorded source by path: the one place that knows which reader fits which file.

Every command that takes a log (`replay`, `eval`, `train`) comes through here, so a new format
(a KITTI drive, say) is added once.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from rig.types import Frame

# A 40-frame synthetic street drive (`sunrig synth OUT --drives 1 --frames 40 --seed 3000`),
# shipped so the quick start runs without any download.
DEMO_LOG = Path(__file__).resolve().parent / "data" / "demo.mcap"


def open_frames(path: str | Path) -> Iterable[Frame]:
    """A re-iterable source of Frames for ``path``; raises :class:`rig.errors.LogError` with a
    one-line message when the path is not a log it can read."""
    from replay.native import open_log

    return open_log(Path(path))
