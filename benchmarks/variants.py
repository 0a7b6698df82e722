"""Run-time variants of the estimator that were measured and not adopted (docs/model.md, "Tried at
run time"). They live here, not in ``estimator/``, so the product carries no switch nobody uses,
while ``bench_accuracy.py --variant NAME`` can still reproduce the card's numbers for them.

- ``clamp``: the transformer's answer is moved along its azimuth into the elevations of the
  training suns (the contract's ``trained_sun_elevation_deg``). Its answers above them are hedges
  of a model unsure of the azimuth; the rig flags them (``ABOVE_TRAINED``), this corrects them.
- ``latin``: each crop angle's top edges are stratified like its left edges (``spread``), each
  crop taking one stratum of each, so a frame's narrow crops reach from the sky to the street
  instead of landing all high or all low by chance.
- ``tiled``: each crop angle's left edges are evenly spaced across the frame, the first flush
  left and the last flush right, the same in every frame (top edges still random), so that every
  frame's crops reach both edges of the view; ``tiledlatin`` stratifies its top edges as well.
- ``split``: for a model run mirrored, the mirrored run sees other crops than the plain one: each
  crop angle spreads twice its crops across the frame, the plain run takes every other one from
  the left and the mirrored run the rest, flipped. The same backbone and aggregator work as
  ``mirror_windows`` (one flipped crop for each plain one), with twice the places seen.

(``mirror``, tried here first, was adopted in session 23: it is the contract's ``mirror_windows``
now, which ``bench_accuracy.py --mirror-windows on|off`` overrides.)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from estimator.calibration import mean_direction
from estimator.crops import (
    crop_angles_rad,
    crop_side_px,
    cut_crops,
    frame_rng,
    spread_crop_boxes,
    stratified_positions,
)
from estimator.estimator import SunEstimator, mirrored_joint_runs, window_tokens
from rig.errors import ValidationError
from rig.geometry import az_el_from_enu, enu_from_az_el
from rig.types import Frame, FrameFeatures, Intrinsics, SunEstimate
from rig.window import view_signature


def clamp_elevation(sun_enu: np.ndarray, low_deg: float, high_deg: float) -> np.ndarray:
    """``sun_enu`` moved along its azimuth to the nearest elevation in [low_deg, high_deg] (straight
    up has no azimuth to keep; az_el_from_enu gives it north)."""
    az, el = az_el_from_enu(sun_enu)
    target = np.clip(el, math.radians(low_deg), math.radians(high_deg))
    return np.asarray(sun_enu, dtype=np.float64) if target == el else enu_from_az_el(az, target)


class ClampEstimator(SunEstimator):
    """The ``clamp`` variant; the other aggregators are the plain ones."""

    def estimate_many(self, window: Sequence[FrameFeatures], aggregators: Sequence[str]) -> dict[str, SunEstimate]:
        results = super().estimate_many(window, aggregators)
        trained = self.model.contract.trained_sun_elevation_deg
        if "transformer" in results and trained is not None:
            est = results["transformer"]
            results["transformer"] = dataclasses.replace(est, sun_enu=clamp_elevation(est.sun_enu, *trained))
        return results


def _stratify_top_edges(boxes: np.ndarray, intrinsics: Intrinsics, rng: np.random.Generator) -> np.ndarray:
    """``boxes`` (of one side) with their top edges redrawn stratified: the valid range cut into as
    many equal strata as boxes, each box's top edge uniform within its own, the strata paired with
    the boxes at random. With left edges spread or tiled, a Latin hypercube of the valid corners."""
    boxes[:, 1] = rng.permutation(stratified_positions(intrinsics.height - int(boxes[0, 3]) + 1, len(boxes), rng))
    return boxes


def latin_crop_boxes(intrinsics: Intrinsics, n: int, side_px: int, rng: np.random.Generator) -> np.ndarray:
    """``spread_crop_boxes`` with the top edges stratified too (the ``latin`` variant)."""
    return _stratify_top_edges(spread_crop_boxes(intrinsics, n, side_px, rng), intrinsics, rng)


def tiled_crop_boxes(intrinsics: Intrinsics, n: int, side_px: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` boxes whose left edges are evenly spaced from the image's left edge to its right, the
    first flush left and the last flush right, the same in every frame; top edges uniform, as in
    ``sample_crop_boxes`` (the ``tiled`` variant)."""
    if n <= 0 or not 0 < side_px <= min(intrinsics.width, intrinsics.height):
        raise ValidationError(f"tiled crops: expected n > 0 and a side within the image, got {n} of {side_px} px")
    x0 = np.round(np.linspace(0.0, intrinsics.width - side_px, n)).astype(np.int64)
    y0 = rng.integers(0, intrinsics.height - side_px + 1, size=n)
    return np.stack([x0, y0, np.full(n, side_px), np.full(n, side_px)], axis=1).astype(np.int64)


def tiled_latin_crop_boxes(intrinsics: Intrinsics, n: int, side_px: int, rng: np.random.Generator) -> np.ndarray:
    """``tiled_crop_boxes`` with the top edges stratified too (the ``tiledlatin`` variant)."""
    return _stratify_top_edges(tiled_crop_boxes(intrinsics, n, side_px, rng), intrinsics, rng)


class LayoutEstimator(SunEstimator):
    """A variant that is a crop layout of its own (``layout``): it takes the place of ``spread``
    and refuses any other ``crop_layout``."""

    layout: Any = None

    def __init__(self, model: Any, **kwargs: Any) -> None:
        if kwargs.get("crop_layout", "spread") != "spread":
            raise ValidationError("this variant is a crop layout of its own; leave --crop-layout at spread")
        super().__init__(model, **kwargs)
        self.sample_boxes = type(self).layout


class LatinEstimator(LayoutEstimator):
    layout = staticmethod(latin_crop_boxes)


class TiledEstimator(LayoutEstimator):
    layout = staticmethod(tiled_crop_boxes)


class TiledLatinEstimator(LayoutEstimator):
    layout = staticmethod(tiled_latin_crop_boxes)


@dataclasses.dataclass(frozen=True, eq=False)
class SplitFeatures(FrameFeatures):
    """A frame's features for the ``split`` variant: ``embeddings_mirrored`` are of other crops
    than ``embeddings``, flipped, whose (unmirrored) view angles these are."""

    crop_angles_mirrored_rad: np.ndarray | None = None


class SplitEstimator(SunEstimator):
    """The ``split`` variant (module docstring). Only the transformer changes: its tokens are the
    plain run's and the mirrored run's side by side, since they are of different crops."""

    def __init__(self, model: Any, **kwargs: Any) -> None:
        super().__init__(model, **kwargs)
        if not self.mirror_windows:
            raise ValidationError("the split variant changes the mirrored run; run it with the model mirrored "
                                  "(--mirror-windows on, or a model whose contract says so)")

    def _split_boxes(self, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
        rng = frame_rng(self.seed, frame.seq)
        plain, other = [], []
        for fov, n in self.crops_per_fov:
            boxes = self.sample_boxes(frame.intrinsics, 2 * n, crop_side_px(frame.intrinsics, fov), rng)
            boxes = boxes[np.argsort(boxes[:, 0], kind="stable")]  # left to right, so alternate strata
            plain.append(boxes[0::2])
            other.append(boxes[1::2])
        return np.concatenate(plain), np.concatenate(other)

    def encode_batch(self, frames: Sequence[Frame]) -> list[FrameFeatures]:
        if not frames:
            return []
        boxes = [self._split_boxes(f) for f in frames]
        plain = [cut_crops(f.image_bgr, a, self.crop_size_px) for f, (a, _) in zip(frames, boxes, strict=True)]
        flipped = [cut_crops(f.image_bgr, b, self.crop_size_px)[:, :, ::-1]
                   for f, (_, b) in zip(frames, boxes, strict=True)]
        emb = self.model.embed(np.concatenate(plain + flipped))  # one backbone run, as the product's
        n_plain = sum(len(a) for a, _ in boxes)
        out: list[FrameFeatures] = []
        start = 0
        for frame, (a, b) in zip(frames, boxes, strict=True):
            n = len(a)
            out.append(SplitFeatures(frame, a, crop_angles_rad(a, frame.intrinsics), emb[start : start + n],
                                     self.model.model_id, emb[n_plain + start : n_plain + start + n],
                                     crop_angles_mirrored_rad=crop_angles_rad(b, frame.intrinsics),
                                     view_signature=view_signature(frame.image_bgr)))
            start += n
        return out

    def estimate_many(self, window: Sequence[FrameFeatures], aggregators: Sequence[str]) -> dict[str, SunEstimate]:
        others = [a for a in aggregators if a != "transformer"]
        results = super().estimate_many(window, others) if others else {}
        if "transformer" not in aggregators:
            return results
        if not all(isinstance(f, SplitFeatures) for f in window):
            raise ValidationError("the split variant needs frames encoded by its own encode_batch")
        tokens = window_tokens(window)
        other_angles = np.concatenate([f.crop_angles_mirrored_rad for f in window])  # type: ignore[attr-defined]
        # Other crops in each run, so their tokens stand side by side rather than averaged in pairs.
        world = np.concatenate(mirrored_joint_runs(self.model, tokens, window, other_angles))
        unit, spread = mean_direction(world)
        results["transformer"] = self._make_estimate("transformer", tokens, unit, spread, world)
        return results


ESTIMATORS: dict[str, type[SunEstimator]] = {
    "plain": SunEstimator, "clamp": ClampEstimator, "latin": LatinEstimator, "split": SplitEstimator,
    "tiled": TiledEstimator, "tiledlatin": TiledLatinEstimator,
}


VARIANTS = tuple(ESTIMATORS)


def estimator_for(variant: str) -> type[SunEstimator]:
    return ESTIMATORS[variant]

