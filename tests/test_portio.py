"""The reconnect backoff and bounded stop shared by the device workers (GNSS, serial, OAK)."""

import logging
import os
import socket
import threading
import time

import pytest
import serial

from rig.errors import PublishError
from rig.portio import Backoff, begin_stop, join_worker


def test_backoff_doubles_to_the_ceiling_and_resets():
    stop = threading.Event()
    stop.set()  # wait() returns at once: only the bookkeeping is under test
    b = Backoff((0.1, 0.5), PublishError)
    seen = []
    for _ in range(5):
        seen.append(b.current_s)
        b.wait(stop)
    assert seen == [0.1, 0.2, 0.4, 0.5, 0.5]
    b.reset()
    assert b.current_s == 0.1


@pytest.mark.parametrize("bad", [(0.0, 1.0), (2.0, 1.0), (-1.0, 1.0), (0.1, float("inf")), (float("nan"), 1.0)])
def test_backoff_refuses_bad_bounds_with_the_callers_error(bad):
    with pytest.raises(PublishError, match="backoff_s"):
        Backoff(bad, PublishError)


def test_backoff_wait_ends_at_stop():
    stop = threading.Event()
    b = Backoff((30.0, 60.0), PublishError)
    threading.Timer(0.05, stop.set).start()
    t0 = time.monotonic()
    b.wait(stop)
    assert time.monotonic() - t0 < 5.0  # not the 30 s backoff


@pytest.mark.parametrize("gone", [OSError("port gone"), ValueError("Attempting to use a port that is not open"),
                                  serial.SerialException("device disconnected")])
def test_waking_a_worker_on_a_port_that_went_away_is_not_an_error(gone):
    # pyserial raises ValueError, not OSError, on a port closed under it (unplugged USB): closing
    # the rig must still join the worker rather than raise out of close().
    release = threading.Event()
    t = threading.Thread(target=release.wait, daemon=True)
    t.start()

    def wake():
        release.set()
        raise gone

    join_worker(t, 1.0, wake, logging.getLogger("t"), "worker")
    assert not t.is_alive()


def test_join_worker_wakes_joins_and_leaves_a_stuck_thread(caplog):
    release = threading.Event()
    woken = []
    t = threading.Thread(target=release.wait, daemon=True)
    t.start()
    join_worker(t, 0.05, lambda: woken.append(True) or release.set(), logging.getLogger("t"), "worker")
    assert woken and not t.is_alive()

    stuck_release = threading.Event()
    stuck = threading.Thread(target=stuck_release.wait, daemon=True)
    stuck.start()

    def wake_fails():
        raise OSError("port gone")

    with caplog.at_level(logging.WARNING):
        join_worker(stuck, 0.05, wake_fails, logging.getLogger("t"), "stuck worker")  # the OSError is swallowed
    assert stuck.is_alive() and "stuck worker did not stop within 0.1 s" in caplog.text
    stuck_release.set()


def test_begin_stop_sets_once_and_wakes_waiters():
    cond, stop = threading.Condition(), threading.Event()
    woke = threading.Event()

    def waiter():
        with cond:
            while not stop.is_set():
                cond.wait(30.0)  # only a notify_all ends this before 30 s
        woke.set()

    t = threading.Thread(target=waiter, daemon=True)
    t.start()
    time.sleep(0.05)  # most likely waiting by now; if not, it sees the event and never waits
    assert begin_stop(cond, stop) is True and stop.is_set()
    assert begin_stop(cond, stop) is False  # idempotent: the second close does nothing
    assert woke.wait(10.0)


# --- Reconnects over a day: each one must give back what it took ------------------------------

CYCLES = 6  # pyserial sleeps 0.3 s in every socket:// close, so a cycle takes about 0.33 s


def open_fds() -> int:
    return len(os.listdir("/proc/self/fd"))


class DroppingPeer:
    """FAKE TCP peer, on real sockets (a GNSS bridge, a controller's serial bridge): accepts a connection, sends
    ``greeting``, reads for a moment and drops it, over and over: a link that keeps going away."""

    def __init__(self, greeting: bytes = b"") -> None:
        self.server = socket.create_server(("127.0.0.1", 0))
        self.server.settimeout(0.2)
        self.url = f"socket://127.0.0.1:{self.server.getsockname()[1]}"
        self.greeting, self.accepted = greeting, 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self.server.accept()
            except (TimeoutError, OSError):
                continue
            with conn:
                self.accepted += 1
                conn.settimeout(0.02)
                try:
                    conn.sendall(self.greeting)
                    conn.recv(4096)
                except OSError:
                    pass

    def close(self) -> None:
        self._stop.set()
        self._thread.join(10.0)
        self.server.close()


@pytest.mark.skipif(not os.path.isdir("/proc/self/fd"), reason="counts descriptors in /proc")
@pytest.mark.parametrize("worker", ["gnss reader", "serial publisher"])
def test_reconnects_give_back_their_descriptors(worker):
    # A rig whose GNSS bridge or controller link drops every minute reconnects ~1400 times a day:
    # a descriptor kept per reconnect would end it at the process's limit. After CYCLES reconnects
    # and a close, the count is back where it was (a little slack for the interpreter's own).
    from drivers.gnss import GnssReader
    from rig.publishers import SerialPublisher
    from tests.test_gnss_nmea import nmea
    from tests.test_protocol import make_estimate

    peer = DroppingPeer(greeting=nmea("GPHDT,33.0,T") * 3)
    before = open_fds()
    if worker == "gnss reader":
        device = GnssReader(peer.url, timeout_s=0.02, backoff_s=(0.005, 0.01))
        feed = None
    else:
        device = SerialPublisher(peer.url, write_timeout_s=0.02, backoff_s=(0.005, 0.01))
        feed = device.publish
    try:
        deadline = time.monotonic() + 30.0  # a guard, not a timing: the cycles take about 2 s
        # Both counts: the peer's accept returns before the worker's connect does, so on a busy
        # machine the last reopen is counted a moment after the peer has counted its connection.
        while ((peer.accepted < CYCLES or device.stats()["reopens"] < CYCLES - 1)
               and time.monotonic() < deadline):
            if feed is not None:
                feed(make_estimate(10.0, 20.0))
            time.sleep(0.005)
        assert peer.accepted >= CYCLES, device.stats()
        assert device.stats()["reopens"] >= CYCLES - 1
    finally:
        device.close()
        after = open_fds()
        peer.close()
    assert after <= before + 2, f"{after - before} descriptors kept after {CYCLES} reconnects"
