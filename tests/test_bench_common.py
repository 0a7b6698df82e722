"""benchmarks/common.py: what every benchmark shares, its timing figures, its options and how it
ends on bad input or a Ctrl-C (one line and a non-zero exit, no traceback)."""

import pytest

from benchmarks import common


def test_time_ms_quantiles_lie_within_the_samples_timed(monkeypatch):
    # Three runs of 10, 20 and 30 ms: statistics.quantiles' default method extrapolates beyond the
    # samples, which gave a p10 under the fastest run and a p90 over the slowest.
    ticks = iter([0.0, 0.010, 0.0, 0.020, 0.0, 0.030])
    monkeypatch.setattr(common.time, "perf_counter", lambda: next(ticks))
    t = common.time_ms(lambda: None, repeats=3, warmup=0)
    assert t["min_ms"] == pytest.approx(10.0) and t["median_ms"] == pytest.approx(20.0)
    assert 10.0 <= t["p10_ms"] <= t["median_ms"] <= t["p90_ms"] <= 30.0
