"""The run-time variants that bench_accuracy.py --variant measures (benchmarks/variants.py), on the
shipped model and the bundled drive: they must be what the card says they are, or its numbers for
them mean nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.variants import ClampEstimator, clamp_elevation
from estimator.models import resolve_model_dir
from estimator.runtime import OnnxModel
from rig.geometry import az_el_from_enu, enu_from_az_el


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
    return model, *(_demo_windows(cls(model)) for cls in (SunEstimator, ClampEstimator))


def test_clamp_leaves_answers_in_the_trained_range_alone(demo_windows):
    model, plain, clamped = demo_windows
    low, high = model.contract.trained_sun_elevation_deg
    assert all(low <= math.degrees(p.elevation_rad) <= high for p in plain)  # the sun is 15.5 deg up
    for p, c in zip(plain, clamped, strict=True):
        np.testing.assert_allclose(c.sun_enu, p.sun_enu)


def test_clamp_lifts_answers_below_the_trained_range_along_their_azimuth(demo_windows, monkeypatch):
    from estimator.contract import ModelContract

    model, plain, _ = demo_windows
    # As if the model had trained on suns 25-74.9 deg up only: every demo answer (near 15 deg) is below.
    monkeypatch.setattr(ModelContract, "trained_sun_elevation_deg", property(lambda self: (25.0, 74.9)))
    clamped = _demo_windows(ClampEstimator(model))
    for p, c in zip(plain, clamped, strict=True):
        assert math.degrees(c.elevation_rad) == pytest.approx(25.0)
        assert _az_el_deg(c.sun_enu)[0] == pytest.approx(_az_el_deg(p.sun_enu)[0])
