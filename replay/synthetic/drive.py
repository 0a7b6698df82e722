"""A synthetic drive: a random street, a sun, a vehicle trajectory along it, and the Frame stream.

Everything random about a drive is drawn when the drive is made, from streams of the seed:
``default_rng([seed, 0])`` the parameters (sun, road, camera), ``[seed, 1]`` the road and the
trajectory, ``[seed, 2]`` the layout; frame k's sensor noise from ``[seed, 3, k]``. The same seed
gives the same images, whichever frames are rendered and in whatever order (auto-exposure is the
one thing carried from frame to frame, as on a real camera).
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, replace
from datetime import UTC, datetime

import numpy as np

from replay.synthetic.camera import Camera, CameraEffects
from replay.synthetic.render import CameraPose, Renderer
from replay.synthetic.scene import LayoutStyle, RoadPath, RoadSpec, Scene, random_path, random_scene
from replay.synthetic.sky import PreethamSky
from rig.errors import ValidationError
from rig.geometry import enu_from_az_el
from rig.types import Attitude, Frame, HeadingRef, Intrinsics

KITTI_INTRINSICS = Intrinsics(fx=721.5377, fy=721.5377, cx=609.5593, cy=172.854, width=1242, height=375)
SUN_ELEVATION_RANGE_DEG = (5.0, 75.0)
CAMERA_HEIGHT_M = 1.65  # KITTI's colour cameras


def kitti_intrinsics(scale: float = 1.0) -> Intrinsics:
    """KITTI image_02 intrinsics, optionally scaled (0.25 gives 310x94 with the same view)."""
    if not (math.isfinite(scale) and scale > 0):  # 0 gave a 1 x 1 px camera without a word
        raise ValidationError(f"kitti_intrinsics: expected a scale > 0, got {scale}")
    if scale == 1.0:
        return KITTI_INTRINSICS
    from replay.synthetic.render import scaled_intrinsics

    return scaled_intrinsics(KITTI_INTRINSICS, scale)


@dataclass(frozen=True)
class DriveParams:
    """Everything a seed decides about a drive, apart from the layout itself."""

    sun_azimuth_rad: float
    sun_elevation_rad: float
    turbidity: float
    sun_visibility: float  # direct sun dimmed by cloud, 1 = clear
    cloud_cover: float
    road: RoadSpec
    style: LayoutStyle
    metres_per_frame: float
    lane_offset_m: float  # camera right of the centreline
    camera_height_m: float
    pitch_bias_rad: float
    roll_bias_rad: float
    jitter_rad: float  # amplitude of the slow pitch/roll sway
    yaw_jitter_rad: float
    fog_m: float
    effects: CameraEffects
    utc_start_ns: int

    @property
    def sun_enu(self) -> np.ndarray:
        return enu_from_az_el(self.sun_azimuth_rad, self.sun_elevation_rad)


def sample_params(rng: np.random.Generator) -> DriveParams:
    el_lo, el_hi = SUN_ELEVATION_RANGE_DEG
    lanes = 1 if rng.random() < 0.6 else 2
    road = RoadSpec(
        lanes_each_way=lanes,
        lane_width=float(rng.uniform(3.0, 3.7)),
        parking=bool(rng.random() < 0.4),
        sidewalk=float(rng.uniform(1.5, 4.5)),
        right_hand=bool(rng.random() < 0.75),
    )
    lane = int(rng.integers(lanes))
    side = 1.0 if road.right_hand else -1.0
    clear = rng.random() < 0.7
    start = datetime(2010, 1, 1, tzinfo=UTC).timestamp() + rng.uniform(0, 15 * 365.25 * 86400)
    return DriveParams(
        sun_azimuth_rad=float(rng.uniform(0.0, 2 * math.pi)),
        sun_elevation_rad=math.radians(float(rng.uniform(el_lo, el_hi))),
        turbidity=float(rng.uniform(2.0, 6.0)),
        sun_visibility=1.0 if clear else float(rng.uniform(0.35, 1.0)),
        cloud_cover=0.0 if rng.random() < 0.4 else float(rng.uniform(0.05, 0.6 if clear else 0.8)),
        road=road,
        style=LayoutStyle(
            urban=float(rng.uniform(0.0, 1.0)),
            trees=float(rng.uniform(0.1, 1.0)),
            parked_cars=float(rng.uniform(0.0, 0.8)),
            oncoming_cars=float(rng.uniform(0.0, 0.6)),
            poles=float(rng.uniform(0.3, 1.0)),
        ),
        metres_per_frame=float(rng.uniform(2.0, 5.0)),
        lane_offset_m=side * (lane + 0.5) * road.lane_width + float(rng.normal(0.0, 0.2)),
        camera_height_m=CAMERA_HEIGHT_M + float(rng.uniform(-0.15, 0.15)),
        pitch_bias_rad=math.radians(float(np.clip(rng.normal(0.0, 0.8), -2.0, 2.0))),
        roll_bias_rad=math.radians(float(np.clip(rng.normal(0.0, 0.5), -1.5, 1.5))),
        jitter_rad=math.radians(float(rng.uniform(0.3, 1.2))),
        yaw_jitter_rad=math.radians(float(rng.uniform(0.1, 0.8))),
        fog_m=float(rng.uniform(600.0, 4000.0)),
        effects=CameraEffects.random(rng),
        utc_start_ns=int(start * 1e9),
    )


def _sway(rng: np.random.Generator, n: int, amplitude: float) -> np.ndarray:
    """Smooth random motion over n frames: a few sinusoids plus a little frame-to-frame shake."""
    k = np.arange(n, dtype=np.float64)
    out = np.zeros(n)
    for _ in range(3):
        period = rng.uniform(4.0, 30.0)
        out += rng.uniform(0.3, 1.0) * np.sin(2 * math.pi * k / period + rng.uniform(0, 2 * math.pi))
    out *= amplitude / 1.5
    return out + rng.normal(0.0, 0.15 * amplitude, n)


def trajectory(rng: np.random.Generator, path: RoadPath, s0: float, n_frames: int, p: DriveParams) -> list[CameraPose]:
    """Camera poses along the path: slower in tight corners, swaying a little in pitch and roll."""
    s = s0
    poses = []
    pitch = _sway(rng, n_frames, p.jitter_rad) + p.pitch_bias_rad
    roll = _sway(rng, n_frames, p.jitter_rad * 0.7) + p.roll_bias_rad
    yaw = _sway(rng, n_frames, p.yaw_jitter_rad)
    wander = _sway(rng, n_frames, 0.25)
    for k in range(n_frames):
        xy, hd, kappa = path.at(s)
        right = np.array([math.cos(hd), -math.sin(hd)])
        pos = xy + right * (p.lane_offset_m + wander[k])
        poses.append(CameraPose((float(pos[0]), float(pos[1]), p.camera_height_m), float(hd + yaw[k]),
                                float(pitch[k]), float(roll[k])))
        speed = p.metres_per_frame * float(np.clip(math.sqrt(1.0 / max(abs(kappa), 1e-6) / 40.0), 0.5, 1.0))
        s += speed * float(rng.uniform(0.9, 1.1))
    return poses


@dataclass(frozen=True)
class DrivePlan:
    """What a drive is before anything is rendered: its parameters, road and camera poses."""

    seed: int
    params: DriveParams
    path: RoadPath
    poses: list[CameraPose]


def plan_drive(seed: int, n_frames: int, **overrides) -> DrivePlan:
    """Parameters, road and poses of drive ``seed`` (cheap: no scene, no rendering).

    Parameters, trajectory and layout draw from separate streams of the seed, so overriding a
    parameter (say the sun) leaves the rest of the drive as it was.
    """
    if n_frames < 1:
        raise ValueError(f"plan_drive: expected n_frames >= 1, got {n_frames}")
    params = sample_params(np.random.default_rng([seed, 0]))
    p = replace(params, **overrides) if overrides else params
    rng = np.random.default_rng([seed, 1])
    path, s0 = random_path(rng, p.metres_per_frame * n_frames, p.road)
    return DrivePlan(int(seed), p, path, trajectory(rng, path, s0, n_frames, p))


class Drive:
    """One synthetic drive. Iterate it (or call :meth:`frames`) for its Frames.

    ``render_scale`` renders at that fraction of the intrinsics' size and upsamples before the
    camera adds noise (0.5 is ~3x faster than 1.0 and hard to tell apart after JPEG);
    ``effects`` overrides the camera (e.g. ``CameraEffects.ideal()`` for tests); keyword
    ``overrides`` replace fields of the sampled :class:`DriveParams` (e.g. ``sun_elevation_rad``).
    """

    def __init__(self, seed: int, n_frames: int, *, intrinsics: Intrinsics | None = None, fps: float = 10.0,
                 render_scale: float = 0.5, effects: CameraEffects | None = None, **overrides) -> None:
        if not fps > 0:
            raise ValueError(f"Drive: expected fps > 0, got {fps}")
        if effects is not None:
            overrides["effects"] = effects
        plan = plan_drive(seed, n_frames, **overrides)
        self.seed = plan.seed
        self.n_frames = int(n_frames)
        self.fps = float(fps)
        self.intrinsics = intrinsics or KITTI_INTRINSICS
        self.params, self.path, self.poses = plan.params, plan.path, plan.poses
        p = self.params
        rng = np.random.default_rng([self.seed, 2])
        self.scene: Scene = random_scene(rng, self.path, p.road, p.lane_offset_m, p.style)
        self.sky = PreethamSky(p.sun_enu, p.turbidity, sun_visibility=p.sun_visibility, cloud_cover=p.cloud_cover)
        self.sun_enu = self.sky.sun_enu.copy()
        self.sun_enu.setflags(write=False)
        self.renderer = Renderer(self.scene, self.sky, self.intrinsics, render_scale=render_scale, fog_m=p.fog_m)

    def render_frame(self, k: int, camera: Camera) -> np.ndarray:
        """Frame k's image through ``camera`` (whose exposure state carries over between calls)."""
        out = self.renderer.render(self.poses[k])
        return camera.capture(out.radiance, np.random.default_rng([self.seed, 3, k]))

    def frames(self) -> Iterator[Frame]:
        camera = Camera(self.params.effects, self.intrinsics.width, self.intrinsics.height, seed=self.seed)
        for k, pose in enumerate(self.poses):
            image = self.render_frame(k, camera)
            t = k / self.fps
            yield Frame(
                t_mono_s=t,
                seq=k,
                image_bgr=image,
                intrinsics=self.intrinsics,
                attitude=Attitude(pose.heading_rad, HeadingRef.TRUE, pose.pitch_rad, pose.roll_rad),
                utc_ns=self.params.utc_start_ns + int(round(t * 1e9)),
                gnss=None,
                sun_enu_truth=self.sun_enu,
            )

    __iter__ = frames


def synth_drive(seed: int, n_frames: int, *, intrinsics: Intrinsics | None = None, fps: float = 10.0,
                render_scale: float = 0.5) -> Iterator[Frame]:
    """The Frames of the synthetic drive ``seed``: ``t_mono_s = k / fps``, ``seq = k``, true
    heading with pitch and roll, a UTC time, and the drive's sun as ``sun_enu_truth``."""
    return Drive(seed, n_frames, intrinsics=intrinsics, fps=fps, render_scale=render_scale).frames()
