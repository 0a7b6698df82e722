"""benchmarks/common.py: what every benchmark shares, its timing figures, its options and how it
ends on bad input or a Ctrl-C (one line and a non-zero exit, no traceback)."""

import argparse
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import common

REPO = Path(__file__).resolve().parent.parent


def test_time_ms_quantiles_lie_within_the_samples_timed(monkeypatch):
    # Three runs of 10, 20 and 30 ms: statistics.quantiles' default method extrapolates beyond the
    # samples, which gave a p10 under the fastest run and a p90 over the slowest.
    ticks = iter([0.0, 0.010, 0.0, 0.020, 0.0, 0.030])
    monkeypatch.setattr(common.time, "perf_counter", lambda: next(ticks))
    t = common.time_ms(lambda: None, repeats=3, warmup=0)
    assert t["min_ms"] == pytest.approx(10.0) and t["median_ms"] == pytest.approx(20.0)
    assert 10.0 <= t["p10_ms"] <= t["median_ms"] <= t["p90_ms"] <= 30.0


def test_a_users_mistake_ends_the_benchmark_in_one_line_and_exit_2(monkeypatch, capsys):
    from rig.errors import ModelError

    def main():
        raise ModelError("model folder 'x' does not exist; pass the folder that holds backbone.onnx")

    monkeypatch.setattr(sys, "argv", ["benchmarks/bench_x.py"])
    with pytest.raises(SystemExit) as end:
        common.run(main)
    assert end.value.code == 2
    err = capsys.readouterr().err
    assert err == "bench_x: error: model folder 'x' does not exist; pass the folder that holds backbone.onnx\n"


def test_a_ctrl_c_ends_the_benchmark_in_one_line_and_exit_130(monkeypatch, capsys):
    def main():
        raise KeyboardInterrupt

    monkeypatch.setattr(sys, "argv", ["benchmarks/bench_x.py"])
    with pytest.raises(SystemExit) as end:
        common.run(main)
    assert end.value.code == 130
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and "interrupted" in err


@pytest.mark.parametrize("bad", [["--drives", "0"], ["--drives", "-3"], ["--frames", "0"], ["--frames", "x"],
                                 ["--drives", "100001"], ["--frames", "5001"]])
def test_drive_options_out_of_range_are_refused_as_usage_errors(bad, capsys):
    ap = argparse.ArgumentParser(prog="bench_x")
    common.add_drive_args(ap, data="d", drives=1, drive_seed=1, drive_seed_help="")
    with pytest.raises(SystemExit) as end:
        ap.parse_args(bad)
    assert end.value.code == 2
    assert f"argument {bad[0]}" in capsys.readouterr().err


def _bench(name: str, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "benchmarks" / name), *args], capture_output=True, text=True,
                          timeout=120)


def test_a_wrong_model_is_one_line_before_any_drive_is_made(tmp_path):
    run = _bench("bench_accuracy.py", "--model", str(tmp_path / "nope"), "--data", str(tmp_path / "d"),
                 "--drives", "1", "--frames", "8")
    assert run.returncode == 2 and run.stdout == ""
    assert run.stderr.count("\n") == 1 and "does not exist" in run.stderr and "Traceback" not in run.stderr
    assert not (tmp_path / "d").exists()


def test_drives_shorter_than_a_window_are_refused_before_any_is_made(tmp_path):
    # 5 frames make no full window of the shipped model's 8: every figure was of nothing, and the
    # benchmark died formatting a mean of None after rendering the drives.
    run = _bench("bench_paper_protocol.py", "--data", str(tmp_path / "d"), "--drives", "1", "--frames", "5")
    assert run.returncode == 2 and run.stdout == ""
    assert run.stderr.count("\n") == 1 and "--frames 5" in run.stderr and "Traceback" not in run.stderr
    assert not (tmp_path / "d").exists()


def test_float_in_takes_finite_numbers_in_its_range_only():
    above_0, from_0_to_60 = common.float_in(0.0), common.float_in(0.0, 60.0, lo_included=True)
    assert above_0("0.5") == 0.5 and from_0_to_60("0") == 0.0 and from_0_to_60("60") == 60.0
    for parse, bad in ((above_0, "0"), (above_0, "nan"), (above_0, "inf"), (above_0, "x"), (from_0_to_60, "-0.1"),
                       (from_0_to_60, "60.5")):
        with pytest.raises(argparse.ArgumentTypeError, match="expected a finite number"):
            parse(bad)


def test_every_benchmarks_help_opens_with_a_whole_sentence():
    # `--help` shows the docstring's first line as the description: one cut mid-sentence read
    # "does the rig's memory," and stopped.
    import ast
    for path in sorted((Path(common.__file__).parent).glob("bench_*.py")):
        first = (ast.get_docstring(ast.parse(path.read_text()), clean=False) or "").splitlines()[0]
        assert first.rstrip().endswith((".", "?")), f"{path.name}: {first!r}"
