"""benchmarks/bench_train.py: seconds per training step (docs/model.md, "Training")."""

import json
import sys

import pytest

from benchmarks import bench_train


def _main(monkeypatch, *args: str) -> None:
    monkeypatch.setattr(sys, "argv", ["bench_train.py", *args])
    bench_train.main()


@pytest.mark.parametrize("bad", [["--drives", "0"], ["--layers", "-1"], ["--steps", "99"]])
def test_options_that_train_nothing_are_usage_errors(bad, monkeypatch, capsys):
    with pytest.raises(SystemExit) as end:
        _main(monkeypatch, *bad)
    assert end.value.code == 2 and bad[0] in capsys.readouterr().err


@pytest.mark.torch
def test_an_unknown_preset_is_a_usage_error_before_any_drive_is_made(monkeypatch, capsys):
    # It was said by train() only, after the drives were rendered.
    pytest.importorskip("torch")
    with pytest.raises(SystemExit) as end:
        _main(monkeypatch, "--preset", "nope")
    assert end.value.code == 2 and "argument --preset" in capsys.readouterr().err


@pytest.mark.torch
@pytest.mark.slow
def test_the_json_says_the_steps_and_drives_it_trained_on(monkeypatch, capsys):
    pytest.importorskip("torch")
    _main(monkeypatch, "--preset", "tiny", "--drives", "1", "--steps", "100")
    out = json.loads(capsys.readouterr().out)
    assert (out["steps"], out["drives"]) == (100, 1)
    assert {p: r["steps_timed"] for p, r in out["results"].items()} == {"fp32": 50, "bf16": 50}
