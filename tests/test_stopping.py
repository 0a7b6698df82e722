"""Ctrl-C, SIGTERM and SIGHUP as one stop request (rig/stopping.py)."""

import signal
import time

import pytest

from rig.stopping import StopSignals


def test_a_first_signal_while_finishing_is_held_then_read_and_a_third_quits(capfd):
    stop = StopSignals()
    before = signal.getsignal(signal.SIGTERM)
    with stop.installed():
        with stop.finishing():
            signal.raise_signal(signal.SIGTERM)  # held: what is being written is not cut
            assert stop.requested and stop.by == "SIGTERM"
            signal.raise_signal(signal.SIGINT)  # told to wait
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(signal.SIGHUP)  # quits at once
                time.sleep(5.0)  # (the interrupt lands before this)
    assert signal.getsignal(signal.SIGTERM) is before
    assert stop.exit_code() == 128 + signal.SIGTERM  # the first one's, as a shell reports it
    assert capfd.readouterr().err.count("signal once more to quit at once") == 1


def test_the_handlers_come_back_when_the_block_is_interrupted():
    stop = StopSignals()
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    with pytest.raises(KeyboardInterrupt), stop.installed():
        signal.raise_signal(signal.SIGINT)
    assert {sig: signal.getsignal(sig) for sig in before} == before
    assert stop.by == "Ctrl-C" and stop.exit_code() == 130
