"""Crop sampling and view angles against the intrinsics."""

import math

import numpy as np
import pytest

from estimator.crops import (
    crop_angles_rad,
    crop_side_px,
    crops_per_scale,
    cut_crops,
    frame_rng,
    sample_crop_boxes,
    spread_crop_boxes,
)
from rig.errors import ValidationError
from rig.types import Intrinsics

KITTI = Intrinsics(fx=721.5377, fy=721.5377, cx=609.5593, cy=172.854, width=1242, height=375)


def test_paper_crop_is_224_px_on_kitti():
    from estimator.contract import PAPER_CROP_FOV_DEG

    assert crop_side_px(KITTI, math.radians(PAPER_CROP_FOV_DEG)) == 224
    # A crop never exceeds the image: a 120 deg crop on a 375 px tall image is 375 px.
    assert crop_side_px(KITTI, math.radians(120)) == 375


def test_boxes_inside_image_uniform_and_seeded():
    boxes = sample_crop_boxes(KITTI, 4000, 224, np.random.default_rng(3))
    x0, y0, w, h = boxes.T
    assert (x0 >= 0).all() and (y0 >= 0).all()
    assert (x0 + w <= KITTI.width).all() and (y0 + h <= KITTI.height).all()
    # Uniform over valid top-left corners: the mean sits mid-range and both ends are reached.
    assert x0.mean() == pytest.approx((KITTI.width - 224) / 2, rel=0.05)
    assert x0.min() < 20 and x0.max() > KITTI.width - 224 - 20
    a = sample_crop_boxes(KITTI, 4, 224, frame_rng(7, 12))
    b = sample_crop_boxes(KITTI, 4, 224, frame_rng(7, 12))
    c = sample_crop_boxes(KITTI, 4, 224, frame_rng(7, 13))
    assert (a == b).all() and not (a == c).all()
    # A crop as large as the image has one valid corner, and every draw uses it.
    k = Intrinsics(fx=100.0, fy=100.0, cx=50.0, cy=50.0, width=100, height=100)
    assert (sample_crop_boxes(k, 4, 100, np.random.default_rng(0))[:, :2] == 0).all()


def test_spread_boxes_one_per_stratum_and_each_uniform_within_it():
    rng = np.random.default_rng(4)
    span = KITTI.width - 224 + 1
    lefts = []
    for _ in range(2000):
        boxes = spread_crop_boxes(KITTI, 4, 224, rng)
        x0, y0, w, h = boxes.T
        assert (x0 >= 0).all() and (x0 + w <= KITTI.width).all() and (y0 + h <= KITTI.height).all()
        # Exactly one box in each quarter of the valid range of left edges.
        edges = np.linspace(0, span, 5)
        x_sorted = np.sort(x0)
        assert ((x_sorted >= np.floor(edges[:-1])) & (x_sorted < edges[1:])).all()
        lefts.append(x0)
    x0 = np.concatenate(lefts)
    # Pooled over frames the left edges are still uniform over the valid range (same marginal as
    # the paper's independent draws): mean mid-range, both ends reached, flat histogram.
    assert x0.mean() == pytest.approx((span - 1) / 2, rel=0.02)
    assert x0.min() < 5 and x0.max() > span - 6
    hist = np.histogram(x0, bins=8, range=(0, span))[0]
    assert hist.min() > 0.85 * hist.mean()
    # Deterministic per frame seed.
    a, b = (spread_crop_boxes(KITTI, 4, 224, frame_rng(7, 12)) for _ in range(2))
    assert (a == b).all()
    # A crop as wide as the image has one valid left edge, and every layout uses it.
    k = Intrinsics(fx=100.0, fy=100.0, cx=50.0, cy=50.0, width=100, height=100)
    assert (spread_crop_boxes(k, 3, 100, rng)[:, 0] == 0).all()


def test_sample_rejects_bad_sizes():
    with pytest.raises(ValidationError, match="crop side"):
        sample_crop_boxes(KITTI, 4, 400, np.random.default_rng(0))
    with pytest.raises(ValidationError, match="crop side"):
        sample_crop_boxes(KITTI, 4, 0, np.random.default_rng(0))
    with pytest.raises(ValidationError, match="crops per frame"):
        sample_crop_boxes(KITTI, 0, 100, np.random.default_rng(0))
    with pytest.raises(ValidationError, match="crop side"):
        spread_crop_boxes(KITTI, 4, 400, np.random.default_rng(0))
    # The smallest valid ones: one crop of one pixel, and one crop as tall as the image.
    assert sample_crop_boxes(KITTI, 1, 1, np.random.default_rng(0)).shape == (1, 4)
    assert spread_crop_boxes(KITTI, 1, KITTI.height, np.random.default_rng(0))[0, 3] == KITTI.height


def test_crop_angles_centre_zero_edges_half_fov():
    k = Intrinsics(fx=100.0, fy=100.0, cx=200.0, cy=100.0, width=400, height=200)
    centred = np.array([[150, 50, 100, 100]])  # centre (200, 100) = principal point
    np.testing.assert_allclose(crop_angles_rad(centred, k), [[0.0, 0.0]], atol=1e-15)
    # Degenerate 0-px boxes at the corners have their centres on the image edges.
    corners = np.array([[0, 0, 0, 0], [400, 200, 0, 0]])
    ang = crop_angles_rad(corners, k)
    half_h, half_v = k.hfov_rad / 2, k.vfov_rad / 2
    np.testing.assert_allclose(ang[0], [-half_h, half_v])  # top left: left and up
    np.testing.assert_allclose(ang[1], [half_h, -half_v])  # bottom right: right and down


def test_crop_side_follows_fx_and_angles_fx_across_fy_up():
    # Non-square pixels (fx = 400, fy = 200): the crop's side is 2 fx tan(fov / 2) = 200 px for a
    # fov of 2 atan(1/4); a box centred 40 px right of and 40 px above the principal point is at
    # atan(40 / fx) across and atan(40 / fy) up.
    k = Intrinsics(fx=400.0, fy=200.0, cx=320.0, cy=240.0, width=640, height=480)
    assert crop_side_px(k, 2 * math.atan(0.25)) == 200
    ang = crop_angles_rad(np.array([[320 + 40 - 50, 240 - 40 - 50, 100, 100]]), k)
    np.testing.assert_allclose(ang[0], [math.atan(40 / 400), math.atan(40 / 200)])


def test_crop_then_reproject_round_trip():
    """The angles of a crop point back at the crop: re-projecting them lands on its centre."""
    boxes = sample_crop_boxes(KITTI, 50, 224, np.random.default_rng(5))
    ang = crop_angles_rad(boxes, KITTI)
    u = KITTI.cx + KITTI.fx * np.tan(ang[:, 0])
    v = KITTI.cy - KITTI.fy * np.tan(ang[:, 1])
    np.testing.assert_allclose(u, boxes[:, 0] + 112, atol=1e-9)
    np.testing.assert_allclose(v, boxes[:, 1] + 112, atol=1e-9)


def test_cut_crops_content_and_resize():
    img = np.zeros((375, 1242, 3), np.uint8)
    img[:, :, 2] = np.arange(1242, dtype=np.uint16)[None, :] % 256  # red ramp along x
    img[:, :, 1] = np.arange(375, dtype=np.uint16)[:, None] % 256  # green ramp along y
    boxes = np.array([[100, 10, 224, 224], [0, 0, 64, 64]])
    crops = cut_crops(img, boxes, 112)
    assert crops.shape == (2, 112, 112, 3) and crops.dtype == np.uint8
    # INTER_AREA halves the ramps: crop 0 starts at x=100, y=10 and spans 224 px each way.
    assert abs(int(crops[0, 0, 0, 2]) - 100) <= 1 and abs(int(crops[0, 0, -1, 2]) - 322 % 256) <= 1
    assert abs(int(crops[0, 0, 0, 1]) - 10) <= 1 and abs(int(crops[0, -1, 0, 1]) - 232) <= 1
    same = cut_crops(img, np.array([[5, 5, 112, 112]]), 112)
    assert (same[0] == img[5:117, 5:117]).all()


@pytest.mark.parametrize(("n", "scales", "counts"), [(8, 2, [4, 4]), (7, 2, [4, 3]), (4, 1, [4]), (1, 2, [1, 0]),
                                                     (5, 3, [2, 2, 1])])
def test_a_frame_s_crops_are_shared_among_its_angles_the_first_first(n, scales, counts):
    assert crops_per_scale(n, scales) == counts
