"""benchmarks/bench_sun_sweep.py: one drive rendered again with the sun turned (docs/model.md)."""

import sys

import pytest

from benchmarks.bench_sun_sweep import main
from rig.errors import SunrigError


def test_drives_shorter_than_a_window_are_refused_before_they_are_rendered(monkeypatch):
    # --frames 5 made no full window: numpy's "zero-size array" ValueError after the first render.
    monkeypatch.setattr(sys, "argv", ["bench_sun_sweep.py", "--frames", "5", "--frame", "1"])
    with pytest.raises(SunrigError, match="--frames 5"):
        main()


@pytest.mark.parametrize("bad", [["--index", "-1"], ["--frames", "0"]])
def test_an_index_or_frames_out_of_range_are_usage_errors(bad, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["bench_sun_sweep.py", *bad])
    with pytest.raises(SystemExit) as end:
        main()
    assert end.value.code == 2 and f"argument {bad[0]}" in capsys.readouterr().err
