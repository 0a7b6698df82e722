"""The camera's share of the image: auto-exposure, white balance, vignetting, blur, sensor noise,
tone curve and 8-bit quantisation. JPEG artefacts come later, from the log writer.

Radiance in, BGR uint8 out. Noise is added to sqrt(exposure), where photon (shot) noise has a
near-constant spread (Anscombe), and generated at half resolution then upsampled, as demosaicing
correlates it; both keep a frame's noise to a few milliseconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

_LUT_SIZE = 4096
_LUT_RANGE = 2.0  # sqrt(exposure) range the LUT covers: exposures up to 4x mid-white


def _tone_lut() -> np.ndarray:
    q = np.arange(_LUT_SIZE, dtype=np.float64) / (_LUT_SIZE - 1) * _LUT_RANGE
    x = q * q  # linear exposure
    y = 1.0 - np.exp(-1.1 * x)  # soft shoulder: highlights roll off, 0.18 stays ~0.18
    srgb = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1 / 2.4) - 0.055)
    return np.clip(np.round(srgb * 255.0), 0, 255).astype(np.uint8)


_LUT = _tone_lut()


@dataclass(frozen=True)
class CameraEffects:
    """What the camera does to the light. ``auto_exposure`` meters each frame (with lag
    ``ae_smoothing`` in [0, 1): 0 follows at once); otherwise ``fixed_exposure`` multiplies the
    radiance (kcd/m^2) directly. ``noise_sqrt`` is the noise spread in sqrt-exposure units."""

    auto_exposure: bool = True
    fixed_exposure: float = 0.02
    exposure_bias_stops: float = 0.0
    ae_key: float = 0.18
    ae_smoothing: float = 0.4
    white_balance_bgr: tuple[float, float, float] = (1.0, 1.0, 1.0)
    vignette: float = 0.0  # fractional light loss at the image corners
    blur_sigma_px: float = 0.0
    noise_sqrt: float = 0.0

    @staticmethod
    def ideal(exposure: float | None = None) -> CameraEffects:
        """No noise, no vignetting, no blur; fixed exposure if given, else auto-exposure."""
        if exposure is None:
            return CameraEffects(ae_smoothing=0.0)
        return CameraEffects(auto_exposure=False, fixed_exposure=exposure)

    @staticmethod
    def random(rng: np.random.Generator) -> CameraEffects:
        return CameraEffects(
            exposure_bias_stops=float(rng.normal(0.0, 0.35)),
            ae_key=float(rng.uniform(0.14, 0.24)),
            ae_smoothing=float(rng.uniform(0.2, 0.7)),
            white_balance_bgr=tuple(float(v) for v in 1.0 + rng.normal(0.0, 0.04, 3)),
            vignette=float(rng.uniform(0.0, 0.35)),
            blur_sigma_px=float(rng.choice([0.0, 0.0, rng.uniform(0.3, 0.9)])),
            noise_sqrt=float(rng.uniform(0.004, 0.02)),
        )


class Camera:
    """Turns radiance into 8-bit frames; keeps the auto-exposure state between frames."""

    def __init__(self, effects: CameraEffects, width: int, height: int) -> None:
        self.effects = effects
        self.width, self.height = width, height
        self._log_exposure: float | None = None
        if effects.vignette > 0.0:
            y, x = np.mgrid[0:height, 0:width].astype(np.float32)
            r2 = ((x + 0.5 - width / 2) ** 2 + (y + 0.5 - height / 2) ** 2) / ((width / 2) ** 2 + (height / 2) ** 2)
            self._vignette = (1.0 - effects.vignette * r2 * (0.6 + 0.4 * r2)).astype(np.float32)[..., None]
        else:
            self._vignette = None

    def exposure_for(self, radiance: np.ndarray) -> float:
        """Exposure that auto-exposure chooses for this frame (updates the state)."""
        e = self.effects
        if not e.auto_exposure:
            return e.fixed_exposure
        small = cv2.resize(radiance, (max(1, radiance.shape[1] // 8), max(1, radiance.shape[0] // 8)),
                           interpolation=cv2.INTER_AREA)
        lum = small @ np.array([0.0722, 0.7152, 0.2126], np.float32)
        # Highlights (sun, bright sky) are clipped in the meter, as a centre-weighted meter would.
        med = float(np.median(lum))
        meter = float(np.mean(np.minimum(lum, 4.0 * med))) if med > 0 else float(np.mean(lum))
        target = math.log(e.ae_key / max(meter, 1e-6)) + e.exposure_bias_stops * math.log(2.0)
        if self._log_exposure is None:
            self._log_exposure = target
        else:
            self._log_exposure = e.ae_smoothing * self._log_exposure + (1.0 - e.ae_smoothing) * target
        return math.exp(self._log_exposure)

    def capture(self, radiance: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """Radiance (h, w, 3) float32 BGR (any size: resized to the camera's) -> BGR uint8."""
        e = self.effects
        if radiance.shape[:2] != (self.height, self.width):
            radiance = cv2.resize(radiance, (self.width, self.height), interpolation=cv2.INTER_LINEAR)
        exposure = self.exposure_for(radiance)
        gain = np.asarray(e.white_balance_bgr, np.float32) * np.float32(exposure)
        x = radiance * gain
        if self._vignette is not None:
            x *= self._vignette
        if e.blur_sigma_px > 0.0:
            x = cv2.GaussianBlur(x, (0, 0), e.blur_sigma_px)
        q = np.sqrt(np.maximum(x, 0.0, out=x), out=x)
        if e.noise_sqrt > 0.0:
            if rng is None:
                raise ValueError("Camera.capture: noise needs an rng")
            hh, hw = (self.height + 1) // 2, (self.width + 1) // 2
            n = rng.standard_normal((hh, hw, 3), dtype=np.float32)
            n = cv2.resize(n, (self.width, self.height), interpolation=cv2.INTER_LINEAR)
            # Upsampling halves the spread; make it up, and add some per-pixel noise on top.
            q += n * np.float32(e.noise_sqrt * 1.6)
        idx = np.clip(q * np.float32((_LUT_SIZE - 1) / _LUT_RANGE), 0, _LUT_SIZE - 1).astype(np.uint16)
        return _LUT[idx]
