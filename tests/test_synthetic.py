"""Synthetic drives: determinism, Frame fields, and that the picture obeys the sun it claims.

The geometric checks build tiny scenes by hand (a pole, a box, a wall and a car) on flat, untextured
ground, light them with a known sun and look at the rendered radiance where the conventions say
the shadow, the sun or the lit face must be: azimuth clockwise from north, ENU, heading along
(sin psi, cos psi), OpenCV camera, pixel (u, v) continuous with the image edge at 0.
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest

from replay.synthetic import Drive, drive_seed, kitti_intrinsics, plan_drive, synth_drive
from replay.synthetic.camera import Camera, CameraEffects
from replay.synthetic.drive import SUN_ELEVATION_RANGE_DEG
from replay.synthetic.render import CameraPose, Renderer, project_direction, project_points, world_from_cam
from replay.synthetic.scene import (
    GroundMap,
    Material,
    Scene,
    SceneObject,
    WindowPattern,
    box_solid,
    ellipsoid_solid,
    make_car,
)
from replay.synthetic.sky import (
    _AEROSOL_LAMBDA,
    _RAYLEIGH_TAU,
    SOLAR_ILLUMINANCE_KLUX,
    SUN_ANGULAR_RADIUS_RAD,
    PreethamSky,
    relative_airmass,
)
from rig.geometry import az_el_from_enu, enu_from_az_el, world_from_heading
from rig.types import HeadingRef

SMALL = kitti_intrinsics(0.25)  # 310 x 94, the KITTI field of view
LUMA = np.array([0.0722, 0.7152, 0.2126], np.float32)  # BGR
GREY = Material((0.3, 0.3, 0.3), contrast=0.0)


def flat_scene(objects, albedo=(0.25, 0.25, 0.25)) -> Scene:
    return Scene(GroundMap.flat(albedo, ((-60.0, -60.0), (60.0, 60.0)), 0.1), objects,
                 np.full((256, 256), 0.5, np.float32))


def render(objects, sun_az_deg, sun_el_deg, pose, intr=SMALL):
    sky = PreethamSky(enu_from_az_el(math.radians(sun_az_deg), math.radians(sun_el_deg)), 3.0)
    r = Renderer(flat_scene(objects), sky, intr, shadow_res_m=0.05)
    out = r.render(pose)
    return r, out, out.radiance @ LUMA


def pixel(uv) -> tuple[int, int]:
    """Row, column of the pixel containing continuous coordinate (u, v)."""
    return int(math.floor(uv[1])), int(math.floor(uv[0]))


# ---------------------------------------------------------------------------------------------
# Camera model


def test_camera_axes_follow_heading_and_opencv():
    for psi in (0.0, 0.7, math.pi / 2, 4.0):
        r = world_from_cam(psi)
        np.testing.assert_allclose(r[:, 2], [math.sin(psi), math.cos(psi), 0.0], atol=1e-12)  # forward
        np.testing.assert_allclose(r[:, 0], [math.cos(psi), -math.sin(psi), 0.0], atol=1e-12)  # right
        np.testing.assert_allclose(r[:, 1], [0.0, 0.0, -1.0], atol=1e-12)  # down
        # Same heading frame as rig.geometry: camera x/z are the heading frame's x/y.
        np.testing.assert_allclose(world_from_heading(psi)[:, :2], r[:, [0, 2]], atol=1e-12)


def test_pitch_up_and_roll_right_move_the_horizon_as_stated():
    pose = CameraPose((0.0, 0.0, 1.65), 1.0, math.radians(3.0), 0.0)
    # Nose up: the horizon (a far point at elevation 0 straight ahead) drops below cy.
    uv, _ = project_direction(enu_from_az_el(1.0, 0.0), pose, SMALL)
    assert uv[1] == pytest.approx(SMALL.cy + SMALL.fy * math.tan(math.radians(3.0)), abs=1e-6)
    # Right side down: the horizon's right end rises in the image.
    pose = CameraPose((0.0, 0.0, 1.65), 1.0, 0.0, math.radians(4.0))
    left, _ = project_direction(enu_from_az_el(1.0 - 0.5, 0.0), pose, SMALL)
    right, _ = project_direction(enu_from_az_el(1.0 + 0.5, 0.0), pose, SMALL)
    assert right[1] < left[1] - 5
    # The optical axis' horizontal projection stays on the heading whatever the pitch and roll.
    r = world_from_cam(2.0, 0.02, -0.03)
    az, _ = az_el_from_enu(r[:, 2])
    assert float(az) == pytest.approx(2.0, abs=1e-12)


def test_sun_in_view_is_the_brightest_pixel_where_the_intrinsics_put_it():
    heading = math.radians(30.0)
    for d_az, el in ((0.0, 8.0), (12.0, 10.0), (-20.0, 6.0)):
        pose = CameraPose((0.0, 0.0, 1.65), heading)
        _, out, lum = render([], math.degrees(heading) + d_az, el, pose)
        # Independent of the renderer: pinhole, OpenCV, heading along (sin, cos).
        da, e = math.radians(d_az), math.radians(el)
        u = SMALL.cx + SMALL.fx * math.tan(da)
        v = SMALL.cy - SMALL.fy * math.tan(e) / math.cos(da)
        i, j = np.unravel_index(np.argmax(lum), lum.shape)
        assert abs(j + 0.5 - u) <= 1.0 and abs(i + 0.5 - v) <= 1.0, (d_az, el, (u, v), (j, i))
        # Sub-pixel: the disk's light centroid (pixel centres at index + 0.5).
        win = lum[i - 3:i + 4, j - 3:j + 4]
        wgt = np.clip(win - np.median(lum), 0.0, None)
        yy, xx = np.mgrid[i - 3:i + 4, j - 3:j + 4] + 0.5
        cu, cv = (wgt * xx).sum() / wgt.sum(), (wgt * yy).sum() / wgt.sum()
        assert abs(cu - u) < 0.25 and abs(cv - v) < 0.25, (d_az, el, (u, v), (cu, cv))
        assert out.sun_visible == pytest.approx(1.0)


def test_sun_behind_the_camera_is_not_drawn():
    pose = CameraPose((0.0, 0.0, 1.65), 0.0)
    _, out, lum = render([], 180.0, 10.0, pose)
    assert np.isnan(out.sun_px).all() and out.sun_visible == 0.0
    assert lum.max() < 100.0  # no disk (the disk is ~1e6 kcd/m^2)


def test_sky_is_brighter_toward_the_sun():
    sky = PreethamSky(enu_from_az_el(math.radians(100.0), math.radians(30.0)), 3.0)
    near = sky.radiance(enu_from_az_el(math.radians(110.0), math.radians(25.0))) @ LUMA
    far = sky.radiance(enu_from_az_el(math.radians(280.0), math.radians(25.0))) @ LUMA
    assert near > 2.0 * far
    # Blue sky: away from the sun the blue channel (BGR index 0) leads.
    rad = sky.radiance(enu_from_az_el(math.radians(280.0), math.radians(60.0)))
    assert rad[0] > rad[2]


def test_kasten_young_air_mass():
    # Kasten & Young (1989): 1 / (sin el + 0.50572 (el + 6.07995 deg)^-1.6364); ~1 at the zenith,
    # ~38 at the horizon (their table: 38.09 for the refracted horizon; 37.92 by this formula),
    # and the horizon's value below it (a sun just set must not give an infinite or negative mass).
    assert relative_airmass(math.radians(90.0)) == pytest.approx(1.0, abs=1e-3)
    assert relative_airmass(math.radians(30.0)) == pytest.approx(1.0 / (0.5 + 0.50572 * 36.07995**-1.6364))
    assert relative_airmass(0.0) == pytest.approx(37.92, abs=0.01)
    assert relative_airmass(math.radians(-5.0)) == relative_airmass(0.0)


def test_preetham_sky_refuses_a_set_sun_and_turbidity_outside_its_fit():
    with pytest.raises(ValueError, match="above the horizon"):
        PreethamSky(enu_from_az_el(0.0, math.radians(-1.0)))
    for t in (1.0, 12.0):  # Preetham's coefficients are fitted for turbidity ~2..10
        with pytest.raises(ValueError, match="turbidity"):
            PreethamSky(enu_from_az_el(0.0, math.radians(30.0)), t)


def test_zenith_luminance_is_preethams_formula():
    # At the zenith the Perez ratio F(0, theta_s) / F(0, theta_s) is 1, so the luminance there is
    # Preetham's (appendix A.2) Y_z = (4.0453 T - 4.9710) tan(chi) - 0.2155 T + 2.4192 with
    # chi = (4/9 - T/120)(pi - 2 theta_s), times sky_scale (0.6); LUMA recovers Y from linear sRGB.
    for t, el_deg in ((3.0, 40.0), (6.0, 20.0)):
        sky = PreethamSky(enu_from_az_el(0.3, math.radians(el_deg)), t)
        theta_s = math.radians(90.0 - el_deg)
        chi = (4.0 / 9.0 - t / 120.0) * (math.pi - 2.0 * theta_s)
        want = 0.6 * ((4.0453 * t - 4.9710) * math.tan(chi) - 0.2155 * t + 2.4192)
        assert float(sky.radiance(np.array([0.0, 0.0, 1.0])) @ LUMA) == pytest.approx(want, rel=1e-3)


def test_direct_sun_follows_the_air_mass_and_the_visibility():
    # Transmittance exp(-tau m): tau = Rayleigh + Angstrom aerosol beta(T) lambda^-1.3 with
    # Preetham's beta = 0.04608 T - 0.04586, m the air mass at the sun's elevation. The per-channel
    # optical depths and the solar constant are the module's; the law is what is checked.
    el = math.radians(30.0)
    sun = enu_from_az_el(1.0, el)
    tau = _RAYLEIGH_TAU + (0.04608 * 3.0 - 0.04586) * _AEROSOL_LAMBDA
    clear = PreethamSky(sun, 3.0)
    np.testing.assert_allclose(clear.sun_irradiance_bgr, SOLAR_ILLUMINANCE_KLUX * np.exp(-tau * relative_airmass(el)),
                               rtol=1e-12)
    assert tau[0] > tau[1] > tau[2]  # blue is scattered most: a low sun is redder
    # A sun dimmed by cloud scales the beam; the visibility is clipped to [0, 1].
    np.testing.assert_allclose(PreethamSky(sun, 3.0, sun_visibility=0.5).sun_irradiance_bgr,
                               0.5 * clear.sun_irradiance_bgr, rtol=1e-12)
    np.testing.assert_allclose(PreethamSky(sun, 3.0, sun_visibility=2.0).sun_irradiance_bgr,
                               clear.sun_irradiance_bgr, rtol=1e-12)
    # The disk's radiance times its solid angle pi r^2 is the beam's irradiance.
    np.testing.assert_allclose(clear.sun_disk_radiance_bgr() * math.pi * SUN_ANGULAR_RADIUS_RAD**2,
                               clear.sun_irradiance_bgr, rtol=1e-12)


def test_cloud_cover_mixes_in_a_grey_cie_overcast_sky():
    # radiance = (1 - 0.4 c) clear + 0.4 c grey, grey following the CIE overcast (1 + 2 sin el) / 3:
    # what is left after removing the clear share has equal channels and is 3x brighter at the
    # zenith than at the horizon.
    sun = enu_from_az_el(2.0, math.radians(35.0))
    dirs = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], np.float32)  # zenith, horizon (east)
    grey = PreethamSky(sun, 3.0, cloud_cover=0.5).radiance(dirs) - 0.8 * PreethamSky(sun, 3.0).radiance(dirs)
    np.testing.assert_allclose(grey, grey[:, :1].repeat(3, axis=1), rtol=1e-4)
    assert grey[0, 0] == pytest.approx(3.0 * grey[1, 0], rel=1e-4)


def test_ground_bounce_lights_only_downward_faces():
    # ambient_irradiance: a face looking up sees only sky; a face looking down sees only the
    # ground, a Lambertian plane of albedo rho lit by the sky and the sun on it:
    # E_down = rho (E_sky,up + E_sun,up). A face turned from the sun gets no direct light.
    sky = PreethamSky(enu_from_az_el(0.5, math.radians(40.0)), 3.0)
    up, down = sky.ambient_irradiance([[0.0, 0.0, 1.0]])[0], sky.ambient_irradiance([[0.0, 0.0, -1.0]])[0]
    np.testing.assert_allclose(down, 0.15 * (up + sky.direct_irradiance([[0.0, 0.0, 1.0]])[0]), rtol=1e-9)
    np.testing.assert_allclose(sky.direct_irradiance([-sky.sun_enu]), 0.0)


# ---------------------------------------------------------------------------------------------
# Shading and shadows


def _shadow_samples(base_xy, height, sun_az_deg, sun_el_deg, fractions):
    """Ground points along where a pole's shadow must fall (away from the sun), and the same
    points mirrored to the sun's side, where no shadow may be."""
    away = -np.array([math.sin(math.radians(sun_az_deg)), math.cos(math.radians(sun_az_deg))])
    length = height / math.tan(math.radians(sun_el_deg))
    shadow = [np.r_[base_xy + away * f * length, 0.0] for f in fractions]
    mirror = [np.r_[base_xy - away * f * length, 0.0] for f in fractions]
    return shadow, mirror


@pytest.mark.parametrize("sun_az_deg", [135.0, 225.0, 300.0, 60.0])
def test_pole_shadow_falls_away_from_the_sun(sun_az_deg):
    base = np.array([0.0, 14.0])
    pole = SceneObject("pole", [box_solid(base, 0.0, 0.4, 0.4, 0.0, 6.0, GREY)])
    pose = CameraPose((0.0, 0.0, 1.65), 0.0, math.radians(-8.0))
    sun_el = 40.0
    _, out, lum = render([pole], sun_az_deg, sun_el, pose, intr=kitti_intrinsics(0.5))
    intr = kitti_intrinsics(0.5)
    shadow, mirror = _shadow_samples(base, 6.0, sun_az_deg, sun_el, (0.3, 0.55, 0.8))
    uv_s, _ = project_points(shadow, pose, intr)
    uv_m, _ = project_points(mirror, pose, intr)
    for a, b in zip(uv_s, uv_m, strict=True):
        ia, ib = pixel(a), pixel(b)
        assert out.ids[ia] == 1 and out.ids[ib] == 1  # both on open ground
        assert out.sunlit[ia] < 0.05, f"no shadow where it must fall: {a}"
        assert out.sunlit[ib] > 0.95, f"shadow on the sun's side: {b}"
        assert lum[ia] < 0.6 * lum[ib]
    # And in image terms: the shadow goes left of the pole exactly when the sun is to the right.
    (u_base,), _ = project_points([np.r_[base, 0.0]], pose, intr)
    sun_right = math.sin(math.radians(sun_az_deg)) > 0  # camera looks north: east is right
    assert (uv_s[-1][0] < u_base[0]) == sun_right


@pytest.mark.parametrize(("sun_az_deg", "brighter"), [(90.0, "east"), (180.0, "south"), (135.0, None)])
def test_face_turned_to_the_sun_is_brighter(sun_az_deg, brighter):
    box = SceneObject("building", [box_solid((0.0, 0.0), 0.0, 6.0, 6.0, 0.0, 8.0, GREY)])
    pose = CameraPose((10.0, -10.0, 1.65), math.radians(315.0))  # looking at the SE corner
    _, out, lum = render([box], sun_az_deg, 30.0, pose)
    (east, south), _ = project_points([[3.0, 0.0, 3.0], [0.0, -3.0, 3.0]], pose, SMALL)
    le, ls = lum[pixel(east)], lum[pixel(south)]
    assert out.ids[pixel(east)] >= 2 and out.ids[pixel(south)] >= 2
    if brighter == "east":
        assert le > 2.0 * ls
    elif brighter == "south":
        assert ls > 2.0 * le
    else:  # sun on the diagonal: both equally lit
        assert le == pytest.approx(ls, rel=0.02)
    # A sunward face is lit, not shadowed by its own box.
    for uv, n in ((east, (1.0, 0.0, 0.0)), (south, (0.0, -1.0, 0.0))):
        if np.dot(n, enu_from_az_el(math.radians(sun_az_deg), math.radians(30.0))) > 0.1:
            assert out.sunlit[pixel(uv)] > 0.95


def test_tall_box_shadows_a_low_box_downsun_but_not_upsun():
    tall = SceneObject("building", [box_solid((0.0, 20.0), 0.0, 4.0, 4.0, 0.0, 10.0, GREY)])
    west = SceneObject("building", [box_solid((-5.0, 20.0), 0.0, 3.0, 3.0, 0.0, 2.0, GREY)])
    east = SceneObject("building", [box_solid((5.0, 20.0), 0.0, 3.0, 3.0, 0.0, 2.0, GREY)])
    pose = CameraPose((0.0, 0.0, 6.0), 0.0, math.radians(-12.0))  # up high to see the roofs
    _, out, _ = render([tall, west, east], 100.0, 30.0, pose)  # sun in the east, a little south
    (roof_w, roof_e), _ = project_points([[-5.0, 20.5, 2.0], [5.0, 20.5, 2.0]], pose, SMALL)
    assert out.ids[pixel(roof_w)] >= 2 and out.ids[pixel(roof_e)] >= 2
    assert out.sunlit[pixel(roof_w)] < 0.05  # in the tall box's shadow (it reaches ~17 m west)
    assert out.sunlit[pixel(roof_e)] > 0.95


def _ray_boxes(origin, dirs, boxes, any_hit=False):
    """Oracle: nearest hit parameter (N,) of rays origin (3,) or (N, 3) + t * dirs with upright yawed boxes
    (centre, yaw, width, length, z0, z1), by the slab method; inf where none is hit. With
    ``any_hit`` a ray starting inside a box counts as hitting it (at 0)."""
    best = np.full(len(dirs), np.inf)
    for (cx, cy), yaw, w, ln, z0, z1 in boxes:
        r = np.array([math.cos(yaw), -math.sin(yaw), 0.0])  # local x (width)
        f = np.array([math.sin(yaw), math.cos(yaw), 0.0])  # local y (length)
        up = np.array([0.0, 0.0, 1.0])
        o = np.asarray(origin, dtype=np.float64) - np.array([cx, cy, 0.0])
        t0, t1 = np.full(len(dirs), -np.inf), np.full(len(dirs), np.inf)
        for axis, lo, hi in ((r, -w / 2, w / 2), (f, -ln / 2, ln / 2), (up, z0, z1)):
            od, dd = o @ axis, dirs @ axis
            with np.errstate(divide="ignore", invalid="ignore"):
                a, b = (lo - od) / dd, (hi - od) / dd
            inside = (od >= lo) & (od <= hi)
            a = np.where(dd == 0, np.where(inside, -np.inf, np.inf), a)
            b = np.where(dd == 0, np.where(inside, np.inf, -np.inf), b)
            t0, t1 = np.maximum(t0, np.minimum(a, b)), np.minimum(t1, np.maximum(a, b))
        hit = (t0 <= t1) & (t1 > 1e-6)
        if any_hit:
            best = np.where(hit, np.minimum(best, np.maximum(t0, 0.0)), best)
        else:
            best = np.where(hit & (t0 > 1e-6) & (t0 < best), t0, best)
    return best


@pytest.mark.parametrize("seed", range(6))
def test_depth_and_shadows_match_a_ray_cast_oracle(seed):
    rng = np.random.default_rng(seed)
    boxes = []
    while len(boxes) < 6:  # footprints must not overlap (the renderer's scene contract)
        c = (float(rng.uniform(-15, 15)), float(rng.uniform(8, 40)))
        w, ln = float(rng.uniform(1, 6)), float(rng.uniform(1, 8))
        if all(math.dist(c, b[0]) > 0.5 * (math.hypot(w, ln) + math.hypot(b[2], b[3])) for b in boxes):
            boxes.append((c, float(rng.uniform(0, math.pi)), w, ln,
                          float(rng.choice([0.0, rng.uniform(0.5, 3.0)])), float(rng.uniform(3, 12))))
    objects = [SceneObject("box", [box_solid(c, yaw, w, ln, z0, z1, GREY)]) for c, yaw, w, ln, z0, z1 in boxes]
    # Stacked objects: a car-like stack below the camera, a sign-like one reaching above it.
    for (cx, cy), parts in (((3.5, 6.0), [(1.6, 3.5, 0.0, 0.35), (1.8, 4.4, 0.35, 1.0), (1.5, 2.2, 1.0, 1.5)]),
                            ((-3.0, 5.0), [(0.1, 0.1, 0.0, 2.2), (0.05, 0.9, 2.2, 2.9)])):
        yaw = float(rng.uniform(0, math.pi))
        stack = [((cx, cy), yaw, w, ln, z0, z1) for w, ln, z0, z1 in parts]
        objects.append(SceneObject("stack", [box_solid(c, a, w, ln, z0, z1, GREY) for c, a, w, ln, z0, z1 in stack]))
        boxes.extend(stack)
    sun_az, sun_el = float(rng.uniform(0, 360)), float(rng.uniform(15, 70))
    pose = CameraPose((float(rng.uniform(-2, 2)), 0.0, 1.65), math.radians(float(rng.uniform(-15, 15))),
                      math.radians(float(rng.uniform(-3, 1))), math.radians(float(rng.uniform(-2, 2))))
    r, out, _ = render(objects, sun_az, sun_el, pose)
    # Rays through pixel centres, z_cam = 1, so that t is the camera depth as in the renderer.
    v, u = np.mgrid[0:SMALL.height, 0:SMALL.width] + 0.5
    cam = np.stack([(u - SMALL.cx) / SMALL.fx, (v - SMALL.cy) / SMALL.fy, np.ones_like(u)], -1).reshape(-1, 3)
    dirs = cam @ pose.world_from_cam().T
    origin = np.asarray(pose.position)
    t_box = _ray_boxes(origin, dirs, boxes)
    t_ground = np.where(dirs[:, 2] < 0, -origin[2] / np.where(dirs[:, 2] < 0, dirs[:, 2], -1.0), np.inf)
    t = np.minimum(t_box, t_ground)
    surface = np.isfinite(t) & (t < 200.0)
    depth = out.depth.reshape(-1)
    # Pixels on an object's outline may go either way; compare away from depth edges.
    tt = np.where(surface, t, 1e4).reshape(SMALL.height, SMALL.width)
    edge = np.zeros_like(tt, bool)
    for dy, dx in ((0, 1), (1, 0), (0, -1), (-1, 0)):
        edge |= np.abs(np.roll(tt, (dy, dx), (0, 1)) - tt) > 0.05 * tt
    keep = surface & ~edge.reshape(-1)
    assert keep.sum() > 0.25 * keep.size
    rel = np.abs(depth[keep] - t[keep]) / t[keep]
    assert np.mean(rel < 0.01) > 0.99, np.mean(rel < 0.01)
    # Outlines too: which box (or the ground) each pixel centre sees.
    which = np.full(len(dirs), -1)
    best = np.where(t_ground < t_box, t_ground, np.inf)
    for i, b in enumerate(boxes):
        ti = _ray_boxes(origin, dirs, [b])
        closer = ti < best
        which[closer], best[closer] = i, ti[closer]
    solid_of_face = np.concatenate([np.full(len(f), i) for i, f in enumerate(r._solid_faces)])
    ids = out.ids.reshape(-1).astype(int)
    got = np.where(ids >= 2, solid_of_face[np.maximum(ids - 2, 0)], -1)
    on_object = surface & ((which >= 0) | (got >= 0))
    mismatch = np.mean(which[on_object] != got[on_object])
    assert mismatch < 0.045, mismatch  # fillConvexPoly's fill is ~1 px fat at outlines: ~2-3 %
    # Shadow: does the ray from the surface point toward the sun hit a box? Only where the sun
    # reaches at all: faces turned away get no direct light whatever their visibility says.
    n_dot_s = r.tab_direct[ids, 0, 3]
    keep &= (n_dot_s > 0.05) | (ids == 1)
    s = enu_from_az_el(math.radians(sun_az), math.radians(sun_el))
    # Start a hair in front of the surface (toward the camera), then head for the sun.
    pts = origin + dirs[keep] * (t[keep, None] * (1.0 - 1e-4))
    lit = ~np.isfinite(_ray_boxes(pts, np.broadcast_to(s, pts.shape), boxes, any_hit=True))
    sunlit = out.sunlit.reshape(-1)[keep]
    agree = np.where(lit, sunlit > 0.5, sunlit < 0.5)
    assert np.mean(agree) > 0.985, np.mean(agree)
    assert (~lit).sum() > 20  # the scene does have shadows to get right


def test_car_in_front_of_a_long_wall_is_drawn_in_front():
    # A depth sort by nearest point would put the wall (6 m away at its closest) in front of
    # the car 15 m ahead; the footprint order must not.
    wall = SceneObject("wall", [box_solid((6.0, 10.0), 0.0, 0.5, 60.0, 0.0, 3.0, GREY)])
    car = make_car(np.random.default_rng(0), np.array([3.5, 15.0]), 0.0)
    r, out, _ = render([wall, car], 200.0, 40.0, CameraPose((0.0, 0.0, 1.65), 0.0))
    (uv,), _ = project_points([[3.5, 15.0 - 2.0, 0.7]], CameraPose((0.0, 0.0, 1.65), 0.0), SMALL)
    face = int(out.ids[pixel(uv)]) - 2
    car_faces = np.concatenate([r._solid_faces[1], r._solid_faces[2], r._solid_faces[3]])
    assert face in car_faces


def test_faces_past_32767_are_drawn_and_shaded_as_the_same_faces_alone():
    # cv2.remap, which fetches each pixel's face attributes, takes tables of under 32767 rows
    # (SHRT_MAX) and the long drives hold more faces than that. A tree of 33 280 faces far behind
    # the camera puts the building's faces past that row: they must shade exactly as alone.
    far = SceneObject("tree", [ellipsoid_solid((0.0, -500.0, 5.0), (4.0, 5.0), GREY, n_lon=256, n_lat=130)])
    brick = Material((0.5, 0.25, 0.15), contrast=0.2, windows=WindowPattern(ground_floor_m=1.0))
    building = SceneObject("building", [box_solid((4.0, 14.0), 0.4, 8.0, 10.0, 0.0, 9.0, brick)])
    pose = CameraPose((0.0, 0.0, 1.65), 0.1)
    _, alone, _ = render([building], 150.0, 35.0, pose)
    radiance, ids = alone.radiance.copy(), alone.ids.copy()
    r, many, _ = render([far, building], 150.0, 35.0, pose)
    n_far = len(far.parts[0].faces)
    assert len(r.F) + 2 > 32767
    assert (ids >= 2).mean() > 0.2  # the building fills much of the picture
    np.testing.assert_array_equal(many.ids, np.where(ids >= 2, ids + n_far, ids))
    np.testing.assert_array_equal(many.radiance, radiance)


# ---------------------------------------------------------------------------------------------
# Drives


def test_same_seed_same_images_other_seed_other_images():
    a = [f.image_bgr for f in synth_drive(11, 3, intrinsics=SMALL)]
    b = [f.image_bgr for f in synth_drive(11, 3, intrinsics=SMALL)]
    c = [f.image_bgr for f in synth_drive(12, 3, intrinsics=SMALL)]
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    assert not np.array_equal(a[0], c[0])


def test_frame_fields():
    frames = list(synth_drive(5, 4, intrinsics=SMALL, fps=20.0))
    assert [f.seq for f in frames] == [0, 1, 2, 3]
    assert [f.t_mono_s for f in frames] == pytest.approx([0.0, 0.05, 0.1, 0.15])
    assert np.all(np.diff([f.utc_ns for f in frames]) == 50_000_000)
    truth = frames[0].sun_enu_truth
    assert np.linalg.norm(truth) == pytest.approx(1.0, abs=1e-9)
    for f in frames:
        assert f.image_bgr.shape == (94, 310, 3) and f.image_bgr.dtype == np.uint8
        assert f.intrinsics == SMALL
        assert f.gnss is None
        assert f.attitude.reference is HeadingRef.TRUE
        assert abs(f.attitude.pitch_rad) < math.radians(5) and abs(f.attitude.roll_rad) < math.radians(4)
        np.testing.assert_array_equal(f.sun_enu_truth, truth)  # one sun per drive
        assert 10 < f.image_bgr.mean() < 245 and f.image_bgr.std() > 5  # a picture, not a blank


def test_truth_is_the_rendering_light_and_elevation_in_range():
    lo, hi = SUN_ELEVATION_RANGE_DEG
    for seed in range(20):
        p = plan_drive(seed, 2).params
        _, el = az_el_from_enu(p.sun_enu)
        assert lo <= math.degrees(float(el)) <= hi
    d = Drive(3, 1, intrinsics=SMALL, sun_azimuth_rad=1.0, sun_elevation_rad=0.5)
    (frame,) = list(d.frames())
    want = enu_from_az_el(1.0, 0.5)
    np.testing.assert_allclose(frame.sun_enu_truth, want, atol=1e-12)
    np.testing.assert_allclose(d.renderer.sun, want, atol=1e-12)  # the light the shading used
    np.testing.assert_allclose(d.sky.sun_enu, want, atol=1e-12)  # and the sky's sun


def test_heading_is_the_camera_yaw_used_to_render():
    d = Drive(8, 2, intrinsics=SMALL)
    for f, pose in zip(d.frames(), d.poses, strict=True):
        assert f.attitude.heading_rad == pytest.approx(pose.heading_rad % (2 * math.pi), abs=1e-12)
        assert f.attitude.pitch_rad == pose.pitch_rad and f.attitude.roll_rad == pose.roll_rad


def test_yaw_varies_along_drives():
    spans = []
    for seed in range(12):
        h = np.unwrap([p.heading_rad for p in plan_drive(seed, 40).poses])
        spans.append(math.degrees(h.max() - h.min()))
    assert sum(s >= 20.0 for s in spans) >= 9, spans
    assert max(spans) >= 90.0, spans


def test_drive_seeds_are_independent_and_stable():
    assert drive_seed(0, 0) == drive_seed(0, 0)
    assert len({drive_seed(0, i) for i in range(50)} | {drive_seed(1, i) for i in range(50)}) == 100


# ---------------------------------------------------------------------------------------------
# The camera's effects (replay/synthetic/camera.py), on flat radiance fields


def _srgb8(linear: float) -> int:
    """The tone curve the camera module documents: 1 - exp(-1.1 x), then the sRGB encoding."""
    y = 1.0 - math.exp(-1.1 * linear)
    return round(255.0 * (12.92 * y if y <= 0.0031308 else 1.055 * y ** (1 / 2.4) - 0.055))


def _flat(value: float, h: int = 64, w: int = 64) -> np.ndarray:
    return np.full((h, w, 3), value, np.float32)


def test_fixed_exposure_and_the_tone_curve():
    # Radiance 2 kcd/m^2 times a fixed exposure 0.09 is mid-grey 0.18 (the LUT quantises sqrt(x) to
    # 1/2048: +-1 level). White balance scales each channel before the curve.
    cam = Camera(CameraEffects(auto_exposure=False, fixed_exposure=0.09, white_balance_bgr=(1.0, 1.0, 0.5)), 64, 64)
    img = cam.capture(_flat(2.0))
    assert abs(int(img[0, 0, 0]) - _srgb8(0.18)) <= 1 and abs(int(img[0, 0, 2]) - _srgb8(0.09)) <= 1
    assert int(img[0, 0, 0]) > int(img[0, 0, 2])


def test_auto_exposure_meters_to_the_key_with_bias_lag_and_clipped_highlights():
    # exposure = key / meter * 2^bias, meter = mean of the luminance clipped at 4 x its median,
    # log exposure smoothed: s * previous + (1 - s) * target (camera.py, exposure_for).
    cam = Camera(CameraEffects(ae_key=0.18, ae_smoothing=0.4), 64, 64)
    assert cam.exposure_for(_flat(2.0)) == pytest.approx(0.09, rel=1e-5)
    want = math.exp(0.4 * math.log(0.09) + 0.6 * math.log(0.18 / 8.0))
    assert cam.exposure_for(_flat(8.0)) == pytest.approx(want, rel=1e-5)
    biased = Camera(CameraEffects(ae_key=0.18, exposure_bias_stops=1.0), 64, 64)
    assert biased.exposure_for(_flat(2.0)) == pytest.approx(0.18, rel=1e-5)  # +1 stop: twice the light
    # A sun-bright 8x8 patch (one cell of the 1/8 meter) counts as 4 x the median, not its 1000.
    sun = _flat(1.0)
    sun[:8, :8] = 1000.0
    fresh = Camera(CameraEffects(ae_key=0.18), 64, 64)
    assert fresh.exposure_for(sun) == pytest.approx(0.18 / ((63 * 1.0 + 4.0) / 64), rel=1e-5)


def test_vignetting_darkens_the_corners_and_blur_softens_edges():
    effects = CameraEffects(auto_exposure=False, fixed_exposure=0.09, vignette=0.3)
    img = Camera(effects, 64, 48).capture(_flat(2.0, 48, 64)).astype(int)
    assert img[0, 0, 1] < img[24, 32, 1] - 10  # 30 % less light at the corner
    step = _flat(0.0, 48, 64)
    step[:, 32:] = 2.0
    sharp = Camera(CameraEffects.ideal(0.09), 64, 48).capture(step)
    blurred = Camera(CameraEffects(auto_exposure=False, fixed_exposure=0.09, blur_sigma_px=1.5), 64, 48).capture(step)
    assert len(np.unique(sharp[..., 1])) == 2 and len(np.unique(blurred[..., 1])) > 4


# sha256 over every frame's image (uint8 BGR, in order) of drives as they rendered before the
# face tables became grids (e1fe4b1, one column of under 32767 rows): the first two drives of the
# shipped model's training set (`sunrig synth data/train --drives 1800 --frames 24 --seed 1000`,
# render scale 0.5 at KITTI size) and two small ones at full scale. A change here changes the
# training data: make it on purpose, and say so.
RENDERED_BEFORE = [
    (drive_seed(1000, 0), 24, None, 0.5, "9f04def0214d76526281afade1bde0f62916ea218038b4f3a2c4b5b62e24dc48"),
    (drive_seed(1000, 1), 24, None, 0.5, "2472a641e2b64da50fdea172da4a7d315e07f9bde615851f6e4edd8d48086470"),
    (3, 6, SMALL, 1.0, "7abd7d804c0857490bc017f5e07797b95b00a84a41dfd12400e4fb6eb6021f28"),
    (7, 6, SMALL, 1.0, "78e07a31675ba0ce96a74840aae3dc989e3da8d7174948b2e7d0316ac233f957"),
]


@pytest.mark.parametrize(("seed", "frames", "intrinsics", "render_scale", "sha256"), RENDERED_BEFORE)
def test_drives_render_the_images_they_always_did(seed, frames, intrinsics, render_scale, sha256):
    import hashlib

    d = Drive(seed, frames, intrinsics=intrinsics, render_scale=render_scale)
    camera = Camera(d.params.effects, d.intrinsics.width, d.intrinsics.height, seed=seed)
    h = hashlib.sha256()
    for k in range(frames):
        h.update(d.render_frame(k, camera).tobytes())
    assert h.hexdigest() == sha256


def test_a_long_drive_renders():
    # Drive 2 of seed 0 at 2000 frames: 1975 objects, 36 612 faces along 6 km of road, which the
    # renderer refused ("a scene may hold at most 32765 faces").
    d = Drive(drive_seed(0, 2), 2000, intrinsics=SMALL, render_scale=1.0, effects=CameraEffects.ideal(0.02))
    assert len(d.renderer.F) > 32767
    camera = Camera(d.params.effects, SMALL.width, SMALL.height, seed=0)
    drawn = set()
    for k in (0, 999, 1999):
        out = d.renderer.render(d.poses[k])
        drawn |= set(np.unique(out.ids).astype(int).tolist())
        img = d.render_frame(k, camera)
        assert img.shape == (SMALL.height, SMALL.width, 3) and img.std() > 5.0
    assert max(drawn) - 2 > 32767  # the end of the drive draws faces past the old limit


def test_noise_needs_an_rng():
    cam = Camera(CameraEffects(noise_sqrt=0.01), 32, 24)
    with pytest.raises(ValueError, match="noise needs an rng"):
        cam.capture(_flat(1.0, 24, 32))
    assert cam.capture(_flat(1.0, 24, 32), np.random.default_rng(0)).shape == (24, 32, 3)


def test_ideal_effects_are_deterministic_without_noise():
    d = Drive(4, 1, intrinsics=SMALL, effects=CameraEffects.ideal(0.02))
    img = next(iter(d))
    assert img.image_bgr.dtype == np.uint8


def test_a_small_drive_written_to_a_log_reads_back(tmp_path):
    native = pytest.importorskip("replay.native")
    from replay.synthetic import write_synthetic_logs

    paths = write_synthetic_logs(tmp_path, drives=2, frames=3, seed=9, intrinsics=SMALL, progress=False)
    assert [p.name for p in paths] == ["drive_9_0000.mcap", "drive_9_0001.mcap"]
    frames = list(native.read_frames(paths[1]))
    want = list(synth_drive(drive_seed(9, 1), 3, intrinsics=SMALL))
    assert len(frames) == 3
    for got, ref in zip(frames, want, strict=True):
        assert got.seq == ref.seq and got.t_mono_s == pytest.approx(ref.t_mono_s)
        np.testing.assert_allclose(got.sun_enu_truth, ref.sun_enu_truth, atol=1e-9)
        assert got.attitude.heading_rad == pytest.approx(ref.attitude.heading_rad, abs=1e-6)
        assert got.image_bgr.shape == ref.image_bgr.shape
        # JPEG: close, not equal.
        assert np.abs(got.image_bgr.astype(int) - ref.image_bgr.astype(int)).mean() < 6


def test_a_resumed_set_keeps_its_drives_and_refuses_drives_of_another_length(tmp_path):
    # An interrupted `sunrig synth` resumes: kept drives are not rendered again. But a set asked
    # for with more frames must not silently be the shorter drives already in the folder.
    from replay.native import frame_count
    from replay.synthetic import write_synthetic_logs
    from rig.errors import ValidationError

    first = write_synthetic_logs(tmp_path, drives=1, frames=2, seed=9, intrinsics=SMALL, progress=False)
    os.utime(first[0], ns=(1, 1))  # a time no rewrite would leave
    more = write_synthetic_logs(tmp_path, drives=2, frames=2, seed=9, intrinsics=SMALL, progress=False)
    assert more[0].stat().st_mtime_ns == 1 and [frame_count(p) for p in more] == [2, 2]
    with pytest.raises(ValidationError, match="drive_9_0000.mcap is kept .* holds 2 frames, not the 3 asked for"):
        write_synthetic_logs(tmp_path, drives=2, frames=3, seed=9, intrinsics=SMALL, progress=False)
    # Nor, asked for at another rate, drives 0.1 s apart (it once mixed 10 fps and 1 fps drives).
    with pytest.raises(ValidationError, match=r"drive_9_0000.mcap is kept .* 0.1 s apart, not the 1 s of --fps 1"):
        write_synthetic_logs(tmp_path, drives=2, frames=2, seed=9, intrinsics=SMALL, progress=False, fps=1.0)
    whole = more[1].read_bytes()
    (tmp_path / "drive_9_0001.mcap").write_bytes(first[0].read_bytes()[:-100])  # a summary cut off
    assert frame_count(tmp_path / "drive_9_0001.mcap") is None
    with pytest.raises(ValidationError, match="drive_9_0001.mcap .* not a whole log .*: delete it, and"):
        write_synthetic_logs(tmp_path, drives=2, frames=2, seed=9, intrinsics=SMALL, progress=False)
    (tmp_path / "drive_9_0001.mcap").unlink()  # as the error says: the drive is made again
    again = write_synthetic_logs(tmp_path, drives=2, frames=2, seed=9, intrinsics=SMALL, progress=False)
    assert again[1].read_bytes() == whole  # the same drive: a seed always makes the same bytes


def test_synth_says_how_many_drives_it_kept_from_an_earlier_run_before_it_renders(tmp_path, capsys):
    # A resumed `sunrig synth` said "3 logs of 2 frames" whether it rendered three or kept them all:
    # a user who meant a fresh set (another seed's folder, a forgotten earlier run) could not tell.
    from rig.cli import main

    out = tmp_path / "s"
    args = ["synth", str(out), "--frames", "2", "--render-scale", "0.1", "--seed", "9"]
    assert main([*args, "--drives", "2"]) == 0
    first = capsys.readouterr().err
    assert "kept" not in first and f"synth: 2 logs of 2 frames in {out}" in first, first
    assert main([*args, "--drives", "3"]) == 0
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines[0] == f"synth: 2 of the 3 drives are in {out} from an earlier run: kept, rendering 1", lines
    assert lines[-1] == f"synth: 3 logs of 2 frames in {out} (2 kept from an earlier run)", lines
    assert main([*args, "--drives", "3", "--quiet"]) == 0
    assert capsys.readouterr().err == ""


def test_a_resumed_set_refuses_drives_of_another_render_scale_and_keeps_drives_that_never_recorded_one(tmp_path):
    # It once kept drives rendered at 0.5 in a set asked for at 1.0: a folder of mixed render scales.
    from replay.native import LogWriter, log_figures
    from replay.synthetic import write_synthetic_logs
    from rig.errors import ValidationError

    first = write_synthetic_logs(tmp_path, drives=1, frames=2, seed=9, intrinsics=SMALL, progress=False)
    assert log_figures(first[0]).metadata["render_scale"] == "0.5"
    with pytest.raises(ValidationError, match=r"drive_9_0000.mcap is kept .* rendered at --render-scale 0.5, "
                                              r"not the 1 asked for: pass another folder, or delete"):
        write_synthetic_logs(tmp_path, drives=2, frames=2, seed=9, intrinsics=SMALL, progress=False,
                             render_scale=1.0)
    assert not (tmp_path / "drive_9_0001.mcap").exists()  # refused before anything was rendered
    # A drive written before the scale was recorded cannot say it: kept, so older folders resume.
    with LogWriter(first[0]) as writer:
        for frame in synth_drive(drive_seed(9, 0), 2, intrinsics=SMALL):
            writer.write_frame(frame)
    os.utime(first[0], ns=(1, 1))  # a time no rewrite would leave
    more = write_synthetic_logs(tmp_path, drives=2, frames=2, seed=9, intrinsics=SMALL, progress=False,
                                render_scale=1.0)
    assert more[0].stat().st_mtime_ns == 1 and "render_scale" not in log_figures(more[0]).metadata
    assert log_figures(more[1]).metadata["render_scale"] == "1.0"


def test_an_output_that_is_a_file_is_refused_in_one_line(tmp_path):
    # `sunrig synth drive.mcap`: mkdir's FileExistsError was an internal error.
    from replay.synthetic import write_synthetic_logs
    from rig.errors import ValidationError

    afile = tmp_path / "drive.mcap"
    afile.write_bytes(b"kept")
    with pytest.raises(ValidationError, match=r"drive.mcap is a file; OUT is the folder the drives are written to"):
        write_synthetic_logs(afile, drives=1, frames=2, seed=9, intrinsics=SMALL, progress=False)
    with pytest.raises(ValidationError, match=r"cannot make the folder .*drive.mcap/sub: Not a directory"):
        write_synthetic_logs(afile / "sub", drives=1, frames=2, seed=9, intrinsics=SMALL, progress=False)
    assert afile.read_bytes() == b"kept"


def test_more_frames_than_synth_takes_are_refused_in_one_line_before_the_folder_is_made(tmp_path):
    # --frames took any int up to 2**31 - 1: 10**8 laid out its road for minutes, growing, and
    # 10 000 could take 8 GB (the layout's memory grows with the square of the route).
    import subprocess

    from replay.synthetic import MAX_FRAMES, write_synthetic_logs
    from rig.errors import ValidationError

    res = subprocess.run(_synth(tmp_path / "s", "--frames", str(MAX_FRAMES + 1)), capture_output=True, text=True,
                         timeout=60)
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    (last,) = res.stderr.strip().splitlines()
    assert "argument --frames" in last and f"from 1 to {MAX_FRAMES}" in last, last
    with pytest.raises(ValidationError, match=f"frames from 1 to {MAX_FRAMES}"):
        write_synthetic_logs(tmp_path / "t", drives=1, frames=MAX_FRAMES + 1, seed=0, progress=False)
    assert not (tmp_path / "s").exists() and not (tmp_path / "t").exists()
    # The help, written before replay.synthetic is imported, says the same number.
    from rig.cli import build_parser

    synth = build_parser()._subparsers._group_actions[0].choices["synth"]  # type: ignore[union-attr]
    (frames,) = (a for a in synth._actions if "--frames" in a.option_strings)
    assert f"at most {MAX_FRAMES}" in frames.help
    # So do --drives and --fps (their help is written out too, for the same reason).
    from replay.synthetic import MAX_DRIVES, MAX_FPS

    (drives,) = (a for a in synth._actions if "--drives" in a.option_strings)
    (fps,) = (a for a in synth._actions if "--fps" in a.option_strings)
    assert f"at most {MAX_DRIVES})" in drives.help and f"at most {MAX_FPS:g})" in fps.help
    with pytest.raises(ValidationError, match=f"drives from 0 to {MAX_DRIVES} .* got {MAX_DRIVES + 1}, 2, 1, 10$"):
        write_synthetic_logs(tmp_path / "u", drives=MAX_DRIVES + 1, frames=2, seed=0, progress=False)
    with pytest.raises(ValidationError, match=f"fps above 0 to {MAX_FPS:g}, got 1, 2, 1, 1e\\+12$"):
        write_synthetic_logs(tmp_path / "u", drives=1, frames=2, seed=0, progress=False, fps=1e12)
    assert not (tmp_path / "u").exists()


def test_the_longest_drive_synth_takes_renders():
    from replay.synthetic import MAX_FRAMES

    d = Drive(drive_seed(0, 0), MAX_FRAMES, intrinsics=SMALL, render_scale=1.0, effects=CameraEffects.ideal(0.02))
    img = d.render_frame(MAX_FRAMES - 1, Camera(d.params.effects, SMALL.width, SMALL.height, seed=0))
    assert img.std() > 5.0


def test_drives_rendered_in_parallel_are_the_drives_rendered_one_by_one(tmp_path):
    # `--jobs 2` is how docs/model.md makes the training set: the same bytes, whatever renders them.
    from replay.synthetic import write_synthetic_logs

    serial = write_synthetic_logs(tmp_path / "one", drives=3, frames=2, seed=4, intrinsics=SMALL, progress=False)
    parallel = write_synthetic_logs(tmp_path / "two", drives=3, frames=2, seed=4, intrinsics=SMALL, progress=False,
                                    jobs=2)
    assert [p.name for p in parallel] == [p.name for p in serial]
    assert [p.read_bytes() for p in parallel] == [p.read_bytes() for p in serial]
    assert not list((tmp_path / "two").glob("*.part"))


def test_a_finished_parallel_run_lets_its_workers_exit_without_a_signal(tmp_path, monkeypatch):
    # The pool's exit terminated (SIGTERM) workers already leaving on its sentinel: one caught in
    # its atexit handlers raised _exit_on_signal's SystemExit there, and a run that made every
    # drive printed "Exception ignored in atexit callback" and a traceback (2 runs in 8).
    import multiprocessing.process

    from replay.synthetic import write_synthetic_logs

    real, stopped = multiprocessing.process.BaseProcess.terminate, []

    def terminate(self):
        stopped.append(self.pid)
        real(self)

    monkeypatch.setattr(multiprocessing.process.BaseProcess, "terminate", terminate)
    paths = write_synthetic_logs(tmp_path, drives=3, frames=1, seed=4, intrinsics=SMALL, progress=False, jobs=2)
    assert all(p.exists() for p in paths) and stopped == []


@pytest.mark.parametrize("jobs", [1, 2])
def test_progress_counts_the_frames_of_a_drive_being_rendered(tmp_path, monkeypatch, jobs):
    # The counter moved only when a whole drive was written: `--drives 1 --frames 5000` showed
    # "0/5000 frames (0.0/s)" for the two minutes of its drive, and off a terminal, the line due
    # every minute waited for the drive's end.
    import replay.synthetic as synthetic
    from rig.progress import Progress

    seen: list[int] = []
    real = Progress.update

    def update(self, done, extra=""):
        seen.append(done)
        real(self, done, extra)

    monkeypatch.setattr(Progress, "update", update)
    monkeypatch.setattr(synthetic, "PROGRESS_POLL_S", 0.001)  # the parent looks at its workers' count
    synthetic.write_synthetic_logs(tmp_path, drives=2, frames=12, seed=4, intrinsics=SMALL, progress=False, jobs=jobs)
    assert seen[-1] == 24 and seen == sorted(seen)
    assert [n for n in seen if n % 12], seen  # counts within a drive, not only whole drives


def test_a_worker_stopped_mid_drive_exits_even_when_its_log_fails_to_close(tmp_path, monkeypatch):
    # On a full disk, `--jobs 2` hung for good: the pool's SIGTERM reached a worker rendering, and
    # the log's close (ENOSPC) replaced its SystemExit with an OSError, which the pool took as the
    # drive's result; the worker went back for work with SIGTERM now ignored, and the run waited
    # in the pool's join forever, holding OUT.
    import errno
    import multiprocessing
    import signal

    import replay.synthetic as synthetic
    from replay.native import LogWriter

    def stopped(self, frame):
        synthetic._exit_on_signal(signal.SIGTERM, None)  # as if the pool's SIGTERM came now

    def disk_full(self):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(signal, "signal", lambda *args: None)  # this process's SIGTERM is left alone
    monkeypatch.setattr(synthetic, "_frames_written", multiprocessing.Value("q", 0))
    monkeypatch.setattr(synthetic, "_stop_signal", 0)
    monkeypatch.setattr(LogWriter, "write_frame", stopped)
    monkeypatch.setattr(LogWriter, "close", disk_full)
    path = tmp_path / "drive_9_0000.mcap"
    with pytest.raises(SystemExit) as stop:
        synthetic._write_in_worker((path, drive_seed(9, 0), 2, SMALL, 0.5, 10.0))
    assert stop.value.code == 128 + signal.SIGTERM
    assert list(tmp_path.iterdir()) == []


def test_a_finished_drive_is_on_the_disk_before_it_takes_its_name(tmp_path, disk_events):
    # A drive was renamed from its .part with its data still in memory: after a power loss the
    # folder could hold the drive's name on an empty or cut file, which a resume refuses until it
    # is deleted by hand, rather than a drive either whole or absent (rendered again).
    from replay.synthetic import write_synthetic_logs

    (path,) = write_synthetic_logs(tmp_path, drives=1, frames=2, seed=9, intrinsics=SMALL, progress=False)
    assert disk_events.synced_in_order(path), disk_events


def test_a_drive_that_fills_the_disk_leaves_no_part_file(tmp_path, monkeypatch):
    # The .part of a drive that failed stayed, holding the space the user was told to free; the
    # folder keeps only whole drives (here the one finished before).
    import errno

    from replay.native import LogWriter
    from replay.synthetic import write_synthetic_logs

    real, written = LogWriter.write_frame, []

    def fills_the_disk(self, frame):
        if len(written) == 3:  # drive 0 whole, then a frame of drive 1
            raise OSError(errno.ENOSPC, "No space left on device")
        written.append(frame.seq)
        return real(self, frame)

    monkeypatch.setattr(LogWriter, "write_frame", fills_the_disk)
    with pytest.raises(OSError, match="No space left"):
        write_synthetic_logs(tmp_path, drives=2, frames=2, seed=9, intrinsics=SMALL, progress=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["drive_9_0000.mcap"]


def test_a_full_disk_names_the_drive_it_could_not_write(tmp_path, monkeypatch):
    # The log writer's ENOSPC named no file, and the CLI said "No space left on device; free
    # space on that disk" without saying which disk: OUT may be on another disk than the shell.
    import errno

    from replay.native import LogWriter
    from replay.synthetic import write_synthetic_logs
    from rig.cli import _machine_error

    def fills_the_disk(self, frame):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(LogWriter, "write_frame", fills_the_disk)
    with pytest.raises(OSError) as full:
        write_synthetic_logs(tmp_path, drives=1, frames=2, seed=9, intrinsics=SMALL, progress=False)
    assert full.value.errno == errno.ENOSPC
    assert _machine_error(full.value) == (f"{tmp_path / 'drive_9_0000.mcap'}: No space left on device; free space on "
                                          "that disk, or write elsewhere")


def _synth(out, *args):
    import sys

    return [sys.executable, "-m", "rig.cli", "synth", str(out), "--render-scale", "0.1", "--quiet", *args]


def _wait_for(what, timeout_s=20.0):
    import time

    end = time.monotonic() + timeout_s
    while not what():
        assert time.monotonic() < end, "waited too long"
        time.sleep(0.02)


def test_a_second_synth_on_a_folder_being_written_is_refused_in_one_line(tmp_path):
    # Nothing kept two processes off one OUT: the second rendered the first's drive into the same
    # .part (truncating it under the first's writes), so a kill of the second left the first a
    # drive named whole that starts with zeros, and its Ctrl-C deleted the first's .part.
    import signal
    import subprocess
    from pathlib import Path

    out = tmp_path / "synth"
    root = Path(__file__).resolve().parents[1]
    cmd = _synth(out, "--drives", "1", "--frames", "5000")
    first = subprocess.Popen(cmd, stderr=subprocess.PIPE, cwd=root)
    try:
        _wait_for(lambda: (out / "drive_0_0000.mcap.part").exists())
        try:
            second = subprocess.run(cmd, capture_output=True, text=True, timeout=10, cwd=root)
        except subprocess.TimeoutExpired:
            pytest.fail("the second synth rendered the first's drive beside it instead of being refused")
        assert second.returncode == 2 and second.stderr.count("\n") == 1, second.stderr
        assert second.stderr.startswith(f"sunrig: error: OUT {out} is in use by another sunrig synth "
                                        f"(pid {first.pid}); "), second.stderr
        first.send_signal(signal.SIGTERM)  # stopped, the first leaves neither its .part nor its lock
        assert first.wait(10) == 128 + signal.SIGTERM, first.stderr.read() if first.stderr else ""
        assert list(out.iterdir()) == []
    finally:
        first.kill()
        first.wait()


def _children(pid):
    """The pids of ``pid``'s living children (Linux /proc)."""
    kids = []
    for entry in os.listdir("/proc"):
        try:
            with open(f"/proc/{entry}/stat") as f:
                state, ppid = f.read().rsplit(")", 1)[1].split()[:2]
        except (OSError, ValueError):
            continue
        if int(ppid) == pid and state != "Z":
            kids.append(int(entry))
    return kids


def _alive(pid):
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


@pytest.mark.parametrize(("signame", "group"), [("SIGKILL", False), ("SIGTERM", False), ("SIGINT", False),
                                                ("SIGINT", True)])
def test_synth_with_jobs_stopped_or_killed_leaves_no_worker_rendering_and_no_part_file(tmp_path, signame, group):
    # Killed with -9, the parent left its workers rendering the drives in hand to their end (the
    # CPU taken, a rerun rendering the same drives into the same .part files), each then dying on
    # a traceback; stopped (SIGTERM, Ctrl-C), the pool killed its workers with their .part files.
    import signal
    import subprocess
    from pathlib import Path

    if not os.path.isdir("/proc/self"):
        pytest.skip("finds the workers in /proc (Linux)")
    sig = getattr(signal, signame)
    out = tmp_path / "synth"
    parent = subprocess.Popen(_synth(out, "--drives", "4", "--frames", "1000", "--jobs", "2"), stderr=subprocess.PIPE,
                              cwd=Path(__file__).resolve().parents[1], start_new_session=True)
    workers = []
    try:
        _wait_for(lambda: len(list(out.glob("*.part"))) == 2)  # both workers are rendering
        workers = _children(parent.pid)
        if group:
            os.killpg(parent.pid, sig)  # Ctrl-C in a terminal
        else:
            parent.send_signal(sig)
        assert parent.wait(10) == (-sig if sig == signal.SIGKILL else 128 + sig)
        _wait_for(lambda: not any(map(_alive, workers)), timeout_s=5.0)
        assert list(out.glob("*.part")) == []
        said = parent.stderr.read().decode() if parent.stderr else ""
        assert "Traceback" not in said, said
    finally:
        workers += _children(parent.pid)  # those of a test that failed before it looked
        parent.kill()
        parent.wait()
        for pid in workers:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


def test_synth_with_jobs_whose_worker_is_killed_stops_in_one_line_and_leaves_no_part_file(tmp_path):
    # A worker killed alone (the out-of-memory killer: a long drive takes gigabytes) was replaced
    # by the pool, but its drive was never handed out again: the run waited for it forever,
    # holding OUT, with the dead worker's .part beside it.
    import signal
    import subprocess
    from pathlib import Path

    if not os.path.isdir("/proc/self"):
        pytest.skip("finds the workers in /proc (Linux)")
    out = tmp_path / "synth"
    parent = subprocess.Popen(_synth(out, "--drives", "4", "--frames", "1000", "--jobs", "2"), stderr=subprocess.PIPE,
                              text=True, cwd=Path(__file__).resolve().parents[1], start_new_session=True)
    workers = []
    try:
        _wait_for(lambda: len(list(out.glob("*.part"))) == 2)  # both workers are rendering
        workers = _children(parent.pid)
        worker = next(pid for pid in workers if "spawn_main" in Path(f"/proc/{pid}/cmdline").read_text())
        os.kill(worker, signal.SIGKILL)
        try:
            code = parent.wait(20)
        except subprocess.TimeoutExpired:
            pytest.fail("the run waited for the killed worker's drive")
        said = parent.stderr.read() if parent.stderr else ""
        assert code == 2 and said.count("\n") == 1 and "worker" in said and "run the command again" in said, said
        assert [p.name for p in out.iterdir() if p.suffix != ".mcap"] == []  # no .part, no lock
    finally:
        workers += _children(parent.pid)
        parent.kill()
        parent.wait()
        for pid in workers:
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)



@pytest.mark.parametrize("scale", [0.0, -0.5, math.nan, math.inf])
def test_kitti_intrinsics_refuses_a_scale_that_makes_no_image(scale):
    # 0 or a negative scale gave a 1 x 1 px camera without a word: the benchmarks measured drift and
    # rendering speed on it and printed them as the rig's.
    from rig.errors import ValidationError

    with pytest.raises(ValidationError, match="kitti_intrinsics: expected a scale > 0"):
        kitti_intrinsics(scale)
