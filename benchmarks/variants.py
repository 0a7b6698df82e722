"""Run-time variants of the estimator that were measured and not adopted (docs/model.md, "Tried at
run time"). They live here, not in ``estimator/``, so the product carries no switch nobody uses,
while ``bench_accuracy.py --variant NAME`` can still reproduce the card's numbers for them.

- ``clamp``: the transformer's answer is moved along its azimuth into the elevations of the
  training suns (the contract's ``trained_sun_elevation_deg``). Its answers above them are hedges
  of a model unsure of the azimuth; the rig flags them (``ABOVE_TRAINED``), this corrects them.

(``mirror``, tried here first, was adopted in session 23: it is the contract's ``mirror_windows``
now, which ``bench_accuracy.py --mirror-windows on|off`` overrides.)
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from estimator.estimator import SunEstimator
from rig.geometry import az_el_from_enu, enu_from_az_el
from rig.types import FrameFeatures, SunEstimate

VARIANTS = ("plain", "clamp")


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
    return {"plain": SunEstimator, "clamp": ClampEstimator}[variant]
