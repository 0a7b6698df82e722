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
standard deviation of at least 18 (``benchmarks/bench_spread.py``).

The gate does not catch dusk or night that auto exposure has brightened into noise: such a frame
keeps the scene's mean and contrast, and the model mostly reads through the noise. On 16 fresh
drives (``benchmarks/bench_exposure.py``: the light 4, 6 and 8 stops down, made up by the camera's
gain, with the photon noise of that gain; a real sensor's read noise adds to it) the mean error is
6.1, 6.7 and 10.5 deg against 6.1 as rendered, and 0, 0 and 12 of 384 windows are valid and over 30
deg, the 12 all of one drive read 36 deg off. A cheap noise measure (the benchmark's ``fine_share``:
the mean square luma difference of horizontally neighbouring pixels over twice the frame's luma
variance) is at most 0.019 on any held-out, validation or fresh frame and at least 0.043 on that
drive's, but two drives noisier by it still read 9-12 deg off, and a threshold between the two
(0.03-0.04) also leaves out 63-160 of the other drives' 360 frames 8 stops down, which the model
reads 4-14 deg off; so the gate has no such measure.

A lens partly covered (a cap slid half over, a sun visor or a hand close to it) keeps a mean and
a standard deviation like any frame's, as auto exposure brightens what the cover leaves, yet the
model reads such frames far off and calls them valid (``benchmarks/bench_exposure.py``: half the
frame capped, 23-45 deg mean error against 6, 44-164 of 384 windows valid and over 30 deg). So the
gate also judges the frame in :data:`COVER_GRID` blocks: one flatter than :data:`COVER_BLOCK_MAX_STD`
and darker than :data:`COVER_DARKER_THAN` of the frame's mean is covered (an out-of-focus cover is
flat, and darker than the scene the camera exposes for), and a frame more than ``max_covered_share``
of which is covered is left out. A hand over 30 % of the frame, which the model reads nearly as
well as the whole frame (7 against 6 deg), passes. A frame with the sun in it that the camera
metered dark for it (mean luma 10, the disk saturated) stays "dark": the model reads such frames
22 deg off on average, against 5 as auto-exposed, so they are no loss.
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
# The cover measure: the frame in 12 x 6 blocks (columns, rows), 104 x 63 px of a KITTI frame and
# about 114 sampled pixels each. A block is covered when its luma's standard deviation is below 3
# (an out-of-focus cover is flat, as the gate's min_std) and its mean below 0.6 of the frame's
# (darker than what the camera exposes for; a flat sky is brighter). On the synthetic drives
# (``benchmarks/bench_exposure.py``) no frame of 16 800 held-out, validation and fresh ones has more
# than 19 % of itself covered; a lens half capped has 39-50 %, a visor over 60 % of it 29-39 %.
# A frame too small for 8 px blocks has fewer: a block one pixel wide judged a frame 6 px wide
# column by column, and saw the dark one of stripes 4 px wide as flat.
COVER_GRID = (12, 6)
COVER_MIN_BLOCK_PX = 8
COVER_BLOCK_MAX_STD = 3.0
COVER_DARKER_THAN = 0.6


@functools.lru_cache(maxsize=8)
def _sample_rows_cols(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The (row, column) of :data:`SAMPLE_PIXELS` pixels drawn once, without replacement, from a
    fixed seed for each frame size. Drawn at random rather than on a regular grid: a grid of
    stride 8 judged a frame 6 px wide on one column, and saw stripes repeating every 8 px (a
    grille, a fence close to the lens) as flat, because it hit the same phase of them every time.
    A fixed seed keeps a frame's verdict the same on every run."""
    rows, cols = np.divmod(_sample_flat(height, width), width)
    return rows, cols


@functools.lru_cache(maxsize=8)
def _sample_flat(height: int, width: int) -> np.ndarray:
    """The pixels of :func:`_sample_rows_cols` as indices into the frame's rows laid end to end."""
    n = height * width
    flat = np.arange(n) if n <= SAMPLE_PIXELS else np.random.default_rng(0).choice(n, SAMPLE_PIXELS, replace=False)
    return np.sort(flat)


@functools.lru_cache(maxsize=8)
def _sample_blocks(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """The :data:`COVER_GRID` block (row-major index) of each pixel :func:`_sample_rows_cols`
    draws, and how many of them each block holds (about 114 of a KITTI frame's 8192). Blocks are
    at least :data:`COVER_MIN_BLOCK_PX` each way, or one block the frame's whole width or height."""
    rows, cols = _sample_rows_cols(height, width)
    grid_cols = max(1, min(COVER_GRID[0], width // COVER_MIN_BLOCK_PX))
    grid_rows = max(1, min(COVER_GRID[1], height // COVER_MIN_BLOCK_PX))
    block = (rows * grid_rows // height) * grid_cols + cols * grid_cols // width
    return block, np.bincount(block, minlength=grid_cols * grid_rows)


def _luma_sample(image_bgr: np.ndarray) -> np.ndarray:
    """The luma (0-255, float64) of the image's sampled pixels, in :func:`_sample_rows_cols` order."""
    height, width = image_bgr.shape[:2]
    if image_bgr.flags.c_contiguous:
        # Gathered by flat index from the (pixels, 3) view: 13 us of a KITTI frame, where indexing
        # by (row, column) took 71, most of what the gate cost before it judged blocks.
        pixels = image_bgr.reshape(-1, 3).take(_sample_flat(height, width), axis=0)
    else:  # a view (a crop, a broadcast frame): reshaping it would copy the whole frame
        pixels = image_bgr[_sample_rows_cols(height, width)]
    # Luma in float32 (a grey's luma is its level exactly), its moments in float64: summed in
    # float32 over 8192 pixels, a flat frame's standard deviation came out 1.5e-5, not 0.
    return (pixels.astype(np.float32) @ _LUMA_BGR).astype(np.float64)


def luminance_stats(image_bgr: np.ndarray) -> tuple[float, float]:
    """Mean and standard deviation of an 8-bit BGR image's luma (0-255), on a fixed random sample
    of its pixels (all of them in a frame of at most :data:`SAMPLE_PIXELS`)."""
    luma = _luma_sample(image_bgr)
    return float(luma.mean()), float(luma.std())


def _covered_share(luma: np.ndarray, height: int, width: int) -> float:
    """The share of the frame (of its sampled pixels) in covered blocks, ``luma`` its sample."""
    block, counts = _sample_blocks(height, width)
    sums = np.bincount(block, luma, minlength=counts.size)
    squares = np.bincount(block, luma * luma, minlength=counts.size)
    n = np.maximum(counts, 1)  # a block no sampled pixel fell in (a frame of few pixels) is no cover
    mean = sums / n
    covered = ((squares / n - mean * mean < COVER_BLOCK_MAX_STD ** 2) & (mean < COVER_DARKER_THAN * luma.mean())
               & (counts > 0))
    return float(counts[covered].sum()) / luma.size


def covered_share(image_bgr: np.ndarray) -> float:
    """The share (0-1) of an 8-bit BGR image in blocks flat and dark enough to be a cover in
    front of the lens (see the module's docstring), on the gate's sample of its pixels."""
    return _covered_share(_luma_sample(image_bgr), *image_bgr.shape[:2])


@dataclass(frozen=True)
class ExposureGate:
    """Frames darker than ``min_mean``, brighter than ``max_mean`` or flatter than ``min_std``
    (8-bit luma), or more than ``max_covered_share`` of which is covered (:func:`covered_share`;
    1 lets every frame through), cannot show the sun and are left out of windows."""

    min_mean: float = 16.0
    max_mean: float = 240.0
    min_std: float = 3.0
    max_covered_share: float = 0.25

    def __post_init__(self) -> None:
        if (not 0.0 <= self.min_mean < self.max_mean <= 255.0 or self.min_std < 0.0
                or not 0.0 <= self.max_covered_share <= 1.0):
            raise ValidationError(
                "ExposureGate: expected 0 <= min_mean < max_mean <= 255 and min_std >= 0 (8-bit luma), "
                "and 0 <= max_covered_share <= 1 (a share of the frame), "
                f"got min_mean {self.min_mean}, max_mean {self.max_mean}, min_std {self.min_std}, "
                f"max_covered_share {self.max_covered_share}"
            )

    def rejects(self, image_bgr: np.ndarray) -> str | None:
        """Why the frame cannot show the sun ("dark", "bright", "flat", "covered"), or None if it can."""
        luma = _luma_sample(image_bgr)
        mean, std = float(luma.mean()), float(luma.std())
        if mean < self.min_mean:
            return "dark"
        if mean > self.max_mean:
            return "bright"
        if std < self.min_std:
            return "flat"
        if self.max_covered_share < 1.0 and _covered_share(luma, *image_bgr.shape[:2]) > self.max_covered_share:
            return "covered"
        return None


DEFAULT_EXPOSURE_GATE = ExposureGate()
