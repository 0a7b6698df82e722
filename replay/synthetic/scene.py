"""Procedural street scenes: the road path, the ground map and the solids that stand on it.

Everything is in the ENU world frame (x east, y north, z up, metres) with the ground at z = 0.
A scene is a flat ground plane (its albedo painted into a top-down map: grass or paving, sidewalks,
road, lane markings) plus objects. An object is a vertical stack of convex solids (a box, a
faceted ellipsoid) with a convex footprint; footprints of different objects never overlap and
never reach into the lane the camera drives in. Those two facts are what the renderer's
visibility order relies on (see ``render.py``).

Headings and yaws are clockwise from north, like the camera heading: a box of yaw ``psi`` has its
local +y (length) axis along (sin psi, cos psi) and its +x (width) axis along (cos psi, -sin psi).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np

# ---------------------------------------------------------------------------------------------
# Textures


def fractal_noise(rng: np.random.Generator, size: int = 256, beta: float = 1.8) -> np.ndarray:
    """A tileable (periodic) 1/f^beta noise image (size, size) float32 in [0, 1]."""
    white = rng.standard_normal((size, size))
    f = np.fft.fftfreq(size)
    fr = np.hypot(f[:, None], f[None, :])
    fr[0, 0] = 1.0
    spec = np.fft.fft2(white) / fr**beta
    spec[0, 0] = 0.0
    img = np.real(np.fft.ifft2(spec))
    lo, hi = np.percentile(img, [1, 99])
    return np.clip((img - lo) / (hi - lo), 0.0, 1.0).astype(np.float32)


# ---------------------------------------------------------------------------------------------
# Materials and solids


@dataclass(frozen=True)
class WindowPattern:
    """A grid of windows on a vertical wall: one row per floor above a ground floor."""

    spacing_m: tuple[float, float] = (3.2, 3.2)  # horizontal, vertical (floor height)
    size_frac: tuple[float, float] = (0.55, 0.5)  # window width, height as fraction of spacing
    ground_floor_m: float = 3.5
    glass_rgb: tuple[float, float, float] = (0.05, 0.06, 0.08)


@dataclass(frozen=True)
class Material:
    """Linear albedo (RGB, 0-1), detail-noise contrast, and optional windows."""

    albedo_rgb: tuple[float, float, float]
    contrast: float = 0.15
    windows: WindowPattern | None = None


@dataclass
class Solid:
    """A convex polyhedron. Faces are vertex-index quads (a triangle repeats its last vertex),
    counter-clockwise seen from outside; ``normals``/``offsets`` give each face's plane n.x = d.
    """

    vertices: np.ndarray  # (V, 3)
    faces: np.ndarray  # (F, 4) int
    materials: list[Material]
    normals: np.ndarray = field(init=False)
    offsets: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64)
        self.faces = np.asarray(self.faces, dtype=np.int64)
        if len(self.materials) == 1:
            self.materials = self.materials * len(self.faces)
        if len(self.materials) != len(self.faces):
            raise ValueError(f"Solid: expected {len(self.faces)} materials, got {len(self.materials)}")
        centroid = self.vertices.mean(axis=0)
        v = self.vertices[self.faces]  # (F, 4, 3)
        a, b = v, np.roll(v, -1, axis=1)
        # Newell's method: robust for quads and for triangles with a repeated vertex.
        n = np.stack([
            np.sum((a[..., 1] - b[..., 1]) * (a[..., 2] + b[..., 2]), axis=1),
            np.sum((a[..., 2] - b[..., 2]) * (a[..., 0] + b[..., 0]), axis=1),
            np.sum((a[..., 0] - b[..., 0]) * (a[..., 1] + b[..., 1]), axis=1),
        ], axis=-1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        inward = np.einsum("ij,ij->i", n, v.mean(axis=1) - centroid) < 0
        n[inward] *= -1.0  # make every face wind outward
        self.faces[inward] = self.faces[inward][:, ::-1]
        self.normals = n
        self.offsets = np.einsum("ij,ij->i", n, self.vertices[self.faces[:, 0]])

    @property
    def z_range(self) -> tuple[float, float]:
        return float(self.vertices[:, 2].min()), float(self.vertices[:, 2].max())


def box_solid(center_xy, yaw_rad: float, width: float, length: float, z0: float, z1: float,
              materials: Material | list[Material]) -> Solid:
    """An upright box: ``width`` along its local x, ``length`` along its local y (the yaw).
    ``materials``: one for all faces, or six in the order south-ish, east-ish, north-ish,
    west-ish side (local -y, +x, +y, -x), top, bottom.
    """
    c = np.asarray(center_xy, dtype=np.float64)
    f = np.array([math.sin(yaw_rad), math.cos(yaw_rad)])
    r = np.array([math.cos(yaw_rad), -math.sin(yaw_rad)])
    corners = [c - r * width / 2 - f * length / 2, c + r * width / 2 - f * length / 2,
               c + r * width / 2 + f * length / 2, c - r * width / 2 + f * length / 2]
    verts = [[p[0], p[1], z0] for p in corners] + [[p[0], p[1], z1] for p in corners]
    faces = [[0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7], [4, 5, 6, 7], [3, 2, 1, 0]]
    mats = materials if isinstance(materials, list) else [materials]
    return Solid(np.array(verts), np.array(faces), list(mats))


def ellipsoid_solid(center, radii, material: Material, n_lon: int = 8, n_lat: int = 4) -> Solid:
    """A faceted ellipsoid of revolution (vertical axis): convex, with planar quad faces."""
    cx, cy, cz = center
    rh, rv = radii
    lats = np.linspace(-math.pi / 2, math.pi / 2, n_lat + 1)[1:-1]
    lons = np.arange(n_lon) * 2 * math.pi / n_lon
    verts = [[cx, cy, cz - rv]]
    for la in lats:
        for lo in lons:
            verts.append([cx + rh * math.cos(la) * math.sin(lo), cy + rh * math.cos(la) * math.cos(lo),
                          cz + rv * math.sin(la)])
    verts.append([cx, cy, cz + rv])
    top = len(verts) - 1
    faces = []
    for j in range(n_lon):
        faces.append([0, 1 + (j + 1) % n_lon, 1 + j, 1 + j])
    for i in range(len(lats) - 1):
        b0, b1 = 1 + i * n_lon, 1 + (i + 1) * n_lon
        for j in range(n_lon):
            jn = (j + 1) % n_lon
            faces.append([b0 + j, b0 + jn, b1 + jn, b1 + j])
    last = 1 + (len(lats) - 1) * n_lon
    for j in range(n_lon):
        faces.append([last + j, last + (j + 1) % n_lon, top, top])
    return Solid(np.array(verts), np.array(faces), [material])


def float3(values) -> tuple[float, float, float]:
    """Three floats (an RGB or BGR colour) from any length-3 sequence; another length is a ValueError."""
    a, b, c = (float(v) for v in values)
    return a, b, c


def convex_hull_ccw(points_xy) -> np.ndarray:
    """Convex hull (K, 2) counter-clockwise in ENU (x east, y north)."""
    pts = np.asarray(points_xy, dtype=np.float32).reshape(-1, 1, 2)
    hull = cv2.convexHull(pts, clockwise=False).reshape(-1, 2).astype(np.float64)
    # OpenCV's orientation flag assumes y down; check the signed area in ENU instead.
    area = np.sum(hull[:, 0] * np.roll(hull[:, 1], -1) - np.roll(hull[:, 0], -1) * hull[:, 1])
    return hull if area > 0 else hull[::-1]


@dataclass
class SceneObject:
    """A vertical stack of convex solids with the convex footprint (K, 2) CCW that holds them."""

    kind: str
    parts: list[Solid]
    # None only until __post_init__ computes it from the parts: a field optional at construction
    # but set after it is not expressible to mypy.
    footprint: np.ndarray = field(default=None)  # type: ignore[arg-type]

    def __post_init__(self) -> None:
        if self.footprint is None:
            self.footprint = convex_hull_ccw(np.concatenate([p.vertices[:, :2] for p in self.parts]))


# ---------------------------------------------------------------------------------------------
# The road path


@dataclass
class RoadPath:
    """The road's centreline sampled every ``ds`` metres: arc length, position, heading."""

    s: np.ndarray  # (N,)
    xy: np.ndarray  # (N, 2)
    heading: np.ndarray  # (N,) unwrapped, clockwise from north
    curvature: np.ndarray  # (N,) 1/m, positive turning right (heading increasing)
    intersections: list[tuple[np.ndarray, float, float]] = field(default_factory=list)
    # each: (corner xy, incoming heading, outgoing heading) of a 90-degree turn

    def at(self, s: float) -> tuple[np.ndarray, float, float]:
        """Position, heading and curvature at arc length ``s`` (linear interpolation)."""
        s = float(np.clip(s, self.s[0], self.s[-1]))
        x = np.interp(s, self.s, self.xy[:, 0])
        y = np.interp(s, self.s, self.xy[:, 1])
        return np.array([x, y]), float(np.interp(s, self.s, self.heading)), float(
            np.interp(s, self.s, self.curvature))

    @property
    def length(self) -> float:
        return float(self.s[-1])


def build_path(start_xy, start_heading: float, pieces: list[tuple[float, float]], ds: float = 0.5) -> RoadPath:
    """Integrate pieces of (length m, curvature 1/m) into a sampled path."""
    xy = [np.asarray(start_xy, dtype=np.float64)]
    hd = [float(start_heading)]
    kap = []
    for length, k in pieces:
        n = max(1, int(round(length / ds)))
        step = length / n
        for _ in range(n):
            h_mid = hd[-1] + 0.5 * step * k
            xy.append(xy[-1] + step * np.array([math.sin(h_mid), math.cos(h_mid)]))
            hd.append(hd[-1] + step * k)
            kap.append(k)
    kap.append(kap[-1] if kap else 0.0)
    xy_arr = np.array(xy)
    seg = np.linalg.norm(np.diff(xy_arr, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    return RoadPath(s=s, xy=xy_arr, heading=np.array(hd), curvature=np.array(kap))


@dataclass(frozen=True)
class RoadSpec:
    """Cross-section of the road: lanes each way, lane width, parking lanes, sidewalks."""

    lanes_each_way: int = 1
    lane_width: float = 3.3
    parking: bool = False
    sidewalk: float = 2.5
    right_hand: bool = True  # traffic drives on the right

    @property
    def half_width(self) -> float:
        return self.lanes_each_way * self.lane_width + (2.2 if self.parking else 0.0)

    @property
    def outer(self) -> float:
        """Distance from the centreline to the outer edge of the sidewalk."""
        return self.half_width + self.sidewalk


def random_path(rng: np.random.Generator, drive_length_m: float, road: RoadSpec,
                behind_m: float = 60.0, ahead_m: float = 140.0) -> tuple[RoadPath, float]:
    """A road of straights, 90-degree turns and gentle bends. Returns the path and the arc length
    where the drive starts (``behind_m`` of road lies behind the camera at the start).
    """
    min_r = road.outer + 3.0
    pieces: list[tuple[float, float]] = [(behind_m, 0.0)]
    total = behind_m
    need = behind_m + drive_length_m + ahead_m
    # The first turn comes within the first ~60 % of the drive, so most drives change heading.
    first = True
    intersections_at: list[tuple[float, float, float]] = []  # (s at arc start, R, sign)
    while total < need:
        straight = rng.uniform(6.0, max(12.0, 0.6 * drive_length_m)) if first else rng.uniform(15.0, 70.0)
        first = False
        pieces.append((straight, 0.0))
        total += straight
        kind = rng.random()
        sign = 1.0 if rng.random() < 0.5 else -1.0
        if kind < 0.5:  # a corner at an intersection
            r = max(rng.uniform(10.0, 22.0), min_r)
            intersections_at.append((total, r, sign))
            pieces.append((r * math.pi / 2, sign / r))
            total += r * math.pi / 2
        elif kind < 0.85:  # a bend
            ang = math.radians(rng.uniform(15.0, 60.0))
            r = max(rng.uniform(40.0, 160.0), min_r)
            pieces.append((r * ang, sign / r))
            total += r * ang
    path = build_path(rng.uniform(-5, 5, 2), rng.uniform(0.0, 2 * math.pi), pieces)
    for s0, r, sign in intersections_at:
        p0, h0, _ = path.at(s0)
        corner = p0 + r * np.array([math.sin(h0), math.cos(h0)])
        path.intersections.append((corner, h0, h0 + sign * math.pi / 2))
    return path, behind_m


def _normals(heading: np.ndarray) -> np.ndarray:
    """Right-pointing unit normals (N, 2) for headings (N,)."""
    return np.stack([np.cos(heading), -np.sin(heading)], axis=-1)


# ---------------------------------------------------------------------------------------------
# The ground map


ALBEDO_SCALE = 512.0  # ground map stores linear albedo * 512 in uint8 (so albedo <= ~0.5)


@dataclass
class GroundMap:
    """Top-down albedo of the ground plane: pixel (row i, col j) is the point
    (x0 + j * res, y0 + i * res). BGR uint8, linear albedo times :data:`ALBEDO_SCALE`.
    ``coarse`` is the same map ``coarse_factor`` times coarser, for distant ground.
    """

    origin_xy: tuple[float, float]
    res_m: float
    albedo: np.ndarray
    default_bgr: tuple[float, float, float]  # linear albedo beyond the map
    # None only until __post_init__ computes it (see SceneObject.footprint).
    coarse: np.ndarray = field(default=None)  # type: ignore[arg-type]
    coarse_factor: int = 8

    def __post_init__(self) -> None:
        if self.coarse is None:
            h, w = self.albedo.shape[:2]
            f = self.coarse_factor
            self.coarse = cv2.resize(self.albedo, (max(1, w // f), max(1, h // f)), interpolation=cv2.INTER_AREA)
            self.coarse = cv2.GaussianBlur(self.coarse, (0, 0), 1.0)

    @staticmethod
    def flat(albedo_rgb=(0.2, 0.2, 0.2), extent=((-100.0, -100.0), (100.0, 100.0)), res_m: float = 0.5) -> GroundMap:
        (x0, y0), (x1, y1) = extent
        w, h = int(math.ceil((x1 - x0) / res_m)), int(math.ceil((y1 - y0) / res_m))
        bgr = np.array(albedo_rgb[::-1]) * ALBEDO_SCALE
        img = np.zeros((h, w, 3), np.uint8)
        cv2.rectangle(img, (0, 0), (w, h), tuple(float(v) for v in np.clip(np.round(bgr), 0, 255)), -1)
        return GroundMap((x0, y0), res_m, img, float3(albedo_rgb[::-1]))

    def to_px(self, xy) -> np.ndarray:
        xy = np.asarray(xy, dtype=np.float64)
        return (xy - np.asarray(self.origin_xy)) / self.res_m


class _Painter:
    """Fills world-space polygons into a map image (sub-pixel accurate)."""

    SHIFT = 3

    def __init__(self, img: np.ndarray, origin_xy, res_m: float) -> None:
        self.img, self.origin, self.res = img, np.asarray(origin_xy), res_m

    def poly(self, xy, color) -> None:
        px = (np.asarray(xy) - self.origin) / self.res * (1 << self.SHIFT)
        cv2.fillConvexPoly(self.img, np.round(px).astype(np.int32), color, cv2.LINE_8, self.SHIFT)

    def strip(self, path_xy: np.ndarray, heading: np.ndarray, lat0: float, lat1: float, color,
              mask: np.ndarray | None = None) -> None:
        """Fill the band between lateral offsets lat0 < lat1 (right positive) along a polyline;
        ``mask`` (N-1,) selects which segments to fill (dashes)."""
        nrm = _normals(heading)
        a = path_xy + lat0 * nrm
        b = path_xy + lat1 * nrm
        for i in range(len(path_xy) - 1):
            if mask is not None and not mask[i]:
                continue
            self.poly(np.array([a[i], a[i + 1], b[i + 1], b[i]]), color)


def _albedo_px(rgb, rng: np.random.Generator | None = None, jitter: float = 0.0) -> tuple[int, int, int]:
    rgb = np.asarray(rgb, dtype=np.float64)
    if rng is not None and jitter:
        rgb = rgb * (1.0 + rng.uniform(-jitter, jitter, 3))
    b, g, r = (int(round(v)) for v in np.clip(rgb[::-1] * ALBEDO_SCALE, 0, 255))
    return b, g, r


GROUND_TYPES = {  # linear albedo RGB of what lies beyond the sidewalks
    "grass": (0.09, 0.13, 0.05),
    "dry_grass": (0.18, 0.16, 0.08),
    "dirt": (0.16, 0.12, 0.08),
    "paving": (0.22, 0.21, 0.19),
    "gravel": (0.20, 0.19, 0.17),
}


def paint_ground(rng: np.random.Generator, path: RoadPath, road: RoadSpec, ground_type: str,
                 margin_m: float = 90.0, max_px: int = 3600, base_res_m: float = 0.125) -> GroundMap:
    """Paint the ground map for a road: base ground with low-frequency variation, sidewalks,
    kerbs, asphalt with patches, lane markings, crosswalks at intersections."""
    lo = path.xy.min(axis=0) - margin_m
    hi = path.xy.max(axis=0) + margin_m
    res = max(base_res_m, float(np.max(hi - lo)) / max_px)
    w, h = int(math.ceil((hi[0] - lo[0]) / res)), int(math.ceil((hi[1] - lo[1]) / res))
    base_rgb = np.array(GROUND_TYPES[ground_type]) * rng.uniform(0.85, 1.15, 3)
    # Low-frequency mottling (metre scale and up), shared by every layer through one multiply.
    var = fractal_noise(rng, 256, beta=1.5)
    # One noise texel per metre: tile the 256-texel tile over the map, then upsample.
    up = max(1, int(round(1.0 / res)))
    var8 = np.clip(96.0 + 64.0 * var, 0, 255).astype(np.uint8)  # 0.75..1.25 in 1/128ths
    var_tiles = np.tile(var8, (h // (256 * up) + 1, w // (256 * up) + 1))
    img = np.zeros((h, w, 3), np.uint8)  # (cv2 fills a fresh map far faster than numpy does)
    cv2.rectangle(img, (0, 0), (w, h), _albedo_px(base_rgb), -1)
    paint = _Painter(img, lo, res)

    hw, outer = road.half_width, road.outer
    stubs = []
    for corner, h_in, h_out in path.intersections:
        # The crossing street continues past the corner both ways, like a real intersection.
        for hd, sgn in ((h_in, 1.0), (h_out, -1.0)):
            d = np.array([math.sin(hd), math.cos(hd)]) * sgn
            pts = np.array([corner + d * t for t in np.linspace(0.0, 45.0, 10)])
            heads = np.full(len(pts), math.atan2(d[0], d[1]))
            stubs.append((pts, heads))
    lines = [(path.xy, path.heading)] + stubs
    sidewalk_rgb = np.array([0.24, 0.23, 0.21]) * rng.uniform(0.8, 1.25) * rng.uniform(0.92, 1.08, 3)
    kerb_rgb = np.array([0.30, 0.30, 0.28]) * rng.uniform(0.8, 1.2)
    asphalt_rgb = np.array([0.065, 0.065, 0.068]) * rng.uniform(0.75, 1.6)
    for xy, heading_rad in lines:
        paint.strip(xy, heading_rad, -outer, outer, _albedo_px(sidewalk_rgb))
    for xy, heading_rad in lines:
        paint.strip(xy, heading_rad, -hw - 0.2, hw + 0.2, _albedo_px(kerb_rgb))
    for xy, heading_rad in lines:
        paint.strip(xy, heading_rad, -hw, hw, _albedo_px(asphalt_rgb))
    # Asphalt patches and repairs: darker or lighter rectangles on the road.
    for _ in range(int(path.length / 25)):
        s = rng.uniform(0, path.length)
        p, hd, _ = path.at(s)
        f = np.array([math.sin(hd), math.cos(hd)])
        r = np.array([math.cos(hd), -math.sin(hd)])
        c = p + r * rng.uniform(-hw, hw)
        a, b = rng.uniform(0.5, 3.0), rng.uniform(0.5, 4.0)
        paint.poly(np.array([c - r * a - f * b, c + r * a - f * b, c + r * a + f * b, c - r * a + f * b]),
                   _albedo_px(asphalt_rgb * rng.uniform(0.6, 1.5)))

    white = _albedo_px((0.45, 0.45, 0.43))
    yellow = _albedo_px((0.42, 0.30, 0.05))
    centre_yellow = rng.random() < 0.35
    lw = 0.12
    for xy, heading_rad in lines:
        seg_s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
        mid = 0.5 * (seg_s[:-1] + seg_s[1:])
        dashes = (mid % 9.0) < 3.0
        if centre_yellow:
            paint.strip(xy, heading_rad, -0.2, -0.2 + lw, yellow)
            paint.strip(xy, heading_rad, 0.2 - lw, 0.2, yellow)
        else:
            paint.strip(xy, heading_rad, -lw / 2, lw / 2, white, dashes)
        for k in range(1, road.lanes_each_way):
            for side in (-1.0, 1.0):
                o = side * k * road.lane_width
                paint.strip(xy, heading_rad, o - lw / 2, o + lw / 2, white, dashes)
        edge = road.lanes_each_way * road.lane_width
        for side in (-1.0, 1.0):
            o = side * (edge + (0.0 if road.parking else -0.3))
            paint.strip(xy, heading_rad, o - lw / 2, o + lw / 2, white)
    # Crosswalks a few metres before each intersection.
    for corner, h_in, h_out in path.intersections:
        for hd, sgn in ((h_in, -1.0), (h_out, 1.0)):
            f = np.array([math.sin(hd), math.cos(hd)])
            r = np.array([math.cos(hd), -math.sin(hd)])
            c = corner + f * sgn * (outer + 3.0)
            for o in np.arange(-hw + 0.5, hw - 0.3, 1.0):
                p = c + r * o
                paint.poly(np.array([p - f * 1.5, p + r * 0.5 - f * 1.5, p + r * 0.5 + f * 1.5, p + f * 1.5]),
                           white)

    # Mottling and wear over everything, a band of rows at a time to bound memory.
    band = 256 * up
    for r0 in range(0, h, band):
        tile_rows = var_tiles[r0 // up: r0 // up + 256]
        mod8 = cv2.resize(tile_rows, (tile_rows.shape[1] * up, tile_rows.shape[0] * up),
                          interpolation=cv2.INTER_LINEAR)[: min(band, h - r0), :w]
        rows = img[r0:r0 + mod8.shape[0]]
        cv2.multiply(rows, cv2.merge([mod8, mod8, mod8]), dst=rows, scale=1.0 / 128.0)
    return GroundMap((float(lo[0]), float(lo[1])), res, img, float3(base_rgb[::-1]))


# ---------------------------------------------------------------------------------------------
# Objects and the random layout


BUILDING_RGB = [
    (0.45, 0.40, 0.32), (0.55, 0.52, 0.45), (0.30, 0.28, 0.26), (0.35, 0.18, 0.12),
    (0.42, 0.25, 0.16), (0.60, 0.58, 0.55), (0.25, 0.26, 0.28), (0.50, 0.42, 0.28),
    (0.38, 0.40, 0.42), (0.52, 0.36, 0.30), (0.40, 0.45, 0.40), (0.58, 0.50, 0.38),
]
CAR_RGB = [
    (0.6, 0.6, 0.6), (0.02, 0.02, 0.02), (0.35, 0.36, 0.38), (0.45, 0.03, 0.03), (0.03, 0.08, 0.35),
    (0.15, 0.15, 0.16), (0.55, 0.55, 0.50), (0.08, 0.20, 0.10), (0.50, 0.35, 0.05), (0.70, 0.70, 0.70),
]


class _Occupancy:
    """A coarse top-down grid of what is taken, to keep footprints apart."""

    def __init__(self, lo, hi, res: float = 0.25) -> None:
        self.lo, self.res = np.asarray(lo, dtype=np.float64), res
        w = int(math.ceil((hi[0] - lo[0]) / res)) + 1
        h = int(math.ceil((hi[1] - lo[1]) / res)) + 1
        self.grid = np.zeros((h, w), np.uint8)

    def _px(self, poly) -> np.ndarray:
        return np.round((np.asarray(poly) - self.lo) / self.res * 8).astype(np.int32)

    def free(self, poly, pad: float = 0.3) -> bool:
        poly = np.asarray(poly, dtype=np.float64)
        c = poly.mean(axis=0)
        d = poly - c
        n = np.linalg.norm(d, axis=1, keepdims=True)
        grown = c + d * (n + pad) / np.maximum(n, 1e-9)
        px = self._px(grown)
        x0, y0 = np.maximum(px.min(axis=0) // 8 - 1, 0)
        x1, y1 = px.max(axis=0) // 8 + 2
        if x1 <= 0 or y1 <= 0 or x0 >= self.grid.shape[1] or y0 >= self.grid.shape[0]:
            return False
        x1, y1 = min(x1, self.grid.shape[1]), min(y1, self.grid.shape[0])
        test = np.zeros((y1 - y0, x1 - x0), np.uint8)
        cv2.fillConvexPoly(test, px - np.array([x0, y0]) * 8, 1, cv2.LINE_8, 3)
        return not np.any(test & self.grid[y0:y1, x0:x1])

    def take(self, poly) -> None:
        cv2.fillConvexPoly(self.grid, self._px(poly), 1, cv2.LINE_8, 3)

    def take_strip(self, xy, heading, lat0, lat1) -> None:
        nrm = _normals(heading)
        a, b = xy + lat0 * nrm, xy + lat1 * nrm
        for i in range(len(xy) - 1):
            self.take(np.array([a[i], a[i + 1], b[i + 1], b[i]]))


def _box_footprint(c, yaw, width, length) -> np.ndarray:
    f = np.array([math.sin(yaw), math.cos(yaw)])
    r = np.array([math.cos(yaw), -math.sin(yaw)])
    return np.array([c - r * width / 2 - f * length / 2, c + r * width / 2 - f * length / 2,
                     c + r * width / 2 + f * length / 2, c - r * width / 2 + f * length / 2])


def _mat(rgb, rng: np.random.Generator, jitter: float = 0.1, contrast: float = 0.15,
         windows: WindowPattern | None = None) -> Material:
    rgb = np.clip(np.asarray(rgb) * (1.0 + rng.uniform(-jitter, jitter, 3)) * rng.uniform(0.85, 1.15), 0.01, 0.9)
    return Material(float3(rgb), contrast, windows)


def make_building(rng: np.random.Generator, c, yaw, width, length, height) -> SceneObject:
    wall = rng.choice(len(BUILDING_RGB))
    glass = np.array([0.04, 0.05, 0.06]) * rng.uniform(0.6, 2.0) * rng.uniform(0.85, 1.15, 3)
    win = WindowPattern(
        spacing_m=(float(rng.uniform(2.4, 4.5)), float(rng.uniform(2.8, 3.6))),
        size_frac=(float(rng.uniform(0.35, 0.75)), float(rng.uniform(0.4, 0.65))),
        ground_floor_m=float(rng.uniform(3.0, 4.5)),
        glass_rgb=float3(glass),
    )
    wall_mat = _mat(BUILDING_RGB[wall], rng, contrast=float(rng.uniform(0.08, 0.3)),
                    windows=win if rng.random() < 0.9 else None)
    roof = _mat((0.15, 0.14, 0.13), rng)
    return SceneObject("building", [box_solid(c, yaw, width, length, 0.0, height, [wall_mat] * 4 + [roof] * 2)])


def make_tree(rng: np.random.Generator, c, crown_r: float, height: float) -> SceneObject:
    crown_v = crown_r * rng.uniform(0.9, 1.6)
    z_bottom = max(height - 2 * crown_v, 2.2)
    trunk_r = rng.uniform(0.12, 0.25)
    trunk = box_solid(c, rng.uniform(0, math.pi), 2 * trunk_r, 2 * trunk_r, 0.0, z_bottom,
                      _mat((0.12, 0.09, 0.06), rng, contrast=0.3))
    green = np.array([0.05, 0.10, 0.03]) * rng.uniform(0.7, 1.5) * rng.uniform(0.85, 1.2, 3)
    crown = ellipsoid_solid((c[0], c[1], z_bottom + crown_v), (crown_r, crown_v),
                            Material(float3(green), contrast=0.6),
                            n_lon=int(rng.choice([6, 8])), n_lat=4)
    return SceneObject("tree", [trunk, crown])


def make_car(rng: np.random.Generator, c, yaw) -> SceneObject:
    length, width = rng.uniform(3.8, 4.9), rng.uniform(1.65, 1.9)
    body_top = rng.uniform(0.85, 1.05)
    cabin_top = body_top + rng.uniform(0.4, 0.6)
    paint = _mat(CAR_RGB[rng.choice(len(CAR_RGB))], rng, jitter=0.05, contrast=0.04)
    glass = Material((0.03, 0.035, 0.04), 0.05)
    tyre = Material((0.025, 0.025, 0.025), 0.1)
    f = np.array([math.sin(yaw), math.cos(yaw)])
    tyres = box_solid(c, yaw, width - 0.08, length - 0.9, 0.0, 0.32, tyre)
    body = box_solid(c, yaw, width, length, 0.32, body_top, paint)
    cab_len = length * rng.uniform(0.45, 0.6)
    cabin = box_solid(c - f * length * 0.08, yaw, width * 0.88, cab_len, body_top, cabin_top,
                      [glass, glass, glass, glass, paint, paint])
    return SceneObject("car", [tyres, body, cabin], _box_footprint(c, yaw, width, length))


def make_pole(rng: np.random.Generator, c, yaw_to_road: float, kind: str = "lamp") -> SceneObject:
    metal = _mat((0.25, 0.25, 0.25), rng, contrast=0.1) if rng.random() < 0.7 else _mat((0.2, 0.13, 0.07), rng)
    if kind == "sign":
        h = rng.uniform(2.0, 2.6)
        post = box_solid(c, yaw_to_road, 0.07, 0.07, 0.0, h, metal)
        colour = [(0.5, 0.03, 0.03), (0.02, 0.1, 0.4), (0.5, 0.42, 0.05), (0.5, 0.5, 0.5)][rng.choice(4)]
        side = rng.uniform(0.5, 0.8)
        plate = box_solid(c, yaw_to_road + math.pi / 2, side, 0.04, h, h + side, _mat(colour, rng, contrast=0.05))
        return SceneObject("sign", [post, plate])
    h = rng.uniform(6.0, 10.0)
    thick = rng.uniform(0.14, 0.3)
    pole = box_solid(c, yaw_to_road, thick, thick, 0.0, h - 0.3, metal)
    # The lamp head reaches over the kerb, toward the road.
    d = np.array([math.sin(yaw_to_road), math.cos(yaw_to_road)])
    arm = rng.uniform(0.6, 1.8)
    head = box_solid(c + d * (arm / 2), yaw_to_road, 0.35, arm + thick, h - 0.3, h, metal)
    return SceneObject("pole", [pole, head])


def make_wall(rng: np.random.Generator, c, yaw, length, height) -> SceneObject:
    rgb = [(0.4, 0.38, 0.35), (0.35, 0.2, 0.14), (0.1, 0.16, 0.06), (0.5, 0.5, 0.48)][rng.choice(4)]
    return SceneObject("wall", [box_solid(c, yaw, rng.uniform(0.25, 0.6), length, 0.0, height,
                                          _mat(rgb, rng, contrast=0.25))])


@dataclass
class Scene:
    """Ground plus objects, and the noise tile every texture samples."""

    ground: GroundMap
    objects: list[SceneObject]
    noise: np.ndarray  # (256, 256) float32 in [0, 1], tileable


@dataclass(frozen=True)
class LayoutStyle:
    """Per-drive knobs of the random layout."""

    urban: float = 0.7  # 0 open country .. 1 dense city
    trees: float = 0.5  # density of street trees
    parked_cars: float = 0.5
    oncoming_cars: float = 0.3
    poles: float = 0.7


def random_scene(rng: np.random.Generator, path: RoadPath, road: RoadSpec, camera_lateral: float,
                 style: LayoutStyle | None = None, ground_type: str | None = None) -> Scene:
    """Lay out buildings, trees, poles, signs, walls and cars along ``path``.

    ``camera_lateral`` is the camera's offset from the centreline (right positive); a corridor
    around it stays free of every footprint.
    """
    style = style or LayoutStyle()
    if ground_type is None:
        ground_type = str(rng.choice(["paving", "gravel"] if style.urban > 0.6 else list(GROUND_TYPES)))
    ground = paint_ground(rng, path, road, ground_type)
    lo = np.asarray(ground.origin_xy)
    hi = lo + np.array(ground.albedo.shape[1::-1]) * ground.res_m
    occ = _Occupancy(lo, hi)  # footprints taken
    corridor = _Occupancy(lo, hi)  # where the camera drives
    corridor.take_strip(path.xy, path.heading, camera_lateral - 1.8, camera_lateral + 1.8)
    roadway = _Occupancy(lo, hi)  # road and sidewalks: no buildings or walls there
    roadway.take_strip(path.xy, path.heading, -road.outer - 0.3, road.outer + 0.3)
    for corner, h_in, h_out in path.intersections:
        for hd, sgn in ((h_in, 1.0), (h_out, -1.0)):
            d = np.array([math.sin(hd), math.cos(hd)]) * sgn
            pts = np.array([corner + d * t for t in np.linspace(0.0, 60.0, 10)])
            roadway.take_strip(pts, np.full(len(pts), math.atan2(d[0], d[1])), -road.outer - 0.3, road.outer + 0.3)

    objects: list[SceneObject] = []

    def place(obj: SceneObject, *, on_road: bool = False, pad: float = 0.3) -> bool:
        fp = obj.footprint
        if not corridor.free(fp, 0.0) or not occ.free(fp, pad):
            return False
        if not on_road and not roadway.free(fp, 0.0):
            return False
        occ.take(fp)
        objects.append(obj)
        return True

    hw, outer = road.half_width, road.outer
    # Buildings: rows along each side, a second row behind, in blocks that come and go.
    for side in (-1.0, 1.0):
        s = rng.uniform(-10.0, 5.0)
        urban_here = style.urban
        while s < path.length:
            if rng.random() < 0.15:  # the character of the street changes every few blocks
                urban_here = float(np.clip(style.urban + rng.uniform(-0.4, 0.4), 0.0, 1.0))
            length = rng.uniform(8.0, 32.0)
            gap = rng.uniform(0.0, 4.0) if rng.random() < urban_here else rng.uniform(6.0, 30.0)
            if rng.random() < 0.25 + 0.7 * urban_here:
                p, hd, _ = path.at(s + length / 2)
                depth = rng.uniform(8.0, 22.0)
                setback = rng.uniform(0.0, 2.0) if rng.random() < urban_here else rng.uniform(2.0, 12.0)
                height = (rng.uniform(8.0, 30.0) if rng.random() < urban_here else rng.uniform(3.5, 10.0))
                nrm = np.array([math.cos(hd), -math.sin(hd)])
                for row in range(2 if rng.random() < urban_here else 1):
                    off = outer + setback + depth / 2 + row * (depth + rng.uniform(3.0, 15.0))
                    c = p + side * nrm * off
                    h_row = height * (rng.uniform(0.8, 1.8) if row else 1.0)
                    place(make_building(rng, c, hd + rng.normal(0, 0.03), depth, length, h_row), pad=0.5)
            elif rng.random() < 0.3:
                p, hd, _ = path.at(s + length / 2)
                nrm = np.array([math.cos(hd), -math.sin(hd)])
                c = p + side * nrm * (outer + rng.uniform(0.3, 3.0))
                place(make_wall(rng, c, hd, length, rng.uniform(0.8, 2.2)))
            s += length + gap
    # Street trees, lamps and signs along the sidewalks.
    for side in (-1.0, 1.0):
        s = rng.uniform(0.0, 10.0)
        while s < path.length:
            s += rng.uniform(6.0, 16.0)
            p, hd, _ = path.at(s)
            nrm = np.array([math.cos(hd), -math.sin(hd)])
            u = rng.random()
            if u < style.trees * 0.7:
                r = rng.uniform(1.2, 3.2)
                lat = hw + (road.sidewalk * rng.uniform(0.4, 0.7) if road.sidewalk > 2.0 else road.sidewalk + r)
                place(make_tree(rng, p + side * nrm * lat, r, rng.uniform(5.0, 12.0)), on_road=True)
            elif u < style.trees * 0.7 + style.poles * 0.3:
                yaw_to_road = hd + (-math.pi / 2 if side > 0 else math.pi / 2)
                kind = "sign" if rng.random() < 0.3 else "lamp"
                place(make_pole(rng, p + side * nrm * (hw + 0.45), yaw_to_road, kind), on_road=True)
    # Trees and sheds in the open, beyond the street.
    n_open = int(rng.uniform(0, 60) * (1.0 - style.urban) + 10)
    span = hi - lo
    for _ in range(n_open):
        c = lo + rng.uniform(0.1, 0.9, 2) * span
        if rng.random() < 0.8:
            place(make_tree(rng, c, rng.uniform(1.5, 4.0), rng.uniform(5.0, 14.0)))
        else:
            place(make_building(rng, c, rng.uniform(0, 2 * math.pi), rng.uniform(4, 12), rng.uniform(4, 15),
                                rng.uniform(2.5, 7.0)))
    # Cars: parked at the kerb, and standing in the other direction's lanes.
    lane_side = 1.0 if road.right_hand else -1.0
    for side in (-1.0, 1.0):
        s = rng.uniform(0.0, 8.0)
        lat = hw - 1.1 if road.parking else hw - 0.9
        while s < path.length:
            s += rng.uniform(5.0, 9.0)
            if rng.random() < style.parked_cars:
                p, hd, k = path.at(s)
                if abs(k) > 1 / 50:
                    continue
                nrm = np.array([math.cos(hd), -math.sin(hd)])
                yaw = hd if side == lane_side else hd + math.pi
                place(make_car(rng, p + side * nrm * lat, yaw + rng.normal(0, 0.03)), on_road=True, pad=0.2)
    n_other = int(style.oncoming_cars * path.length / 20)
    for _ in range(n_other):
        s = rng.uniform(0.0, path.length)
        p, hd, _ = path.at(s)
        nrm = np.array([math.cos(hd), -math.sin(hd)])
        lane = rng.integers(road.lanes_each_way)
        lat = -lane_side * (lane + 0.5) * road.lane_width
        place(make_car(rng, p + nrm * lat, hd + math.pi + rng.normal(0, 0.02)),
              on_road=True, pad=1.0)
    return Scene(ground=ground, objects=objects, noise=fractal_noise(rng, 256, beta=1.2))
