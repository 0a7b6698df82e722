"""Calibration (paper Sec. 3.4): per-token sun vectors from their heading frames into the world.

Each token's vector is rotated by its own frame's yaw (``R_f^-1 v``), and the normalised mean is
the estimate. Pure numpy: the exactness of this step is what lets relative headings work.
"""

from __future__ import annotations

import numpy as np

from rig.errors import SunrigError
from rig.geometry import angle_between, normalize, world_from_heading

# Below this norm a vector (a token's, or the tokens' mean) has no direction to normalise.
MIN_DIRECTION_NORM = 1e-6


class EstimationError(SunrigError):
    """A window cannot give an estimate (no heading, mixed heading references, tokens cancel out,
    a model that computed NaN)."""


def world_from_tokens(v_heading: np.ndarray, yaw_rad: np.ndarray) -> np.ndarray:
    """Rotate per-token vectors (T, 3) in their heading frames into the world frame by yaw (T,)."""
    v = np.asarray(v_heading, dtype=np.float64)
    return np.einsum("tij,tj->ti", world_from_heading(np.asarray(yaw_rad, dtype=np.float64)), v)


def spread_rad(v_world: np.ndarray, centre: np.ndarray) -> float:
    """RMS angle between each vector and ``centre``: how much the tokens disagree."""
    ang = angle_between(normalize(v_world), centre)
    return float(np.sqrt(np.mean(ang**2)))


def mean_direction(v_world: np.ndarray) -> tuple[np.ndarray, float]:
    """The paper's final step: mean of the calibrated vectors, normalised; and their spread.

    The mean is of the raw vectors (the loss trains their norm towards 1), as in the paper.
    """
    v = np.asarray(v_world, dtype=np.float64)
    if not np.isfinite(v).all():
        # Not a window the tokens disagree on: the model itself computed NaN or inf.
        bad = int((~np.isfinite(v).all(axis=1)).sum())
        raise EstimationError(
            f"the model gave {bad} of {len(v)} token vectors that are not finite (NaN or inf); "
            "check the model folder, or re-export it"
        )
    mean = v.mean(axis=0)
    norm = np.linalg.norm(mean)
    if not np.isfinite(norm) or norm < MIN_DIRECTION_NORM:
        raise EstimationError(
            f"the {len(v)} token estimates cancel out (mean norm {norm:.2e}); no direction for this window"
        )
    unit = mean / norm
    return unit, spread_rad(v, unit)


# A window mirrored left to right (about the north-up plane) is a real window of the mirrored
# street under the mirrored sun. Training mirrors windows so (estimator.train.mirror_window) and
# the runtime runs them so (the contract's mirror_windows): both take the signs from here, so the
# two cannot come to mirror differently. Headings are negated too; that needs no helper.


def mirrored_angles(angles_rad: np.ndarray) -> np.ndarray:
    """Token angles (..., 3: yaw relative to the newest frame, horizontal, vertical view angle) of
    the mirrored window: the two that turn left-right are negated. A new array of the same dtype."""
    out = np.array(angles_rad, copy=True)
    out[..., :2] *= -1.0
    return out


def mirrored_enu(v_enu: np.ndarray) -> np.ndarray:
    """ENU vectors (..., 3) in the mirrored world, or back from it: east negated. A new array."""
    out = np.array(v_enu, copy=True)
    out[..., 0] *= -1.0
    return out
