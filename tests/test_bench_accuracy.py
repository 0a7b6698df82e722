"""benchmarks/bench_accuracy.py: the model card's accuracy tables are its JSON; the JSON and the
figures it writes must say which drives they are of."""

import json
import sys

import pytest

from benchmarks import bench_accuracy


def _main(monkeypatch, *args: str) -> None:
    monkeypatch.setattr(sys, "argv", ["bench_accuracy.py", *args])
    bench_accuracy.main()


@pytest.mark.slow
def test_the_figures_go_beside_the_drives_measured_and_the_json_names_both(tmp_path, monkeypatch, capsys):
    # The documented validation run (--data data/val) wrote its figures over data/heldout-eval.png,
    # the held-out set's, whatever --data said.
    monkeypatch.chdir(tmp_path)
    _main(monkeypatch, "--data", str(tmp_path / "val"), "--drives", "1", "--frames", "8", "--seeds", "0")
    out = json.loads(capsys.readouterr().out)
    assert (tmp_path / "val-eval.png").is_file() and not (tmp_path / "data").exists()
    assert out["data_dir"] == str(tmp_path / "val") and out["plot"] == str(tmp_path / "val-eval.png")


def test_a_plot_that_cannot_be_written_is_refused_before_any_drive_is_made(tmp_path, monkeypatch):
    (tmp_path / "file").write_text("")
    from rig.errors import SunrigError

    with pytest.raises(SunrigError, match="--plot"):
        _main(monkeypatch, "--data", str(tmp_path / "d"), "--drives", "1", "--frames", "8",
              "--plot", str(tmp_path / "file" / "x.png"))
    assert not (tmp_path / "d").exists()
