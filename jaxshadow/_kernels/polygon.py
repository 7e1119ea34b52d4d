r"""Point-to-polygon form factor: Lambert's contour sum (Campbell & Fussell eq. 11, Hottel).

$$F(p, n) = \frac{1}{2\pi} \sum_i \theta_i\, (n \cdot \hat\Gamma_i),\qquad
\hat\Gamma_i = \frac{(v_i - p) \times (v_{i+1} - p)}{|\cdot|},\quad
\theta_i = \angle(v_i - p, v_{i+1} - p)$$

over the edges of the visible region (here: the emitter clipped exactly to the receiver's
horizon). Campbell & Fussell write $\theta_i = \arccos(V_i \cdot V_{i+1})$; we use
`atan2(|a x b|, a . b)` (accurate at small and near-$\pi$ angles) and fold $\theta/\sin\theta$
into one smooth factor so that a receiver on the supporting line of an edge has finite
gradients. Their eq. 11 also writes $V_{i-P_r}$ as the vector *from the vertex to* $P_r$; only
the overall sign depends on that choice, and we fix it so that $F \ge 0$ for an emitter whose
vertices run counter-clockwise seen from its lit side (DESIGN.md).
"""

from __future__ import annotations

from typing import Any, no_type_check

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._core.geometry import (
    AnyArray,
    as_input,
    check_convex_polygon_cached,
    check_finite_leaves,
    check_points_normals,
    evaluate_checked,
    inputs_ok,
    is_concrete,
    on_lit_side,
)
from .._core.misc import angle_over_sin, arctan2, divide_by_scale, fusible, max_abs3, unit_rows


def _unit3(x: Array, y: Array, z: Array) -> tuple[Array, Array, Array]:
    r"""Componentwise `v / |v|` (zero, with zero gradient, for `v = 0`), scale-free.

    Divided by the largest component first (`_misc.divide_by_scale`, the scale without a
    gradient: `v / |v|` does not depend on it): the square never over- or underflows, and the
    derivative is formed as $(1/s) D\hat u(v/s)$, never as $1/|v|^3$ -- which overflowed in
    float32 for a receiver 1e-16 from a vertex and made a NaN gradient of a zero value."""
    s = jax.lax.stop_gradient(max_abs3(x, y, z))
    ok = s > 0
    s = jnp.where(ok, s, 1.0)
    x, y, z = (fusible(divide_by_scale(c, s)) for c in (x, y, z))
    sq = x * x + y * y + z * z
    inv = jnp.where(ok, fusible(jax.lax.rsqrt(jnp.where(ok, sq, 1.0))), 0.0)
    return x * inv, y * inv, z * inv


def _edge_term_c(A: tuple, B: tuple, n: tuple) -> Array:
    r"""$	heta\,(n\cdot\hat\Gamma)$ for edge vectors `A -> B` (seen from the origin), by components.

    Scale-free: `A`, `B` may have any length (callers pass unit vectors, which keeps float32
    far from under/overflow for tiny or huge scenes).
    """
    ax, ay, az = A
    bx, by, bz = B
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    s2 = cx * cx + cy * cy + cz * cz
    d = ax * bx + ay * by + az * bz
    return angle_over_sin(s2, d) * (n[0] * cx + n[1] * cy + n[2] * cz)


def edge_term(
    p: Float[Array, "3"], n: Float[Array, "3"], a: Float[Array, "3"], b: Float[Array, "3"]
) -> Float[Array, ""]:
    r"""Signed contribution $\theta\,(n \cdot \hat\Gamma)$ of the oriented edge `a -> b` seen from `p`.

    Exactly zero (with zero gradient) for a zero-length edge, for an edge whose line passes
    through `p` outside the edge, and (by convention) when `p` lies on the edge itself.
    """
    A = _unit3(a[0] - p[0], a[1] - p[1], a[2] - p[2])
    B = _unit3(b[0] - p[0], b[1] - p[1], b[2] - p[2])
    return _edge_term_c(A, B, (n[0], n[1], n[2]))


def contour_form_factor(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    starts: Float[Array, "e 3"],
    ends: Float[Array, "e 3"],
) -> Float[Array, ""]:
    r"""Form factor of the planar region bounded by an edge soup (Lambert's contour sum).

    The edges must all lie above the receiver's tangent plane (clip first) and be oriented
    counter-clockwise seen from the receiver side.
    """
    terms = jax.vmap(edge_term, in_axes=(None, None, 0, 0))(p, n, starts, ends)
    return -jnp.sum(terms) / (2 * jnp.pi)


@jax.custom_jvp
def form_factor_kernel(
    p: Float[Array, "3"], n: Float[Array, "3"], verts: Float[Array, "k 3"]
) -> Float[Array, ""]:
    r"""Unoccluded point-to-polygon form factor $F(p, n)$ (Campbell & Fussell eq. 11).

    The emitter is clipped exactly to the receiver's horizon $n \cdot (x - p) \ge 0$; a
    receiver behind the emitter or in its plane gets 0.

    Two evaluations of the same formula, both component by component (no length-3 minor
    axis, which XLA:CPU cannot fuse well): values come from a version with the `K` edges
    unrolled (after `vmap` all intermediates are `(N,)` arrays fused into one loop: the fast
    path for millions of receivers), derivatives from a version vectorised over the edges
    (`(K,)` arrays: the edge code appears once, so second derivatives compile ~10x faster).
    `tests/test_polygon.py` checks that the two agree. Lambert's term is scale-free, so each vertex is
    turned into a unit direction once; the horizon crossing of edge `a -> b` is the point
    $(h_a \hat b - h_b \hat a)/(h_a - h_b)$ of the chord, $h = n\cdot\hat v$ (it lies in the
    tangent plane, between $\hat a$ and $\hat b$; `_horizon_crossing`).

    **Arguments:** `p (3,)` receiving point (m), `n (3,)` receiver normal (unit length),
    `verts (K, 3)` padded convex polygon, counter-clockwise seen from its lit side.

    **Returns:** dimensionless $F \in [0, 1]$.
    """
    return _form_factor_unrolled(p, n, verts)


@form_factor_kernel.defjvp
def _form_factor_jvp(primals, tangents):
    return jax.jvp(_form_factor_compact, primals, tangents)


# Edges per fused loop of the unrolled kernel. XLA:CPU's loop for one polygon stops being
# vectorised somewhere between 28 and 32 edges (32 vertices at 10^5 points: 85 ms in one loop,
# 13 ms in groups of 16); longer
# polygons are evaluated in groups of this many edges by a `lax.scan`.
EDGE_GROUP = 16


def _horizon_crossing(a: tuple, b: tuple, ha: Array, hb: Array, crossing: Array) -> tuple:
    r"""Where the chord from the unit direction `a` to `b` (heights $h = n\cdot\hat v$ above
    the tangent plane) crosses it: $(h_a b - h_b a)/(h_a - h_b)$, of length between
    $\cos(\theta_{ab}/2)$ and 1 (scale-free). Edges that do not cross get `a` (double
    `where`): their unused crossing was rounding noise of length ~1e-9, whose derivatives
    (~1/length^3) overflowed float32 and turned every gradient into NaN through `0 * inf`
    (e.g. the zero-length padding edge of a padded polygon below the horizon)."""
    den = jnp.where(crossing, ha - hb, 1.0)
    return tuple(jnp.where(crossing, fusible((ha * bc - hb * ac) / den), ac) for ac, bc in zip(a, b, strict=True))


def _horizon_arc_term(a: tuple, b: tuple, n: tuple) -> Array:
    r"""Lambert's term of the closing edge `a -> b`, which lies in the tangent plane: there
    $\hat\Gamma = \pm\hat n$, and the term is $|n|$ times the signed angle
    $\operatorname{atan2}(\hat n\cdot(a\times b), a\cdot b)$ ($|n|$ keeps the kernel's
    degree-1 homogeneity in `n`, which its derivatives in `n` rely on). `_edge_term_c` would
    take $n\cdot\hat\Gamma$ from the direction of $a \times b$, which is rounding noise when the
    crossings are nearly opposite (a receiver close to the light's plane, its horizon cutting
    the light in two): float32 lost 3e-5 of F."""
    c = n[0] * (a[1] * b[2] - a[2] * b[1]) + n[1] * (a[2] * b[0] - a[0] * b[2]) + n[2] * (a[0] * b[1] - a[1] * b[0])
    nn2 = n[0] * n[0] + n[1] * n[1] + n[2] * n[2]
    ok = nn2 > 0
    nn = fusible(jnp.sqrt(jnp.where(ok, nn2, 1.0)))
    angle = arctan2(fusible(c / nn), a[0] * b[0] + a[1] * b[1] + a[2] * b[2])
    return jnp.where(ok, nn * angle, 0.0)


def _unrolled_edges(n: tuple, dirs: list, carry: tuple) -> tuple:
    """Lambert's terms of the edges `dirs[i] -> dirs[i + 1]` (unit vertex directions from the
    receiver, normal components `n`), horizon-clipped, added to `carry = (total, exit_pt,
    entry_pt, any_exit)` (the crossing points collected for the closing horizon edge)."""
    total, exit_pt, entry_pt, any_exit = carry
    h = [n[0] * v[0] + n[1] * v[1] + n[2] * v[2] for v in dirs]
    up = [hi >= 0 for hi in h]
    for i in range(len(dirs) - 1):
        a, b, ha, hb = dirs[i], dirs[i + 1], h[i], h[i + 1]
        x = _horizon_crossing(a, b, ha, hb, up[i] != up[i + 1])
        start = tuple(jnp.where(up[i], ac, xc) for ac, xc in zip(a, x, strict=True))
        end = tuple(jnp.where(up[i + 1], bc, xc) for bc, xc in zip(b, x, strict=True))
        keep = up[i] | up[i + 1]
        total = total + jnp.where(keep, _edge_term_c(start, end, n), 0.0)
        exiting = up[i] & ~up[i + 1]
        entering = ~up[i] & up[i + 1]
        exit_pt = tuple(jnp.where(exiting, xc, e) for xc, e in zip(x, exit_pt, strict=True))
        entry_pt = tuple(jnp.where(entering, xc, e) for xc, e in zip(x, entry_pt, strict=True))
        any_exit = any_exit | exiting
    return total, exit_pt, entry_pt, any_exit


def _form_factor_unrolled(p: Array, n: Array, verts: Array) -> Array:
    """`form_factor_kernel` with the edges unrolled (fast values); in groups of `EDGE_GROUP`
    edges (a `lax.scan`) above `1.5 EDGE_GROUP` vertices."""
    k = verts.shape[0]
    in_front = on_lit_side(p, verts)
    nc = (n[0], n[1], n[2])

    def unit(v: Array) -> tuple:
        return _unit3(v[0] - p[0], v[1] - p[1], v[2] - p[2])

    zero = jnp.zeros_like(p[0])
    carry = (zero, (zero, zero, zero), (zero, zero, zero), jnp.zeros_like(p[0], dtype=bool))
    closed = jnp.concatenate([verts, verts[:1]])  # edge i runs closed[i] -> closed[i + 1]
    if k <= (3 * EDGE_GROUP) // 2:
        carry = _unrolled_edges(nc, [unit(closed[i]) for i in range(k + 1)], carry)
    else:
        g = EDGE_GROUP
        n_groups = -(-k // g)
        # Padding edges verts[0] -> verts[0] have zero length: they add nothing and never cross.
        padded = jnp.concatenate([closed, jnp.broadcast_to(verts[:1], (n_groups * g - k, 3))])
        groups = jnp.stack([padded[i * g : i * g + g + 1] for i in range(n_groups)])

        def step(c: tuple, vs: Array) -> tuple:
            return _unrolled_edges(nc, [unit(vs[j]) for j in range(g + 1)], c), None

        carry, _ = jax.lax.scan(step, carry, groups)
    total, exit_pt, entry_pt, any_exit = carry
    # The closing edge along the horizon, from the exit to the entry crossing.
    total = total + jnp.where(any_exit, _horizon_arc_term(exit_pt, entry_pt, nc), 0.0)
    return jnp.where(in_front, -total / (2 * jnp.pi), 0.0)


def _form_factor_compact(p: Array, n: Array, verts: Array) -> Array:
    """`form_factor_kernel` vectorised over the edges (compact program for derivatives)."""
    in_front = on_lit_side(p, verts)
    nc = (n[0], n[1], n[2])
    # Per-vertex unit directions and heights above the tangent plane, one (K,) array per
    # component; "next" is the same rolled by one (the edge i -> i+1).
    a = _unit3(verts[:, 0] - p[0], verts[:, 1] - p[1], verts[:, 2] - p[2])
    b = tuple(jnp.roll(c, -1) for c in a)
    ha = nc[0] * a[0] + nc[1] * a[1] + nc[2] * a[2]
    hb = jnp.roll(ha, -1)
    up_a, up_b = ha >= 0, hb >= 0
    x = _horizon_crossing(a, b, ha, hb, up_a != up_b)
    start = tuple(jnp.where(up_a, ac, xc) for ac, xc in zip(a, x, strict=True))
    end = tuple(jnp.where(up_b, bc, xc) for bc, xc in zip(b, x, strict=True))
    terms = jnp.where(up_a | up_b, _edge_term_c(start, end, nc), 0.0)
    # The closing edge along the horizon, from the exit to the entry crossing.
    exiting = up_a & ~up_b
    entering = ~up_a & up_b
    exit_pt = tuple(jnp.sum(jnp.where(exiting, xc, 0.0)) for xc in x)
    entry_pt = tuple(jnp.sum(jnp.where(entering, xc, 0.0)) for xc in x)
    closing = jnp.where(jnp.any(exiting), _horizon_arc_term(exit_pt, entry_pt, nc), 0.0)
    total = jnp.sum(terms) + closing
    return jnp.where(in_front, -total / (2 * jnp.pi), 0.0)


@jax.jit
def _form_factor_batch(points: Array, normals: Array, vertices: Array) -> tuple[Array, Array]:
    """Form factors `(N,)` and the input flag (`_geometry.inputs_ok`), one compiled call."""
    f = jax.vmap(form_factor_kernel, in_axes=(0, 0, None))(points, unit_rows(normals), vertices)
    return f, inputs_ok(points, normals)


def _check_vertices(vertices: Any, dtype: Any) -> AnyArray:
    """Validate the emitter of `form_factor` (NumPy, when concrete) and cast it to `dtype`."""
    v = as_input(vertices, "form_factor: vertices")
    if v.ndim != 2 or v.shape[-1] != 3:
        raise ValueError(f"form_factor: vertices must have shape (k, 3), got {v.shape}.")
    if v.shape[0] < 3:
        raise ValueError(f"form_factor: a polygon needs at least 3 vertices, got {v.shape[0]}.")
    if not (jnp.issubdtype(v.dtype, jnp.floating) or jnp.issubdtype(v.dtype, jnp.integer)):
        raise ValueError(f"form_factor: vertices must be a real array, got dtype {v.dtype}.")
    if is_concrete(v):
        check_convex_polygon_cached(v, "form_factor: vertices")
    else:
        v = check_finite_leaves(v, "form_factor: vertices")
    return v.astype(dtype)


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def form_factor(
    points: Float[ArrayLike, "N 3"], normals: Float[ArrayLike, "N 3"], vertices: Float[ArrayLike, "k 3"]
) -> Float[Array, " N"]:
    r"""Unoccluded point-to-polygon form factor for a batch of receivers.

    $E = \pi L F$ is the irradiance from a Lambertian emitter of radiance $L$.

    **Arguments:**

    - `points`: `(N, 3)` receiving points (scene units, e.g. m), floating point.
    - `normals`: `(N, 3)` receiver normals (normalised here; zero vectors are an error).
    - `vertices`: `(k, 3)` convex planar polygon, counter-clockwise seen from the side it
      emits to (right-hand rule gives the emitting normal). Cast to the dtype of `points`.

    Concrete inputs are validated in NumPy before tracing (shapes, dtypes, NaN/inf, zero
    normals, non-planar / non-convex / degenerate polygons); `ValueError` names the culprit.
    Traced inputs (under the caller's `jit`) are checked for NaN/inf when the program runs.

    Validity bound: a receiver closer to the light's plane than the rounding of the
    coordinates (about 8 eps times their distance: 5e-7 in float32, 2e-15 in float64) is on an
    undecidable side of it; F is then 0 or the value from the lit side, that of a
    configuration within rounding of the input. Computed in light- and receiver-relative,
    scale-free form, F does not depend on where the scene sits or on its scale.

    **Returns:** `(N,)` form factors (dimensionless), dtype following `points`.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js

        quad = np.array([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2.0]])   # faces -z
        points = np.array([[0.5, 0.5, 0.0], [3.0, 0.0, 0.0]])
        normals = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
        F = js.form_factor(points, normals, quad)   # (2,), dimensionless
        ```
    """
    points, normals = check_points_normals(points, normals, "form_factor", values=False)
    vertices = _check_vertices(vertices, points.dtype)
    return evaluate_checked(lambda p, n: _form_factor_batch(p, n, vertices), points, normals, "form_factor")
