"""Ctrl-C, SIGTERM and SIGHUP as one stop request (rig/stopping.py)."""

import signal
import time

import pytest

from rig.stopping import StopSignals


def test_a_first_signal_while_finishing_is_held_and_the_next_quits(capfd):
    # A frame being written, the outputs being closed: the first signal waits for it, says so,
    # and the next one quits (a disk that never answers must not make the command unstoppable).
    stop = StopSignals()
    before = signal.getsignal(signal.SIGTERM)
    with stop.installed():
        with stop.finishing():
            signal.raise_signal(signal.SIGTERM)  # held
            assert stop.requested and stop.by == "SIGTERM"
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(signal.SIGINT)  # told "signal once more": this is it
                time.sleep(5.0)  # (the interrupt lands before this)
    assert signal.getsignal(signal.SIGTERM) is before
    assert stop.exit_code() == 128 + signal.SIGTERM  # the first one's, as a shell reports it
    assert capfd.readouterr().err.count("signal once more to quit at once") == 1


def test_a_stop_under_way_lets_its_close_finish_once_and_a_third_quits(capfd):
    # The first signal stops the command; a second (GNU timeout sends two) finds it closing its
    # outputs and waits; a third quits at once.
    stop = StopSignals()
    with stop.installed():
        with pytest.raises(KeyboardInterrupt):
            signal.raise_signal(signal.SIGINT)  # nothing to finish: stops at once
        with stop.finishing():
            signal.raise_signal(signal.SIGINT)  # the close goes on
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
