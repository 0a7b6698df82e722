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
from rig.geometry import angle_between

# The shipped model's windows on the bundled drive are a few degrees off (test_shipped_model.py);
# a mirrored run brought back into the world with east left negated answers the mirror image of
# the sun, tens of degrees off wherever the sun is not due north or south (here: 38 deg mean). Its
# mirrored half alone is 11.4 deg off on average and 13.6 at most; with the crops' horizontal view
# angles left unmirrored the worst window is 27 deg off, which only the max catches.
MIRRORED_MEAN_ERR_DEG = 15.0
MIRRORED_MAX_ERR_DEG = 20.0


def _enu(az_deg: float, el_deg: float) -> np.ndarray:
    az, el = math.radians(az_deg), math.radians(el_deg)
    return np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el), math.sin(el)])


def _az_el_deg(u: np.ndarray) -> tuple[float, float]:
    return math.degrees(math.atan2(u[0], u[1])) % 360.0, math.degrees(math.asin(u[2]))


@pytest.mark.parametrize(("el_deg", "expected_deg"), [(40.0, 40.0), (82.0, 74.9), (-3.0, 5.0), (5.0, 5.0)])
def test_clamp_moves_only_the_elevation_into_the_range(el_deg, expected_deg):
    az, el = _az_el_deg(clamp_elevation(_enu(123.0, el_deg), 5.0, 74.9))
    assert az == pytest.approx(123.0) and el == pytest.approx(expected_deg)


def test_clamp_of_the_zenith_is_a_unit_vector_at_the_top_of_the_range():
    u = clamp_elevation(np.array([0.0, 0.0, 1.0]), 5.0, 74.9)
    assert np.linalg.norm(u) == pytest.approx(1.0) and _az_el_deg(u)[1] == pytest.approx(74.9)


@pytest.fixture(scope="module")
def demo_windows():
    from estimator.estimator import SunEstimator
    from replay.sources import DEMO_LOG, open_frames
    from rig.offline import estimate_stream
    from rig.window import SpreadWindowPolicy

    model = OnnxModel.load(resolve_model_dir(None))

    def run(cls: type[SunEstimator]) -> list:
        windows = estimate_stream(open_frames(DEMO_LOG), cls(model), SpreadWindowPolicy(n_frames=8))
        return [w["transformer"] for w in windows if w["transformer"].n_frames == 8]

    return model, run(SunEstimator), run(MirrorEstimator), run(ClampEstimator)


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
    from replay.sources import DEMO_LOG, open_frames
    from rig.offline import estimate_stream
    from rig.window import SpreadWindowPolicy

    model, plain, _, _ = demo_windows
    # As if the model had trained on suns 25-74.9 deg up only: every demo answer (near 15 deg) is below.
    monkeypatch.setattr(ModelContract, "trained_sun_elevation_deg", property(lambda self: (25.0, 74.9)))
    clamped = [w["transformer"] for w in estimate_stream(open_frames(DEMO_LOG), ClampEstimator(model),
                                                         SpreadWindowPolicy(n_frames=8))
               if w["transformer"].n_frames == 8]
    for p, c in zip(plain, clamped, strict=True):
        assert math.degrees(c.elevation_rad) == pytest.approx(25.0)
        assert _az_el_deg(c.sun_enu)[0] == pytest.approx(_az_el_deg(p.sun_enu)[0])
