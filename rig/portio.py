"""What every device worker thread shares: the errors a port raises, the reconnect backoff, and a
bounded stop.

The GNSS reader, the serial publisher and the OAK reader each own a device from one background
thread. They differ in what they read or write, not in how they give up and come back: a failed
port is closed, reopened after a wait that doubles up to a ceiling, and the wait resets once data
flows again; ``close()`` sets the stop event, wakes the blocking call and joins the thread for a
bounded time, leaving a daemon thread stuck below Python rather than hanging the caller.
"""

from __future__ import annotations

import logging
import math
import threading
from collections.abc import Callable

import serial

try:  # pyserial's posix reset_output_buffer raises termios.error on a dead fd, not OSError
    from termios import error as _TermiosError
except ImportError:  # pragma: no cover - Windows

    class _TermiosError(Exception):  # type: ignore[no-redef]  # the stand-in for termios.error
        pass


# Everything a pyserial port (or a socket behind a pyserial URL) raises when its device goes away.
PORT_ERRORS: tuple[type[Exception], ...] = (serial.SerialException, OSError, ValueError, _TermiosError)


class Backoff:
    """The wait between reconnect attempts: ``first_s``, doubled after every failure up to
    ``longest_s``, back to ``first_s`` after a success. Waits on a stop event, so a close ends it."""

    def __init__(self, backoff_s: tuple[float, float], error: Callable[[str], Exception]) -> None:
        lo, hi = backoff_s
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 < lo <= hi):
            raise error(f"backoff_s: expected 0 < min <= max seconds, got {backoff_s!r}")
        self.first_s, self.longest_s = float(lo), float(hi)
        self.current_s = self.first_s

    def wait(self, stop: threading.Event) -> None:
        """Wait the current backoff (or until ``stop``), then double it for next time."""
        stop.wait(self.current_s)
        self.current_s = min(2.0 * self.current_s, self.longest_s)

    def reset(self) -> None:
        self.current_s = self.first_s


def begin_stop(cond: threading.Condition, stop: threading.Event) -> bool:
    """Set the worker's stop event under its lock and wake everything waiting on the lock.
    False when it was already set: ``close()`` is idempotent, and the stop event is the one record
    of "closed"."""
    with cond:
        if stop.is_set():
            return False
        stop.set()
        cond.notify_all()
    return True


def join_worker(thread: threading.Thread, join_timeout_s: float, wake: Callable[[], object] | None,
                log: logging.Logger, what: str, waited_s: float = 0.0) -> None:
    """After the stop event is set: wake the thread's blocking call (``wake``, e.g. pyserial's
    ``cancel_read``), join it for at most ``join_timeout_s`` and, if it is stuck below Python (a
    driver, a port without a timeout), leave the daemon thread to finish on its own.
    ``waited_s``: how long the caller already waited for it, for the warning's total."""
    if wake is not None:
        try:
            wake()
        except PORT_ERRORS:
            pass
    thread.join(join_timeout_s)
    if thread.is_alive():
        log.warning("%s did not stop within %.1f s; it releases its device when its call returns",
                    what, waited_s + join_timeout_s)
