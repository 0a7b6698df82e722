"""Whether a frame's exposure can show the sun at all: the gate in front of the backbone.

The model reads the sun from shading, shadows and the sky. A black frame (night, a lens cap), a
white one (a blinded or saturated sensor) or a flat one (a covered or fogged lens) shows none of
them, yet a trained model still answers with a direction, and its tokens agree on it. Measured on
the shipped model (``benchmarks/bench_spread.py``): a window of eight black frames gets 0.5 deg of
token spread and an elevation of 50 deg, so the status rule (``rig/protocol.py``) would call it
valid. Such frames are therefore counted and left out of windows, as frames without heading are,
before the backbone runs on them.

The thresholds sit far outside what a usable frame looks like: the 7200 frames of the 300 synthetic
validation drives (auto-exposed, as most vehicle cameras are) have a mean luma of 73-150 and a
standard deviation of at least 18 (``benchmarks/bench_spread.py``). The gate does not catch a night
scene that auto exposure has brightened into noise: that frame has contrast, only not of the sun.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from rig.errors import ValidationError

# ITU-R BT.601 luma weights, in the frame's BGR channel order.
_LUMA_BGR = np.array([0.114, 0.587, 0.299], dtype=np.float32)
# Pixels the gate looks at: about a KITTI frame's share of every 8th pixel of every 8th row, and
# tens of microseconds. A frame of fewer pixels is looked at whole.
SAMPLE_PIXELS = 8192


@functools.lru_cache(maxsize=8)
def _sample_rows_cols(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The (row, column) of :data:`SAMPLE_PIXELS` pixels drawn once, without replacement, from a
    fixed seed for each frame size. Drawn at random rather than on a regular grid: a grid of
    stride 8 judged a frame 6 px wide on one column, and saw stripes repeating every 8 px (a
    grille, a fence close to the lens) as flat, because it hit the same phase of them every time.
    A fixed seed keeps a frame's verdict the same on every run."""
    n = height * width
    flat = np.arange(n) if n <= SAMPLE_PIXELS else np.random.default_rng(0).choice(n, SAMPLE_PIXELS, replace=False)
    rows, cols = np.divmod(np.sort(flat), width)
    return rows, cols


def luminance_stats(image_bgr: np.ndarray) -> tuple[float, float]:
    """Mean and standard deviation of an 8-bit BGR image's luma (0-255), on a fixed random sample
    of its pixels (all of them in a frame of at most :data:`SAMPLE_PIXELS`)."""
    rows, cols = _sample_rows_cols(*image_bgr.shape[:2])
    # Luma in float32 (a grey's luma is its level exactly), its moments in float64: summed in
    # float32 over 8192 pixels, a flat frame's standard deviation came out 1.5e-5, not 0.
    luma = (image_bgr[rows, cols].astype(np.float32) @ _LUMA_BGR).astype(np.float64)
    return float(luma.mean()), float(luma.std())


@dataclass(frozen=True)
class ExposureGate:
    """Frames darker than ``min_mean``, brighter than ``max_mean`` or flatter than ``min_std``
    (8-bit luma) cannot show the sun and are left out of windows."""

    min_mean: float = 16.0
    max_mean: float = 240.0
    min_std: float = 3.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.min_mean < self.max_mean <= 255.0 or self.min_std < 0.0:
            raise ValidationError(
                "ExposureGate: expected 0 <= min_mean < max_mean <= 255 and min_std >= 0 (8-bit luma), "
                f"got min_mean {self.min_mean}, max_mean {self.max_mean}, min_std {self.min_std}"
            )

    def rejects(self, image_bgr: np.ndarray) -> str | None:
        """Why the frame cannot show the sun ("dark", "bright", "flat"), or None if it can."""
        mean, std = luminance_stats(image_bgr)
        if mean < self.min_mean:
            return "dark"
        if mean > self.max_mean:
            return "bright"
        if std < self.min_std:
            return "flat"
        return None


DEFAULT_EXPOSURE_GATE = ExposureGate()
