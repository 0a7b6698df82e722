"""sunrig's rig: core types, conventions, and (later) the live pipeline that ties sources,
estimator and publishers together. Importing it pulls in no device SDK and no torch.

Nor numpy: the core types (rig.types) load on first use (PEP 562), so that a small module of
ours, above all the ``sunrig`` command's entry (rig/entry.py), starts before anything heavy has
loaded. A Ctrl-C during that import landed inside numpy and printed a traceback.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from rig.errors import ContractMismatch, LogError, ModelError, SunrigError, ValidationError

if TYPE_CHECKING:
    from rig.types import Attitude, Frame, FrameFeatures, FrameMeta, GnssFix, HeadingRef, Intrinsics, SunEstimate

__all__ = [
    "Attitude",
    "ContractMismatch",
    "Frame",
    "FrameFeatures",
    "FrameMeta",
    "GnssFix",
    "HeadingRef",
    "Intrinsics",
    "LogError",
    "ModelError",
    "SunEstimate",
    "SunrigError",
    "ValidationError",
]

# The names imported on first use, and the module each comes from.
_LAZY = dict.fromkeys(("Attitude", "Frame", "FrameFeatures", "FrameMeta", "GnssFix", "HeadingRef", "Intrinsics",
                                "SunEstimate"),
                      "rig.types")


if not TYPE_CHECKING:  # hidden from mypy, which would take any name as an attribute of rig
    def __getattr__(name: str) -> Any:
        module = _LAZY.get(name)
        if module is None:
            # AttributeError, not another: `from rig import cli` then imports the submodule.
            raise AttributeError(f"module 'rig' has no attribute {name!r}")
        value = getattr(importlib.import_module(module), name)
        globals()[name] = value  # once: later look-ups find it without calling here
        return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
