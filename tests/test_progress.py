"""The progress line: drawn only on a terminal, rate and time left for this run only."""

import contextlib
import io

from rig.progress import Progress


class _Tty(io.StringIO):
    def isatty(self):
        return True


def test_counts_rate_and_time_left_exclude_work_done_before_this_run():
    now = [100.0]
    out = _Tty()
    p = Progress("synth", total=1000, unit="frames", stream=out, clock=lambda: now[0])
    p.skip(400)  # a resumed run kept 400 frames
    now[0] += 10.0
    p.advance(100)  # 100 frames in 10 s: 10/s, 500 left -> 50 s
    assert p.line() == "synth: 500/1000 frames (10.0/s, 0:50 left)"
    assert out.getvalue().endswith("synth: 500/1000 frames (10.0/s, 0:50 left)\033[K")
    p.close("done")
    assert out.getvalue().endswith("\r\033[Ksynth: done\n")


def test_not_a_terminal_gets_only_the_summary_and_redraws_are_throttled():
    out = io.StringIO()
    p = Progress("eval", stream=out)
    for i in range(100):
        p.update(i, "windows")
    p.close("mean 9 deg")
    assert out.getvalue() == "eval: mean 9 deg\n"
    now = [0.0]
    tty = _Tty()
    q = Progress("eval", stream=tty, clock=lambda: now[0], min_interval_s=0.2)
    for i in range(10):
        now[0] += 0.05
        q.update(i)
    assert tty.getvalue().count("\r") == 3  # at 0.05 s, then every 0.2 s: 0.25, 0.45
    q.close()
    assert not tty.getvalue().endswith("\n")  # no summary: the line is only cleared


def test_not_a_terminal_gets_a_plain_line_a_minute_on_long_work():
    # A training run under nohup: no redraws, but a line every log_every_s, so its log shows it
    # is alive and how far it got.
    now = [0.0]
    out = io.StringIO()
    p = Progress("train", total=100, unit="steps", stream=out, clock=lambda: now[0], log_every_s=60.0)
    for step in range(1, 101):
        now[0] += 2.0  # 2 s a step: 200 s in all
        p.update(step, "err 7.1 deg")
    lines = out.getvalue().splitlines()
    assert len(lines) == 3 and "\r" not in out.getvalue()  # at 60, 120 and 180 s
    assert lines[0] == "train: 30/100 steps (0.5/s, 2:20 left) err 7.1 deg"
    # Told explicitly (enabled=False: --quiet), nothing but the summary.
    quiet = io.StringIO()
    q = Progress("train", stream=quiet, enabled=False, clock=lambda: now[0])
    now[0] += 1000.0
    q.update(5)
    assert quiet.getvalue() == ""


def test_time_left_is_rounded_shows_hours_and_stops_at_the_end():
    # _clock rounds to the second (59.6 s -> 1:00, not 0:59) and shows hours from 1 h on
    # (3700 s -> 1:01:40); a finished count shows no time left at all.
    now = [0.0]
    p = Progress("synth", total=303, stream=_Tty(), clock=lambda: now[0])
    now[0] = 1.0
    p.update(5)  # 5/s, 298 left -> 59.6 s
    assert p.line() == "synth: 5/303 (5.0/s, 1:00 left)"
    q = Progress("train", total=3701, stream=_Tty(), clock=lambda: now[0])
    now[0] = 2.0  # 1 s after q started
    q.update(1)  # 1/s, 3700 left
    assert q.line() == "train: 1/3701 (1.0/s, 1:01:40 left)"
    q.update(3701)
    assert q.line() == "train: 3701/3701 (3701.0/s)"


class _FlushLog(io.StringIO):
    """Records what had been written at each flush: what a reader of the stream has seen."""

    def __init__(self, tty: bool):
        super().__init__()
        self.tty, self.seen = tty, []

    def isatty(self):
        return self.tty

    def flush(self):
        self.seen.append(self.getvalue())


def test_every_line_written_is_flushed_at_once():
    # A redraw ends without a newline, so a line-buffered terminal would hold it back; a log line
    # under nohup and the closing summary must reach the file while the job runs, not at exit.
    now = [0.0]
    tty = _FlushLog(tty=True)
    p = Progress("eval", total=10, stream=tty, clock=lambda: now[0])
    now[0] = 1.0
    p.update(4)
    assert tty.seen and tty.seen[-1].endswith("eval: 4/10 (4.0/s, 0:02 left)\033[K")
    p.close("mean 9 deg")
    assert tty.seen[-1].endswith("\r\033[Keval: mean 9 deg\n")
    log = _FlushLog(tty=False)
    q = Progress("train", stream=log, clock=lambda: now[0])
    now[0] += 60.0
    q.update(3)
    assert log.seen and log.seen[-1].startswith("train: 3 (")


def test_not_a_terminal_logs_once_a_minute_by_default():
    # The default interval is the documented 60 s: nothing at 59 s, a line at 60 s.
    now = [0.0]
    out = io.StringIO()
    p = Progress("synth", stream=out, clock=lambda: now[0])
    now[0] = 59.0
    p.update(1)
    assert out.getvalue() == ""
    now[0] = 60.0
    p.update(2)
    assert out.getvalue().startswith("synth: 2 (")


def test_advance_counts_one_by_default_and_the_first_second_has_a_rate():
    # 5 units in the first half second is 10/s: the rate is not held back until a second has passed.
    now = [0.0]
    p = Progress("replay", total=20, stream=_Tty(), clock=lambda: now[0])
    now[0] = 0.5
    for _ in range(5):
        p.advance()
    assert p.done == 5
    assert p.line() == "replay: 5/20 (10.0/s, 0:02 left)"


def test_the_default_stream_is_stderr_when_made_not_when_imported():
    # A default bound at import wrote to whatever stderr was then: after a redirect closed it,
    # every later Progress (train's loading counter) failed with "I/O operation on closed file".
    first = io.StringIO()
    with contextlib.redirect_stderr(first):
        assert Progress("eval").stream is first
    first.close()
    second = io.StringIO()
    with contextlib.redirect_stderr(second):
        p = Progress("eval", total=2, enabled=False)
        p.close("2 logs")
    assert p.stream is second and second.getvalue() == "eval: 2 logs\n"



def _pty_stream(columns: int):
    """A real pseudo-terminal ``columns`` wide: the stream a redraw writes to, and the fd to read it back."""
    import fcntl
    import os
    import struct
    import termios
    master, slave = os.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, columns, 0, 0))
    return os.fdopen(slave, "w", encoding="utf-8"), master


def _read_all(master: int) -> str:
    import os
    import select
    out = b""
    while select.select([master], [], [], 0.2)[0]:
        try:
            out += os.read(master, 65536)
        except OSError:
            break
    return out.decode()


def test_a_redraw_never_wraps_on_a_narrow_terminal():
    # A line wider than the terminal wraps, and "\r" goes back to its last row only: each redraw
    # then left the rows above it behind, a scrolling heap of half lines instead of one counter.
    from rig.progress import Progress
    stream, master = _pty_stream(40)
    with stream:
        p = Progress("train", total=900, unit="steps", stream=stream, enabled=True, min_interval_s=0.0)
        p.update(12, extra="loss 0.2345 lr 1.0e-04 val mean 7.1 deg, best 6.9 deg at step 600")
        p.update(13, extra="loss 0.2345 lr 1.0e-04 val mean 7.1 deg, best 6.9 deg at step 600")
        written = _read_all(master)
    import os
    os.close(master)
    rows = [r.split("\x1b[K")[0] for r in written.split("\r") if r]
    assert rows and all(len(r) < 40 for r in rows), rows
    assert rows[-1].startswith("train: 13/900 steps"), rows


def test_a_redraw_keeps_the_whole_line_when_it_fits_or_no_width_is_known():
    from rig.progress import fit_row
    assert fit_row("short line", 80) == "short line"
    assert fit_row("x" * 200, None) == "x" * 200
    assert fit_row("x" * 200, 40) == "x" * 36 + "..."
