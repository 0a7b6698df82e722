"""The exposure gate: frames that cannot show the sun are counted and left out of windows."""

import logging
import math
import re

import numpy as np
import pytest

from estimator.estimator import SunEstimator
from replay.sources import DEMO_LOG, open_frames
from rig.errors import ValidationError
from rig.exposure import DEFAULT_EXPOSURE_GATE, SAMPLE_PIXELS, ExposureGate, covered_share, luminance_stats
from rig.offline import OfflineStats, estimate_stream
from rig.pipeline import RigConfig, RigPipeline
from rig.types import Attitude, Frame, HeadingRef, Intrinsics
from rig.window import SpreadWindowPolicy

INTR = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
RNG = np.random.default_rng(0)
TEXTURED = RNG.integers(0, 256, size=(80, 128, 3), dtype=np.uint8)


def _bands(lo, hi):
    """Grey bands 4 rows high alternating ``lo`` and ``hi``, small enough (64 x 128) that the gate
    looks at every pixel: luma lo, hi, lo, ... (grey's luma is its level: the weights sum to 1),
    so mean (lo + hi) / 2 and standard deviation (hi - lo) / 2 exactly."""
    image = np.empty((64, 128, 3), np.uint8)
    assert image.shape[0] * image.shape[1] <= SAMPLE_PIXELS
    image[:] = np.where(np.arange(64) // 4 % 2, hi, lo)[:, None, None]
    return image


# Luma 100, 104, 100, ...: standard deviation 2 (variance 4).
BANDED = _bands(100, 104)


def test_luminance_uses_bt601_weights_in_bgr_order():
    blue, green, red = (np.zeros((16, 16, 3), np.uint8) for _ in range(3))
    blue[..., 0], green[..., 1], red[..., 2] = 200, 200, 200
    means = [luminance_stats(img)[0] for img in (blue, green, red)]
    assert means == pytest.approx([0.114 * 200, 0.587 * 200, 0.299 * 200], rel=1e-5)
    assert luminance_stats(green)[1] == 0.0


@pytest.mark.parametrize(("image", "reason"), [
    (np.zeros((80, 128, 3), np.uint8), "dark"),  # night, a lens cap
    (np.full((80, 128, 3), 8, np.uint8), "dark"),
    (np.full((80, 128, 3), 255, np.uint8), "bright"),  # a blinded sensor
    (np.full((80, 128, 3), 128, np.uint8), "flat"),  # a covered lens
    (np.clip(128 + RNG.normal(0, 1, (80, 128, 3)), 0, 255).astype(np.uint8), "flat"),
    (BANDED, "flat"),  # min_std 3 is a standard deviation: 2 is below it (a variance of 4 is not)
    (TEXTURED, None),
])
def test_gate_names_why_a_frame_cannot_show_the_sun(image, reason):
    assert DEFAULT_EXPOSURE_GATE.rejects(image) == reason


@pytest.mark.parametrize(("lo", "hi", "reason"), [
    (6, 26, None),  # mean 16: not darker than min_mean 16
    (5, 25, "dark"),  # mean 15
    (230, 250, None),  # mean 240: not brighter than max_mean 240
    (231, 251, "bright"),  # mean 241
    (125, 131, None),  # standard deviation 3: not flatter than min_std 3
    (126, 130, "flat"),  # standard deviation 2
])
def test_a_frame_at_a_threshold_passes_one_past_it_does_not(lo, hi, reason):
    image = _bands(lo, hi)
    assert luminance_stats(image) == ((lo + hi) / 2, (hi - lo) / 2)
    assert DEFAULT_EXPOSURE_GATE.rejects(image) == reason


@pytest.mark.parametrize("shape", [(375, 1242), (375, 6), (6, 1242), (2000, 3000)])
def test_stripes_of_any_period_and_frames_of_any_width_are_seen_as_they_are(shape):
    # A frame's every other 4 px dark (a grille, a fence close to the lens), vertical or
    # horizontal: a gate sampling every 8th pixel of every 8th row hit one phase of them and
    # called the frame flat; a frame 6 px wide it judged on one column.
    h, w = shape
    for stripes in (np.arange(w)[None, :] // 4 % 2, np.arange(h)[:, None] // 4 % 2):
        image = np.broadcast_to(np.where(stripes, 200, 20).astype(np.uint8)[..., None], (h, w, 3))
        mean, std = luminance_stats(image)
        exact = image[..., 0].astype(np.float64)
        assert mean == pytest.approx(exact.mean(), abs=3.0) and std == pytest.approx(exact.std(), abs=3.0)
        assert DEFAULT_EXPOSURE_GATE.rejects(image) is None
    # The verdict on a frame does not change from one look to the next (a fixed sample).
    assert luminance_stats(TEXTURED) == luminance_stats(TEXTURED.copy())
    # Nor whether the frame is a view of a larger one (its pixels gathered by row and column) or
    # an array of its own (by flat index).
    view = RNG.integers(0, 256, size=(400, 1300, 3), dtype=np.uint8)[:375, :1242]
    assert not view.flags.c_contiguous
    assert luminance_stats(view) == luminance_stats(view.copy()) and covered_share(view) == covered_share(view.copy())


def test_the_widest_gate_is_valid_and_passes_every_frame():
    # The limits 0 <= min_mean, max_mean <= 255, min_std >= 0 and max_covered_share <= 1 are
    # inclusive: this gate is open.
    gate = ExposureGate(min_mean=0.0, max_mean=255.0, min_std=0.0, max_covered_share=1.0)
    for level in (0, 128, 255):
        assert gate.rejects(np.full((80, 128, 3), level, np.uint8)) is None
    assert gate.rejects(_covered(72)) is None


def test_gate_thresholds_are_checked():
    for bad in ({"min_mean": 200.0, "max_mean": 100.0}, {"min_mean": 100.0, "max_mean": 100.0}, {"max_mean": 300.0},
                {"min_std": -1.0}, {"max_covered_share": -0.1}, {"max_covered_share": 1.5},
                {"max_covered_share": math.nan}):
        with pytest.raises(ValidationError, match="ExposureGate"):
            ExposureGate(**bad)


def _covered(blocks, level=0, noise=0.0):
    """A 48 x 96 frame (every pixel looked at) in the gate's 12 x 6 blocks of 8 x 8 px: the first
    ``blocks`` of them (row by row) at luma ``level`` give or take ``noise``, the rest TEXTURED."""
    image = TEXTURED[:48, :96].copy()
    assert image.shape[0] * image.shape[1] <= SAMPLE_PIXELS
    for b in range(blocks):
        r, c = divmod(b, 12)
        image[8 * r:8 * r + 8, 8 * c:8 * c + 8] = np.clip(level + RNG.normal(0.0, noise, (8, 8, 1)), 0, 255)
    return image


@pytest.mark.parametrize(("cover", "share"), [
    (lambda im: im[im.shape[0] // 2:], 0.5),  # a cap slid over the lower half
    (lambda im: im[:, : im.shape[1] // 2], 0.5),  # over the left half
    (lambda im: im[: im.shape[0] // 2], 0.5),  # the upper half: over the sky, as dark
])
def test_a_lens_partly_capped_is_left_out_as_covered(cover, share):
    # Its mean and standard deviation pass (auto exposure brightens what the cap leaves), so the
    # gate let it through, and the model read it 23-45 deg off on average, calling most of it valid
    # (benchmarks/bench_exposure.py).
    for shape in ((375, 1242), (80, 128)):
        image = RNG.integers(0, 256, size=(*shape, 3), dtype=np.uint8)
        cover(image)[:] = 0
        mean, std = luminance_stats(image)
        assert 16.0 < mean < 240.0 and std > 3.0
        # All of it but the blocks its edge cuts: up to a row of the 6 (or a column of the 12).
        assert share - 1 / 6 <= covered_share(image) <= share + 0.03
        assert DEFAULT_EXPOSURE_GATE.rejects(image) == "covered"


def test_a_dark_flat_blob_over_more_than_a_quarter_is_covered_and_up_to_a_quarter_passes():
    # 18 of the 72 blocks are a quarter of the frame: not more than max_covered_share 0.25.
    assert covered_share(_covered(18)) == 0.25 and DEFAULT_EXPOSURE_GATE.rejects(_covered(18)) is None
    assert covered_share(_covered(19)) == 19 / 72 and DEFAULT_EXPOSURE_GATE.rejects(_covered(19)) == "covered"
    # A hand or a visor is not black: out of focus it is flat (sensor noise only) and darker than
    # 0.6 of the frame's mean (about 95 here).
    assert DEFAULT_EXPOSURE_GATE.rejects(_covered(30, level=50, noise=1.0)) == "covered"


@pytest.mark.parametrize(("level", "noise", "why"), [
    (200, 1.0, "a flat sky: brighter than 0.6 of the frame's mean"),
    (60, 1.0, "the frame's mean falls with it: 60 is not below 0.6 of it (about 93)"),
    (30, 8.0, "shade that shows its texture: a standard deviation of 8, not under 3"),
])
def test_a_large_flat_bright_or_dark_textured_region_is_no_cover(level, noise, why):
    image = _covered(40, level=level, noise=noise)  # 56 % of the frame
    assert covered_share(image) == 0.0, why
    assert DEFAULT_EXPOSURE_GATE.rejects(image) is None, why


def test_a_frame_too_small_for_the_grid_has_fewer_blocks_none_thinner_than_8_px():
    # 6 px wide: one column of blocks (one per column judged the dark of stripes 4 px wide as flat,
    # test_stripes_...), 40 px high: five rows of them, so a cap over its lower half is seen.
    image = RNG.integers(0, 256, size=(40, 6, 3), dtype=np.uint8)
    image[:, :3] = 0  # its left half: no block is all of it
    assert covered_share(image) == 0.0 and DEFAULT_EXPOSURE_GATE.rejects(image) is None
    image = RNG.integers(0, 256, size=(40, 6, 3), dtype=np.uint8)
    image[16:] = 0
    assert covered_share(image) == pytest.approx(24 / 40) and DEFAULT_EXPOSURE_GATE.rejects(image) == "covered"


def test_the_bundled_drive_passes_the_gate():
    # The bundled drive is auto-exposed like the training data: none of its frames may be lost.
    frames = list(open_frames(DEMO_LOG))
    assert frames and not [f.seq for f in frames if DEFAULT_EXPOSURE_GATE.rejects(f.image_bgr)]


def drive(n, dark_from=None, dark_to=None):
    for i in range(n):
        dark = dark_from is not None and dark_from <= i < dark_to
        yield Frame(t_mono_s=0.1 * i, seq=i, image_bgr=np.zeros_like(TEXTURED) if dark else TEXTURED,
                    intrinsics=INTR, attitude=Attitude(math.radians(3.0 * i), HeadingRef.TRUE),
                    sun_enu_truth=np.array([0.0, 0.8, 0.6]))


@pytest.fixture(scope="module")
def estimator(tiny_model_dir):
    from estimator.runtime import OnnxModel

    return SunEstimator(OnnxModel.load(tiny_model_dir))


def run_live(frames, estimator, config=None, **kw):
    pipe = RigPipeline(frames, estimator, SpreadWindowPolicy(8, 4.0), config=config or RigConfig(queue_size=100), **kw)
    return pipe.run(timeout_s=30.0)


@pytest.mark.torch
def test_replay_leaves_dark_frames_out_of_every_window(estimator):
    stats = OfflineStats()
    out = [r["transformer"] for r in estimate_stream(drive(30, 10, 14), estimator, SpreadWindowPolicy(8, 4.0),
                                                     stats=stats)]
    assert stats.frames == 30 and stats.frames_bad_exposure == 4
    assert [e.seq for e in out] == [*range(10), *range(14, 30)]
    # The lit frames before the 0.4 s dark stretch are still within the 4 s span, so the first
    # window after it is full at once: the gate takes frames out, it does not reset the ring.
    assert all(e.n_frames == min(e.seq + 1, 8) for e in out)

    kept = OfflineStats()
    assert len(list(estimate_stream(drive(30, 10, 14), estimator, SpreadWindowPolicy(8, 4.0), stats=kept,
                                    exposure_gate=None))) == 30
    assert kept.frames_bad_exposure == 0


@pytest.mark.torch
def test_live_rig_counts_dark_frames_and_never_estimates_them(estimator, caplog):
    seen: list[Frame] = []
    stats = run_live(drive(40, 0, 40), estimator, on_frame=seen.append)
    # Night all the way: every frame is still handed to the recorder, none reaches the backbone.
    assert len(seen) == stats.frames_captured == stats.frames_bad_exposure == 40
    assert stats.frames_encoded == stats.estimates == 0
    assert "bad exposure 40" in stats.status_line(stats.ended_s)
    # Reported once, when it starts, not once per frame.
    warned = [r.getMessage() for r in caplog.records if "show the sun" in r.getMessage()]
    assert warned == ["from seq 0 frames are too dark to show the sun: left out of windows until that changes"]


@pytest.mark.torch
def test_live_rig_recovers_when_the_light_returns(estimator, caplog):
    caplog.set_level(logging.INFO, logger="rig.pipeline")
    stats = run_live(drive(30, 0, 10), estimator)
    assert stats.frames_bad_exposure == 10 and stats.frames_encoded == 20
    assert stats.estimates + stats.windows_skipped + stats.estimates_failed == 20 and stats.estimates >= 1
    said = [r.getMessage() for r in caplog.records if r.name == "rig.pipeline"]
    assert said == ["from seq 0 frames are too dark to show the sun: left out of windows until that changes",
                    "from seq 10 frames show the scene again: windows refill"]


def capped(n):
    """Frames whose left half is a cap over the lens (black, flat), the rest the textured scene."""
    image = TEXTURED.copy()
    image[:, : image.shape[1] // 2] = 0
    for i in range(n):
        yield Frame(t_mono_s=0.1 * i, seq=i, image_bgr=image, intrinsics=INTR,
                    attitude=Attitude(math.radians(3.0 * i), HeadingRef.TRUE), sun_enu_truth=np.array([0.0, 0.8, 0.6]))


@pytest.mark.torch
def test_live_rig_says_a_covered_lens_with_what_to_do_if_it_is_the_vehicles_own(estimator, caplog):
    # A camera that always sees its own hood or dashboard would send nothing all day: the line says
    # what the check saw and which setting lets such frames through.
    stats = run_live(capped(20), estimator)
    assert stats.frames_bad_exposure == 20 and stats.estimates == 0
    (warned,) = [r.getMessage() for r in caplog.records if r.name == "rig.pipeline" and "covered" in r.getMessage()]
    assert warned.startswith("from seq 0 frames are partly covered (dark and flat over more than 25% of the frame")
    assert warned.endswith("raise [rig] max_covered_share (docs/deploy.md)")
    # Raised to 1, they are used as they are.
    kept = run_live(capped(20), estimator, config=RigConfig(queue_size=100,
                                                            exposure_gate=ExposureGate(max_covered_share=1.0)))
    assert kept.frames_bad_exposure == 0 and kept.frames_encoded == 20


def flickering(n, dark_every=2):
    """Frames at 10 fps, every ``dark_every``-th one black: a scene at the gate's threshold, or a
    lens flickering under trees, which the gate judges frame by frame."""
    for i in range(n):
        dark = i % dark_every == 0
        yield Frame(t_mono_s=0.1 * i, seq=i, image_bgr=np.zeros_like(TEXTURED) if dark else TEXTURED,
                    intrinsics=INTR, attitude=Attitude(math.radians(3.0 * i), HeadingRef.TRUE),
                    sun_enu_truth=np.array([0.0, 0.8, 0.6]))


@pytest.mark.torch
def test_a_verdict_flipping_at_every_frame_is_said_a_few_times_then_summed_up(estimator, caplog):
    # Each change was said at once: a verdict flipping at every frame wrote a line per frame, ten a
    # second into the journal. The first changes are said at once, then one line a minute (by the
    # frames' clock) sums up the changes since; the counts stay exact.
    caplog.set_level(logging.INFO, logger="rig.pipeline")
    stats = run_live(flickering(1300), estimator)  # 130 s
    assert stats.frames_bad_exposure == 650
    said = [r.getMessage() for r in caplog.records if r.name == "rig.pipeline" and any(
            words in r.getMessage() for words in ("show the sun", "show the scene again", "exposure gate"))]
    assert said[:2] == ["from seq 0 frames are too dark to show the sun: left out of windows until that changes",
                        "from seq 1 frames show the scene again: windows refill"]
    assert len(said) == 6, said  # 4 at once, then one at about 60 s and one at about 120 s
    for line, at_s in zip(said[4:], (60.0, 120.0), strict=True):
        changes, seconds, left_out, judged = map(int, re.findall(r"(\d+) changes in (\d+) s, (\d+) of (\d+) frames",
                                                                 line)[0])
        assert changes == judged - 1 and left_out in (judged // 2, judged // 2 + 1), line
        assert 590 <= changes <= 600 and abs(seconds - 60) <= 1, line
        assert f"from seq {round(at_s * 10)}" in line or f"from seq {round(at_s * 10) + 1}" in line, line
