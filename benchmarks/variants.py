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
"""

from __future__ import annotations

import dataclasses
import math
from collections import OrderedDict
from collections.abc import Sequence

import numpy as np

from estimator.calibration import mean_direction, world_from_tokens
from estimator.crops import cut_crops
from estimator.estimator import SunEstimator, window_tokens
from rig.geometry import az_el_from_enu, enu_from_az_el
from rig.types import Frame, FrameFeatures, SunEstimate

VARIANTS = ("plain", "mirror", "clamp")


class MirrorEstimator(SunEstimator):
    """The ``mirror`` variant; the other aggregators are the plain ones."""

    # Mirrored embeddings of the frames seen lately, by the identity of their FrameFeatures. The
    # entry holds the FrameFeatures itself, so its id cannot be reused while the entry lives; a
    # window reaches back at most a few dozen frames (the policy's span at 10 Hz).
    _KEEP = 256

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self._mirrored: OrderedDict[int, tuple[FrameFeatures, np.ndarray]] = OrderedDict()

    def encode_batch(self, frames: Sequence[Frame]) -> list[FrameFeatures]:
        out = super().encode_batch(frames)
        if not out:
            return out
        flipped = np.concatenate([cut_crops(f.image_bgr, ff.crop_boxes_px, self.crop_size_px)[:, :, ::-1]
                                  for f, ff in zip(frames, out, strict=True)])
        emb = self.model.embed(np.ascontiguousarray(flipped))
        start = 0
        for ff in out:
            self._mirrored[id(ff)] = (ff, emb[start : start + ff.n_crops])
            start += ff.n_crops
        while len(self._mirrored) > self._KEEP:
            self._mirrored.popitem(last=False)
        return out

    def estimate_many(self, window: Sequence[FrameFeatures], aggregators: Sequence[str]) -> dict[str, SunEstimate]:
        results = super().estimate_many(window, aggregators)
        if "transformer" not in results:
            return results
        tokens = window_tokens(window)  # the same frames, in the same order, as the plain run's
        # window_tokens() keeps only frames with a heading, and raised above if any had none.
        emb = np.concatenate([self._mirrored[id(f)][1] for f in window]).astype(np.float32)
        angles = tokens.angles_rad.copy()
        angles[:, :2] *= -1.0
        v = self.model.aggregate(emb[None], angles[None], np.ones((1, len(emb)), dtype=bool))[0]
        mirrored = world_from_tokens(np.asarray(v, dtype=np.float64), -tokens.yaw_rad)
        mirrored[:, 0] *= -1.0  # back from the mirrored world: east negated
        world = np.concatenate([results["transformer"].token_enu, mirrored])
        unit, spread = mean_direction(world)
        results["transformer"] = self._make_estimate("transformer", tokens, unit, spread, world)
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


def estimator_for(variant: str) -> type[SunEstimator]:
    return {"plain": SunEstimator, "mirror": MirrorEstimator, "clamp": ClampEstimator}[variant]
