"""benchmarks/bench_confidence.py's probe: the ridge fit the model card's figures for a learnt
flag come from."""

import argparse

import numpy as np
import pytest

from benchmarks.bench_confidence import drive_set, fit_ridge


def test_without_a_ridge_the_fit_recovers_a_linear_law_and_reports_weights_per_standard_deviation():
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.normal(0, 2, 200), rng.normal(5, 0.5, 200), np.full(200, 7.0)])
    y = 2.0 * x[:, 0] - 4.0 * x[:, 1] + 3.0
    predict, weights = fit_ridge(x, y, ridge=0.0)
    x_new = rng.normal(0, 1, (5, 3))
    assert predict(x_new) == pytest.approx(2.0 * x_new[:, 0] - 4.0 * x_new[:, 1] + 3.0)
    # A weight is the move per standard deviation of its column; the constant column gets none.
    assert weights == pytest.approx([2.0 * x[:, 0].std(), -4.0 * x[:, 1].std(), 0.0])


def test_a_ridge_shrinks_the_weights_but_not_the_intercept():
    rng = np.random.default_rng(1)
    x = rng.normal(0, 1, (100, 2))
    y = x[:, 0] + 10.0
    _, free = fit_ridge(x, y, ridge=0.0)
    predict, shrunk = fit_ridge(x, y, ridge=100.0)
    assert 0.0 < shrunk[0] < free[0]
    # With the weights shrunk, the predictions still average the target's mean: the intercept is free.
    assert predict(x).mean() == pytest.approx(y.mean())


def test_a_drive_set_is_dir_drives_seed_and_anything_else_is_refused():
    assert drive_set("data/val:300:2500") == ("data/val", 300, 2500)
    assert drive_set("C:/logs:3:1") == ("C:/logs", 3, 1)  # the folder may hold a colon itself
    with pytest.raises(argparse.ArgumentTypeError, match="DIR:DRIVES:SEED"):
        drive_set("data/val:300")


@pytest.mark.parametrize("bad", ["data/probe:0:4000", "data/probe:-3:4000", "data/probe:100001:4000", ":300:4000"])
def test_a_drive_set_of_no_drives_or_no_folder_is_refused(bad):
    # 0 drives fitted the probe on no window: numpy's matmul error after the test sets' drives.
    with pytest.raises(argparse.ArgumentTypeError, match="DIR:DRIVES:SEED"):
        drive_set(bad)
