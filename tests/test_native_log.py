"""Native log (MCAP): round trips, what other MCAP readers see, truncation, corruption, non-logs.

Tolerances: images go through JPEG, so a round trip is checked against the original at quality 95
with mean absolute difference < JPEG_MEAN_ABS; frames read from a cut or damaged log are checked
against the same log read whole, where the decoded images must be identical. Everything else
round-trips exactly, except degrees <-> radians (EXACT_F64) and seconds <-> integer ns (1 ns).
"""

from __future__ import annotations

import base64
import dataclasses
import errno
import io
import json
import logging
import math
import os
import signal
import stat
import struct
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from foxglove_schemas_protobuf.CameraCalibration_pb2 import CameraCalibration
from foxglove_schemas_protobuf.CompressedImage_pb2 import CompressedImage
from foxglove_schemas_protobuf.LocationFix_pb2 import LocationFix
from mcap.decoder import DecoderFactory as McapDecoderFactory
from mcap.reader import make_reader
from mcap.writer import Writer as McapWriter
from mcap_protobuf.decoder import DecoderFactory as ProtobufDecoderFactory

from replay import native
from replay.native import (
    FORMAT_VERSION,
    TOPIC_CALIBRATION,
    TOPIC_ESTIMATE,
    TOPIC_GNSS,
    TOPIC_HEADING,
    TOPIC_IMAGE,
    TOPIC_SUN_TRUTH,
    TOPIC_UTC,
    LogWriter,
    NativeLogSource,
    encode_calibration,
    estimate_from_dict,
    open_log,
    read_estimates,
    read_frames,
)
from replay.sources import open_frames
from rig.errors import EmptyLogError, LogError, ValidationError
from rig.types import Attitude, Frame, GnssFix, HeadingRef, Intrinsics, SunEstimate
from tests.tolerances import EXACT_F64, JPEG_MEAN_ABS

ROOT = Path(__file__).resolve().parents[1]
W, H = 64, 48
INTR = Intrinsics(fx=50.0, fy=51.0, cx=31.5, cy=24.25, width=W, height=H)
UTC0 = 1_317_042_145_964_389_123  # 2011-09-26T13:02:25.964389123Z, ns precision on purpose
NS = 1e-9


def make_image(i: int, rng: np.random.Generator, w: int = W, h: int = H) -> np.ndarray:
    """Smooth gradients (JPEG-friendly) that differ per frame, with a seeded offset per channel."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    off = rng.uniform(0, 60, size=3)
    img = np.stack([xx * 2.0 + off[0] + i, yy * 3.0 + off[1], (xx + yy) * 1.5 + off[2]], axis=-1)
    return np.clip(img, 0, 255).astype(np.uint8)


def make_frames(n: int, seed: int = 0, *, full: bool = True, t0: float = 1234.5678) -> list[Frame]:
    rng = np.random.default_rng(seed)
    frames = []
    for i in range(n):
        extra = {}
        if full:
            el, az = rng.uniform(0.1, 1.2), rng.uniform(0, 2 * math.pi)
            extra = dict(
                attitude=Attitude(
                    heading_rad=rng.uniform(0, 2 * math.pi),
                    reference=(HeadingRef.TRUE, HeadingRef.MAGNETIC, HeadingRef.RELATIVE)[i % 3],
                    pitch_rad=rng.uniform(-0.2, 0.2),
                    roll_rad=None if i % 3 == 0 else rng.uniform(-0.1, 0.1),
                    epoch=i // 5 if i % 3 == 2 else 0,  # relative headings of two zeros
                ),
                utc_ns=UTC0 + i * 33_333_333,
                gnss=GnssFix(
                    utc_ns=UTC0 + i * 33_333_333 - 7,
                    lat_deg=49.011 + 1e-5 * i,
                    lon_deg=8.4236 - 1e-5 * i,
                    alt_m=None if i % 4 == 0 else 115.25 + i,
                ),
                sun_enu_truth=[
                    math.cos(el) * math.sin(az),
                    math.cos(el) * math.cos(az),
                    math.sin(el),
                ],
            )
        frames.append(
            Frame(
                t_mono_s=t0 + i / 30.0,
                seq=10 + i,
                image_bgr=make_image(i, rng),
                intrinsics=INTR,
                **extra,
            )
        )
    return frames


def write_log(path, frames, *, chunk_size=1 << 20, quality=95, estimates=()) -> Path:
    with LogWriter(path, chunk_size=chunk_size) as w:
        for f in frames:
            w.write_frame(f, jpeg_quality=quality)
        for e in estimates:
            w.write_estimate(e)
    return Path(path)


def mean_abs(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.abs(a.astype(np.int16) - b.astype(np.int16)).mean())


class JsonDecoderFactory(McapDecoderFactory):
    """What Foxglove does with a json channel with a jsonschema schema: parse the JSON."""

    def decoder_for(self, message_encoding, schema):
        if message_encoding == "json" and schema is not None and schema.encoding == "jsonschema":
            return json.loads
        return None


def assert_same_meta(got: Frame, want: Frame) -> None:
    """Everything but the image, to the tolerances in the module docstring."""
    assert got.seq == want.seq
    assert got.t_mono_s == pytest.approx(want.t_mono_s, abs=NS)
    assert got.intrinsics == want.intrinsics
    assert got.utc_ns == want.utc_ns
    assert got.gnss == want.gnss
    if want.attitude is None:
        assert got.attitude is None
    else:
        assert got.attitude.reference == want.attitude.reference
        assert got.attitude.epoch == want.attitude.epoch
        assert got.attitude.heading_rad == pytest.approx(want.attitude.heading_rad, abs=EXACT_F64)
        for name in ("pitch_rad", "roll_rad"):
            w = getattr(want.attitude, name)
            g = getattr(got.attitude, name)
            assert (g is None) == (w is None)
            if w is not None:
                assert g == pytest.approx(w, abs=EXACT_F64)
    if want.sun_enu_truth is None:
        assert got.sun_enu_truth is None
    else:
        np.testing.assert_array_equal(got.sun_enu_truth, want.sun_enu_truth)


def assert_same_frames(got: list[Frame], want: list[Frame]) -> None:
    """Frames read from one log vs another copy of it: metadata and decoded images identical."""
    assert [f.seq for f in got] == [f.seq for f in want]
    for g, w in zip(got, want, strict=True):
        assert_same_meta(g, w)
        np.testing.assert_array_equal(g.image_bgr, w.image_bgr)


# ---------------------------------------------------------------------------------------------
# Round trips


def test_round_trip_all_fields(tmp_path):
    frames = make_frames(12)
    path = write_log(tmp_path / "a.mcap", frames)
    src = open_log(path)
    got = list(src)
    assert len(got) == len(frames)
    for g, w in zip(got, frames, strict=True):
        assert_same_meta(g, w)
        assert g.image_bgr.dtype == np.uint8 and g.image_bgr.shape == (H, W, 3)
        assert mean_abs(g.image_bgr, w.image_bgr) < JPEG_MEAN_ABS
    # a different frame's image is much further away than the JPEG error: the check can fail
    assert mean_abs(got[0].image_bgr, frames[5].image_bgr) > 3 * JPEG_MEAN_ABS
    assert src.stats.frames_read == 12 and src.stats.corrupt_skipped == 0
    assert not src.truncated
    assert src.info.metadata["format_version"] == FORMAT_VERSION


def test_frames_without_attitude_gnss_utc_or_truth(tmp_path):
    frames = make_frames(5, seed=3, full=False)
    path = write_log(tmp_path / "bare.mcap", frames)
    got = list(read_frames(path))
    assert len(got) == 5
    for g, w in zip(got, frames, strict=True):
        assert_same_meta(g, w)
        assert (
            g.attitude is None and g.gnss is None and g.utc_ns is None and g.sun_enu_truth is None
        )
    with open(path, "rb") as f:
        topics = {c.topic for c in make_reader(f).get_summary().channels.values()}
    # Every per-frame channel is declared with the first frame, used or not (docs/log-format.md).
    assert topics == {TOPIC_IMAGE, TOPIC_CALIBRATION, TOPIC_HEADING, TOPIC_GNSS, TOPIC_UTC, TOPIC_SUN_TRUTH}


def test_mixed_optional_fields_do_not_leak_between_frames(tmp_path):
    full = make_frames(6, seed=4)
    bare = make_frames(6, seed=4, full=False)
    mixed = [full[i] if i % 2 else bare[i] for i in range(6)]
    got = list(read_frames(write_log(tmp_path / "mixed.mcap", mixed)))
    for g, w in zip(got, mixed, strict=True):
        assert_same_meta(g, w)


def test_intrinsics_change_mid_log(tmp_path):
    other = Intrinsics(fx=70.0, fy=70.0, cx=40.0, cy=30.0, width=80, height=60)
    rng = np.random.default_rng(7)
    frames = make_frames(4, seed=5)
    frames += [
        Frame(
            t_mono_s=2000.0 + i, seq=100 + i, image_bgr=make_image(i, rng, 80, 60), intrinsics=other
        )
        for i in range(3)
    ]
    frames.append(Frame(t_mono_s=2010.0, seq=200, image_bgr=make_image(9, rng), intrinsics=INTR))
    path = write_log(tmp_path / "k.mcap", frames)
    got = list(read_frames(path))
    assert [g.intrinsics for g in got] == [f.intrinsics for f in frames]
    assert [g.image_bgr.shape for g in got] == [f.image_bgr.shape for f in frames]
    with open(path, "rb") as f:
        calib = [m for _, _, m in make_reader(f).iter_messages(topics=[TOPIC_CALIBRATION])]
    # first frame and each change, not every frame (one chunk here)
    assert [m.sequence for m in calib] == [10, 100, 200]


def test_estimates_round_trip(tmp_path):
    rng = np.random.default_rng(11)
    tokens = rng.normal(size=(4, 3))
    tokens /= np.linalg.norm(tokens, axis=1, keepdims=True)
    ests = [
        SunEstimate(
            t_mono_s=1235.0 + i,
            seq=20 + i,
            sun_enu=[0.0, 0.6, 0.8],
            heading_rad=0.3 * i,
            heading_ref=HeadingRef.RELATIVE,
            spread_rad=0.05,
            n_frames=8,
            n_tokens=4,
            aggregator="transformer",
            utc_ns=UTC0 + i,
            truth_enu=[0.6, 0.0, 0.8],
            token_enu=tokens,
            heading_epoch=i,
        )
        for i in range(3)
    ]
    ests.append(
        SunEstimate(
            t_mono_s=1240.0,
            seq=30,
            sun_enu=[1.0, 0.0, 0.0],
            heading_rad=1.0,
            heading_ref=HeadingRef.TRUE,
            spread_rad=math.pi,
            n_frames=1,
            n_tokens=1,
            aggregator="meanshift",
        )
    )
    frames = make_frames(3)
    path = write_log(tmp_path / "e.mcap", frames, estimates=ests)
    dicts = list(read_estimates(path))
    assert len(dicts) == len(ests)
    for d, e in zip(dicts, ests, strict=True):
        for key, value in e.to_json_dict().items():
            assert d[key] == value, key
        back = estimate_from_dict(d)
        assert back.seq == e.seq and back.t_mono_s == e.t_mono_s
        assert back.utc_ns == e.utc_ns
        assert back.heading_ref == e.heading_ref and back.aggregator == e.aggregator
        assert back.heading_epoch == e.heading_epoch
        np.testing.assert_allclose(back.sun_enu, e.sun_enu, atol=1e-7)
        assert back.heading_rad == pytest.approx(e.heading_rad, abs=EXACT_F64)
        assert back.spread_rad == pytest.approx(e.spread_rad, abs=EXACT_F64)
        if e.token_enu is not None:
            np.testing.assert_array_equal(back.token_enu, e.token_enu)
        if e.truth_enu is not None:
            np.testing.assert_allclose(back.truth_enu, e.truth_enu, atol=1e-7)
    # estimates on their own channel do not disturb frame replay
    assert len(list(read_frames(path))) == 3


def test_estimate_from_dict_names_a_missing_field():
    with pytest.raises(ValidationError, match="seq"):
        estimate_from_dict({"t": 1.0})


# ---------------------------------------------------------------------------------------------
# What other MCAP readers (Foxglove, the mcap library) see


def test_layout_seen_by_the_mcap_library(tmp_path):
    frames = make_frames(6)
    path = write_log(tmp_path / "l.mcap", frames)
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[ProtobufDecoderFactory(), JsonDecoderFactory()])
        header = reader.get_header()
        assert header.profile == "sunrig" and header.library.startswith("sunrig/")
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        assert meta["sunrig"]["format_version"] == "1"
        summary = reader.get_summary()
        by_topic = {c.topic: c for c in summary.channels.values()}
        expect = {
            TOPIC_IMAGE: ("foxglove.CompressedImage", "protobuf"),
            TOPIC_CALIBRATION: ("foxglove.CameraCalibration", "protobuf"),
            TOPIC_GNSS: ("foxglove.LocationFix", "protobuf"),
            TOPIC_HEADING: ("sunrig.Attitude", "json"),
            TOPIC_UTC: ("sunrig.UtcTime", "json"),
            TOPIC_SUN_TRUTH: ("sunrig.SunTruth", "json"),
        }
        assert set(by_topic) == set(expect)
        for topic, (schema_name, encoding) in expect.items():
            ch = by_topic[topic]
            assert summary.schemas[ch.schema_id].name == schema_name
            assert ch.message_encoding == encoding
            want_schema_enc = "protobuf" if encoding == "protobuf" else "jsonschema"
            assert summary.schemas[ch.schema_id].encoding == want_schema_enc
        counts = {
            by_topic[t].topic: summary.statistics.channel_message_counts[by_topic[t].id]
            for t in by_topic
        }
        assert counts[TOPIC_IMAGE] == 6 and counts[TOPIC_CALIBRATION] == 1

        by_seq: dict[int, list[str]] = {}
        for _, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            frame = next(fr for fr in frames if fr.seq == message.sequence)
            t_ns = round(frame.t_mono_s * 1e9)
            assert message.log_time == message.publish_time == t_ns
            by_seq.setdefault(message.sequence, []).append(channel.topic)
            if channel.topic == TOPIC_IMAGE:
                assert decoded.format == "jpeg" and decoded.frame_id == "camera"
                assert decoded.timestamp.seconds * 10**9 + decoded.timestamp.nanos == t_ns
            elif channel.topic == TOPIC_GNSS:
                assert (
                    decoded.timestamp.seconds * 10**9 + decoded.timestamp.nanos == frame.gnss.utc_ns
                )
                assert decoded.latitude == frame.gnss.lat_deg
            elif channel.topic == TOPIC_CALIBRATION:
                assert list(decoded.K) == [50.0, 0, 31.5, 0, 51.0, 24.25, 0, 0, 1]
                assert decoded.distortion_model == "plumb_bob" and list(decoded.D) == [0.0] * 5
                assert (decoded.width, decoded.height) == (W, H)
            elif channel.topic == TOPIC_HEADING:
                assert decoded["heading_deg"] == pytest.approx(
                    math.degrees(frame.attitude.heading_rad)
                )
                assert decoded["seq"] == frame.seq
                if frame.attitude.roll_rad is None:
                    assert decoded["roll_deg"] is None
    # the image comes last in each frame, so a streaming reader can emit the frame on it
    assert all(topics[-1] == TOPIC_IMAGE for topics in by_seq.values())
    assert len(by_seq) == 6


def test_calibration_repeats_at_each_chunk_and_chunks_hold_whole_frames(tmp_path):
    frames = make_frames(20)
    path = write_log(tmp_path / "c.mcap", frames, chunk_size=3000)
    with open(path, "rb") as f:
        reader = make_reader(f)
        n_chunks = len(reader.get_summary().chunk_indexes)
        calib = [m.sequence for _, _, m in reader.iter_messages(topics=[TOPIC_CALIBRATION])]
    assert n_chunks > 3
    assert len(calib) == n_chunks  # once per chunk, constant intrinsics
    assert len(list(read_frames(path))) == 20


# ---------------------------------------------------------------------------------------------
# Truncated logs


def test_finished_log_cut_anywhere_replays_a_growing_prefix(tmp_path, caplog):
    frames = make_frames(30)
    path = write_log(tmp_path / "full.mcap", frames, chunk_size=2500)
    whole = list(read_frames(path))
    data = path.read_bytes()
    counts = []
    for frac in np.linspace(0.1, 0.95, 18):
        cut = tmp_path / f"cut{frac:.3f}.mcap"
        cut.write_bytes(data[: int(len(data) * frac)])
        src = open_log(cut)
        with caplog.at_level(logging.WARNING, logger="replay.native"):
            caplog.clear()
            got = list(src)
        assert got, f"cut at {frac:.0%} replayed nothing"
        assert_same_frames(got, whole[: len(got)])
        if len(got) < len(whole):
            assert src.truncated
            assert any(
                "ends early" in r.getMessage() or "cut off" in r.getMessage() or "not closed" in r.getMessage()
                for r in caplog.records
            )
        counts.append(len(got))
    assert counts == sorted(counts)  # the prefix grows with the cut point
    assert counts[0] < counts[-1]
    # at 50% about half of the frames survive (chunks hold ~2-3 frames here)
    assert 0.3 * len(frames) < counts[len(counts) // 2] < 0.8 * len(frames)


def test_a_log_ending_after_a_whole_record_is_said_to_be_unclosed_not_cut_mid_record(tmp_path, caplog):
    # A file that ends where a record ends (a recording killed, or cut back to its last chunk after
    # a full disk) was said to be cut off mid-write, "its last record is incomplete": none was.
    frames = make_frames(12)
    path = write_log(tmp_path / "full.mcap", frames, chunk_size=2500)
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    data = path.read_bytes()
    third = chunks[2].chunk_start_offset + chunks[2].chunk_length + chunks[2].message_index_length
    said = {}
    for name, end in (("boundary", third), ("mid-record", third - 30)):
        cut = tmp_path / f"{name}.mcap"
        cut.write_bytes(data[:end])
        src = open_log(cut)
        with caplog.at_level(logging.WARNING, logger="replay.native"):
            caplog.clear()
            got = list(src)
        assert src.truncated and got
        (said[name],) = [r.getMessage() for r in caplog.records]
    assert "\n" not in said["boundary"]
    assert f"ends after a complete record, at byte {third}, without its summary" in said["boundary"]
    assert "a recording that was not closed" in said["boundary"] and "incomplete" not in said["boundary"]
    assert f"cut off mid-write (its last record is incomplete, at byte {third - 30})" in said["mid-record"]


@pytest.mark.parametrize("zeros", ["at-a-record", "at-a-record-9", "in-a-chunk", "in-a-record-header",
                                   "from-a-block"])
def test_a_log_ending_in_zeros_after_a_power_cut_replays_what_it_holds_and_says_so(tmp_path, caplog, zeros):
    # A file system that had made the file longer but never wrote its data (ext4 after a power
    # cut) leaves zeros where the last chunk was being written. They were read as records of
    # opcode 0 (a log "not closed", when they came in nines), or the chunk they cut short as a
    # corrupt chunk, skipped and counted; what they are was said by none of it.
    path = write_log(tmp_path / "full.mcap", make_frames(30), chunk_size=2500)
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    data = path.read_bytes()
    last = chunks[5]
    end = last.chunk_start_offset + last.chunk_length + last.message_index_length  # a record ends here
    start, length = {
        "at-a-record": (end, 3000),
        "at-a-record-9": (end, 9 * 333),
        "in-a-chunk": (chunks[6].chunk_start_offset + 100, chunks[6].chunk_length + 500),
        "in-a-record-header": (chunks[6].chunk_start_offset + 3, 5000),
        "from-a-block": ((end // 4096 + 1) * 4096, 4096),
    }[zeros]
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[:start])
    want = list(read_frames(cut))  # the complete chunks before the zeros
    zeroed = tmp_path / "zeroed.mcap"
    zeroed.write_bytes(data[:start] + bytes(length))
    src = open_log(zeroed)
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        got = list(src)
    assert len(want) >= 10 and src.truncated and src.stats.corrupt_skipped == 0
    assert_same_frames(got, want)
    (said,) = [r.getMessage() for r in caplog.records if "zeroed.mcap" in r.getMessage()]
    z = len(data[:start].rstrip(b"\0"))  # the log's own bytes may end in zeros too (a length's high bytes)
    assert f"ends in {start + length - z} bytes of zeros from byte {z}" in said and "power cut" in said, said
    assert "\n" not in said


@pytest.mark.parametrize(("content", "needle"), [
    (b"", "it is empty, 0 bytes: a recording stopped, or its power cut, before its first chunk was written"),
    (bytes(8192), "it is 8192 bytes of zeros"),
    (native.MCAP_MAGIC + bytes(4000), "ends in 4000 bytes of zeros from byte 8, before its first complete chunk"),
], ids=["empty", "zeros", "magic-then-zeros"])
def test_a_power_cut_recording_that_holds_nothing_is_refused_saying_what_it_is(tmp_path, content, needle):
    # A file of zeros only was "not an MCAP log (it starts with bytes 00 00 ...)", and an empty one
    # "the recording never started", of a recording that did start.
    path = tmp_path / "cut.mcap"
    path.write_bytes(content)
    with pytest.raises(EmptyLogError, match="holds no frames") as info:
        open_log(path)
    assert needle in str(info.value) and "\n" not in str(info.value)


def test_a_log_still_being_written_replays_what_it_held_and_says_so(tmp_path, caplog):
    # A recording in progress, replayed while it grows: the reader read on into chunks written
    # after it opened the file, then said the log was "cut off mid-write" at a byte it had long
    # read past (the size when it opened), of a log that was never cut.
    frames = make_frames(24)
    path = tmp_path / "live.mcap"
    with LogWriter(path, chunk_size=4000) as w:  # chunks of 2 frames
        for f in frames[:13]:
            w.write_frame(f, jpeg_quality=95)
        held = path.read_bytes()  # what the file holds when the replay opens it
        (tmp_path / "held.mcap").write_bytes(held)
        want = list(read_frames(tmp_path / "held.mcap"))
        source = open_log(path)
        replay = iter(source)
        with caplog.at_level(logging.WARNING, logger="replay.native"):
            got = [next(replay)]
            for f in frames[13:]:  # the recording goes on while it is replayed
                w.write_frame(f, jpeg_quality=95)
            w.flush()
            got += list(replay)
    assert len(want) == 12  # the frame in the chunk in progress is not in the file yet
    assert_same_frames(got, want)
    assert source.truncated and source.stats.bytes_read == len(held)
    said = [r.getMessage() for r in caplog.records if "live.mcap" in r.getMessage()]
    assert len(said) == 1 and "\n" not in said[0], said
    assert "still being written" in said[0] and f"{len(held)} bytes" in said[0] and "cut off" not in said[0]


def test_a_log_of_estimates_only_says_how_it_was_made(tmp_path):
    # `sunrig run --record` without --record-frames: sunrig's own file, but nothing to replay.
    from tests.test_protocol import make_estimate

    path = tmp_path / "est.mcap"
    with LogWriter(path) as w:
        w.write_estimate(make_estimate(10.0, 20.0, seq=1))
    with pytest.raises(LogError, match="holds estimates only .*--record-frames"):
        list(read_frames(path))


def test_a_log_closed_before_its_first_frame_says_so_and_a_foreign_empty_one_does_not(tmp_path):
    # A recording stopped before the camera sent a frame: sunrig's own, whole, and empty. It was
    # called "not a sunrig log ... pass a file written by sunrig record/synth".
    path = tmp_path / "empty.mcap"
    with LogWriter(path):
        pass
    with pytest.raises(EmptyLogError, match=r"empty.mcap holds no frames \(a sunrig log whose recording stopped"):
        open_log(path)
    foreign = tmp_path / "foreign.mcap"
    _foreign_mcap(foreign, finish=True, topic=None)
    with pytest.raises(LogError, match=f"foreign.mcap is an MCAP log but not a sunrig log: it has no {TOPIC_IMAGE} "):
        open_log(foreign)


def test_cut_inside_the_first_chunk_is_a_clear_error(tmp_path):
    path = write_log(tmp_path / "full.mcap", make_frames(5))
    data = path.read_bytes()
    cut = tmp_path / "early.mcap"
    cut.write_bytes(data[:200])  # header and metadata only
    with pytest.raises(EmptyLogError, match="cut off before its first complete chunk") as info:
        open_log(cut)
    assert "\n" not in str(info.value)


def test_writer_never_closed_replays_its_finished_chunks(tmp_path):
    frames = make_frames(25)
    reference = list(read_frames(write_log(tmp_path / "ref.mcap", frames, chunk_size=2500)))
    stream = io.BytesIO()
    w = LogWriter(stream, chunk_size=2500)
    snapshots = []
    for i, f in enumerate(frames):
        w.write_frame(f, jpeg_quality=95)
        if i in (8, 16, 24):
            snapshots.append(stream.getvalue())  # what a killed process leaves on disk
    counts = []
    for k, blob in enumerate(snapshots):
        p = tmp_path / f"killed{k}.mcap"
        p.write_bytes(blob)
        src = open_log(p)
        got = list(src)
        assert src.truncated
        assert got
        assert_same_frames(got, reference[: len(got)])
        counts.append(len(got))
    assert counts == sorted(counts) and counts[0] < counts[-1]
    assert counts[0] <= 9 and counts[-1] <= 25
    w.close()
    assert not stream.closed  # a stream handed in stays the caller's
    p = tmp_path / "closed.mcap"
    p.write_bytes(stream.getvalue())
    src = open_log(p)
    assert_same_frames(list(src), reference)
    assert not src.truncated


def test_process_killed_mid_recording(tmp_path):
    path = tmp_path / "killed.mcap"
    script = (
        "import os, signal, sys\n"
        f"sys.path.insert(0, {str(ROOT)!r})\n"
        "from tests.test_native_log import make_frames\n"
        "from replay.native import LogWriter\n"
        "w = LogWriter(sys.argv[1], chunk_size=2500)\n"
        "for f in make_frames(23):\n"
        "    w.write_frame(f, jpeg_quality=95)\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script, str(path)], cwd=ROOT, timeout=120, capture_output=True
    )
    assert proc.returncode == -signal.SIGKILL, proc.stderr.decode()[-2000:]
    reference = list(
        read_frames(write_log(tmp_path / "ref.mcap", make_frames(23), chunk_size=2500))
    )
    src = open_log(path)
    got = list(src)
    assert src.truncated
    assert 0 < len(got) <= 23
    assert_same_frames(got, reference[: len(got)])


def test_each_finished_chunk_is_synced_to_the_disk(tmp_path, monkeypatch):
    # A power cut (a rig's ignition switched off) loses what the OS had not yet written back, up
    # to half a minute on Linux: handed to the OS only, every chunk of those last seconds went
    # with it, where a killed process loses only the chunk in progress.
    synced: list[int] = []  # the file's size at each fsync of it
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        synced.append(os.fstat(fd).st_size)
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    path = write_log(tmp_path / "synced.mcap", make_frames(12), chunk_size=2500)
    monkeypatch.undo()
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    ends = [c.chunk_start_offset + c.chunk_length for c in chunks]
    starts = [c.chunk_start_offset for c in chunks[1:]] + [path.stat().st_size]
    assert len(chunks) > 3
    for end, next_start in zip(ends, starts, strict=True):
        assert any(end <= size <= next_start for size in synced), (end, synced)
    assert synced[-1] == path.stat().st_size  # the summary too, at close


def test_a_new_logs_folder_entry_is_synced_with_its_first_chunk(tmp_path, monkeypatch):
    # The chunks were synced but not the folder's entry for the new file: a power cut in the
    # first seconds of a recording could lose the file itself, every synced chunk with it.
    synced: list[tuple[bool, int]] = []  # (a folder?, the log's size then) at each fsync
    real_fsync = os.fsync
    path = tmp_path / "new.mcap"

    def fsync(fd: int) -> None:
        synced.append((stat.S_ISDIR(os.fstat(fd).st_mode), path.stat().st_size))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    write_log(path, make_frames(12), chunk_size=2500)
    monkeypatch.undo()
    folders = [i for i, (is_dir, _) in enumerate(synced) if is_dir]
    assert folders == [1], synced  # once: right after the first chunk, the file's first sync


def test_a_log_written_to_a_device_that_cannot_sync_is_written(tmp_path):
    # `record --out /dev/null --overwrite`, a check of the rig that keeps nothing: the null
    # device (as a pipe) refuses fsync with EINVAL, which is no failure of the write.
    with LogWriter(os.devnull, chunk_size=2500) as w:
        for f in make_frames(6):
            w.write_frame(f)
    assert w.frames_written == 6


def test_the_writer_says_how_much_of_its_log_is_on_the_disk(tmp_path, monkeypatch):
    # The recorder worked out what a full disk left of a recording from the file's size after each
    # write, as the writer did not say: the end of its last finished and synced chunk, and the
    # frames and estimates before it.
    from tests.test_protocol import make_estimate

    synced: list[int] = []  # the log's size at each fsync of it
    real_fsync = os.fsync

    def fsync(fd: int) -> None:
        if stat.S_ISREG(os.fstat(fd).st_mode):
            synced.append(os.fstat(fd).st_size)
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", fsync)
    path = tmp_path / "growing.mcap"
    w = LogWriter(path, chunk_size=2500)
    assert w.on_disk == native.LogOnDisk(size_bytes=0, frames=0, estimates=0)  # the header is not synced
    reported, cuts = [w.on_disk], [b""]
    for i, f in enumerate(make_frames(12)):
        w.write_frame(f, jpeg_quality=95)
        if i % 4 == 1:
            w.write_estimate(make_estimate(10.0, 20.0, seq=f.seq))
        if w.on_disk not in reported:
            reported.append(w.on_disk)
            cuts.append(path.read_bytes()[: w.on_disk.size_bytes])
    before = w.on_disk
    w.write_estimate(make_estimate(10.0, 20.0, seq=99))
    assert w.on_disk == before  # the chunk in progress is not on the disk
    w.flush()
    assert w.on_disk == native.LogOnDisk(path.stat().st_size, 12, 4) and synced[-1] == path.stat().st_size
    monkeypatch.undo()
    assert len(reported) > 4
    for on_disk, blob in zip(reported[1:], cuts[1:], strict=True):
        assert on_disk.size_bytes in synced
        cut = tmp_path / f"cut{on_disk.size_bytes}.mcap"
        cut.write_bytes(blob)
        assert len(list(read_frames(cut))) == on_disk.frames, on_disk
        assert len(list(read_estimates(cut))) == on_disk.estimates, on_disk
    w.close()
    assert w.on_disk == native.LogOnDisk(path.stat().st_size, 12, 4)  # the summary too


class _SmallDisk(io.FileIO):
    """FAKE file system of ``free`` bytes for the file it opens: as Linux writes to a full disk, a
    write that does not fit writes what fits and the next one fails with ENOSPC."""

    free = 0

    def write(self, b) -> int:
        data = bytes(b)
        if data and _SmallDisk.free <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = super().write(data[:_SmallDisk.free])
        _SmallDisk.free -= n
        return n


@pytest.fixture
def small_disk(monkeypatch) -> type[_SmallDisk]:
    """Every log a LogWriter opens is on a _SmallDisk; set ``free`` before the log is made."""

    def fake_open(file, mode="r", *args, **kwargs):
        if "w" not in mode and "x" not in mode:
            return open(file, mode, *args, **kwargs)
        return io.BufferedWriter(_SmallDisk(file, mode.replace("b", "")))

    monkeypatch.setattr(native, "open", fake_open, raising=False)
    monkeypatch.setattr(_SmallDisk, "free", 10**9)
    return _SmallDisk


@pytest.mark.parametrize("freed", [False, True])
def test_a_log_whose_disk_filled_is_abandoned_at_its_last_synced_chunk(tmp_path, small_disk, caplog, freed):
    # After a write the disk had no room for, close() still wrote the summary and footer, behind
    # the part chunk, when space had been freed since (and failed when not): the recorder then cut
    # the file back itself. abandon() writes neither and keeps only what on_disk counts.
    from tests.test_protocol import make_estimate

    path = tmp_path / "filled.mcap"
    w = LogWriter(path, chunk_size=1)  # a chunk per estimate
    for seq in range(3):
        w.write_estimate(make_estimate(10.0, 20.0, seq=seq))
    small_disk.free = 40  # the start of the next chunk fits
    with pytest.raises(OSError, match="No space left"):
        for seq in range(3, 10):
            w.write_estimate(make_estimate(10.0, 20.0, seq=seq))
    kept = w.on_disk
    assert (kept.frames, kept.estimates) == (0, 3) and path.stat().st_size > kept.size_bytes
    if freed:
        small_disk.free = 10**9
    w.abandon()
    w.abandon()
    assert w.closed and w.on_disk == kept
    assert path.stat().st_size == kept.size_bytes
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        assert [d["seq"] for d in read_estimates(path)] == [0, 1, 2]
    assert not [r for r in caplog.records if "damaged" in r.getMessage() or "corrupt" in r.getMessage()]
    with pytest.raises(LogError, match="closed"):
        w.write_estimate(make_estimate(10.0, 20.0, seq=11))


def test_a_close_the_disk_has_no_room_for_leaves_the_log_at_its_last_synced_chunk(tmp_path, small_disk, caplog):
    # The chunk in progress and the summary did not fit: close() raised, and left the part of them
    # that fitted in the file, a record cut short that replays as a log cut off mid-write.
    from tests.test_protocol import make_estimate

    path = tmp_path / "full-at-close.mcap"
    w = LogWriter(path, chunk_size=2500)
    for f in make_frames(11):
        w.write_frame(f, jpeg_quality=95)
    kept = w.on_disk
    assert 0 < kept.frames < 11
    w.write_estimate(make_estimate(10.0, 20.0, seq=99))
    small_disk.free = 100
    with pytest.raises(OSError, match="No space left"):
        w.close()
    assert w.closed and w.on_disk == kept and path.stat().st_size == kept.size_bytes
    src = open_log(path)
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        assert len(list(src)) == kept.frames
    (said,) = [r.getMessage() for r in caplog.records]
    assert "a recording that was not closed" in said, said


def test_an_abandoned_log_keeps_its_finished_chunks_and_drops_the_one_in_progress(tmp_path):
    frames = make_frames(12)
    path = tmp_path / "abandoned.mcap"
    w = LogWriter(path, chunk_size=2500)
    for f in frames:
        w.write_frame(f, jpeg_quality=95)
        if w.on_disk.frames > 3 and w.on_disk.frames < w.frames_written:
            break  # a chunk in progress
    kept = w.on_disk
    assert 0 < kept.frames < w.frames_written
    w.abandon()
    w.close()  # closed already: no summary after all
    assert path.stat().st_size == kept.size_bytes
    src = open_log(path)
    assert len(list(src)) == kept.frames and src.truncated
    empty = LogWriter(tmp_path / "empty.mcap")
    empty.write_frame(frames[0])
    empty.abandon()  # no chunk finished: nothing kept, the file is the caller's to remove
    assert empty.on_disk.size_bytes == 0 and (tmp_path / "empty.mcap").stat().st_size == 0
    stream = io.BytesIO()
    w = LogWriter(stream, chunk_size=2500)
    for f in frames:
        w.write_frame(f, jpeg_quality=95)
    held = stream.getvalue()
    w.abandon()
    assert not stream.closed and stream.getvalue() == held  # the owner's to cut back


# ---------------------------------------------------------------------------------------------
# Corrupt messages and chunks


def test_corrupt_jpeg_is_skipped_counted_and_warned(tmp_path, monkeypatch, caplog):
    frames = make_frames(8)
    bad = CompressedImage(data=b"\xff\xd8 definitely not a jpeg", format="jpeg").SerializeToString()
    path = tmp_path / "badjpeg.mcap"
    with LogWriter(path) as w:
        for f in frames:
            if f.seq == 13:
                monkeypatch.setattr(native, "encode_image", lambda *a: bad)
            w.write_frame(f, jpeg_quality=95)
            monkeypatch.undo()
    src = open_log(path)
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        got = list(src)
    assert [g.seq for g in got] == [f.seq for f in frames if f.seq != 13]
    assert src.stats.corrupt_skipped == 1 and src.stats.frames_read == 7
    assert not src.truncated
    assert any("corrupt" in r.getMessage() and "seq 13" in r.getMessage() for r in caplog.records)
    # the frame after the bad one did not inherit its heading
    after = next(g for g in got if g.seq == 14)
    assert_same_meta(after, frames[4])


def test_messages_of_a_frame_whose_image_is_missing_stay_with_it(tmp_path, monkeypatch):
    full = make_frames(4, seed=8)
    bare = make_frames(4, seed=8, full=False)
    frames = [full[0], full[1], bare[2], full[3]]  # seq 11 loses its image; seq 12 has no extras
    path = tmp_path / "noimage.mcap"
    real_add = LogWriter._add

    def drop_image_11(self, topic, t_ns, seq, data):
        if not (topic == TOPIC_IMAGE and seq == 11):
            real_add(self, topic, t_ns, seq, data)

    monkeypatch.setattr(LogWriter, "_add", drop_image_11)
    write_log(path, frames)
    monkeypatch.undo()
    got = list(read_frames(path))
    assert [g.seq for g in got] == [10, 12, 13]
    for g, w in zip(got, [frames[0], frames[2], frames[3]], strict=True):
        assert_same_meta(g, w)  # seq 12 did not pick up seq 11's heading, fix, UTC or truth


def test_channels_of_other_tools_are_ignored_not_counted(tmp_path):
    frames = make_frames(3)
    path = tmp_path / "extra.mcap"
    with LogWriter(path) as w:
        # another recorder's channel in the same file (reaching into the writer is test-only)
        sid = w._mcap.register_schema("other.Thing", "jsonschema", b"{}")
        cid = w._mcap.register_channel("/other", "json", sid)
        for f in frames:
            w._mcap.add_message(cid, log_time=1, publish_time=1, data=b"{}", sequence=0)
            w.write_frame(f, jpeg_quality=95)
    src = open_log(path)
    assert_same_frames(list(src), list(read_frames(write_log(tmp_path / "plain.mcap", frames))))
    assert src.stats.corrupt_skipped == 0


@pytest.mark.parametrize("bad", [b"{not json",
                                 # a heading no writer gives: it wrapped to some angle and was graded
                                 b'{"heading_deg": 1e308, "reference": "true", "seq": 12}'])
def test_corrupt_heading_drops_only_that_message(tmp_path, monkeypatch, bad):
    frames = make_frames(5)
    path = tmp_path / "badjson.mcap"
    with LogWriter(path) as w:
        for f in frames:
            if f.seq == 12:
                monkeypatch.setattr(native, "encode_attitude", lambda *a: bad)
            w.write_frame(f)
            monkeypatch.undo()
    src = open_log(path)
    got = list(src)
    assert [g.seq for g in got] == [f.seq for f in frames]
    assert got[2].attitude is None and got[2].gnss == frames[2].gnss
    assert got[3].attitude is not None
    assert src.stats.corrupt_skipped == 1


def _log_with_message_of_seq_12(path, frames, monkeypatch, encoder, payload):
    """A log of ``frames`` in which ``encoder`` (of replay.native) wrote ``payload`` for seq 12."""
    with LogWriter(path) as w:
        for f in frames:
            if f.seq == 12:
                monkeypatch.setattr(native, encoder, lambda *a: payload)
            w.write_frame(f)
            monkeypatch.undo()
    return path


_DEEP_JSON = b"[" * 100_000 + b"]" * 100_000  # valid JSON, nested past the decoder's recursion limit


@pytest.mark.parametrize(("encoder", "field"), [("encode_attitude", "attitude"), ("encode_utc", "utc_ns"),
                                                ("encode_sun_truth", "sun_enu_truth")])
def test_a_json_message_nested_too_deep_is_skipped_as_corrupt(tmp_path, monkeypatch, caplog, encoder, field):
    # A crafted payload [[[[...]]]] made the JSON decoder raise RecursionError, which no reader
    # caught: replay, eval and record ended in an internal error instead of skipping one message.
    frames = make_frames(5)
    src = open_log(_log_with_message_of_seq_12(tmp_path / "deep.mcap", frames, monkeypatch, encoder, _DEEP_JSON))
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        got = list(src)
    assert [g.seq for g in got] == [f.seq for f in frames]
    assert getattr(got[2], field) is None and getattr(got[3], field) is not None
    assert src.stats.corrupt_skipped == 1
    assert any("corrupt message at seq 12" in r.getMessage() for r in caplog.records)


def test_an_estimate_nested_too_deep_is_skipped(tmp_path, monkeypatch):
    est = SunEstimate(t_mono_s=1235.0, seq=20, sun_enu=[0.0, 0.6, 0.8], heading_rad=0.3,
                      heading_ref=HeadingRef.TRUE, spread_rad=0.05, n_frames=8, n_tokens=4, aggregator="mean")
    path = tmp_path / "deep-estimate.mcap"
    with LogWriter(path) as w:
        w.write_frame(make_frames(1)[0])
        w.write_estimate(est)
        monkeypatch.setattr(native, "encode_estimate", lambda *a: _DEEP_JSON)
        w.write_estimate(dataclasses.replace(est, seq=21))
        monkeypatch.undo()
        w.write_estimate(dataclasses.replace(est, seq=22))
    assert [d["seq"] for d in read_estimates(path)] == [20, 22]


@pytest.mark.parametrize(
    ("encoder", "bad", "field"),
    [
        ("encode_utc", b'{"utc": {"sec": 1317042145, "nsec": 1000000000}, "seq": 12}', "utc_ns"),  # nsec past 1 s
        # past year 9999: it replayed, then failed as an internal error where the JSONL showed it
        ("encode_utc", b'{"utc": {"sec": 100000000000000000000, "nsec": 0}, "seq": 12}', "utc_ns"),
        ("encode_sun_truth", b'{"sun_enu": [0.0, 0.6, 0.8, 0.0], "seq": 12}', "sun_enu_truth"),  # 4 numbers
    ],
)
def test_an_out_of_range_utc_or_truth_drops_only_that_message(tmp_path, monkeypatch, encoder, bad, field):
    frames = make_frames(5)
    src = open_log(_log_with_message_of_seq_12(tmp_path / "badaux.mcap", frames, monkeypatch, encoder, bad))
    got = list(src)
    assert [g.seq for g in got] == [f.seq for f in frames]
    assert getattr(got[2], field) is None and got[2].attitude is not None
    assert src.stats.corrupt_skipped == 1


def _gnss_at(seconds: int):
    real = native.encode_gnss  # the writer's, before the test puts this one in its place

    def encode(fix: GnssFix) -> bytes:
        msg = LocationFix.FromString(real(fix))
        msg.timestamp.seconds = seconds
        return msg.SerializeToString()
    return encode


@pytest.mark.parametrize(
    ("encoder", "bad", "field"),
    [
        ("encode_utc", b'{"utc": {"sec": 10413792000, "nsec": 0}, "seq": 13}', "utc_ns"),  # 2300-01-01
        ("encode_utc", b'{"utc": {"sec": 9223372036, "nsec": 854775808}, "seq": 13}', "utc_ns"),  # 1 ns past int64
        ("encode_gnss", _gnss_at(10413792000), "gnss"),
        ("encode_gnss", _gnss_at(-10413792000), "gnss"),  # 1640
    ],
)
def test_a_time_past_what_ns_hold_drops_only_that_message(tmp_path, monkeypatch, encoder, bad, field):
    # A UTC of 2300 (the reader took 1970..9999) reached the ephemeris, which takes int64 ns
    # (1678..2262): replay of a frame with a TRUE heading and no truth of its own ended in an
    # internal OverflowError. Seq 13 has a TRUE heading; the truth is the reader's to compute.
    frames = [dataclasses.replace(f, sun_enu_truth=None) for f in make_frames(5)]
    assert frames[3].seq == 13 and frames[3].attitude.reference == HeadingRef.TRUE
    path = tmp_path / "badtime.mcap"
    real = getattr(native, encoder)
    with LogWriter(path) as w:
        for f in frames:
            if f.seq == 13:
                monkeypatch.setattr(native, encoder, bad if callable(bad) else (lambda *a: bad))
            w.write_frame(f)
            monkeypatch.setattr(native, encoder, real)
    src = open_frames(path)  # as replay, eval and train read it: with the truth from fix and UTC
    got = list(src)
    assert [g.seq for g in got] == [f.seq for f in frames]
    assert getattr(got[3], field) is None and got[3].attitude is not None
    assert got[3].sun_enu_truth is not None  # from the fix and UTC left whole
    assert src.stats.corrupt_skipped == 1


def _cut_calibration(intr: Intrinsics, t_ns: int) -> bytes:
    return b"\x0a\xff\xff"  # a protobuf field whose length runs past the message


def _distorted_calibration(intr: Intrinsics, t_ns: int) -> bytes:
    """A well-formed calibration with lens distortion, which sunrig's rectified frames never have."""
    msg = CameraCalibration.FromString(encode_calibration(intr, t_ns))
    msg.D[:] = [0.1, 0.0, 0.0, 0.0, 0.0]
    return msg.SerializeToString()


def _focal_length_of_no_camera(intr: Intrinsics, t_ns: int) -> bytes:
    """fx = fy = 1e308, as a recording made with such a calibration file holds it: its crops' side
    was inf px, and replay, eval and quantize of the log ended in an internal OverflowError."""
    msg = CameraCalibration.FromString(encode_calibration(intr, t_ns))
    msg.K[0] = msg.K[4] = msg.P[0] = msg.P[5] = 1e308
    return msg.SerializeToString()


def _size_beyond_opencv(intr: Intrinsics, t_ns: int) -> bytes:
    """A width of 2**31 px, more than OpenCV's C int holds (the field is a uint32)."""
    msg = CameraCalibration.FromString(encode_calibration(intr, t_ns))
    msg.width = 2**31
    return msg.SerializeToString()


@pytest.mark.parametrize("bad_calibration", [_cut_calibration, _distorted_calibration, _focal_length_of_no_camera,
                                             _size_beyond_opencv],
                         ids=["cut", "distorted", "focal-1e308", "width-2**31"])
def test_a_refused_calibration_drops_frames_until_the_next_one(tmp_path, monkeypatch, bad_calibration):
    # The camera's calibration changes at seq 100 and that message is refused: frames 100 and 101
    # would otherwise be read with the calibration before it (same image size, wrong fx), so they
    # are dropped until the calibration of seq 200.
    other = Intrinsics(fx=70.0, fy=70.0, cx=32.0, cy=24.0, width=W, height=H)
    rng = np.random.default_rng(7)
    frames = make_frames(3, seed=5, full=False)
    frames += [Frame(t_mono_s=2000.0 + i, seq=100 + i, image_bgr=make_image(i, rng), intrinsics=other)
               for i in range(2)]
    frames.append(Frame(t_mono_s=2010.0, seq=200, image_bgr=make_image(9, rng), intrinsics=INTR))
    path = tmp_path / "badcalib.mcap"
    with LogWriter(path) as w:
        for f in frames:
            if f.seq == 100:
                monkeypatch.setattr(native, "encode_calibration", bad_calibration)
            w.write_frame(f)
            monkeypatch.undo()
    src = open_log(path)
    got = list(src)
    assert [g.seq for g in got] == [10, 11, 12, 200]
    assert all(g.intrinsics == INTR for g in got)
    assert src.stats.corrupt_skipped == 3  # the calibration and the two images after it


@pytest.mark.parametrize("damage", ["bytes", "name-length", "records-length-sign", "uncompressed-size-sign"])
@pytest.mark.parametrize("which", ["middle", "first"])
def test_a_corrupt_chunk_loses_only_its_own_frames(tmp_path, caplog, which, damage):
    # The first chunk is where the data section declares the channels; the summary at the end
    # of a finished log repeats them, so the chunks after a damaged first one still replay.
    # "name-length": the length of the chunk's compression name, damaged, overruns the chunk;
    # read straight from the file it would have swallowed the chunks after it.
    frames = make_frames(24)
    path = write_log(tmp_path / "chunks.mcap", frames, chunk_size=2500)
    whole = list(read_frames(path))
    with open(path, "rb") as f:
        chunks = make_reader(f).get_summary().chunk_indexes
    victim = chunks[len(chunks) // 2] if which == "middle" else chunks[0]
    data = bytearray(path.read_bytes())
    if damage == "bytes":
        mid = victim.chunk_start_offset + victim.chunk_length - victim.compressed_size // 2
        data[mid : mid + 16] = bytes(b ^ 0x5A for b in data[mid : mid + 16])
    elif damage == "name-length":
        data[_chunk_name_length_at(victim) + 2] = 0x7F
    else:
        # The top bit of a 64-bit length: an OverflowError (no index holds it) ended the replay
        # as an internal error, where a CRC mismatch is a skipped chunk.
        name_length = struct.unpack_from("<I", data, _chunk_name_length_at(victim))[0]
        field_at = (_chunk_name_length_at(victim) + 4 + name_length if damage == "records-length-sign"
                    else victim.chunk_start_offset + 9 + 16)
        data[field_at + 7] |= 0x80
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    src = open_log(damaged)
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        got = list(src)
    lost = {
        fr.seq
        for fr in whole
        if victim.message_start_time <= round(fr.t_mono_s * 1e9) <= victim.message_end_time
    }
    assert lost
    assert_same_frames(got, [fr for fr in whole if fr.seq not in lost])
    assert src.stats.corrupt_skipped == 1
    assert not src.truncated
    assert any("corrupt chunk" in r.getMessage() for r in caplog.records)


def test_a_damaged_chunk_of_an_unfinished_log_loses_no_channel(tmp_path):
    # A recording cut off before its summary, one frame a chunk, whose heading and truth begin at
    # frame 5 (a compass getting its fix late). Their channels were declared in frame 5's chunk,
    # so damaging it cost every later frame its heading and truth, not only frame 5.
    frames = make_frames(5, seed=4, full=False) + make_frames(12, seed=4)[5:]
    path = tmp_path / "live.mcap"
    w = LogWriter(path, chunk_size=1)  # every frame ends its chunk and goes to the OS
    for f in frames:
        w.write_frame(f, jpeg_quality=95)
    data = bytearray(path.read_bytes())  # as a killed process leaves it: no summary
    w.close()
    chunk_starts, at = [], 8
    while at < len(data):
        opcode, length = struct.unpack_from("<BQ", data, at)
        if opcode == 0x06:
            chunk_starts.append(at)
        at += 9 + length
    assert len(chunk_starts) == len(frames)
    victim = chunk_starts[5]
    mid = victim + (chunk_starts[6] - victim) // 2
    data[mid : mid + 16] = bytes(b ^ 0x5A for b in data[mid : mid + 16])
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    src = open_log(damaged)
    got = list(src)
    assert [g.seq for g in got] == [f.seq for i, f in enumerate(frames) if i != 5]
    assert all(g.attitude is not None and g.sun_enu_truth is not None for g in got[5:])
    assert src.stats.corrupt_skipped == 1


def _chunk_name_length_at(chunk_index) -> int:
    """Where a chunk record's compression-name length is: after its opcode and length (9 bytes),
    its message start and end times and uncompressed size (24) and its CRC (4)."""
    return chunk_index.chunk_start_offset + 9 + 28


def test_a_damaged_records_length_in_a_chunk_loses_nothing(tmp_path):
    # One byte of a chunk's records-length field made it 2**47: mcap read the field straight from
    # the file, and the file object tried to allocate that much (a MemoryError that ended the
    # replay). Framed by the chunk record's own length, the records are all there and pass the
    # chunk's CRC, so nothing is lost.
    frames = make_frames(24)
    path = write_log(tmp_path / "chunks.mcap", frames, chunk_size=2500)
    whole = list(read_frames(path))
    with open(path, "rb") as f:
        victim = make_reader(f).get_summary().chunk_indexes[1]
    data = bytearray(path.read_bytes())
    name_at = _chunk_name_length_at(victim)
    field_at = name_at + 4 + struct.unpack_from("<I", data, name_at)[0]
    assert struct.unpack_from("<Q", data, field_at)[0] == victim.compressed_size
    data[field_at + 5] = 0x7F
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(bytes(data))
    src = open_log(damaged)
    assert_same_frames(list(src), whole)
    assert src.stats.corrupt_skipped == 0 and not src.truncated


# ---------------------------------------------------------------------------------------------
# Not a log


def _png_bytes() -> bytes:
    return cv2.imencode(".png", np.zeros((4, 4, 3), np.uint8))[1].tobytes()


@pytest.mark.parametrize(
    ("name", "content", "needle"),
    [
        ("random.mcap", np.random.default_rng(0).bytes(4096), "not an MCAP log"),
        ("empty.mcap", b"", "empty"),
        ("foo.png", None, "PNG signature"),
        ("notes.mcap", b'{"hello": "world"}\n', "not an MCAP log"),
        ("stub.mcap", b"\x89MCA", "cut off inside the MCAP magic"),
        ("dir.mcap", "dir", "is a directory"),
        ("missing.mcap", "missing", "does not exist"),
        # A FIFO's open waited for a writer without a word; a pipe (<(cat log.mcap)) said
        # "cannot read /dev/fd/63: None"; /dev/zero was "empty, 0 bytes".
        ("fifo.mcap", "fifo", "is not a regular file (a pipe, FIFO or device)"),
    ],
)
def test_not_a_log_raises_one_line_log_error(tmp_path, name, content, needle):
    path = tmp_path / name
    if content == "dir":
        path.mkdir()
    elif content == "fifo":
        os.mkfifo(path)
    elif content != "missing":
        path.write_bytes(_png_bytes() if content is None else content)
    for call in (
        open_log,
        NativeLogSource,
        lambda p: list(read_frames(p)),
        lambda p: list(read_estimates(p)),
    ):
        with pytest.raises(LogError) as info:
            call(path)
        msg = str(info.value)
        assert needle in msg
        assert name in msg
        assert "\n" not in msg and "\r" not in msg
        # Only a log that holds no frames may be skipped by eval and train over many logs.
        assert isinstance(info.value, EmptyLogError) == (name in ("empty.mcap", "stub.mcap"))


def _foreign_mcap(
    path: Path, *, finish: bool, topic: str | None = "/foo", schema_name: str = "foo.Bar"
) -> None:
    """Another tool's MCAP: five messages on ``topic``, or no channel at all when it is None."""
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile="", library="someone-else")
        if topic is not None:
            sid = w.register_schema(schema_name, "jsonschema", b"{}")
            cid = w.register_channel(topic, "json", sid)
            for i in range(5):
                w.add_message(cid, log_time=i, publish_time=i, data=b"{}", sequence=i)
        if finish:
            w.finish()
        else:
            w.flush()


@pytest.mark.parametrize("finish", [True, False])
def test_valid_mcap_without_sunrig_channels(tmp_path, finish):
    path = tmp_path / "other.mcap"
    _foreign_mcap(path, finish=finish)
    with pytest.raises(LogError, match=f"no {TOPIC_IMAGE} channel") as info:
        open_log(path)
    assert "/foo" in str(info.value) and "\n" not in str(info.value)
    assert list(read_estimates(path)) == []  # estimates need only an MCAP file


def test_camera_image_channel_of_another_type_is_refused(tmp_path):
    path = tmp_path / "ros.mcap"
    _foreign_mcap(path, finish=True, topic=TOPIC_IMAGE, schema_name="sensor_msgs/msg/Image")
    with pytest.raises(LogError, match="expected foxglove.CompressedImage"):
        open_log(path)


def _camera_mcap(path: Path, channels: dict[str, tuple[str, str, str]], *, finish: bool = True,
                 images: bool = True) -> None:
    """A camera recording by another tool (Foxglove's SDK, say): five images at wall-clock times
    (none without ``images``), a calibration before the first when ``channels`` has one.
    ``channels``: topic -> (schema name, schema encoding, message encoding); messages are written
    in that encoding."""
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile="", library="someone-else")
        ids = {}
        for topic, (schema_name, schema_encoding, message_encoding) in channels.items():
            spec = native.CHANNELS.get(topic)
            data = spec.schema_bytes() if spec is not None and schema_encoding == spec.schema_encoding else b"{}"
            sid = w.register_schema(schema_name, schema_encoding, data)
            ids[topic] = (w.register_channel(topic, message_encoding, sid), message_encoding)
        t0 = 1_700_000_000 * 10**9
        jpeg = cv2.imencode(".jpg", make_image(0, np.random.default_rng(0)))[1].tobytes()
        for i in range(5):
            t = t0 + i * 100_000_000
            stamp = {"sec": t // 10**9, "nsec": t % 10**9}
            messages = {
                TOPIC_CALIBRATION: (
                    encode_calibration(INTR, t),
                    {"timestamp": stamp, "frame_id": "camera", "width": W, "height": H, "distortion_model": "plumb_bob",
                     "D": [0.0] * 5, "K": [50.0, 0, 31.5, 0, 51.0, 24.25, 0, 0, 1]},
                ),
                TOPIC_IMAGE: (
                    native.encode_image(make_image(i, np.random.default_rng(0)), t, 90),
                    {"timestamp": stamp, "frame_id": "camera", "format": "jpeg",
                     "data": base64.b64encode(jpeg).decode()},
                ),
            }
            for topic in (TOPIC_CALIBRATION, TOPIC_IMAGE):
                if topic not in ids or (topic == TOPIC_CALIBRATION and i) or (topic == TOPIC_IMAGE and not images):
                    continue
                cid, encoding = ids[topic]
                pb, js = messages[topic]
                w.add_message(cid, log_time=t, publish_time=t, sequence=i,
                              data=pb if encoding == "protobuf" else json.dumps(js).encode())
        if finish:
            w.finish()
        else:
            w.flush()


_PROTOBUF_CALIBRATION = ("foxglove.CameraCalibration", "protobuf", "protobuf")
_PROTOBUF_IMAGE = ("foxglove.CompressedImage", "protobuf", "protobuf")


@pytest.mark.parametrize("finish", [True, False])
def test_a_foxglove_image_in_json_encoding_is_refused_by_name(tmp_path, finish):
    # Foxglove's schemas also come as JSON (jsonschema, base64 image data). Such a file passed
    # open_log on its schema name, then every image was passed over as another tool's channel:
    # replay said "no frame of it could be read (the warnings above say why)" with no warning, and
    # eval over a folder listed it among the logs it graded.
    path = tmp_path / "fg.mcap"
    _camera_mcap(path, {TOPIC_CALIBRATION: _PROTOBUF_CALIBRATION,
                        TOPIC_IMAGE: ("foxglove.CompressedImage", "jsonschema", "json")}, finish=finish)
    with pytest.raises(LogError) as info:
        open_log(path)
    msg = str(info.value)
    assert f"{TOPIC_IMAGE} as foxglove.CompressedImage in json encoding" in msg
    assert "protobuf" in msg and "fg.mcap" in msg and "\n" not in msg
    assert not isinstance(info.value, EmptyLogError)  # eval may not leave it out as holding nothing


@pytest.mark.parametrize("finish", [True, False])
def test_a_foxglove_camera_recording_in_protobuf_replays(tmp_path, finish):
    # Its calibration channel declared after the image channel, unlike sunrig's writer: without a
    # summary, the check on opening reads on past the image channel to find it.
    path = tmp_path / "fg.mcap"
    _camera_mcap(path, {TOPIC_IMAGE: _PROTOBUF_IMAGE, TOPIC_CALIBRATION: _PROTOBUF_CALIBRATION}, finish=finish)
    frames = list(open_log(path))
    assert [f.seq for f in frames] == list(range(5))
    assert frames[0].t_mono_s == 1_700_000_000.0 and frames[0].intrinsics == INTR


@pytest.mark.parametrize("finish", [True, False])
@pytest.mark.parametrize(
    "calibration",
    [None, ("foxglove.CameraCalibration", "jsonschema", "json"), ("sensor_msgs/msg/CameraInfo", "ros2msg", "cdr")],
    ids=["none", "json", "ros2"],
)
def test_a_camera_recording_without_a_calibration_sunrig_reads_is_refused_by_name(tmp_path, calibration, finish):
    # Foxglove CompressedImages with no calibration sunrig can read opened as a log, then every
    # image was warned about as "a corrupt message ... image without a valid calibration before
    # it", and replay ended with "no frame of it could be read ...; re-record this one": the
    # images were whole, the intrinsics missing.
    path = tmp_path / "fg.mcap"
    channels = {TOPIC_IMAGE: _PROTOBUF_IMAGE}
    if calibration is not None:
        channels[TOPIC_CALIBRATION] = calibration
    _camera_mcap(path, channels, finish=finish)
    with pytest.raises(LogError) as info:
        open_log(path)
    msg = str(info.value)
    if calibration is None:
        assert f"has no {TOPIC_CALIBRATION} channel" in msg
    else:
        assert f"{TOPIC_CALIBRATION} as {calibration[0]} in {calibration[2]} encoding" in msg
    assert "intrinsics" in msg and "foxglove.CameraCalibration" in msg and "fg.mcap" in msg and "\n" not in msg
    assert not isinstance(info.value, EmptyLogError)


def _foreign_writer(f) -> tuple[McapWriter, dict[str, int]]:
    """Another writer's MCAP, started, with sunrig's calibration, image and heading channels: the
    writer and each topic's channel id."""
    w = McapWriter(f)
    w.start(profile="", library="someone-else")
    ids = {}
    for topic in (TOPIC_CALIBRATION, TOPIC_IMAGE, TOPIC_HEADING):
        spec = native.CHANNELS[topic]
        sid = w.register_schema(spec.schema_name, spec.schema_encoding, spec.schema_bytes())
        ids[topic] = w.register_channel(topic, spec.message_encoding, sid)
    return w, ids


def _heading_after_image_mcap(path: Path, *, heading_offset_ns: int = 0, finish: bool = True,
                              sequence: str = "zero") -> list[float]:
    """Another writer's camera log whose frames write the heading after the image, at the image's
    log time plus ``heading_offset_ns``, and every message at MCAP sequence 0 (``sequence``
    "zero") or at the frame's index ("frame"); returns the heading (deg) of each of its five
    frames."""
    headings = [10.0 * i + 5.0 for i in range(5)]
    with open(path, "wb") as f:
        w, ids = _foreign_writer(f)
        t0 = 1_700_000_000 * 10**9  # wall-clock log times, as such a writer stamps them
        for i, heading in enumerate(headings):
            t = t0 + i * 100_000_000
            seq = i if sequence == "frame" else 0
            if i == 0:
                w.add_message(ids[TOPIC_CALIBRATION], log_time=t, publish_time=t, sequence=seq,
                              data=encode_calibration(INTR, t))
            w.add_message(ids[TOPIC_IMAGE], log_time=t, publish_time=t, sequence=seq,
                          data=native.encode_image(make_image(i, np.random.default_rng(0)), t, 90))
            attitude = json.dumps({"heading_deg": heading, "reference": "true", "pitch_deg": None,
                                   "roll_deg": None, "seq": seq}).encode()
            th = t + heading_offset_ns
            w.add_message(ids[TOPIC_HEADING], log_time=th, publish_time=th, sequence=seq, data=attitude)
        if finish:
            w.finish()
        else:
            w.flush()
    return headings


@pytest.mark.parametrize("finish", [True, False])
@pytest.mark.parametrize("sequence", ["zero", "frame"])
def test_a_heading_written_after_its_image_stays_with_its_frame(tmp_path, caplog, finish, sequence):
    # Every image at sequence 0 and each heading after its image: the reader paired a heading with
    # the next image of the same sequence, so every frame replayed with the heading of the frame
    # before it (a wrong sun on every turn), and only the last heading was said to be dropped.
    # With the frame's own sequence, every heading was dropped (and said to be).
    path = tmp_path / "after.mcap"
    headings = _heading_after_image_mcap(path, finish=finish, sequence=sequence)
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        frames = list(open_log(path))
    assert len(frames) == 5
    assert [round(math.degrees(f.attitude.heading_rad), 9) if f.attitude else None for f in frames] == headings
    assert "matched no image" not in caplog.text


def test_a_heading_at_another_log_time_than_its_image_is_dropped_and_said(tmp_path, caplog):
    # Its own log time (1 ms after the image's): which image it belongs to cannot be told, and a
    # heading paired with the wrong frame is a wrong sun; so none is paired, and the warning says
    # what the writer must do.
    path = tmp_path / "own-time.mcap"
    _heading_after_image_mcap(path, heading_offset_ns=1_000_000)
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        frames = list(open_log(path))
    assert len(frames) == 5 and all(f.attitude is None for f in frames)
    said = [r.getMessage() for r in caplog.records if "matched no image" in r.getMessage()]
    assert len(said) == 1 and "\n" not in said[0]
    assert f"5 {TOPIC_HEADING} messages" in said[0] and "log time and sequence" in said[0]


def _channels_and_metadata(path: Path) -> tuple[set[str], dict[str, str]]:
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return {c.topic for c in summary.channels.values()}, metadata.get(native.METADATA_NAME, {})


def test_the_bundled_demo_log_is_laid_out_as_a_drive_synth_writes_today(tmp_path):
    # The demo is what users copy, and the log-format page says every log registers each
    # per-frame channel with its first frame, an empty /gnss/fix in a log without GNSS. The
    # shipped one was written before that (and before synth recorded its render scale): it had
    # no /gnss/fix channel at all, and no render_scale.
    from replay.sources import DEMO_LOG
    from replay.synthetic import RENDER_SCALE_KEY

    today = tmp_path / "today.mcap"
    with LogWriter(today) as w:
        w.write_frame(make_frames(1, full=False)[0])
    demo_topics, demo_meta = _channels_and_metadata(DEMO_LOG)
    assert demo_topics == _channels_and_metadata(today)[0]
    assert TOPIC_GNSS in demo_topics
    # As `sunrig synth OUT --drives 1 --frames 40 --seed 3000` writes it (replay/sources.py), at the default scale.
    assert demo_meta.get(RENDER_SCALE_KEY) == "0.5"
    frames = list(read_frames(DEMO_LOG))
    assert len(frames) == 40 and all(f.gnss is None and f.utc_ns is not None and f.sun_enu_truth is not None
                                     for f in frames)  # a synthetic drive: its truth, no place


def test_newer_format_version_is_refused(tmp_path):
    path = tmp_path / "v2.mcap"
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile="sunrig", library="sunrig/9")
        w.add_metadata("sunrig", {"format_version": "2"})
        w.finish()
    with pytest.raises(LogError, match="format version 2"):
        open_log(path)


def test_a_damaged_format_version_key_warns_and_reads_the_log(tmp_path, caplog):
    # One flipped bit in the key's name refused the whole log as "version None", its data intact.
    path = write_log(tmp_path / "log.mcap", make_frames(3))
    data = path.read_bytes()
    at = data.index(b"format_version")
    damaged = tmp_path / "damaged.mcap"
    damaged.write_bytes(data[:at] + b"f" + bytes([data[at + 1] ^ 0x01]) + data[at + 2 :])
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        got = list(open_log(damaged))
    assert_same_frames(got, list(read_frames(path)))
    assert any("has no format_version (damaged?)" in r.getMessage() for r in caplog.records)


# ---------------------------------------------------------------------------------------------
# Writer contract


def test_writer_close_is_idempotent_and_refuses_writes_after(tmp_path):
    frames = make_frames(2)
    w = LogWriter(tmp_path / "w.mcap")
    w.write_frame(frames[0])
    w.close()
    w.close()
    assert w.closed
    with pytest.raises(LogError, match="closed"):
        w.write_frame(frames[1])
    assert len(list(read_frames(tmp_path / "w.mcap"))) == 1


def test_writer_on_an_unbuffered_stream_flushes_everything_and_leaves_it_open(tmp_path):
    path = tmp_path / "raw.mcap"
    with open(path, "wb", buffering=0) as raw:
        with LogWriter(raw) as w:
            for f in make_frames(3):
                w.write_frame(f)
        assert not raw.closed
        raw.write(b"")  # still usable by its owner
    src = open_log(path)
    assert len(list(src)) == 3 and not src.truncated
    with open(path, "rb") as f:  # the summary and footer reached the file too
        # one calibration, then heading, fix, UTC, truth and image per frame
        assert make_reader(f).get_summary().statistics.message_count == 1 + 3 * 5


def test_writer_closes_the_log_when_the_block_raises(tmp_path):
    path = tmp_path / "raised.mcap"
    with pytest.raises(ZeroDivisionError), LogWriter(path) as w:
        w.write_frame(make_frames(1)[0])
        1 / 0  # noqa: B018
    src = open_log(path)
    assert len(list(src)) == 1 and not src.truncated


@pytest.mark.parametrize(
    ("kwargs", "needle"),
    [({"compression": "gzip"}, "compression"), ({"chunk_size": 0}, "chunk_size")],
)
def test_writer_validates_its_options(tmp_path, kwargs, needle):
    with pytest.raises(ValidationError, match=needle):
        LogWriter(tmp_path / "x.mcap", **kwargs)


def test_writer_validates_frames(tmp_path):
    frame = make_frames(1)[0]
    with LogWriter(tmp_path / "x.mcap") as w:
        with pytest.raises(ValidationError, match="jpeg_quality"):
            w.write_frame(frame, jpeg_quality=0)
        with pytest.raises(ValidationError, match="2\\*\\*32"):
            w.write_frame(
                Frame(t_mono_s=1.0, seq=2**32, image_bgr=frame.image_bgr, intrinsics=INTR)
            )
        with pytest.raises(ValidationError, match=">= 0 s"):
            w.write_frame(Frame(t_mono_s=-1.0, seq=1, image_bgr=frame.image_bgr, intrinsics=INTR))
        with pytest.raises(ValidationError, match="expected a Frame"):
            w.write_frame("frame")  # type: ignore[arg-type]


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_every_compression_round_trips(tmp_path, compression):
    frames = make_frames(4)
    path = tmp_path / f"{compression}.mcap"
    with LogWriter(path, compression=compression, chunk_size=3000) as w:
        for f in frames:
            w.write_frame(f, jpeg_quality=95)
    got = list(read_frames(path))
    for g, want in zip(got, frames, strict=True):
        assert_same_meta(g, want)
    assert len(got) == 4


def test_source_is_reiterable_and_resets_its_stats(tmp_path):
    path = write_log(tmp_path / "r.mcap", make_frames(4))
    src = NativeLogSource(path)
    first = list(src)
    assert src.stats.frames_read == 4
    second = list(src)
    assert src.stats.frames_read == 4
    assert_same_frames(second, first)
    assert src.path == path
    assert (
        json.loads(native.CHANNELS[TOPIC_ESTIMATE].schema_bytes())["title"] == "sunrig.SunEstimate"
    )
    assert os.path.getsize(path) > 0


def test_summary_reads_stop_at_the_end_of_the_file(tmp_path):
    # The summary is read by mcap straight from the file: a damaged length there must not ask the
    # file object for more bytes than the file has (it allocates them before reading).
    path = write_log(tmp_path / "a.mcap", make_frames(3))
    size = path.stat().st_size
    with open(path, "rb") as f:
        bounded = native._BoundedReads(f, size)
        bounded.seek(-10, os.SEEK_END)
        assert bounded.read(1 << 62) == path.read_bytes()[-10:]
        assert bounded.read(5) == b"" and bounded.tell() == size
        bounded.seek(0)
        assert bounded.read(8) == native.MCAP_MAGIC


@pytest.mark.parametrize("damaged", [False, True])
def test_a_finished_recording_whose_camera_sent_nothing_holds_no_frames(tmp_path, caplog, damaged):
    # A recorder that declared the camera's channels, and the camera never sent an image: replay
    # said "no frame of it could be read (the warnings above say why)" with no warning, and eval
    # over a folder listed it among the logs it graded instead of leaving it out.
    path = tmp_path / "fg.mcap"
    _camera_mcap(path, {TOPIC_CALIBRATION: _PROTOBUF_CALIBRATION, TOPIC_IMAGE: _PROTOBUF_IMAGE}, images=False)
    if not damaged:
        with pytest.raises(EmptyLogError, match=f"no message on its {TOPIC_IMAGE} channel") as info:
            open_log(path)
        assert "fg.mcap" in str(info.value) and "\n" not in str(info.value)
        return
    # A damaged chunk may have held its frames: the log opens, and its replay warns of the damage.
    with open(path, "rb") as f:
        (chunk,) = make_reader(f).get_summary().chunk_indexes
    data = bytearray(path.read_bytes())
    data[chunk.chunk_start_offset + chunk.chunk_length - 2] ^= 0xFF  # in its compressed records
    path.write_bytes(bytes(data))
    source = open_log(path)
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        assert list(source) == []
    assert source.stats.corrupt_skipped == 1 and caplog.records


def test_per_frame_messages_that_match_no_image_are_warned_about(tmp_path, caplog):
    # Another writer's /heading with a sequence counted per channel (as publishers number their
    # messages) rather than the image's. Every heading was dropped without a word, and replay then
    # told the user to record with a heading source, of a log that has one. (A heading after its
    # image, at its time and sequence, is its frame's: test_a_heading_written_after_its_image_...)
    frames = make_frames(4, seed=3)
    path = tmp_path / "other.mcap"
    with open(path, "wb") as f:
        w, ids = _foreign_writer(f)
        for i, fr in enumerate(frames):
            t = native.ns_from_s(fr.t_mono_s)
            heading_seq = i  # its own count, not its image's sequence
            messages = [(TOPIC_HEADING, heading_seq, native.encode_attitude(fr.attitude, heading_seq)),
                        (TOPIC_IMAGE, fr.seq, native.encode_image(fr.image_bgr, t, 90))]
            if i == 0:
                messages.insert(0, (TOPIC_CALIBRATION, fr.seq, encode_calibration(INTR, t)))
            for topic, seq, data in messages:
                w.add_message(ids[topic], log_time=t, publish_time=t, data=data, sequence=seq)
        w.finish()
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        got = list(open_log(path))
    assert [g.seq for g in got] == [fr.seq for fr in frames]
    assert all(g.attitude is None for g in got)
    warned = [r.getMessage() for r in caplog.records if "matched no image" in r.getMessage()]
    assert len(warned) == 1, [r.getMessage() for r in caplog.records]
    assert "other.mcap" in warned[0] and TOPIC_HEADING in warned[0] and "sequence" in warned[0]


def test_a_sunrig_log_warns_of_no_unmatched_message(tmp_path, caplog):
    path = write_log(tmp_path / "l.mcap", make_frames(5, seed=4))
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        assert len(list(open_log(path))) == 5
    assert not caplog.records


@pytest.mark.parametrize("finish", [True, False])
def test_a_sunrig_channel_in_an_encoding_it_cannot_read_is_warned_about(tmp_path, caplog, finish):
    # Another recorder's /gnss/fix in Foxglove's JSON and /time/utc in ROS 2's CDR: every message
    # on them was passed over as another tool's channel without a word, and the frames replayed
    # without a place or a time (a /heading so written: "record with a heading source", of a log
    # that has one).
    path = tmp_path / "ros.mcap"
    with open(path, "wb") as f:
        w, ids = _foreign_writer(f)
        gnss_json = w.register_channel(TOPIC_GNSS, "json",
                                       w.register_schema("foxglove.LocationFix", "jsonschema", b"{}"))
        utc_cdr = w.register_channel(TOPIC_UTC, "cdr", w.register_schema("builtin_interfaces/msg/Time", "ros2msg",
                                                                          b"int32 sec\nuint32 nanosec"))
        # another tool's own channel: not sunrig's to read, and not said
        imu_cdr = w.register_channel("/imu", "cdr", w.register_schema("sensor_msgs/msg/Imu", "ros2msg", b""))
        for i in range(3):
            t = 1_700_000_000 * 10**9 + i * 100_000_000
            if i == 0:
                w.add_message(ids[TOPIC_CALIBRATION], log_time=t, publish_time=t, sequence=i,
                              data=encode_calibration(INTR, t))
            for cid, data in ((gnss_json, b'{"latitude": 49.0}'), (utc_cdr, b"\x00\x01\x00\x00"), (imu_cdr, b"")):
                w.add_message(cid, log_time=t, publish_time=t, sequence=i, data=data)
            w.add_message(ids[TOPIC_IMAGE], log_time=t, publish_time=t, sequence=i,
                          data=native.encode_image(make_image(i, np.random.default_rng(0)), t, 90))
        if finish:
            w.finish()
        else:
            w.flush()
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        frames = list(open_log(path))
    assert len(frames) == 3 and all(f.gnss is None and f.utc_ns is None for f in frames)
    said = [r.getMessage() for r in caplog.records if "encoding" in r.getMessage()]
    assert len(said) == 1 and "\n" not in said[0] and "ros.mcap" in said[0], caplog.text
    assert f"{TOPIC_GNSS} in json encoding" in said[0] and f"{TOPIC_UTC} in cdr encoding" in said[0]
    assert "/imu" not in said[0]


@pytest.mark.parametrize("layout", ["sunrig", "image-first"])
def test_duplicated_messages_replay_each_frame_once(tmp_path, caplog, layout):
    # Every message written twice (a recorder that retried its writes, or `mcap merge` of a log
    # with itself): each frame replayed twice, the copy without its heading, UTC and truth, and
    # the warning blamed the writer's log times and sequences.
    frames = make_frames(4, seed=2)
    path = tmp_path / "twice.mcap"
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile="", library="someone-else")
        ids = {}
        for topic in native._FRAME_TOPICS:
            spec = native.CHANNELS[topic]
            ids[topic] = w.register_channel(topic, spec.message_encoding, w.register_schema(
                spec.schema_name, spec.schema_encoding, spec.schema_bytes()))
        for i, fr in enumerate(frames):
            t = native.ns_from_s(fr.t_mono_s)
            messages = [(TOPIC_HEADING, native.encode_attitude(fr.attitude, fr.seq)),
                        (TOPIC_GNSS, native.encode_gnss(fr.gnss)),
                        (TOPIC_UTC, native.encode_utc(fr.utc_ns, fr.seq)),
                        (TOPIC_SUN_TRUTH, native.encode_sun_truth(fr.sun_enu_truth, fr.seq))]
            image = (TOPIC_IMAGE, native.encode_image(fr.image_bgr, t, 95))
            messages = [image, *messages] if layout == "image-first" else [*messages, image]
            if i == 0:
                messages.insert(0, (TOPIC_CALIBRATION, encode_calibration(INTR, t)))
            for topic, data in messages:
                for _ in range(2):
                    w.add_message(ids[topic], log_time=t, publish_time=t, sequence=fr.seq, data=data)
        w.finish()
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        got = list(open_log(path))
    assert_same_frames(got, list(read_frames(write_log(tmp_path / "once.mcap", frames))))
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and "\n" not in said[0] and "twice.mcap" in said[0], said
    assert f"4 {TOPIC_IMAGE}" in said[0] and f"4 {TOPIC_HEADING}" in said[0] and "duplicate" in said[0]


@pytest.mark.parametrize("finish", [True, False])
def test_a_calibration_written_after_its_image_keeps_the_frame(tmp_path, caplog, finish):
    # Another writer's layout, each frame's calibration after its image at the image's log time
    # and sequence (as the reader takes a heading after its image): the first image, with no
    # calibration before it, was skipped as corrupt, and its heading said to match no image.
    path = tmp_path / "calib-after.mcap"
    with open(path, "wb") as f:
        w, ids = _foreign_writer(f)
        for i in range(3):
            t = 1_700_000_000 * 10**9 + i * 100_000_000
            intr = INTR if i < 2 else dataclasses.replace(INTR, fx=60.0)  # a zoom at the last frame
            w.add_message(ids[TOPIC_IMAGE], log_time=t, publish_time=t, sequence=i,
                          data=native.encode_image(make_image(i, np.random.default_rng(0)), t, 90))
            w.add_message(ids[TOPIC_CALIBRATION], log_time=t, publish_time=t, sequence=i,
                          data=encode_calibration(intr, t))
            attitude = json.dumps({"heading_deg": 10.0 * i, "reference": "true", "pitch_deg": None,
                                   "roll_deg": None, "seq": i}).encode()
            w.add_message(ids[TOPIC_HEADING], log_time=t, publish_time=t, sequence=i, data=attitude)
        if finish:
            w.finish()
        else:
            w.flush()
    source = open_log(path)
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        frames = list(source)
    assert [f.seq for f in frames] == [0, 1, 2] and source.stats.corrupt_skipped == 0
    assert [f.intrinsics.fx for f in frames] == [INTR.fx, INTR.fx, 60.0]
    assert [round(math.degrees(f.attitude.heading_rad), 9) for f in frames] == [0.0, 10.0, 20.0]
    assert not [r for r in caplog.records if "not closed" not in r.getMessage()], caplog.text


def test_an_image_whose_calibration_never_comes_is_skipped_and_said_with_its_own_seq(tmp_path, caplog):
    # The calibration arrives only with the third image, at its own log time: the two images
    # before it have no intrinsics, and each is said by its own sequence number.
    path = tmp_path / "calib-late.mcap"
    with open(path, "wb") as f:
        w, ids = _foreign_writer(f)
        for i in range(4):
            t = 1_700_000_000 * 10**9 + i * 100_000_000
            if i == 2:
                w.add_message(ids[TOPIC_CALIBRATION], log_time=t, publish_time=t, sequence=i,
                              data=encode_calibration(INTR, t))
            w.add_message(ids[TOPIC_IMAGE], log_time=t, publish_time=t, sequence=i,
                          data=native.encode_image(make_image(i, np.random.default_rng(0)), t, 90))
        w.finish()
    source = open_log(path)
    with caplog.at_level(logging.WARNING, logger="replay.native"):
        assert [f.seq for f in source] == [2, 3]
    assert source.stats.corrupt_skipped == 2
    said = [r.getMessage() for r in caplog.records if "calibration" in r.getMessage()]
    assert ["at seq 0" in said[0], "at seq 1" in said[1], len(said)] == [True, True, 2], said
