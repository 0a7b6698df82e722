"""The static checks, run as CI runs them: ruff and mypy from the repository root, each with its
settings from pyproject.toml (mypy: the shipped packages, not tests or benchmarks)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent  # the repository root: pyproject.toml is there


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    # The interpreter running the tests, so the tool sees the same installed packages and stubs.
    return subprocess.run([sys.executable, "-m", *args], cwd=ROOT, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_ruff_finds_nothing():
    pytest.importorskip("ruff")
    res = _run("ruff", "check", ".")
    assert res.returncode == 0, f"ruff check . failed:\n{res.stdout}{res.stderr}"


@pytest.mark.slow
def test_mypy_finds_nothing():
    pytest.importorskip("mypy")
    res = _run("mypy")
    assert res.returncode == 0, f"mypy failed:\n{res.stdout}{res.stderr}"
