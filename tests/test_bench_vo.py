"""benchmarks/bench_vo.py's heading error, which the drift table in docs/drivers.md quotes: it
counts from each epoch's zero, since visual odometry starts again at 0 where it cannot carry its
heading over a loss."""

import math
import sys

import pytest

from benchmarks.bench_vo import epoch_zeros, heading_errors_deg, main


def test_each_frame_counts_from_the_first_frame_of_its_epoch():
    assert epoch_zeros([0, 0, 0, 1, 1, 2]) == [0, 0, 0, 3, 3, 5]
    assert epoch_zeros([3, 3]) == [0, 0]  # an odometry that had already restarted: one epoch


def test_a_new_epoch_is_measured_against_the_true_turn_since_its_own_zero():
    # The vehicle turns 10 deg a frame; the odometry loses frame 2, which is the zero of a new epoch
    # (heading 0 there, not reported), and goes on from it.
    truth = [math.radians(10.0 * k) for k in range(5)]
    estimate = [0.0, math.radians(11.0), None, math.radians(10.5), math.radians(19.0)]
    zeros = epoch_zeros([0, 0, 1, 1, 1])
    assert zeros == [0, 0, 2, 2, 2]
    errors = heading_errors_deg(truth, estimate, zeros)
    assert errors == [pytest.approx(0.0), pytest.approx(1.0), None, pytest.approx(0.5), pytest.approx(-1.0)]
    # Counted from the first frame instead, the restart looks like a 20 deg error.
    assert heading_errors_deg(truth, estimate)[3] == pytest.approx(-19.5)


@pytest.mark.parametrize("bad", [["--drives", "0"], ["--frames", "1"], ["--repeats", "0"], ["--substeps", "0"],
                                 ["--scale", "0"], ["--scale", "-1"], ["--threads", "-5"]])
def test_options_that_measure_nothing_are_usage_errors(bad, monkeypatch, capsys):
    # Each was a traceback (IndexError, ZeroDivisionError, StatisticsError), or, for --scale 0, a
    # drift figure measured on 1 x 1 px images.
    monkeypatch.setattr(sys, "argv", ["bench_vo.py", *bad])
    with pytest.raises(SystemExit) as end:
        main()
    assert end.value.code == 2 and f"argument {bad[0]}" in capsys.readouterr().err


def test_an_out_that_cannot_be_written_is_refused_before_the_drives_are_rendered(tmp_path, monkeypatch):
    from rig.errors import SunrigError

    monkeypatch.setattr(sys, "argv", ["bench_vo.py", "--out", str(tmp_path / "no" / "vo.json")])
    with pytest.raises(SunrigError, match="--out"):
        main()
