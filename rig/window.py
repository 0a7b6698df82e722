"""Which frames form a window. Pure logic: takes the candidates, returns the chosen ones.

Consecutive frames at 10-30 Hz are nearly identical, so "the last 8" would show the network one
view eight times. The policy instead picks frames that differ: the newest frame always, then,
greedily, the candidate farthest from every frame chosen so far (farthest-point sampling), where
two frames' distance combines their time apart (in units of the span) and their headings apart
(in units of ``yaw_scale_rad``). On a straight road that spreads the window over the span; in a
turn it takes more of the frames that look in new directions, which is where the paper's
spatio-temporal aggregation gains most.

Candidates are the frames with a heading from the last ``span_s`` seconds. While fewer than
``n_frames`` are there (the ring is filling, or the source is slow), the window is all of them:
an estimate from fewer frames now (reported in ``n_frames``) beats none.

A window's frames share one heading zero: the newest frame's reference and epoch, and no heading
jump between them. A heading that changes between two frames by more than ``MIN_JUMP_RAD`` faster
than ``max_yaw_rate_rad_s`` is not a turn the camera made (a compass glitch, a source whose zero
moved unsaid), and the picture did not turn with it. The farthest-point rule would take such a
frame first, as the most different view, into every window for a whole span. So a frame that jumps
away from both its neighbours while they agree (one glitched heading) is left out, and otherwise
the window starts again from the jump, as after a new epoch: until the next frame says which it
was, a newest frame that jumped is a window of its own.

A vehicle that stands still (a red light, a jam) shows one view frame after frame: its span would
soon hold that view only, 8 times, and the estimate fall to what one view gives, with a small
spread that looks sure. So a frame showing the same view as the frame that began it (its image
shrunk to a signature, ``SAME_VIEW_MAX_RMS`` apart once an idling engine's shake of the camera and
a change of its gain are taken out, and its heading) is a repeat of that view
(:class:`ViewClock`): a window takes one frame a view, the newest, and the time stood still does
not count towards the span (``FrameFeatures.t_view_s``), so that the views before the stop stay in
the windows for as long as the vehicle stands, up to ``rig.ring.MAX_HOLD_S``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np

from rig.errors import ValidationError
from rig.geometry import wrap_pi
from rig.types import FrameFeatures

T = TypeVar("T", bound=FrameFeatures)

# Faster than a vehicle turns its camera: a car rarely turns 40 deg/s. The synthetic drives turn at
# most 17.4 deg a frame (173.5 deg/s at their 10 frames a second, over the 100 held-out drives), under
# MIN_JUMP_RAD a frame at any frame rate, so no synthetic frame is ever taken for a jump.
DEFAULT_MAX_YAW_RATE_RAD_S = math.radians(180.0)
# A smaller change is never a jump, however close the frames' stamps: a compass's noise (a few
# degrees) between frames stamped together (a burst, a frozen clock) is an impossible rate too.
MIN_JUMP_RAD = math.radians(45.0)


# A frame's view signature: its image in gray, shrunk by area to this size (width, height: about a
# KITTI frame's 3.3:1), to zero mean and unit spread (an exposure change is no new view). Each
# number averages about 1200 pixels of a KITTI frame, so sensor noise all but leaves it.
SIGNATURE_SIZE = (32, 12)
# The difference of two signatures (view_rms: RMS, a shake and a gain taken out) up to which they
# show the same view. Standing (benchmarks/bench_standstill.py, 8 drives of seed 3000 each), a pose
# captured again with fresh noise differs by at most 0.008 (0.017 with 8-bit cells), with an idle
# shake of 2 px each way by 0.029 (0.118 compared where they stood: each frame a view of its own),
# at dusk's noise (--dusk) by 0.036, a 30 % gain swing or JPEG at quality 30 by 0.021. Driving,
# the held-out drives' nearest two frames 0.1 s apart differ by 0.059 (0.079 before: the camera
# swayed 4x3 px between them, in a slow corner), the next by 0.074, the validation and fresh drives'
# (300 each) by 0.109. A frame wrongly taken for a new view only makes the windows as they were
# before views were told apart.
SAME_VIEW_MAX_RMS = 0.05
# How far the camera may move along each axis, in signature cells (a KITTI frame's cell is 39x31 px),
# between two frames of one view: an engine idling shakes it by 0.5-2 px each way, so two frames
# are up to 4 px apart; 0.125 cells is 4.9x3.9 px. A larger move counts, less this much.
SAME_VIEW_MAX_SHAKE_CELLS = 0.125
# A heading this far from the view's first frame's is a new view, whatever the image (a turn on the
# spot, which a blank scene would not show).
SAME_VIEW_MAX_TURN_RAD = math.radians(2.0)
# How long a view must have lasted before the time it goes on being shown is time stood still.
# Driving, even slowly or with a fast camera, the view has changed past SAME_VIEW_MAX_RMS well before
# (the held-out drives' nearest frames 0.1 s apart differ by 0.059), so the frames of a fast
# camera that show one view for a moment keep their own times.
MIN_STAND_S = 0.5


def view_signature(image_bgr: np.ndarray) -> np.ndarray | None:
    """The image shrunk to ``SIGNATURE_SIZE``, gray, zero mean, unit spread, with how each of its
    numbers changes as the image moves right and down by one of its cells: float32, (3, height,
    width). None for an image without contrast to compare (a black or flat frame), which is then a
    view of its own."""
    import cv2

    gray = cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY) if image_bgr.ndim == 3 else image_bgr
    # Halved twice first (a Gaussian pyramid, each level a 5x5 blur): area averaging straight from a
    # KITTI frame to 32x12 took 0.84 ms a frame on the rig's per-frame path, this 0.11 ms.
    while min(gray.shape[:2]) >= 4 * max(SIGNATURE_SIZE):
        gray = cv2.pyrDown(gray)
    # The image's slope, averaged over each cell below, is how the cell changes as the image moves
    # (to first order). Shrunk together in floats, as one image of three channels (one resize costs
    # little more than one channel's); 8-bit cells were rounded to a level, 0.013 RMS of a still
    # camera's 0.014.
    planes = cv2.merge([gray.astype(np.float32), cv2.Sobel(gray, cv2.CV_32F, 1, 0, ksize=3),
                        cv2.Sobel(gray, cv2.CV_32F, 0, 1, ksize=3)])
    small = cv2.resize(planes, SIGNATURE_SIZE, interpolation=cv2.INTER_AREA).transpose(2, 0, 1)
    small[0] -= small[0].mean()
    spread = float(small[0].std())
    if spread <= 1e-3:
        return None
    small[0] /= spread
    # Sobel's 3x3 is 8 times the slope per pixel; in spreads per cell moved.
    small[1] *= np.float32(gray.shape[1] / SIGNATURE_SIZE[0] / (8.0 * spread))
    small[2] *= np.float32(gray.shape[0] / SIGNATURE_SIZE[1] / (8.0 * spread))
    return np.ascontiguousarray(small)


def same_view(first: FrameFeatures, other: FrameFeatures) -> bool:
    """Whether ``other`` shows the view ``first`` showed: the same camera, heading zero and (within
    ``SAME_VIEW_MAX_TURN_RAD``) heading, and signatures within ``SAME_VIEW_MAX_RMS``."""
    a, b = first.view_signature, other.view_signature
    att_a, att_b = first.frame.attitude, other.frame.attitude
    if a is None or b is None or att_a is None or att_b is None or a.shape != b.shape:
        return False
    if (att_a.reference, att_a.epoch) != (att_b.reference, att_b.epoch):
        return False
    if first.frame.intrinsics != other.frame.intrinsics:
        return False
    if abs(math.remainder(att_b.heading_rad - att_a.heading_rad, math.tau)) > SAME_VIEW_MAX_TURN_RAD:
        return False
    return view_rms(a, b) <= SAME_VIEW_MAX_RMS


def view_rms(first: np.ndarray, other: np.ndarray) -> float:
    """How far apart two view signatures of one camera are (:func:`view_signature`): the RMS of
    their difference, less what a move of the camera by up to ``SAME_VIEW_MAX_SHAKE_CELLS`` along
    each axis and a bend of its tone curve explain (a least-squares fit of the two slopes, the
    first signature and its square, the move then held to the bound)."""
    a = first[0].ravel()
    diff = (other[0] - first[0]).ravel()
    # Both frames' slopes: the move's change to first order, whichever frame is off the mount.
    slopes = ((first[1:] + other[1:]) / 2).reshape(2, -1)
    tone = np.stack([a, a * a - np.mean(a * a)])
    terms = np.concatenate([slopes, tone])
    fit = _least_squares(terms, diff)
    if np.any(np.abs(fit[:2]) > SAME_VIEW_MAX_SHAKE_CELLS):
        # Moved further than a shake: that much is taken out, the rest counts.
        fit[:2] = np.clip(fit[:2], -SAME_VIEW_MAX_SHAKE_CELLS, SAME_VIEW_MAX_SHAKE_CELLS)
        fit[2:] = _least_squares(tone, diff - fit[:2] @ slopes)
    return float(np.sqrt(np.mean(np.square(diff - fit @ terms))))


def _least_squares(terms: np.ndarray, target: np.ndarray) -> np.ndarray:
    """The weights of ``terms`` (one a row) that best make ``target``: by the normal equations,
    a quarter of lstsq's time; lstsq where they are singular (terms that say the same)."""
    try:
        return np.linalg.solve(terms @ terms.T, terms @ target)
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(terms.T, target, rcond=None)[0]


class ViewClock:
    """Stamps the frames of one stream, in order, with their view and view time: a frame that shows
    the view of the frame that began it (:func:`same_view`) is a repeat of it (``view_seq`` that
    frame's seq), and from ``MIN_STAND_S`` after that frame on, the time since the frame before it
    is time stood still; ``t_view_s`` is the frame's time less all the time stood still so far.
    Until the vehicle first stands, that is the frame's own time, to the bit."""

    def __init__(self) -> None:
        self._first: FrameFeatures | None = None  # the first frame of the view now shown
        self._last_t_s: float | None = None
        self._last_view_s = 0.0  # the view time last stamped
        self.stood_s = 0.0

    def stamp(self, feats: FrameFeatures) -> FrameFeatures:
        t_s = feats.frame.t_mono_s
        last_t_s, self._last_t_s = self._last_t_s, t_s
        first = self._first
        if first is not None and last_t_s is not None and same_view(first, feats):
            if t_s - first.frame.t_mono_s >= MIN_STAND_S:
                self.stood_s += max(t_s - last_t_s, 0.0)  # a clock that stepped back stood no time
                # The view time stands still: the frame before's, exactly (not t_s - stood_s, rounded).
                return dataclasses.replace(feats, t_view_s=self._last_view_s, view_seq=first.frame.seq)
            # Too soon to tell standing from a moment of a fast camera: time goes on, the view is one.
            return self._stamp(feats, first.frame.seq)
        self._first = self._stamp(feats, feats.frame.seq)
        return self._first

    def _stamp(self, feats: FrameFeatures, view_seq: int) -> FrameFeatures:
        """``feats`` stamped with its own time, less the time stood still so far."""
        self._last_view_s = feats.frame.t_mono_s - self.stood_s
        return dataclasses.replace(feats, t_view_s=self._last_view_s, view_seq=view_seq)


def one_per_view(frames: Sequence[T]) -> list[T]:
    """The newest frame of each view among ``frames`` (in order; a view's repeats follow each other)."""
    return [f for i, f in enumerate(frames) if i + 1 == len(frames) or frames[i + 1].view_key != f.view_key]


@dataclass(frozen=True)
class SpreadWindowPolicy:
    """Up to ``n_frames`` frames from the last ``span_s`` seconds, diverse in time and yaw."""

    n_frames: int = 8
    span_s: float = 4.0
    yaw_scale_rad: float = math.radians(45.0)
    max_yaw_rate_rad_s: float = DEFAULT_MAX_YAW_RATE_RAD_S

    def __post_init__(self) -> None:
        if self.n_frames < 1:
            raise ValidationError(f"window n_frames: expected >= 1, got {self.n_frames}")
        if not self.span_s > 0:
            raise ValidationError(f"window span_s: expected > 0 s, got {self.span_s}")
        if not self.yaw_scale_rad > 0:
            raise ValidationError(f"window yaw_scale_rad: expected > 0, got {self.yaw_scale_rad}")
        if not self.max_yaw_rate_rad_s > 0:
            raise ValidationError(f"window max_yaw_rate_rad_s: expected > 0 rad/s, got {self.max_yaw_rate_rad_s}")

    def select(self, candidates: Sequence[T]) -> list[T]:
        """Chosen frames, oldest first. ``candidates`` must be ordered by time, oldest first.

        Only frames whose heading shares the newest heading's zero are candidates
        (:meth:`same_zero`): the same reference and, for relative headings, the same epoch (after
        a source lost its zero, the window starts again from the frames after it), and no heading
        jump between them; and one frame a view, the newest (:func:`one_per_view`), the span
        measured in view time (``FrameFeatures.window_t_s``: time stood still left out)."""
        return self.select_same_zero(self.same_zero(candidates))

    def select_same_zero(self, same_zero: Sequence[T]) -> list[T]:
        """:meth:`select` of candidates already narrowed by :meth:`same_zero` (the live rig also
        needs them, to say why a window is partial)."""
        usable = one_per_view(same_zero)
        t_s = np.array([c.window_t_s for c in usable])
        # Every one has an attitude (same_zero); the test only tells the type checker so.
        heading_rad = np.array([c.frame.attitude.heading_rad for c in usable if c.frame.attitude is not None])
        return [usable[i] for i in self.select_indices(t_s, heading_rad)] if usable else []

    def same_zero(self, candidates: Sequence[T]) -> list[T]:
        """The candidates (in order) whose heading shares the newest heading's zero: the same
        reference and epoch, after the last heading jump (:meth:`_jumps`), less any frame whose
        heading alone jumped away and back. The frames a window can be made of."""
        with_attitude = [(c, c.frame.attitude) for c in candidates if c.frame.attitude is not None]
        if not with_attitude:
            return []
        newest = with_attitude[-1][1]
        usable = [c for c, a in with_attitude if (a.reference, a.epoch) == (newest.reference, newest.epoch)]
        t_s = np.array([c.frame.t_mono_s for c in usable])
        heading_rad = np.array([a.heading_rad for c in usable if (a := c.frame.attitude) is not None])
        # A heading off both its neighbours, which agree with each other: a glitch of that frame alone.
        into = self._jumps(t_s[:-1], heading_rad[:-1], t_s[1:], heading_rad[1:])  # into frame i + 1 from i
        glitch = np.zeros(len(usable), bool)
        glitch[1:-1] = into[:-1] & into[1:] & ~self._jumps(t_s[:-2], heading_rad[:-2], t_s[2:], heading_rad[2:])
        kept = np.flatnonzero(~glitch)
        # Any other jump is where the heading's zero moved: the window starts again from the last one.
        t_s, heading_rad = t_s[kept], heading_rad[kept]
        into = np.flatnonzero(self._jumps(t_s[:-1], heading_rad[:-1], t_s[1:], heading_rad[1:]))
        start = int(into[-1]) + 1 if len(into) else 0
        return [usable[i] for i in kept[start:]]

    def _jumps(self, t_from_s: np.ndarray, heading_from_rad: np.ndarray, t_to_s: np.ndarray,
               heading_to_rad: np.ndarray) -> np.ndarray:
        """Whether the heading changed between each pair of frames by more than ``MIN_JUMP_RAD``,
        faster than ``max_yaw_rate_rad_s``: more than a vehicle turns its camera."""
        turn_rad = np.abs(wrap_pi(heading_to_rad - heading_from_rad))
        dt_s = np.abs(t_to_s - t_from_s)
        return (turn_rad > MIN_JUMP_RAD) & (turn_rad > self.max_yaw_rate_rad_s * dt_s)

    def pool_start(self, t_s: np.ndarray, newest: int | np.ndarray = -1) -> np.ndarray:
        """Of frames at times ``t_s`` (ascending): the index of the oldest within the span of the
        frame ``newest`` (an index, or an array of them), where a window ending there may start."""
        return np.searchsorted(t_s, t_s[newest] - self.span_s, side="left")

    def select_indices(self, t_s: np.ndarray, heading_rad: np.ndarray) -> list[int]:
        """The window of frames at times ``t_s`` (ascending, the last the newest) with headings
        ``heading_rad`` in one reference: their indices, ascending. The rule of :meth:`select`, on
        arrays, for training to draw its windows as the rig does (``estimator/train.py``)."""
        first = int(self.pool_start(t_s))
        n_pool = len(t_s) - first
        if n_pool <= self.n_frames:
            return list(range(first, len(t_s)))
        t = t_s[first:] / self.span_s
        yaw = heading_rad[first:]
        dist = np.hypot(t[:, None] - t[None, :], wrap_pi(yaw[:, None] - yaw[None, :]) / self.yaw_scale_rad)
        chosen = [n_pool - 1]  # the newest frame is always in
        nearest = dist[-1].copy()
        # A chosen frame is never chosen again, even where frames share a time and a heading (a
        # coarse or frozen clock while the vehicle stands): every distance is then 0, and the
        # argmax would take the newest frame again and again.
        nearest[n_pool - 1] = -np.inf
        for _ in range(self.n_frames - 1):
            # Ties (e.g. equal distances) go to the newer frame: argmax of the reversed array.
            best = n_pool - 1 - int(np.argmax(nearest[::-1]))
            chosen.append(best)
            nearest = np.minimum(nearest, dist[best])
            nearest[best] = -np.inf
        return [first + i for i in sorted(chosen)]
