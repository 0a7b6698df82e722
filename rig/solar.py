"""The sun's position from UTC time and place: NREL's Solar Position Algorithm (SPA), in numpy.

Reda & Andreas, "Solar Position Algorithm for Solar Radiation Applications", NREL/TP-560-34302
(2004, revised 2008); the step numbers below are the report's (section 3.x). Stated uncertainty
+-0.0003 deg for the years -2000 to 6000. It is the ground truth of the paper this project
implements (Lee et al., IJCV 2023: sun direction from GPS position + UTC through SPA).

Everything is vectorised: times, latitudes, longitudes and the atmosphere broadcast against each
other, so a whole drive is one call. It lives in ``rig/`` beside the geometry, not in
``estimator/``: it is the world's truth, not a part of the learned estimator, and replay
(KITTI, native logs), the CLI and a live GNSS-equipped rig all need it without onnxruntime.

Units: the algorithm is written in degrees, like the report, so each intermediate can be checked
against its worked example; the public result (:class:`SunPosition`) is in radians, as
everywhere inside sunrig. Time is UTC: integer nanoseconds since the Unix epoch, or numpy
datetime64 of any unit (coarser units reach the report's whole -2000..6000 range; ns stops at
1678..2262). Calendar dates are proleptic Gregorian (numpy's), also before 1582.

Defaults, as the report suggests where it gives one:

- pressure 1013.25 hPa and temperature 12 C: they only scale the refraction (<= 0.6 deg at the
  horizon, ~0.02 deg at 40 deg elevation), so a 5 % error in pressure moves the sun < 0.03 deg.
- atmospheric refraction at sunrise/sunset 0.5667 deg (decides when refraction is applied).
- Delta T = TT - UT1: by default the Espenak & Meeus (2006) polynomial approximation
  (:func:`delta_t_approx_s`, ~67 s in 2011, ~74 s in 2024 where the observed value is ~69 s).
  Delta T only moves the sun along its orbit (~0.04 arcsec per second of Delta T), so for
  present-day dates any reasonable value gives the same answer to 1e-5 deg.
"""

from __future__ import annotations

import datetime as _dt
import re
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from rig.errors import ValidationError
from rig.geometry import enu_from_az_el

DEFAULT_PRESSURE_HPA = 1013.25
DEFAULT_TEMPERATURE_C = 12.0
DEFAULT_REFRACTION_DEG = 0.5667
SUN_RADIUS_DEG = 0.26667
# The observer elevations taken (from the SPA code's -6500 km up to 10,000 km); a reader checks its
# records against them first, so that one damaged altitude costs its record, not the whole call.
ELEVATION_RANGE_M = (-6_500_000.0, 1e7)
# The times integer ns since the epoch hold in int64, as datetime64[ns] does (whose lowest value is
# NaT, not a time): 1677-09-21 to 2262-04-11, "the years 1678..2262" of the messages. A reader
# checks its times against them, since numpy wraps a date past them around without a word.
UTC_NS_MIN, UTC_NS_MAX = -(2**63) + 1, 2**63 - 1
NS_YEARS = "1678..2262"
_JD_UNIX_EPOCH = 2440587.5  # Julian day of 1970-01-01T00:00Z
_J2000 = 2451545.0
_JD_MIN, _JD_MAX = 990574.5, 3912880.5  # -2000-01-01T00:00 and 6001-01-01T00:00, proleptic Gregorian
_EARTH_RADIUS_M = 6378140.0  # the report's value (IAU 1976), used with its flattening below
_POLAR_RATIO = 0.99664719  # 1 - f of the same ellipsoid


def _terms(text: str) -> np.ndarray:
    """A periodic-term table as the report prints it: rows of A, B, C (term = A cos(B + C x))."""
    return np.array([[float(v) for v in line.split()] for line in text.strip().splitlines()])


# Earth periodic terms, Table A4.2 of the report (VSOP87 as truncated by Meeus): heliocentric
# longitude L (L0..L5), latitude B (B0, B1) and radius vector R (R0..R4), in units of 1e-8 rad / AU.
_L0 = _terms("""
    175347046 0 0
    3341656 4.6692568 6283.07585
    34894 4.6261 12566.1517
    3497 2.7441 5753.3849
    3418 2.8289 3.5231
    3136 3.6277 77713.7715
    2676 4.4181 7860.4194
    2343 6.1352 3930.2097
    1324 0.7425 11506.7698
    1273 2.0371 529.691
    1199 1.1096 1577.3435
    990 5.233 5884.927
    902 2.045 26.298
    857 3.508 398.149
    780 1.179 5223.694
    753 2.533 5507.553
    505 4.583 18849.228
    492 4.205 775.523
    357 2.92 0.067
    317 5.849 11790.629
    284 1.899 796.298
    271 0.315 10977.079
    243 0.345 5486.778
    206 4.806 2544.314
    205 1.869 5573.143
    202 2.458 6069.777
    156 0.833 213.299
    132 3.411 2942.463
    126 1.083 20.775
    115 0.645 0.98
    103 0.636 4694.003
    102 0.976 15720.839
    102 4.267 7.114
    99 6.21 2146.17
    98 0.68 155.42
    86 5.98 161000.69
    85 1.3 6275.96
    85 3.67 71430.7
    80 1.81 17260.15
    79 3.04 12036.46
    75 1.76 5088.63
    74 3.5 3154.69
    74 4.68 801.82
    70 0.83 9437.76
    62 3.98 8827.39
    61 1.82 7084.9
    57 2.78 6286.6
    56 4.39 14143.5
    56 3.47 6279.55
    52 0.19 12139.55
    52 1.33 1748.02
    51 0.28 5856.48
    49 0.49 1194.45
    41 5.37 8429.24
    41 2.4 19651.05
    39 6.17 10447.39
    37 6.04 10213.29
    37 2.57 1059.38
    36 1.71 2352.87
    36 1.78 6812.77
    33 0.59 17789.85
    30 0.44 83996.85
    30 2.74 1349.87
    25 3.16 4690.48
""")
_L1 = _terms("""
    628331966747 0 0
    206059 2.678235 6283.07585
    4303 2.6351 12566.1517
    425 1.59 3.523
    119 5.796 26.298
    109 2.966 1577.344
    93 2.59 18849.23
    72 1.14 529.69
    68 1.87 398.15
    67 4.41 5507.55
    59 2.89 5223.69
    56 2.17 155.42
    45 0.4 796.3
    36 0.47 775.52
    29 2.65 7.11
    21 5.34 0.98
    19 1.85 5486.78
    19 4.97 213.3
    17 2.99 6275.96
    16 0.03 2544.31
    16 1.43 2146.17
    15 1.21 10977.08
    12 2.83 1748.02
    12 3.26 5088.63
    12 5.27 1194.45
    12 2.08 4694
    11 0.77 553.57
    10 1.3 6286.6
    10 4.24 1349.87
    9 2.7 242.73
    9 5.64 951.72
    8 5.3 2352.87
    6 2.65 9437.76
    6 4.67 4690.48
""")
_L2 = _terms("""
    52919 0 0
    8720 1.0721 6283.0758
    309 0.867 12566.152
    27 0.05 3.52
    16 5.19 26.3
    16 3.68 155.42
    10 0.76 18849.23
    9 2.06 77713.77
    7 0.83 775.52
    5 4.66 1577.34
    4 1.03 7.11
    4 3.44 5573.14
    3 5.14 796.3
    3 6.05 5507.55
    3 1.19 242.73
    3 6.12 529.69
    3 0.31 398.15
    3 2.28 553.57
    2 4.38 5223.69
    2 3.75 0.98
""")
_L3 = _terms("""
    289 5.844 6283.076
    35 0 0
    17 5.49 12566.15
    3 5.2 155.42
    1 4.72 3.52
    1 5.3 18849.23
    1 5.97 242.73
""")
_L4 = _terms("""
    114 3.142 0
    8 4.13 6283.08
    1 3.84 12566.15
""")
_L5 = _terms("""
    1 3.14 0
""")
_B0 = _terms("""
    280 3.199 84334.662
    102 5.422 5507.553
    80 3.88 5223.69
    44 3.7 2352.87
    32 4 1577.34
""")
_B1 = _terms("""
    9 3.9 5507.55
    6 1.73 5223.69
""")
_R0 = _terms("""
    100013989 0 0
    1670700 3.0984635 6283.07585
    13956 3.05525 12566.1517
    3084 5.1985 77713.7715
    1628 1.1739 5753.3849
    1576 2.8469 7860.4194
    925 5.453 11506.77
    542 4.564 3930.21
    472 3.661 5884.927
    346 0.964 5507.553
    329 5.9 5223.694
    307 0.299 5573.143
    243 4.273 11790.629
    212 5.847 1577.344
    186 5.022 10977.079
    175 3.012 18849.228
    110 5.055 5486.778
    98 0.89 6069.78
    86 5.69 15720.84
    86 1.27 161000.69
    65 0.27 17260.15
    63 0.92 529.69
    57 2.01 83996.85
    56 5.24 71430.7
    49 3.25 2544.31
    47 2.58 775.52
    45 5.54 9437.76
    43 6.01 6275.96
    39 5.36 4694
    38 2.39 8827.39
    37 0.83 19651.05
    37 4.9 12139.55
    36 1.67 12036.46
    35 1.84 2942.46
    33 0.24 7084.9
    32 0.18 5088.63
    32 1.78 398.15
    28 1.21 6286.6
    28 1.9 6279.55
    26 4.59 10447.39
""")
_R1 = _terms("""
    103019 1.10749 6283.07585
    1721 1.0644 12566.1517
    702 3.142 0
    32 1.02 18849.23
    31 2.84 5507.55
    25 1.32 5223.69
    18 1.42 1577.34
    10 5.91 10977.08
    9 1.42 6275.96
    9 0.27 5486.78
""")
_R2 = _terms("""
    4359 5.7846 6283.0758
    124 5.579 12566.152
    12 3.14 0
    9 3.63 77713.77
    6 1.87 5573.14
    3 5.47 18849.23
""")
_R3 = _terms("""
    145 4.273 6283.076
    7 3.92 12566.15
""")
_R4 = _terms("""
    4 2.56 6283.08
""")
# Periodic terms of the nutation in longitude and obliquity, Table A4.3 of the report: the
# multiples Y0..Y4 of the arguments X0..X4, then the coefficients a, b (longitude), c, d (obliquity).
_NUTATION = """
    0 0 0 0 1   -171996 -174.2 92025 8.9
    -2 0 0 2 2   -13187 -1.6 5736 -3.1
    0 0 0 2 2   -2274 -0.2 977 -0.5
    0 0 0 0 2   2062 0.2 -895 0.5
    0 1 0 0 0   1426 -3.4 54 -0.1
    0 0 1 0 0   712 0.1 -7 0
    -2 1 0 2 2   -517 1.2 224 -0.6
    0 0 0 2 1   -386 -0.4 200 0
    0 0 1 2 2   -301 0 129 -0.1
    -2 -1 0 2 2   217 -0.5 -95 0.3
    -2 0 1 0 0   -158 0 0 0
    -2 0 0 2 1   129 0.1 -70 0
    0 0 -1 2 2   123 0 -53 0
    2 0 0 0 0   63 0 0 0
    0 0 1 0 1   63 0.1 -33 0
    2 0 -1 2 2   -59 0 26 0
    0 0 -1 0 1   -58 -0.1 32 0
    0 0 1 2 1   -51 0 27 0
    -2 0 2 0 0   48 0 0 0
    0 0 -2 2 1   46 0 -24 0
    2 0 0 2 2   -38 0 16 0
    0 0 2 2 2   -31 0 13 0
    0 0 2 0 0   29 0 0 0
    -2 0 1 2 2   29 0 -12 0
    0 0 0 2 0   26 0 0 0
    -2 0 0 2 0   -22 0 0 0
    0 0 -1 2 1   21 0 -10 0
    0 2 0 0 0   17 -0.1 0 0
    2 0 -1 0 1   16 0 -8 0
    -2 2 0 2 2   -16 0.1 7 0
    0 1 0 0 1   -15 0 9 0
    -2 0 1 0 1   -13 0 7 0
    0 -1 0 0 1   -12 0 6 0
    0 0 2 -2 0   11 0 0 0
    2 0 -1 2 1   -10 0 5 0
    2 0 1 2 2   -8 0 3 0
    0 1 0 2 2   7 0 -3 0
    -2 1 1 0 0   -7 0 0 0
    0 -1 0 2 2   -7 0 3 0
    2 0 0 2 1   -7 0 3 0
    2 0 1 0 0   6 0 0 0
    -2 0 2 2 2   6 0 -3 0
    -2 0 1 2 1   6 0 -3 0
    2 0 -2 0 1   -6 0 3 0
    2 0 0 0 1   -6 0 3 0
    0 -1 1 0 0   5 0 0 0
    -2 -1 0 2 1   -5 0 3 0
    -2 0 0 0 1   -5 0 3 0
    0 0 2 2 1   -5 0 3 0
    -2 0 2 0 1   4 0 0 0
    -2 1 0 2 1   4 0 0 0
    0 0 1 -2 0   4 0 0 0
    -1 0 1 0 0   -4 0 0 0
    -2 1 0 0 0   -4 0 0 0
    1 0 0 0 0   -4 0 0 0
    0 0 1 2 0   3 0 0 0
    0 0 -2 2 2   -3 0 0 0
    -1 -1 1 0 0   -3 0 0 0
    0 1 1 0 0   -3 0 0 0
    0 -1 1 2 2   -3 0 0 0
    2 -1 -1 2 2   -3 0 0 0
    0 0 3 2 2   -3 0 0 0
    2 -1 0 2 2   -3 0 0 0
"""

_NUTATION_TABLE = np.array([[float(v) for v in line.split()] for line in _NUTATION.strip().splitlines()])
_NUT_Y = _NUTATION_TABLE[:, :5]  # multiples of X0..X4 in each term's argument
_NUT_ABCD = _NUTATION_TABLE[:, 5:]  # dpsi = (a + b JCE) sin(arg), deps = (c + d JCE) cos(arg), 0.0001"


# ------------------------------------------------------------------------------------------
# Time


_UNITS_PER_DAY = {"D": 1, "h": 24, "m": 1440, "s": 86_400, "ms": 86_400_000, "us": 86_400_000_000,
                  "ns": 86_400_000_000_000}


def _day_and_fraction(utc) -> tuple[np.ndarray, np.ndarray]:
    """Whole days since 1970-01-01 (int64) and the fraction of the day, from ns or datetime64.

    Split so that the Julian day keeps its precision: the integer part is exact and the fraction
    is taken from an integer remainder, never from a large float.
    """
    if isinstance(utc, _dt.datetime):
        if utc.tzinfo is None:
            raise ValidationError(f"time: expected an aware datetime (UTC), got the naive {utc.isoformat()}")
        utc = np.datetime64(utc.astimezone(_dt.UTC).replace(tzinfo=None), "us")
    arr = np.asarray(utc)
    if arr.dtype.kind == "M":
        if np.any(np.isnat(arr)):
            raise ValidationError("time: expected valid times, got NaT")
        unit, count = np.datetime_data(arr.dtype)
        if unit in ("Y", "M", "W"):
            arr = arr.astype("datetime64[D]")
            unit, count = "D", 1
        if unit not in _UNITS_PER_DAY:
            raise ValidationError(f"time: datetime64 unit {unit!r} is not supported; use s, ms, us or ns")
        ticks = arr.view(np.int64)
        per_day = _UNITS_PER_DAY[unit] // count if _UNITS_PER_DAY[unit] % count == 0 else None
        if per_day is None:
            raise ValidationError(f"time: datetime64[{count}{unit}] does not divide a day; use s, ms, us or ns")
    elif arr.dtype.kind in "iu" or (arr.dtype == object and all(isinstance(v, int) for v in arr.flat)):
        try:  # Python ints too large for int64 arrive as an object array and fail here
            ticks = np.array(arr, dtype=np.int64) if arr.dtype == object else arr.astype(np.int64, casting="safe")
        except (OverflowError, TypeError):
            raise ValidationError(f"time: integer ns since the epoch must fit in int64 (years {NS_YEARS}); "
                                  "pass numpy datetime64[s] for other years") from None
        per_day = _UNITS_PER_DAY["ns"]
    else:
        raise ValidationError(f"time: expected integer ns since the Unix epoch or datetime64, got dtype {arr.dtype}")
    days, rem = np.divmod(ticks, per_day)
    return days, rem / per_day


def julian_day(utc) -> np.ndarray:
    """Julian day (UT) of UTC times (integer ns since the epoch or datetime64). Step 3.1.1."""
    days, frac = _day_and_fraction(utc)
    return (_JD_UNIX_EPOCH + days) + frac


def delta_t_approx_s(decimal_year) -> np.ndarray:
    """Delta T = TT - UT1 in seconds from Espenak & Meeus (2006), "Five Millennium Canon of Solar
    Eclipses" (NASA/TP-2006-214141), the polynomials also on NASA's eclipse site.

    Good to ~1 s for 1900..2005, drifting to a few seconds now (the polynomial gives 74 s for
    2024, observed 69 s) and to minutes over past millennia: irrelevant for the sun's direction
    (see the module notes). ``decimal_year`` is e.g. ``year + (month - 0.5) / 12``.
    """
    y = np.asarray(decimal_year, dtype=np.float64)
    out = np.empty_like(y)
    u_long = (y - 1820.0) / 100.0
    pieces = [  # (upper bound of the piece, value)
        (-500.0, -20.0 + 32.0 * u_long**2),
        (500.0, np.polyval([0.0090316521, 0.022174192, -0.1798452, -5.952053, 33.78311, -1014.41, 10583.6],
                           y / 100.0)),
        (1600.0, np.polyval([0.0083572073, -0.005050998, -0.8503463, 0.319781, 71.23472, -556.01, 1574.2],
                            (y - 1000.0) / 100.0)),
        (1700.0, np.polyval([1.0 / 7129.0, -0.01532, -0.9808, 120.0], y - 1600.0)),
        (1800.0, np.polyval([-1.0 / 1174000.0, 0.00013336, -0.0059285, 0.1603, 8.83], y - 1700.0)),
        (1860.0, np.polyval([0.000000000875, -0.0000001699, 0.0000121272, -0.00037436, 0.0041116, 0.0068612,
                             -0.332447, 13.72], y - 1800.0)),
        (1900.0, np.polyval([1.0 / 233174.0, -0.0004473624, 0.01680668, -0.251754, 0.5737, 7.62], y - 1860.0)),
        (1920.0, np.polyval([-0.000197, 0.0061966, -0.0598939, 1.494119, -2.79], y - 1900.0)),
        (1941.0, np.polyval([0.0020936, -0.076100, 0.84493, 21.20], y - 1920.0)),
        (1961.0, np.polyval([1.0 / 2547.0, -1.0 / 233.0, 0.407, 29.07], y - 1950.0)),
        (1986.0, np.polyval([-1.0 / 718.0, -1.0 / 260.0, 1.067, 45.45], y - 1975.0)),
        (2005.0, np.polyval([0.00002373599, 0.000651814, 0.0017275, -0.060374, 0.3345, 63.86], y - 2000.0)),
        (2050.0, np.polyval([0.005589, 0.32217, 62.92], y - 2000.0)),
        (2150.0, -20.0 + 32.0 * u_long**2 - 0.5628 * (2150.0 - y)),
        (np.inf, -20.0 + 32.0 * u_long**2),
    ]
    done = np.zeros(y.shape, dtype=bool)
    for upper, value in pieces:
        sel = ~done & (y < upper)
        out[sel] = np.asarray(value)[sel] if np.ndim(value) else value
        done |= sel
    return out


# ------------------------------------------------------------------------------------------
# The algorithm, step by step (degrees, as the report)


def _series(tables: tuple[np.ndarray, ...], jme: np.ndarray) -> np.ndarray:
    """Sum_i (Sum_k A_k cos(B_k + C_k JME)) JME^i / 1e8: a VSOP87 series (step 3.2.1-3.2.4)."""
    x = jme[..., None]
    total = np.zeros_like(jme)
    for i, t in enumerate(tables):
        total = total + np.sum(t[:, 0] * np.cos(t[:, 1] + t[:, 2] * x), axis=-1) * jme**i
    return total / 1e8


def heliocentric_lbr(jme) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Earth's heliocentric longitude L and latitude B (deg, L in [0, 360)) and radius R (AU). 3.2."""
    jme = np.asarray(jme, dtype=np.float64)
    lon = np.mod(np.degrees(_series((_L0, _L1, _L2, _L3, _L4, _L5), jme)), 360.0)
    lat = np.degrees(_series((_B0, _B1), jme))
    radius = _series((_R0, _R1, _R2, _R3, _R4), jme)
    return lon, lat, radius


def nutation(jce) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nutation in longitude and obliquity (deg) and the arguments X0..X4 (deg, shape (..., 5)). 3.4."""
    t = np.asarray(jce, dtype=np.float64)
    x = np.stack([
        297.85036 + 445267.111480 * t - 0.0019142 * t**2 + t**3 / 189474.0,  # Moon's mean elongation
        357.52772 + 35999.050340 * t - 0.0001603 * t**2 - t**3 / 300000.0,  # Sun's mean anomaly
        134.96298 + 477198.867398 * t + 0.0086972 * t**2 + t**3 / 56250.0,  # Moon's mean anomaly
        93.27191 + 483202.017538 * t - 0.0036825 * t**2 + t**3 / 327270.0,  # Moon's argument of latitude
        125.04452 - 1934.136261 * t + 0.0020708 * t**2 + t**3 / 450000.0,  # Moon's ascending node
    ], axis=-1)
    arg = np.radians(x @ _NUT_Y.T)
    tt = t[..., None]
    d_psi = np.sum((_NUT_ABCD[:, 0] + _NUT_ABCD[:, 1] * tt) * np.sin(arg), axis=-1) / 36_000_000.0
    d_eps = np.sum((_NUT_ABCD[:, 2] + _NUT_ABCD[:, 3] * tt) * np.cos(arg), axis=-1) / 36_000_000.0
    return d_psi, d_eps, x


def mean_obliquity_arcsec(jme) -> np.ndarray:
    """Mean obliquity of the ecliptic (arc seconds), Laskar's polynomial in U = JME / 10. 3.5.1."""
    u = np.asarray(jme, dtype=np.float64) / 10.0
    return np.polyval([2.45, 5.79, 27.87, 7.12, -39.05, -249.67, -51.38, 1999.25, -1.55, -4680.93, 84381.448], u)


class RangeError(ValidationError):
    """An input outside its range. ``index``: where the first such value is in its (flattened)
    array, None for a scalar, so that a caller with one value per row (a CSV) can name the row."""

    def __init__(self, message: str, index: int | None) -> None:
        super().__init__(message)
        self.index = index


def _first(bad: np.ndarray) -> int | None:
    return int(np.flatnonzero(bad)[0]) if bad.ndim else None


def _check_range(name: str, value, lo: float, hi: float, unit: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    bad = ~((arr >= lo) & (arr <= hi))  # also catches NaN
    if np.any(bad):
        first = arr[bad].flat[0] if arr.ndim else float(arr)
        raise RangeError(f"{name}: expected within [{lo:g}, {hi:g}] {unit}, got {first}", _first(bad))
    return arr


def spa_steps(utc, lat_deg, lon_deg, elevation_m=0.0, pressure_hpa=DEFAULT_PRESSURE_HPA,
              temperature_c=DEFAULT_TEMPERATURE_C, delta_t_s=None,
              refraction_deg=DEFAULT_REFRACTION_DEG) -> dict[str, np.ndarray]:
    """Every intermediate of the SPA by the report's names (degrees), broadcast over all inputs.

    Keys as in the report's worked example: JD, JDE, JC, JCE, JME, L, B, R, Theta, beta, X0..X4,
    dPsi, dEpsilon, epsilon0 (arcsec), epsilon, dTau, lamd, v0, v, alpha, delta, H, xi, dAlpha,
    alpha_prime, delta_prime, H_prime, e0, de, e, theta (zenith), Gamma, Phi (azimuth, clockwise
    from north). :func:`sun_position` is the interface; this is for checking and debugging.
    """
    lat = _check_range("latitude", lat_deg, -90.0, 90.0, "deg")
    lon = _check_range("longitude", lon_deg, -180.0, 360.0, "deg")
    elev = _check_range("elevation", elevation_m, *ELEVATION_RANGE_M, "m")
    pressure = _check_range("pressure", pressure_hpa, 1e-6, 5000.0, "hPa")
    temp = _check_range("temperature", temperature_c, -273.0, 6000.0, "C")
    refraction = _check_range("refraction", refraction_deg, -5.0, 5.0, "deg")
    jd = julian_day(utc)
    if delta_t_s is None:
        dt_s = delta_t_approx_s(2000.0 + (jd - _J2000) / 365.25)
    else:
        dt_s = _check_range("delta_t", delta_t_s, -8000.0, 8000.0, "s")
    outside = ~((jd >= _JD_MIN) & (jd <= _JD_MAX))
    if np.any(outside):
        # Said as a time, not a Julian day: at a limit, JD's decimals would hide which side it is on.
        first_s = round((float(np.ravel(jd)[np.ravel(outside)][0]) - _JD_UNIX_EPOCH) * 86_400.0)
        raise RangeError(f"time: expected within the years -2000..6000 (the algorithm's range), got "
                         f"{np.datetime64(first_s, 's')}Z", _first(outside))

    s: dict[str, np.ndarray] = {"JD": jd}
    # 3.1: Julian ephemeris day and centuries/millennia from J2000.
    s["JDE"] = jd + dt_s / 86400.0
    s["JC"] = (jd - _J2000) / 36525.0
    s["JCE"] = (s["JDE"] - _J2000) / 36525.0
    s["JME"] = s["JCE"] / 10.0
    # 3.2-3.3: Earth heliocentric, then the Sun's geocentric longitude and latitude.
    s["L"], s["B"], s["R"] = heliocentric_lbr(s["JME"])
    s["Theta"] = np.mod(s["L"] + 180.0, 360.0)
    s["beta"] = -s["B"]
    # 3.4-3.5: nutation, obliquity.
    s["dPsi"], s["dEpsilon"], x = nutation(s["JCE"])
    for i in range(5):
        s[f"X{i}"] = x[..., i]
    s["epsilon0"] = mean_obliquity_arcsec(s["JME"])
    s["epsilon"] = s["epsilon0"] / 3600.0 + s["dEpsilon"]
    # 3.6-3.7: aberration, apparent longitude.
    s["dTau"] = -20.4898 / (3600.0 * s["R"])
    s["lamd"] = s["Theta"] + s["dPsi"] + s["dTau"]
    # 3.8: apparent sidereal time at Greenwich.
    s["v0"] = np.mod(280.46061837 + 360.98564736629 * (jd - _J2000) + 0.000387933 * s["JC"] ** 2
                     - s["JC"] ** 3 / 38710000.0, 360.0)
    eps_r = np.radians(s["epsilon"])
    s["v"] = s["v0"] + s["dPsi"] * np.cos(eps_r)
    # 3.9-3.10: geocentric right ascension and declination.
    lam_r, beta_r = np.radians(s["lamd"]), np.radians(s["beta"])
    s["alpha"] = np.mod(np.degrees(np.arctan2(np.sin(lam_r) * np.cos(eps_r) - np.tan(beta_r) * np.sin(eps_r),
                                              np.cos(lam_r))), 360.0)
    delta_r = np.arcsin(np.sin(beta_r) * np.cos(eps_r) + np.cos(beta_r) * np.sin(eps_r) * np.sin(lam_r))
    s["delta"] = np.degrees(delta_r)
    # 3.11: local hour angle (longitude positive east).
    s["H"] = np.mod(s["v"] + lon - s["alpha"], 360.0)
    # 3.12: parallax: topocentric right ascension, declination and hour angle.
    s["xi"] = 8.794 / (3600.0 * s["R"])
    lat_r, xi_r, h_r = np.radians(lat), np.radians(s["xi"]), np.radians(s["H"])
    u = np.arctan(_POLAR_RATIO * np.tan(lat_r))
    px = np.cos(u) + elev / _EARTH_RADIUS_M * np.cos(lat_r)
    py = _POLAR_RATIO * np.sin(u) + elev / _EARTH_RADIUS_M * np.sin(lat_r)
    denom = np.cos(delta_r) - px * np.sin(xi_r) * np.cos(h_r)
    d_alpha_r = np.arctan2(-px * np.sin(xi_r) * np.sin(h_r), denom)
    s["dAlpha"] = np.degrees(d_alpha_r)
    s["alpha_prime"] = s["alpha"] + s["dAlpha"]
    delta_p_r = np.arctan2((np.sin(delta_r) - py * np.sin(xi_r)) * np.cos(d_alpha_r), denom)
    s["delta_prime"] = np.degrees(delta_p_r)
    s["H_prime"] = s["H"] - s["dAlpha"]
    hp_r = np.radians(s["H_prime"])
    # 3.14: topocentric elevation, refraction only while the sun's upper limb can be above the horizon.
    s["e0"] = np.degrees(np.arcsin(np.sin(lat_r) * np.sin(delta_p_r) + np.cos(lat_r) * np.cos(delta_p_r)
                                   * np.cos(hp_r)))
    up = s["e0"] >= -(SUN_RADIUS_DEG + refraction)
    e0_up = np.where(up, s["e0"], 0.0)  # keep tan() away from its pole where the term is unused
    bennett = 1.02 / (60.0 * np.tan(np.radians(e0_up + 10.3 / (e0_up + 5.11))))  # Bennett's formula, deg
    de = (pressure / 1010.0) * (283.0 / (273.0 + temp)) * bennett
    s["de"] = np.where(up, de, 0.0)
    s["e"] = s["e0"] + s["de"]
    s["theta"] = 90.0 - s["e"]
    # 3.15: azimuth, westward from south (astronomers'), then clockwise from north.
    s["Gamma"] = np.mod(np.degrees(np.arctan2(np.sin(hp_r), np.cos(hp_r) * np.sin(lat_r)
                                              - np.tan(delta_p_r) * np.cos(lat_r))), 360.0)
    s["Phi"] = np.mod(s["Gamma"] + 180.0, 360.0)
    s["delta_t"] = np.broadcast_to(dt_s, np.shape(jd)) if np.ndim(dt_s) == 0 else dt_s
    return s


# ------------------------------------------------------------------------------------------
# Interface


@dataclass(frozen=True, eq=False)
class SunPosition:
    """Where the sun is seen from a place at a time (topocentric). Arrays broadcast from the inputs.

    ``elevation_rad`` is the apparent (refracted) elevation, where the sun is seen and so where a
    camera sees it; ``elevation_geometric_rad`` is without refraction. ``azimuth_rad`` is clockwise
    from true north in [0, 2 pi); ``enu`` (..., 3) is the apparent direction as an ENU unit vector.
    """

    zenith_rad: np.ndarray
    azimuth_rad: np.ndarray
    elevation_rad: np.ndarray
    elevation_geometric_rad: np.ndarray
    enu: np.ndarray
    delta_t_s: np.ndarray


def sun_position(utc, lat_deg, lon_deg, elevation_m=0.0, *, pressure_hpa=DEFAULT_PRESSURE_HPA,
                 temperature_c=DEFAULT_TEMPERATURE_C, delta_t_s=None,
                 refraction_deg=DEFAULT_REFRACTION_DEG) -> SunPosition:
    """The sun's topocentric position by NREL's SPA; every argument broadcasts.

    ``utc``: integer ns since the Unix epoch (int or int64 array) or numpy datetime64 (any unit);
    ``lat_deg`` north positive, ``lon_deg`` east positive, ``elevation_m`` above the ellipsoid (or
    sea level: the difference is far below the algorithm's precision); ``pressure_hpa`` (= mbar)
    and ``temperature_c`` for refraction; ``delta_t_s`` = TT - UT1 (None: the Espenak & Meeus
    approximation); ``refraction_deg``: refraction at sunrise/sunset. Raises
    :class:`rig.errors.ValidationError` with a one-line message for out-of-range input.
    """
    s = spa_steps(utc, lat_deg, lon_deg, elevation_m, pressure_hpa, temperature_c, delta_t_s, refraction_deg)
    az = np.radians(s["Phi"])
    el = np.radians(s["e"])
    return SunPosition(
        zenith_rad=np.radians(s["theta"]),
        azimuth_rad=az,
        elevation_rad=el,
        elevation_geometric_rad=np.radians(s["e0"]),
        enu=enu_from_az_el(az, el),
        delta_t_s=np.asarray(s["delta_t"]),
    )


def standard_pressure_hpa(altitude_m) -> np.ndarray:
    """Pressure of the ICAO standard atmosphere at an altitude: a refraction input better than a
    constant when only the altitude is known (1013 hPa at sea level, 899 at 1 km)."""
    h = np.clip(np.asarray(altitude_m, dtype=np.float64), -500.0, 11_000.0)
    return DEFAULT_PRESSURE_HPA * (1.0 - 2.25577e-5 * h) ** 5.25588


# ISO 8601: a year of 4 digits, or an expanded one (a sign and 4 to 6 digits: -1000, +002011), as
# the algorithm's range -2000..6000 needs; year 0 is 1 BC, as numpy and the SPA count.
_ISO_RE = re.compile(
    r"^(?P<year>[+-]\d{4,6}|\d{4})-(?P<date>\d{2}-\d{2})"
    r"(?:[T ](?P<hm>\d{2}:\d{2})(?::(?P<second>\d{2})(?P<fraction>\.\d{1,9})?)?)?"
    r"(?P<tz>Z|[+-]\d{2}(?::?\d{2})?)?$"
)
_NS_LIMIT = ("time: {what} is written to the nanosecond (7 to 9 decimals), which numpy holds only within the "
             f"years {NS_YEARS}; write at most 6 decimals")


def parse_utc_iso(text: str) -> np.datetime64:
    """ISO 8601 time -> numpy datetime64 in UTC, to the precision written (up to ns).

    ``2003-10-17T19:30:30Z``, ``2003-10-17 12:30:30-07:00``, ``2011-09-26T11:02:25.961661696``,
    ``2003-10-17`` (midnight), ``-1000-01-01T12:00Z`` (a signed year). A time without an offset is
    taken as UTC. Raises :class:`ValidationError` with a one-line message.
    """
    shown = repr(text.strip()[:40])
    m = _ISO_RE.match(text.strip())
    if not m:
        raise ValidationError(f"time: expected ISO 8601 like 2003-10-17T19:30:30Z (or a signed year: "
                              f"-1000-01-01T00:00Z), got {shown}")
    year = int(m.group("year"))
    base = (f"{year:04d}" if year >= 0 else f"-{-year:04d}") + "-" + m.group("date")
    # A leap second (23:59:60, as a GNSS receiver reports it) is the next minute's first second,
    # as the NMEA decoder counts it: numpy's time scale, like POSIX, has no second 60.
    leap = m.group("second") == "60"
    if m.group("hm"):
        base += "T" + m.group("hm")
        if m.group("second"):
            base += ":" + ("59" if leap else m.group("second")) + (m.group("fraction") or "")
    try:
        t = np.datetime64(base)
    except ValueError:
        raise ValidationError(f"time: not a valid date/time: {shown}; check the month, day, hour, "
                              "minute and second") from None
    ns = np.datetime_data(t.dtype)[0] == "ns"
    if ns and int(t.astype("datetime64[Y]").astype(np.int64)) + 1970 != year:  # numpy wrapped it round
        raise ValidationError(_NS_LIMIT.format(what=shown))
    if leap:
        t = t + np.timedelta64(1, "s")
    tz = m.group("tz")
    if tz and tz != "Z":
        sign = -1 if tz[0] == "-" else 1
        digits = tz[1:].replace(":", "")
        hours, minutes = int(digits[:2]), int(digits[2:]) if len(digits) > 2 else 0
        if hours > 14 or minutes > 59:
            raise ValidationError(f"time: UTC offset {tz} is not one; expected within -14:00..+14:00")
        minutes += 60 * hours
        local = t
        t = t - np.timedelta64(sign * minutes, "m")  # local = UTC + offset
        if minutes and (t < local) != (sign > 0):  # past the ns limit, the shift wrapped round
            raise ValidationError(_NS_LIMIT.format(what=shown))
    return t


def utc_column(times: Sequence[np.datetime64], places: Sequence[str] | None = None) -> np.ndarray:
    """Times parsed one by one as one array, in the finest unit written (numpy's promotion). A
    time to the ns makes the whole column ns, which holds only the years 1678..2262, and numpy
    wraps a time outside them round without a word: that time is a :class:`RangeError` whose
    ``index`` is its place in ``times``. ``places``: what a message calls each time (a CSV's
    "line 2"; default "time 1", ...)."""
    column = np.array(times)
    if not column.size or np.datetime_data(column.dtype)[0] != "ns":
        return column
    lo, hi = UTC_NS_MIN // 10**9 + 1, UTC_NS_MAX // 10**9 - 1  # whole seconds, safely inside
    seconds = np.array([t.astype("datetime64[s]").astype(np.int64) for t in times])
    outside = (seconds < lo) | (seconds > hi)
    if not np.any(outside):
        return column
    i = int(np.flatnonzero(outside)[0])
    fine = next(j for j, t in enumerate(times) if np.datetime_data(t.dtype)[0] == "ns")
    place = places[fine] if places is not None else f"time {fine + 1}"
    raise RangeError(f"time: {times[i].astype('datetime64[s]')} is outside the years {NS_YEARS} that times written "
                     f"to the nanosecond ({place}) limit the column to; write those with at most 6 decimals", i)
