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

from replay.synthetic.scene import float3

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
            white_balance_bgr=float3(1.0 + rng.normal(0.0, 0.04, 3)),
            vignette=float(rng.uniform(0.0, 0.35)),
            blur_sigma_px=float(rng.choice([0.0, 0.0, rng.uniform(0.3, 0.9)])),
            noise_sqrt=float(rng.uniform(0.002, 0.008)),
        )


class Camera:
    """Turns radiance into 8-bit frames; keeps the auto-exposure state between frames.

    ``seed`` draws the sensor's noise bank: per frame, a randomly shifted and flipped window of
    it (chosen by the frame's rng) is the noise, which costs far less than fresh normal deviates.
    """

    _BANK_MARGIN = 48

    def __init__(self, effects: CameraEffects, width: int, height: int, seed: int = 0) -> None:
        self.effects = effects
        self.width, self.height = width, height
        self._log_exposure: float | None = None
        gain = np.ones((height, width, 3), np.float32) * np.asarray(effects.white_balance_bgr, np.float32)
        if effects.vignette > 0.0:
            y, x = np.mgrid[0:height, 0:width].astype(np.float32)
            r2 = ((x + 0.5 - width / 2) ** 2 + (y + 0.5 - height / 2) ** 2) / ((width / 2) ** 2 + (height / 2) ** 2)
            gain *= (1.0 - effects.vignette * r2 * (0.6 + 0.4 * r2))[..., None]
        self._gain = gain
        if effects.noise_sqrt > 0.0:
            hh, hw = (height + 1) // 2, (width + 1) // 2
            m = self._BANK_MARGIN
            rng = np.random.default_rng([seed, 0x6E6F697365])
            self._bank = rng.standard_normal((hh + m, hw + m, 3), dtype=np.float32)
            self._bank_shape = (hh, hw)
        self._noise_up = np.empty((height, width, 3), np.float32)
        self._idx = np.empty((height, width, 3), np.uint16)

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
        exposure = self.exposure_for(radiance)  # metered before upsampling: cheaper, same answer
        if radiance.shape[:2] != (self.height, self.width):
            x = cv2.resize(radiance, (self.width, self.height), interpolation=cv2.INTER_LINEAR)
        else:
            x = radiance.copy()
        cv2.multiply(x, self._gain, dst=x, scale=exposure)
        if e.blur_sigma_px > 0.0:
            cv2.GaussianBlur(x, (0, 0), e.blur_sigma_px, dst=x)
        np.maximum(x, 0.0, out=x)
        q = np.sqrt(x, out=x)
        if e.noise_sqrt > 0.0:
            if rng is None:
                raise ValueError("Camera.capture: noise needs an rng")
            hh, hw = self._bank_shape
            dy, dx = rng.integers(0, self._BANK_MARGIN, 2)
            win = self._bank[dy:dy + hh, dx:dx + hw]
            if rng.random() < 0.5:
                win = win[::-1]
            if rng.random() < 0.5:
                win = win[:, ::-1]
            n = cv2.resize(np.ascontiguousarray(win), (self.width, self.height), dst=self._noise_up,
                           interpolation=cv2.INTER_LINEAR)
            # Bilinear upsampling lowers the spread by ~1.6; the scale restores it.
            cv2.scaleAdd(n, e.noise_sqrt * 1.6, q, dst=q)
        q *= np.float32((_LUT_SIZE - 1) / _LUT_RANGE)
        np.clip(q, 0, _LUT_SIZE - 1, out=q)
        np.copyto(self._idx, q, casting="unsafe")
        return np.take(_LUT, self._idx)
