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
   table (laid out as a grid, see :data:`TABLE_COLS`); the ray-plane intersection gives the world
   point P; shading is Lambertian, direct sun times visibility plus sky/ground ambient; visibility
   comes from an exit-height map (below).

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

from replay.synthetic.scene import ALBEDO_SCALE, Scene, Solid
from replay.synthetic.sky import SUN_ANGULAR_RADIUS_RAD, PreethamSky
from rig.geometry import world_from_heading
from rig.types import Intrinsics

SKY_ID, GROUND_ID, FIRST_FACE_ID = 0, 1, 2
_FAR = 1.0e5  # metres: the depth of the sky
_NEAR = 0.3  # metres: the near clipping plane
_SHIFT = 4  # fillConvexPoly sub-pixel bits
_SHADOW_TOL = 0.06  # metres of exit height above P before P counts as shadowed
_SHADOW_SOFT = 0.12  # metres over which the shadow fades in (a penumbra of sorts)
_NOISE_TEXELS_PER_M = 12.0
_GROUND_NOISE_TEXELS_PER_M = 24.0
_DOME_STEP_DEG = 0.5
_MAX_SHADOW_CELLS = 4096  # per side of the exit-height map
# The per-face tables are fetched with cv2.remap, which takes images of under 32767 (SHRT_MAX) rows
# and columns: one row per face held 32 764 faces, fewer than a long drive's (2000 frames can make
# 37 000). Row-major over TABLE_COLS columns, the id's (id mod TABLE_COLS, id div TABLE_COLS)
# addresses a table's row id; a power of two, so that those are exact in float32.
TABLE_COLS = 1024
# The id buffer is float32 (cv2.remap's map type), whose integers are exact up to 2**24.
MAX_FACES = 2**24 - FIRST_FACE_ID
_IRRADIANCE_CHUNK = 32768  # faces (table rows) lit per call, above the old limit of 32 766 rows


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
    depth: np.ndarray = field(repr=False)
    sunlit: np.ndarray = field(repr=False)


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
        # Long drives cover more ground: coarsen the shadow map rather than let it grow unbounded.
        shadow_res_m = max(shadow_res_m, float(extent.max()) / _MAX_SHADOW_CELLS)
        self.shadow_res = shadow_res_m
        self.shadow_origin = g.origin_xy
        shape = (int(math.ceil(extent[1] / shadow_res_m)), int(math.ceil(extent[0] / shadow_res_m)))
        self.hmap = exit_height_map(scene, self.sun, g.origin_xy, shadow_res_m, shape)
        w, h = self.intr.width, self.intr.height
        u = (np.arange(w, dtype=np.float32) + 0.5 - self.intr.cx) / self.intr.fx
        v = (np.arange(h, dtype=np.float32) + 0.5 - self.intr.cy) / self.intr.fy
        self.xn, self.yn = np.meshgrid(u, v)
        self._xcol, self._yrow = u.astype(np.float64), v.astype(np.float64)
        self._ws: dict[str, np.ndarray] = {}
        hs, ws = -(-h // sky_step_px), -(-w // sky_step_px)
        us = ((np.arange(ws) + 0.5) * sky_step_px - self.intr.cx) / self.intr.fx
        vs = ((np.arange(hs) + 0.5) * sky_step_px - self.intr.cy) / self.intr.fy
        self.xs, self.ys = (a.astype(np.float32) for a in np.meshgrid(us, vs))
        self._noise = scene.noise
        self._ground_border = tuple(float(v) * ALBEDO_SCALE for v in g.default_bgr)
        self._build_dome()

    # -- scene compilation

    def _compile_faces(self) -> None:
        solids: list[Solid] = [p for o in self.scene.objects for p in o.parts]
        verts, faces, normals, offsets, mats = [], [], [], [], []
        base = n0 = 0
        self._solid_faces: list[np.ndarray] = []
        for sol in solids:
            verts.append(sol.vertices)
            faces.append(sol.faces + base)
            normals.append(sol.normals)
            offsets.append(sol.offsets)
            mats.extend(sol.materials)
            self._solid_faces.append(np.arange(n0, n0 + len(sol.faces)))
            base += len(sol.vertices)
            n0 += len(sol.faces)
        self.V = np.concatenate(verts) if verts else np.zeros((0, 3))
        self.F = np.concatenate(faces) if faces else np.zeros((0, 4), np.int64)
        self.N = np.concatenate(normals) if normals else np.zeros((0, 3))
        self.D = np.concatenate(offsets) if offsets else np.zeros(0)
        nf = len(self.F)
        if nf > MAX_FACES:
            raise ValueError(f"Renderer: a scene may hold at most {MAX_FACES} faces, got {nf}")
        # Every table is padded to whole rows of TABLE_COLS; ids never reach the padding.
        total = -(-(nf + FIRST_FACE_ID) // TABLE_COLS) * TABLE_COLS
        # Texture coordinates (metres): a = e1 . P + a0 along the face (e1 horizontal, a from 0
        # at the face's left edge); b = z on walls (buildings stand on z = 0, so b is the height
        # on the wall), y on flat faces and the ground.
        e1 = np.zeros((total, 3))
        a0 = np.zeros(total)
        e1[GROUND_ID] = (1.0, 0.0, 0.0)
        win_a = np.zeros((total, 4), np.float32)  # 1/spacing, offset, columns, half width fraction
        win_b = np.zeros((total, 4), np.float32)  # 1/floor height, offset, floors, half height fraction
        win_a[:, 0] = win_b[:, 0] = 1.0
        glass = np.zeros((total, 4), np.float32)
        alb = np.zeros((total, 4), np.float32)
        alb[GROUND_ID] = (0.0, 0.0, 0.0, 0.35)  # ground albedo comes from the map
        fs = slice(FIRST_FACE_ID, FIRST_FACE_ID + nf)
        n = self.N
        flat = np.abs(n[:, 2]) >= 0.99
        d1 = np.cross(np.array([0.0, 0.0, 1.0]), n)
        d1[flat] = (1.0, 0.0, 0.0)
        d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
        d2 = np.cross(n, d1)
        fv = self.V[self.F]  # (F, 4, 3)
        pa = np.einsum("fkj,fj->fk", fv, d1)
        pb = np.einsum("fkj,fj->fk", fv, d2)
        e1[fs] = d1
        a0[fs] = -pa.min(axis=1)
        alb[fs, :3] = np.array([m.albedo_rgb[::-1] for m in mats], dtype=np.float64).reshape(-1, 3)
        alb[fs, 3] = np.array([m.contrast for m in mats], dtype=np.float64)
        lengths, heights = pa.max(axis=1) - pa.min(axis=1), pb.max(axis=1) - pb.min(axis=1)
        has_windows = np.array([m.windows is not None for m in mats], dtype=bool)
        for i in np.nonzero(has_windows & (np.abs(n[:, 2]) < 0.2))[0]:
            f = i + FIRST_FACE_ID
            w = mats[i].windows
            assert w is not None  # has_windows selected only the faces whose material has windows
            su, sw = w.spacing_m
            ncol = int((lengths[i] - 1.0) // su)
            if ncol >= 1:
                start = (lengths[i] - ncol * su) / 2
                # In cell units: fa = a / su - start / su lies in [0, ncol) on the grid.
                win_a[f] = (1.0 / su, start / su, ncol, w.size_frac[0] / 2)
                nfloor = int((heights[i] - w.ground_floor_m - 0.6) // sw)
                win_b[f] = (1.0 / sw, w.ground_floor_m / sw, max(nfloor, 0), w.size_frac[1] / 2)
                glass[f, :3] = w.glass_rgb[::-1]
        horizontal = np.zeros(total)
        horizontal[GROUND_ID] = 1.0
        horizontal[FIRST_FACE_ID:FIRST_FACE_ID + nf] = np.abs(self.N[:, 2]) > 0.7
        self.tab_tex = np.stack([e1[:, 0], e1[:, 1], a0, horizontal], axis=-1).astype(np.float32).reshape(-1, 1, 4)
        self._noise_scale = np.full((total, 1), _NOISE_TEXELS_PER_M, np.float32)
        self._noise_scale[GROUND_ID] = _GROUND_NOISE_TEXELS_PER_M
        self._plane_tab = np.zeros((total, 1, 4), np.float32)
        self._plane_tab[SKY_ID, 0] = (0.0, 0.0, 0.0, _FAR)  # den 0 -> t inf -> clipped to _FAR
        self.tab_alb = alb.reshape(-1, 1, 4)
        self.tab_wa = win_a.reshape(-1, 1, 4)
        self.tab_wb = win_b.reshape(-1, 1, 4)
        self.tab_glass = glass.reshape(-1, 1, 4)
        normals_all = np.zeros((total, 3))
        normals_all[GROUND_ID] = (0.0, 0.0, 1.0)
        normals_all[SKY_ID] = (0.0, 0.0, 1.0)
        normals_all[FIRST_FACE_ID:FIRST_FACE_ID + nf] = self.N
        direct, ambient = np.zeros((total, 3)), np.zeros((total, 3))
        # In chunks: the sky integral holds a float64 (rows, 1200) matrix, 9.6 kB a face. A scene
        # that fits one chunk (every scene before the tables became grids) takes the one BLAS
        # call over its rows it always took: another split can change the last bit (OpenBLAS
        # takes a single row through gemv), and with it a pixel.
        for r0 in range(0, nf + FIRST_FACE_ID, _IRRADIANCE_CHUNK):
            rows = slice(r0, min(r0 + _IRRADIANCE_CHUNK, nf + FIRST_FACE_ID))
            direct[rows] = self.sky.direct_irradiance(normals_all[rows])
            ambient[rows] = self.sky.ambient_irradiance(normals_all[rows])
        direct[SKY_ID] = ambient[SKY_ID] = 0.0
        # Channels 0-2: direct irradiance / pi (so albedo * it is radiance); 3: n . s.
        self.tab_direct = np.concatenate([direct / math.pi, (normals_all @ self.sky.sun_enu)[:, None]], axis=1) \
            .astype(np.float32).reshape(-1, 1, 4)
        self.tab_ambient = np.concatenate([ambient, np.zeros((total, 1))], axis=1) \
            .astype(np.float32).reshape(-1, 1, 4) / np.float32(math.pi)

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
        ids = self._buf("ids")
        # Below the horizon the ray meets the ground (id 1), above it the sky (id 0).
        np.copyto(ids, np.less(rz, 0.0, out=self._buf("below", dtype=bool)))
        if len(self.F) == 0:
            return ids
        c = np.asarray(pose.position, dtype=np.float64)
        order = self.visibility_order(c[:2], pose.heading_rad)
        if not order:
            return ids
        # These two products stay over the whole scene: a BLAS call over other rows can round
        # a row's last bit otherwise, and the pixels must not change. They are cheap.
        vc = (self.V - c) @ r_wc  # camera coordinates of every vertex
        front_all = self.N @ c - self.D > 1e-6
        # The rest only for the faces of the objects drawn: over a long drive's every face (200 000
        # at 10 000 frames) it was most of a frame. Element by element, so the same values.
        drawn = np.concatenate([f for oi in order for f in self._obj_parts[oi]])
        local = np.empty(len(self.F), np.int64)  # a face's index in ``drawn`` (only those are read)
        local[drawn] = np.arange(len(drawn))
        fvc = vc[self.F[drawn]]  # (n, 4, 3)
        fz = fvc[..., 2]
        all_in = np.all(fz >= _NEAR, axis=1)
        any_in = np.any(fz >= _NEAR, axis=1)
        with np.errstate(divide="ignore", invalid="ignore"):
            fu = intr.fx * fvc[..., 0] / fz + intr.cx
            fv = intr.fy * fvc[..., 1] / fz + intr.cy
        w, h = intr.width, intr.height
        onscreen = ~all_in | (
            (fu.max(axis=1) >= 0) & (fu.min(axis=1) <= w) & (fv.max(axis=1) >= 0) & (fv.min(axis=1) <= h)
        )
        drawable = front_all[drawn] & any_in & onscreen
        scale = float(1 << _SHIFT)
        pts_all = np.zeros((len(drawn), 4, 2), np.int32)
        ok = drawable & all_in
        pts_all[ok, :, 0] = np.round((np.clip(fu[ok], -1e5, 1e5) - 0.5) * scale)
        pts_all[ok, :, 1] = np.round((np.clip(fv[ok], -1e5, 1e5) - 0.5) * scale)
        cam_z = float(c[2])
        for oi in order:
            parts = self._obj_parts[oi]
            for pi in _part_order(self._obj_zr[oi], cam_z):
                fids = parts[pi]
                lids = local[fids]
                keep = drawable[lids]
                for fi, li in zip(fids[keep].tolist(), lids[keep].tolist(), strict=True):
                    if all_in[li]:
                        pts = pts_all[li]
                    else:
                        poly = _clip_near(fvc[li], _NEAR)
                        if len(poly) < 3:
                            continue
                        pu = intr.fx * poly[:, 0] / poly[:, 2] + intr.cx
                        pv = intr.fy * poly[:, 1] / poly[:, 2] + intr.cy
                        pts = np.round((np.clip(np.stack([pu, pv], -1), -1e5, 1e5) - 0.5) * scale).astype(np.int32)
                    cv2.fillConvexPoly(ids, pts, float(fi + FIRST_FACE_ID), cv2.LINE_8, _SHIFT)
        return ids

    # -- sky

    def _build_dome(self) -> None:
        """The sky (and cloud layer) over azimuth x elevation, once per scene: the sun is fixed."""
        step = math.radians(_DOME_STEP_DEG)
        n_az = int(round(2 * math.pi / step))
        n_el = int(round(math.pi / 2 / step)) + 1
        az = np.arange(n_az) * step
        el = np.arange(n_el) * step
        az_g, el_g = np.meshgrid(az, el)
        d = np.stack([np.cos(el_g) * np.sin(az_g), np.cos(el_g) * np.cos(az_g), np.sin(el_g)], axis=-1)
        d = d.astype(np.float32)
        rad = self.sky.radiance(d)
        if self.sky.cloud_cover > 0.0:
            rad = self._clouds(d, rad)
        self.dome = rad.astype(np.float32)
        self._dome_inv_step = 1.0 / step

    def sky_radiance_lowres(self, r_wc: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sky radiance at every sky_step-th pixel (below the horizon: just above it, for fog),
        and the angle to the sun there (for the glare)."""
        rw = r_wc.astype(np.float32)
        dx = rw[0, 0] * self.xs + rw[0, 1] * self.ys + rw[0, 2]
        dy = rw[1, 0] * self.xs + rw[1, 1] * self.ys + rw[1, 2]
        dz = rw[2, 0] * self.xs + rw[2, 1] * self.ys + rw[2, 2]
        inv = 1.0 / np.sqrt(dx * dx + dy * dy + dz * dz)
        dx, dy, dz = dx * inv, dy * inv, dz * inv
        az = np.mod(np.arctan2(dx, dy), np.float32(2 * math.pi))
        el = np.arcsin(np.clip(dz, 0.03, 1.0))
        k = np.float32(self._dome_inv_step)
        rad = cv2.remap(self.dome, az * k, el * k, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        s = self.sun.astype(np.float32)
        gamma = np.arccos(np.clip(dx * s[0] + dy * s[1] + dz * s[2], -1.0, 1.0))
        return rad, gamma

    def _clouds(self, d: np.ndarray, rad: np.ndarray) -> np.ndarray:
        # Cloud layer: the noise tile stretched over a plane high above.
        z = np.maximum(d[..., 2], 0.02)
        mx = (d[..., 0] / z * 60.0).astype(np.float32)
        my = (d[..., 1] / z * 60.0).astype(np.float32)
        n = cv2.remap(self._noise, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
        cover = self.sky.cloud_cover
        # Near the horizon the layer is seen edge-on: fade it into haze rather than streaks.
        dens = np.clip((n - (1.0 - cover)) / 0.2, 0.0, 1.0) * np.clip((d[..., 2] - 0.04) / 0.2, 0.0, 1.0)
        cos_g = np.clip(d @ self.sun.astype(np.float32), -1.0, 1.0)
        e_h = float(self.sky.ambient_irradiance([[0.0, 0.0, 1.0]])[0][1] + self.sky.sun_irradiance_bgr[1] * self.sun[2])
        lum = 0.75 * e_h / math.pi * (0.8 + 0.6 * np.exp((cos_g - 1.0) * 8.0)) * (0.7 + 0.3 * n)
        return rad * (1.0 - dens[..., None]) + (lum * dens)[..., None] * np.array([1.0, 0.99, 0.97], np.float32)

    # -- shading

    def _buf(self, name: str, channels: int = 0, dtype=np.float32) -> np.ndarray:
        """A preallocated per-pixel work buffer. Fresh full-frame temporaries cost page faults
        each frame (about as much as the arithmetic), so the shading pass writes into these."""
        b = self._ws.get(name)
        if b is None:
            shape = (self.intr.height, self.intr.width) + ((channels,) if channels else ())
            b = self._ws[name] = np.empty(shape, dtype)
        return b

    def _outer(self, name: str, col: np.ndarray, row: np.ndarray) -> np.ndarray:
        """col[j] + row[i] over the image, in one pass (for anything affine in xn, yn)."""
        out = self._buf(name)
        np.add(col[None, :], row[:, None], out=out)
        return out

    def render(self, pose: CameraPose) -> RenderOutput:
        """Radiance of the scene seen from ``pose``. The returned arrays are the renderer's work
        buffers: copy them before the next call if they must be kept."""
        r_wc = pose.world_from_cam()
        c = np.asarray(pose.position, dtype=np.float64)
        f32 = np.float32
        buf = self._buf
        xcol, yrow = self._xcol, self._yrow
        # World ray directions (z_cam = 1) are affine in xn, yn: each an outer sum.
        rx = self._outer("rx", r_wc[0, 0] * xcol + r_wc[0, 2], r_wc[0, 1] * yrow)
        ry = self._outer("ry", r_wc[1, 0] * xcol + r_wc[1, 2], r_wc[1, 1] * yrow)
        rz = self._outer("rz", r_wc[2, 0] * xcol + r_wc[2, 2], r_wc[2, 1] * yrow)
        ids = self._rasterise(pose, r_wc, rz)
        # Where each pixel's face sits in the tables' grid of TABLE_COLS columns (exact: ids are
        # integers under 2**24 and TABLE_COLS a power of two).
        id_row = np.multiply(ids, f32(1.0 / TABLE_COLS), out=buf("id_row"))
        np.floor(id_row, out=id_row)
        id_col = np.multiply(id_row, f32(-TABLE_COLS), out=buf("id_col"))
        id_col += ids

        def fetch(tab: np.ndarray, name: str) -> np.ndarray:
            grid = tab.reshape(-1, TABLE_COLS, tab.shape[-1])  # a view: the tables are padded to whole rows
            return cv2.remap(grid, id_col, id_row, cv2.INTER_NEAREST, dst=buf(name, tab.shape[-1]))

        tmp, tmp2 = buf("tmp"), buf("tmp2")
        # Ray-plane intersection n.(c + t r) = d in camera coordinates: t = k / (n_cam . (xn, yn, 1)).
        plane = self._plane_tab
        faces = slice(FIRST_FACE_ID, FIRST_FACE_ID + len(self.F))
        plane[faces, 0, :3] = self.N @ r_wc
        plane[faces, 0, 3] = self.D - self.N @ c
        plane[GROUND_ID, 0, :3] = r_wc[2]
        plane[GROUND_ID, 0, 3] = -c[2]
        g = fetch(plane, "plane")
        den = np.multiply(g[..., 0], self.xn, out=buf("den"))
        den += np.multiply(g[..., 1], self.yn, out=tmp)
        den += g[..., 2]
        t = buf("t")
        with np.errstate(divide="ignore", invalid="ignore"):
            np.divide(g[..., 3], den, out=t)
        np.clip(t, _NEAR, _FAR, out=t)  # camera-z depth; the sky (0 / 0 -> nan) is fixed below
        t[np.isnan(t)] = _FAR
        px = np.multiply(t, rx, out=buf("px"))
        px += f32(c[0])
        py = np.multiply(t, ry, out=buf("py"))
        py += f32(c[1])
        pz = np.multiply(t, rz, out=buf("pz"))
        pz += f32(c[2])
        # Shadow: the exit height over the point's sun-ward ground point, in map cells:
        # (P - P_z s / s_z - origin) / res = (c - c_z s / s_z - origin) / res + t (r - r_z s / s_z) / res.
        s = self.sun
        inv = 1.0 / self.shadow_res
        kx, ky = s[0] / s[2], s[1] / s[2]
        ox, oy = self.shadow_origin
        hx = self._outer("hx", inv * ((r_wc[0, 0] - kx * r_wc[2, 0]) * xcol + r_wc[0, 2] - kx * r_wc[2, 2]),
                         inv * (r_wc[0, 1] - kx * r_wc[2, 1]) * yrow)
        hx *= t
        hx += f32(inv * (c[0] - kx * c[2] - ox))
        hy = self._outer("hy", inv * ((r_wc[1, 0] - ky * r_wc[2, 0]) * xcol + r_wc[1, 2] - ky * r_wc[2, 2]),
                         inv * (r_wc[1, 1] - ky * r_wc[2, 1]) * yrow)
        hy *= t
        hy += f32(inv * (c[1] - ky * c[2] - oy))
        hval = cv2.remap(self.hmap, hx, hy, cv2.INTER_LINEAR, dst=buf("hval"),
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)
        sunlit = np.subtract(pz, hval, out=buf("sunlit"))
        sunlit += f32(_SHADOW_TOL + _SHADOW_SOFT)
        sunlit *= f32(1.0 / _SHADOW_SOFT)
        np.clip(sunlit, 0.0, 1.0, out=sunlit)
        # Texture coordinates in metres: along the face horizontally, and up (z) or north (y).
        tex = fetch(self.tab_tex, "tex")
        ta = np.multiply(tex[..., 0], px, out=buf("ta"))
        ta += np.multiply(tex[..., 1], py, out=tmp)
        ta += tex[..., 2]
        tb = np.subtract(py, pz, out=buf("tb"))
        tb *= tex[..., 3]
        tb += pz
        # Windows: cells of a grid, inside the grid's extent.
        wa, wb = fetch(self.tab_wa, "wa"), fetch(self.tab_wb, "wb")
        fa = np.multiply(ta, wa[..., 0], out=tmp)
        fa -= wa[..., 1]
        fb = np.multiply(tb, wb[..., 0], out=tmp2)
        fb -= wb[..., 1]
        win = np.greater_equal(fa, 0, out=buf("win", dtype=bool))
        mask = buf("mask", dtype=bool)
        win &= np.less(fa, wa[..., 2], out=mask)
        win &= np.greater_equal(fb, 0, out=mask)
        win &= np.less(fb, wb[..., 2], out=mask)
        fl = np.floor(fa, out=buf("floor"))
        fa -= fl
        fa -= f32(0.5)
        np.abs(fa, out=fa)
        win &= np.less(fa, wa[..., 3], out=mask)
        np.floor(fb, out=fl)
        fb -= fl
        fb -= f32(0.5)
        np.abs(fb, out=fb)
        win &= np.less(fb, wb[..., 3], out=mask)
        # Ground albedo: the fine map near, the coarse map far, where a pixel spans metres.
        gm = self.scene.ground
        ginv = 1.0 / gm.res_m
        gx0, gy0 = gm.origin_xy
        mgx = np.multiply(t, rx, out=buf("mgx"))
        mgx *= f32(ginv)
        mgx += f32((c[0] - gx0) * ginv)
        mgy = np.multiply(t, ry, out=buf("mgy"))
        mgy *= f32(ginv)
        mgy += f32((c[1] - gy0) * ginv)
        fine = cv2.remap(gm.albedo, mgx, mgy, cv2.INTER_LINEAR, dst=buf("fine", 3, np.uint8),
                         borderMode=cv2.BORDER_CONSTANT, borderValue=self._ground_border)
        cf = f32(1.0 / gm.coarse_factor)
        off = f32(0.5 - 0.5 / gm.coarse_factor)
        mgx *= cf
        mgx -= off
        mgy *= cf
        mgy -= off
        coarse = cv2.remap(gm.coarse, mgx, mgy, cv2.INTER_LINEAR, dst=buf("coarse", 3, np.uint8),
                           borderMode=cv2.BORDER_CONSTANT, borderValue=self._ground_border)
        coarse_w = np.multiply(t, t, out=buf("coarse_w"))
        coarse_w *= f32(1.0 / (self.intr.fy * max(c[2], 0.3) * gm.res_m * gm.coarse_factor))
        coarse_w -= f32(0.2)
        np.clip(coarse_w, 0.0, 1.0, out=coarse_w)
        coarse_w *= f32(1.0 / ALBEDO_SCALE)
        fine_w = np.subtract(f32(1.0 / ALBEDO_SCALE), coarse_w, out=buf("fine_w"))
        is_ground = np.equal(ids, GROUND_ID, out=buf("is_ground", dtype=bool))
        # Detail noise, fading with distance where it would only alias.
        nscale = self._noise_scale  # per face: texels per metre
        nsc = cv2.remap(nscale.reshape(-1, TABLE_COLS), id_col, id_row, cv2.INTER_NEAREST, dst=buf("nsc"))
        np.multiply(ta, nsc, out=tmp)
        np.multiply(tb, nsc, out=tmp2)
        noise = cv2.remap(self._noise, tmp, tmp2, cv2.INTER_LINEAR, dst=buf("noise"), borderMode=cv2.BORDER_WRAP)
        alb = fetch(self.tab_alb, "alb")
        detail = np.subtract(noise, f32(0.5), out=noise)
        detail *= alb[..., 3]
        fade = np.multiply(t, f32(1.0 / 12.0), out=tmp)
        fade += f32(1.0)
        detail /= fade
        detail += f32(1.0)
        glass = fetch(self.tab_glass, "glass")
        direct = fetch(self.tab_direct, "direct")
        ambient = fetch(self.tab_ambient, "ambient")
        sky_lo, gamma_lo = self.sky_radiance_lowres(r_wc)
        h, w = ids.shape
        sky_full = cv2.resize(sky_lo, (w, h), dst=buf("sky", 3), interpolation=cv2.INTER_LINEAR)
        fog = np.multiply(t, f32(-1.0 / self.fog_m), out=buf("fog"))
        np.exp(fog, out=fog)  # transmittance of the air between camera and surface
        radiance = self._buf("radiance", 3)
        albedo, light = buf("albedo"), buf("light")
        for k in range(3):
            np.multiply(fine[..., k], fine_w, out=tmp)
            tmp += np.multiply(coarse[..., k], coarse_w, out=tmp2)
            np.copyto(albedo, alb[..., k])
            np.copyto(albedo, glass[..., k], where=win)
            np.copyto(albedo, tmp, where=is_ground)
            albedo *= detail
            np.multiply(direct[..., k], sunlit, out=light)
            light += ambient[..., k]
            albedo *= light  # now the surface radiance
            albedo -= sky_full[..., k]
            albedo *= fog
            np.add(albedo, sky_full[..., k], out=radiance[..., k])
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
            glow = e * (3.0 * np.exp(-gamma_lo / 0.03) + 0.3 * np.exp(-gamma_lo / 0.2))
            glow_full = cv2.resize(glow.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)
            tint = (self.sky.sun_irradiance_bgr / self.sky.sun_irradiance_bgr[1]).astype(np.float32)
            radiance += glow_full[..., None] * tint
        return np.array([u, v]), visible
