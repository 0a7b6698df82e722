"""benchmarks/bench_soak.py: the long-run figures in docs/architecture.md come from it; a run
stopped early must leave nothing behind, and its JSON must name the model it ran."""

import sys
import tempfile

import pytest

from benchmarks import bench_soak
from rig.errors import SunrigError


def _main(monkeypatch, *args: str) -> None:
    monkeypatch.setattr(sys, "argv", ["bench_soak.py", *args])
    bench_soak.main()


@pytest.mark.parametrize("minutes", ["0", "-1", "nan"])
def test_minutes_that_are_no_run_are_a_usage_error(minutes, monkeypatch):
    with pytest.raises(SystemExit) as end:
        _main(monkeypatch, "--minutes", minutes)
    assert end.value.code == 2


def test_a_wrong_model_is_refused_before_the_rig_and_its_folder(tmp_path, monkeypatch):
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    with pytest.raises(SunrigError, match="does not exist"):
        _main(monkeypatch, "--model", str(tmp_path / "nope"))
    assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_ctrl_c_stops_the_rig_and_removes_its_folder(tmp_path, monkeypatch):
    # Interrupted, the run kept its temporary folder (a partial recording and JSONL) in /tmp.
    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    started = []

    def interrupt(pid):
        started.append(pid)
        raise KeyboardInterrupt

    monkeypatch.setattr(bench_soak, "sample", interrupt)
    with pytest.raises(KeyboardInterrupt):
        _main(monkeypatch, "--minutes", "1")
    assert started and list(tmp_path.iterdir()) == []
    with pytest.raises(ProcessLookupError):
        import os

        os.kill(started[0], 0)
