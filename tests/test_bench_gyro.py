"""benchmarks/bench_gyro.py, whose tables docs/oak.md quotes: its simulated vehicle and IMU agree
with themselves (an ideal gyro integrates to the true heading), its plan stands where it says,
and its error figures are what they claim."""

import json
import math
import sys

import numpy as np
import pytest

from benchmarks.bench_gyro import (
    PiecewiseLinear,
    SimConfig,
    main,
    plan_drive,
    run_drive,
    span_error_deg,
)


def test_piecewise_linear_integral_is_exact():
    f = PiecewiseLinear([0.0, 2.0, 4.0], [0.0, 2.0, 2.0])  # a ramp to 2, then 2
    assert f.integral(np.array([0.0, 1.0, 2.0, 3.0, 4.0, 5.0])).tolist() == [0.0, 0.5, 2.0, 4.0, 6.0, 8.0]
    assert f.slope(np.array([1.0, 3.0, 5.0])).tolist() == [1.0, 0.0, 0.0]


def test_an_ideal_gyro_integrates_to_the_true_heading():
    """No bias, no noise (nor quantisation, which without noise to dither it is a bias), no tilt
    term (which vehicle accelerations pull off) and no accelerometer vibration (the first report
    gives the integrator its up: 0.3 m/s² off tilts it by up to 1.7 deg, which nothing then
    corrects): what the simulated gyro reports, turns, engine vibration and road motion included,
    integrates to the simulated attitude, so every error the benchmark shows is the sensor's and
    the integrator's."""
    cfg = SimConfig(minutes=2.0, bias_deg_s=0.0, bias_walk=0.0, gyro_noise=0.0, gyro_lsb_deg_s=0.0,
                    idle_accel_m_s2=0.0)
    d = run_drive(cfg, 3, 4.0, {"tilt_gain": 0.0, "gyro_bias": False})
    # Not exact: the integrator's steps of 10 ms sample the engine's 20-40 Hz vibration coarsely.
    assert d["max_abs_heading_error_deg"] < 0.1 and d["max_abs_pitch_error_deg"] < 0.2


def test_the_drive_stands_at_boot_and_at_each_stop():
    cfg = SimConfig(minutes=6.0, boot_still_s=30.0, stop_every_s=120.0, stop_s=20.0)
    plan = plan_drive(cfg, np.random.default_rng(0))
    t = np.arange(0.0, 360.0, 0.1)
    still = plan.speed(t) == 0.0
    assert still[t < 30.0].all() and not still[(t > 31.0) & (t < 40.0)].any()
    edges = np.flatnonzero(np.diff(still.astype(int)) == 1)  # where a stop begins (after the boot)
    assert len(edges) >= 2
    for e in edges[:2]:
        assert still[e + 1:e + 200].all()  # 20 s standing


def test_span_error_is_the_largest_change_within_the_span():
    t = np.arange(0.0, 10.0, 1.0)
    err = np.array([0.0, 0.0, 1.0, 3.0, 3.0, 3.0, 3.0, 3.0, 9.0, 9.0])
    assert span_error_deg(t, err, 4.0) == 6.0  # 3 at t 4-7, 9 at t 8: within 4 s
    assert span_error_deg(t, err, 1.0) == 6.0
    assert span_error_deg(t, np.zeros(10), 4.0) == 0.0


@pytest.mark.parametrize("bad", [["--drives", "0"], ["--minutes", "0"], ["--rate-hz", "10"],
                                 ["--scenario", "park"], ["--span-s", "0"], ["--repeats", "0"],
                                 ["--gyro-bias", "maybe"]])
def test_options_that_measure_nothing_are_usage_errors(bad, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["bench_gyro.py", *bad])
    with pytest.raises(SystemExit) as end:
        main()
    assert end.value.code == 2 and f"argument {bad[0]}" in capsys.readouterr().err


def test_a_short_run_prints_its_json_marked_as_a_simulation(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["bench_gyro.py", "--minutes", "1.2", "--drives", "1", "--repeats", "1"])
    main()
    out = json.loads(capsys.readouterr().out)
    assert out["benchmark"] == "gyro_heading" and "simulated" in out["simulated"]
    drive = out["drives"][0]
    # 0.5 deg/s on each axis, one of which is about up (the camera pitched 2 deg, rolled 1 deg):
    # about 30 deg of heading a minute, as the datasheet's typical offset gives.
    assert abs(drive["heading_drift_deg_s_true"]) == pytest.approx(0.5, abs=0.03)
    assert math.isfinite(out["summary"]["abs_heading_error_1min_deg"]["median"])
    assert out["cost_us_per_report"]["median"] > 0
    # The driver's default learns the bias at the 30 s standstill at boot.
    assert out["config"]["gyro_bias"] == "on" and out["summary"]["gyro_bias_learned"] >= 1
