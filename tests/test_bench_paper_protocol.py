"""benchmarks/bench_paper_protocol.py: the model card's figures under the paper's windows (8 frames
drawn at random from the whole drive) rest on its drawing them as the paper says."""

import json
import sys

import numpy as np
import pytest

from benchmarks.bench_paper_protocol import main, paper_windows


def test_paper_windows_are_distinct_frames_from_the_whole_drive_in_time_order():
    windows = paper_windows(24, 8, np.random.default_rng(0))
    assert len(windows) == 17  # as many as the live policy forms on a drive of 24 frames
    for w in windows:
        assert len(set(w)) == 8 and w == sorted(w) and 0 <= w[0] and w[-1] < 24
    # Drawn from the whole drive, not a run of 8 frames back to back as a drive's first live window.
    assert any(w[-1] - w[0] > 7 for w in windows)
    assert {i for w in windows for i in w} == set(range(24))
    # The same generator state, the same windows; a drive shorter than a window has none.
    assert windows == paper_windows(24, 8, np.random.default_rng(0))
    assert paper_windows(7, 8, np.random.default_rng(0)) == []
    assert len(paper_windows(8, 8, np.random.default_rng(0))) == 1


@pytest.mark.slow
def test_every_aggregator_is_graded_on_the_same_paper_windows(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["bench_paper_protocol.py", "--data", str(tmp_path / "d"), "--drives", "2",
                                      "--frames", "10", "--drive-seed", "7", "--seeds", "0,1"])
    main()
    out = json.loads(capsys.readouterr().out)
    # 2 drives x (10 - 8 + 1) windows x 2 crop seeds, for every aggregator alike.
    assert {a: s["n_windows"] for a, s in out["aggregators"].items()} == dict.fromkeys(
        ("transformer", "mean", "meanshift", "single"), 12)
    assert {s: v["n_windows"] for s, v in out["per_seed"]["transformer"].items()} == {"0": 6, "1": 6}
    t = out["aggregators"]["transformer"]
    assert 0 <= t["median_deg"] <= t["max_deg"] < 180
    assert [r["n_windows"] for r in out["worst_logs"]["transformer"]] == [6, 6]
