"""Ctrl-C, SIGTERM and SIGHUP as one stop request (rig/stopping.py)."""

import signal
import time

import pytest

from rig.stopping import BURST_S, StopSignals


class Clock:
    """Time that moves only when told, so a burst of signals is one without a sleep."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def test_a_first_signal_while_finishing_is_held_and_the_next_quits(capfd):
    # A frame being written, the outputs being closed: the first signal waits for it, says so,
    # and the next one quits (a disk that never answers must not make the command unstoppable).
    clock = Clock()
    stop = StopSignals(clock=clock)
    before = signal.getsignal(signal.SIGTERM)
    with stop.installed():
        with stop.finishing():
            signal.raise_signal(signal.SIGTERM)  # held
            assert stop.requested and stop.by == "SIGTERM"
            clock.t += BURST_S
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(signal.SIGINT)  # told "signal once more": this is it
                time.sleep(5.0)  # (the interrupt lands before this)
    assert signal.getsignal(signal.SIGTERM) is before
    assert stop.exit_code() == 128 + signal.SIGTERM  # the first one's, as a shell reports it
    assert capfd.readouterr().err.count("signal once more to quit at once") == 1


def test_a_stop_under_way_lets_its_close_finish_once_and_a_third_quits(capfd):
    # The first signal stops the command; a second request finds it closing its outputs and
    # waits; a third quits at once.
    clock = Clock()
    stop = StopSignals(clock=clock)
    with stop.installed():
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)  # nothing to finish: stops at once
        with stop.finishing():
            clock.t += BURST_S
            signal.raise_signal(signal.SIGINT)  # the close goes on
            clock.t += BURST_S
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(signal.SIGINT)
    assert stop.by == "Ctrl-C" and stop.exit_code() == 130
    assert capfd.readouterr().err.count("signal once more to quit at once") == 1


def test_the_handlers_come_back_when_the_block_is_interrupted():
    stop = StopSignals()
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    with pytest.raises(KeyboardInterrupt), stop.installed():
        signal.raise_signal(signal.SIGINT)
    assert {sig: signal.getsignal(sig) for sig in before} == before
    assert stop.by == "Ctrl-C" and stop.exit_code() == 130


def test_signals_sent_together_are_one_request(capfd):
    # GNU timeout signals the command, then its process group, a few ms apart: counted as two
    # requests, the second quit a recording whose frame write had held the first, leaving it
    # without its summary (8 of 30 tries). Within BURST_S of the first, they are one.
    clock = Clock()
    stop = StopSignals(clock=clock)
    with stop.installed():
        with stop.finishing():
            signal.raise_signal(signal.SIGTERM)  # held
            clock.t += 0.003
            signal.raise_signal(signal.SIGTERM)  # the process group's copy: the same request
            clock.t += 0.2
            signal.raise_signal(signal.SIGHUP)
        # The close after the held frame is not cut by the burst either.
        with stop.finishing():
            clock.t += 0.2
            signal.raise_signal(signal.SIGINT)
    assert stop.requested and stop.by == "SIGTERM" and len(stop.received) == 4
    assert capfd.readouterr().err.count("signal once more to quit at once") == 1


def test_a_burst_is_timed_from_its_first_signal_so_mashing_still_quits():
    # Signals every 0.125 s (a key held down): the burst does not stretch with them, so the one
    # BURST_S after the first is a new request.
    clock = Clock()
    stop = StopSignals(clock=clock)
    with stop.installed(), pytest.raises(KeyboardInterrupt), stop.finishing():
        signal.raise_signal(signal.SIGINT)  # held, told to wait
        for _ in range(20):
            clock.t += 0.125
            signal.raise_signal(signal.SIGINT)  # the one at +0.5 s quits
    assert clock.t == pytest.approx(100.0 + BURST_S)


def test_a_process_about_to_exit_ignores_a_late_signal():
    # The `sunrig` command: GNU timeout's second signal came once the work was done, and the
    # default action killed a command that had finished (exit 143 for a complete recording).
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    try:
        with StopSignals().installed(after="ignore"):
            pass
        assert all(signal.getsignal(sig) is signal.SIG_IGN for sig in before)
        signal.raise_signal(signal.SIGTERM)  # nothing happens
    finally:
        for sig, handler in before.items():
            signal.signal(sig, handler)
    with pytest.raises(ValueError, match="restore' or 'ignore"), StopSignals().installed(after="drop"):
        pass
