"""benchmarks/bench_exposure.py: what the exposure gate lets through of a covered lens and of a frame
metered dark for the sun in it, and what the model makes of it."""

import json
import math
import shutil
import sys

import numpy as np
import pytest

from benchmarks import bench_exposure
from benchmarks.bench_exposure import (
    IMPAIRMENTS,
    NIGHT_IMPAIRMENTS,
    SUN_IMPAIRMENTS,
    Windows,
    capture_metered,
    count_gate,
    cover_mask,
    fine_share,
    impaired_radiance,
    luma_mean,
    night_camera,
    night_stops,
)
from rig.errors import SunrigError


def _main(monkeypatch, *args: str) -> None:
    monkeypatch.setattr(sys, "argv", ["bench_exposure.py", *args])
    bench_exposure.main()


@pytest.mark.parametrize("bad, said", [
    (["--drive-seed", "1000"], "--drive-seed 1000"),  # the training drives
    (["--drives", "0", "--sun-drives", "0"], "nothing to measure"),
    (["--drives", "-1"], "--drives"),
    (["--metered-mean", "0"], "--metered-mean"),
    (["--metered-mean", "nan"], "--metered-mean"),
    (["--frames", "0"], "--frames"),
])
def test_bad_arguments_are_usage_errors_naming_the_option(bad, said, monkeypatch, capsys):
    with pytest.raises(SystemExit) as end:
        _main(monkeypatch, *bad)
    assert end.value.code == 2 and said in capsys.readouterr().err


@pytest.mark.parametrize(("kind", "share"), [("none", 0.0), ("cap_lower_half", 0.5), ("cap_left_half", 0.5),
                                             ("blob_30", 0.30), ("blob_60", 0.60)])
def test_each_cover_takes_its_share_of_the_frame(kind, share):
    mask = cover_mask(188, 621, kind)  # a KITTI frame at the render scale
    assert mask.shape == (188, 621) and mask.min() >= 0.0 and mask.max() <= 1.0
    assert float(mask.mean()) == pytest.approx(share, abs=0.02)


def test_a_cap_covers_the_half_it_names_and_a_blob_where_it_comes_from():
    lower, left = cover_mask(80, 120, "cap_lower_half"), cover_mask(80, 120, "cap_left_half")
    assert (lower[40:] == 1).all() and (lower[:40] == 0).all()
    assert (left[:, :60] == 1).all() and (left[:, 60:] == 0).all()
    hand, visor = cover_mask(80, 240, "blob_30"), cover_mask(80, 240, "blob_60")
    assert hand[-1, 192] > 0.99 and hand[-1, -1] > 0.9 and hand[0, 0] < 0.01  # up from the lower right
    assert visor[0, 120] > 0.99 and visor[-1, 0] < 0.01  # from the top
    with pytest.raises(ValueError, match="unknown impairment"):
        cover_mask(8, 8, "fog")


def test_a_cap_takes_the_light_and_a_blob_puts_its_own_flat_dark_light_in_its_place():
    rng = np.random.default_rng(0)
    radiance = rng.uniform(1.0, 2.0, (40, 60, 3)).astype(np.float32)
    assert impaired_radiance(radiance, "none") is radiance
    capped = impaired_radiance(radiance, "cap_lower_half")
    assert (capped[20:] == 0).all() and (capped[:20] == radiance[:20]).all()
    blob = impaired_radiance(radiance, "blob_60")
    core = cover_mask(40, 60, "blob_60") > 0.999
    level = bench_exposure.BLOB_LEVEL * float(np.median(radiance))
    # Where the blob is whole, its own light and at most 0.1 % of the scene's (up to 2) behind it.
    assert core.any() and np.allclose(blob[core], level, rtol=0.0, atol=0.002)


def test_a_night_cuts_the_stops_it_names():
    assert [night_stops(kind) for kind in NIGHT_IMPAIRMENTS] == [4, 6, 8]
    with pytest.raises(ValueError, match="unknown impairment"):
        night_stops("night_3")


def test_a_night_camera_adds_the_noise_of_the_gain_its_auto_exposure_applies():
    from replay.synthetic.camera import Camera, CameraEffects

    effects = CameraEffects(ae_smoothing=0.0, noise_sqrt=0.005)
    radiance = np.full((60, 80, 3), 5.0, np.float32)  # flat grey: any spread is the sensor's noise

    def spread(camera, light):
        return float(camera.capture(light, np.random.default_rng(0)).astype(np.float64).std())

    day = spread(Camera(effects, 80, 60, seed=1), radiance)
    # The synthetic camera alone: 8 stops less light, made up by its auto exposure, is the same frame.
    dark = Camera(effects, 80, 60, seed=1).capture(radiance / 256, np.random.default_rng(0))
    assert (dark == Camera(effects, 80, 60, seed=1).capture(radiance, np.random.default_rng(0))).all()
    # A sensor's photon noise at 2^8 the gain: 2^4 as large in sqrt-exposure units; the tone curve
    # near mid grey turns that into about as much more spread in levels.
    night = spread(night_camera(effects, 80, 60, 1, 8), radiance / 256)
    assert day > 0.5 and 12 < night / day < 20


def test_the_fine_share_is_about_1_for_white_noise_and_near_0_for_a_smooth_scene():
    rng = np.random.default_rng(0)
    noise = rng.integers(0, 256, (80, 128, 3), dtype=np.uint8)
    ramp = np.broadcast_to(np.linspace(0, 255, 128).astype(np.uint8)[None, :, None], (80, 128, 3))
    assert fine_share(noise) == pytest.approx(1.0, abs=0.1)
    assert 0.0 < fine_share(ramp) < 0.001
    assert fine_share(np.full((8, 8, 3), 7, np.uint8)) == 0.0  # flat: no spread to share
    assert fine_share(np.ascontiguousarray(noise[:, :1])) == 0.0  # one column: no neighbour beside it


def test_metering_for_the_sun_darkens_the_frame_to_the_mean_asked_and_the_sun_stays_saturated():
    from replay.synthetic import drive_seed
    from replay.synthetic.camera import _LUT, Camera
    from replay.synthetic.drive import Drive

    # drive_3000_0224 shows the sun whole in its first frame (the benchmark's first sun drive).
    drive = Drive(drive_seed(3000, 224), 2)
    out = drive.renderer.render(drive.poses[0])
    assert out.sun_visible > 0.9
    camera = Camera(drive.params.effects, drive.intrinsics.width, drive.intrinsics.height, seed=drive.seed)
    image = capture_metered(camera, out.radiance, [drive.seed, 3, 0], 10.0)
    assert luma_mean(image) == pytest.approx(10.0, abs=0.25)
    # The renderer's sun pixel is at its own (half) scale.
    u, v = (out.sun_px * drive.intrinsics.width / out.radiance.shape[1]).astype(int)
    # Saturated: the top of the camera's tone curve (254: its shoulder never quite reaches 255).
    assert image[v - 1:v + 2, u - 1:u + 2].min() == _LUT[-1] == 254


def test_a_window_summary_counts_the_valid_windows_far_off():
    w = Windows(error_deg=[10.0, 40.0, 50.0, 30.0], valid=[True, True, False, True])
    s = w.summary()
    assert s["windows"] == 4 and s["mean_deg"] == 32.5 and s["max_deg"] == 50.0
    assert s["valid_share"] == 0.75 and s["valid_mean_deg"] == pytest.approx(80.0 / 3)
    assert s["valid_over_30_deg"] == 1  # 30.0 is not over 30; 50 is not valid
    assert Windows().summary()["mean_deg"] is None


def test_counting_the_gate_on_a_folder_of_logs(tmp_path):
    from replay.sources import DEMO_LOG

    with pytest.raises(SunrigError, match="no .mcap logs"):
        count_gate(str(tmp_path))
    shutil.copy(DEMO_LOG, tmp_path / "demo.mcap")
    out = count_gate(str(tmp_path))
    assert out["logs"] == 1 and out["frames"] == out["shipped_gate"]["passed"] == out["mean_std_only"]["passed"]
    assert out["newly_rejected"] == 0 and out["newly_rejected_frames"] == []
    assert 0.0 <= out["covered_share"]["min"] <= out["covered_share"]["max"] <= 0.25
    assert 0.0 < out["fine_share"]["min"] <= out["fine_share"]["max"] < 0.05  # a drive's frames, not noise


def test_a_tiny_run_reports_every_impairment_with_and_without_the_gate(tiny_model_dir, monkeypatch, capsys):
    _main(monkeypatch, "--model", str(tiny_model_dir), "--drives", "1", "--sun-drives", "1", "--frames", "8")
    out = json.loads(capsys.readouterr().out)
    assert list(out["impairments"]) == [*IMPAIRMENTS, *NIGHT_IMPAIRMENTS, *SUN_IMPAIRMENTS]
    assert len(out["drives"]["sun_in_view"]) == 1 and out["gate_us"]["median"] > 0
    for kind, got in out["impairments"].items():
        assert got["frames"] == 8
        passed = got["gate"].get("passed", 0)
        assert sum(got["gate"].values()) == 8
        assert 0.0 <= got["covered_share"]["min"] <= got["covered_share"]["max"] <= 1.0
        assert 0.0 <= got["fine_share"]["min"] <= got["fine_share"]["max"]
        # One window a frame: every frame without the gate, those it let through with it.
        assert got["gate_off"]["windows"] == 8 and got["gate_on"]["windows"] == passed
        assert got["frames_impaired"] == (0 if kind in ("none", "sun_none") else
                                          8 if kind in (*IMPAIRMENTS, *NIGHT_IMPAIRMENTS) else got["frames_impaired"])
    metered = out["impairments"]["sun_metered"]
    assert metered["frames_impaired"] >= 4 and math.isclose(metered["impaired_luma_mean"]["median"], 10.0, abs_tol=0.3)
