"""Shared fixtures and the ``--hardware`` switch.

``tiny_model_dir`` is a real model folder (two ONNX graphs with their contract) holding an
UNTRAINED tiny model: it exercises loading, shapes and plumbing in seconds, never accuracy.
"""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest


def pytest_configure(config: pytest.Config) -> None:
    # A shell without job control starts a background command (`pytest &`, nohup) with Ctrl-C
    # ignored, and Python keeps it ignored: every test of what a Ctrl-C does then failed (13 of
    # them, the commands under test running to the end). The suite tests the handling, not the
    # shell it was started from, so it starts from Python's own.
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        "--hardware",
        action="store_true",
        default=False,
        help="run tests marked 'hardware' (need a real OAK camera or serial GNSS attached)",
    )


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--hardware"):
        return
    skip = pytest.mark.skip(reason="needs a real device: run with `pytest --hardware`")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session")
def tiny_model_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Folder of an untrained tiny model (crop 32 px, D = 64, 4 crops x 8 frames), built once per
    session with the torch exporter. Skips when the train extra (torch, onnx) is not installed."""
    pytest.importorskip(
        "torch", reason="building the test model needs the train extra: pip install 'sunrig[train]'"
    )
    pytest.importorskip(
        "onnx", reason="building the test model needs the train extra: pip install 'sunrig[train]'"
    )
    from estimator.export import build_random_model
    from estimator.nets import TINY

    # The tiny model every test shares: the real architecture (4 ResNet stages, multi-head
    # attention, cyclic encoding), shrunk until the export takes seconds on two cores (base width
    # 8, embedding D = 64, 32 px crops, width 48, 1 layer). Contract: 4 crops x 8 frames per
    # window, like the paper. (Its encoding fills the width exactly; the zero padding the paper's
    # width needs is tested in test_encoding.py.)
    return build_random_model(tmp_path_factory.mktemp("tiny_model"), TINY, seed=0, crops_per_frame=4,
                              frames_per_window=8)


class DiskEvents(list):
    """The fsyncs (("fsync", path the descriptor names)) and renames (("replace", src, dst)) a
    process made, in order, real paths."""

    def synced_in_order(self, path: str | os.PathLike[str]) -> bool:
        """Whether ``path`` was written as a power loss cannot tear: renamed into place once, its
        data synced before the rename, and its folder (the rename) after."""
        path = os.path.realpath(path)
        renames = [i for i, e in enumerate(self) if e[0] == "replace" and e[2] == path]
        if len(renames) != 1:
            return False
        i = renames[0]
        return ("fsync", self[i][1]) in self[:i] and ("fsync", os.path.dirname(path)) in self[i + 1:]


@pytest.fixture
def disk_events(monkeypatch: pytest.MonkeyPatch) -> DiskEvents:
    """Records this process's fsyncs and renames (:class:`DiskEvents`) while the test runs."""
    if not os.path.isdir("/proc/self/fd"):
        pytest.skip("names an fsync's file by /proc/self/fd (Linux)")
    events = DiskEvents()
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        events.append(("fsync", os.path.realpath(f"/proc/self/fd/{fd}")))
        real_fsync(fd)

    def replace(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
        events.append(("replace", os.path.realpath(src), os.path.realpath(dst)))
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    return events
