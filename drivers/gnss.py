"""GNSS compass / INS heading, position and UTC from NMEA 0183 on a serial line: the I/O shell.

``GnssReader`` owns a port and one reader thread. The thread only reads bytes, stamps them with
the injected clock and hands them to the pure :class:`drivers.nmea.NmeaStream`; everything it
learns is kept under a lock for the caller to ask: :meth:`GnssReader.latest_heading`,
:meth:`~GnssReader.latest_fix`, :meth:`~GnssReader.utc_at`, :meth:`~GnssReader.heading_history`,
:meth:`~GnssReader.stats`. ``docs/gnss.md`` is the specification.

The source is a transport, not only a path: an opened pyserial port, a pyserial URL
(``/dev/ttyUSB0``, ``socket://host:port``, ``loop://``, ``spy://``) or a capture file, which
replays to its end and then finishes.
"""

from __future__ import annotations

import dataclasses
import errno
import logging
import math
import os
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any, BinaryIO

import serial

from drivers.nmea import (
    MAX_SENTENCE_LEN,
    GnssUpdate,
    HeadingReading,
    HeadingSample,
    NmeaStream,
    newest_heading,
    suspended_between,
)
from rig.errors import GnssError
from rig.portio import PORT_ERRORS, Backoff, begin_stop, join_worker
from rig.types import GnssFix

log = logging.getLogger(__name__)


DEFAULT_BAUD = 115200  # what GNSS compasses ship with; NMEA 0183 itself says 4800, 0183-HS 38400
# A heading older than this is stale. It is above 1 s because many GNSS compasses send one
# heading a second, and the line and the device add latency and jitter on top.
DEFAULT_MAX_AGE_S = 1.5
_READ_CHUNK = 4096
# Bytes for this long without one NMEA sentence in them is a wrong baud rate or a port that is not
# the GNSS, not noise: said once, live (the rig's frames go without heading meanwhile).
UNFRAMED_SAY_S = 5.0


def boottime_offset_s() -> float | None:
    """CLOCK_BOOTTIME - CLOCK_MONOTONIC in seconds: the time the host has spent suspended since it
    booted, which ``time.monotonic()`` does not count. None where there is no CLOCK_BOOTTIME (not
    Linux): suspends go unseen there, and ages are judged by the monotonic clock alone."""
    boottime = getattr(time, "CLOCK_BOOTTIME", None)
    if boottime is None:
        return None
    return time.clock_gettime(boottime) - time.clock_gettime(time.CLOCK_MONOTONIC)


class FileTransport:
    """A capture file behind the small part of the pyserial interface the reader uses.

    ``read`` never blocks; at the end of the file it returns b"" and sets ``at_eof``.
    (``serial_for_url`` cannot open a regular file: it is not a terminal.)
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.port = str(path)
        self.timeout = 0.0
        self.at_eof = False
        self._file: BinaryIO | None = None
        self.open()

    @property
    def is_open(self) -> bool:
        return self._file is not None

    @property
    def in_waiting(self) -> int:
        return 0 if self.at_eof else _READ_CHUNK

    def open(self) -> None:
        if self._file is None:
            self._file = open(self.port, "rb")  # closed in close()
            self.at_eof = False

    def read(self, size: int = 1) -> bytes:
        if self._file is None:
            raise serial.PortNotOpenError()
        data = self._file.read(size)
        if not data:
            self.at_eof = True
        return data

    def cancel_read(self) -> None:
        pass  # reads never block

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def _open_error(name: str, exc: BaseException) -> GnssError:
    """One line that says what failed and what to do (pyserial nests the errno text twice)."""
    code = exc.errno if isinstance(exc, OSError) else None
    reason = os.strerror(code) if isinstance(code, int) and code > 0 else str(exc)
    if code == errno.EACCES:
        hint = "add the user to the 'dialout' group, or check the file's permissions"
    else:
        hint = "check the device path and cable, or pass socket://HOST:PORT or a capture file"
    return GnssError(f"cannot open GNSS source {name}: {reason}; {hint}")


def open_source(source: Any, *, baudrate: int = DEFAULT_BAUD, timeout_s: float = 0.1) -> Any:
    """An open transport for ``source``: a port object (opened if needed), a pyserial URL or
    device path (``serial_for_url``), or a regular file (:class:`FileTransport`). GnssError otherwise."""
    if hasattr(source, "read"):
        if not source.is_open:
            try:
                source.open()
            except PORT_ERRORS as exc:
                raise _open_error(str(getattr(source, "port", source)), exc) from None
        return source
    name = os.fspath(source)
    if "://" not in name:
        path = Path(name)
        if not path.exists():
            raise GnssError(f"cannot open GNSS source {name}: no such file or device; "
                            "check the path, or pass socket://HOST:PORT")
        if path.is_dir():
            raise GnssError(f"cannot open GNSS source {name}: it is a directory; pass a device or a capture file")
        if path.is_file():
            try:
                return FileTransport(path)
            except OSError as exc:
                raise _open_error(name, exc) from None
    try:
        port = serial.serial_for_url(name, baudrate=baudrate, timeout=timeout_s, do_not_open=True)
        port.open()
    except PORT_ERRORS as exc:
        raise _open_error(name, exc) from None
    return port


class GnssReader:
    """Read NMEA from a GNSS compass / INS in a thread; ask for the newest heading, fix and UTC.

    ``port_or_url``: an opened (or openable) pyserial port, a device path or pyserial URL, or a
    capture file. The reader owns the port from then on and closes it in :meth:`close`.

    Every wait is bounded: a read returns within ``timeout_s`` (the port's ``timeout``), so the
    thread sees the stop event promptly, and :meth:`close` joins it for at most
    ``join_timeout_s``. A read error (the device unplugged, the TCP bridge gone) is counted in
    ``read_errors`` and kept as ``last_error``; the port is closed and reopened after a backoff
    that doubles from ``backoff_s[0]`` to ``backoff_s[1]``.

    ``history``: how many heading samples are kept for interpolation (a ring: the oldest goes).
    ``events``: when > 0, every :class:`GnssUpdate` is also queued (up to this many) for
    :meth:`get_events`. A live port never waits for the consumer: the oldest is dropped and
    counted in ``events_dropped``; a capture file waits instead, since nothing is lost by
    replaying more slowly.

    ``clock`` stamps each read (the monotonic time frames are stamped with). It does not advance
    while the host is suspended, so a sentence from before a suspend would look a moment old after
    it: ``boot_offset`` (:func:`boottime_offset_s`: CLOCK_BOOTTIME - CLOCK_MONOTONIC, the time spent
    suspended so far) is kept with each sentence too, and a heading, fix or UTC kept from before a
    suspend is not handed out after it. Nor are the bytes the first read after a suspend finds
    waiting (sent before it, maybe, and kept by the kernel meanwhile): they are dropped, counted in
    ``stale_bytes``. Where it returns None (no CLOCK_BOOTTIME), it is not checked.
    """

    def __init__(
        self,
        port_or_url: Any,
        *,
        baudrate: int = DEFAULT_BAUD,
        timeout_s: float = 0.1,
        clock: Callable[[], float] = time.monotonic,
        boot_offset: Callable[[], float | None] = boottime_offset_s,
        history: int = 512,
        events: int = 0,
        require_checksum: bool = False,
        max_len: int = MAX_SENTENCE_LEN,
        backoff_s: tuple[float, float] = (0.1, 2.0),
        join_timeout_s: float = 2.0,
    ) -> None:
        if not (isinstance(timeout_s, int | float) and math.isfinite(timeout_s) and timeout_s > 0):
            # None or 0 would make the thread block forever or spin; either breaks close().
            raise GnssError(f"timeout_s: expected a finite number of seconds > 0, got {timeout_s!r}")
        self._backoff = Backoff(backoff_s, GnssError)
        if history < 1 or events < 0:
            raise GnssError(f"history: expected >= 1 samples and events >= 0, got {history}, {events}")
        self._clock = clock
        self._boot_offset = boot_offset
        self._join_timeout_s = join_timeout_s
        self._port = open_source(port_or_url, baudrate=baudrate, timeout_s=timeout_s)
        self._is_file = isinstance(self._port, FileTransport)
        if not self._is_file:
            self._port.timeout = timeout_s
        self._name = str(getattr(self._port, "port", None) or type(self._port).__name__)
        self._stream = NmeaStream(max_len=max_len, require_checksum=require_checksum)

        self._cond = threading.Condition()  # guards everything below, and wakes get_events()
        # Each with the boot offset when it was read (a heading sample carries its own): what is from
        # before a suspend is not handed out, nor interpolated across (drivers/pairing.py).
        self._headings: deque[HeadingSample] = deque(maxlen=history)
        self._fix: tuple[float | None, float, GnssFix] | None = None
        self._utc: tuple[float | None, float, int] | None = None
        self._resumed_at_s: float | None = None
        self._events: deque[GnssUpdate] = deque()
        self._events_max = events
        self._counts = dict.fromkeys(("bytes", "updates", "read_errors", "reopens", "events_dropped", "suspends",
                                      "stale_bytes"), 0)
        self._stream_counts = self._stream.counts
        self._last_error: str | None = None
        self._failing = False  # only the reader thread touches it
        # Bytes since the last NMEA sentence (reader thread only): when they began, how many, and
        # whether that was said (UNFRAMED_SAY_S).
        self._sentences_seen = 0
        self._unframed_since_s: float | None = None
        self._unframed_bytes = 0
        self._unframed_said = False
        self._read_boot_s: float | None = None  # the boot offset at the last read (reader thread only)
        self._failure: str | None = None
        self._finished = threading.Event()  # the thread has ended (end of a capture, close, a bug)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"sunrig-gnss {self._name}", daemon=True)
        self._thread.start()

    # --- the caller's side: never waits on I/O ----------------------------------------------

    # ``now_s`` below is the monotonic time now (the clock's): a suspend is judged by the clocks as
    # they are when asked, so a heading, fix or UTC from before one is never handed out after it.

    def latest_heading(self, now_s: float, max_age_s: float = DEFAULT_MAX_AGE_S) -> HeadingReading | None:
        """The newest heading received at or before ``now_s`` (monotonic) with its age, or None
        when there is none or it is older than ``max_age_s`` or from before a suspend: a stale
        heading is never returned."""
        with self._cond:
            kept = list(self._headings)
        boot_now = self._boot_offset()
        samples = [s for s in kept if not suspended_between(s.boot_offset_s, boot_now)]
        return newest_heading(samples, now_s, max_age_s)

    def heading_history(self) -> list[HeadingSample]:
        """The kept heading samples, oldest first (for interpolating to a frame's time), each with
        the boot offset it was read under (``boot_offset_s``: the pairing does not interpolate
        across a suspend)."""
        with self._cond:
            return list(self._headings)

    def latest_fix(self, now_s: float, max_age_s: float = DEFAULT_MAX_AGE_S) -> GnssFix | None:
        """The newest position fix, or None when there is none, it arrived more than ``max_age_s``
        ago, or before a suspend."""
        with self._cond:
            kept = self._fix
        if kept is None or not self._fresh(kept[0], now_s - kept[1], max_age_s):
            return None
        return kept[2]

    def utc_at(self, now_s: float, max_age_s: float = 10.0) -> int | None:
        """UTC (ns) at monotonic ``now_s``, carried forward from the newest UTC sentence by the
        monotonic clock; None when there is none, it is older than ``max_age_s``, or it is from
        before a suspend (which the monotonic clock does not count: carried forward, it would be
        late by the whole suspend). It is late by the sentence's transmit time and the device's
        latency (tens of ms; docs/gnss.md)."""
        with self._cond:
            kept = self._utc
        if kept is None or not self._fresh(kept[0], now_s - kept[1], max_age_s):
            return None
        return kept[2] + round((now_s - kept[1]) * 1e9)

    def _fresh(self, boot_then: float | None, age_s: float, max_age_s: float) -> bool:
        return 0.0 <= age_s <= max_age_s and not suspended_between(boot_then, self._boot_offset())

    @property
    def resumed_at_s(self) -> float | None:
        """The monotonic time of the reader's first read after the latest host suspend it saw, or
        None. That clock stood still through the suspend, so a frame stamped before this may have
        been taken before it: the UTC and the fix the reader has now are not that frame's (the
        pairing, drivers/pairing.py, gives it neither)."""
        with self._cond:
            return self._resumed_at_s

    def get_events(self, timeout_s: float = 0.5) -> list[GnssUpdate]:
        """Take every queued update (``events`` > 0), waiting at most ``timeout_s`` for one."""
        with self._cond:
            if not self._events and not self._finished.is_set():
                self._cond.wait(timeout_s)
            out = list(self._events)
            self._events.clear()
            self._cond.notify_all()  # a capture replay may be waiting for room
        return out

    @property
    def finished(self) -> bool:
        """The reader thread has ended: the capture file is read to its end, or the reader is closed."""
        return self._finished.is_set()

    @property
    def failure(self) -> str | None:
        """Why the reader thread died of a bug (never for I/O errors, which it retries), or None."""
        with self._cond:
            return self._failure

    def wait_finished(self, timeout_s: float) -> bool:
        return self._finished.wait(timeout_s)

    def stats(self) -> dict[str, Any]:
        """Counters (``drivers.nmea`` FRAMER_COUNTS + STREAM_COUNTS, and the reader's own) and state."""
        with self._cond:
            out: dict[str, Any] = {**self._stream_counts, **self._counts}
            out["port"] = self._name
            out["port_open"] = bool(self._port.is_open)
            out["reader_alive"] = self._thread.is_alive()
            out["finished"] = self._finished.is_set()
            out["last_error"] = self._last_error
            out["history"] = len(self._headings)
        return out

    def close(self) -> None:
        """Stop the thread and close the port. Idempotent; returns within about ``join_timeout_s``."""
        if not begin_stop(self._cond, self._stop):
            return
        # cancel_read wakes a pyserial read() waiting in select() at once.
        join_worker(self._thread, self._join_timeout_s, getattr(self._port, "cancel_read", None), log,
                    f"GNSS reader for {self._name}")

    def __enter__(self) -> GnssReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the reader thread: all port I/O happens here -----------------------------------------

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if not self._port.is_open and not self._reopen():
                    self._backoff.wait(self._stop)
                    continue
                try:
                    data = self._port.read(self._port.in_waiting or 1)
                    t_mono_s, boot_offset_s = self._stamp()
                    suspended_s = self._suspended_since_last_read(boot_offset_s)
                    if suspended_s is not None:
                        # What the kernel kept through the suspend is all waiting now (the read that
                        # waited through it took as little as one byte of it): it goes with it.
                        waiting = self._port.in_waiting
                        if waiting:
                            data += self._port.read(waiting)
                except PORT_ERRORS as exc:
                    self._read_failed(exc)
                    self._backoff.wait(self._stop)  # a vanished device fails at once: do not spin
                    continue
                if data:
                    self._backoff.reset()
                if suspended_s is not None:
                    self._drop_stale(data, t_mono_s, suspended_s)
                elif data:
                    self._take(data, t_mono_s, boot_offset_s)
                elif self._is_file and self._port.at_eof:
                    self._take(b"", t_mono_s, boot_offset_s, end=True)
                    break
        except BaseException as exc:  # a bug: report it rather than die silently
            with self._cond:
                self._failure = f"{type(exc).__name__}: {exc}"
                self._last_error = f"reader thread failed: {self._failure}"
            log.exception("GNSS reader for %s failed", self._name)
        finally:
            self._close_port()
            with self._cond:
                self._finished.set()
                self._cond.notify_all()

    def _stamp(self) -> tuple[float, float | None]:
        """The monotonic time of a read, and the boot offset then. The offset first: a suspend
        between the two reads leaves the bytes marked as from before it (not handed out), never
        bytes from before it marked as from after."""
        boot_offset_s = self._boot_offset()
        return self._clock(), boot_offset_s

    def _suspended_since_last_read(self, boot_offset_s: float | None) -> float | None:
        """How long the host was suspended since the reader's last read (seconds), or None if it
        was not (or it cannot tell). Never for a capture file: its bytes wait nowhere meanwhile."""
        before, self._read_boot_s = self._read_boot_s, boot_offset_s
        if self._is_file or before is None or boot_offset_s is None or not suspended_between(before, boot_offset_s):
            return None
        return boot_offset_s - before

    def _drop_stale(self, data: bytes, t_mono_s: float, suspended_s: float) -> None:
        """The first read after a suspend. What it found waiting, and the partial line kept, may
        have been sent before the suspend: stamped now they would pass for fresh, an hour-old
        heading or UTC handed out as current. Bytes sent after the resume cannot be told apart
        from them, so all go (counted in ``stale_bytes``); the device's next sentences are fresh."""
        # The partial line from before is counted as truncated, as for a reopen; the date that GGA and
        # PASHR times of day take moves on by the time suspended.
        self._stream.suspended(suspended_s)
        counts = self._stream.counts
        with self._cond:
            self._counts["bytes"] += len(data)
            self._counts["stale_bytes"] += len(data)
            self._counts["suspends"] += 1
            self._resumed_at_s = t_mono_s
            self._stream_counts = counts
        log.info("GNSS reader for %s: the host was suspended for %.1f s; dropped %d bytes read after it that "
                 "may be from before it", self._name, suspended_s, len(data))

    def _take(self, data: bytes, t_mono_s: float, boot_offset_s: float | None, end: bool = False) -> None:
        """Decode outside the lock (pure work), then publish the results under it."""
        updates = self._stream.flush(t_mono_s) if end else self._stream.feed(data, t_mono_s)
        # A heading sample carries its boot offset itself: heading_history() hands it to the pairing.
        updates = [u if u.heading is None else
                   dataclasses.replace(u, heading=dataclasses.replace(u.heading, boot_offset_s=boot_offset_s))
                   for u in updates]
        counts = self._stream.counts
        self._failing = False
        self._note_framing(counts.get("sentences", 0), len(data), t_mono_s)
        with self._cond:
            self._counts["bytes"] += len(data)
            self._counts["updates"] += len(updates)
            self._stream_counts = counts
            for u in updates:
                if u.heading is not None:
                    self._headings.append(u.heading)
                if u.fix is not None:
                    self._fix = (boot_offset_s, u.t_mono_s, u.fix)
                if u.utc_ns is not None:
                    self._utc = (boot_offset_s, u.t_mono_s, u.utc_ns)
            if self._events_max and updates:
                self._queue(updates)
                self._cond.notify_all()

    def _note_framing(self, sentences: int, n_bytes: int, t_mono_s: float) -> None:
        """Say once when bytes come for UNFRAMED_SAY_S without one NMEA sentence in them (a wrong
        baud rate, or a port that is not the GNSS: the exit report's garbage bytes, said only at
        the end), and when sentences come again."""
        if sentences != self._sentences_seen:
            self._sentences_seen = sentences
            if self._unframed_said:
                log.info("GNSS port %s: NMEA sentences again, after %d bytes of none", self._name, self._unframed_bytes)
            self._unframed_since_s, self._unframed_bytes, self._unframed_said = None, 0, False
            return
        if self._unframed_since_s is None:
            self._unframed_since_s = t_mono_s
        self._unframed_bytes += n_bytes
        if not self._unframed_said and t_mono_s - self._unframed_since_s >= UNFRAMED_SAY_S:
            self._unframed_said = True
            baud = getattr(self._port, "baudrate", None)
            log.warning("GNSS port %s: %d bytes in %.0f s and no NMEA sentence in them; check that it is the GNSS's "
                        "NMEA output and its baud rate (--baud, now %s)", self._name, self._unframed_bytes,
                        t_mono_s - self._unframed_since_s, baud if baud is not None else "unknown")

    def _queue(self, updates: list[GnssUpdate]) -> None:
        """Called under the lock. Live: drop the oldest. File: wait for room (bounded, sees stop)."""
        for u in updates:
            while self._is_file and len(self._events) >= self._events_max and not self._stop.is_set():
                self._cond.wait(0.1)
            if len(self._events) >= self._events_max:
                self._events.popleft()
                self._counts["events_dropped"] += 1
            self._events.append(u)
            self._cond.notify_all()

    def _read_failed(self, exc: BaseException) -> None:
        message = f"{type(exc).__name__}: {exc}"
        with self._cond:
            self._counts["read_errors"] += 1
            self._last_error = message
        if not self._failing:  # once per outage, not once per retry
            self._failing = True
            log.warning("GNSS read from %s failed (%s); reopening with backoff", self._name, message)
        self._close_port()
        self._stream.reset()  # counts the sentence the outage cut short as truncated
        with self._cond:  # ... which stats() shows now, not only once the device sends again
            self._stream_counts = self._stream.counts

    def _reopen(self) -> bool:
        try:
            self._port.open()
        except PORT_ERRORS as exc:
            with self._cond:
                self._last_error = f"reopen failed: {type(exc).__name__}: {exc}"
            return False
        with self._cond:
            self._counts["reopens"] += 1
        log.info("GNSS source %s reopened", self._name)
        return True

    def _close_port(self) -> None:
        try:
            if self._port.is_open:
                self._port.close()
        except PORT_ERRORS:
            pass
