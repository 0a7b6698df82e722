"""benchmarks/bench_crop_draws.py: the model card's finding that the held-out max is a crop lottery
on one window rests on it estimating a window again with nothing but the crop seed changed."""

import argparse
import json
import sys
from pathlib import Path

import pytest

from benchmarks.bench_crop_draws import draw_summary, main, window_arg


def test_window_arg_takes_the_last_colon_as_the_newest_frame():
    assert window_arg("data/val/drive_2500_0194.mcap:6") == (Path("data/val/drive_2500_0194.mcap"), 6)
    assert window_arg("C:/logs/d.mcap:0") == (Path("C:/logs/d.mcap"), 0)
    for bad in ("data/val/d.mcap", "d.mcap:", ":3", "d.mcap:-1", "d.mcap:x"):
        with pytest.raises(argparse.ArgumentTypeError, match="LOG:NEWEST_FRAME"):
            window_arg(bad)


def test_summary_counts_only_errors_strictly_over_30_deg():
    s = draw_summary([10.0, 30.0, 30.5, 50.0], [-10.0, 0.0, 5.0, 20.0], [30.0, 31.0, 32.0, 40.0])
    assert s["n_draws"] == 4 and s["over_30_deg"] == 2
    assert (s["min_deg"], s["max_deg"], s["median_deg"]) == (10.0, 50.0, 30.25)
    assert s["mean_deg"] == pytest.approx(30.125)
    assert s["answer_rel_azimuth_deg"] == {"median": 2.5, "min": -10.0, "max": 20.0}


def test_the_crop_draws_alone_move_a_windows_answer(monkeypatch, capsys):
    from replay.sources import DEMO_LOG

    monkeypatch.setattr(sys, "argv", ["bench_crop_draws.py", "--window", f"{DEMO_LOG}:7", "--crop-seeds", "3",
                                      "--variants", "plain,tiled"])
    main()
    (window,) = json.loads(capsys.readouterr().out)["windows"]
    assert window["frames_seq"] == list(range(8)) and -180 <= window["truth"]["rel_azimuth_deg"] < 180
    plain, tiled = window["runs"]
    assert (plain["variant"], tiled["variant"]) == ("plain", "tiled")
    for run in (plain, tiled):
        assert run["n_draws"] == 3 and 0 <= run["min_deg"] <= run["median_deg"] <= run["max_deg"] < 40
    assert plain["max_deg"] > plain["min_deg"]  # the crops alone change the answer


@pytest.mark.parametrize(("newest", "says"), [(10000, "pick a newest frame in them"), (6, "no full window of 8")])
def test_a_window_the_log_cannot_give_is_a_usage_error(monkeypatch, capsys, newest, says):
    from replay.sources import DEMO_LOG

    monkeypatch.setattr(sys, "argv", ["bench_crop_draws.py", "--window", f"{DEMO_LOG}:{newest}", "--crop-seeds", "1"])
    with pytest.raises(SystemExit) as exc:
        main()
    assert exc.value.code == 2 and says in capsys.readouterr().err


def test_a_window_is_the_frames_the_live_policy_picks():
    """Past the first full window the live policy spreads its frames over the last 4 s, so the
    window ending at a frame is not the 8 frames before it."""
    from benchmarks.bench_crop_draws import window_frames
    from replay.sources import DEMO_LOG, open_frames

    frames = list(open_frames(DEMO_LOG))
    assert [f.seq for f in window_frames(frames, 7, 8)] == [f.seq for f in frames[:8]]
    late = [f.seq for f in window_frames(frames, 30, 8)]
    assert len(late) == 8 and late[-1] == frames[30].seq and late != [f.seq for f in frames[23:31]]
