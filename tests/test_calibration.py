"""Calibration: per-token heading-frame vectors into the world, exactly (paper Sec. 3.4)."""

import math

import numpy as np
import pytest

from estimator.calibration import EstimationError, mean_direction, spread_rad, world_from_tokens
from rig.geometry import angle_between, enu_from_az_el, heading_from_world, normalize, world_from_heading
from tests.tolerances import CALIBRATION_DEG, EXACT_F64


def _rz_clockwise(offset_rad):
    """Rotation of ENU vectors that adds ``offset`` to their azimuth (clockwise about up)."""
    return world_from_heading(offset_rad)


def test_round_trip_world_heading_world():
    rng = np.random.default_rng(0)
    sun = enu_from_az_el(rng.uniform(0, 2 * math.pi), rng.uniform(0.1, 1.3))
    yaw = rng.uniform(0, 2 * math.pi, 32)
    # What each token should say in its own heading frame, then calibrated back.
    v_heading = np.einsum("tij,j->ti", heading_from_world(yaw), sun)
    world = world_from_tokens(v_heading, yaw)
    np.testing.assert_allclose(world, np.broadcast_to(sun, world.shape), atol=EXACT_F64)
    unit, spread = mean_direction(world)
    np.testing.assert_allclose(unit, sun, atol=EXACT_F64)
    assert spread == pytest.approx(0.0, abs=1e-7)


def test_sun_ahead_in_heading_frame_is_at_heading_azimuth():
    # A token that sees the sun straight ahead (+y) while heading 90 deg: the sun is east.
    world = world_from_tokens(np.array([[0.0, 1.0, 0.0]]), np.array([math.pi / 2]))
    np.testing.assert_allclose(world[0], [1.0, 0.0, 0.0], atol=EXACT_F64)


@pytest.mark.parametrize("offset_deg", [0.0, 1.0, 37.5, -90.0, 180.0, 359.0, 1234.5])
def test_global_yaw_offset_rotates_estimate_exactly(offset_deg):
    """Same per-token vectors, every yaw shifted by one offset: the estimate turns by that offset."""
    rng = np.random.default_rng(int(offset_deg * 10) % 2**31)
    v_heading = rng.normal(size=(32, 3)) + [0, 0, 1.0]
    yaw = rng.uniform(0, 2 * math.pi, 32)
    offset = math.radians(offset_deg)
    base, spread0 = mean_direction(world_from_tokens(v_heading, yaw))
    shifted, spread1 = mean_direction(world_from_tokens(v_heading, yaw + offset))
    expected = _rz_clockwise(offset) @ base
    assert math.degrees(float(angle_between(shifted, expected))) < CALIBRATION_DEG
    assert spread1 == pytest.approx(spread0, abs=1e-12)


def test_mean_is_of_raw_vectors_and_spread_is_rms_angle():
    v = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    unit, spread = mean_direction(v)
    np.testing.assert_allclose(unit, normalize([1.0, 1.0, 0.0]), atol=EXACT_F64)
    assert spread == pytest.approx(math.pi / 4)
    assert spread_rad(v, np.array([1.0, 0.0, 0.0])) == pytest.approx(math.sqrt((0 + (math.pi / 2) ** 2) / 2))
    # Equal lengths cannot tell the raw mean from a mean of unit vectors, nor the RMS over every
    # token from the first token's angle. A token twice as long pulls the mean twice as far:
    # (2, 1, 0) / sqrt(5), which is atan(1/2) from the first token and atan(2) from the second.
    unit, spread = mean_direction(np.array([[2.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    np.testing.assert_allclose(unit, np.array([2.0, 1.0, 0.0]) / math.sqrt(5.0), atol=EXACT_F64)
    assert spread == pytest.approx(math.sqrt((math.atan(0.5) ** 2 + math.atan(2.0) ** 2) / 2))


def test_cancelling_tokens_raise():
    with pytest.raises(EstimationError, match="cancel out"):
        mean_direction(np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]))


def test_a_nan_token_raises_as_the_model_s_fault_not_as_cancelling_tokens():
    for bad in (np.nan, np.inf):
        with pytest.raises(EstimationError, match="1 of 2 token vectors that are not finite.*re-export"):
            mean_direction(np.array([[bad, 0.0, 0.0], [0.0, 1.0, 0.0]]))
