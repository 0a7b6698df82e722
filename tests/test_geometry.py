"""Frames and angle conventions (docs/conventions.md): golden values, round trips, batching."""

import math

import numpy as np
import pytest

from rig.geometry import (
    angle_between,
    az_el_from_enu,
    enu_from_az_el,
    heading_from_world,
    view_angles_rad,
    world_from_heading,
    wrap_2pi,
    wrap_pi,
    wrapped_deg,
)
from tests.tolerances import ANGLE_RAD_F64, EXACT_F64


@pytest.mark.parametrize(
    ("az_deg", "el_deg", "enu"),
    [
        (0.0, 0.0, (0.0, 1.0, 0.0)),  # north
        (90.0, 0.0, (1.0, 0.0, 0.0)),  # east: azimuth is clockwise from north
        (180.0, 0.0, (0.0, -1.0, 0.0)),
        (270.0, 0.0, (-1.0, 0.0, 0.0)),
        (123.0, 90.0, (0.0, 0.0, 1.0)),  # zenith
        (45.0, 30.0, (math.cos(math.radians(30)) * math.sqrt(0.5),) * 2 + (0.5,)),
    ],
)
def test_enu_from_az_el_golden(az_deg, el_deg, enu):
    np.testing.assert_allclose(enu_from_az_el(math.radians(az_deg), math.radians(el_deg)), enu, atol=EXACT_F64)


def test_az_el_round_trip_batched_equals_scalar():
    rng = np.random.default_rng(0)
    az = rng.uniform(0, 2 * math.pi, 200)
    el = rng.uniform(-1.5, 1.5, 200)
    v = enu_from_az_el(az, el)
    az2, el2 = az_el_from_enu(v)
    np.testing.assert_allclose(wrap_pi(az2 - az), 0.0, atol=ANGLE_RAD_F64)
    np.testing.assert_allclose(el2, el, atol=ANGLE_RAD_F64)
    for i in (0, 17, 199):
        np.testing.assert_allclose(enu_from_az_el(az[i], el[i]), v[i], atol=EXACT_F64)


def test_az_el_of_a_vector_that_is_not_unit_length():
    # (0.3, 0.4, 1.0) is 0.5 along the ground and 1.0 up: elevation atan2(1, 0.5), not asin(1).
    az, el = az_el_from_enu([0.3, 0.4, 1.0])
    assert float(az) == pytest.approx(math.atan2(0.3, 0.4), abs=ANGLE_RAD_F64)
    assert float(el) == pytest.approx(math.atan2(1.0, 0.5), abs=ANGLE_RAD_F64)


@pytest.mark.parametrize(
    ("heading_deg", "forward_enu", "right_enu"),
    [
        (0.0, (0, 1, 0), (1, 0, 0)),  # facing north, right is east
        (90.0, (1, 0, 0), (0, -1, 0)),  # facing east, right is south
        (180.0, (0, -1, 0), (-1, 0, 0)),
        (270.0, (-1, 0, 0), (0, 1, 0)),
    ],
)
def test_world_from_heading_golden(heading_deg, forward_enu, right_enu):
    r = world_from_heading(math.radians(heading_deg))
    np.testing.assert_allclose(r @ [0, 1, 0], forward_enu, atol=EXACT_F64)
    np.testing.assert_allclose(r @ [1, 0, 0], right_enu, atol=EXACT_F64)
    np.testing.assert_allclose(r @ [0, 0, 1], [0, 0, 1], atol=EXACT_F64)


def test_heading_rotation_round_trip_and_batch():
    rng = np.random.default_rng(1)
    psi = rng.uniform(-10, 10, 50)
    v = rng.normal(size=(50, 3))
    r = world_from_heading(psi)
    assert r.shape == (50, 3, 3)
    back = np.einsum("nij,nj->ni", heading_from_world(psi), np.einsum("nij,nj->ni", r, v))
    np.testing.assert_allclose(back, v, atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(r), 1.0, atol=EXACT_F64)
    np.testing.assert_allclose(r[7], world_from_heading(psi[7]), atol=EXACT_F64)


def test_forward_azimuth_equals_heading():
    """A heading psi looks along azimuth psi: the conventions agree with each other."""
    for psi in np.radians([0.0, 10.0, 135.0, 359.0]):
        fwd = world_from_heading(psi) @ [0, 1, 0]
        assert az_el_from_enu(fwd)[0] == pytest.approx(psi, abs=ANGLE_RAD_F64)


def test_wraps():
    assert float(wrap_2pi(-1e-18)) < 2 * math.pi
    np.testing.assert_allclose(wrap_2pi([-math.pi / 2, 5 * math.pi]), [1.5 * math.pi, math.pi])
    np.testing.assert_allclose(wrap_pi([3 * math.pi / 2, -3 * math.pi / 2]), [-math.pi / 2, math.pi / 2])
    # Just below -pi the sum rounds to 2 pi in the modulo, which once came back as +pi.
    assert float(wrap_pi(np.nextafter(-math.pi, -math.inf))) == -math.pi
    assert float(az_el_from_enu([-1e-17, 1.0, 0.0])[0]) == 0.0  # not 2 pi
    assert isinstance(wrap_2pi(0.5), np.floating) and isinstance(wrap_pi(0.5), np.floating)


def test_wrapped_deg_never_sends_the_top_of_its_range():
    assert wrapped_deg(2 * math.pi) == 0.0
    assert float(np.float32(359.99999)) == 360.0  # what a plain float32 field would carry
    assert wrapped_deg(math.radians(359.99999), float32=True) == 0.0
    assert wrapped_deg(math.radians(179.999999), -180.0, float32=True) == -180.0
    assert wrapped_deg(math.radians(359.9), float32=True) == pytest.approx(359.9, abs=1e-4)
    assert wrapped_deg(-math.pi, -180.0) == -180.0


def test_angle_between_small_and_opposite():
    a = np.array([1.0, 0.0, 0.0])
    b = np.array([math.cos(1e-8), math.sin(1e-8), 0.0])
    assert angle_between(a, b) == pytest.approx(1e-8, rel=1e-6)
    assert angle_between(a, -a) == pytest.approx(math.pi)


def test_view_angles_centre_and_edges():
    fx, fy, cx, cy, w, h = 721.5377, 721.5377, 609.5593, 172.854, 1242, 375
    hz, vt = view_angles_rad(cx, cy, fx, fy, cx, cy)
    assert (hz, vt) == (0.0, 0.0)
    left, top = view_angles_rad(0.0, 0.0, fx, fy, cx, cy)
    right, bottom = view_angles_rad(w, h, fx, fy, cx, cy)
    assert left == pytest.approx(-math.atan(cx / fx)) and right == pytest.approx(math.atan((w - cx) / fx))
    assert top == pytest.approx(math.atan(cy / fy)) and bottom == pytest.approx(-math.atan((h - cy) / fy))
    # KITTI image_02: 81.4 x 29.1 deg edge to edge (docs/conventions.md).
    assert math.degrees(right - left) == pytest.approx(81.4, abs=0.05)
    assert math.degrees(top - bottom) == pytest.approx(29.1, abs=0.05)


def test_view_angles_with_non_square_pixels():
    # fx = 500, fy = 250: 100 px right of centre and 50 px above it are both tan = 0.2.
    hz, vt = view_angles_rad(300.0 + 100.0, 200.0 - 50.0, 500.0, 250.0, 300.0, 200.0)
    assert float(hz) == pytest.approx(math.atan(0.2), abs=ANGLE_RAD_F64)
    assert float(vt) == pytest.approx(math.atan(0.2), abs=ANGLE_RAD_F64)
