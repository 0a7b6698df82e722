"""Analytic daylight: the Preetham (1999) clear sky, the direct sun and the ambient light they give.

Radiance is in kcd/m^2 and irradiance in klux (Preetham's zenith luminance is in kcd/m^2), colour
as linear sRGB in BGR channel order (OpenCV's), so a surface of albedo ``rho`` lit by irradiance
``E`` has radiance ``rho * E / pi`` in the same units as the sky behind it.

Reference: A. J. Preetham, P. Shirley, B. Smits, "A Practical Analytic Model for Daylight",
SIGGRAPH 1999 (the Perez sky distribution with turbidity-dependent coefficients, appendix A.2).
"""

from __future__ import annotations

import math

import numpy as np

from rig.geometry import normalize

# Perez coefficients (A..E) as (slope, intercept) in turbidity T: appendix A.2 of Preetham 1999.
_PEREZ_Y = np.array(
    [[0.1787, -1.4630], [-0.3554, 0.4275], [-0.0227, 5.3251], [0.1206, -2.5771], [-0.0670, 0.3703]]
)
_PEREZ_X = np.array(
    [[-0.0193, -0.2592], [-0.0665, 0.0008], [-0.0004, 0.2125], [-0.0641, -0.8989], [-0.0033, 0.0452]]
)
_PEREZ_YC = np.array(
    [[-0.0167, -0.2608], [-0.0950, 0.0092], [-0.0079, 0.2102], [-0.0441, -1.6537], [-0.0109, 0.0529]]
)
# Zenith chromaticity: [T^2, T, 1] @ M @ [theta^3, theta^2, theta, 1].
_ZENITH_X = np.array(
    [
        [0.00166, -0.00375, 0.00209, 0.0],
        [-0.02903, 0.06377, -0.03202, 0.00394],
        [0.11693, -0.21196, 0.06052, 0.25886],
    ]
)
_ZENITH_Y = np.array(
    [
        [0.00275, -0.00610, 0.00317, 0.0],
        [-0.04214, 0.08970, -0.04153, 0.00516],
        [0.15346, -0.26756, 0.06670, 0.26688],
    ]
)
# CIE XYZ -> linear sRGB (D65), rows reordered to B, G, R.
_BGR_FROM_XYZ = np.array(
    [
        [0.0557, -0.2040, 1.0570],
        [-0.9689, 1.8758, 0.0415],
        [3.2406, -1.5372, -0.4986],
    ]
)
# Optical depth per channel (B, G, R at ~465, 550, 610 nm): Rayleigh, and the aerosol share
# scaled by Preetham's Angstrom beta(T) = 0.04608 T - 0.04586 with alpha = 1.3.
_RAYLEIGH_TAU = np.array([0.19, 0.097, 0.062])
_AEROSOL_LAMBDA = np.array([0.465, 0.55, 0.61]) ** -1.3
SOLAR_ILLUMINANCE_KLUX = 128.0  # outside the atmosphere
SUN_ANGULAR_RADIUS_RAD = math.radians(0.267)


def _perez(cos_theta, gamma, cos_gamma, coef):
    a, b, c, d, e = coef
    return (1.0 + a * np.exp(b / cos_theta)) * (1.0 + c * np.exp(d * gamma) + e * cos_gamma * cos_gamma)


def relative_airmass(elevation_rad: float) -> float:
    """Kasten & Young (1989) air mass; finite down to the horizon."""
    el_deg = max(math.degrees(elevation_rad), 0.0)
    return 1.0 / (math.sin(math.radians(el_deg)) + 0.50572 * (el_deg + 6.07995) ** -1.6364)


class PreethamSky:
    """Clear-sky radiance around a sun direction, plus the direct sun it implies.

    ``sun_enu``: unit vector to the sun (ENU, above the horizon). ``turbidity``: 2 (very clear)
    to ~8 (hazy). ``sun_visibility`` in (0, 1] scales the direct beam for a sun dimmed by cloud;
    ``cloud_cover`` in [0, 1) greys the sky and raises its brightness toward an overcast sky.
    ``sky_scale`` scales the sky's luminance: Preetham's absolute zenith luminance gives a diffuse
    share of ~1/3 of the global light at 45 deg, about twice what clear-sky measurements show, so
    the default brings the shadow/sunlit contrast of horizontal ground to ~0.2-0.25.
    """

    def __init__(
        self,
        sun_enu,
        turbidity: float = 3.0,
        *,
        sun_visibility: float = 1.0,
        cloud_cover: float = 0.0,
        sky_scale: float = 0.6,
    ) -> None:
        s = normalize(np.asarray(sun_enu, dtype=np.float64))
        if s[2] <= 0.0:
            raise ValueError(f"PreethamSky: expected the sun above the horizon, got z = {s[2]:.4f}")
        if not 1.7 <= turbidity <= 10.0:
            raise ValueError(f"PreethamSky: expected turbidity in [1.7, 10], got {turbidity}")
        self.sun_enu = s
        self.turbidity = float(turbidity)
        self.sun_visibility = float(np.clip(sun_visibility, 0.0, 1.0))
        self.cloud_cover = float(np.clip(cloud_cover, 0.0, 0.95))
        t = self.turbidity
        theta_s = math.acos(min(1.0, s[2]))
        self.theta_s = theta_s
        self._cy = _PEREZ_Y @ np.array([t, 1.0])
        self._cx = _PEREZ_X @ np.array([t, 1.0])
        self._cyc = _PEREZ_YC @ np.array([t, 1.0])
        th = np.array([theta_s**3, theta_s**2, theta_s, 1.0])
        tt = np.array([t * t, t, 1.0])
        self._zx = float(tt @ _ZENITH_X @ th)
        self._zy = float(tt @ _ZENITH_Y @ th)
        chi = (4.0 / 9.0 - t / 120.0) * (math.pi - 2.0 * theta_s)
        self._zY = sky_scale * max((4.0453 * t - 4.9710) * math.tan(chi) - 0.2155 * t + 2.4192, 0.05)
        # Perez normalisation F(0, theta_s): the zenith, which lies theta_s from the sun.
        cos_ts = math.cos(theta_s)
        self._f0 = [float(_perez(1.0, theta_s, cos_ts, c)) for c in (self._cy, self._cx, self._cyc)]
        # Direct sun: per-channel transmittance along the air mass.
        beta = max(0.04608 * t - 0.04586, 0.0)
        tau = _RAYLEIGH_TAU + beta * _AEROSOL_LAMBDA
        m = relative_airmass(math.asin(s[2]))
        self.sun_transmittance_bgr = np.exp(-tau * m)
        self.sun_irradiance_bgr = (
            SOLAR_ILLUMINANCE_KLUX * self.sun_transmittance_bgr * self.sun_visibility
        )
        # Overcast component: a grey, brighter-at-zenith sky (CIE overcast, L ~ (1 + 2 sin el)/3)
        # whose level is set so clouds are lit by what the clear sky and the sun give them.
        clear_h = self._horizontal_sky_irradiance_clear()
        sun_h = float(SOLAR_ILLUMINANCE_KLUX * self.sun_transmittance_bgr[1] * s[2])
        self._overcast_zenith = 0.35 * (clear_h + 0.6 * sun_h) / math.pi * 9.0 / 7.0
        self._ambient_cache: dict[tuple, np.ndarray] = {}

    # -- radiance

    def _clear_radiance(self, dirs: np.ndarray) -> np.ndarray:
        d = np.asarray(dirs, dtype=np.float32)
        cos_theta = np.clip(d[..., 2], 0.02, 1.0)
        cos_gamma = np.clip(d @ self.sun_enu.astype(np.float32), -1.0, 1.0)
        gamma = np.arccos(cos_gamma)
        lum = self._zY * _perez(cos_theta, gamma, cos_gamma, self._cy) / self._f0[0]
        x = self._zx * _perez(cos_theta, gamma, cos_gamma, self._cx) / self._f0[1]
        y = self._zy * _perez(cos_theta, gamma, cos_gamma, self._cyc) / self._f0[2]
        # Near the horizon the model's chromaticity dips below the daylight locus (a magenta
        # cast); keep it on or above the locus y_D(x) = -3 x^2 + 2.87 x - 0.275.
        y = np.maximum(y, -3.0 * x * x + 2.87 * x - 0.275 - 0.002)
        y = np.maximum(y, 1e-4)
        big_x = x / y * lum
        big_z = (1.0 - x - y) / y * lum
        xyz = np.stack([big_x, lum, big_z], axis=-1)
        return np.maximum(xyz @ _BGR_FROM_XYZ.T.astype(np.float32), 0.0)

    def radiance(self, dirs) -> np.ndarray:
        """Sky radiance (..., 3) BGR for unit directions (..., 3); directions below the horizon
        get the radiance just above it. The sun disk itself is not included (see :meth:`sun_disk`).
        """
        d = np.asarray(dirs, dtype=np.float32)
        clear = self._clear_radiance(d)
        if self.cloud_cover <= 0.0:
            return clear.astype(np.float32)
        sin_el = np.clip(d[..., 2], 0.0, 1.0)
        grey = self._overcast_zenith * (1.0 + 2.0 * sin_el) / 3.0
        # The cloud layer itself is drawn by the renderer; this is the veil between the clouds.
        c = 0.4 * self.cloud_cover
        return ((1.0 - c) * clear + c * grey[..., None]).astype(np.float32)

    def sun_disk_radiance_bgr(self) -> np.ndarray:
        """Radiance of the disk: direct irradiance over the disk's solid angle."""
        omega = math.pi * SUN_ANGULAR_RADIUS_RAD**2
        return self.sun_irradiance_bgr / omega

    # -- irradiance

    def _hemisphere(self, n: int = 1200) -> tuple[np.ndarray, float]:
        # Fibonacci points on the upper hemisphere: equal solid angle 2 pi / n each.
        i = np.arange(n) + 0.5
        z = 1.0 - i / n
        phi = i * math.pi * (3.0 - math.sqrt(5.0))
        r = np.sqrt(1.0 - z * z)
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=-1), 2.0 * math.pi / n

    def _horizontal_sky_irradiance_clear(self) -> float:
        dirs, dw = self._hemisphere(600)
        lum = self._clear_radiance(dirs) @ np.array([0.0722, 0.7152, 0.2126], dtype=np.float32)
        return float(np.sum(lum * dirs[:, 2]) * dw)

    def ambient_irradiance(self, normals, ground_albedo: float = 0.15) -> np.ndarray:
        """Sky plus ground-bounced irradiance (N, 3) BGR on surfaces with unit normals (N, 3).

        The sky is integrated over the hemisphere the normal sees (no occlusion by the scene);
        the ground is a uniform Lambertian plane lit by the sun and the sky.
        """
        nrm = np.atleast_2d(np.asarray(normals, dtype=np.float64))
        dirs, dw = self._hemisphere()
        sky = self.radiance(dirs).astype(np.float64)  # (M, 3)
        cosw = nrm @ dirs.T  # (N, M)
        np.clip(cosw, 0.0, None, out=cosw)  # in place: at 9.6 kB a normal, a second copy is felt
        e_sky = cosw @ sky * dw
        e_sky_h = (dirs[:, 2] @ sky) * dw
        e_ground_h = e_sky_h + self.sun_irradiance_bgr * self.sun_enu[2]
        # A plane of radiance rho E / pi filling the lower hemisphere seen by the normal.
        e_ground = ground_albedo * e_ground_h[None, :] * (1.0 - nrm[:, 2:3]) / 2.0
        return e_sky + e_ground

    def direct_irradiance(self, normals) -> np.ndarray:
        """Direct sun irradiance (N, 3) BGR on unshadowed surfaces with unit normals (N, 3)."""
        nrm = np.atleast_2d(np.asarray(normals, dtype=np.float64))
        cos = np.clip(nrm @ self.sun_enu, 0.0, None)
        return cos[:, None] * self.sun_irradiance_bgr[None, :]
