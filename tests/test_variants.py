"""The run-time variants that bench_accuracy.py --variant measures (benchmarks/variants.py), on the
shipped model and the bundled drive: they must be what the card says they are, or its numbers for
them mean nothing."""

from __future__ import annotations

import math

import numpy as np
import pytest

from benchmarks.variants import ClampEstimator, clamp_elevation
from estimator.models import resolve_model_dir
from estimator.runtime import OnnxModel
from rig.geometry import az_el_from_enu, enu_from_az_el


def _az_el_deg(u: np.ndarray) -> tuple[float, float]:
    az, el = az_el_from_enu(u)
    return math.degrees(az), math.degrees(el)


@pytest.mark.parametrize(("el_deg", "expected_deg"), [(40.0, 40.0), (82.0, 74.9), (-3.0, 5.0), (5.0, 5.0)])
def test_clamp_moves_only_the_elevation_into_the_range(el_deg, expected_deg):
    az, el = _az_el_deg(clamp_elevation(enu_from_az_el(math.radians(123.0), math.radians(el_deg)), 5.0, 74.9))
    assert az == pytest.approx(123.0) and el == pytest.approx(expected_deg)


def test_clamp_of_the_zenith_is_a_unit_vector_at_the_top_of_the_range():
    u = clamp_elevation(np.array([0.0, 0.0, 1.0]), 5.0, 74.9)
    assert np.linalg.norm(u) == pytest.approx(1.0) and _az_el_deg(u)[1] == pytest.approx(74.9)


def _demo_windows(estimator) -> list:
    """The transformer's estimates of the bundled drive's full windows."""
    from replay.sources import DEMO_LOG, open_frames
    from rig.offline import estimate_stream
    from rig.window import SpreadWindowPolicy

    windows = estimate_stream(open_frames(DEMO_LOG), estimator, SpreadWindowPolicy(n_frames=8))
    return [w["transformer"] for w in windows if w["transformer"].n_frames == 8]


@pytest.fixture(scope="module")
def demo_windows():
    from estimator.estimator import SunEstimator

    model = OnnxModel.load(resolve_model_dir(None))
    return model, *(_demo_windows(cls(model)) for cls in (SunEstimator, ClampEstimator))


def test_clamp_leaves_answers_in_the_trained_range_alone(demo_windows):
    model, plain, clamped = demo_windows
    low, high = model.contract.trained_sun_elevation_deg
    assert all(low <= math.degrees(p.elevation_rad) <= high for p in plain)  # the sun is 15.5 deg up
    for p, c in zip(plain, clamped, strict=True):
        np.testing.assert_allclose(c.sun_enu, p.sun_enu)


def test_clamp_lifts_answers_below_the_trained_range_along_their_azimuth(demo_windows, monkeypatch):
    from estimator.contract import ModelContract

    model, plain, _ = demo_windows
    # As if the model had trained on suns 25-74.9 deg up only: every demo answer (near 15 deg) is below.
    monkeypatch.setattr(ModelContract, "trained_sun_elevation_deg", property(lambda self: (25.0, 74.9)))
    clamped = _demo_windows(ClampEstimator(model))
    for p, c in zip(plain, clamped, strict=True):
        assert math.degrees(c.elevation_rad) == pytest.approx(25.0)
        assert _az_el_deg(c.sun_enu)[0] == pytest.approx(_az_el_deg(p.sun_enu)[0])


def _narrow_side_px(intr) -> int:
    from estimator.crops import crop_side_px

    return crop_side_px(intr, math.radians(17.648))


def _strata(edges: np.ndarray, span: int, n: int) -> list[int]:
    return sorted(np.floor(edges / (span / n)).astype(int))


def test_latin_boxes_take_one_stratum_of_each_edge():
    from benchmarks.variants import latin_crop_boxes
    from replay.synthetic import kitti_intrinsics

    intr = kitti_intrinsics()
    side = _narrow_side_px(intr)
    for seed in range(20):
        boxes = latin_crop_boxes(intr, 4, side, np.random.default_rng(seed))
        x0, y0 = boxes[:, 0], boxes[:, 1]
        assert (x0 >= 0).all() and (x0 + side <= intr.width).all()
        assert (y0 >= 0).all() and (y0 + side <= intr.height).all()
        assert _strata(x0, intr.width - side + 1, 4) == [0, 1, 2, 3]
        assert _strata(y0, intr.height - side + 1, 4) == [0, 1, 2, 3]


def test_tiled_boxes_reach_both_edges_evenly_in_every_frame():
    from benchmarks.variants import tiled_crop_boxes, tiled_latin_crop_boxes
    from replay.synthetic import kitti_intrinsics

    intr = kitti_intrinsics()
    side = _narrow_side_px(intr)
    lefts = set()
    for seed in range(20):
        boxes = tiled_crop_boxes(intr, 4, side, np.random.default_rng(seed))
        x0, y0 = boxes[:, 0], boxes[:, 1]
        assert x0[0] == 0 and x0[-1] + side == intr.width
        assert np.ptp(np.diff(x0)) <= 1  # evenly spaced, to the pixel
        assert (y0 >= 0).all() and (y0 + side <= intr.height).all()
        lefts.add(tuple(x0))
        strat = tiled_latin_crop_boxes(intr, 4, side, np.random.default_rng(seed))
        assert (strat[:, 0] == x0).all() and _strata(strat[:, 1], intr.height - side + 1, 4) == [0, 1, 2, 3]
    assert len(lefts) == 1  # the same left edges whatever the generator


@pytest.mark.parametrize("variant", ["latin", "tiled", "tiledlatin"])
def test_layout_variants_refuse_another_crop_layout(variant):
    from benchmarks.variants import estimator_for
    from rig.errors import ValidationError

    with pytest.raises(ValidationError, match="leave --crop-layout at spread"):
        estimator_for(variant)(OnnxModel.load(resolve_model_dir(None)), crop_layout="uniform")


def test_tiled_estimator_uses_tiled_crops():
    from benchmarks.variants import TiledEstimator
    from replay.sources import DEMO_LOG, open_frames

    est = TiledEstimator(OnnxModel.load(resolve_model_dir(None)))
    frame = next(iter(open_frames(DEMO_LOG)))
    boxes = est.encode(frame).crop_boxes_px
    start = 0
    for _, n in est.crops_per_fov:  # each crop angle's crops from the left edge to the right
        x0, side = boxes[start : start + n, 0], boxes[start, 2]
        assert x0[0] == 0 and x0[-1] + side == frame.intrinsics.width
        start += n


def test_split_alternates_its_two_runs_crops_across_the_frame():
    from benchmarks.variants import SplitEstimator
    from replay.sources import DEMO_LOG, open_frames

    est = SplitEstimator(OnnxModel.load(resolve_model_dir(None)))
    frame = next(iter(open_frames(DEMO_LOG)))
    plain, other = est._split_boxes(frame)
    assert plain.shape == other.shape == (est.crops_per_frame, 4)
    start = 0
    for _, n in est.crops_per_fov:  # per crop angle: plain, other, plain, other ... from the left
        both = np.concatenate([plain[start : start + n], other[start : start + n]])
        order = np.argsort(both[:, 0], kind="stable")
        assert list(order % n) == [i // 2 for i in range(2 * n)] and list(order // n) == [0, 1] * n
        start += n


def test_split_on_the_same_crops_is_the_shipped_mirrored_run(monkeypatch):
    """With its two runs given the same crops, split must answer what the product's mirrored run
    answers: this checks its angles, headings and east are mirrored as the product mirrors them."""
    from benchmarks.variants import SplitEstimator
    from estimator.estimator import SunEstimator

    model = OnnxModel.load(resolve_model_dir(None))
    assert model.contract.mirror_windows
    plain = SunEstimator(model)
    split = SplitEstimator(model)
    monkeypatch.setattr(SplitEstimator, "_split_boxes", lambda self, frame: (plain.encode(frame).crop_boxes_px,) * 2)
    want, got = _demo_windows(plain), _demo_windows(split)
    assert len(want) == len(got) > 20
    for w, g in zip(want, got, strict=True):
        np.testing.assert_allclose(g.sun_enu, w.sun_enu, atol=1e-5)
        assert g.n_tokens == 2 * w.n_tokens


def test_split_needs_the_model_run_mirrored():
    from benchmarks.variants import SplitEstimator
    from rig.errors import ValidationError

    with pytest.raises(ValidationError, match="mirror"):
        SplitEstimator(OnnxModel.load(resolve_model_dir(None)), mirror_windows=False)
