"""Polygons as padded arrays, planes, horizon clipping, and build-time validation.

**Padded polygons.** Every polygon in jaxshadow is a `(K, 3)` array whose trailing slots
repeat the *first* vertex. With that padding a plain cyclic edge sum over all `K` slots is
exactly the sum over the polygon's real edges (the padded edges have zero length and every
contour kernel returns exactly 0 for them, with a zero gradient). No masks, no counts, one
shape per batch.

**Edge soups.** A planar region is handed to the contour-integral kernels as oriented edges
`(starts (E, 3), ends (E, 3))`. Horizon clipping produces one (`K + 1` edges: the clipped
original edges plus the closing edge along the horizon); the shadow code produces others.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .misc import divide_by_scale, map_chunks

# A JAX array or tracer, or a NumPy array: what the entry points' checks pass on (`as_input`).
AnyArray = Array | np.ndarray

# Relative tolerances used by build-time validation (NumPy, float64).
PLANARITY_RTOL = 1e-6
DEGENERACY_RTOL = 1e-9


# --------------------------------------------------------------------------------------
# JAX side
# --------------------------------------------------------------------------------------


def newell_normal(verts: Float[Array, "k 3"]) -> Float[Array, "3"]:
    """Newell's normal of a (padded) polygon: twice the vector area, right-hand rule."""
    nxt = jnp.roll(verts, -1, axis=0)
    return jnp.sum(jnp.cross(verts, nxt), axis=0)


def on_lit_side(p: Float[Array, "3"], verts: Float[Array, "k 3"]) -> Array:
    """True where `p` lies strictly on the side the (padded, planar) polygon's right-hand
    normal points to.

    Translation- and scale-free: the normal comes from the vertices relative to the first one,
    each set divided by its largest component before any product (the absolute-coordinate
    Newell sum cancels catastrophically away from the origin: in float32 a unit light 1e5 from
    the origin got a normal of rounding noise and lit nothing; products of raw coordinates
    over- and underflow at large and small scales). Only the sign is used: no gradient.
    """
    verts = jax.lax.stop_gradient(verts)
    p = jax.lax.stop_gradient(p)
    rel = verts - verts[:1]
    s = jnp.max(jnp.abs(rel))
    ne = newell_normal(divide_by_scale(rel, jnp.where(s > 0, s, 1.0)))
    w = p - verts[0]
    t = jnp.max(jnp.abs(w))
    w = divide_by_scale(w, jnp.where(t > 0, t, 1.0))
    return jnp.dot(ne, w) > 0


def horizon_clip_edges(
    p: Float[Array, "3"], n: Float[Array, "3"], verts: Float[Array, "k 3"]
) -> tuple[Float[Array, "k+1 3"], Float[Array, "k+1 3"]]:
    r"""Clip a padded convex polygon to the closed half-space $n \cdot (x - p) \ge 0$.

    Exact clipping (not a clamp of the integrand): the part of the polygon below the tangent
    plane of the receiver is cut away. Returns the boundary of the clipped polygon as an edge
    soup of `K + 1` oriented edges: edge `i` is the part of the original edge `i -> i+1` above
    the plane (zero-length if none), and the last edge closes the polygon along the horizon from
    the exit point to the entry point (zero-length when nothing is cut). Orientation is kept.

    **Arguments:** `p (3,)` point on the plane, `n (3,)` plane normal (any length),
    `verts (K, 3)` padded convex polygon.

    **Returns:** `(starts, ends)`, each `(K + 1, 3)`.
    """
    nxt = jnp.roll(verts, -1, axis=0)
    da = (verts - p[None, :]) @ n
    db = (nxt - p[None, :]) @ n
    a_in = da >= 0
    b_in = db >= 0
    crossing = a_in != b_in
    den = jnp.where(crossing, da - db, 1.0)
    t = jnp.where(crossing, da / den, 0.0)
    x = verts + t[:, None] * (nxt - verts)
    start = jnp.where(a_in[:, None], verts, x)
    end = jnp.where(b_in[:, None], nxt, x)
    # Both endpoints below: collapse the edge onto its start (zero length, zero contribution).
    keep = a_in | b_in
    start = jnp.where(keep[:, None], start, verts)
    end = jnp.where(keep[:, None], end, verts)
    exiting = (a_in & ~b_in)[:, None]
    entering = (~a_in & b_in)[:, None]
    exit_pt = jnp.sum(jnp.where(exiting, x, 0.0), axis=0)
    entry_pt = jnp.sum(jnp.where(entering, x, 0.0), axis=0)
    any_cut = jnp.any(exiting) & jnp.any(entering)
    close_start = jnp.where(any_cut, exit_pt, verts[0])
    close_end = jnp.where(any_cut, entry_pt, verts[0])
    starts = jnp.concatenate([start, close_start[None]], axis=0)
    ends = jnp.concatenate([end, close_end[None]], axis=0)
    return starts, ends


# --------------------------------------------------------------------------------------
# NumPy side: validation and padding (run at build time, before jit)
# --------------------------------------------------------------------------------------


def inputs_ok(points: AnyArray, normals: AnyArray) -> Array:
    """Traceable: True when every point and normal is finite and no normal is zero. The public
    entry points evaluate it inside their own compiled call (one pass fused with the kernel,
    no extra dispatch) and hand the flag to `raise_if_bad`."""
    # Componentwise, one reduction: XLA:CPU fuses it into 4 small loops instead of ~10.
    def finite(v: AnyArray) -> Array:
        return jnp.isfinite(v[..., 0]) & jnp.isfinite(v[..., 1]) & jnp.isfinite(v[..., 2])

    nonzero = (normals[..., 0] != 0) | (normals[..., 1] != 0) | (normals[..., 2] != 0)
    return jnp.all(finite(points) & finite(normals) & nonzero)


_all_good = jax.jit(inputs_ok)


def check_points_normals(points: Any, normals: Any, what: str = "", values: bool = True) -> tuple[AnyArray, AnyArray]:
    """Shape/dtype/value checks shared by every public entry point.

    Returns the inputs as arrays (`as_input`: NumPy arrays stay NumPy); normals are *not* normalised here (the jitted kernels do it, fused).
    With `values=False` only shapes and dtypes are checked here: the caller evaluates
    `inputs_ok` in its compiled call and passes the flag to `raise_if_bad` (`evaluate_checked`).
    """
    pre = f"{what}: " if what else ""
    points, normals = as_input(points, pre + "points"), as_input(normals, pre + "normals")
    for name, x in (("points", points), ("normals", normals)):
        if x.ndim != 2 or x.shape[-1] != 3:
            raise ValueError(f"{pre}{name} must have shape (N, 3), got {x.shape}.")
        if not jnp.issubdtype(x.dtype, jnp.floating):
            raise ValueError(f"{pre}{name} must be a floating-point array, got dtype {x.dtype}.")
    if points.shape[0] != normals.shape[0]:
        raise ValueError(
            f"{pre}points and normals must have the same length, got {points.shape[0]} and {normals.shape[0]}."
        )
    if values:
        check_values_eagerly(points, normals, what)
    if isinstance(points, jax.core.Tracer) or isinstance(normals, jax.core.Tracer):
        # Values that arrive traced (the caller's jit/vmap/grad): checked when the program runs.
        points, normals = eqx.error_if(
            (points, normals),
            ~inputs_ok(points, normals),
            f"{pre}a point or normal is not finite, or a normal is the zero vector.",
        )
    return points, normals


def check_finite_leaves(tree: Any, what: str) -> Any:
    """Every floating leaf of `tree` finite: concrete leaves are checked in NumPy (`ValueError`
    naming the leaf), traced ones when the program runs (`eqx.error_if`, whose result is
    returned: use it). For values changed after build (`eqx.tree_at`) or traced under the
    caller's own `jit`, where the build-time checks never saw them."""
    leaves = jax.tree_util.tree_leaves_with_path(tree)
    traced = []
    for path, leaf in leaves:
        if not hasattr(leaf, "dtype") or not jnp.issubdtype(leaf.dtype, jnp.inexact):
            continue
        if isinstance(leaf, jax.core.Tracer):
            traced.append(leaf)
            continue
        a = np.asarray(leaf)
        if not np.all(np.isfinite(a)):
            idx = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
            raise ValueError(
                f"{what}{jax.tree_util.keystr(path)}: non-finite value {a[idx]} at index {idx}."
            )
    if not traced:
        return tree
    bad = jnp.zeros((), bool)
    for leaf in traced:
        bad = bad | ~jnp.all(jnp.isfinite(leaf))
    return eqx.error_if(tree, bad, f"{what}: a value is not finite (NaN or inf).")


def as_input(x: Any, what: str) -> Any:
    """A JAX array (or tracer) as it is; anything else as a NumPy array, which a compiled call
    takes directly at about half the cost of `jnp.asarray` first. A NumPy dtype JAX would
    change (float64 without x64) is converted, so that the caller's dtype bookkeeping follows
    the dtype the kernels compute in."""
    if isinstance(x, jnp.ndarray):
        return x
    try:
        a = np.asarray(x)
    except (ValueError, TypeError) as e:
        raise ValueError(f"{what} is not an array of numbers: {e}") from None
    return jnp.asarray(a) if a.dtype != jax.dtypes.canonicalize_dtype(a.dtype) else a


def check_values_eagerly(points: AnyArray, normals: AnyArray, what: str) -> None:
    if not isinstance(points, jax.core.Tracer) and not isinstance(normals, jax.core.Tracer):
        # One fused pass decides; the slow NumPy search for the culprit runs only on failure.
        # Concrete arrays closed over by a caller's jit are still checked: evaluate eagerly.
        with jax.ensure_compile_time_eval():
            good = bool(_all_good(points, normals))
        if not good:
            raise_if_bad(False, points, normals, what)


def raise_if_bad(good: Any, points: AnyArray, normals: AnyArray, what: str) -> None:
    """Raise the precise `ValueError` (first non-finite value, first zero normal) unless `good`."""
    if bool(good):
        return
    pre = f"{what}: " if what else ""
    pp, nn = np.asarray(points), np.asarray(normals)
    for name, x in (("points", pp), ("normals", nn)):
        bad = ~np.isfinite(x)
        if bad.any():
            i = int(np.argwhere(bad.any(axis=1))[0, 0])
            raise ValueError(f"{pre}{name}[{i}] is not finite: {x[i].tolist()}.")
    zero = ~np.any(nn != 0, axis=1)
    i = int(np.argmax(zero))
    raise ValueError(f"{pre}normals[{i}] is the zero vector; a normal needs a direction.")


def evaluate_checked(fn: Any, points: AnyArray, normals: AnyArray, what: str) -> Any:
    """`fn(points, normals) -> (out, inputs_ok(points, normals))` (one compiled call that also
    checks the inputs), evaluated in blocks (`_misc.map_chunks`); returns `out`, or raises the
    precise error when some block's flag is False. Under a caller's transformation (the flag
    is traced) concrete inputs are checked eagerly instead, and traced ones not at all."""
    out, ok = map_chunks(fn, (points, normals))
    if isinstance(ok, jax.core.Tracer):
        check_values_eagerly(points, normals, what)
        return out
    raise_if_bad(bool(np.all(np.asarray(ok))), points, normals, what)  # one transfer, no dispatch
    return out


def is_concrete(x: object) -> bool:
    """False for JAX tracers (validation is skipped under jit/vmap/grad)."""
    import jax

    return not isinstance(x, jax.core.Tracer)


def check_finite(x: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(x)
    if np.any(bad):
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"{what}: non-finite value {float(x[idx])} at index {idx}.")


def check_vector3(x: object, what: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.shape != (3,):
        raise ValueError(f"{what}: expected shape (3,), got {a.shape}.")
    check_finite(a, what)
    return a


def check_rgb(x: object, what: str, nonnegative: bool = True) -> np.ndarray:
    """An RGB triple (a scalar is broadcast to grey); finite and, by default, >= 0."""
    a = np.asarray(x, dtype=np.float64)
    if a.shape == ():
        a = np.full(3, float(a))
    if a.shape != (3,):
        raise ValueError(f"{what}: expected a scalar or an RGB triple of shape (3,), got {a.shape}.")
    check_finite(a, what)
    if nonnegative and np.any(a < 0):
        i = int(np.argmin(a))
        raise ValueError(f"{what}: must be >= 0, got {float(a[i])} in channel {'RGB'[i]}.")
    return a


def check_unit_direction(x: object, what: str) -> np.ndarray:
    a = check_vector3(x, what)
    if not np.any(a != 0):
        raise ValueError(f"{what}: a direction must be non-zero, got (0, 0, 0).")
    return a


_VALID_POLYGONS: dict = {}


def check_convex_polygon_cached(verts: Any, what: str) -> None:
    """`check_convex_polygon`, remembering the last few polygons that passed (keyed on their
    bytes): a batch entry point called again with the same emitter skips the NumPy checks."""
    v = np.asarray(verts)
    key = (v.shape, v.dtype.str, v.tobytes())
    if key in _VALID_POLYGONS:
        return
    check_convex_polygon(v, what)
    if len(_VALID_POLYGONS) >= 64:
        _VALID_POLYGONS.pop(next(iter(_VALID_POLYGONS)))
    _VALID_POLYGONS[key] = True


def triangles_pass(tris: np.ndarray) -> bool:
    """True when every triangle of `tris (m, 3, 3)` surely passes `check_convex_polygon`: finite,
    edges longer and twice the area larger than twice that check's limits (the same formulas,
    vectorised; a triangle is planar and convex once its area is). False sends the caller to the
    one-by-one check, which names the offending polygon."""
    t = np.asarray(tris, dtype=np.float64)
    if t.ndim != 3 or t.shape[1:] != (3, 3) or not np.all(np.isfinite(t)):
        return False
    c = t - t.mean(axis=1, keepdims=True)
    size = np.sqrt((c * c).sum(axis=2)).max(axis=1)
    edges = np.roll(t, -1, axis=1) - t
    elen = np.sqrt((edges * edges).sum(axis=2)).min(axis=1)
    normal = np.cross(c, np.roll(c, -1, axis=1)).sum(axis=1)
    area2 = np.sqrt((normal * normal).sum(axis=1))
    return bool(np.all(elen > 2 * DEGENERACY_RTOL * size) & np.all(area2 > 2 * DEGENERACY_RTOL * size * size))


def check_convex_polygon(verts: object, what: str) -> np.ndarray:
    """Validate a convex planar polygon and return it as a float64 `(k, 3)` array.

    Errors (each names the offending vertex): wrong shape, NaN/inf, fewer than 3 distinct
    vertices, repeated vertices, zero area, non-planar (distance to the best plane above
    `PLANARITY_RTOL` times the polygon's size), non-convex (a turn of the wrong sign, or a
    polygon that winds more than once).
    """
    v = np.asarray(verts, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{what}: vertices must have shape (k, 3), got {v.shape}.")
    check_finite(v, what)
    k = v.shape[0]
    distinct = np.unique(v, axis=0).shape[0] if k else 0
    if distinct < 3:
        raise ValueError(
            f"{what}: a polygon needs at least 3 distinct vertices, got {distinct} "
            f"(of {k} given)."
        )
    size = float(np.max(np.linalg.norm(v - v.mean(axis=0), axis=1)))
    edges = np.roll(v, -1, axis=0) - v
    elen = np.linalg.norm(edges, axis=1)
    for i in range(k):
        if elen[i] <= DEGENERACY_RTOL * size:
            raise ValueError(
                f"{what}: vertices {i} and {(i + 1) % k} coincide (zero-length edge); "
                "remove the repeated vertex."
            )
    # Newell's normal about the centroid (absolute coordinates cancel for a sliver far from the
    # origin, and a triangle was then "non-planar").
    c = v - v.mean(axis=0)
    normal = np.sum(np.cross(c, np.roll(c, -1, axis=0)), axis=0)
    area2 = float(np.linalg.norm(normal))
    if area2 <= DEGENERACY_RTOL * size * size:
        raise ValueError(f"{what}: zero area (all vertices are collinear).")
    nhat = normal / area2
    dist = (v - v.mean(axis=0)) @ nhat
    worst = int(np.argmax(np.abs(dist)))
    if abs(dist[worst]) > PLANARITY_RTOL * size:
        raise ValueError(
            f"{what}: non-planar polygon: vertex {worst} is {abs(dist[worst]):.3g} from the "
            f"plane of the polygon (tolerance {PLANARITY_RTOL:g} x size {size:.3g})."
        )
    turns = np.cross(edges, np.roll(edges, -1, axis=0)) @ nhat
    tol = DEGENERACY_RTOL * size * size
    for i in range(k):
        if turns[i] < -tol:
            raise ValueError(
                f"{what}: non-convex polygon: the turn at vertex {(i + 1) % k} goes the wrong "
                "way (vertices must be in convex, consistent order)."
            )
    # A star polygon turns the same way everywhere but winds more than once.
    e2 = edges - np.outer(edges @ nhat, nhat)
    ang = np.arctan2(np.cross(e2, np.roll(e2, -1, axis=0)) @ nhat, np.sum(e2 * np.roll(e2, -1, axis=0), axis=1))
    winding = float(np.sum(ang)) / (2 * np.pi)
    if abs(winding - 1.0) > 1e-6:
        raise ValueError(
            f"{what}: non-convex polygon: its boundary winds {winding:.3g} times "
            "(self-intersecting)."
        )
    return v


def strip_padding(v: np.ndarray) -> np.ndarray:
    """Drop trailing copies of the first vertex (jaxshadow's padding convention): `(k, 3)` ->
    `(k', 3)`, at least 3 vertices kept."""
    k = v.shape[0]
    while k > 3 and np.array_equal(v[k - 1], v[0]):
        k -= 1
    return v[:k]


def pad_polygon(v: np.ndarray, k: int) -> np.ndarray:
    """Pad `(j, 3)` vertices to `(k, 3)` by repeating the first vertex."""
    j = v.shape[0]
    if j > k:
        raise ValueError(f"cannot pad a {j}-gon to {k} vertices")
    return np.concatenate([v, np.repeat(v[:1], k - j, axis=0)], axis=0)


def pad_polygons_jax(polys: list, k: int | None = None) -> Array:
    """Stack polygons of different vertex counts into `(m, K, 3)` with first-vertex padding.

    Works on JAX arrays (differentiable leaves stay differentiable).
    """
    if k is None:
        k = max(int(np.shape(p)[0]) for p in polys)
    if not any(isinstance(p, jax.core.Tracer) for p in polys):
        # Concrete: pad in NumPy and convert once (one eager JAX op per polygon costs ~1 ms).
        return jnp.asarray(np.stack([pad_polygon(np.asarray(p), k) for p in polys]))
    polys = [p if isinstance(p, jnp.ndarray) else jnp.asarray(p) for p in polys]
    out = []
    for p in polys:
        j = p.shape[0]
        if j < k:
            p = jnp.concatenate([p, jnp.repeat(p[:1], k - j, axis=0)], axis=0)
        out.append(p)
    return jnp.stack(out)
