"""benchmarks/bench_standstill.py: what the rig says while the vehicle stands still."""

import json
import sys

import pytest

from benchmarks import bench_standstill
from benchmarks.bench_standstill import CONTROL_PHASES, PHASES, stop_plan, stop_poses


def _main(monkeypatch, *args: str) -> None:
    monkeypatch.setattr(sys, "argv", ["bench_standstill.py", *args])
    bench_standstill.main()


@pytest.mark.parametrize("bad, said", [
    (["--stop-at", "120"], "--stop-at"),  # the default drive's poses are 0..119
    (["--frames", "10", "--stop-at", "10"], "--stop-at"),
    (["--stop-at", "-1"], "--stop-at"),
    (["--stop-s", "0"], "--stop-s"),
    (["--stop-s", "nan"], "--stop-s"),
    (["--fps", "0"], "--fps"),
    (["--drives", "0"], "--drives"),
    (["--drive-seed", "1000"], "--drive-seed 1000"),  # the training drives
])
def test_bad_arguments_are_usage_errors_naming_the_option(bad, said, monkeypatch, capsys):
    with pytest.raises(SystemExit) as end:
        _main(monkeypatch, *bad)
    assert end.value.code == 2 and said in capsys.readouterr().err


def test_each_frame_has_one_phase_in_the_order_of_the_drive():
    # 2 frames a second: a stop of 12 s is 24 frames, the first at pose 5.
    plan = stop_plan(20, 5, 12.0, 2.0)
    assert plan.n_stop == 24 and plan.n_frames == 20 + 24 - 1
    phases = [plan.phase(seq) for seq in range(plan.n_frames)]
    # In order, each a run of its own: a phase never comes back.
    runs = [p for i, p in enumerate(phases) if i == 0 or phases[i - 1] != p]
    assert runs == list(PHASES)
    assert phases.count("moving_before") == 5
    assert phases.count("stop_0_4s") == 8 and phases.count("stop_4_10s") == 12 and phases.count("stop_10s_on") == 4
    assert phases.count("moving_after_0_4s") == 8 and phases.count("moving_after_4s_on") == 20 - 6 - 8
    control = [plan.control_phase(pose) for pose in range(20)]
    assert [control.count(p) for p in CONTROL_PHASES] == [5, 1, 8, 6]


def test_the_stop_stands_at_one_pose_with_fresh_noise_and_the_drive_goes_on_after_it():
    plan = stop_plan(10, 4, 0.5, 10.0)  # 5 frames at pose 4
    poses, keys = stop_poses(plan)
    assert poses == [0, 1, 2, 3, 4, 4, 4, 4, 4, 5, 6, 7, 8, 9]
    # The first standing frame is the plain drive's frame 4; the others draw noise of their own.
    assert keys == [(0,), (1,), (2,), (3,), (4,), (4, 1), (4, 2), (4, 3), (4, 4), (5,), (6,), (7,), (8,), (9,)]


def test_a_tiny_run_puts_every_window_in_one_phase(tiny_model_dir, monkeypatch, capsys):
    # 2 frames a second fill a window of 8 within the 4 s span; 12 s standing reach every stop phase.
    _main(monkeypatch, "--model", str(tiny_model_dir), "--drives", "1", "--frames", "20", "--stop-at", "5",
          "--stop-s", "12", "--fps", "2")
    out = json.loads(capsys.readouterr().out)
    assert list(out["phases"]) == list(PHASES) and list(out["control"]) == list(CONTROL_PHASES)
    stop, control = out["counts"]["stop"], out["counts"]["control"]
    assert stop["frames"] == 20 + 24 - 1 and control["frames"] == 20
    # One window per frame the exposure gate let through, each in exactly one phase.
    for counts, phases in ((stop, out["phases"]), (control, out["control"])):
        windows = counts["frames"] - counts["frames_bad_exposure"] - counts["windows_failed"]
        assert sum(p["n_windows"] for p in phases.values()) == windows
    # This drive's frames all pass the gate: a window for every frame.
    assert stop["frames_bad_exposure"] == 0 and stop["windows_failed"] == 0
    assert [out["phases"][p]["n_windows"] for p in PHASES] == [5, 8, 12, 4, 8, 6]
    assert [out["control"][p]["n_windows"] for p in CONTROL_PHASES] == [5, 1, 8, 6]
    # Standing past the span, every window holds the views from before the stop (poses 0-4) and the
    # standing one once (rig/window.py): each frame a pose of its own. It was the one pose, 8 times.
    for p in ("stop_4_10s", "stop_10s_on"):
        assert out["phases"][p]["distinct_poses_mean"] == 6.0 and out["phases"][p]["n_frames_mean"] == 6.0
    assert out["control"]["moving_after_4s_on"]["distinct_poses_mean"] == 8.0
    assert out["per_drive"][0]["drive"] == "drive_3000_0000" and "runtime_s" in out
    assert out["paired"]["drives"] == 1


def test_the_stop_streams_frames_are_the_drives_own_and_standing_ones_differ_by_noise_alone():
    import cv2
    import numpy as np

    from benchmarks.bench_standstill import drive_frames
    from benchmarks.common import SYNTH_JPEG_QUALITY
    from replay.synthetic.drive import Drive, kitti_intrinsics

    drive = Drive(5, 6, intrinsics=kitti_intrinsics(0.25))
    plan = stop_plan(6, 2, 0.3, 10.0)  # frames 2, 3 and 4 stand at pose 2
    poses, keys = stop_poses(plan)
    radiance: dict = {}
    frames = list(drive_frames(drive, poses, keys, radiance))
    plain = list(drive.frames())

    def jpeg(image):
        return cv2.imdecode(cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, SYNTH_JPEG_QUALITY])[1],
                            cv2.IMREAD_COLOR)

    # Before the stop and at its first frame, the drive's frames (one render per pose, kept apart:
    # the renderer reuses its buffers, so a kept render that is not a copy turns into the last pose).
    for seq in range(3):
        assert np.array_equal(frames[seq].image_bgr, jpeg(plain[seq].image_bgr))
    standing = [f.image_bgr.astype(np.int16) for f in frames[2:5]]
    for other in standing[1:]:
        diff = np.abs(other - standing[0]).mean()
        assert 0 < diff < 3  # fresh noise, the same view
    assert [f.attitude.heading_rad for f in frames] == [drive.poses[k].heading_rad for k in poses]
    assert [f.t_mono_s for f in frames] == pytest.approx([seq / 10.0 for seq in range(8)])
    # The control, from the same kept renders, is the plain drive.
    again = list(drive_frames(drive, range(6), [(k,) for k in range(6)], radiance))
    for seq in range(6):
        assert np.array_equal(again[seq].image_bgr, jpeg(plain[seq].image_bgr))


@pytest.mark.parametrize("bad, said", [
    (["--idle-shake-px", "-1"], "--idle-shake-px"),
    (["--gain-drift", "1"], "--gain-drift"),  # a gain of 0 or 2: no view to compare
    (["--crossing", "bus"], "--crossing"),
    (["--jpeg-quality", "0"], "--jpeg-quality"),
])
def test_bad_idle_options_are_usage_errors_naming_the_option(bad, said, monkeypatch, capsys):
    with pytest.raises(SystemExit) as end:
        _main(monkeypatch, *bad)
    assert end.value.code == 2 and said in capsys.readouterr().err


def test_only_standing_frames_idle_and_each_option_shows():
    import math

    from benchmarks.bench_standstill import GAIN_PERIOD_S, Idle, idle_effects

    plan = stop_plan(10, 4, 12.0, 10.0)  # 120 frames at pose 4
    standing = range(4, 4 + 120)
    assert idle_effects(plan, Idle(), 1) == [None] * plan.n_frames  # the default run: the plain stop
    shaken = idle_effects(plan, Idle(shake_px=2.0), 1)
    assert all((e is None) == (seq not in standing) for seq, e in enumerate(shaken))
    moves = [(e.dx_px, e.dy_px) for e in shaken if e is not None]
    assert max(abs(m) for xy in moves for m in xy) <= 2.0 and len(set(moves)) == len(moves)
    drift = [e.dy_px for e in idle_effects(plan, Idle(drift_px=1.0), 1) if e is not None]
    assert drift[0] == 0.0 and drift[-1] == pytest.approx(1.0) and drift == sorted(drift)
    gains = [e.gain for e in idle_effects(plan, Idle(gain_drift=-0.3), 1) if e is not None]
    assert gains[0] == 1.0 and gains[round(GAIN_PERIOD_S / 2 * 10)] == pytest.approx(0.7) and min(gains) >= 0.7
    boxes = [e.box for e in idle_effects(plan, Idle(crossing="car"), 1) if e is not None]
    assert boxes[:10] == [None] * 10  # from 1 s into the stop on
    crossing = [b for b in boxes if b is not None]
    assert crossing and all(b[2] - b[0] == pytest.approx(0.18) for b in crossing)
    assert not math.isclose(crossing[0][0], crossing[1][0])  # it moves


def test_an_idle_standing_frame_is_the_plain_one_moved_and_darkened():
    import numpy as np

    from benchmarks.bench_standstill import FrameEffect, apply_effect

    rng = np.random.default_rng(0)
    light = rng.uniform(0.1, 1.0, (20, 40, 3)).astype(np.float32)
    moved = apply_effect(light, FrameEffect(dx_px=2.0))
    assert np.allclose(moved[:, 2:], light[:, :-2]) and moved is not light
    boxed = apply_effect(light, FrameEffect(box=(0.5, 0.5, 0.75, 1.0), light=0.1))
    assert np.allclose(boxed[10:, 20:30], 0.1 * np.median(light.reshape(-1, 3), axis=0))
    assert np.array_equal(boxed[:10], light[:10]) and np.array_equal(light, apply_effect(light, FrameEffect()))


def test_a_tiny_idle_run_says_how_the_view_clock_took_the_stop(tiny_model_dir, monkeypatch, capsys):
    _main(monkeypatch, "--model", str(tiny_model_dir), "--drives", "1", "--frames", "20", "--stop-at", "5",
          "--stop-s", "12", "--fps", "2", "--idle-shake-px", "1", "--gain-drift", "-0.2")
    out = json.loads(capsys.readouterr().out)
    assert out["idle"]["shake_px"] == 1.0 and out["idle"]["gain_drift"] == -0.2
    views = out["views"]
    assert views["standing_frames"] == 23 and views["standing_rms"]["frames"] == 23
    assert 0 < views["standing_rms"]["p50"] <= views["standing_rms"]["p99"] <= views["standing_rms"]["max"]
    assert 0 <= views["standing_repeat_share"] <= 1 and views["views_per_stop_max"] >= 1
    # Driving, no frame is a repeat, and the nearest two are far apart.
    assert views["moving_frames"] == 19 and views["moving_repeats"] == 0
    assert views["moving_nearest_rms"] > views["same_view_max_rms"]
