"""Shared fixtures and the ``--hardware`` switch.

``tiny_model_dir`` is a real model folder (two ONNX graphs with their contract) holding an
UNTRAINED tiny model: it exercises loading, shapes and plumbing in seconds, never accuracy.
"""

from __future__ import annotations

from pathlib import Path

import pytest


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
