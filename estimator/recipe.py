"""The training recipe's settings, apart from the trainer: ``sunrig train``'s options take their
defaults from here without importing torch, so the CLI and the library cannot drift apart."""

from __future__ import annotations

import hashlib
import shlex
import sys
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


@dataclass
class TrainConfig:
    preset: str = "fast"
    layers: int = 0  # transformer layers; 0: the preset's
    minutes: float = 80.0  # wall-clock budget of this and earlier (resumed) sessions together
    max_steps: int = 0  # 0: until the time budget ends
    batch_windows: int = 6
    lr: float = 5e-4
    weight_decay: float = 0.05
    warmup_steps: int = 300
    subset_prob: float = 0.3
    hard_share: float = 0.5  # windows whose drive is drawn by its running error
    mirror_share: float = 0.5  # windows mirrored left to right (mirror_window)
    live_share: float = 0.0  # windows whose frames are those the rig's window policy picks
    # Weight of nets.tail_loss on each full window's estimate: misses beyond the margin cost more.
    tail_weight: float = 0.0
    tail_margin_deg: float = 15.0
    # Export a moving average of the weights, decayed by this much a step, instead of the last
    # step's (0: the last step's). It smooths the step-to-step noise of the final weights.
    ema_decay: float = 0.0
    precision: str = "auto"  # auto: bf16 autocast where the CPU has native bf16, else fp32
    init: str = ""  # a model folder whose weights.npz a new run starts from (fine-tuning)
    frames_per_window: int = 8
    crops_per_frame: int = 0  # 0: the resumed checkpoint's, else the paper's 4
    # One angle, or one per crop scale (a frame's crops shared among them); 0: the --init model's,
    # else the paper's 17.6 deg (PAPER_CROP_FOV_DEG).
    crop_fov_deg: float | tuple[float, ...] = 0.0
    seed: int = 0
    threads: int = 0  # 0: all cores
    checkpoint_every_s: float = 300.0
    # Recorded in the contract; filled by the CLI.
    command: str = ""
    data: dict[str, Any] = field(default_factory=dict)


def data_fingerprint(paths: Sequence[Path]) -> str:
    """Short hash of the logs' names and sizes, recorded in the contract: of a run's training
    logs, and of an int8 model's calibration logs.

    A native log (a file) counts by its file name and size. A KITTI drive (a folder: its date
    folder or its drive folder, one fingerprint either way) counts by the files its reader uses,
    named from the date folder, so a copy elsewhere is the same data. Sizes, not contents: a
    drive holds thousands of images, stat-ed here rather than read."""
    h = hashlib.sha256()
    for _, files in sorted(_log_files(Path(p)) for p in paths):
        for name, size in files:
            h.update(name.encode())
            h.update(str(size).encode())
    return h.hexdigest()[:12]


def _log_files(path: Path) -> tuple[Path, list[tuple[str, int]]]:
    """(where the log sorts among the others, its files' names and sizes)."""
    if not path.is_dir():
        # As the shipped models' contracts recorded it: the same bytes hashed, in path order.
        return path, [(path.name, path.stat().st_size)]
    from replay.kitti import drive_files, find_drive

    date_dir, drive_dir = find_drive(path)
    calib, *used = drive_files(date_dir, drive_dir)
    # A NUL between name and size, which no file name holds: a name cannot pass for a size.
    files = [(f"{calib.name}\0", calib.stat().st_size)]
    files += [(f"{drive_dir.name}/{f.relative_to(drive_dir).as_posix()}\0", f.stat().st_size) for f in used]
    return drive_dir, files


def command_line() -> str:
    """This process's command as a shell would take it again: an argument with spaces (a
    ``--data-note``) stays one argument, so a recorded command can be copied and run."""
    return "sunrig " + shlex.join(sys.argv[1:])
