"""The torch networks and their ONNX export: PyTorch and ONNX Runtime agree, batching and padding
change nothing, the loss and the heading rotation have the paper's values, the presets the
paper's numbers."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from tests.tolerances import BATCHED_F32, EXACT_F64, ONNX_VS_TORCH

pytestmark = pytest.mark.torch
torch = pytest.importorskip("torch", reason="the torch model needs the train extra")
ort = pytest.importorskip("onnxruntime")

from estimator.contract import (  # noqa: E402
    AGG_INPUT_ANGLES,
    AGG_INPUT_EMBEDDINGS,
    AGG_INPUT_MASK,
    AGG_OUTPUT,
    AGGREGATOR_FILE,
    BACKBONE_FILE,
    BACKBONE_INPUT,
    BACKBONE_OUTPUT,
    CHECKSUMS_FILE,
    set_metadata,
)
from estimator.export import build_random_nets, export_model  # noqa: E402
from estimator.nets import (  # noqa: E402
    LIGHT,
    PAPER,
    Aggregator,
    Backbone,
    NetConfig,
    sun_loss,
    tail_loss,
    world_from_heading_torch,
)
from estimator.runtime import OnnxModel  # noqa: E402
from rig.errors import ValidationError  # noqa: E402
from rig.geometry import world_from_heading  # noqa: E402


class Engines:
    """The tiny model twice: torch modules rebuilt from its contract, and its ONNX graphs."""

    def __init__(self, model_dir: Path) -> None:
        self.model = OnnxModel.load(model_dir)
        contract = self.model.contract
        self.config = NetConfig.from_architecture(contract.architecture)
        self.backbone, self.aggregator = build_random_nets(self.config, contract.training["seed"])
        self.bb_session = ort.InferenceSession(
            str(model_dir / BACKBONE_FILE), providers=["CPUExecutionProvider"]
        )
        self.agg_session = ort.InferenceSession(
            str(model_dir / AGGREGATOR_FILE), providers=["CPUExecutionProvider"]
        )
        self.s = contract.crop_size_px
        self.d = contract.embedding_dim

    def backbone_torch(self, crops: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self.backbone(torch.from_numpy(crops)).numpy()

    def backbone_onnx(self, crops: np.ndarray) -> np.ndarray:
        return self.bb_session.run([BACKBONE_OUTPUT], {BACKBONE_INPUT: crops})[0]

    def aggregator_torch(self, emb, ang, mask) -> np.ndarray:
        with torch.no_grad():
            return self.aggregator(
                torch.from_numpy(emb), torch.from_numpy(ang), torch.from_numpy(mask)
            ).numpy()

    def aggregator_onnx(self, emb, ang, mask) -> np.ndarray:
        feeds = {AGG_INPUT_EMBEDDINGS: emb, AGG_INPUT_ANGLES: ang, AGG_INPUT_MASK: mask}
        return self.agg_session.run([AGG_OUTPUT], feeds)[0]


@pytest.fixture(scope="module")
def engines(tiny_model_dir) -> Engines:
    return Engines(tiny_model_dir)


def random_window(rng: np.random.Generator, b: int, t: int, d: int):
    emb = rng.normal(size=(b, t, d)).astype(np.float32)
    ang = rng.uniform(-math.pi, math.pi, size=(b, t, 3)).astype(np.float32)
    return emb, ang


def test_backbone_torch_and_onnx_agree(engines):
    crops = np.random.default_rng(0).normal(size=(5, 3, engines.s, engines.s)).astype(np.float32)
    want = engines.backbone_torch(crops)
    got = engines.backbone_onnx(crops)
    assert got.shape == (5, engines.d) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=ONNX_VS_TORCH, rtol=0)
    # a single crop: the dynamic axis was traced with 2, and must not have been fixed to it
    np.testing.assert_allclose(
        engines.backbone_onnx(crops[:1]), want[:1], atol=ONNX_VS_TORCH, rtol=0
    )


def test_aggregator_torch_and_onnx_agree_with_padding(engines):
    rng = np.random.default_rng(1)
    emb, ang = random_window(rng, 3, 12, engines.d)
    mask = np.ones((3, 12), dtype=bool)
    mask[1, 7:] = False
    mask[2, 1:] = False
    want = engines.aggregator_torch(emb, ang, mask)
    got = engines.aggregator_onnx(emb, ang, mask)
    assert got.shape == (3, 12, 3) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, atol=ONNX_VS_TORCH, rtol=0)
    assert np.all(got[~mask] == 0.0)
    for b, t in ((1, 1), (5, 1), (1, 32)):  # shapes the estimator feeds, unlike the traced (2, 5)
        e, a = random_window(rng, b, t, engines.d)
        m = np.ones((b, t), dtype=bool)
        np.testing.assert_allclose(
            engines.aggregator_onnx(e, a, m), engines.aggregator_torch(e, a, m), atol=ONNX_VS_TORCH
        )


@pytest.mark.parametrize("engine", ["torch", "onnx"])
def test_backbone_batched_equals_one_by_one(engines, engine):
    run = engines.backbone_torch if engine == "torch" else engines.backbone_onnx
    crops = np.random.default_rng(2).normal(size=(6, 3, engines.s, engines.s)).astype(np.float32)
    batched = run(crops)
    single = np.concatenate([run(crops[i : i + 1]) for i in range(len(crops))])
    np.testing.assert_allclose(batched, single, atol=BATCHED_F32, rtol=0)


@pytest.mark.parametrize("engine", ["torch", "onnx"])
def test_aggregator_batched_equals_one_by_one(engines, engine):
    run = engines.aggregator_torch if engine == "torch" else engines.aggregator_onnx
    emb, ang = random_window(np.random.default_rng(3), 4, 9, engines.d)
    mask = np.ones((4, 9), dtype=bool)
    mask[3, 5:] = False
    batched = run(emb, ang, mask)
    single = np.concatenate(
        [run(emb[i : i + 1], ang[i : i + 1], mask[i : i + 1]) for i in range(4)]
    )
    np.testing.assert_allclose(batched, single, atol=BATCHED_F32, rtol=0)


@pytest.mark.parametrize("engine", ["torch", "onnx"])
def test_padding_does_not_change_real_tokens(engines, engine):
    run = engines.aggregator_torch if engine == "torch" else engines.aggregator_onnx
    rng = np.random.default_rng(4)
    emb, ang = random_window(rng, 1, 6, engines.d)
    alone = run(emb, ang, np.ones((1, 6), dtype=bool))
    for _ in range(2):  # whatever garbage sits in the padded slots
        pad_emb, pad_ang = random_window(rng, 1, 5, engines.d)
        e = np.concatenate([emb, 100.0 * pad_emb], axis=1)
        a = np.concatenate([ang, pad_ang], axis=1)
        m = np.arange(11)[None] < 6
        out = run(e, a, m)
        np.testing.assert_allclose(out[:, :6], alone, atol=BATCHED_F32, rtol=0)
        assert np.all(out[:, 6:] == 0.0)
    # and padding first instead of last
    e = np.concatenate([pad_emb, emb], axis=1)
    a = np.concatenate([pad_ang, ang], axis=1)
    np.testing.assert_allclose(
        run(e, a, np.arange(11)[None] >= 5)[:, 5:], alone, atol=BATCHED_F32, rtol=0
    )


@pytest.mark.parametrize("engine", ["torch", "onnx"])
def test_all_padding_window_is_finite(engines, engine):
    run = engines.aggregator_torch if engine == "torch" else engines.aggregator_onnx
    emb, ang = random_window(np.random.default_rng(5), 2, 4, engines.d)
    mask = np.zeros((2, 4), dtype=bool)
    mask[0] = True
    out = run(emb, ang, mask)
    assert np.all(np.isfinite(out))
    assert np.all(out[1] == 0.0)


def test_contract_round_trips_through_the_graphs(engines, tiny_model_dir):
    contract = engines.model.contract
    rebuilt = engines.config.contract(
        crops_per_frame=contract.crops_per_frame,
        frames_per_window=contract.frames_per_window,
        training=contract.training,
    )
    assert rebuilt.differences(contract) == []
    assert contract.training["trained"] is False
    assert contract.embedding_dim == engines.backbone.embedding_dim == 8 * engines.config.base_width
    assert contract.encoding["depth_per_angle"] == engines.aggregator.encoding.depth_per_angle


def test_legacy_exporter_gives_the_same_graphs(engines, tmp_path):
    backbone, aggregator = build_random_nets(
        engines.config, engines.model.contract.training["seed"]
    )
    backbone.train()  # export must use eval mode and hand the flag back
    out = export_model(backbone, aggregator, engines.model.contract, tmp_path, exporter="legacy")
    assert backbone.training and not aggregator.training
    assert sorted(p.name for p in out.iterdir()) == [CHECKSUMS_FILE, AGGREGATOR_FILE, BACKBONE_FILE]  # no leftovers
    legacy = Engines(out)
    rng = np.random.default_rng(6)
    crops = rng.normal(size=(3, 3, engines.s, engines.s)).astype(np.float32)
    np.testing.assert_allclose(
        legacy.backbone_onnx(crops), engines.backbone_onnx(crops), atol=ONNX_VS_TORCH
    )
    emb, ang = random_window(rng, 2, 7, engines.d)
    mask = np.arange(7)[None].repeat(2, 0) < np.array([[7], [3]])
    np.testing.assert_allclose(
        legacy.aggregator_onnx(emb, ang, mask),
        engines.aggregator_onnx(emb, ang, mask),
        atol=ONNX_VS_TORCH,
    )


def test_export_refuses_modules_that_do_not_fit_the_contract(engines, tmp_path):
    other = NetConfig(base_width=4, crop_size=32, width=48, layers=1, heads=2, mlp=64)
    backbone, aggregator = other.build(seed=0)
    with pytest.raises(ValidationError, match="embedding_dim 32 != contract 64"):
        export_model(backbone, aggregator, engines.model.contract, tmp_path)
    assert list(tmp_path.iterdir()) == []


def test_export_to_a_path_that_is_a_file_is_refused_in_one_line(engines, tmp_path):
    # `train --export-only FILE`: mkdir's FileExistsError was an internal error.
    afile = tmp_path / "model"
    afile.write_bytes(b"kept")
    with pytest.raises(ValidationError, match="model is a file; a model is a folder"):
        export_model(engines.backbone, engines.aggregator, engines.model.contract, afile)
    with pytest.raises(ValidationError, match=r"cannot make the model folder .*model/sub: Not a directory"):
        export_model(engines.backbone, engines.aggregator, engines.model.contract, afile / "sub")
    assert afile.read_bytes() == b"kept"


def test_dropout_is_active_in_training_only():
    torch.manual_seed(0)
    agg = Aggregator(16, width=24, layers=1, heads=2, mlp=32, dropout=0.5)
    emb, ang = torch.randn(1, 5, 16), torch.randn(1, 5, 3)
    mask = torch.ones(1, 5, dtype=torch.bool)
    agg.train()
    assert not torch.equal(agg(emb, ang, mask), agg(emb, ang, mask))
    agg.eval()
    assert torch.equal(agg(emb, ang, mask), agg(emb, ang, mask))


# ---------------------------------------------------------------------------- loss


def t(x) -> torch.Tensor:
    return torch.tensor(x, dtype=torch.float64)


@pytest.mark.parametrize(
    ("v_pred", "v_gt", "loss"),
    [
        ([0.0, 0.6, 0.8], [0.0, 0.6, 0.8], 0.0),  # perfect
        ([0.0, 0.0, -1.0], [0.0, 0.0, 1.0], 3.0),  # opposite (2) + below the horizon (1)
        ([0.0, 1.2, 1.6], [0.0, 0.6, 0.8], 1.0),  # right direction, twice as long: (1 - 2)^2
        ([1.0, 0.0, 0.0], [0.0, 0.0, 1.0], 1.0),  # perpendicular
        ([0.0, 0.0, -0.5], [1.0, 0.0, 0.0], 1.0 + 0.25 + 0.5),
        ([0.0, 0.0, 0.0], [0.0, 0.0, 1.0], 2.0),  # no direction: cosine term 1, norm term 1
    ],
)
def test_sun_loss_golden(v_pred, v_gt, loss):
    assert sun_loss(t([v_pred]), t([v_gt])).item() == pytest.approx(loss, abs=EXACT_F64)


def test_sun_loss_mask_and_gradient():
    v_gt = t([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    v_pred = t([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 0.0, 0.0]]).requires_grad_(True)
    mask = torch.tensor([True, True, False])
    loss = sun_loss(v_pred, v_gt, mask)
    assert loss.item() == pytest.approx((0.0 + 3.0) / 2, abs=EXACT_F64)
    loss.backward()
    assert torch.all(torch.isfinite(v_pred.grad))
    assert torch.all(v_pred.grad[2] == 0.0)  # a masked vector gets no gradient
    assert v_pred.grad[1, 2] < 0  # pushing a wrong prediction up lowers the loss
    # all padding: zero, not NaN
    assert sun_loss(v_pred, v_gt, torch.zeros(3, dtype=torch.bool)).item() == 0.0
    # a zero prediction still has a finite gradient
    zero = torch.zeros(1, 3, requires_grad=True)
    sun_loss(zero, torch.tensor([[0.0, 0.0, 1.0]])).backward()
    assert torch.all(torch.isfinite(zero.grad))


def test_sun_loss_rejects_bad_shapes():
    with pytest.raises(ValidationError, match="matching shapes"):
        sun_loss(torch.zeros(2, 3), torch.zeros(3, 3))
    with pytest.raises(ValidationError, match="mask shape"):
        sun_loss(torch.zeros(2, 3), torch.zeros(2, 3), torch.ones(3, dtype=torch.bool))


def test_tail_loss_counts_only_the_miss_beyond_its_margin():
    up = [0.0, 0.0, 1.0]

    def tilted(deg, length=1.0):  # ``deg`` away from the zenith, toward north
        return [0.0, length * math.sin(math.radians(deg)), length * math.cos(math.radians(deg))]

    margin = math.radians(15.0)
    # Within the margin: nothing, and no pull (the paper's loss alone decides there).
    near = t([tilted(10.0)]).requires_grad_(True)
    loss = tail_loss(near, t([up]), margin)
    loss.backward()
    assert loss.item() == 0.0 and torch.all(near.grad == 0.0)
    # Beyond it: the squared excess in radians, whatever the vector's length.
    for deg, length in ((35.0, 1.0), (35.0, 0.3), (90.0, 2.0), (179.0, 1.0)):
        got = tail_loss(t([tilted(deg, length)]), t([up]), margin).item()
        assert got == pytest.approx(math.radians(deg - 15.0) ** 2, rel=1e-5), (deg, length)
    # The mean over vectors, and a finite pull toward the truth even from straight opposite.
    far = t([tilted(35.0), tilted(170.0)]).requires_grad_(True)
    loss = tail_loss(far, t([up, up]), margin)
    assert loss.item() == pytest.approx((math.radians(20.0) ** 2 + math.radians(155.0) ** 2) / 2, rel=1e-5)
    loss.backward()
    assert far.grad[0, 2] < 0 and far.grad[0, 1] > 0  # up and back toward the zenith lowers it
    opposite = t([[0.0, 0.0, -1.0]]).requires_grad_(True)
    tail_loss(opposite, t([up]), margin).backward()
    assert torch.all(torch.isfinite(opposite.grad))
    # A mask counts only its vectors, and none counted is 0, not NaN.
    masked = tail_loss(far, t([up, up]), margin, torch.tensor([True, False])).item()
    assert masked == pytest.approx(math.radians(20.0) ** 2, rel=1e-5)
    assert tail_loss(far, t([up, up]), margin, torch.zeros(2, dtype=torch.bool)).item() == 0.0
    with pytest.raises(ValidationError, match="matching shapes"):
        tail_loss(torch.zeros(2, 3), torch.zeros(3, 3), margin)
    with pytest.raises(ValidationError, match="mask shape"):
        tail_loss(torch.zeros(2, 3), torch.zeros(2, 3), margin, torch.ones(3, dtype=torch.bool))


def test_loss_trains_the_aggregator_end_to_end():
    """The loss, the rotation to the world frame and the aggregator fit together: a few steps on
    one window lower the loss."""
    torch.manual_seed(0)
    agg = Aggregator(8, width=24, layers=1, heads=2, mlp=32, dropout=0.0)
    emb, ang = torch.randn(2, 6, 8), torch.rand(2, 6, 3) * 2 * math.pi
    yaw = ang[..., 0]
    sun = torch.tensor([0.3, 0.5, 0.81]) / torch.tensor([0.3, 0.5, 0.81]).norm()
    opt = torch.optim.Adam(agg.parameters(), lr=1e-2)
    losses = []
    for _ in range(30):
        world = world_from_heading_torch(agg(emb, ang, torch.ones(2, 6, dtype=torch.bool)), yaw)
        loss = sun_loss(world, sun.expand_as(world))
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.5 * losses[0]


# ---------------------------------------------------------------------------- frames


def test_world_from_heading_torch_matches_geometry():
    rng = np.random.default_rng(7)
    yaw = rng.uniform(-3 * math.pi, 3 * math.pi, size=(4, 5))
    vec = rng.normal(size=(4, 5, 3))
    want = np.einsum("...ij,...j->...i", world_from_heading(yaw), vec)
    got = world_from_heading_torch(torch.from_numpy(vec), torch.from_numpy(yaw)).numpy()
    np.testing.assert_allclose(got, want, atol=EXACT_F64, rtol=0)


@pytest.mark.parametrize(
    ("yaw_deg", "heading_vec", "enu"),
    [
        (0.0, [0.0, 1.0, 0.0], [0.0, 1.0, 0.0]),  # facing north, ahead is north
        (90.0, [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]),  # facing east, ahead is east
        (90.0, [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]),  # facing east, right is south
        (180.0, [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]),  # up stays up
    ],
)
def test_world_from_heading_torch_golden(yaw_deg, heading_vec, enu):
    got = world_from_heading_torch(t(heading_vec), t(math.radians(yaw_deg)))
    np.testing.assert_allclose(got.numpy(), enu, atol=EXACT_F64)


# ---------------------------------------------------------------------------- presets


def test_paper_preset_has_the_papers_numbers():
    assert (PAPER.layers, PAPER.heads, PAPER.width, PAPER.mlp, PAPER.dropout) == (
        4,
        4,
        512,
        1024,
        0.2,
    )
    assert (PAPER.base_width, PAPER.crop_size, PAPER.embedding_dim) == (64, 224, 512)
    assert PAPER.blocks == (2, 2, 2, 2)
    contract = PAPER.contract()
    assert (contract.crops_per_frame, contract.frames_per_window, contract.tokens_per_window) == (
        4,
        8,
        32,
    )
    assert contract.encoding["depth_per_angle"] == 170
    # The paper's backbone is ResNet18: torchvision's resnet18 has 11,689,512 parameters, of which
    # its 1000-class head holds 513,000.
    assert sum(p.numel() for p in Backbone(64).parameters()) == 11_689_512 - 513_000
    _, agg = PAPER.build(seed=0)
    assert len(agg.layers) == 4 and agg.layers[0].attn.heads == 4
    assert agg.layers[0].mlp[0].out_features == 1024 and agg.layers[0].mlp[2].p == 0.2


def test_light_preset_keeps_the_transformer():
    assert (LIGHT.base_width, LIGHT.crop_size, LIGHT.embedding_dim) == (32, 128, 256)
    assert (LIGHT.layers, LIGHT.heads, LIGHT.width, LIGHT.mlp, LIGHT.dropout) == (
        4,
        4,
        512,
        1024,
        0.2,
    )


def test_backbone_accepts_any_crop_size():
    backbone = Backbone(8).eval()
    with torch.no_grad():
        for s in (32, 57, 128):
            assert backbone(torch.zeros(2, 3, s, s)).shape == (2, 64)


@pytest.mark.slow
def test_paper_preset_export_round_trip(tmp_path):
    backbone, aggregator = build_random_nets(PAPER, seed=3)
    contract = PAPER.contract(training={"trained": False, "seed": 3})
    model = OnnxModel.load(export_model(backbone, aggregator, contract, tmp_path))
    assert model.contract.differences(contract) == []
    rng = np.random.default_rng(8)
    crops = rng.integers(0, 256, size=(2, 224, 224, 3), dtype=np.uint8)
    with torch.no_grad():
        want = backbone(torch.from_numpy(model.normalise(crops))).numpy()
    got = model.embed(crops)
    # embeddings of a random ResNet18 reach ~10: compare relative to their scale
    np.testing.assert_allclose(
        got, want, atol=ONNX_VS_TORCH * max(1.0, float(np.abs(want).max())), rtol=0
    )
    emb, ang = random_window(rng, 2, 32, 512)
    mask = np.ones((2, 32), dtype=bool)
    mask[1, 20:] = False
    with torch.no_grad():
        want = aggregator(
            torch.from_numpy(emb), torch.from_numpy(ang), torch.from_numpy(mask)
        ).numpy()
    np.testing.assert_allclose(model.aggregate(emb, ang, mask), want, atol=ONNX_VS_TORCH, rtol=0)


def test_set_metadata_replaces_keys_it_is_given_and_keeps_the_others():
    # A re-export (--export-only) sets the contract again on a graph that has one: a second
    # entry under the same key would leave the runtime reading whichever came first.
    import onnx

    model = onnx.ModelProto()
    model.metadata_props.add(key="sunrig.contract", value="old")
    model.metadata_props.add(key="producer.note", value="kept")
    set_metadata(model, {"sunrig.contract": "new", "sunrig.graph": "backbone"})
    assert sorted((p.key, p.value) for p in model.metadata_props) == [
        ("producer.note", "kept"), ("sunrig.contract", "new"), ("sunrig.graph", "backbone")]
