"""benchmarks/bench_spread.py's grouping of windows by where the answer puts the sun, and its
figures for a flag on a gap (mirror, crop) or score, which the model card quotes to say whether
any of them could flag the windows far off."""

import numpy as np
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


def test_rank_auc_counts_pairs_a_positive_wins_and_ties_as_half():
    from benchmarks.bench_spread import rank_auc

    # Positives 3 and 1 against negatives 2, 1, 0: 3 beats all three, 1 beats 0 and ties 1,
    # so 3 + 1.5 = 4.5 of the 6 pairs.
    score = np.array([3.0, 2.0, 1.0, 1.0, 0.0])
    positive = np.array([True, False, True, False, False])
    assert rank_auc(score, positive) == pytest.approx(4.5 / 6)
    assert rank_auc(score, ~positive) == pytest.approx(1.5 / 6)  # the complement, flagged the other way
    assert rank_auc(score, np.zeros(5, dtype=bool)) is None


def test_a_flag_on_the_largest_gaps_counts_what_it_catches_and_the_worst_it_leaves():
    from benchmarks.bench_spread import gap_flags

    # Ten windows; the two with the largest gaps are 25 and 5 deg off; 40 deg is left unflagged.
    gap = np.array([9.0, 8.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 0.5, 0.2])
    err = np.array([25.0, 5.0, 40.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0])
    out = gap_flags(gap, err, shares=(0.2,))
    assert out["windows_over_20_deg"] == 2 and out["windows_over_30_deg"] == 1
    assert out["on_windows_over_30_deg"] == {"min": 1.0, "median": 1.0, "max": 1.0}
    (flag,) = out["flag_largest"]
    assert flag["flagged"] == 2 and flag["caught_over_20_deg"] == 1 and flag["caught_over_30_deg"] == 0
    assert flag["max_deg_left"] == 40.0
    assert flag["mean_deg_flagged"] == 15.0 and flag["flagged_under_10_deg"] == 1  # 25 and 5 deg
    # The 40-deg window has the third smallest gap: 2 of the 9 others are below it.
    assert out["auc_over_30_deg"] == pytest.approx(2 / 9)
    # Another score's threshold is named by its unit.
    assert set(gap_flags(gap, err, shares=(0.2,), unit="score")["flag_largest"][0]) - set(flag) == {"threshold_score"}
