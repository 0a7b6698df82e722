"""A one-line progress counter for long work (replay, eval, synth, train), on stderr.

Drawn in place when the stream is a terminal. Elsewhere (a log file, ``nohup``, CI) a plain line
every ``log_every_s`` (60 s), so a long job in the background still shows it is alive and how
far it got, and a short one writes nothing but its summary, which is always written. Work
already done before this run (a resumed ``synth``) counts toward the total but not toward the
rate, so the rate and the time left describe this run.
"""

from __future__ import annotations

import os
import sys
import time
from typing import TextIO


def _clock(seconds: float) -> str:
    m, s = divmod(int(round(seconds)), 60)
    h, m = divmod(m, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m}:{s:02d}"


# The stream whose current row a redraw in place holds (one at most): a line written there next
# (a log line) must start below it, not run on after the row's text.
_open_row: list[TextIO] = []


def _drew_row(stream: TextIO, drawn: bool) -> None:
    _open_row[:] = [stream] if drawn else [s for s in _open_row if s is not stream]


def end_row(stream: TextIO | None = None) -> None:
    """Start a new line below a row drawn in place on ``stream`` (on any stream when None), so that
    what is written next begins a row of its own; the row stays on the screen."""
    for open_stream in list(_open_row):
        if stream is None or open_stream is stream:
            _drew_row(open_stream, False)
            try:
                open_stream.write("\n")
                open_stream.flush()
            except (OSError, ValueError):  # a closed or full stream: nothing to move below
                pass


def terminal_columns(stream: TextIO) -> int | None:
    """The width of the terminal ``stream`` writes to, now (it may have been resized); None when it
    is not a terminal or does not say."""
    try:
        return os.get_terminal_size(stream.fileno()).columns or None
    except (AttributeError, OSError, ValueError):  # no fileno (StringIO), not a tty, closed
        return None


def fit_row(text: str, columns: int | None) -> str:
    """``text`` cut to fit one row of a terminal ``columns`` wide (whole when unknown).

    A line as wide as the terminal or wider wraps, and ``\\r`` goes back to the start of its last
    row only: every redraw in place then left the rows above it behind."""
    if columns is None or len(text) < columns:
        return text
    return text[:max(columns - 4, 0)] + "..."


class StatusRow:
    """Status lines on ``stream``: on a terminal, one row redrawn in place; elsewhere (a log file,
    the journal), a line each time. A line too wide for the terminal is written whole as a line of
    its own too: cut to the row, the rig's status would lose its estimates and latency, and wrapped,
    each redraw left the rows above it behind."""

    def __init__(self, stream: TextIO) -> None:
        self.stream = stream
        self.tty = stream.isatty()

    @property
    def drawn(self) -> bool:
        """A row drawn in place is on the screen, the cursor at its end."""
        return self.stream in _open_row

    def show(self, text: str) -> None:
        columns = terminal_columns(self.stream) if self.tty else None
        if self.tty and (columns is None or len(text) < columns):
            self.stream.write(f"\r{text}\033[K")
            _drew_row(self.stream, True)
        else:
            self.stream.write(f"\r\033[K{text}\n" if self.drawn else f"{text}\n")
            _drew_row(self.stream, False)
        self.stream.flush()

    def end(self) -> None:
        """Close a row drawn in place, so that what is written next starts on a line of its own."""
        end_row(self.stream)


class Progress:
    """``label: done[/total] [unit] (rate/s[, time left]) extra``, redrawn at most every
    ``min_interval_s``; ``clock`` is injectable for tests."""

    def __init__(self, label: str, *, total: int | None = None, unit: str = "", stream: TextIO | None = None,
                 enabled: bool | None = None, min_interval_s: float = 0.2, log_every_s: float = 60.0,
                 clock=time.monotonic) -> None:
        self.label, self.total, self.unit = label, total, unit
        # sys.stderr as it is now, not as it was at import: a caller that redirects it (pytest's
        # capture, contextlib.redirect_stderr) must not get a counter writing to a closed stream.
        self.stream = sys.stderr if stream is None else stream
        self.enabled = self.stream.isatty() if enabled is None else enabled
        # Not a terminal and not told otherwise: a line now and then instead of redraws.
        self.log_every_s = log_every_s if enabled is None and not self.enabled else None
        self.min_interval_s = min_interval_s
        self.clock = clock
        self.start = clock()
        self.last = float("-inf")
        self.done = 0
        self.skipped = 0  # done before this run: not part of the rate

    def line(self, extra: str = "") -> str:
        elapsed = max(self.clock() - self.start, 1e-9)
        rate = (self.done - self.skipped) / elapsed
        count = f"{self.done}/{self.total}" if self.total is not None else f"{self.done}"
        unit = f" {self.unit}" if self.unit else ""
        timing = f"{rate:.1f}/s"
        if self.total is not None and rate > 0 and self.done < self.total:
            timing += f", {_clock((self.total - self.done) / rate)} left"
        return f"{self.label}: {count}{unit} ({timing})" + (f" {extra}" if extra else "")

    def update(self, done: int, extra: str = "") -> None:
        """Set the count to ``done`` (work finished so far, including skipped) and maybe redraw."""
        self.done = done
        now = self.clock()
        if not self.enabled:
            if self.log_every_s is not None and now - max(self.last, self.start) >= self.log_every_s:
                self.last = now
                self.stream.write(f"{self.line(extra)}\n")
                self.stream.flush()
            return
        if now - self.last < self.min_interval_s:
            return
        self.last = now
        self.stream.write(f"\r{fit_row(self.line(extra), terminal_columns(self.stream))}\033[K")
        _drew_row(self.stream, True)
        self.stream.flush()

    def advance(self, n: int = 1, extra: str = "") -> None:
        self.update(self.done + n, extra)

    def skip(self, n: int) -> None:
        """``n`` units were already done before this run (e.g. logs a resumed run keeps)."""
        self.skipped += n
        self.update(self.done + n)

    def close(self, summary: str | None = None) -> None:
        """Clear the counter; write ``summary`` as the final line when given."""
        if self.enabled:
            self.stream.write("\r\033[K")
            _drew_row(self.stream, False)
        if summary is not None:
            self.stream.write(f"{self.label}: {summary}\n")
        self.stream.flush()
