"""How a command is stopped: Ctrl-C, SIGTERM and SIGHUP, all alike.

The default action of SIGTERM (`systemctl stop`, `docker stop`, `kill`) and SIGHUP (the terminal
of an ssh session that dropped) ends the process at once with nothing flushed: a recording
stopped that way was left empty. :class:`StopSignals` makes them what Ctrl-C is in Python, a
``KeyboardInterrupt`` in the main thread, so every command stops the way it stops on Ctrl-C: the
rig closes its outputs and finishes its recording, training keeps its steps.

An interrupt must not land in the middle of finishing something, where it would leave a
recording unfinished; and a second signal is common (GNU ``timeout`` signals the command and its
process group, so twice; an impatient Ctrl-C). So:

- signals within :data:`BURST_S` of the first of them are one request, not several: GNU timeout
  signals the command and then its process group, a few ms apart, and two signals counted as two
  requests quit a recording the first had asked to finish (a quarter of the time, when the first
  landed in a frame's write), leaving it without its summary;
- the first request raises ``KeyboardInterrupt``, unless the command is inside :meth:`finishing`
  (writing a frame, closing its outputs): then it is held, and :attr:`requested` tells the command
  to stop at the next point it looks;
- a request that finds the command finishing (the first, held; or the second, while the first's
  stop closes the outputs) is told to wait, once;
- the next one after that raises ``KeyboardInterrupt`` wherever the command is: quit at once.

Every wait in a stop is bounded, so waiting never means hanging. A signal ignored when the
command started (``nohup`` ignores SIGHUP) stays ignored.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from types import FrameType
from typing import Any

NAMES = ("SIGINT", "SIGTERM", "SIGHUP", "SIGBREAK")  # each skipped where the OS has none (SIGBREAK: Windows)

_WAIT_MESSAGE = b"sunrig: stopping: finishing what is under way; signal once more to quit at once\n"
# Signals this close to the first of them are one stop request (GNU timeout's two, a few ms apart);
# a person who means "quit at once" signals again after reading the wait message.
BURST_S = 0.5


class StopSignals:
    """Ctrl-C, SIGTERM and SIGHUP as one stop request (module docstring). Install with
    :meth:`installed` around a command; the command reads :attr:`requested` and wraps what must
    not be cut in :meth:`finishing`."""

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.received: list[int] = []
        self._finishing = 0
        self._told_at: int | None = None  # how many requests had come when told to wait
        self._requests = 0  # bursts of signals (BURST_S), each one request
        self._burst_start_s: float | None = None
        self._clock = clock

    @property
    def requested(self) -> bool:
        return bool(self.received)

    @property
    def by(self) -> str | None:
        """What asked first, in a user's words: ``Ctrl-C``, ``SIGTERM``, ``SIGHUP``; None if nothing."""
        if not self.received:
            return None
        first = self.received[0]
        return "Ctrl-C" if first == signal.SIGINT else signal.Signals(first).name

    def exit_code(self) -> int:
        """128 + the first signal's number, as a shell reports death by it (130 for Ctrl-C)."""
        return 128 + (self.received[0] if self.received else int(signal.SIGINT))

    def handle(self, signum: int, frame: object) -> None:  # noqa: ARG002 - a signal handler's signature
        self.received.append(signum)
        now = self._clock()
        if self._burst_start_s is not None and now - self._burst_start_s < BURST_S:
            return  # the request under way, sent again (module docstring)
        self._burst_start_s = now
        self._requests += 1
        n = self._requests
        if (n == 1 and not self._finishing) or (self._told_at is not None and n > self._told_at):
            raise KeyboardInterrupt  # the first, with nothing to finish; or once more after the wait message
        if self._told_at is None:
            self._told_at = n
            # os.write, not sys.stderr: the main thread may be inside a stderr write right now,
            # and a buffered stream refuses a reentrant call.
            with contextlib.suppress(OSError):
                os.write(2, _WAIT_MESSAGE)

    @contextlib.contextmanager
    def finishing(self) -> Iterator[None]:
        """A block a stop signal must not cut: one arriving inside is held (see :attr:`requested`) and
        says so, and only the next one quits."""
        self._finishing += 1
        try:
            yield
        finally:
            self._finishing -= 1

    @contextlib.contextmanager
    def installed(self, names: tuple[str, ...] = NAMES, after: str = "restore") -> Iterator[StopSignals]:
        """:meth:`handle` for ``names`` while the block runs, then the previous handlers back, or,
        with ``after="ignore"``, those signals ignored: for a process that exits once the block
        ends, where a late signal (the second of GNU timeout's, after the work is done) would kill
        a command that finished with the default action. Off the main thread (a library caller:
        Python sets handlers there only) nothing changes."""
        if after not in ("restore", "ignore"):
            raise ValueError(f"installed(after=...): expected 'restore' or 'ignore', got {after!r}")
        previous: dict[signal.Signals, Callable[[int, FrameType | None], Any] | int] = {}
        try:
            if threading.current_thread() is threading.main_thread():
                for name in names:
                    sig: signal.Signals | None = getattr(signal, name, None)
                    if sig is None:
                        continue
                    before = signal.getsignal(sig)
                    # Ignored (nohup) stays ignored; None is a handler set outside Python, which
                    # could not be put back: both are left alone.
                    if before is None or before is signal.SIG_IGN:
                        continue
                    # Recorded before the handler goes in: a signal landing in between still
                    # finds the previous handler put back by the finally below.
                    previous[sig] = before
                    signal.signal(sig, self.handle)
            yield self
        finally:
            for sig, before in previous.items():
                signal.signal(sig, signal.SIG_IGN if after == "ignore" else before)
