"""The statistical aggregation the paper compares against (Lee et al., GCPR 2021): independent
per-crop estimates, outliers removed, then mean shift on the unit sphere to the densest direction.

Pure numpy. The hyper-parameters this needs (bandwidth, outlier threshold) are exactly what the
transformer aggregation does away with; the defaults here are documented, not tuned per dataset.
"""

from __future__ import annotations

import math

import numpy as np

from estimator.calibration import MIN_DIRECTION_NORM, EstimationError
from rig.geometry import angle_between, normalize

DEFAULT_BANDWIDTH_RAD = math.radians(15.0)
DEFAULT_OUTLIER_RAD = math.radians(60.0)
# 1.4826 * MAD estimates a normal standard deviation; 3 of them bound the inliers.
_MAD_TO_SIGMA = 1.4826
_MAD_K = 3.0


def remove_outliers(units: np.ndarray, outlier_rad: float = DEFAULT_OUTLIER_RAD,
                    floor_rad: float = DEFAULT_BANDWIDTH_RAD) -> np.ndarray:
    """Boolean inlier mask of unit vectors (N, 3).

    The centre is the medoid (the sample with the least summed angle to all others), robust to
    half the samples being wrong. A sample is an inlier within ``outlier_rad`` of it and within
    3 scaled MADs of the median distance (never tighter than ``floor_rad``).
    """
    u = normalize(units)
    pairwise = angle_between(u[:, None, :], u[None, :, :])
    medoid = int(np.argmin(pairwise.sum(axis=1)))
    dist = pairwise[medoid]
    med = float(np.median(dist))
    mad = float(np.median(np.abs(dist - med)))
    limit = min(outlier_rad, max(floor_rad, med + _MAD_K * _MAD_TO_SIGMA * mad))
    return dist <= limit


def meanshift_sphere(units: np.ndarray, bandwidth_rad: float = DEFAULT_BANDWIDTH_RAD,
                     max_iter: int = 100, tol_rad: float = 1e-7) -> np.ndarray:
    """Densest direction of unit vectors (N, 3) under a von Mises-Fisher kernel.

    Mean shift starts from every sample (a few dozen at most here); the mode with the highest
    kernel density wins, so a tight cluster beats a lone far sample.
    """
    u = normalize(units)
    kappa = 1.0 / bandwidth_rad**2  # vMF concentration matching a Gaussian of that angular width
    modes = u.copy()
    for _ in range(max_iter):
        w = np.exp(kappa * (modes @ u.T - 1.0))  # shifted by -1 so exp never overflows
        new = normalize(w @ u)
        moved = float(np.max(angle_between(new, modes)))
        modes = new
        if moved < tol_rad:
            break
    density = np.exp(kappa * (modes @ u.T - 1.0)).sum(axis=1)
    return modes[int(np.argmax(density))]


def meanshift_aggregate(units: np.ndarray, bandwidth_rad: float = DEFAULT_BANDWIDTH_RAD,
                        outlier_rad: float = DEFAULT_OUTLIER_RAD) -> tuple[np.ndarray, np.ndarray]:
    """Outlier removal then mean shift: (mode unit vector, inlier mask).

    A token with no direction (a zero or non-finite vector) is no sample and never an inlier;
    with none that has one, the window has no answer (:class:`EstimationError`, which the rig
    counts and skips, as it does the other aggregators' bad windows)."""
    v = np.asarray(units, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore"):  # the non-finite rows are left out anyway
        norms = np.linalg.norm(np.nan_to_num(v), axis=1)
        usable: np.ndarray = np.isfinite(v).all(axis=1) & (norms >= MIN_DIRECTION_NORM)
    if not usable.any():
        raise EstimationError(
            f"none of the {len(v)} token estimates has a direction (all zero or not finite); "
            "no meanshift answer for this window"
        )
    inliers = np.zeros(len(v), dtype=bool)
    inliers[usable] = remove_outliers(v[usable], outlier_rad=outlier_rad, floor_rad=bandwidth_rad)
    mode = meanshift_sphere(v[inliers], bandwidth_rad=bandwidth_rad)
    return mode, inliers
