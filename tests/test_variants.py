"""The run-time variants that bench_accuracy.py --variant measures (benchmarks/variants.py), on the
shipped model and the bundled drive: they must be what the card says they are, or its numbers for
them mean nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.variants import ClampEstimator, MirrorEstimator, clamp_elevation
from estimator.calibration import mean_direction
from estimator.models import resolve_model_dir
from estimator.runtime import OnnxModel
from rig.geometry import angle_between, az_el_from_enu, enu_from_az_el

# The shipped model's windows on the bundled drive are a few degrees off (test_shipped_model.py);
# a mirrored run brought back into the world with east left negated answers the mirror image of
# the sun, tens of degrees off wherever the sun is not due north or south (here: 38 deg mean). Its
# mirrored half alone is 11.4 deg off on average and 13.6 at most; with the crops' horizontal view
# angles left unmirrored the worst window is 27 deg off, which only the max catches.
MIRRORED_MEAN_ERR_DEG = 15.0
MIRRORED_MAX_ERR_DEG = 20.0


def _az_el_deg(u: np.ndarray) -> tuple[float, float]:
    az, el = az_el_from_enu(u)
    return math.degrees(az), math.degrees(el)


@pytest.mark.parametrize(("el_deg", "expected_deg"), [(40.0, 40.0), (82.0, 74.9), (-3.0, 5.0), (5.0, 5.0)])
def test_clamp_moves_only_the_elevation_into_the_range(el_deg, expected_deg):
    az, el = _az_el_deg(clamp_elevation(enu_from_az_el(math.radians(123.0), math.radians(el_deg)), 5.0, 74.9))
    assert az == pytest.approx(123.0) and el == pytest.approx(expected_deg)


def test_clamp_of_the_zenith_is_a_unit_vector_at_the_top_of_the_range():
    u = clamp_elevation(np.array([0.0, 0.0, 1.0]), 5.0, 74.9)
    assert np.linalg.norm(u) == pytest.approx(1.0) and _az_el_deg(u)[1] == pytest.approx(74.9)


def _demo_windows(estimator) -> list:
    """The transformer's estimates of the bundled drive's full windows."""
    from replay.sources import DEMO_LOG, open_frames
    from rig.offline import estimate_stream
    from rig.window import SpreadWindowPolicy

    windows = estimate_stream(open_frames(DEMO_LOG), estimator, SpreadWindowPolicy(n_frames=8))
    return [w["transformer"] for w in windows if w["transformer"].n_frames == 8]


@pytest.fixture(scope="module")
def demo_windows():
    from estimator.estimator import SunEstimator

    model = OnnxModel.load(resolve_model_dir(None))
    return model, *(_demo_windows(cls(model)) for cls in (SunEstimator, MirrorEstimator, ClampEstimator))


def test_mirror_adds_a_mirrored_run_that_finds_the_same_sun(demo_windows):
    _, plain, mirror, _ = demo_windows
    assert len(mirror) == len(plain) == 33
    errors = []
    for p, m in zip(plain, mirror, strict=True):
        n = len(p.token_enu)
        assert len(m.token_enu) == 2 * n
        np.testing.assert_allclose(m.token_enu[:n], p.token_enu, atol=1e-6)  # the plain run, unchanged
        mirrored_alone, _ = mean_direction(m.token_enu[n:])
        errors.append(math.degrees(angle_between(mirrored_alone, p.truth_enu)))
    assert float(np.mean(errors)) < MIRRORED_MEAN_ERR_DEG
    assert max(errors) < MIRRORED_MAX_ERR_DEG


def test_clamp_leaves_answers_in_the_trained_range_alone(demo_windows):
    model, plain, _, clamped = demo_windows
    low, high = model.contract.trained_sun_elevation_deg
    assert all(low <= math.degrees(p.elevation_rad) <= high for p in plain)  # the sun is 15.5 deg up
    for p, c in zip(plain, clamped, strict=True):
        np.testing.assert_allclose(c.sun_enu, p.sun_enu)


def test_clamp_lifts_answers_below_the_trained_range_along_their_azimuth(demo_windows, monkeypatch):
    from estimator.contract import ModelContract

    model, plain, _, _ = demo_windows
    # As if the model had trained on suns 25-74.9 deg up only: every demo answer (near 15 deg) is below.
    monkeypatch.setattr(ModelContract, "trained_sun_elevation_deg", property(lambda self: (25.0, 74.9)))
    clamped = _demo_windows(ClampEstimator(model))
    for p, c in zip(plain, clamped, strict=True):
        assert math.degrees(c.elevation_rad) == pytest.approx(25.0)
        assert _az_el_deg(c.sun_enu)[0] == pytest.approx(_az_el_deg(p.sun_enu)[0])
