"""Training: backbone and transformer end to end on any logs that carry the true sun.

Train extra only (torch). The recipe follows the paper (Sec. 3-4): random 8-frame windows from one
drive, n random crops per frame, the cyclic encoding of (yaw, view angles), per-token vectors
calibrated by each frame's yaw, and L = cosine + norm + hemisphere. What differs, and why:

- Frames are stored pre-scaled so that a crop of the contract's angular size is exactly
  ``crop_size`` pixels: cutting a crop is then a slice, not a resize, and a drive of 1242 x 375
  frames fits in memory at 128 px crops (scale 0.57). A model whose crops mix angles holds every
  frame once per angle (a wider angle, a smaller copy: 17.6 and 26 deg at 96 px take 258 and
  116 kB a frame, 16 GB for the 43 200 frames of the shipped recipe's data).
- The loss is taken on every token's calibrated vector and on the window mean: the mean is the
  paper's estimate, the per-token terms keep each token a usable estimate on its own.
- A share of windows keeps only a random subset of tokens (down to one): live windows while the
  ring fills are short, and the `single`/`mean`/`meanshift` baselines run tokens alone.
- A random global yaw offset per window rotates the truth and every heading together. With yaw
  fed relative to the newest frame (docs/conventions.md) the network's input is unchanged by it,
  so this only guards the calibration path; it costs nothing.
- The backbone starts from scratch (no ImageNet weights can be downloaded here) with a higher
  learning rate than the paper's fine-tuning rate of 2e-5.
- Hard drives are drawn more often: each drive keeps a running error of its full windows, and a
  share of windows (``hard_share``) picks drives in proportion to it. The held-out errors that
  matter most are the worst ones (low sun, dimmed sun, few shadows), and uniform sampling spends
  most steps on drives the model has already solved.
- ``precision="bf16"`` runs the forward pass under bf16 autocast with channels-last images (on
  CPUs with native bfloat16, AMX / AVX512-BF16; "auto" picks it there); weights, the loss and the
  exported graphs stay float32. It buys 1.1-1.3x the steps per minute for the fast preset on this
  machine (``python3 benchmarks/bench_train.py``: 0.24 against 0.27-0.31 s per step).

Checkpoints (``checkpoint.pt`` in the output folder, written atomically every few minutes and at
the end) hold weights, optimiser, step and random state: a run that is killed resumes where it
stopped when started again with the same ``--out``. While a run trains it holds its folder
(:func:`run_lock`): a second process on it is refused. The final model is exported as the two ONNX
graphs with the contract, including the command and data that produced it.
"""

from __future__ import annotations

import contextlib
import io
import json
import logging
import math
import os
import re
import shutil
import time
import zipfile
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from estimator.calibration import mirrored_angles, mirrored_enu
from estimator.contract import (
    AGGREGATOR_FILE,
    BACKBONE_FILE,
    CHECKPOINT,
    CONTRACT_REMEDY,
    MAX_CROPS_PER_FRAME,
    PAPER_CROP_FOV_DEG,
    PAPER_CROPS_PER_FRAME,
    WEIGHTS_FILE,
    format_fovs_deg,
    fovs_deg,
    input_affine,
    is_crop_fov_deg,
)
from estimator.crops import MAX_CROP_ENLARGEMENT, crop_side_px, crops_per_scale
from estimator.recipe import TrainConfig, data_fingerprint
from rig.errors import ContractMismatch, SunrigError, ValidationError, require_torch
from rig.files import check_folder_writable, folder_lock, make_output_folder, sync_to_disk, write_replacing
from rig.geometry import az_el_from_enu, view_angles_rad, wrap_pi
from rig.ring import DEFAULT_MAX_AGE_S, UTC_DISAGREEMENT_TOLERANCE_S
from rig.types import Frame, HeadingRef
from rig.window import SpreadWindowPolicy

require_torch()  # a missing torch names the extra to install
import torch  # noqa: E402  (imported, not require_torch's value, so mypy types it)

from estimator import nets  # noqa: E402  (needs torch, checked just above)
from estimator.export import STAGING_PREFIX, export_model  # noqa: E402

log = logging.getLogger(__name__)
# The trained weights beside the exported graphs, as plain arrays (float16, no pickle, ignored by
# the runtime): what ``--init`` starts a fine-tuning run from. The ONNX graphs cannot serve, since
# export folds batch-norm into the convolutions.
METRICS = "train_metrics.jsonl"  # one line per 50 steps, appended across resumes (see _trim_metrics)


class TrainingDataError(SunrigError):
    """The logs given to training cannot train anything (no frames with a TRUE heading and true sun)."""


class CheckpointError(SunrigError):
    """A run's ``checkpoint.pt`` cannot be used: damaged (cut short, emptied, overwritten) or not
    a training run's. The message names the file and how to go on without it."""


class TrainingDivergedError(SunrigError):
    """Training diverged: a loss that is not finite, or weights that are not finite or beyond
    float16 (which ``weights.npz`` keeps). A lower ``--lr`` does; nothing diverged is saved."""


class BatchMemoryError(SunrigError):
    """A training step's batch does not fit in memory: fewer windows a step (``--batch``), or
    fewer crops a frame (``--crops``), do."""


# ------------------------------------------------------------------------------------------
# Data


@dataclass
class DriveView:
    """A drive's frames scaled for one crop angle, so that a crop of that angle is exactly
    ``crop_size`` pixels: images (F, h, w, 3) uint8 BGR and the intrinsics scaled with them."""

    images: np.ndarray
    fx: float
    fy: float
    cx: float
    cy: float


@dataclass
class Drive:
    """One log's usable frames: one view per crop angle (the contract's order) and per-frame values."""

    name: str
    views: tuple[DriveView, ...]
    yaw_rad: np.ndarray  # (F,)
    sun_enu: np.ndarray  # (F, 3)
    t_s: np.ndarray  # (F,) monotonic time of each frame, for windows drawn as the rig draws them

    @property
    def images(self) -> np.ndarray:
        """The first crop angle's images (every view has the same frames)."""
        return self.views[0].images


def _scaled(frame: Frame, crop_size: int, crop_fov_rad: float) -> tuple[np.ndarray, float]:
    side = crop_side_px(frame.intrinsics, crop_fov_rad)
    scale = crop_size / side
    img = frame.image_bgr
    if abs(scale - 1.0) > 1e-6:
        size = (max(crop_size, round(img.shape[1] * scale)), max(crop_size, round(img.shape[0] * scale)))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    return img, scale


def trainable(frame: Frame) -> bool:
    """A frame training can use: a heading and a true sun in the same world, true-north ENU. A
    RELATIVE or MAGNETIC heading would pair the truth with yaws turned by an unknown offset."""
    # The rule of replay.groundtruth.truth_allowed, for frames that have a heading.
    has_true_heading = frame.attitude is not None and frame.attitude.reference == HeadingRef.TRUE
    return has_true_heading and frame.sun_enu_truth is not None


# MAX_CROP_ENLARGEMENT (estimator/crops.py): beyond it a crop is interpolation to the network, and
# every frame is stored over 16x its recorded size (--crop-fov 0.1 on a KITTI frame is one pixel,
# enlarged 96x to the fast preset's crops: 12 GB a frame).


def _check_crop_span(frame: Frame, name: str, crop_size: int, crop_fov_rad: float) -> None:
    k = frame.intrinsics
    need = math.ceil(crop_size / MAX_CROP_ENLARGEMENT)  # source pixels a crop must span
    if min(k.width, k.height) < need:
        raise ValidationError(f"{name}: its frames ({k.width}x{k.height} px) are too small for {crop_size} px crops: "
                              f"a crop needs at least {need} px of them; leave this log out, or train from scratch "
                              "with a preset of smaller crops (a fine-tune keeps its --init model's)")
    side = crop_side_px(k, crop_fov_rad)
    if side < need:
        # The least angle whose crop rounds to `need` px (crop_side_px rounds), up to the 0.01 deg shown.
        least = math.ceil(math.degrees(2.0 * math.atan((need - 0.5) / (2.0 * k.fx))) * 100.0) / 100.0
        raise ValidationError(
            f"{name}: --crop-fov {math.degrees(crop_fov_rad):g} deg spans {side} px of its frames (fx {k.fx:g}), "
            f"enlarged {crop_size / side:.0f}x to {crop_size} px crops; for this camera pass a --crop-fov of at "
            f"least {least:.2f} deg ({need} px: enlarged more than {MAX_CROP_ENLARGEMENT}x, a crop is interpolation "
            f"to the network's first stage, and each frame is stored at over {MAX_CROP_ENLARGEMENT ** 2}x its size)")


def _view(usable: Sequence[Frame], name: str, crop_size: int, crop_fov_rad: float) -> DriveView:
    for frame in {f.intrinsics: f for f in usable}.values():  # once per camera, before any frame is scaled
        _check_crop_span(frame, name, crop_size, crop_fov_rad)
    images, scales = zip(*(_scaled(f, crop_size, crop_fov_rad) for f in usable), strict=True)
    shapes = {im.shape for im in images}
    if len(shapes) > 1:
        raise TrainingDataError(f"{name}: frames of different sizes in one drive ({sorted(shapes)}); split the log")
    k, s = usable[0].intrinsics, scales[0]
    # Intrinsics scale with the image about the pixel grid's corner (continuous coordinates).
    return DriveView(np.stack(images), fx=k.fx * s, fy=k.fy * s, cx=k.cx * s, cy=k.cy * s)


def load_drive(frames: Sequence[Frame], name: str, crop_size: int,
               crop_fov_rad: float | Sequence[float]) -> Drive | None:
    """A drive from its frames, one view per crop angle; frames without a TRUE heading or true sun
    are left out (None if none)."""
    usable = [f for f in frames if trainable(f)]
    if not usable:
        return None
    fovs = (crop_fov_rad,) if isinstance(crop_fov_rad, int | float) else tuple(crop_fov_rad)
    yaw_rad, sun_enu = [], []
    for f in usable:
        assert f.attitude is not None and f.sun_enu_truth is not None  # what trainable() checked
        yaw_rad.append(f.attitude.heading_rad)
        sun_enu.append(f.sun_enu_truth)
    return Drive(name=name, views=tuple(_view(usable, name, crop_size, fov) for fov in fovs),
                 yaw_rad=np.array(yaw_rad), sun_enu=np.stack(sun_enu),
                 t_s=np.array([f.t_mono_s for f in usable], dtype=np.float64))


def split_at_clock_jumps(frames: Sequence[Frame], max_gap_s: float = DEFAULT_MAX_AGE_S) -> list[list[Frame]]:
    """``frames`` in runs of one clock: a new run wherever the time steps back (a source that
    restarted its clock) or forward by more than ``max_gap_s`` (a recording paused), or where a
    frame and the one before both carry UTC and their UTC difference disagrees with their
    monotonic one by more than ``rig.ring.UTC_DISAGREEMENT_TOLERANCE_S`` (a suspend, which the
    monotonic clock does not count, or a clock set). The rig never puts frames across such a jump
    in one window (``rig.ring.FrameRing`` starts again, and the window span is shorter than the
    gap), and training must not either: a window across it paired frames an hour apart under one
    sun, and the live draws' binary search over times out of order picked frames of both runs."""
    runs: list[list[Frame]] = []
    for f in frames:
        if not runs or _clock_jumps(runs[-1][-1], f, max_gap_s):
            runs.append([])
        runs[-1].append(f)
    return runs


def _clock_jumps(before: Frame, f: Frame, max_gap_s: float) -> bool:
    """Whether the clock jumped between two frames of a log (:func:`split_at_clock_jumps`)."""
    mono_s = f.t_mono_s - before.t_mono_s
    if mono_s < 0 or mono_s > max_gap_s:
        return True
    if before.utc_ns is None or f.utc_ns is None:
        return False  # nothing to compare, as in the ring
    return abs((f.utc_ns - before.utc_ns) / 1e9 - mono_s) > UTC_DISAGREEMENT_TOLERANCE_S


def split_at_camera_changes(frames: Sequence[Frame]) -> list[list[Frame]]:
    """``frames`` in runs of one camera (one set of intrinsics): a new run wherever they change (a
    resolution or calibration changed mid-recording). A drive is scaled and cropped by one
    camera's intrinsics (:class:`DriveView`): frames of another size could not be stacked with it,
    and frames of the same size took the first camera's view angles."""
    runs: list[list[Frame]] = []
    for f in frames:
        if not runs or f.intrinsics != runs[-1][-1].intrinsics:
            runs.append([])
        runs[-1].append(f)
    return runs


def load_drives(paths: Sequence[Path], crop_size: int, crop_fov_rad: float | Sequence[float],
                read_frames: Callable[[Path], Iterable[Frame]] | None = None,
                progress: Callable[[int, int], None] | None = None) -> list[Drive]:
    """Every log as one drive, or one per run of its clock (:func:`split_at_clock_jumps`) and of
    its camera (:func:`split_at_camera_changes`). ``read_frames`` defaults to the native log reader."""
    if read_frames is None:
        from replay.sources import open_frames

        read_frames = open_frames
    from estimator.evaluate import TruthTally

    drives = []
    lacking: list[str] = []  # of the logs left out: each with what its frames lack
    for i, path in enumerate(paths):
        tally = TruthTally()
        clock_runs = split_at_clock_jumps([f for f in tally.counted(read_frames(Path(path))) if trainable(f)])
        if len(clock_runs) > 1:
            log.warning("%s: its clock jumps %d times (at seq %s); trained as %d drives, no window across a jump",
                        path, len(clock_runs) - 1, ", ".join(str(r[0].seq) for r in clock_runs[1:6]), len(clock_runs))
        runs = [part for run in clock_runs for part in split_at_camera_changes(run)]
        if len(runs) > len(clock_runs):
            starts = {id(run[0]) for run in clock_runs}
            changes = [r[0].seq for r in runs if id(r[0]) not in starts]
            log.warning("%s: its camera changes %d time%s (at seq %s); trained as %d drives, each of one camera",
                        path, len(changes), "" if len(changes) == 1 else "s", ", ".join(map(str, changes[:5])),
                        len(runs))
        named = [(Path(path).name, run) for run in runs] if len(runs) <= 1 else [
            (f"{Path(path).name}#{k}", run) for k, run in enumerate(runs)]
        loaded = [d for name, run in named if (d := load_drive(run, name, crop_size, crop_fov_rad)) is not None]
        drives.extend(loaded)
        if not loaded:
            lacking.append(f"{path}: {tally.why()}")
            if len(paths) > 1:  # said once, at the end, when none is usable
                log.warning("%s: no frame with both a TRUE heading and the true sun (%s); not trained on", path,
                            tally.why())
        if progress:
            progress(i + 1, len(paths))
    if not drives:
        # One log: its cause is said here, as no warning said it.
        cause = f" ({lacking[0]})" if len(lacking) == 1 else " (the warnings above say what each lacks)"
        raise TrainingDataError(
            f"none of the logs has frames with both a TRUE heading and the true sun{cause}; "
            "train on logs from `sunrig synth`, KITTI drives, or recordings with GNSS time and position"
        )
    return drives


@dataclass
class Batch:
    crops: np.ndarray  # (B, T, S, S, 3) uint8 BGR
    angles: np.ndarray  # (B, T, 3) float32: yaw relative to the newest frame, horizontal, vertical
    yaw: np.ndarray  # (B, T) float64 absolute yaw (with the random global offset)
    mask: np.ndarray  # (B, T) bool
    truth: np.ndarray  # (B, 3) float64 ENU (with the random global offset)
    drive: np.ndarray  # (B,) int index of each window's drive in the sampler
    frame_index: np.ndarray  # (B, F) int: each window's frames in its drive, ascending (the last the newest)


class WindowSampler:
    """Random windows: a drive, ``frames`` of its frames, ``crops`` random crops each, shared
    among the drive's crop angles as the runtime shares them (:func:`estimator.crops.crops_per_scale`).

    A ``hard_share`` of windows draws its drive in proportion to the drive's running error
    (:meth:`record`); the rest in proportion to drive length, so every frame is equally likely.
    A drive not yet seen counts as :data:`UNSEEN_ERR_DEG`, so early hard draws explore.
    A ``mirror_share`` of windows is mirrored left to right (:func:`mirror_window`).

    A ``live_share`` of windows takes its frames as the rig does: the newest frame anywhere in the
    drive where the live window policy (:class:`rig.window.SpreadWindowPolicy`) finds ``frames``
    frames, and the frames that policy picks before it. The rest are ``frames`` frames drawn at
    random from the whole drive, whose newest is then nearly always near the drive's end (of 24
    frames, frame 20 or later in 83 % of windows) and whose frames span most of it. The rig's
    first windows of a drive, a short span of frames close together, are then all but never
    drawn (newest frame 7, the rig's first window: 1 in 735 471); they are where the held-out
    errors are largest (``docs/model.md``).
    """

    UNSEEN_ERR_DEG = 90.0
    ERR_EMA = 0.3  # weight of the newest window in a drive's running error

    def __init__(self, drives: Sequence[Drive], frames: int, crops: int, crop_size: int,
                 subset_prob: float, rng: np.random.Generator, hard_share: float = 0.0,
                 mirror_share: float = 0.0, live_share: float = 0.0) -> None:
        self.drives = list(drives)
        self.frames, self.crops, self.size = frames, crops, crop_size
        self.subset_prob = subset_prob
        self.hard_share = hard_share
        self.mirror_share = mirror_share
        self.live_share = live_share
        self.policy = SpreadWindowPolicy(n_frames=frames)
        # Per drive: the frames that can be a live window's newest, those with a full window.
        self.live_newest = [self._full_window_ends(d.t_s) for d in self.drives]
        self.rng = rng
        lengths = np.array([len(d.images) for d in self.drives], dtype=np.float64)
        self.p = lengths / lengths.sum()
        n_views = {len(d.views) for d in self.drives}
        if len(n_views) > 1:
            raise ValidationError(f"drives with different numbers of crop angles ({sorted(n_views)}); load them alike")
        # The view each crop of a frame is cut from, grouped by angle in the contract's order.
        self.crop_view = np.repeat(np.arange(n_views.pop()), crops_per_scale(crops, len(self.drives[0].views)))
        self.err_deg = np.full(len(self.drives), self.UNSEEN_ERR_DEG)

    def _full_window_ends(self, t_s: np.ndarray) -> np.ndarray:
        newest = np.arange(len(t_s))
        return np.flatnonzero(newest - self.policy.pool_start(t_s, newest) + 1 >= self.frames)

    def _frame_indices(self, drive_index: int) -> np.ndarray:
        """The window's frames of the drive, ascending (the last is the newest)."""
        rng, d = self.rng, self.drives[drive_index]
        # Drawn only when asked for, so a run without live windows draws what it always did.
        ends = self.live_newest[drive_index]
        if self.live_share > 0.0 and rng.random() < self.live_share and len(ends):
            newest = int(rng.choice(ends))
            return np.array(self.policy.select_indices(d.t_s[: newest + 1], d.yaw_rad[: newest + 1]))
        n = len(d.images)
        return np.sort(rng.choice(n, size=self.frames, replace=n < self.frames))

    def record(self, drive_index: np.ndarray, err_deg: np.ndarray) -> None:
        """Fold full windows' errors into their drives' running errors."""
        for i, e in zip(drive_index, err_deg, strict=True):
            self.err_deg[i] += self.ERR_EMA * (float(e) - self.err_deg[i])

    def _drive_index(self) -> int:
        rng = self.rng
        if self.hard_share > 0.0 and rng.random() < self.hard_share:
            w = self.err_deg * self.p
            return int(rng.choice(len(self.drives), p=w / w.sum()))
        return int(rng.choice(len(self.drives), p=self.p))

    def sample(self, batch: int) -> Batch:
        t = self.frames * self.crops
        s = self.size
        out = Batch(
            crops=np.empty((batch, t, s, s, 3), np.uint8),
            angles=np.empty((batch, t, 3), np.float32),
            yaw=np.empty((batch, t)),
            mask=np.ones((batch, t), bool),
            truth=np.empty((batch, 3)),
            drive=np.empty(batch, np.int64),
            frame_index=np.empty((batch, self.frames), np.int64),
        )
        rng = self.rng
        for b in range(batch):
            out.drive[b] = self._drive_index()
            d = self.drives[out.drive[b]]
            idx = out.frame_index[b] = self._frame_indices(int(out.drive[b]))
            newest = idx[-1]
            offset = rng.uniform(0.0, 2.0 * math.pi)
            views = [d.views[v] for v in self.crop_view]  # per crop of a frame
            h = np.array([v.images.shape[1] for v in views])
            w = np.array([v.images.shape[2] for v in views])
            x0 = rng.integers(0, w - s + 1, size=(self.frames, self.crops))
            y0 = rng.integers(0, h - s + 1, size=(self.frames, self.crops))
            fx, fy, cx, cy = np.array([(v.fx, v.fy, v.cx, v.cy) for v in views]).T  # each (crops,)
            hz, vt = view_angles_rad(x0 + s / 2.0, y0 + s / 2.0, fx, fy, cx, cy)
            for j, fi in enumerate(idx):
                for c in range(self.crops):
                    k = j * self.crops + c
                    out.crops[b, k] = views[c].images[fi, y0[j, c] : y0[j, c] + s, x0[j, c] : x0[j, c] + s]
                rows = slice(j * self.crops, (j + 1) * self.crops)
                out.angles[b, rows, 0] = wrap_pi(d.yaw_rad[fi] - d.yaw_rad[newest])
                out.angles[b, rows, 1] = hz[j]
                out.angles[b, rows, 2] = vt[j]
                out.yaw[b, rows] = d.yaw_rad[fi] + offset
            cos_o, sin_o = math.cos(offset), math.sin(offset)
            x, y, z = d.sun_enu[newest]
            out.truth[b] = (cos_o * x + sin_o * y, -sin_o * x + cos_o * y, z)  # world_from_heading(offset)
            if rng.random() < self.subset_prob:
                keep = rng.integers(1, t + 1)
                out.mask[b] = False
                out.mask[b, rng.choice(t, size=keep, replace=False)] = True
            # Drawn last and only when asked for, so a run without mirroring draws what it always did.
            if self.mirror_share > 0.0 and rng.random() < self.mirror_share:
                mirror_window(out, b)
        return out


def mirror_window(batch: Batch, b: int) -> None:
    """Turn window ``b`` of ``batch`` into the same drive in a world mirrored about the north-up
    plane, in place: each crop flipped left to right, east negated, headings and horizontal view
    angles negated (compass angles and view angles both turn the other way in a mirror).

    A mirrored frame is a real pinhole image of the mirrored street (principal point at w - cx,
    which only moves where a crop's angle is measured from, not the angle), so the cues stay
    physically consistent: the sky brighter on the sun's side, shadows away from it. It doubles
    the layouts a model sees per drive without rendering any."""
    batch.crops[b] = batch.crops[b, :, :, ::-1]
    batch.angles[b] = mirrored_angles(batch.angles[b])
    batch.yaw[b] *= -1.0
    batch.truth[b] = mirrored_enu(batch.truth[b])


# ------------------------------------------------------------------------------------------
# Training


LR_FLOOR = 0.02  # the schedule ends at this share of the peak rate


@dataclass
class Schedule:
    """Warmup, then cosine from ``start_lr`` at ``start_step`` down to the floor at the run's end.

    A first run starts at step 0 from the peak rate. A run resumed with a longer budget starts a
    new segment from the rate it stopped at, so the rate never rises again on resume: stretching
    the original cosine over the new budget would lift a nearly finished run back to a high rate
    and undo its last minutes (seen: 85 + 12 minutes trained to a worse model than 85).
    """

    start_step: int = 0
    start_lr: float = 0.0  # 0: the config's peak rate
    minutes: float = 0.0  # the budget this segment was planned for

    def lr_at(self, step: int, total: int, cfg: TrainConfig) -> float:
        peak = self.start_lr or cfg.lr
        # At most a tenth of a --steps run: a 150-step fine-tune would otherwise end still warming
        # up, never reaching its --lr. (A --minutes run learns its length only after 20 steps; a
        # warmup fixed from that would jump there.)
        warmup = max(1, min(cfg.warmup_steps, cfg.max_steps // 10)) if cfg.max_steps else cfg.warmup_steps
        if self.start_step == 0 and step < warmup:
            return peak * (step + 1) / warmup
        begin = max(self.start_step, warmup if self.start_step == 0 else 0)
        frac = min(1.0, max(0.0, (step - begin) / max(1, total - begin)))
        floor = LR_FLOOR * cfg.lr
        return floor + (peak - floor) * 0.5 * (1.0 + math.cos(math.pi * frac))


def net_config(cfg: TrainConfig) -> nets.NetConfig:
    """The networks a run trains: its preset, with ``cfg.layers`` transformer layers if given."""
    preset = nets.PRESETS[cfg.preset]
    return replace(preset, layers=cfg.layers) if cfg.layers else preset


def use_bf16(precision: str) -> bool:
    """Whether to train under bf16 autocast: only where the CPU computes bf16 natively, since
    emulated bf16 is slower than float32."""
    if precision not in ("auto", "bf16", "fp32"):
        raise ValidationError(f"precision: expected auto, bf16 or fp32, got {precision!r}")
    if precision == "auto":
        return bool(torch.backends.mkldnn.is_available() and torch.ops.mkldnn._is_mkldnn_bf16_supported())
    return precision == "bf16"


# Runnable processes beyond training's own threads above which the CPU counts as shared.
BUSY_EXTRA_LOAD = 0.5


def other_cpu_load(threads: int) -> float | None:
    """The 1-minute load average beyond ``threads`` (training's own), or None where the OS has
    no load average. A minutes budget on a shared CPU trains fewer steps and a weaker model
    (docs/model.md, "Training", measures it)."""
    try:
        return os.getloadavg()[0] - threads
    except (AttributeError, OSError):
        return None


class _Normaliser:
    """The contract's input normalisation, as torch ops on a uint8 NHWC batch."""

    def __init__(self, input_norm: dict[str, Any]) -> None:
        swap, gain, offset = input_affine(input_norm)
        self.swap = swap
        self.gain = torch.tensor(gain, dtype=torch.float32).view(1, 3, 1, 1)
        self.offset = torch.tensor(offset, dtype=torch.float32).view(1, 3, 1, 1)

    def __call__(self, crops_bgr: np.ndarray) -> Any:
        x = torch.from_numpy(crops_bgr).permute(0, 3, 1, 2).float()
        if self.swap:
            x = x.flip(1)
        return x * self.gain + self.offset


# What torch's CPU allocator says when the OS refuses it memory ("can't allocate memory" on Linux
# and macOS, "not enough memory" on Windows). It raises a bare RuntimeError, like any bug of ours,
# so only this text tells a batch too large for the machine from a bug.
_TORCH_ALLOC_FAILED = ("DefaultCPUAllocator: can't allocate memory", "DefaultCPUAllocator: not enough memory")


def _allocation_failed(exc: BaseException) -> bool:
    """Whether ``exc`` is a refused allocation: numpy's (a MemoryError) or torch's."""
    return isinstance(exc, MemoryError) or (
        isinstance(exc, RuntimeError) and any(said in str(exc) for said in _TORCH_ALLOC_FAILED))


def _gib(n_bytes: float) -> str:
    return f"{n_bytes / 2**30:.1f} GiB"


def _asked(exc: BaseException) -> str:
    """How much the refused allocation asked for, as its message says it (torch in bytes, numpy
    in its own units), or "" if it does not."""
    said = str(exc)
    if m := re.search(r"allocate (\d+) bytes", said):
        return _gib(int(m.group(1)))
    m = re.search(r"allocate ([\d.]+ [KMGTPE]?i?B)", said)
    return m.group(1) if m else ""


def _memory_bytes() -> int | None:
    """This machine's memory and swap together (``/proc/meminfo``), or None where the OS does not
    say: more than that, no process can hold. (A container's limit may be lower; that only makes
    the check below let through a batch that then fails at its first step.)"""
    try:
        with open("/proc/meminfo", encoding="ascii") as fh:
            kib = {key: int(rest.split()[0]) for key, rest in (line.split(":", 1) for line in fh)
                   if key in ("MemTotal", "SwapTotal")}
    except (OSError, ValueError, IndexError):
        return None
    return 1024 * (kib["MemTotal"] + kib.get("SwapTotal", 0)) if "MemTotal" in kib else None


def _batch_input_bytes(windows: int, tokens: int, crop_size: int) -> int:
    """A floor on a step's memory: its crops as the sampler's uint8 array and as the float32 input
    the backbone is called on, both alive then. The step needs more (activations, gradients), by
    an amount that depends on the preset; this part alone is exact."""
    return windows * tokens * crop_size * crop_size * 3 * (1 + 4)


def _check_batch_fits(windows: int, frames: int, crops_per_frame: int, crop_size: int) -> None:
    """Refuse, before minutes of loading data, a batch whose crops alone exceed the machine's
    memory and swap: it could never run here. A batch under that may still fail at its first step
    (the step's activations are not counted), which :func:`train` says the same way."""
    memory = _memory_bytes()
    tokens = frames * crops_per_frame
    need = _batch_input_bytes(windows, tokens, crop_size)
    if memory is not None and need > memory:
        raise BatchMemoryError(
            f"train: a step of {windows} windows x {tokens} crops ({windows * tokens} crops of {crop_size} px) "
            f"needs at least {_gib(need)} for its crops alone, more than the {_gib(memory)} of memory and swap "
            f"this machine has; {_smaller_batch_advice(windows, crops_per_frame)}")


def _check_layers(cfg: TrainConfig) -> None:
    """Refuse, before anything is built, a depth that cannot become a model: an aggregator graph
    beyond what one ONNX file holds (it would train, then fail to export), or networks whose
    training state alone exceeds the machine's memory and swap (--layers 100000 grew past 8 GB
    building them, with no step made)."""
    if not cfg.layers:
        return
    preset = nets.PRESETS[cfg.preset]
    sizes = preset.sizes()  # built once, for both bounds
    most = preset.max_layers(sizes)
    why = ("a deeper aggregator graph would pass the 2 GiB one ONNX file holds, so the model could not be "
           "exported")
    memory = _memory_bytes()
    if memory is not None:
        backbone, rest, layer = sizes
        # Training holds every value four times in float32: itself, its gradient and AdamW's two
        # moments. A floor, as for the batch: the activations come on top.
        fits = (memory // 16 - backbone - rest) // layer
        if fits < most:
            most, why = fits, (f"deeper, its weights, gradients and optimiser state alone would pass the "
                               f"{_gib(memory)} of memory and swap this machine has")
    if cfg.layers > most:
        raise ValidationError(f"layers: expected 1 to {most} for the {cfg.preset} preset ({why}), got {cfg.layers}")


def _smaller_batch_advice(windows: int, crops_per_frame: int) -> str:
    recipe = TrainConfig.batch_windows
    # Fewer crops than the paper's would change the recipe, so --crops is named only above it.
    fewer_crops = (f" or fewer --crops than {crops_per_frame}" if crops_per_frame > PAPER_CROPS_PER_FRAME
                   else "")
    return f"pass a smaller --batch{f' (the recipe is {recipe})' if windows > recipe else ''}{fewer_crops}"


# The largest weight weights.npz can hold: it keeps float16, where anything beyond is inf.
_FLOAT16_MAX = float(np.finfo(np.float16).max)


def _unfit_weights(parts: dict[str, dict[str, Any] | None]) -> list[str]:
    """The floating tensors (``part/name``) of state dicts that hold a value not finite or beyond
    float16's range. No trained network has such a weight (gradients are clipped at 1 and decayed),
    so it means the run diverged: weights.npz would hold inf and the exported graphs answer nan
    (a run at --lr 100 did both, and said "model written"). One pass over every weight: run at
    checkpoints and exports, not every step."""
    return [f"{part}/{key}" for part, tensors in parts.items() for key, t in (tensors or {}).items()
            if t.is_floating_point() and not bool((t.abs() <= _FLOAT16_MAX).all())]  # nan compares False


def _weights_of(state: dict[str, Any]) -> dict[str, dict[str, Any] | None]:
    """A checkpoint's state dicts of weights: the networks' and, with --ema-decay, their average's."""
    average = state.get("weight_average") or {}
    return {"backbone": state["backbone"], "aggregator": state["aggregator"],
            "average of backbone": average.get("backbone"), "average of aggregator": average.get("aggregator")}


def _arrays(names: list[str]) -> str:
    return f"{names[0]}{f' and {len(names) - 1} more arrays' if len(names) > 1 else ''}"


def _lower_lr_advice(lr: float) -> str:
    # The recipe's rate is named only below the one that diverged: a fine-tune's is lower still.
    recipe = f" (the recipe's is {TrainConfig.lr:g})" if lr > TrainConfig.lr else ""
    return f"a lower --lr than {lr:g}{recipe}"


def _save_checkpoint(path: Path, state: dict[str, Any]) -> None:
    # Serialised in memory first: torch.save reports a full disk as a bare RuntimeError ("unexpected
    # pos"), an internal error at the CLI; Python's own write says ENOSPC, with what to do.
    buffer = io.BytesIO()
    torch.save(state, buffer)
    write_synced(path, lambda tmp: tmp.write_bytes(buffer.getbuffer()))


def write_synced(path: Path, write: Callable[[Path], object]) -> None:
    """:func:`rig.files.write_replacing` (a kill mid-write leaves the old file), made to last a power
    loss too: the new file is on the disk before it is renamed over the old one, and the rename is
    on the disk (its folder synced) before this returns. Renamed with its data still in memory, a
    file can come back empty or torn after a power loss, with the old one gone."""
    def written(tmp: Path) -> None:
        write(tmp)
        if tmp.is_file():  # not a device or FIFO written in place, whose open could wait
            sync_to_disk(tmp)

    write_replacing(path, written)
    sync_to_disk(Path(path).parent)



# What each use of a checkpoint reads from it: an export the weights and how they were trained,
# a resume train()'s whole state besides.
_CHECKPOINT_KEYS_EXPORT = ("config", "backbone", "aggregator", "step", "elapsed_s")
_CHECKPOINT_KEYS_RESUME = (*_CHECKPOINT_KEYS_EXPORT, "optimizer", "rng", "torch_rng")


def load_checkpoint(path: Path, resume: bool) -> dict[str, Any]:
    """A run's checkpoint, checked whole before it is used (``resume``: to go on training, else
    to export): it loads, holds what that use reads, and its weights fit the networks its config
    names. Anything else is a :class:`CheckpointError` naming the file as damaged, raised before
    minutes of loading data rather than midway."""
    remedy = ("restore it from a copy to resume the run, or pass a new --out to train from the start" if resume
              else "restore it from a copy to export it, or train again with a new --out")

    def damaged(why: str) -> CheckpointError:
        return CheckpointError(f"{path} is damaged ({why}); {remedy}")

    if path.stat().st_size == 0:  # torch says only "Ran out of input"
        raise damaged("it is empty")
    try:
        state = torch.load(path, weights_only=False)
    except (OSError, MemoryError):
        raise  # the disk's or the machine's trouble, not the file's: the CLI words those itself
    except Exception as exc:
        # A file cut short or overwritten makes torch's zip reader or the unpickler raise nearly
        # anything: RuntimeError, EOFError, UnpicklingError, UnicodeDecodeError, AssertionError and
        # TypeError all came from flipping bytes of a real checkpoint. Each is the file's fault.
        # (torch's own advice runs on for three more sentences: the first says what failed.)
        raise damaged(f"{type(exc).__name__}: {str(exc).split('. ')[0]}") from exc
    keys = _CHECKPOINT_KEYS_RESUME if resume else _CHECKPOINT_KEYS_EXPORT
    missing = [key for key in keys if key not in state] if isinstance(state, dict) else list(keys)
    if missing:
        raise damaged(f"not a training run's state: no {', '.join(map(repr, missing))}")
    try:
        # Every module a resume or an export loads, loaded now: a state dict that fits no network
        # of the recorded preset would otherwise fail at the first step or the export.
        net_cfg = net_config(TrainConfig(**state["config"]))
        for weights in (state, state.get("weight_average")):
            if weights:
                modules_from(net_cfg, weights)
        if not (isinstance(state["step"], int) and isinstance(state["elapsed_s"], int | float)):
            raise TypeError(f"step {state['step']!r} and time {state['elapsed_s']!r} are not numbers")
    except (TypeError, KeyError, ValueError, RuntimeError, AttributeError) as exc:
        said = " ".join(str(exc).split())  # load_state_dict's list of keys runs over many lines
        raise damaged(f"its weights do not fit the networks its settings name: {type(exc).__name__}: "
                      f"{said if len(said) <= 160 else said[:157] + '...'}") from exc
    bad = _unfit_weights(_weights_of(state))
    if bad:  # written before training checked for divergence
        raise TrainingDivergedError(
            f"{path} holds weights that are not finite or beyond float16 ({_arrays(bad)}): its run "
            f"diverged by step {state['step']}, and there is nothing to {'resume' if resume else 'export'}; "
            f"train again in a new --out with {_lower_lr_advice(float(state['config'].get('lr', TrainConfig.lr)))}")
    return state


def _trim_metrics(path: Path, step: int) -> int:
    """Keep the metric lines up to ``step``, the checkpoint a run resumes from; returns how many
    were dropped. Lines after it describe steps a kill threw away (they are trained again), and a
    kill mid-write can leave a torn last line; either would make the curve run backwards."""
    if not path.exists():
        return 0
    kept, dropped = [], 0
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            row_step = json.loads(line)["step"]
        except (ValueError, KeyError, TypeError):
            row_step = None
        if isinstance(row_step, int) and row_step <= step:
            kept.append(line + "\n")
        else:
            dropped += 1
    if dropped:
        write_synced(path, lambda tmp: tmp.write_text("".join(kept), encoding="utf-8"))
    return dropped


class WeightAverage:
    """An exponential moving average of two modules' weights and buffers (the batch-norm
    statistics too, so the averaged network normalises as its weights expect).

    The decay ramps up as ``(1 + n) / (10 + n)`` until it reaches ``decay``, so the average of a
    short run (a fine-tune of a few hundred steps) is not mostly the weights it started from.
    Made after the modules are in their final memory format: it holds their tensors, which a
    ``.to()`` replaces.
    """

    def __init__(self, decay: float, modules: dict[str, Any], state: dict[str, Any] | None = None) -> None:
        self.decay = decay
        self.updates = 0 if state is None else int(state["updates"])
        self._avg: dict[str, dict[str, Any]] = {}
        # (average, the module's own tensor) pairs. state_dict() detaches, sharing the storage:
        # the optimiser and batch norm update it in place, so each update reads the step's values.
        self._pairs: list[tuple[Any, Any]] = []
        for part, module in modules.items():
            live = module.state_dict()
            self._avg[part] = {key: (t if state is None else state[part][key]).detach().clone()
                               for key, t in live.items()}
            self._pairs += [(self._avg[part][key], t) for key, t in live.items()]

    @torch.no_grad()
    def update(self) -> None:
        self.updates += 1
        keep = min(self.decay, (1 + self.updates) / (10 + self.updates))
        for avg, t in self._pairs:
            if avg.is_floating_point():
                avg.lerp_(t, 1.0 - keep)
            else:  # a counter (batch norm's num_batches_tracked): the latest
                avg.copy_(t)

    def state_dict(self) -> dict[str, Any]:
        return {"updates": self.updates, **{part: dict(tensors) for part, tensors in self._avg.items()}}


def modules_from(net_cfg: nets.NetConfig, state: dict[str, Any]) -> tuple[Any, Any]:
    """A backbone and an aggregator loaded from saved ``"backbone"`` and ``"aggregator"`` state
    dicts: a checkpoint's, or its :class:`WeightAverage`'s."""
    backbone, aggregator = net_cfg.build()
    backbone.load_state_dict(state["backbone"])
    aggregator.load_state_dict(state["aggregator"])
    return backbone, aggregator


def train(log_paths: Sequence[Path], out_dir: Path, cfg: TrainConfig,
          progress: Callable[[dict[str, Any]], None] | None = None) -> Path:
    """Train (or resume) and export; returns the model folder."""
    if cfg.preset not in nets.PRESETS:
        raise ValidationError(f"preset: expected one of {sorted(nets.PRESETS)}, got {cfg.preset!r}")
    if not (isinstance(cfg.layers, int) and cfg.layers >= 0):
        raise ValidationError(f"layers: expected a count of transformer layers >= 1 (0: the preset's), "
                              f"got {cfg.layers!r}")
    if cfg.layers == nets.PRESETS[cfg.preset].layers:
        cfg = replace(cfg, layers=0)  # the preset's own depth, named: the same run as not naming it
    _check_layers(cfg)
    for name in ("hard_share", "mirror_share", "live_share"):
        if not 0.0 <= getattr(cfg, name) <= 1.0:
            raise ValidationError(f"{name}: expected a share in [0, 1], got {getattr(cfg, name)}")
    if not (math.isfinite(cfg.tail_weight) and cfg.tail_weight >= 0):
        raise ValidationError(f"tail weight: expected a finite weight >= 0 (0: the paper's loss alone), "
                              f"got {cfg.tail_weight}")
    if not 0.0 <= cfg.ema_decay < 1.0:
        raise ValidationError(f"ema decay: expected a decay in [0, 1) (0: export the last step's weights), "
                              f"got {cfg.ema_decay}")
    if not 0.0 <= cfg.tail_margin_deg <= 180.0:
        raise ValidationError(f"tail margin: expected an angle in [0, 180] deg, got {cfg.tail_margin_deg}")
    if not cfg.max_steps and not (math.isfinite(cfg.minutes) and cfg.minutes > 0):
        # A nan budget never ends and a negative one exports random weights as "trained".
        raise ValidationError(f"minutes: expected a finite budget > 0, got {cfg.minutes}")
    if not (math.isfinite(cfg.lr) and cfg.lr > 0):
        raise ValidationError(f"lr: expected a finite learning rate > 0, got {cfg.lr}")
    fovs = fovs_deg(cfg.crop_fov_deg)
    if not all(is_crop_fov_deg(f) for f in fovs):
        raise ValidationError(f"crop fov: expected angles in (0, 180) deg (0: the --init model's or the paper's), "
                              f"got {format_fovs_deg(cfg.crop_fov_deg)}")
    if len(fovs) > max(1, cfg.crops_per_frame or PAPER_CROPS_PER_FRAME):
        raise ValidationError(f"crop fov: {len(fovs)} angles for {cfg.crops_per_frame or PAPER_CROPS_PER_FRAME} crops "
                              "a frame leave an angle without crops; pass at most one angle per crop")
    if cfg.crops_per_frame < 0 or cfg.batch_windows < 1:
        raise ValidationError(f"crops per frame and windows per step: expected at least 1 each "
                              f"(crops 0: the run's or the paper's), got {cfg.crops_per_frame} and {cfg.batch_windows}")
    if cfg.crops_per_frame > MAX_CROPS_PER_FRAME:  # 10^6 asked numpy for 137 GiB mid-load
        raise ValidationError(f"crops per frame: expected at most {MAX_CROPS_PER_FRAME} (a model's contract allows no "
                              f"more), got {cfg.crops_per_frame}")
    net_cfg = net_config(cfg)
    out_dir = Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():
        raise ValidationError(f"--out {out_dir} is a file; pass a folder for the model (it is made if missing)")
    _check_out_writable(out_dir)
    with run_lock(out_dir):  # held to the end of the export: one process writes a run's folder
        return _train_locked(log_paths, out_dir, cfg, net_cfg, progress)


def _train_locked(log_paths: Sequence[Path], out_dir: Path, cfg: TrainConfig, net_cfg: nets.NetConfig,
                  progress: Callable[[dict[str, Any]], None] | None) -> Path:
    """:func:`train`, once its settings are checked and it holds ``out_dir`` (:func:`run_lock`)."""
    ckpt_path = out_dir / CHECKPOINT
    fovs = fovs_deg(cfg.crop_fov_deg)
    state = _resumable_state(out_dir, cfg)
    if state is not None:
        cfg = _with_own_unflagged(cfg, state["config"])
    _check_batch_fits(cfg.batch_windows, cfg.frames_per_window,
                      int(state["config"]["crops_per_frame"]) if state is not None  # saved resolved, never 0
                      else cfg.crops_per_frame or PAPER_CROPS_PER_FRAME, net_cfg.crop_size)
    # Checked before minutes of loading data; used only by a new run (a resumed one has its weights).
    init_start = _checked_init(Path(cfg.init), net_cfg) if cfg.init and state is None else None
    init_weights = init_start[0] if init_start is not None else None
    if cfg.init:
        # Recorded whole: a run resumed from another folder compares it with --init from there, and
        # the contract's provenance of a relative "shipped" or "model" would not say which folder.
        cfg = replace(cfg, init=os.path.abspath(cfg.init))
    if state is not None:
        if _run_finished(state, cfg) and _exported_step(out_dir) == state["step"]:
            # At DEBUG: the progress callback has the CLI say it, as it does the resume below.
            log.debug("the run in %s already reached its end (step %d); nothing to train", out_dir, state["step"])
            if progress:
                progress({"phase": "finished", "step": state["step"]})
            return out_dir
        if progress:
            progress({"phase": "resume", "step": state["step"], "minutes": state["elapsed_s"] / 60.0})
    # What a fine-tune started from, read once at its start: the folder may be gone by the export.
    # (The model check_init loaded, if it did: loading a model twice costs about a second.)
    init_info = (state or {}).get("init_info") or (
        _init_provenance(Path(cfg.init), init_start[1] if init_start is not None else None) if cfg.init else None)
    # How the model will run: as its start did (the shipped model: 8 crops a frame, though trained
    # with 4), unless --crops said; fixed at the run's start, so a resume or --export-only keeps it.
    if state is not None and "run_crops_per_frame" in state:
        run_crops = int(state["run_crops_per_frame"] or 0)
    else:  # a new run, or one checkpointed before session 11 recorded it
        run_crops = 0 if cfg.crops_per_frame or not init_info else int(init_info.get("crops_per_frame") or 0)
    # The angle a crop spans, fixed at the run's start like the crops: a fine-tune keeps its start's
    # (a model sees its crops at one angular scale), a resume its run's.
    if state is not None:
        fovs = fovs_deg(state["config"].get("crop_fov_deg", PAPER_CROP_FOV_DEG))
    elif not fovs:
        fovs = fovs_deg((init_info or {}).get("crop_fov_deg") or PAPER_CROP_FOV_DEG)
    cfg = replace(cfg, crop_fov_deg=fovs[0] if len(fovs) == 1 else fovs)  # one angle stays a number
    if cfg.threads:
        torch.set_num_threads(cfg.threads)

    t_load = time.monotonic()
    on_load = None
    if progress:
        def on_load(done: int, total: int) -> None:
            progress({"phase": "load", "done": done, "total": total})
    drives = load_drives(sorted(Path(p) for p in log_paths), net_cfg.crop_size,
                         [math.radians(f) for f in fovs], progress=on_load)
    n_frames = sum(len(d.images) for d in drives)
    sun_range_deg = sun_elevation_range_deg(d.sun_enu for d in drives)  # once: state_dict() runs at every checkpoint
    log.info("loaded %d drives, %d frames in %.0f s", len(drives), n_frames, time.monotonic() - t_load)

    backbone, aggregator = net_cfg.build(seed=cfg.seed)
    params = list(backbone.parameters()) + list(aggregator.parameters())
    # fused: one kernel over all parameters instead of a loop of small ops (7 vs 13 ms a step
    # for the fast preset on this machine); same update, same state dict for resumes.
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay, fused=True)
    if init_weights is not None and state is None:
        _load_npz(init_weights, backbone, aggregator)
        log.info("starting from the weights of %s", cfg.init)
    step, elapsed_s = 0, 0.0
    schedule = Schedule(minutes=cfg.minutes)
    drive_err = None
    rng = np.random.default_rng(cfg.seed)
    if state is not None:
        cfg = replace(cfg, crops_per_frame=state["config"]["crops_per_frame"])  # saved resolved, never 0
        backbone.load_state_dict(state["backbone"])
        aggregator.load_state_dict(state["aggregator"])
        opt.load_state_dict(state["optimizer"])
        step, elapsed_s = state["step"], state["elapsed_s"]
        rng.bit_generator.state = state["rng"]
        torch.set_rng_state(state["torch_rng"])
        schedule = Schedule(**state.get("schedule", {"minutes": state["config"]["minutes"]}))
        # Any change of budget: other --steps, other --minutes, or from --steps to --minutes.
        budget_changed = (cfg.max_steps != state["config"].get("max_steps", 0)
                          or (not cfg.max_steps and cfg.minutes != schedule.minutes))
        if budget_changed:
            # A new budget: a new cosine segment from where the rate stands now, never back up.
            schedule = Schedule(start_step=step, start_lr=opt.param_groups[0]["lr"], minutes=cfg.minutes)
        drive_err = state.get("drive_err_deg")
        log.debug("resuming from step %d (%.1f min trained)", step, elapsed_s / 60)
        dropped = _trim_metrics(out_dir / METRICS, step)
        if dropped:
            log.info("dropped %d metric lines past the checkpoint (steps lost when the run stopped)", dropped)

    if not cfg.crops_per_frame:
        cfg = replace(cfg, crops_per_frame=PAPER_CROPS_PER_FRAME)
    sampler = WindowSampler(drives, cfg.frames_per_window, cfg.crops_per_frame, net_cfg.crop_size,
                            cfg.subset_prob, rng, hard_share=cfg.hard_share, mirror_share=cfg.mirror_share,
                            live_share=cfg.live_share)
    if drive_err is not None and len(drive_err) == len(drives):
        sampler.err_deg[:] = drive_err
    bf16 = use_bf16(cfg.precision)
    if bf16:
        # Module.to(memory_format=...) is documented and works; torch's overloads omit it.
        backbone = backbone.to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    log.info("training in %s", "bf16 autocast, channels-last" if bf16 else "float32")
    average = (WeightAverage(cfg.ema_decay, {"backbone": backbone, "aggregator": aggregator},
                             (state or {}).get("weight_average")) if cfg.ema_decay else None)
    contract_stub = net_cfg.contract(crops_per_frame=cfg.crops_per_frame,
                                     frames_per_window=cfg.frames_per_window, crop_fov_deg=list(fovs))
    normalise = _Normaliser(contract_stub.input_norm)
    budget_s = cfg.minutes * 60.0
    tail_margin_rad = math.radians(cfg.tail_margin_deg)
    t_step = cfg.frames_per_window * cfg.crops_per_frame  # crops of a window
    # The schedule's length: steps if given, else estimated from the measured step time once 20
    # steps are timed (until then a length so long the rate is flat, and no total to report).
    unknown_total = 10**9
    est_total = cfg.max_steps or unknown_total
    backbone.train()
    aggregator.train()
    if state is None:
        (out_dir / METRICS).unlink(missing_ok=True)  # a killed run's, from before its first checkpoint
    start = time.monotonic() - elapsed_s
    start_step = step  # where this session began: a resumed run's earlier steps are not its rate
    last_ckpt = time.monotonic()
    saved_step = None if state is None else state["step"]  # of the checkpoint in out_dir, if any
    ema_loss: float | None = None  # exponential moving averages, from the first step on
    ema_err: float | None = None
    warned_busy = False

    def state_dict() -> dict[str, Any]:
        return {
            "backbone": backbone.state_dict(), "aggregator": aggregator.state_dict(),
            "optimizer": opt.state_dict(), "step": step, "elapsed_s": time.monotonic() - start,
            "rng": rng.bit_generator.state, "torch_rng": torch.get_rng_state(), "config": asdict(cfg),
            "data_counts": {"drives": len(drives), "frames": n_frames, "sun_elevation_deg": sun_range_deg},
            "err_deg_ema": None if ema_err is None else round(ema_err, 2),
            "schedule": asdict(schedule), "drive_err_deg": sampler.err_deg.tolist(), "init_info": init_info,
            "run_crops_per_frame": run_crops,
            "weight_average": None if average is None else average.state_dict(),
        }

    def diverged(when: str) -> TrainingDivergedError:
        kept = ("; nothing was saved" if saved_step is None else
                f" and a new --out (a run keeps its --lr); its checkpoint at step {saved_step} in {out_dir} is kept")
        return TrainingDivergedError(f"train: training diverged {when}; run again with "
                                     f"{_lower_lr_advice(cfg.lr)}{kept}")

    def fit_state() -> dict[str, Any]:
        """:func:`state_dict`, for a checkpoint or the export: refused if the weights diverged,
        so that the checkpoint in ``out_dir`` stays the last good one."""
        snapshot = state_dict()
        bad = _unfit_weights(_weights_of(snapshot))
        if bad:
            raise diverged(f"by step {step}: weights not finite or beyond float16 ({_arrays(bad)})")
        return snapshot

    try:
        while True:
            elapsed = time.monotonic() - start
            if cfg.max_steps and step >= cfg.max_steps:
                break
            if not cfg.max_steps and elapsed >= budget_s:
                break
            if not cfg.max_steps and step >= 20:
                est_total = int(step * budget_s / max(elapsed, 1e-9))
            for g in opt.param_groups:
                g["lr"] = schedule.lr_at(step, est_total, cfg)

            try:
                batch = sampler.sample(cfg.batch_windows)
                b, t = batch.mask.shape
                x = normalise(batch.crops.reshape(b * t, *batch.crops.shape[2:]))
                mask = torch.from_numpy(batch.mask)
                with torch.autocast("cpu", dtype=torch.bfloat16, enabled=bf16):
                    if bf16:
                        x = x.contiguous(memory_format=torch.channels_last)
                    emb = backbone(x).view(b, t, -1)
                    v_head = aggregator(emb, torch.from_numpy(batch.angles), mask)
                v_head = v_head.float()
                v_world = nets.world_from_heading_torch(v_head, torch.from_numpy(batch.yaw).float())
                truth = torch.from_numpy(batch.truth).float()
                token_loss = nets.sun_loss(v_world, truth[:, None, :].expand_as(v_world), mask)
                maskf = mask.float().unsqueeze(-1)
                mean = (v_world * maskf).sum(1) / maskf.sum(1).clamp_min(1.0)
                window_loss = nets.sun_loss(mean, truth)
                full = batch.mask.all(axis=1)  # the windows with every token: what the rig runs once filled
                if cfg.tail_weight:
                    # Full windows only: the accuracy targets are on those, and a subset window of a
                    # token or two is often far off for want of views, which this term should not chase.
                    window_loss = window_loss + cfg.tail_weight * nets.tail_loss(mean, truth, tail_margin_rad,
                                                                                 torch.from_numpy(full))
                loss = token_loss + window_loss
                # The scalar the progress line shows, read before the update rather than after:
                # a nan or inf loss would turn every weight nan through its gradients. One number a
                # step, already computed; a scan of the weights waits for the checkpoints.
                loss_value = float(loss.detach())
                if not math.isfinite(loss_value):
                    raise diverged(f"at step {step + 1}: its loss became {loss_value}")
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(params, 1.0)
                opt.step()
                if average is not None:
                    average.update()
            except (RuntimeError, MemoryError) as exc:
                if not _allocation_failed(exc):
                    raise
                # No checkpoint of this step: it may have failed halfway through the update. The
                # last one is kept as it is, for the same command to resume once memory is free.
                asked = _asked(exc)
                kept = ("" if saved_step is None else
                        f" with a new --out (a run keeps its batch), or free memory and run the same command to "
                        f"resume: its checkpoint at step {saved_step} in {out_dir} is kept")
                raise BatchMemoryError(
                    f"train: step {step + 1} cannot allocate memory for its batch of {cfg.batch_windows} windows x "
                    f"{t_step} crops ({cfg.batch_windows * t_step} crops of {net_cfg.crop_size} px"
                    f"{f'; it asked for {asked} more' if asked else ''}); "
                    f"{_smaller_batch_advice(cfg.batch_windows, cfg.crops_per_frame)}{kept}") from exc
            step += 1

            with torch.no_grad():
                cos = (torch.nn.functional.normalize(mean, dim=-1) * truth).sum(-1).clamp(-1, 1)
                window_err = torch.rad2deg(torch.acos(cos)).numpy()
                err_deg = float(window_err.mean())
                # A subset window's error says little about its drive.
                sampler.record(batch.drive[full], window_err[full])
            ema_loss = loss_value if ema_loss is None else 0.98 * ema_loss + 0.02 * loss_value
            ema_err = err_deg if ema_err is None else 0.98 * ema_err + 0.02 * err_deg
            if step % 50 == 0:
                with open(out_dir / METRICS, "a", encoding="utf-8") as fh:
                    fh.write(json.dumps({"step": step, "elapsed_s": round(time.monotonic() - start, 1),
                                         "lr": opt.param_groups[0]["lr"], "loss_ema": round(ema_loss, 4),
                                         "window_err_deg_ema": round(ema_err, 2)}) + "\n")
            if progress:
                progress({"phase": "train", "step": step, "start_step": start_step,
                          "total": None if est_total == unknown_total else est_total,
                          "elapsed_s": time.monotonic() - start, "budget_s": None if cfg.max_steps else budget_s,
                          "loss": ema_loss, "err_deg": ema_err})
            if time.monotonic() - last_ckpt > cfg.checkpoint_every_s:
                _save_checkpoint(ckpt_path, fit_state())
                saved_step, last_ckpt = step, time.monotonic()
                if not warned_busy and not cfg.max_steps:  # a step budget is not shortened by load
                    threads = torch.get_num_threads()
                    extra = other_cpu_load(threads)
                    if extra is not None and extra > BUSY_EXTRA_LOAD:
                        warned_busy = True  # once: the advice does not change, and the log stays readable
                        log.warning("other work is using the CPU (load %.1f beyond training's %d threads): this "
                                    "%.0f-minute budget will train fewer steps; leave the machine idle while it trains",
                                    extra, threads, cfg.minutes)
        # One snapshot for both, so the exported contract's minutes are the checkpoint's to the second
        # (a second snapshot after a slow save reads a later clock). Saved under the Ctrl-C below:
        # a stop cutting this save lost every step since the last checkpoint, without a word.
        final = fit_state()
        _save_checkpoint(ckpt_path, final)
    except KeyboardInterrupt:
        # Ctrl-C (or a kill by SIGINT) keeps what was trained since the last checkpoint: up to
        # checkpoint_every_s of steps would otherwise be lost. The same command resumes.
        try:
            _save_checkpoint(ckpt_path, fit_state())
        except TrainingDivergedError as exc:  # the stop asked for stays the exit; the last good checkpoint stays
            log.warning("interrupted: %s", exc)
            raise KeyboardInterrupt from exc
        log.warning("interrupted at step %d: saved %s; run the same command to resume", step, ckpt_path)
        raise

    if final["weight_average"] is not None:
        backbone, aggregator = modules_from(net_cfg, final["weight_average"])
    try:
        # (memory_format: see the channels_last call above for the ignore)
        return _export(backbone.to(memory_format=torch.contiguous_format),  # type: ignore[call-overload]
                       aggregator, cfg, final, out_dir)
    except KeyboardInterrupt:
        # The export is seconds of ONNX tracing, most of a short run's time: a stop there exited
        # without a word, leaving a checkpoint and weights.npz but no graphs.
        log.warning("interrupted while exporting the model of step %d: %s is saved, but the model is not "
                    "exported; run the same command to export it", step, ckpt_path)
        raise


# What makes a run itself: resuming with any of these changed would make a contract that lies
# about how its model was trained.
_RUN_IDENTITY = {"preset": "--preset", "layers": "--layers", "lr": "--lr", "batch_windows": "--batch",
                 "seed": "--seed", "hard_share": "--hard-share", "mirror_share": "--mirror-share",
                 "live_share": "--live-share", "tail_weight": "--tail-weight", "tail_margin_deg": "--tail-margin",
                 "ema_decay": "--ema-decay"}
# What a checkpoint written before a setting was recorded ran with (all had their preset's depth,
# trained on the paper's loss alone and exported its last weights, and none mirrored its windows
# or drew them as the rig does).
_RAN_BEFORE_RECORDED = {"layers": 0, "mirror_share": 0.0, "live_share": 0.0, "tail_weight": 0.0,
                        "tail_margin_deg": 15.0, "ema_decay": 0.0}
# Settings whose 0 means "the run's own" (so a resume need not repeat them): the flag, what a
# checkpoint written before the setting was recorded ran with, the setting's value as compared
# (an angle setting of 17.6 and one of [17.6] are one angle) and as the flag takes it.
_RUN_OWN_WHEN_ZERO: dict[str, tuple[str, Any, Callable[[Any], Any], Callable[[Any], str]]] = {
    "crops_per_frame": ("--crops", PAPER_CROPS_PER_FRAME, int, str),
    "crop_fov_deg": ("--crop-fov", PAPER_CROP_FOV_DEG, fovs_deg, format_fovs_deg),
}


# Settings no flag sets: a command passes this sunrig's defaults, so a resume takes its run's own
# (a default changed since the run began must not change the rest of the run, nor the contract's
# account of it; frames_per_window is the model's window length).
_RUN_OWN_UNFLAGGED = ("weight_decay", "warmup_steps", "subset_prob", "frames_per_window")


def _with_own_unflagged(cfg: TrainConfig, ran: dict[str, Any]) -> TrainConfig:
    """``cfg`` with the :data:`_RUN_OWN_UNFLAGGED` settings its checkpoint's run recorded (``ran``)."""
    own = {key: ran[key] for key in _RUN_OWN_UNFLAGGED if key in ran and ran[key] != getattr(cfg, key)}
    if own:
        log.info("resuming with the run's own %s (not this sunrig's %s)",
                 ", ".join(f"{key} {value!r}" for key, value in own.items()),
                 ", ".join(f"{getattr(cfg, key)!r}" for key in own))
    return replace(cfg, **own)


def _check_out_writable(out_dir: Path) -> None:
    """Refuse, before minutes of loading data, an ``--out`` that cannot be written: it was found
    by the mkdir after every log had loaded, or (a folder the user may not write) by the first
    metrics line or checkpoint, after the training (:func:`rig.files.check_folder_writable`)."""
    check_folder_writable(out_dir, flag="--out")


RUN_LOCK = ".train.lock"  # hidden, like every file a run keeps beside its own (_resumable_state)


@contextlib.contextmanager
def run_lock(out_dir: Path) -> Iterator[None]:
    """Hold ``out_dir`` for one process (:func:`rig.files.folder_lock`): a second ``sunrig train``
    (or an ``--export-only`` into the run's folder) is refused in one line naming the holder's pid
    while it is held, instead of resuming the same checkpoint and writing the folder's files
    through the same temporary names. A run killed by any means frees the folder. Once it is held,
    the staging folder of an export killed midway (graphs that never became the model) is removed."""
    with folder_lock(out_dir, name=RUN_LOCK, command="sunrig train", flag="--out") as held:
        # What a run or an export killed midway left here (held, no process writes the folder).
        for staged in out_dir.glob(f"{STAGING_PREFIX}*") if held else ():
            shutil.rmtree(staged, ignore_errors=True)
        yield


def _resumable_state(out_dir: Path, cfg: TrainConfig) -> dict[str, Any] | None:
    """The checkpoint of the run in ``out_dir`` when ``cfg`` resumes it; None for a new run in a
    new or empty folder. Anything else is refused before data loads: a folder holding another
    run, a model or logs would be overwritten or mixed with this run."""
    ckpt_path = out_dir / CHECKPOINT
    if not ckpt_path.is_file():
        # Not held: a killed run's metrics, or the hidden sibling of a checkpoint it was writing.
        held = sorted(p.name for p in out_dir.iterdir()
                      if p.name != METRICS and not p.name.startswith(".")) if out_dir.is_dir() else []
        if held:
            shown = ", ".join(held[:3]) + (", ..." if len(held) > 3 else "")
            raise ValidationError(f"--out {out_dir} already holds files ({shown}) and no training run; pass a new "
                                  "or empty folder: a model or logs there would be overwritten")
        return None
    state = load_checkpoint(ckpt_path, resume=True)
    was = state["config"]
    ran = {key: was.get(key, _RAN_BEFORE_RECORDED.get(key)) for key in _RUN_IDENTITY}
    changed = [key for key in _RUN_IDENTITY if ran[key] is not None and ran[key] != getattr(cfg, key)]
    differs = [f"{_RUN_IDENTITY[key]} {ran[key]!r}, not {getattr(cfg, key)!r}" for key in changed]
    if (was.get("init") or "") != cfg.init and not (was.get("init") and cfg.init
                                                     and Path(was["init"]).resolve() == Path(cfg.init).resolve()):
        differs.append(f"--init {was.get('init')!r}, not {cfg.init!r}")
    for key, (flag, before_recorded, value, as_flag) in _RUN_OWN_WHEN_ZERO.items():
        ran_with, asked = was.get(key, before_recorded), getattr(cfg, key)
        if value(asked) and value(asked) != value(ran_with):
            differs.append(f"{flag} {as_flag(ran_with)}, not {as_flag(asked)}")
    old_data, new_data = was.get("data", {}).get("fingerprint"), cfg.data.get("fingerprint")
    other_logs = bool(old_data and new_data and old_data != new_data)
    if other_logs:
        n_was, n_now = was.get("data", {}).get("logs"), cfg.data.get("logs")
        differs.append(f"logs with fingerprint {old_data}{f' ({n_was} logs)' if n_was is not None else ''}, "
                       f"not {new_data} ({f'{n_now} logs: ' if n_now is not None else ''}a log added, removed or "
                       "changed since the run began)")
    if differs:
        # A default may have changed since the run began (--mirror-share did), so its own command
        # alone may not resume it: name the settings to give as well.
        give = f" with `{' '.join(f'{_RUN_IDENTITY[key]} {ran[key]}' for key in changed)}`" if changed else ""
        # Its own command names folders whose logs may have changed since (a drive recorded into one).
        began = " on the logs it began with" if other_logs else ""
        raise ValidationError(f"--out {out_dir} holds a run with {'; '.join(differs)}. To resume it, run its own "
                              f"command (`{was.get('command') or 'see its checkpoint'}`){give}{began}; for a new "
                              "run pass another --out")
    return state


def _run_finished(state: dict[str, Any], cfg: TrainConfig) -> bool:
    """Whether a checkpoint's run has reached the end ``cfg`` asks for (its steps, or its minutes)."""
    if cfg.max_steps:
        return state["step"] >= cfg.max_steps
    return state["elapsed_s"] >= cfg.minutes * 60.0


def _exported_step(out_dir: Path) -> int | None:
    """The step of the model exported in ``out_dir`` (its contract's), or None if there is none
    that loads: a finished run whose export is missing, stale or broken is exported again. So is
    one without ``weights.npz``: an export cut short (a kill, a full disk) by a sunrig that wrote
    the graphs before it."""
    from estimator.runtime import OnnxModel

    if not (out_dir / WEIGHTS_FILE).is_file():
        return None
    try:
        steps = OnnxModel.load(out_dir).contract.training.get("steps")
        return None if steps is None else int(steps)
    except (SunrigError, TypeError, ValueError):
        return None


def _export(backbone: Any, aggregator: Any, cfg: TrainConfig, state: dict[str, Any], out_dir: Path,
            run_crops_per_frame: int = 0, export_command: str = "", run_mirror_windows: bool | None = None) -> Path:
    """The two graphs with a contract that records the recipe, the data and how far training got.

    The contract's ``crops_per_frame`` is what the runtime feeds the model: ``run_crops_per_frame``
    if given, else the run's own (a fine-tune's start's, recorded in the checkpoint), else the
    training count (the recipe keeps it). Its ``mirror_windows`` is ``run_mirror_windows`` if
    given, else a fine-tune's start's, else off.
    """
    run_crops_per_frame = run_crops_per_frame or int(state.get("run_crops_per_frame") or 0)
    if run_mirror_windows is None:
        run_mirror_windows = bool((state.get("init_info") or {}).get("mirror_windows", False))
    training = {
        "trained": True,
        "command": cfg.command,
        "data": {**cfg.data, **state.get("data_counts", {})},
        "recipe": {k: v for k, v in asdict(cfg).items() if k not in ("command", "data")},
        "steps": state["step"],
        "windows_seen": state["step"] * cfg.batch_windows,
        "minutes": round(state["elapsed_s"] / 60.0, 1),
        "final_train_err_deg_ema": state.get("err_deg_ema"),
    }
    if cfg.init:
        training["init"] = state.get("init_info") or _init_provenance(Path(cfg.init))
    if export_command:
        training["export_command"] = export_command
    contract = net_config(cfg).contract(
        crops_per_frame=run_crops_per_frame or cfg.crops_per_frame, frames_per_window=cfg.frames_per_window,
        crop_fov_deg=list(fovs_deg(cfg.crop_fov_deg)), mirror_windows=run_mirror_windows, training=training)
    # The weights first, the graphs last: the graphs' contract names the step, which is how a run
    # knows it was exported (_exported_step), so a kill or a full disk between the two leaves a
    # folder the same command exports again rather than graphs whose weights.npz is missing or
    # an earlier export's.
    save_weights(backbone, aggregator, make_output_folder(out_dir, what="model folder", holds="a model is a folder"))
    return export_model(backbone, aggregator, contract, out_dir)


def save_weights(backbone: Any, aggregator: Any, out_dir: Path) -> Path:
    """``weights.npz``: every tensor of both modules (batch-norm statistics included) as float16."""
    arrays = {f"{part}/{k}": v.detach().cpu().numpy().astype(np.float16 if v.is_floating_point() else v.numpy().dtype)
              for part, module in (("backbone", backbone), ("aggregator", aggregator))
              for k, v in module.state_dict().items()}
    path = Path(out_dir) / WEIGHTS_FILE
    write_synced(path, lambda tmp: np.savez_compressed(tmp, **arrays))
    return path


def check_init(model_dir: Path, net_cfg: nets.NetConfig) -> Path:
    """The ``weights.npz`` a run can start from, or a one-line error (checked before any data loads)."""
    return _checked_init(model_dir, net_cfg)[0]


def _checked_init(model_dir: Path, net_cfg: nets.NetConfig) -> tuple[Path, Any]:
    """:func:`check_init`'s ``weights.npz``, and the model it loaded to check it (an ``OnnxModel``)."""
    from estimator.runtime import OnnxModel

    path = Path(model_dir) / WEIGHTS_FILE
    if not Path(model_dir).is_dir():
        what = "is a file, not a model folder" if Path(model_dir).exists() else "does not exist"
        raise ValidationError(f"--init {model_dir} {what}; pass a model folder written by `sunrig train`, "
                              "e.g. the shipped model's")
    graphs = all((Path(model_dir) / name).is_file() for name in (BACKBONE_FILE, AGGREGATOR_FILE))
    # A run stopped before its end exports nothing; one stopped in its export has weights.npz
    # (written first) and no graphs, where the runtime's refusal named --model.
    if not (path.is_file() and graphs) and (Path(model_dir) / CHECKPOINT).is_file():
        raise ValidationError(f"--init {model_dir} holds a training run that has not exported its model yet; "
                              f"export it with `sunrig train --out {model_dir} --export-only DIR` and pass "
                              "--init DIR, or run its `sunrig train` command again to finish and export it")
    if not path.is_file():
        raise ValidationError(f"--init {model_dir}: no {WEIGHTS_FILE} there; pass a model folder written by "
                              "`sunrig train` (the shipped model has one)")
    try:
        start = OnnxModel.load(model_dir)
    except ContractMismatch as exc:  # its remedy named --model, which train does not have
        own = CONTRACT_REMEDY.replace("--model", "--init")
        raise ContractMismatch(str(exc).replace(CONTRACT_REMEDY, own)) from None
    contract = start.contract
    arch = contract.architecture
    if arch != net_cfg.architecture():
        diff = sorted(k for k in set(arch) | set(net_cfg.architecture())
                      if arch.get(k) != net_cfg.architecture().get(k))
        recipe = contract.training.get("recipe") or {}
        preset = recipe.get("preset")
        which = f"--preset {preset}" if preset in nets.PRESETS else "the preset it was trained with"
        if recipe.get("layers"):
            which += f" --layers {recipe['layers']}"
        elif "layers" in diff and net_cfg not in nets.PRESETS.values():
            # The start has its preset's depth and this run was given --layers (net_config names no
            # preset then); a depth differing only with the preset is no flag to leave out.
            which += " without --layers"
        raise ValidationError(f"--init {model_dir}: its architecture differs from this preset in {', '.join(diff)}; "
                              f"pass {which}")
    # Loaded into networks of its architecture now, not after minutes of loading data: weights.npz
    # is not in SHA256SUMS (the runtime never reads it), so damage shows only here.
    backbone, aggregator = net_cfg.build(seed=0)
    _load_npz(path, backbone, aggregator)
    return path, start


def load_weights(model_dir: Path, net_cfg: nets.NetConfig, backbone: Any, aggregator: Any) -> None:
    """Load a model folder's ``weights.npz`` into freshly built modules of the same architecture."""
    _load_npz(check_init(model_dir, net_cfg), backbone, aggregator)


def _load_npz(path: Path, backbone: Any, aggregator: Any) -> None:
    try:
        with np.load(path, allow_pickle=False) as z:
            for part, module in (("backbone", backbone), ("aggregator", aggregator)):
                own = module.state_dict()
                state = {k: torch.from_numpy(z[f"{part}/{k}"].astype(own[k].numpy().dtype)) for k in own}
                module.load_state_dict(state)
    # What numpy, zipfile, zlib and torch raise for a damaged, foreign or mismatched archive (zlib's
    # and zipfile's errors are Exceptions of their own; a wrong key is a KeyError, a wrong shape a
    # RuntimeError): an internal error before, though the fix is the user's.
    except (OSError, ValueError, KeyError, RuntimeError, EOFError, zipfile.BadZipFile, zlib.error) as exc:
        # numpy calls a file that is no archive "pickled" and advises allow_pickle: not advice to pass on.
        why = ("not an archive of arrays" if isinstance(exc, ValueError) and "pickle" in str(exc)
               else f"{type(exc).__name__}: {exc}")
        raise ValidationError(f"{path} cannot be loaded ({why}); re-export the model from its "
                              "training run, or pass another --init") from None


def _init_provenance(model_dir: Path, start: Any = None) -> dict[str, Any]:
    """What a fine-tuned model started from: the starting model's id and how it was trained, so
    the contract still says how to remake the whole chain after that folder is gone. ``start``:
    that model (an ``OnnxModel``) if it is loaded already, else it is loaded from ``model_dir``."""
    from estimator.runtime import OnnxModel

    if start is None:
        try:
            start = OnnxModel.load(model_dir)
        except SunrigError as exc:  # moved or deleted since the run started
            return {"dir": str(model_dir), "unavailable": str(exc)}
    t = start.contract.training
    sun_range = start.contract.trained_sun_elevation_deg  # its own chain's, for the status rule
    return {"dir": str(model_dir), "model_id": start.model_id,
            # "quantization": an int8 copy (sunrig quantize), whose float weights.npz the run
            # started from; without it the record read as the float model's under another id.
            **{k: t.get(k) for k in ("command", "data", "steps", "minutes", "init", "quantization")
               if t.get(k) is not None},
            **({"sun_elevation_deg": list(sun_range)} if sun_range else {}),
            "crops_per_frame": start.contract.crops_per_frame, "crop_fov_deg": start.contract.crop_fov_deg,
            "mirror_windows": start.contract.mirror_windows}


def export_checkpoint(checkpoint_dir: Path, out_dir: Path, run_crops_per_frame: int = 0,
                      export_command: str = "", log_paths: Sequence[Path] = (), data_note: str = "",
                      run_mirror_windows: bool | None = None) -> Path:
    """Export the model in ``checkpoint_dir``'s checkpoint as it stands (e.g. while it trains).

    ``run_crops_per_frame`` sets the crops per frame the runtime will feed it (default: the
    run's own, which for a fine-tune is its start's; else as trained). The aggregator takes any
    number of tokens, and more crops than it was trained with average out more of the luck of
    where crops land (docs/model.md measures it). ``run_mirror_windows`` sets whether it also runs
    each window mirrored (default: as a fine-tune's start ran, else not).

    ``log_paths``: the run's training logs, for a checkpoint written before training recorded
    its data's sun elevations (the status rule's limit, :meth:`ModelContract.trained_sun_elevation_deg`).
    They must be the logs the run trained on (same fingerprint); a checkpoint that has the range
    keeps its own.

    ``data_note``: what those logs are, for a run that was started without ``--data-note``
    (the contract's ``training.data.source``). It needs ``log_paths``, so that the note is
    attached to the logs the run trained on, and it cannot rename data a run has recorded.
    """
    if not 0 <= run_crops_per_frame <= MAX_CROPS_PER_FRAME:
        raise ValidationError(f"crops per frame: expected 1 to {MAX_CROPS_PER_FRAME} (0: as trained), "
                              f"got {run_crops_per_frame}")
    path = Path(checkpoint_dir) / CHECKPOINT
    if not path.is_file():
        raise ValidationError(f"no {CHECKPOINT} in {checkpoint_dir}; pass the --out folder of a training run")
    _refuse_export_over_others(Path(out_dir), Path(checkpoint_dir))
    state = load_checkpoint(path, resume=False)
    cfg = TrainConfig(**state["config"])  # train() saves the crop count resolved, never 0
    counts = state.setdefault("data_counts", {})
    if data_note:
        recorded = cfg.data.get("source") or ""
        if recorded and recorded != data_note:
            raise ValidationError(f"the run in {checkpoint_dir} recorded its data as {recorded!r}; "
                                  "--data-note names the data of a run that recorded none")
        if not log_paths:
            raise ValidationError("--data-note with --export-only needs the run's training logs too, "
                                  "so that the note is checked to be about them (their fingerprint)")
        cfg.data = {**cfg.data, "source": data_note}  # exported only once the logs below are the run's
    if log_paths:
        trained_on = cfg.data.get("fingerprint")
        if data_fingerprint(log_paths) != trained_on:
            raise ValidationError(f"these {len(log_paths)} logs are not the ones {checkpoint_dir} trained on "
                                  f"(fingerprint {data_fingerprint(log_paths)}, not {trained_on}); "
                                  "pass the run's training logs, or none")
        if "sun_elevation_deg" not in counts:
            counts["sun_elevation_deg"] = sun_elevation_range_deg(_truth_enu(p) for p in log_paths)
    # A run with --ema-decay exports its average, as it does when it ends.
    backbone, aggregator = modules_from(net_config(cfg), state.get("weight_average") or state)
    # Into the run's own folder, only while no run trains there: its export writes the same files.
    own = Path(out_dir).is_dir() and Path(out_dir).resolve() == Path(checkpoint_dir).resolve()
    with run_lock(Path(out_dir)) if own else contextlib.nullcontext():
        return _export(backbone, aggregator, cfg, state, Path(out_dir), run_crops_per_frame, export_command,
                       run_mirror_windows)


def _refuse_export_over_others(out_dir: Path, checkpoint_dir: Path) -> None:
    """An export replaces a folder's graphs: refuse one that holds another run (its graphs would
    no longer be its checkpoint's) or logs. A model folder alone, or the run's own, is re-exported,
    as docs/model.md does to the shipped model."""
    if not out_dir.is_dir() or out_dir.resolve() == checkpoint_dir.resolve():
        return
    if (out_dir / CHECKPOINT).exists():
        raise ValidationError(f"--export-only {out_dir} holds another training run ({CHECKPOINT}); its graphs "
                              "would no longer be its checkpoint's: pass a new folder, or that run's own")
    logs = sorted(p.name for p in out_dir.glob("*.mcap"))
    if logs:
        raise ValidationError(f"--export-only {out_dir} holds logs ({logs[0]}"
                              f"{f' and {len(logs) - 1} more' if len(logs) > 1 else ''}); pass a folder for the model")


def sun_elevation_range_deg(sun_enu: Iterable[np.ndarray]) -> list[float]:
    """The lowest and highest true sun (deg above the horizon) in arrays of (F, 3) ENU vectors."""
    enu = np.concatenate([np.asarray(v, dtype=np.float64).reshape(-1, 3) for v in sun_enu])
    if enu.size == 0:
        raise TrainingDataError("no frame with a true sun in the training data")
    el = np.degrees(az_el_from_enu(enu)[1])
    return [round(float(el.min()), 1), round(float(el.max()), 1)]


def _truth_enu(path: Path) -> np.ndarray:
    """A log's true sun for the frames training uses (:func:`trainable`)."""
    from replay.sources import open_frames

    rows = [f.sun_enu_truth for f in open_frames(Path(path)) if trainable(f)]
    return np.asarray(rows, dtype=np.float64).reshape(-1, 3)


