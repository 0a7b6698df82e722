"""The meanshift baseline (Lee et al. 2021): outliers removed, mode of the densest cluster."""

import math

import numpy as np
import pytest

from estimator.calibration import EstimationError
from estimator.meanshift import DEFAULT_BANDWIDTH_RAD, meanshift_aggregate, meanshift_sphere, remove_outliers
from rig.geometry import angle_between, enu_from_az_el, normalize


def _cluster(rng, centre, n, sigma_rad):
    return normalize(centre + rng.normal(scale=sigma_rad, size=(n, 3)))


def test_finds_dense_cluster_despite_outliers():
    rng = np.random.default_rng(0)
    sun = enu_from_az_el(math.radians(200), math.radians(35))
    inl = _cluster(rng, sun, 24, math.radians(4))
    out = normalize(rng.normal(size=(8, 3)))  # a quarter of the crops say anything at all
    units = np.concatenate([inl, out])
    mode, inliers = meanshift_aggregate(units)
    assert math.degrees(angle_between(mode, sun)) < 3.0
    # The plain mean is dragged by the outliers; the baseline must do better than that.
    mean = normalize(units.mean(axis=0))
    assert angle_between(mode, sun) < angle_between(mean, sun)
    assert inliers[:24].mean() > 0.9


def test_two_clusters_picks_the_bigger():
    rng = np.random.default_rng(1)
    a = enu_from_az_el(0.3, 0.5)
    b = enu_from_az_el(2.5, 0.4)
    units = np.concatenate([_cluster(rng, a, 20, 0.05), _cluster(rng, b, 8, 0.05)])
    assert angle_between(meanshift_sphere(units), a) < math.radians(3)


def test_clusters_38_deg_apart_are_two_modes_to_the_default_bandwidth():
    # 40 deg of azimuth at 17 deg elevation is 38 deg on the sphere, two and a half 15 deg
    # bandwidths: the mode stays on the bigger cluster instead of being pulled between them.
    rng = np.random.default_rng(7)
    a, b = enu_from_az_el(0.0, 0.3), enu_from_az_el(math.radians(40.0), 0.3)
    units = np.concatenate([_cluster(rng, a, 12, 0.02), _cluster(rng, b, 9, 0.02)])
    assert angle_between(meanshift_sphere(units), a) < math.radians(3)


def test_mode_is_a_fixed_point_of_the_kernel_mean():
    # A skewed cluster, so that one shift does not reach the mode: the iteration must run until
    # the kernel-weighted mean of the samples around the mode is the mode itself, with the
    # documented kernel (a vMF of concentration 1 / bandwidth^2).
    rng = np.random.default_rng(5)
    u = np.concatenate([_cluster(rng, enu_from_az_el(0.3, 0.5), 12, 0.05),
                        _cluster(rng, enu_from_az_el(0.55, 0.5), 6, 0.05)])
    mode = meanshift_sphere(u)
    kappa = 1.0 / DEFAULT_BANDWIDTH_RAD**2
    again = normalize(np.exp(kappa * (u @ mode - 1.0)) @ u)
    assert float(angle_between(again, mode)) < 1e-5


def test_a_narrow_bandwidth_does_not_overflow():
    # kappa = 1 / (1 deg)^2 ~ 3300: exp(kappa * cos) would overflow; the kernel is shifted by -1, so
    # a mode's own samples weigh about exp(0) = 1 and the densities of the modes stay comparable:
    # the bigger cluster, 10 deg from the smaller one listed first, still wins.
    rng = np.random.default_rng(0)
    small, big = enu_from_az_el(1.0, 0.5), enu_from_az_el(1.0 + math.radians(10.0) / math.cos(0.5), 0.5)
    u = np.concatenate([_cluster(rng, small, 4, 0.002), _cluster(rng, big, 10, 0.002)])
    mode = meanshift_sphere(u, bandwidth_rad=math.radians(1.0))
    assert np.isfinite(mode).all() and np.linalg.norm(mode) == pytest.approx(1.0)
    assert math.degrees(float(angle_between(mode, big))) < 0.5


def test_outliers_are_removed_around_the_medoid_before_the_mode():
    # A tight minority 120 deg away is denser than the wide majority, so mean shift alone would
    # pick it; it is far from the medoid (inside the majority), so outlier removal drops it first.
    rng = np.random.default_rng(4)
    a = enu_from_az_el(0.0, 0.4)
    b = enu_from_az_el(math.radians(120.0), 0.4)
    u = np.concatenate([_cluster(rng, a, 12, math.radians(12)), _cluster(rng, b, 8, math.radians(0.5))])
    mode, inliers = meanshift_aggregate(u)
    assert not inliers[12:].any()
    assert math.degrees(float(angle_between(mode, a))) < 6.0


def test_identical_samples_are_their_own_mode():
    v = np.tile(normalize([1.0, 2.0, 3.0]), (5, 1))
    mode, inliers = meanshift_aggregate(v)
    np.testing.assert_allclose(mode, v[0], atol=1e-12)
    assert inliers.all()


@pytest.mark.parametrize(
    ("samples", "kept"),
    [
        # (deg from the pole, azimuth deg); the pole is the medoid. Distances 0, 10..14, 30, 40:
        # median 12.5, MAD 2.0, so the limit is 12.5 + 3 * 1.4826 * 2.0 = 21.4 deg.
        ([(0, 0), (10, 0), (11, 90), (12, 180), (13, 270), (14, 45), (30, 135), (40, 225)], [True] * 6 + [False] * 2),
        # Distances 0, 9..12, 19, 21: median 11, MAD 2 (deviations 0, 1, 1, 2, 8, 10, 11), so the limit
        # is 11 + 3 * 1.4826 * 2 = 19.9 deg: 19 deg (4 MADs past the median) is in, 21 deg (5) is out.
        ([(0, 0), (9, 0), (10, 90), (11, 180), (12, 270), (19, 45), (21, 225)], [True] * 6 + [False]),
        # A tight cluster makes the MAD limit a fraction of a degree: the 15 deg floor keeps 12 deg.
        ([(0, 0), (0.01, 0), (0.02, 0), (0.03, 0), (0.04, 0), (12, 0)], [True] * 6),
    ],
)
def test_inlier_limit_is_three_scaled_mads_past_the_median_never_below_the_floor(samples, kept):
    u = np.array([enu_from_az_el(math.radians(az), math.radians(90 - d)) for d, az in samples])
    assert remove_outliers(u).tolist() == kept


def test_remove_outliers_keeps_at_least_the_medoid():
    units = normalize(np.random.default_rng(2).normal(size=(6, 3)))
    assert remove_outliers(units).sum() >= 1


def test_a_sample_at_the_limit_is_an_inlier():
    # With both radii 0 the limit is 0 deg: only the medoid (the pole) and its duplicate, at
    # distance exactly 0, are within it.
    samples = [(0, 0), (0, 0), (10, 0), (11, 90), (12, 180)]
    u = np.array([enu_from_az_el(math.radians(az), math.radians(90 - d)) for d, az in samples])
    assert remove_outliers(u, outlier_rad=0.0, floor_rad=0.0).tolist() == [True, True, False, False, False]


@pytest.mark.parametrize("n", [1, 2, 32])
def test_any_count(n):
    units = normalize(np.random.default_rng(n).normal(size=(n, 3)) + [0, 0, 2])
    mode, _ = meanshift_aggregate(units)
    assert np.linalg.norm(mode) == pytest.approx(1.0)


def test_tokens_without_a_direction_are_no_samples_and_none_is_no_answer():
    # A model that gives zero or NaN vectors once returned [0, 0, 0] as the "unit" mode (or raised
    # a numpy error), which ended a live run; the other aggregators skip such a window.
    sun = enu_from_az_el(math.radians(120), math.radians(40))
    units = np.stack([sun, sun, np.zeros(3), np.full(3, np.nan), sun])
    mode, inliers = meanshift_aggregate(units)
    assert math.degrees(angle_between(mode, sun)) < 1e-6
    assert inliers.tolist() == [True, True, False, False, True]
    for bad in (np.zeros((64, 3)), np.full((64, 3), np.nan), np.full((4, 3), np.inf)):
        with pytest.raises(EstimationError, match="has a direction"):
            meanshift_aggregate(bad)
