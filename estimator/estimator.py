"""From frames to a sun direction: crops and backbone once per frame, an aggregator per window.

:class:`SunEstimator` is the one object the rig, replay, eval and the CLI use. It is not
thread-safe by itself; the rig gives each stage its own.

Aggregators (all behind :meth:`SunEstimator.estimate`):

- ``transformer``: the paper. All tokens of the window attend to each other in one aggregator
  run; per-token vectors are calibrated into the world frame and averaged.
- ``mean``: each crop alone through the same aggregator graph (a window of one token), i.e.
  independent per-crop estimates, calibrated and averaged.
- ``meanshift``: the same independent estimates, outliers removed, mean shift on the sphere
  (Lee et al. 2021, the paper's baseline).
- ``single``: one crop of the newest frame alone: no aggregation at all.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from estimator.calibration import (
    EstimationError,
    mean_direction,
    mirrored_angles,
    mirrored_enu,
    spread_rad,
    world_from_tokens,
)
from estimator.contract import ModelContract
from estimator.crops import (
    crop_angles_rad,
    crop_side_px,
    crops_per_scale,
    cut_crops,
    enlarged_too_far,
    frame_rng,
    sample_crop_boxes,
    spread_crop_boxes,
)
from estimator.meanshift import meanshift_aggregate
from rig.errors import ValidationError
from rig.geometry import wrap_pi
from rig.protocol import StatusRule
from rig.types import Frame, FrameFeatures, HeadingRef, Intrinsics, SunEstimate
from rig.window import view_signature

log = logging.getLogger(__name__)

AGGREGATORS = ("transformer", "mean", "meanshift", "single")
# How a frame's crops are placed: "spread" (default) one per horizontal stratum, "uniform" the
# paper's independent draws (estimator/crops.py says why spread is the default).
CROP_LAYOUTS = {"spread": spread_crop_boxes, "uniform": sample_crop_boxes}


class SunModel(Protocol):
    """What the estimator needs of a model (``estimator.runtime.OnnxModel`` is the real one)."""

    contract: ModelContract
    model_id: str

    def embed(self, crops_bgr: np.ndarray) -> np.ndarray: ...

    def aggregate(self, embeddings: np.ndarray, angles: np.ndarray, mask: np.ndarray) -> np.ndarray: ...


@dataclass(frozen=True)
class WindowTokens:
    """A window flattened to tokens: what the aggregator graph and the calibration need."""

    embeddings: np.ndarray  # (T, D) float32
    embeddings_mirrored: np.ndarray | None  # (T, D) float32 of the flipped crops, if every frame has them
    angles_rad: np.ndarray  # (T, 3) float32: yaw relative to the newest frame, horizontal, vertical
    yaw_rad: np.ndarray  # (T,) absolute yaw of each token's frame, for calibration
    newest: FrameFeatures
    heading_ref: HeadingRef
    n_frames: int


def window_tokens(window: Sequence[FrameFeatures]) -> WindowTokens:
    """Check a window and flatten it. The newest frame (largest t) is the window's reference.

    Yaw enters the network relative to the newest frame, so the network's answer cannot depend
    on a global yaw offset (as with the paper's SfM poses, whose world frame is arbitrary); the
    absolute yaw is applied only in the calibration, where it is exact.
    """
    if not window:
        raise EstimationError("empty window: at least one frame with a heading is needed")
    # Each frame with its attitude, checked present once here for the uses below.
    with_attitude = [(f, f.frame.attitude) for f in window if f.frame.attitude is not None]
    if len(with_attitude) < len(window):
        missing = [f.frame.seq for f in window if f.frame.attitude is None]
        raise EstimationError(f"frames {missing[:5]} have no heading; drop them before forming a window")
    refs = {a.reference for _, a in with_attitude}
    if len(refs) > 1:
        raise EstimationError(f"window mixes heading references {sorted(r.value for r in refs)}")
    epochs = {a.epoch for _, a in with_attitude}
    if len(epochs) > 1:
        raise EstimationError(f"window mixes heading epochs {sorted(epochs)}: their zeros differ; "
                              "form windows with rig.window.SpreadWindowPolicy, which keeps one epoch")
    models = {f.model_id for f in window}
    if len(models) > 1:
        raise EstimationError(f"window mixes embeddings of different models {sorted(models)}")
    newest, newest_attitude = max(with_attitude, key=lambda fa: (fa[0].frame.t_mono_s, fa[0].frame.seq))
    yaw_ref = newest_attitude.heading_rad
    emb, ang, yaw = [], [], []
    for f, attitude in with_attitude:
        psi = attitude.heading_rad
        emb.append(f.embeddings)
        rel = np.full((f.n_crops, 1), wrap_pi(psi - yaw_ref))
        ang.append(np.concatenate([rel, f.crop_angles_rad], axis=1))
        yaw.append(np.full(f.n_crops, psi))
    mirrored = [f.embeddings_mirrored for f, _ in with_attitude if f.embeddings_mirrored is not None]
    return WindowTokens(
        embeddings=np.concatenate(emb).astype(np.float32, copy=False),
        embeddings_mirrored=np.concatenate(mirrored) if len(mirrored) == len(with_attitude) else None,
        angles_rad=np.concatenate(ang).astype(np.float32),
        yaw_rad=np.concatenate(yaw),
        newest=newest,
        heading_ref=refs.pop(),
        n_frames=len(window),
    )


def _joint_tokens(model: SunModel, tokens: WindowTokens) -> np.ndarray:
    """All tokens in one aggregator run: (T, 3) heading-frame vectors."""
    t = len(tokens.embeddings)
    out = model.aggregate(tokens.embeddings[None], tokens.angles_rad[None], np.ones((1, t), dtype=bool))
    return np.asarray(out[0], dtype=np.float64)


def mirrored_joint_runs(model: SunModel, tokens: WindowTokens, window: Sequence[FrameFeatures],
                        mirrored_view_angles_rad: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The transformer's world vectors (T, 3) of a window and of its mirror image, the second
    turned back into this world: the two runs of the contract's ``mirror_windows``.

    The mirror image is the window as training mirrors it (``estimator.train.mirror_window``): each
    crop flipped left to right (``tokens.embeddings_mirrored``), relative yaws and horizontal view
    angles negated, and its answer's east negated, with the headings, on the way back. Both runs go
    through the aggregator as one batch of two. ``mirrored_view_angles_rad`` (T, 2) are the view
    angles of the crops the mirrored embeddings were flipped from, when they are not the plain
    run's own (a benchmark variant's); they are given unmirrored.
    """
    if tokens.embeddings_mirrored is None:
        missing = [f.frame.seq for f in window if f.embeddings_mirrored is None]  # only to name them
        raise EstimationError(f"frames {missing[:5]} were encoded without mirrored embeddings, which this "
                              "model runs with (mirror_windows); encode them with this estimator")
    angles = tokens.angles_rad
    if mirrored_view_angles_rad is not None:
        angles = angles.copy()
        angles[:, 1:] = mirrored_view_angles_rad
    t = len(tokens.embeddings)
    out = np.asarray(model.aggregate(np.stack([tokens.embeddings, tokens.embeddings_mirrored]),
                                     np.stack([tokens.angles_rad, mirrored_angles(angles)]),
                                     np.ones((2, t), dtype=bool)), dtype=np.float64)
    plain = world_from_tokens(out[0], tokens.yaw_rad)
    return plain, mirrored_enu(world_from_tokens(out[1], -tokens.yaw_rad))  # back from the mirrored world


def _independent_tokens(model: SunModel, tokens: WindowTokens) -> np.ndarray:
    """Each token alone (a batch of one-token windows): (T, 3) heading-frame vectors."""
    t = len(tokens.embeddings)
    out = model.aggregate(tokens.embeddings[:, None], tokens.angles_rad[:, None], np.ones((t, 1), dtype=bool))
    return np.asarray(out[:, 0], dtype=np.float64)


class SunEstimator:
    """Crops + backbone per frame (:meth:`encode`), aggregator per window (:meth:`estimate`)."""

    def __init__(self, model: SunModel, *, aggregator: str = "transformer", seed: int = 0,
                 crops_per_frame: int | None = None, crop_layout: str = "spread",
                 mirror_windows: bool | None = None) -> None:
        if aggregator not in AGGREGATORS:
            raise ValidationError(f"aggregator: expected one of {', '.join(AGGREGATORS)}, got {aggregator!r}")
        if crop_layout not in CROP_LAYOUTS:
            raise ValidationError(f"crop layout: expected one of {', '.join(CROP_LAYOUTS)}, got {crop_layout!r}")
        self.sample_boxes = CROP_LAYOUTS[crop_layout]
        self.model = model
        self.aggregator = aggregator
        self.seed = int(seed)
        contract = model.contract
        self.crops_per_frame = int(crops_per_frame or contract.crops_per_frame)
        # None: as the model's contract says (the shipped model runs mirrored too).
        self.mirror_windows = bool(contract.mirror_windows if mirror_windows is None else mirror_windows)
        self.crop_size_px = int(contract.crop_size_px)
        # (angle, crops of that angle) per frame: fixed for the estimator, so not redone per frame.
        fovs_rad = [math.radians(f) for f in contract.crop_fovs_deg]
        self.crops_per_fov = [(fov, n) for fov, n in zip(fovs_rad, crops_per_scale(self.crops_per_frame, len(fovs_rad)),
                                                         strict=True) if n]
        self.frames_per_window = int(contract.frames_per_window)
        self._intrinsics_checked: Intrinsics | None = None  # the camera last checked for crops too small

    def status_rule(self) -> StatusRule:
        """When the rig calls this model's estimates valid: a full window of its frames, and a
        sun no higher than its training suns allow (:meth:`StatusRule.for_model`)."""
        trained = self.model.contract.trained_sun_elevation_deg
        return StatusRule.for_model(self.frames_per_window, None if trained is None else trained[1])

    # -- per frame ---------------------------------------------------------------------------
    def _crops(self, frame: Frame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # Each crop angle lays out its own crops (spread across the frame among themselves), the
        # first angle first, all from the frame's one generator: a single-angle model draws exactly
        # what it always did.
        if frame.intrinsics != self._intrinsics_checked:  # once a camera: a change of camera is said again
            self._intrinsics_checked = frame.intrinsics
            too_far = enlarged_too_far(frame.intrinsics, [fov for fov, _ in self.crops_per_fov], self.crop_size_px)
            if too_far is not None:
                log.warning("%s", too_far)
        rng = frame_rng(self.seed, frame.seq)
        boxes = np.concatenate([self.sample_boxes(frame.intrinsics, n, crop_side_px(frame.intrinsics, fov), rng)
                                for fov, n in self.crops_per_fov])
        return boxes, crop_angles_rad(boxes, frame.intrinsics), cut_crops(frame.image_bgr, boxes, self.crop_size_px)

    @property
    def backbone_crops_per_frame(self) -> int:
        """How many crops of each frame the backbone runs on: the frame's, and as many flipped
        when the model runs mirrored."""
        return self.crops_per_frame * (2 if self.mirror_windows else 1)

    def backbone_crops(self, frame: Frame) -> np.ndarray:
        """The uint8 BGR crops [n, S, S, 3] the backbone runs on for ``frame``, as :meth:`encode`
        cuts them (what an int8 backbone is calibrated on, ``estimator.quantize``)."""
        return self._with_mirrored(self._crops(frame)[2])

    def _with_mirrored(self, crops: np.ndarray) -> np.ndarray:
        # One backbone run: the crops, then the same crops flipped left to right.
        return np.concatenate([crops, crops[:, :, ::-1]]) if self.mirror_windows else crops

    def encode(self, frame: Frame) -> FrameFeatures:
        """Crops and backbone embeddings of one frame: done once, cached with the frame."""
        return self.encode_batch([frame])[0]

    def encode_batch(self, frames: Sequence[Frame]) -> list[FrameFeatures]:
        """Several frames in one backbone run (replay and eval; live frames come one at a time)."""
        if not frames:
            return []
        parts = [self._crops(f) for f in frames]
        crops = np.concatenate([p[2] for p in parts])
        n_all = len(crops)
        emb = self.model.embed(self._with_mirrored(crops))
        out, start = [], 0
        for frame, (boxes, angles, _) in zip(frames, parts, strict=True):
            n = len(boxes)
            mirrored = emb[n_all + start : n_all + start + n] if self.mirror_windows else None
            # The frame's pixels stay out of its features: the crops above are all that reads them.
            out.append(FrameFeatures(frame.meta(), boxes, angles, emb[start : start + n], self.model.model_id,
                                     mirrored, view_signature=view_signature(frame.image_bgr)))
            start += n
        return out

    # -- per window --------------------------------------------------------------------------
    def estimate(self, window: Sequence[FrameFeatures], aggregator: str | None = None) -> SunEstimate:
        """The sun direction of one window with this estimator's (or the given) aggregator."""
        return self.estimate_many(window, [aggregator or self.aggregator])[aggregator or self.aggregator]

    def estimate_many(self, window: Sequence[FrameFeatures], aggregators: Sequence[str]) -> dict[str, SunEstimate]:
        """Several aggregators on one window, sharing the independent per-crop run (for eval)."""
        unknown = [a for a in aggregators if a not in AGGREGATORS]
        if unknown:
            raise ValidationError(f"aggregator: expected one of {', '.join(AGGREGATORS)}, got {unknown}")
        tokens = window_tokens(window)
        independent = None
        results = {}
        for name in aggregators:
            if name == "transformer":
                if self.mirror_windows:
                    # Each token the mean of its two runs: the window's mean, and so its answer, is
                    # what averaging all 2T vectors would give, while n_tokens and the spread still
                    # count crops.
                    plain, mirrored = mirrored_joint_runs(self.model, tokens, window)
                    world = 0.5 * (plain + mirrored)
                else:
                    world = world_from_tokens(_joint_tokens(self.model, tokens), tokens.yaw_rad)
                unit, spread = mean_direction(world)
            else:
                if independent is None:
                    independent = world_from_tokens(_independent_tokens(self.model, tokens), tokens.yaw_rad)
                world = independent
                if name == "mean":
                    unit, spread = mean_direction(world)
                elif name == "meanshift":
                    unit, inliers = meanshift_aggregate(world)
                    spread = spread_rad(world[inliers], unit)
                else:  # single: the first crop of the newest frame
                    first = sum(f.n_crops for f in window[: window.index(tokens.newest)])
                    unit, _ = mean_direction(world[first : first + 1])
                    # Its spread is the other crops' around it, not one vector's around itself
                    # (always 0, so the status rule called every single-crop answer valid).
                    spread = spread_rad(world, unit)
                    world = world[first : first + 1]
            results[name] = self._make_estimate(name, tokens, unit, spread, world)
        return results

    def _make_estimate(self, name: str, tokens: WindowTokens, unit: np.ndarray, spread: float,
                       world: np.ndarray) -> SunEstimate:
        frame = tokens.newest.frame
        assert frame.attitude is not None  # window_tokens() took only frames with a heading
        # The truth is in true-north ENU: it grades only an estimate made in that world. A RELATIVE
        # or MAGNETIC window's world is turned by its start heading or the declination.
        truth = frame.sun_enu_truth if tokens.heading_ref == HeadingRef.TRUE else None
        return SunEstimate(
            t_mono_s=frame.t_mono_s,
            seq=frame.seq,
            sun_enu=unit,
            heading_rad=frame.attitude.heading_rad,
            heading_ref=tokens.heading_ref,
            spread_rad=min(spread, math.pi),
            n_frames=tokens.n_frames,
            n_tokens=len(world),
            aggregator=name,
            utc_ns=frame.utc_ns,
            truth_enu=truth,
            token_enu=world,
            heading_epoch=frame.attitude.epoch if tokens.heading_ref is HeadingRef.RELATIVE else 0,
        )
