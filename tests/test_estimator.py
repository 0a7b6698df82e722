"""The estimator end to end on a tiny random model: cache, aggregators, exact yaw invariance."""

import math

import numpy as np
import pytest

from estimator.calibration import EstimationError
from estimator.estimator import AGGREGATORS, SunEstimator
from rig.errors import ValidationError
from rig.geometry import angle_between, world_from_heading
from rig.types import Attitude, Frame, HeadingRef, Intrinsics

pytestmark = pytest.mark.torch

INTR = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)


def make_frames(n, heading_offset_deg=0.0, seed=0):
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        img = rng.integers(0, 256, size=(80, 128, 3), dtype=np.uint8)
        att = Attitude(math.radians(20.0 * i + heading_offset_deg), HeadingRef.TRUE)
        frames.append(Frame(t_mono_s=0.1 * i, seq=i, image_bgr=img, intrinsics=INTR, attitude=att,
                            sun_enu_truth=[0.0, 0.6, 0.8]))
    return frames


@pytest.fixture(scope="module")
def model(tiny_model_dir):
    from estimator.runtime import OnnxModel

    return OnnxModel.load(tiny_model_dir)


def test_window_from_cache_equals_recomputed(model):
    est = SunEstimator(model, seed=3)
    frames = make_frames(8)
    cached = [est.encode(f) for f in frames]  # one at a time, as frames arrive live
    fresh = SunEstimator(model, seed=3).encode_batch(frames)  # from scratch, batched
    for a, b in zip(cached, fresh, strict=True):
        np.testing.assert_array_equal(a.crop_boxes_px, b.crop_boxes_px)
        np.testing.assert_allclose(a.embeddings, b.embeddings, atol=1e-5)
    ea, eb = est.estimate(cached), est.estimate(fresh)
    np.testing.assert_allclose(ea.sun_enu, eb.sun_enu, atol=1e-5)
    assert ea.n_frames == 8 and ea.n_tokens == 8 * model.contract.crops_per_frame


def test_all_aggregators_give_unit_vectors_with_truth(model):
    est = SunEstimator(model)
    window = est.encode_batch(make_frames(8))
    results = est.estimate_many(window, AGGREGATORS)
    t = 8 * model.contract.crops_per_frame
    for name, r in results.items():
        assert r.aggregator == name
        assert np.linalg.norm(r.sun_enu) == pytest.approx(1.0)
        assert r.error_rad is not None and r.seq == 7
        assert r.n_tokens == (1 if name == "single" else t)
    assert results["single"].spread_rad == 0.0


def test_global_yaw_offset_rotates_every_aggregator_exactly(model):
    est = SunEstimator(model, seed=1)
    offset = math.radians(123.4)
    base = est.estimate_many(est.encode_batch(make_frames(8)), AGGREGATORS)
    turned = est.estimate_many(est.encode_batch(make_frames(8, heading_offset_deg=123.4)), AGGREGATORS)
    for name in AGGREGATORS:
        expected = world_from_heading(offset) @ base[name].sun_enu
        assert math.degrees(angle_between(turned[name].sun_enu, expected)) < 1e-4, name


def test_frame_order_in_window_does_not_matter(model):
    est = SunEstimator(model)
    window = est.encode_batch(make_frames(8))
    a = est.estimate(window)
    b = est.estimate(window[::-1])
    np.testing.assert_allclose(a.sun_enu, b.sun_enu, atol=1e-5)


def test_bad_windows(model):
    est = SunEstimator(model)
    frames = make_frames(2)
    no_heading = Frame(t_mono_s=1.0, seq=9, image_bgr=frames[0].image_bgr, intrinsics=INTR)
    with pytest.raises(EstimationError, match="no heading"):
        est.estimate(est.encode_batch([frames[0], no_heading]))
    relative = Frame(t_mono_s=1.0, seq=9, image_bgr=frames[0].image_bgr, intrinsics=INTR,
                     attitude=Attitude(0.0, HeadingRef.RELATIVE))
    with pytest.raises(EstimationError, match="mixes heading references"):
        est.estimate(est.encode_batch([frames[0], relative]))
    later = Frame(t_mono_s=1.1, seq=10, image_bgr=frames[0].image_bgr, intrinsics=INTR,
                  attitude=Attitude(0.0, HeadingRef.RELATIVE, epoch=1))
    with pytest.raises(EstimationError, match="mixes heading epochs"):
        est.estimate(est.encode_batch([relative, later]))
    with pytest.raises(EstimationError, match="empty window"):
        est.estimate([])
    with pytest.raises(ValidationError, match="aggregator"):
        SunEstimator(model, aggregator="median")
    with pytest.raises(ValidationError, match="crop layout"):
        SunEstimator(model, crop_layout="grid")


def test_crop_layouts_place_crops_differently_from_the_same_seed(model):
    frame = make_frames(1)[0]
    spread = SunEstimator(model).encode(frame).crop_boxes_px
    uniform = SunEstimator(model, crop_layout="uniform").encode(frame).crop_boxes_px
    assert spread.shape == uniform.shape and not (spread[:, 0] == uniform[:, 0]).all()
