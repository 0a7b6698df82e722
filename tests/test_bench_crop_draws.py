"""benchmarks/bench_crop_draws.py: the model card's finding that the held-out max is a crop lottery
on one window rests on it estimating a window again with nothing but the crop seed changed."""

import argparse
import json
import sys
from pathlib import Path

import pytest

from benchmarks.bench_crop_draws import draw_summary, main, window_arg


def test_window_arg_takes_the_last_colon_as_the_first_frame():
    assert window_arg("data/val/drive_2500_0194.mcap:6") == (Path("data/val/drive_2500_0194.mcap"), 6)
    assert window_arg("C:/logs/d.mcap:0") == (Path("C:/logs/d.mcap"), 0)
    for bad in ("data/val/d.mcap", "d.mcap:", ":3", "d.mcap:-1", "d.mcap:x"):
        with pytest.raises(argparse.ArgumentTypeError, match="LOG:FIRST_FRAME"):
            window_arg(bad)


def test_summary_counts_only_errors_strictly_over_30_deg():
    s = draw_summary([10.0, 30.0, 30.5, 50.0], [-10.0, 0.0, 5.0, 20.0], [30.0, 31.0, 32.0, 40.0])
    assert s["n_draws"] == 4 and s["over_30_deg"] == 2
    assert (s["min_deg"], s["max_deg"], s["median_deg"]) == (10.0, 50.0, 30.25)
    assert s["mean_deg"] == pytest.approx(30.125)
    assert s["answer_rel_azimuth_deg"] == {"median": 2.5, "min": -10.0, "max": 20.0}


def test_the_crop_draws_alone_move_a_windows_answer(monkeypatch, capsys):
    from replay.sources import DEMO_LOG

    monkeypatch.setattr(sys, "argv", ["bench_crop_draws.py", "--window", f"{DEMO_LOG}:0", "--crop-seeds", "3",
                                      "--variants", "plain,tiled"])
    main()
    (window,) = json.loads(capsys.readouterr().out)["windows"]
    assert window["frames"] == 8 and -180 <= window["truth"]["rel_azimuth_deg"] < 180
    plain, tiled = window["runs"]
    assert (plain["variant"], tiled["variant"]) == ("plain", "tiled")
    for run in (plain, tiled):
        assert run["n_draws"] == 3 and 0 <= run["min_deg"] <= run["median_deg"] <= run["max_deg"] < 40
    assert plain["max_deg"] > plain["min_deg"]  # the crops alone change the answer


def test_a_window_past_the_end_of_the_log_is_a_usage_error(monkeypatch, capsys):
    from replay.sources import DEMO_LOG

    monkeypatch.setattr(sys, "argv", ["bench_crop_draws.py", "--window", f"{DEMO_LOG}:10000", "--crop-seeds", "1"])
    with pytest.raises(SystemExit) as exc:
        main()
    assert exc.value.code == 2 and "pick an earlier first frame" in capsys.readouterr().err
