"""The publishers (rig/publishers.py) over real pseudo-terminals, loop:// and files.

pyserial opens the slave side of an ``os.openpty()`` pair, exactly as it opens /dev/ttyUSB0; the
test reads the master side. Nothing is mocked. There are no timed asserts (speed is for the
benchmarks): waits poll a condition with a deadline, and ``within()`` guards against hangs.
"""

from __future__ import annotations

import gc
import io
import json
import logging
import math
import os
import re
import socket
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pynmea2
import pytest
import serial
from serial.urlhandler.protocol_loop import Serial as LoopSerial

from rig.errors import PublishError
from rig.protocol import (
    NMEA_MAX_LEN,
    BinaryFrameReader,
    NmeaLineReader,
    decode_binary,
    decode_nmea,
    encode_binary,
    encode_nmea,
    nmea_fields,
)
from rig.publishers import (
    BackgroundPublisher,
    JsonlPublisher,
    Publisher,
    QueuedWriter,
    SentencePublisher,
    SerialPublisher,
    publisher_name,
)
from tests.test_protocol import F32_DEG, F32_UNIT, make_estimate, random_estimates, worst_case_estimates

HANG_GUARD_S = 10.0  # generous: only a hang fails it, never a slow machine


def wait_until(condition: Callable[[], bool], what: str, timeout_s: float = HANG_GUARD_S) -> None:
    """Poll ``condition`` until true; fail (not hang) after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(0.002)


def within(seconds: float, fn: Callable[[], Any]) -> Any:
    """Run ``fn`` in a thread; fail if it has not returned after ``seconds`` (a hang guard)."""
    result: dict[str, Any] = {}

    def run() -> None:
        try:
            result["value"] = fn()
        except BaseException as exc:  # handed back to the test thread, re-raised there
            result["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"{getattr(fn, '__name__', fn)} did not return within {seconds} s"
    if "error" in result:
        raise result["error"]
    return result.get("value")


def accounted(stats: dict[str, Any]) -> int:
    """Every published message is written, dropped one of four ways, pending or in flight."""
    keys = ("written", "dropped_overwritten", "dropped_write_timeout", "dropped_unsent", "write_errors", "pending",
            "in_flight")
    return sum(stats[k] for k in keys)


class Pty:
    """A pseudo-terminal pair: pyserial opens ``name`` (the slave); the test reads ``master``."""

    def __init__(self) -> None:
        self.master, self.slave = os.openpty()
        tty.setraw(self.slave)  # no echo, no CR/LF translation: bytes pass as written
        self.name = os.ttyname(self.slave)

    def fill(self) -> None:
        """Fill the kernel buffers from the test's own slave fd, as a reader that stopped would.

        The kernel moves bytes on to the master's line discipline in the background, so room can
        reappear just after an EAGAIN: fill until two rounds in a row find none."""
        os.set_blocking(self.slave, False)
        deadline = time.monotonic() + HANG_GUARD_S
        empty_rounds = 0
        while empty_rounds < 2:
            assert time.monotonic() < deadline, "the pty never filled"
            empty_rounds = empty_rounds + 1 if self._fill_once() == 0 else 0
            time.sleep(0.01)  # let the kernel move what it can, then try again

    def _fill_once(self) -> int:
        total = 0
        for size in (4096, 256, 1):
            try:
                while True:
                    total += os.write(self.slave, b"\x00" * size)
            except BlockingIOError:
                pass
        return total

    def close_master(self) -> None:
        if self.master >= 0:
            os.close(self.master)
            self.master = -1

    def close(self) -> None:
        self.close_master()
        if self.slave >= 0:
            os.close(self.slave)
            self.slave = -1


@pytest.fixture
def pty():
    pair = Pty()
    yield pair
    pair.close()


class MasterReader:
    """Reads a pty master in a thread and feeds a stream reader; ``raw`` keeps every byte."""

    def __init__(self, master: int, reader: NmeaLineReader | BinaryFrameReader) -> None:
        self.master = master
        self.reader = reader
        self.raw = bytearray()
        self.messages: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import select

        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if not ready:
                continue
            try:
                data = os.read(self.master, 65536)
            except OSError:  # EIO while no slave is open: wait for the publisher to reopen
                self._stop.wait(0.01)
                continue
            with self._lock:
                self.raw += data
                self.messages += self.reader.feed(data)

    def snapshot(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self.messages)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(HANG_GUARD_S)
        assert not self._thread.is_alive()


def publish_and_wait(pub: SerialPublisher, est, written_before: int) -> None:
    """Publish one message and wait until the writer wrote it (no drop: one at a time)."""
    pub.publish(est)
    wait_until(lambda: pub.stats()["written"] > written_before, "the writer to write the message")


def publish_until_seen(pub: SerialPublisher, reader: MasterReader, seq: int, what: str) -> None:
    """Publish (again and again: the newest wins) until the reader has a message with ``seq``."""

    def seen() -> bool:
        pub.publish(make_estimate(40, 5, seq=seq))
        return any(m["seq"] == seq for m in reader.snapshot())

    wait_until(seen, what)


# --- NMEA and binary over a real pseudo-terminal ---------------------------------------------


def test_nmea_over_a_pty_is_accepted_by_pynmea2(pty):
    estimates = random_estimates(120, seed=20) + worst_case_estimates()
    reader = MasterReader(pty.master, NmeaLineReader())
    try:
        with SerialPublisher(pty.name, format="nmea") as pub:
            for i, est in enumerate(estimates):
                publish_and_wait(pub, est, i)
            wait_until(lambda: len(reader.snapshot()) == len(estimates), "every sentence at the reader")
            stats = pub.stats()
    finally:
        reader.stop()
    assert stats["written"] == stats["published"] == len(estimates)
    assert stats["dropped_overwritten"] == stats["dropped_write_timeout"] == stats["write_errors"] == 0
    lines = bytes(reader.raw).split(b"\r\n")
    assert lines[-1] == b"" and len(lines) - 1 == len(estimates)
    for line, est in zip(lines[:-1], estimates, strict=True):
        assert len(line) + 2 <= NMEA_MAX_LEN
        parsed = pynmea2.parse(line.decode("ascii"), check=True)  # raises on a checksum mismatch
        assert isinstance(parsed, pynmea2.ProprietarySentence)
        assert parsed.manufacturer == "SRG"
        assert parsed.data == ["S", *nmea_fields(est)]
    assert reader.snapshot() == [decode_nmea(encode_nmea(e)) for e in estimates]
    assert max(len(line) + 2 for line in lines[:-1]) == NMEA_MAX_LEN  # the worst cases went through
    assert reader.reader.counts["bad_checksum"] == reader.reader.counts["garbage_bytes"] == 0


def test_binary_frames_over_a_pty_pass_their_crc_and_round_trip(pty):
    estimates = random_estimates(80, seed=21) + worst_case_estimates()
    reader = MasterReader(pty.master, BinaryFrameReader())
    try:
        with SerialPublisher(pty.name, format="binary") as pub:
            for i, est in enumerate(estimates):
                publish_and_wait(pub, est, i)
            wait_until(lambda: len(reader.snapshot()) == len(estimates), "every frame at the reader")
    finally:
        reader.stop()
    counts = reader.reader.counts
    assert counts["messages"] == len(estimates)
    assert counts["bad_crc"] == counts["malformed"] == counts["garbage_bytes"] == 0
    assert bytes(reader.raw) == b"".join(encode_binary(e) for e in estimates)
    for got, est in zip(reader.snapshot(), estimates, strict=True):
        np.testing.assert_allclose(got["sun_enu"], est.sun_enu, atol=F32_UNIT)
        assert got["azimuth_deg"] == pytest.approx(math.degrees(est.azimuth_rad), abs=F32_DEG)
        assert got["elevation_deg"] == pytest.approx(math.degrees(est.elevation_rad), abs=F32_DEG)
        assert got["seq"] == est.seq % 2**32 and got["utc_ns"] == est.utc_ns and got["t_mono_s"] == est.t_mono_s


# --- a reader that stops reading, or goes away ------------------------------------------------


def test_publish_never_waits_for_a_stuck_write(pty):
    """The writer is stuck on a full pty (a long write timeout): publish() still returns at once,
    every call, and the counters show the overwritten messages. close() still returns."""
    pty.fill()
    pub = SerialPublisher(pty.name, format="nmea", write_timeout_s=60.0)
    try:
        pub.publish(make_estimate(10, 10, seq=0))
        wait_until(lambda: pub.stats()["in_flight"] == 1, "the writer to take the first message")

        def burst() -> None:
            for k in range(1, 201):
                pub.publish(make_estimate(10, 10, seq=k))

        within(HANG_GUARD_S, burst)
        stats = pub.stats()
        # Structural: the writer still holds message 0 in its write; every later message went to
        # the mailbox and all but the newest were overwritten there. publish() never waited on it.
        assert stats["in_flight"] == 1 and stats["written"] == 0
        assert stats["dropped_overwritten"] == 199 and stats["pending"] == 1
        assert accounted(stats) == stats["published"] == 201
        within(HANG_GUARD_S, pub.close)
        stats = pub.stats()
        assert not stats["writer_alive"] and not stats["port_open"]
        assert stats["dropped_write_timeout"] == 1 and stats["in_flight"] == 0  # the abandoned write
        assert accounted(stats) == 201
    finally:
        pub.close()


def test_waiting_for_the_writer_loses_nothing_to_a_burst(pty):
    """wait_for_writer (a replay): a burst that newest-wins would mostly overwrite reaches the
    reader whole and in order, the last one sent by close()."""
    reader = MasterReader(pty.master, NmeaLineReader())
    pub = SerialPublisher(pty.name, format="nmea", wait_for_writer=True)
    try:
        within(HANG_GUARD_S, lambda: [pub.publish(make_estimate(30, 20, seq=k)) for k in range(300)])
        within(HANG_GUARD_S, pub.close)
        stats = pub.stats()
        assert stats["written"] == stats["published"] == 300 and stats["dropped_overwritten"] == 0
        wait_until(lambda: len(reader.snapshot()) == 300, "the reader to get every sentence")
        assert [m["seq"] for m in reader.snapshot()] == list(range(300))
    finally:
        reader.stop()
        pub.close()


class FlushSpyPort(serial.Serial):
    """A real pyserial port (on the test's pty) that records ``reset_output_buffer()`` calls."""

    flushes = 0

    def reset_output_buffer(self) -> None:
        self.flushes += 1
        super().reset_output_buffer()


@pytest.mark.parametrize("fmt", ["nmea", "binary"])
def test_close_leaves_what_was_written_for_the_reader(pty, fmt):
    """A burst written just before a normal close still reaches the reader. The close discards
    only what a port reports as unsent after a short drain; a pty reports nothing, and a flush
    there dropped bytes the kernel had not yet handed to the reader (25 of 200 in one of five
    runs of this burst)."""
    port = FlushSpyPort(pty.name)
    reader = MasterReader(pty.master, NmeaLineReader() if fmt == "nmea" else BinaryFrameReader())
    pub = SerialPublisher(port, format=fmt, wait_for_writer=True)
    try:
        for k in range(200):
            pub.publish(make_estimate(30, 20, seq=k))
        within(HANG_GUARD_S, pub.close)
        assert pub.stats()["written"] == 200 and port.flushes == 0
        wait_until(lambda: len(reader.snapshot()) == 200, "the reader to get the burst written before the close")
        assert [m["seq"] for m in reader.snapshot()] == list(range(200))
    finally:
        reader.stop()
        pub.close()


def test_a_pyserial_written_port_sends_and_counts_the_last_message_at_close(pty):
    """spy:// (and socket://) ports are written by pyserial's own write(). close() used to call
    its cancel_write() at once, so the last write sent its bytes yet returned 0: delivered, counted
    as dropped, and the port flushed as after a failure."""
    reader = MasterReader(pty.master, NmeaLineReader())
    pub = SerialPublisher(f"spy://{pty.name}?file=/dev/null", format="nmea", wait_for_writer=True)
    try:
        for k in range(5):
            pub.publish(make_estimate(30, 20, seq=k))
        within(HANG_GUARD_S, pub.close)
        stats = pub.stats()
        assert stats["written"] == 5 and stats["dropped_write_timeout"] == 0, stats
        wait_until(lambda: len(reader.snapshot()) == 5, "the reader to get all five")
    finally:
        reader.stop()
        pub.close()


class UartPort(LoopSerial):
    """FAKE serial port: a loop:// port that reports bytes still unsent (``out_waiting``, a UART's
    TIOCOUTQ), as a UART whose reader holds the line with flow control does. ``drained_after``
    polls it reports 0; ``flushes`` counts ``reset_output_buffer()`` calls."""

    def __init__(self, drained_after: int | None) -> None:
        self.drained_after, self.polls = drained_after, 0
        super().__init__("loop://")  # (opening the port resets its buffers: not counted)
        self.flushes = 0

    @property
    def out_waiting(self) -> int:
        self.polls += 1
        return 0 if self.drained_after is not None and self.polls > self.drained_after else 64

    def reset_output_buffer(self) -> None:
        self.flushes = getattr(self, "flushes", 0) + 1
        super().reset_output_buffer()


@pytest.mark.parametrize(("drained_after", "flushed"), [(3, 0), (None, 1)])
def test_a_normal_close_lets_the_uart_send_what_it_holds_and_discards_only_what_it_cannot(drained_after, flushed):
    """A line that drains is closed with nothing discarded; one still holding bytes after the
    drain time is flushed, so that the close does not wait up to 30 s (closing_wait) for it."""
    port = UartPort(drained_after)
    pub = SerialPublisher(port, format="nmea")
    publish_and_wait(pub, make_estimate(5, 5), 0)
    within(HANG_GUARD_S, pub.close)
    assert port.flushes == flushed and port.polls > (drained_after or 1) and not port.is_open
    # The sentence the flush discarded (64 bytes unsent: its tail at least) is not counted as written.
    stats = pub.stats()
    assert (stats["written"], stats["dropped_unsent"]) == (1 - flushed, flushed)
    assert accounted(stats) == stats["published"] == 1


class HeldLinePort(serial.Serial):
    """A real pyserial port on the test's pty, written by the publisher through its fd as a UART
    is, but whose reader holds the line (flow control): nothing is sent until the test calls
    ``send()``. ``out_waiting`` (a UART's TIOCOUTQ; a pty reports 0) takes what the kernel holds
    into ``held`` and reports it, and ``reset_output_buffer()`` discards that (one item of
    ``discarded`` per flush)."""

    def __init__(self, master: int, name: str) -> None:
        self.master, self.held, self.discarded = master, bytearray(), list[bytes]()
        super().__init__(name)

    def _take_from_kernel(self) -> None:
        import select

        while select.select([self.master], [], [], 0.01)[0]:
            try:
                self.held += os.read(self.master, 65536)
            except OSError:  # EIO while the publisher has the slave closed: nothing is queued
                return

    @property
    def out_waiting(self) -> int:
        self._take_from_kernel()
        return len(self.held)

    def reset_output_buffer(self) -> None:
        self.discarded.append(bytes(self.held))
        self.held.clear()
        super().reset_output_buffer()

    def send(self) -> bytes:
        """Let the line go: what the reader gets."""
        self._take_from_kernel()
        sent, self.held = bytes(self.held), bytearray()
        return sent


def whole_sentences(data: bytes) -> int:
    """Sentences from '$' to '*HH' CR LF in ``data`` (not a head cut off, nor a resync CR LF)."""
    return len(re.findall(rb"\$[^$\r\n]*\*[0-9A-F]{2}\r\n", data))


def test_a_uart_flush_moves_the_messages_it_discarded_from_written_and_no_others(pty):
    """After a write timeout the messages still in a UART's buffer are discarded and move from
    written to dropped_unsent. The timed-out message, already counted as dropped, may have put its
    head there too: those bytes used to be charged to the newest written message, so a sentence
    the reader got was counted as dropped."""
    port = HeldLinePort(pty.master, pty.name)
    pub = SerialPublisher(port, format="nmea", write_timeout_s=0.05, backoff_s=(0.01, 0.1))
    rng = np.random.default_rng(7)
    try:
        # The line flows: sentences reach the reader (and are in the publisher's record of sizes).
        for k in range(5):
            publish_and_wait(pub, make_estimate(30, 20, seq=k), k)
        delivered = port.send()
        # The reader holds the line until a write times out and the port is flushed; again until a
        # timed-out write had put part of its sentence in (a round whose last sentence fitted whole
        # cannot tell the difference; sentences of random lengths make that rare).
        for _ in range(6):
            if port.discarded and not port.discarded[-1].endswith(b"\n"):
                break
            flushes, timeouts = len(port.discarded), pub.stats()["dropped_write_timeout"]
            while len(port.discarded) == flushes:
                assert pub.stats()["published"] < 20000, "the line never filled"
                if pub.stats()["dropped_write_timeout"] == timeouts:  # one timeout per round
                    pub.publish(make_estimate(30, 20, seq=int(rng.integers(0, 10 ** int(rng.integers(1, 9))))))
                wait_until(lambda n=flushes: pub.stats()["pending"] == 0 or len(port.discarded) > n, "the writer")
        assert not port.discarded[-1].endswith(b"\n"), "no timed-out write was cut inside its sentence"
        within(HANG_GUARD_S, pub.close)
        delivered += port.send()
        stats = pub.stats()
        assert stats["dropped_unsent"] == sum(whole_sentences(d) for d in port.discarded)
        assert stats["written"] == whole_sentences(delivered) == 5  # every one written reached the reader
        assert accounted(stats) == stats["published"]
    finally:
        within(HANG_GUARD_S, pub.close)


def test_waiting_for_the_writer_is_bounded_when_nobody_reads(pty):
    """A stalled reader slows a replay's publish() (while the writer times out, closes and
    reopens the port); it never stops it, and every message is accounted for."""
    pty.fill()
    pub = SerialPublisher(pty.name, format="nmea", write_timeout_s=0.05, backoff_s=(0.01, 0.1),
                          wait_for_writer=True)
    try:
        within(HANG_GUARD_S, lambda: [pub.publish(make_estimate(30, 20, seq=k)) for k in range(20)])
        within(HANG_GUARD_S, pub.close)
        stats = pub.stats()
        assert stats["dropped_write_timeout"] >= 1  # (a reopen discards the stale output: room again)
        assert accounted(stats) == stats["published"] == 20
    finally:
        pub.close()


def test_waiting_for_a_writer_stuck_below_python_is_bounded():
    """A write hung in a wedged driver never frees the mailbox: each publish() of a replay waits
    its bound (1 s here), then replaces the unsent message as a live rig would."""
    port = HungDriverPort()
    pub = SerialPublisher(port, format="nmea", write_timeout_s=0.05, join_timeout_s=0.2, wait_for_writer=True)
    try:
        pub.publish(make_estimate(5, 5, seq=0))
        wait_until(lambda: pub.stats()["in_flight"] == 1, "the writer to enter the hung write")
        within(HANG_GUARD_S, lambda: [pub.publish(make_estimate(5, 5, seq=k)) for k in range(1, 4)])
        stats = pub.stats()
        assert stats["dropped_overwritten"] == 2 and stats["pending"] == 1 and stats["in_flight"] == 1
    finally:
        port.release.set()
        pub.close()


class HungDriverPort(LoopSerial):
    """FAKE serial port: a loop:// port whose write() hangs until released (a wedged USB driver)."""

    def __init__(self) -> None:
        super().__init__("loop://")
        self.release = threading.Event()

    def write(self, data: bytes) -> int:
        self.release.wait(HANG_GUARD_S)
        return super().write(data)

    @property
    def out_waiting(self) -> int:
        # loop:// reports what nobody has read back from it as unsent, which a close then discards
        # (counted dropped_unsent); this driver's bytes, once written, have gone down the wire.
        return 0


class GatedPort(HungDriverPort):
    """FAKE serial port: a loop:// port whose write() waits until ``cancel_write()`` (which the
    publisher's close() calls) and then completes: a write that returns just as the rig stops."""

    def cancel_write(self) -> None:
        self.release.set()


def test_close_sends_the_message_left_in_the_mailbox():
    """The last estimate of a replay (or the newest of a stopping rig) is not left unsent."""
    port = GatedPort()
    pub = SerialPublisher(port, format="nmea")
    try:
        pub.publish(make_estimate(5, 5, seq=0))
        wait_until(lambda: pub.stats()["in_flight"] == 1, "the writer to enter the write")
        pub.publish(make_estimate(5, 5, seq=1))
        assert pub.stats()["pending"] == 1
        within(HANG_GUARD_S, pub.close)
        stats = pub.stats()
        assert stats["written"] == stats["published"] == 2 and stats["pending"] == 0
    finally:
        port.release.set()
        pub.close()


def test_stalled_reader_drops_are_counted_and_sentences_flow_again_when_it_reads(pty):
    pub = SerialPublisher(pty.name, format="nmea", write_timeout_s=0.05, backoff_s=(0.01, 0.1))
    reader = None
    try:
        # Nobody reads the master: the kernel buffer fills and writes start to time out.
        seq = 0
        while pub.stats()["dropped_write_timeout"] < 2:
            seq += 1
            assert seq < 5000, "the pty never filled"
            pub.publish(make_estimate(30, 20, seq=seq))
            wait_until(lambda: pub.stats()["pending"] == 0 or pub.stats()["dropped_write_timeout"] >= 2,
                       "the writer to take the message")
        stalled = pub.stats()
        assert stalled["written"] > 0 and stalled["reopens"] >= 1  # closed on the timeout, then reopened
        assert accounted(stalled) == stalled["published"]

        # The reader comes back: new sentences arrive, whole.
        reader = MasterReader(pty.master, NmeaLineReader())
        publish_until_seen(pub, reader, 90000, "a sentence published after the reader came back")
        # The reader can have the sentence before the writer thread, back from write(), has counted
        # it (seen once on a loaded machine): the count must follow, not precede.
        wait_until(lambda: pub.stats()["written"] > stalled["written"], "the sentence counted as written")
        resumed = pub.stats()
        assert accounted(resumed) == resumed["published"]
        assert reader.reader.counts["bad_checksum"] == 0
        # Every sentence counted as written reached the reader, the stalled backlog too: the port
        # used to be flushed at each timeout (a pty cannot say what it holds), discarding about half
        # of what was counted as written.
        within(HANG_GUARD_S, pub.close)
        final = pub.stats()
        wait_until(lambda: len(reader.snapshot()) == final["written"], "the reader to get every sentence written")
        assert final["dropped_unsent"] == 0
    finally:
        if reader is not None:
            reader.stop()
        within(HANG_GUARD_S, pub.close)


def test_vanished_reader_counts_errors_and_the_url_is_reopened_when_it_returns(tmp_path):
    """Like a USB adapter unplugged and plugged back under its udev symlink: the master side
    closes (the device goes), writes fail, and the publisher reopens the path once it exists."""
    first, second = Pty(), None
    link = tmp_path / "ttySUN"
    os.symlink(first.name, link)
    pub = SerialPublisher(str(link), format="nmea", write_timeout_s=0.05, backoff_s=(0.01, 0.1))
    reader = MasterReader(first.master, NmeaLineReader())
    try:
        publish_until_seen(pub, reader, 1, "the first sentence")
        reader.stop()
        first.close()  # the device goes away

        def errors_seen() -> bool:
            pub.publish(make_estimate(40, 5, seq=2))
            return pub.stats()["write_errors"] >= 1

        wait_until(errors_seen, "a write error after the device went away")
        gone = pub.stats()
        assert accounted(gone) == gone["published"]
        within(HANG_GUARD_S, lambda: [pub.publish(make_estimate(40, 5, seq=3)) for _ in range(100)])

        second = Pty()  # the device comes back, maybe under another /dev/pts number
        tmp_link = tmp_path / "ttySUN.new"
        os.symlink(second.name, tmp_link)
        os.replace(tmp_link, link)
        reader = MasterReader(second.master, NmeaLineReader())
        publish_until_seen(pub, reader, 77, "a sentence on the reopened port")
        back = pub.stats()
        assert back["reopens"] >= 1 and back["write_errors"] >= 1
        assert back["dropped_overwritten"] > 0
        # Only whole sentences arrive; the first may be the one left in the mailbox during the outage.
        assert {m["seq"] for m in reader.snapshot()} <= {3, 77}
        assert reader.reader.counts["bad_checksum"] == reader.reader.counts["malformed"] == 0
        assert accounted(back) == back["published"]
    finally:
        reader.stop()
        within(HANG_GUARD_S, pub.close)
        first.close()
        if second is not None:
            second.close()


def test_socket_url_reconnects_after_the_peer_goes():
    """A TCP serial bridge (socket://): the peer drops the connection, writes fail, and the
    publisher makes a new connection from the URL."""
    server = socket.create_server(("127.0.0.1", 0))
    server.settimeout(HANG_GUARD_S)
    url = f"socket://127.0.0.1:{server.getsockname()[1]}"
    pub = SerialPublisher(url, format="binary", write_timeout_s=0.05, backoff_s=(0.01, 0.1))
    conns: list[socket.socket] = []
    try:
        conns.append(server.accept()[0])
        frames = BinaryFrameReader()

        def received(seq: int) -> bool:
            pub.publish(make_estimate(60, 30, seq=seq))
            conns[-1].settimeout(0.02)
            try:
                got = frames.feed(conns[-1].recv(4096))
            except TimeoutError:
                return False
            return any(m["seq"] == seq for m in got)

        wait_until(lambda: received(1), "a frame over the first connection")
        conns[-1].close()  # the peer goes

        def errors_seen() -> bool:
            pub.publish(make_estimate(60, 30, seq=2))
            return pub.stats()["write_errors"] >= 1

        wait_until(errors_seen, "a write error after the peer went")
        conns.append(server.accept()[0])  # the publisher reconnects by itself
        wait_until(lambda: received(3), "a frame over the new connection")
        stats = pub.stats()
        assert stats["reopens"] >= 1 and stats["write_errors"] >= 1
        assert accounted(stats) == stats["published"]
    finally:
        within(HANG_GUARD_S, pub.close)
        for conn in conns:
            conn.close()
        server.close()


def test_given_port_object_is_reopened_with_open(pty):
    port = serial.Serial(pty.name, 115200)
    reader = MasterReader(pty.master, NmeaLineReader())
    try:
        with SerialPublisher(port, format="nmea", backoff_s=(0.01, 0.1)) as pub:
            publish_and_wait(pub, make_estimate(1, 1, seq=1), 0)
            port.close()  # as if a write had failed and the port was closed
            publish_until_seen(pub, reader, 3, "a sentence after the writer reopened the port object")
            assert pub.stats()["reopens"] >= 1
        assert not port.is_open  # the publisher owns the port and closed it
    finally:
        reader.stop()


class FailingPort(LoopSerial):
    """FAKE serial port: a loop:// port that opens, but whose write() fails while ``failing`` is set,
    as a USB adapter that hangs with its device node still there, or a TCP bridge whose serial side
    is gone: every reopen works and every write after it fails."""

    def __init__(self) -> None:
        super().__init__("loop://")
        self.failing = threading.Event()
        self.failing.set()

    def write(self, data: bytes) -> int:
        if self.failing.is_set():
            raise serial.SerialException("write failed: [Errno 5] Input/output error")
        return super().write(data)

    @property
    def out_waiting(self) -> int:
        return 0  # as HungDriverPort's: what it wrote has gone down the wire


def serial_lines(caplog) -> list[logging.LogRecord]:
    return [r for r in caplog.records if r.name == "rig.publishers" and "serial" in r.getMessage()]


def test_a_port_whose_writes_keep_failing_is_said_when_it_starts_and_when_it_recovers(caplog):
    # Each failed write said a warning and each reopen an info line: with the default backoff that
    # is a line a second for as long as the adapter stays hung (3600 an hour, in the journal).
    port = FailingPort()
    caplog.set_level(logging.INFO, logger="rig.publishers")
    with SerialPublisher(port, format="nmea", backoff_s=(0.01, 0.02)) as pub:

        def failed_often() -> bool:
            pub.publish(make_estimate(40, 5, seq=1))
            return pub.stats()["write_errors"] >= 30

        wait_until(failed_often, "30 failed writes")
        port.failing.clear()  # the adapter answers again

        def written() -> bool:
            pub.publish(make_estimate(40, 5, seq=2))
            return pub.stats()["written"] >= 1

        wait_until(written, "a write that goes through")
        wait_until(lambda: len(serial_lines(caplog)) >= 2, "the recovery said")
        stats = pub.stats()
    said = serial_lines(caplog)
    assert [r.levelno for r in said] == [logging.WARNING, logging.INFO], [r.getMessage() for r in said]
    assert said[0].getMessage().startswith("serial write to loop:// failed (SerialException: write failed: "
                                           "[Errno 5] Input/output error); reopening with backoff")
    # The recovery says how long it lasted, with the counts the statistics keep (exact, as before).
    assert f"after {stats['write_errors']} failed writes" in said[1].getMessage()
    assert f"reopened {stats['reopens']} times" in said[1].getMessage()
    assert stats["write_errors"] == stats["reopens"] >= 30


def test_a_reader_that_stopped_reading_is_said_once_not_at_every_reopen(pty, caplog):
    # A controller that stops reading: every write times out, the port is closed and reopened, and
    # each reopen said "serial port ... reopened", a line per backoff for as long as it lasted.
    caplog.set_level(logging.INFO, logger="rig.publishers")
    pub = SerialPublisher(pty.name, format="nmea", write_timeout_s=0.02, backoff_s=(0.01, 0.02))
    reader = None
    try:
        pty.fill()

        def timed_out_often() -> bool:
            pub.publish(make_estimate(30, 20, seq=1))
            return pub.stats()["dropped_write_timeout"] >= 20

        wait_until(timed_out_often, "20 writes timing out")
        reader = MasterReader(pty.master, NmeaLineReader())  # it reads again
        publish_until_seen(pub, reader, 90000, "a sentence after the reader came back")
        wait_until(lambda: len(serial_lines(caplog)) >= 2, "the recovery said")
        stats = pub.stats()
    finally:
        if reader is not None:
            reader.stop()
        within(HANG_GUARD_S, pub.close)
    said = serial_lines(caplog)
    assert [r.levelno for r in said] == [logging.WARNING, logging.INFO], [r.getMessage() for r in said]
    assert "timed out" in said[0].getMessage()
    assert f"{stats['dropped_write_timeout']} timed out" in said[1].getMessage()


class SwitchingPort(FailingPort):
    """FAKE serial port: a loop:// port whose write() fails (``mode`` "error"), times out ("timeout")
    or goes through ("ok"), as an adapter that hangs and later a controller that stops reading."""

    def __init__(self) -> None:
        super().__init__()
        self.failing.clear()
        self.mode = "error"

    def write(self, data: bytes) -> int:
        if self.mode == "error":
            raise serial.SerialException("write failed: [Errno 5] Input/output error")
        if self.mode == "timeout":
            raise serial.SerialTimeoutException("Write timeout")
        return super().write(data)


def test_a_lasting_outage_of_timeouts_says_they_timed_out_not_an_error_of_none_or_of_an_earlier_outage(
        caplog, monkeypatch):
    # The reminder of a lasting outage said "last error: None" when its writes only timed out, and
    # after an earlier outage with an error it named that old error as this one's.
    monkeypatch.setattr("rig.publishers._STILL_FAILING_FIRST_S", 0.02)  # the reminder without a minute's wait
    caplog.set_level(logging.INFO, logger="rig.publishers")
    port = SwitchingPort()
    port.mode = "timeout"
    with SerialPublisher(port, format="nmea", backoff_s=(0.005, 0.01)) as pub:
        def still_said(count: int, text: str = "") -> Callable[[], bool]:
            def check() -> bool:
                pub.publish(make_estimate(40, 5, seq=1))
                return sum("still failing" in r.getMessage() and text in r.getMessage()
                           for r in serial_lines(caplog)) >= count
            return check

        wait_until(still_said(1), "an outage of timeouts said again")
        port.mode = "error"
        wait_until(still_said(1, "last error: "), "the same outage, now with errors, said again")
        port.mode = "ok"

        def written() -> bool:
            pub.publish(make_estimate(40, 5, seq=2))
            return pub.stats()["written"] >= 1

        wait_until(written, "a write that goes through")
        port.mode = "timeout"
        count = sum("still failing" in r.getMessage() for r in serial_lines(caplog))
        wait_until(still_said(count + 1), "a second outage of timeouts said again")
        stats = pub.stats()
    still = [r.getMessage() for r in serial_lines(caplog) if "still failing" in r.getMessage()]
    error = "SerialException: write failed: [Errno 5] Input/output error"
    assert "timed out with no error" in still[0] and "None" not in still[0], still
    assert any(f"last error: {error}" in line for line in still), still
    assert stats["dropped_write_timeout"] >= 1 and stats["last_error"] == error
    assert "timed out with no error" in still[-1] and error not in still[-1], still


# --- loop://, close(), errors --------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["nmea", "binary"])
def test_loop_url_round_trip(fmt):
    port = serial.serial_for_url("loop://", timeout=HANG_GUARD_S)
    est = make_estimate(321.0, 12.3, heading_deg=45.0, seq=42)
    encoded = encode_nmea(est) if fmt == "nmea" else encode_binary(est)
    with SerialPublisher(port, format=fmt) as pub:
        pub.publish(est)
        data = port.read(len(encoded))  # loop:// echoes what the writer thread wrote
        wait_until(lambda: pub.stats()["written"] == 1, "the written count")
    assert data == encoded
    assert (decode_nmea if fmt == "nmea" else decode_binary)(data)["seq"] == 42


def test_loop_url_string_is_opened_and_closed_by_the_publisher():
    pub = SerialPublisher("loop://", format="binary")
    publish_and_wait(pub, make_estimate(5, 5), 0)
    assert pub.stats()["port"] == "loop://" and pub.stats()["port_open"]
    within(HANG_GUARD_S, pub.close)
    within(HANG_GUARD_S, pub.close)  # idempotent
    assert not pub.stats()["port_open"] and not pub.stats()["writer_alive"]
    with pytest.raises(PublishError, match="closed"):
        pub.publish(make_estimate(5, 5))


def test_what_loop_url_holds_for_its_reader_stays_written_at_close():
    # loop://'s out_waiting counts its loopback queue (sent, not yet read back), not unsent bytes:
    # taken for them, a close called every sentence the rig had sent there dropped.
    pub = SerialPublisher("loop://", format="nmea")
    for seq in range(3):
        publish_and_wait(pub, make_estimate(5, 5, seq=seq), seq)
    within(HANG_GUARD_S, pub.close)
    st = pub.stats()
    assert (st["written"], st["dropped_unsent"]) == (3, 0), st


def test_close_returns_while_the_write_is_stuck_and_the_writer_closes_the_port_later(caplog):
    port = HungDriverPort()
    pub = SerialPublisher(port, format="nmea", join_timeout_s=0.2)
    try:
        pub.publish(make_estimate(5, 5))
        wait_until(lambda: pub.stats()["in_flight"] == 1, "the writer to enter the hung write")
        with caplog.at_level(logging.WARNING, logger="rig.publishers"):
            within(HANG_GUARD_S, pub.close)
        assert "did not stop" in caplog.text
        within(HANG_GUARD_S, pub.close)  # idempotent, and does not wait again
        assert pub.stats()["writer_alive"] and port.is_open
    finally:
        port.release.set()
    wait_until(lambda: not pub.stats()["writer_alive"], "the writer to end once the write returned")
    assert not port.is_open


def test_open_and_option_errors_say_what_to_do(tmp_path):
    missing = str(tmp_path / "ttyUSB9")
    expected = r"cannot open serial port .*ttyUSB9.*check the cable or pass another --serial"
    with pytest.raises(PublishError, match=expected):
        SerialPublisher(missing)
    with pytest.raises(PublishError, match="unknown serial format 'csv'"):
        SerialPublisher("loop://", format="csv")
    for bad in (None, 0, -1.0, math.inf):
        with pytest.raises(PublishError, match="write_timeout_s"):
            SerialPublisher("loop://", write_timeout_s=bad)
    with pytest.raises(PublishError, match="backoff_s"):
        SerialPublisher("loop://", backoff_s=(1.0, 0.5))


# --- JSONL ------------------------------------------------------------------------------------


def test_jsonl_file_one_object_per_line_flushed_per_line(tmp_path):
    path = tmp_path / "est.jsonl"
    estimates = random_estimates(5, seed=22)
    pub = JsonlPublisher(path)
    for i, est in enumerate(estimates):
        pub.publish(est)
        lines = path.read_text().splitlines()  # read while still open: flushed per line
        assert len(lines) == i + 1
    pub.close()
    pub.close()
    assert [json.loads(line) for line in path.read_text().splitlines()] == [
        json.loads(json.dumps(e.to_json_dict())) for e in estimates
    ]
    assert pub.stats()["written"] == 5
    with pytest.raises(PublishError, match="closed"):
        pub.publish(estimates[0])


def test_jsonl_with_a_status_rule_says_what_the_serial_output_says(tmp_path):
    from rig.protocol import StatusRule

    rule = StatusRule.for_model(8, 74.9)
    path = tmp_path / "est.jsonl"
    with JsonlPublisher(path, status_rule=rule) as pub:
        pub.publish(make_estimate(100, 30))  # a full window, a sun the model knows
        pub.publish(make_estimate(100, 85, n_frames=3))  # filling, and above the trained suns
    rows = [json.loads(line) for line in path.read_text().splitlines()]
    assert rows[0]["valid"] is True and rows[0]["status"] == ["VALID", "HAS_UTC"]
    assert rows[1]["valid"] is False and rows[1]["status"] == ["HAS_UTC", "PARTIAL_WINDOW", "ABOVE_TRAINED"]
    nmea = [decode_nmea(encode_nmea(make_estimate(100, el, n_frames=n), rule)) for el, n in ((30, 8), (85, 3))]
    assert [r["valid"] for r in rows] == [d["valid"] for d in nmea]


def test_jsonl_stream_and_stdout_are_flushed_not_closed(capsys):
    stream = io.StringIO()
    with JsonlPublisher(stream) as pub:
        pub.publish(make_estimate(90, 45, seq=7))
    assert not stream.closed and json.loads(stream.getvalue())["seq"] == 7
    with JsonlPublisher("-") as pub:
        pub.publish(make_estimate(90, 45, seq=8))
    assert json.loads(capsys.readouterr().out)["seq"] == 8


def test_jsonl_unwritable_path_says_what_to_do(tmp_path):
    with pytest.raises(PublishError, match="cannot write JSONL .*check the folder"):
        JsonlPublisher(tmp_path / "no" / "such" / "dir" / "est.jsonl")


def test_jsonl_file_is_touched_only_by_its_first_estimate(tmp_path):
    # Opened with truncation, a run that failed before its first estimate (a log none of whose
    # frames could be read) emptied the file a run before had written, and left a new path as a
    # 0-byte file. A stream is not written whole or not at all, but nothing is touched for nothing.
    keep = tmp_path / "keep.jsonl"
    keep.write_text("prev\n")
    JsonlPublisher(keep).close()
    new = tmp_path / "new.jsonl"
    JsonlPublisher(new).close()
    assert keep.read_text() == "prev\n" and not new.exists() and sorted(os.listdir(tmp_path)) == ["keep.jsonl"]
    for path in (keep, new):  # the first estimate replaces what was there
        with JsonlPublisher(path) as pub:
            pub.publish(make_estimate(90, 45, seq=3))
            assert json.loads(path.read_text())["seq"] == 3  # flushed, before close
    # A path that cannot be written is still refused when opened, not at the first estimate.
    keep.chmod(0o444)
    if not os.access(keep, os.W_OK):  # (root may write anyway)
        with pytest.raises(PublishError, match="cannot write JSONL"):
            JsonlPublisher(keep)
    (tmp_path / "a-file").write_text("x")
    with pytest.raises(PublishError, match="cannot write JSONL .*Not a directory"):
        JsonlPublisher(tmp_path / "a-file" / "est.jsonl")
    assert not os.path.exists(tmp_path / "a-file" / "est.jsonl")


@pytest.mark.skipif(not os.path.exists("/dev/null"), reason="needs /dev/null")
def test_jsonl_to_a_device_writes_in_place(tmp_path):
    # Not a regular file: opened at once and written there, as rig.files.write_replacing does.
    with JsonlPublisher("/dev/null") as pub:
        pub.publish(make_estimate(90, 45))
    assert pub.stats()["written"] == 1 and Path("/dev/null").is_char_device()


def test_publishers_share_the_protocol(tmp_path: Path):
    with SerialPublisher("loop://") as serial_pub, JsonlPublisher(tmp_path / "x.jsonl") as jsonl_pub:
        assert isinstance(serial_pub, Publisher) and isinstance(jsonl_pub, Publisher)


# --- BackgroundPublisher: the stream outputs, live ----------------------------------------------


def test_a_pipe_nobody_reads_stalls_its_output_not_the_caller(caplog):
    # Finalise earlier tests' file objects first: one collected later would close whatever
    # descriptor reuses its number, perhaps this pipe's.
    gc.collect()
    r, w = os.pipe()
    # Fill the pipe first, as a reader that stopped a while ago leaves it: the first write blocks.
    os.set_blocking(w, False)
    filled = 0
    try:
        while True:
            filled += os.write(w, b"x" * 4096)
    except BlockingIOError:
        pass
    os.set_blocking(w, True)
    stream = os.fdopen(w, "w", encoding="utf-8")
    bg = BackgroundPublisher(JsonlPublisher(stream), max_pending=16, join_timeout_s=0.2)
    # The writer takes the first estimate into its write, which blocks, before the rest arrive:
    # otherwise the counts below depend on which thread the scheduler ran first (CI saw both).
    bg.publish(make_estimate(10.0, 20.0, seq=0))
    wait_until(lambda: bg.stats()["published"] == 1, f"the writer to take the first estimate: {bg.stats()}")
    # The caller (the rig's estimate thread) must not block, though the writer is stuck.
    within(HANG_GUARD_S, lambda: [bg.publish(make_estimate(10.0, 20.0, seq=i)) for i in range(1, 1000)])
    wait_until(lambda: bg.stats()["pending"] == 16, f"the writer to stall with a full queue: {bg.stats()}")
    stats = bg.stats()
    assert stats["writer_alive"] and stats["written"] == 0
    # Every estimate is accounted for: handed to the inner publisher (stuck in its write),
    # dropped oldest-first, or waiting.
    assert stats["published"] == 1 and stats["dropped"] == 1000 - 1 - 16
    with caplog.at_level(logging.WARNING, logger="rig.publishers"):
        within(HANG_GUARD_S, bg.close)  # bounded, though the writer is stuck
    assert any("stuck in a write" in rec.getMessage() for rec in caplog.records)
    # Once someone reads, the writer writes what was pending and ends: whole lines, the newest last.
    os.set_blocking(r, False)
    got = bytearray()

    def drained() -> bool:
        try:
            while chunk := os.read(r, 65536):
                got.extend(chunk)
        except BlockingIOError:
            pass
        return not bg.stats()["writer_alive"]

    wait_until(drained, "the writer to finish once the pipe is read")
    stream.close()
    drained()
    os.close(r)
    lines = got[filled:].decode().splitlines()
    seqs = [json.loads(line)["seq"] for line in lines]
    # The one that was in the write, then the newest 16.
    assert seqs == [0, *range(1000 - 16, 1000)]


def test_a_background_publisher_counts_what_its_publisher_raises_on(tmp_path, caplog):
    inner = JsonlPublisher(tmp_path / "out.jsonl")
    inner.close()  # every publish now raises
    bg = BackgroundPublisher(inner)
    with caplog.at_level(logging.WARNING, logger="rig.publishers"):
        for i in range(5):
            bg.publish(make_estimate(10.0, 20.0, seq=i))
        wait_until(lambda: bg.stats()["errors"] == 5, "five errors")
    assert "closed JSONL publisher" in bg.stats()["last_error"]
    assert sum("could not write" in rec.getMessage() for rec in caplog.records) == 1  # once per kind
    bg.close()
    with pytest.raises(PublishError, match="closed background"):
        bg.publish(make_estimate(10.0, 20.0))


class ShortWritePort(LoopSerial):
    """FAKE serial port: a loop:// port whose first write() returns having written only a few bytes, as a write
    cut short by ``cancel_write()`` does."""

    def __init__(self) -> None:
        super().__init__("loop://")
        self.cut = True

    def write(self, data: bytes) -> int:
        if self.cut:
            self.cut = False
            return super().write(data[:5])
        return super().write(data)


def test_a_write_cut_short_is_a_drop_and_the_next_sentence_starts_on_its_own_line():
    # The controller holds half a sentence: that message is lost (counted as a timeout drop, not
    # as written), and the next one starts with a line end so the half line is not glued to it.
    port = ShortWritePort()
    first, second = make_estimate(10.0, 20.0, seq=1), make_estimate(30.0, 40.0, seq=2)
    with SerialPublisher(port, format="nmea", backoff_s=(0.01, 0.1)) as pub:
        pub.publish(first)
        wait_until(lambda: pub.stats()["dropped_write_timeout"] == 1 and pub.stats()["reopens"] == 1,
                   "the cut write counted and the port reopened")
        port.read(port.in_waiting)  # the half sentence, as far as it got
        pub.publish(second)
        wait_until(lambda: pub.stats()["written"] == 1, "the next sentence written")
        data = port.read(port.in_waiting)
    assert data == b"\r\n" + encode_nmea(second)
    assert pub.stats()["written"] == 1 and accounted(pub.stats()) == 2


def test_a_background_publisher_is_named_after_what_it_runs():
    # The status line and the statistics name outputs by what they write ("JsonlPublisher"), not
    # by the thread they run in.
    bg = BackgroundPublisher(JsonlPublisher(io.StringIO()))
    try:
        assert publisher_name(bg) == "JsonlPublisher"
        assert publisher_name(JsonlPublisher(io.StringIO())) == "JsonlPublisher"
    finally:
        bg.close()


class GoneReader(io.StringIO):
    """FAKE stream whose reader went away (`sunrig replay ... | head`): every write is a broken pipe."""

    def write(self, text: str) -> int:
        raise BrokenPipeError(32, "Broken pipe")


def test_a_broken_pipe_ends_the_jsonl_output_rather_than_failing_it():
    # The pipeline takes BrokenPipeError as "this output has ended" (and stops when all have), but
    # a PublishError as a write that failed: `| head` must not turn into counted errors.
    pub = JsonlPublisher(GoneReader())
    with pytest.raises(BrokenPipeError):
        pub.publish(make_estimate(10.0, 20.0))


def test_a_background_publisher_whose_reader_went_away_says_so_to_its_caller():
    # In its own thread the broken pipe cannot reach the caller at once: the next publish() raises
    # it, as the inner publisher would have, so the pipeline stops feeding this output.
    bg = BackgroundPublisher(JsonlPublisher(GoneReader()))
    try:
        bg.publish(make_estimate(10.0, 20.0, seq=1))
        wait_until(lambda: not bg.stats()["writer_alive"], "the writer to end on the broken pipe")
        with pytest.raises(BrokenPipeError):
            bg.publish(make_estimate(10.0, 20.0, seq=2))
        assert bg.stats()["errors"] == 0  # a reader that left is not an error
    finally:
        bg.close()


def test_a_background_publisher_closes_what_it_runs_and_sentences_are_counted():
    # close() finishes the inner publisher too (a JSONL file gets closed, stdout flushed); and the
    # NMEA-on-stdout output counts what it wrote, as the exit report shows it.
    text = io.StringIO()
    inner = SentencePublisher(text)
    bg = BackgroundPublisher(inner)
    for seq in (1, 2):
        bg.publish(make_estimate(10.0, 20.0, seq=seq))
    bg.close()
    assert inner.stats() == {"published": 2, "written": 2}
    assert len(text.getvalue().splitlines()) == 2
    jsonl = JsonlPublisher(io.StringIO())
    BackgroundPublisher(jsonl).close()
    with pytest.raises(PublishError, match="closed JSONL"):
        jsonl.publish(make_estimate(10.0, 20.0))


# --- QueuedWriter: the thread behind the background outputs and the recorder ------------------


def test_a_queued_writer_finishes_its_output_once_in_the_caller_of_close():
    # Drained within the join: the output is finished by close(), so a failure to finish (a full
    # disk under the summary of a recording) reaches whoever closed it, and a second close is a no-op.
    written, finished = [], []

    def finish():
        finished.append(threading.current_thread().name)
        raise OSError(28, "No space left on device")

    w = QueuedWriter(written.append, finish, what="test output", max_pending=8)
    for seq in range(5):
        w.put(make_estimate(10.0, 20.0, seq=seq))
    with pytest.raises(OSError, match="No space left"):
        w.close(HANG_GUARD_S)
    assert [e.seq for e in written] == list(range(5)) and w.written == 5
    assert finished == [threading.current_thread().name]
    assert w.close(HANG_GUARD_S) and len(finished) == 1


def test_a_queued_writer_stuck_past_close_finishes_its_output_when_the_write_returns(caplog):
    # A pipe nobody reads, a disk that stopped answering: close() must return, and the output must
    # not be closed from the caller while the thread is still writing to it. The thread finishes it
    # after its write returns (its error logged: there is no caller left to take it).
    entered, release = threading.Event(), threading.Event()
    written, finished = [], []

    def stuck_write(est):
        entered.set()
        release.wait(HANG_GUARD_S)  # a guard, not a timing: released below
        written.append(est.seq)

    def finish():
        finished.append((threading.current_thread().name, list(written)))
        raise OSError(5, "Input/output error")

    w = QueuedWriter(stuck_write, finish, what="test output", max_pending=8)
    for seq in range(3):
        w.put(make_estimate(10.0, 20.0, seq=seq))
    assert entered.wait(HANG_GUARD_S)
    with caplog.at_level(logging.WARNING, logger="rig.publishers"):
        assert within(HANG_GUARD_S, lambda: w.close(0.05)) is False
        assert finished == [] and w.stats()["writer_alive"]
        release.set()
        wait_until(lambda: not w.stats()["writer_alive"], "the stuck writer to end")
    assert finished == [("sunrig-test output", [0, 1, 2])]  # after every queued write, in its own thread
    messages = [rec.getMessage() for rec in caplog.records]
    assert any("stuck in a write" in m and "2 pending" in m for m in messages)
    assert any("could not finish after its stuck write" in m and "Input/output error" in m for m in messages)
    assert w.close(HANG_GUARD_S) and len(finished) == 1


def test_a_close_interrupted_by_a_signal_leaves_the_finish_to_the_thread():
    # Ctrl-C or SIGTERM landing while close() waits for the writer: without a hand-off nobody
    # would finish the output (a recording with no summary, for good).
    release = threading.Event()
    finished = []
    w = QueuedWriter(lambda est: release.wait(HANG_GUARD_S), lambda: finished.append(True), what="test output",
                     max_pending=8)
    w.put(make_estimate(10.0, 20.0, seq=0))

    def interrupted_join(timeout=None):
        raise KeyboardInterrupt  # FAKE: the signal, at the one place where it would land

    real_join, w._thread.join = w._thread.join, interrupted_join
    with pytest.raises(KeyboardInterrupt):
        w.close(HANG_GUARD_S)
    assert w.left_behind and not w.finished
    release.set()
    real_join(HANG_GUARD_S)
    assert finished == [True] and w.finished and not w.left_behind


def test_a_transport_raising_something_unforeseen_is_a_write_error_and_the_writer_lives_on():
    # pyserial's own loop:// port raises queue.Full once its 4096-byte buffer fills with nobody
    # reading. That killed the writer thread, and every estimate after it was a silent drop.
    pub = SerialPublisher("loop://", write_timeout_s=0.05)
    try:
        for i in range(200):  # 4096 bytes are about 57 sentences
            pub.publish(make_estimate(100.0, 30.0, seq=i))
            wait_until(lambda: (pub.stats()["pending"], pub.stats()["in_flight"]) == (0, 0)
                       or pub.stats()["write_errors"] > 0, "the writer to take the sentence")
            if pub.stats()["write_errors"]:
                break
        stats = pub.stats()
        assert stats["write_errors"] == 1 and stats["last_error"].startswith("Full"), stats
        pub.publish(make_estimate(100.0, 30.0, seq=1000))  # the writer is there to take it: it reopens
        wait_until(lambda: pub.stats()["reopens"] >= 1, "the writer to reopen the port")
        assert pub.stats()["writer_alive"]
    finally:
        within(5.0, pub.close)


@pytest.mark.parametrize("preempted_in", ["publish", "put"])
def test_a_publish_racing_a_close_is_written_or_refused_never_lost_unsaid(preempted_in):
    # The estimate thread checks that the background output is open, is descheduled, and close()
    # runs to its end before it queues the estimate: publish() returned as if the estimate were
    # taken, and it was neither written nor counted (dropped before it was queued, or left in a
    # queue no writer reads). It lands after the first check the publishing thread makes, or
    # after the one inside QueuedWriter.put.
    import sys

    preempted, closed = threading.Event(), threading.Event()
    publishing: list[threading.Thread] = []

    class PreemptedAfterTheCheck(threading.Event):
        def is_set(self) -> bool:
            seen = super().is_set()
            if (publishing and threading.current_thread() is publishing[0] and not preempted.is_set()
                    and (preempted_in == "publish" or sys._getframe(1).f_code.co_name == "put")):
                preempted.set()
                closed.wait(1.0)  # close() runs meanwhile; bounded, for a close() that must wait for this
            return seen

    text = io.StringIO()
    inner = JsonlPublisher(text)
    bg = BackgroundPublisher(inner)
    bg._worker._stop = PreemptedAfterTheCheck()
    outcome: list[str] = []

    def publish() -> None:
        try:
            bg.publish(make_estimate(10.0, 20.0, seq=7))
            outcome.append("taken")
        except PublishError:
            outcome.append("refused")

    publishing.append(threading.Thread(target=publish))
    publishing[0].start()
    assert preempted.wait(HANG_GUARD_S)
    within(HANG_GUARD_S, bg.close)
    closed.set()
    publishing[0].join(HANG_GUARD_S)
    assert outcome == ["refused"] or (outcome == ["taken"] and inner.stats()["written"] == 1), (
        f"publish() said {outcome}, and {inner.stats()['written']} written, {bg.stats()['pending']} left pending "
        f"after close")


def test_an_item_queued_just_before_close_is_written_not_left_in_the_queue():
    # The writer's wait for an item ends empty-handed (its 0.5-s poll), and before it looks at the
    # stop an item is queued and close() sets it: the writer took the stop as "nothing left" and
    # ended, and the item, queued while the output was open, was never written.
    written, finished = [], []
    w = QueuedWriter(written.append, lambda: finished.append(list(written)), what="test output", max_pending=8)
    waiting = threading.Event()
    real_get = w._queue.get

    def get_that_comes_back_empty_as_the_item_arrives(timeout: float):
        if waiting.is_set():
            return real_get(timeout)
        waiting.set()
        w._stop.wait(HANG_GUARD_S)  # its wait ended; it looks at the stop only once close() set it
        return None

    w._queue.get = get_that_comes_back_empty_as_the_item_arrives
    assert waiting.wait(HANG_GUARD_S)  # (after the 0.5-s poll it was in when patched, if it was)
    assert w.put(make_estimate(10.0, 20.0, seq=3))
    assert within(HANG_GUARD_S, lambda: w.close(HANG_GUARD_S))
    assert [e.seq for e in written] == [3] and finished == [written], (
        f"{len(w._queue)} left in the queue, {len(written)} written")
