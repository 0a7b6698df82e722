"""The estimator end to end on a tiny random model: cache, aggregators, exact yaw invariance."""

import dataclasses
import gc
import math
import weakref
from types import SimpleNamespace

import numpy as np
import pytest

from estimator.calibration import EstimationError
from estimator.crops import cut_crops
from estimator.estimator import AGGREGATORS, SunEstimator, mirrored_joint_runs, window_tokens
from rig.errors import ValidationError
from rig.geometry import angle_between, world_from_heading
from rig.protocol import ELEVATION_MARGIN_DEG
from rig.types import Attitude, Frame, FrameFeatures, HeadingRef, Intrinsics

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


def test_a_window_mixing_models_is_refused(model):
    # Embeddings of two backbones live in different spaces: one aggregator run over both is noise.
    est = SunEstimator(model)
    window = est.encode_batch(make_frames(2))
    other = FrameFeatures(window[1].frame, window[1].crop_boxes_px, window[1].crop_angles_rad, window[1].embeddings,
                          "another-model")
    with pytest.raises(EstimationError, match="different models"):
        est.estimate([window[0], other])


def test_token_yaw_is_relative_to_the_newest_frame(model):
    # Frames at headings 0, 20, 40 deg (make_frames): the newest looks at 40, so the first frame's
    # crops are 40 deg to its left, i.e. -40 (yaw is clockwise, as the heading); the absolute yaw
    # goes to the calibration unchanged.
    tokens = window_tokens(SunEstimator(model).encode_batch(make_frames(3)))
    per_frame = tokens.angles_rad[:, 0].reshape(3, -1)
    np.testing.assert_allclose(per_frame, np.radians([[-40.0], [-20.0], [0.0]]) * np.ones_like(per_frame), atol=1e-6)
    np.testing.assert_allclose(tokens.yaw_rad.reshape(3, -1)[:, 0], np.radians([0.0, 20.0, 40.0]))


def test_crops_per_frame_overrides_the_contract(model):
    # --crops (eval) asks for another number of crops than the model was trained with.
    est = SunEstimator(model, crops_per_frame=2)
    window = est.encode_batch(make_frames(3))
    assert [f.n_crops for f in window] == [2, 2, 2]
    assert est.estimate(window).n_tokens == 6


def test_a_two_angle_model_shares_each_frame_s_crops_between_its_angles(model):
    from estimator.crops import crop_side_px

    first = model.contract.crop_fov_deg
    mixed = SimpleNamespace(contract=dataclasses.replace(model.contract, crop_fov_deg=[first, 40.0]),
                            model_id=model.model_id, embed=model.embed, aggregate=model.aggregate)
    est = SunEstimator(mixed, crops_per_frame=5)
    frames = make_frames(3)
    window = est.encode_batch(frames)
    sides = [crop_side_px(INTR, math.radians(a)) for a in (first, 40.0)]
    for f in window:  # grouped by angle, the first angle first and taking the odd crop
        assert f.crop_boxes_px[:, 2].tolist() == [sides[0]] * 3 + [sides[1]] * 2
    # The first angle's crops are what a one-angle model draws: adding an angle moves none of them.
    np.testing.assert_array_equal(window[0].crop_boxes_px[:3],
                                  SunEstimator(model, crops_per_frame=3).encode(frames[0]).crop_boxes_px)
    assert est.estimate(window).n_tokens == 15


def test_each_frame_draws_its_own_crops(model):
    # The crop draw is seeded by (seed, seq): frames of one window look at different parts of the
    # sky, and a frame's crops do not depend on which frames came with it.
    est = SunEstimator(model)
    a, b = est.encode_batch(make_frames(2))
    assert not np.array_equal(a.crop_boxes_px, b.crop_boxes_px)
    np.testing.assert_array_equal(est.encode(make_frames(2)[1]).crop_boxes_px, b.crop_boxes_px)


def test_single_is_the_first_crop_of_the_newest_frame(model):
    # "single" is one crop of the newest frame; its vector is that crop's independent estimate,
    # which "mean" lists among its per-token vectors (frames in order: the newest is the last).
    est = SunEstimator(model)
    window = est.encode_batch(make_frames(8))
    r = est.estimate_many(window, ["single", "mean"])
    first_of_newest = 7 * window[0].n_crops
    expected = r["mean"].token_enu[first_of_newest]
    np.testing.assert_allclose(r["single"].sun_enu, expected / np.linalg.norm(expected), atol=1e-9)


def test_single_spread_is_the_other_crops_around_it(model):
    # One vector has no spread around itself (0 made the status rule call every single-crop
    # answer valid, one 100 deg off included); the window's crops around it say how far it can be
    # trusted, as for the other aggregators.
    est = SunEstimator(model)
    r = est.estimate_many(est.encode_batch(make_frames(8)), ["single", "mean"])
    crops = r["mean"].token_enu / np.linalg.norm(r["mean"].token_enu, axis=1, keepdims=True)
    angles = np.arccos(np.clip(crops @ r["single"].sun_enu, -1.0, 1.0))  # each crop's, by hand
    assert r["single"].spread_rad == pytest.approx(math.sqrt(np.mean(angles**2)), abs=1e-9)
    assert r["single"].spread_rad > 0.0


def test_meanshift_spread_is_over_its_inliers(model):
    # The spread the status rule reads must describe the tokens the answer was made of, not the
    # outliers mean shift threw away.
    from estimator.calibration import spread_rad
    from estimator.meanshift import meanshift_aggregate

    est = SunEstimator(model, aggregator="meanshift")
    r = est.estimate(est.encode_batch(make_frames(8)))
    unit, inliers = meanshift_aggregate(r.token_enu)
    assert not inliers.all()  # the case this test is about: some tokens were outliers
    assert r.spread_rad == pytest.approx(spread_rad(r.token_enu[inliers], unit))


def test_estimates_carry_the_newest_frames_utc_and_reference(model):
    # The UTC goes into the NMEA time field and the reference into the status: both are the newest
    # frame's, as the window's sun is.
    utc0 = 1_700_000_000 * 10**9
    frames = [dataclasses.replace(f, utc_ns=utc0 + f.seq * 10**8,
                                  attitude=Attitude(f.attitude.heading_rad, HeadingRef.RELATIVE))
              for f in make_frames(3)]
    est = SunEstimator(model)
    for r in est.estimate_many(est.encode_batch(frames), AGGREGATORS).values():
        assert r.utc_ns == utc0 + 2 * 10**8
        assert r.heading_ref is HeadingRef.RELATIVE



@pytest.mark.parametrize("ref", [HeadingRef.RELATIVE, HeadingRef.MAGNETIC])
def test_only_a_true_heading_window_carries_the_truth(model, ref):
    # The truth is in true-north ENU; a relative or magnetic window's world is turned by the start
    # heading or the declination, so an error against it would be that offset, not the estimator's.
    frames = [dataclasses.replace(f, attitude=Attitude(f.attitude.heading_rad, ref)) for f in make_frames(3)]
    est = SunEstimator(model)
    for r in est.estimate_many(est.encode_batch(frames), AGGREGATORS).values():
        assert r.truth_enu is None and r.error_rad is None
        assert "error_deg" not in r.to_json_dict() and "truth_enu" not in r.to_json_dict()
    true = est.estimate(est.encode_batch(make_frames(3)))
    np.testing.assert_array_equal(true.truth_enu, [0.0, 0.6, 0.8])

def test_a_relative_window_gives_its_heading_epoch_to_each_estimate(model):
    frames = [dataclasses.replace(f, attitude=Attitude(f.attitude.heading_rad, HeadingRef.RELATIVE, epoch=5))
              for f in make_frames(3)]
    est = SunEstimator(model)
    assert {r.heading_epoch for r in est.estimate_many(est.encode_batch(frames), AGGREGATORS).values()} == {5}
    assert est.estimate(est.encode_batch(make_frames(3))).heading_epoch == 0


def test_estimate_many_refuses_an_unknown_aggregator(model):
    # A misspelt name in eval's --aggregators must not quietly run another aggregator.
    est = SunEstimator(model)
    with pytest.raises(ValidationError, match="aggregator"):
        est.estimate_many(est.encode_batch(make_frames(2)), ["mean", "median"])


def test_status_rule_limit_follows_the_highest_training_sun(model):
    # Suns above what the model was trained on are flagged: the limit is the training's highest sun
    # (plus the protocol's margin), not its lowest.
    contract = dataclasses.replace(model.contract, training={"data": {"sun_elevation_deg": [10.0, 40.0]}})
    # FAKE model: status_rule() reads only the contract and the model id.
    rule = SunEstimator(SimpleNamespace(contract=contract, model_id=model.model_id)).status_rule()
    assert rule.max_elevation_deg == 40.0 + ELEVATION_MARGIN_DEG
    assert rule.full_window == model.contract.frames_per_window


def test_encoding_no_frames_is_no_features(model):
    # A replay whose frame count is a multiple of the batch ends with an empty batch to encode.
    assert SunEstimator(model).encode_batch([]) == []


# -- mirrored windows (the contract's mirror_windows) -----------------------------------------


def _mirror_image(ff: FrameFeatures) -> FrameFeatures:
    """The same frame as the mirrored street would give it: the two embeddings swapped, the heading,
    the horizontal view angles and the true sun's east negated (a mirror about the north-up plane)."""
    f = ff.frame
    truth = np.asarray(f.sun_enu_truth) * [-1.0, 1.0, 1.0]
    frame = dataclasses.replace(f, attitude=dataclasses.replace(f.attitude, heading_rad=-f.attitude.heading_rad),
                                sun_enu_truth=truth)
    return FrameFeatures(frame, ff.crop_boxes_px, ff.crop_angles_rad * [-1.0, 1.0], ff.embeddings_mirrored,
                         ff.model_id, ff.embeddings)


def test_an_encoded_frame_lets_its_image_go(model):
    # Nothing after the backbone reads a frame's pixels, and the ring holds seconds of features:
    # a camera's image must be freed once encoded, not kept alive by the features made from it.
    image = np.random.default_rng(0).integers(0, 256, size=(80, 128, 3), dtype=np.uint8)
    freed = weakref.ref(image)
    frame = Frame(t_mono_s=0.0, seq=0, image_bgr=image, intrinsics=INTR,
                  attitude=Attitude(0.0, HeadingRef.TRUE))
    feats = SunEstimator(model, mirror_windows=True).encode(frame)
    del frame, image
    gc.collect()
    assert freed() is None and feats.frame.seq == 0 and feats.frame.attitude.heading_rad == 0.0


def test_mirror_windows_follows_the_contract_unless_told(model):
    frames = make_frames(2)
    assert model.contract.mirror_windows is False  # the tiny test model's export
    plain = SunEstimator(model).encode_batch(frames)
    assert SunEstimator(model).mirror_windows is False and plain[0].embeddings_mirrored is None
    mirrored = SunEstimator(model, mirror_windows=True).encode_batch(frames)
    for frame, p, m in zip(frames, plain, mirrored, strict=True):
        np.testing.assert_array_equal(p.crop_boxes_px, m.crop_boxes_px)  # the same crops ...
        np.testing.assert_allclose(p.embeddings, m.embeddings, atol=1e-5)
        crops = cut_crops(frame.image_bgr, p.crop_boxes_px, model.contract.crop_size_px)
        flipped = model.embed(np.ascontiguousarray(crops[:, :, ::-1]))  # ... and their flips' embeddings beside them
        np.testing.assert_allclose(m.embeddings_mirrored, flipped, atol=1e-5)


def test_a_mirrored_estimate_of_the_mirror_image_is_the_mirror_image_of_the_estimate(model):
    # Run mirrored, the estimator is exactly symmetric: the mirrored street's answer is this street's
    # answer with east negated. A sign left out anywhere (yaw, view angle, east) breaks this.
    est = SunEstimator(model, mirror_windows=True, seed=2)
    window = est.encode_batch(make_frames(8, heading_offset_deg=37.0))
    a = est.estimate(window)
    b = est.estimate([_mirror_image(ff) for ff in window])
    np.testing.assert_allclose(b.sun_enu, a.sun_enu * [-1.0, 1.0, 1.0], atol=1e-5)
    np.testing.assert_allclose(b.token_enu, a.token_enu * [-1.0, 1.0, 1.0], atol=1e-5)
    assert b.error_rad == pytest.approx(a.error_rad, abs=1e-5)
    # Not so unmirrored: a random model is no mirror of itself, which is what makes the test bite.
    plain = SunEstimator(model, seed=2)
    c = plain.estimate(window)
    d = plain.estimate([_mirror_image(ff) for ff in window])
    assert math.degrees(angle_between(d.sun_enu, c.sun_enu * [-1.0, 1.0, 1.0])) > 1.0


def test_a_mirrored_estimate_averages_each_crop_s_two_runs_and_counts_crops(model):
    est = SunEstimator(model, mirror_windows=True, seed=4)
    window = est.encode_batch(make_frames(8))
    results = est.estimate_many(window, AGGREGATORS)
    t = 8 * model.contract.crops_per_frame
    assert results["transformer"].n_tokens == t and results["transformer"].token_enu.shape == (t, 3)
    # The baselines are the paper's, run on the crops as they are.
    unmirrored = SunEstimator(model, seed=4).estimate_many(SunEstimator(model, seed=4).encode_batch(make_frames(8)),
                                                           AGGREGATORS)
    for name in ("mean", "meanshift", "single"):
        np.testing.assert_allclose(results[name].sun_enu, unmirrored[name].sun_enu, atol=1e-5)
    assert math.degrees(angle_between(results["transformer"].sun_enu, unmirrored["transformer"].sun_enu)) > 0.1


def test_a_mirrored_estimator_refuses_frames_encoded_without_their_mirror(model):
    window = SunEstimator(model).encode_batch(make_frames(3))
    with pytest.raises(EstimationError, match=r"frames \[0, 1, 2\] were encoded without mirrored embeddings"):
        SunEstimator(model, mirror_windows=True).estimate(window)
    ff = window[0]
    with pytest.raises(ValidationError, match="embeddings_mirrored: expected float32 of shape"):
        FrameFeatures(ff.frame, ff.crop_boxes_px, ff.crop_angles_rad, ff.embeddings, ff.model_id, ff.embeddings[:1])


def test_the_mirrored_run_takes_other_crops_view_angles_when_given_and_the_plain_run_does_not(model):
    # mirrored_joint_runs' last argument is for a mirrored run on other crops (benchmarks/variants.py
    # "split"): their view angles must reach the mirrored run, and only it.
    est = SunEstimator(model, mirror_windows=True, seed=5)
    window = est.encode_batch(make_frames(8))
    tokens = window_tokens(window)
    plain, mirrored = mirrored_joint_runs(model, tokens, window)
    same = mirrored_joint_runs(model, tokens, window, tokens.angles_rad[:, 1:])
    np.testing.assert_allclose(same[0], plain, atol=1e-6)
    np.testing.assert_allclose(same[1], mirrored, atol=1e-6)
    other = mirrored_joint_runs(model, tokens, window, tokens.angles_rad[:, 1:] + np.float32(0.2))
    np.testing.assert_allclose(other[0], plain, atol=1e-6)
    assert np.max(np.degrees(angle_between(other[1], mirrored))) > 0.1


def test_frames_too_small_for_the_models_crops_are_said_once_per_camera(model, caplog):
    # Train refuses a camera whose crops would be enlarged more than 4x to the model's crop size
    # (the network sees interpolation, not the scene); eval and the rig took it without a word, and
    # a 75x22 px camera's fine-tune was graded 52.8 deg off as though it were a result.
    est = SunEstimator(model)
    size = est.crop_size_px
    tiny = Intrinsics(fx=30.0, fy=30.0, cx=4.0, cy=2.0, width=8, height=5)
    with caplog.at_level("WARNING", logger="estimator"):
        est.encode_batch(make_frames(2))  # the test camera: crops big enough
        assert not caplog.records
        for seq in range(3):
            est.encode(Frame(t_mono_s=seq, seq=seq, image_bgr=np.zeros((5, 8, 3), np.uint8), intrinsics=tiny,
                             attitude=Attitude(0.0, HeadingRef.TRUE)))
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1, said
    assert said[0].startswith("frames of 8x5 px give crops of ") and f"the model's {size} px crops" in said[0]
    assert "use the camera at" in said[0]
