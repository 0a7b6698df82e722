"""Visual odometry (drivers/visual_odometry.py): the yaw sign convention, the pure geometry, pure
rotations made by warping a textured image, and turns on synthetic street drives against their
true heading.

Tolerances are measured, not guessed (on this code, kitti_intrinsics(0.5), the frames named):
- warped pure rotations, 5 x 3 deg: error < 0.05 deg; allowed 0.3 deg.
- synthetic drive 3 frames 6-23 (a right turn of +90 deg): max error 1.7 deg, final -1.7 deg;
  drive 5 frames 17-34 (a left turn of -90 deg): max error 3.1 deg, final -1.1 deg; no frame
  without heading. Allowed: DRIVE_TOL_DEG = 6 deg at every frame with a heading, and at most 2
  frames without one.
``benchmarks/bench_vo.py`` measures the drift over many drives.
"""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from drivers.visual_odometry import (
    VisualOdometry,
    VoConfig,
    fit_rotation,
    in_front,
    refine_pose,
    rotation_from_yaw,
    sampson_px,
    with_visual_heading,
    yaw_from_rotation,
)
from replay.native import open_log
from replay.sources import DEMO_LOG
from rig.errors import ValidationError
from rig.types import Frame, HeadingRef, Intrinsics
from tests.tolerances import DEG, EXACT_F64

WARP_TOL_DEG = 0.3
DRIVE_TOL_DEG = 6.0
INTR = Intrinsics.from_hfov(320, 240, math.radians(70.0))


def k_matrix(intr: Intrinsics) -> np.ndarray:
    return np.array([[intr.fx, 0, intr.cx], [0, intr.fy, intr.cy], [0, 0, 1.0]])


def textured(seed: int = 0, size=(240, 320)) -> np.ndarray:
    """A BGR image full of corners: blurred random blocks at two scales."""
    rng = np.random.default_rng(seed)
    coarse = cv2.resize(rng.integers(0, 256, (size[0] // 8, size[1] // 8), dtype=np.uint8), size[::-1],
                        interpolation=cv2.INTER_NEAREST)
    fine = cv2.resize(rng.integers(0, 256, (size[0] // 3, size[1] // 3), dtype=np.uint8), size[::-1],
                      interpolation=cv2.INTER_NEAREST)
    gray = cv2.GaussianBlur(cv2.addWeighted(coarse, 0.6, fine, 0.4, 0), (3, 3), 0)
    return cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)


def other_exposure(image: np.ndarray, k: int) -> np.ndarray:
    """The same view in another frame: one pixel differs, as sensor noise would make it (an
    identical image is a repeated frame, VisualOdometry's ``repeated``)."""
    out = image.copy()
    out[0, 0] ^= np.uint8(k % 255 + 1)
    return out


def rotated_view(image: np.ndarray, intr: Intrinsics, yaw_rad: float) -> np.ndarray:
    """What a camera sees after turning right by ``yaw_rad`` on the spot (a homography K R K^-1)."""
    k = k_matrix(intr)
    h = k @ rotation_from_yaw(yaw_rad) @ np.linalg.inv(k)
    return cv2.warpPerspective(image, h, (intr.width, intr.height), borderMode=cv2.BORDER_REFLECT)


# --- the sign convention -------------------------------------------------------------------------


def test_a_right_turn_moves_the_point_ahead_to_the_left():
    # Turning right (clockwise from above, heading up) the old optical axis ends up left of the new one.
    r = rotation_from_yaw(math.radians(10.0))
    ahead_before = r @ np.array([0.0, 0.0, 1.0])
    assert ahead_before[0] < 0 and ahead_before[2] > 0
    assert yaw_from_rotation(r) == pytest.approx(math.radians(10.0), abs=EXACT_F64)


@pytest.mark.parametrize("yaw_deg", [-170.0, -45.0, -1.0, 0.0, 0.5, 30.0, 120.0])
def test_yaw_round_trip(yaw_deg):
    assert yaw_from_rotation(rotation_from_yaw(math.radians(yaw_deg))) == pytest.approx(math.radians(yaw_deg),
                                                                                        abs=EXACT_F64)


def test_yaw_ignores_a_small_pitch():
    # Second order: 2 deg of pitch moves a 20 deg turn by 0.011 deg.
    pitch = cv2.Rodrigues(np.array([[math.radians(2.0)], [0.0], [0.0]]))[0]
    r = rotation_from_yaw(math.radians(20.0)) @ pitch
    assert yaw_from_rotation(r) == pytest.approx(math.radians(20.0), abs=0.02 * DEG)


# --- the pure geometry ---------------------------------------------------------------------------


def two_views(seed: int = 1, n: int = 80):
    """Points in front of a camera that turns right by 4 deg and moves forward and a little right."""
    rng = np.random.default_rng(seed)
    pts = np.column_stack([rng.uniform(-10, 10, n), rng.uniform(-3, 2, n), rng.uniform(5, 60, n)])
    r = rotation_from_yaw(math.radians(4.0))
    t = np.array([-0.1, 0.0, -1.0])  # x2 = R x1 + t: moving forward is t_z < 0
    x1 = pts / pts[:, 2:3]
    p2 = pts @ r.T + t
    x2 = p2 / p2[:, 2:3]
    return x1, x2, r, t / np.linalg.norm(t)


def test_sampson_is_zero_for_the_true_pose_and_not_for_another():
    x1, x2, r, t = two_views()
    assert np.max(np.abs(sampson_px(r, t, x1, x2, 300.0))) < 1e-9
    assert np.median(np.abs(sampson_px(rotation_from_yaw(math.radians(6.0)), t, x1, x2, 300.0))) > 0.5


def test_refine_pose_returns_to_the_truth_from_a_nearby_start():
    x1, x2, r, t = two_views()
    r0 = rotation_from_yaw(math.radians(2.5))
    t0 = np.array([0.1, 0.05, -1.0])
    r_fit, t_fit, cost = refine_pose(x1, x2, r0, t0, 300.0)
    assert yaw_from_rotation(r_fit) == pytest.approx(math.radians(4.0), abs=1e-4 * DEG)
    assert np.allclose(t_fit, t, atol=1e-5)
    assert cost < 1e-10


def test_cheirality():
    x1, x2, r, t = two_views()
    assert in_front(r, t, x1, x2).all()
    assert not in_front(r, -t, x1, x2).any()


def test_fit_rotation_is_exact_for_a_pure_rotation():
    x1, _, _, _ = two_views()
    r = rotation_from_yaw(math.radians(-7.0))
    x2 = x1 @ r.T
    x2 = x2 / x2[:, 2:3]
    k = k_matrix(INTR)
    to_px = lambda x: x[:, :2] * INTR.fx + [INTR.cx, INTR.cy]  # noqa: E731
    r_fit, resid = fit_rotation(to_px(x1), to_px(x2), k)
    assert yaw_from_rotation(r_fit) == pytest.approx(math.radians(-7.0), abs=1e-9)
    assert resid.max() < 1e-6


# --- pure rotations: warped images ---------------------------------------------------------------


@pytest.mark.parametrize("step_deg", [3.0, -3.0])
def test_turning_on_the_spot_gives_the_turn_with_its_sign(step_deg):
    base = textured()
    vo = VisualOdometry()
    headings = []
    for k in range(6):
        sample = vo.update(k * 0.1, rotated_view(base, INTR, math.radians(step_deg * k)), INTR)
        assert sample is not None and sample.reference is HeadingRef.RELATIVE
        headings.append(math.degrees(math.remainder(sample.heading_rad, 2 * math.pi)))
    assert headings[0] == 0.0
    assert headings == pytest.approx([step_deg * k for k in range(6)], abs=WARP_TOL_DEG)
    assert vo.stats["rotation_only"] >= 4  # no translation: the essential matrix is not used


def test_a_still_camera_keeps_its_heading():
    vo = VisualOdometry()
    image = textured(3)
    out = [vo.update(k * 0.1, other_exposure(image, k), INTR) for k in range(4)]
    assert all(s is not None and s.heading_rad == 0.0 for s in out)
    assert vo.stats["still"] == 3


def test_a_featureless_image_gives_no_heading_and_no_crash():
    vo = VisualOdometry()
    grey = np.full((240, 320, 3), 128, np.uint8)
    first = vo.update(0.0, grey, INTR)
    assert first is not None and first.heading_rad == 0.0  # the start is the reference by definition
    assert vo.update(0.1, grey, INTR) is None
    assert vo.stats["lost"] == 1


def test_new_intrinsics_or_a_gap_start_a_new_epoch_at_zero():
    # The turn across a change of camera mode, or a gap in the frames, is unknown: the heading
    # carried on in the same epoch, so the rig could window frames from before and after it as
    # if nothing had turned (docs/conventions.md: odometry that restarts begins a new epoch).
    vo = VisualOdometry()
    image = textured(4)
    first = vo.update(0.0, image, INTR)
    assert first is not None and first.attitude().epoch == 0
    vo._last_heading = 0.5  # as if it had turned since
    other = Intrinsics.from_hfov(320, 240, math.radians(60.0))
    restarted = vo.update(0.1, image, other)
    assert restarted is not None and restarted.heading_rad == 0.0 and restarted.attitude().epoch == 1
    assert vo.stats["restarts"] == 1
    after = vo.update(0.2, other_exposure(image, 1), other)
    assert after is not None and after.attitude().epoch == 1
    vo._last_heading = 0.5
    resumed = vo.update(0.2 + vo.config.max_gap_s + 0.01, other_exposure(image, 2), other)
    assert resumed is not None and resumed.heading_rad == 0.0 and resumed.attitude().epoch == 2
    assert vo.stats["gaps"] == 1
    # A frame within the gap allowance goes on in its epoch.
    kept = vo.update(0.3 + vo.config.max_gap_s, other_exposure(image, 3), other)
    assert kept is not None and kept.attitude().epoch == 2 and vo.stats["gaps"] == 1


def test_config_is_checked():
    with pytest.raises(ValidationError, match="refresh_fraction"):
        VoConfig(refresh_fraction=1.5)
    with pytest.raises(ValidationError, match="magsac"):
        VoConfig(ransac="guess")
    # Counts must be >= 1 and refresh_fraction strictly inside (0, 1) (VoConfig.__post_init__):
    # min_points=0 would "track" with no points, refresh_fraction=1 would make every frame a keyframe.
    with pytest.raises(ValidationError, match="min_points"):
        VoConfig(min_points=0)
    for bad in (0.0, 1.0):
        with pytest.raises(ValidationError, match="refresh_fraction"):
            VoConfig(refresh_fraction=bad)
    with pytest.raises(ValidationError, match="max_yaw_rate_rad_s"):
        VoConfig(max_yaw_rate_rad_s=0.0)
    with pytest.raises(ValidationError, match="shift_max_frac"):
        VoConfig(shift_max_frac=0.0)


def test_heading_rad_is_wrapped_to_0_2pi():
    # VisualOdometry.heading_rad: "wrapped to [0, 2 pi)", also for a start heading given negative.
    assert VisualOdometry(start_heading_rad=-0.5).heading_rad == pytest.approx(2 * math.pi - 0.5, abs=EXACT_F64)


# --- synthetic drives: a right and a left turn against the truth ---------------------------------


def drive_frames(seed: int, first: int, last: int) -> list[Frame]:
    """Frames first..last of the 40-frame synthetic drive ``seed`` at half KITTI size."""
    from replay.synthetic import Drive, kitti_intrinsics
    from replay.synthetic.camera import Camera

    intr = kitti_intrinsics(0.5)
    drive = Drive(seed, 40, intrinsics=intr)
    camera = Camera(drive.params.effects, intr.width, intr.height, seed=seed)
    frames = []
    for k in range(first, last + 1):
        pose = drive.poses[k]
        from rig.types import Attitude

        frames.append(Frame(k / drive.fps, k, intr, image_bgr=drive.render_frame(k, camera),
                            attitude=Attitude(pose.heading_rad, HeadingRef.TRUE)))
    return frames


@pytest.mark.parametrize(("seed", "first", "last", "turn_deg"), [(3, 6, 23, 90.0), (5, 17, 34, -90.0)],
                         ids=["right", "left"])
def test_relative_yaw_tracks_a_synthetic_turn(seed, first, last, turn_deg):
    frames = drive_frames(seed, first, last)
    headings = [f.attitude.heading_rad for f in frames if f.attitude is not None]
    assert len(headings) == len(frames)  # truth[k] is frame k's, as the errors below take it
    truth = np.degrees(np.unwrap(headings) - headings[0])
    assert truth[-1] == pytest.approx(turn_deg, abs=2.0)  # the drive turns as the test says

    vo = VisualOdometry()
    out = list(with_visual_heading(frames, vo))
    assert [f.seq for f in out] == [f.seq for f in frames]
    with_heading = [(k, f.attitude) for k, f in enumerate(out) if f.attitude is not None]
    assert len(out) - len(with_heading) <= 2, vo.stats
    assert all(a.reference is HeadingRef.RELATIVE for _, a in with_heading)
    assert with_heading[0][0] == 0 and with_heading[0][1].heading_rad == 0.0
    errors = [math.degrees(math.remainder(a.heading_rad - math.radians(truth[k]), 2 * math.pi))
              for k, a in with_heading]
    assert max(abs(e) for e in errors) < DRIVE_TOL_DEG, (errors, vo.stats)
    last = out[-1].attitude
    assert last is not None
    final = math.degrees(math.remainder(last.heading_rad, 2 * math.pi))
    assert math.copysign(1.0, final) == math.copysign(1.0, turn_deg)


def frozen_drive_errors(seed: int, frozen_after: int, kind: str, last: int) -> tuple[list[float | None], float, dict]:
    """Visual odometry over frames 0..last of synthetic drive ``seed`` with frames frozen_after+1 ..
    +5 frozen (``repeated``: the frame before them again, a dashcam repeating its last image for
    0.5 s) or missing (``dropped``). Returns each frame's heading error in deg against the true turn
    since its epoch's zero (None without a heading; benchmarks/bench_vo.py's measure), the true
    turn over the freeze in deg, and the odometry's stats."""
    from benchmarks.bench_vo import epoch_zeros, heading_errors_deg

    frames = drive_frames(seed, 0, last)
    frozen = range(frozen_after + 1, frozen_after + 6)
    truth = np.unwrap([f.attitude.heading_rad for f in frames if f.attitude is not None])
    assert len(truth) == len(frames)
    vo = VisualOdometry()
    estimates: list[float | None] = []
    epochs = []
    for k, f in enumerate(frames):
        if k in frozen and kind == "dropped":
            estimates.append(None)
            epochs.append(vo.epoch)
            continue
        image = frames[frozen_after].image_bgr if k in frozen else f.image_bgr
        sample = vo.update(f.t_mono_s, image, f.intrinsics)
        estimates.append(None if sample is None else sample.heading_rad)
        epochs.append(vo.epoch)
    assert vo.stats["gaps"] == 0  # the freeze is shorter than max_gap_s
    turn_deg = math.degrees(truth[frozen_after + 6] - truth[frozen_after])
    return heading_errors_deg(list(truth), estimates, epoch_zeros(epochs)), turn_deg, vo.stats


@pytest.mark.parametrize("frozen_after", [7, 10])
@pytest.mark.parametrize("kind", ["repeated", "dropped"])
def test_a_short_freeze_in_a_sharp_turn_carries_no_wrong_turn(kind, frozen_after):
    # Drive 3 turns right about 7 deg a frame from frame 7 on: the vehicle turned 36 / 41 deg
    # between the two new images around the freeze, under max_gap_s, so no gap. Tracking is lost
    # on the frame after it and the image shift's turn was carried: at a third of the 81 deg view
    # the correlation peak is a wrong one (carried +1 / -6 deg), and every later heading was 36 / 48
    # deg off, silently. Starting a new zero there costs no heading error; so a carried turn may
    # cost no more than the odometry's own error on these turns (DRIVE_TOL_DEG, measured above),
    # at every frame with a heading after the freeze.
    errors, turn_deg, stats = frozen_drive_errors(3, frozen_after, kind, 23)
    assert turn_deg > 35.0  # a sharp turn over the freeze, as the test says
    after = [e for e in errors[frozen_after + 6:] if e is not None]
    # The drive goes on with a heading after the freeze: the frame after it may be lost.
    assert len(after) >= len(errors) - (frozen_after + 6) - 1, (errors, stats)
    assert max(abs(e) for e in after) < DRIVE_TOL_DEG, (errors, stats)


@pytest.mark.parametrize("kind", ["repeated", "dropped"])
def test_a_short_freeze_on_a_straight_road_keeps_its_heading(kind):
    # Drive 6 runs nearly straight (1.8 deg over the freeze after frame 10). The image shift over the
    # freeze is still a check of the fit after it: taken out with the carried turn, a wrong fit
    # (-18 deg) agreed with nothing and went through. DRIVE_TOL_DEG as above, at every frame after it.
    errors, turn_deg, stats = frozen_drive_errors(6, 10, kind, 29)
    assert abs(turn_deg) < 3.0
    after = [e for e in errors[16:] if e is not None]
    assert len(after) >= len(errors) - 16 - 1, (errors, stats)
    assert max(abs(e) for e in after) < DRIVE_TOL_DEG, (errors, stats)


# --- what stats and the fallbacks do ---------------------------------------------------------------


@pytest.mark.parametrize("step_deg", [3.0, -3.0])
def test_lost_frames_carry_the_image_shift_turn_with_its_sign(step_deg):
    # min_points above any feature count: tracking is lost on every frame after the first, so each
    # one only carries the coarse turn of the image shift (fx * tan(turn), VisualOdometry._lose).
    # Measured: 5 x 3 deg carries +15.69 / -15.70 deg; allowed 1.5 deg.
    base = textured()
    vo = VisualOdometry(VoConfig(min_points=10**6))
    out = [vo.update(k * 0.1, rotated_view(base, INTR, math.radians(step_deg * k)), INTR) for k in range(6)]
    assert out[0] is not None and all(s is None for s in out[1:])
    assert vo.stats["lost"] == 5 and vo.stats["carried"] == 5
    assert math.degrees(math.remainder(vo.heading_rad, 2 * math.pi)) == pytest.approx(5 * step_deg, abs=1.5)


def test_a_loss_with_no_rough_turn_starts_a_new_epoch_at_zero():
    # A featureless stretch (a lens covered, a dark underpass): tracking is lost and the image shift
    # has no peak, so no turn is carried. The heading went on at its old value in the same epoch, as
    # if the vehicle had not turned meanwhile, and the rig could window frames from either side of
    # the stretch together; the turn is as unknown as across a gap in the frames, so it is a new zero.
    base = textured()
    grey = np.full_like(base, 128)
    vo = VisualOdometry()
    first = vo.update(0.0, base, INTR)
    assert first is not None and first.attitude().epoch == 0
    assert vo.update(0.1, grey, INTR) is None
    assert vo.stats["lost"] == 1 and vo.stats["carried"] == 0 and vo.stats["uncarried"] == 1
    turned = rotated_view(base, INTR, math.radians(30.0))
    assert vo.update(0.2, turned, INTR) is None  # nothing tracks out of the grey keyframe either
    after = vo.update(0.3, rotated_view(base, INTR, math.radians(33.0)), INTR)
    # Each of the two losses carried nothing, and each started a new zero.
    assert after is not None and after.attitude().epoch == vo.stats["uncarried"] == 2
    # Its zero is the frame tracking started again from, not the first frame: 3 deg on from there.
    assert math.degrees(math.remainder(after.heading_rad, 2 * math.pi)) == pytest.approx(3.0, abs=WARP_TOL_DEG)
    assert vo.stats["lost"] == vo.stats["carried"] + vo.stats["uncarried"]


@pytest.mark.parametrize("level", [0, 128])
def test_a_featureless_stretch_carries_no_turn_on_any_of_its_frames(level):
    # A dashcam clip with a black stretch (or a covered lens): two uniform images phase-correlate
    # on the Hanning window alone, a peak of response 1.0 at a shift of about 0 px, and every frame
    # of the stretch after its first was counted "carried" (a 2 s black stretch at 30 fps: 61
    # carried, 2 uncarried) as if a rough turn had been seen across it (docs/drivers.md: a dark or
    # featureless stretch is "uncarried").
    base = textured()
    flat = np.full_like(base, level)
    vo = VisualOdometry()
    vo.update(0.0, base, INTR)
    assert all(vo.update(0.1 * k, flat, INTR) is None for k in range(1, 5))
    assert vo.stats["lost"] == 4 and vo.stats["carried"] == 0 and vo.stats["uncarried"] == 4


def test_a_repeated_frame_gets_the_heading_of_the_frame_it_repeats_and_changes_nothing():
    # A dashcam that repeats frames (15 fps in a 30 fps file, or frozen while it drops them): each
    # repeat was fitted again from the keyframe, or counted "still" (heading_key, not the previous
    # frame's heading), and phase-correlated at 0.5 px, a phantom turn summed into the coarse yaw.
    base = textured()
    vo = VisualOdometry()
    out = []
    for k in range(4):
        view = rotated_view(base, INTR, math.radians(3.0 * k))
        out += [vo.update(k / 15, view, INTR), vo.update(k / 15 + 1 / 30, view.copy(), INTR)]
    headings = [s.heading_rad for s in out if s is not None]
    assert len(headings) == len(out) and headings[1::2] == headings[0::2]
    assert vo.stats["repeated"] == 4 and vo.stats["rotation_only"] + vo.stats["essential"] == 3
    assert vo.stats["still"] == 0 and vo._coarse_since_key is not None
    assert abs(math.degrees(vo._coarse_since_key + vo._heading_key) - 9.0) < 1.0


def test_a_frozen_stretch_longer_than_max_gap_is_a_gap():
    # A dashcam frozen for 1.2 s repeats its last image at 30 fps: no frame is further apart than
    # max_gap_s, yet no new image came for longer than that, and the turn meanwhile is as unknown
    # as across a gap in the frames. The frame after it went on in the old epoch.
    base = textured()
    vo = VisualOdometry()
    frozen = rotated_view(base, INTR, math.radians(3.0))
    vo.update(0.0, base, INTR)
    last = vo.update(1 / 30, frozen, INTR)
    assert last is not None
    repeats = [vo.update(k / 30, frozen, INTR) for k in range(2, 38)]
    assert all(s is not None and s.heading_rad == last.heading_rad and s.epoch == 0 for s in repeats)
    after = vo.update(38 / 30, rotated_view(base, INTR, math.radians(6.0)), INTR)
    assert after is not None and after.epoch == 1 and after.heading_rad == 0.0
    assert vo.stats["gaps"] == 1 and vo.stats["repeated"] == 36


def test_a_fit_that_disagrees_with_the_image_shift_and_the_rotation_only_fit_is_rejected():
    # With both tolerances of VisualOdometry._plausible at 0 an essential-matrix fit (the drive
    # moves forward: no rotation-only frame, measured) never equals the coarse or rotation-only yaw,
    # so every frame after the first is refused, counted in "rejected", and carries the rotation-only turn.
    frames = drive_frames(3, 0, 3)
    vo = VisualOdometry(VoConfig(coarse_tol_rad=0.0, coarse_tol_frac=0.0))
    out = [vo.update(f.t_mono_s, f.image_bgr, f.intrinsics) for f in frames]
    assert out[0] is not None and all(s is None for s in out[1:])
    assert vo.stats["rejected"] == 3 and vo.stats["lost"] == 3 and vo.stats["carried"] == 3, vo.stats


def test_a_new_keyframe_when_the_features_moved_keyframe_parallax_px():
    # 2 deg steps move the features fx * tan(2 deg) = 8 px at INTR (fx 228.5): the parallax since the
    # keyframe reaches keyframe_parallax_px (12 px) every second frame, with nearly all points left.
    base = textured()
    vo = VisualOdometry()
    out = [vo.update(k * 0.1, rotated_view(base, INTR, math.radians(2.0 * k)), INTR) for k in range(5)]
    assert all(s is not None for s in out)
    assert vo.stats["keyframes"] == 3  # the first frame, frame 2 and frame 4


WIDE = Intrinsics.from_hfov(1280, 960, math.radians(70.0))


def test_wide_images_are_downscaled_so_pixel_thresholds_apply_to_the_working_image():
    # max_width_px 640 halves a 1280 px image: a 1 deg step moves features fx * tan(1 deg) = 16 px
    # at full size (fx 914) but 8 px in the working image, so only every second frame reaches
    # keyframe_parallax_px (12 px; VoConfig: "Pixel sizes are in the (possibly downscaled) working image").
    base = textured(size=(960, 1280))
    vo = VisualOdometry()
    out = [vo.update(k * 0.1, rotated_view(base, WIDE, math.radians(1.0 * k)), WIDE) for k in range(4)]
    assert all(s is not None for s in out)
    assert vo.stats["keyframes"] == 2  # the first frame and frame 2


@pytest.mark.parametrize("step_deg", [3.0, -3.0])
def test_turning_on_the_spot_with_a_wide_image_gives_the_turn(step_deg):
    # The downscaled image needs the intrinsics scaled with it (fx, cx, cy); WARP_TOL_DEG as for INTR
    # (measured: error < 0.01 deg).
    base = textured(size=(960, 1280))
    vo = VisualOdometry()
    headings = []
    for k in range(4):
        sample = vo.update(k * 0.1, rotated_view(base, WIDE, math.radians(step_deg * k)), WIDE)
        assert sample is not None
        headings.append(math.degrees(math.remainder(sample.heading_rad, 2 * math.pi)))
    assert headings == pytest.approx([step_deg * k for k in range(4)], abs=WARP_TOL_DEG)


def test_a_turn_larger_than_max_step_between_two_frames_gives_no_heading():
    # VoConfig.max_step_rad: a larger turn between two frames is taken as a failed fit. At 2 deg a
    # 1 deg turn still gives its heading; the next 3 deg (4 deg since the keyframe) gives none.
    base = textured()
    vo = VisualOdometry(VoConfig(max_step_rad=math.radians(2.0)))
    out = [vo.update(k * 0.1, rotated_view(base, INTR, math.radians(yaw)), INTR) for k, yaw in enumerate([0, 1, 4])]
    assert out[1] is not None and math.degrees(out[1].heading_rad) == pytest.approx(1.0, abs=WARP_TOL_DEG)
    assert out[2] is None
    assert vo.stats["lost"] == 1


def test_a_cut_to_an_unrelated_scene_gives_no_heading():
    # Tracks into an unrelated image do not track back to where they came from: the forward-backward
    # check (fb_max_px) drops them all and tracking is lost, instead of fitting a turn to garbage
    # (measured without the check: a 20 deg "turn").
    vo = VisualOdometry()
    assert vo.update(0.0, textured(0), INTR) is not None
    assert vo.update(0.1, textured(7), INTR) is None
    assert vo.stats["lost"] == 1 and vo.stats["essential"] == 0 and vo.stats["rotation_only"] == 0


def test_with_visual_heading_drops_the_frames_true_sun():
    # The demo drive carries a TRUE heading and its true sun (true-north ENU). Visual odometry's
    # heading is relative to the first frame, so the truth no longer fits the frame's world: kept,
    # it graded relative estimates against a sun turned by the start heading.
    frames = list(open_log(DEMO_LOG))[:3]
    assert all(f.sun_enu_truth is not None and f.attitude is not None and f.attitude.reference == HeadingRef.TRUE
               for f in frames)
    out = list(with_visual_heading(frames, VisualOdometry()))
    assert [f.attitude is not None and f.attitude.reference for f in out] == [HeadingRef.RELATIVE] * 3
    assert all(f.sun_enu_truth is None for f in out)
