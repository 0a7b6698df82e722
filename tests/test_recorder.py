"""Where a recording goes: never over an existing one by accident, a new file per start with {start}."""

import errno
import io
import logging
import os
import re
import shutil
import threading
from datetime import UTC, datetime

import pytest

from replay.native import LogWriter, read_estimates, read_frames
from rig.recorder import RecorderPublisher, RecordingRefused, check_recording_path, discard_if_empty, open_recording
from tests.test_native_log import make_frames
from tests.test_protocol import make_estimate
from tests.test_publishers import wait_until

START = datetime(2026, 11, 23, 3, 15, 0, 400_000, tzinfo=UTC)
MCAP_MAGIC = b"\x89MCAP0\r\n"


def refused(why, fn, *args, **kwargs):
    with pytest.raises(RecordingRefused) as err:
        fn(*args, **kwargs)
    assert err.value.why == why, err.value
    return err.value


def test_start_in_the_name_is_the_utc_start_second(tmp_path):
    with open_recording(tmp_path / "rig-{start}.mcap", start_utc=START) as log:
        assert log.path == tmp_path / "rig-20261123T031500Z.mcap"
    assert log.path.read_bytes().startswith(MCAP_MAGIC)


def test_starts_within_one_second_get_files_of_their_own(tmp_path):
    # A restart loop, or a board without a clock that repeats its boot time before it syncs: the
    # rig must still start and lose nothing, so the next start takes the next free name. The
    # check before devices open lets it through: which name is free is known only at the open.
    first = tmp_path / "rig-20261123T031500Z.mcap"
    first.write_bytes(b"the first start's drive")
    check_recording_path(tmp_path / "rig-{start}.mcap")
    names = []
    for template in ("rig-{start}.mcap", "rig-{start}.mcap", "rig.{start}"):
        with open_recording(tmp_path / template, start_utc=START) as log:
            names.append(log.path.name)
    # The number follows the time, wherever {start} sits in the name.
    assert names == ["rig-20261123T031500Z-1.mcap", "rig-20261123T031500Z-2.mcap", "rig.20261123T031500Z"]
    assert first.read_bytes() == b"the first start's drive"


def test_a_hundred_starts_in_one_second_are_refused_not_looped_over(tmp_path):
    stamp = "20261123T031500Z"
    for name in [stamp, *(f"{stamp}-{k}" for k in range(1, 100))]:
        (tmp_path / f"{name}.mcap").write_bytes(b"x")
    refused("taken", open_recording, tmp_path / "{start}.mcap", start_utc=START)


def test_an_existing_file_is_refused_and_kept(tmp_path):
    keep = tmp_path / "drive.mcap"
    keep.write_bytes(b"yesterday's drive")
    assert refused("exists", check_recording_path, keep).path == keep
    assert refused("exists", open_recording, keep, start_utc=START).path == keep
    assert keep.read_bytes() == b"yesterday's drive"


def test_a_file_made_after_the_check_is_not_truncated(tmp_path, monkeypatch):
    # Between the check and the open the sources start (an OAK: up to 15 s); a file made then by
    # another recorder must survive: the open is exclusive, not a second look.
    import rig.recorder

    keep = tmp_path / "drive.mcap"
    monkeypatch.setattr(rig.recorder, "check_recording_path", lambda *a, **k: keep.write_bytes(b"another run's"))
    refused("exists", open_recording, keep, start_utc=START)
    assert keep.read_bytes() == b"another run's"


def test_a_dangling_link_is_a_taken_name(tmp_path):
    link = tmp_path / "drive.mcap"
    os.symlink(tmp_path / "gone.mcap", link)
    refused("exists", check_recording_path, link)


def test_overwriting_a_link_into_a_missing_folder_is_refused_before_devices_open(tmp_path):
    # With --overwrite a dangling link was let through; the camera opened, and then the log could not
    # be made ("cannot create log ... No such file or directory").
    link = tmp_path / "drive.mcap"
    os.symlink(tmp_path / "gone" / "drive.mcap", link)
    refused("no folder", check_recording_path, link, overwrite=True)
    (tmp_path / "gone").mkdir()  # made where it points: it is written through the link
    check_recording_path(link, overwrite=True)
    with open_recording(link, start_utc=START, overwrite=True):
        pass
    assert (tmp_path / "gone" / "drive.mcap").read_bytes().startswith(MCAP_MAGIC)


def test_overwrite_replaces_an_existing_file(tmp_path):
    old = tmp_path / "drive.mcap"
    old.write_bytes(b"yesterday's drive")
    check_recording_path(old, overwrite=True)
    with open_recording(old, start_utc=START, overwrite=True) as log:
        assert log.path == old
    assert old.read_bytes().startswith(MCAP_MAGIC)


@pytest.mark.parametrize("overwrite", [False, True])
def test_where_no_file_can_be_made_is_refused_before_devices_open(tmp_path, overwrite):
    refused("folder", check_recording_path, tmp_path, overwrite=overwrite)
    refused("folder", open_recording, tmp_path, start_utc=START, overwrite=overwrite)
    refused("no folder", check_recording_path, tmp_path / "nowhere" / "{start}.mcap", overwrite=overwrite)
    refused("stdout", check_recording_path, "-", overwrite=overwrite)
    assert list(tmp_path.iterdir()) == []


def test_demo_never_writes_over_its_own_log(tmp_path, monkeypatch, capsys):
    # The demo's input is not named by [source], so it is passed to the overwrite check itself.
    import replay.sources
    from rig.cli import main

    log = tmp_path / "demo.mcap"
    shutil.copy(replay.sources.DEMO_LOG, log)
    before = log.read_bytes()
    monkeypatch.setattr(replay.sources, "DEMO_LOG", log)
    config = tmp_path / "rig.toml"
    config.write_text(f"[output]\nrecord = {str(log)!r}\nrecord_overwrite = true\n")
    for args in (["demo", "--fast", "--jsonl", str(log)], ["demo", "--fast", "--config", str(config)]):
        assert main(args) == 2, args
        assert "is the input being read" in capsys.readouterr().err, args
        assert log.read_bytes() == before, args


def test_a_recorder_that_fails_to_start_leaves_no_file(tmp_path, monkeypatch):
    # The file is made just before the recorder's thread starts; if that fails (or Ctrl-C lands
    # there), the half-made log would sit in the drives folder as if it were a recording.
    import rig.recorder
    from rig.cli import _publishers
    from rig.stopping import StopSignals

    def no_thread(*args, **kwargs):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(rig.recorder, "RecorderPublisher", no_thread)
    with pytest.raises(RuntimeError, match="can't start new thread"):
        _publishers(serial=None, baud=115200, fmt="nmea", jsonl=None, rule=None, stop=StopSignals(),
                    record=str(tmp_path / "{start}.mcap"))
    assert list(tmp_path.iterdir()) == []


# --- RecorderPublisher: the recording as a live output ---------------------------------------


def test_the_recorder_keeps_frames_only_when_asked_and_every_estimate_on_close(tmp_path):
    # `--record` without `--record-frames` records the estimates only (frames are most of a log's
    # size); close() drains what is queued, so the last seconds of a drive are in the file.
    frames = make_frames(2)
    for record_frames, name in ((False, "est.mcap"), (True, "all.mcap")):
        rec = RecorderPublisher(LogWriter(tmp_path / name), record_frames=record_frames, queue_size=64)
        for f in frames:
            rec.record_frame(f)
        for seq in range(40):
            rec.publish(make_estimate(10.0, 20.0, seq=seq))
        rec.close()
        n_frames = len(frames) if record_frames else 0
        assert rec.stats() == {"written": 40 + n_frames, "dropped": 0, "errors": 0, "last_error": None,
                               "pending": 0, "writer_alive": False}
        assert [d["seq"] for d in read_estimates(tmp_path / name)] == list(range(40))
        if record_frames:  # (a log of estimates alone has no image channel to replay)
            assert [f.seq for f in read_frames(tmp_path / name)] == [f.seq for f in frames]


def test_a_recorder_write_that_fails_is_counted_not_raised(tmp_path):
    # A failed write must not stop the rig: the estimate is lost, counted in `errors` (which the
    # status line sums as a publish error) with its reason, and the next ones are tried. (A full
    # disk ends the recording instead: the tests above.)
    rec = RecorderPublisher(LogWriter(tmp_path / "failing.mcap"))
    real = rec._writer.write_estimate

    def fails_once(est):
        if est.seq == 1:
            raise OSError(errno.EIO, "Input/output error")
        real(est)

    rec._writer.write_estimate = fails_once
    for seq in range(3):
        rec.publish(make_estimate(10.0, 20.0, seq=seq))
    rec.close()
    stats = rec.stats()
    assert (stats["written"], stats["errors"]) == (2, 1) and "Input/output error" in stats["last_error"]
    assert [d["seq"] for d in read_estimates(tmp_path / "failing.mcap")] == [0, 2]


class FakeDisk:
    """FAKE disk of ``free`` more bytes under every log a LogWriter makes (reading is untouched):
    as Linux writes to a full disk, a write that does not fit writes what fits and the next one
    fails with ENOSPC (``errno``: EFBIG, a file system's file size limit). Raise ``free`` to free
    space mid-test. The bytes written are real files."""

    def __init__(self, free: int, errno: int = errno.ENOSPC) -> None:
        self.free, self.errno = free, errno

    def open(self, file, mode="r", *args, **kwargs):
        if "w" not in mode and "x" not in mode:
            return open(file, mode, *args, **kwargs)
        return io.BufferedWriter(_FileOnDisk(self, file, mode.replace("b", "")))


class _FileOnDisk(io.FileIO):
    def __init__(self, disk: FakeDisk, file, mode: str) -> None:
        super().__init__(file, mode)
        self._disk = disk

    def write(self, b) -> int:
        data = bytes(b)
        if data and self._disk.free <= 0:
            raise OSError(self._disk.errno, os.strerror(self._disk.errno))
        n = super().write(data[:self._disk.free])
        self._disk.free -= n
        return n


@pytest.fixture
def disk(monkeypatch) -> FakeDisk:
    """A FakeDisk with no room left; set ``free`` before the log is made."""
    import replay.native

    fake = FakeDisk(free=0)
    monkeypatch.setattr(replay.native, "open", fake.open, raising=False)
    return fake


def chunk_ends(path, estimates: int) -> list[int]:
    """The size of a log of ``estimates`` estimates, each in a chunk of its own, after each chunk."""
    sizes = []
    with LogWriter(path, chunk_size=1) as w:
        for seq in range(estimates):
            w.write_estimate(make_estimate(10.0, 20.0, seq=seq))
            sizes.append(path.stat().st_size)
    return sizes


def test_a_recording_on_a_full_disk_keeps_no_file_and_counts_what_it_did_not_record(tmp_path, disk, caplog):
    # A rig booting on a full disk left a 0-byte {start}.mcap at every boot, and its close failed
    # ("unfinished", exit 2): the header and the one chunk of estimates never reached the disk.
    rec = RecorderPublisher(open_recording(tmp_path / "{start}.mcap", start_utc=START), record_frames=True)
    with caplog.at_level(logging.WARNING, logger="rig.recorder"):
        for f in make_frames(2):
            rec.record_frame(f)
        for seq in range(5):
            rec.publish(make_estimate(10.0, 20.0, seq=seq))
        rec.close()
    assert rec.finished and list(tmp_path.iterdir()) == []
    full = rec.disk_full
    assert full is not None and full.removed and full.errno == errno.ENOSPC
    assert (full.frames_recorded, full.estimates_recorded, full.frames_lost, full.estimates_lost) == (0, 0, 2, 5)
    stats = rec.stats()
    assert (stats["written"], stats["errors"]) == (0, 7)
    (said,) = [r.getMessage() for r in caplog.records]
    assert "disk is full (No space left on device)" in said and f"free space in {tmp_path}" in said, said
    assert "not recorded (counted in the status line's publish errors)" in said, said  # where to watch it


def test_a_recording_whose_disk_fills_ends_at_its_last_chunk_and_does_not_resume(tmp_path, disk, caplog):
    # The first write that does not fit leaves part of a chunk in the file. Writing went on after
    # it, and once space was freed the log took all of it in bytes that replay as a damaged record
    # (a real 2 MB tmpfs: 23 frames replayed of 137, the disk full again), and its close failed.
    disk.free = 10**9
    sizes = chunk_ends(tmp_path / "measure.mcap", 4)
    disk.free = sizes[2] + 40  # three chunks fit, and the start of the fourth
    rec = RecorderPublisher(LogWriter(tmp_path / "drive.mcap", chunk_size=1), queue_size=64)
    with caplog.at_level(logging.WARNING):
        for seq in range(5):
            rec.publish(make_estimate(10.0, 20.0, seq=seq))
        wait_until(lambda: rec.stats()["errors"], "the recorder to find its disk full")
        disk.free = 10**9  # space freed while the rig runs
        for seq in range(5, 8):
            rec.publish(make_estimate(10.0, 20.0, seq=seq))
        rec.close()
    assert rec.finished and not rec.stuck
    assert (tmp_path / "drive.mcap").stat().st_size == sizes[2]  # cut back to its last complete chunk
    assert [d["seq"] for d in read_estimates(tmp_path / "drive.mcap")] == [0, 1, 2]
    assert not [r for r in caplog.records if "corrupt" in r.getMessage() or "damaged" in r.getMessage()]
    full = rec.disk_full
    assert full is not None and (full.estimates_recorded, full.estimates_lost, full.removed) == (3, 5, False)
    assert (rec.stats()["written"], rec.stats()["errors"]) == (3, 5)


def test_a_recording_ends_a_chunk_once_its_oldest_item_waited_chunk_every_s(tmp_path):
    # A chunk ended only at 1 MiB: about 3000 estimates, 5 minutes at 10 Hz, of an estimates-only
    # recording held in memory, so a full disk was found (and said) minutes late, all of them lost
    # with it, and as many lost at a power cut.
    from rig.recorder import Recording

    now = [0.0]
    path = tmp_path / "estimates.mcap"
    rec = Recording(LogWriter(path), chunk_every_s=10.0, monotonic=lambda: now[0])
    for seq, t in enumerate((100.0, 105.0, 109.9)):
        now[0] = t
        assert rec.write_estimate(make_estimate(10.0, 20.0, seq=seq))
    assert path.stat().st_size == 0  # all three wait in the chunk in progress
    now[0] = 110.0
    assert rec.write_estimate(make_estimate(10.0, 20.0, seq=3))
    assert [d["seq"] for d in read_estimates(path)] == [0, 1, 2, 3]  # on the disk, the log still open
    now[0] = 115.0
    assert rec.write_estimate(make_estimate(10.0, 20.0, seq=4))
    size = path.stat().st_size
    now[0] = 119.9  # counted from the first estimate after the chunk ended, not from the last chunk
    assert rec.write_estimate(make_estimate(10.0, 20.0, seq=5)) and path.stat().st_size == size
    rec.close()
    assert [d["seq"] for d in read_estimates(path)] == list(range(6))


def test_a_run_recorder_finds_a_full_disk_as_its_first_chunk_ends_not_at_its_close(tmp_path, disk, caplog):
    rec = RecorderPublisher(LogWriter(tmp_path / "estimates.mcap"), chunk_every_s=0.0)
    with caplog.at_level(logging.WARNING, logger="rig.recorder"):
        rec.publish(make_estimate(10.0, 20.0, seq=0))
        wait_until(lambda: caplog.records, "the recorder to say its disk is full")
    assert "disk is full" in caplog.records[0].getMessage() and rec.disk_full is not None
    rec.close()
    assert list(tmp_path.iterdir()) == []


def stall_estimate_writes(monkeypatch) -> tuple[threading.Event, threading.Event]:
    """FAKE stalled disk: every LogWriter's estimate writes wait (up to 10 s, a guard, not a
    timing) until the returned ``release`` is set; ``entered`` is set once a writer is inside one."""
    real = LogWriter.write_estimate
    entered, release = threading.Event(), threading.Event()

    def stuck(self, est):
        entered.set()
        release.wait(10.0)
        real(self, est)

    monkeypatch.setattr(LogWriter, "write_estimate", stuck)
    return entered, release


def test_a_recorder_behind_a_stalled_disk_drops_the_oldest_and_counts_them(tmp_path, monkeypatch):
    # The recorder never stalls capture or the estimator: while the disk is stuck its queue (2 here)
    # keeps the newest estimates and counts the ones it let go. Seq 0 is in the stuck write; of
    # 1..5 the queue ends holding 4 and 5, so 3 are dropped.
    rec = RecorderPublisher(LogWriter(tmp_path / "slow.mcap"), queue_size=2)
    entered, release = stall_estimate_writes(monkeypatch)
    rec.publish(make_estimate(10.0, 20.0, seq=0))
    assert entered.wait(10.0)
    for seq in range(1, 6):
        rec.publish(make_estimate(10.0, 20.0, seq=seq))
    release.set()
    rec.close()
    assert (rec.stats()["dropped"], rec.stats()["written"]) == (3, 3)
    assert [d["seq"] for d in read_estimates(tmp_path / "slow.mcap")] == [0, 4, 5]


def test_a_recorder_stuck_past_close_finishes_its_file_when_the_disk_answers(tmp_path, caplog, monkeypatch):
    # The rig's shutdown must not wait on a dead disk, nor close the log under a write in progress
    # (two threads in one MCAP writer): the writer thread finishes the file when the write returns,
    # so the recording keeps every queued estimate and its summary.
    rec = RecorderPublisher(LogWriter(tmp_path / "late.mcap"), join_timeout_s=0.05)
    entered, release = stall_estimate_writes(monkeypatch)
    for seq in range(3):
        rec.publish(make_estimate(10.0, 20.0, seq=seq))
    assert entered.wait(10.0)
    with caplog.at_level(logging.WARNING, logger="rig.publishers"):
        rec.close()
    assert not rec._writer.closed and any("stuck in a write" in r.getMessage() for r in caplog.records)
    assert rec.stuck and not rec.finished
    release.set()
    # Finished, not only closed: the writer says closed as its close() begins, before the summary
    # is written and synced to the disk (a few ms more since the sync), so waiting for closed and
    # then asking finished failed now and then.
    wait_until(lambda: rec.finished, "the writer thread to finish the log")
    assert rec._writer.closed and rec.stats()["written"] == 3 and rec.finished and not rec.stuck
    assert [d["seq"] for d in read_estimates(tmp_path / "late.mcap")] == [0, 1, 2]
    assert (tmp_path / "late.mcap").read_bytes().endswith(MCAP_MAGIC)  # finished: a footer and its magic


def test_a_run_whose_recording_is_stuck_at_the_end_says_it_is_unfinished(tmp_path, monkeypatch, capsys):
    # The daemon thread dies with the process: "recorded to" and exit 0 would be a lie.
    import rig.recorder
    from replay.sources import DEMO_LOG
    from rig.cli import main

    _, release = stall_estimate_writes(monkeypatch)

    class QuickToGiveUp(rig.recorder.RecorderPublisher):
        def __init__(self, writer, **kw):
            super().__init__(writer, join_timeout_s=0.05, **kw)

    monkeypatch.setattr(rig.recorder, "RecorderPublisher", QuickToGiveUp)
    out = tmp_path / "rec.mcap"
    try:
        code = main(["run", "--camera", f"file:{DEMO_LOG}", "--heading", "log", "--record", str(out), "--fast"])
        err = capsys.readouterr().err
    finally:
        release.set()
    assert code == 2 and "recorded to" not in err, err
    assert f"the recording {out} is unfinished (a write to its disk did not return in 0.05 s" in err


def test_a_stop_signal_while_the_rig_closes_its_recording_lets_it_finish(tmp_path, monkeypatch):
    # A file camera has just ended and the outputs are closing when systemd's SIGTERM arrives:
    # the log is finished all the same, and the run ends as it would have.
    import signal

    from replay.sources import DEMO_LOG
    from rig.cli import main

    real_close = LogWriter.close

    def signalled_close(self):
        signal.raise_signal(signal.SIGTERM)  # lands inside the close
        real_close(self)

    monkeypatch.setattr(LogWriter, "close", signalled_close)
    out = tmp_path / "rec.mcap"
    assert main(["run", "--camera", f"file:{DEMO_LOG}", "--heading", "log", "--record", str(out), "--fast",
                 "--quiet"]) == 0
    assert out.read_bytes().endswith(MCAP_MAGIC) and len(list(read_estimates(out))) >= 1


def test_only_a_closed_recording_that_holds_nothing_is_discarded(tmp_path):
    empty = LogWriter(tmp_path / "empty.mcap")
    assert not discard_if_empty(empty) and empty.path.exists()  # still open: it may yet get frames
    empty.close()
    assert discard_if_empty(empty) and not empty.path.exists()
    with LogWriter(tmp_path / "estimates.mcap") as w:  # `run --record` without --record-frames
        w.write_estimate(make_estimate(10.0, 20.0, seq=1))
    assert not discard_if_empty(w) and w.path.exists()
    with LogWriter(tmp_path / "frames.mcap") as w:
        w.write_frame(make_frames(1)[0])
    assert not discard_if_empty(w) and w.path.exists()


def test_an_empty_recording_made_through_a_link_removes_the_file_it_made_and_keeps_the_link(tmp_path):
    # `record --out latest.mcap --overwrite`, latest.mcap a link into drives/: a run that recorded
    # nothing unlinked the link and left the 0-byte file it had truncated behind it, which every
    # later eval or train of drives/ warned about as a damaged log.
    (tmp_path / "drives").mkdir()
    target = tmp_path / "drives" / "drive.mcap"
    target.write_bytes(b"yesterday's drive")
    link = tmp_path / "latest.mcap"
    os.symlink(target, link)
    w = open_recording(link, start_utc=START, overwrite=True)
    w.close()
    assert discard_if_empty(w)
    assert not target.exists() and link.is_symlink()  # the link is the user's; the file was this run's


def test_a_recording_through_a_link_on_a_full_disk_removes_the_file_it_made_and_keeps_the_link(tmp_path, disk, caplog):
    (tmp_path / "drives").mkdir()
    target = tmp_path / "drives" / "drive.mcap"
    link = tmp_path / "latest.mcap"
    os.symlink(target, link)
    rec = RecorderPublisher(open_recording(link, start_utc=START, overwrite=True))
    with caplog.at_level(logging.WARNING, logger="rig.recorder"):
        for seq in range(3):
            rec.publish(make_estimate(10.0, 20.0, seq=seq))
        rec.close()
    assert rec.disk_full is not None and rec.disk_full.removed
    assert not target.exists() and link.is_symlink()
    (said,) = [r.getMessage() for r in caplog.records]
    # The disk that filled is the one the link points into, which may not be the link's own.
    assert f"free space in {tmp_path / 'drives'}," in said, said


def test_an_empty_recording_to_a_device_leaves_the_device(tmp_path):
    # `record --out /dev/null --overwrite` with a camera that gave nothing unlinked the device node
    # itself (as root, /dev/null). A null device of our own, made where the test may make one.
    import stat

    node = tmp_path / "null"
    try:
        os.mknod(node, stat.S_IFCHR | 0o666, os.makedev(1, 3))
    except PermissionError:
        pytest.skip("making a device node needs root (CAP_MKNOD)")
    w = LogWriter(node)
    w.close()
    assert not discard_if_empty(w) and stat.S_ISCHR(os.stat(node).st_mode)


def test_an_estimate_published_to_a_closed_recorder_is_refused_not_lost_unsaid(tmp_path):
    # As a closed background output does: the pipeline counts a PublishError; a silent drop left
    # the recording short by estimates the rig believed recorded.
    from rig.errors import PublishError

    rec = RecorderPublisher(LogWriter(tmp_path / "closed.mcap"))
    rec.publish(make_estimate(10.0, 20.0, seq=0))
    rec.close()
    with pytest.raises(PublishError, match="closed"):
        rec.publish(make_estimate(10.0, 20.0, seq=1))
    assert [d["seq"] for d in read_estimates(tmp_path / "closed.mcap")] == [0]


def test_record_seconds_of_a_log_counts_the_logs_own_time(tmp_path, capsys):
    # `--seconds` was timed by the wall clock, and a log is read as fast as it can be: re-recording
    # the first second of the 3.9 s bundled drive kept all of it. A log's own time says how much.
    from replay.sources import DEMO_LOG
    from rig.cli import main

    frames = list(read_frames(DEMO_LOG))
    t0 = frames[0].t_mono_s
    within_1s = [f.seq for f in frames if f.t_mono_s - t0 <= 1.0]
    assert 5 < len(within_1s) < len(frames) - 5
    out = tmp_path / "first-second.mcap"
    rc = main(["record", "--camera", f"file:{DEMO_LOG}", "--heading", "log", "--out", str(out), "--seconds", "1",
               "--quiet"])
    assert rc == 0, capsys.readouterr().err
    assert [f.seq for f in read_frames(out)] == within_1s


def test_record_seconds_of_a_video_file_counts_the_videos_own_time(tmp_path, capsys):
    # A video file is read as fast as a log is, its frames stamped with its own time: `--seconds 1`
    # of a 10 fps clip kept every frame read within a wall-clock second, all 30 of them.
    import cv2

    from rig.cli import main
    from tests.test_opencv_camera import FPS, H, W, clip_image

    clip = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(clip), cv2.VideoWriter_fourcc(*"MJPG"), FPS, (W, H))
    for k in range(30):
        writer.write(clip_image(k % 12))
    writer.release()
    out = tmp_path / "first-second.mcap"
    rc = main(["record", "--camera", f"opencv:{clip}", "--hfov-deg", "60", "--heading", "none", "--out", str(out),
               "--seconds", "1", "--quiet"])
    assert rc == 0, capsys.readouterr().err
    times = [f.t_mono_s for f in read_frames(out)]
    assert len(times) == 11 and times[-1] - times[0] == pytest.approx(1.0, abs=1e-3), times


# --- A full disk under the live rig and `record` -------------------------------------------


def test_a_run_on_a_full_disk_keeps_no_recording_and_says_what_to_do(tmp_path, disk, capsys):
    # Booting on a full disk left a 0-byte {start}.mcap at every boot, "unfinished (closing it
    # failed)". Nothing was recorded: exit 2, as for any output that wrote nothing.
    from replay.sources import DEMO_LOG
    from rig.cli import main

    code = main(["run", "--camera", f"file:{DEMO_LOG}", "--heading", "log", "--fast",
                 "--record", str(tmp_path / "{start}.mcap")])
    err = capsys.readouterr().err
    assert list(tmp_path.iterdir()) == [] and code == 2, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("sunrig: error: nothing could be recorded to ") and "unfinished" not in err, err
    assert "its disk is full (No space left on device), so no file is kept" in last, last
    assert re.search(r", and \d+ estimates were not recorded; ", last), last
    assert last.endswith(f"free space in {tmp_path}, and the next start records again"), last


def test_a_run_whose_disk_fills_keeps_what_it_recorded_and_says_what_it_lost(tmp_path, disk, capsys, caplog):
    # The disk filled mid-run: the serial output went on, and the stop that followed (systemd's
    # SIGTERM) exited 2 "unfinished (closing it failed)", a failed unit. The run did its job: exit 0,
    # with the journal told when the recording ended, what it keeps and what it lost.
    from replay.sources import DEMO_LOG
    from rig.cli import main

    disk.free = 1_200_000  # the bundled drive's first chunk (1 MiB of frames) fits, not the rest
    out = tmp_path / "drive.mcap"
    with caplog.at_level(logging.WARNING):
        code = main(["run", "--camera", f"file:{DEMO_LOG}", "--heading", "log", "--fast", "--record-frames",
                     "--record", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    said = [r.getMessage() for r in caplog.records if r.name == "rig.cli"]
    assert len(said) == 1, said
    m = re.fullmatch(rf"the recording {re.escape(str(out))} ends at \d\d:\d\d:\d\d UTC: its disk is full "
                     r"\(No space left on device\); it keeps the (\d+) frames? and (\d+) estimates? before, and (\d+) "
                     r"frames? and \d+ estimates? from then on were not recorded; free space in "
                     rf"{re.escape(str(tmp_path))}, and the next start records again", said[0])
    assert m, said[0]
    kept, estimates, lost = (int(g) for g in m.groups())
    assert kept == len(list(read_frames(out))) and 0 < kept < kept + lost <= 40
    assert estimates == len(list(read_estimates(out)))
    assert "recorded to" not in err and "unfinished" not in err


@pytest.mark.parametrize(("free", "code", "cause", "remedy"), [
    (0, errno.ENOSPC, "its disk is full (No space left on device)", "free space in {folder}"),
    (1_200_000, errno.ENOSPC, "its disk is full (No space left on device)", "free space in {folder}"),
    # A FAT32 stick's 4 GiB: free space would not help.
    (1_200_000, errno.EFBIG, "its file is as large as its file system allows (File too large)",
     "record to a file system that allows larger files than that of {folder} (ext4 or exFAT, not FAT32)"),
])
def test_record_to_a_disk_that_fills_keeps_its_complete_chunks_and_says_what_it_lost(tmp_path, disk, capsys, caplog,
                                                                                    free, code, cause, remedy):
    # `record` said "No space left on device after 23 frames; its complete chunks still replay" of
    # a 0-byte file it kept (and of one that held 24 of "40 frames", its part chunk left on).
    from replay.sources import DEMO_LOG
    from rig.cli import main

    disk.free, disk.errno = free, code
    remedy = remedy.format(folder=tmp_path)
    out = tmp_path / "drive.mcap"
    with caplog.at_level(logging.WARNING):
        rc = main(["record", "--camera", f"file:{DEMO_LOG}", "--heading", "log", "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    (said,) = err.strip().splitlines()
    assert rc == 2 and said.endswith(f"; {remedy} or pass another --out"), err
    if not free:
        assert list(tmp_path.iterdir()) == []
        assert said.startswith(f"sunrig: error: record: nothing could be recorded to {out}: {cause}, so no file is "
                               "kept, and its "), said
        return
    m = re.fullmatch(rf"sunrig: error: record: {re.escape(str(out))} ends at \d\d:\d\d:\d\d UTC: {re.escape(cause)}; "
                     rf"it keeps the (\d+) frames before \(sunrig replay {re.escape(str(out))}\), and (\d+) frames "
                     rf"from then on were not recorded; {re.escape(remedy)} or pass another --out", said)
    assert m, said
    kept, lost = int(m[1]), int(m[2])
    assert kept == len(list(read_frames(out))) and 0 < kept < kept + lost <= 40
    assert not [r for r in caplog.records if "corrupt" in r.getMessage() or "damaged" in r.getMessage()]


def test_a_recording_to_a_device_or_stream_ends_its_chunks_every_chunk_every_s_not_at_every_item(tmp_path):
    # Where the log's size says nothing (`record --out /dev/null --overwrite`, a device, or a
    # stream), a chunk's end went unseen: its first item was taken to wait still, and from then on
    # every item ended a chunk of its own, synced. A stream stands in for the device, whose size
    # cannot be watched.
    from rig.recorder import Recording

    now = [0.0]
    stream = io.BytesIO()
    rec = Recording(LogWriter(stream), chunk_every_s=10.0, monotonic=lambda: now[0])
    for seq, t in enumerate((100.0, 110.0)):
        now[0] = t
        assert rec.write_estimate(make_estimate(10.0, 20.0, seq=seq))
    size = len(stream.getvalue())
    assert size > 0  # the first chunk ended 10 s after its first item
    now[0] = 111.0
    assert rec.write_estimate(make_estimate(10.0, 20.0, seq=2))
    assert len(stream.getvalue()) == size  # waits in the next chunk, 1 s old


def test_a_recording_whose_close_finds_the_disk_full_keeps_its_complete_chunks(tmp_path, disk):
    # Every write fit, and the disk filled before the chunk in progress (and the summary) could be
    # written at the close: the log is its complete chunks, and the full disk is said from when
    # the chunk that did not fit began.
    from rig.recorder import Recording

    now, utc = [0.0], [START]
    disk.free = 10**9
    path = tmp_path / "estimates.mcap"
    rec = Recording(LogWriter(path), chunk_every_s=10.0, monotonic=lambda: now[0], clock=lambda: utc[0])
    for seq, t in enumerate((100.0, 110.0, 111.0, 115.0)):
        now[0], utc[0] = t, START.replace(second=int(t) - 100)
        assert rec.write_estimate(make_estimate(10.0, 20.0, seq=seq))
    first_chunk = path.stat().st_size  # estimates 0 and 1; 2 and 3 wait in the chunk in progress
    disk.free = 40  # the start of the next chunk fits, not the rest
    rec.close()
    assert path.stat().st_size == first_chunk
    assert [d["seq"] for d in read_estimates(path)] == [0, 1]
    full = rec.disk_full
    assert full is not None and full.since_utc == START.replace(second=11)
    assert (full.estimates_recorded, full.estimates_lost, full.removed) == (2, 2, False)
