"""benchmarks/bench_clear_sky.py: the model card's finding that most of the validation tail is not
the clouds rests on it re-rendering a drive with only its sky changed."""

import json
import sys

import pytest

from benchmarks.bench_clear_sky import SKIES, main, relative_azimuth_deg, summarise


@pytest.mark.parametrize(("sun_deg", "heading_deg", "expected_deg"),
                         [(90.0, 90.0, 0.0), (180.0, 90.0, 90.0), (0.0, 90.0, -90.0), (270.0, 90.0, -180.0),
                          (10.0, 350.0, 20.0), (350.0, 10.0, -20.0)])
def test_relative_azimuth_is_clockwise_from_the_heading_from_minus_180_to_180(sun_deg, heading_deg, expected_deg):
    import math

    assert relative_azimuth_deg(math.radians(sun_deg), math.radians(heading_deg)) == pytest.approx(expected_deg)


def test_summary_counts_only_errors_strictly_over_30_deg():
    s = summarise([10.0, 30.0, 30.5, 50.0])
    assert s == {"n_estimates": 4, "mean_deg": pytest.approx(30.125), "max_deg": 50.0, "over_30_deg": 2}


@pytest.mark.slow
def test_only_the_sky_changes_between_renders(monkeypatch, capsys):
    # Validation drive 231 has clouds (cover 0.44) and its direct sun at full strength: without the
    # cloud layer its windows read differently, while "full sun" renders exactly what was recorded.
    monkeypatch.setattr(sys, "argv", ["bench_clear_sky.py", "--indices", "231", "--frames", "9", "--crop-seeds", "0"])
    main()
    out = json.loads(capsys.readouterr().out)
    (drive,) = out["drives"]
    assert drive["cloud_cover"] > 0.3 and drive["sun_visibility"] == 1.0
    skies = drive["skies"]
    assert list(skies) == list(SKIES) and all(s["n_estimates"] == 2 for s in skies.values())
    assert skies["full_sun"] == skies["recorded"]
    assert skies["no_clouds"]["mean_deg"] != skies["recorded"]["mean_deg"]  # renders are deterministic
    assert skies["clear"] == skies["no_clouds"]


def test_drives_shorter_than_a_window_are_refused_before_they_are_rendered(monkeypatch):
    # --frames 5 made no full window and ended in a ZeroDivisionError after rendering four skies.
    from rig.errors import SunrigError

    monkeypatch.setattr(sys, "argv", ["bench_clear_sky.py", "--indices", "231", "--frames", "5"])
    with pytest.raises(SunrigError, match="--frames 5"):
        main()
