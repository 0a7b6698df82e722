"""Frames, angles and rotations shared by every part of sunrig. Pure numpy, radians throughout.

Frames (see docs/conventions.md for the full table):

- ``enu``: world frame, x east, y north, z up.
- ``heading``: per camera frame; z up (gravity), y the optical axis projected onto the horizontal
  plane, x = y cross z (to the right). The network's per-token sun vectors live here.
- ``cam``: OpenCV camera frame, x right, y down, z forward.

Heading (yaw) ``psi`` is clockwise from north (north = 0, east = pi/2). Sun azimuth is clockwise
from north too, elevation is above the horizon. Transforms are named ``<to>_from_<from>``.
"""

from __future__ import annotations

import math

import numpy as np

TWO_PI = 2.0 * np.pi


def wrap_2pi(angle_rad) -> np.ndarray:
    """Wrap angles to [0, 2 pi)."""
    wrapped = np.mod(angle_rad, TWO_PI)
    # np.mod can return exactly 2 pi for tiny negative inputs through rounding. Multiplying by the
    # mask, not np.where, keeps a scalar a numpy scalar for the callers that format it.
    return wrapped - TWO_PI * (wrapped >= TWO_PI)


def wrap_pi(angle_rad):
    """Wrap angles to [-pi, pi)."""
    wrapped = np.mod(np.asarray(angle_rad) + np.pi, TWO_PI)
    # As in wrap_2pi: a tiny negative sum would come back as 2 pi, i.e. +pi.
    return wrapped - TWO_PI * (wrapped >= TWO_PI) - np.pi


def wrapped_deg(angle_rad: float, low_deg: float = 0.0, *, float32: bool = False) -> float:
    """An angle already wrapped to [low, low + 2 pi) rad, in degrees within [low_deg, low_deg + 360).

    Converting can round a value just below the top onto the top itself: ``math.degrees`` of the
    largest double under 2 pi is 360.0, and a float32 holds about 2e-5 deg at 360. The wire's
    ranges say the top is never sent, so the top becomes the bottom, the same direction."""
    deg = math.degrees(angle_rad)
    if float32:
        deg = float(np.float32(deg))
    return low_deg if deg >= low_deg + 360.0 else deg


def enu_from_az_el(azimuth_rad, elevation_rad) -> np.ndarray:
    """Unit vector(s) in ENU for azimuth (clockwise from north) and elevation; shape (..., 3)."""
    az = np.asarray(azimuth_rad, dtype=np.float64)
    el = np.asarray(elevation_rad, dtype=np.float64)
    return np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], axis=-1)


def az_el_from_enu(v_enu) -> tuple[np.ndarray, np.ndarray]:
    """Azimuth in [0, 2 pi) clockwise from north and elevation in [-pi/2, pi/2] of (..., 3)."""
    v = np.asarray(v_enu, dtype=np.float64)
    az = wrap_2pi(np.arctan2(v[..., 0], v[..., 1]))
    el = np.arctan2(v[..., 2], np.hypot(v[..., 0], v[..., 1]))
    return az, el


def world_from_heading(heading_rad) -> np.ndarray:
    """Rotation(s) taking heading-frame vectors into the world frame; shape (..., 3, 3).

    The heading frame's x (right), y (forward) and z (up) axes are the columns:
    forward = (sin psi, cos psi, 0), right = (cos psi, -sin psi, 0), up = (0, 0, 1) in ENU.
    The paper writes this as R_f^-1.
    """
    psi = np.asarray(heading_rad, dtype=np.float64)
    c, s = np.cos(psi), np.sin(psi)
    zero, one = np.zeros_like(psi), np.ones_like(psi)
    rows = [
        np.stack([c, s, zero], axis=-1),
        np.stack([-s, c, zero], axis=-1),
        np.stack([zero, zero, one], axis=-1),
    ]
    return np.stack(rows, axis=-2)


def heading_from_world(heading_rad) -> np.ndarray:
    """Inverse of :func:`world_from_heading` (its transpose)."""
    return np.swapaxes(world_from_heading(heading_rad), -1, -2)


def normalize(v, axis: int = -1, eps: float = 1e-12) -> np.ndarray:
    """Unit vectors along ``axis``; a zero vector stays zero instead of becoming NaN."""
    v = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(v, axis=axis, keepdims=True)
    return v / np.maximum(n, eps)


def angle_between(a, b) -> np.ndarray:
    """Angle in radians between vectors (..., 3), accurate near 0 and pi (atan2 form)."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    cross = np.linalg.norm(np.cross(a, b), axis=-1)
    dot = np.sum(a * b, axis=-1)
    return np.arctan2(cross, dot)


def view_angles_rad(u_px, v_px, fx: float | np.ndarray, fy: float | np.ndarray, cx: float | np.ndarray,
                    cy: float | np.ndarray):
    """Horizontal and vertical view angle of pixel (u, v) for a pinhole camera.

    Horizontal is positive to the right, ``atan((u - cx) / fx)``; vertical is positive up,
    ``atan((cy - v) / fy)``. Pixel coordinates are continuous: the left image edge is u = 0.
    """
    u = np.asarray(u_px, dtype=np.float64)
    v = np.asarray(v_px, dtype=np.float64)
    return np.arctan((u - cx) / fx), np.arctan((cy - v) / fy)
