"""An int8 backbone (estimator/quantize.py): a real ONNX Runtime quantization of a tiny model."""

import math
import shutil
from typing import NamedTuple

import numpy as np
import pytest

from estimator.estimator import SunEstimator
from rig.errors import ValidationError
from rig.types import Attitude, Frame, HeadingRef, Intrinsics

pytestmark = pytest.mark.torch  # the onnx package of the train extra, and the tiny model's export
onnx = pytest.importorskip("onnx", reason="quantizing needs the train extra")

INTR = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)


def _frames(n, seed=0):
    """Smooth random scenes (noise blurred), so that crops differ as a street's do."""
    import cv2

    rng = np.random.default_rng(seed)
    out = []
    for i in range(n):
        img = cv2.GaussianBlur(rng.integers(0, 256, (80, 128, 3), dtype=np.uint8), (9, 9), 3)
        out.append(Frame(t_mono_s=0.1 * i, seq=i, image_bgr=img, intrinsics=INTR,
                         attitude=Attitude(math.radians(15.0 * i), HeadingRef.TRUE)))
    return out


@pytest.fixture(scope="module")
def model(tiny_model_dir):
    from estimator.runtime import OnnxModel

    return OnnxModel.load(tiny_model_dir)


@pytest.fixture(scope="module")
def int8_dir(model, tmp_path_factory):
    from estimator.quantize import calibration_crops, quantize_model

    calibration = calibration_crops(SunEstimator(model), [_frames(40, seed=1)], n_crops=128)
    return quantize_model(model, calibration, tmp_path_factory.mktemp("q") / "int8", record={"note": "test"})


def test_the_int8_model_is_a_model_folder_with_integer_convolutions_and_says_so(model, int8_dir):
    from estimator.runtime import OnnxModel

    q = OnnxModel.load(int8_dir)  # its SHA256SUMS and both contracts are checked on load
    ops = {n.op_type for n in onnx.load(str(int8_dir / "backbone.onnx")).graph.node}
    assert {"QuantizeLinear", "DequantizeLinear", "Conv"} <= ops
    agg_ops = {n.op_type for n in onnx.load(str(int8_dir / "aggregator.onnx")).graph.node}
    assert "QuantizeLinear" not in agg_ops  # the aggregator stays float
    record = q.contract.training["quantization"]
    assert record["backbone"] == "int8" and record["from_model"] == model.model_id
    assert record["calibration_crops"] == 128 and record["note"] == "test"
    # Everything else is the float model's contract: it is fed and read the same way.
    assert {k: v for k, v in q.contract.training.items() if k != "quantization"} == model.contract.training
    assert q.contract.differences(model.contract) == [f"training: {q.contract.training!r} != "
                                                      f"{model.contract.training!r}"]
    assert q.model_id != model.model_id


def test_int8_embeddings_and_answers_stay_close_to_the_float_models(model, int8_dir):
    from estimator.runtime import OnnxModel

    q = OnnxModel.load(int8_dir)
    frames = _frames(8, seed=7)  # not the calibration frames
    crops = np.concatenate([SunEstimator(model).backbone_crops(f) for f in frames])
    a, b = model.embed(crops), q.embed(crops)
    cos = (a * b).sum(1) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
    assert cos.min() > 0.98, cos.min()
    assert not np.allclose(a, b, atol=1e-6)  # it is not the float graph under another name
    est_f, est_q = SunEstimator(model, seed=2), SunEstimator(q, seed=2)
    sun_f = est_f.estimate(est_f.encode_batch(frames)).sun_enu
    sun_q = est_q.estimate(est_q.encode_batch(frames)).sun_enu
    assert math.degrees(math.acos(min(1.0, float(np.dot(sun_f, sun_q))))) < 5.0


def test_calibration_crops_are_the_runtimes_own_from_frames_drawn_across_the_sources(model):
    from estimator.quantize import calibration_crops

    est = SunEstimator(model, seed=4)
    short, long = _frames(3, seed=2), _frames(60, seed=3)
    x = calibration_crops(est, [short, long], n_crops=40, seed=0)
    s = model.contract.crop_size_px
    assert x.shape == (40, s, s, 3) and x.dtype == np.uint8
    # Each kept frame gives its crops as the runtime cuts them, whole (normalised a batch at a
    # time as they are fed: test_calibration_is_held_as_the_crops_and_normalised_a_batch_at_a_time).
    per_frame = est.backbone_crops_per_frame
    blocks = {est.backbone_crops(f).tobytes(): f for f in (*short, *long)}
    found = [blocks.get(x[i:i + per_frame].tobytes()) for i in range(0, 40, per_frame)]
    kept = [f for f in found if f is not None]
    assert len(kept) == len(found) and len({id(f) for f in kept}) == len(kept)
    # Drawn across both sources, not the first frames read.
    assert any(f in long and f.seq >= 30 for f in kept)
    # Same seed, same draw; another seed, another.
    np.testing.assert_array_equal(x, calibration_crops(est, [short, long], n_crops=40, seed=0))
    assert not np.array_equal(x, calibration_crops(est, [short, long], n_crops=40, seed=1))
    # Fewer frames than asked for: all of them, no more.
    assert len(calibration_crops(est, [short], n_crops=1000)) == 3 * per_frame
    assert len(calibration_crops(est, [[]], n_crops=10)) == 0
    with pytest.raises(ValidationError, match="calibration crops: expected a positive integer"):
        calibration_crops(est, [short], n_crops=0)


def test_calibration_is_held_as_the_crops_and_normalised_a_batch_at_a_time(model):
    # The crops were normalised all at once into float32, 4 bytes a value where a crop has 1, and
    # through two float temporaries: quantizing the paper's architecture (224 px, 1024 crops)
    # peaked at 1.7 GB before ONNX Runtime began, which a small computer does not have.
    import tracemalloc

    from estimator.contract import BACKBONE_INPUT
    from estimator.quantize import _CalibrationReader, calibration_crops

    est = SunEstimator(model, seed=0)
    frames = _frames(60, seed=5)
    tracemalloc.start()
    try:
        x = calibration_crops(est, [frames], n_crops=200)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert x.dtype == np.uint8 and peak < 3 * x.nbytes, (peak, x.nbytes)
    fed = []
    reader = _CalibrationReader(model, x)
    while (batch := reader.get_next()) is not None:
        fed.append(batch[BACKBONE_INPUT])
    assert all(len(b) <= 8 for b in fed)
    np.testing.assert_array_equal(np.concatenate(fed), model.normalise(x))


def test_a_mirrored_model_is_calibrated_on_its_flipped_crops_too(model):
    est = SunEstimator(model, seed=0, mirror_windows=True)
    frame = _frames(1)[0]
    crops = est.backbone_crops(frame)
    n = est.crops_per_frame
    assert est.backbone_crops_per_frame == 2 * n == len(crops)
    np.testing.assert_array_equal(crops[n:], crops[:n, :, ::-1])


def test_quantizing_refuses_to_replace_anything_or_to_quantize_twice(model, int8_dir, tmp_path):
    from estimator.quantize import quantize_model
    from estimator.runtime import OnnxModel

    calibration = np.zeros((4, 3, model.contract.crop_size_px, model.contract.crop_size_px), np.float32)
    with pytest.raises(ValidationError, match="is the model being quantized"):
        quantize_model(model, calibration, model.model_dir)
    with pytest.raises(ValidationError, match="holds backbone.onnx already; pass a new folder"):
        quantize_model(model, calibration, int8_dir)
    run = tmp_path / "run"
    run.mkdir()
    (run / "checkpoint.pt").write_bytes(b"a training run")
    with pytest.raises(ValidationError, match="holds checkpoint.pt already"):
        quantize_model(model, calibration, run)
    with pytest.raises(ValidationError, match="its backbone is int8 already; quantize the float model"):
        quantize_model(OnnxModel.load(int8_dir), calibration, tmp_path / "twice")
    with pytest.raises(ValidationError, match="no frames to calibrate on"):
        quantize_model(model, calibration[:0], tmp_path / "empty")
    assert not (tmp_path / "twice").exists() and not (tmp_path / "empty").exists()


def test_the_weights_for_fine_tuning_come_along(model, tmp_path):
    from estimator.quantize import calibration_crops, quantize_model

    src = tmp_path / "float"
    shutil.copytree(model.model_dir, src)
    (src / "weights.npz").write_bytes(b"float weights")
    from estimator.runtime import OnnxModel

    out = quantize_model(OnnxModel.load(src), calibration_crops(SunEstimator(model), [_frames(4)], n_crops=16),
                         tmp_path / "int8")
    assert (out / "weights.npz").read_bytes() == b"float weights"


def test_without_the_onnx_package_it_names_the_extra_before_reading_a_log(model, tmp_path, monkeypatch):
    import sys

    from estimator.quantize import quantize_logs_model
    from rig.errors import MissingExtraError

    def never_read():
        raise AssertionError("a log was read before the missing package was named")
        yield

    monkeypatch.setitem(sys.modules, "onnx", None)  # as if the train extra were not installed
    monkeypatch.setitem(sys.modules, "onnxruntime.quantization", None)
    with pytest.raises(MissingExtraError, match=r"install the train extra with `pip install 'sunrig\[train\]'`"):
        quantize_logs_model(model, [(tmp_path / "drive.mcap", never_read())], tmp_path / "int8")
    assert not (tmp_path / "int8").exists()


@pytest.mark.parametrize("existed", [False, True])
def test_an_interrupted_quantization_leaves_no_folder_it_made(model, tmp_path, monkeypatch, existed):
    # Ctrl-C during the quantizer's calibration left an empty --out: neither a model nor absent.
    # A folder the user made beforehand stays, empty as it was.
    from onnxruntime import quantization

    from estimator.quantize import calibration_crops, quantize_model

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(quantization, "quantize_static", interrupted)
    out = tmp_path / "int8"
    if existed:
        out.mkdir()
    calibration = calibration_crops(SunEstimator(model), [_frames(10, seed=1)], n_crops=16)
    with pytest.raises(KeyboardInterrupt):
        quantize_model(model, calibration, out)
    assert out.exists() == existed and (not existed or not any(out.iterdir()))


def _never_read():
    raise AssertionError("a log was read before the --out was refused")
    yield


def test_an_out_that_cannot_be_written_is_refused_before_a_log_is_read(model, tmp_path):
    # It was found by the mkdir after every log had been read for calibration: minutes of a
    # fleet's logs, then "cannot make the model folder".
    from estimator.quantize import quantize_logs_model

    a_file = tmp_path / "notes.txt"
    a_file.write_text("not a folder")
    with pytest.raises(ValidationError, match=r"--out .*notes.txt/int8: cannot write there \(Not a directory"):
        quantize_logs_model(model, [(tmp_path / "drive.mcap", _never_read())], a_file / "int8")
    assert a_file.read_text() == "not a folder"


class _DiskUsage(NamedTuple):
    total: int
    used: int
    free: int


class _Usage:
    """shutil.disk_usage's answer with ``free`` bytes, for the calls after the first ``plenty``."""

    def __init__(self, free, plenty=0):
        self.free, self.plenty, self.calls = free, plenty, 0

    def __call__(self, path):
        self.calls += 1
        free = 10**12 if self.calls <= self.plenty else self.free
        return _DiskUsage(10**12, 10**12 - free, free)


def test_an_out_on_a_disk_without_room_for_the_model_is_refused_before_a_log_is_read(model, tmp_path, monkeypatch):
    import estimator.quantize as quantize

    monkeypatch.setattr(quantize.shutil, "disk_usage", _Usage(free=1000))
    with pytest.raises(ValidationError, match=r"--out .*int8: writing the int8 model needs about [\d.]+ MB on its "
                                              r"disk, 0.0 MB free; free space there"):
        quantize.quantize_logs_model(model, [(tmp_path / "drive.mcap", _never_read())], tmp_path / "int8")
    assert not (tmp_path / "int8").exists()


def test_a_disk_that_fills_while_the_model_is_written_is_said_as_a_full_disk_where_the_model_goes(
        model, tmp_path, monkeypatch):
    # A full disk was an internal error: shutil.copyfile names the file it read (the shipped
    # model's weights.npz, sunrig's own file, a bug to the command line), and a graph that onnx's
    # C++ shape inference wrote cut short failed to parse ("DecodeError: ... Wire format was
    # corrupt"), a full disk nowhere said.
    import errno

    import estimator.quantize as quantize
    from estimator.quantize import calibration_crops, quantize_model
    from estimator.runtime import OnnxModel

    src = tmp_path / "float"
    shutil.copytree(model.model_dir, src)
    (src / "weights.npz").write_bytes(b"float weights")
    calibration = calibration_crops(SunEstimator(model), [_frames(4)], n_crops=16)

    def copy_filling(a, b):
        raise OSError(errno.ENOSPC, "No space left on device", str(a), None, str(b))

    monkeypatch.setattr(quantize.shutil, "copyfile", copy_filling)
    out = tmp_path / "int8"
    with pytest.raises(OSError) as caught:
        quantize_model(OnnxModel.load(src), calibration, out)
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(out)
    assert not out.exists()
    monkeypatch.undo()

    from onnxruntime import quantization

    def truncated(*args, **kwargs):
        raise ValueError("Error parsing message with type 'onnx.ModelProto': Wire format was corrupt")

    monkeypatch.setattr(quantization, "quantize_static", truncated)
    monkeypatch.setattr(quantize.shutil, "disk_usage", _Usage(free=0, plenty=1))  # full once the writing began
    with pytest.raises(OSError) as caught:
        quantize_model(model, calibration, out)
    assert caught.value.errno == errno.ENOSPC and caught.value.filename == str(out)
    assert not out.exists()
    # With room on the disk, a failure is what it is.
    monkeypatch.setattr(quantize.shutil, "disk_usage", _Usage(free=10**9))
    with pytest.raises(ValueError, match="Wire format was corrupt"):
        quantize_model(model, calibration, out)


def test_each_file_is_on_the_disk_before_it_is_moved_into_place(model, tmp_path, disk_events):
    # Renamed with their data still in memory, a power loss could leave empty graphs under their
    # names, which a rig then refuses (or the weights.npz a fine-tune starts from, empty).
    from estimator.quantize import calibration_crops, quantize_model
    from estimator.runtime import OnnxModel

    src = tmp_path / "float"
    shutil.copytree(model.model_dir, src)
    (src / "weights.npz").write_bytes(b"float weights")
    calibration = calibration_crops(SunEstimator(model), [_frames(4)], n_crops=16)
    out = quantize_model(OnnxModel.load(src), calibration, tmp_path / "int8")
    for name in ("backbone.onnx", "aggregator.onnx", "SHA256SUMS", "weights.npz"):
        assert disk_events.synced_in_order(out / name), name


@pytest.mark.parametrize("held", ["weights.npz", "SHA256SUMS"])
def test_an_out_holding_a_models_other_files_is_refused_too(model, tmp_path, held):
    # Only the graphs and a checkpoint were looked for: another model's weights.npz was replaced
    # (or, from a model without one, left beside the int8 graphs as if theirs, for a fine-tune to
    # start from), and a stale SHA256SUMS replaced without a word.
    from estimator.quantize import quantize_model

    out = tmp_path / "int8"
    out.mkdir()
    (out / held).write_bytes(b"another model's")
    calibration = np.zeros((4, 3, model.contract.crop_size_px, model.contract.crop_size_px), np.float32)
    with pytest.raises(ValidationError, match=f"holds {held} already; pass a new folder as --out"):
        quantize_model(model, calibration, out)
    assert [p.name for p in out.iterdir()] == [held] and (out / held).read_bytes() == b"another model's"


def test_logs_with_fewer_crops_than_asked_are_calibrated_on_with_a_warning(model, tmp_path, caplog):
    # 40 frames gave the shipped model 640 crops where 1024 were asked, without a word: only the
    # contract's calibration_crops said it.
    import logging

    from estimator.quantize import quantize_logs_model
    from estimator.runtime import OnnxModel

    caplog.set_level(logging.WARNING)
    (tmp_path / "drive.mcap").write_bytes(b"the frames' log, for its fingerprint")
    out = quantize_logs_model(model, [(tmp_path / "drive.mcap", _frames(5))], tmp_path / "int8", n_crops=64)
    per_frame = SunEstimator(model).backbone_crops_per_frame
    assert OnnxModel.load(out).contract.training["quantization"]["calibration_crops"] == 5 * per_frame
    assert [r.getMessage() for r in caplog.records] == [
        f"quantize: the logs hold 5 frames, {5 * per_frame} crops of the 64 asked; calibrating on those (more "
        "frames like the rig's calibrate the int8 model better)"]
    caplog.clear()
    quantize_logs_model(model, [(tmp_path / "drive.mcap", _frames(20))], tmp_path / "int8b", n_crops=64)
    assert not caplog.records


def test_the_backbone_runs_of_the_calibration_report_their_progress(model, tmp_path):
    # Reading the logs reported frames; ONNX Runtime's runs of the backbone over the crops, the
    # longer part for a wide backbone (20 s for the paper's on 2 cores, 1024 crops), said nothing.
    from estimator.quantize import calibration_crops, quantize_model

    calibration = calibration_crops(SunEstimator(model), [_frames(10, seed=1)], n_crops=40)
    calls = []
    quantize_model(model, calibration, tmp_path / "int8", calibration_progress=lambda done, total: calls.append(
        (done, total)))
    assert calls[0] == (0, 40) and calls[-1] == (40, 40)
    assert [d for d, _ in calls] == sorted(d for d, _ in calls) and {t for _, t in calls} == {40}


def test_the_same_logs_in_another_order_give_the_same_int8_graph(model, tmp_path):
    # The draw followed the order the logs were given in (a shell's glob, another's listing), so
    # the same logs, under the same calibration_fingerprint, made another int8 model.
    from onnx import numpy_helper

    from estimator.quantize import quantize_logs_model

    a, b = tmp_path / "drive_a.mcap", tmp_path / "drive_b.mcap"
    a.write_bytes(b"a")
    b.write_bytes(b"bb")

    def weights(order, name):
        frames = {a: _frames(12, seed=1), b: _frames(12, seed=2)}
        out = quantize_logs_model(model, [(p, frames[p]) for p in order], tmp_path / name, n_crops=24)
        return {t.name: numpy_helper.to_array(t) for t in onnx.load(str(out / "backbone.onnx")).graph.initializer}

    first, second = weights([a, b], "ab"), weights([b, a], "ba")
    assert first.keys() == second.keys()
    assert all(np.array_equal(first[k], second[k]) for k in first)


def test_a_second_quantize_into_one_out_is_refused_and_a_killed_runs_staging_is_cleared(model, tmp_path):
    # Two runs into one --out staged into the same folder unguarded; and a run killed with -9 left
    # its .quantize-* staging (MBs) inside the folder, which the next run's model then carried.
    import fcntl
    import os

    from estimator.quantize import QUANTIZE_LOCK, calibration_crops, quantize_model

    calibration = calibration_crops(SunEstimator(model), [_frames(4)], 16)
    out = tmp_path / "int8"
    out.mkdir()
    debris = out / ".quantize-k1ll3d"
    debris.mkdir()
    (debris / "backbone.onnx").write_bytes(b"half a graph")
    lock = out / QUANTIZE_LOCK
    fd = os.open(lock, os.O_RDWR | os.O_CREAT)  # another process's run holds the folder
    try:
        os.write(fd, b"4242")
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(ValidationError, match=r"--out .*int8 is in use by another sunrig quantize \(pid 4242\)"):
            quantize_model(model, calibration, out)
    finally:
        os.close(fd)
    assert debris.exists()  # not another's to clear while it was held
    lock.unlink()
    quantize_model(model, calibration, out)
    assert sorted(p.name for p in out.iterdir()) == ["SHA256SUMS", "aggregator.onnx", "backbone.onnx"]
