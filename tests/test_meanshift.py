"""The meanshift baseline (Lee et al. 2021): outliers removed, mode of the densest cluster."""

import math

import numpy as np
import pytest

from estimator.meanshift import meanshift_aggregate, meanshift_sphere, remove_outliers
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


def test_identical_samples_are_their_own_mode():
    v = np.tile(normalize([1.0, 2.0, 3.0]), (5, 1))
    mode, inliers = meanshift_aggregate(v)
    np.testing.assert_allclose(mode, v[0], atol=1e-12)
    assert inliers.all()


def test_remove_outliers_keeps_at_least_the_medoid():
    units = normalize(np.random.default_rng(2).normal(size=(6, 3)))
    assert remove_outliers(units).sum() >= 1


@pytest.mark.parametrize("n", [1, 2, 32])
def test_any_count(n):
    units = normalize(np.random.default_rng(n).normal(size=(n, 3)) + [0, 0, 2])
    mode, _ = meanshift_aggregate(units)
    assert np.linalg.norm(mode) == pytest.approx(1.0)
