"""A fast deferred rasteriser for the synthetic street: OpenCV polygon fills plus per-pixel shading.

Per frame:

1. Visibility order. Objects are vertical stacks of convex solids with disjoint convex footprints,
   so along any viewing ray's horizontal projection the footprint hit first is in front. The order
   is read off rays fanned across the field of view (each ray sorts the footprints it crosses;
   consecutive pairs become "draw before" edges) and a topological sort; within an object the
   parts follow from the camera height (see :func:`_part_order`); within a convex part the front
   faces do not overlap. This is exact for such scenes, where a depth sort is not (a long wall
   beside the camera sorts nearer than the car parked in front of it).
2. Face ids are painted with ``cv2.fillConvexPoly`` (near-plane clipped) into an id buffer whose
   background is the ground plane below the horizon and the sky above it.
3. Per pixel, the id fetches the face's plane and attributes in one ``cv2.remap`` (nearest) per
   table; the ray-plane intersection gives the world point P; shading is Lambertian, direct sun
   times visibility plus sky/ground ambient; visibility comes from an exit-height map (below).

Shadows: for a ground point G the ray toward the sun leaves the last solid it crosses at some
height; the map ``H(G)`` stores that height (max over solids; convex solids make it the min over
their sun-facing planes). A point P is in shadow iff H at G = P - (P_z / s_z) s exceeds P_z: some
solid lies between P and the sun. This shadows the ground, walls, cars and tree crowns alike,
including objects onto each other. It is computed once per scene and sun.

Conventions: world ENU; camera OpenCV (x right, y down, z forward); pixel (u, v) is continuous
with the image's left/top edge at 0, so pixel index i is centred at i + 0.5. Attitude: heading
clockwise from north, pitch positive nose up, roll positive right side down, applied
yaw, then pitch about the camera's right axis, then roll about its optical axis. The optical
axis' horizontal projection is therefore along the heading exactly.
"""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass, field

import cv2
import numpy as np

from rig.geometry import world_from_heading
from rig.types import Intrinsics
from replay.synthetic.scene import ALBEDO_SCALE, Scene, Solid
from replay.synthetic.sky import SUN_ANGULAR_RADIUS_RAD, PreethamSky

SKY_ID, GROUND_ID, FIRST_FACE_ID = 0, 1, 2
_FAR = 1.0e5  # metres: the depth of the sky
_NEAR = 0.3  # metres: the near clipping plane
_SHIFT = 4  # fillConvexPoly sub-pixel bits
_SHADOW_TOL = 0.06  # metres of exit height above P before P counts as shadowed
_SHADOW_SOFT = 0.12  # metres over which the shadow fades in (a penumbra of sorts)
_NOISE_TEXELS_PER_M = 12.0
_GROUND_NOISE_TEXELS_PER_M = 24.0


# ---------------------------------------------------------------------------------------------
# Camera geometry (pure)


def world_from_cam(heading_rad: float, pitch_rad: float = 0.0, roll_rad: float = 0.0) -> np.ndarray:
    """Rotation taking OpenCV camera vectors to ENU: columns are the camera's x, y, z axes."""
    cp, sp = math.cos(pitch_rad), math.sin(pitch_rad)
    cr, sr = math.cos(roll_rad), math.sin(roll_rad)
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cp, -sp], [0.0, sp, cp]])  # nose up about heading-x
    ry = np.array([[cr, 0.0, sr], [0.0, 1.0, 0.0], [-sr, 0.0, cr]])  # right side down about y
    heading_from_cam = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])
    return world_from_heading(heading_rad) @ rx @ ry @ heading_from_cam


@dataclass(frozen=True)
class CameraPose:
    """Camera position (ENU, metres) and attitude (radians; see the module docstring)."""

    position: tuple[float, float, float]
    heading_rad: float
    pitch_rad: float = 0.0
    roll_rad: float = 0.0

    def world_from_cam(self) -> np.ndarray:
        return world_from_cam(self.heading_rad, self.pitch_rad, self.roll_rad)


def project_points(points_enu, pose: CameraPose, intr: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) (continuous, edge at 0) and camera depth z (N,) of ENU points."""
    p = np.atleast_2d(np.asarray(points_enu, dtype=np.float64))
    cam = (p - np.asarray(pose.position)) @ pose.world_from_cam()
    z = cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([intr.fx * cam[:, 0] / z + intr.cx, intr.fy * cam[:, 1] / z + intr.cy], axis=-1)
    return uv, z


def project_direction(d_enu, pose: CameraPose, intr: Intrinsics) -> tuple[np.ndarray, float]:
    """Pixel (2,) where a direction (a point at infinity, e.g. the sun) appears, and its camera z."""
    cam = np.asarray(d_enu, dtype=np.float64) @ pose.world_from_cam()
    z = float(cam[2])
    if z <= 1e-9:
        return np.array([np.nan, np.nan]), z
    return np.array([intr.fx * cam[0] / z + intr.cx, intr.fy * cam[1] / z + intr.cy]), z


def scaled_intrinsics(intr: Intrinsics, scale: float) -> Intrinsics:
    w, h = max(1, int(round(intr.width * scale))), max(1, int(round(intr.height * scale)))
    sx, sy = w / intr.width, h / intr.height
    return Intrinsics(fx=intr.fx * sx, fy=intr.fy * sy, cx=intr.cx * sx, cy=intr.cy * sy, width=w, height=h)


# ---------------------------------------------------------------------------------------------
# Shadows: the exit-height map


def exit_height_map(scene: Scene, sun_enu, origin_xy, res_m: float, shape: tuple[int, int]) -> np.ndarray:
    """For each ground point G of the grid, the height at which the ray from G toward the sun
    leaves the last solid it passes through (0 where it passes none). float32 (rows, cols)."""
    s = np.asarray(sun_enu, dtype=np.float64)
    rows, cols = shape
    hmap = np.zeros((rows, cols), np.float32)
    x0, y0 = origin_xy
    shift_xy = s[:2] / s[2]
    for obj in scene.objects:
        for solid in obj.parts:
            v = solid.vertices
            ground = v[:, :2] - v[:, 2:3] * shift_xy  # where each vertex' shadow falls
            j0 = max(int(math.floor((ground[:, 0].min() - x0) / res_m)) - 1, 0)
            j1 = min(int(math.ceil((ground[:, 0].max() - x0) / res_m)) + 2, cols)
            i0 = max(int(math.floor((ground[:, 1].min() - y0) / res_m)) - 1, 0)
            i1 = min(int(math.ceil((ground[:, 1].max() - y0) / res_m)) + 2, rows)
            if j0 >= j1 or i0 >= i1:
                continue
            n = solid.normals
            ns = n @ s
            ns = np.where(np.abs(ns) < 1e-9, 1e-9, ns)  # grazing planes: never the binding one
            lit = ns > 0
            gx = (x0 + np.arange(j0, j1) * res_m).astype(np.float64)
            for r0 in range(i0, i1, 128):  # bands of rows bound the memory of a long low-sun shadow
                r1 = min(r0 + 128, i1)
                gy = y0 + np.arange(r0, r1) * res_m
                # Height along the ray where it crosses each face plane: (d - n.G) s_z / (n.s).
                num = solid.offsets[:, None, None] - n[:, 0, None, None] * gx[None, None, :] \
                    - n[:, 1, None, None] * gy[None, :, None]
                z = num * (s[2] / ns)[:, None, None]
                z_exit = np.min(np.where(lit[:, None, None], z, np.inf), axis=0)
                z_entry = np.max(np.where(lit[:, None, None], -np.inf, z), axis=0)
                hit = (z_entry <= z_exit) & (z_exit > 0)
                block = hmap[r0:r1, j0:j1]
                np.maximum(block, np.where(hit, z_exit, 0.0).astype(np.float32), out=block)
    return hmap


# ---------------------------------------------------------------------------------------------
# The renderer


def _part_order(z_ranges: list[tuple[float, float]], cam_z: float) -> list[int]:
    """Draw order of the stacked parts of one object, back to front, for a camera at ``cam_z``.

    A part wholly above the camera can only be hidden by parts below it (rays climb to it), and
    one wholly below only by parts above it; the part the camera's height cuts through hides
    both kinds and goes last.
    """
    above = sorted((i for i, (z0, _) in enumerate(z_ranges) if z0 >= cam_z), key=lambda i: -z_ranges[i][0])
    below = sorted((i for i, (_, z1) in enumerate(z_ranges) if z1 <= cam_z), key=lambda i: z_ranges[i][0])
    rest = [i for i in range(len(z_ranges)) if i not in above and i not in below]
    return above + below + rest


def _clip_near(cam_pts: np.ndarray, near: float) -> np.ndarray:
    """Sutherland-Hodgman clip of a polygon (K, 3) in camera coordinates to z >= near."""
    out = []
    k = len(cam_pts)
    for i in range(k):
        a, b = cam_pts[i], cam_pts[(i + 1) % k]
        ina, inb = a[2] >= near, b[2] >= near
        if ina:
            out.append(a)
        if ina != inb:
            t = (near - a[2]) / (b[2] - a[2])
            out.append(a + t * (b - a))
    return np.array(out) if out else np.zeros((0, 3))


@dataclass
class RenderOutput:
    """Linear radiance (H, W, 3) float32 BGR in kcd/m^2 at the render resolution, the face-id
    buffer (0 sky, 1 ground, 2+ faces), the sun's pixel (NaN when behind the camera) and how
    much of its disk is unoccluded (0-1)."""

    radiance: np.ndarray
    ids: np.ndarray
    sun_px: np.ndarray
    sun_visible: float
    depth: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]
    sunlit: np.ndarray = field(repr=False, default=None)  # type: ignore[assignment]


class Renderer:
    """Renders one scene under one sky from any camera pose.

    ``render_scale`` renders at a fraction of the intrinsics' size (the caller upsamples);
    ``shadow_res_m`` is the exit-height map's cell; ``fog_m`` the aerial-perspective distance.
    """

    def __init__(self, scene: Scene, sky: PreethamSky, intrinsics: Intrinsics, *, render_scale: float = 1.0,
                 shadow_res_m: float = 0.15, fog_m: float = 2000.0, sky_step_px: int = 4,
                 max_distance_m: float = 400.0) -> None:
        self.scene, self.sky = scene, sky
        self.out_intrinsics = intrinsics
        self.intr = scaled_intrinsics(intrinsics, render_scale) if render_scale != 1.0 else intrinsics
        self.sun = sky.sun_enu.astype(np.float64)
        self.fog_m = fog_m
        self.max_distance_m = max_distance_m
        self.sky_step = sky_step_px
        self._compile_faces()
        self._compile_objects()
        g = scene.ground
        extent = np.array(g.albedo.shape[1::-1]) * g.res_m
        self.shadow_res = shadow_res_m
        self.shadow_origin = g.origin_xy
        shape = (int(math.ceil(extent[1] / shadow_res_m)), int(math.ceil(extent[0] / shadow_res_m)))
        self.hmap = exit_height_map(scene, self.sun, g.origin_xy, shadow_res_m, shape)
        w, h = self.intr.width, self.intr.height
        u = (np.arange(w, dtype=np.float32) + 0.5 - self.intr.cx) / self.intr.fx
        v = (np.arange(h, dtype=np.float32) + 0.5 - self.intr.cy) / self.intr.fy
        self.xn, self.yn = np.meshgrid(u, v)
        self.zeros = np.zeros((h, w), np.float32)
        hs, ws = -(-h // sky_step_px), -(-w // sky_step_px)
        us = ((np.arange(ws) + 0.5) * sky_step_px - self.intr.cx) / self.intr.fx
        vs = ((np.arange(hs) + 0.5) * sky_step_px - self.intr.cy) / self.intr.fy
        self.xs, self.ys = (a.astype(np.float32) for a in np.meshgrid(us, vs))
        self._noise = scene.noise
        ambient_ground = sky.ambient_irradiance([[0.0, 0.0, 1.0]])[0]
        self._ground_light = (sky.direct_irradiance([[0.0, 0.0, 1.0]])[0], ambient_ground)

    # -- scene compilation

    def _compile_faces(self) -> None:
        solids: list[Solid] = [p for o in self.scene.objects for p in o.parts]
        verts, faces, normals, offsets, mats = [], [], [], [], []
        base = 0
        self._solid_faces: list[np.ndarray] = []
        for sol in solids:
            verts.append(sol.vertices)
            faces.append(sol.faces + base)
            normals.append(sol.normals)
            offsets.append(sol.offsets)
            mats.extend(sol.materials)
            n0 = sum(len(f) for f in faces[:-1])
            self._solid_faces.append(np.arange(n0, n0 + len(sol.faces)))
            base += len(sol.vertices)
        self.V = np.concatenate(verts) if verts else np.zeros((0, 3))
        self.F = np.concatenate(faces) if faces else np.zeros((0, 4), np.int64)
        self.N = np.concatenate(normals) if normals else np.zeros((0, 3))
        self.D = np.concatenate(offsets) if offsets else np.zeros(0)
        nf = len(self.F)
        total = nf + FIRST_FACE_ID
        # Texture frame: e1 horizontal along the face, e2 up the face (or north on flat faces);
        # a, b in metres from the face's lower-left corner.
        e1 = np.zeros((total, 3))
        e2 = np.zeros((total, 3))
        a0 = np.zeros(total)
        b0 = np.zeros(total)
        e1[GROUND_ID] = (1.0, 0.0, 0.0)
        e2[GROUND_ID] = (0.0, 1.0, 0.0)
        win_a = np.zeros((total, 4), np.float32)  # spacing, a_start, a_end, half width fraction
        win_b = np.zeros((total, 4), np.float32)  # spacing, first floor, top, half height fraction
        win_a[:, 0] = win_b[:, 0] = 1.0
        glass = np.zeros((total, 4), np.float32)
        alb = np.zeros((total, 4), np.float32)
        g = self.scene.ground
        alb[GROUND_ID] = (0.0, 0.0, 0.0, 0.35)  # ground albedo comes from the map
        for i in range(nf):
            f = i + FIRST_FACE_ID
            n = self.N[i]
            if abs(n[2]) < 0.99:
                d1 = np.cross([0.0, 0.0, 1.0], n)
                d1 /= np.linalg.norm(d1)
            else:
                d1 = np.array([1.0, 0.0, 0.0])
            d2 = np.cross(n, d1)
            fv = self.V[self.F[i]]
            pa, pb = fv @ d1, fv @ d2
            e1[f], e2[f] = d1, d2
            a0[f], b0[f] = -pa.min(), -pb.min()
            m = mats[i]
            alb[f] = (*m.albedo_rgb[::-1], m.contrast)
            w = m.windows
            if w is not None and abs(n[2]) < 0.2:
                length, height = pa.max() - pa.min(), pb.max() - pb.min()
                su, sw = w.spacing_m
                ncol = int((length - 1.0) // su)
                if ncol >= 1:
                    start = (length - ncol * su) / 2
                    win_a[f] = (su, start, start + ncol * su, w.size_frac[0] / 2)
                    nfloor = int((height - w.ground_floor_m - 0.6) // sw)
                    win_b[f] = (sw, w.ground_floor_m, w.ground_floor_m + max(nfloor, 0) * sw, w.size_frac[1] / 2)
                    glass[f, :3] = w.glass_rgb[::-1]
        self.tab_e1 = np.concatenate([e1, a0[:, None]], axis=1).astype(np.float32).reshape(-1, 1, 4)
        self.tab_e2 = np.concatenate([e2, b0[:, None]], axis=1).astype(np.float32).reshape(-1, 1, 4)
        self.tab_alb = alb.reshape(-1, 1, 4)
        self.tab_wa = win_a.reshape(-1, 1, 4)
        self.tab_wb = win_b.reshape(-1, 1, 4)
        self.tab_glass = glass.reshape(-1, 1, 4)
        normals_all = np.zeros((total, 3))
        normals_all[GROUND_ID] = (0.0, 0.0, 1.0)
        normals_all[SKY_ID] = (0.0, 0.0, 1.0)
        normals_all[FIRST_FACE_ID:] = self.N
        direct = self.sky.direct_irradiance(normals_all)
        ambient = self.sky.ambient_irradiance(normals_all)
        direct[SKY_ID] = ambient[SKY_ID] = 0.0
        self.tab_direct = np.concatenate([direct, (normals_all @ self.sky.sun_enu)[:, None]], axis=1) \
            .astype(np.float32).reshape(-1, 1, 4) / np.float32(math.pi)
        self.tab_ambient = np.concatenate([ambient, np.zeros((total, 1))], axis=1) \
            .astype(np.float32).reshape(-1, 1, 4) / np.float32(math.pi)
        if total >= 32767:
            raise ValueError(f"Renderer: a scene may hold at most 32765 faces, got {nf}")

    def _compile_objects(self) -> None:
        objs = self.scene.objects
        kmax = max([len(o.footprint) for o in objs] + [3])
        n = len(objs)
        self._hp_n = np.zeros((n, kmax, 2))
        self._hp_q = np.ones((n, kmax))  # padding rows: 0 . x <= 1, always true
        self._obj_centre = np.zeros((n, 2))
        self._obj_radius = np.zeros(n)
        self._obj_parts: list[list[np.ndarray]] = []
        self._obj_zr: list[list[tuple[float, float]]] = []
        k = 0
        for i, o in enumerate(objs):
            fp = np.asarray(o.footprint, dtype=np.float64)
            edges = np.roll(fp, -1, axis=0) - fp
            outward = np.stack([edges[:, 1], -edges[:, 0]], axis=-1)  # CCW polygon: right normal
            outward /= np.maximum(np.linalg.norm(outward, axis=1, keepdims=True), 1e-12)
            self._hp_n[i, : len(fp)] = outward
            self._hp_q[i, : len(fp)] = np.einsum("ij,ij->i", outward, fp)
            c = fp.mean(axis=0)
            self._obj_centre[i] = c
            self._obj_radius[i] = np.max(np.linalg.norm(fp - c, axis=1))
            self._obj_parts.append(self._solid_faces[k: k + len(o.parts)])
            self._obj_zr.append([p.z_range for p in o.parts])
            k += len(o.parts)

    # -- per frame

    def visibility_order(self, cam_xy, heading: float) -> list[int]:
        """Indices of the objects in view, farthest (drawn first) to nearest."""
        n = len(self.scene.objects)
        if n == 0:
            return []
        half = 0.5 * self.intr.hfov_rad + math.radians(8.0)  # margin for roll and wide objects
        rel = self._obj_centre - np.asarray(cam_xy)
        dist = np.hypot(rel[:, 0], rel[:, 1])
        ang = np.mod(np.arctan2(rel[:, 0], rel[:, 1]) - heading + math.pi, 2 * math.pi) - math.pi
        halfw = np.where(dist > self._obj_radius, np.arcsin(np.clip(self._obj_radius / np.maximum(dist, 1e-9), 0, 1)),
                         math.pi)
        cand = np.nonzero((np.abs(ang) - halfw < half) & (dist - self._obj_radius < self.max_distance_m))[0]
        if len(cand) == 0:
            return []
        phis = np.concatenate([np.linspace(-half, half, 160), np.clip(ang[cand], -half, half)])
        rays = np.stack([np.sin(heading + phis), np.cos(heading + phis)], axis=-1)  # (R, 2)
        hn, hq = self._hp_n[cand], self._hp_q[cand]
        num = hq - hn @ np.asarray(cam_xy, dtype=np.float64)  # (n, K)
        den = hn @ rays.T  # (n, K, R): inside iff t * den <= num
        den = np.where(np.abs(den) < 1e-12, 1e-12, den)
        t = num[:, :, None] / den
        lower = np.max(np.where(den < 0, t, -np.inf), axis=1)
        upper = np.min(np.where(den > 0, t, np.inf), axis=1)
        entry = np.maximum(lower, 0.0)
        dmat = np.where(entry <= upper, entry, np.inf)  # (n, R)
        order = np.argsort(dmat, axis=0, kind="stable")
        ds = np.take_along_axis(dmat, order, axis=0)
        valid = np.isfinite(ds[1:])
        near, far = order[:-1][valid], order[1:][valid]
        m = len(cand)
        pairs = np.unique(near * m + far)
        near, far = pairs // m, pairs % m
        # Kahn's algorithm, far before near; free nodes go farthest first.
        indeg = np.zeros(m, np.int64)
        np.add.at(indeg, near, 1)
        succ: list[list[int]] = [[] for _ in range(m)]
        for a, b in zip(far.tolist(), near.tolist(), strict=True):
            succ[a].append(b)
        key = np.where(np.isfinite(dmat).any(axis=1), np.min(dmat, axis=1), dist[cand])
        heap = [(-key[i], i) for i in range(m) if indeg[i] == 0]
        heapq.heapify(heap)
        done = np.zeros(m, bool)
        out: list[int] = []
        while len(out) < m:
            if not heap:  # a cycle (only from rays grazing corners): break it at the farthest node
                rest = np.nonzero(~done)[0]
                i = int(rest[np.argmax(key[rest])])
                indeg[i] = 0
                heap.append((-key[i], i))
            _, i = heapq.heappop(heap)
            if done[i]:
                continue
            done[i] = True
            out.append(int(cand[i]))
            for j in succ[i]:
                indeg[j] -= 1
                if indeg[j] == 0 and not done[j]:
                    heapq.heappush(heap, (-key[j], j))
        return out

    def _rasterise(self, pose: CameraPose, r_wc: np.ndarray, rz: np.ndarray) -> np.ndarray:
        intr = self.intr
        ids = np.where(rz < 0.0, np.float32(GROUND_ID), np.float32(SKY_ID)).astype(np.float32)
        if len(self.F) == 0:
            return ids
        c = np.asarray(pose.position, dtype=np.float64)
        vc = (self.V - c) @ r_wc  # camera coordinates of every vertex
        front = self.N @ c - self.D > 1e-6
        fz = vc[self.F, 2]  # (F, 4)
        all_in = np.all(fz >= _NEAR, axis=1)
        any_in = np.any(fz >= _NEAR, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = intr.fx * vc[:, 0] / vc[:, 2] + intr.cx
            v = intr.fy * vc[:, 1] / vc[:, 2] + intr.cy
        fu, fv = u[self.F], v[self.F]
        w, h = intr.width, intr.height
        onscreen = ~all_in | ((fu.max(axis=1) >= 0) & (fu.min(axis=1) <= w) & (fv.max(axis=1) >= 0) & (fv.min(axis=1) <= h))
        drawable = front & any_in & onscreen
        scale = float(1 << _SHIFT)
        pts_all = np.zeros((len(self.F), 4, 2), np.int32)
        ok = drawable & all_in
        pts_all[ok, :, 0] = np.round((np.clip(fu[ok], -1e5, 1e5) - 0.5) * scale)
        pts_all[ok, :, 1] = np.round((np.clip(fv[ok], -1e5, 1e5) - 0.5) * scale)
        cam_z = float(c[2])
        for oi in self.visibility_order(c[:2], pose.heading_rad):
            parts = self._obj_parts[oi]
            for pi in _part_order(self._obj_zr[oi], cam_z):
                fids = parts[pi]
                for fi in fids[drawable[fids]].tolist():
                    if all_in[fi]:
                        pts = pts_all[fi]
                    else:
                        poly = _clip_near(vc[self.F[fi]], _NEAR)
                        if len(poly) < 3:
                            continue
                        pu = intr.fx * poly[:, 0] / poly[:, 2] + intr.cx
                        pv = intr.fy * poly[:, 1] / poly[:, 2] + intr.cy
                        pts = np.round((np.clip(np.stack([pu, pv], -1), -1e5, 1e5) - 0.5) * scale).astype(np.int32)
                    cv2.fillConvexPoly(ids, pts, float(fi + FIRST_FACE_ID), cv2.LINE_8, _SHIFT)
        return ids

    def sky_radiance_lowres(self, r_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sky radiance at every sky_step-th pixel (below the horizon: just above it, for fog),
        and the angle to the sun there (for the glare)."""
        d = np.stack([self.xs, self.ys, np.ones_like(self.xs)], axis=-1) @ r_wc.T.astype(np.float32)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        d[..., 2] = np.maximum(d[..., 2], 0.03)
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        rad = self.sky.radiance(d)
        if self.sky.cloud_cover > 0.0:
            rad = self._clouds(d, rad)
        gamma = np.arccos(np.clip(d @ self.sun.astype(np.float32), -1.0, 1.0))
        return rad, gamma

    def _clouds(self, d: np.ndarray, rad: np.ndarray) -> np.ndarray:
        # Cloud layer: the noise tile stretched over a plane ~1.5 km up.
        z = np.maximum(d[..., 2], 0.03)
        mx = (d[..., 0] / z * 40.0).astype(np.float32)
        my = (d[..., 1] / z * 40.0).astype(np.float32)
        n = cv2.remap(self._noise, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        cover = self.sky.cloud_cover
        dens = np.clip((n - (1.0 - cover)) / 0.2, 0.0, 1.0) * np.clip(d[..., 2] / 0.1, 0.0, 1.0)
        cos_g = np.clip(d @ self.sun.astype(np.float32), -1.0, 1.0)
        e_h = float(self.sky.ambient_irradiance([[0.0, 0.0, 1.0]])[0][1] + self.sky.sun_irradiance_bgr[1] * self.sun[2])
        lum = 0.75 * e_h / math.pi * (0.8 + 0.6 * np.exp((cos_g - 1.0) * 8.0)) * (0.7 + 0.3 * n)
        return rad * (1.0 - dens[..., None]) + (lum * dens)[..., None] * np.array([1.0, 0.99, 0.97], np.float32)

    def render(self, pose: CameraPose) -> RenderOutput:
        r_wc = pose.world_from_cam()
        c = np.asarray(pose.position, dtype=np.float64)
        xn, yn = self.xn, self.yn
        rw = [np.float32(r_wc[k, 0]) * xn + np.float32(r_wc[k, 1]) * yn + np.float32(r_wc[k, 2]) for k in range(3)]
        rx, ry, rz = rw
        ids = self._rasterise(pose, r_wc, rz)
        zeros = self.zeros

        def fetch(tab: np.ndarray) -> tuple[np.ndarray, ...]:
            return cv2.split(cv2.remap(tab, zeros, ids, cv2.INTER_NEAREST))

        # Ray-plane intersection: n.(c + t r) = d.
        nrm4 = np.concatenate([self.N, -(self.D - self.N @ c)[:, None]], axis=1)  # (F, 4): n, -(d - n.c)
        plane = np.zeros((len(self.F) + FIRST_FACE_ID, 1, 4), np.float32)
        plane[SKY_ID, 0] = (0.0, 0.0, 0.0, -_FAR)
        plane[GROUND_ID, 0] = (0.0, 0.0, 1.0, c[2])
        plane[FIRST_FACE_ID:, 0] = nrm4
        nx, ny, nz, negk = fetch(plane)
        den = nx * rx + ny * ry + nz * rz
        is_sky = ids == SKY_ID
        den[is_sky] = 1.0
        den = np.where(np.abs(den) < 1e-6, np.float32(-1e-6), den)
        t = np.clip(negk / -den, _NEAR, _FAR)  # camera-z depth, since r has z_cam = 1
        px = np.float32(c[0]) + t * rx
        py = np.float32(c[1]) + t * ry
        pz = np.float32(c[2]) + t * rz
        is_ground = ids == GROUND_ID
        pz[is_ground] = 0.0
        # Shadow lookup.
        s = self.sun
        gx = px - pz * np.float32(s[0] / s[2])
        gy = py - pz * np.float32(s[1] / s[2])
        inv = np.float32(1.0 / self.shadow_res)
        hval = cv2.remap(self.hmap, (gx - np.float32(self.shadow_origin[0])) * inv,
                         (gy - np.float32(self.shadow_origin[1])) * inv, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        sunlit = np.clip((pz + np.float32(_SHADOW_TOL + _SHADOW_SOFT) - hval) * np.float32(1.0 / _SHADOW_SOFT), 0.0, 1.0)
        # Texture coordinates (metres) on each face; ground: world x, y.
        e1x, e1y, e1z, a0 = fetch(self.tab_e1)
        e2x, e2y, e2z, b0 = fetch(self.tab_e2)
        ta = e1x * px + e1y * py + e1z * pz + a0
        tb = e2x * px + e2y * py + e2z * pz + b0
        # Albedo: faces from their material and windows, ground from the map.
        ab, ag, ar, contrast = fetch(self.tab_alb)
        su, a_start, a_end, hwf = fetch(self.tab_wa)
        sw, gf, top, hhf = fetch(self.tab_wb)
        fa = (ta - a_start) / su
        fa -= np.floor(fa)
        fb = (tb - gf) / sw
        fb -= np.floor(fb)
        win = (np.abs(fa - 0.5) < hwf) & (np.abs(fb - 0.5) < hhf) & (ta > a_start) & (ta < a_end) & (tb > gf) & (tb < top)
        gb, gg, gr, _ = fetch(self.tab_glass)
        ab = np.where(win, gb, ab)
        ag = np.where(win, gg, ag)
        ar = np.where(win, gr, ar)
        gm = self.scene.ground
        ginv = np.float32(1.0 / gm.res_m)
        mgx = (px - np.float32(gm.origin_xy[0])) * ginv
        mgy = (py - np.float32(gm.origin_xy[1])) * ginv
        border = tuple(float(v) * ALBEDO_SCALE for v in gm.default_bgr)
        fine = cv2.remap(gm.albedo, mgx, mgy, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=border)
        cf = np.float32(1.0 / gm.coarse_factor)
        coarse = cv2.remap(gm.coarse, mgx * cf - np.float32(0.5 - 0.5 * cf), mgy * cf - np.float32(0.5 - 0.5 * cf),
                           cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=border)
        # Distant ground samples the coarse map: a pixel there spans metres of road.
        footprint = t * t * np.float32(1.0 / (self.intr.fy * max(c[2], 0.3)))
        wc = np.clip((footprint - np.float32(gm.res_m * 1.5)) / np.float32(gm.res_m * gm.coarse_factor), 0.0, 1.0)
        groundalb = cv2.split(fine.astype(np.float32) * (1.0 - wc)[..., None] + coarse.astype(np.float32) * wc[..., None])
        gscale = np.float32(1.0 / ALBEDO_SCALE)
        # Detail noise, fading with distance where it would only alias.
        ng = np.float32(_NOISE_TEXELS_PER_M)
        scale_map = np.where(is_ground, np.float32(_GROUND_NOISE_TEXELS_PER_M), ng)
        noise = cv2.remap(self._noise, ta * scale_map, tb * scale_map, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        fade = np.float32(1.0) / (np.float32(1.0) + t * np.float32(1.0 / 25.0))
        detail = np.float32(1.0) + np.float32(2.0) * contrast * (noise - np.float32(0.5)) * fade
        dirb, dirg, dirr, _ = fetch(self.tab_direct)
        ambb, ambg, ambr, _ = fetch(self.tab_ambient)
        sky_lo, gamma_lo = self.sky_radiance_lowres(r_wc)
        h, w = ids.shape
        sky_full = cv2.resize(sky_lo, (w, h), interpolation=cv2.INTER_LINEAR)
        fog = np.float32(1.0) - np.exp(-t * np.float32(1.0 / self.fog_m))
        fog[is_sky] = 1.0
        out = []
        for k, (fa_, ga_, dk, ak) in enumerate(((ab, groundalb[0], dirb, ambb), (ag, groundalb[1], dirg, ambg),
                                                  (ar, groundalb[2], dirr, ambr))):
            albedo = np.where(is_ground, ga_ * gscale, fa_) * detail
            light = dk * sunlit + ak
            surf = albedo * light
            out.append(surf + (sky_full[..., k] - surf) * fog)
        radiance = cv2.merge(out)
        sun_px, sun_vis = self._add_sun(radiance, ids, r_wc, gamma_lo)
        return RenderOutput(radiance, ids, sun_px, sun_vis, depth=t, sunlit=sunlit)

    def _add_sun(self, radiance: np.ndarray, ids: np.ndarray, r_wc: np.ndarray, gamma_lo: np.ndarray):
        intr = self.intr
        cam = self.sun @ r_wc
        h, w = ids.shape
        if cam[2] <= 1e-6:
            return np.array([np.nan, np.nan]), 0.0
        u = intr.fx * cam[0] / cam[2] + intr.cx
        v = intr.fy * cam[1] / cam[2] + intr.cy
        r_px = intr.fx * math.tan(SUN_ANGULAR_RADIUS_RAD)
        rr = int(math.ceil(r_px * 2 + 2))
        x0, x1 = max(int(u) - rr, 0), min(int(u) + rr + 1, w)
        y0, y1 = max(int(v) - rr, 0), min(int(v) + rr + 1, h)
        visible = 0.0
        if x0 < x1 and y0 < y1:
            yy, xx = np.mgrid[y0:y1, x0:x1].astype(np.float32)
            dist = np.hypot(xx + 0.5 - u, yy + 0.5 - v)
            cover = np.clip(r_px + 0.5 - dist, 0.0, 1.0)
            skyroi = ids[y0:y1, x0:x1] == SKY_ID
            total = float(cover.sum())
            if total > 0:
                visible = float((cover * skyroi).sum()) / total
            disk = self.sky.sun_disk_radiance_bgr().astype(np.float32)
            radiance[y0:y1, x0:x1] += (cover * skyroi)[..., None] * disk
        if visible > 0.0:
            # Veiling glare and the aureole around a visible sun, over everything.
            e = float(self.sky.sun_irradiance_bgr[1]) / math.pi * visible
            glow = e * (0.5 * np.exp(-gamma_lo / 0.02) + 0.06 * np.exp(-gamma_lo / 0.15))
            glow_full = cv2.resize(glow.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
            tint = (self.sky.sun_irradiance_bgr / self.sky.sun_irradiance_bgr[1]).astype(np.float32)
            radiance += glow_full[..., None] * tint
        return np.array([u, v]), visible
