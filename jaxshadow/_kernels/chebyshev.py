r"""Chebyshev fits and their analytic integrals (Poulin 1993, §3.2.1.2, fig. 3.9; Clenshaw).

The Phong integrals of the specular kernels are one-dimensional integrals of smooth, peaked,
monotone-on-each-side functions such as $\cos^n\phi$. Poulin approximates $\cos^n\phi$ on
$[0, x_M]$ by a Chebyshev polynomial fitted at the Chebyshev(-Lobatto) nodes and integrates the
polynomial analytically; beyond the *cut-off angle* $x_M$ the function is taken as zero.

Everything here works on JAX arrays with the exponent $n$ an ordinary (differentiable) array:
the fit is a constant matrix (built in NumPy at trace time from the static degree) applied to
samples of the integrand, so $\partial/\partial n$ of the approximation is exact.

**Cut-off angle.** The thesis prints $x_M = (\cos^{-1}\epsilon)^{1/n}$, which is wrong (it is
not even an angle where $\cos^n$ is small: for $n \to \infty$ it tends to 1 rad). The intended
value solves $\cos^n x_M = \epsilon$, i.e. $x_M = \arccos(\epsilon^{1/n})$, see `cutoff_angle`.

**Fig. 3.9.** The second loop of the pseudo-code multiplies each coefficient by
`Cheby(i, x_cheby)` with the stale loop value `x_cheby = cos(pi) = -1`, i.e. by $(-1)^i$, which
mirrors the polynomial ($t \to -t$). The coefficients of the interpolant are just
$a_i = b_i$ (halved for $i = 0, D$); `poulin_cos_power_coefficients` does that.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Float
from numpy.polynomial import chebyshev as npcheb

# --------------------------------------------------------------------------------------
# Constant matrices (NumPy, float64, cached per static degree)
# --------------------------------------------------------------------------------------


@functools.cache
def lobatto_nodes(degree: int) -> np.ndarray:
    """Chebyshev-Lobatto nodes $t_k = \\cos(k\\pi/D)$, $k = 0..D$ (Poulin's `x_cheby`)."""
    if degree < 1:
        raise ValueError(f"Chebyshev degree must be >= 1, got {degree}.")
    t = np.cos(np.arange(degree + 1) * np.pi / degree)
    t[np.abs(t) < 1e-15] = 0.0
    return t


@functools.cache
def _fit_matrix(degree: int) -> np.ndarray:
    """`(D+1, D+1)`: samples at the Lobatto nodes -> Chebyshev coefficients of the interpolant."""
    d = degree
    k = np.arange(d + 1)
    w = np.ones(d + 1)
    w[0] = w[-1] = 0.5
    m = (2.0 / d) * np.cos(np.outer(k, k) * np.pi / d) * w[None, :]
    m[0] *= 0.5
    m[-1] *= 0.5
    return m


@functools.cache
def _antiderivative_matrix(degree: int, lbnd: float) -> np.ndarray:
    """`(D+2, D+1)`: Chebyshev coefficients -> coefficients of the antiderivative vanishing at `lbnd`."""
    eye = np.eye(degree + 1)
    return np.stack([npcheb.chebint(eye[i], lbnd=lbnd) for i in range(degree + 1)], axis=1)


@functools.cache
def _interval_matrix(degree: int) -> np.ndarray:
    """Samples at the Lobatto nodes -> antiderivative (from $t = -1$) of the interpolant."""
    return _antiderivative_matrix(degree, -1.0) @ _fit_matrix(degree)


@functools.cache
def even_nodes(degree: int) -> np.ndarray:
    """Non-negative half of the degree-`2D` Lobatto grid: $t_j = \\cos(j\\pi/2D)$, $j = 0..D$."""
    return lobatto_nodes(2 * degree)[: degree + 1]


@functools.cache
def _even_matrix(degree: int) -> np.ndarray:
    """Samples of an even function at `even_nodes(D)` -> odd antiderivative (zero at 0).

    The interpolant has degree `2D` on $[-1, 1]$ (only even terms) but needs only `D + 1`
    samples, thanks to the symmetry.
    """
    d2 = 2 * degree
    fold = np.zeros((d2 + 1, degree + 1))
    for j in range(d2 + 1):
        fold[j, min(j, d2 - j)] = 1.0
    return _antiderivative_matrix(d2, 0.0) @ _fit_matrix(d2) @ fold


# --------------------------------------------------------------------------------------
# JAX side
# --------------------------------------------------------------------------------------


def clenshaw(coeffs: Float[Array, " m"], t: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
    r"""$\sum_i c_i T_i(t)$ by Clenshaw's recurrence (`t` of any shape).

    A `lax.scan` over the coefficients rather than an unrolled loop: the traced graph (and XLA's
    compile time, notably of second derivatives) stays small at any degree.
    """

    def step(carry, c):
        b1, b2 = carry
        return (c + 2.0 * t * b1 - b2, b1), None

    zero = jnp.zeros_like(t)
    (b1, b2), _ = lax.scan(step, (zero, zero), coeffs[:0:-1])
    return coeffs[0] + t * b1 - b2


def cutoff_angle(
    exponent: Float[Array, ""], tol: float, start: Float[Array, ""] | None = None
) -> Float[Array, ""]:
    r"""Cut-off angle $x_M$ with $\cos^n x_M = \epsilon$: $x_M = \arccos(\epsilon^{1/n})$.

    Poulin (§3.2.1.2) prints $x_M = (\cos^{-1}\epsilon)^{1/n}$; that is a typo for the value
    used here. Evaluated as $\operatorname{atan2}(\sqrt{1 - \epsilon^{2/n}}, \epsilon^{1/n})$
    with `expm1`, accurate (and smooth in $n$) up to $n = 10^6$ and beyond, where the plain
    `arccos` of a number next to 1 loses all its digits.

    With `start` $= u_0 \in [0, \pi/2]$ the cut-off is relative to the value there:
    $\cos^n x_M = \epsilon \cos^n u_0$ (used for an interval that starts in the tail).

    **Arguments:** `exponent` $n > 0$ (array), `tol` $\epsilon \in (0, 1)$ (static float),
    `start` optional array.
    """
    if not 0.0 < tol < 1.0:
        raise ValueError(f"cut-off tolerance must lie in (0, 1), got {tol!r}.")
    log_tol = float(np.log(tol))
    c = jnp.exp(log_tol / exponent)
    s2 = -jnp.expm1(2.0 * log_tol / exponent)
    if start is not None:
        # 1 - c^2 cos^2 u0 = (1 - c^2) + c^2 sin^2 u0, without cancellation.
        s2 = s2 + c * c * jnp.sin(start) ** 2
        c = c * jnp.cos(start)
    return jnp.arctan2(jnp.sqrt(s2), c)


def poulin_cos_power_coefficients(
    exponent: Float[Array, ""], x_max: Float[Array, ""], degree: int
) -> Float[Array, " degree_plus_1"]:
    r"""Poulin's fig. 3.9: Chebyshev coefficients of $\cos^n x$ on $[0, x_M]$.

    The fit variable is $t \in [-1, 1]$ with $x = x_M (t + 1)/2$; samples at the
    Chebyshev-Lobatto nodes. (With the stale $(-1)^i$ factor of the printed pseudo-code dropped,
    see the module docstring.)
    """
    t = jnp.asarray(lobatto_nodes(degree), dtype=x_max.dtype)
    x = x_max * (t + 1.0) / 2.0
    vals = jnp.exp(exponent * jnp.log(jnp.cos(x)))
    return jnp.asarray(_fit_matrix(degree), dtype=vals.dtype) @ vals


def poulin_cos_power_integral(
    lo: Float[Array, ""], hi: Float[Array, ""], exponent: Float[Array, ""], degree: int, tol: float
) -> Float[Array, ""]:
    r"""$\int_{lo}^{hi} \cos^n\phi\,d\phi$ with Poulin's half-range fit on $[0, x_M]$.

    Limits in $[-\pi/2, \pi/2]$; an interval straddling 0 uses the symmetry of $\cos^n$, the
    parts beyond $\pm x_M$ count as zero. Kept as the reference point of the benchmark (Poulin's
    degree 6, $\epsilon = 1/250$); the kernels use `even_fit_integral`.
    """
    x_max = cutoff_angle(exponent, tol)
    coeffs = poulin_cos_power_coefficients(exponent, x_max, degree)
    anti = jnp.asarray(_antiderivative_matrix(degree, -1.0), dtype=coeffs.dtype) @ coeffs

    def prim(x):
        ax = jnp.minimum(jnp.abs(x), x_max)
        return jnp.sign(x) * (x_max / 2.0) * clenshaw(anti, 2.0 * ax / x_max - 1.0)

    both = prim(jnp.stack([lo, hi]))
    return both[1] - both[0]


def even_fit_integral(
    f: Callable[[Array], Array],
    half_width: Float[Array, ""],
    lo: Float[Array, ""],
    hi: Float[Array, ""],
    degree: int,
) -> Float[Array, ""]:
    r"""$\int_{lo}^{hi} f$ for an even $f$, from one Chebyshev fit of $f$ on $[-X, X]$.

    `f` is sampled at the `D + 1` points $X \cos(j\pi/2D)$ (the non-negative half of the
    degree-`2D` Lobatto grid), the even degree-`2D` interpolant is integrated analytically and
    its (odd) antiderivative evaluated by Clenshaw at `lo / X`, `hi / X`. Requires
    $-X \le lo \le hi \le X$ (clip first) and $X > 0$. `f` must accept an array of nodes.
    """
    t = jnp.asarray(even_nodes(degree), dtype=half_width.dtype)
    vals = f(half_width * t)
    anti = jnp.asarray(_even_matrix(degree), dtype=vals.dtype) @ vals
    prim = clenshaw(anti, jnp.stack([lo, hi]) / half_width)
    return half_width * (prim[1] - prim[0])


def interval_fit_integral(
    f: Callable[[Array], Array], lo: Float[Array, ""], hi: Float[Array, ""], degree: int
) -> Float[Array, ""]:
    r"""$\int_{lo}^{hi} f$ from the degree-`D` Chebyshev fit of $f$ on $[lo, hi]$ itself.

    (Clenshaw-Curtis: `D + 1` samples at the Lobatto nodes of the interval.) Exactly 0 with a
    zero gradient for an empty interval `lo == hi`.
    """
    t = jnp.asarray(lobatto_nodes(degree), dtype=lo.dtype)
    half = (hi - lo) / 2.0
    vals = f((lo + hi) / 2.0 + half * t)
    # The antiderivative from -1 evaluated at t = 1 is the sum of its coefficients (T_i(1) = 1).
    weights = np.sum(_interval_matrix(degree), axis=0)
    return half * (jnp.asarray(weights, dtype=vals.dtype) @ vals)
