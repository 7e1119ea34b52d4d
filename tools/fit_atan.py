import numpy as np, mpmath
mpmath.mp.dps = 40
T8 = float(mpmath.tan(mpmath.pi/8))
zmax = T8*T8
def fit(deg):
    # Chebyshev interpolation of g(z) = atan(sqrt z)/sqrt z on [0, zmax] with mpmath values
    k = np.arange(deg+1)
    xs = np.cos((2*k+1)*np.pi/(2*(deg+1)))
    z = (xs+1)/2*zmax
    g = [float(mpmath.atan(mpmath.sqrt(mpmath.mpf(zz)))/mpmath.sqrt(mpmath.mpf(zz))) if zz>0 else 1.0 for zz in z]
    # solve Vandermonde in z (monomial) directly with high precision via mpmath
    A = mpmath.matrix([[mpmath.mpf(zz)**j for j in range(deg+1)] for zz in z])
    b = mpmath.matrix([mpmath.atan(mpmath.sqrt(mpmath.mpf(zz)))/mpmath.sqrt(mpmath.mpf(zz)) for zz in z])
    c = mpmath.lu_solve(A, b)
    return [float(ci) for ci in c]
for deg in [4, 10]:
    c = fit(deg)
    zz = np.linspace(0, zmax, 20001)
    t = np.sqrt(zz)
    p = np.polyval(c[::-1], zz)*t
    err = np.abs(p - np.arctan(t)).max()
    print(deg, err)
    if deg in (4, 10): print(repr(c))
