r"""Planes through the receiver: every visibility test of `jaxshadow._kernels.clip` (module
docstring, "Everything is a plane through p") is a sign test against planes through the receiver
$p$, built here straight from the input vertices and brought to order one by exact powers of two:
the emitter's and occluders' edge planes, the occluder sides (`_occluder_sides`, the on-surface
rule), the cut where an occluder crosses the emitter plane (`_occluder_regions`), Cyrus-Beck
clipping, the central projection (`project`), the crossing of two planes (`crossing_point`) and
the parameter interval of an edge inside a region (`_interval_on_region`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array

from .._core.geometry import newell_normal
from .._core.misc import safe_div, safe_normalize

# Planes through p whose unit normals are parallel within COLLINEAR_EPS * machine epsilon
# are the same plane: their traces on the emitter plane are one line (coincident edges).
COLLINEAR_EPS = 64.0

# A receiver closer to an occluder face's plane than ON_SURFACE * S (S: the largest coordinate
# magnitude of the face's vertices and the receiver) lies on that face, which then blocks
# nothing (nor does any face coplanar with it): 32 float32 epsilons (2^-18 ~ 3.8e-6) of S in
# float32 and float64 alike, since a face built from float32-rounded vertices (OBJ, PLY,
# Mitsuba) is planar, and a point computed on it lies in its plane, only to a few float32
# roundings of S (`_occluder_sides`; the engine's `kOnSurface`).
ON_SURFACE = 2.0**-18
# The same rule for faces of other doubles: 256 double epsilons of S (points computed on such a
# face lie in its plane to a few roundings of S, not of the face's size; the engine's
# `kOnSurface64`).
ON_SURFACE_64 = 2.0**-44


def _eps(x: Array) -> float:
    return float(jnp.finfo(x.dtype).eps)


def _lex_less(a: Array, b: Array) -> Array:
    """Whether `a` precedes `b` `(..., 3)` lexicographically (x, then y, then z)."""
    return (a[..., 0] < b[..., 0]) | ((a[..., 0] == b[..., 0]) & ((a[..., 1] < b[..., 1]) | (
        (a[..., 1] == b[..., 1]) & (a[..., 2] < b[..., 2]))))


def edge_planes(p: Array, a: Array, b: Array) -> Array:
    r"""Planes through `p (3,)` and the edges `a -> b` `(..., 3)`: $(b - p)\times(a - p)$ up to a
    positive factor (each brought to order one by a power of two), computed as
    $(h - l)\times(x - p)$ from the endpoints in lexicographic order $l$, $h$ (the sign restored
    after), with $x$ the endpoint nearer `p`.

    The same vector, with two properties the plain form lacks: one edge gives bit-identical
    normals (up to an exact sign) whichever face it comes from and whichever way it runs, so
    coincident lines (two faces sharing an edge) are recognised exactly; and there is no
    cancellation for an edge short beside its distance from `p` (the rounding of
    $(b - p)\times(a - p)$ is about $\epsilon\,|a - p|\,|b - p|$ against a result of
    $|(b - p)\times(a - p)|$, i.e. $\epsilon$ times the conditioning of `plane_condition`; this
    form's is at most twice that, smaller by $|b - a|$ over the farther endpoint's distance: a
    1.5 cm face seen from 5.6 m at a grazing angle lost 400 eps of its plane, and the crossing of
    two such planes, a boundary vertex, 1e-10 of its distance). The engine's `edge_plane`
    (`csrc/engine/geometry.h`) computes the same; the host path's decoder
    (`jaxshadow._shadows.binding.decode_endpoints`) calls this one."""
    swap = _lex_less(b, a)
    lo = jnp.where(swap[..., None], b, a)
    hi = jnp.where(swap[..., None], a, b)
    # `p` given unit axes by each difference on its own: in the gradient each difference's
    # cotangent is reduced over the edges and reaches `p` as a term of its own (one
    # `broadcast_to` shared by both would add them first: other roundings in float64).
    lead = (None,) * (lo.ndim - 1)
    rl, rh = lo - p[lead], hi - p[lead]
    near = jnp.where((jnp.sum(rh * rh, axis=-1) < jnp.sum(rl * rl, axis=-1))[..., None], rh, rl)
    c = rescale_rows(jnp.cross(rescale_rows(hi - lo), rescale_rows(near)))
    return jnp.where(swap[..., None], -c, c)


def _edge_planes(p: Array, verts: Array) -> Array:
    r"""The plane through $p$ and edge $i$ (`edge_planes` of $v_i \to v_{i+1}$) for each edge of
    a padded polygon `verts (K, 3)`, oriented so that a polygon that runs counter-clockwise seen
    from $p$ lies on its positive side. Padded (zero-length) edges give exactly 0."""
    nxt = jnp.roll(verts, -1, axis=0)
    real = jnp.any(nxt != verts, axis=1)
    return jnp.where(real[:, None], edge_planes(p, verts, nxt), 0.0)


def plane_condition(p: Array, a: Array, b: Array) -> Array:
    r"""The conditioning of the plane through `p (3,)` and the edge `a -> b` `(..., 3)`:
    $|a - p|\,|b - p| / |(b - p)\times(a - p)|$, one over the sine of the angle the edge
    subtends at $p$ (its normal's direction is about that many epsilons off); $\infty$ where the
    edge's line passes through $p$. Scale-free (computed on the differences brought to order one
    by one power of two); no gradient (the engine's `through_condition`)."""
    a, b, p = jax.lax.stop_gradient((a, b, p))
    p = jnp.broadcast_to(p, a.shape)
    ra, rb = a - p, b - p
    sc = pow2_scale(jnp.maximum(jnp.max(jnp.abs(ra), axis=-1), jnp.max(jnp.abs(rb), axis=-1)))[..., None]
    ra, rb = ra * sc, rb * sc
    cn = jnp.sqrt(jnp.sum(jnp.cross(rb, ra) ** 2, axis=-1))
    num = jnp.sqrt(jnp.sum(ra * ra, axis=-1)) * jnp.sqrt(jnp.sum(rb * rb, axis=-1))
    ok = cn > 0
    return jnp.where(ok, num / jnp.where(ok, cn, 1.0), jnp.inf)


def collinear_in_space(a: Array, b: Array, c: Array, d: Array, p: Array) -> Array:
    r"""Whether the edges `a -> b` and `c -> d` `(..., 3)` lie on one line in space: each vertex
    within `COLLINEAR_EPS` $\epsilon S$ of the other edge's line ($S$ the largest coordinate
    magnitude of the four vertices and `p (3,)`). A T-junction of a mesh (a vertex of one face
    inside its neighbour's edge, as `Mesh`'s coplanar merging leaves where it drops a collinear
    vertex), or faces overlapping along an edge: the planes through $p$ are then computed from
    different pairs of points and differ by their rounding, which grows as the edge's angular
    length seen from $p$ shrinks, while this test does not depend on $p$ (the engine's
    `collinear_in_space`). No gradient."""
    a, b, c, d, p = jax.lax.stop_gradient((a, b, c, d, p))
    def mx(x):
        return jnp.max(jnp.abs(x), axis=-1)

    big = jnp.maximum(jnp.maximum(jnp.maximum(mx(a), mx(b)), jnp.maximum(mx(c), mx(d))), mx(p))
    tau = COLLINEAR_EPS * _eps(p) * big

    def near_line(o, q, x, y):
        u = q - o
        l2 = jnp.sum(u * u, axis=-1)
        cx, cy = jnp.cross(x - o, u), jnp.cross(y - o, u)
        lim = tau * tau * l2
        return (l2 > 0) & (jnp.sum(cx * cx, axis=-1) <= lim) & (jnp.sum(cy * cy, axis=-1) <= lim)

    return near_line(a, b, c, d) & near_line(c, d, a, b)


def pow2_scale(mag: Array) -> Array:
    """Power of two `2**-e` with `mag * 2**-e` in [0.5, 1) (1/2, the scale of 1, where `mag` is 0
    or not finite), built from the exponent bits so that multiplying by it is exact. No gradient.

    `e` is `frexp`'s exponent, read straight from the bits (biased exponent - bias + 1; a
    subnormal `mag` reads as the smallest normal exponent, which the clip below maps to the
    same `2**-e` as `frexp` would): bit-identical to the `jnp.frexp` form it replaced
    (`tests/test_planes.py`), at a twentieth of its tracing cost."""
    mag = jax.lax.stop_gradient(mag)
    fi = jnp.finfo(mag.dtype)
    int_t = {2: jnp.int16, 4: jnp.int32, 8: jnp.int64}[mag.dtype.itemsize]
    # lax primitives only (no nested jits such as jnp.where's: this runs under several
    # transformations in the solvers, where each nested jit is traced again).
    lax = jax.lax
    ok = lax.bitwise_and(lax.gt(mag, jnp.zeros((), mag.dtype)), lax.is_finite(mag))
    bits = lax.bitcast_convert_type(lax.select(ok, mag, jnp.ones_like(mag)), int_t)
    bias = fi.maxexp - 1

    def c(v: int) -> Array:
        return jnp.asarray(v, int_t)

    e = lax.sub(lax.bitwise_and(lax.shift_right_logical(bits, c(fi.nmant)), c((1 << int(fi.nexp)) - 1)),
                c(bias - 1))
    k = lax.add(lax.clamp(c(2 - bias), lax.neg(e), c(bias - 1)), c(bias))  # biased exponent of 2**-e
    return lax.bitcast_convert_type(lax.shift_left(k, c(fi.nmant)), mag.dtype)


def rescale_rows(x: Array) -> Array:
    """Each row (a plane normal; only its direction matters) times an exact power of two that
    brings its largest component into [0.5, 1): nothing under- or overflows downstream
    (cross products of two normals, their squares in gradients), the values are unchanged."""
    return x * pow2_scale(jnp.max(jnp.abs(x), axis=-1, keepdims=True))


def _abs_cross(a, b):
    """Componentwise bound on the terms of `cross(a, b)`: `|a_y b_z| + |a_z b_y|`, ..."""
    a, b = jnp.abs(a), jnp.abs(b)
    return jnp.stack(
        [
            a[..., 1] * b[..., 2] + a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] + a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _occluder_sides(p, occluders):
    r"""Per occluder, in the frame of p scaled by an exact power of two $\sigma$ (largest
    coordinate of $o_i - p$ in [0.5, 1), so that tiny or huge occluders neither under- nor
    overflow): the Newell normal `no` of the $\sigma(o_i - p)$, `d_o = no . sigma (o_0 - p)`,
    the side sign `s` (+1 when the vertex order runs counter-clockwise seen from p), `active`,
    the oriented planes through p and the edges `s (v_{i+1}-p) x (v_i-p)` (each rescaled) and
    $\sigma$ (`no` is $\sigma^2$, `d_o` $\sigma^3$ times their unscaled values).

    `active` is False when p cannot be told apart from the occluder's plane (it then blocks a
    zero solid angle): the heights $h_j = $ `no` $\cdot\,\sigma(o_j - p)$ of *all* its
    vertices must share one sign and each exceed its own rounding-error bound,
    $|h_j| > \tfrac{K_o + 8}{2}\,\epsilon\,A\cdot|r_j|$ with $r_j = \sigma(o_j - p)$ and
    $A = \sum_i |r_i| \otimes |r_{i+1}|$ the Newell sum of the absolute values of the terms.
    With $u = \epsilon/2$ that is $(K_o + 8)\,u$ against the first-order bound
    $(K_o + 7)\,u\,A\cdot|r_j|$ on the error of $h_j$ ($(K_o + 4)\,u$ for `no` and the dot
    product, $3u$ for the rounding of $o_j - p$). The bound follows the actual terms: an
    occluder parallel to a coordinate plane 1e-9 above p is resolved in float32, a tilted one
    only beyond several $\epsilon$ times its size; p within the thickness of a (tolerated)
    non-planar occluder, or exactly in its plane, or at a vertex ($h_j = 0$) is inactive.

    A receiver *on* an occluder of float32 values is inactive too: every $|h_j|$ must also exceed
    `ON_SURFACE` $\cdot S\,\sigma\,|$`no`$|$, i.e. p must be farther than `ON_SURFACE` $S$
    ($2^{-18} S$, $S$ the largest coordinate magnitude of the occluder's vertices and p) from
    its plane. Faces made of float32-rounded vertices (meshes from files, Mitsuba) are planar,
    and points computed on them lie in their planes, only to that order; a receiver on such a
    face taken as behind it by 1e-8 is shadowed by the whole face (0, or a negative contour sum
    from its nearly degenerate projection). For faces of other doubles the distance is
    `ON_SURFACE_64` $S$ ($2^{-44} S$): a point computed on them lies in their plane to a few
    double roundings of $S$ (not of the face's size, which the rounding bound above follows)."""
    rel = occluders - p[None, None, :]  # (M, Ko, 3)
    sigma = pow2_scale(jnp.max(jnp.abs(rel), axis=(1, 2)))  # (M,)
    rel = rel * sigma[:, None, None]
    no = jax.vmap(newell_normal)(rel)  # (M, 3)
    nxt = jnp.roll(rel, -1, axis=1)
    bound_no = jnp.sum(_abs_cross(rel, nxt), axis=1)  # (M, 3)
    # Elementwise products and sums, not einsum: a matrix unit may round its inputs (TF32).
    h = jnp.sum(no[:, None, :] * rel, axis=-1)  # (M, Ko)
    err = jnp.sum(bound_no[:, None, :] * jnp.abs(rel), axis=-1)
    bound = (occluders.shape[1] + 8) / 2 * _eps(p) * err
    d_o = h[:, 0]
    s = jnp.where(d_o < 0, 1.0, -1.0).astype(p.dtype)
    # On the face (ON_SURFACE): every height also exceeds ON_SURFACE * S * |no| (scaled frame).
    big = jnp.maximum(jnp.max(jnp.abs(occluders), axis=(1, 2)), jnp.max(jnp.abs(p)))
    no_c = jax.lax.stop_gradient(no)
    dtol = ON_SURFACE * jax.lax.stop_gradient(big) * sigma * jnp.sqrt(jnp.sum(no_c * no_c, axis=-1))
    # ON_SURFACE for faces of float32 values (files, Mitsuba); others are planar to their own
    # rounding, and take ON_SURFACE_64.
    occ_c = jax.lax.stop_gradient(occluders)
    f32 = jnp.all(occ_c.astype(jnp.float32).astype(occ_c.dtype) == occ_c, axis=(1, 2))
    dtol = jnp.where(f32, dtol, dtol * (ON_SURFACE_64 / ON_SURFACE))
    active = jnp.all((-s[:, None] * h > bound) & (-s[:, None] * h > dtol[:, None]), axis=1)
    # Planes through p and the edges (`edge_planes`, no cancellation for a short far edge);
    # zero for padded (repeated) vertices.
    planes = jax.vmap(_edge_planes, in_axes=(None, 0))(p, occluders)
    planes = s[:, None, None] * planes
    return no, d_o, s, active, planes, sigma


def _occluder_regions(p, occluders, ne, hp):
    """Per occluder: interior plane normals `(M, Ko+1, 3)` (edges, then the emitter-plane cut),
    the side sign `s` (+1 when its vertex order runs counter-clockwise seen from p) and an
    `active` flag (False when p lies in its plane: it blocks a zero solid angle)."""
    no, d_o, s, active, planes, sigma = _occluder_sides(p, occluders)
    # N_L = h_p sgn(d_o) N_o + |d_o| N_e, with no and d_o in the sigma-scaled frame (hp too).
    n_cut = (hp * sigma * -s)[:, None] * no + jnp.abs(d_o)[:, None] * ne[None, :]
    normals = jnp.concatenate([planes, rescale_rows(n_cut)[:, None, :]], axis=1)
    return normals, s, active


def _cyrus_beck(p, a, b, normals, n_own):
    """Parameter interval `[t0, t1]` of the segment `a -> b` inside `{x : (x-p).N >= 0}` for all N.

    `n_own`: the normal of the plane through p and the segment. A plane that holds the
    segment's line (parallel to `n_own` within the collinear tolerance of `_interval_on_region`,
    which decides with the same test) neither cuts nor drops it: its parameter there would be
    the ratio of two rounding errors, and the crossing point that of two coincident planes (a
    receiver on a face: its horizon holds the neighbouring faces' shared edges). The
    tie-break of `_boundary_runs` keeps one of the coincident edges (the engine's
    `cyrus_beck`)."""
    tol = COLLINEAR_EPS * _eps(p)
    g0 = (a - p) @ normals.T
    g1 = (b - a) @ normals.T
    sp, sa, sb, sn, so, h0, h1 = jax.lax.stop_gradient((p, a, b, normals, n_own, g0, g1))
    pn = jnp.sqrt(jnp.sum(sn * sn, axis=-1))
    apn = jnp.sqrt(jnp.sum((sa - sp) ** 2)) + jnp.sqrt(jnp.sum((sb - sp) ** 2))
    near = (jnp.any(sn != 0, axis=-1) & ~(jnp.abs(h0) > 4 * tol * pn * apn)
            & ~(jnp.abs(h0 + h1) > 4 * tol * pn * apn))
    cr = jnp.cross(safe_normalize(so)[None, :], safe_div(sn, pn[:, None]))
    on_line = near & (jnp.sum(cr * cr, axis=-1) <= tol * tol)
    g0 = jnp.where(on_line, 0.0, g0)
    g1 = jnp.where(on_line, 0.0, g1)
    pos = g1 > 0
    neg = g1 < 0
    tc = safe_div(-g0, g1)
    t_lo = jnp.where(pos, tc, 0.0)
    t_hi = jnp.where(neg, tc, 1.0)
    i0 = jnp.argmax(t_lo)
    i1 = jnp.argmin(t_hi)
    t0 = jnp.maximum(t_lo[i0], 0.0)
    t1 = jnp.minimum(t_hi[i1], 1.0)
    const_ok = jnp.all((g1 != 0) | (g0 >= 0))
    return t0, t1, const_ok & (t1 > t0), i0, i1


def project(p, x, ne, hp):
    """Central projection from p `(3,)` of x `(..., 3)` onto the emitter plane (unit-free: `ne`
    `(3,)` its normal, `hp` p's height above it along `ne`; x strictly towards it): `(..., 3)`."""
    r = x - p
    w = -(r @ ne)
    ok = w > 0
    scale = jnp.where(ok, hp / jnp.where(ok, w, 1.0), 0.0)
    return p + scale[..., None] * r


def crossing_point(p, c, ne, hp):
    r"""Where the line through p `(3,)` with direction `c` `(3,)` meets the emitter plane (normal
    `ne`, p's height `hp` above it, as in `project`; either sign of c): `(3,)`.

    A direction within $\epsilon^2$ (relative) of parallel to that plane meets it farther than
    $1/\epsilon^2$ times the distance from p to the plane, at infinity for all purposes: it gets
    `p` (such a point is never the end of a kept piece), so that $1/\mathrm{den}^2$ in the
    gradient cannot overflow (`c`, `ne` are of order one here)."""
    c = rescale_rows(c)  # only its direction matters
    den = -jnp.dot(c, ne)
    eps = _eps(c)
    ok = jnp.abs(den) > eps * eps * jnp.max(jnp.abs(c)) * jnp.max(jnp.abs(ne))
    return p + c * jnp.where(ok, hp / jnp.where(ok, den, 1.0), 0.0)


NEAR_PLANES = 1.0 / 1024  # the engine's kNearPlanes (`csrc/engine/polygon_types.h`)


def near_planes(c, m):
    """Whether the planes with normals `c`, `m` `(3,)` are within `NEAR_PLANES` of each other (the
    sine of their angle; no gradient)."""
    x = jnp.cross(c, m)
    return jax.lax.stop_gradient(jnp.sum(x * x) < NEAR_PLANES**2 * jnp.sum(c * c) * jnp.sum(m * m))


def light_edge_point(p, va, vb, m):
    r"""Where the plane through p `(3,)` with normal `m` meets the light edge `va -> vb`:
    $v_a + t (v_b - v_a)$, $t = m\cdot(v_a - p) / m\cdot(v_a - v_b)$ clamped to [0, 1], `(3,)`.

    The boundary vertex where that plane crosses the light edge's plane through p, met with the
    emitter plane, for planes within `NEAR_PLANES` of each other (`near_planes`: an occluder edge
    grazing the light edge's shadow line; the callers select it there and `crossing_point` of
    the planes' common line elsewhere, as the engine's `light_edge_crossing` in
    `polygon_types.h`): this point lies on the edge's line to rounding however nearly the planes
    coincide, where the cross product of their normals is off by $\epsilon$ over their angle
    (4e-6 of the value 1e-13 m off coincidence, `tests/test_exact_reference.py`)."""
    da, db = jnp.dot(va - p, m), jnp.dot(vb - p, m)
    apart = da != db
    t = jnp.where(apart, jnp.clip(da / jnp.where(apart, da - db, 1.0), 0.0, 1.0), 0.0)
    return va + t * (vb - va)


def _subtended_sine(p, a, b):
    """The sine of the angle the segment `a b` `(3,)` subtends at `p` (no gradient; the engine's
    `subtended_sine`)."""
    ra, rb = jax.lax.stop_gradient((a - p, b - p))
    ra = ra * (1.0 / jnp.max(jnp.abs(ra)))
    rb = rb * (1.0 / jnp.max(jnp.abs(rb)))
    return jnp.sqrt(jnp.sum(jnp.cross(ra, rb) ** 2)) / (jnp.sqrt(jnp.sum(ra * ra)) * jnp.sqrt(jnp.sum(rb * rb)))


def occluder_edges_point(p, a1, b1, n1, a2, b2, n2, ne, hp):
    r"""Where the planes through p `(3,)` and two occluder edges `a1 -> b1` (normal `n1`) and
    `a2 -> b2` (normal `n2`) cross, met with the emitter plane (`ne`, `hp` as in `project`), for
    planes within `NEAR_PLANES` of each other (`near_planes`: two edges nearly in line as seen
    from p; the callers select it there): `(3,)`.

    The cross product of the normals is off by $\epsilon$ over the planes' angle, in a direction
    off both edges. Here the vertex is where one edge's plane meets the other edge
    (`light_edge_point`'s formula), projected from p: on that edge's line to rounding, and off
    the plane by the plane's own rounding only, $\epsilon$ times its conditioning (one over the
    sine of the angle its edge subtends at p). The plane is the edge's subtending the larger
    angle (the first on a tie), the line the other's (the engine's `occluder_edges_crossing` in
    `polygon_types.h`). Differentiable in every point and normal (the choice carries none)."""
    first = ~(_subtended_sine(p, a1, b1) < _subtended_sine(p, a2, b2))
    x = jnp.where(first, light_edge_point(p, a2, b2, n1), light_edge_point(p, a1, b1, n2))
    return project(p, x, ne, hp)


def _interval_on_region(p, a, d, n_own, sigma, normals, valid, tol, own_cond=None, own_ends=None, conds=None,
                        ends=None, at=None):
    """Where the `sigma`-side of the edge `a + t d` is inside one convex region (planes through p).

    Returns `(lo, hi, i_lo, i_hi, const_ok_noncollinear, const_ok_collinear, any_collinear)`;
    the region contains the one-sided neighbourhood of `a + t d` iff `lo < t < hi` and both
    `const_ok`; `i_lo`, `i_hi` are the planes that cut the edge at `lo` and `hi` (the crossing
    points there are the lines common to the edge's plane and those, `_decode`).

    A plane holds the edge's line (collinear: it neither cuts the edge nor bounds it, the
    one-sided rule decides) when the unit normals are parallel within `tol`. Two occluder
    edges' planes (`own_cond`, `conds` > 0: their `plane_condition`s; `own_ends (2, 3)`,
    `ends (P, 2, 3)`: their vertices) are computed from different pairs of points, and each is
    off by about `tol` times its conditioning: where both ends of the edge lie within the
    rounding band `(4 + own_cond + cond) tol` of the other plane, they are collinear when the
    two edges lie on one line in space (`collinear_in_space`: a T-junction) or when their unit
    normals are parallel within that band (edges of different faces coplanar with p). Taken as
    crossing, their common line's point would be that of two planes a rounding apart, anywhere
    on the line or off it: a boundary vertex off both edges (the engine's `boundary_runs`).

    Shared vertices: `at = (start, end, start_ok, end_ok)` are the points in space the edge's
    ends are the projections of (where `*_ok`). An occluder edge's plane through such a point
    (one of its two vertices equal to it, bit for bit: faces sharing a vertex) holds that end
    exactly, so the edge crosses the plane there, at t = 0 or 1 exactly, and not at the
    parameter the two roundings put it at: a sliver of the edge beside the vertex, kept or
    dropped by rounding, left the contour open by the crossing's 1e-13 (the shared vertex of two
    faces folding at a silhouette, seen from afar).
    """
    g0 = (a - p) @ normals.T
    g1 = d @ normals.T
    if at is not None:
        sv, ev, sv_ok, ev_ok = at
        edge_pl = conds > 0  # an occluder edge's plane, its vertices `ends`
        hits_s = edge_pl & sv_ok & jnp.any(jnp.all(ends == sv[None, None, :], axis=-1), axis=-1)
        hits_e = edge_pl & ev_ok & jnp.any(jnp.all(ends == ev[None, None, :], axis=-1), axis=-1)
        g0 = jnp.where(hits_s, 0.0, g0)
        g1 = jnp.where(hits_e, -g0, g1)
    un = safe_normalize(normals)
    uo = safe_normalize(n_own)
    cr = jnp.cross(uo[None, :], un)
    cr2 = jnp.sum(cr * cr, axis=-1)
    collinear = valid & (cr2 <= tol * tol)
    if conds is not None:
        pn = jnp.sqrt(jnp.sum(normals * normals, axis=-1))
        apn = jnp.sqrt(jnp.sum((a - p) ** 2)) + jnp.sqrt(jnp.sum((a + d - p) ** 2))
        cb = (4 + own_cond + conds) * tol
        band = cb * pn * apn
        near = ~(jnp.abs(g0) > band) & ~(jnp.abs(g0 + g1) > band)
        in_space = collinear_in_space(own_ends[0][None, :], own_ends[1][None, :], ends[:, 0], ends[:, 1], p)
        rounding = valid & (own_cond > 0) & (conds > 0) & near & (in_space | (cr2 <= cb * cb))
        collinear = collinear | rounding
    side_ok = sigma * (un @ uo) > 0
    generic = valid & ~collinear
    pos = generic & (g1 > 0)
    neg = generic & (g1 < 0)
    tc = safe_div(-g0, g1)
    t_lo = jnp.where(pos, tc, -jnp.inf)
    t_hi = jnp.where(neg, tc, jnp.inf)
    i_lo = jnp.argmax(t_lo)
    i_hi = jnp.argmin(t_hi)
    const_noncol = jnp.all(~generic | (g1 != 0) | (g0 >= 0))
    const_col = jnp.all(~collinear | side_ok)
    return t_lo[i_lo], t_hi[i_hi], i_lo, i_hi, const_noncol, const_col, jnp.any(collinear)
