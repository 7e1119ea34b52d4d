"""Small numerical helpers shared by every kernel (NaN-safe forms of common operations)."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float


def fusible(x: Array) -> Array:
    r"""`x`, unchanged to the bit, marked so that XLA:CPU fuses the expensive op that made it.

    XLA:CPU never fuses an "expensive" producer (divide, sqrt, rsqrt, exp, log, ...) into a
    consumer loop that reads it more than once per element ("fusion is not profitable",
    `CpuInstructionFusion::ShouldFuse`): the result is written to memory and read back, and its
    consumers split into separate loops. `reduce_precision` to the dtype's own exponent and
    mantissa widths is an exact identity (every value, denormals, infinities and NaN included;
    its derivative is the identity too) that XLA counts as cheap, so wrapping an expensive
    result in it lets the whole computation around it fuse into one loop. In the quad form
    factor this took the compiled kernel from 48 fused loops to 4 and ~8x less time at 10^6
    points (commit 34489f5). It only changes how XLA schedules the work, never a value.
    """
    fi = jnp.finfo(x.dtype)
    return jax.lax.reduce_precision(x, exponent_bits=fi.nexp, mantissa_bits=fi.nmant)


def max_abs3(x: Array, y: Array, z: Array) -> Array:
    """`max(|x|, |y|, |z|)` of three components (elementwise): the scale of a vector."""
    return jnp.maximum(jnp.maximum(jnp.abs(x), jnp.abs(y)), jnp.abs(z))


_BIG = 2.0**64


def divide_by_scale(x: Array, s: Array) -> Array:
    """`x / s` for a positive scale `s` (e.g. the largest component of `x`), exact where `x / s`
    is. XLA:CPU divides by multiplying with the reciprocal, and flushes subnormals to zero: for
    `s` above 2^126 (float32; 2^1022 in float64) `1/s` is subnormal and every quotient came
    out 0. Both are first multiplied by an exact power of two that brings `s` into
    [2^-64, 2^64]."""
    f = jnp.where(s > _BIG, 1.0 / _BIG, jnp.where(s < 1.0 / _BIG, _BIG, 1.0)).astype(x.dtype)
    return (x * f) / (s * f)


def _scaled(x: Float[Array, "... 3"], axis: int) -> tuple[Array, Array, Array]:
    """`(x / s, s, s > 0)` with `s = max |x_i|` along `axis` (keepdims); `x` itself where `s = 0`.

    Dividing by the largest component before squaring keeps the sum of squares in `[1, 3]`:
    no overflow (|x| up to the largest float) and no underflow (|x| down to the smallest normal
    number) in either dtype, where `sum(x * x)` overflows above `sqrt(max)` (1.8e19 in float32,
    1.3e154 in float64) and vanishes below `sqrt(tiny)`. `s` gets no gradient: what is formed
    from `x / s` below is invariant under the scaling (or scales with `s`, put back outside)."""
    s = jax.lax.stop_gradient(jnp.max(jnp.abs(x), axis=axis, keepdims=True))
    ok = s > 0
    return divide_by_scale(x, jnp.where(ok, s, 1.0)), s, ok


def safe_norm(x: Float[Array, "... 3"], axis: int = -1) -> Float[Array, "..."]:
    """Euclidean norm, scale-free (`_scaled`) and with a zero gradient at `x = 0` (double `where`)."""
    xs, s, _ = _scaled(x, axis)
    sq = jnp.sum(xs * xs, axis=axis, keepdims=True)
    ok = sq > 0
    safe_sq = jnp.where(ok, sq, 1.0)
    return jnp.squeeze(jnp.where(ok, s * fusible(jnp.sqrt(safe_sq)), 0.0), axis=axis)


def safe_normalize(x: Float[Array, "... 3"], axis: int = -1) -> Float[Array, "... 3"]:
    """`x / |x|` along `axis` (same shape as `x`), scale-free (`_scaled`: any length from the
    smallest normal number to the largest float), zero (with zero gradient) where `x = 0`.
    Public (`jaxshadow.safe_normalize`) for `inverse`, which uses jaxshadow's public names only
    (`PaintedTargets` normalises painted normals of any length with it).

    Example:
        ```python
        import jax.numpy as jnp
        import jaxshadow as js

        js.safe_normalize(jnp.array([[3e30, 4e30, 0.0], [0.0, 0.0, 0.0]]))   # [[0.6, 0.8, 0], [0, 0, 0]] (float32: |x|^2 overflows)
        ```
    """
    xs, _, _ = _scaled(x, axis)
    sq = jnp.sum(xs * xs, axis=axis, keepdims=True)
    ok = sq > 0
    safe_sq = jnp.where(ok, sq, 1.0)
    return jnp.where(ok, xs / fusible(jnp.sqrt(safe_sq)), 0.0)


def unit_rows(x: Float[ArrayLike, "N 3"]) -> Float[Array, "N 3"]:
    """`safe_normalize` of each row, written component by component: XLA:CPU fuses it into the
    kernel that reads the rows (a reduction over the length-3 axis is a separate loop).
    Scale-free: a normal of any length from the smallest subnormal to the largest float is
    normalised exactly (a plain sum of squares over- or underflows and gave a zero normal)."""

    def one(v: Array) -> Array:
        s = jax.lax.stop_gradient(max_abs3(v[0], v[1], v[2]))
        s = jnp.where(s > 0, s, 1.0)
        w = [fusible(divide_by_scale(v[i], s)) for i in range(3)]
        sq = w[0] * w[0] + w[1] * w[1] + w[2] * w[2]
        ok = sq > 0
        r = fusible(jnp.sqrt(jnp.where(ok, sq, 1.0)))
        return jnp.stack([jnp.where(ok, fusible(w[i] / r), 0.0) for i in range(3)])

    return jax.vmap(one)(x)


_unit_rows_jit = jax.jit(unit_rows)


def unit_rows_host(x: Float[ArrayLike, "N 3"]) -> np.ndarray:
    """`unit_rows` of concrete rows as a NumPy array, as one compiled call (bit for bit what a
    compiled program computes; op by op it took ~70 ms for 2e5 rows)."""
    return np.asarray(_unit_rows_jit(jnp.asarray(x)))


def safe_div(num: Array, den: Array, fallback: float | Array = 0.0) -> Array:
    """`num / den` where `den != 0`, else `fallback`, NaN-free in value and gradient."""
    ok = den != 0
    safe_den = jnp.where(ok, den, 1.0)
    return jnp.where(ok, fusible(num / safe_den), fallback)


def angle_over_sin(s2: Array | float, c: Array | float) -> Array:
    r"""$\theta / s$ for $\theta = \operatorname{atan2}(s, c)$, $s = \sqrt{s_2} \ge 0$.

    This is the factor that turns the (unnormalised) cross product of two edge vectors into
    Lambert's $\theta \hat\Gamma$ term. It is smooth in `s2` (an even function of $s$) when
    $c > 0$, so gradients stay finite when a receiver lies on the supporting line of an edge
    (outside the edge, where $\theta \to 0$). It is set to 0 in the one truly singular case,
    $s = 0,\ c \le 0$ (the receiver on the edge itself or at a vertex), which only happens for
    receivers in the emitter's plane, where the caller returns 0 anyway.
    """
    # One polynomial evaluation for both regimes: theta = base + u P(u^2) after the octant
    # reduction of `arctan2`. Angles below pi/8 (c > 0, s <= tan(pi/8) c) use u/s = 1/c and
    # u^2 = s2/c^2 -- no square root, smooth in s2 -- and the rest divide by s = sqrt(s2) > 0.
    tiny = (c > 0) & (s2 <= _TAN_PI_8 * _TAN_PI_8 * c * c)
    generic = (~tiny) & (s2 > 0)
    s2g = jnp.where(generic, s2, 1.0)
    cg = jnp.where(generic, c, 1.0)
    inv_s = fusible(jax.lax.rsqrt(s2g))
    sg = s2g * inv_s
    acg = jnp.abs(cg)
    # Select, not min/max: at a tie (45 degrees) min/max would split the derivative.
    swap = sg > acg
    t = fusible(jnp.where(swap, acg, sg) / jnp.where(swap, sg, acg))
    big = t > _TAN_PI_8
    u = jnp.where(big, fusible((t - 1.0) / (t + 1.0)), t)
    base = jnp.where(big, jnp.pi / 4, 0.0)
    base = jnp.where(swap, jnp.pi / 2 - base, base)
    u = jnp.where(swap, -u, u)
    neg = cg < 0
    base = jnp.where(neg, jnp.pi - base, base)
    u = jnp.where(neg, -u, u)
    ct = jnp.where(tiny, c, 1.0)
    inv_c = fusible(1.0 / ct)
    z = jnp.where(tiny, s2 * inv_c * inv_c, u * u)
    k = jnp.where(tiny, inv_c, u * inv_s)
    b = jnp.where(tiny, 0.0, base * inv_s)
    return jnp.where(tiny | generic, b + k * _atan_over_t(z), 0.0)


# Polynomial atan on |t| <= tan(pi/8): atan(t) = t * P(t^2), P fitted by Chebyshev-node
# interpolation in mpmath (tools/fit_atan.py). Max error 6.8e-9 (degree 4, float32) and
# 5.6e-17 (degree 10, float64), i.e. below one ulp of each dtype.
_ATAN_F32 = (0.9999999812646111, -0.33332785771924844, 0.19974082415507666, -0.13848490212269207, 0.07976291806794558)
_ATAN_F64 = (
    1.0,
    -0.3333333333332844,
    0.1999999999885511,
    -0.14285714180976467,
    0.11111106180455946,
    -0.09090773074808414,
    0.07689953496306857,
    -0.06640233930429408,
    0.056883492268090106,
    -0.04348052215716462,
    0.021135373157693243,
)
_TAN_PI_8 = 0.41421356237309503


def _atan_over_t(z: Array) -> Array:
    """`atan(t)/t` as a polynomial in `z = t^2`, for `0 <= z <= tan(pi/8)^2`."""
    coeffs = _ATAN_F32 if z.dtype == jnp.float32 else _ATAN_F64
    poly = jnp.full_like(z, coeffs[-1])
    for c in coeffs[-2::-1]:
        poly = poly * z + c
    return poly


@jax.custom_jvp
def arctan2(y: Array | float, x: Array | float) -> Array:
    r"""`atan2(y, x)` in $(-\pi, \pi]$, branch-free and vectorisable (XLA:CPU's own `atan2` is a
    scalar libm call, ~25 ns per float32 element, which dominated the form-factor kernel).

    Octant reduction to $t = \min/\max \in [0, 1]$, then $t \to (t-1)/(t+1)$ above
    $\tan(\pi/8)$, then an odd polynomial accurate to below one ulp of the input dtype. The JVP
    is the exact $(x\,dy - y\,dx)/(x^2 + y^2)$ (0 at the origin).
    """
    ax, ay = jnp.abs(x), jnp.abs(y)
    hi = jnp.maximum(ax, ay)
    lo = jnp.minimum(ax, ay)
    t = fusible(lo / jnp.where(hi > 0, hi, 1.0))
    big = t > _TAN_PI_8
    u = jnp.where(big, fusible((t - 1.0) / (t + 1.0)), t)
    r = u * _atan_over_t(u * u) + jnp.where(big, jnp.pi / 4, 0.0)
    r = jnp.where(ay > ax, jnp.pi / 2 - r, r)
    r = jnp.where(x < 0, jnp.pi - r, r)
    return jnp.where(y < 0, -r, r)


@arctan2.defjvp
def _arctan2_jvp(primals, tangents):
    y, x = primals
    dy, dx = tangents
    r2 = x * x + y * y
    ok = r2 > 0
    inv = jnp.where(ok, fusible(1.0 / jnp.where(ok, r2, 1.0)), 0.0)
    return arctan2(y, x), (x * dy - y * dx) * inv


#: Receivers per call of a batched kernel: bounds the memory of the kernels that do keep
#: `(N, ...)` intermediates (the shadow kernels' edge soups). The unoccluded kernels fuse into a
#: few loops (`fusible`) and run at the same rate from 2^14 to 2^24 rows per call.
CHUNK = 1 << 16


def map_chunks(fn, batched: tuple, *rest, chunk: int = CHUNK):
    """`fn(*batched, *rest)` over the leading axis in blocks of `chunk` rows (one call up to
    `2 chunk` rows). `fn`'s output may be a pytree: leaves with a leading axis are joined
    along it, scalar leaves (per-block flags) are stacked into `(blocks,)`.

    Only for concrete inputs called from Python (eager): one compiled call cuts the inputs into
    blocks (the last padded with copies of the first row, so every block has one shape and
    `fn` compiles once), the blocks are dispatched asynchronously, and one compiled call joins
    the results. Traced inputs (inside jit/grad/vmap) get a single call.
    """
    n = batched[0].shape[0]
    # Up to two blocks' worth, one call (fewer rows than a padded pair of blocks, one dispatch).
    if n <= 2 * chunk or any(isinstance(b, jax.core.Tracer) for b in batched):
        return fn(*batched, *rest)
    blocks = _split_blocks(tuple(batched), chunk)
    outs = [fn(*block, *rest) for block in zip(*blocks, strict=True)]
    return _join_blocks(outs, n)


@functools.partial(jax.jit, static_argnums=1)
def _split_blocks(batched: tuple, chunk: int) -> tuple:
    """Each array of `batched` cut into blocks of `chunk` rows, the last padded with its first row."""
    n = batched[0].shape[0]
    nb = -(-n // chunk)
    out = []
    for b in batched:
        pad = jnp.broadcast_to(b[:1], (nb * chunk - n,) + b.shape[1:])
        full = jnp.concatenate([b, pad])
        out.append([full[i * chunk : (i + 1) * chunk] for i in range(nb)])
    return tuple(out)


@functools.partial(jax.jit, static_argnums=1)
def _join_blocks(outs: list, n: int):
    """Inverse of `_split_blocks` for `fn`'s outputs (scalar leaves stacked)."""
    return jax.tree.map(lambda *xs: jnp.stack(xs) if xs[0].ndim == 0 else jnp.concatenate(xs)[:n], *outs)
