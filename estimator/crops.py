"""Random square sub-image crops and their view angles (paper Sec. 3.2-3.3). Pure numpy + OpenCV.

A crop spans a fixed horizontal angle (the contract's ``crop_fov_deg``), not a fixed number of
pixels, so a model trained on one camera sees the same angular detail on another. Its centre is
uniform over the positions that keep the crop inside the image, and its position enters the
network only as two view angles computed from the intrinsics (never from a hard-coded FOV).
"""

from __future__ import annotations

import math

import cv2
import numpy as np

from rig.errors import ValidationError
from rig.geometry import view_angles_rad
from rig.types import Intrinsics

# The most a crop is enlarged from the frame to the model's crop size. The backbone's stem (a
# stride-2 convolution, then a stride-2 max-pool) reduces a crop 4x before its first stage, so up
# to 4x that stage still sees about one position per recorded pixel; beyond, it sees interpolation
# only, not the scene (train refuses such frames; the rig and eval say so: ``enlarged_too_far``).
MAX_CROP_ENLARGEMENT = 4


def enlarged_too_far(intrinsics: Intrinsics, crop_fovs_rad: list[float], crop_size_px: int) -> str | None:
    """What to say of a camera whose smallest crop (of the angles ``crop_fovs_rad``) is enlarged
    more than ``MAX_CROP_ENLARGEMENT`` times to ``crop_size_px``: its estimates are not the model's
    reading of a scene. None when every crop is big enough."""
    side = min(crop_side_px(intrinsics, fov) for fov in crop_fovs_rad)
    need = math.ceil(crop_size_px / MAX_CROP_ENLARGEMENT)
    if side >= need:
        return None
    scale = need / side
    least = f"{math.ceil(intrinsics.width * scale)}x{math.ceil(intrinsics.height * scale)}"
    return (f"frames of {intrinsics.width}x{intrinsics.height} px give crops of {side} px, enlarged "
            f"{crop_size_px / side:.1f}x to the model's {crop_size_px} px crops: the network sees interpolation, not "
            f"the scene, and estimates from them are unreliable; use the camera at {least} px or more")


def crop_side_px(intrinsics: Intrinsics, crop_fov_rad: float) -> int:
    """Side in source pixels of a square crop spanning ``crop_fov_rad`` around the optical axis.

    Clipped to the image's shorter side: a narrow-angle camera gets a crop that fills its height.
    """
    side = 2.0 * intrinsics.fx * math.tan(crop_fov_rad / 2.0)
    return int(max(1, min(round(side), intrinsics.width, intrinsics.height)))


def crops_per_scale(n: int, n_scales: int) -> list[int]:
    """How many of a frame's ``n`` crops each of ``n_scales`` crop angles gets, in the contract's
    order: as even as they go, the earlier angles taking the odd ones (7 crops, 2 angles: 4 and 3).
    A frame's crops come grouped by angle in that order, so its first crop has the first angle."""
    return [len(range(k, n, n_scales)) for k in range(n_scales)]


def _check_boxes(intrinsics: Intrinsics, n: int, side_px: int) -> None:
    if n <= 0:
        raise ValidationError(f"crops per frame: expected a positive integer, got {n}")
    if not 0 < side_px <= min(intrinsics.width, intrinsics.height):
        raise ValidationError(
            f"crop side: expected within (0, {min(intrinsics.width, intrinsics.height)}] px, got {side_px}"
        )


def _boxes(x0: np.ndarray, y0: np.ndarray, side_px: int) -> np.ndarray:
    side = np.full(len(x0), side_px)
    return np.stack([x0, y0, side, side], axis=1).astype(np.int64)


def sample_crop_boxes(intrinsics: Intrinsics, n: int, side_px: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` square boxes (x0, y0, side, side) with top-left corners uniform over valid positions."""
    _check_boxes(intrinsics, n, side_px)
    x0 = rng.integers(0, intrinsics.width - side_px + 1, size=n)
    y0 = rng.integers(0, intrinsics.height - side_px + 1, size=n)
    return _boxes(x0, y0, side_px)


def spread_crop_boxes(intrinsics: Intrinsics, n: int, side_px: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` square boxes spread across the image: the valid range of left edges is cut into ``n``
    equal strata and each box's left edge is uniform within its own (jittered stratified
    sampling); top edges are uniform as in :func:`sample_crop_boxes`.

    At run time a frame's few crops are all the network sees of it. Independent uniform draws
    often land two of four crops on nearly the same patch and leave most of the frame unseen;
    spreading them keeps every crop a different observation, as the paper intends, while each
    crop's position stays random. On held-out synthetic drives it lowered the mean error of the
    same weights (docs/model.md).
    Training keeps independent uniform crops: there they are augmentation, not observations.
    """
    _check_boxes(intrinsics, n, side_px)
    x0 = stratified_positions(intrinsics.width - side_px + 1, n, rng)
    y0 = rng.integers(0, intrinsics.height - side_px + 1, size=n)
    return _boxes(rng.permutation(x0), y0, side_px)


def stratified_positions(span: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` integer positions in [0, span): the range cut into ``n`` equal strata, one position
    uniform within each, in stratum order (callers permute them)."""
    edges = np.linspace(0.0, span, n + 1)
    return np.minimum(np.floor(edges[:-1] + rng.random(n) * np.diff(edges)).astype(np.int64), span - 1)


def crop_angles_rad(boxes_px: np.ndarray, intrinsics: Intrinsics) -> np.ndarray:
    """(horizontal, vertical) view angles of each box's centre, shape (n, 2), radians."""
    boxes = np.asarray(boxes_px, dtype=np.float64)
    u = boxes[:, 0] + boxes[:, 2] / 2.0
    v = boxes[:, 1] + boxes[:, 3] / 2.0
    h, vert = view_angles_rad(u, v, intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy)
    return np.stack([h, vert], axis=1)


def cut_crops(image_bgr: np.ndarray, boxes_px: np.ndarray, size_px: int) -> np.ndarray:
    """The boxes cut out of the image and resized to ``size_px``; shape (n, S, S, 3) uint8 BGR.

    INTER_AREA when shrinking keeps fine shading and shadow edges without aliasing.
    """
    out = np.empty((len(boxes_px), size_px, size_px, 3), dtype=np.uint8)
    for i, (x0, y0, w, h) in enumerate(np.asarray(boxes_px, dtype=np.int64)):
        patch = image_bgr[y0 : y0 + h, x0 : x0 + w]
        if patch.shape[:2] == (size_px, size_px):
            out[i] = patch
        else:
            interp = cv2.INTER_AREA if w > size_px else cv2.INTER_LINEAR
            out[i] = cv2.resize(patch, (size_px, size_px), interpolation=interp)
    return out


def frame_rng(seed: int, seq: int) -> np.random.Generator:
    """The crop generator for one frame: reproducible from (seed, seq) alone, so a replay of the
    same log gives the same crops whatever order or subset of frames is processed."""
    return np.random.default_rng([int(seed), int(seq)])
