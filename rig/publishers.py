"""Publishers: where a :class:`~rig.types.SunEstimate` goes once it is made.

The I/O shells around ``rig/protocol.py``. ``SerialPublisher`` never blocks its caller (the
estimator thread): ``publish()`` encodes and drops the message into a one-slot mailbox, newest
wins, and a writer thread does the I/O with a write timeout, dropping, counting and reopening
the port as needed. ``JsonlPublisher`` writes one JSON object per line, for scripts and
evaluation, in its caller's thread; live, :class:`BackgroundPublisher` moves it (and the NMEA
text on stdout) to a thread of its own, so a reader that stops reading stalls that output and
not the rig. The drop policy and counters are specified in ``docs/protocol.md``.
"""

from __future__ import annotations

import errno
import json
import logging
import math
import os
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Hashable
from pathlib import Path
from typing import IO, Any, Generic, Protocol, TypeVar, runtime_checkable

import serial

from rig.errors import PublishError
from rig.files import StreamFile
from rig.lasting import LastingCondition
from rig.portio import PORT_ERRORS, Backoff, begin_stop, join_worker
from rig.protocol import DEFAULT_STATUS_RULE, FLAG_VALID, StatusRule, encode_binary, encode_nmea, flag_names
from rig.ring import DropOldestQueue
from rig.types import SunEstimate

log = logging.getLogger(__name__)

T = TypeVar("T")


FORMATS: dict[str, Callable[[SunEstimate, StatusRule], bytes]] = {"nmea": encode_nmea, "binary": encode_binary}
# After a timeout, an error or a reopen the controller may hold half a message. An NMEA line
# end closes that line so the next sentence starts on its own line; a binary frame already
# starts with its own delimiter.
_RESYNC_PREFIX = {"nmea": b"\r\n", "binary": b""}


@runtime_checkable
class Publisher(Protocol):
    """What the pipeline hands each estimate to."""

    def publish(self, est: SunEstimate) -> None: ...

    def close(self) -> None: ...

    def stats(self) -> dict[str, Any]: ...


# The stats() keys that count estimates an output failed to write (a broken output, not a slow
# one): the serial writer's, a background writer's or the recorder's, and the pipeline's count of
# those a publish() call raised on ("raised").
ERROR_KEYS = ("write_errors", "errors", "raised")


def failed_writes(stats: dict[str, Any]) -> int:
    """Estimates an output failed to write, from its statistics (:data:`ERROR_KEYS`)."""
    return sum(int(stats.get(k) or 0) for k in ERROR_KEYS)


class ErrorTally:
    """Counts an output's failures and logs the first of each kind (same type and text): an
    output that fails the same way on every estimate is one warning, not one per estimate."""

    def __init__(self, logger: logging.Logger, what: str) -> None:
        self._log, self._what = logger, what
        self.count = 0
        self.last: str | None = None

    def add(self, exc: BaseException, seq: int) -> None:
        self.count += 1
        text = f"{type(exc).__name__}: {exc}"
        if text != self.last:
            self._log.warning("%s could not write seq %d (%s): counted, and the next ones are tried",
                              self._what, seq, text)
        self.last = text


def publisher_name(p: Publisher) -> str:
    """What a publisher is called in statistics and logs: its class, or the class it wraps."""
    inner = getattr(p, "inner", None)
    return type(inner if inner is not None else p).__name__


def open_serial(url: str, baudrate: int, write_timeout_s: float) -> serial.Serial:
    """Open ``url`` (a device path or a pyserial URL: ``socket://``, ``loop://``, ``spy://``), 8N1.

    Raises :class:`PublishError` with a message that says what to do.
    """
    try:
        port = serial.serial_for_url(url, baudrate=baudrate, write_timeout=write_timeout_s, do_not_open=True)
        port.open()
    except (serial.SerialException, OSError, ValueError) as exc:
        raise _open_error(url, exc) from None
    return port


def _open_error(name: str, exc: Exception) -> PublishError:
    """One line that says what failed and what to do (pyserial nests the errno text twice)."""
    code = exc.errno if isinstance(exc, OSError) else None
    reason = os.strerror(code) if isinstance(code, int) and code > 0 else str(exc)
    if code == errno.EACCES:
        hint = "add the user to the 'dialout' group or pass another --serial"
    else:
        hint = "check the cable or pass another --serial"
    return PublishError(f"cannot open serial port {name}: {reason}; {hint}")


# How often the writer retries a full kernel buffer: the line drains 4 KB in 0.36 s at 115200 baud.
_FULL_BUFFER_POLL_S = 0.005
# At close, how long the port's own buffer may take to send what it holds: 0.5 s is a 4 KiB
# kernel buffer at 115200 baud, or 6 sentences at 9600 (more than the rig leaves there when its
# reader keeps up; a stalled reader's backlog is stale anyway).
_CLOSE_DRAIN_S = 0.5
# wait_for_writer: how long publish() waits for the writer to take the previous message, at
# least. The writer takes it as soon as its write ends (within write_timeout_s); the rest is for
# a busy machine that schedules the writer thread late.
_WAIT_FOR_WRITER_MIN_S = 1.0


# A port whose writes keep failing (or timing out, or whose reopen fails) is said when that starts,
# again after this long if it lasts and then at doubling intervals up to an hour, and when a write
# goes through again: not at every failed write and reopen, a line a second for as long as it lasted.
_STILL_FAILING_FIRST_S = 60.0


# How many of the newest messages' sizes are kept for that: a UART buffer of 4 KiB holds about
# 60 NMEA sentences of ~70 bytes.
_WRITTEN_SIZES_KEPT = 1024


def _unsent_bytes(port: serial.Serial) -> int:
    """Bytes the port holds unsent (TIOCOUTQ); 0 where it cannot say (socket://, loop://)."""
    if type(port).__module__.endswith(".protocol_loop"):
        # loop://'s out_waiting is its loopback queue: bytes sent, waiting for its own reader, not
        # bytes unsent; counted as unsent, every sentence it carried was called dropped at close.
        return 0
    try:
        return int(port.out_waiting)
    except (AttributeError, NotImplementedError):
        return 0


def _plain_posix_fd(port: serial.Serial) -> int | None:
    """The non-blocking fd of a plain posix pyserial port, written directly (see ``_write_fd``).

    None for everything else (loop://, socket://, spy:// which logs in its write, Windows, a
    blocking fd): those go through their own ``write()`` and its write timeout.
    """
    if os.name != "posix" or type(port).write is not serial.Serial.write:
        return None
    try:
        fd = port.fileno()
        return fd if not os.get_blocking(fd) else None
    except PORT_ERRORS:
        return None


def _port_name(port: serial.Serial) -> str:
    return str(getattr(port, "port", None) or getattr(port, "name", None) or type(port).__name__)


class SerialPublisher:
    """Publish estimates as NMEA sentences or binary frames on a serial port, never blocking.

    ``port``: an opened (or openable) pyserial port object, or a device path / pyserial URL,
    opened here with ``serial_for_url``. The publisher owns the port from then on and closes it
    in :meth:`close`.

    Drop policy: one-slot mailbox, newest wins. A message overwritten before the writer took it
    counts in ``dropped_overwritten``; one whose write timed out in ``dropped_write_timeout``;
    one whose write failed in ``write_errors``; one written but then discarded unsent from the
    port's buffer (a close after a stall) in ``dropped_unsent``. After a timeout or an error the writer closes the
    port and reopens it after a backoff that doubles from ``backoff_s[0]`` to ``backoff_s[1]``:
    from the URL when it was given one, else with ``port.open()``.

    ``wait_for_writer``: for a replay, which has no deadline. ``publish()`` then waits (at most two
    write timeouts or 1 s, and only while the port is open) for the writer to take the previous
    message instead of replacing it: a replay at full speed reaches the controller whole, and a stalled
    or lost link slows it, never stops it. A live rig must not wait (the default).
    """

    def __init__(
        self,
        port: serial.Serial | str,
        *,
        format: str = "nmea",
        baudrate: int = 115200,
        write_timeout_s: float = 0.1,
        status_rule: StatusRule = DEFAULT_STATUS_RULE,
        backoff_s: tuple[float, float] = (0.1, 2.0),
        join_timeout_s: float = 2.0,
        wait_for_writer: bool = False,
    ) -> None:
        if format not in FORMATS:
            raise PublishError(f"unknown serial format {format!r}: expected one of {sorted(FORMATS)}")
        # A finite timeout is what bounds every wait of the writer thread; None would block forever.
        if not (isinstance(write_timeout_s, int | float) and math.isfinite(write_timeout_s) and write_timeout_s > 0):
            raise PublishError(f"write_timeout_s: expected a finite number of seconds > 0, got {write_timeout_s!r}")
        self._backoff = Backoff(backoff_s, PublishError)
        self._format = format
        self._encode = FORMATS[format]
        self._rule = status_rule
        self._baudrate = baudrate
        self._write_timeout_s = float(write_timeout_s)
        self._join_timeout_s = join_timeout_s
        self._wait_for_writer = wait_for_writer
        if isinstance(port, str):
            self._url: str | None = port
            self._port = open_serial(port, baudrate, self._write_timeout_s)
        else:
            self._url = None
            self._port = port
            if not port.is_open:
                try:
                    port.open()
                except PORT_ERRORS as exc:
                    raise _open_error(_port_name(port), exc) from None
            port.write_timeout = self._write_timeout_s
        self._name = self._url or _port_name(self._port)
        self._cond = threading.Condition()  # guards the mailbox, the counters and _in_flight
        self._slot: bytes | None = None
        self._in_flight = False
        self._resync = False
        self._last_error: str | None = None
        self._counts = dict.fromkeys(
            ("published", "written", "dropped_overwritten", "dropped_write_timeout", "dropped_unsent", "write_errors",
             "reopens"), 0
        )
        # The sizes of the newest messages written, newest last: when the port's unsent bytes are
        # discarded (a close after a stall), the messages they held move from written to dropped_unsent.
        self._written_sizes: deque[int] = deque(maxlen=_WRITTEN_SIZES_KEPT)
        # The bytes of a message whose write timed out or failed that went into the port's buffer
        # anyway: the newest unsent bytes, but that message is already counted as dropped.
        self._cut_bytes = 0
        # The writer's outage: None while writes go through, "failing" while they fail, time out or the
        # port cannot be reopened; its events are counted under the names of the counters above.
        self._outage = LastingCondition(None, remind_s=_STILL_FAILING_FIRST_S)
        # The newest error of the current outage, for its reminder: ``_last_error`` is the run's, and
        # an outage of write timeouts alone has none (it said "last error: None", or an old outage's).
        self._outage_error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"sunrig-serial {self._name}", daemon=True)
        self._thread.start()

    # --- the caller's side: never waits on I/O --------------------------------------------

    def publish(self, est: SunEstimate) -> None:
        """Encode ``est`` and leave it for the writer; returns at once, replacing an unsent message."""
        message = self._encode(est, self._rule)
        with self._cond:
            if self._wait_for_writer:  # returns at once when closed: that is one of its conditions
                self._cond.wait_for(self._slot_free_or_link_down,
                                    timeout=max(2 * self._write_timeout_s, _WAIT_FOR_WRITER_MIN_S))
            if self._stop.is_set():  # closed before, or while waiting
                raise PublishError(f"publish() on the closed serial publisher of {self._name}; make a new one")
            if self._slot is not None:
                self._counts["dropped_overwritten"] += 1
            self._slot = message
            self._counts["published"] += 1
            self._cond.notify_all()  # the writer; with wait_for_writer, publishers wait here too

    def _slot_free_or_link_down(self) -> bool:
        port = self._port
        return (self._slot is None or self._stop.is_set() or port is None or not port.is_open
                or not self._thread.is_alive())

    def stats(self) -> dict[str, Any]:
        """Counters and state. ``published`` = ``written`` + the four kinds of drop + ``pending``
        + ``in_flight``: every message is accounted for."""
        with self._cond:
            out: dict[str, Any] = dict(self._counts)
            out["pending"] = int(self._slot is not None)
            out["in_flight"] = int(self._in_flight)
            out["format"] = self._format
            out["port"] = self._name
            out["port_open"] = bool(self._port is not None and self._port.is_open)
            out["writer_alive"] = self._thread.is_alive()
            out["last_error"] = self._last_error
        return out

    def close(self) -> None:
        """Stop the writer and close the port. Idempotent; returns within about ``join_timeout_s``
        even when a write is stuck (the writer thread then closes the port when its write returns)."""
        if not begin_stop(self._cond, self._stop):
            return
        # First let the writer finish on its own: the last message and the drain take at most a
        # write timeout and _CLOSE_DRAIN_S. Only a writer still stuck then gets cancel_write(),
        # which wakes a pyserial write() waiting in select() (ports not written by _write_fd) but
        # also makes one that already wrote return 0, a message sent yet counted as dropped.
        first_s = min(self._join_timeout_s / 2, self._write_timeout_s + _CLOSE_DRAIN_S + 0.5)
        self._thread.join(first_s)
        join_worker(self._thread, self._join_timeout_s - first_s, getattr(self._port, "cancel_write", None), log,
                    f"serial writer for {self._name}", waited_s=first_s)

    def __enter__(self) -> SerialPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # --- the writer thread: all port I/O happens here ------------------------------------

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                if not self._port.is_open and not self._reopen():
                    self._backoff.wait(self._stop)
                    continue
                message = self._take()
                if message is None:
                    continue
                if self._write(message):
                    self._backoff.reset()
                else:
                    self._backoff.wait(self._stop)  # let a stalled reader drain, or a device come back
            self._send_last()
            self._close_port(drain_s=_CLOSE_DRAIN_S)  # a normal close: what was written is sent
        finally:
            self._close_port()

    def _send_last(self) -> None:
        """At close, send the message still in the mailbox (the last estimate of a replay, the
        newest of a live run) if the port is open: one write, cut short by a full buffer."""
        with self._cond:
            if self._slot is None or self._port is None or not self._port.is_open:
                return
            message, self._slot = self._slot, None
            self._in_flight = True
        self._write(message)

    def _take(self) -> bytes | None:
        """The newest message, waiting at most a bounded time so a stop is seen promptly."""
        with self._cond:
            if self._slot is None and not self._stop.is_set():
                self._cond.wait(0.5)
            if self._stop.is_set():  # closing: _send_last() has the last word
                return None
            message, self._slot = self._slot, None
            self._in_flight = message is not None
            self._cond.notify_all()  # a publish() waiting for the slot (wait_for_writer)
        return message

    def _write(self, message: bytes) -> bool:
        """Write one message; on a timeout or an error count the drop and close the port."""
        data = _RESYNC_PREFIX[self._format] + message if self._resync else message
        outcome, error = "written", None
        try:
            fd = _plain_posix_fd(self._port)
            if fd is not None:
                self._write_fd(fd, data)
            else:
                n = self._port.write(data)
                if n is not None and n < len(data):  # cancel_write() from close() cut it short
                    outcome = "dropped_write_timeout"
        except serial.SerialTimeoutException:
            outcome = "dropped_write_timeout"
        except PORT_ERRORS as exc:
            outcome, error = "write_errors", f"{type(exc).__name__}: {exc}"
        except Exception as exc:  # noqa: BLE001 - a transport may raise anything; the writer must live on
            # pyserial's loop:// raises queue.Full once nobody reads it; that killed this thread,
            # and every estimate after was counted as dropped with no error said.
            outcome, error = "write_errors", f"{type(exc).__name__}: {exc}"
        with self._cond:
            self._counts[outcome] += 1
            self._in_flight = False
            if outcome == "written":
                self._written_sizes.append(len(data))
            if error is not None:
                self._last_error = error
        if outcome == "written":
            self._resync = False
            self._note(None, outcome)
            return True
        if error is not None or not self._stop.is_set():  # a write cut short by close() is no outage
            self._note("failing", outcome, error)
        self._close_port()
        return False

    def _write_fd(self, fd: int, data: bytes) -> None:
        """Write all of ``data`` to a non-blocking fd within the write timeout, without spinning.

        pyserial's posix write retries EAGAIN in a busy loop until its timeout, and select()
        reports a full pseudo-terminal as writable, so waiting on select() would spin too. On a
        2-core rig a stalled reader would then take a core from the estimator. Instead: try,
        and on a full buffer wait a few milliseconds on the stop event (close() wakes it).
        """
        deadline = time.monotonic() + self._write_timeout_s
        view = memoryview(data)
        while view:
            try:
                view = view[os.write(fd, view) :]
                # What a write cut short left in the buffer (0 once whole); pyserial's own write()
                # cannot say, so there it stays 0. _close_port() uses it and sets it back to 0.
                self._cut_bytes = len(data) - len(view) if view else 0
                continue
            except (BlockingIOError, InterruptedError):
                pass
            except OSError as exc:
                raise serial.SerialException(f"write failed: {exc}") from None
            if time.monotonic() >= deadline:
                raise serial.SerialTimeoutException("Write timeout")
            if self._stop.wait(_FULL_BUFFER_POLL_S):
                raise serial.SerialTimeoutException("Write abandoned: the publisher is closing")

    def _close_port(self, drain_s: float = 0.0) -> None:
        """Close the port. After a failed write (``drain_s`` 0) what it holds is stale and is
        discarded; at a normal close it first gets up to ``drain_s`` to send it."""
        port = self._port
        if port is None or not port.is_open:
            return
        try:
            # A close with unsent data waits for it to drain (up to closing_wait, 30 s by default
            # on Linux UARTs), so what is still unsent after the drain is discarded. Only what the
            # port reports as unsent: a pty reports 0, and a flush there would drop bytes its
            # reader has not read yet.
            deadline = time.monotonic() + drain_s
            while _unsent_bytes(port) and time.monotonic() < deadline:
                time.sleep(_FULL_BUFFER_POLL_S)
            # Only bytes the port says it holds, and counted: a flush where it cannot say (a pty
            # reports 0) discarded sentences its reader had not read yet, still counted as written.
            unsent = _unsent_bytes(port)
            if unsent:
                port.reset_output_buffer()
                self._count_discarded(unsent - self._cut_bytes)
        except PORT_ERRORS:
            pass
        self._cut_bytes = 0
        try:
            port.close()
        except PORT_ERRORS:
            pass
        self._resync = True
        with self._cond:
            self._cond.notify_all()  # a publish() waiting for the writer: the link is down

    def _count_discarded(self, unsent_bytes: int) -> None:
        """Move the newest written messages that ``unsent_bytes`` held (a partly sent one too: its
        reader gets half a sentence) from ``written`` to ``dropped_unsent``."""
        with self._cond:
            while unsent_bytes > 0 and self._written_sizes:
                unsent_bytes -= self._written_sizes.pop()
                self._counts["written"] -= 1
                self._counts["dropped_unsent"] += 1

    def _reopen(self) -> bool:
        """Open the port again: a fresh one from the URL, else the given object. False if not yet."""
        try:
            if self._url is not None:
                port = serial.serial_for_url(
                    self._url, baudrate=self._baudrate, write_timeout=self._write_timeout_s, do_not_open=True
                )
                port.open()
                self._port = port
            else:
                self._port.open()
        except PORT_ERRORS as exc:
            with self._cond:
                self._last_error = f"reopen: {type(exc).__name__}: {exc}"
            self._note("failing", "reopen_failed", f"{type(exc).__name__}: {exc}")
            return False
        with self._cond:
            self._counts["reopens"] += 1
        self._resync = True
        if self._outage.said is None and self._outage.state is None:
            log.info("serial port %s reopened", self._name)  # closed by its owner, say: no outage to sum up
        self._note(self._outage.state, "reopens")
        return True

    def _note(self, state: Hashable, event: str, error: str | None = None) -> None:
        """Count a write or reopen in the outage (:class:`LastingCondition`) and say what it decides:
        an outage when it starts, at doubling intervals while it lasts, and when it ends."""
        now = time.monotonic()
        if state is None:
            self._outage_error = None
        elif error is not None:
            self._outage_error = f"reopen: {error}" if event == "reopen_failed" else error  # as in last_error
        said = self._outage.update(state, now, event)
        if said is None:
            return
        n = said.counts
        counted = (f"{n.get('write_errors', 0)} failed writes, {n.get('dropped_write_timeout', 0)} timed out "
                   f"and {n.get('reopen_failed', 0)} failed reopens in {now - said.since_s:.1f} s "
                   f"(reopened {n.get('reopens', 0)} times)")
        if said.kind == "change" and said.state is None:
            log.info("serial port %s writes again after %s", self._name, counted)
        elif said.kind == "change" and said.changes == 1:
            if event == "dropped_write_timeout":
                what = (f"serial write to {self._name} timed out after {self._write_timeout_s:g} s "
                        "(a reader that stopped reading?)")
            elif event == "reopen_failed":
                what = f"serial port {self._name} cannot be reopened ({error})"
            else:
                what = f"serial write to {self._name} failed ({error})"
            log.warning("%s; reopening with backoff: the failures are counted, and said again in %.0f s if they last "
                        "and when a write goes through", what, _STILL_FAILING_FIRST_S)
        elif said.changes:  # it went from failing to writing and back, unsaid: the budget was spent
            log.warning("serial writes to %s fail and go through in turn: %d changes, %d written, %s; %s", self._name,
                        said.changes, n.get("written", 0), counted,
                        "failing now" if said.state is not None else "writing now")
        else:
            last = (f"last error: {self._outage_error}" if self._outage_error is not None
                    else "they timed out with no error (a reader that stopped reading?)")
            log.warning("serial writes to %s still failing: %s; %s", self._name, counted, last)


class JsonRow(Protocol):
    """What a JSONL line can be made of: an estimate, or a GNSS update (``sunrig gnss``)."""

    def to_json_dict(self) -> dict[str, Any]: ...


class JsonlPublisher:
    """One ``json.dumps(est.to_json_dict())`` per line, flushed per line.

    ``target``: a path (checked now, replaced or made at the first estimate, closed by
    :meth:`close`: a run that writes none leaves it as it was; rig.files.StreamFile), ``"-"``
    for stdout, or an open text stream (flushed, left open: its owner closes it). This one writes in the caller's
    thread: it is for files and pipes, where a write does not stall. With a ``status_rule``, each
    line also says what the serial output would: ``valid`` and the ``status`` flag names.
    """

    def __init__(self, target: str | Path | IO[str], *, status_rule: StatusRule | None = None) -> None:
        self._rule = status_rule
        self._owned = False
        if target == "-":
            self._stream: IO[str] | StreamFile = sys.stdout
            self._name = "<stdout>"
        elif isinstance(target, str | Path):
            try:
                self._stream = StreamFile(target)  # closed in close()
            except OSError as exc:
                raise PublishError(
                    f"cannot write JSONL to {target}: {exc.strerror}; check the folder exists and is writable"
                ) from None
            self._owned = True
            self._name = str(target)
        else:
            self._stream = target
            self._name = getattr(target, "name", type(target).__name__)
        self._closed = False
        self._failed = False  # a write failed and said so: close() need not say it again
        self._counts = {"published": 0, "written": 0}

    def publish(self, est: SunEstimate | JsonRow) -> None:
        if self._closed:
            raise PublishError(f"publish() on the closed JSONL publisher of {self._name}; make a new one")
        self._counts["published"] += 1
        try:
            self._stream.write(json.dumps(self._row(est)) + "\n")
            self._stream.flush()  # a reader tailing the file, or a crash, sees every line whole
        except BrokenPipeError:
            raise  # the reader went away (`| head`): the output has ended (see RigPipeline._publish)
        except OSError as exc:
            self._failed = True
            raise self._write_error(exc) from None
        self._counts["written"] += 1

    def _row(self, est: SunEstimate | JsonRow) -> dict[str, Any]:
        row = est.to_json_dict()
        # What the serial output says of an estimate, by the same rule (a GNSS update has no status).
        if self._rule is not None and isinstance(est, SunEstimate):
            flags = self._rule.flags(est)
            row["valid"] = bool(flags & FLAG_VALID)
            row["status"] = flag_names(flags)
        return row

    def stats(self) -> dict[str, Any]:
        return {**self._counts, "target": self._name}

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            if self._owned:
                self._stream.close()
            else:
                self._stream.flush()
        except BrokenPipeError:
            raise
        except OSError as exc:
            # What a failed write left in the buffer fails again here: the same lost lines. Said
            # only if no write has said it (a file that filled up between the last write and close).
            if not self._failed:
                raise self._write_error(exc) from None

    def _write_error(self, exc: OSError) -> PublishError:
        return PublishError(f"cannot write JSONL to {self._name}: {exc.strerror or exc}; "
                            "free space or pass another --jsonl")

    def __enter__(self) -> JsonlPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


class SentencePublisher:
    """NMEA sentences as text lines on a stream (``sunrig demo`` without a serial port).

    Writes in the caller's thread, like :class:`JsonlPublisher`: for a terminal or a pipe.
    """

    def __init__(self, stream: IO[str], *, status_rule: StatusRule = DEFAULT_STATUS_RULE) -> None:
        self._stream = stream
        self._rule = status_rule
        self._closed = False
        self._counts = {"published": 0, "written": 0}

    def publish(self, est: SunEstimate) -> None:
        if self._closed:
            return
        self._counts["published"] += 1
        self._stream.write(encode_nmea(est, self._rule).decode("ascii").rstrip("\r\n") + "\n")
        self._stream.flush()
        self._counts["written"] += 1

    def stats(self) -> dict[str, Any]:
        return dict(self._counts)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._stream.flush()


class QueuedWriter(Generic[T]):
    """One writer thread behind a bounded queue: the thread half of :class:`BackgroundPublisher`
    and of the recorder (``rig/recorder.py``), so that the caller, the rig's estimate thread,
    never waits on a write.

    ``put`` returns at once; when ``max_pending`` items wait, the oldest is dropped (``dropped``).
    The thread hands each item to ``write``: an exception is counted (``errors``, logged once per
    kind) and the next item is tried; a ``BrokenPipeError`` (the reader went away) ends the thread
    and sets :attr:`gone`. ``finish`` (closing what ``write`` writes to) runs exactly once, after
    the last write: :meth:`close` runs it in its caller's thread, where its error reaches that
    caller, when the thread has drained the queue within ``join_timeout_s``; otherwise the thread
    is stuck in a write (a pipe nobody reads, a disk that stopped answering) and is left behind,
    and it runs ``finish`` itself when that write returns, so even then the output is finished
    rather than written to and closed from two threads at once.
    """

    def __init__(self, write: Callable[[T], object], finish: Callable[[], object], *, what: str,
                 max_pending: int) -> None:
        self._write, self._finish, self._what = write, finish, what
        self._queue: DropOldestQueue[T] = DropOldestQueue(max_pending)
        self._stop = threading.Event()
        self._gone = threading.Event()
        self._lock = threading.Lock()  # hands `finish` to exactly one of close() and the thread
        self._ended = self._left_behind = False
        self._finished = False  # `finish` returned (on either side)
        self.written = 0
        self._errors = ErrorTally(log, what)
        self._thread = threading.Thread(target=self._run, name=f"sunrig-{what}", daemon=True)
        self._thread.start()

    @property
    def closed(self) -> bool:
        return self._stop.is_set()

    @property
    def finished(self) -> bool:
        """``finish`` has run to its end: the output is complete."""
        return self._finished

    @property
    def left_behind(self) -> bool:
        """close() gave up on the thread, which is still in a write (it finishes the output if the
        write returns)."""
        return self._left_behind and not self._ended

    @property
    def gone(self) -> bool:
        """The reader went away (a broken pipe): nothing more can be written."""
        return self._gone.is_set()

    def put(self, item: T) -> bool:
        """Queue ``item``; False once closed: nothing is queued, no writer would take it.

        The check and the queuing hold the lock :meth:`close` sets the stop under: an item put while
        closing is queued before the stop, and written, or refused. Checked apart, a close landing in
        between left the item in a queue nobody reads, or dropped it with its caller told nothing."""
        with self._lock:
            if self._stop.is_set():
                return False
            self._queue.put(item)
            return True

    def stats(self) -> dict[str, Any]:
        return {"dropped": self._queue.dropped, "pending": len(self._queue), "errors": self._errors.count,
                "last_error": self._errors.last, "writer_alive": self._thread.is_alive()}

    def close(self, join_timeout_s: float) -> bool:
        """Let the thread write what is queued, for at most ``join_timeout_s``, then finish.
        False when the thread is stuck in a write and was left to finish on its own (warned).
        Idempotent: later calls return True and do nothing."""
        with self._lock:
            if self._stop.is_set():
                return True
            self._stop.set()
        self._queue.close()
        try:
            self._thread.join(join_timeout_s)
        finally:
            # Also when the join was interrupted (a signal): the thread then finishes the output
            # itself, rather than nobody.
            with self._lock:
                if not self._ended:
                    self._left_behind = True
        if self._left_behind:
            log.warning("%s is stuck in a write (a reader that stopped reading, a disk that stopped answering?); "
                        "left behind with %d pending, to finish when that write returns", self._what, len(self._queue))
            return False
        self._finish()
        self._finished = True
        return True

    def _run(self) -> None:
        try:
            self._drain()
        finally:
            with self._lock:
                self._ended = True
                late = self._left_behind
            if late:  # close() gave up on this thread: finishing is left to it
                try:
                    self._finish()
                    self._finished = True
                except Exception as exc:  # noqa: BLE001 - no caller is left to take it
                    log.warning("%s could not finish after its stuck write: %s", self._what, exc)

    def _drain(self) -> None:
        while True:
            item = self._queue.get(0.5)
            if item is None:
                # Closed, and nothing left (get() returns at once once closed). Empty is looked at
                # after the stop: an item queued after this wait ended and before close() set the
                # stop (put() refuses none after) was once left in the queue, never written.
                if self._stop.is_set() and not len(self._queue):
                    return
                continue
            try:
                self._write(item)
            except BrokenPipeError:
                self._gone.set()  # `| head` has read enough: no error, and nothing left to write
                return
            except Exception as exc:  # noqa: BLE001 - counted and reported; the next item may pass
                self._errors.add(exc, getattr(item, "seq", -1))
                continue
            self.written += 1


class BackgroundPublisher:
    """Another publisher, run in a thread of its own (:class:`QueuedWriter`): ``publish``
    returns at once.

    For the publishers that write in their caller's thread (:class:`JsonlPublisher`,
    :class:`SentencePublisher`) when the caller is the live rig. A pipe nobody drains or a
    terminal paused with Ctrl-S blocks their write; here that stalls this output only.

    Drop policy: up to ``max_pending`` estimates wait, and when full the oldest is dropped
    (``dropped``): a stall shorter than that loses nothing. An estimate the inner publisher
    raised on is counted in ``errors`` (the error logged once per kind). :meth:`close` waits at
    most ``join_timeout_s`` for the writer and closes the inner publisher; a writer stuck in a
    write is left to finish on its own (daemon thread), and it closes the inner publisher when
    that write returns. A broken pipe (the reader went away, ``| head``) ends the writer: later
    ``publish()`` calls raise ``BrokenPipeError``, as the inner publisher would in the caller's
    thread, and the pipeline then stops feeding this output.
    """

    def __init__(self, inner: Publisher, *, max_pending: int = 256, join_timeout_s: float = 2.0) -> None:
        self.inner = inner
        self._join_timeout_s = join_timeout_s
        self._worker: QueuedWriter[SunEstimate] = QueuedWriter(inner.publish, inner.close, what=type(inner).__name__,
                                                               max_pending=max_pending)

    def publish(self, est: SunEstimate) -> None:
        if self._worker.gone:
            # As the inner publisher would raise in the caller's thread: the caller (the pipeline)
            # takes a broken pipe as "this output has ended", not as an error.
            raise BrokenPipeError(f"the reader of {type(self.inner).__name__}'s stream went away")
        if not self._worker.put(est):  # closed, before this call or during it: said, so it is counted
            raise PublishError(f"publish() on the closed background {type(self.inner).__name__}; make a new one")

    def stats(self) -> dict[str, Any]:
        return {**self.inner.stats(), **self._worker.stats()}

    def close(self) -> None:
        """Write what is pending (within ``join_timeout_s``), then close the inner publisher."""
        self._worker.close(self._join_timeout_s)

    def __enter__(self) -> BackgroundPublisher:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
