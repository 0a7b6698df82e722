"""The training loop's mechanics: it runs, checkpoints, resumes where it stopped, and exports a
model the runtime loads with its recipe in the contract. (Whether it learns the sun is measured by
`sunrig eval` on held-out drives, docs/model.md, not here.)"""

import math

import numpy as np
import pytest

from rig.types import Attitude, Frame, HeadingRef, Intrinsics

pytestmark = pytest.mark.torch
torch = pytest.importorskip("torch", reason="training needs the train extra")

from estimator.train import CHECKPOINT, TrainConfig, TrainingDataError, WindowSampler, load_drive, train  # noqa: E402


def _frames(n, seed, truth=True):
    rng = np.random.default_rng(seed)
    k = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    return [
        Frame(t_mono_s=0.5 * i, seq=i, image_bgr=rng.integers(0, 256, (80, 128, 3), dtype=np.uint8), intrinsics=k,
              attitude=Attitude(math.radians(30.0 * i), HeadingRef.TRUE),
              sun_enu_truth=[0.0, 0.6, 0.8] if truth else None)
        for i in range(n)
    ]


@pytest.fixture
def logs(tmp_path):
    from replay.native import LogWriter

    paths = []
    for d in range(3):
        p = tmp_path / f"drive_{d}.mcap"
        with LogWriter(p) as w:
            for f in _frames(10, d):
                w.write_frame(f)
        paths.append(p)
    return paths


def test_drive_is_prescaled_so_a_crop_is_a_slice():
    from estimator.contract import PAPER_CROP_FOV_DEG

    fov = math.radians(PAPER_CROP_FOV_DEG)
    drive = load_drive(_frames(3, 0), "d", crop_size=16, crop_fov_rad=fov)
    side = 2 * 100.0 * math.tan(fov / 2)  # source pixels of one crop
    assert drive.images.shape[0] == 3
    assert drive.fx == pytest.approx(100.0 * 16 / round(side))
    # The view angle of the image centre is unchanged by the scaling.
    assert drive.cx / drive.fx == pytest.approx(64.0 / 100.0)
    assert load_drive(_frames(3, 0, truth=False), "d", 16, fov) is None


def test_sampler_windows_are_consistent():
    drive = load_drive(_frames(10, 1), "d", crop_size=16, crop_fov_rad=math.radians(17.6))
    sampler = WindowSampler([drive], frames=8, crops=4, crop_size=16, subset_prob=0.0,
                            rng=np.random.default_rng(0))
    b = sampler.sample(3)
    assert b.crops.shape == (3, 32, 16, 16, 3) and b.mask.all()
    # The newest frame's tokens (the last 4) have relative yaw 0, and the random global offset
    # turns truth and headings together: seen from the newest frame's heading, the sun is where
    # it is in the drive, seen from one of the drive's frames.
    from rig.geometry import heading_from_world

    seen_in_drive = np.einsum("fij,fj->fi", heading_from_world(drive.yaw_rad), drive.sun_enu)
    for w in range(3):
        np.testing.assert_allclose(b.angles[w, 28:, 0], 0.0, atol=1e-6)
        seen = heading_from_world(b.yaw[w, 28]) @ b.truth[w]
        assert np.min(np.linalg.norm(seen_in_drive - seen, axis=1)) < 1e-9
    subset = WindowSampler([drive], 8, 4, 16, subset_prob=1.0, rng=np.random.default_rng(0)).sample(4)
    assert (subset.mask.sum(1) >= 1).all() and (subset.mask.sum(1) < 32).any()


def test_train_checkpoint_resume_export(logs, tmp_path):
    from estimator.runtime import OnnxModel

    out = tmp_path / "model"
    cfg = TrainConfig(preset="tiny", max_steps=3, batch_windows=2, warmup_steps=1, command="test")
    train(logs, out, cfg)
    state = torch.load(out / CHECKPOINT, weights_only=False)
    assert state["step"] == 3
    model = OnnxModel.load(out)
    assert model.contract.training["trained"] is True and model.contract.training["steps"] == 3
    assert model.contract.training["data"]["drives"] == 3
    # Resume: a larger step budget continues from step 3, not from scratch.
    train(logs, out, TrainConfig(preset="tiny", max_steps=5, batch_windows=2, warmup_steps=1))
    assert torch.load(out / CHECKPOINT, weights_only=False)["step"] == 5
    assert OnnxModel.load(out).contract.training["steps"] == 5
    # The checkpoint exports on its own (to watch a run while it trains) to the same model.
    from estimator.train import export_checkpoint

    again = OnnxModel.load(export_checkpoint(out, tmp_path / "exported"))
    assert again.contract == OnnxModel.load(out).contract
    crops = np.random.default_rng(0).integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    np.testing.assert_allclose(again.embed(crops), OnnxModel.load(out).embed(crops), atol=1e-6)


def test_train_refuses_logs_without_truth(tmp_path):
    from replay.native import LogWriter

    p = tmp_path / "no_truth.mcap"
    with LogWriter(p) as w:
        for f in _frames(4, 0, truth=False):
            w.write_frame(f)
    with pytest.raises(TrainingDataError, match="true sun"):
        train([p], tmp_path / "m", TrainConfig(preset="tiny", max_steps=1))


def test_resume_with_another_preset_is_refused(logs, tmp_path):
    from rig.errors import ValidationError

    out = tmp_path / "model"
    train(logs, out, TrainConfig(preset="tiny", max_steps=1, batch_windows=1))
    with pytest.raises(ValidationError, match="preset"):
        train(logs, out, TrainConfig(preset="fast", max_steps=2, batch_windows=1))
