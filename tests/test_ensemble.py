"""`sunrig ensemble`: several trained models run as one (estimator/nets.py EnsembleBackbone and
EnsembleAggregator, estimator/train.py combine_models). The ensemble must answer what its members
answer together, keep the record of how each was made, and fine-tune like any model."""

import math

import numpy as np
import pytest

from rig.errors import ValidationError

pytestmark = pytest.mark.torch
torch = pytest.importorskip("torch", reason="ensembles are made with the train extra")

from estimator.runtime import OnnxModel  # noqa: E402
from estimator.train import TrainConfig, combine_models, export_checkpoint, train  # noqa: E402
from tests.test_train import _write_logs  # noqa: E402


@pytest.fixture(scope="module")
def members(tmp_path_factory):
    """Two tiny runs that differ only by their seed, on drives with the sun 53.1 deg up."""
    root = tmp_path_factory.mktemp("members")
    logs = _write_logs(root / "logs", 3)
    runs = [train(logs, root / f"run{seed}", TrainConfig(preset="tiny", max_steps=3, batch_windows=2,
                                                         warmup_steps=1, seed=seed)) for seed in (1, 2)]
    return logs, runs


def _crops(model, n=6, seed=0):
    s = model.contract.crop_size_px
    return np.random.default_rng(seed).integers(0, 256, (n, s, s, 3), dtype=np.uint8)


def test_an_ensemble_answers_the_mean_of_its_members_on_the_same_crops(members, tmp_path):
    _, runs = members
    a, b = (OnnxModel.load(r) for r in runs)
    ens = OnnxModel.load(combine_models(runs, tmp_path / "ens"))
    crops = _crops(a)
    emb_a, emb_b, emb = a.embed(crops), b.embed(crops), ens.embed(crops)
    d = a.contract.embedding_dim
    assert ens.contract.embedding_dim == emb.shape[1] == 2 * d
    # float16 weights in the ensemble's graphs: close to the members' float32 answers, not equal.
    np.testing.assert_allclose(emb[:, :d], emb_a, rtol=0.02, atol=0.02 * np.abs(emb_a).max())
    np.testing.assert_allclose(emb[:, d:], emb_b, rtol=0.02, atol=0.02 * np.abs(emb_b).max())
    rng = np.random.default_rng(1)
    angles = rng.uniform(-math.pi, math.pi, (1, 6, 3)).astype(np.float32)
    mask = np.ones((1, 6), dtype=bool)
    mean = (a.aggregate(emb_a[None], angles, mask) + b.aggregate(emb_b[None], angles, mask)) / 2.0
    got = ens.aggregate(emb[None], angles, mask)
    np.testing.assert_allclose(got, mean, atol=0.01 * (1.0 + np.abs(mean).max()))
    # Not merely one member's answer: the members differ here by more than the tolerance above.
    assert np.abs(a.aggregate(emb_a[None], angles, mask) - mean).max() > 0.05 * (1.0 + np.abs(mean).max())


def test_an_ensemble_records_its_members_and_their_suns(members, tmp_path):
    _, runs = members
    ens = OnnxModel.load(combine_models(runs, tmp_path / "ens", run_crops_per_frame=6, command="sunrig ensemble x"))
    c = ens.contract
    assert c.architecture["members"] == 2 and c.crops_per_frame == 6
    assert c.training["command"] == "sunrig ensemble x"
    assert [m["model_id"] for m in c.training["members"]] == [OnnxModel.load(r).model_id for r in runs]
    assert [m["steps"] for m in c.training["members"]] == [3, 3]
    assert c.trained_sun_elevation_deg == (53.1, 53.1)
    assert (tmp_path / "ens" / "weights.npz").is_file()


def test_one_model_other_crops_a_nested_ensemble_and_an_untrained_member_are_refused(members, tmp_path):
    from estimator.export import build_random_model

    _, runs = members
    with pytest.raises(ValidationError, match="at least 2"):
        combine_models(runs[:1], tmp_path / "one")
    wider = export_checkpoint(runs[1], tmp_path / "six", run_crops_per_frame=6)
    with pytest.raises(ValidationError, match="pass --crops"):
        combine_models([runs[0], wider], tmp_path / "crops")
    assert OnnxModel.load(combine_models([runs[0], wider], tmp_path / "ok", run_crops_per_frame=8))
    ens = combine_models(runs, tmp_path / "ens")
    with pytest.raises(ValidationError, match="ensemble already"):
        combine_models([runs[0], ens], tmp_path / "nested")
    untrained = build_random_model(tmp_path / "random")  # the tiny preset, as the runs
    (untrained / "weights.npz").write_bytes((runs[0] / "weights.npz").read_bytes())
    with pytest.raises(ValidationError, match="never trained"):
        combine_models([runs[0], untrained], tmp_path / "untrained")


def test_an_ensemble_fine_tunes_and_resumes_as_an_ensemble(members, tmp_path):
    logs, runs = members
    ens = combine_models(runs, tmp_path / "ens")
    tune = TrainConfig(preset="tiny", max_steps=1, batch_windows=2, warmup_steps=1, init=str(ens))
    tuned = train(logs, tmp_path / "tuned", tune)
    c = OnnxModel.load(tuned).contract
    assert c.architecture["members"] == 2
    assert c.training["init"]["model_id"] == OnnxModel.load(ens).model_id
    assert len(c.training["init"]["members"]) == 2  # the chain reaches back to the separate runs
    # More steps resume the ensemble's run; export_checkpoint rebuilds it from the checkpoint.
    train(logs, tuned, TrainConfig(**{**tune.__dict__, "max_steps": 2}))
    assert OnnxModel.load(tuned).contract.training["steps"] == 2
    assert OnnxModel.load(export_checkpoint(tuned, tmp_path / "again")).contract.architecture["members"] == 2


def test_weights_of_one_network_do_not_load_into_an_ensemble(members):
    from dataclasses import replace

    from estimator import nets
    from estimator.train import _load_npz

    _, runs = members
    with pytest.raises(ValidationError, match="other networks"):
        _load_npz(runs[0] / "weights.npz", *replace(nets.TINY, members=2).build())


def test_the_cli_makes_an_ensemble_and_refuses_an_out_that_holds_files(members, tmp_path, capsys):
    from rig.cli import main

    _, runs = members
    out = tmp_path / "ens"
    assert main(["ensemble", *map(str, runs), "--out", str(out), "--crops", "5"]) == 0
    c = OnnxModel.load(out).contract
    assert c.crops_per_frame == 5 and c.training["command"].startswith("sunrig ")
    assert main(["ensemble", *map(str, runs), "--out", str(out)]) == 2
    assert "not an empty folder" in capsys.readouterr().err
