"""Run-time variants of the estimator that were measured and not adopted (docs/model.md, "Tried at
run time"). They live here, not in ``estimator/``, so the product carries no switch nobody uses,
while ``bench_accuracy.py --variant NAME`` can still reproduce the card's numbers for them.

- ``mirror``: each window is run a second time mirrored left to right, as training mirrors half
  its windows (``estimator.train.mirror_window``: crops flipped, relative yaw, horizontal view
  angle and yaw negated, east negated after calibration); the transformer's calibrated token
  vectors of both runs are averaged. Twice the backbone and aggregator work.
- ``clamp``: the transformer's answer is moved along its azimuth into the elevations of the
  training suns (the contract's ``trained_sun_elevation_deg``). Its answers above them are hedges
  of a model unsure of the azimuth; the rig flags them (``ABOVE_TRAINED``), this corrects them.
- ``ensemble``: the same crops through further, independently trained models (``--members``),
  each with its own backbone and transformer; every member's calibrated token vectors are pooled
  into one mean. A deep ensemble: models that differ only by their training seed miss on different
  drives (docs/model.md), and averaging them is the usual cure for a model sure and wrong. One
  backbone and aggregator run per member.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections import OrderedDict
from collections.abc import Callable, Sequence

import numpy as np

from estimator.calibration import mean_direction, world_from_tokens
from estimator.crops import cut_crops
from estimator.estimator import SunEstimator, window_tokens
from rig.errors import ValidationError
from rig.geometry import az_el_from_enu, enu_from_az_el
from rig.types import Frame, FrameFeatures, SunEstimate

VARIANTS = ("plain", "mirror", "clamp", "ensemble")


class _ExtraEmbeddings:
    """Embeddings made beside the estimator's own for the frames seen lately (a mirrored run, or
    another model's), found again by the identity of their FrameFeatures. The entry holds the
    FrameFeatures itself, so its id cannot be reused while the entry lives; a window reaches back
    at most a few dozen frames (the policy's span at 10 Hz)."""

    KEEP = 256

    def __init__(self) -> None:
        self._by_frame: OrderedDict[int, tuple[FrameFeatures, np.ndarray]] = OrderedDict()

    def add(self, features: Sequence[FrameFeatures], embeddings: np.ndarray) -> None:
        start = 0
        for ff in features:
            self._by_frame[id(ff)] = (ff, embeddings[start : start + ff.n_crops])
            start += ff.n_crops
        while len(self._by_frame) > self.KEEP:
            self._by_frame.popitem(last=False)

    def of_window(self, window: Sequence[FrameFeatures]) -> np.ndarray:
        """(T, D) float32, in window_tokens' order (every frame: it raised if one had no heading)."""
        return np.concatenate([self._by_frame[id(f)][1] for f in window]).astype(np.float32)


def _cut(estimator: SunEstimator, frames: Sequence[Frame], features: Sequence[FrameFeatures]) -> np.ndarray:
    """The crops the estimator cut for ``features``, cut again (a benchmark may pay for it twice)."""
    return np.concatenate([cut_crops(f.image_bgr, ff.crop_boxes_px, estimator.crop_size_px)
                           for f, ff in zip(frames, features, strict=True)])


class MirrorEstimator(SunEstimator):
    """The ``mirror`` variant; the other aggregators are the plain ones."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._mirrored = _ExtraEmbeddings()

    def encode_batch(self, frames: Sequence[Frame]) -> list[FrameFeatures]:
        out = super().encode_batch(frames)
        if out:
            self._mirrored.add(out, self.model.embed(np.ascontiguousarray(_cut(self, frames, out)[:, :, ::-1])))
        return out

    def estimate_many(self, window: Sequence[FrameFeatures], aggregators: Sequence[str]) -> dict[str, SunEstimate]:
        results = super().estimate_many(window, aggregators)
        if "transformer" not in results:
            return results
        tokens = window_tokens(window)  # the same frames, in the same order, as the plain run's
        emb = self._mirrored.of_window(window)
        angles = tokens.angles_rad.copy()
        angles[:, :2] *= -1.0
        v = self.model.aggregate(emb[None], angles[None], np.ones((1, len(emb)), dtype=bool))[0]
        mirrored = world_from_tokens(np.asarray(v, dtype=np.float64), -tokens.yaw_rad)
        mirrored[:, 0] *= -1.0  # back from the mirrored world: east negated
        world = np.concatenate([results["transformer"].token_enu, mirrored])
        unit, spread = mean_direction(world)
        results["transformer"] = self._make_estimate("transformer", tokens, unit, spread, world)
        return results


class EnsembleEstimator(SunEstimator):
    """The ``ensemble`` variant: ``model`` and ``members`` on the same crops; the other aggregators
    are ``model``'s alone. ``token_enu`` of an estimate holds ``model``'s tokens first, then each
    member's, in the order given."""

    def __init__(self, model, *args, members: Sequence = (), **kwargs) -> None:
        super().__init__(model, *args, **kwargs)
        if not members:
            raise ValidationError("ensemble: give at least one more model (--members DIR[,DIR])")
        for m in members:
            differs = [k for k in ("crop_size_px", "crop_fovs_deg", "frames_per_window")
                       if getattr(m.contract, k) != getattr(model.contract, k)]
            if differs:
                raise ValidationError(f"ensemble: {m.model_dir} differs from {model.model_dir} in "
                                      f"{', '.join(differs)}; members must see the same crops")
        self.members = list(members)
        self._member_embeddings = [_ExtraEmbeddings() for _ in self.members]

    def encode_batch(self, frames: Sequence[Frame]) -> list[FrameFeatures]:
        out = super().encode_batch(frames)
        if out:
            crops = _cut(self, frames, out)
            for member, cache in zip(self.members, self._member_embeddings, strict=True):
                cache.add(out, member.embed(crops))
        return out

    def estimate_many(self, window: Sequence[FrameFeatures], aggregators: Sequence[str]) -> dict[str, SunEstimate]:
        results = super().estimate_many(window, aggregators)
        if "transformer" not in results:
            return results
        tokens = window_tokens(window)
        world = [results["transformer"].token_enu]
        for member, cache in zip(self.members, self._member_embeddings, strict=True):
            emb = cache.of_window(window)
            v = member.aggregate(emb[None], tokens.angles_rad[None], np.ones((1, len(emb)), dtype=bool))[0]
            world.append(world_from_tokens(np.asarray(v, dtype=np.float64), tokens.yaw_rad))
        unit, spread = mean_direction(np.concatenate(world))
        results["transformer"] = self._make_estimate("transformer", tokens, unit, spread, np.concatenate(world))
        return results


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


def estimator_for(variant: str, members: Sequence = ()) -> Callable[..., SunEstimator]:
    """What makes the variant's estimator from (model, **SunEstimator options); ``members`` are the
    further models of ``ensemble``, which the other variants refuse."""
    if variant == "ensemble":
        return functools.partial(EnsembleEstimator, members=members)
    if members:
        raise ValidationError(f"--members is for the ensemble variant, not {variant!r}")
    return {"plain": SunEstimator, "mirror": MirrorEstimator, "clamp": ClampEstimator}[variant]
