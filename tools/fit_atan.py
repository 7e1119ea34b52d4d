"""Fit the polynomial of `jaxshadow._core.misc.arctan2`: atan(t) = t P(t^2) on |t| <= tan(pi/8).

Interpolation at Chebyshev nodes in z = t^2, solved in 40-digit arithmetic (mpmath); prints
the max error on a fine grid and the coefficients for degree 4 (float32) and 10 (float64).
Run: `.venv/bin/python tools/fit_atan.py`.
"""

import mpmath
import numpy as np

mpmath.mp.dps = 40
T8 = float(mpmath.tan(mpmath.pi / 8))
ZMAX = T8 * T8


def fit(deg: int) -> list[float]:
    k = np.arange(deg + 1)
    z = (np.cos((2 * k + 1) * np.pi / (2 * (deg + 1))) + 1) / 2 * ZMAX
    a = mpmath.matrix([[mpmath.mpf(zz) ** j for j in range(deg + 1)] for zz in z])
    b = mpmath.matrix([mpmath.atan(mpmath.sqrt(mpmath.mpf(zz))) / mpmath.sqrt(mpmath.mpf(zz)) for zz in z])
    return [float(ci) for ci in mpmath.lu_solve(a, b)]


if __name__ == "__main__":
    for deg in (4, 10):
        c = fit(deg)
        zz = np.linspace(0, ZMAX, 20001)
        t = np.sqrt(zz)
        err = np.abs(np.polyval(c[::-1], zz) * t - np.arctan(t)).max()
        print(deg, err)
        print(repr(c))
