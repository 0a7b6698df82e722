"""Procedural street drives with a known sun: training and test data no download can give here.

Each drive is a random street (road with markings, sidewalks, buildings with windows, trees,
poles, signs, walls, cars) under a Preetham sky with the sun at a random azimuth and an
elevation of 5-75 deg, seen by a KITTI-like camera on a vehicle that drives straights, bends and
corners. Lambertian shading (sun plus sky and ground ambient) and cast shadows (onto the ground
and onto other objects) follow exactly the sun in ``Frame.sun_enu_truth``.

    from replay.synthetic import synth_drive, write_synthetic_logs
    for frame in synth_drive(seed=3, n_frames=40): ...
    write_synthetic_logs("data/synth", drives=100, frames=40, seed=0)

Modules: ``scene`` (road path, ground map, solids, random layout), ``sky`` (Preetham sky, sun,
ambient), ``render`` (rasteriser, shading, shadows), ``camera`` (exposure, noise, tone curve),
``drive`` (parameters, trajectory, the Frame stream).
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np

from replay.synthetic.camera import CameraEffects
from replay.synthetic.drive import KITTI_INTRINSICS, Drive, DriveParams, kitti_intrinsics, plan_drive, synth_drive
from rig.types import Intrinsics

__all__ = [
    "KITTI_INTRINSICS",
    "CameraEffects",
    "Drive",
    "DriveParams",
    "drive_seed",
    "kitti_intrinsics",
    "plan_drive",
    "synth_drive",
    "write_synthetic_logs",
]


def drive_seed(seed: int, index: int) -> int:
    """The seed of drive ``index`` of a set made with ``seed``: independent streams per drive."""
    return int(np.random.SeedSequence([int(seed), int(index)]).generate_state(1, dtype=np.uint32)[0])


class _Progress:
    """tqdm when installed, else a counter on stderr."""

    def __init__(self, total: int, enabled: bool, desc: str) -> None:
        self.total, self.enabled, self.n = total, enabled, 0
        self._bar = None
        if enabled:
            try:
                from tqdm import tqdm
            except ImportError:
                pass
            else:
                self._bar = tqdm(total=total, desc=desc, unit="frame")

    def update(self, n: int = 1) -> None:
        self.n += n
        if self._bar is not None:
            self._bar.update(n)
        elif self.enabled:
            print(f"\rsynthetic: {self.n}/{self.total} frames", end="", file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        elif self.enabled:
            print(file=sys.stderr)


def write_synthetic_logs(out_dir: str | os.PathLike[str], *, drives: int, frames: int, seed: int,
                         intrinsics: Intrinsics | None = None, progress: bool = True,
                         render_scale: float = 0.5) -> list[Path]:
    """Write ``drives`` native logs of ``frames`` frames each, ``drive_{seed}_{i:04d}.mcap``.

    Drive i uses :func:`drive_seed` (seed, i), so any one log can be remade alone. Returns the
    paths in order. Images go through the log writer's JPEG encoder.
    """
    from replay.native import LogWriter

    if drives < 0 or frames < 1:
        raise ValueError(f"write_synthetic_logs: expected drives >= 0 and frames >= 1, got {drives}, {frames}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    bar = _Progress(drives * frames, progress, "synthetic drives")
    paths = []
    try:
        for i in range(drives):
            path = out / f"drive_{seed}_{i:04d}.mcap"
            drive = Drive(drive_seed(seed, i), frames, intrinsics=intrinsics, render_scale=render_scale)
            with LogWriter(path) as writer:
                for frame in drive.frames():
                    writer.write_frame(frame)
                    bar.update()
            paths.append(path)
    finally:
        bar.close()
    return paths
