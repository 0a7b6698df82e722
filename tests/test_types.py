"""Core types validate once, at the boundary, with messages that say expected vs actual."""

import math

import numpy as np
import pytest

from rig.errors import ValidationError
from rig.types import (
    MIN_FOV_DEG,
    Attitude,
    Frame,
    FrameFeatures,
    FrameMeta,
    GnssFix,
    HeadingRef,
    Intrinsics,
    SunEstimate,
    utc_iso,
)

INTR = Intrinsics(fx=50.0, fy=50.0, cx=32.0, cy=24.0, width=64, height=48)


def make_frame(**kw):
    base = dict(t_mono_s=1.0, seq=0, image_bgr=np.zeros((48, 64, 3), np.uint8), intrinsics=INTR)
    base.update(kw)
    return Frame(**base)


def test_frame_is_frozen_and_image_read_only():
    img = np.zeros((48, 64, 3), np.uint8)
    f = make_frame(image_bgr=img)
    with pytest.raises(AttributeError):
        f.seq = 3
    with pytest.raises(ValueError):
        f.image_bgr[0, 0, 0] = 1
    img[0, 0, 0] = 7  # the caller's own array stays writable
    assert f.image_bgr[0, 0, 0] == 7


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"image_bgr": np.zeros((48, 64, 3), np.float32)}, "expected dtype uint8, got float32"),
        ({"image_bgr": np.zeros((48, 64), np.uint8)}, "expected shape (H, W, 3) BGR, got (48, 64)"),
        ({"image_bgr": np.zeros((40, 64, 3), np.uint8)}, "expected shape (48, 64, 3) to match the intrinsics"),
        ({"seq": -1}, "Frame.seq: expected a non-negative integer, got -1"),
        ({"t_mono_s": float("nan")}, "expected a finite number"),
        ({"sun_enu_truth": [0.0, 0.0, 2.0]}, "expected a unit vector"),
        ({"sun_enu_truth": [0.0, 1.0]}, "expected shape (3,), got (2,)"),
    ],
)
def test_frame_rejects_with_expected_vs_actual(kwargs, message):
    with pytest.raises(ValidationError) as info:
        make_frame(**kwargs)
    assert message in str(info.value)


def test_intrinsics_checks_and_fov():
    with pytest.raises(ValidationError, match="fx: expected > 0 pixels, got -1"):
        Intrinsics(fx=-1, fy=1, cx=1, cy=1, width=2, height=2)
    with pytest.raises(ValidationError, match=r"cx: expected within \[0, 64\] pixels, got 65"):
        Intrinsics(fx=50, fy=50, cx=65, cy=1, width=64, height=48)
    k = Intrinsics.from_hfov(1242, 375, math.radians(81.4))
    assert math.degrees(k.hfov_rad) == pytest.approx(81.4)
    assert k.fx == k.fy and k.cx == 621.0


def test_attitude_wraps_and_checks_reference():
    a = Attitude(heading_rad=-math.pi / 2, reference="true")
    assert a.heading_rad == pytest.approx(1.5 * math.pi) and a.reference is HeadingRef.TRUE
    with pytest.raises(ValidationError, match="expected one of"):
        Attitude(heading_rad=0.0, reference="north-ish")
    with pytest.raises(ValidationError, match="pitch_rad"):
        Attitude(heading_rad=0.0, reference="true", pitch_rad=4.0)
    assert a.epoch == 0 and Attitude(0.0, "relative", epoch=np.int64(3)).epoch == 3
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(ValidationError, match="epoch"):
            Attitude(heading_rad=0.0, reference="relative", epoch=bad)


def test_gnss_ranges():
    with pytest.raises(ValidationError, match="lat_deg: expected within"):
        GnssFix(utc_ns=0, lat_deg=91.0, lon_deg=0.0)
    with pytest.raises(ValidationError, match="integer ns"):
        GnssFix(utc_ns=1.5, lat_deg=0.0, lon_deg=0.0)


def test_sun_estimate_json_view():
    est = SunEstimate(
        t_mono_s=2.0, seq=5, sun_enu=[0.0, math.cos(0.5), math.sin(0.5)], heading_rad=math.radians(350.0),
        heading_ref="true", spread_rad=math.radians(3.0), n_frames=8, n_tokens=32, aggregator="transformer",
        utc_ns=1_317_042_145_964_389_000, truth_enu=[0.0, 1.0, 0.0],
    )
    d = est.to_json_dict()
    assert d["azimuth_deg"] == pytest.approx(0.0, abs=1e-9)
    assert d["elevation_deg"] == pytest.approx(math.degrees(0.5))
    assert d["heading_deg"] == pytest.approx(350.0)
    assert d["relative_bearing_deg"] == pytest.approx(10.0)  # sun 10 deg to the right
    assert d["error_deg"] == pytest.approx(math.degrees(0.5))
    assert d["spread_deg"] == pytest.approx(3.0)
    assert d["utc"] == "2011-09-26T13:02:25.964389Z"
    for key in ("t", "seq", "sun_enu", "heading_ref", "n_frames", "truth_enu"):
        assert key in d


def test_sun_estimate_without_truth_has_no_error_fields():
    est = SunEstimate(t_mono_s=0.0, seq=0, sun_enu=[0, 0, 1], heading_rad=0.0, heading_ref="relative",
                      spread_rad=0.0, n_frames=1, n_tokens=1, aggregator="single")
    assert "error_deg" not in est.to_json_dict() and est.error_rad is None


def test_utc_iso_epoch():
    assert utc_iso(0) == "1970-01-01T00:00:00.000000Z"


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        # A zero focal length divides by zero in every view angle; a zero-pixel image has no crops.
        ({"fx": 0}, "Intrinsics.fx: expected > 0 pixels, got 0"),
        ({"fy": 0}, "Intrinsics.fy: expected > 0 pixels, got 0"),
        ({"width": 0, "cx": 0}, "Intrinsics.width: expected a positive integer, got 0"),
        ({"height": 0, "cy": 0}, "Intrinsics.height: expected a positive integer, got 0"),
    ],
)
def test_intrinsics_refuse_zero_focal_lengths_and_sizes(kwargs, message):
    base = dict(fx=50.0, fy=50.0, cx=32.0, cy=24.0, width=64, height=48)
    with pytest.raises(ValidationError) as info:
        Intrinsics(**{**base, **kwargs})
    assert message in str(info.value)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        # A calibration's fx of 1e308 made a crop side of inf px: the live rig's encode stage died
        # in round(), and replay, eval and quantize of its recording in an internal OverflowError.
        ({"fx": 1e308}, "Intrinsics.fx: expected at most 3.66693e+07 pixels (a field of view of at least 0.0001 deg "
                        "across the image's 64 px), got 1e+308"),
        ({"fy": 1e308}, "Intrinsics.fy: expected at most 3.66693e+07 pixels"),
        ({"fx": 1e-300}, "Intrinsics.fx: expected at least 1e-06 pixels"),
        # OpenCV keeps rows and columns in C ints; a larger size overflowed float arithmetic.
        ({"width": 2**31}, "Intrinsics.width: expected at most 2147483647 pixels, got 2147483648"),
        ({"height": 10**400}, "Intrinsics.height: expected at most 2147483647 pixels"),
        # These raised ValueError, OverflowError or TypeError from int(), not a ValidationError.
        ({"width": "64"}, "Intrinsics.width: expected a positive integer, got '64'"),
        ({"width": float("nan")}, "Intrinsics.width: expected a positive integer, got nan"),
        ({"height": float("inf")}, "Intrinsics.height: expected a positive integer, got inf"),
        ({"height": None}, "Intrinsics.height: expected a positive integer, got None"),
        ({"width": -64}, "Intrinsics.width: expected a positive integer, got -64"),
    ],
)
def test_intrinsics_refuse_what_no_camera_has(kwargs, message):
    base = dict(fx=50.0, fy=50.0, cx=0.0, cy=0.0, width=64, height=48)
    with pytest.raises(ValidationError) as info:
        Intrinsics(**{**base, **kwargs})
    assert message in str(info.value)


def test_the_narrowest_field_of_view_is_still_a_camera():
    # At MIN_FOV_DEG exactly (what --hfov-deg takes at its lowest), over any width: no crop side
    # or view angle overflows there.
    for width, height in ((64, 48), (1, 1), (2**31 - 1, 2**31 - 1)):
        k = Intrinsics.from_hfov(width, height, math.radians(MIN_FOV_DEG))
        assert math.degrees(k.hfov_rad) == pytest.approx(MIN_FOV_DEG)
        assert math.isfinite(2.0 * k.fx * math.tan(math.radians(179.0) / 2.0))
    # The bound is over the longer side: a line-scan camera's one row spans less, and is a camera.
    line = Intrinsics(fx=5e6, fy=5e6, cx=8192.0, cy=0.5, width=16384, height=1)
    assert math.degrees(line.vfov_rad) < MIN_FOV_DEG < math.degrees(line.hfov_rad)
    assert Intrinsics(fx=1e-6, fy=1e-6, cx=0.5, cy=0.5, width=1, height=1).fx == 1e-6


def test_each_field_of_view_uses_its_own_focal_length():
    # Non-square pixels (fx != fy): the horizontal FOV comes from fx alone, the vertical from fy
    # alone. Expected: 2 atan(half size / focal length) with the principal point at the centre.
    k = Intrinsics(fx=100.0, fy=50.0, cx=50.0, cy=25.0, width=100, height=50)
    assert k.hfov_rad == pytest.approx(2 * math.atan(50 / 100))
    assert k.vfov_rad == pytest.approx(2 * math.atan(25 / 50))


def test_gnss_longitude_below_minus_180_is_refused():
    # -180..360 covers both conventions (east negative or 0..360); below -180 is a parse error.
    with pytest.raises(ValidationError, match="lon_deg: expected within"):
        GnssFix(utc_ns=0, lat_deg=0.0, lon_deg=-180.5)
    assert GnssFix(utc_ns=0, lat_deg=0.0, lon_deg=-180.0).lon_deg == -180.0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"spread_rad": 3.5}, "SunEstimate.spread_rad: expected within [0, pi] rad, got 3.5"),
        ({"n_frames": 0}, "expected at least one frame and token, got 0 frames, 2 tokens"),
        ({"n_tokens": 0, "token_enu": None}, "expected at least one frame and token, got 1 frames, 0 tokens"),
        # token_enu is one world vector per token: the plots and the spread read it that way.
        ({"token_enu": np.zeros((3, 3))}, "SunEstimate.token_enu: expected shape (2, 3), got (3, 3)"),
        # From a log's estimate channel or a library caller: the encoders format these as integers
        # of fixed width and failed on them with a bare ValueError or struct.error.
        ({"seq": 1.5}, "SunEstimate.seq: expected a non-negative integer, got 1.5"),
        ({"seq": -1}, "SunEstimate.seq: expected a non-negative integer, got -1"),
        ({"utc_ns": 1.7e18}, "SunEstimate.utc_ns: expected integer ns since the epoch (int64), got 1.7e+18"),
        ({"utc_ns": 2**63}, "SunEstimate.utc_ns: expected integer ns since the epoch (int64), got 9223372036854775808"),
        ({"n_frames": 2.0}, "SunEstimate.n_frames: expected a non-negative integer, got 2.0"),
    ],
)
def test_sun_estimate_rejects_with_expected_vs_actual(kwargs, message):
    base = dict(t_mono_s=0.0, seq=0, sun_enu=[0, 0, 1], heading_rad=0.0, heading_ref="true", spread_rad=0.1,
                n_frames=1, n_tokens=2, aggregator="mean", token_enu=[[0, 0, 1], [0, 0, 1]])
    with pytest.raises(ValidationError) as info:
        SunEstimate(**{**base, **kwargs})
    assert message in str(info.value)


def test_frame_features_want_float32_embeddings():
    # The aggregator graph takes float32: float64 embeddings (a backbone run elsewhere) are refused
    # where they are made, not by onnxruntime in the middle of a window.
    boxes, angles = np.zeros((2, 4)), np.zeros((2, 2))
    with pytest.raises(ValidationError, match="expected dtype float32, got float64"):
        FrameFeatures(make_frame(), boxes, angles, np.zeros((2, 8), np.float64), "m")
    assert FrameFeatures(make_frame(), boxes, angles, np.zeros((2, 8), np.float32), "m").n_crops == 2


def test_vectors_are_copied_not_frozen_in_the_callers_hands():
    # The caller's float64 array is the kind np.asarray would share: it must stay writable, and
    # writing it must not change the estimate (or the frame's truth) made from it.
    sun, truth = np.array([0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0])
    est = SunEstimate(t_mono_s=0.0, seq=0, sun_enu=sun, heading_rad=0.0, heading_ref="true", spread_rad=0.0,
                      n_frames=1, n_tokens=1, aggregator="single")
    f = make_frame(sun_enu_truth=truth)
    sun[2], truth[1] = 0.5, 0.5
    assert est.sun_enu.tolist() == [0.0, 0.0, 1.0] and f.sun_enu_truth.tolist() == [0.0, 1.0, 0.0]


def test_vectors_must_be_finite_even_when_their_norm_cannot_say():
    # A NaN makes the norm NaN, and NaN > tolerance is False: only the finite check stops it.
    with pytest.raises(ValidationError, match="Frame.sun_enu_truth: expected finite values"):
        make_frame(sun_enu_truth=[float("nan"), 0.0, 1.0])
    with pytest.raises(ValidationError, match="SunEstimate.sun_enu: expected finite values"):
        SunEstimate(t_mono_s=0.0, seq=0, sun_enu=[0.0, float("inf"), 1.0], heading_rad=0.0, heading_ref="true",
                    spread_rad=0.0, n_frames=1, n_tokens=1, aggregator="single")


def _estimate(**kw):
    base = dict(t_mono_s=0.0, seq=0, sun_enu=[0.0, 0.0, 1.0], heading_rad=0.0, heading_ref="true", spread_rad=0.0,
                n_frames=1, n_tokens=2, aggregator="mean")
    return SunEstimate(**{**base, **kw})


def test_estimate_arrays_are_read_only_and_its_heading_wrapped():
    est = _estimate(truth_enu=[0.0, 1.0, 0.0], token_enu=[[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]],
                    heading_rad=-math.pi / 2)
    assert est.token_enu.shape == (2, 3)  # one world vector per token is accepted as it is
    for arr in (est.sun_enu, est.truth_enu, est.token_enu):
        with pytest.raises(ValueError):
            arr[0] = 0.5
    assert est.heading_rad == pytest.approx(1.5 * math.pi)  # clockwise from north, in [0, 2 pi)
    with pytest.raises(ValidationError, match="SunEstimate.truth_enu: expected a unit vector"):
        _estimate(truth_enu=[0.0, 0.0, 2.0])


def test_estimate_json_view_has_every_field_a_consumer_reads():
    d = _estimate(utc_ns=0, truth_enu=[0.0, 0.0, 1.0]).to_json_dict()
    assert set(d) == {"t", "seq", "sun_enu", "azimuth_deg", "elevation_deg", "heading_deg", "heading_ref",
                      "relative_bearing_deg", "spread_deg", "n_frames", "n_tokens", "aggregator", "utc",
                      "truth_enu", "error_deg"}
    assert (d["n_tokens"], d["aggregator"], d["n_frames"]) == (2, "mean", 1)


def test_a_relative_estimate_says_which_zero_its_heading_counts_from():
    # A relative heading's zero changes when its source restarts (an OAK reconnect, odometry that
    # lost track); from then on the azimuth is in another frame. The estimate carries the epoch,
    # and its JSON view says it, so that a script sees the azimuth jump is a new zero.
    d = _estimate(heading_ref="relative", heading_epoch=3).to_json_dict()
    assert d["heading_epoch"] == 3
    assert "heading_epoch" not in _estimate().to_json_dict()  # an absolute reference has one zero
    for bad in (-1, 1.5, True):
        with pytest.raises(ValidationError, match="SunEstimate.heading_epoch: expected an integer >= 0"):
            _estimate(heading_ref="relative", heading_epoch=bad)
    with pytest.raises(ValidationError, match="SunEstimate.heading_epoch: 2 with a true heading"):
        _estimate(heading_epoch=2)


def test_value_types_cannot_change_after_they_were_checked():
    import dataclasses

    fix = GnssFix(utc_ns=0, lat_deg=49.0, lon_deg=8.4)
    att = Attitude(heading_rad=0.0, reference="true")
    ff = FrameFeatures(make_frame(), np.zeros((1, 4)), np.zeros((1, 2)), np.zeros((1, 8), np.float32), "m")
    for obj, name in ((INTR, "fx"), (fix, "lat_deg"), (_estimate(), "spread_rad"), (att, "heading_rad"),
                      (ff, "model_id")):
        with pytest.raises(dataclasses.FrozenInstanceError):
            setattr(obj, name, 0.0)


def test_intrinsics_sizes_are_plain_ints_and_from_hfov_centres_the_principal_point():
    # 64.0 or a numpy int64 is a whole number: accepted, and stored as int (image slicing and JSON need one).
    k = Intrinsics(fx=50.0, fy=50.0, cx=32.0, cy=24.0, width=64.0, height=np.int64(48))
    assert type(k.width) is int and type(k.height) is int
    c = Intrinsics.from_hfov(1242, 375, math.radians(81.4))
    assert (c.cx, c.cy) == (621.0, 187.5)
    assert math.degrees(c.vfov_rad) == pytest.approx(2 * math.degrees(math.atan(187.5 / c.fy)))


def test_gnss_range_edges_and_altitude():
    with pytest.raises(ValidationError, match="lat_deg: expected within"):
        GnssFix(utc_ns=0, lat_deg=-90.5, lon_deg=0.0)
    assert GnssFix(utc_ns=0, lat_deg=-90.0, lon_deg=360.0).lon_deg == 360.0  # the 0..360 convention's end
    with pytest.raises(ValidationError, match="alt_m: expected a finite number"):
        GnssFix(utc_ns=0, lat_deg=0.0, lon_deg=0.0, alt_m=float("nan"))


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"image_bgr": [[[0, 0, 0]]]}, "Frame.image_bgr: expected a numpy array, got list"),
        ({"intrinsics": {"fx": 50.0}}, "Frame.intrinsics: expected Intrinsics, got dict"),
        ({"attitude": 1.5}, "Frame.attitude: expected Attitude or None, got float"),
        ({"gnss": (49.0, 8.4)}, "Frame.gnss: expected GnssFix or None, got tuple"),
        ({"utc_ns": 1.5e18}, "Frame.utc_ns: expected integer ns since the epoch"),
    ],
)
def test_frame_refuses_wrong_types_with_a_validation_error(kwargs, message):
    # Wrong types are a ValidationError naming the field, not an AttributeError from deeper down.
    with pytest.raises(ValidationError) as info:
        make_frame(**kwargs)
    assert message in str(info.value)


def test_frame_heading_and_utc():
    f = make_frame(attitude=Attitude(heading_rad=-math.pi / 2, reference="true"), utc_ns=np.int64(5))
    assert f.heading_rad == pytest.approx(1.5 * math.pi) and make_frame().heading_rad is None
    assert f.utc_ns == 5 and type(f.utc_ns) is int


def test_frame_features_check_their_shapes_and_keep_their_own_read_only_copies():
    boxes, angles, emb = np.zeros((2, 4)), np.zeros((2, 2)), np.zeros((2, 8), np.float32)
    with pytest.raises(ValidationError, match=r"crop_angles_rad: expected shape \(2, 2\), got \(2, 3\)"):
        FrameFeatures(make_frame(), boxes, np.zeros((2, 3)), emb, "m")
    with pytest.raises(ValidationError, match=r"embeddings: expected shape \(2, D\), got \(3, 8\)"):
        FrameFeatures(make_frame(), boxes, angles, np.zeros((3, 8), np.float32), "m")
    ff = FrameFeatures(make_frame(), boxes, angles, emb, "m")
    boxes[0, 0], angles[0, 0], emb[0, 0] = 9.0, 9.0, 9.0  # the caller's arrays stay writable
    assert ff.crop_boxes_px[0, 0] == 0.0 and ff.crop_angles_rad[0, 0] == 0.0 and ff.embeddings[0, 0] == 0.0
    for arr in (ff.crop_boxes_px, ff.crop_angles_rad, ff.embeddings):
        with pytest.raises(ValueError):
            arr[0, 0] = 1.0


def test_frame_features_keep_the_frame_without_its_pixels():
    # The ring keeps seconds of features; with the frames' images inside them that was 800 MB for a
    # 1920 x 1080 camera. Every field but the image is kept, with the same names and values.
    truth = [0.0, 0.6, 0.8]
    frame = make_frame(attitude=Attitude(1.0, HeadingRef.TRUE), utc_ns=7,
                       gnss=GnssFix(utc_ns=7, lat_deg=49.0, lon_deg=8.4), sun_enu_truth=truth)
    ff = FrameFeatures(frame, np.zeros((1, 4)), np.zeros((1, 2)), np.zeros((1, 8), np.float32), "m")
    assert isinstance(ff.frame, FrameMeta) and not hasattr(ff.frame, "image_bgr")
    for name in ("t_mono_s", "seq", "intrinsics", "attitude", "utc_ns", "gnss", "heading_rad"):
        assert getattr(ff.frame, name) == getattr(frame, name), name
    np.testing.assert_array_equal(ff.frame.sun_enu_truth, frame.sun_enu_truth)
    with pytest.raises(ValidationError, match="FrameFeatures.frame: expected Frame or FrameMeta, got dict"):
        FrameFeatures({"seq": 1}, np.zeros((1, 4)), np.zeros((1, 2)), np.zeros((1, 8), np.float32), "m")


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"seq": -1}, "FrameMeta.seq: expected a non-negative integer, got -1"),
        ({"attitude": 1.5}, "FrameMeta.attitude: expected Attitude or None, got float"),
        ({"utc_ns": 1.5e18}, "FrameMeta.utc_ns: expected integer ns since the epoch"),
        ({"sun_enu_truth": [0.0, 0.0, 2.0]}, "FrameMeta.sun_enu_truth: expected a unit vector"),
    ],
)
def test_frame_meta_checks_its_fields_as_a_frame_does(kwargs, message):
    with pytest.raises(ValidationError) as info:
        FrameMeta(**{"t_mono_s": 0.0, "seq": 0, "intrinsics": make_frame().intrinsics, **kwargs})
    assert message in str(info.value)


def test_a_value_that_is_no_number_is_a_validation_error():
    with pytest.raises(ValidationError, match="t_mono_s: expected a real number, got 'soon'"):
        make_frame(t_mono_s="soon")
    with pytest.raises(ValidationError, match="SunEstimate.sun_enu: expected a unit vector"):
        _estimate(sun_enu=[0.0, 0.0, 2.0])


def test_utc_iso_keeps_the_second_of_the_last_microsecond():
    # 13:02:25.999999999 is still second 25: integer arithmetic, no float rounding up to :26.
    assert utc_iso(1_317_042_145_999_999_999) == "2011-09-26T13:02:25.999999Z"


@pytest.mark.parametrize("norm", [0.9991, 1.0009])
def test_a_vector_within_the_unit_tolerance_is_made_unit(norm):
    # The wire promises 1 +- 0.0009 after rounding to 3 decimals: a 0.9991-long vector that passed
    # the check went out as 0.000,0.999,0.000 (NMEA) and 0.9991 (binary).
    from rig.protocol import decode_binary, decode_nmea, encode_binary, encode_nmea

    est = _estimate(sun_enu=[0.0, norm, 0.0], truth_enu=[0.0, 0.0, norm])
    assert np.linalg.norm(est.sun_enu) == pytest.approx(1.0, abs=1e-15)
    assert np.linalg.norm(est.truth_enu) == pytest.approx(1.0, abs=1e-15)
    assert decode_nmea(encode_nmea(est))["sun_enu"] == (0.0, 1.0, 0.0)
    assert decode_binary(encode_binary(est))["sun_enu"] == pytest.approx((0.0, 1.0, 0.0), abs=1e-12)
