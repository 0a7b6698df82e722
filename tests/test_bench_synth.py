"""benchmarks/bench_synth.py: the synthetic generator's speed."""

import sys

import pytest

from benchmarks import bench_synth


@pytest.mark.parametrize("bad", [["--frames", "0"], ["--repeats", "0"], ["--render-scale", "0"],
                                 ["--render-scale", "1.5"], ["--scale", "-1"], ["--scale", "0.001"],
                                 ["--threads", "-5"]])
def test_options_that_measure_nothing_are_usage_errors(bad, monkeypatch, capsys):
    # --frames 0 and --repeats 0 were tracebacks; --scale -1 or 0.001 timed 1 x 1 px frames and
    # --render-scale 0 a 0 x 0 render, each printed as a speed.
    monkeypatch.setattr(sys, "argv", ["bench_synth.py", *bad])
    with pytest.raises(SystemExit) as end:
        bench_synth.main()
    assert end.value.code == 2 and f"argument {bad[0]}" in capsys.readouterr().err
