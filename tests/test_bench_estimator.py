"""benchmarks/bench_estimator.py: the per-frame costs in docs/model.md (float32 and int8 by preset)."""

import json
import sys

import pytest

from benchmarks import bench_estimator


def _main(monkeypatch, *args: str) -> None:
    monkeypatch.setattr(sys, "argv", ["bench_estimator.py", *args])
    bench_estimator.main()


@pytest.mark.parametrize("bad", [["--presets", "nope"], ["--presets", ","], ["--repeats", "0"],
                                 ["--threads", "-1"]])
def test_options_that_measure_nothing_are_usage_errors(bad, monkeypatch, capsys):
    # Each was a traceback (KeyError, StatisticsError, ValidationError), the first two after torch loaded.
    with pytest.raises(SystemExit) as end:
        _main(monkeypatch, *bad)
    assert end.value.code == 2 and f"argument {bad[0]}" in capsys.readouterr().err


@pytest.mark.torch
@pytest.mark.slow
def test_the_json_says_the_threads_and_repeats_measured_with(monkeypatch, capsys):
    pytest.importorskip("torch")
    _main(monkeypatch, "--presets", "tiny", "--repeats", "2", "--threads", "1")
    out = json.loads(capsys.readouterr().out)
    assert out["intra_op_threads"] == 1 and out["repeats"] == 2 and list(out["results"]) == ["tiny"]
    assert out["results"]["tiny"]["frame_encode"]["repeats"] == 2
