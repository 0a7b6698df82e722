"""sunrig's rig: core types, conventions, and (later) the live pipeline that ties sources,
estimator and publishers together. Importing it pulls in no device SDK and no torch."""

from rig.errors import ContractMismatch, LogError, ModelError, SunrigError, ValidationError
from rig.types import Attitude, Frame, FrameFeatures, GnssFix, HeadingRef, Intrinsics, SunEstimate

__all__ = [
    "Attitude",
    "ContractMismatch",
    "Frame",
    "FrameFeatures",
    "GnssFix",
    "HeadingRef",
    "Intrinsics",
    "LogError",
    "ModelError",
    "SunEstimate",
    "SunrigError",
    "ValidationError",
]
