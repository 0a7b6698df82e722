"""Heading from the images alone: monocular visual odometry, yaw relative to the start.

For a rig without an IMU or GNSS compass the camera itself can say how it turned. This is the
classic two-view pipeline in OpenCV:

- Shi-Tomasi corners (``cv2.goodFeaturesToTrack``) in a keyframe, tracked frame to frame with
  pyramidal Lucas-Kanade optical flow and a forward-backward check (a point that does not track
  back to where it came from is dropped: occlusions, moving cars, repeated texture). None in the
  bottom quarter of the image by default: the road just ahead streams fast and repeats (lane
  dashes), and tracks there lock onto the next dash, all agreeing on a wrong motion.
- Between the keyframe and the current frame, the rotation: the essential matrix with RANSAC
  (``cv2.findEssentialMat``) and ``cv2.recoverPose``. When the scene shows no translation
  parallax (the rig turns on the spot, or sees only far things) the essential matrix is
  degenerate, so a rotation-only fit of the bearing vectors (Kabsch) is used instead; which one
  applies is decided by how well a pure rotation explains the point motion.
- Sharp turns move everything tens of pixels between frames: each track starts at the dominant
  shift of the whole image (``cv2.phaseCorrelate``), which also gives a coarse turn (far things
  move by about fx * tan(turn)).
- A narrow view cannot tell a turn with forward motion from a larger turn with sideways motion
  when the tracks are noisy; RANSAC picks either. A motion prior (the rig keeps its direction of
  travel, learnt slowly) picks between the two, and a fit that disagrees with both the coarse
  turn and the rotation-only fit is refused.
- The yaw change is the turn of the optical axis about the camera's vertical axis (the camera is
  assumed level: pitch and roll of a few degrees change the yaw by a second-order amount),
  clockwise from above positive like every heading here. It is added to the keyframe's heading;
  a frame becomes the next keyframe when its features moved far enough (parallax) or too few
  are left.

The heading is :attr:`HeadingRef.RELATIVE`, 0 at the first frame, and drifts: every keyframe adds
its rotation error (``benchmarks/bench_vo.py`` measures the drift per 100 m on synthetic drives).
When tracking is lost (too few points, a failed or refused fit) the frame gets no heading and
odometry restarts from it, carrying over the rough turn (image shift or rotation-only fit) where
there is one: its error goes into the drift. Where there is none (a featureless or dark stretch),
across a gap in the frames, or across a change of camera mode, no turn can be carried: the heading
starts again at 0 in a new epoch. ``stats`` counts each case; ``docs/drivers.md`` states it.

:class:`VisualOdometry` is pure (an image and a time in, a heading sample out, no clock, no I/O);
:func:`with_visual_heading` attaches its heading to a frame stream.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from drivers.nmea import HeadingSample
from rig.errors import ValidationError
from rig.geometry import wrap_pi
from rig.types import Frame, HeadingRef, Intrinsics

SOURCE_NAME = "visual"  # HeadingSample.source_sentence of visual odometry samples
_ESTIMATORS = {"magsac": cv2.USAC_MAGSAC, "ransac": cv2.RANSAC, "lmeds": cv2.LMEDS}  # robust fits of E


@dataclass(frozen=True)
class VoConfig:
    """Tuning of :class:`VisualOdometry`. Pixel sizes are in the (possibly downscaled) working image."""

    max_width_px: int = 640  # wider images are downscaled first: the cost is per pixel, the yaw is not
    max_features: int = 500
    quality_level: float = 0.005  # Shi-Tomasi: relative to the strongest corner; low, since scenes can be flat
    min_distance_px: float = 7.0
    ignore_below: float = 0.75  # no features below this fraction of the image height (1: use it all)
    lk_window_px: int = 21
    lk_levels: int = 3  # pyramid levels: about 2**levels * window / 2 px of motion per frame
    lk_min_eig: float = 1e-4  # Lucas-Kanade drops a window whose gradients are weaker than this (OpenCV's default)
    fb_max_px: float = 1.0  # forward-backward error above which a track is dropped
    keyframe_parallax_px: float = 12.0  # median feature motion since the keyframe that makes a new one
    refresh_fraction: float = 0.3  # a new keyframe also when fewer than this share of its points are left
    min_points: int = 25  # fewer tracked points: tracking is lost
    min_inliers: int = 15  # fewer RANSAC inliers: the fit is not trusted
    ransac_px: float = 1.0  # RANSAC threshold of the essential matrix
    ransac: str = "magsac"  # magsac (cv2.USAC_MAGSAC), ransac or lmeds
    predict: bool = True  # start each track at the image's dominant shift (phase correlation)
    prior: bool = True  # prefer the pose that keeps the rig's usual direction of travel (see _with_prior)
    prior_margin: float = 0.1  # ... unless RANSAC's pose has a robust cost this much lower
    prior_rate: float = 0.1  # how fast the prior direction of travel follows the fits
    normalize: bool = True  # equalise mean and contrast of each image before tracking
    still_px: float = 0.3  # median motion below this: the camera did not move, no fit needed
    rotation_only_px: float = 0.8  # a pure rotation explains the motion this well (median px) ...
    rotation_only_frac: float = 0.1  # ... or to this fraction of the motion: no usable translation parallax
    max_step_rad: float = math.radians(45.0)  # a larger turn between two frames is taken as a failed fit
    shift_min_response: float = 0.05  # phase correlation peak below this: no usable image shift
    # The image shift is a rough turn only over an interval in which the vehicle cannot turn the view
    # by more than shift_max_frac of the image width at max_yaw_rate (see _shift_measures_turn).
    max_yaw_rate_rad_s: float = math.radians(120.0)  # the synthetic drives' sharpest corners (a car: rarely 40)
    # Measured on synthetic drives: a shift is > 5 deg off 1 time in 6 up to 15 % of the width, 1 in 4
    # at 15-25 %, 1 in 2 beyond 30 %.
    shift_max_frac: float = 0.2
    min_contrast: float = 2.0  # grey-level std below this: a featureless image (black, a covered lens), no shift
    coarse_tol_rad: float = math.radians(3.0)  # a fit further than this from the coarse image-shift yaw ...
    coarse_tol_frac: float = 0.5  # ... and than this fraction of it is rejected
    max_gap_s: float = 1.0  # frames further apart: the turn between them is unknown, a new epoch starts

    def __post_init__(self) -> None:
        for name in ("max_width_px", "max_features", "lk_window_px", "lk_levels", "min_points", "min_inliers"):
            if int(getattr(self, name)) < 1:
                raise ValidationError(f"VoConfig.{name}: expected a positive integer, got {getattr(self, name)!r}")
        if not 0.0 < self.refresh_fraction < 1.0:
            raise ValidationError(f"VoConfig.refresh_fraction: expected within (0, 1), got {self.refresh_fraction}")
        if not (math.isfinite(self.max_gap_s) and self.max_gap_s > 0):
            raise ValidationError(f"VoConfig.max_gap_s: expected a number of seconds > 0, got {self.max_gap_s!r}")
        if not (math.isfinite(self.max_yaw_rate_rad_s) and self.max_yaw_rate_rad_s > 0):
            raise ValidationError(f"VoConfig.max_yaw_rate_rad_s: expected a rate in rad/s > 0, got "
                                  f"{self.max_yaw_rate_rad_s!r}")
        if not 0.0 < self.shift_max_frac <= 1.0:
            raise ValidationError(f"VoConfig.shift_max_frac: expected a share of the width within (0, 1], got "
                                  f"{self.shift_max_frac!r}")
        if not (math.isfinite(self.min_contrast) and self.min_contrast >= 0):
            raise ValidationError(f"VoConfig.min_contrast: expected grey levels >= 0, got {self.min_contrast!r}")
        if self.ransac not in _ESTIMATORS:
            raise ValidationError(f"VoConfig.ransac: expected one of {', '.join(_ESTIMATORS)}, got {self.ransac!r}")


def yaw_from_rotation(r_cur_from_key: np.ndarray) -> float:
    """Heading change (rad, clockwise from above positive) of a camera whose OpenCV frame (x right,
    y down, z forward) turned by ``r_cur_from_key`` (``x_cur = R @ x_key``, as ``cv2.recoverPose``).

    The current optical axis seen from the keyframe is ``R.T @ (0, 0, 1)``, the third row of R; its
    angle in the keyframe's horizontal (x-z) plane, towards +x (the right), is the turn.
    """
    r = np.asarray(r_cur_from_key, dtype=np.float64)
    return math.atan2(r[2, 0], r[2, 2])


def rotation_from_yaw(dpsi_rad: float) -> np.ndarray:
    """``x_cur = R @ x_key`` for a level camera that turned right by ``dpsi_rad`` (inverse of
    :func:`yaw_from_rotation`): a rotation about the camera's y (down) axis."""
    c, s = math.cos(dpsi_rad), math.sin(dpsi_rad)
    # The world turns the other way in the camera: rotation about y by -dpsi.
    return np.array([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]])


def _bearings(pts: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Unit rays (N, 3) in the camera frame of pixel points (N, 2)."""
    rays = np.column_stack([(pts[:, 0] - k[0, 2]) / k[0, 0], (pts[:, 1] - k[1, 2]) / k[1, 1], np.ones(len(pts))])
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def _project(rays: np.ndarray, k: np.ndarray) -> np.ndarray:
    z = np.where(np.abs(rays[:, 2]) < 1e-9, 1e-9, rays[:, 2])
    return np.column_stack([k[0, 0] * rays[:, 0] / z + k[0, 2], k[1, 1] * rays[:, 1] / z + k[1, 2]])


def fit_rotation(pts_key: np.ndarray, pts_cur: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation-only fit ``x_cur = R @ x_key`` of matched pixels (Kabsch on bearing vectors),
    refitted once without the points it explains worst. Returns R and each point's reprojection
    residual in pixels: small residuals everywhere mean the motion has no translation parallax."""
    b1, b2 = _bearings(pts_key, k), _bearings(pts_cur, k)
    keep = np.ones(len(b1), dtype=bool)
    r = np.eye(3)
    for _ in range(2):
        u, _s, vt = np.linalg.svd(b2[keep].T @ b1[keep])
        d = np.sign(np.linalg.det(u @ vt)) or 1.0
        r = u @ np.diag([1.0, 1.0, d]) @ vt
        resid = np.linalg.norm(_project(b1 @ r.T, k) - pts_cur, axis=1)
        # Trim moving objects and bad tracks, but never below half the points.
        keep = resid <= max(np.median(resid) * 3.0, 1.0)
        if keep.sum() < max(3, len(b1) // 2):
            break
    return r, resid


def _skew(t: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])


def sampson_px(r: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray, f_px: float) -> np.ndarray:
    """Sampson distance (first-order epipolar error) of each match under ``x2 = R x1 + t``, in
    pixels; ``x1``, ``x2``: (N, 3) normalised homogeneous image points."""
    e = _skew(t) @ r
    ex1 = x1 @ e.T
    etx2 = x2 @ e
    num = np.sum(x2 * ex1, axis=1)
    den = ex1[:, 0] ** 2 + ex1[:, 1] ** 2 + etx2[:, 0] ** 2 + etx2[:, 1] ** 2
    return f_px * num / np.sqrt(np.maximum(den, 1e-18))


def _pose(p: np.ndarray, r0: np.ndarray, t0: np.ndarray, basis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    r = cv2.Rodrigues(p[:3].reshape(3, 1))[0] @ r0
    t = t0 + basis @ p[3:]
    return r, t / np.linalg.norm(t)


def refine_pose(x1: np.ndarray, x2: np.ndarray, r0: np.ndarray, t0: np.ndarray, f_px: float,
                scale_px: float = 1.0, iterations: int = 12) -> tuple[np.ndarray, np.ndarray, float]:
    """Relative pose (R, unit t) near the start (r0, t0) that minimises the Cauchy-robust Sampson
    error (scale ``scale_px``): Levenberg-Marquardt with a numeric Jacobian over 5 parameters (a
    rotation vector and two translation-direction offsets). Local, so it stays in the basin of
    its start. Returns R, t and the robust cost, summed over the points."""
    t0 = np.asarray(t0, dtype=np.float64) / np.linalg.norm(t0)
    # Two directions orthogonal to t0: the translation moves on the sphere around it.
    helper = np.array([1.0, 0.0, 0.0]) if abs(t0[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(t0, helper)
    u /= np.linalg.norm(u)
    basis = np.column_stack([u, np.cross(t0, u)])

    def residuals(p: np.ndarray) -> np.ndarray:
        r, t = _pose(p, r0, t0, basis)
        return sampson_px(r, t, x1, x2, f_px) / scale_px

    def cost(res: np.ndarray) -> float:
        return float(np.sum(np.log1p(res**2)))

    p = np.zeros(5)
    res = residuals(p)
    best = cost(res)
    lam = 1e-3
    h = 1e-6
    for _ in range(iterations):
        w = 1.0 / (1.0 + res**2)  # IRLS weights of the Cauchy loss
        jac = np.empty((len(res), 5))
        for i in range(5):
            dp = np.zeros(5)
            dp[i] = h
            jac[:, i] = (residuals(p + dp) - res) / h
        jtw = jac.T * w
        a = jtw @ jac
        g = jtw @ res
        step = np.linalg.solve(a + lam * np.diag(np.diag(a) + 1e-12), -g)
        cand = p + step
        cres = residuals(cand)
        c = cost(cres)
        if c < best:
            p, res, best = cand, cres, c
            lam = max(lam / 10.0, 1e-7)
            if np.max(np.abs(step)) < 1e-9:
                break
        else:
            lam *= 10.0
            if lam > 1e4:
                break
    r, t = _pose(p, r0, t0, basis)
    return r, t, best


def in_front(r: np.ndarray, t: np.ndarray, x1: np.ndarray, x2: np.ndarray) -> np.ndarray:
    """Which matches triangulate in front of both cameras under ``x2 = R x1 + t`` (cheirality)."""
    a = x1 @ r.T  # z1 * a - z2 * x2 = -t, solved per point in least squares
    aa = np.sum(a * a, axis=1)
    bb = np.sum(x2 * x2, axis=1)
    ab = np.sum(a * x2, axis=1)
    at = a @ t
    bt = x2 @ t
    det = aa * bb - ab**2
    det = np.where(np.abs(det) < 1e-12, 1e-12, det)
    z1 = (-at * bb + bt * ab) / det
    z2 = (aa * bt - ab * at) / det
    return (z1 > 0) & (z2 > 0)


class VisualOdometry:
    """Heading relative to the first frame from consecutive images of one camera. Pure: no clock,
    no I/O; feed frames in time order with :meth:`update`.

    ``stats`` counts frames and keyframes; which fit gave each heading (``essential``,
    ``rotation_only``, ``still``; ``prior``: the essential fit chosen by the motion prior); frames
    without heading (``lost``), of which ``rejected`` had a fit that disagreed with both the image
    shift and the rotation-only fit; ``carried``: losses over which a rough turn was carried, and
    ``uncarried``: those with none; ``restarts`` (the intrinsics changed) and ``gaps`` (new images
    more than ``max_gap_s`` apart); ``repeated``: frames identical to the one before (a dashcam or
    stream that repeats frames), given that frame's heading and otherwise ignored, so a freeze
    longer than ``max_gap_s`` is a gap.

    A restart, a gap or an uncarried loss hides the turn made meanwhile, so the heading cannot go
    on: the frame after it starts a new epoch (:attr:`epoch`, carried by each sample) at heading 0, as the first frame
    did, and the rig never puts frames of two epochs in one window (``docs/conventions.md``).
    """

    STATS = ("frames", "keyframes", "essential", "rotation_only", "still", "prior", "lost", "rejected", "carried",
             "uncarried", "restarts", "gaps", "repeated")

    # The tracking state, set by _forget_images and each keyframe.
    _heading_key: float
    _key_pts: np.ndarray | None  # (N, 2) in the keyframe, row-aligned with _prev_pts
    _prev_pts: np.ndarray | None  # the same points in the previous frame
    _prev_gray: np.ndarray | None
    _key_count: int
    _coarse_since_key: float | None
    _t_prior: np.ndarray | None  # the rig's usual direction of travel (camera frame)

    def __init__(self, config: VoConfig | None = None, start_heading_rad: float = 0.0) -> None:
        self.config = config or VoConfig()
        self.stats = dict.fromkeys(self.STATS, 0)
        self._last_heading = float(start_heading_rad)
        self._last_t_s: float | None = None
        self.epoch = 0
        self._intrinsics: Intrinsics | None = None
        self._k = np.eye(3)
        self._scale = 1.0
        self._window: np.ndarray | None = None  # Hanning window of the phase correlation
        self._prev_flat = False  # the previous image was featureless (below min_contrast)
        self._prev_given: float | None = None  # the heading the previous frame was given (None: it had none)
        self._forget_images()

    @property
    def heading_rad(self) -> float:
        """The heading of the newest frame (wrapped to [0, 2 pi)); 0 before any."""
        return self._last_heading % (2.0 * math.pi)

    def update(self, t_mono_s: float, image_bgr: np.ndarray, intrinsics: Intrinsics) -> HeadingSample | None:
        """The heading of this frame, or None when it cannot be measured on it (see ``stats``)."""
        cfg = self.config
        self.stats["frames"] += 1
        same_camera = intrinsics == self._intrinsics
        gray: np.ndarray | None = None
        if same_camera and self._prev_gray is not None and self._prev_given is not None:
            gray, flat = self._gray(image_bgr)
            if not flat and np.array_equal(gray, self._prev_gray):
                # The previous image again (a dashcam or stream that repeats frames: 15 fps in a
                # 30 fps file, or frozen while it drops them). Same view, same heading; fitting it
                # again only adds noise. It is no new image either, so the gap rule counts from
                # the last new one: a freeze longer than max_gap_s hides a turn as a gap does.
                self.stats["repeated"] += 1
                return self._sample(t_mono_s, self._prev_given)
        restart = self._intrinsics is not None and not same_camera
        since_new_s = None if self._last_t_s is None else t_mono_s - self._last_t_s  # since the last new image
        gap = since_new_s is not None and since_new_s > cfg.max_gap_s
        self._last_t_s = t_mono_s
        if restart or gap:
            # Another camera mode, or a gap in the frames: nothing tracks across it and the turn
            # meanwhile is unknown, so this frame is the zero of a new epoch.
            self.stats["restarts" if restart else "gaps"] += 1
            self.epoch += 1
            self._last_heading = 0.0
            self._forget_images()
        if not same_camera:  # the first frame's, or a restart's (forgotten above)
            self._set_camera(intrinsics)
        if gray is None:
            gray, flat = self._gray(image_bgr)
        prev_flat, self._prev_flat = self._prev_flat, flat  # this frame is the next one's previous, on every path
        if self._prev_gray is None:
            self._new_keyframe(gray, self._last_heading)
            return self._sample(t_mono_s, self._last_heading)

        # Two featureless images phase-correlate on the Hanning window alone (a peak of response 1
        # at 0 px): that is no image shift, and a black stretch would carry it as a turn.
        shift = self._dominant_shift(gray) if cfg.predict and not (flat or prev_flat) else None
        # A coarse yaw from the shift of the whole image: far things move by fx * tan(turn).
        coarse_step = None if shift is None else -math.atan2(shift[0], self._k[0, 0])
        if self._coarse_since_key is not None:
            self._coarse_since_key = None if coarse_step is None else self._coarse_since_key + coarse_step
        # After a freeze or dropped frames in a sharp turn the view may have turned by a third of the
        # image: the correlation peak of what little overlaps is then often a wrong one (36 deg carried
        # as 1 deg in the tests), and carried it is a silent error. The shift still starts the tracks
        # (the forward-backward check catches a wrong start) and is one of the two checks of the fit
        # (without it a wrong fit after a freeze went through unchecked), but no turn to carry.
        carry_step = coarse_step
        if since_new_s is not None and not self._shift_measures_turn(since_new_s, gray):
            carry_step = None

        tracked = self._track(gray, shift)
        if tracked is None:
            self._lose(gray, carry_step)
            return None
        key_pts, cur_pts = tracked
        parallax = float(np.median(np.linalg.norm(cur_pts - key_pts, axis=1)))
        if parallax < cfg.still_px:
            self.stats["still"] += 1
            dpsi: float | None = 0.0
        else:
            dpsi, dpsi_rot = self._yaw_change(key_pts, cur_pts, parallax)
            if dpsi is not None and not self._plausible(dpsi, dpsi_rot):
                # A fit that far from both what the whole image did and what a pure rotation
                # would explain is a wrong solution (too few or badly placed points), not a
                # measurement: refuse it rather than drift by it, and carry the rotation-only turn.
                self.stats["rejected"] += 1
                self._lose(gray, self._heading_key + dpsi_rot - self._last_heading)
                return None
        if dpsi is None:
            self._lose(gray, carry_step)
            return None
        heading = self._heading_key + dpsi
        if parallax >= cfg.keyframe_parallax_px or len(cur_pts) < cfg.refresh_fraction * self._key_count:
            self._new_keyframe(gray, heading)
        else:
            self._prev_gray, self._prev_pts, self._key_pts = gray, cur_pts, key_pts
        return self._sample(t_mono_s, heading)

    # -- internals -----------------------------------------------------------------------------

    def _forget_images(self) -> None:
        self._heading_key = self._last_heading
        self._key_pts = None
        self._prev_pts = None
        self._prev_gray = None
        self._key_count = 0
        self._coarse_since_key = 0.0
        self._t_prior = None

    def _set_camera(self, intr: Intrinsics) -> None:
        self._intrinsics = intr
        self._scale = min(1.0, self.config.max_width_px / intr.width)
        s = self._scale
        self._k = np.array([[intr.fx * s, 0.0, intr.cx * s], [0.0, intr.fy * s, intr.cy * s], [0.0, 0.0, 1.0]])

    def _gray(self, image_bgr: np.ndarray) -> tuple[np.ndarray, bool]:
        """The working image, and whether it is featureless (contrast below ``min_contrast``)."""
        gray = cv2.cvtColor(np.ascontiguousarray(image_bgr), cv2.COLOR_BGR2GRAY)
        if self._scale < 1.0:
            gray = cv2.resize(gray, None, fx=self._scale, fy=self._scale, interpolation=cv2.INTER_AREA)
        mean, std = cv2.meanStdDev(gray)
        flat = float(std[0, 0]) < self.config.min_contrast
        if self.config.normalize:
            # Auto-exposure changes the gain between frames; optical flow assumes it does not.
            gain = 48.0 / max(float(std[0, 0]), 1.0)
            gray = cv2.convertScaleAbs(gray, alpha=gain, beta=128.0 - gain * float(mean[0, 0]))
        return gray, flat

    def _sample(self, t_mono_s: float, heading: float) -> HeadingSample:
        self._last_heading = heading
        self._prev_given = heading
        return HeadingSample(t_mono_s=t_mono_s, heading_rad=heading, reference=HeadingRef.RELATIVE, pitch_rad=None,
                             roll_rad=None, source_sentence=SOURCE_NAME, utc_ns=None, epoch=self.epoch)

    def _lose(self, gray: np.ndarray, carry_rad: float | None) -> None:
        """No heading for this frame; odometry starts again from it.

        ``carry_rad``: a rough turn since the previous frame (the image shift, or the rotation-only
        fit), carried over when there is one: better than none in a featureless corner, but not
        good enough to give this frame a heading.
        """
        self.stats["lost"] += 1
        self._prev_given = None
        if carry_rad is not None:
            self.stats["carried"] += 1
            self._last_heading += carry_rad
        else:
            # Not even a rough turn: what the vehicle turned since the previous frame is as unknown
            # as across a gap in the frames, so this frame is the zero of a new epoch. Going on at
            # the old heading would put frames from either side of an unseen turn in one window.
            self.stats["uncarried"] += 1
            self.epoch += 1
            self._last_heading = 0.0
        self._new_keyframe(gray, self._last_heading)

    def _new_keyframe(self, gray: np.ndarray, heading: float) -> None:
        cfg = self.config
        mask = None
        if cfg.ignore_below < 1.0:
            # The road just ahead streams fast and repeats (lane dashes, crossings): tracks there lock
            # onto the next dash and agree with each other on a wrong motion.
            mask = np.zeros(gray.shape, np.uint8)
            mask[: int(round(cfg.ignore_below * gray.shape[0]))] = 255
        pts = cv2.goodFeaturesToTrack(gray, maxCorners=cfg.max_features, qualityLevel=cfg.quality_level,
                                      minDistance=cfg.min_distance_px, blockSize=7, mask=mask)
        pts = np.zeros((0, 2), np.float32) if pts is None else pts.reshape(-1, 2).astype(np.float32)
        self._heading_key = heading
        self._prev_gray, self._prev_pts, self._key_pts = gray, pts, pts.copy()
        self._key_count = len(pts)
        self._coarse_since_key = 0.0
        self.stats["keyframes"] += 1

    def _dominant_shift(self, gray: np.ndarray) -> tuple[float, float] | None:
        """Shift of the whole image since the previous one (phase correlation), or None when the
        correlation peak is weak."""
        if self._prev_gray is None or self._prev_gray.shape != gray.shape:
            return None
        if self._window is None or self._window.shape != gray.shape:
            self._window = cv2.createHanningWindow(gray.shape[::-1], cv2.CV_32F)
        (dx, dy), response = cv2.phaseCorrelate(self._prev_gray.astype(np.float32), gray.astype(np.float32),
                                                self._window)
        return (float(dx), float(dy)) if response >= self.config.shift_min_response else None

    def _shift_measures_turn(self, interval_s: float, gray: np.ndarray) -> bool:
        """Can the image shift over ``interval_s`` be taken as a rough turn? Only while the largest
        turn the vehicle can make meanwhile (``max_yaw_rate_rad_s``) moves far things by at most
        ``shift_max_frac`` of the image width: beyond, too little of the two images overlaps for the
        correlation peak to be trusted."""
        cfg = self.config
        turn_rad = cfg.max_yaw_rate_rad_s * max(interval_s, 0.0)
        return turn_rad < math.pi / 2 and self._k[0, 0] * math.tan(turn_rad) <= cfg.shift_max_frac * gray.shape[1]

    def _track(self, gray: np.ndarray, shift: tuple[float, float] | None) -> tuple[np.ndarray, np.ndarray] | None:
        """Keyframe and current positions of the points that track forward and back, or None."""
        cfg = self.config
        prev, key_pts, prev_gray = self._prev_pts, self._key_pts, self._prev_gray
        if prev is None or key_pts is None or prev_gray is None or len(prev) < cfg.min_points:
            return None
        p0 = prev.reshape(-1, 1, 2)
        tracks: tuple[np.ndarray, np.ndarray] | None = None  # (good, cur)
        if shift is not None:
            # Start each track at the image's dominant shift: in a sharp turn everything moves
            # tens of pixels, more than the pyramid finds on its own.
            tracks = self._lk(prev_gray, gray, p0, p0 + np.asarray(shift, dtype=np.float32))
        if tracks is None or tracks[0].sum() < cfg.min_points:
            # No shift, or it misled the tracker (a repeated pattern can win the correlation).
            unguided = self._lk(prev_gray, gray, p0, None)
            if tracks is None or unguided[0].sum() > tracks[0].sum():
                tracks = unguided
        good, cur = tracks
        if good.sum() < cfg.min_points:
            return None
        return key_pts[good], cur[good]

    def _lk(self, prev_gray: np.ndarray, gray: np.ndarray, p0: np.ndarray,
            guess: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Pyramidal Lucas-Kanade from the previous image, checked by tracking back."""
        cfg = self.config
        lk: dict[str, Any] = {"winSize": (cfg.lk_window_px, cfg.lk_window_px), "maxLevel": cfg.lk_levels,
                              "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
                              "minEigThreshold": cfg.lk_min_eig}
        if guess is None:
            # Without OPTFLOW_USE_INITIAL_FLOW, nextPts is only the output buffer. Passing one, not
            # None, types the same under every cv2 stub set (4.x wanted an array, 5.x takes None).
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev_gray, gray, p0, np.empty_like(p0), **lk)
        else:
            p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev_gray, gray, p0, guess.astype(np.float32),
                                                  flags=cv2.OPTFLOW_USE_INITIAL_FLOW, **lk)
        p0r, st2, _ = cv2.calcOpticalFlowPyrLK(gray, prev_gray, p1, np.empty_like(p1), **lk)
        fb = np.linalg.norm((p0 - p0r).reshape(-1, 2), axis=1)
        h, w = gray.shape
        cur = p1.reshape(-1, 2)
        inside = (cur[:, 0] >= 0) & (cur[:, 0] < w) & (cur[:, 1] >= 0) & (cur[:, 1] < h)
        good = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < cfg.fb_max_px) & inside
        return good, cur

    def _yaw_change(self, key_pts: np.ndarray, cur_pts: np.ndarray, parallax: float) -> tuple[float | None, float]:
        """Yaw from the keyframe to now (None when no fit can be trusted), and the yaw of the
        rotation-only fit."""
        cfg = self.config
        k = self._k
        r_rot, resid = fit_rotation(key_pts, cur_pts, k)
        yaw_rot = yaw_from_rotation(r_rot)
        if float(np.median(resid)) < max(cfg.rotation_only_px, cfg.rotation_only_frac * parallax):
            # No translation parallax: E would be degenerate, while the rotation fit is exact.
            self.stats["rotation_only"] += 1
            return self._checked(yaw_rot), yaw_rot
        e, mask = cv2.findEssentialMat(key_pts, cur_pts, k, method=_ESTIMATORS[cfg.ransac], prob=0.999,
                                       threshold=cfg.ransac_px)
        if e is not None and e.shape[0] > 3:
            e = e[:3]  # the 5-point solver can return several candidates stacked; the first is the best
        if e is None or e.shape != (3, 3) or mask is None or int(mask.sum()) < cfg.min_inliers:
            return None, yaw_rot
        n_good, r, t, _mask = cv2.recoverPose(e, key_pts, cur_pts, k, mask=mask.copy())
        if n_good < cfg.min_inliers:
            return None, yaw_rot
        r, t = self._with_prior(key_pts, cur_pts, r, t.ravel(), r_rot)
        # The prior learns the rig's usual direction of travel slowly, so one wrong pick cannot
        # drag it (and the picks after it) sideways.
        d = t if self._t_prior is None else (1.0 - cfg.prior_rate) * self._t_prior + cfg.prior_rate * t
        self._t_prior = d / np.linalg.norm(d)
        self.stats["essential"] += 1
        return self._checked(yaw_from_rotation(r)), yaw_rot

    def _with_prior(self, key_pts: np.ndarray, cur_pts: np.ndarray, r_e: np.ndarray, t_e: np.ndarray,
                    r_rot: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Resolve the turn / sideways-translation ambiguity of a narrow view with a motion prior.

        With noisy tracks and a narrow field of view, a turn with forward motion and a larger turn
        with sideways motion explain the points almost equally well, and RANSAC picks either. A
        rig keeps its direction of travel, so the pose refined from (the rotation-only fit, the
        usual direction of travel) is preferred unless RANSAC's pose fits clearly better (by
        ``prior_margin``) or the preferred one puts the points behind the cameras.
        """
        cfg = self.config
        if not cfg.prior or self._t_prior is None:
            return r_e, t_e
        kinv = np.linalg.inv(self._k)
        x1 = np.column_stack([key_pts, np.ones(len(key_pts))]) @ kinv.T
        x2 = np.column_stack([cur_pts, np.ones(len(cur_pts))]) @ kinv.T
        f = float(self._k[0, 0])
        r_a, t_a, c_a = refine_pose(x1, x2, r_e, t_e, f, cfg.ransac_px)
        r_b, t_b, c_b = refine_pose(x1, x2, r_rot, self._t_prior, f, cfg.ransac_px)
        if c_b <= c_a * (1.0 + cfg.prior_margin) and in_front(r_b, t_b, x1, x2).mean() > 0.5:
            self.stats["prior"] += 1
            return r_b, t_b
        return r_a, t_a

    def _plausible(self, dpsi: float, dpsi_rot: float) -> bool:
        """Does the fitted turn agree with the coarse image shift or the rotation-only fit?"""
        cfg = self.config
        for other in (self._coarse_since_key, dpsi_rot):
            if other is None or abs(wrap_pi(dpsi - other)) <= max(cfg.coarse_tol_rad, cfg.coarse_tol_frac * abs(other)):
                return True
        return False

    def _checked(self, dpsi: float) -> float | None:
        return dpsi if abs(wrap_pi(dpsi)) <= self.config.max_step_rad else None


def with_visual_heading(frames: Iterable[Frame], vo: VisualOdometry | None = None) -> Iterator[Frame]:
    """The frames with their attitude replaced by the visual odometry heading (relative to the
    first frame), or None where tracking was lost. A heading the frames carried is dropped: one
    stream never mixes references. So is a true sun they carried (``sun_enu_truth``)."""
    vo = vo or VisualOdometry()
    for frame in frames:
        sample = vo.update(frame.t_mono_s, frame.image_bgr, frame.intrinsics)
        # The truth is in true-north ENU; this stream's world has its "north" at the start heading,
        # so the truth would grade (or train) its estimates by the unknown start heading's offset.
        yield dataclasses.replace(frame, attitude=None if sample is None else sample.attitude(), sun_enu_truth=None)
