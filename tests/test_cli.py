"""`sunrig replay` as a user runs it: a subprocess, its exit code, its stdout and stderr."""

import functools
import json
import math
import operator
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from replay.sources import DEMO_LOG
from rig.types import Attitude, Frame, HeadingRef, Intrinsics

PNG_BYTES = bytes.fromhex("89504e470d0a1a0a0000000d4948445200000001000000010806000000") + b"\x00" * 20


def run_cli(*args, timeout=120):
    env = dict(os.environ, PYTHONWARNINGS="ignore")
    return subprocess.run([sys.executable, "-m", "rig.cli", *args], capture_output=True, text=True,
                          timeout=timeout, env=env)


@pytest.fixture
def bad_inputs(tmp_path):
    paths = {
        "random": tmp_path / "random.mcap",
        "empty": tmp_path / "empty.mcap",
        "png": tmp_path / "image.png",
    }
    paths["random"].write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    paths["empty"].write_bytes(b"")
    paths["png"].write_bytes(PNG_BYTES)
    paths["missing"] = tmp_path / "nope.mcap"
    paths["directory"] = tmp_path
    return paths


@pytest.mark.parametrize("kind", ["random", "empty", "png", "missing", "directory"])
def test_replay_of_a_non_log_fails_with_one_line(bad_inputs, kind):
    res = run_cli("replay", str(bad_inputs[kind]), "--jsonl", "-")
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1, res.stderr
    assert lines[0].startswith("sunrig: error: ") and "Traceback" not in res.stderr
    assert str(bad_inputs[kind].name) in lines[0]
    assert res.stdout == ""


def test_replay_of_a_log_none_of_whose_frames_can_be_read_fails(tmp_path, monkeypatch):
    # Each corrupt image is skipped with a warning; a log of nothing else replayed "0 frames,
    # 0 estimates" and exited 0, as if it had worked.
    import replay.native

    log = _write_log(tmp_path / "good.mcap")
    res = run_cli("replay", str(log), "--jsonl", str(tmp_path / "good.jsonl"))
    assert res.returncode == 0, res.stderr
    monkeypatch.setattr(replay.native, "encode_image", lambda *a, **k: b"not an image message")
    log = _write_log(tmp_path / "bad.mcap")
    res = run_cli("replay", str(log), "--jsonl", str(tmp_path / "bad.jsonl"))
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines()[-1] == (
        f"sunrig: error: {log}: no frame of it could be read (the warnings above say why); "
        "replay another log, or re-record this one")


def _unreadable_log(path, monkeypatch):
    """A native log of 12 frames none of whose images can be read."""
    import replay.native

    with monkeypatch.context() as m:
        m.setattr(replay.native, "encode_image", lambda *a, **k: b"not an image message")
        return _write_log(path)


@pytest.mark.parametrize("command", ["replay", "run", "gnss"])
def test_a_command_that_writes_no_estimate_leaves_its_jsonl_as_it_was(tmp_path, capsys, monkeypatch, command):
    # The JSONL output was opened with truncation before the first frame was read: a replay of a log
    # none of whose frames could be read ended rc 2 with yesterday's file at 0 bytes, and a new path
    # left behind as a 0-byte file. run and gnss open theirs the same way.
    if command == "gnss":
        bad = tmp_path / "capture.txt"
        bad.write_text("hello\n")  # no NMEA sentence
        argv = ["gnss", str(bad)]
    else:
        bad = _unreadable_log(tmp_path / "bad.mcap", monkeypatch)
        argv = (["replay", str(bad), "--aggregator", "mean"] if command == "replay" else
                ["run", "--camera", f"file:{bad}", "--heading", "log", "--fast"])
    keep, new = tmp_path / "keep.jsonl", tmp_path / "new.jsonl"
    keep.write_text("prev\n")
    for out in (keep, new):
        rc, captured = _main_in_process([*argv, "--jsonl", str(out), "--quiet"], capsys)
        if command != "run":  # (a live run that read nothing ends as a camera that sent nothing)
            _assert_one_line_error(rc, captured, names=bad.name)
    assert keep.read_text() == "prev\n" and not new.exists()
    if command == "replay":  # the first estimate replaces what was there
        rc, captured = _main_in_process(["replay", "--aggregator", "mean", "--jsonl", str(keep), "--quiet"], capsys)
        assert rc == 0, captured.err
        assert "prev" not in keep.read_text() and len(keep.read_text().splitlines()) > 1


def test_replay_of_a_log_with_no_heading_fails_saying_so(tmp_path):
    # Every frame read, none with a heading: it replayed "0 estimates" and exited 0.
    from replay.native import LogWriter

    intr = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    log = tmp_path / "nohead.mcap"
    with LogWriter(log) as w:
        for i in range(4):
            w.write_frame(Frame(t_mono_s=0.2 * i, seq=i, image_bgr=np.full((80, 128, 3), 90 + i, np.uint8),
                                intrinsics=intr))
    res = run_cli("replay", str(log), "--jsonl", str(tmp_path / "out.jsonl"), "--quiet")
    assert res.returncode == 2 and "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines()[-1] == (
        f"sunrig: error: {log}: no estimate: 4 of its 4 frames have no heading; record with a heading source "
        "(--heading)")


def test_debug_shows_the_traceback(bad_inputs):
    res = run_cli("--debug", "replay", str(bad_inputs["random"]))
    assert res.returncode != 0 and "Traceback" in res.stderr


def _write_log(path, n=12, **writer):
    from replay.native import LogWriter

    intr = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    rng = np.random.default_rng(4)
    with LogWriter(path, **writer) as w:
        for i in range(n):
            img = rng.integers(0, 256, size=(80, 128, 3), dtype=np.uint8)
            att = Attitude(math.radians(10.0 * i), HeadingRef.TRUE) if i != 5 else None
            w.write_frame(Frame(t_mono_s=0.2 * i, seq=i, image_bgr=img, intrinsics=intr, attitude=att,
                                sun_enu_truth=[0.6, 0.0, 0.8]))
    return path


def test_eval_of_logs_with_no_window_to_grade_says_why(tmp_path):
    from replay.native import LogWriter

    log = tmp_path / "no_heading.mcap"
    intr = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    with LogWriter(log) as w:  # the true sun on every frame, but no heading
        for i in range(12):
            w.write_frame(Frame(t_mono_s=0.2 * i, seq=i, image_bgr=np.full((80, 128, 3), 100, np.uint8),
                                intrinsics=intr, sun_enu_truth=[0.6, 0.0, 0.8]))
    res = run_cli("eval", str(log), "--json", str(tmp_path / "e.json"))
    assert res.returncode == 2, res.stderr
    assert res.stderr.startswith("sunrig: error: eval graded nothing: no full window with ground truth in these "
                                 "logs (12 of the 12 frames have no heading); evaluate logs from `sunrig synth`")
    # --quiet silences progress, not errors: it exited 2 with nothing said.
    res = run_cli("eval", str(log), "--json", str(tmp_path / "e.json"), "--quiet")
    assert res.returncode == 2 and res.stderr.startswith("sunrig: error: eval graded nothing"), res.stderr
    assert len(res.stderr.strip().splitlines()) == 1


def test_eval_of_logs_without_the_true_sun_says_so(tmp_path):
    from replay.native import LogWriter

    log = tmp_path / "no_truth.mcap"
    intr = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    rng = np.random.default_rng(3)
    with LogWriter(log) as w:  # headings, but no true sun
        for i in range(12):
            w.write_frame(Frame(t_mono_s=0.2 * i, seq=i, image_bgr=rng.integers(0, 256, (80, 128, 3), np.uint8),
                                intrinsics=intr, attitude=Attitude(math.radians(10.0 * i), HeadingRef.TRUE)))
    res = run_cli("eval", str(log), "--json", str(tmp_path / "e.json"), "--aggregators", "mean")
    assert res.returncode == 2, res.stderr
    assert "no full window with ground truth in these logs (5 windows had no true sun)" in res.stderr


@pytest.mark.torch
def test_eval_json_counts_the_records_a_damaged_log_lost(tmp_path, capsys, caplog, tiny_model_dir):
    # A chunk that fails its CRC, or an image that does not decode, is skipped with a warning on
    # stderr; the JSON said nothing of it, so a figure read later from a damaged log looked like
    # one from a whole log. Pooled over the logs, and per log among the worst.
    from mcap.reader import make_reader

    from tests.test_kitti import DRIVE, make_drive

    fleet = tmp_path / "fleet"
    fleet.mkdir()
    whole = _write_log(fleet / "a.mcap")
    damaged = _write_log(fleet / "b.mcap", chunk_size=1)  # a chunk a frame: the damage costs one frame
    with open(damaged, "rb") as f:
        victim = make_reader(f).get_summary().chunk_indexes[9]
    data = bytearray(damaged.read_bytes())
    mid = victim.chunk_start_offset + victim.chunk_length - victim.compressed_size // 2
    data[mid : mid + 16] = bytes(b ^ 0x5A for b in data[mid : mid + 16])  # fails the chunk's CRC
    damaged.write_bytes(bytes(data))
    date = make_drive(tmp_path / "kitti", 12)
    (date / DRIVE / "image_02" / "data" / "0000000003.png").write_bytes(b"not a png")
    out = tmp_path / "e.json"
    rc, captured = _main_in_process(["eval", str(fleet), str(date / DRIVE), "--utc-offset", "2", "--model",
                                     str(tiny_model_dir), "--aggregators", "mean", "--quiet", "--json", str(out)],
                                    capsys)
    assert rc == 0, captured.err
    said = " ".join(r.getMessage() for r in caplog.records)  # what stderr says: warned, and now counted too
    assert "skipped a corrupt chunk" in said and "0000000003.png is missing or not an image" in said
    summary = json.loads(out.read_text())
    assert summary["frames"] == 12 + 11 + 11
    assert summary["records_skipped_corrupt"] == 2
    rows = {row["log"]: row["records_skipped_corrupt"] for row in summary["worst_logs"]["mean"]}
    assert rows == {str(whole): 0, str(damaged): 1, str(date / DRIVE): 1}


def _fleet_with_a_cut_recording(tmp_path):
    """A folder of one good log and one that a power cut ended before its first chunk."""
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    good = _write_log(fleet / "a.mcap")
    cut = fleet / "b.mcap"
    cut.write_bytes(good.read_bytes()[:200])  # header and metadata: no complete chunk, no frame
    return fleet, good, cut


_CUT_LEFT_OUT = "left out {}: it holds no frames (an MCAP log cut off before its first complete chunk)"


def test_eval_of_a_folder_leaves_out_a_log_with_no_frames_and_says_so(tmp_path):
    # One such file in a fleet's folder made the evaluation of the whole folder fail.
    fleet, good, cut = _fleet_with_a_cut_recording(tmp_path)
    res = run_cli("eval", str(fleet), "--json", str(tmp_path / "e.json"), "--aggregators", "mean", "--quiet")
    assert res.returncode == 0, res.stderr
    assert res.stderr == f"sunrig: WARNING: eval: {_CUT_LEFT_OUT.format(cut)}\n"
    summary = json.loads((tmp_path / "e.json").read_text())
    assert summary["logs"] == [str(good)] and summary["logs_left_out"] == [str(cut)]
    assert summary["aggregators"]["mean"]["n_windows"] > 0
    # Named alone, or with only others like it, it is still an error: there is nothing to evaluate.
    res = run_cli("eval", str(cut), "--json", str(tmp_path / "e2.json"))
    assert res.returncode == 2 and res.stderr == (
        f"sunrig: error: {cut} holds no frames (an MCAP log cut off before its first complete chunk); record "
        "again or pass another log\n")
    shutil.copy(cut, tmp_path / "c.mcap")
    res = run_cli("eval", str(cut), str(tmp_path / "c.mcap"), "--json", str(tmp_path / "e2.json"))
    assert res.returncode == 2 and res.stderr.startswith("sunrig: error: none of the 2 logs holds frames ("), res.stderr
    assert len(res.stderr.splitlines()) == 1 and not (tmp_path / "e2.json").exists()


@pytest.mark.slow
@pytest.mark.torch
def test_train_of_a_folder_leaves_out_a_log_with_no_frames_and_its_fingerprint_too(tmp_path):
    from estimator.recipe import data_fingerprint
    from estimator.runtime import OnnxModel

    fleet, good, cut = _fleet_with_a_cut_recording(tmp_path)
    res = run_cli("train", str(fleet), "--out", str(tmp_path / "m"), "--preset", "tiny", "--batch", "1",
                  "--steps", "1", "--quiet")
    assert res.returncode == 0, res.stderr
    assert f"sunrig: WARNING: train: {_CUT_LEFT_OUT.format(cut)}\n" in res.stderr
    assert "INFO" not in res.stderr  # --quiet: warnings, not the run's progress ("loaded 1 drives ...")
    data = OnnxModel.load(tmp_path / "m").contract.training["data"]
    # The run's data are the logs it read: deleting the cut one later must not stop a resume.
    assert data["logs"] == 1 and data["fingerprint"] == data_fingerprint([good])


@pytest.mark.parametrize("command", ["eval", pytest.param("train", marks=pytest.mark.torch)])
def test_a_folder_without_logs_says_what_it_holds_and_what_to_do(tmp_path, capsys, command):
    # `sunrig train data/train recordings/` with recordings/ still empty said "not a KITTI raw
    # drive ... and not a native log", of a folder given as a folder of logs.
    from tests.test_kitti import DRIVE, make_drive

    out = ["--json", str(tmp_path / "e.json")] if command == "eval" else ["--out", str(tmp_path / "m")]

    def refused(folder):
        rc, captured = _main_in_process([command, str(DEMO_LOG), str(folder), *out, "--quiet"], capsys)
        assert rc == 2 and len(captured.err.splitlines()) == 1, captured.err
        assert not (tmp_path / "e.json").exists() and not (tmp_path / "m").exists()  # refused before any work
        return captured.err.removeprefix("sunrig: error: ").rstrip("\n")

    empty = tmp_path / "rec"
    empty.mkdir()
    assert refused(empty) == (f"{empty}: no .mcap logs in this folder (it is empty); record or copy logs into it, "
                              "or pass another folder")
    (empty / "notes.txt").write_text("to do")
    (empty / "clip.mp4").write_bytes(b"video")
    assert refused(empty) == (f"{empty}: no .mcap logs in this folder (only clip.mp4, notes.txt) and not a KITTI "
                              "drive; pass .mcap logs, folders of them, or KITTI drive folders")
    (empty / "notes.txt").unlink()
    (empty / "clip.mp4").unlink()
    # Logs one level down: subfolders are not searched, so name them.
    for day in ("day2", "day1"):
        shutil.copy(DEMO_LOG, (empty / day).mkdir() or empty / day / "a.mcap")
    assert refused(empty) == (f"{empty}: no .mcap logs in this folder, only in its 2 subfolders ({empty / 'day1'} "
                              "...); pass those folders")
    shutil.rmtree(empty / "day1")
    shutil.rmtree(empty / "day2")
    # A KITTI folder is still the reader's to judge: its message names what the drive lacks.
    date = make_drive(tmp_path / "kitti", 3)
    (date / "calib_cam_to_cam.txt").unlink()
    for folder in (date, date / DRIVE):
        rc, captured = _main_in_process([command, str(folder), *out, "--quiet"], capsys)
        assert rc == 2 and "no calib_cam_to_cam.txt in its date folder" in captured.err, captured.err


@pytest.mark.torch
def test_quantize_shows_the_backbones_runs_over_the_crops_as_well_as_the_reading(tmp_path, tiny_model_dir,
                                                                                 capsys, monkeypatch):
    # Its one progress line, "calibrating", counted the frames read; the backbone's runs over the
    # crops after it (20 s for the paper's architecture on 2 cores) passed without a word.
    import rig.cli

    bars: dict[str, list[int]] = {}

    class Seen(rig.cli.Progress):  # the real progress line, its counts kept to look at
        def update(self, done, extra=""):
            bars.setdefault(f"{self.label} /{self.total}", []).append(done)
            super().update(done, extra)

    monkeypatch.setattr(rig.cli, "Progress", Seen)
    log = _write_log(tmp_path / "drive.mcap")
    rc, captured = _main_in_process(["quantize", str(log), "--model", str(tiny_model_dir), "--out",
                                     str(tmp_path / "int8"), "--calibration-crops", "32"], capsys)
    assert rc == 0, captured.err
    assert set(bars) == {"quantize: reading frames /None", "quantize: running the backbone /32"}, bars
    assert bars["quantize: running the backbone /32"][-1] == 32


@pytest.mark.torch
def test_quantize_writes_an_int8_model_that_every_command_runs(tmp_path, tiny_model_dir, capsys):
    from estimator.runtime import OnnxModel

    log = _write_log(tmp_path / "drive.mcap")
    out = tmp_path / "int8"
    res = run_cli("quantize", str(log), "--model", str(tiny_model_dir), "--out", str(out), "--calibration-crops",
                  "32")  # in its own process: the contract records the process's command line
    assert res.returncode == 0, res.stderr
    assert f"quantize: int8 model written to {out}; measure it with `sunrig eval LOG... --model {out}`" in res.stderr
    record = OnnxModel.load(out).contract.training["quantization"]
    assert record["calibration_crops"] == 32 and record["calibration_logs"] == 1
    assert record["command"].startswith("sunrig ") and "--calibration-crops 32" in record["command"]
    rc, captured = _main_in_process(["replay", str(log), "--model", str(out), "--jsonl", "-"], capsys)
    assert rc == 0 and len(captured.out.splitlines()) == 11, captured.err  # frame 5 has no heading
    # Again into the same folder: refused, nothing replaced.
    before = (out / "backbone.onnx").read_bytes()
    rc, captured = _main_in_process(["quantize", str(log), "--model", str(tiny_model_dir), "--out", str(out)],
                                    capsys)
    _assert_one_line_error(rc, captured, names=f"{out} holds backbone.onnx already; pass a new folder as --out")
    assert (out / "backbone.onnx").read_bytes() == before


def test_replay_without_model_says_pass_model(tmp_path, monkeypatch):
    log = _write_log(tmp_path / "a.mcap")
    res = run_cli("replay", str(log), "--model", str(tmp_path / "no-such-model"))
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1
    assert "no-such-model" in res.stderr


def test_replay_with_a_broken_model_file(tmp_path):
    log = _write_log(tmp_path / "a.mcap")
    model = tmp_path / "model"
    model.mkdir()
    (model / "backbone.onnx").write_bytes(b"not onnx at all")
    (model / "aggregator.onnx").write_bytes(b"not onnx either")
    res = run_cli("replay", str(log), "--model", str(model))
    assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, res.stderr
    assert "backbone.onnx" in res.stderr


@pytest.mark.torch
@pytest.mark.parametrize("aggregator", ["transformer", "mean", "meanshift", "single"])
def test_replay_writes_one_json_object_per_estimate(tmp_path, tiny_model_dir, aggregator):
    log = _write_log(tmp_path / "a.mcap")
    out = tmp_path / "est.jsonl"
    res = run_cli("replay", str(log), "--model", str(tiny_model_dir), "--aggregator", aggregator,
                  "--jsonl", str(out))
    assert res.returncode == 0, res.stderr
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(rows) == 11  # 12 frames, one without heading
    assert "1 frames without heading skipped" in res.stderr
    required = {"t", "seq", "sun_enu", "azimuth_deg", "elevation_deg", "heading_deg", "heading_ref",
                "spread_deg", "n_frames", "truth_enu", "error_deg"}
    for row in rows:
        assert required <= set(row)
        assert row["aggregator"] == aggregator
        assert np.linalg.norm(row["sun_enu"]) == pytest.approx(1.0, abs=1e-6)
        assert 0.0 <= row["error_deg"] <= 180.0
        assert row["truth_enu"] == pytest.approx([0.6, 0.0, 0.8])
    assert [r["seq"] for r in rows] == [0, 1, 2, 3, 4, 6, 7, 8, 9, 10, 11, 12][: len(rows)]
    assert rows[0]["n_frames"] == 1 and max(r["n_frames"] for r in rows) > 1


def _model_computing_nan(src: Path, dst: Path) -> Path:
    """A copy of the model at ``src`` whose aggregator computes NaN: every float weight NaN, its
    checksums written anew, as a bad export or a run that diverged would leave it."""
    import hashlib

    onnx = pytest.importorskip("onnx")
    from onnx import numpy_helper

    from estimator.contract import AGGREGATOR_FILE, BACKBONE_FILE, CHECKSUMS_FILE, format_checksums

    dst.mkdir()
    shutil.copy(src / BACKBONE_FILE, dst / BACKBONE_FILE)
    graph = onnx.load(str(src / AGGREGATOR_FILE))
    for init in graph.graph.initializer:
        weights = numpy_helper.to_array(init)
        if weights.dtype == np.float32:
            init.CopyFrom(numpy_helper.from_array(np.full_like(weights, np.nan), init.name))
    onnx.save(graph, str(dst / AGGREGATOR_FILE))
    digests = {n: hashlib.sha256((dst / n).read_bytes()).hexdigest() for n in (BACKBONE_FILE, AGGREGATOR_FILE)}
    (dst / CHECKSUMS_FILE).write_text(format_checksums(digests))
    return dst


@pytest.mark.torch
@pytest.mark.parametrize("aggregator", ["transformer", "meanshift"])
def test_a_model_computing_nan_fails_replay_and_eval_and_the_live_rig_skips_its_windows(
    tmp_path, tiny_model_dir, aggregator
):
    # Each window is skipped with a warning that blames the model; a replay or an evaluation
    # that so made nothing fails, while the live rig goes on (it once ended on meanshift's NaN).
    log = _write_log(tmp_path / "a.mcap")
    model = _model_computing_nan(tiny_model_dir, tmp_path / "nan-model")
    res = run_cli("replay", str(log), "--model", str(model), "--aggregator", aggregator, "--jsonl", "-")
    assert res.returncode == 2 and res.stdout == "", res.stderr
    assert "not finite" in res.stderr or "has a direction" in res.stderr
    assert res.stderr.strip().splitlines()[-1].startswith(f"sunrig: error: {log}: every one of its 11 windows failed")
    res = run_cli("eval", str(log), "--model", str(model), "--json", str(tmp_path / "e.json"))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines()[-1].startswith("sunrig: error: eval graded nothing: 11 windows failed")
    res = run_cli("run", "--camera", f"file:{log}", "--heading", "log", "--model", str(model), "--aggregator",
                  aggregator, "--jsonl", str(tmp_path / "live.jsonl"))
    assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
    assert not (tmp_path / "live.jsonl").exists()  # made at the first estimate: there was none


@pytest.mark.torch
def test_replay_to_stdout(tmp_path, tiny_model_dir):
    log = _write_log(tmp_path / "a.mcap", n=3)
    res = run_cli("replay", str(log), "--model", str(tiny_model_dir), "--jsonl", "-", "--quiet")
    assert res.returncode == 0 and res.stderr == ""
    assert len(res.stdout.splitlines()) == 3


def test_bundled_demo_log_is_a_drive_with_truth():
    from replay.sources import open_frames

    frames = list(open_frames(DEMO_LOG))
    assert len(frames) == 40
    assert all(f.attitude is not None and f.sun_enu_truth is not None for f in frames)
    headings = np.unwrap([f.attitude.heading_rad for f in frames])
    assert np.ptp(headings) > 0.0  # the car moves: yaw is not constant


@pytest.mark.torch
def test_replay_defaults_to_the_bundled_log(tiny_model_dir):
    res = run_cli("replay", "--model", str(tiny_model_dir), "--jsonl", "-", "--quiet")
    assert res.returncode == 0, res.stderr
    assert len(res.stdout.splitlines()) == 40


@pytest.mark.torch
def test_demo_prints_valid_nmea_and_a_status(tiny_model_dir):
    import pynmea2

    res = run_cli("demo", "--model", str(tiny_model_dir), "--fast")
    assert res.returncode == 0, res.stderr
    lines = res.stdout.splitlines()
    assert lines and all(pynmea2.parse(line, check=True) for line in lines)
    assert "sunrig: done: frames 40" in res.stderr


@pytest.mark.torch
def test_demo_piped_into_head_ends_quietly(tiny_model_dir):
    # `sunrig demo | head -2`: once head has gone, the rig has no reader left and stops.
    proc = subprocess.Popen([sys.executable, "-m", "rig.cli", "demo", "--model", str(tiny_model_dir)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONWARNINGS="ignore"))
    lines = [proc.stdout.readline() for _ in range(2)]
    proc.stdout.close()
    _, err = proc.communicate(timeout=60)
    assert all(line.startswith("$PSRGS") for line in lines)
    assert proc.returncode == 0 and "Traceback" not in err and "failed to write" not in err, err
    frames = int(re.search(r"done: frames (\d+)", err).group(1))
    assert frames < 40, err  # it stopped before the end of the 4-s drive (paced at 10 Hz)


@pytest.mark.torch
def test_run_file_camera_to_loop_serial_jsonl_and_record(tmp_path, tiny_model_dir):
    from replay.native import read_estimates

    rec, out = tmp_path / "rec.mcap", tmp_path / "est.jsonl"
    res = run_cli("run", "--camera", f"file:{DEMO_LOG}", "--model", str(tiny_model_dir), "--serial", "loop://",
                  "--jsonl", str(out), "--record", str(rec))
    assert res.returncode == 0, res.stderr
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(list(read_estimates(rec))) == len(rows) >= 1, res.stderr
    # Paced at 10 Hz the live path keeps up with nearly every frame on an idle machine, but how
    # many it drops depends on the load; what must hold is that every frame is accounted for.
    done = re.search(r"frames (\d+) \(dropped (\d+), no heading (\d+), bad exposure (\d+), out of order (\d+), "
                     r"clock jumps (\d+)\) \| estimates (\d+) at .*skipped (\d+), failed (\d+)", res.stderr)
    assert done, res.stderr
    frames, dropped, no_heading, bad_exposure, late, jumps, estimates, skipped, failed = map(int, done.groups())
    assert frames == 40 and estimates == len(rows) and jumps == 0, res.stderr
    assert dropped + no_heading + bad_exposure + late + estimates + skipped + failed == frames, res.stderr


@pytest.mark.torch
@pytest.mark.parametrize("fmt", ["nmea", "binary"])
def test_replay_at_full_speed_reaches_a_serial_controller_whole(tmp_path, tiny_model_dir, fmt):
    """A replay has no deadline: its serial port waits for the writer instead of replacing an
    unsent estimate (newest wins is for the live rig), and the last one is sent at close. The
    controller gets what the JSONL holds, every one, in order, over a real pty."""
    from rig.protocol import BinaryFrameReader, NmeaLineReader
    from tests.test_publishers import MasterReader, Pty, wait_until

    pty, out = Pty(), tmp_path / "est.jsonl"
    reader = MasterReader(pty.master, NmeaLineReader() if fmt == "nmea" else BinaryFrameReader())
    try:
        res = run_cli("replay", "--model", str(tiny_model_dir), "--serial", pty.name, "--format", fmt,
                      "--jsonl", str(out))
        assert res.returncode == 0, res.stderr
        rows = [json.loads(line) for line in out.read_text().splitlines()]
        wait_until(lambda: len(reader.snapshot()) >= len(rows), "the controller to read every estimate")
    finally:
        reader.stop()
        pty.close()
    assert [m["seq"] for m in reader.snapshot()] == [r["seq"] for r in rows] and len(rows) >= 30
    assert "dropped" not in res.stderr, res.stderr


def signalled_after_three_estimates(args, jsonl, signum) -> tuple[int, str]:
    """Run `sunrig ARGS` (paced: the 4-s demo drive), send ``signum`` once its JSONL has three
    lines (about 3 s of the drive left), and return its exit code and stderr."""
    import signal
    import time

    def as_in_a_terminal() -> None:
        # A suite run under nohup (or by a runner that ignores SIGHUP) passes the ignored SIGHUP
        # on, and the rig rightly keeps it ignored: the rig under test gets the default.
        signal.signal(signal.SIGHUP, signal.SIG_DFL)
        signal.signal(signal.SIGINT, signal.SIG_DFL)

    proc = subprocess.Popen([sys.executable, "-m", "rig.cli", *args], preexec_fn=as_in_a_terminal,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60.0  # a guard, not a timing
        while time.monotonic() < deadline and proc.poll() is None:
            if jsonl.exists() and len(jsonl.read_text().splitlines()) >= 3:
                break
            time.sleep(0.02)
        proc.send_signal(signum)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    return proc.returncode, err


@pytest.mark.parametrize("signame", ["SIGTERM", "SIGHUP"])
def test_a_rig_stopped_by_its_service_manager_finishes_its_outputs(tmp_path, signame):
    # `systemctl stop` and `docker stop` send SIGTERM; a dropped ssh session sends SIGHUP. Either
    # used to end the rig at once, and the recording (whose chunks are buffered) was left empty.
    # Now they stop it as Ctrl-C does: exit 0, every estimate in the JSONL also in a finished log.
    import signal

    from replay.native import read_estimates

    rec, out = tmp_path / "rec.mcap", tmp_path / "est.jsonl"
    returncode, err = signalled_after_three_estimates(
        ["run", "--camera", f"file:{DEMO_LOG}", "--jsonl", str(out), "--record", str(rec)], out,
        getattr(signal, signame))
    assert returncode == 0 and "Traceback" not in err, err
    rows = out.read_text().splitlines()
    assert 3 <= len(rows) < 33, err  # stopped early, by the signal
    assert rec.read_bytes().endswith(b"\x89MCAP0\r\n"), "the log was not finished"
    assert len(list(read_estimates(rec))) == len(rows)
    assert "sunrig: done:" in err


def test_an_interrupted_replay_says_how_far_it_got(tmp_path):
    # Every line written stays written; the summary says the replay was cut short, and where.
    import signal

    out = tmp_path / "est.jsonl"
    returncode, err = signalled_after_three_estimates(["replay", "--realtime", "--jsonl", str(out)], out,
                                                      signal.SIGINT)
    lines = len(out.read_text().splitlines())
    assert returncode == 130 and "Traceback" not in err, err
    assert re.search(rf"interrupted after \d+ frames, {lines} estimates", err), err
    assert lines < 33, err


def test_stop_signals_end_any_command_as_ctrl_c_does_and_nohup_is_respected(monkeypatch):
    # A command that does not catch the interrupt exits 128 + the signal's number, as a shell
    # reports death by that signal; a signal ignored at start (`nohup` ignores SIGHUP) stays
    # ignored; and the handlers are put back after the command.
    import signal
    import time

    import rig.cli

    def interrupted_by(signum):
        def cmd(args):
            signal.raise_signal(signum)
            time.sleep(5.0)  # the interrupt lands here: not reached in full
            return 0
        return cmd

    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    monkeypatch.setattr(rig.cli, "cmd_sun", interrupted_by(signal.SIGTERM))
    assert rig.cli.main(["sun"]) == 128 + signal.SIGTERM
    assert {sig: signal.getsignal(sig) for sig in before} == before
    previous = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        monkeypatch.setattr(rig.cli, "cmd_sun", lambda args: signal.raise_signal(signal.SIGHUP) or 0)
        assert rig.cli.main(["sun"]) == 0
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, previous)


@pytest.mark.parametrize("signals", [2, 3])
def test_a_second_signal_lets_the_outputs_close_and_a_third_quits(monkeypatch, capfd, signals):
    # Users press Ctrl-C again: the second must not interrupt the closing of the outputs (a
    # recording would be left unfinished, the exit report lost). It is told to wait; a third quits
    # at once. (Signals within rig.stopping.BURST_S are one request, as GNU timeout's two are: here
    # they come microseconds apart, so the burst is switched off to make them a person's three.)
    import signal
    import time

    import rig.cli
    import rig.stopping

    monkeypatch.setattr(rig.stopping, "BURST_S", 0.0)

    closed = []

    def cmd(args):
        try:
            signal.raise_signal(signal.SIGINT)
            time.sleep(5.0)  # the first interrupt lands here
        finally:
            for _ in range(signals - 1):
                signal.raise_signal(signal.SIGINT)  # the next ones land while closing
            closed.append(True)
        return 0

    monkeypatch.setattr(rig.cli, "cmd_sun", cmd)
    assert rig.cli.main(["sun"]) == 130
    assert closed == ([True] if signals == 2 else [])
    assert "signal once more to quit at once" in capfd.readouterr().err  # written to fd 2 (rig/stopping.py)


@pytest.mark.skipif(not (os.path.exists("/dev/full") and os.access("/dev", os.W_OK)),
                    reason="needs /dev/full in a writable /dev (else --json is refused before the run)")
def test_a_full_disk_found_after_a_whole_evaluation_is_one_line():
    res = run_cli("eval", str(DEMO_LOG), "--quiet", "--json", "/dev/full")
    assert res.returncode == 2 and "Traceback" not in res.stderr, res.stderr
    assert res.stderr.strip().splitlines() == [
        "sunrig: error: No space left on device; free space on that disk, or write elsewhere"]


def test_an_output_the_machine_refuses_is_a_user_error_not_a_bug(monkeypatch, capsys):
    # A full disk or a path that turns out unwritable only when written (after a whole evaluation)
    # is the user's to fix: one line, exit 2, never "internal error" (which asks for a bug report).
    import errno

    import rig.cli

    def fails_with(exc):
        def cmd(args):
            raise exc
        return cmd

    denied = PermissionError(errno.EPERM, "Operation not permitted", "/sys/m")
    monkeypatch.setattr(rig.cli, "cmd_sun", fails_with(denied))
    assert rig.cli.main(["sun"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "sunrig: error: /sys/m: Operation not permitted; check the path is right and writable"]
    full = OSError(errno.ENOSPC, "No space left on device")  # a write's: no file name
    monkeypatch.setattr(rig.cli, "cmd_sun", fails_with(full))
    assert rig.cli.main(["sun"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "sunrig: error: No space left on device; free space on that disk, or write elsewhere"]
    monkeypatch.setattr(rig.cli, "cmd_sun", fails_with(OSError("a bug of ours, with no errno")))
    assert rig.cli.main(["sun"]) == 1
    # A file of sunrig's own that is missing is a broken install or a bug, whatever its errno.
    own = Path(rig.cli.__file__).parent / "no_such_table.json"
    monkeypatch.setattr(rig.cli, "cmd_sun", fails_with(FileNotFoundError(errno.ENOENT, "No such file", str(own))))
    assert rig.cli.main(["sun"]) == 1


def test_outputs_that_cannot_work_as_asked_are_refused_or_warned():
    # demo writes NMEA text on stdout when it has no port: binary there, or JSON lines mixed in,
    # would give a reader neither format. A rig with no output at all runs (bring-up), but says so.

    for args, said in ((["demo", "--fast", "--format", "binary"], "--format binary needs --serial PORT"),
                       (["demo", "--fast", "--jsonl", "-"], "--jsonl - would mix JSON lines")):
        res = run_cli(*args)
        assert res.returncode == 2 and res.stdout == "" and said in res.stderr, (args, res.stderr)
    res = run_cli("run", "--camera", f"file:{DEMO_LOG}", "--fast", "--quiet")
    assert res.returncode == 0 and "WARNING: no output: estimates are made and dropped" in res.stderr, res.stderr


def test_run_errors_are_one_line(tmp_path):
    for args in (["run", "--camera", "oak"], ["run"], ["run", "--camera", "file:/nope.mcap"],
                 ["run", "--camera", f"file:{tmp_path}", "--config", str(tmp_path / "missing.toml")]):
        res = run_cli(*args)
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, (args, res.stderr)
    # A ring too small for the shipped model's window: refused once the model is known, before
    # any output is made.
    (tmp_path / "small.toml").write_text("[rig]\nring_capacity = 4\n")
    out = tmp_path / "est.jsonl"
    res = run_cli("run", "--camera", f"file:{DEMO_LOG}", "--heading", "log", "--config", str(tmp_path / "small.toml"),
                  "--jsonl", str(out))
    assert res.returncode == 2 and res.stderr.startswith("sunrig: error: [rig] ring_capacity: 4 frames"), res.stderr
    assert len(res.stderr.strip().splitlines()) == 1 and not out.exists()


def test_gnss_stopped_while_its_output_opens_ends_with_the_summary(tmp_path, monkeypatch, capsys):
    # Ctrl-C while the JSONL output is being opened (a FIFO's open waits for its reader) left the
    # output None, and the summary's out.stats() turned the stop into an AttributeError (mypy found it).
    import drivers.gnss
    import rig.cli
    import rig.publishers
    from tests.test_gnss_nmea import nmea

    capture = tmp_path / "gnss.log"
    capture.write_bytes(nmea("GPHDT,33.0,T"))
    readers = []

    class Reader(drivers.gnss.GnssReader):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            readers.append(self)

    def interrupted_open(*args, **kwargs):
        assert readers[0].wait_finished(10.0)  # the capture read whole: the counts below are fixed
        raise KeyboardInterrupt

    monkeypatch.setattr(drivers.gnss, "GnssReader", Reader)
    monkeypatch.setattr(rig.publishers, "JsonlPublisher", interrupted_open)
    # A capture file cut short is an interrupted command, 128 + the signal, as replay of a log is
    # (it exited 0, as a live port's session does, saying nothing of the sentences left unread).
    assert rig.cli.main(["gnss", str(capture), "--jsonl", str(tmp_path / "out.jsonl")]) == 130
    said = capsys.readouterr().err
    assert "gnss: 0 updates from 1 sentences" in said and f"(stopped by Ctrl-C before the end of {capture})" in said
    assert not (tmp_path / "out.jsonl").exists()


def test_an_output_never_overwrites_the_input_it_reads(tmp_path):
    from tests.test_gnss_nmea import nmea

    log = tmp_path / "drive.mcap"
    shutil.copy(DEMO_LOG, log)
    before = log.read_bytes()
    capture = tmp_path / "gnss.log"
    capture.write_bytes(nmea("GPHDT,33.0,T"))
    nmea_before = capture.read_bytes()
    for args in (["replay", str(log), "--jsonl", str(log)],
                 ["record", "--camera", f"file:{log}", "--heading", "log", "--out", str(log), "--overwrite"],
                 ["run", "--camera", f"file:{log}", "--heading", "log", "--jsonl", str(log)],
                 ["eval", str(log), "--json", str(log)]):
        res = run_cli(*args)
        assert res.returncode == 2 and "is the input being read" in res.stderr, (args, res.stderr)
        assert log.read_bytes() == before, args
    res = run_cli("gnss", str(capture), "--jsonl", str(capture))  # a GNSS capture file
    assert res.returncode == 2 and "is the input being read" in res.stderr, res.stderr
    assert capture.read_bytes() == nmea_before
    # Two outputs on one path: the figure overwrote the JSON, and the run exited 0.
    out = tmp_path / "out.png"
    for args, flags in ((["eval", str(log), "--json", str(out), "--plot", str(out)], "--json and --plot"),
                        (["run", "--camera", f"file:{log}", "--heading", "log", "--jsonl", str(out),
                          "--record", str(tmp_path / "." / "out.png")], "--jsonl and --record")):
        res = run_cli(*args)
        assert res.returncode == 2 and f"{flags} are both" in res.stderr, (args, res.stderr)
        assert not out.exists(), args


def test_an_existing_recording_is_refused_in_the_words_of_the_command(tmp_path):
    # rig.recorder's own rules are tests/test_recorder.py; here: each command names its own way out.
    from replay.native import read_estimates
    from replay.sources import open_frames

    keep = tmp_path / "drive.mcap"
    keep.write_bytes(b"yesterday's drive")
    config = tmp_path / "rig.toml"
    config.write_text(f"[output]\nrecord = {str(keep)!r}\n")
    record = ["record", "--camera", f"file:{DEMO_LOG}", "--heading", "log", "--frames", "3"]
    run = ["run", "--camera", f"file:{DEMO_LOG}", "--fast"]
    for args, says in (([*record, "--out", str(keep)], "or --overwrite to replace it"),
                       ([*run, "--record", str(keep)], "or --record-overwrite to replace it"),
                       ([*run, "--config", str(config)], "set [output] record_overwrite = true"),
                       (["demo", "--fast", "--config", str(config)], "set [output] record_overwrite = true"),
                       # Refused before the camera opens: there is no OAK here, and that is not what it says.
                       (["run", "--camera", "oak", "--heading", "oak-imu", "--record", str(keep)],
                        "or --record-overwrite to replace it")):
        res = run_cli(*args)
        assert res.returncode == 2 and len(res.stderr.strip().splitlines()) == 1, (args, res.stderr)
        assert f"{keep} exists" in res.stderr and says in res.stderr, (args, res.stderr)
        assert keep.read_bytes() == b"yesterday's drive", args

    # A path under a file: it said "a folder that does not exist (.../drive.mcap)", which does exist.
    res = run_cli(*record, "--out", str(keep / "x.mcap"))
    assert res.returncode == 2 and res.stderr.strip() == (
        f"sunrig: error: --out {keep / 'x.mcap'} is in {keep}, which is a file, not a folder: pass another path")
    res = run_cli(*record, "--out", str(keep), "--overwrite", "--quiet")
    assert res.returncode == 0, res.stderr
    assert len(list(open_frames(keep))) == 3
    # {start} names the file, and the run says which.
    res = run_cli(*run, "--record", str(tmp_path / "rig-{start}.mcap"))
    assert res.returncode == 0, res.stderr
    (made,) = tmp_path.glob("rig-*.mcap")
    assert re.fullmatch(r"rig-\d{8}T\d{6}Z\.mcap", made.name) and f"recorded to {made}" in res.stderr
    assert len(list(read_estimates(made))) >= 1


def test_bad_numbers_fail_before_any_file_is_touched(tmp_path):
    keep = tmp_path / "keep.mcap"
    keep.write_bytes(b"a recording worth keeping")
    bad_rig = tmp_path / "rig.toml"
    bad_rig.write_text("[rig]\nqueue_size = 0\n")
    cases = (
        (["replay", "--seed", "-1"], "argument --seed"),
        (["synth", str(tmp_path / "s"), "--fps", "0"], "argument --fps"),
        (["synth", str(tmp_path / "s"), "--render-scale", "nan"], "argument --render-scale"),
        (["train", str(DEMO_LOG), "--out", str(tmp_path / "m"), "--minutes", "nan"], "argument --minutes"),
        (["train", str(DEMO_LOG), "--out", str(tmp_path / "m"), "--lr", "-1"], "argument --lr"),
        # --overwrite: even where replacing the recording is allowed, a bad number must not reach it.
        (["record", "--camera", f"file:{DEMO_LOG}", "--out", str(keep), "--overwrite", "--seconds", "inf"],
         "argument --seconds"),
        (["record", "--camera", f"file:{DEMO_LOG}", "--out", str(keep), "--overwrite", "--jpeg-quality", "101"],
         "argument --jpeg-quality"),
        (["run", "--camera", f"file:{DEMO_LOG}", "--config", str(bad_rig), "--record", str(keep),
          "--record-overwrite"], "[rig] queue_size"),
        (["eval", str(DEMO_LOG), "--plot", str(tmp_path / "curves.txt")], "--plot"),
        (["eval", str(DEMO_LOG), "--json", str(tmp_path / "no" / "such" / "folder" / "out.json")], "--json"),
        # 0 once meant "no limit" / "all cores" for these: a full 80-minute run the user did not ask for.
        (["train", str(DEMO_LOG), "--out", str(tmp_path / "m"), "--steps", "0"], "argument --steps"),
        (["train", str(DEMO_LOG), "--out", str(tmp_path / "m"), "--threads", "0"], "argument --threads"),
        (["train", str(DEMO_LOG), "--out", str(tmp_path / "m"), "--hard-share", "nan"], "argument --hard-share"),
        (["eval", str(DEMO_LOG), "--utc-offset", "nan"], "argument --utc-offset"),
        # Source options are checked even where the source does not use them (a config moved to
        # another rig keeps them), and before any device opens.
        (["run", "--camera", f"file:{DEMO_LOG}", "--max-gap-s", "nan"], "argument --max-gap-s"),
        (["run", "--camera", f"file:{DEMO_LOG}", "--max-age-s", "-1"], "argument --max-age-s"),
        (["run", "--camera", f"file:{DEMO_LOG}", "--heading-latency-s", "nan"], "argument --heading-latency-s"),
        (["run", "--camera", f"file:{DEMO_LOG}", "--hfov-deg", "nan"], "argument --hfov-deg"),
        (["run", "--camera", f"file:{DEMO_LOG}", "--width", "-1"], "argument --width"),
        (["record", "--camera", f"file:{DEMO_LOG}", "--out", str(keep), "--overwrite", "--declination-deg", "inf"],
         "argument --declination-deg"),
        # A 400-digit integer: math.isfinite() overflowed on it (a traceback from argparse), or it
        # reached an int64 timestamp or a C int as an internal error.
        (["record", "--camera", f"file:{DEMO_LOG}", "--out", str(keep), "--overwrite", "--width", "9" * 400],
         "argument --width"),
        (["synth", str(tmp_path / "s"), "--frames", "9" * 400], "argument --frames"),
        (["run", "--camera", f"file:{DEMO_LOG}", "--baud", "9" * 400], "argument --baud"),
        (["synth", str(tmp_path / "s"), "--fps", "1e-300"], "argument --fps"),
        # Frames 0 ns apart in int64 nanoseconds, written without a word.
        (["synth", str(tmp_path / "s"), "--fps", "1e12"], "argument --fps"),
        # A few zeros too many: 4 GB and a minute listing the drives' names before the first frame.
        (["synth", str(tmp_path / "s"), "--drives", "10000000"], "argument --drives"),
        # numpy was asked for 137 GiB of crops after the data had loaded
        (["train", str(DEMO_LOG), "--out", str(tmp_path / "m"), "--crops", "1000000"],
         "crops per frame: expected at most 256"),
    )
    for args, names in cases:
        res = run_cli(*args)
        assert res.returncode == 2 and "Traceback" not in res.stderr, (args, res.stderr)
        # One line: argparse's usage block before it (5-12 lines) buried it.
        (last,) = res.stderr.strip().splitlines()
        # The refusal is for the bad value, not a usage error of another kind (also exit 2).
        assert "error:" in last and names in last and "unrecognized" not in last, (args, res.stderr)
        assert keep.read_bytes() == b"a recording worth keeping", args
    assert not (tmp_path / "m").exists() and not (tmp_path / "s").exists()


# Every path a command takes, given as "" (an unset shell variable: --out "$OUT"): it wrote into the
# current folder (quantize --out, synth), dropped the output without a word (eval --plot, run
# --record), or read the folder as the input (gnss).
_EMPTY_PATHS = {
    "replay LOG": ("replay '' --quiet", "log"),
    "replay --jsonl": ("replay --jsonl ''", "--jsonl"),
    "replay --model": ("replay --model ''", "--model"),
    "replay --serial": ("replay --serial ''", "--serial"),
    "run --calibration": ("run --camera opencv:99 --calibration ''", "--calibration"),
    "run --config": ("run --camera file:{demo} --config ''", "--config"),
    "run --record": ("run --camera file:{demo} --fast --record ''", "--record"),
    "run --jsonl": ("run --camera file:{demo} --fast --jsonl ''", "--jsonl"),
    "record --out": ("record --camera file:{demo} --frames 2 --out ''", "--out"),
    "demo --model": ("demo --fast --model ''", "--model"),
    "config --config": ("config --print --config ''", "--config"),
    "eval LOG": ("eval {demo} '' --quiet", "logs"),
    "eval --json": ("eval {demo} --quiet --json ''", "--json"),
    "eval --plot": ("eval {demo} --quiet --plot ''", "--plot"),
    "quantize --out": ("quantize {demo} --calibration-crops 16 --quiet --out ''", "--out"),
    "train --out": ("train {demo} --preset tiny --steps 1 --quiet --out ''", "--out"),
    "train --init": ("train {demo} --preset tiny --steps 1 --quiet --out {tmp}/m --init ''", "--init"),
    "train --export-only": ("train --out {tmp}/m --export-only ''", "--export-only"),
    "synth OUT": ("synth '' --drives 1 --frames 2", "out"),
    "sun --csv": ("sun --csv ''", "--csv"),
    "gnss SOURCE": ("gnss ''", "PORT_OR_FILE"),
    "gnss --jsonl": ("gnss {demo} --jsonl ''", "--jsonl"),
}


@pytest.mark.parametrize("slot", [pytest.param(s, marks=[pytest.mark.torch] if s.startswith(("train", "quantize"))
                                               else []) for s in _EMPTY_PATHS])
def test_an_empty_path_is_a_usage_error_naming_its_option(tmp_path, capsys, monkeypatch, slot):
    line, option = _EMPTY_PATHS[slot]
    work = tmp_path / "cwd"
    work.mkdir()
    monkeypatch.chdir(work)
    argv = [arg if arg != "''" else "" for arg in _command(line, tmp=tmp_path)]
    rc, captured = _main_in_process(argv, capsys)
    assert rc == 2 and captured.out == "", captured.err
    (said,) = captured.err.strip().splitlines()
    assert said.startswith(f"sunrig {argv[0]}: error: argument {option}: expected a path, got an empty string"), said
    assert os.listdir(work) == [] and not (tmp_path / "m").exists()


def test_debug_is_taken_after_the_subcommand_too(tmp_path):
    # As the errors' advice ("rerun with --debug") is most often followed: at the end of the line.
    res = run_cli("replay", str(tmp_path / "missing.mcap"), "--debug")
    assert res.returncode != 0 and "Traceback" in res.stderr and "unrecognized" not in res.stderr


@pytest.mark.torch
def test_an_output_that_writes_nothing_fails_the_run_and_says_so(tiny_model_dir):
    res = run_cli("run", "--camera", f"file:{DEMO_LOG}", "--heading", "log", "--model", str(tiny_model_dir),
                  "--jsonl", "/dev/full", "--serial", "loop://", "--fast")
    assert res.returncode == 2, res.stderr
    assert re.search(r"JsonlPublisher: \d+ estimates failed to write, 0 written .*No space left", res.stderr)
    # The serial output went on: the failing JSONL file did not stop the rig.
    assert re.search(r"estimates [1-9]\d* at", res.stderr), res.stderr


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_a_full_disk_under_replay_jsonl_is_said_once():
    # The failed write says it; closing the file fails again on the same buffered line, and
    # saying that too (as a warning before the error) told the user twice.
    res = run_cli("replay", "--jsonl", "/dev/full")
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        "sunrig: error: cannot write JSONL to /dev/full: No space left on device; free space or pass another --jsonl"]


def test_config_print_merges_file_and_flags(tmp_path):
    cfg = tmp_path / "rig.toml"
    cfg.write_text('[output]\nbaud = 9600\n[window]\nspan_s = 6.0\n')
    res = run_cli("config", "--print", "--config", str(cfg))
    assert res.returncode == 0
    assert "baud = 9600" in res.stdout and "span_s = 6.0" in res.stdout and "[rig]" in res.stdout


def test_config_print_refuses_a_camera_and_heading_that_do_not_go_together(tmp_path, capsys):
    # A service's config with a live camera and the default heading (a log's): `config --print`
    # passed it, and boot refused it.
    cfg = tmp_path / "rig.toml"
    cfg.write_text('[source]\ncamera = "opencv:0"\nhfov_deg = 70.0\n')
    rc, captured = _main_in_process(["config", "--print", "--config", str(cfg)], capsys)
    assert rc == 2 and captured.out == ""
    assert captured.err.strip().splitlines() == [
        f"sunrig: error: {cfg}: [source] camera opencv:0 with heading log: --heading log is a log's recorded "
        "heading: --camera opencv:0 has none; pass --heading nmea:PORT, visual or none (or set [source] heading "
        "in --config)"]
    cfg.write_text('[source]\ncamera = "opencv:0"\nhfov_deg = 70.0\nheading = "visual"\n')
    rc, captured = _main_in_process(["config", "--print", "--config", str(cfg)], capsys)
    assert rc == 0 and 'heading = "visual"' in captured.out, captured.err


@pytest.mark.torch
@pytest.mark.slow
def test_train_init_errors_are_one_line_before_any_data_loads(tmp_path):
    from estimator.models import DEFAULT_MODEL_DIR

    a_file = tmp_path / "notes.txt"
    a_file.write_text("not a model")
    # The shipped model with its weights damaged (they are not in SHA256SUMS: the runtime never
    # reads them): a zlib error from deep in training, after the data had loaded.
    damaged = tmp_path / "damaged"
    shutil.copytree(DEFAULT_MODEL_DIR, damaged)
    weights = bytearray((damaged / "weights.npz").read_bytes())
    weights[len(weights) // 2: len(weights) // 2 + 64] = bytes(64)
    (damaged / "weights.npz").write_bytes(bytes(weights))
    for init, preset, needle in ((tmp_path, "tiny", "no weights.npz"),
                                 (tmp_path / "gone", "tiny", "gone does not exist"),
                                 (a_file, "tiny", "notes.txt is a file, not a model folder"),
                                 (damaged, "fast", "damaged/weights.npz cannot be loaded"),
                                 ("shipped", "tiny", "; pass --preset fast")):  # the shipped model's preset, by name
        # The word `shipped` is the installed model, the fast preset: --init it into a tiny run is
        # refused by name (so the word reached that model, not a folder of that name).
        args = ["train", str(DEMO_LOG), "--out", str(tmp_path / "m"), "--preset", preset, "--steps", "1", "--quiet"]
        res = run_cli(*args, "--init", str(init))
        assert res.returncode == 2, res.stderr
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and needle in lines[0] and "Traceback" not in res.stderr
    assert not (tmp_path / "m" / "checkpoint.pt").exists()


@pytest.mark.torch
def test_train_init_shipped_beside_a_folder_of_that_name_is_refused_not_guessed(tmp_path):
    (tmp_path / "shipped").mkdir()
    res = subprocess.run([sys.executable, "-m", "rig.cli", "train", str(DEMO_LOG), "--out", "m", "--init", "shipped",
                          "--steps", "1", "--quiet"], capture_output=True, text=True, timeout=120, cwd=tmp_path,
                         env=dict(os.environ, PYTHONWARNINGS="ignore"))
    lines = res.stderr.strip().splitlines()
    assert res.returncode == 2 and len(lines) == 1 and "write ./shipped" in lines[0], res.stderr
    assert not (tmp_path / "m").exists()


@pytest.mark.slow
def test_train_crops_per_frame_goes_into_the_contract_and_a_resume_must_keep_it(tmp_path):
    from estimator.runtime import OnnxModel

    args = ["train", str(DEMO_LOG), "--out", str(tmp_path / "m"), "--preset", "tiny", "--batch", "1", "--quiet"]
    res = run_cli(*args, "--steps", "1", "--crops", "6")
    assert res.returncode == 0, res.stderr
    assert OnnxModel.load(tmp_path / "m").contract.crops_per_frame == 6
    res = run_cli(*args, "--steps", "2", "--crops", "4")
    assert res.returncode == 2 and "--crops 6, not 4" in res.stderr and "Traceback" not in res.stderr
    res = run_cli(*args, "--steps", "2")  # no --crops: the resume keeps its run's 6
    assert res.returncode == 0, res.stderr
    assert OnnxModel.load(tmp_path / "m").contract.training["steps"] == 2
    res = run_cli(*args[:3], str(tmp_path / "other"), *args[4:], "--steps", "1", "--crops", "0")
    assert res.returncode == 2 and "--crops: expected a positive integer" in res.stderr
    assert "Traceback" not in res.stderr and not (tmp_path / "other").exists()


@pytest.mark.slow
def test_train_says_when_it_resumes_a_run_and_when_there_is_nothing_left_to_train(tmp_path):
    args = ["train", str(DEMO_LOG), "--out", str(tmp_path / "m"), "--preset", "tiny", "--batch", "1"]
    res = run_cli(*args, "--steps", "1")
    assert res.returncode == 0 and "resuming" not in res.stderr, res.stderr
    res = run_cli(*args, "--steps", "2")
    assert res.returncode == 0 and f"resuming the run in {tmp_path / 'm'} at step 1" in res.stderr, res.stderr
    res = run_cli(*args, "--steps", "2")
    assert res.returncode == 0, res.stderr
    assert "already reached its end; nothing to train (pass a larger --steps" in res.stderr


@pytest.mark.slow
def test_export_only_sets_the_run_time_crops_and_keeps_the_recipe(tmp_path):
    from estimator.runtime import OnnxModel

    out = tmp_path / "m"
    res = run_cli("train", str(DEMO_LOG), "--out", str(out), "--preset", "tiny", "--batch", "1", "--steps", "1",
                  "--quiet")
    assert res.returncode == 0, res.stderr
    res = run_cli("train", "--out", str(out), "--export-only", str(tmp_path / "e8"), "--crops", "8", "--quiet")
    assert res.returncode == 0, res.stderr
    trained, exported = OnnxModel.load(out), OnnxModel.load(tmp_path / "e8")
    assert (trained.contract.crops_per_frame, exported.contract.crops_per_frame) == (4, 8)
    assert exported.contract.training["recipe"]["crops_per_frame"] == 4
    assert "--crops 8" in exported.contract.training["export_command"]
    crops = np.random.default_rng(0).integers(0, 256, (2, 32, 32, 3), dtype=np.uint8)
    np.testing.assert_array_equal(exported.embed(crops), trained.embed(crops))
    # The run had no --data-note: the export can name its data, given the run's logs to check.
    note = "the bundled demo drive, seed 7"
    res = run_cli("train", "--out", str(out), "--export-only", str(tmp_path / "n"), "--data-note", note, "--quiet")
    assert res.returncode == 2 and "needs the run's training logs" in res.stderr and "Traceback" not in res.stderr
    res = run_cli("train", str(DEMO_LOG), "--out", str(out), "--export-only", str(tmp_path / "n"),
                  "--data-note", note, "--quiet")
    assert res.returncode == 0, res.stderr
    named = OnnxModel.load(tmp_path / "n").contract.training
    assert named["data"]["source"] == note
    # Recorded as a shell takes it again: the note is one argument.
    assert shlex.split(named["export_command"])[-2:] == [note, "--quiet"]


@pytest.mark.slow
def test_export_only_sets_whether_the_model_runs_mirrored_and_a_fine_tune_keeps_it(tmp_path):
    from estimator.runtime import OnnxModel

    out = tmp_path / "m"
    args = ["train", str(DEMO_LOG), "--preset", "tiny", "--batch", "1", "--steps", "1", "--quiet"]
    res = run_cli(*args, "--out", str(out), "--mirror-windows")
    assert res.returncode == 2 and "pass it with --export-only" in res.stderr and "Traceback" not in res.stderr
    assert run_cli(*args, "--out", str(out)).returncode == 0
    assert OnnxModel.load(out).contract.mirror_windows is False  # not unless asked
    res = run_cli("train", "--out", str(out), "--export-only", str(tmp_path / "mirrored"), "--mirror-windows",
                  "--quiet")
    assert res.returncode == 0, res.stderr
    mirrored = OnnxModel.load(tmp_path / "mirrored").contract
    assert mirrored.mirror_windows is True and "--mirror-windows" in mirrored.training["export_command"]
    # A fine-tune runs as its start ran, unless its export says otherwise.
    res = run_cli(*args, "--out", str(tmp_path / "ft"), "--init", str(tmp_path / "mirrored"))
    assert res.returncode == 0, res.stderr
    assert OnnxModel.load(tmp_path / "ft").contract.mirror_windows is True
    res = run_cli("train", "--out", str(tmp_path / "ft"), "--export-only", str(tmp_path / "plain"),
                  "--no-mirror-windows", "--quiet")
    assert res.returncode == 0, res.stderr
    assert OnnxModel.load(tmp_path / "plain").contract.mirror_windows is False


def test_every_option_of_every_command_says_what_it_does():
    # `sunrig CMD --help` is the reference a rig user has at hand: no option without a line.
    import argparse

    from rig.cli import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction)).choices
    silent = [f"{name} {a.option_strings[0] if a.option_strings else a.dest}"
              for name, sub in commands.items() for a in sub._actions
              if not a.help and not isinstance(a, argparse._HelpAction)]
    assert silent == []


def test_the_source_summary_says_why_frames_had_no_heading():
    # `run` printed only "no heading 52": a heading port sending bad checksums looked like a silent one.
    from rig.cli import _source_summary

    stats = {"camera": {"dropped": 0}, "pairing": {"before": 53, "gap": 0},
             "gnss": {"sentences": 0, "bad_checksum": 57, "garbage_bytes": 0, "reopens": 1, "port": "/dev/ttyUSB0"}}
    assert _source_summary(stats) == "heading before 53, heading port bad checksum 57, heading port reopens 1"
    # A compass's glitched samples, left out by the pairing (drivers/pairing.py), were not said at all.
    stats["pairing"]["glitch"] = 2
    assert _source_summary(stats).startswith("heading before 53, heading samples left out as glitches 2, ")
    assert _source_summary({"log": {"frames_read": 40}}) == ""


def test_gnss_on_sentences_that_all_fail_their_checksum_says_so(tmp_path, capsys):
    # It said "no NMEA sentence ... check it is the GNSS device or a capture", of a capture whose
    # sentences were there, only damaged.
    from rig.cli import main

    capture = tmp_path / "noisy.nmea"
    capture.write_bytes(b"$GPHDT,33.0,T*00\r\n$GPHDT,34.0,T*00\r\n")
    assert main(["gnss", str(capture), "--jsonl", str(tmp_path / "out.jsonl"), "--quiet"]) == 2
    assert capsys.readouterr().err.strip() == (
        f"sunrig: error: gnss: every sentence from {capture} failed its checksum (2); "
        "check the wiring and the --baud rate, or the capture's integrity")


# --- every input and output of every command, against the same bad files -------------------------
# Each bad-input fix above was found by probing one command. These tables put every path a
# command reads or writes through the same bad files, so that a new command or option that forgets
# a case fails here rather than on a vehicle. In-process (main()), so the table costs seconds.

_BAD_FILES = {
    "empty": b"",
    "random": np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes(),
    "latin1": "caf\xe9 = 1\n".encode("latin-1"),
    "text": b"hello world\n",
}
# Each slot is a command line, split on spaces before its placeholders are filled in (so a path
# with a space stays one argument): {bad} the bad file, {out} an output, {demo} the bundled log.
_INPUT_SLOTS = {
    "replay LOG": "replay {bad} --jsonl {out}",
    "replay --model": "replay --model {bad} --jsonl {out}",
    "eval LOG": "eval {bad} --quiet --json {out}",
    "eval --model": "eval {demo} --model {bad} --quiet --json {out}",
    "run --camera file:": "run --heading log --camera file:{bad} --jsonl {out}",
    "run --model": "run --heading log --camera file:{demo} --model {bad} --jsonl {out}",
    "run --config": "run --heading log --camera file:{demo} --config {bad} --jsonl {out}",
    "run --calibration": "run --heading none --camera opencv:99 --calibration {bad} --jsonl {out}",
    "record --config": "record --config {bad} --out {out}.mcap",
    "demo --model": "demo --fast --model {bad}",
    "demo --config": "demo --fast --config {bad}",
    "config --config": "config --print --config {bad}",
    "sun --csv": "sun --csv {bad}",
    "gnss SOURCE": "gnss {bad} --jsonl {out}",
    "train LOG": "train {bad} --out {out} --steps 1",
    "train --init": "train {demo} --init {bad} --out {out} --steps 1",
    "quantize LOG": "quantize {bad} --out {out} --quiet",
    "quantize --model": "quantize {demo} --model {bad} --out {out} --quiet",
}
_TORCH_SLOTS = {"train LOG", "train --init", "quantize LOG", "quantize --model"}


def _command(line, **values):
    """``line`` split on spaces, then each ``{name}`` in it filled in from ``values`` ({demo}: the bundled log)."""
    values = {"{" + k + "}": str(v) for k, v in {"demo": DEMO_LOG, **values}.items()}
    args = []
    for arg in line.split():
        for key, value in values.items():
            arg = arg.replace(key, value)
        args.append(arg)
    return args


def _main_in_process(argv, capsys):
    from rig.cli import main

    try:
        rc = main(argv)
    except SystemExit as exc:  # argparse
        rc = exc.code
    return rc, capsys.readouterr()


def test_a_stop_while_the_pipeline_is_built_closes_the_outputs_and_keeps_no_empty_recording(
    tmp_path, monkeypatch, capsys
):
    # The outputs were open and the pipeline not yet running: a SIGTERM there skipped the close,
    # and left a 0-byte recording that every later replay of its folder refused.
    import rig.pipeline

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt  # what the stop handler raises on a first signal (rig/stopping.py)

    monkeypatch.setattr(rig.pipeline.RigPipeline, "__init__", stopped)
    rec, jsonl = tmp_path / "rec.mcap", tmp_path / "est.jsonl"
    rc, captured = _main_in_process(["run", "--camera", f"file:{DEMO_LOG}", "--heading", "log", "--record", str(rec),
                                     "--record-frames", "--jsonl", str(jsonl)], capsys)
    assert rc == 130 and not rec.exists() and not jsonl.exists()  # (made at the first estimate)
    assert f"nothing was recorded, so {rec} is not kept" in captured.err


def test_eval_on_a_full_disk_leaves_no_empty_json(tmp_path, monkeypatch, capsys):
    # The JSON was written in place: a full disk left it empty (0 bytes), results lost, beside a
    # one-line error. Written whole or not at all, the error names the file and nothing is left.
    import errno

    def disk_full(self, text, encoding=None):
        with open(self, "w", encoding=encoding) as f:
            f.write(text[:10])
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Path, "write_text", disk_full)
    out = tmp_path / "eval.json"
    rc, captured = _main_in_process(["eval", str(DEMO_LOG), "--aggregators", "mean", "--quiet", "--json", str(out)],
                                    capsys)
    assert rc == 2 and captured.err.startswith(f"sunrig: error: {out}: No space left on device"), captured.err
    assert list(tmp_path.iterdir()) == []


def _assert_one_line_error(rc, captured, *, names):
    assert rc == 2, captured.err
    assert "Traceback" not in captured.err and "internal error" not in captured.err, captured.err
    last = captured.err.strip().splitlines()[-1]
    assert last.startswith("sunrig: error: ") and names in last, captured.err


@pytest.mark.parametrize(("slot", "kind"), [
    pytest.param(slot, kind, marks=[pytest.mark.torch] if slot in _TORCH_SLOTS else [])
    for slot in _INPUT_SLOTS for kind in (*_BAD_FILES, "folder", "missing")
    if not (kind == "empty" and slot.endswith("--config"))  # an empty TOML file is the defaults: valid
])
def test_every_input_of_every_command_refuses_a_bad_file_in_one_line(tmp_path, capsys, slot, kind):
    bad = tmp_path / f"bad-{kind}"
    if kind == "folder":
        bad.mkdir()
    elif kind in _BAD_FILES:
        bad.write_bytes(_BAD_FILES[kind])
    (tmp_path / "out").mkdir()
    out = str(tmp_path / "out" / "result")
    argv = _command(_INPUT_SLOTS[slot], bad=bad, out=out)
    rc, captured = _main_in_process(argv, capsys)
    _assert_one_line_error(rc, captured, names=bad.name)
    # A stream's output (gnss) too: made at its first line, not when opened.
    assert not os.listdir(tmp_path / "out"), "an output was left by a command that failed"


@pytest.mark.parametrize("special", ["/dev/zero", "fifo"])
@pytest.mark.parametrize("command", ["run", "record"])
def test_a_calibration_that_is_a_device_or_fifo_is_said_to_be_one(tmp_path, capsys, command, special):
    # "calibration file /dev/zero does not exist": it does, it is only not a file to read.
    if special == "fifo":
        special = tmp_path / "cam.fifo"
        os.mkfifo(special)  # never opened: a FIFO's open would wait for a writer
    elif not os.path.exists(special):
        pytest.skip(f"needs {special}")
    argv = [command, "--camera", "opencv:99", "--heading", "none", "--calibration", str(special)]
    out = ["--out", str(tmp_path / "d.mcap")] if command == "record" else ["--jsonl", str(tmp_path / "e.jsonl")]
    rc, captured = _main_in_process([*argv, *out], capsys)
    _assert_one_line_error(rc, captured, names=f"calibration file {special} is not a regular file (a FIFO or "
                                               "device); save the calibration to a file and pass that")
    assert "does not exist" not in captured.err and sorted(os.listdir(tmp_path)) == (
        ["cam.fifo"] if isinstance(special, Path) else [])


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="needs /dev/zero")
def test_sun_csv_of_a_file_that_never_ends_a_line_is_one_line():
    # csv read /dev/zero's one endless line until the machine ran out of memory (here: the 2 GiB
    # limit, an internal MemoryError); a row is a line, and none is a MiB long.
    import resource

    def limit_memory():
        resource.setrlimit(resource.RLIMIT_AS, (2 << 30, 2 << 30))

    res = subprocess.run([sys.executable, "-m", "rig.cli", "sun", "--csv", "/dev/zero"], capture_output=True,
                         text=True, timeout=120, preexec_fn=limit_memory, env=dict(os.environ, OMP_NUM_THREADS="1",
                                                                                  OPENBLAS_NUM_THREADS="1"))
    assert res.returncode == 2 and res.stdout == "", res.stderr
    assert res.stderr.strip().splitlines() == [
        "sunrig: error: /dev/zero line 1: over 1 MiB without a line end, which no row time,lat,lon is; pass a CSV "
        "file of rows time,lat,lon with a header"]


def test_eval_refuses_a_json_it_cannot_make_before_the_evaluation_and_names_it(tmp_path, capsys, monkeypatch):
    # os.access says yes to root for any folder (/proc too), so --json /proc/x.json passed the check,
    # the evaluation ran for minutes, and the write failed naming the hidden /proc/.x.tmp.json.
    import estimator.evaluate
    from rig.files import write_replacing

    def evaluated(*args, **kwargs):
        raise AssertionError("evaluated before the output was checked")

    monkeypatch.setattr(estimator.evaluate, "evaluate", evaluated)
    ro = tmp_path / "ro"
    ro.mkdir()

    def refuses(path, *args, **kwargs):  # a folder that refuses files, whoever asks (/proc, a read-only mount)
        if Path(path).parent == ro:
            raise OSError(30, "Read-only file system", str(path))
        return real_open(path, *args, **kwargs)

    real_open = os.open
    with monkeypatch.context() as m:
        m.setattr(os, "open", refuses)
        for flag, name in (("--json", "x.json"), ("--plot", "x.png")):
            rc, captured = _main_in_process(["eval", str(DEMO_LOG), "--quiet", flag, str(ro / name)], capsys)
            _assert_one_line_error(rc, captured, names=f"{flag} {ro / name}: cannot write there (Read-only file "
                                                       "system); check the folder exists and is writable")
            assert ".tmp" not in captured.err and os.listdir(ro) == []
    # A write that fails all the same (the folder changed meanwhile) names the user's path, not the hidden one.
    with pytest.raises(OSError) as failed:
        write_replacing(ro / "x.json", lambda tmp: refuses(tmp, os.O_WRONLY | os.O_CREAT))
    assert failed.value.filename == str(ro / "x.json") and os.listdir(ro) == []
    if Path("/proc").is_dir():  # the real one, as the reviewer met it
        rc, captured = _main_in_process(["eval", str(DEMO_LOG), "--quiet", "--json", "/proc/x.json"], capsys)
        _assert_one_line_error(rc, captured, names="--json /proc/x.json: cannot write there")


_OUTPUT_SLOTS = {
    "replay --jsonl": "replay --jsonl {target}",
    "run --jsonl": "run --heading log --camera file:{demo} --fast --jsonl {target}",
    "run --record": "run --heading log --camera file:{demo} --fast --record {target}.mcap",
    "record --out": "record --heading log --camera file:{demo} --out {target}.mcap",
    "eval --json": "eval {demo} --aggregators mean --quiet --json {target}",
    "eval --plot": "eval {demo} --aggregators mean --quiet --plot {target}.png",
    "gnss --jsonl": "gnss {nmea} --jsonl {target}",
    "synth OUT": "synth {target} --drives 1 --frames 2",
    "train --out": "train {demo} --steps 1 --out {target}",
    "quantize --out": "quantize {demo} --calibration-crops 16 --quiet --out {target}",
}


@pytest.mark.parametrize("slot", [pytest.param(s, marks=[pytest.mark.torch] if s.startswith(("train", "quantize"))
                                               else [])
                                  for s in _OUTPUT_SLOTS])
def test_every_output_of_every_command_under_a_file_is_refused_in_one_line(tmp_path, capsys, slot):
    nmea = tmp_path / "capture.nmea"  # a GNSS heading, as gnss reads it
    body = b"GPHDT,123.4,T"
    nmea.write_bytes(b"$%s*%02X\r\n" % (body, functools.reduce(operator.xor, body)) * 3)
    (tmp_path / "a-file").write_text("not a folder\n")
    target = str(tmp_path / "a-file" / "result")
    argv = _command(_OUTPUT_SLOTS[slot], target=target, nmea=nmea)
    rc, captured = _main_in_process(argv, capsys)
    _assert_one_line_error(rc, captured, names="a-file")
    assert (tmp_path / "a-file").read_text() == "not a folder\n"


class _SilentCamera:
    """FAKE: a camera that sends no frame (a dead cable), since no real device can do that here."""

    def __iter__(self):
        return iter(())

    def stop(self):
        pass


@pytest.fixture
def silent_camera(monkeypatch):
    """Every --camera opens as a _SilentCamera (with the heading asked for)."""
    import rig.cli
    from drivers.sources import LiveSource, parse_camera, parse_heading

    monkeypatch.setattr(rig.cli, "_open_camera", lambda spec, heading, options=None: LiveSource(
        parse_camera(spec), parse_heading(heading), _SilentCamera(), {"camera": _SilentCamera()}))


@pytest.mark.parametrize("stopped", [False, True])
def test_a_recording_that_got_no_frame_is_not_kept(tmp_path, capsys, monkeypatch, silent_camera, stopped):
    # It was kept as a whole, empty log, which then failed every replay, eval or train of its folder.
    if stopped:  # as a service manager's SIGTERM before the first frame would
        import rig.stopping

        monkeypatch.setattr(rig.stopping.StopSignals, "requested", property(lambda self: True))
    out = tmp_path / "drive.mcap"
    rc, captured = _main_in_process(["record", "--camera", "opencv:0", "--hfov-deg", "60", "--heading", "none",
                                     "--out", str(out)], capsys)
    assert not out.exists() and os.listdir(tmp_path) == []
    last = captured.err.strip().splitlines()[-1]
    assert "record: no frame came in " in last and f"so {out} is not kept" in last
    if stopped:
        assert rc == 0 and last.endswith(")")
    else:
        assert rc == 2 and last.startswith("sunrig: error: ") and last.endswith("check the camera and its cable "
                                                                                "(docs/drivers.md)")


@pytest.mark.parametrize("command", ["record", "run"])
def test_a_recording_through_a_link_that_got_nothing_names_the_file_it_removes(tmp_path, capsys, silent_camera,
                                                                                command):
    # With --overwrite a link is written through. The file it points to is the one removed, and the
    # message named the link, which is kept.
    (tmp_path / "drives").mkdir()
    target = tmp_path / "drives" / "drive.mcap"
    link = tmp_path / "latest.mcap"
    os.symlink(target, link)
    out = (["--out", str(link), "--overwrite"] if command == "record" else
           ["--record", str(link), "--record-overwrite", "--quiet"])
    rc, captured = _main_in_process([command, "--camera", "opencv:0", "--hfov-deg", "60", "--heading", "none", *out],
                                    capsys)
    assert not target.exists() and link.is_symlink(), captured.err
    assert f"so {target} (where {link} points) is not kept" in captured.err, captured.err


def test_a_recording_whose_camera_fails_on_its_first_frame_is_not_kept(tmp_path, capsys):
    # A calibration made at another resolution is found on the first frame: the log was kept empty,
    # and the corrected command was then refused because --out existed.
    import cv2

    from tests.test_opencv_camera import StallingMjpegServer, clip_image, write_calibration

    clip = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for k in range(5):
        writer.write(clip_image(k))
    writer.release()
    write_calibration(tmp_path / "cam.yaml", np.array([[100.0, 0, 64], [0, 100.0, 36], [0, 0, 1]]), 128, 72)
    out = tmp_path / "drive.mcap"
    argv = ["record", "--camera", f"opencv:{clip}", "--heading", "none", "--out", str(out)]
    rc, captured = _main_in_process([*argv, "--calibration", str(tmp_path / "cam.yaml")], capsys)
    assert rc == 2 and not out.exists()
    # A video file's first frame is read as the camera opens (5c37fa3): refused before the
    # recording is made, in one line.
    (said,) = captured.err.strip().splitlines()
    assert said.startswith("sunrig: error: ") and "calibrat" in said
    # A live stream's first frame comes only once the recording is open (a real MJPEG stream over
    # HTTP, of the clip's 64x48 frames): the empty log is removed, and said before the error.
    server = StallingMjpegServer(frames=3)
    try:
        rc, captured = _main_in_process(["record", "--camera", f"opencv:{server.url}", "--heading", "none",
                                         "--out", str(out), "--calibration", str(tmp_path / "cam.yaml")], capsys)
    finally:
        server.close()
    assert rc == 2 and not out.exists(), captured.err
    said = captured.err.strip().splitlines()
    assert said[0] == f"sunrig: nothing was recorded, so {out} is not kept", said
    assert said[1].startswith("sunrig: error: ") and "calibrat" in said[1], said
    # The corrected command records.
    rc, captured = _main_in_process([*argv, "--hfov-deg", "60"], capsys)
    assert rc == 0 and out.exists(), captured.err


def test_a_run_that_recorded_nothing_keeps_no_file(tmp_path, capsys, silent_camera):
    out = tmp_path / "run.mcap"
    rc, captured = _main_in_process(["run", "--camera", "opencv:0", "--hfov-deg", "60", "--heading", "none",
                                     "--record", str(out), "--record-frames", "--quiet"], capsys)
    assert not out.exists() and os.listdir(tmp_path) == []
    assert f"sunrig: nothing was recorded, so {out} is not kept" in captured.err.splitlines(), (rc, captured.err)


@pytest.mark.parametrize(("argv", "words"), [
    ("train --out {out}", "train: no logs given; pass native logs or folders of them"),
    ("train {demo} --out {out} --mirror-windows", "pass it with --export-only once the run is done"),
])
def test_train_asked_for_what_it_cannot_do_says_what_to_pass_and_writes_nothing(tmp_path, capsys, argv, words):
    out = tmp_path / "model"
    rc, captured = _main_in_process(_command(argv, out=out), capsys)
    _assert_one_line_error(rc, captured, names=words)
    assert len(captured.err.strip().splitlines()) == 1 and not out.exists()


@pytest.mark.parametrize(("n", "image", "dt", "why"), [
    (12, "black", 0.2, "no full window with ground truth in these logs (12 of the 12 frames too dark, bright, "
                       "flat or covered to use); "),
    (5, "noise", 0.2, "no log has 8 frames within --window-span-s 4 s (5 frames in all); give longer logs"),
    # Frames enough, too far apart: it once said "too few" and to evaluate logs from synth.
    (20, "noise", 1.0, "no log has 8 frames within --window-span-s 4 s (20 frames in all); give longer logs, or "
                       "raise --window-span-s for a camera slower than 1.75 frames a second"),
])
def test_eval_that_grades_nothing_says_which_frames_were_unusable(tmp_path, capsys, n, image, dt, why):
    from replay.native import LogWriter

    log = tmp_path / "drive.mcap"
    intr = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    rng = np.random.default_rng(5)
    with LogWriter(log) as w:  # heading and true sun on every frame
        for i in range(n):
            pixels = np.zeros((80, 128, 3), np.uint8) if image == "black" else rng.integers(0, 256, (80, 128, 3),
                                                                                           np.uint8)
            w.write_frame(Frame(t_mono_s=dt * i, seq=i, image_bgr=pixels, intrinsics=intr,
                                attitude=Attitude(math.radians(10.0 * i), HeadingRef.TRUE),
                                sun_enu_truth=[0.6, 0.0, 0.8]))
    rc, captured = _main_in_process(["eval", str(log), "--aggregators", "mean", "--quiet",
                                     "--json", str(tmp_path / "e.json")], capsys)
    assert rc == 2 and captured.out == ""
    assert captured.err.startswith(f"sunrig: error: eval graded nothing: {why}"), captured.err


def test_eval_of_logs_none_of_whose_frames_can_be_read_says_so_as_replay_does(tmp_path, capsys, monkeypatch):
    # It said "no log has 8 frames within --window-span-s 4 s (0 frames in all); give longer logs, or
    # raise --window-span-s": neither helps a log whose every image is damaged.
    bad = _unreadable_log(tmp_path / "bad.mcap", monkeypatch)
    rc, captured = _main_in_process(["eval", str(bad), "--aggregators", "mean", "--quiet"], capsys)
    _assert_one_line_error(rc, captured, names=f"eval graded nothing: {bad}: no frame of it could be read (the "
                                               "warnings above say why); evaluate another log, or re-record this one")
    assert "window-span-s" not in captured.err and json.loads(captured.out)["frames"] == 0  # (the JSON says so too)
    other = _unreadable_log(tmp_path / "other.mcap", monkeypatch)
    rc, captured = _main_in_process(["eval", str(bad), str(other), "--aggregators", "mean", "--quiet"], capsys)
    _assert_one_line_error(rc, captured, names="eval graded nothing: no frame of the 2 logs could be read (the "
                                               "warnings above say why); evaluate other logs, or re-record these")


def test_replay_says_which_frames_it_skipped_and_why(tmp_path, capsys):
    from replay.native import LogWriter

    log = tmp_path / "drive.mcap"
    intr = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    rng = np.random.default_rng(9)
    times = [0.2 * i for i in range(30)]  # 0 .. 5.8 s
    times[16:16] = [times[15] - 0.1]  # one frame older than the one before it
    times += [0.5, 0.7, 0.9]  # the clock jumps back past the 4 s window span: windows start again
    with LogWriter(log) as w:
        for i, t in enumerate(times):
            black = i in (3, 4)
            pixels = np.zeros((80, 128, 3), np.uint8) if black else rng.integers(0, 256, (80, 128, 3), np.uint8)
            heading = None if i in (7, 8) else Attitude(math.radians(5.0 * i), HeadingRef.TRUE)
            w.write_frame(Frame(t_mono_s=t, seq=i, image_bgr=pixels, intrinsics=intr, attitude=heading,
                                sun_enu_truth=[0.6, 0.0, 0.8]))
    rc, captured = _main_in_process(["replay", str(log), "--jsonl", str(tmp_path / "out.jsonl")], capsys)
    assert rc == 0, captured.err
    summary = captured.err.strip().splitlines()[-1]
    for said in ("2 frames without heading skipped",
                 "2 frames too dark, bright, flat or covered to show the sun skipped",
                 "1 frames older than the one before skipped", "1 clock jumps (windows started again)"):
        assert said in summary, summary


@pytest.mark.parametrize("command", ["replay", "eval"])
def test_replay_and_eval_let_a_camera_that_sees_its_own_hood_through_with_max_covered_share(tmp_path, capsys,
                                                                                           command):
    # The bottom third of every frame dark and flat, as a dashcam's view of its dashboard: left out
    # as covered by default, so nothing was estimated, with no way to say it is the vehicle's own.
    from replay.native import LogWriter

    log = tmp_path / "drive.mcap"
    intr = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    rng = np.random.default_rng(9)
    with LogWriter(log) as w:
        for i in range(12):
            pixels = rng.integers(0, 256, (80, 128, 3), np.uint8)
            pixels[50:] = 5
            w.write_frame(Frame(t_mono_s=0.2 * i, seq=i, image_bgr=pixels, intrinsics=intr,
                                attitude=Attitude(math.radians(5.0 * i), HeadingRef.TRUE),
                                sun_enu_truth=[0.6, 0.0, 0.8]))
    out = ["--jsonl", str(tmp_path / "out.jsonl")] if command == "replay" else ["--json", str(tmp_path / "e.json")]
    rc, captured = _main_in_process([command, str(log), *out], capsys)
    assert "12 frames too dark, bright, flat or covered" in captured.err, (rc, captured.err)
    rc, captured = _main_in_process([command, str(log), *out, "--max-covered-share", "1"], capsys)
    assert rc == 0 and "covered" not in captured.err, captured.err
    rc, captured = _main_in_process([command, str(log), *out, "--max-covered-share", "1.5"], capsys)
    assert rc == 2, captured.err
    assert "--max-covered-share: expected a finite number in [0, 1], got '1.5'" in captured.err, captured.err


# Every device a command opens, absent. No real device is here, so these are real failures to open.
_MISSING_DEVICES = {
    "run --camera opencv:N": ("run --camera opencv:99 --hfov-deg 60 --heading none --jsonl {out}", "index 99"),
    "run --camera opencv:URL": ("run --camera opencv:rtsp://127.0.0.1:1/x --hfov-deg 60 --heading none "
                                "--jsonl {out}", "rtsp://127.0.0.1:1/x"),
    "run --camera oak": ("run --camera oak --heading oak-imu --jsonl {out}", "no OAK device found"),
    "run --heading nmea:PORT": ("run --camera opencv:99 --hfov-deg 60 --heading nmea:{tmp}/ttyNOPE --jsonl {out}",
                                "ttyNOPE"),
    "run --serial": ("run --camera file:{demo} --heading log --serial {tmp}/ttyNOPE", "ttyNOPE"),
    "replay --serial": ("replay --serial {tmp}/ttyNOPE", "ttyNOPE"),
    "demo --serial": ("demo --serial {tmp}/ttyNOPE", "ttyNOPE"),
    "record --camera opencv:N": ("record --camera opencv:99 --hfov-deg 60 --heading none --out {out}.mcap",
                                 "index 99"),
    "gnss PORT": ("gnss {tmp}/ttyNOPE", "ttyNOPE"),
}


@pytest.mark.parametrize("slot", list(_MISSING_DEVICES))
def test_every_device_a_command_opens_when_absent_is_one_line_and_leaves_no_output(tmp_path, capsys, slot):
    line, names = _MISSING_DEVICES[slot]
    (tmp_path / "out").mkdir()
    rc, captured = _main_in_process(_command(line, tmp=tmp_path, out=tmp_path / "out" / "result"), capsys)
    _assert_one_line_error(rc, captured, names=names)
    assert not os.listdir(tmp_path / "out")


def _clip(path: Path) -> Path:
    """A real 64 x 48 MJPG video of 5 frames."""
    import cv2

    from tests.test_opencv_camera import clip_image

    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, (64, 48))
    for k in range(5):
        writer.write(clip_image(k))
    writer.release()
    return path


@pytest.mark.parametrize(("k", "size", "needle"), [
    # Ran until the encode stage died ("OverflowError: cannot convert float infinity to integer",
    # the crop side fx * tan(angle)); record kept a log that replay, eval and quantize failed on.
    ([[1e308, 0, 32], [0, 1e308, 24], [0, 0, 1]], (64, 48), "fx: expected at most"),
    # The camera reader divided by it: a traceback without --debug ("camera reader ... failed").
    ([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]], (0, 0), "width: expected a positive integer, got 0"),
    # Loaded, then failed once capture started.
    ([[60.0, 0, 32], [0, 60.0, 24], [0, 0, 1]], (-64, -48), "width: expected a positive integer, got -64"),
], ids=["fx-1e308", "width-0", "negative-size"])
@pytest.mark.parametrize("command", ["run", "record"])
def test_a_calibration_that_is_no_camera_is_refused_at_start_up_in_one_line(tmp_path, capsys, command, k, size,
                                                                             needle):
    from tests.test_opencv_camera import write_calibration

    clip = _clip(tmp_path / "clip.avi")
    cal = tmp_path / "cal.yaml"
    write_calibration(cal, np.array(k, dtype=np.float64), *size)
    (tmp_path / "out").mkdir()
    out = tmp_path / "out" / "result"
    argv = [command, "--camera", f"opencv:{clip}", "--calibration", str(cal), "--heading", "visual"]
    argv += ["--aggregator", "mean", "--jsonl", str(out)] if command == "run" else ["--out", f"{out}.mcap"]
    rc, captured = _main_in_process(argv, capsys)
    _assert_one_line_error(rc, captured, names=f"calibration file {cal}: ")
    assert len(captured.err.strip().splitlines()) == 1 and needle in captured.err, captured.err
    assert not os.listdir(tmp_path / "out")


@pytest.mark.parametrize("command", ["run", "record"])
def test_a_field_of_view_narrower_than_any_camera_is_refused_before_anything_opens(tmp_path, capsys, command):
    # --hfov-deg 1e-300 made fx 1e302 px: numpy overflow warnings on stderr from every window.
    clip = _clip(tmp_path / "clip.avi")
    (tmp_path / "out").mkdir()
    out = tmp_path / "out" / "result"
    argv = [command, "--camera", f"opencv:{clip}", "--hfov-deg", "1e-300", "--heading", "visual"]
    argv += ["--aggregator", "mean", "--jsonl", str(out)] if command == "run" else ["--out", f"{out}.mcap"]
    rc, captured = _main_in_process(argv, capsys)
    assert rc == 2 and "Traceback" not in captured.err, captured.err
    (line,) = captured.err.strip().splitlines()  # argparse's, as for every other bad number
    assert line.startswith(f"sunrig {command}: error: argument --hfov-deg: expected 0 (unset) or at least 0.0001 deg")
    assert not os.listdir(tmp_path / "out")


@pytest.mark.parametrize("command", ["run", "record"])
def test_a_camera_index_beyond_a_c_int_is_one_line(tmp_path, capsys, command):
    # OpenCV takes a C int: "internal error: error: OpenCV ... Overload resolution failed" and six
    # lines of candidate signatures.
    (tmp_path / "out").mkdir()
    out = tmp_path / "out" / "result"
    argv = [command, "--camera", "opencv:2147483648", "--hfov-deg", "60", "--heading", "none"]
    argv += ["--jsonl", str(out)] if command == "run" else ["--out", f"{out}.mcap"]
    rc, captured = _main_in_process(argv, capsys)
    _assert_one_line_error(rc, captured, names="camera index 2147483648: expected at most 2147483647")
    assert len(captured.err.strip().splitlines()) == 1 and not os.listdir(tmp_path / "out")


def _log_with_no_camera(path: Path, monkeypatch) -> Path:
    """A log recorded with fx = fy = 1e308 (before calibrations were checked as they load): none
    of its frames can be read."""
    from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration

    import replay.native

    encode = replay.native.encode_calibration

    def no_camera(intr, t_ns):
        msg = CameraCalibration.FromString(encode(intr, t_ns))
        msg.K[0] = msg.K[4] = 1e308
        return msg.SerializeToString()

    with monkeypatch.context() as m:
        m.setattr(replay.native, "encode_calibration", no_camera)
        return _write_log(path)


def test_a_recording_or_drive_whose_focal_length_is_no_camera_is_no_internal_error(tmp_path, capsys, monkeypatch):
    # A log recorded with fx = 1e308 (before calibrations were checked as they load), and a KITTI
    # drive whose P_rect_02 says so: replay and eval ended in an internal OverflowError.
    from tests.test_kitti import _CALIB, DRIVE, make_drive

    log = _log_with_no_camera(tmp_path / "drive.mcap", monkeypatch)
    date = make_drive(tmp_path / "kitti", 3)
    calib = date / "calib_cam_to_cam.txt"
    calib.write_text(_CALIB.replace("P_rect_02: 7.215377e+02", "P_rect_02: 1e308"))
    for argv, names in (
        (["replay", str(log), "--aggregator", "mean", "--jsonl", str(tmp_path / "o.jsonl")],
         f"{log}: no frame of it could be read"),
        (["eval", str(log), "--aggregators", "mean", "--quiet", "--json", str(tmp_path / "e.json")], str(log)),
        (["replay", str(date / DRIVE), "--utc-offset", "2", "--aggregator", "mean", "--jsonl",
          str(tmp_path / "o.jsonl")], f"{calib}: P_rect_02: Intrinsics.fx: expected at most"),
    ):
        rc, captured = _main_in_process(argv, capsys)
        _assert_one_line_error(rc, captured, names=names)
        assert not (tmp_path / "o.jsonl").exists()


def test_a_run_whose_source_gives_no_frame_is_an_error(tmp_path, capsys, monkeypatch):
    # `run --camera file:LOG` of a log none of whose frames could be read said "frames 0" and
    # exited 0, where replay and record call it an error.
    log = _log_with_no_camera(tmp_path / "drive.mcap", monkeypatch)
    rc, captured = _main_in_process(["run", "--camera", f"file:{log}", "--heading", "log", "--fast", "--jsonl",
                                     str(tmp_path / "o.jsonl")], capsys)
    last = captured.err.strip().splitlines()[-1]
    assert rc == 2 and last.startswith("sunrig: error: the source gave no frame"), captured.err
    assert "Traceback" not in captured.err and not (tmp_path / "o.jsonl").exists()


@pytest.mark.parametrize(("stats", "said"), [
    # A stalled reader with the port up: its reader is named.
    ({"published": 10, "written": 6, "dropped_overwritten": 4, "port_open": True},
     "sunrig: SerialPublisher: 4 estimates dropped because its reader did not keep up, 6 written"),
    # The port gone for good, one estimate still waiting at the end: once blamed on the reader,
    # and the line added up to one less than was published.
    ({"published": 599, "written": 24, "dropped_overwritten": 574, "pending": 1, "port_open": False},
     "sunrig: SerialPublisher: 574 estimates dropped while its port was failing or its reader did not keep up, "
     "24 written, 1 unsent at the end"),
])
def test_the_exit_report_of_an_output_adds_up_and_does_not_blame_the_reader_for_a_lost_port(stats, said, capsys):
    from rig.cli import _report_output_losses

    assert _report_output_losses({"SerialPublisher": stats}) == 0
    assert capsys.readouterr().err.strip() == said


def _sunrig_script() -> tuple[str, str]:
    """The module and function that pyproject's ``sunrig`` console script calls."""
    import tomllib

    target = tomllib.loads((Path(__file__).resolve().parent.parent / "pyproject.toml").read_text())
    module, _, function = target["project"]["scripts"]["sunrig"].partition(":")
    return module, function


def test_the_sunrig_command_starts_without_importing_numpy():
    # A Ctrl-C in the first ~0.3 s of any command landed inside `import numpy` (which `import rig`
    # did, for rig.types) or another import of rig.cli, before any handler of ours ran: a
    # traceback. The module the console script imports, and the rig package, load nothing heavy;
    # the names `from rig import ...` gives still resolve, to the same objects as before.
    module, _ = _sunrig_script()
    code = (f"import sys, rig, {module}\n"
            "heavy = [m for m in ('numpy', 'rig.types', 'rig.cli') if m in sys.modules]\n"
            "from rig import *\n"
            "from rig import Frame, ValidationError\n"
            "import rig.errors, rig.types\n"
            "assert Frame is rig.types.Frame and ValidationError is rig.errors.ValidationError\n"
            "assert all(getattr(rig, name) is globals()[name] for name in rig.__all__)\n"
            "assert set(rig.__all__) <= set(dir(rig))\n"
            "print(heavy)")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and res.stdout.strip() == "[]", res.stdout + res.stderr


_CTRL_C_WHILE_IMPORTING_THE_CLI = """
import signal, sys

class CtrlCOnImport:  # a real SIGINT, delivered while rig.cli is being imported
    def find_spec(self, name, path=None, target=None):
        if name == "rig.cli":
            signal.raise_signal(signal.SIGINT)
        return None

sys.meta_path.insert(0, CtrlCOnImport())
from {module} import {function}
sys.exit({function}())
"""


def test_a_ctrl_c_before_the_command_has_started_exits_130_without_a_traceback():
    module, function = _sunrig_script()
    code = _CTRL_C_WHILE_IMPORTING_THE_CLI.format(module=module, function=function)
    res = subprocess.run([sys.executable, "-c", code, "replay", "--jsonl", os.devnull], capture_output=True,
                         text=True, timeout=120)
    assert res.returncode == 130, res.stderr
    assert res.stderr == "sunrig: interrupted\n", res.stderr


def test_the_sunrig_console_script_runs_the_command(tmp_path):
    # What the console script calls is the whole command: its errors and exit codes are main()'s.
    module, function = _sunrig_script()
    res = subprocess.run([sys.executable, "-c", f"import sys; from {module} import {function}; sys.exit({function}())",
                          "replay", str(tmp_path / "nope.mcap")], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2 and res.stderr.startswith("sunrig: error:"), res.stderr
    assert "Traceback" not in res.stderr


def _shipped_copy(tmp_path, monkeypatch):
    """A copy of the shipped model that sunrig takes for the installed one (its DEFAULT_MODEL_DIR)."""
    import estimator.models

    copy = tmp_path / "site-packages" / "estimator" / "default_model"
    shutil.copytree(estimator.models.DEFAULT_MODEL_DIR, copy)
    monkeypatch.setattr(estimator.models, "DEFAULT_MODEL_DIR", copy.resolve())
    return copy


@pytest.mark.parametrize("damage", ["no SHA256SUMS", "a flipped byte", "unreadable"])
def test_a_damaged_shipped_model_says_to_reinstall_sunrig(tmp_path, monkeypatch, capsys, damage):
    # The remedies a user's own folder gets (copy it again, re-export it from its training run)
    # are none for the package's own files; and a shipped model with its SHA256SUMS gone ran unchecked.
    shipped = _shipped_copy(tmp_path, monkeypatch)
    if damage == "no SHA256SUMS":
        (shipped / "SHA256SUMS").unlink()
        names = "the model installed with sunrig is damaged: "
    elif damage == "a flipped byte":
        blob = bytearray((shipped / "backbone.onnx").read_bytes())
        blob[len(blob) // 2] ^= 0xFF
        (shipped / "backbone.onnx").write_bytes(bytes(blob))
        names = "the model installed with sunrig is damaged: "
    else:
        real_read = Path.read_bytes

        def read_bytes(path):
            if path.name == "aggregator.onnx":
                raise PermissionError(13, "Permission denied")
            return real_read(path)

        monkeypatch.setattr(Path, "read_bytes", read_bytes)
        names = "aggregator.onnx: cannot read it (Permission denied)"
    rc, captured = _main_in_process(["replay", "--jsonl", str(tmp_path / "out.jsonl"), "--quiet"], capsys)
    _assert_one_line_error(rc, captured, names=names)
    assert "reinstall sunrig" in captured.err and "re-export" not in captured.err
    assert not (tmp_path / "out.jsonl").exists()


def test_a_users_folder_without_sha256sums_still_loads_unchecked(tmp_path, monkeypatch):
    # Required of the shipped model only: a user's copy of a folder may have lost it on the way.
    from estimator.runtime import OnnxModel

    shipped = _shipped_copy(tmp_path, monkeypatch)
    mine = tmp_path / "mine"
    shutil.copytree(shipped, mine)
    (mine / "SHA256SUMS").unlink()
    assert OnnxModel.load(mine).model_id == OnnxModel.load(shipped).model_id


def test_a_missing_demo_log_says_to_reinstall_sunrig(tmp_path, monkeypatch, capsys):
    # The user named no log: "check the path" is no remedy for the install's own demo log.
    import replay.sources

    monkeypatch.setattr(replay.sources, "DEMO_LOG", tmp_path / "data" / "demo.mcap")
    for command in (["replay", "--quiet"], ["demo", "--fast", "--quiet"]):
        rc, captured = _main_in_process(command, capsys)
        _assert_one_line_error(rc, captured, names=f"the demo log installed with sunrig ({tmp_path}")
        assert "reinstall sunrig" in captured.err and "check the path" not in captured.err


def test_demo_takes_rig_realtime_from_its_config_unless_fast_is_given(tmp_path, monkeypatch, capsys):
    # demo set [rig] realtime from --fast alone, so a config's `realtime = false` was overwritten by
    # a flag that was not given (its help says demo reads [rig] from --config).
    import rig.cli

    seen = []
    monkeypatch.setattr(rig.cli, "_live", lambda cfg, source, **kwargs: seen.append(cfg["rig"]["realtime"]) or 0)
    fast = tmp_path / "fast.toml"
    fast.write_text("[rig]\nrealtime = false\n")
    paced = tmp_path / "paced.toml"
    paced.write_text("[rig]\nrealtime = true\n")
    for argv in (["demo", "--config", str(fast)], ["demo"], ["demo", "--config", str(paced), "--fast"],
                 ["demo", "--config", str(paced)]):
        rc, captured = _main_in_process([*argv, "--quiet"], capsys)
        assert rc == 0, captured.err
    assert seen == [False, True, False, True]


@pytest.mark.parametrize("flag", ["--camera", "--heading"])
def test_an_empty_source_flag_is_a_usage_error_not_an_override_of_the_config(tmp_path, capsys, flag):
    # `--camera "$CAMERA"` with the variable unset replaced the config's [source] camera with "",
    # and the error then said to set [source] camera in --config, which was set.
    config = tmp_path / "rig.toml"
    config.write_text('[source]\ncamera = "opencv:0"\nheading = "nmea:/dev/ttyUSB0"\n')
    for command in (["run"], ["record", "--out", str(tmp_path / "o.mcap")]):
        rc, captured = _main_in_process([*command, "--config", str(config), flag, ""], capsys)
        assert rc == 2 and captured.out == "", captured.err
        (said,) = captured.err.strip().splitlines()
        assert said.startswith(f"sunrig {command[0]}: error: argument {flag}: expected a source, got an empty "
                               "string (leave the flag out to use the config's)"), said


def test_the_exit_report_counts_what_the_outputs_wrote_as_they_closed(tmp_path, monkeypatch, capsys):
    # A background output still writing when the run ended was reported from the statistics taken
    # then: "0 written" and exit 2 ("wrote none") for a JSONL that held estimates once closed.
    import threading

    import rig.cli
    from rig.publishers import BackgroundPublisher, JsonlPublisher

    closing = threading.Event()
    real_publish, real_close_all, real_init = JsonlPublisher.publish, rig.cli._close_all, BackgroundPublisher.__init__

    def slow_publish(self, est):  # a slow disk: nothing is written before the outputs close
        closing.wait(10.0)
        return real_publish(self, est)

    def close_all(pubs, stop):
        closing.set()
        return real_close_all(pubs, stop)

    monkeypatch.setattr(JsonlPublisher, "publish", slow_publish)
    monkeypatch.setattr(rig.cli, "_close_all", close_all)
    # A short queue, so that the slow disk costs estimates and the report has a line to say.
    monkeypatch.setattr(BackgroundPublisher, "__init__",
                        lambda self, inner, **kw: real_init(self, inner, max_pending=4))
    out = tmp_path / "est.jsonl"
    rc, captured = _main_in_process(["demo", "--fast", "--quiet", "--jsonl", str(out)], capsys)
    lines = out.read_text().splitlines()
    reported = re.search(r"JsonlPublisher: (\d+) estimates dropped .*, (\d+) written", captured.err)
    assert reported is not None, captured.err
    assert rc == 0 and int(reported.group(2)) == len(lines) > 0, captured.err


def test_eval_that_grades_nothing_draws_no_empty_figure(tmp_path, capsys):
    # A log shorter than a window: the error said graded nothing, yet an empty chart was saved at
    # --plot as if it were the figure asked for, with matplotlib's legend warning beside it.
    log = _write_log(tmp_path / "short.mcap", n=5)
    png = tmp_path / "e.png"
    rc, captured = _main_in_process(["eval", str(log), "--aggregators", "mean", "--quiet", "--json",
                                     str(tmp_path / "e.json"), "--plot", str(png)], capsys)
    _assert_one_line_error(rc, captured, names="eval graded nothing: no log has 8 frames")
    assert len(captured.err.strip().splitlines()) == 1, captured.err
    assert not png.exists() and not (tmp_path / "e-tokens.png").exists()


def test_eval_stopped_before_any_window_draws_no_figure_and_says_so(tmp_path, capsys, monkeypatch):
    # "interrupted after 0 windows ...; the JSON and figures hold those": an empty chart was saved.
    # The evaluation is the real one, stopped by a real Ctrl-C as it reads the log's first frame.
    import signal

    import replay.sources

    real_open_frames = replay.sources.open_frames

    def ctrl_c_at_the_first_frame(path, **kwargs):
        frames = real_open_frames(path, **kwargs)

        def read():
            signal.raise_signal(signal.SIGINT)
            yield from frames

        return read()

    monkeypatch.setattr(replay.sources, "open_frames", ctrl_c_at_the_first_frame)
    png, out = tmp_path / "e.png", tmp_path / "e.json"
    rc, captured = _main_in_process(["eval", str(_write_log(tmp_path / "d.mcap")), "--aggregators", "mean",
                                     "--json", str(out), "--plot", str(png)], capsys)
    summary = json.loads(out.read_text())
    assert rc == 130 and not png.exists() and summary["interrupted"] is True
    assert summary["aggregators"]["mean"]["n_windows"] == 0 and summary["logs"] == [str(tmp_path / "d.mcap")]
    assert captured.err == "eval: interrupted before any window was graded; the JSON holds what was counted, " \
                           "and no figure was drawn\n"


def test_eval_of_a_log_named_twice_grades_it_once_and_says_so(tmp_path, capsys, caplog):
    # A folder and a log in it (or overlapping globs): the log's windows were graded twice, its
    # errors weighing double in every figure and its worst_logs row counting each window twice.
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    a, b = _write_log(fleet / "a.mcap"), _write_log(fleet / "b.mcap", n=14)
    out = tmp_path / "e.json"
    rc, captured = _main_in_process(["eval", str(fleet), str(a), str(fleet / ".." / "fleet" / "b.mcap"),
                                     "--aggregators", "mean", "--quiet", "--json", str(out)], capsys)
    assert rc == 0, captured.err
    summary = json.loads(out.read_text())
    assert summary["logs"] == [str(a), str(b)]
    assert summary["aggregators"]["mean"]["n_windows"] == 4 + 6  # 11 frames with a heading, and 13
    assert [r.getMessage() for r in caplog.records] == [
        f"eval: {a}: named before; read once",
        f"eval: {fleet / '..' / 'fleet' / 'b.mcap'}: named before as {b}; read once"]


def test_train_and_quantize_read_a_log_named_twice_once(tmp_path, caplog):
    # The same expansion as eval's: a log named twice weighed double in training (and calibration).
    from rig.cli import _expand_logs

    fleet = tmp_path / "fleet"
    fleet.mkdir()
    a, b = _write_log(fleet / "a.mcap"), _write_log(fleet / "b.mcap", n=14)
    for command in ("train", "quantize"):
        caplog.clear()
        assert _expand_logs(command, [str(fleet), str(a)]) == [a, b]
        assert [r.getMessage() for r in caplog.records] == [f"{command}: {a}: named before; read once"]


def test_eval_names_a_log_of_which_no_window_was_graded(tmp_path, capsys, caplog):
    # A log too short for a window among logs graded: exit 0 and figures over "every log", with
    # nothing said of the one that gave none (only a pooled count in the JSON).
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    _write_log(fleet / "a.mcap")
    short = _write_log(fleet / "b.mcap", n=5)
    out = tmp_path / "e.json"
    rc, captured = _main_in_process(["eval", str(fleet), "--aggregators", "mean", "--json", str(out)], capsys)
    assert rc == 0, captured.err
    assert [r.getMessage() for r in caplog.records] == [
        f"eval: {short}: no window graded (it has 5 frames, fewer than a window's 8); the figures are of the "
        "other logs"]
    assert json.loads(out.read_text())["logs_not_graded"] == {str(short): "it has 5 frames, fewer than a window's 8"}
    assert captured.err.startswith("eval: mean: mean ")  # the summary line, after the counter is cleared


def test_eval_refuses_to_write_its_json_over_a_log(tmp_path, capsys):
    # `sunrig eval --json drives/*.mcap`: the first log became the JSON's path, and the evaluation
    # of the others wrote over it, a recording lost without a word.
    a, b = _write_log(tmp_path / "a.mcap"), _write_log(tmp_path / "b.mcap")
    before = a.read_bytes()
    rc, captured = _main_in_process(["eval", "--json", str(a), str(b), "--aggregators", "mean", "--quiet"], capsys)
    _assert_one_line_error(rc, captured, names=f"--json {a}: that is a log's name (.mcap), not a JSON file's; "
                                               "pass the JSON file's own path after --json (or - for stdout)")
    assert a.read_bytes() == before


@pytest.mark.parametrize(("given", "unknown"), [("bogus", "aggregator 'bogus'"), ("mean,", "aggregator ''"),
                                                ("Mean,single,x", "aggregators 'Mean', 'x'")])
def test_eval_names_the_aggregators_it_does_not_know_by_the_flag(tmp_path, capsys, given, unknown):
    # "aggregator: expected one of ..., got ['bogus']", after the logs were opened and the model
    # loaded: no flag named, and a Python list for the user to read.
    rc, captured = _main_in_process(["eval", str(_write_log(tmp_path / "d.mcap")), "--aggregators", given], capsys)
    assert rc == 2 and captured.out == ""
    assert captured.err == (f"sunrig eval: error: argument --aggregators: no {unknown}: pass a "
                            "comma-separated subset of transformer, mean, meanshift, single (see sunrig eval --help)\n")


def test_the_exit_report_says_what_a_suspend_cost_the_heading_port():
    # The GNSS reader drops what its first read after a host suspend finds waiting (a668782): the
    # exit report named every other loss of the port's bytes, but not that one.
    from rig.cli import _source_summary

    assert _source_summary({"gnss": {"suspends": 1, "stale_bytes": 412, "reopens": 0}}) == (
        "heading port suspends 1, heading port stale bytes 412")


def test_the_exit_report_says_how_often_visual_odometry_started_a_new_zero():
    # A black stretch or a frozen camera starts a new zero, and the windows refill from it: the
    # report said only how many frames were lost, not that the heading had started again.
    from rig.cli import _source_summary

    vo = {"frames": 240, "lost": 63, "gaps": 1, "uncarried": 61, "restarts": 0, "repeated": 30}
    assert _source_summary({"visual_odometry": vo}) == (
        "visual odometry lost 63 of 240 frames, visual odometry started 62 new heading zeros, "
        "camera repeated 30 frames")
    assert _source_summary({"visual_odometry": {"frames": 240, "lost": 0, "gaps": 0}}) == ""


def test_the_exit_report_says_what_an_oaks_gyro_learned_of_its_bias():
    # imu_mode gyro learns the gyro's bias while the IMU stands still (drivers/imu_heading.py); the
    # report read none of the IMU's counts, so a user could not tell a heading held from one drifting.
    from rig.cli import _source_summary

    imu = {"gyro_bias_learned": 3, "gyro_bias_refused": 1, "gyro_bias_deg_s": 0.52, "gyro_bias_heading_deg_s": -0.48}
    assert _source_summary({"camera": {"imu_counts": imu}}) == (
        "gyro bias learned 3 times (-0.48 deg/s of heading), gyro still stretches refused as too fast a bias 1")
    quiet = {"gyro_bias_learned": 0, "gyro_bias_refused": 0, "gyro_bias_deg_s": 0.0, "gyro_bias_heading_deg_s": 0.0}
    assert _source_summary({"camera": {"imu_counts": quiet}}) == ""


def test_the_exit_report_says_what_an_opencv_camera_lost():
    # The OpenCV camera counts stalled reads, frames it could not use, failed reopens and a frozen
    # driver's repeated frames (dropped): the report left all four out, so a run that lost minutes
    # to a stalled stream ended without a word of it.
    from rig.cli import _source_summary

    camera = {"frames": 900, "dropped": 0, "bad_frames": 3, "read_failures": 2, "reconnects": 1,
              "open_failures": 4, "stalls": 2, "repeated": 17}
    assert _source_summary({"camera": camera}) == (
        "camera read failures 2, camera reconnects 1, camera bad frames 3, camera open failures 4, camera stalls 2, "
        "camera repeated frames dropped 17")


def test_the_exit_report_says_what_an_oak_lost_on_the_device_and_why_frames_had_no_heading():
    # The OAK counts frames it never sent (a slow USB link) and frames its IMU gave no heading, by
    # reason; the report showed none of it.
    from rig.cli import _source_summary

    camera = {"frames_dropped_device": 12, "no_heading_inaccurate": 40, "no_heading_gap": 0, "reconnects": 1}
    assert _source_summary({"camera": camera}) == (
        "camera frames dropped device 12, camera reconnects 1, camera frames without heading (inaccurate) 40")


def test_a_live_camera_is_never_paced_and_its_frames_age_from_their_stamps():
    # [rig] realtime (default true) paced every source as a recording: a live camera's frame that
    # came 1.3 s late (a GNSS pause held it in the pairing) started the pace again from it, and
    # every later frame was held as late, 1.4 s, flagged invalid, for the rest of the run.
    from rig.cli import _rig_config
    from rig.config import DEFAULTS

    assert DEFAULTS["rig"]["realtime"]
    live = _rig_config(DEFAULTS["rig"], live_camera=True)
    recording = _rig_config(DEFAULTS["rig"], live_camera=False)
    assert (live.realtime, live.live_clock) == (False, True)
    assert (recording.realtime, recording.live_clock) == (True, False)


def test_the_rigs_own_event_lines_reach_stderr_and_other_libraries_info_does_not():
    # The CLI logged at WARNING, so every line saying an outage had ended ("serial port ... writes
    # again", "GNSS source ... reopened", "camera ... is back", "estimates are in time again") was
    # dropped: a journal said when the GNSS stopped and never that it came back.
    script = (
        "import logging, sys\n"
        "from rig.cli import main\n"
        "main(['sun', '--time', '2011-09-26T11:02:26Z', '--lat', '49', '--lon', '8'])\n"
        "logging.getLogger('drivers.gnss').info('GNSS source x reopened')\n"
        "logging.getLogger('rig.publishers').info('serial port y writes again')\n"
        "logging.getLogger('estimator.train').info('starting from the weights of z')\n"
        "logging.getLogger('somelib').info('chatter')\n"
        "logging.getLogger('drivers.gnss').debug('detail')\n"
    )
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert res.stderr.splitlines() == ["sunrig: INFO: GNSS source x reopened",
                                       "sunrig: INFO: serial port y writes again",
                                       "sunrig: INFO: starting from the weights of z"], res.stderr


@pytest.mark.torch
def test_the_live_status_on_a_narrow_terminal_is_whole_lines_not_wrapped_redraws(tiny_model_dir):
    # The status line (about 200 characters) redrawn in place on an 80-column terminal wrapped, and
    # "\r" went back to its last row only: each redraw left the rows above it behind.
    rc, raw = _run_on_pty(["demo", "--model", str(tiny_model_dir)], columns=80)
    assert rc == 0
    text = raw.replace("\r\n", "\n")  # the pty's own line ending
    drawn = [seg.split("\x1b[K")[0] for seg in text.split("\r") if "\x1b[K" in seg]
    assert all(len(row) < 80 for row in drawn), drawn
    statuses = [line for line in text.split("\n") if line.startswith("sunrig: frames ")]
    assert statuses and all("| estimates " in line for line in statuses), text


def test_the_status_line_says_the_camera_s_drops_as_they_happen():
    # The status line's "dropped" is the rig's own queue; a camera dropping frames or reconnecting
    # showed only in the exit report, so a journal read mid-run said nothing of it.
    from rig.cli import _status_text

    class Source:
        def stats(self):
            return {"camera": {"dropped": 7, "reconnects": 2}, "pairing": {"gap": 0}}

    line = _status_text("frames 10 (dropped 0, ...)", Source())
    assert line == "sunrig: frames 10 (dropped 0, ...) | source: camera dropped 7, camera reconnects 2"
    assert _status_text("frames 10", object()) == "sunrig: frames 10"


def _screen_lines(raw: str) -> list[str]:
    """What a terminal shows of ``raw``, one string per line: a "\\r" returns to the row's start,
    text overwrites from the cursor, and "ESC [K" erases from the cursor to the row's end."""
    shown = []
    for line in raw.replace("\r\n", "\n").split("\n"):
        row, col = "", 0
        for token in re.split(r"(\r|\x1b\[K)", line):
            if token == "\r":
                col = 0
            elif token == "\x1b[K":
                row = row[:col]
            else:
                row = row[:col] + token + row[col + len(token):]
                col += len(token)
        shown.append(row)
    return shown


def _run_on_pty(argv: list[str], columns: int) -> tuple[int, str]:
    import fcntl
    import select
    import struct
    import termios

    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
    proc = subprocess.Popen([sys.executable, "-m", "rig.cli", *argv], stdout=subprocess.DEVNULL, stderr=slave,
                            env=dict(os.environ, PYTHONWARNINGS="ignore"))
    os.close(slave)
    raw = b""
    while select.select([master], [], [], 60)[0]:
        try:
            chunk = os.read(master, 65536)
        except OSError:  # the pty's other end closed: the command is done
            break
        if not chunk:
            break
        raw += chunk
    os.close(master)
    return proc.wait(timeout=60), raw.decode()


@pytest.mark.torch
def test_a_warning_during_a_status_row_drawn_in_place_starts_a_row_of_its_own(tiny_model_dir, tmp_path):
    # On a terminal wide enough for the status row, a warning was written after the row's text, on
    # the same row: "sunrig: frames 11 (...) | ... errors 0sunrig: WARNING: [rig] ring_capacity ...".
    config = tmp_path / "ring.toml"
    config.write_text("[rig]\nring_capacity = 16\n")  # too few frames for the span: warned once, mid-run
    rc, raw = _run_on_pty(["demo", "--model", str(tiny_model_dir), "--config", str(config)], columns=400)
    assert rc == 0
    warned = [line for line in _screen_lines(raw) if "WARNING" in line]
    assert warned and all(line.startswith("sunrig: WARNING: ") for line in warned), warned
