r"""Occluder culling for exact soft shadows: fewer occluders, same result.

`jaxshadow._clip.visible_edges` costs $O(M^2)$ per receiver and light in the number of occluders
$M$ (its edge soup has $((K+1) + M(K_o+1))(M+1)$ slots). Most occluders of a big mesh cannot
shadow a given receiver from a given light, so this module finds, exactly or conservatively,
the ones that can, in two stages. Neither stage ever changes the result beyond rounding: an
occluder is only removed when it provably blocks a zero solid angle of the light.

**NumPy side (once per scene, before jit).**

- `merge_coplanar(polygons)`: greedily merges convex polygons that share an edge and lie in one
  plane into convex polygons (a flat region of a triangle mesh becomes one occluder; the shared
  edges, which the clipping kernel would cut and then drop, vanish). The union of two coplanar
  polygons sharing an edge is the same point set, so blocking is unchanged.
- `prune_occluders(occluders, emitters, points)`: drops occluders that cannot meet the convex
  hull of the receivers' bounding box and any polygon light (Campbell & Fussell §3.1: an
  occluder outside every occlusion volume casts no shadow; Chrysanthou & Slater's "shadow
  overlap cube" is the same idea with boxes). Separating-axis test on a few axes (the
  coordinate axes, the emitter's and the occluder's normals): conservative, never drops an
  occluder that meets the hull. Valid for polygon lights only (point, segment and directional
  lights have other shadow volumes).

**JAX side (per receiver and light, under jit/vmap).**

- `occluder_relevance(p, n, verts, occluders)`: $O(M)$ test of each occluder against the
  pyramid $P = \mathrm{conv}(\{p\} \cup E_h)$ whose segments $p \to x$, $x \in E_h$, are the
  rays the clipping kernel integrates over. An occluder is *irrelevant* when a plane separates
  it from $P$: all its vertices strictly outside one of the planes through $p$ and an emitter
  edge, or below the receiver's tangent plane, or on the unlit side of the emitter plane; or
  $p$ and every emitter vertex strictly on one side of the occluder's own plane. Strict means
  by more than `64 eps` times the size of the quantity, so occluders that touch $P$ (a vertex on
  a pyramid plane, an edge grazing the horizon) are *kept*. Not a full separating-axis test
  (edge-edge axes are skipped): it may keep an occluder that misses $P$, which costs time, not
  accuracy.
- `select_occluders(p, n, verts, occluders, max_active)`: gathers the relevant occluders, in
  their original order (so the clipping kernel's coincident-edge priority is unchanged), into a
  fixed `(max_active, Ko, 3)` array padded with *inactive dummies* (all-zero polygons: their
  Newell normal is exactly 0, so the kernel marks them inactive and they contribute exactly
  nothing). Returns an `overflow` flag when more than `max_active` are relevant.
- `culled_form_factor_kernel(p, n, verts, occluders, max_active)` -> `(F, overflow)`: the
  clipping kernel on the selected occluders, its boundary gathered into `edge_capacity` slots
  (`_clip.visible_edges_compact`); `overflow` also when the boundary has more edges than that.
- `with_fallback(culled, overflow, full)`: `lax.cond` at the *batch* level: if any receiver
  overflowed, the full kernel is evaluated (for the whole batch, then used only where
  `overflow`); otherwise it is never run. A receiver with more relevant occluders than
  capacity is therefore never wrong, only slow. (Inside an outer `vmap` the `cond` becomes a
  `select` and both branches run: call it on the stacked `(lights, points)` result, not per
  light.)
- `visible_form_factor_culled(points, normals, vertices, occluders, max_active)`: the batched
  public-style wrapper (jitted) built from the above.
- `max_relevant(points, normals, emitters, occluders)`: the largest relevant count over
  concrete receivers and lights (NumPy-side planning): a `max_active` that never overflows for
  these points; `capacity_for` rounds it up to a power of two to limit recompilation.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ._clip import (
    COLLINEAR_EPS,
    _edge_planes,
    masked_contour_form_factor,
    visible_edges_compact,
    visible_form_factor_kernel,
)
from ._geometry import newell_normal

# --------------------------------------------------------------------------------------
# NumPy side
# --------------------------------------------------------------------------------------


def _strip(poly: np.ndarray) -> np.ndarray:
    """Drop first-vertex padding from a `(K, 3)` polygon."""
    poly = np.asarray(poly, dtype=np.float64)
    k = poly.shape[0]
    while k > 3 and np.array_equal(poly[k - 1], poly[0]):
        k -= 1
    return poly[:k]


def _np_cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`np.cross` on the last axis, component by component (its values, a third of its call
    overhead, which dominates for the small batches of `_clip_host`)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _np_next(x: np.ndarray, axis: int) -> np.ndarray:
    """`np.roll(x, -1, axis)` by slicing (a fifth of its overhead)."""
    lead = (slice(None),) * (axis % x.ndim)
    return np.concatenate([x[lead + (slice(1, None),)], x[lead + (slice(0, 1),)]], axis=axis)


def _newell_np(v: np.ndarray) -> np.ndarray:
    """Newell's normal of `(..., K, 3)` polygons."""
    return np.sum(_np_cross(v, _np_next(v, -2)), axis=-2)


def _drop_collinear(v: np.ndarray, nhat: np.ndarray, tol: float) -> np.ndarray:
    """Remove vertices whose two edges are collinear (T-junctions left by a merge)."""
    changed = True
    while changed and len(v) > 3:
        changed = False
        e = np.roll(v, -1, axis=0) - v
        turn = np.cross(np.roll(e, 1, axis=0), e) @ nhat  # turn at vertex i
        straight = np.abs(turn) <= tol * np.linalg.norm(
            np.roll(e, 1, axis=0), axis=1
        ) * np.linalg.norm(e, axis=1)
        if straight.any():
            i = int(np.argmax(straight))
            v = np.delete(v, i, axis=0)
            changed = True
    return v


def _try_merge(a: np.ndarray, b: np.ndarray, max_vertices: int, tol: float) -> np.ndarray | None:
    """The union of convex polygons `a` and `b` if they share an edge, are coplanar and the union
    is convex with at most `max_vertices` vertices; else None. Keeps `a`'s orientation."""
    na = _newell_np(a)
    nb = _newell_np(b)
    la, lb = np.linalg.norm(na), np.linalg.norm(nb)
    nhat = na / la
    size = max(np.max(np.abs(a - a[0])), np.max(np.abs(b - a[0])))
    if np.linalg.norm(np.cross(na, nb)) > tol * la * lb:
        return None
    if np.max(np.abs((b - a[0]) @ nhat)) > tol * size:
        return None
    if np.dot(na, nb) < 0:
        b = b[::-1]
    ka, kb = len(a), len(b)
    for i in range(ka):
        u, v = a[i], a[(i + 1) % ka]
        for j in range(kb):
            if np.array_equal(b[j], v) and np.array_equal(b[(j + 1) % kb], u):
                # a: v -> ... -> u (all of a, starting after the shared edge), then b from
                # u (exclusive) round to v (exclusive).
                loop_a = [a[(i + 1 + t) % ka] for t in range(ka)]
                loop_b = [b[(j + 2 + t) % kb] for t in range(kb - 2)]
                m = _drop_collinear(np.array(loop_a + loop_b), nhat, tol)
                e = np.roll(m, -1, axis=0) - m
                turn = np.cross(e, np.roll(e, -1, axis=0)) @ nhat
                if np.any(turn < 0) or len(m) > max_vertices:
                    return None
                if len(np.unique(m, axis=0)) != len(m):
                    return None
                return m
    return None


def merge_coplanar(
    polygons: list | np.ndarray, max_vertices: int = 8, rtol: float = COLLINEAR_EPS * 2.0**-52
) -> list[np.ndarray]:
    """Merge coplanar convex polygons that share an edge (same two vertices, bit for bit).

    Greedy: repeatedly merges a pair whose union is convex with at most `max_vertices`
    vertices; coplanar means normals parallel and vertices within `rtol` times the size of the
    pair from the plane. Exact: the union of two coplanar polygons is the same point set.

    **Arguments:** `polygons`: list of `(k, 3)` convex polygons or a padded `(m, K, 3)` array;
    `max_vertices`: largest merged polygon (the kernel's padded size grows with it).

    **Returns:** a list of `(k, 3)` float64 polygons (first polygon's orientation kept for each
    merged group).
    """
    polys = [_strip(p) for p in polygons]
    merged = True
    while merged:
        merged = False
        edge_owner: dict[frozenset, int] = {}
        for idx, poly in enumerate(polys):
            for i in range(len(poly)):
                key = frozenset((poly[i].tobytes(), poly[(i + 1) % len(poly)].tobytes()))
                if key in edge_owner and edge_owner[key] != idx:
                    j = edge_owner[key]
                    m = _try_merge(polys[j], poly, max_vertices, rtol)
                    if m is not None:
                        polys[j] = m
                        polys.pop(idx)
                        merged = True
                        break
                else:
                    edge_owner[key] = idx
            if merged:
                break
    return polys


def prune_occluders(
    occluders: list | np.ndarray, emitters: list | np.ndarray, points: np.ndarray
) -> np.ndarray:
    """Indices of the occluders that may shadow some receiver in `points` from some emitter.

    Keeps occluder $j$ unless, for every emitter $E$, a plane strictly separates it from
    $\\mathrm{conv}(B \\cup E)$, $B$ the bounding box of `points` (axes tried: x, y, z, the
    emitter's and the occluder's normals). Conservative (touching is kept); polygon lights only.

    **Arguments:** `occluders` list of `(k, 3)` or `(m, K, 3)`; `emitters` likewise; `points`
    `(N, 3)` receivers.

    **Returns:** sorted int array of kept occluder indices.
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    box = np.array(
        [[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])]
    )
    occs = [_strip(o) for o in occluders]
    ems = [_strip(e) for e in emitters]
    keep = []
    for j, o in enumerate(occs):
        no = _newell_np(o)
        relevant = False
        for e in ems:
            hull = np.concatenate([box, e])
            axes = np.concatenate([np.eye(3), _newell_np(e)[None], no[None]])
            axes = axes / np.linalg.norm(axes, axis=1, keepdims=True)
            po = o @ axes.T
            ph = hull @ axes.T
            scale = np.max(np.abs(np.concatenate([po, ph])), axis=0)
            margin = COLLINEAR_EPS * 2.0**-52 * scale
            sep = (po.max(axis=0) < ph.min(axis=0) - margin) | (
                ph.max(axis=0) < po.min(axis=0) - margin
            )
            if not sep.any():
                relevant = True
                break
        if relevant:
            keep.append(j)
    return np.asarray(keep, dtype=np.int64)


# --------------------------------------------------------------------------------------
# JAX side
# --------------------------------------------------------------------------------------


def _outside_all(g: Array, scale: Array, tol: float) -> Array:
    """True where every vertex value `g (..., Ko)` is below `-tol * scale`: strictly outside."""
    return jnp.all(g < -tol * scale, axis=-1)


def occluder_relevance(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    verts: Float[Array, "k 3"],
    occluders: Float[Array, "m ko 3"],
    closed: bool = False,
) -> Bool[Array, " m"]:
    r"""Which occluders may block part of the light seen from `p` (conservative, $O(M K K_o)$).

    False only when a plane strictly separates the occluder from the pyramid
    $\mathrm{conv}(\{p\} \cup E_h)$ (module docstring): then it blocks a zero solid angle and
    dropping it leaves `visible_form_factor_kernel` unchanged. All False when `p` is not in
    front of the light (the form factor is 0 there anyway). Gradient: none (a selection).

    `closed=True` (static) promises that the occluders are the faces of closed meshes with
    outward (right-hand-rule) normals and that `p` is outside them; then faces that `p` sees
    from behind are irrelevant too: a segment from `p` that passes through a solid enters it
    through a face whose outward side faces `p`, so the front faces block the same rays as
    the whole mesh (grazing rays aside: a zero solid angle).

    **Arguments:** `p (3,)`, `n (3,)` receiver and normal; `verts (K, 3)` padded convex light;
    `occluders (M, Ko, 3)` padded convex occluders; `closed` (static bool).

    **Returns:** `(M,)` bool.
    """
    p, n, verts, occluders = (jax.lax.stop_gradient(x) for x in (p, n, verts, occluders))
    tol = COLLINEAR_EPS * float(jnp.finfo(p.dtype).eps)
    e0 = verts[0]
    ne = newell_normal(verts)
    in_front = jnp.dot(ne, p - e0) > 0
    rel = occluders - p[None, None, :]  # (M, Ko, 3)
    rnorm = jnp.sqrt(jnp.sum(rel * rel, axis=-1))  # (M, Ko)

    # Planes through p and the emitter's edges (interior positive), and the horizon.
    planes = jnp.concatenate([_edge_planes(p, verts), n[None, :]], axis=0)  # (K+1, 3)
    pnorm = jnp.sqrt(jnp.sum(planes * planes, axis=-1))
    g = jnp.einsum("mvi,ki->mkv", rel, planes)  # (M, K+1, Ko)
    cut_by_cone = jnp.any(
        _outside_all(g, pnorm[None, :, None] * rnorm[:, None, :], tol) & (pnorm > 0)[None, :],
        axis=1,
    )

    # Unlit side of the emitter plane.
    relv = occluders - e0[None, None, :]
    h = relv @ ne
    behind = _outside_all(h, jnp.linalg.norm(ne) * jnp.sqrt(jnp.sum(relv * relv, axis=-1)), tol)

    # The occluder's own plane with p and all emitter vertices strictly on one side.
    no = jax.vmap(newell_normal)(occluders)  # (M, 3)
    nn = jnp.sqrt(jnp.sum(no * no, axis=-1))
    xs = jnp.concatenate([p[None, :], verts], axis=0)  # (K+1, 3)
    dx = xs[None, :, :] - occluders[:, :1, :]  # (M, K+1, 3)
    d = jnp.einsum("mxi,mi->mx", dx, no)
    dscale = nn[:, None] * jnp.sqrt(jnp.sum(dx * dx, axis=-1))
    one_side = jnp.all(d > tol * dscale, axis=1) | jnp.all(d < -tol * dscale, axis=1)
    one_side = one_side & (nn > 0)
    irrelevant = cut_by_cone | behind | one_side
    if closed:
        # Back faces: p strictly behind the face's plane (d[:, 0] is no . (p - o_0)).
        irrelevant = irrelevant | (d[:, 0] < -tol * dscale[:, 0])
    return in_front & ~irrelevant


def select_occluders(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    verts: Float[Array, "k 3"],
    occluders: Float[Array, "m ko 3"],
    max_active: int,
    closed: bool = False,
) -> tuple[Float[Array, "a ko 3"], Int[Array, ""], Bool[Array, ""]]:
    r"""The occluders that may shadow `p`, gathered into a fixed-capacity array.

    Relevant occluders (`occluder_relevance`) in their original order, then all-zero dummy
    polygons (inactive in the clipping kernel: they contribute exactly 0, value and gradient).

    **Arguments:** `p`, `n`, `verts`, `occluders` as `occluder_relevance`; `max_active` (static
    int) the capacity.

    **Returns:** `(active (max_active, Ko, 3), count, overflow)`: `count` the number of
    relevant occluders, `overflow = count > max_active` (then `active` holds the first
    `max_active` of them only and the caller must fall back, see `with_fallback`).
    Differentiable in `occluders` through the gather.
    """
    m_occ = occluders.shape[0]
    relevant = occluder_relevance(p, n, verts, occluders, closed)
    (idx,) = jnp.nonzero(relevant, size=max_active, fill_value=m_occ)
    padded = jnp.concatenate([occluders, jnp.zeros((1,) + occluders.shape[1:], occluders.dtype)])
    count = jnp.sum(relevant.astype(jnp.int32))
    return padded[idx], count, count > max_active


def culled_form_factor_kernel(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    verts: Float[Array, "k 3"],
    occluders: Float[Array, "m ko 3"],
    max_active: int,
    closed: bool = False,
    host: bool = False,
) -> tuple[Float[Array, ""], Bool[Array, ""]]:
    """`visible_form_factor_kernel` on the selected occluders only, the boundary of the visible
    region gathered into `edge_capacity(K, Ko, max_active)` slots: `(F, overflow)`. Equal to
    the full kernel (rounding aside) wherever `overflow` is False. `host` as
    `culled_visible_edges`."""
    starts, ends, overflow = culled_visible_edges(p, n, verts, occluders, max_active, closed, host)
    return masked_contour_form_factor(p, n, verts, starts, ends), overflow


def culled_visible_edges(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    verts: Float[Array, "k 3"],
    occluders: Float[Array, "m ko 3"],
    max_active: int,
    closed: bool = False,
    host: bool = False,
) -> tuple[Float[Array, "b 3"], Float[Array, "b 3"], Bool[Array, ""]]:
    """The boundary of the visible region with the selected occluders only, in
    `edge_capacity(K, Ko, max_active)` slots: `(starts, ends, overflow)` (the edges are exact
    wherever `overflow` is False). `host` (static): the selection and the clipping's
    combinatorics run in NumPy on the host (`_clip_host.culled_visible_edges_host`; the same
    edges to rounding, a much smaller compiled program)."""
    if host:
        from ._clip_host import culled_visible_edges_host  # it imports this module

        return culled_visible_edges_host(p, n, verts, occluders, max_active, closed)
    active, _, overflow = select_occluders(p, n, verts, occluders, max_active, closed)
    cap = edge_capacity(verts.shape[0], occluders.shape[1], max_active)
    starts, ends, e_over = visible_edges_compact(p, n, verts, active, cap)
    return starts, ends, overflow | e_over


def grouped_culled_form_factor(
    points: Float[Array, "N 3"],
    normals: Float[Array, "N 3"],
    verts: Float[Array, "k 3"],
    occluders: Float[Array, "m ko 3"],
    max_active: int,
    n_wide: int,
    closed: bool = False,
) -> tuple[Float[Array, " N"], Bool[Array, " N"]]:
    """`culled_form_factor_kernel` over a batch with two capacities: the `n_wide` (static)
    receivers with the most relevant occluders get `max_active`, all others 1 (most receivers
    of a scene see at most one occluder; the kernel's cost grows quadratically with the
    capacity). Returns `(F (N,), overflow (N,))`; a receiver of the narrow group with two or
    more relevant occluders overflows (more than `n_wide` receivers needed the wide one)."""
    counts = jax.vmap(lambda p, n: jnp.sum(occluder_relevance(p, n, verts, occluders, closed).astype(jnp.int32)))(
        points, normals
    )
    order = jnp.argsort(-counts, stable=True)
    wide, narrow = order[:n_wide], order[n_wide:]
    kern = jax.vmap(culled_form_factor_kernel, in_axes=(0, 0, None, None, None, None))
    fw, ow = kern(points[wide], normals[wide], verts, occluders, max_active, closed)
    fn, on = kern(points[narrow], normals[narrow], verts, occluders, 1, closed)
    inv = jnp.argsort(order)
    return jnp.concatenate([fw, fn])[inv], jnp.concatenate([ow, on])[inv]


def edge_capacity(k: int, ko: int, max_active: int) -> int:
    """Edge slots for the boundary of the visible region with at most `max_active` occluders:
    `(K + 1) + max_active (Ko + 1)` (every candidate edge once) plus 4 for edges split by
    another region, rounded up to a multiple of 8. The worst case, `max_active + 1` runs per
    edge, is far rarer: it overflows and falls back."""
    need = (k + 1) + max_active * (ko + 1) + 4
    return -(-need // 8) * 8


def with_fallback(culled: Array, overflow: Array, full) -> Array:
    """`culled` where no receiver overflowed; else `where(overflow, full(), culled)`.

    `full` is a zero-argument callable computing the uncull'd values with `culled`'s shape;
    it runs (under `lax.cond`) only when some entry overflowed.
    """
    return jax.lax.cond(
        jnp.any(overflow),
        lambda: jnp.where(overflow, full(), culled),
        lambda: culled,
    )


@eqx.filter_jit
def visible_form_factor_culled(
    points: Float[Array, "N 3"],
    normals: Float[Array, "N 3"],
    vertices: Float[Array, "k 3"],
    occluders: Float[Array, "m ko 3"],
    max_active: int,
    closed: bool = False,
    batch_size: int | None = None,
) -> Float[Array, " N"]:
    """`jaxshadow._clip.visible_form_factor` with per-receiver occluder culling.

    **Arguments:** as `visible_form_factor`, plus `max_active` (static int): the capacity of
    the per-receiver occluder list; `closed` (static): see `occluder_relevance`;
    `batch_size` (static): receivers evaluated at once (`lax.map`; bounds the memory of the
    edge soup, `O(batch_size max_active^2)`), `None` for all at once. Cost per receiver $O(M)$
    for the selection plus $O(\\text{max\\_active}^2)$ for the clipping. Receivers with more
    relevant occluders fall back to the full kernel (`with_fallback`), so the result is exact
    whatever `max_active`.

    **Returns:** `(N,)` form factors, dtype following the inputs.
    """

    def culled(pn):
        return culled_form_factor_kernel(pn[0], pn[1], vertices, occluders, max_active, closed)

    def full_one(pn):
        return visible_form_factor_kernel(pn[0], pn[1], vertices, occluders)

    f, over = jax.lax.map(culled, (points, normals), batch_size=batch_size)
    return with_fallback(
        f, over, lambda: jax.lax.map(full_one, (points, normals), batch_size=batch_size)
    )


@eqx.filter_jit
def _counts(
    points: Array, normals: Array, emitters: Array, occluders: Array, closed: bool
) -> Array:
    rel = jax.vmap(
        jax.vmap(occluder_relevance, in_axes=(0, 0, None, None, None)),
        in_axes=(None, None, 0, None, None),
    )(points, normals, emitters, occluders, closed)
    return jnp.sum(rel.astype(jnp.int32), axis=-1)


def max_relevant(
    points: np.ndarray,
    normals: np.ndarray,
    emitters: np.ndarray,
    occluders: np.ndarray,
    closed: bool = False,
) -> int:
    """Largest number of relevant occluders over concrete receivers and polygon lights.

    **Arguments:** `points`, `normals` `(N, 3)`; `emitters (L, K, 3)` padded lights;
    `occluders (M, Ko, 3)` padded occluders; `closed` as `occluder_relevance`.

    **Returns:** a Python int (0 when nothing can shadow anything): a `max_active` with which
    no receiver overflows.
    """
    pts = jnp.asarray(points)
    nrm = jnp.asarray(normals)
    nrm = nrm / jnp.linalg.norm(nrm, axis=-1, keepdims=True)
    c = _counts(
        pts, nrm, jnp.asarray(emitters, pts.dtype), jnp.asarray(occluders, pts.dtype), closed
    )
    return int(jnp.max(c)) if c.size else 0


def capacity_for(count: int, m_occ: int) -> int:
    """`max_active` for a relevant count: the next power of two (>= 1), at most `m_occ`."""
    cap = 1
    while cap < count:
        cap *= 2
    return max(1, min(cap, m_occ))
