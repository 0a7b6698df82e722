"""The reconnect backoff and bounded stop shared by the device workers (GNSS, serial, OAK)."""

import logging
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
