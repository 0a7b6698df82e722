"""The onnxruntime model: loading a model folder, feeding it, and refusing every folder that does
not fit its contract with a one-line message that names the difference."""

from __future__ import annotations

import dataclasses
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from estimator.contract import (
    AGGREGATOR_FILE,
    BACKBONE_FILE,
    CHECKSUMS_FILE,
    IMAGENET_MEAN,
    IMAGENET_STD,
    ModelContract,
    parse_checksums,
)
from estimator.runtime import OnnxModel, check_expected
from rig.errors import ContractMismatch, ModelError, ValidationError
from tests.tolerances import BATCHED_F32

REPO = Path(__file__).resolve().parents[1]


def copy_model(src: Path, dst: Path) -> Path:
    dst.mkdir(parents=True, exist_ok=True)
    for name in (BACKBONE_FILE, AGGREGATOR_FILE):
        shutil.copy(src / name, dst / name)
    return dst


def edit_metadata(
    path: Path,
    *,
    contract_changes: dict | None = None,
    set_keys: dict | None = None,
    drop_keys: tuple[str, ...] = (),
) -> None:
    """Rewrite an ONNX file's metadata in place, as a careless tool or a hand edit would."""
    onnx = pytest.importorskip("onnx")
    model = onnx.load(str(path))
    meta = {p.key: p.value for p in model.metadata_props}
    if contract_changes:
        raw = json.loads(meta["sunrig.contract"])
        raw.update(contract_changes)
        meta["sunrig.contract"] = json.dumps(raw)
    meta.update(set_keys or {})
    for key in drop_keys:
        meta.pop(key, None)
    del model.metadata_props[:]
    for key, value in meta.items():
        model.metadata_props.add(key=key, value=value)
    onnx.save(model, str(path))


def refusal(exc_type, model_dir: Path, **kwargs) -> str:
    with pytest.raises(exc_type) as info:
        OnnxModel.load(model_dir, **kwargs)
    message = str(info.value)
    assert "\n" not in message, f"expected a one-line message, got {message!r}"
    return message


@pytest.fixture(scope="module")
def model(tiny_model_dir) -> OnnxModel:
    return OnnxModel.load(tiny_model_dir, intra_op_threads=1)


@pytest.fixture(scope="module")
def crop48_model_dir(tmp_path_factory) -> Path:
    """Another tiny model with 48 px crops (same D), to swap graphs between folders. The legacy
    exporter is enough here and takes a tenth of the time."""
    pytest.importorskip("torch", reason="building a test model needs the train extra")
    from dataclasses import replace

    from estimator.export import build_random_model
    from estimator.nets import TINY

    return build_random_model(tmp_path_factory.mktemp("crop48"), replace(TINY, crop_size=48), seed=5,
                              exporter="legacy")


# ---------------------------------------------------------------------------- loading


@pytest.mark.torch
def test_load_reads_the_contract(model, tiny_model_dir):
    c = model.contract
    assert (c.crop_size_px, c.embedding_dim, c.crops_per_frame, c.frames_per_window) == (
        32,
        64,
        4,
        8,
    )
    assert c.training["trained"] is False
    assert model.model_dir == Path(tiny_model_dir)
    assert len(model.model_id) == 12 and int(model.model_id, 16) >= 0
    assert OnnxModel.load(tiny_model_dir).model_id == model.model_id  # stable
    assert "32px" in repr(model)


def test_sessions_sleep_rather_than_spin_between_ops():
    # Spinning workers held a core the live rig's other threads needed (estimator/runtime.py).
    from estimator.runtime import session_options

    for threads in (None, 1, 2):
        opts = session_options(threads)
        assert opts.get_session_config_entry("session.intra_op.allow_spinning") == "0"
        assert opts.inter_op_num_threads == 1
    # Only a benchmark asks for ONNX Runtime's default, to measure what it cost.
    assert session_options(spin_wait=True).get_session_config_entry("session.intra_op.allow_spinning") == "1"


@pytest.mark.torch
def test_model_id_follows_the_graph_bytes(tiny_model_dir, tmp_path):
    folder = copy_model(tiny_model_dir, tmp_path / "m")
    before = OnnxModel.load(folder).model_id
    edit_metadata(folder / AGGREGATOR_FILE, set_keys={"note": "retouched"})
    assert OnnxModel.load(folder).model_id != before


@pytest.mark.torch
def test_expected_fields(tiny_model_dir):
    OnnxModel.load(
        tiny_model_dir, expect={"crops_per_frame": 4, "encoding": {"kind": "cyclic-nested-sine"}}
    )
    message = refusal(
        ContractMismatch, tiny_model_dir, expect={"crop_size_px": 128, "frames_per_window": 8}
    )
    assert "crop_size_px: 32 != expected 128" in message
    assert "frames_per_window" not in message


def test_check_expected_names_nested_fields():
    contract = ModelContract(crop_size_px=64, embedding_dim=32)
    check_expected(contract, {"embedding_dim": 32, "input_norm": {"color_order": "RGB"}})
    with pytest.raises(ContractMismatch, match=r"input_norm.color_order: 'RGB' != expected 'BGR'"):
        check_expected(contract, {"input_norm": {"color_order": "BGR"}})
    with pytest.raises(ValidationError, match="not contract fields: crop_size"):
        check_expected(contract, {"crop_size": 64})


CONTRACT = ModelContract(crop_size_px=64, embedding_dim=32)


@pytest.mark.parametrize(
    ("changes", "named"),
    [
        ({"crop_size_px": 0}, "crop_size_px"),
        ({"crop_fov_deg": 0.0}, "crop_fov_deg"),
        ({"crop_fov_deg": 180.0}, "crop_fov_deg"),  # 2 fx tan(90 deg): no crop spans it
        ({"crop_fov_deg": [17.6, 0.0]}, "crop_fov_deg"),  # every angle of a mixed model is checked
        ({"crop_fov_deg": []}, "crop_fov_deg"),
        ({"input_norm": {**CONTRACT.input_norm, "mean": [0.5] * 4}}, "input_norm.mean"),  # one per colour
        # the encoding interlaces a sin(phi) and a cos(phi) branch per frequency (nets.py): depth is even
        ({"encoding": {**CONTRACT.encoding, "depth_per_angle": 171}}, "depth_per_angle"),
        ({"mirror_windows": "yes"}, "mirror_windows"),  # JSON's true or false, not a word that reads as one
    ],
)
def test_contract_refuses_values_no_model_can_have(changes, named):
    with pytest.raises(ContractMismatch, match=named):
        ModelContract(**{"crop_size_px": 64, "embedding_dim": 32, **changes})


def test_a_contract_carries_one_crop_angle_as_a_number_and_several_as_a_list():
    mixed = ModelContract(crop_size_px=64, embedding_dim=32, crop_fov_deg=(17.6, 26.0))
    assert mixed.crop_fov_deg == [17.6, 26.0] and mixed.crop_fovs_deg == (17.6, 26.0)
    assert ModelContract.from_json(mixed.to_json()) == mixed  # JSON has no tuples: stored as the list
    one = ModelContract(crop_size_px=64, embedding_dim=32, crop_fov_deg=[26.0])
    assert one.crop_fov_deg == 26.0 and one.crop_fovs_deg == (26.0,)  # as a model of one angle writes it
    assert not one.differences(ModelContract(crop_size_px=64, embedding_dim=32, crop_fov_deg=26.0))


def test_a_contract_without_mirror_windows_runs_unmirrored_and_one_with_it_keeps_it():
    # Models exported before session 23 have no such field: they ran, and still run, unmirrored.
    without = json.loads(CONTRACT.to_json())
    del without["mirror_windows"]
    assert ModelContract.from_json(json.dumps(without)).mirror_windows is False
    mirrored = dataclasses.replace(CONTRACT, mirror_windows=True)
    assert ModelContract.from_json(mirrored.to_json()) == mirrored
    assert mirrored.differences(CONTRACT) == ["mirror_windows: True != False"]


def test_trained_sun_elevations_are_read_only_as_a_range():
    def trained(elevations):
        data = {"data": {"sun_elevation_deg": elevations}}
        return ModelContract(crop_size_px=64, embedding_dim=32, training=data).trained_sun_elevation_deg

    assert trained([10.0, 60.0]) == (10.0, 60.0)
    assert trained([60.0, 10.0]) is None  # lowest above highest: a broken record, not a range
    assert trained([10.0, 95.0]) is None


def test_contract_from_json_refuses_unknown_fields_and_other_versions():
    # OnnxModel.load checks a graph's contract version before it parses the contract (tests
    # below); the contract itself checks too, for every other reader of one.
    good = json.loads(CONTRACT.to_json())
    assert ModelContract.from_json(json.dumps(good)) == CONTRACT
    with pytest.raises(ContractMismatch, match="does not know \\(colour_space\\)"):
        ModelContract.from_json(json.dumps({**good, "colour_space": "linear"}))
    with pytest.raises(ContractMismatch, match="contract version 1, got 0"):
        ModelContract.from_json(json.dumps({**good, "version": 0}))


def test_checksums_keep_only_sha256_lines():
    # An md5sum line has the same shape but a 32-digit digest: it checks nothing sunrig trusts.
    sha = "a" * 64
    text = f"{sha}  backbone.onnx\nd41d8cd98f00b204e9800998ecf8427e  aggregator.onnx\n"
    assert parse_checksums(text) == {"backbone.onnx": sha}


@pytest.mark.torch
def test_thread_count_is_validated(tiny_model_dir):
    with pytest.raises(ValidationError, match="intra_op_threads"):
        OnnxModel.load(tiny_model_dir, intra_op_threads=0)


# ---------------------------------------------------------------------------- running


@pytest.mark.torch
def test_normalise_follows_input_norm(model):
    crops = np.random.default_rng(0).integers(0, 256, size=(3, 32, 32, 3), dtype=np.uint8)
    rgb = crops[..., ::-1].astype(np.float64) / 255.0
    want = ((rgb - np.array(IMAGENET_MEAN)) / np.array(IMAGENET_STD)).transpose(0, 3, 1, 2)
    got = model.normalise(crops)
    assert got.dtype == np.float32 and got.shape == (3, 3, 32, 32) and got.flags.c_contiguous
    np.testing.assert_allclose(got, want, atol=1e-5, rtol=0)


@pytest.mark.torch
def test_embed_shapes_and_batching(model):
    crops = np.random.default_rng(1).integers(0, 256, size=(5, 32, 32, 3), dtype=np.uint8)
    whole = model.embed(crops)
    assert whole.shape == (5, 64) and whole.dtype == np.float32
    np.testing.assert_allclose(model.embed(crops, batch_size=2), whole, atol=BATCHED_F32, rtol=0)
    np.testing.assert_allclose(model.embed(crops[3:4]), whole[3:4], atol=BATCHED_F32, rtol=0)
    assert model.embed(crops[:0]).shape == (0, 64)


@pytest.mark.torch
@pytest.mark.parametrize(
    ("crops", "match"),
    [
        (np.zeros((2, 32, 32, 3), np.float32), "dtype uint8"),
        (np.zeros((2, 48, 48, 3), np.uint8), r"expected shape \(N, 32, 32, 3\)"),
        (np.zeros((32, 32, 3), np.uint8), r"expected shape \(N, 32, 32, 3\)"),
        ([[0]], "numpy array"),
    ],
)
def test_embed_rejects_bad_crops(model, crops, match):
    with pytest.raises(ValidationError, match=match):
        model.embed(crops)


@pytest.mark.torch
def test_aggregate_shapes(model):
    rng = np.random.default_rng(2)
    emb = rng.normal(size=(2, 32, 64)).astype(np.float32)
    ang = rng.uniform(-3, 3, size=(2, 32, 3))  # float64 is accepted and cast
    mask = np.ones((2, 32), dtype=bool)
    mask[1, 10:] = False
    out = model.aggregate(emb, ang, mask)
    assert out.shape == (2, 32, 3) and out.dtype == np.float32
    assert np.all(np.isfinite(out)) and np.all(out[1, 10:] == 0.0)
    single = model.aggregate(emb[1:, :10], ang[1:, :10], mask[1:, :10])
    np.testing.assert_allclose(out[1:, :10], single, atol=BATCHED_F32, rtol=0)
    assert model.aggregate(emb[:0], ang[:0], mask[:0]).shape == (0, 32, 3)


@pytest.mark.torch
def test_aggregate_rejects_bad_inputs(model):
    emb = np.zeros((1, 4, 64), np.float32)
    ang = np.zeros((1, 4, 3), np.float32)
    mask = np.ones((1, 4), bool)
    with pytest.raises(ValidationError, match=r"embeddings: expected shape \(B, T, 64\)"):
        model.aggregate(np.zeros((1, 4, 32), np.float32), ang, mask)
    with pytest.raises(ValidationError, match=r"angles: expected shape \(1, 4, 3\)"):
        model.aggregate(emb, ang[:, :3], mask)
    with pytest.raises(ValidationError, match="dtype bool"):
        model.aggregate(emb, ang, mask.astype(np.int64))
    with pytest.raises(ValidationError, match=r"mask: expected shape \(1, 4\)"):
        model.aggregate(emb, ang, mask[:, :2])
    with pytest.raises(ValidationError, match="finite"):
        model.aggregate(emb, np.full((1, 4, 3), np.nan, np.float32), mask)


# ---------------------------------------------------------------------------- refusals


def test_refuses_a_missing_folder(tmp_path):
    message = refusal(ModelError, tmp_path / "nowhere")
    assert "does not exist" in message and "backbone.onnx" in message


def test_a_graph_file_given_for_the_folder_is_called_a_file(tmp_path):
    graph = tmp_path / BACKBONE_FILE
    graph.write_bytes(b"")
    message = refusal(ModelError, graph)
    assert "is a file, not a model folder" in message and "does not exist" not in message


def test_refuses_a_folder_without_graphs(tmp_path):
    (tmp_path / BACKBONE_FILE).write_bytes(b"")
    message = refusal(ModelError, tmp_path)
    assert "lacks aggregator.onnx" in message
    (tmp_path / "checkpoint.pt").write_bytes(b"")  # an interrupted `sunrig train --out` folder
    message = refusal(ModelError, tmp_path)
    assert f"sunrig train --out {tmp_path} --export-only DIR" in message and "--model DIR" in message
    # Not "let the run finish": a stopped run does not finish by itself, its command run again does.
    assert message.endswith("or run its `sunrig train` command again to finish and export it")


def test_refuses_random_bytes(tmp_path):
    rng = np.random.default_rng(3)
    for name in (BACKBONE_FILE, AGGREGATOR_FILE):
        (tmp_path / name).write_bytes(rng.integers(0, 256, 4096, dtype=np.uint8).tobytes())
    message = refusal(ModelError, tmp_path)
    assert "backbone.onnx: not a usable ONNX graph" in message and "re-export" in message


@pytest.mark.torch
def test_a_graph_damaged_in_a_copy_is_refused_by_its_checksum(tiny_model_dir, tmp_path):
    folder = copy_model(tiny_model_dir, tmp_path / "m")
    shutil.copy(tiny_model_dir / CHECKSUMS_FILE, folder / CHECKSUMS_FILE)
    OnnxModel.load(folder)  # an export writes the sums, and an intact copy passes them
    # 64 bytes flipped deep inside the aggregator's weights: the graph still parses and runs
    # (without the sums it loads, and answers wrong), but not past its checksum.
    blob = bytearray((folder / AGGREGATOR_FILE).read_bytes())
    mid = len(blob) // 2
    blob[mid:mid + 64] = bytes(b ^ 0xFF for b in blob[mid:mid + 64])
    (folder / AGGREGATOR_FILE).write_bytes(bytes(blob))
    message = refusal(ModelError, folder)
    assert "aggregator.onnx does not match SHA256SUMS" in message and "copy the model folder again" in message
    # A sums file that checks nothing is refused too: empty, or cut short before a graph's line.
    sums = (tiny_model_dir / CHECKSUMS_FILE).read_text()
    (folder / CHECKSUMS_FILE).write_text("")
    assert "no line in sha256sum's format" in refusal(ModelError, folder)
    (folder / CHECKSUMS_FILE).write_text("".join(line + "\n" for line in sums.splitlines() if "backbone" in line))
    assert "no checksum for aggregator.onnx" in refusal(ModelError, folder)
    (folder / CHECKSUMS_FILE).unlink()
    (folder / CHECKSUMS_FILE).mkdir()  # it loaded unchecked, as if there were no sums
    assert "SHA256SUMS is not a file" in refusal(ModelError, folder)
    (folder / CHECKSUMS_FILE).rmdir()
    OnnxModel.load(folder)  # a folder without sums (older, or hand-made) is not checked
    # sha256sum's own ways of naming the files (`sha256sum ./*.onnx`, binary mode) are read.
    intact = copy_model(tiny_model_dir, tmp_path / "intact")
    renamed = sums.replace("  backbone", "  ./backbone").replace("  aggregator", " *aggregator")
    (intact / CHECKSUMS_FILE).write_text(renamed)
    OnnxModel.load(intact)


def test_the_shipped_model_passes_its_checksums():
    from estimator.models import DEFAULT_MODEL_DIR

    sums = parse_checksums((DEFAULT_MODEL_DIR / CHECKSUMS_FILE).read_text())
    assert set(sums) == {BACKBONE_FILE, AGGREGATOR_FILE}
    OnnxModel.load(DEFAULT_MODEL_DIR)


@pytest.mark.torch
def test_refuses_a_graph_without_contract(tiny_model_dir, tmp_path):
    folder = copy_model(tiny_model_dir, tmp_path / "m")
    edit_metadata(folder / AGGREGATOR_FILE, drop_keys=("sunrig.contract",))
    message = refusal(ModelError, folder)
    assert "aggregator.onnx" in message and "no 'sunrig.contract' metadata" in message


@pytest.mark.torch
def test_refuses_contract_that_is_not_json(tiny_model_dir, tmp_path):
    folder = copy_model(tiny_model_dir, tmp_path / "m")
    edit_metadata(folder / BACKBONE_FILE, set_keys={"sunrig.contract": "{crop_size_px: 32"})
    assert "not JSON" in refusal(ContractMismatch, folder)


@pytest.mark.torch
def test_refuses_graphs_from_two_models(tiny_model_dir, crop48_model_dir, tmp_path):
    folder = copy_model(tiny_model_dir, tmp_path / "m")
    shutil.copy(crop48_model_dir / BACKBONE_FILE, folder / BACKBONE_FILE)
    message = refusal(ContractMismatch, folder)
    assert "carry different contracts" in message
    assert "crop_size_px: 48 != 32" in message and "re-export" in message
    # The training record (a whole recipe) is named, not printed twice: the line stays readable.
    assert "training: differs" in message and len(message) < 600, message


@pytest.mark.torch
def test_refuses_contracts_differing_in_one_field(tiny_model_dir, tmp_path):
    folder = copy_model(tiny_model_dir, tmp_path / "m")
    edit_metadata(folder / AGGREGATOR_FILE, contract_changes={"frames_per_window": 16})
    message = refusal(ContractMismatch, folder)
    assert "frames_per_window: 8 != 16" in message and "crop_size_px" not in message


@pytest.mark.torch
def test_refuses_swapped_graphs(tiny_model_dir, tmp_path):
    folder = copy_model(tiny_model_dir, tmp_path / "m")
    shutil.copy(tiny_model_dir / AGGREGATOR_FILE, folder / BACKBONE_FILE)
    message = refusal(ContractMismatch, folder)
    assert "backbone.onnx: holds the 'aggregator' graph" in message and "swapped" in message


@pytest.mark.torch
@pytest.mark.parametrize("graph", [BACKBONE_FILE, AGGREGATOR_FILE])
def test_refuses_a_graph_with_an_input_the_runtime_does_not_feed(tiny_model_dir, tmp_path, graph):
    # It loaded once, and the first frame or window failed for a feed without that input.
    onnx = pytest.importorskip("onnx")
    folder = copy_model(tiny_model_dir, tmp_path / "m")
    model = onnx.load(str(folder / graph))
    model.graph.input.append(onnx.helper.make_tensor_value_info("frame_valid", onnx.TensorProto.FLOAT, ["B"]))
    onnx.save(model, str(folder / graph))
    message = refusal(ContractMismatch, folder)
    assert f"{graph}: input(s) ['frame_valid'] that no sunrig runtime feeds" in message
    assert message.endswith("re-export the model")


@pytest.mark.torch
@pytest.mark.parametrize(
    ("changes", "expected"),
    [
        ({"crop_size_px": 48}, "input 'crops' axis 2 is 32 but contract crop_size_px 48"),
        ({"embedding_dim": 128}, "output 'embeddings' axis 1 is 64 but contract embedding_dim 128"),
    ],
)
def test_refuses_a_contract_that_lies_about_the_graph(tiny_model_dir, tmp_path, changes, expected):
    folder = copy_model(tiny_model_dir, tmp_path / "m")
    for name in (BACKBONE_FILE, AGGREGATOR_FILE):
        edit_metadata(folder / name, contract_changes=changes)
    message = refusal(ContractMismatch, folder)
    assert "backbone.onnx" in message and expected in message


@pytest.mark.torch
@pytest.mark.parametrize(("version", "fix"), [(2, "upgrade sunrig"), (0, "re-export")])
def test_refuses_an_unknown_contract_version(tiny_model_dir, tmp_path, version, fix):
    folder = copy_model(tiny_model_dir, tmp_path / "m")
    for name in (BACKBONE_FILE, AGGREGATOR_FILE):
        edit_metadata(folder / name, contract_changes={"version": version})
    message = refusal(ContractMismatch, folder)
    assert (
        f"contract version {version}" in message and "reads version 1" in message and fix in message
    )


@pytest.mark.torch
def test_refuses_unknown_contract_fields(tiny_model_dir, tmp_path):
    folder = copy_model(tiny_model_dir, tmp_path / "m")
    for name in (BACKBONE_FILE, AGGREGATOR_FILE):
        edit_metadata(folder / name, contract_changes={"colour_space": "linear"})
    assert "colour_space" in refusal(ContractMismatch, folder)


# ---------------------------------------------------------------------------- packaging


def test_runtime_does_not_import_torch():
    code = (
        "import estimator.runtime, rig, replay, drivers, sys; "
        "assert 'torch' not in sys.modules, 'torch imported'"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr


@pytest.mark.torch
def test_aggregate_and_embed_refuse_what_would_be_cast_silently(model):
    # Integer angles are degrees or indices, never radians; cast to float they would run as
    # nonsense. A batch of 0 crops per run would loop forever or fail deep in range().
    emb = np.zeros((1, 4, 64), np.float32)
    mask = np.ones((1, 4), bool)
    with pytest.raises(ValidationError, match="angles: expected a float array, got dtype int64"):
        model.aggregate(emb, np.zeros((1, 4, 3), np.int64), mask)
    with pytest.raises(ValidationError, match="embeddings: expected a float array"):
        model.aggregate(np.zeros((1, 4, 64), np.int32), np.zeros((1, 4, 3), np.float32), mask)
    with pytest.raises(ValidationError, match="batch_size: expected a positive integer, got 0"):
        model.embed(np.zeros((2, 32, 32, 3), np.uint8), batch_size=0)


def test_a_contract_that_is_not_a_json_object_is_refused_as_such():
    # A list or a string in the metadata is no contract: said so, not reported as unknown fields.
    for text in ("[1, 2]", '"crop_size_px"'):
        with pytest.raises(ContractMismatch, match="m.onnx: the contract metadata is not a JSON object"):
            ModelContract.from_json(text, "m.onnx")


def test_a_contract_missing_a_required_field_is_refused():
    # A contract without its embedding size cannot feed the aggregator: from_json must refuse it
    # with ContractMismatch (one line, naming the model), never hand back something half made.
    raw = json.loads(CONTRACT.to_json())
    del raw["embedding_dim"]
    with pytest.raises(ContractMismatch, match=r"m.onnx: incomplete contract \(.*embedding_dim.*\); re-export"):
        ModelContract.from_json(json.dumps(raw), "m.onnx")


def test_contract_refuses_a_colour_order_the_runtime_cannot_feed():
    # input_affine swaps channels for RGB and leaves them for anything else: another order
    # ("YUV", or a lower-case "rgb") would be fed as BGR without a word, so it is refused here.
    for order in ("YUV", "rgb"):
        with pytest.raises(ContractMismatch, match="input_norm.color_order: expected 'RGB' or 'BGR'"):
            ModelContract(crop_size_px=64, embedding_dim=32, input_norm={**CONTRACT.input_norm, "color_order": order})
    assert ModelContract(crop_size_px=64, embedding_dim=32,
                         input_norm={**CONTRACT.input_norm, "color_order": "BGR"}).input_norm["color_order"] == "BGR"


def test_defaults_feed_a_model_as_the_shipped_one_is_fed():
    # A model exported with the default contract must be fed as the shipped model is: ImageNet
    # normalisation (which its pretrained backbone expects), the same angle encoding (kind, alpha,
    # base, yaw input) and 8 frames a window. An edited default would feed new exports numbers
    # their networks never learnt. (depth_per_angle is the architecture's: the paper's 170 by default.)
    from estimator.models import DEFAULT_MODEL_DIR

    shipped = OnnxModel.load(DEFAULT_MODEL_DIR).contract
    # Key by key: pytest 9.2's approx refuses a dict holding lists (9.0's compared it).
    mine, theirs = CONTRACT.input_norm, shipped.input_norm
    assert mine.keys() == theirs.keys() and mine["color_order"] == theirs["color_order"]
    for key in ("scale", "mean", "std"):
        assert mine[key] == pytest.approx(theirs[key]), key
    assert list(IMAGENET_MEAN) == shipped.input_norm["mean"] and list(IMAGENET_STD) == shipped.input_norm["std"]
    for key in ("kind", "alpha", "base", "yaw_input"):
        assert CONTRACT.encoding[key] == shipped.encoding[key], key
    assert CONTRACT.frames_per_window == shipped.frames_per_window == 8


def test_encoding_the_runtime_does_not_compute_is_refused():
    # The runtime computes one encoding, fed yaw relative to the newest frame: a contract asking
    # for another kind or another yaw input would get numbers its network never saw.
    for changes, named in (({"kind": "learned"}, "encoding.kind: expected 'cyclic-nested-sine'"),
                           ({"yaw_input": "absolute"}, "encoding.yaw_input: this runtime feeds")):
        with pytest.raises(ContractMismatch, match=named):
            ModelContract(crop_size_px=64, embedding_dim=32, encoding={**CONTRACT.encoding, **changes})


def test_a_contract_cannot_change_after_it_was_checked():
    # Validated once, when made: a field set afterwards would bypass every check above.
    import dataclasses

    with pytest.raises(dataclasses.FrozenInstanceError):
        CONTRACT.crop_size_px = 0


def test_trained_elevation_range_bounds_are_inclusive():
    def trained(elevations):
        return ModelContract(crop_size_px=64, embedding_dim=32,
                             training={"data": {"sun_elevation_deg": elevations}}).trained_sun_elevation_deg

    assert trained([-90.0, 90.0]) == (-90.0, 90.0)  # the horizon's far side to the zenith: the whole sky
    assert trained([35.0, 35.0]) == (35.0, 35.0)  # one short drive: one elevation is still a range
    assert trained([10.0, 90.5]) is None and trained([-90.5, 10.0]) is None  # no sun is there


def test_a_fine_tuned_models_trained_range_includes_its_starts():
    # Fine-tuned on drives with the sun at 12..18 deg from a model trained on 5..75 deg: it has
    # seen suns up to 75 deg, so suns above 18 deg must not be flagged as beyond its training.
    def trained(training):
        return ModelContract(crop_size_px=64, embedding_dim=32, training=training).trained_sun_elevation_deg

    own = {"sun_elevation_deg": [12.0, 18.0]}
    assert trained({"data": own, "init": {"data": {"sun_elevation_deg": [5.0, 75.0]}}}) == (5.0, 75.0)
    # The start's own chain (its range including its start's) wins over its data's range.
    assert trained({"data": own, "init": {"sun_elevation_deg": [3.0, 80.0],
                                          "data": {"sun_elevation_deg": [5.0, 75.0]}}}) == (3.0, 80.0)
    assert trained({"data": own}) == (12.0, 18.0)


def test_an_encoding_missing_a_parameter_is_refused_by_name():
    # Without alpha, base or depth_per_angle the runtime cannot compute the encoding: refused when
    # the contract is read, naming the key, not a KeyError in the middle of the first window.
    for key in ("alpha", "base", "depth_per_angle"):
        encoding = {k: v for k, v in CONTRACT.encoding.items() if k != key}
        with pytest.raises(ContractMismatch, match=f"encoding.{key}: missing"):
            ModelContract(crop_size_px=64, embedding_dim=32, encoding=encoding)


@pytest.mark.parametrize(("changes", "says"), [
    # Each was an AttributeError, KeyError, ValueError or ZeroDivisionError at load or at the first
    # window (an internal error), or (the sizes) ran the runtime out of memory without a word.
    ({"training": None}, "training: expected a JSON object, got None"),
    ({"training": [1]}, "training: expected a JSON object, got [1]"),
    ({"encoding": []}, "encoding: expected a JSON object, got []"),
    ({"input_norm": None}, "input_norm: expected a JSON object, got None"),
    ({"input_norm": {**CONTRACT.input_norm, "scale": "x"}}, "input_norm.scale: expected a finite number > 0, got 'x'"),
    ({"input_norm": {k: v for k, v in CONTRACT.input_norm.items() if k != "scale"}},
     "input_norm.scale: expected a finite number > 0, got None"),
    ({"input_norm": {**CONTRACT.input_norm, "mean": ["a", "b", "c"]}},
     "input_norm.mean: expected 3 finite numbers, got ['a', 'b', 'c']"),
    ({"input_norm": {**CONTRACT.input_norm, "std": [0, 0, 0]}}, "input_norm.std: expected 3 finite numbers > 0"),
    # Finite in the contract, inf in the float32 crops: every window failed on the model's NaN.
    ({"input_norm": {**CONTRACT.input_norm, "scale": 1e300}}, "give pixel values beyond float32"),
    ({"input_norm": {**CONTRACT.input_norm, "std": [1e-300, 1.0, 1.0]}}, "give pixel values beyond float32"),
    ({"encoding": {**CONTRACT.encoding, "depth_per_angle": "x"}},
     "encoding.depth_per_angle: expected an even number > 0, got 'x'"),
    ({"encoding": {**CONTRACT.encoding, "alpha": float("nan")}}, "encoding.alpha: expected a finite number > 0"),
    ({"crops_per_frame": 100_000}, "crops_per_frame: expected an integer from 1 to 256, got 100000"),
    ({"frames_per_window": True}, "frames_per_window: expected an integer from 1 to 64, got True"),
])
def test_a_contract_with_a_part_of_the_wrong_type_is_refused_by_name(changes, says):
    with pytest.raises(ContractMismatch) as info:
        ModelContract(**{**dataclasses.asdict(CONTRACT), **changes})
    assert says in str(info.value)
    assert str(info.value).endswith("; re-export the model from its training run, or pass another --model")
    # Read from a model's metadata, the same refusal names the file (a one-line error at the CLI).
    with pytest.raises(ContractMismatch, match=r"^backbone.onnx: invalid model contract: "):
        ModelContract.from_json(json.dumps({**dataclasses.asdict(CONTRACT), **changes}), where="backbone.onnx")
