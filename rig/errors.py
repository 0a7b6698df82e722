"""One small exception tree. Every message says what is wrong and what to do about it.

The CLI prints ``str(error)`` of any :class:`SunrigError` as one line and exits non-zero; anything
else is a bug and gets a traceback only with ``--debug``.
"""

from __future__ import annotations


class SunrigError(Exception):
    """Base of every error a user can cause or fix (bad input, wrong model, missing device)."""


class ValidationError(SunrigError, ValueError):
    """A value handed to a core type does not fit (shape, dtype, range or unit)."""


class LogError(SunrigError):
    """A log file cannot be read: not a log, corrupt, or missing the channels a replay needs."""


class ModelError(SunrigError):
    """A model folder cannot be used: missing graph, unreadable file, or no contract."""


class ContractMismatch(ModelError):
    """A model's contract does not fit what the runtime or the other graph expects."""


class MissingExtraError(SunrigError, ImportError):
    """An optional dependency is not installed; the message names the extra to install."""


def require_torch():
    """Import torch lazily, naming the extra to install when it is absent."""
    try:
        import torch
    except ImportError as exc:  # pragma: no cover - depends on the environment
        raise MissingExtraError(
            "this needs PyTorch: install the train extra with `pip install 'sunrig[train]'`"
        ) from exc
    return torch
