"""`sunrig eval`: the summary's numbers and shape, and the figures."""

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from estimator.evaluate import EvalResult, error_summary
from rig.protocol import FLAG_ABOVE_TRAINED, FLAG_SPREAD_HIGH, FLAG_VALID
from rig.types import Attitude, Frame, HeadingRef, Intrinsics


def noise_drive(n: int, ref: HeadingRef = HeadingRef.TRUE) -> list:
    """``n`` frames of noise turning 7 deg a frame, with a true sun: enough for the tiny model."""
    k = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    rng = np.random.default_rng(2)
    return [Frame(t_mono_s=0.1 * i, seq=i, image_bgr=rng.integers(0, 256, (80, 128, 3), np.uint8), intrinsics=k,
                  attitude=Attitude(math.radians(7.0 * i), ref), sun_enu_truth=[0.0, 0.8, 0.6])
            for i in range(n)]


def test_error_summary_numbers():
    s = error_summary([1.0, 4.0, 6.0, 12.0, 30.0])
    assert s["mean_deg"] == pytest.approx(10.6)
    assert s["median_deg"] == 6.0 and s["max_deg"] == 30.0 and s["n_windows"] == 5
    assert s["under_5_deg"] == pytest.approx(0.4)
    assert s["under_10_deg"] == pytest.approx(0.6)
    assert s["under_20_deg"] == pytest.approx(0.8)
    assert s["windows_over_30_deg"] == 0  # 30.0 itself is on target, not past it
    assert s["p99_deg"] == pytest.approx(np.percentile([1.0, 4.0, 6.0, 12.0, 30.0], 99))
    assert error_summary([10.0, 30.5, 75.0])["windows_over_30_deg"] == 2



def test_the_summary_of_no_window_has_every_key_with_none_for_what_it_cannot_say():
    # It was {"n_windows": 0}: a reader of eval's JSON (an interrupted run, a log shorter than a
    # window) met a KeyError on "mean_deg" where the shape promised one.
    s = error_summary([])
    assert set(s) == set(error_summary([1.0]))
    assert s["n_windows"] == 0 and s["windows_over_30_deg"] == 0
    assert all(s[k] is None for k in s if k not in ("n_windows", "windows_over_30_deg"))



def test_pooled_results_add_windows_and_keep_this_ones_logs():
    ok, hedge = FLAG_VALID, FLAG_ABOVE_TRAINED
    a = EvalResult(errors_deg={"transformer": [1.0, 2.0], "mean": [5.0, 6.0]},
                   flags={"transformer": [ok, ok], "mean": [ok, ok]}, logs=["d0"],
                   window_logs=["d0", "d0"], frames=10, frames_bad_exposure=2, windows_skipped_filling=7,
                   windows_failed=1, records_skipped_corrupt_by_log={"d0": 1})
    b = EvalResult(errors_deg={"transformer": [40.0], "mean": [3.0]}, flags={"transformer": [hedge], "mean": [ok]},
                   logs=["d0"], window_logs=["d0"], frames=10,
                   frames_without_heading=3, frames_bad_exposure=2, windows_skipped_filling=7, windows_without_truth=2,
                   records_skipped_corrupt_by_log={"d0": 1})
    a.extend(b)
    s = a.summary()
    # The status figures pool too: the 40-deg window was flagged, so the controller's worst is 2 deg.
    assert s["status"]["transformer"] == {"valid_windows": 2, "above_trained": 1, "spread_high": 0,
                                          "windows_over_30_deg_not_valid": 1, "valid_max_deg": 2.0}
    assert s["status"]["mean"]["valid_windows"] == 3 and s["status"]["mean"]["valid_max_deg"] == 6.0
    assert s["worst_logs"]["transformer"] == [{"log": "d0", "n_windows": 3, "mean_deg": pytest.approx(43.0 / 3),
                                               "max_deg": 40.0, "windows_over_30_deg": 1,
                                               "records_skipped_corrupt": 2}]
    assert s["aggregators"]["transformer"]["n_windows"] == 3
    assert s["aggregators"]["transformer"]["max_deg"] == 40.0
    assert s["aggregators"]["mean"]["mean_deg"] == pytest.approx(14.0 / 3)
    assert s["logs"] == ["d0"]
    counts = (s["frames"], s["frames_without_heading"], s["frames_bad_exposure"], s["windows_skipped_filling"],
              s["windows_failed"], s["windows_without_truth"], s["records_skipped_corrupt"])
    assert counts == (20, 3, 4, 14, 1, 2, 2)


def test_worst_logs_come_first_and_the_list_is_cut():
    errs = {"d0": [3.0, 5.0], "d1": [2.0, 31.0, 45.0], "d2": [1.0], "d3": [9.0], "d4": [8.0], "d5": [7.0]}
    r = EvalResult(errors_deg={"transformer": [e for v in errs.values() for e in v]},
                   flags={"transformer": [FLAG_VALID for v in errs.values() for _ in v]},
                   window_logs=[name for name, v in errs.items() for _ in v])
    rows = r.by_log("transformer")
    assert [row["log"] for row in rows] == ["d1", "d3", "d4", "d5", "d0", "d2"]
    assert rows[0]["n_windows"] == 3 and rows[0]["mean_deg"] == pytest.approx(26.0)
    assert rows[0]["windows_over_30_deg"] == 2 and rows[1]["windows_over_30_deg"] == 0
    assert [row["log"] for row in r.summary()["worst_logs"]["transformer"]] == ["d1", "d3", "d4", "d5", "d0"]
    with pytest.raises(ValueError, match="window logs"):
        EvalResult(errors_deg={"transformer": [1.0]}).by_log("transformer")


@pytest.mark.torch
def test_eval_cli_json_shape_and_plots(tmp_path, tiny_model_dir):
    from replay.native import LogWriter
    from rig.types import Attitude, Frame, HeadingRef, Intrinsics

    k = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    rng = np.random.default_rng(0)
    logs = []
    for d in range(2):
        path = tmp_path / f"d{d}.mcap"
        with LogWriter(path) as w:
            for i in range(12):
                # The second log opens with two black frames: counted, and left out of its windows.
                img = rng.integers(0, 256, (80, 128, 3), np.uint8)
                if d == 1 and i < 2:
                    img[:] = 0
                w.write_frame(Frame(t_mono_s=0.1 * i, seq=i, image_bgr=img,
                                    intrinsics=k, attitude=Attitude(math.radians(7.0 * i), HeadingRef.TRUE),
                                    sun_enu_truth=[0.0, 0.8, 0.6]))
        logs.append(path)
    out, png = tmp_path / "eval.json", tmp_path / "eval.png"
    res = subprocess.run([sys.executable, "-m", "rig.cli", "eval", str(tmp_path), "--model", str(tiny_model_dir),
                          "--json", str(out), "--plot", str(png), "--quiet"],
                         capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr
    summary = json.loads(out.read_text())
    aggs = summary["aggregators"]
    assert set(aggs) == {"transformer", "mean", "meanshift", "single"}
    for s in aggs.values():
        # Windows are full from the 8th usable frame on: 5 of the first log's 12, 3 of the second's 10.
        assert s["n_windows"] == 8
        assert 0.0 <= s["median_deg"] <= s["max_deg"] <= 180.0
        assert {"mean_deg", "median_deg", "max_deg", "under_5_deg", "under_10_deg", "under_20_deg"} <= set(s)
    assert summary["windows_skipped_filling"] == 14
    assert (summary["frames"], summary["frames_bad_exposure"], summary["frames_without_heading"]) == (24, 2, 0)
    assert summary["records_skipped_corrupt"] == 0  # undamaged logs: said, as 0
    worst = summary["worst_logs"]["transformer"]
    assert [row["records_skipped_corrupt"] for row in worst] == [0, 0]
    assert sorted(row["log"] for row in worst) == sorted(str(p) for p in logs)
    assert worst[0]["max_deg"] == aggs["transformer"]["max_deg"] and sum(r["n_windows"] for r in worst) == 8
    assert png.stat().st_size > 10_000 and (tmp_path / "eval-tokens.png").stat().st_size > 10_000


@pytest.mark.torch
def test_ctrl_c_keeps_the_windows_evaluated_so_far(tiny_model_dir):
    from estimator.estimator import SunEstimator
    from estimator.evaluate import evaluate
    from estimator.runtime import OnnxModel
    from rig.types import Attitude, Frame, HeadingRef, Intrinsics
    from rig.window import SpreadWindowPolicy

    k = Intrinsics(fx=100.0, fy=100.0, cx=64.0, cy=40.0, width=128, height=80)
    rng = np.random.default_rng(1)

    def drive(n, ctrl_c_after=None):
        for i in range(n):
            if i == ctrl_c_after:
                raise KeyboardInterrupt  # as Ctrl-C arrives: anywhere in the second log
            yield Frame(t_mono_s=0.1 * i, seq=i, image_bgr=rng.integers(0, 256, (80, 128, 3), np.uint8),
                        intrinsics=k, attitude=Attitude(math.radians(7.0 * i), HeadingRef.TRUE),
                        sun_enu_truth=[0.0, 0.8, 0.6])

    estimator = SunEstimator(OnnxModel.load(tiny_model_dir))
    seen = []
    result = evaluate([("d0", drive(12)), ("d1", drive(12, ctrl_c_after=10)), ("d2", drive(12))], estimator,
                      SpreadWindowPolicy(8, 4.0), progress=lambda w, logs: seen.append((w, logs)))
    assert result.interrupted and result.logs == ["d0", "d1"]  # d2 never started
    # 5 whole windows of d0; of d1 the one of its first batch of 8 frames (offline encodes in
    # batches of 8, and the Ctrl-C came while frames 8 and 9 waited for theirs). Every list alike.
    assert len(result.window_logs) == 6 and result.window_logs.count("d1") == 1
    assert all(len(v) == 6 for d in (result.errors_deg, result.flags, result.elevation_deg) for v in d.values())
    assert len(result.truth_elevation_deg) == 6 and result.frames == 22  # d1's 10 frames counted too
    assert result.window_seqs == [7, 8, 9, 10, 11, 7]  # each window's newest frame
    s = result.summary()
    assert s["interrupted"] is True and s["aggregators"]["transformer"]["n_windows"] == 6
    assert seen[-1] == (6, 1) and (5, 1) in seen  # windows and logs done, as the CLI's progress shows them
    # The plot's sample windows: the first full window of each log, so the figure shows each sky once.
    assert [(log, next(iter(w.values())).seq) for log, w in result.samples] == [("d0", 7), ("d1", 7)]
    # The true sun is [0, 0.8, 0.6] (east, north, up): 36.87 deg above the horizon, for every window.
    assert result.truth_elevation_deg == pytest.approx([math.degrees(math.asin(0.6))] * 6)



@pytest.mark.torch
def test_windows_without_a_true_heading_are_counted_not_graded(tiny_model_dir):
    # A drive with a relative heading that still carries a true-north truth (a synthetic drive
    # recorded with visual odometry): its windows have no truth, so they are counted, not graded.
    from estimator.estimator import SunEstimator
    from estimator.evaluate import evaluate
    from estimator.runtime import OnnxModel
    from rig.window import SpreadWindowPolicy

    estimator = SunEstimator(OnnxModel.load(tiny_model_dir))
    result = evaluate([("rel", noise_drive(10, HeadingRef.RELATIVE)), ("true", noise_drive(10))], estimator,
                      SpreadWindowPolicy(8, 4.0), aggregators=["transformer"])
    # Full windows from the 8th frame on: 3 per drive. Only the TRUE drive's are graded.
    assert result.windows_without_truth == 3 and result.window_logs == ["true"] * 3
    assert len(result.errors_deg["transformer"]) == 3 and len(result.truth_elevation_deg) == 3


@pytest.mark.torch
def test_the_records_a_damaged_log_lost_are_counted_per_log_and_once_per_pass(tmp_path, monkeypatch,
                                                                               tiny_model_dir):
    # The readers skip a damaged record with a warning on stderr; the evaluation must count it too,
    # or a figure computed over a damaged log reads as one over a whole log. Evaluated twice (as
    # with two crop seeds) and pooled, each pass counts its own damage, once.
    import replay.native
    from estimator.estimator import SunEstimator
    from estimator.evaluate import evaluate
    from estimator.runtime import OnnxModel
    from replay.native import LogWriter
    from replay.sources import open_frames
    from rig.window import SpreadWindowPolicy
    from tests.test_kitti import DRIVE, make_drive

    def write(path, bad_seq=None):
        with LogWriter(path) as w:
            for f in noise_drive(12):
                if f.seq == bad_seq:  # its image message does not decode: that frame is lost
                    monkeypatch.setattr(replay.native, "encode_image", lambda *a, **k: b"not an image message")
                w.write_frame(f)
                monkeypatch.undo()
        return path

    damaged, whole = write(tmp_path / "damaged.mcap", bad_seq=9), write(tmp_path / "whole.mcap")
    date = make_drive(tmp_path / "kitti", 12)
    (date / DRIVE / "image_02" / "data" / "0000000003.png").write_bytes(b"not a png")
    sources = [("damaged", open_frames(damaged)), ("kitti", open_frames(date, utc_offset_h=2.0)),
               ("whole", open_frames(whole))]
    estimator, policy = SunEstimator(OnnxModel.load(tiny_model_dir)), SpreadWindowPolicy(8, 4.0)
    result = evaluate(sources, estimator, policy, aggregators=["mean"])
    assert result.frames == 11 + 11 + 12
    assert result.records_skipped_corrupt == 2
    assert result.records_skipped_corrupt_by_log == {"damaged": 1, "kitti": 1, "whole": 0}
    assert {r["log"]: r["records_skipped_corrupt"] for r in result.by_log("mean")} == {
        "damaged": 1, "kitti": 1, "whole": 0}
    result.extend(evaluate(sources, estimator, policy, aggregators=["mean"]))  # the same sources, read again
    assert result.summary()["records_skipped_corrupt"] == 4
    assert result.records_skipped_corrupt_by_log == {"damaged": 2, "kitti": 2, "whole": 0}


def test_a_window_cut_short_is_trimmed_from_every_list():
    # Ctrl-C between two appends of one window: window_logs (appended last) says what is whole.
    r = EvalResult(errors_deg={"transformer": [1.0, 2.0, 3.0], "mean": [1.0, 2.0]},
                   flags={"transformer": [1, 1, 1], "mean": [1, 1]}, elevation_deg={"transformer": [5.0, 6.0, 7.0]},
                   truth_elevation_deg=[5.0, 6.0], window_logs=["d0", "d0"])
    r.trim_to_whole_windows()
    assert r.errors_deg == {"transformer": [1.0, 2.0], "mean": [1.0, 2.0]}
    assert r.flags["transformer"] == [1, 1] and r.elevation_deg["transformer"] == [5.0, 6.0]


def test_a_valid_window_past_the_target_is_not_counted_as_flagged():
    # windows_over_30_deg_not_valid counts the tail the status flags caught; a window the controller
    # was told to trust (valid) at 35 deg is the tail they missed, and shows in valid_max_deg instead.
    r = EvalResult(errors_deg={"transformer": [35.0, 40.0, 2.0, 50.0]},
                   flags={"transformer": [FLAG_VALID, FLAG_ABOVE_TRAINED, FLAG_VALID, FLAG_SPREAD_HIGH]},
                   window_logs=["d0"] * 4)
    status = r.summary()["status"]["transformer"]
    assert status["windows_over_30_deg_not_valid"] == 2
    assert status["valid_max_deg"] == 35.0 and status["valid_windows"] == 2
    assert status["above_trained"] == 1 and status["spread_high"] == 1


def test_pooling_an_interrupted_evaluation_marks_the_pool_interrupted():
    # Seeds pooled with one cut short by Ctrl-C: the pooled figures cover fewer windows than asked,
    # and the summary must say so.
    whole, cut = EvalResult(), EvalResult(interrupted=True)
    whole.extend(cut)
    assert whole.interrupted and whole.summary()["interrupted"] is True
    assert "interrupted" not in EvalResult().summary()


def test_trimming_also_cuts_the_true_elevations():
    # The true elevation is appended per window before window_logs: a Ctrl-C between the two
    # leaves one too many, which the elevation plots would pair with the wrong window.
    r = EvalResult(errors_deg={"transformer": [1.0, 2.0]}, flags={"transformer": [1, 1]},
                   elevation_deg={"transformer": [5.0, 6.0]}, truth_elevation_deg=[5.0, 6.0, 7.0],
                   window_logs=["d0", "d0"])
    r.trim_to_whole_windows()
    assert r.truth_elevation_deg == [5.0, 6.0]


def test_windows_grouped_by_their_newest_frame_pool_logs_and_seeds():
    a = EvalResult(errors_deg={"transformer": [40.0, 2.0, 10.0]}, window_seqs=[7, 8, 7], window_logs=["d0", "d0", "d1"])
    a.extend(EvalResult(errors_deg={"transformer": [20.0, 4.0]}, window_seqs=[7, 9], window_logs=["d0", "d0"]))
    rows = a.by_newest_frame("transformer")
    assert [r["newest_seq"] for r in rows] == [7, 8, 9]
    assert rows[0]["n_windows"] == 3 and rows[0]["mean_deg"] == pytest.approx(70.0 / 3)
    assert rows[0]["max_deg"] == 40.0 and rows[0]["windows_over_30_deg"] == 1
    assert rows[2]["mean_deg"] == 4.0 and rows[2]["windows_over_30_deg"] == 0
    with pytest.raises(ValueError, match="2 window errors but 1 window seqs"):
        EvalResult(errors_deg={"transformer": [1.0, 2.0]}, window_seqs=[7]).by_newest_frame("transformer")


def test_trimming_also_cuts_the_newest_frames():
    r = EvalResult(errors_deg={"transformer": [1.0, 2.0]}, window_seqs=[7, 8, 9], window_logs=["d0", "d0"])
    r.trim_to_whole_windows()
    assert r.window_seqs == [7, 8]


@pytest.mark.torch
def test_a_given_status_rule_decides_the_flags(tiny_model_dir):
    # evaluate(status_rule=...) scores windows by the rule given (e.g. a stricter one being tried),
    # not by the model's own: with a full window of 99 frames asked, no 8-frame window is valid.
    from estimator.estimator import SunEstimator
    from estimator.evaluate import evaluate
    from estimator.runtime import OnnxModel
    from rig.protocol import FLAG_PARTIAL_WINDOW, StatusRule
    from rig.window import SpreadWindowPolicy

    frames = noise_drive(8)
    # A second log without the true sun: its full window is counted, not scored.
    untrue = [dataclasses.replace(f, sun_enu_truth=None) for f in frames]
    result = evaluate([("d0", frames), ("d1", untrue)], SunEstimator(OnnxModel.load(tiny_model_dir)),
                      SpreadWindowPolicy(8, 4.0), aggregators=["mean"], status_rule=StatusRule(full_window=99))
    assert len(result.flags["mean"]) == 1 and result.windows_without_truth == 1
    assert result.flags["mean"][0] & FLAG_PARTIAL_WINDOW and not result.flags["mean"][0] & FLAG_VALID


def test_share_under_a_threshold_leaves_out_a_window_exactly_at_it():
    # "Under 5 deg" is strict, as the tail count is (30.0 is on target, not past it): a window at
    # exactly 5, 10 or 20 deg does not count as under that threshold.
    s = error_summary([5.0, 10.0, 20.0, 1.0])
    assert s["under_5_deg"] == pytest.approx(0.25)  # only the 1.0
    assert s["under_10_deg"] == pytest.approx(0.5)  # 1.0 and 5.0
    assert s["under_20_deg"] == pytest.approx(0.75)  # all but the 20.0


def test_a_flagged_window_exactly_at_the_target_is_not_in_the_caught_tail():
    # windows_over_30_deg_not_valid counts as windows_over_30_deg does: past 30 deg, not at it.
    r = EvalResult(errors_deg={"transformer": [30.0, 30.5, 1.0]},
                   flags={"transformer": [FLAG_SPREAD_HIGH, FLAG_SPREAD_HIGH, FLAG_VALID]}, window_logs=["d0"] * 3)
    s = r.summary()
    assert s["aggregators"]["transformer"]["windows_over_30_deg"] == 1
    assert s["status"]["transformer"]["windows_over_30_deg_not_valid"] == 1


def test_pooling_keeps_each_windows_true_elevation_with_its_answer():
    # bench_accuracy pairs pooled elevation_deg with pooled truth_elevation_deg window by window
    # (how far above the truth the answer lies): both must grow together when seeds are pooled.
    a = EvalResult(errors_deg={"transformer": [1.0]}, flags={"transformer": [FLAG_VALID]},
                   elevation_deg={"transformer": [40.0]}, truth_elevation_deg=[38.0], window_logs=["d0"])
    b = EvalResult(errors_deg={"transformer": [2.0, 3.0]}, flags={"transformer": [FLAG_VALID, FLAG_VALID]},
                   elevation_deg={"transformer": [41.0, 60.0]}, truth_elevation_deg=[38.5, 52.0],
                   window_logs=["d0", "d1"])
    a.extend(b)
    assert a.elevation_deg["transformer"] == [40.0, 41.0, 60.0]
    assert a.truth_elevation_deg == [38.0, 38.5, 52.0]
    assert a.window_logs == ["d0", "d0", "d1"]


@pytest.mark.torch
def test_ctrl_c_inside_a_window_leaves_no_half_window(tiny_model_dir):
    # A Ctrl-C can arrive while a window is being scored, after its error is appended for one
    # aggregator but before its flags, elevations and log are: evaluate() must trim that half
    # window, or the summary pairs errors with the wrong windows (by_log refuses the mismatch).
    from estimator.estimator import SunEstimator
    from estimator.evaluate import evaluate
    from estimator.runtime import OnnxModel
    from rig.protocol import StatusRule
    from rig.window import SpreadWindowPolicy

    class CtrlCOnThirdFlags:
        def __init__(self):
            self.rule, self.calls = StatusRule(), 0

        def flags(self, est):
            self.calls += 1
            if self.calls == 3:  # the second full window, its first aggregator
                raise KeyboardInterrupt
            return self.rule.flags(est)

    result = evaluate([("d0", noise_drive(12))], SunEstimator(OnnxModel.load(tiny_model_dir)),
                      SpreadWindowPolicy(8, 4.0), aggregators=["mean", "single"], status_rule=CtrlCOnThirdFlags())
    assert result.interrupted and result.window_logs == ["d0"]
    for per_agg in (result.errors_deg, result.flags, result.elevation_deg):
        assert {name: len(v) for name, v in per_agg.items()} == {"mean": 1, "single": 1}
    assert len(result.truth_elevation_deg) == 1
    assert result.summary()["aggregators"]["mean"]["n_windows"] == 1


@pytest.mark.torch
def test_frames_a_misbehaving_clock_cost_are_counted(tiny_model_dir):
    # One frame stamped 0.5 s ahead (late by no more than 1 s, so not a jump): the 4 frames after
    # it that are older are left out, as live. eval once counted them nowhere, its JSON saying only
    # "frames: 40" beside 10 graded windows. A stamp an hour ahead is a clock jump (the frames
    # after it start the windows again, once), counted too.
    from estimator.estimator import SunEstimator
    from estimator.evaluate import evaluate
    from estimator.runtime import OnnxModel
    from rig.window import SpreadWindowPolicy

    ahead = [dataclasses.replace(f, t_mono_s=f.t_mono_s + 0.5) if f.seq == 10 else f for f in noise_drive(40)]
    jump = [dataclasses.replace(f, t_mono_s=3600.0) if f.seq == 10 else f for f in noise_drive(40)]
    result = evaluate([("ahead", ahead), ("jump", jump)], SunEstimator(OnnxModel.load(tiny_model_dir)),
                      SpreadWindowPolicy(8, 4.0), aggregators=["transformer"])
    summary = result.summary()
    assert summary["frames"] == 80 and summary["frames_out_of_order"] == 4 and summary["clock_jumps"] == 1


def _plotted_result(interrupted: bool = False) -> EvalResult:
    """Two graded windows of one log, one of them sampled for the per-token figure."""
    from rig.types import SunEstimate

    est = SunEstimate(t_mono_s=1.0, seq=7, sun_enu=np.array([0.0, 0.8, 0.6]), heading_rad=0.0,
                      heading_ref=HeadingRef.TRUE, spread_rad=0.1, n_frames=8, n_tokens=4, aggregator="mean",
                      truth_enu=np.array([0.0, 0.6, 0.8]), token_enu=np.array([[0.0, 0.8, 0.6]] * 4))
    return EvalResult(errors_deg={"mean": [3.0, 14.0]}, flags={"mean": [FLAG_VALID] * 2},
                      samples=[("d0.mcap", {"mean": est})], logs=["d0.mcap"], window_logs=["d0.mcap"] * 2,
                      window_seqs=[7, 8], interrupted=interrupted)


@pytest.mark.parametrize("failing", ["eval.png", "eval-tokens.png"])
def test_a_figure_cut_short_by_a_full_disk_leaves_the_one_that_was_there(tmp_path, monkeypatch, failing):
    # savefig wrote in place: a full disk mid-write left a torn PNG under the name asked for, which
    # reads as the figure of the run; a previous run's figure there was lost too.
    import errno

    from matplotlib.figure import Figure

    from estimator.evaluate import plot_eval

    real_savefig = Figure.savefig

    # FAKE full disk (no disk here can be filled): the save of the figure `failing` (under the name
    # asked for or a hidden sibling's) writes a few bytes and fails as on a full disk. (A comment, not
    # a docstring: matplotlib refuses a savefig with a docstring of its own.)
    def disk_full_on(self, fname, *args, **kwargs):
        if Path(fname).name.replace(".tmp", "").lstrip(".") == failing:
            Path(fname).write_bytes(b"\x89PNG torn")
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_savefig(self, fname, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", disk_full_on)
    (tmp_path / failing).write_bytes(b"the previous run's figure")
    with pytest.raises(OSError, match="No space left on device") as caught:
        plot_eval(_plotted_result(), tmp_path / "eval.png")
    assert caught.value.filename == str(tmp_path / failing)  # the user's name, not a hidden sibling's
    assert (tmp_path / failing).read_bytes() == b"the previous run's figure"
    assert not [p.name for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_the_figure_of_an_interrupted_evaluation_says_so(tmp_path, monkeypatch):
    # The JSON of a Ctrl-C'd run says "interrupted": true; its figure was titled as a whole run's,
    # "cumulative angular error, 2 windows", and read later as the figure of every log.
    from matplotlib.axes import Axes

    from estimator.evaluate import plot_eval

    titles: list[str] = []
    real_set_title = Axes.set_title

    def recorded(self, label, *args, **kwargs):
        titles.append(label)
        return real_set_title(self, label, *args, **kwargs)

    monkeypatch.setattr(Axes, "set_title", recorded)
    plot_eval(_plotted_result(interrupted=True), tmp_path / "eval.png")
    assert titles[0] == "cumulative angular error, 2 windows (interrupted: 1 log begun)"
    titles.clear()
    plot_eval(_plotted_result(), tmp_path / "eval.png")
    assert titles[0] == "cumulative angular error, 2 windows"


@pytest.mark.torch
def test_a_log_of_which_no_window_was_graded_is_named_with_why(tiny_model_dir):
    # A log without the true sun (or shorter than a window) among logs with it: its windows were
    # left out unsaid, the figures reading as the figures of every log given.
    from estimator.estimator import SunEstimator
    from estimator.evaluate import evaluate
    from estimator.runtime import OnnxModel
    from rig.window import SpreadWindowPolicy

    no_truth = [dataclasses.replace(f, sun_enu_truth=None) for f in noise_drive(12)]
    no_heading = [dataclasses.replace(f, attitude=None) for f in noise_drive(12)]
    slow = [dataclasses.replace(f, t_mono_s=1.0 * f.seq) for f in noise_drive(12)]
    result = evaluate([("graded", noise_drive(12)), ("no_truth", no_truth), ("short", noise_drive(5)),
                       ("no_heading", no_heading), ("slow", slow)],
                      SunEstimator(OnnxModel.load(tiny_model_dir)), SpreadWindowPolicy(8, 4.0), aggregators=["mean"])
    assert result.window_logs == ["graded"] * 5
    assert result.summary()["logs_not_graded"] == {
        "no_truth": "its 5 full windows have no true sun: 12 of its 12 frames have a TRUE heading and no GNSS fix "
                    "(the true sun needs the place and UTC: record with a GNSS, docs/ground-truth.md)",
        "short": "it has 5 frames, fewer than a window's 8",
        "no_heading": "12 of its 12 frames have no heading",
        "slow": "no 8 of its 12 frames are within 4 s of each other",
    }


def test_why_frames_have_no_true_sun_names_what_each_lacks_and_what_to_record():
    # A drive recorded with a compass and no GNSS fix was left out of eval and train saying only
    # that it had "no true sun" (or "no frame with both a TRUE heading and the true sun"), which
    # neither says what is missing nor what to record.
    from estimator.evaluate import TruthTally

    tally = TruthTally()
    drive = noise_drive(10)
    frames = ([dataclasses.replace(f, sun_enu_truth=None) for f in drive[:4]]
              + [dataclasses.replace(f, attitude=Attitude(0.0, HeadingRef.RELATIVE), sun_enu_truth=None)
                 for f in drive[4:7]]
              + [dataclasses.replace(f, attitude=Attitude(0.0, HeadingRef.MAGNETIC), sun_enu_truth=None)
                 for f in drive[7:8]]
              + [dataclasses.replace(f, attitude=None) for f in drive[8:9]] + drive[9:])
    assert list(tally.counted(frames)) == frames  # counted as they pass, not held
    assert tally.why() == (
        "4 of its 10 frames have a TRUE heading and no GNSS fix (the true sun needs the place and UTC: record with "
        "a GNSS, docs/ground-truth.md); 3 have a relative heading and 1 a magnetic one (the true sun needs a TRUE "
        "heading: a GNSS compass or INS); 1 has no heading")
    assert TruthTally().why() == "it holds no frames"
