"""benchmarks/bench_spread.py's grouping of windows by where the answer puts the sun, which the
model card quotes to say whether that place could flag the windows far off."""

import pytest

from benchmarks.bench_spread import answer_place, by_answer_place


@pytest.mark.parametrize(("az_deg", "el_deg", "place"),
                         [(0.0, 10.0, "ahead low"), (-59.9, 30.0, "ahead mid"), (60.0, 59.9, "side mid"),
                          (-119.9, 60.0, "side high"), (120.0, 90.0, "behind high"), (-180.0, -3.0, "behind low"),
                          (180.0, 45.0, "behind mid")])
def test_an_answer_falls_in_the_band_of_its_azimuth_either_side_and_its_elevation(az_deg, el_deg, place):
    assert answer_place(az_deg, el_deg) == place


def test_each_band_has_its_share_mean_and_count_over_30_deg_and_every_band_is_listed():
    places = ["behind high", "behind high", "ahead low", "ahead low"]
    out = by_answer_place(places, [40.0, 10.0, 30.0, 2.0])
    assert len(out) == 9 and sum(b["share"] for b in out.values()) == pytest.approx(1.0)
    assert out["behind high"] == {"share": 0.5, "mean_deg": 25.0, "over_30_deg": 1}
    assert out["ahead low"] == {"share": 0.5, "mean_deg": 16.0, "over_30_deg": 0}  # 30.0 is not over 30
    assert out["side mid"] == {"share": 0.0, "mean_deg": None, "over_30_deg": 0}
