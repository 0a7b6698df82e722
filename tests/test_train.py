"""The training loop's mechanics: it runs, checkpoints, resumes where it stopped, and exports a
model the runtime loads with its recipe in the contract. (Whether it learns the sun is measured by
`sunrig eval` on held-out drives, docs/model.md, not here.)"""

import math
from dataclasses import replace

import numpy as np
import pytest

from estimator.contract import PAPER_CROP_FOV_DEG
from rig.errors import ValidationError
from rig.types import Attitude, Frame, HeadingRef, Intrinsics

pytestmark = pytest.mark.torch
torch = pytest.importorskip("torch", reason="training needs the train extra")

from estimator.train import (  # noqa: E402
    CHECKPOINT,
    LR_FLOOR,
    METRICS,
    Schedule,
    TrainConfig,
    TrainingDataError,
    WindowSampler,
    data_fingerprint,
    load_drive,
    load_weights,
    train,
    use_bf16,
)


def _frames(n, seed, truth=True, sun_enu=(0.0, 0.6, 0.8)):
    rng = np.random.default_rng(seed)
    k = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    return [
        Frame(t_mono_s=0.5 * i, seq=i, image_bgr=rng.integers(0, 256, (80, 128, 3), dtype=np.uint8), intrinsics=k,
              attitude=Attitude(math.radians(30.0 * i), HeadingRef.TRUE),
              sun_enu_truth=list(sun_enu) if truth else None)
        for i in range(n)
    ]


def _write_logs(folder, n_drives, **frame_kw):
    from replay.native import LogWriter

    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for d in range(n_drives):
        p = folder / f"drive_{d}.mcap"
        with LogWriter(p) as w:
            for f in _frames(10, d, **frame_kw):
                w.write_frame(f)
        paths.append(p)
    return paths


@pytest.fixture
def logs(tmp_path):
    return _write_logs(tmp_path, 3)  # the sun 53.1 deg up


def test_drive_is_prescaled_so_a_crop_is_a_slice():

    fov, wide = math.radians(PAPER_CROP_FOV_DEG), math.radians(30.0)
    drive = load_drive(_frames(3, 0), "d", crop_size=16, crop_fov_rad=[fov, wide])
    assert drive.images.shape[0] == 3 and len(drive.views) == 2
    for view, angle in zip(drive.views, (fov, wide), strict=True):
        side = 2 * 100.0 * math.tan(angle / 2)  # source pixels of one crop of this angle
        assert view.fx == pytest.approx(100.0 * 16 / round(side))
        # The view angle of the image centre is unchanged by the scaling.
        assert view.cx / view.fx == pytest.approx(64.0 / 100.0)
    assert drive.views[1].images.shape[1] < drive.views[0].images.shape[1]  # a wider crop: a smaller image
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


@pytest.mark.slow
def test_train_checkpoint_resume_export(logs, tmp_path):
    from estimator.runtime import OnnxModel

    out = tmp_path / "model"
    cfg = TrainConfig(preset="tiny", max_steps=3, batch_windows=2, warmup_steps=1, command="test")
    events = []
    train(logs, out, cfg, progress=events.append)
    # Progress: every log loaded, then every step, each saying where this session started.
    assert [(e["done"], e["total"]) for e in events if e["phase"] == "load"] == [(1, 3), (2, 3), (3, 3)]
    assert [(e["step"], e["start_step"]) for e in events if e["phase"] == "train"] == [(1, 0), (2, 0), (3, 0)]
    assert {e["total"] for e in events if e["phase"] == "train"} == {3}  # a step budget is its own total
    state = torch.load(out / CHECKPOINT, weights_only=False)
    assert state["step"] == 3
    model = OnnxModel.load(out)
    assert model.contract.training["trained"] is True and model.contract.training["steps"] == 3
    assert model.contract.training["data"]["drives"] == 3
    # The data's sun elevations, for the status rule (every test frame's sun is asin(0.8) up).
    assert model.contract.trained_sun_elevation_deg == (53.1, 53.1)
    # Resume: a larger step budget continues from step 3, not from scratch. Metric lines written
    # after the checkpoint (steps a kill threw away) and a torn last line do not survive it.
    (out / METRICS).write_text('{"step": 2}\n{"step": 4}\n{"st', encoding="utf-8")
    events.clear()
    train(logs, out, TrainConfig(preset="tiny", max_steps=5, batch_windows=2, warmup_steps=1), progress=events.append)
    assert torch.load(out / CHECKPOINT, weights_only=False)["step"] == 5
    assert [(e["step"], e["start_step"]) for e in events if e["phase"] == "train"] == [(4, 3), (5, 3)]
    assert (out / METRICS).read_text(encoding="utf-8") == '{"step": 2}\n'
    assert OnnxModel.load(out).contract.training["steps"] == 5
    # The checkpoint exports on its own (to watch a run while it trains) to the same model.
    from estimator.train import export_checkpoint

    again = OnnxModel.load(export_checkpoint(out, tmp_path / "exported"))
    assert again.contract == OnnxModel.load(out).contract
    crops = np.random.default_rng(0).integers(0, 256, (3, 32, 32, 3), dtype=np.uint8)
    np.testing.assert_allclose(again.embed(crops), OnnxModel.load(out).embed(crops), atol=1e-6)


@pytest.mark.slow
def test_an_older_checkpoint_takes_its_sun_elevations_from_its_own_logs(logs, tmp_path):
    from estimator.runtime import OnnxModel
    from estimator.train import export_checkpoint

    out = tmp_path / "model"
    train(logs, out, TrainConfig(preset="tiny", max_steps=1, batch_windows=1, warmup_steps=1,
                                 data={"fingerprint": data_fingerprint(logs)}))
    # A checkpoint written before training recorded the range (as the shipped model's was).
    state = torch.load(out / CHECKPOINT, weights_only=False)
    del state["data_counts"]["sun_elevation_deg"]
    torch.save(state, out / CHECKPOINT)
    assert OnnxModel.load(export_checkpoint(out, tmp_path / "bare")).contract.trained_sun_elevation_deg is None
    with pytest.raises(ValidationError, match="not the ones"):
        export_checkpoint(out, tmp_path / "wrong", log_paths=logs[:2])
    again = OnnxModel.load(export_checkpoint(out, tmp_path / "again", log_paths=logs))
    assert again.contract.trained_sun_elevation_deg == (53.1, 53.1)


@pytest.mark.slow
def test_a_run_started_without_a_data_note_gets_one_at_export_checked_against_its_logs(logs, tmp_path):
    from estimator.runtime import OnnxModel
    from estimator.train import export_checkpoint

    out = tmp_path / "model"
    train(logs, out, TrainConfig(preset="tiny", max_steps=1, batch_windows=1, warmup_steps=1,
                                 data={"fingerprint": data_fingerprint(logs), "source": ""}))
    note = "sunrig synth train --drives 3 --seed 7"
    with pytest.raises(ValidationError, match="needs the run's training logs"):
        export_checkpoint(out, tmp_path / "unchecked", data_note=note)
    with pytest.raises(ValidationError, match="not the ones"):
        export_checkpoint(out, tmp_path / "wrong", log_paths=logs[:2], data_note=note)
    named = OnnxModel.load(export_checkpoint(out, tmp_path / "named", log_paths=logs, data_note=note))
    assert named.contract.training["data"]["source"] == note
    assert named.contract.training["data"]["fingerprint"] == data_fingerprint(logs)
    # Data a run recorded itself is not renamed; the same words again change nothing.
    state = torch.load(out / CHECKPOINT, weights_only=False)
    state["config"]["data"]["source"] = note
    torch.save(state, out / CHECKPOINT)
    with pytest.raises(ValidationError, match="recorded its data as"):
        export_checkpoint(out, tmp_path / "renamed", log_paths=logs, data_note="something else")
    same = OnnxModel.load(export_checkpoint(out, tmp_path / "same", log_paths=logs, data_note=note))
    assert same.contract.training["data"]["source"] == note


def interrupt_at_step_2(p):
    """A progress callback that presses Ctrl-C once step 2 is done."""
    if p["phase"] == "train" and p["step"] == 2:
        raise KeyboardInterrupt


def test_ctrl_c_keeps_the_steps_since_the_last_checkpoint(logs, tmp_path):
    out = tmp_path / "model"
    # No checkpoint is due for an hour: without the save on Ctrl-C, both steps would be lost.
    cfg = TrainConfig(preset="tiny", max_steps=4, batch_windows=1, warmup_steps=1, checkpoint_every_s=3600.0)
    with pytest.raises(KeyboardInterrupt):
        train(logs, out, cfg, progress=interrupt_at_step_2)
    assert torch.load(out / CHECKPOINT, weights_only=False)["step"] == 2
    events = []
    train(logs, out, cfg, progress=events.append)  # the same command resumes
    assert [e["step"] for e in events if e["phase"] == "train"] == [3, 4]


def test_ctrl_c_during_the_final_save_or_export_says_what_is_kept_and_how_to_go_on(logs, tmp_path, monkeypatch,
                                                                                   caplog):
    # The export is most of a short run's time (seconds of ONNX tracing): a Ctrl-C there exited
    # 130 without a word, leaving checkpoint.pt and weights.npz and no graphs; one during the final
    # save lost every step since the last checkpoint, also silently.
    # A real Ctrl-C (SIGINT, through Python's own handler) lands at the start of each.
    import signal

    import estimator.train as train_mod

    cfg = TrainConfig(preset="tiny", max_steps=2, batch_windows=1, warmup_steps=1, checkpoint_every_s=3600.0)
    save = train_mod._save_checkpoint
    calls = []

    def save_cut_once(path, state):
        calls.append(state["step"])
        if len(calls) == 1:
            signal.raise_signal(signal.SIGINT)
        save(path, state)

    monkeypatch.setattr(train_mod, "_save_checkpoint", save_cut_once)
    with caplog.at_level("WARNING"), pytest.raises(KeyboardInterrupt):
        train(logs, tmp_path / "saved", cfg)
    assert calls == [2, 2]  # the final save, cut; then the save of the same step on the way out
    assert torch.load(tmp_path / "saved" / CHECKPOINT, weights_only=False)["step"] == 2  # kept, not lost
    assert "run the same command to resume" in caplog.text
    monkeypatch.undo()
    caplog.clear()

    export = train_mod.export_model

    def export_cut(*args, **kwargs):
        signal.raise_signal(signal.SIGINT)
        return export(*args, **kwargs)

    out = tmp_path / "exported"
    monkeypatch.setattr(train_mod, "export_model", export_cut)
    with caplog.at_level("WARNING"), pytest.raises(KeyboardInterrupt):
        train(logs, out, cfg)
    assert f"interrupted while exporting the model of step 2: {out / CHECKPOINT} is saved" in caplog.text
    assert "run the same command to export it" in caplog.text
    monkeypatch.undo()
    events = []
    train(logs, out, cfg, progress=events.append)  # as it says: the same command exports it
    assert not any(e["phase"] == "train" for e in events) and (out / "backbone.onnx").is_file()


@pytest.mark.slow
def test_a_stopped_and_resumed_run_ends_on_the_weights_of_one_never_stopped(logs, tmp_path):
    # The draws, dropout, hard-draw errors and optimizer all carry on where they stopped, so the
    # command a contract records names its model exactly. The fast preset: the tiny one has no
    # dropout to draw.
    cfg = TrainConfig(preset="fast", max_steps=4, batch_windows=1, warmup_steps=1, checkpoint_every_s=3600.0)
    with pytest.raises(KeyboardInterrupt):
        train(logs, tmp_path / "resumed", cfg, progress=interrupt_at_step_2)
    torch.manual_seed(1)  # as in a new process: not the generator the stopped run left behind
    train(logs, tmp_path / "resumed", cfg)
    train(logs, tmp_path / "straight", cfg)
    resumed, straight = (torch.load(tmp_path / d / CHECKPOINT, weights_only=False) for d in ("resumed", "straight"))
    assert resumed["step"] == straight["step"] == 4
    assert resumed["drive_err_deg"] == straight["drive_err_deg"]  # what the hard draws go on drawing by
    for part in ("backbone", "aggregator"):
        for name, tensor in straight[part].items():
            assert torch.equal(resumed[part][name], tensor), f"{part}.{name}"


def test_a_budget_that_never_ends_or_never_starts_is_refused(logs, tmp_path):
    for minutes in (float("nan"), -1.0, 0.0):
        with pytest.raises(ValidationError, match="minutes"):
            train(logs, tmp_path / "m", TrainConfig(preset="tiny", minutes=minutes))
    with pytest.raises(ValidationError, match="lr"):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", max_steps=1, lr=float("nan")))


def test_train_refuses_logs_without_truth(tmp_path):
    from replay.native import LogWriter

    p = tmp_path / "no_truth.mcap"
    with LogWriter(p) as w:
        for f in _frames(4, 0, truth=False):
            w.write_frame(f)
    with pytest.raises(TrainingDataError, match="true sun"):
        train([p], tmp_path / "m", TrainConfig(preset="tiny", max_steps=1))



def test_a_log_without_a_gnss_fix_is_left_out_saying_so_and_what_to_record(tmp_path, caplog):
    # A drive recorded with a compass and no GNSS: TRUE headings and UTC, no fix, so no true sun.
    # It was left out saying only "no frame with both a TRUE heading and the true sun", and alone
    # the error named no log and no cause.
    from estimator.train import load_drives
    from replay.native import LogWriter

    no_fix, good = tmp_path / "no_fix.mcap", tmp_path / "good.mcap"
    for path, truth in ((no_fix, False), (good, True)):
        with LogWriter(path) as w:
            for f in _frames(10, 0, truth=truth):
                w.write_frame(replace(f, utc_ns=1_700_000_000_000_000_000 + f.seq * 500_000_000))
    fov = math.radians(PAPER_CROP_FOV_DEG)
    why = "10 of its 10 frames have a TRUE heading and no GNSS fix"
    with caplog.at_level("WARNING", logger="estimator.train"):
        assert [d.name for d in load_drives([no_fix, good], 16, fov)] == ["good.mcap"]
    assert f"{no_fix}: no frame with both a TRUE heading and the true sun ({why}" in caplog.text
    assert "record with a GNSS" in caplog.text
    with pytest.raises(TrainingDataError, match=f"{no_fix}: {why}"):
        load_drives([no_fix], 16, fov)


@pytest.mark.parametrize("ref", [HeadingRef.RELATIVE, HeadingRef.MAGNETIC])
def test_frames_without_a_true_heading_do_not_train(tmp_path, ref):
    # Their yaws are turned from true north by the start heading or the declination, the truth is
    # not: together they are inconsistent targets. Read here without the ground-truth wrapper
    # (which drops such truths too), so training's own rule is what is tested.
    import dataclasses
    from functools import partial

    from estimator.train import load_drives
    from replay.native import LogWriter
    from replay.sources import open_frames

    fov = math.radians(PAPER_CROP_FOV_DEG)
    frames = _frames(4, 0)
    mixed = frames[:2] + [dataclasses.replace(f, attitude=Attitude(f.attitude.heading_rad, ref)) for f in frames[2:]]
    assert load_drive(mixed, "d", 16, fov).images.shape[0] == 2
    p = tmp_path / "not_true.mcap"
    with LogWriter(p) as w:
        for f in mixed[2:]:
            w.write_frame(f)
    assert all(f.sun_enu_truth is not None for f in open_frames(p, ground_truth=False))
    with pytest.raises(TrainingDataError, match="TRUE heading"):
        load_drives([p], 16, fov, read_frames=partial(open_frames, ground_truth=False))

def test_resume_with_another_preset_is_refused(logs, tmp_path):
    out = tmp_path / "model"
    train(logs, out, TrainConfig(preset="tiny", max_steps=1, batch_windows=1))
    with pytest.raises(ValidationError, match="preset"):
        train(logs, out, TrainConfig(preset="fast", max_steps=2, batch_windows=1))


def test_hard_share_draws_drives_by_their_running_error():
    drives = [load_drive(_frames(10, i), f"d{i}", crop_size=16, crop_fov_rad=math.radians(17.6)) for i in range(2)]
    sampler = WindowSampler(drives, 8, 4, 16, subset_prob=0.0, rng=np.random.default_rng(0), hard_share=1.0)
    assert (sampler.err_deg == WindowSampler.UNSEEN_ERR_DEG).all()  # unseen drives count as hard
    for _ in range(60):  # drive 0 solved, drive 1 not (0.7^60 of the unseen prior is left)
        sampler.record(np.array([0, 1]), np.array([1.0, 60.0]))
    assert sampler.err_deg[0] == pytest.approx(1.0, abs=1e-3) and sampler.err_deg[1] == pytest.approx(60.0, abs=1e-3)
    drawn = sampler.sample(200).drive
    assert 0.9 < np.mean(drawn == 1) < 1.0  # 60:1 odds, and drive 0 still drawn
    uniform = WindowSampler(drives, 8, 4, 16, 0.0, np.random.default_rng(0), hard_share=0.0)
    uniform.err_deg[:] = sampler.err_deg
    assert 0.35 < np.mean(uniform.sample(200).drive == 1) < 0.65


def _relative_sun(batch, b):
    """Per token: the sun's azimuth from the crop's view direction (rad) and its elevation. A
    mirror turns the first to the other side and keeps the second."""
    from rig.geometry import az_el_from_enu, wrap_pi

    az, el = az_el_from_enu(batch.truth[b])
    newest_yaw = batch.yaw[b] - batch.angles[b, :, 0]  # every token's: yaw minus its relative yaw
    assert np.allclose(wrap_pi(newest_yaw - newest_yaw[0]), 0.0, atol=1e-6)  # float32 angles
    return wrap_pi(az - batch.yaw[b] - batch.angles[b, :, 1]), el


def _ramp_drive(seed):
    """A drive whose frames are a left-to-right ramp, so a crop's content tells left from right."""
    ramp = np.broadcast_to(np.linspace(0, 255, 128).astype(np.uint8)[None, :, None], (80, 128, 3)).copy()
    frames = [replace(f, image_bgr=ramp) for f in _frames(10, seed, sun_enu=(0.48, 0.36, 0.8))]
    return load_drive(frames, "d", crop_size=16, crop_fov_rad=math.radians(17.6))


def test_mirrored_window_is_the_mirror_world():
    drive = _ramp_drive(1)
    kw = dict(frames=8, crops=4, crop_size=16, subset_prob=0.0)
    plain = WindowSampler([drive], rng=np.random.default_rng(5), **kw).sample(1)
    mirrored = WindowSampler([drive], rng=np.random.default_rng(5), mirror_share=1.0, **kw).sample(1)
    # The same draws, mirrored: crops flipped, headings and horizontal angles negated, east negated.
    assert np.array_equal(mirrored.crops, plain.crops[:, :, :, ::-1])
    assert mirrored.crops[0, 0, 0, 0, 0] > mirrored.crops[0, 0, 0, -1, 0]  # brighter on the left now
    assert np.allclose(mirrored.angles[..., 2], plain.angles[..., 2])
    assert np.allclose(mirrored.angles[..., :2], -plain.angles[..., :2])
    assert np.allclose(mirrored.truth, plain.truth * [-1.0, 1.0, 1.0])
    rel_plain, el_plain = _relative_sun(plain, 0)
    rel_mirror, el_mirror = _relative_sun(mirrored, 0)
    assert np.allclose(rel_mirror, -rel_plain) and el_mirror == pytest.approx(el_plain)
    assert np.abs(rel_plain).max() > 0.1  # the check above is not 0 == -0


class _CountingRng:
    """A generator that counts its ``random()`` draws (the kind the mirror decision takes)."""

    def __init__(self, seed):
        self._rng, self.randoms = np.random.default_rng(seed), 0

    def random(self, *args, **kwargs):
        self.randoms += 1
        return self._rng.random(*args, **kwargs)

    def __getattr__(self, name):
        return getattr(self._rng, name)


def test_mirror_share_mirrors_its_share_and_draws_nothing_when_off():
    drive = _ramp_drive(2)
    kw = dict(frames=8, crops=4, crop_size=16, subset_prob=0.3)
    # Off, no draw is taken for it, so runs without mirroring draw the stream they always did
    # (one random() per window: the subset decision). On, however rarely, one more per window.
    for share, per_window in ((0.0, 1), (1e-12, 2)):
        rng = _CountingRng(3)
        WindowSampler([drive], rng=rng, mirror_share=share, **kw).sample(20)
        assert rng.randoms == 20 * per_window
    half = WindowSampler([drive], rng=np.random.default_rng(3), mirror_share=0.5, **kw).sample(400)
    mirrored = half.crops[:, :, 0, 0, 0] > half.crops[:, :, 0, -1, 0]  # darker to the right: flipped
    assert (mirrored == mirrored[:, :1]).all()  # a window is mirrored whole
    assert 0.4 < mirrored[:, 0].mean() < 0.6


@pytest.mark.slow
def test_resume_with_another_mirror_share_is_refused_also_from_a_checkpoint_before_it(logs, tmp_path):
    out = tmp_path / "model"
    train(logs, out, TrainConfig(preset="tiny", max_steps=1, batch_windows=1, mirror_share=0.0))
    # Mirroring became the default after such runs began, so their own command now asks for it:
    # the refusal names the setting to add.
    with pytest.raises(ValidationError, match=r"--mirror-share 0.0, not 0.5\. .* with `--mirror-share 0.0`"):
        train(logs, out, TrainConfig(preset="tiny", max_steps=2, batch_windows=1))
    # A checkpoint that predates the setting mirrored nothing: resuming it with mirroring would
    # make a contract that says it mirrored all along.
    state = torch.load(out / CHECKPOINT, weights_only=False)
    del state["config"]["mirror_share"]
    torch.save(state, out / CHECKPOINT)
    with pytest.raises(ValidationError, match="--mirror-share 0.0, not 0.5"):
        train(logs, out, TrainConfig(preset="tiny", max_steps=2, batch_windows=1))
    # Nor did it draw live windows.
    with pytest.raises(ValidationError, match="--live-share 0.0, not 0.5"):
        train(logs, out, TrainConfig(preset="tiny", max_steps=2, batch_windows=1, mirror_share=0.0, live_share=0.5))
    # Nor did it train with the tail loss.
    with pytest.raises(ValidationError, match="--tail-weight 0.0, not 1.0"):
        train(logs, out, TrainConfig(preset="tiny", max_steps=2, batch_windows=1, mirror_share=0.0, tail_weight=1.0))
    # Nor did it average its weights: its export would be the average of only the resumed steps.
    with pytest.raises(ValidationError, match="--ema-decay 0.0, not 0.9"):
        train(logs, out, TrainConfig(preset="tiny", max_steps=2, batch_windows=1, mirror_share=0.0, ema_decay=0.9))
    # Given as the refusal says, it resumes.
    train(logs, out, TrainConfig(preset="tiny", max_steps=2, batch_windows=1, mirror_share=0.0))
    assert torch.load(out / CHECKPOINT, weights_only=False)["step"] == 2


def test_the_cli_and_the_library_train_with_the_same_defaults():
    # argparse takes its defaults from TrainConfig (estimator/recipe.py, no torch); a default
    # written into the parser again would train two recipes under one name.
    from rig.cli import build_parser

    args = build_parser().parse_args(["train", "x.mcap", "--out", "m"])
    cfg = TrainConfig()
    for flag, key in (("preset", "preset"), ("batch", "batch_windows"), ("lr", "lr"), ("hard_share", "hard_share"),
                      ("mirror_share", "mirror_share"), ("live_share", "live_share"), ("precision", "precision"),
                      ("tail_weight", "tail_weight"), ("tail_margin", "tail_margin_deg"),
                      ("ema_decay", "ema_decay"), ("seed", "seed"), ("layers", "layers"),
                      ("minutes", "minutes"), ("crop_fov", "crop_fov_deg")):
        assert getattr(args, flag) == getattr(cfg, key), flag


def test_the_cli_takes_one_crop_angle_or_a_list_and_refuses_what_no_crop_spans(capsys):
    from rig.cli import build_parser

    def crop_fov(text):
        return build_parser().parse_args(["train", "x.mcap", "--out", "m", "--crop-fov", text]).crop_fov

    assert crop_fov("26") == 26.0 and crop_fov("17.6,26") == (17.6, 26.0)
    for bad in ("17.6,x", "180", "17.6,180", "17.6,,26", "0", "nan"):
        with pytest.raises(SystemExit):
            crop_fov(bad)
        assert f"expected an angle in (0, 180) deg or a comma-separated list of them, got '{bad}'" \
            in capsys.readouterr().err, bad


@pytest.mark.parametrize("share", ["mirror_share", "live_share"])
def test_a_window_share_is_refused_outside_a_share(logs, tmp_path, share):
    with pytest.raises(ValidationError, match=share):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", max_steps=1, **{share: 1.5}))


def _turning_drive(n, fps):
    """A drive of n frames at fps whose heading turns 3 deg a frame, then holds (a turn, a straight)."""
    frames = [replace(f, t_mono_s=i / fps, attitude=Attitude(math.radians(3.0 * min(i, 12)), HeadingRef.TRUE))
              for i, f in enumerate(_frames(n, 0))]
    return load_drive(frames, "d", crop_size=16, crop_fov_rad=math.radians(17.6))


def test_live_windows_are_the_windows_the_rig_picks():
    from rig.window import SpreadWindowPolicy

    drive = _turning_drive(60, fps=10.0)  # 6 s: longer than the policy's 4 s span
    kw = dict(frames=8, crops=4, crop_size=16, subset_prob=0.0)
    live = WindowSampler([drive], rng=np.random.default_rng(0), live_share=1.0, **kw).sample(1200)
    policy = SpreadWindowPolicy(n_frames=8)
    for idx in live.frame_index:
        newest = idx[-1]
        assert list(idx) == policy.select_indices(drive.t_s[: newest + 1], drive.yaw_rad[: newest + 1])
        assert drive.t_s[newest] - drive.t_s[idx[0]] <= policy.span_s
    # Every frame with a full window before it is a newest frame, about equally often: the rig's
    # first window (frames 0-7) too, which random frames of the drive (below) all but never give.
    newest = live.frame_index[:, -1]
    assert set(newest) == set(range(7, 60))
    counts = np.bincount(newest)[7:]  # 22.6 a frame on average
    assert counts.min() > 0.3 * counts.mean() and counts.max() < 2.0 * counts.mean()
    assert list(live.frame_index[newest == 7][0]) == list(range(8))
    uniform = WindowSampler([drive], rng=np.random.default_rng(0), **kw).sample(600)
    assert np.median(uniform.frame_index[:, -1]) > 50 and (uniform.frame_index[:, -1] == 7).sum() == 0
    # The newest frame's tokens are at relative yaw 0, the others at their frames' turn from it.
    for b in range(5):
        rel = live.angles[b, ::4, 0]
        want = drive.yaw_rad[live.frame_index[b]] - drive.yaw_rad[live.frame_index[b, -1]]
        np.testing.assert_allclose(rel, want, atol=1e-6)


def test_live_share_draws_its_share_and_nothing_when_off():
    drive = _turning_drive(24, fps=10.0)
    kw = dict(frames=8, crops=4, crop_size=16, subset_prob=0.3)
    for share, per_window in ((0.0, 1), (1e-12, 2)):  # as for mirror_share: off, the old stream
        rng = _CountingRng(3)
        WindowSampler([drive], rng=rng, live_share=share, **kw).sample(20)
        assert rng.randoms == 20 * per_window
    half = WindowSampler([drive], rng=np.random.default_rng(3), live_share=0.5, **kw).sample(400)
    early = half.frame_index[:, -1] <= 15  # live: 9 in 17; random frames of the drive: 1 in 57
    assert 0.2 < early.mean() < 0.33


def test_a_drive_too_short_for_a_live_window_draws_random_frames():
    drive = _turning_drive(6, fps=10.0)
    b = WindowSampler([drive], 8, 4, 16, 0.0, np.random.default_rng(0), live_share=1.0).sample(10)
    assert b.frame_index.shape == (10, 8) and (b.frame_index < 6).all()  # with repeats, as before


def test_schedule_warms_up_decays_and_never_rises_on_a_longer_resume():
    cfg = TrainConfig(lr=1e-3, warmup_steps=10)
    first = Schedule(minutes=10.0)
    lrs = [first.lr_at(s, 100, cfg) for s in range(101)]
    assert lrs[0] == pytest.approx(1e-4) and max(lrs) == pytest.approx(1e-3)
    assert np.all(np.diff(lrs[10:]) <= 0) and lrs[100] == pytest.approx(LR_FLOOR * 1e-3)
    # Stopped at step 80 of 100, resumed with twice the budget (about 200 steps in all): the new
    # segment starts at the rate the run stopped at and decays from there to the same floor.
    stop_lr = first.lr_at(80, 100, cfg)
    resumed = Schedule(start_step=80, start_lr=stop_lr, minutes=20.0)
    tail = [resumed.lr_at(s, 200, cfg) for s in range(80, 201)]
    assert tail[0] == pytest.approx(stop_lr) and np.all(np.diff(tail) <= 0)
    assert tail[-1] == pytest.approx(LR_FLOOR * 1e-3)


def test_checkpoint_keeps_schedule_and_drive_errors(logs, tmp_path):
    out = tmp_path / "model"
    train(logs, out, TrainConfig(preset="tiny", max_steps=4, batch_windows=2, warmup_steps=1, subset_prob=0.0))
    state = torch.load(out / CHECKPOINT, weights_only=False)
    assert state["schedule"]["start_step"] == 0
    errs = np.array(state["drive_err_deg"])
    assert errs.shape == (3,) and (errs < WindowSampler.UNSEEN_ERR_DEG).any()  # 8 full windows were recorded


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_both_precisions_train_and_export_float32(logs, tmp_path, precision):
    from estimator.runtime import OnnxModel

    out = train(logs, tmp_path / precision, TrainConfig(preset="tiny", max_steps=2, batch_windows=2,
                                                        warmup_steps=1, precision=precision))
    model = OnnxModel.load(out)
    crops = np.random.default_rng(0).integers(0, 256, (2, 32, 32, 3), dtype=np.uint8)
    emb = model.embed(crops)
    assert emb.dtype == np.float32 and np.isfinite(emb).all()


def test_bad_precision_and_hard_share_are_refused(logs, tmp_path):
    from rig.errors import ValidationError

    with pytest.raises(ValidationError, match="precision"):
        use_bf16("fp16")
    with pytest.raises(ValidationError, match="hard_share"):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", max_steps=1, hard_share=1.5))


@pytest.mark.slow
def test_init_starts_a_new_run_from_a_model_folders_weights(logs, tmp_path):
    from estimator import nets
    from rig.errors import ValidationError

    first = train(logs, tmp_path / "first", TrainConfig(preset="tiny", max_steps=3, batch_windows=2, warmup_steps=1))
    assert (first / "weights.npz").is_file()
    trained = torch.load(first / CHECKPOINT, weights_only=False)
    backbone, aggregator = nets.TINY.build(seed=123)  # different random weights
    load_weights(first, nets.TINY, backbone, aggregator)
    for module, key in ((backbone, "backbone"), (aggregator, "aggregator")):
        for name, value in module.state_dict().items():
            want = trained[key][name]
            if want.is_floating_point():  # stored as float16
                torch.testing.assert_close(value, want, atol=2e-3 * (1 + want.abs().max().item()), rtol=2e-3)
            else:
                assert torch.equal(value, want)
    # A fine-tuning run records where it started and continues from there, not from scratch.
    tuned = train(logs, tmp_path / "tuned", TrainConfig(preset="tiny", max_steps=1, batch_windows=2,
                                                        warmup_steps=1, init=str(first)))
    from estimator.runtime import OnnxModel

    training = OnnxModel.load(tuned).contract.training
    assert training["recipe"]["init"] == str(first)
    # The contract keeps the chain: the starting model's id and how it was trained.
    assert training["init"]["model_id"] == OnnxModel.load(first).model_id
    assert training["init"]["steps"] == 3
    with pytest.raises(ValidationError, match="architecture differs"):
        load_weights(first, nets.FAST, *nets.FAST.build())
    with pytest.raises(ValidationError, match="no weights.npz"):
        load_weights(tmp_path, nets.TINY, backbone, aggregator)


def test_a_fine_tune_of_an_int8_model_records_that_it_started_from_an_int8_copy(tiny_model_dir, tmp_path):
    # An int8 model (sunrig quantize) carries its float model's weights.npz, which --init starts
    # from; the fine-tuned model is float. Its contract's training.init named the int8 model's id
    # and the float model's command, and nothing said the start was an int8 copy.
    from estimator.estimator import SunEstimator
    from estimator.quantize import calibration_crops, quantize_model
    from estimator.runtime import OnnxModel
    from estimator.train import _init_provenance

    model = OnnxModel.load(tiny_model_dir)
    crops = calibration_crops(SunEstimator(model), [_frames(10, 1)], n_crops=16)
    int8 = quantize_model(model, crops, tmp_path / "int8", record={"command": "sunrig quantize logs --out int8"})
    quantization = OnnxModel.load(int8).contract.training["quantization"]
    assert _init_provenance(int8)["quantization"] == quantization
    assert "quantization" not in _init_provenance(tiny_model_dir)


def test_an_init_model_with_an_invalid_contract_is_refused_with_trains_own_flag(tiny_model_dir, tmp_path):
    import json

    import onnx

    from estimator import nets
    from estimator.contract import AGGREGATOR_FILE, BACKBONE_FILE
    from estimator.train import check_init
    from rig.errors import ContractMismatch

    folder = tmp_path / "m"
    folder.mkdir()
    (folder / "weights.npz").write_bytes(b"")  # the contract is refused before the weights are read
    for name in (BACKBONE_FILE, AGGREGATOR_FILE):
        graph = onnx.load(str(tiny_model_dir / name))
        for prop in graph.metadata_props:
            if prop.key == "sunrig.contract":
                prop.value = json.dumps({**json.loads(prop.value), "training": None})
        onnx.save(graph, str(folder / name))
    # (No SHA256SUMS: loaded unchecked, as a hand-edited model is.)
    with pytest.raises(ContractMismatch) as info:
        check_init(folder, nets.TINY)
    # The contract's own remedy names replay's --model; `sunrig train` has no such flag.
    assert "training: expected a JSON object, got None" in str(info.value)
    assert str(info.value).endswith("or pass another --init"), str(info.value)


def test_an_init_whose_weights_are_no_archive_is_refused_without_numpys_pickle_advice(tiny_model_dir, tmp_path):
    import shutil

    from estimator import nets
    from estimator.train import check_init
    from rig.errors import ValidationError

    folder = shutil.copytree(tiny_model_dir, tmp_path / "m")
    (folder / "weights.npz").write_bytes(b"not a zip archive at all")
    with pytest.raises(ValidationError) as info:
        check_init(folder, nets.TINY)
    assert "weights.npz cannot be loaded (not an archive of arrays); re-export" in str(info.value)
    assert "allow_pickle" not in str(info.value)  # numpy's advice to load it unsafely


@pytest.mark.parametrize("extra_load, warned", [(3.0, True), (0.0, False)])
@pytest.mark.slow
def test_a_minutes_budget_on_a_shared_cpu_is_warned_about(logs, tmp_path, monkeypatch, caplog, extra_load, warned):
    import os

    monkeypatch.setattr(os, "getloadavg", lambda: (torch.get_num_threads() + extra_load, 0.0, 0.0))
    cfg = TrainConfig(preset="tiny", minutes=0.02, batch_windows=1, warmup_steps=1, checkpoint_every_s=0.0)
    with caplog.at_level("WARNING", logger="estimator.train"):
        train(logs, tmp_path / "m", cfg)
    busy = [r for r in caplog.records if "using the CPU" in r.getMessage()]
    assert len(busy) == (1 if warned else 0)  # once per run, however many checkpoints


def test_a_short_run_warms_up_in_a_tenth_of_it():
    # A 150-step fine-tune with the recipe's 300 warmup steps would end still warming up.
    cfg = TrainConfig(lr=1e-4, warmup_steps=300, max_steps=150)
    lrs = [Schedule().lr_at(s, 150, cfg) for s in range(151)]
    assert lrs[14] == pytest.approx(1e-4) and max(lrs) == pytest.approx(1e-4)
    # A --minutes run keeps its 300, also once its length is known (no jump at step 20).
    minutes = TrainConfig(lr=1e-4, warmup_steps=300, minutes=2.0)
    assert [Schedule().lr_at(s, total, minutes) for s, total in ((19, 10**9), (20, 200))] == pytest.approx(
        [1e-4 * 20 / 300, 1e-4 * 21 / 300])


@pytest.mark.slow
def test_more_steps_for_a_finished_run_decay_from_where_it_stopped(logs, tmp_path):
    out = tmp_path / "m"
    cfg = TrainConfig(preset="tiny", max_steps=20, batch_windows=1, lr=1e-3, warmup_steps=2)
    train(logs, out, cfg)
    lr_end = Schedule().lr_at(19, 20, cfg)
    train(logs, out, replace(cfg, max_steps=40))
    state = torch.load(out / CHECKPOINT, weights_only=False)
    # A new segment from the rate it stopped at (the old one's end), not the old cosine stretched
    # over 40 steps, which would lift the rate back to about half the peak.
    assert state["schedule"]["start_step"] == 20 and state["schedule"]["start_lr"] == pytest.approx(lr_end)


@pytest.mark.slow
def test_a_fine_tune_keeps_the_suns_and_the_crop_count_of_the_model_it_started_from(logs, tmp_path):
    from estimator.runtime import OnnxModel
    from estimator.train import export_checkpoint

    first = train(logs, tmp_path / "first", TrainConfig(preset="tiny", max_steps=2, batch_windows=1))
    start = export_checkpoint(first, tmp_path / "start", run_crops_per_frame=6)  # runs with 6, as shipped runs 8
    low_sun = _write_logs(tmp_path / "own", 2, sun_enu=(0.0, 0.96, 0.28))  # 16.3 deg up
    tune = TrainConfig(preset="tiny", max_steps=2, batch_windows=1, init=str(start))
    tuned = train(low_sun, tmp_path / "tuned", tune)
    contract = OnnxModel.load(tuned).contract
    assert contract.training["data"]["sun_elevation_deg"] == [16.3, 16.3]  # its own drives
    assert contract.trained_sun_elevation_deg == (16.3, 53.1)  # and the suns its start had seen
    assert contract.crops_per_frame == 6
    assert OnnxModel.load(export_checkpoint(tuned, tmp_path / "exported")).contract.crops_per_frame == 6
    # A model fine-tuned before the start's range was recorded at the top of `init` still unions it.
    old = replace(contract, training={**contract.training, "init": {"data": {"sun_elevation_deg": [40.0, 60.0]}}})
    assert old.trained_sun_elevation_deg == (16.3, 60.0)
    explicit = train(low_sun, tmp_path / "explicit", TrainConfig(preset="tiny", max_steps=2, batch_windows=1,
                                                                   crops_per_frame=3, init=str(start)))
    assert OnnxModel.load(explicit).contract.crops_per_frame == 3
    # The start's range is read when the run starts: a start folder gone by the export loses nothing.
    import shutil

    again = train(low_sun, tmp_path / "again", replace(tune, max_steps=1))
    shutil.rmtree(start)
    train(low_sun, again, tune)
    assert OnnxModel.load(again).contract.trained_sun_elevation_deg == (16.3, 53.1)


@pytest.mark.slow
def test_the_crop_angle_is_the_paper_s_or_the_given_one_and_a_fine_tune_keeps_its_start_s(logs, tmp_path):
    from estimator.runtime import OnnxModel

    one = TrainConfig(preset="tiny", max_steps=1, batch_windows=1)
    paper = train(logs, tmp_path / "paper", one)
    assert OnnxModel.load(paper).contract.crop_fov_deg == pytest.approx(PAPER_CROP_FOV_DEG)
    wide = train(logs, tmp_path / "wide", replace(one, crop_fov_deg=26.0))
    assert OnnxModel.load(wide).contract.crop_fov_deg == 26.0
    # A model sees its crops at one angular scale: a fine-tune keeps its start's unless told.
    tuned = train(logs, tmp_path / "tuned", replace(one, init=str(wide)))
    assert OnnxModel.load(tuned).contract.crop_fov_deg == 26.0
    told = train(logs, tmp_path / "told", replace(one, init=str(wide), crop_fov_deg=20.0))
    assert OnnxModel.load(told).contract.crop_fov_deg == 20.0
    # A resume keeps its run's, given or not, and refuses another before loading anything.
    train(logs, wide, replace(one, max_steps=2))
    assert OnnxModel.load(wide).contract.crop_fov_deg == 26.0
    with pytest.raises(ValidationError, match="--crop-fov 26, not 17.6"):
        train(logs, wide, replace(one, max_steps=3, crop_fov_deg=PAPER_CROP_FOV_DEG))
    # Two scales: recorded as a list, kept by a fine-tune and by a resume like one angle is.
    mixed = train(logs, tmp_path / "mixed", replace(one, crop_fov_deg=(17.6, 26.0)))
    assert OnnxModel.load(mixed).contract.crop_fov_deg == [17.6, 26.0]
    assert OnnxModel.load(train(logs, tmp_path / "tuned2", replace(one, init=str(mixed)))).contract.crop_fov_deg \
        == [17.6, 26.0]
    with pytest.raises(ValidationError, match="--crop-fov 17.6,26, not 26"):
        train(logs, mixed, replace(one, max_steps=2, crop_fov_deg=26.0))


def test_a_mixed_window_cuts_each_crop_from_its_angle_s_view():
    """Crops of two angles in one window: each is cut from the view scaled for its angle, and its
    view angle is that of the pixel at its centre in the source frame (a gradient image says which)."""
    gradient = np.broadcast_to((np.arange(128) * 2).astype(np.uint8)[None, :, None], (80, 128, 3))  # 2 x column
    frames = [replace(f, image_bgr=np.ascontiguousarray(gradient)) for f in _frames(4, 0)]
    narrow, wide = math.radians(17.6), math.radians(40.0)
    drive = load_drive(frames, "d", crop_size=16, crop_fov_rad=[narrow, wide])
    b = WindowSampler([drive], frames=4, crops=3, crop_size=16, subset_prob=0.0,
                      rng=np.random.default_rng(1)).sample(30)
    # 3 crops a frame, 2 angles: the first two of each frame narrow, the third wide.
    col = b.crops[:, :, 8, 7:9, 0].astype(np.float64).mean(-1) / 2.0  # source column at each crop's centre
    horizontal = np.degrees(np.arctan((col - 64.0) / 100.0))
    np.testing.assert_allclose(np.degrees(b.angles[..., 1]), horizontal, atol=1.0)
    side = np.abs(b.crops[:, :, 8, 15, 0].astype(np.float64) - b.crops[:, :, 8, 0, 0]) / 2.0  # columns spanned
    narrow_side, wide_side = (2 * 100.0 * math.tan(a / 2) for a in (narrow, wide))
    per_frame = side.reshape(30, 4, 3)
    np.testing.assert_allclose(per_frame[..., :2], narrow_side * 15 / 16, rtol=0.15)
    np.testing.assert_allclose(per_frame[..., 2], wide_side * 15 / 16, rtol=0.15)


def test_more_crop_angles_than_crops_are_refused(logs, tmp_path):
    with pytest.raises(ValidationError, match="at most one angle per crop"):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", max_steps=1, crops_per_frame=2,
                                                crop_fov_deg=(17.6, 26.0, 40.0)))
    assert not (tmp_path / "m").exists()


@pytest.mark.parametrize("deg", [-1.0, 180.0, float("nan"), (17.6, 0.0), (17.6, 180.0)])
def test_a_crop_angle_outside_a_half_turn_is_refused(logs, tmp_path, deg):
    with pytest.raises(ValidationError, match="crop fov"):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", max_steps=1, crop_fov_deg=deg))
    assert not (tmp_path / "m").exists()


@pytest.mark.slow
def test_out_must_be_this_runs_folder_or_a_new_one(logs, tmp_path):
    cfg = TrainConfig(preset="tiny", max_steps=1, batch_windows=1, lr=3e-4)
    a_file = tmp_path / "clip.mp4"
    a_file.write_bytes(b"video")
    with pytest.raises(ValidationError, match="is a file"):
        train(logs, a_file, cfg)
    # A folder of logs, or a model without a run: overwriting it would lose what it holds.
    with pytest.raises(ValidationError, match=r"already holds files \(clip.mp4, drive_0.mcap, drive_1.mcap, \.\.\.\)"):
        train(logs, logs[0].parent, cfg)
    out = tmp_path / "run"
    train(logs, out, cfg)
    (out / CHECKPOINT).rename(tmp_path / "kept.pt")
    with pytest.raises(ValidationError, match="backbone.onnx.*no training run"):
        train(logs, out, cfg)
    (tmp_path / "kept.pt").rename(out / CHECKPOINT)
    # Another run's folder: resuming it with another rate, seed or data would make a contract that lies.
    with pytest.raises(ValidationError, match=r"--lr 0.0003, not 0.001.*--seed 0, not 5.*another --out"):
        train(logs, out, replace(cfg, max_steps=2, lr=1e-3, seed=5))
    out_on_data = tmp_path / "run_on_data"
    train(logs, out_on_data, replace(cfg, data={"fingerprint": data_fingerprint(logs), "logs": 3}))
    # Its own command is not the remedy when a folder it named has changed (a drive recorded into
    # it since): the refusal told to run the very command it refused.
    with pytest.raises(ValidationError, match=r"logs with fingerprint \w+ \(3 logs\), not \w+ \(2 logs: a log added, "
                                              r"removed or changed since the run began\)\. To resume it, run its own "
                                              r"command \(`.*`\) on the logs it began with;"):
        train(logs[:2], out_on_data, replace(cfg, max_steps=2, data={"fingerprint": data_fingerprint(logs[:2]),
                                                                     "logs": 2}))


def test_the_fingerprint_of_native_logs_is_their_names_and_sizes_as_shipped_models_recorded(tmp_path):
    # The shipped model's contract records one of .mcap logs: the hash is the one it was made with
    # (file names and sizes in path order), or a fine-tune from the same logs could not be matched.
    (tmp_path / "x").mkdir()
    (tmp_path / "y").mkdir()
    (tmp_path / "x" / "drive_1.mcap").write_bytes(bytes(1000))
    (tmp_path / "y" / "drive_0.mcap").write_bytes(bytes(25))
    assert data_fingerprint([tmp_path / "y" / "drive_0.mcap", tmp_path / "x" / "drive_1.mcap"]) == "fe126cf1436d"
    assert data_fingerprint([tmp_path / "x" / "drive_1.mcap"]) == "7fd958fb7481"


def test_a_kitti_drive_has_one_fingerprint_by_either_folder_from_the_files_it_reads(tmp_path, monkeypatch):
    # A drive is a folder: its "size" was the folder entry's (4096 bytes), so changed images went
    # unnoticed, and the same drive named by its date folder had another fingerprint than by its
    # drive folder (both taken by sunrig train), and a resume named the other way was refused.
    import builtins
    import io
    import shutil

    from tests.test_kitti import DRIVE, make_drive

    date = make_drive(tmp_path / "kitti", 3)
    drive = date / DRIVE
    fingerprint = data_fingerprint([drive])
    assert data_fingerprint([date]) == fingerprint
    # Names are the drive's own, not where it sits: a copy elsewhere is the same data.
    copy = shutil.copytree(date, tmp_path / "elsewhere" / date.name)
    assert data_fingerprint([copy]) == data_fingerprint([copy / DRIVE]) == fingerprint
    # Files the reader does not use do not count (velodyne points deleted to save space).
    (drive / "velodyne_points").mkdir()
    (drive / "velodyne_points" / "timestamps.txt").write_text("2011-09-26 13:02:25.0\n")
    assert data_fingerprint([drive]) == fingerprint
    # Each file it reads does, by its size: an image, an OXTS record, the calibration.
    for changed in (drive / "image_02" / "data" / "0000000001.png", drive / "oxts" / "data" / "0000000002.txt",
                    date / "calib_cam_to_cam.txt"):
        kept = changed.read_bytes()
        changed.write_bytes(kept + b"\n")
        assert data_fingerprint([date]) == data_fingerprint([drive]) != fingerprint, changed
        changed.write_bytes(kept)
    assert data_fingerprint([drive]) == fingerprint
    # Thousands of images a drive: they are stat-ed, never read.
    real_open = io.open

    def no_images(file, *args, **kwargs):
        assert not str(file).endswith(".png"), f"read {file}"
        return real_open(file, *args, **kwargs)

    monkeypatch.setattr(io, "open", no_images)
    monkeypatch.setattr(builtins, "open", no_images)
    assert data_fingerprint([date]) == fingerprint


@pytest.mark.slow
def test_a_run_switched_from_steps_to_minutes_decays_from_where_it_stopped(logs, tmp_path):
    # The same --minutes as the steps run carried (as the CLI's default does): only --steps went.
    # 18 s, far more than 4 tiny steps take even on a loaded machine: a budget the steps run had
    # already spent would leave the minutes run nothing to resume (6 s once did, beside a benchmark).
    cfg = TrainConfig(preset="tiny", max_steps=4, batch_windows=1, minutes=0.3)
    out = train(logs, tmp_path / "m", cfg)
    train(logs, out, replace(cfg, max_steps=0))
    assert torch.load(out / CHECKPOINT, weights_only=False)["schedule"]["start_step"] == 4  # not back to warmup


@pytest.mark.slow
def test_a_fine_tune_checkpointed_before_its_crop_count_was_recorded_keeps_its_starts(logs, tmp_path):
    from estimator.runtime import OnnxModel
    from estimator.train import export_checkpoint

    first = train(logs, tmp_path / "first", TrainConfig(preset="tiny", max_steps=1, batch_windows=1))
    start = export_checkpoint(first, tmp_path / "start", run_crops_per_frame=6)
    tune = TrainConfig(preset="tiny", max_steps=1, batch_windows=1, init=str(start))
    tuned = train(logs, tmp_path / "tuned", tune)
    state = torch.load(tuned / CHECKPOINT, weights_only=False)
    del state["run_crops_per_frame"]  # as an older sunrig wrote it
    torch.save(state, tuned / CHECKPOINT)
    train(logs, tuned, replace(tune, max_steps=2))
    assert OnnxModel.load(tuned).contract.crops_per_frame == 6


def test_a_refused_run_leaves_no_folder(tmp_path):
    no_truth = _write_logs(tmp_path / "logs", 1, truth=False)
    with pytest.raises(TrainingDataError):
        train(no_truth, tmp_path / "new", TrainConfig(preset="tiny", max_steps=1, batch_windows=1))
    assert not (tmp_path / "new").exists()


def test_a_finished_run_is_not_exported_again(logs, tmp_path):
    cfg = TrainConfig(preset="tiny", max_steps=2, batch_windows=1)
    out = train(logs, tmp_path / "m", cfg)
    contract = (out / "backbone.onnx").read_bytes()  # the contract is in its metadata
    stamp = (out / "backbone.onnx").stat().st_mtime_ns
    assert train(logs, out, cfg) == out
    assert (out / "backbone.onnx").read_bytes() == contract and (out / "backbone.onnx").stat().st_mtime_ns == stamp


@pytest.mark.slow
def test_the_tail_loss_enters_training_only_when_weighted(logs, tmp_path, monkeypatch):
    from estimator import nets
    from estimator.runtime import OnnxModel

    margins = []
    real = nets.tail_loss

    def counted(v_pred, v_gt, margin_rad, mask):
        margins.append(margin_rad)
        counted_rows.append(mask.tolist())
        return real(v_pred, v_gt, margin_rad, mask)

    counted_rows = []
    monkeypatch.setattr(nets, "tail_loss", counted)
    train(logs, tmp_path / "off", TrainConfig(preset="tiny", max_steps=2, batch_windows=1))
    assert margins == []  # the paper's loss alone: the recipe as before, not a zero-weighted extra term
    out = train(logs, tmp_path / "on", TrainConfig(preset="tiny", max_steps=4, batch_windows=8, tail_weight=1.0,
                                                   tail_margin_deg=20.0, subset_prob=0.5))
    assert margins == [pytest.approx(math.radians(20.0))] * 4  # on every step's windows, in radians
    # Full windows count, subset windows do not (a draw of 32 windows has both).
    rows = [row for step in counted_rows for row in step]
    assert len(rows) == 32 and 0 < sum(rows) < 32
    recipe = OnnxModel.load(out).contract.training["recipe"]
    assert (recipe["tail_weight"], recipe["tail_margin_deg"]) == (1.0, 20.0)  # the contract says how it trained


@pytest.mark.parametrize("weight, margin", [(-1.0, 15.0), (math.nan, 15.0), (1.0, -1.0), (1.0, 181.0)])
def test_a_bad_tail_setting_is_refused_before_training(logs, tmp_path, weight, margin):
    with pytest.raises(ValidationError, match="tail (weight|margin): expected"):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", max_steps=1, tail_weight=weight,
                                                tail_margin_deg=margin))
    assert not (tmp_path / "m").exists()


@pytest.mark.slow
def test_a_run_may_stack_more_transformer_layers_than_its_preset(logs, tmp_path):
    from estimator import nets
    from estimator.runtime import OnnxModel
    from estimator.train import export_checkpoint, load_weights

    out = train(logs, tmp_path / "deep", TrainConfig(preset="tiny", layers=3, max_steps=2, batch_windows=1))
    contract = OnnxModel.load(out).contract
    assert contract.architecture["layers"] == 3 and contract.training["recipe"]["layers"] == 3
    deep = nets.NetConfig.from_architecture(contract.architecture)
    backbone, aggregator = deep.build()
    load_weights(out, deep, backbone, aggregator)  # the weights are those of three layers
    assert len(aggregator.layers) == 3
    # Re-exported from the checkpoint, it keeps its depth.
    again = export_checkpoint(tmp_path / "deep", tmp_path / "again")
    assert OnnxModel.load(again).contract.architecture["layers"] == 3
    # A resume without the depth would train another network under the run's name.
    with pytest.raises(ValidationError, match="--layers 3, not 0"):
        train(logs, tmp_path / "deep", TrainConfig(preset="tiny", max_steps=3, batch_windows=1))
    # A fine-tune from it is told to name the depth too.
    with pytest.raises(ValidationError, match="--preset tiny --layers 3"):
        train(logs, tmp_path / "fine", TrainConfig(preset="tiny", init=str(out), max_steps=1, batch_windows=1))
    # And one from a model of its preset's depth, to leave the flag out.
    shallow = train(logs, tmp_path / "shallow", TrainConfig(preset="tiny", max_steps=1, batch_windows=1))
    with pytest.raises(ValidationError, match="--preset tiny without --layers"):
        train(logs, tmp_path / "fine", TrainConfig(preset="tiny", layers=3, init=str(shallow), max_steps=1,
                                                   batch_windows=1))


def test_an_init_of_another_preset_names_that_preset_and_no_layers_flag_not_given():
    # --preset tiny --init shipped was told "pass --preset fast without --layers", with no --layers
    # given: the depth differs only because the presets do.
    from estimator import nets
    from estimator.models import resolve_init_dir
    from estimator.train import check_init

    shipped = resolve_init_dir("shipped")
    with pytest.raises(ValidationError, match=r"; pass --preset fast$"):
        check_init(shipped, nets.TINY)
    with pytest.raises(ValidationError, match=r"; pass --preset fast without --layers$"):  # given, it is named
        check_init(shipped, replace(nets.TINY, layers=3))


@pytest.mark.slow
def test_naming_the_presets_own_depth_is_the_same_run(logs, tmp_path):
    from estimator import nets

    out = tmp_path / "m"
    train(logs, out, TrainConfig(preset="tiny", max_steps=2, batch_windows=1))
    # tiny has one layer: --layers 1 resumes the run made without the flag.
    train(logs, out, TrainConfig(preset="tiny", layers=nets.TINY.layers, max_steps=3, batch_windows=1))
    assert torch.load(out / CHECKPOINT, weights_only=False)["step"] == 3


@pytest.mark.parametrize("layers", [-1, 1.5])
def test_a_bad_layer_count_is_refused_before_training(logs, tmp_path, layers):
    with pytest.raises(ValidationError, match="layers: expected a count"):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", layers=layers, max_steps=1))
    assert not (tmp_path / "m").exists()


def test_the_weight_average_is_the_decayed_mean_of_every_step_with_a_ramped_decay():
    from estimator.train import WeightAverage

    net = torch.nn.Sequential(torch.nn.Linear(2, 1), torch.nn.BatchNorm1d(1))
    with torch.no_grad():
        net[0].weight.fill_(0.0)
    avg = WeightAverage(0.5, {"net": net})
    for value in (1.0, 2.0, 3.0, 4.0):
        with torch.no_grad():
            net[0].weight.fill_(value)  # in place, as the optimiser steps
        net[1].num_batches_tracked += 1
        avg.update()
    # By hand: the ramp keeps 2/11, 3/12, 4/13, 5/14 of the average, all below the decay 0.5:
    # 9/11 = 0.8182; 0.25 * 0.8182 + 0.75 * 2 = 1.7045; 4/13 * 1.7045 + 9/13 * 3 = 2.6014;
    # 5/14 * 2.6014 + 9/14 * 4 = 3.5005.
    saved = avg.state_dict()
    assert saved["updates"] == 4
    assert saved["net"]["0.weight"].flatten().tolist() == pytest.approx([3.5005] * 2, abs=1e-4)
    assert int(saved["net"]["1.num_batches_tracked"]) == 4  # a counter is the latest, not averaged
    # A decay below the ramp's first 2/11 caps it from the first update: each keeps a tenth.
    capped = WeightAverage(0.1, {"net": net})  # starts from 4.0
    with torch.no_grad():
        net[0].weight.fill_(0.0)
    capped.update()
    capped.update()
    assert capped.state_dict()["net"]["0.weight"].flatten().tolist() == pytest.approx([0.04] * 2)
    # Resumed from its saved state it goes on from there.
    again = WeightAverage(0.5, {"net": net}, saved)
    assert again.state_dict()["net"]["0.weight"].flatten().tolist() == pytest.approx([3.5005] * 2, abs=1e-4)
    assert again.updates == 4


def test_a_run_with_ema_decay_exports_its_average_at_the_end_and_from_the_checkpoint(logs, tmp_path):
    from estimator.runtime import OnnxModel
    from estimator.train import export_checkpoint

    # A high rate, so that six steps move the weights well beyond float16's rounding.
    cfg = TrainConfig(preset="tiny", max_steps=3, batch_windows=2, warmup_steps=1, lr=0.05, ema_decay=0.99)
    train(logs, tmp_path / "m", cfg)
    out = train(logs, tmp_path / "m", replace(cfg, max_steps=6))  # resumed: the average goes on
    state = torch.load(out / CHECKPOINT, weights_only=False)
    assert state["weight_average"]["updates"] == 6
    with np.load(out / "weights.npz") as z:
        exported = {k: z[k].astype(np.float32) for k in z.files if k.startswith("backbone/")}
    averaged = {f"backbone/{k}": v.float().numpy() for k, v in state["weight_average"]["backbone"].items()}
    last = {f"backbone/{k}": v.float().numpy() for k, v in state["backbone"].items()}
    key = "backbone/conv1.weight"
    np.testing.assert_allclose(exported[key], averaged[key], atol=5e-4)  # weights.npz is float16
    assert np.abs(exported[key] - last[key]).max() > 3e-3  # not the last step's weights
    assert OnnxModel.load(out).contract.training["recipe"]["ema_decay"] == 0.99
    again = export_checkpoint(out, tmp_path / "again")
    with np.load(again / "weights.npz") as z:
        np.testing.assert_array_equal(z[key].astype(np.float32), exported[key])


@pytest.mark.parametrize("decay", [-0.1, 1.0, math.nan])
def test_an_ema_decay_outside_0_to_1_is_refused_before_training(logs, tmp_path, decay):
    with pytest.raises(ValidationError, match="ema decay: expected a decay in"):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", max_steps=1, ema_decay=decay))
    assert not (tmp_path / "m").exists()


def test_a_checkpoint_that_fills_the_disk_is_an_os_error_naming_it_and_leaves_no_torn_copy(tmp_path, monkeypatch):
    # torch.save reports a full disk as a bare RuntimeError ("unexpected pos"): an internal error at
    # the CLI, with the torn temporary copy left to keep the disk full. Serialised in memory and
    # written by Python, the write says ENOSPC, which the CLI turns into one line (rig/cli.py).
    import errno
    from pathlib import Path

    from estimator.train import _save_checkpoint

    def disk_full(self, data):
        with open(self, "wb") as f:
            f.write(bytes(data)[:100])  # what fitted
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_bytes", disk_full)
    path = tmp_path / "checkpoint.pt"
    with pytest.raises(OSError) as info:
        _save_checkpoint(path, {"w": torch.zeros(1000)})
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(path)
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    _save_checkpoint(path, {"w": torch.arange(5.0)})  # and a checkpoint written so loads as before
    assert torch.equal(torch.load(path)["w"], torch.arange(5.0))


def test_export_only_refuses_a_folder_of_another_run_or_of_logs(tmp_path):
    # It overwrote another run's graphs (no longer its checkpoint's) or wrote among logs, where
    # --out and quantize --out refuse such folders.
    from estimator.train import CHECKPOINT, _refuse_export_over_others

    run, other, logs, model = (tmp_path / n for n in ("run", "other", "logs", "model"))
    for folder in (run, other, logs, model):
        folder.mkdir()
    (run / CHECKPOINT).write_bytes(b"x")
    (other / CHECKPOINT).write_bytes(b"x")
    (logs / "drive_0.mcap").write_bytes(b"x")
    (model / "backbone.onnx").write_bytes(b"x")
    with pytest.raises(ValidationError, match=r"holds another training run \(checkpoint.pt\)"):
        _refuse_export_over_others(other, run)
    with pytest.raises(ValidationError, match=r"holds logs \(drive_0.mcap\); pass a folder for the model"):
        _refuse_export_over_others(logs, run)
    for fine in (run, model, tmp_path / "new"):  # its own folder, a model alone (docs/model.md), a new one
        _refuse_export_over_others(fine, run)


# What torch 2.13 raises, word for word, when the CPU allocator is refused (provoked once by hand
# with torch.empty(10**13) on a machine without that much memory).
TORCH_ALLOC_FAILED = ("[enforce fail at alloc_cpu.cpp:127] err == 0. DefaultCPUAllocator: can't allocate memory: "
                      "you tried to allocate 39321600000 bytes. Error code 12 (Cannot allocate memory)")


def _refuse_memory(monkeypatch, exc):
    """Make every step's input allocation fail as ``exc``: where the real 39 GB allocation of
    `--batch 100000` failed, without asking for it."""
    from estimator import train as train_module

    def refused(self, crops_bgr):
        raise exc

    monkeypatch.setattr(train_module._Normaliser, "__call__", refused)


@pytest.mark.parametrize("exc", [RuntimeError(TORCH_ALLOC_FAILED),
                                 MemoryError("Unable to allocate 36.6 GiB for an array with shape (100000, 32, 32, 32, "
                                             "3) and data type float32")], ids=["torch", "numpy"])
def test_a_step_that_cannot_allocate_its_batch_is_one_line_saying_to_lower_batch(logs, tmp_path, monkeypatch,
                                                                                capsys, exc):
    # It was an internal error (exit 1) naming neither the batch nor what to do about it.
    from rig.cli import main

    _refuse_memory(monkeypatch, exc)
    out = tmp_path / "m"
    code = main(["train", *map(str, logs), "--out", str(out), "--preset", "tiny", "--batch", "3", "--steps", "1",
                 "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert "internal error" not in err[0] and "step 1 cannot allocate memory" in err[0], err[0]
    assert "3 windows x 32 crops (96 crops of 32 px" in err[0] and "36.6 GiB" in err[0], err[0]
    assert "pass a smaller --batch" in err[0] and "--crops" not in err[0], err[0]  # 4 crops a frame: the paper's
    assert not (out / CHECKPOINT).exists()
    monkeypatch.undo()
    # As the error says: a smaller batch in the same --out trains.
    assert main(["train", *map(str, logs), "--out", str(out), "--preset", "tiny", "--batch", "2", "--steps", "1",
                 "--quiet"]) == 0


def test_a_run_that_runs_out_of_memory_keeps_its_checkpoint_and_other_errors_stay_bugs(logs, tmp_path, monkeypatch):
    from estimator.train import BatchMemoryError

    out = tmp_path / "m"
    cfg = TrainConfig(preset="tiny", max_steps=2, batch_windows=2, crops_per_frame=6, warmup_steps=1)
    train(logs, out, cfg)
    saved = (out / CHECKPOINT).read_bytes()
    _refuse_memory(monkeypatch, RuntimeError(TORCH_ALLOC_FAILED))
    with pytest.raises(BatchMemoryError) as info:
        train(logs, out, replace(cfg, max_steps=4))
    message = str(info.value)
    assert "step 3 cannot allocate memory for its batch of 2 windows x 48 crops" in message, message
    assert "fewer --crops than 6" in message and "with a new --out" in message, message
    assert f"its checkpoint at step 2 in {out} is kept" in message, message
    assert (out / CHECKPOINT).read_bytes() == saved
    # Only an allocation that failed: any other RuntimeError is a bug, and says so as it did.
    _refuse_memory(monkeypatch, RuntimeError("mat1 and mat2 shapes cannot be multiplied (96x48 and 64x48)"))
    with pytest.raises(RuntimeError, match="mat1 and mat2") as info:
        train(logs, out, replace(cfg, max_steps=4))
    assert not isinstance(info.value, BatchMemoryError)


def test_a_batch_whose_crops_alone_exceed_the_machines_memory_is_refused_before_loading(logs, tmp_path, monkeypatch):
    from estimator import train as train_module

    monkeypatch.setattr(train_module, "_memory_bytes", lambda: 2**30)  # a 1 GiB machine, swap included
    monkeypatch.setattr(train_module, "load_drives", None)  # refused before any data loads
    # 10 000 windows of 32 crops of 32 px are 0.9 GiB as bytes and 3.7 GiB as floats.
    with pytest.raises(train_module.BatchMemoryError, match=r"10000 windows x 32 crops \(320000 crops of 32 px\) "
                       r"needs at least 4.6 GiB .* more than the 1.0 GiB of memory and swap this machine has; "
                       r"pass a smaller --batch \(the recipe is 6\)$"):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", max_steps=1, batch_windows=10000))
    assert not (tmp_path / "m").exists()
    monkeypatch.undo()
    monkeypatch.setattr(train_module, "_memory_bytes", lambda: None)  # where the OS does not say: not checked
    monkeypatch.setattr(train_module, "load_drives", lambda *a, **k: pytest.fail("reached") or [])
    with pytest.raises(pytest.fail.Exception, match="reached"):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", max_steps=1, batch_windows=10000))


def _damage(path, how):
    """``path`` as a damaged checkpoint: cut short, emptied, or a torch file that is not a run's."""
    if how == "truncated":  # a copy cut short: torch's zip reader fails ("PytorchStreamReader failed ...")
        torch.save({"config": {"preset": "tiny"}, "backbone": {"w": torch.zeros(10_000)}}, path)
        path.write_bytes(path.read_bytes()[:1000])
    elif how == "empty":  # EOFError: Ran out of input
        path.write_bytes(b"")
    elif how == "foreign":  # a valid torch file without the run's state: KeyError 'config'
        torch.save({"weights": torch.zeros(3)}, path)
    else:  # a run's keys, but weights that fit no network of its preset (RuntimeError from load_state_dict)
        torch.save({"config": {"preset": "tiny"}, "backbone": {"w": torch.zeros(3)}, "aggregator": {},
                    "step": 2, "elapsed_s": 1.0, "optimizer": {}, "rng": {}, "torch_rng": torch.zeros(1)}, path)


@pytest.mark.parametrize("how", ["truncated", "empty", "foreign", "mismatched"])
def test_a_damaged_checkpoint_is_one_line_naming_it_on_resume_and_export(logs, tmp_path, capsys, monkeypatch, how):
    # It was an internal error (RuntimeError, EOFError or KeyError from torch.load or the state's keys).
    from estimator import train as train_module
    from rig.cli import main

    out = tmp_path / "m"
    out.mkdir()
    _damage(out / CHECKPOINT, how)
    monkeypatch.setattr(train_module, "load_drives", None)  # refused before any data loads
    for argv, then in (([*map(str, logs), "--out", str(out), "--preset", "tiny", "--steps", "3"],
                        "restore it from a copy to resume the run, or pass a new --out to train from the start"),
                       (["--out", str(out), "--export-only", str(tmp_path / "exported")],
                        "restore it from a copy to export it, or train again with a new --out")):
        code = main(["train", *argv, "--quiet"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1, err
        assert "internal error" not in err[0] and f"{out / CHECKPOINT} is damaged (" in err[0], err[0]
        assert err[0].endswith(then), err[0]
    assert not (tmp_path / "exported").exists()


def _diverging_loss_at(monkeypatch, call):
    """Make the window loss nan from its ``call``-th computation on (two a step: tokens, window)."""
    from estimator import nets

    real, calls = nets.sun_loss, []

    def loss(*args, **kw):
        calls.append(1)
        value = real(*args, **kw)
        return value * math.nan if len(calls) >= call else value

    monkeypatch.setattr(nets, "sun_loss", loss)


def test_a_loss_that_is_not_finite_stops_the_run_at_its_step_keeping_the_last_checkpoint(logs, tmp_path,
                                                                                      monkeypatch):
    from rig.errors import SunrigError

    out = tmp_path / "m"
    # A checkpoint after every step; the loss turns nan in step 3 (its 5th and 6th computations).
    cfg = TrainConfig(preset="tiny", max_steps=5, batch_windows=1, lr=1e-4, checkpoint_every_s=0.0)
    _diverging_loss_at(monkeypatch, 5)
    with pytest.raises(SunrigError) as info:
        train(logs, out, cfg)
    message = str(info.value)
    assert type(info.value).__name__ == "TrainingDivergedError", message
    assert message.startswith("train: training diverged at step 3: its loss became nan"), message
    assert "lower --lr than 0.0001 and a new --out" in message, message  # below the recipe's, which is not named
    assert f"its checkpoint at step 2 in {out} is kept" in message, message
    state = torch.load(out / CHECKPOINT, weights_only=False)
    assert state["step"] == 2 and not (out / "backbone.onnx").exists() and not (out / "weights.npz").exists()
    assert all(bool(torch.isfinite(t).all()) for t in state["backbone"].values() if t.is_floating_point())


def test_a_run_that_diverges_is_one_line_saying_to_lower_lr_and_writes_no_model(logs, tmp_path, capsys):
    # --lr 100 exited 0 with "model written" and weights beyond float16 (inf in weights.npz, nan in
    # the graphs' answers); --lr 1e6 was an internal error (the hard-drive sampler's errors were nan).
    from rig.cli import main

    for lr, said in (("100", "diverged by step 5: "), ("1e6", "diverged at step 2: its loss became nan")):
        out = tmp_path / f"m{lr}"
        code = main(["train", *map(str, logs), "--out", str(out), "--preset", "tiny", "--steps", "5",
                     "--batch", "1", "--lr", lr])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1, err
        assert "internal error" not in err[0] and "model written" not in err[0] and said in err[0], err[0]
        assert f"lower --lr than {float(lr):g} (the recipe's is 0.0005)" in err[0], err[0]
        assert "nothing was saved" in err[0], err[0]
        assert not (out / CHECKPOINT).exists() and not (out / "weights.npz").exists()


def _checkpoint_with_nan_weights(path):
    from dataclasses import asdict

    from estimator import nets

    backbone, aggregator = nets.TINY.build(seed=0)
    with torch.no_grad():
        next(iter(aggregator.parameters())).fill_(math.nan)
    opt = torch.optim.AdamW(list(backbone.parameters()) + list(aggregator.parameters()))
    torch.save({"config": asdict(TrainConfig(preset="tiny", max_steps=5, batch_windows=1, lr=100.0,
                                                crops_per_frame=4, crop_fov_deg=PAPER_CROP_FOV_DEG)),
                "backbone": backbone.state_dict(), "aggregator": aggregator.state_dict(),
                "optimizer": opt.state_dict(), "step": 4, "elapsed_s": 1.0,
                "rng": np.random.default_rng(0).bit_generator.state, "torch_rng": torch.get_rng_state()}, path)


def test_a_checkpoint_holding_nan_weights_is_neither_exported_nor_resumed(logs, tmp_path, capsys, monkeypatch):
    # A run before the divergence check wrote such checkpoints; --export-only made a model of them.
    from estimator import train as train_module
    from rig.cli import main

    out = tmp_path / "m"
    out.mkdir()
    _checkpoint_with_nan_weights(out / CHECKPOINT)
    monkeypatch.setattr(train_module, "load_drives", None)  # refused before any data loads
    for argv in (["--out", str(out), "--export-only", str(tmp_path / "exported")],
                 [*map(str, logs), "--out", str(out), "--preset", "tiny", "--steps", "5", "--batch", "1",
                  "--lr", "100"]):
        code = main(["train", *argv, "--quiet"])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(err) == 1, err
        assert "internal error" not in err[0] and f"{out / CHECKPOINT} holds weights that are not finite" in err[0]
        assert "its run diverged by step 4" in err[0] and "a lower --lr than 100" in err[0], err[0]
    assert not (tmp_path / "exported").exists()


def test_a_crop_angle_too_narrow_for_the_camera_is_refused_naming_the_least_that_works(tmp_path):
    # --crop-fov 0.1 spans one pixel of a KITTI frame: every frame was stored enlarged to make that
    # pixel a whole crop (96x for the fast preset: 12 GB a frame), an internal MemoryError.
    fov = math.radians(4.3)  # the test camera (fx 100) at 8 px, a quarter of the tiny preset's 32 px crops
    assert load_drive(_frames(2, 0), "d", crop_size=32, crop_fov_rad=fov).images.shape[1:] == (320, 512, 3)
    for narrow in (math.radians(4.2), [math.radians(17.6), math.radians(0.1)]):
        with pytest.raises(ValidationError, match=r"^d: --crop-fov (4.2|0.1) deg spans (7|1) px of its frames "
                           r"\(fx 100\), enlarged (5|32)x to 32 px crops; for this camera pass a --crop-fov of at "
                           r"least 4.30 deg \(8 px"):
            load_drive(_frames(2, 0), "d", crop_size=32, crop_fov_rad=narrow)
    one = _write_logs(tmp_path / "logs", 1)
    with pytest.raises(ValidationError, match="at least 4.30 deg"):
        train(one, tmp_path / "m", TrainConfig(preset="tiny", max_steps=1, batch_windows=1, crop_fov_deg=0.1))
    assert not (tmp_path / "m").exists()


def test_frames_too_small_for_the_presets_crops_are_refused():
    # The advice was only "pass a preset with smaller crops", which a fine-tune (--init, whose
    # preset must be its model's) cannot follow: it says to leave the log out too.
    with pytest.raises(ValidationError, match=r"its frames \(128x80 px\) are too small for 400 px crops: a crop "
                       r"needs at least 100 px of them; leave this log out, or train from scratch with a preset of "
                       r"smaller crops \(a fine-tune keeps its --init model's\)"):
        load_drive(_frames(2, 0), "d", crop_size=400, crop_fov_rad=math.radians(60.0))


def test_more_transformer_layers_than_an_onnx_file_or_the_memory_holds_are_refused(logs, tmp_path, monkeypatch):
    # --layers 100000 was accepted and grew past 8 GB building the networks, with no step made.
    from estimator import nets
    from estimator import train as train_module

    def reached(*args, **kw):
        raise AssertionError("reached")

    monkeypatch.setattr(train_module, "load_drives", reached)  # refused before any data loads
    monkeypatch.setattr(train_module, "_memory_bytes", lambda: 2**40)
    with pytest.raises(ValidationError, match=r"^layers: expected 1 to (\d+) for the tiny preset \(a deeper "
                       r"aggregator graph would pass the 2 GiB one ONNX file holds, so the model could not be "
                       r"exported\), got 100000$") as info:
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", layers=100000, max_steps=1))
    most = nets.TINY.max_layers()
    assert f"expected 1 to {most} " in str(info.value) and 1000 < most < 100000
    with pytest.raises(AssertionError, match="reached"):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", layers=most, max_steps=1))
    # On a machine of 1 GiB, the weights, gradients and AdamW's two moments (16 bytes a value) bound it first.
    monkeypatch.setattr(train_module, "_memory_bytes", lambda: 2**30)
    with pytest.raises(ValidationError, match=r"^layers: expected 1 to \d+ for the tiny preset \(deeper, its "
                       r"weights, gradients and optimiser state alone would pass the 1.0 GiB of memory and swap "
                       rf"this machine has\), got {most}$"):
        train(logs, tmp_path / "m", TrainConfig(preset="tiny", layers=most, max_steps=1))
    assert not (tmp_path / "m").exists()


def test_the_onnx_size_estimate_of_the_aggregator_is_an_upper_bound(tiny_model_dir):
    from estimator import nets

    size = (tiny_model_dir / "aggregator.onnx").stat().st_size
    assert size <= nets.TINY.aggregator_graph_bytes(nets.TINY.layers) < 1.5 * size


def test_a_log_whose_clock_jumps_trains_as_one_drive_per_run_of_its_clock(tmp_path, caplog):
    # A clock that restarted (100-110 s, then 0-10 s) or was suspended for an hour: windows drawn
    # across the jump paired frames of other instants, and the live draws' binary search over times
    # out of order picked frames of both runs in 198 of 200 windows.
    from estimator.train import load_drives, split_at_clock_jumps
    from replay.native import LogWriter

    frames = _frames(24, 0)
    times = [100.0 + 0.5 * i for i in range(8)] + [0.5 * i for i in range(8)] + [3600.0 + 0.5 * i for i in range(8)]
    jumpy = [replace(f, t_mono_s=t) for f, t in zip(frames, times, strict=True)]
    assert [[f.seq for f in run] for run in split_at_clock_jumps(jumpy)] == [
        list(range(8)), list(range(8, 16)), list(range(16, 24))]
    assert len(split_at_clock_jumps(frames)) == 1  # an even clock, and equal times, are one run
    assert len(split_at_clock_jumps([replace(f, t_mono_s=5.0) for f in frames])) == 1
    log = tmp_path / "jumpy.mcap"
    with LogWriter(log) as w:
        for f in jumpy:
            w.write_frame(f)
    drives = load_drives([log], 16, math.radians(PAPER_CROP_FOV_DEG))
    assert [d.name for d in drives] == ["jumpy.mcap#0", "jumpy.mcap#1", "jumpy.mcap#2"]
    for d in drives:
        assert np.all(np.diff(d.t_s) > 0) and d.t_s[-1] - d.t_s[0] == pytest.approx(3.5)
    assert "its clock jumps 2 times (at seq 8, 16); trained as 3 drives" in caplog.text


def test_a_log_whose_utc_leaps_past_its_clock_splits_where_the_ring_starts_again():
    # A suspend recorded in a log: CLOCK_MONOTONIC stood still for an hour and UTC did not, so the
    # monotonic stamps step on evenly and the log trained as one drive, with windows pairing frames
    # an hour apart in sun time (~15 deg) under one sun. Training splits where the live ring starts
    # again: UTC and monotonic stamps of a frame and the one before disagree by more than the ring's
    # tolerance; a frame without UTC is not compared.
    from estimator.train import split_at_clock_jumps
    from rig.ring import UTC_DISAGREEMENT_TOLERANCE_S as tol
    from rig.ring import FrameRing
    from rig.types import FrameFeatures

    utc0_ns = 1_700_000_000 * 10**9
    frames = _frames(24, 0)  # 0.5 s apart on the monotonic clock

    def with_utc(shift_s, from_seq=8, without=()):
        """The frames with UTC = their monotonic time + ``shift_s`` from ``from_seq`` on (none for ``without``)."""
        return [replace(f, utc_ns=None if f.seq in without else
                        utc0_ns + round((f.t_mono_s + (shift_s if f.seq >= from_seq else 0.0)) * 1e9))
                for f in frames]

    def split(fs):
        return [run[0].seq for run in split_at_clock_jumps(fs)]

    def ring_starts(fs):
        ring, starts = FrameRing(capacity=128), [fs[0].seq]
        for f in fs:
            restarts = ring.restarts
            assert ring.push(FrameFeatures(f, np.zeros((1, 4)), np.zeros((1, 2)), np.zeros((1, 2), np.float32), "m"))
            if ring.restarts > restarts:
                starts.append(f.seq)
        return starts

    cases = {
        "suspended for an hour": (with_utc(3600.0), [0, 8]),
        "a clock set back": (with_utc(-(tol + 0.5)), [0, 8]),
        "two suspends": ([replace(f, utc_ns=f.utc_ns + (60 * 10**9 if f.seq >= 16 else 0))
                          for f in with_utc(3600.0)], [0, 8, 16]),
        "a leap second and the tolerance itself": (with_utc(tol), [0]),
        "no UTC: nothing to compare": (frames, [0]),
        "the frame before has no UTC": (with_utc(3600.0, without={7}), [0]),
        "the frame itself has none": (with_utc(3600.0, from_seq=9, without={8}), [0]),
    }
    for name, (fs, starts) in cases.items():
        assert split(fs) == starts == ring_starts(fs), name
    # A monotonic jump still splits, whatever UTC says.
    jumped = [replace(f, t_mono_s=f.t_mono_s + (3600.0 if f.seq >= 8 else 0.0)) for f in with_utc(3600.0)]
    assert split(jumped) == [0, 8]


def test_an_out_that_cannot_be_written_is_refused_before_the_logs_load(logs, tmp_path, monkeypatch):
    # It was found by the mkdir after loading every log (minutes for a fleet's folder), or, in a
    # folder the user may not write, by the first metrics line or checkpoint: after the training.
    import estimator.train as train_module

    def no_loading(*args, **kwargs):
        raise AssertionError("the logs were loaded before --out was checked")

    monkeypatch.setattr(train_module, "load_drives", no_loading)
    a_file = tmp_path / "notes.txt"
    a_file.write_text("not a folder")
    with pytest.raises(ValidationError, match=r"--out .*notes.txt/model: cannot write there .*; pass a folder"):
        train(logs, a_file / "model", TrainConfig(preset="tiny", max_steps=1, batch_windows=1))
    assert not (a_file.parent / "model").exists()


def test_a_fine_tune_with_a_relative_init_resumes_from_another_working_directory(logs, tmp_path, monkeypatch):
    # The run recorded --init as given ("start"), then compared it, resolved against the new working
    # directory, with the same folder named from there ("models/start"): refused as another run.
    from estimator.runtime import OnnxModel

    cfg = TrainConfig(preset="tiny", max_steps=1, batch_windows=1, warmup_steps=1)
    models = tmp_path / "models"
    train(logs, models / "start", cfg)
    monkeypatch.chdir(models)
    out = train(logs, tmp_path / "tuned", replace(cfg, init="start"))
    assert OnnxModel.load(out).contract.training["recipe"]["init"] == str(models / "start")
    monkeypatch.chdir(tmp_path)
    events = []
    train(logs, tmp_path / "tuned", replace(cfg, max_steps=2, init="models/start"), progress=events.append)
    assert [e["step"] for e in events if e["phase"] == "train"] == [2]


def test_an_init_folder_of_a_run_not_yet_exported_says_how_to_export_it(tmp_path):
    from estimator import nets
    from estimator.train import check_init

    run = tmp_path / "run"
    run.mkdir()
    (run / CHECKPOINT).write_bytes(b"")  # a run stopped before its end: a checkpoint, no model yet
    with pytest.raises(ValidationError, match=r"holds a training run that has not exported its model yet; "
                                              r"export it with `sunrig train --out .*run --export-only DIR`"):
        check_init(run, nets.TINY)
    # A run stopped during its export has weights.npz (written first) and no graphs: the runtime's
    # refusal came through, telling to pass --model DIR, which train does not have.
    (run / "weights.npz").write_bytes(b"")
    with pytest.raises(ValidationError, match=r"not exported its model yet; export it with .* and pass --init DIR"):
        check_init(run, nets.TINY)


@pytest.mark.parametrize("other", [
    Intrinsics(fx=200.0, fy=200.0, cx=80.0, cy=50.0, width=160, height=100),  # another size: refused
    Intrinsics(fx=100.0, fy=100.0, cx=40.0, cy=40.0, width=128, height=80),  # same size: the first's used
])
def test_a_log_whose_camera_changes_trains_as_one_drive_per_camera(tmp_path, caplog, other):
    # One camera's frames, then another's (a resolution or calibration changed mid-recording). A
    # drive holds one camera's intrinsics: frames of another size refused the whole run ("frames of
    # different sizes in one drive ... split the log", though no sunrig command splits a log, and
    # replay and eval take it), and frames of the same size took the first camera's view angles.
    from estimator.train import load_drives
    from replay.native import LogWriter

    frames = _frames(16, 0)
    rng = np.random.default_rng(1)
    mixed = frames[:8] + [replace(f, intrinsics=other, image_bgr=rng.integers(
        0, 256, (other.height, other.width, 3), dtype=np.uint8)) for f in frames[8:]]
    log = tmp_path / "two_cameras.mcap"
    with LogWriter(log) as w:
        for f in mixed:
            w.write_frame(f)
    drives = load_drives([log], 16, math.radians(PAPER_CROP_FOV_DEG))
    assert [(d.name, len(d.images)) for d in drives] == [("two_cameras.mcap#0", 8), ("two_cameras.mcap#1", 8)]
    for d, k in zip(drives, (frames[0].intrinsics, other), strict=True):
        view = d.views[0]
        scale = view.images.shape[2] / k.width
        assert view.cx == pytest.approx(k.cx * scale, rel=0.02) and view.fx == pytest.approx(k.fx * scale, rel=0.02)
    assert "its camera changes 1 time (at seq 8); trained as 2 drives" in caplog.text


# ------------------------------------------------------------------------------------------
# Durability: a kill, a power loss or a full disk at any moment, and two runs on one folder.


def test_an_export_cut_short_before_its_weights_is_made_again_by_the_same_command(logs, tmp_path, monkeypatch):
    # The graphs were written first and weights.npz after: a full disk (or a kill) between the two
    # left graphs that say the run reached its end, so the same command said "nothing to train"
    # forever, and weights.npz, what --init starts from, was never written.
    import errno

    from estimator.train import net_config

    out = tmp_path / "m"
    cfg = TrainConfig(preset="tiny", max_steps=2, batch_windows=1, command="test")

    def disk_full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez_compressed", disk_full)
    with pytest.raises(OSError):
        train(logs, out, cfg)
    monkeypatch.undo()
    events = []
    train(logs, out, cfg, progress=events.append)  # the same command, once there is space
    assert not any(e["phase"] == "finished" for e in events)
    backbone, aggregator = net_config(cfg).build()
    load_weights(out, net_config(cfg), backbone, aggregator)  # there, and whole


def test_a_second_run_on_a_folder_whose_run_is_training_is_refused_in_one_line(logs, tmp_path):
    # Nothing kept two processes off one --out: the second resumed the first's checkpoint and both
    # trained, writing checkpoint.pt through the same temporary name and the metrics file together.
    # A real second process holds the folder here; a kill -9 of it frees the folder.
    import subprocess
    import sys
    import textwrap
    from pathlib import Path

    from estimator.train import export_checkpoint

    out = tmp_path / "m"
    first = textwrap.dedent("""
        import sys
        from pathlib import Path
        from estimator.train import TrainConfig, train
        def said(p):
            if p["phase"] == "train" and p["step"] == 2:
                print("training", flush=True)
        train([Path(p) for p in sys.argv[2:]], Path(sys.argv[1]),
              TrainConfig(preset="tiny", max_steps=10**6, batch_windows=1, checkpoint_every_s=0.0, command="test"),
              progress=said)
    """)
    cfg = TrainConfig(preset="tiny", max_steps=3, batch_windows=1, checkpoint_every_s=0.0, command="test")
    with open(tmp_path / "first.err", "wb") as err:
        proc = subprocess.Popen([sys.executable, "-c", first, str(out), *map(str, logs)], stdout=subprocess.PIPE,
                                stderr=err, cwd=Path(__file__).resolve().parents[1])
    try:
        assert proc.stdout is not None and proc.stdout.readline() == b"training\n", (tmp_path / "first.err").read_text()
        with pytest.raises(ValidationError) as info:
            train(logs, out, cfg)
        said = str(info.value)
        assert "\n" not in said and f"--out {out} is in use by another sunrig train (pid {proc.pid})" in said, said
        with pytest.raises(ValidationError, match="is in use by another sunrig train"):
            export_checkpoint(out, out)  # its graphs and weights.npz, written beside the run's own
    finally:
        proc.kill()  # SIGKILL: the kernel drops its lock with it
        proc.wait()
    assert train(logs, out, cfg) == out  # the folder is free again: the same command resumes its run


def test_a_resume_keeps_the_settings_without_a_flag_that_its_run_began_with(logs, tmp_path):
    # Weight decay, warmup, subset share and window length have no flag: the same command passes
    # whatever this sunrig's defaults are, and a resume trained on with those, under a contract
    # naming them for the whole run (the window length is the model's, the warmup moved the rate).
    out = tmp_path / "m"
    cfg = TrainConfig(preset="tiny", max_steps=2, batch_windows=1, command="test")
    train(logs, out, cfg)
    new_defaults = {"weight_decay": 0.01, "warmup_steps": 7, "subset_prob": 0.1, "frames_per_window": 6}
    train(logs, out, replace(cfg, max_steps=3, **new_defaults))  # the same command after the defaults changed
    from estimator.runtime import OnnxModel

    ran = torch.load(out / CHECKPOINT, weights_only=False)["config"]
    contract = OnnxModel.load(out).contract
    for key in new_defaults:
        assert ran[key] == getattr(cfg, key) == contract.training["recipe"][key], key
    assert contract.frames_per_window == cfg.frames_per_window


def test_a_checkpoint_and_the_weights_reach_the_disk_before_they_replace_the_last(tmp_path, disk_events):
    # Renamed over the last checkpoint with nothing synced, a power loss minutes later can leave
    # checkpoint.pt empty or torn (the rename reached the disk, the data did not), and a resume
    # then only says it is damaged: the whole run lost, not the minutes since the last checkpoint.
    from estimator.train import _save_checkpoint, save_weights

    _save_checkpoint(tmp_path / CHECKPOINT, {"w": torch.zeros(10)})
    save_weights(torch.nn.Linear(2, 2), torch.nn.Linear(2, 2), tmp_path)
    for name in (CHECKPOINT, "weights.npz"):
        assert disk_events.synced_in_order(tmp_path / name), (name, disk_events)


def test_an_exported_model_reaches_the_disk_before_it_replaces_the_last(tmp_path, disk_events):
    # The graphs and their sums were renamed into the folder with nothing synced: after a power
    # loss the folder could hold empty graphs (refused by their sums, but the model gone).
    from estimator.contract import AGGREGATOR_FILE, BACKBONE_FILE, CHECKSUMS_FILE
    from estimator.export import build_random_model

    out = build_random_model(tmp_path / "model")
    for name in (CHECKSUMS_FILE, BACKBONE_FILE, AGGREGATOR_FILE):
        assert disk_events.synced_in_order(out / name), (name, disk_events)


def test_a_run_killed_mid_export_exports_again_and_leaves_nothing_of_the_first(logs, tmp_path):
    # kill -9 after the first graph: the same command exports again (its graphs never became the
    # model), but the staging folder of the killed export stayed in --out for good, a graph or two
    # in it (11 MB for the fast preset), one more each time.
    import subprocess
    import sys
    import textwrap
    from pathlib import Path

    from estimator.runtime import OnnxModel

    out = tmp_path / "m"
    killed = textwrap.dedent("""
        import os, signal, sys
        from pathlib import Path
        import estimator.export as export
        from estimator.train import TrainConfig, train
        real = export.export_graph
        def killed_after_it(*args, **kwargs):
            real(*args, **kwargs)
            os.kill(os.getpid(), signal.SIGKILL)
        export.export_graph = killed_after_it
        train([Path(p) for p in sys.argv[2:]], Path(sys.argv[1]),
              TrainConfig(preset="tiny", max_steps=2, batch_windows=1, command="test"))
    """)
    done = subprocess.run([sys.executable, "-c", killed, str(out), *map(str, logs)], capture_output=True,
                          cwd=Path(__file__).resolve().parents[1], check=False)
    assert done.returncode == -9 and list(out.glob(".export-*/*.onnx")), done.stderr.decode()
    train(logs, out, TrainConfig(preset="tiny", max_steps=2, batch_windows=1, command="test"))
    assert OnnxModel.load(out).contract.training["steps"] == 2
    assert not list(out.glob(".export-*"))
