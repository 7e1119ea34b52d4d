r"""The culled clipping kernel with its combinatorics on the host: C (or NumPy) decides, JAX computes.

`jaxshadow._clip` splits the exact soft-shadow kernel into combinatorics (which pieces of which
candidate edges bound the visible region $R$, as integer endpoint codes: `_boundary_runs`,
with no gradient) and geometry (the points those codes name, and Lambert's contour sum over
them: what is differentiated). In a compiled program both are code that XLA has to compile,
and the combinatorics (the occluder selection, the splitting of every candidate edge at every
region, the sorting, the runs, the compaction) are most of it: a light fit's first call is
mostly XLA compiling the kernel (`benchmarks/README.md`, "Inverse solvers").

Here the combinatorics run on the host, called from the compiled program (`jax.pure_callback`,
once per evaluation of the kernel, for every receiver of the batch at once, one packed array
each way), and the program keeps only the geometry. They run in C (`_clipc.c`, built by
`setup.py`: `host_culled_codes` transcribed loop by loop, returning exactly its codes) where
the extension is built, else in NumPy:

- `host_culled_codes` (NumPy, batched over leading axes): the occluder selection of
  `_bsp.select_occluders` and, on the selected occluders, `_clip._candidates`,
  `_boundary_runs` and the compaction of `visible_edges_compact`, line by line the same
  arithmetic and the same tests. It returns, per receiver, the selected occluders' indices
  and, per endpoint of each edge slot, a *recipe* the device evaluates directly from the
  inputs: a vertex of the light or of a selected occluder; the crossing of one of their
  edges with the receiver's horizon (light) or the emitter plane (occluder), as
  `horizon_clip_edges` computes it; projected from $p$ onto the emitter plane (occluder
  points, `_clip._project`); or the crossing of two planes through $p$ (`_clip._decode`).
  Nothing is computed on the device for points no edge uses (the device kernel clips every
  candidate edge: that table and its tangents were about half of the program's XLA compile
  time, `benchmarks/README.md`, Session 8).
- `culled_visible_edges_host` (JAX, traceable): the callback, then the recipes, vectorised
  over the edge slots. A drop-in for `_bsp.culled_visible_edges`: the same
  `(starts, ends, overflow)`.

The recipes are piecewise constant in the inputs, so the derivatives are the geometry's, as in
`_clip`. Host and device evaluate the same formulas in the same precision; where rounding
could flip a test (a piece exactly on a region's boundary line) the two describe the same
region either way, as the device kernel's own tie-breaks do (`_clip` module docstring). What
is gained: the fit's compiled program no longer holds the combinatorics (`benchmarks/README.md`,
Session 8). What it costs: one host round trip per evaluation (the program waits for the
host; ~0.6 ms with the C kernel, most of it JAX's own callback machinery), so this is for the
CPU backend's fits (`fit_light`'s default there), not for the public batched entry points.
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ._bsp import _newell_np, _np_cross, _np_next, edge_capacity
from ._clip import (
    COLLINEAR_EPS,
    _crossing_point,
    _emitter_frame,
    _occluder_regions,
    _project,
    _region_planes,
)

# --------------------------------------------------------------------------------------
# NumPy mirrors of `_clip`'s and `_bsp`'s helpers, batched over the leading axes.
# --------------------------------------------------------------------------------------


@functools.cache
def _finfo(dtype: Any) -> Any:
    return np.finfo(dtype)  # (np.finfo's constructor costs ~15 us a call; it is called often)


def _np_take_last(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """`np.take_along_axis(a, idx, -1)` for `idx` with `a`'s leading shape, as one flat gather
    (`take_along_axis` builds broadcast index grids: ~20 us a call on these small arrays)."""
    if a.shape[:-1] != idx.shape[:-1]:
        return np.take_along_axis(a, idx, -1)
    n = a.shape[-1]
    off = (np.arange(a.size // max(n, 1), dtype=np.int64) * n).reshape(a.shape[:-1] + (1,))
    return a.reshape(-1)[idx + off]


def _np_take_rows(x: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """`np.take_along_axis(x, idx[..., None], -2)` for `x (..., K, 3)`, `idx (..., J)`."""
    if x.shape[:-2] != idx.shape[:-1]:
        return np.take_along_axis(x, idx[..., None], -2)
    k = x.shape[-2]
    off = (np.arange(x.size // (3 * max(k, 1)), dtype=np.int64) * k).reshape(x.shape[:-2] + (1,))
    return x.reshape(-1, 3)[idx + off]


def _np_pad_axis(x: np.ndarray, axis: int, size: int) -> np.ndarray:
    """`x` zero-padded at the end of `axis` to `size` (`np.pad`'s values, without its overhead)."""
    extra = size - x.shape[axis]
    if extra <= 0:
        return x
    shape = list(x.shape)
    shape[axis] = extra
    return np.concatenate([x, np.zeros(shape, x.dtype)], axis=axis)


def _np_pow2_scale(mag: np.ndarray) -> np.ndarray:
    """`_clip._pow2_scale`: `2**-e` with `frexp(mag) = (f, e)`, clamped to the normal range;
    1/2 where `mag` is 0 or not finite. The same values (frexp's exponent is what `_clip`
    reads from the bits, and the clamp maps a subnormal `mag` to the same scale)."""
    fi = _finfo(mag.dtype)
    bias = int(fi.maxexp) - 1
    ok = (mag > 0) & np.isfinite(mag)
    _, e = np.frexp(np.where(ok, mag, 1.0).astype(mag.dtype))
    k = np.clip(-e.astype(np.int64), 2 - bias, bias - 1)
    return np.ldexp(np.ones_like(mag), k).astype(mag.dtype)


def _np_rescale_rows(x: np.ndarray) -> np.ndarray:
    return x * _np_pow2_scale(np.max(np.abs(x), axis=-1, keepdims=True))


def _np_dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.sum(a * b, axis=-1)


def _np_safe_div(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    ok = den != 0
    return np.where(ok, num / np.where(ok, den, 1.0), 0.0)


def _np_safe_normalize(x: np.ndarray) -> np.ndarray:
    sq = np.sum(x * x, axis=-1, keepdims=True)
    ok = sq > 0
    return np.where(ok, x / np.sqrt(np.where(ok, sq, 1.0)), 0.0)


def _np_edge_planes(p: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """`_clip._edge_planes`; `p (..., 3)`, `verts (..., K, 3)`."""
    nxt = _np_next(verts, -2)
    real = np.any(nxt != verts, axis=-1)
    planes = _np_cross(nxt - p[..., None, :], verts - p[..., None, :])
    return np.where(real[..., None], planes, 0.0)


def _np_abs_cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    a, b = np.abs(a), np.abs(b)
    return np.stack(
        [
            a[..., 1] * b[..., 2] + a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] + a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] + a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def _np_horizon_clip_edges(p: np.ndarray, n: np.ndarray,
                           verts: np.ndarray) -> tuple[np.ndarray, np.ndarray, tuple[np.ndarray, ...]]:
    """`_geometry.horizon_clip_edges`; `p, n (..., 3)`, `verts (..., K, 3)`. Also returns how
    each point is formed (`_np_clip_recipes`), from which the points are computed here."""
    nxt = _np_next(verts, -2)
    da = _np_dot(verts - p[..., None, :], n[..., None, :])
    db = _np_dot(nxt - p[..., None, :], n[..., None, :])
    recipes = _np_clip_recipes(da, db)
    s_a, _, s_interp, e_a, _, e_interp, _ = recipes
    crossing = (da >= 0) != (db >= 0)
    den = np.where(crossing, da - db, 1.0)
    x = verts + np.where(crossing, da / den, 0.0)[..., None] * (nxt - verts)  # each edge's crossing

    def point(a: np.ndarray, interp: np.ndarray) -> np.ndarray:
        return np.where(interp[..., None], _np_take_rows(x, a), _np_take_rows(verts, a))

    return point(s_a, s_interp), point(e_a, e_interp), recipes


def _np_clip_recipes(da: np.ndarray, db: np.ndarray) -> tuple[np.ndarray, ...]:
    """How `horizon_clip_edges` forms each of its `K + 1` starts and ends, from the heights
    `da`, `db (..., K)` of each edge's two vertices above the clipping plane: `(s_a, s_b,
    s_interp, e_a, e_b, e_interp, bad)`. A point is vertex `a`, or (`interp`) the crossing
    `v_a + t (v_b - v_a)`, `t = da / (da - db)`, of edge `a -> b` with the plane. `bad`: more
    than one edge leaves or enters (never for a convex polygon; the caller then reports an
    overflow, so that the solver falls back to the device kernel)."""
    k = da.shape[-1]
    i = np.broadcast_to(np.arange(k), da.shape)
    nxt = (i + 1) % k
    a_in, b_in = da >= 0, db >= 0
    exiting, entering = a_in & ~b_in, ~a_in & b_in
    any_cut = np.any(exiting, axis=-1, keepdims=True) & np.any(entering, axis=-1, keepdims=True)
    ix = np.argmax(exiting, axis=-1)[..., None]
    ie = np.argmax(entering, axis=-1)[..., None]
    zero = np.zeros_like(ix)
    s_a = np.concatenate([i, np.where(any_cut, ix, zero)], axis=-1)
    s_b = np.concatenate([nxt, (ix + 1) % k], axis=-1)
    s_interp = np.concatenate([entering, any_cut], axis=-1)
    e_a = np.concatenate([np.where(b_in, nxt, i), np.where(any_cut, ie, zero)], axis=-1)
    e_b = np.concatenate([nxt, (ie + 1) % k], axis=-1)
    e_interp = np.concatenate([exiting, any_cut], axis=-1)
    bad = (np.sum(exiting, axis=-1) > 1) | (np.sum(entering, axis=-1) > 1)
    return s_a, s_b, s_interp, e_a, e_b, e_interp, bad


def _np_project(p: np.ndarray, x: np.ndarray, ne: np.ndarray, hp: np.ndarray) -> np.ndarray:
    """`_clip._project`; `x (..., 3)` with `p`, `ne`, `hp` broadcast against it."""
    r = x - p
    w = -_np_dot(r, ne)
    ok = w > 0
    scale = np.where(ok, hp / np.where(ok, w, 1.0), 0.0)
    return p + scale[..., None] * r


def _np_crossing_point(p: np.ndarray, c: np.ndarray, ne: np.ndarray, hp: np.ndarray) -> np.ndarray:
    """`_clip._crossing_point`."""
    c = _np_rescale_rows(c)
    den = -_np_dot(c, ne)
    eps = float(_finfo(c.dtype).eps)
    ok = np.abs(den) > eps * eps * np.max(np.abs(c), axis=-1) * np.max(np.abs(ne), axis=-1)
    return p + c * np.where(ok, hp / np.where(ok, den, 1.0), 0.0)[..., None]


def _np_first_true(mask: np.ndarray, size: int, fill: int) -> np.ndarray:
    """`jnp.nonzero(mask, size=size, fill_value=fill)` along the last axis, batched."""
    m = mask.shape[-1]
    order = np.argsort(~mask, axis=-1, kind="stable")
    if size > m:
        order = np.concatenate([order, np.zeros(mask.shape[:-1] + (size - m,), order.dtype)], axis=-1)
    order = order[..., :size]
    count = np.sum(mask, axis=-1, keepdims=True)
    return np.where(np.arange(size) < count, order, fill)


def _np_relevance(p: np.ndarray, n: np.ndarray, verts: np.ndarray, occ: np.ndarray, closed: bool) -> np.ndarray:
    """`_bsp.occluder_relevance`; `p, n (B, 3)`, `verts (B or 1, K, 3)`, `occ (B or 1, M, Ko, 3)`
    -> `(B, M)` (a leading 1 is shared by all receivers and computed once)."""
    tol = COLLINEAR_EPS * float(_finfo(p.dtype).eps)
    e0 = verts[:, 0]
    ne = _newell_np(verts)  # (Bv, 3)
    in_front = _np_dot(ne, p - e0) > 0  # (B,)
    rel = occ - p[:, None, None, :]  # (B, M, Ko, 3)
    rnorm = np.sqrt(_np_dot(rel, rel))  # (B, M, Ko)
    planes = np.concatenate([_np_edge_planes(p, verts), n[:, None, :]], axis=1)  # (B, K+1, 3)
    pnorm = np.sqrt(_np_dot(planes, planes))
    rx, ry, rz = rel[:, :, None, :, 0], rel[:, :, None, :, 1], rel[:, :, None, :, 2]  # (B, M, 1, Ko)
    qx, qy, qz = planes[:, None, :, None, 0], planes[:, None, :, None, 1], planes[:, None, :, None, 2]
    g = rx * qx + ry * qy + rz * qz  # (B, M, K+1, Ko)
    out_cone = np.all(g < -tol * (pnorm[:, None, :, None] * rnorm[:, :, None, :]), axis=-1)
    cut_by_cone = np.any(out_cone & (pnorm > 0)[:, None, :], axis=2)
    relv = occ - e0[:, None, None, :]  # (Bo or Bv, M, Ko, 3)
    h = _np_dot(relv, ne[:, None, None, :])
    behind = np.all(h < -tol * (np.sqrt(_np_dot(ne, ne))[:, None, None] * np.sqrt(_np_dot(relv, relv))), axis=-1)
    no = _newell_np(occ)  # (Bo, M, 3)
    nn = np.sqrt(_np_dot(no, no))
    # The occluder's plane against p and against each emitter vertex.
    dp = p[:, None, :] - occ[:, :, 0, :]  # (B, M, 3)
    d_p = _np_dot(dp, no)  # (B, M)
    s_p = nn * np.sqrt(_np_dot(dp, dp))
    dv = verts[:, None, :, :] - occ[:, :, None, 0, :]  # (Bv or Bo, M, K, 3)
    d_v = _np_dot(dv, no[:, :, None, :])
    s_v = nn[:, :, None] * np.sqrt(_np_dot(dv, dv))
    one_side = (((d_p > tol * s_p) & np.all(d_v > tol * s_v, axis=-1))
                | ((d_p < -tol * s_p) & np.all(d_v < -tol * s_v, axis=-1))) & (nn > 0)
    irrelevant = cut_by_cone | behind | one_side
    if closed:
        irrelevant = irrelevant | (d_p < -tol * s_p)
    return in_front[:, None] & ~irrelevant


def _batch_or_one(x: np.ndarray, batch: tuple, core: int) -> np.ndarray:
    """`x (*batch or 1s, *core)` as `(B or 1, *core)`."""
    lead = x.shape[: x.ndim - core]
    if all(d == 1 for d in lead):
        return x.reshape((1,) + x.shape[x.ndim - core:])
    return np.broadcast_to(x, batch + x.shape[x.ndim - core:]).reshape((-1,) + x.shape[x.ndim - core:])


def relevant_counts(points: np.ndarray, normals: np.ndarray, emitters: np.ndarray, occluders: np.ndarray,
                    closed: bool = False) -> np.ndarray:
    """`(L, N)` numbers of relevant occluders (`_bsp.occluder_relevance`, in NumPy: no
    compilation) for receivers `points, normals (N, 3)` (unit normals), padded convex lights
    `emitters (L, K, 3)` and `occluders (M, Ko, 3)`."""
    points, normals = np.asarray(points), np.asarray(normals)
    occ = np.asarray(occluders, points.dtype)
    n_pts = points.shape[0]
    out = np.zeros((len(emitters), n_pts), np.int64)
    for i, em in enumerate(np.asarray(emitters, points.dtype)):
        out[i] = np.sum(_np_relevance(points, normals, em[None], occ[None], closed), axis=-1)
    return out


def host_culled_codes(p: np.ndarray, n: np.ndarray, verts: np.ndarray, occluders: np.ndarray, max_active: int,
                      capacity: int, closed: bool = False) -> tuple[np.ndarray, ...]:
    r"""The combinatorics of `_bsp.culled_visible_edges`, in NumPy, batched over leading axes.

    **Arguments:** `p, n (..., 3)` receivers and unit normals, `verts (..., K, 3)` padded convex
    light, `occluders (..., M, Ko, 3)`, `max_active` and `capacity` (the edge slots,
    `_bsp.edge_capacity(K, Ko, max_active)`) ints, `closed` as `_bsp.occluder_relevance`.

    **Returns:** `(idx (..., A), kind, a, b, interp (each (..., 2 capacity)), used (...,
    capacity), overflow (...))` with `A = max_active`: the selected occluders (index `M`: an
    all-zero dummy); per endpoint (the slots' starts, then their ends) its recipe, `kind` 0
    (a light point: vertex `a` of the light, or with `interp` the crossing of its edge
    `a -> b` with the receiver's horizon), 1 (the same for the selected occluders' vertices,
    numbered after the light's, with the emitter plane, then projected from `p`) or 2 (the
    crossing of planes `a < b` through `p`, `_clip._decode`'s numbering); `used` the slots
    that hold an edge; `overflow` as `_bsp.culled_visible_edges` (too many relevant
    occluders, or too many edges).
    """
    dt = np.result_type(p.dtype, verts.dtype)
    k = verts.shape[-2]
    m_occ, ko = occluders.shape[-3], occluders.shape[-2]
    # The callback's `expand_dims`: every argument has all batch axes, size 1 where unbatched.
    batch = np.broadcast_shapes(p.shape[:-1], n.shape[:-1], verts.shape[:-2], occluders.shape[:-3])
    p = np.broadcast_to(np.asarray(p, dt), batch + (3,)).reshape(-1, 3)
    b = p.shape[0]
    n = np.broadcast_to(np.asarray(n, dt), batch + (3,)).reshape(b, 3)
    # A light or an occluder set shared by the whole batch (size-1 leading axes, the callback's
    # `expand_dims`) stays one copy.
    verts = _batch_or_one(np.asarray(verts, dt), batch, 2)
    occ_all = _batch_or_one(np.asarray(occluders, dt), batch, 3)

    # Occluder selection (`_bsp.select_occluders`).
    relevant = _np_relevance(p, n, verts, occ_all, closed)
    count_sel = np.sum(relevant, axis=-1)
    idx = _np_first_true(relevant, max_active, m_occ)
    padded = np.concatenate([occ_all, np.zeros((occ_all.shape[0], 1, ko, 3), dt)], axis=1)
    occ = padded[np.arange(padded.shape[0])[:, None] if padded.shape[0] > 1 else 0, idx]  # (B, A, Ko, 3)
    verts = np.broadcast_to(verts, (b, k, 3))

    # Receivers without a relevant occluder: the emitter's edges clipped to the horizon (the
    # device kernel also returns the dummies' zero-length edges there: they add exactly 0).
    k1 = k + 1
    kq = ko + 1
    t_ps = 2 * k1
    t_pe = t_ps + max_active * kq
    t_e0 = t_pe + max_active * kq
    n_table = t_e0 + 1
    e0 = verts[:, 0]
    in_front = _np_dot(_newell_np(verts), p - e0) > 0
    out_sc = np.full((b, capacity), t_e0, np.int64)
    out_ec = np.full((b, capacity), t_e0, np.int64)
    used = np.zeros((b, capacity), bool)
    count = np.zeros(b, np.int64)
    trivial = count_sel == 0
    out_sc[:, :k1] = np.where(trivial[:, None], np.arange(k1), t_e0)
    out_ec[:, :k1] = np.where(trivial[:, None], k1 + np.arange(k1), t_e0)
    used[:, :k1] = (trivial & in_front)[:, None]

    # How the device forms each table point (`culled_visible_edges_host`): the light's edges
    # clipped to the receiver's horizon, the selected occluders' edges clipped to the lit side
    # of the emitter plane (then projected), e0.
    e_starts, e_ends, (ls_a, ls_b, ls_i, le_a, le_b, le_i, bad) = _np_horizon_clip_edges(p, n, verts)
    rec_a = np.zeros((b, n_table), np.int64)
    rec_b = np.zeros((b, n_table), np.int64)
    rec_i = np.zeros((b, n_table), bool)
    rec_a[:, :k1], rec_b[:, :k1], rec_i[:, :k1] = ls_a, ls_b, ls_i
    rec_a[:, k1:t_ps], rec_b[:, k1:t_ps], rec_i[:, k1:t_ps] = le_a, le_b, le_i
    sub = np.flatnonzero(~trivial)
    n_pl = (max_active + 1) * max(k1, kq)
    if sub.size:
        sc_s, ec_s, used_s, count_s, orec, obad = _codes_shadowed(p[sub], n[sub], verts[sub], occ[sub], e_starts[sub],
                                                                   e_ends[sub], capacity)
        out_sc[sub], out_ec[sub], used[sub], count[sub] = sc_s, ec_s, used_s, count_s
        for arr, part in zip((rec_a, rec_b, rec_i), orec, strict=True):
            arr[sub, t_ps:t_e0] = part
        bad[sub] |= obad
    # Slot codes -> (kind, a, b, interp): kind 0 a light point, 1 an occluder point (vertex
    # ids into the light's then the selected occluders' vertices), 2 the crossing of planes a < b.
    codes = np.concatenate([out_sc, out_ec], axis=1)  # (B, 2 capacity)
    is_tab = codes < n_table
    tab = np.where(is_tab, codes, 0)
    kk = np.where(is_tab, 0, codes - n_table)
    kind = np.where(is_tab, np.where((tab >= t_ps) & (tab < t_e0), 1, 0), 2)
    ra = np.where(is_tab, _np_take_last(rec_a, tab), kk // n_pl)
    rb = np.where(is_tab, _np_take_last(rec_b, tab), kk % n_pl)
    ri = is_tab & _np_take_last(rec_i, tab)
    overflow = (count_sel > max_active) | (count > capacity) | bad
    shape = batch + (2 * capacity,)
    return (idx.astype(np.int32).reshape(batch + (max_active,)), kind.astype(np.int32).reshape(shape),
            ra.astype(np.int32).reshape(shape), rb.astype(np.int32).reshape(shape), ri.reshape(shape),
            used.reshape(batch + (capacity,)), overflow.reshape(batch))


def _codes_shadowed(p: np.ndarray, n: np.ndarray, verts: np.ndarray, occ: np.ndarray, e_starts: np.ndarray,
                    e_ends: np.ndarray, capacity: int) -> tuple[Any, ...]:
    """`host_culled_codes` for receivers `p, n (B, 3)` with the light `verts (B, K, 3)` (its
    edges clipped to the horizon `e_starts`, `e_ends (B, K + 1, 3)`) and their selected
    occluders `occ (B, A, Ko, 3)`: `(start_codes, end_codes, used, count, recipes,
    bad)`: table codes, the selected occluders' table recipes `(a, b, interp)` (each
    `(B, 2 A (Ko + 1))`: starts, then ends) and whether one is not convex enough for them."""
    dt = p.dtype
    b, k = verts.shape[0], verts.shape[1]
    a_occ, ko = occ.shape[1], occ.shape[2]
    eps = float(_finfo(dt).eps)

    # `_clip._candidates`.
    e0 = verts[:, 0]
    ne = _newell_np(verts)
    hp = _np_dot(ne, p - e0)
    e_scale = _np_pow2_scale(np.max(np.abs(ne), axis=-1))
    ne, hp = ne * e_scale[:, None], hp * e_scale
    e_normals = _np_rescale_rows(np.concatenate([_np_edge_planes(p, verts), n[:, None, :]], axis=1))  # (B, K+1, 3)

    # `_clip._occluder_sides` / `_occluder_regions`.
    rel = occ - p[:, None, None, :]
    sigma = _np_pow2_scale(np.max(np.abs(rel), axis=(2, 3)))  # (B, A)
    rel = rel * sigma[..., None, None]
    no = _newell_np(rel)  # (B, A, 3)
    nxt = _np_next(rel, 2)
    bound_no = np.sum(_np_abs_cross(rel, nxt), axis=2)
    h = np.sum(no[:, :, None, :] * rel, axis=-1)  # (B, A, Ko)
    err = np.sum(bound_no[:, :, None, :] * np.abs(rel), axis=-1)
    bound = (ko + 8) / 2 * eps * err
    d_o = h[..., 0]
    s = np.where(d_o < 0, 1.0, -1.0).astype(dt)
    active = np.all(-s[..., None] * h > bound, axis=-1)  # (B, A)
    real = np.any(_np_next(occ, 2) != occ, axis=-1)
    o_planes = np.where(real[..., None], _np_cross(nxt, rel), 0.0)
    o_planes = _np_rescale_rows(s[..., None, None] * o_planes)
    n_cut = (hp[:, None] * sigma * -s)[..., None] * no + np.abs(d_o)[..., None] * ne[:, None, :]
    o_normals = np.concatenate([o_planes, _np_rescale_rows(n_cut)[:, :, None, :]], axis=2)  # (B, A, Ko+1, 3)

    o_s, o_e, (os_a, os_b, os_i, oe_a, oe_b, oe_i, obad) = _np_horizon_clip_edges(
        e0[:, None, :], ne[:, None, :], occ)  # (B, A, Ko+1, 3)
    base = k + ko * np.arange(a_occ)[None, :, None]  # the selected occluders' vertex ids
    orec = (np.concatenate([(os_a + base).reshape(b, -1), (oe_a + base).reshape(b, -1)], axis=1),
            np.concatenate([(os_b + base).reshape(b, -1), (oe_b + base).reshape(b, -1)], axis=1),
            np.concatenate([os_i.reshape(b, -1), oe_i.reshape(b, -1)], axis=1))
    kq = ko + 1
    # Cyrus-Beck of every occluder edge against the cone (p, E_h) (`_clip._cyrus_beck`).
    cone = e_normals
    pp = p[:, None, None, :]
    g0 = np.einsum("bajx,bcx->bajc", o_s - pp, cone)
    g1 = np.einsum("bajx,bcx->bajc", o_e - o_s, cone)
    tc = _np_safe_div(-g0, g1)
    t_lo = np.where(g1 > 0, tc, 0.0)
    t_hi = np.where(g1 < 0, tc, 1.0)
    i0 = np.argmax(t_lo, axis=-1)
    i1 = np.argmin(t_hi, axis=-1)
    t0 = np.maximum(_np_take_last(t_lo, i0[..., None])[..., 0], 0.0)
    t1 = np.minimum(_np_take_last(t_hi, i1[..., None])[..., 0], 1.0)
    ok = np.all((g1 != 0) | (g0 >= 0), axis=-1) & (t1 > t0) & active[..., None]  # (B, A, Kq)
    bi = np.arange(b)[:, None, None]
    cone_i0, cone_i1 = cone[bi, i0], cone[bi, i1]  # (B, A, Kq, 3)
    ppj, nej, hpj = p[:, None, None, :], ne[:, None, None, :], hp[:, None, None]
    x0 = _np_crossing_point(ppj, _np_cross(cone_i0, o_normals), nej, hpj)
    x1 = _np_crossing_point(ppj, _np_cross(cone_i1, o_normals), nej, hpj)
    pr_s = _np_project(ppj, o_s, nej, hpj)
    pr_e = _np_project(ppj, o_e, nej, hpj)
    e0j = e0[:, None, None, :]
    a2 = np.where(ok[..., None], np.where((t0 > 0)[..., None], x0, pr_s), e0j)
    b2 = np.where(ok[..., None], np.where((t1 < 1)[..., None], x1, pr_e), e0j)
    ccw = (s > 0)[:, :, None]
    q_starts = np.where(ccw[..., None], b2, a2)
    q_ends = np.where(ccw[..., None], a2, b2)

    # Device table: e_starts (K+1), e_ends (K+1), projected o_s (A Kq), projected o_e (A Kq), e0.
    n_planes = max(k + 1, kq)
    n_pl = (a_occ + 1) * n_planes
    t_es, t_ee = 0, k + 1
    t_ps, t_pe = 2 * (k + 1), 2 * (k + 1) + a_occ * kq
    t_e0 = 2 * (k + 1) + 2 * a_occ * kq
    n_table = t_e0 + 1
    u = np.arange(a_occ * kq).reshape(a_occ, kq)
    plane_q = (1 + np.arange(a_occ))[:, None] * n_planes + np.arange(kq)[None, :]  # (A, Kq) plane ids
    cross0 = n_table + i0 * n_pl + plane_q  # cone plane ids (region 0) come first
    cross1 = n_table + i1 * n_pl + plane_q
    a_code = np.where(ok, np.where(t0 > 0, cross0, t_ps + u), t_e0)
    b_code = np.where(ok, np.where(t1 < 1, cross1, t_pe + u), t_e0)
    qs_code = np.where(ccw, b_code, a_code).reshape(b, -1)
    qe_code = np.where(ccw, a_code, b_code).reshape(b, -1)

    starts = np.concatenate([e_starts, q_starts.reshape(b, -1, 3)], axis=1)  # (B, C, 3)
    ends = np.concatenate([e_ends, q_ends.reshape(b, -1, 3)], axis=1)
    n_cand = starts.shape[1]
    cand_start = np.concatenate([np.broadcast_to(t_es + np.arange(k + 1), (b, k + 1)), qs_code], axis=1)
    cand_end = np.concatenate([np.broadcast_to(t_ee + np.arange(k + 1), (b, k + 1)), qe_code], axis=1)
    own = np.concatenate([e_normals, o_normals.reshape(b, -1, 3)], axis=1)  # (B, C, 3)
    reg_ids = np.arange(n_pl).reshape(a_occ + 1, n_planes)
    own_id = np.concatenate([reg_ids[0, : k + 1], reg_ids[1:, :kq].reshape(-1)])  # (C,)
    sig = np.concatenate([np.ones(k + 1, dt), -np.ones(a_occ * kq, dt)])
    region = np.concatenate([np.zeros(k + 1, np.int64), np.repeat(np.arange(1, a_occ + 1), kq)])
    planes = np.concatenate(
        [_np_pad_axis(e_normals, 1, n_planes)[:, None], _np_pad_axis(o_normals, 2, n_planes)], axis=1)  # (B, R, P, 3)
    reg_active = np.concatenate([np.ones((b, 1), bool), active], axis=1)  # (B, R)
    reg_valid = np.any(planes != 0, axis=-1) & reg_active[..., None]  # (B, R, P)
    in_front = hp > 0

    # `_clip.edge_breakpoints` / `_interval_on_region`, every candidate against every region.
    tol = COLLINEAR_EPS * eps
    n_reg = a_occ + 1
    # Component by component on (B, C, R, P) arrays: the same sums, without (B, C, R, P, 3)
    # temporaries (this is most of the host's time).
    d = ends - starts
    rs = starts - p[:, None, :]
    px, py, pz = (planes[None, ..., i].transpose(1, 0, 2, 3) for i in range(3))  # (B, 1, R, P)
    sx, sy, sz = (rs[..., i][:, :, None, None] for i in range(3))  # (B, C, 1, 1)
    dx, dy, dz = (d[..., i][:, :, None, None] for i in range(3))
    g0 = sx * px + sy * py + sz * pz  # (B, C, R, P)
    g1 = dx * px + dy * py + dz * pz
    un = _np_safe_normalize(planes)[:, None]  # (B, 1, R, P, 3)
    uo = _np_safe_normalize(own)[:, :, None, None, :]  # (B, C, 1, 1, 3)
    ux, uy, uz = un[..., 0], un[..., 1], un[..., 2]
    ox, oy, oz = uo[..., 0], uo[..., 1], uo[..., 2]
    c1, c2, c3 = oy * uz - oz * uy, oz * ux - ox * uz, ox * uy - oy * ux  # uo x un
    valid = reg_valid[:, None]
    collinear = valid & (c1 * c1 + c2 * c2 + c3 * c3 <= tol * tol)
    side_ok = sig[None, :, None, None] * (ux * ox + uy * oy + uz * oz) > 0
    generic = valid & ~collinear
    tcr = _np_safe_div(-g0, g1)
    t_lo = np.where(generic & (g1 > 0), tcr, -np.inf)
    t_hi = np.where(generic & (g1 < 0), tcr, np.inf)
    i_lo = np.argmax(t_lo, axis=-1)  # (B, C, R)
    i_hi = np.argmin(t_hi, axis=-1)
    lo = _np_take_last(t_lo, i_lo[..., None])[..., 0]
    hi = _np_take_last(t_hi, i_hi[..., None])[..., 0]
    c_nc = np.all(~generic | (g1 != 0) | (g0 >= 0), axis=-1)
    c_c = np.all(~collinear | side_ok, axis=-1)
    any_c = np.any(collinear, axis=-1)
    region_ids = np.arange(n_reg)
    other = region_ids[None, None, :] != region[None, :, None]  # (1, C, R)
    cuts = np.concatenate([np.where(other, lo, 0.0), np.where(other, hi, 0.0)], axis=-1)  # (B, C, 2R)
    ids = np.concatenate([region_ids * n_planes + i_lo, region_ids * n_planes + i_hi], axis=-1)
    n_tab = 2 * n_cand
    i_own = own_id[None, :, None]
    cut_codes = n_tab + np.minimum(i_own, ids) * n_pl + np.maximum(i_own, ids)
    ci = np.arange(n_cand)[None, :, None]
    code_a, code_b = ci, n_cand + ci
    cut_codes = np.where(cuts <= 0, code_a, np.where(cuts >= 1, code_b, cut_codes))
    ts = np.concatenate([np.zeros((b, n_cand, 1), dt), np.ones((b, n_cand, 1), dt), np.clip(cuts, 0.0, 1.0)], axis=-1)
    codes = np.concatenate([np.broadcast_to(code_a, (b, n_cand, 1)), np.broadcast_to(code_b, (b, n_cand, 1)),
                            cut_codes], axis=-1)

    # `_clip._boundary_runs.split_edge`.
    order = np.argsort(ts, axis=-1, kind="stable")
    ts = _np_take_last(ts, order)
    codes = _np_take_last(codes, order)
    t0p = ts[..., :-1]
    tm = 0.5 * (t0p + ts[..., 1:])
    inside = (lo[:, :, None, :] < tm[..., None]) & (tm[..., None] < hi[:, :, None, :])  # (B, C, pieces, R)
    member = inside & (c_nc & c_c & reg_active[:, None, :])[:, :, None, :]
    tie = inside & (c_nc & any_c)[:, :, None, :] & (region_ids[None, :] < region[:, None])[None, :, None, :]
    blocked = np.any(((member & (region_ids > 0)) | tie) & other[:, :, None, :], axis=-1)
    free = ~blocked
    n_pieces = free.shape[-1]
    pidx = np.arange(n_pieces)
    last = np.concatenate([~free[..., 1:], np.ones(free.shape[:-1] + (1,), bool)], axis=-1)
    run_end = np.minimum.accumulate(np.where(last, pidx, n_pieces - 1)[..., ::-1], axis=-1)[..., ::-1]
    begins = free & np.concatenate([np.ones(free.shape[:-1] + (1,), bool), ~free[..., :-1]], axis=-1)
    keep = begins & (_np_take_last(ts, run_end + 1) > t0p)
    end_codes = _np_take_last(codes, run_end + 1)
    sel = _np_first_true(keep, n_reg, 0)
    run_valid = np.arange(n_reg) < np.sum(keep, axis=-1, keepdims=True)
    sc = _np_take_last(codes, sel).reshape(b, -1)
    ec = _np_take_last(end_codes, sel).reshape(b, -1)
    run_valid = (run_valid.reshape(b, -1)) & in_front[:, None]

    # Compaction (`visible_edges_compact`), and `_boundary_runs`'s codes -> the device's.
    count = np.sum(run_valid, axis=-1)
    slot = _np_first_true(run_valid, capacity, 0)
    used = np.arange(capacity) < count[:, None]
    sc = _np_take_last(sc, slot)
    ec = _np_take_last(ec, slot)

    def device_code(c: np.ndarray) -> np.ndarray:
        is_start = c < n_cand
        is_end = (c >= n_cand) & (c < n_tab)
        cs = _np_take_last(cand_start, np.clip(c, 0, n_cand - 1))
        ce = _np_take_last(cand_end, np.clip(c - n_cand, 0, n_cand - 1))
        return np.where(is_start, cs, np.where(is_end, ce, c - n_tab + n_table))

    out_sc = np.where(used, device_code(sc), t_e0)
    out_ec = np.where(used, device_code(ec), t_e0)
    return out_sc, out_ec, used, count, orec, np.any(obad, axis=-1)



# --------------------------------------------------------------------------------------
# The same combinatorics compiled (`_clipc.c`, built by setup.py; ctypes).
# --------------------------------------------------------------------------------------


@functools.cache
def _clipc() -> Any:
    """The compiled kernel's ctypes library, or None where the extension was not built (no C
    compiler when the package was installed: `host_culled_codes` in NumPy is used instead)."""
    import ctypes

    try:
        from . import _clipc as mod  # type: ignore[attr-defined]
    except ImportError:
        return None
    lib = ctypes.CDLL(mod.__file__)
    if lib.jaxshadow_clipc_abi_version() != 2:
        return None
    i64, i32, ptr = ctypes.c_int64, ctypes.c_int, ctypes.c_void_p
    for name in ("jaxshadow_host_codes_f64", "jaxshadow_host_codes_f32"):
        fn = getattr(lib, name)
        fn.argtypes = [i64] + [i32] * 6 + [ptr] * 2
        fn.restype = i32
    return lib


def compiled_available() -> bool:
    """Whether the compiled host combinatorics (`_clipc`) are built and loadable."""
    return _clipc() is not None


def _packed_width(k: int, m: int, ko: int, max_active: int, capacity: int) -> tuple[int, int]:
    """Row widths of the packed input `[p | n | verts | occluders]` and output `[idx | kind |
    a | b | interp | used | overflow]` (`_clipc.c`, `culled_visible_edges_host`)."""
    return 6 + 3 * k + 3 * m * ko, max_active + 9 * capacity + 1


def _unpack_codes(out: Any, max_active: int, capacity: int) -> tuple[Any, ...]:
    """A packed result `(..., W_out)` (NumPy or JAX) as `host_culled_codes`'s `(idx, kind, a,
    b, interp, used, overflow)`, the last three boolean."""
    two = 2 * capacity
    kind, ra, rb, ri = (out[..., max_active + i * two: max_active + (i + 1) * two] for i in range(4))
    return (out[..., :max_active], kind, ra, rb, ri != 0, out[..., max_active + 4 * two: -1] != 0,
            out[..., -1] != 0)


def _codes_packed_c(x: np.ndarray, k: int, m: int, ko: int, max_active: int, capacity: int,
                    closed: bool) -> np.ndarray:
    """The compiled combinatorics on packed rows `x (..., W_in)` (float32 or float64) ->
    `(..., W_out)` int32 (`_packed_width`)."""
    lib = _clipc()
    if lib is None:
        raise RuntimeError("jaxshadow._clipc is not built (reinstall jaxshadow with a C compiler)")
    if x.dtype not in (np.float32, np.float64):
        x = x.astype(np.float64)
    x = np.ascontiguousarray(x)
    w_in, w_out = _packed_width(k, m, ko, max_active, capacity)
    if x.shape[-1] != w_in:
        raise ValueError(f"_codes_packed_c: rows of {x.shape[-1]} values, expected {w_in}")
    out = np.empty(x.shape[:-1] + (w_out,), np.int32)
    fn = lib.jaxshadow_host_codes_f64 if x.dtype == np.float64 else lib.jaxshadow_host_codes_f32
    if fn(x.size // w_in, k, m, ko, max_active, capacity, int(bool(closed)), x.ctypes.data, out.ctypes.data):
        raise ValueError(f"_codes_packed_c: bad sizes (K={k}, Ko={ko}, M={m}, max_active={max_active}, "
                         f"capacity={capacity})")
    return out


def host_culled_codes_c(p: np.ndarray, n: np.ndarray, verts: np.ndarray, occluders: np.ndarray, max_active: int,
                        capacity: int, closed: bool = False) -> tuple[np.ndarray, ...]:
    """`host_culled_codes`, compiled (`_clipc.c`: the same arithmetic, receiver by receiver).
    The same arguments and results; float32 and float64 (other dtypes are computed in float64).
    ~7x faster than NumPy on 48 receivers with this function's packing; the fit's callback,
    which passes packed rows (`_codes_packed_c`), takes ~0.2 ms a call against ~9 ms in NumPy.
    Raises RuntimeError where the extension is not built."""
    dt = np.result_type(p.dtype, verts.dtype)
    if dt not in (np.float32, np.float64):
        dt = np.dtype(np.float64)
    k = verts.shape[-2]
    m_occ, ko = occluders.shape[-3], occluders.shape[-2]
    batch = np.broadcast_shapes(p.shape[:-1], n.shape[:-1], verts.shape[:-2], occluders.shape[:-3])
    rows = [np.broadcast_to(np.asarray(a, dt).reshape(a.shape[: a.ndim - c] + (-1,)), batch + (w,))
            for a, c, w in ((p, 1, 3), (n, 1, 3), (verts, 2, 3 * k), (occluders, 3, 3 * m_occ * ko))]
    out = _codes_packed_c(np.concatenate(rows, axis=-1), k, m_occ, ko, max_active, capacity, closed)
    return _unpack_codes(out, max_active, capacity)


def _pinned(x: Array) -> Array:
    """`x (K, ...)` as the result of a product by the identity (the same values, exactly):
    XLA does not fuse a dot's operands into its consumers, so whatever computed `x` is computed
    once, not again inside every fused loop that reads it."""
    return jnp.dot(jnp.eye(x.shape[0], dtype=x.dtype), x, precision=jax.lax.Precision.HIGHEST)


def culled_visible_edges_host(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    verts: Float[Array, "k 3"],
    occluders: Float[Array, "m ko 3"],
    max_active: int,
    closed: bool = False,
) -> tuple[Float[Array, "b 3"], Float[Array, "b 3"], Bool[Array, ""]]:
    r"""`_bsp.culled_visible_edges` with the combinatorics computed by `host_culled_codes`.

    The same arguments and results: `p (3,)` receiver, `n (3,)` unit normal, `verts (K, 3)`
    padded convex light, `occluders (M, Ko, 3)`, `max_active` (static int), `closed` (static);
    returns `(starts, ends, overflow)` in `_bsp.edge_capacity(K, Ko, max_active)` slots.
    Traceable under `jit`, `vmap` (one host call for the whole batch) and forward- and
    reverse-mode differentiation (the recipes carry no gradient; the geometry is
    differentiated). Every endpoint is computed from its recipe (`host_culled_codes`)."""
    k, ko = verts.shape[0], occluders.shape[1]
    cap = edge_capacity(k, ko, max_active)
    # One packed input, `[p | n | verts | occluders]` per receiver, and one packed int32 result,
    # `[idx (A) | kind, a, b, interp (2 cap each) | used (cap) | overflow]`: the callback's fixed
    # cost is mostly JAX putting each argument and result on the device (~0.2 ms an array: with
    # eleven of them, more than the compiled combinatorics take).
    m = occluders.shape[0]
    width = _packed_width(k, m, ko, max_active, cap)[1]
    compiled = compiled_available()

    def host(x: Any) -> np.ndarray:
        x = np.asarray(x)
        if compiled:
            return _codes_packed_c(x, k, m, ko, max_active, cap, closed)
        lead = x.shape[:-1]
        out = host_culled_codes(x[..., :3], x[..., 3:6], x[..., 6: 6 + 3 * k].reshape(lead + (k, 3)),
                                x[..., 6 + 3 * k:].reshape(lead + (m, ko, 3)), max_active, cap, closed)
        return np.concatenate([y.astype(np.int32, copy=False) for y in out[:-1]] + [out[-1][..., None].astype(np.int32)],
                              axis=-1)

    sg = jax.lax.stop_gradient
    dt_in = jnp.result_type(p, verts)
    x = jnp.concatenate([p, n, verts.reshape(-1), occluders.reshape(-1)]).astype(dt_in)
    packed = jax.pure_callback(host, jax.ShapeDtypeStruct((width,), jnp.int32), sg(x), vmap_method="expand_dims")
    idx, kind, ia, ib, interp, used, overflow = _unpack_codes(packed, max_active, cap)
    dt = p.dtype
    # The light's vertices (and their tangents) computed once, as a dot's result: XLA:CPU fuses
    # the elementwise chain that made them (in a fit, the pose from the parameters) into every
    # consumer, recomputing it per element of the (receivers x edge slots) arrays below (the
    # same values; ~9% of a fit's evaluation, `benchmarks/README.md`, Session 10).
    verts = _pinned(verts)
    padded = jnp.concatenate([occluders, jnp.zeros((1,) + occluders.shape[1:], occluders.dtype)])
    occ = padded[idx]
    e0, ne, hp, e_normals = _emitter_frame(p, n, verts)
    o_normals, _, _ = _occluder_regions(p, occ, ne, hp)
    planes = _region_planes(e_normals, o_normals).reshape(-1, 3)
    # Table points as `horizon_clip_edges` forms them (a vertex, or an edge's crossing with the
    # receiver's horizon / the emitter plane), the occluders' then projected (`_project`).
    # The vertices are picked by one-hot products, not gathers: XLA:CPU fuses whatever computed
    # a gather's operand into it, so that in a fit the light's pose and its tangents were
    # recomputed from the parameters for every gathered coordinate (~17% of an evaluation). A
    # dot takes its operands computed. Exact (finite inputs): each row sums one product by 1
    # and zeros, in the highest precision.
    V = jnp.concatenate([verts, occ.reshape(-1, 3)])
    on_occ = (kind == 1)[:, None]
    is_pt = kind < 2
    slots = jnp.arange(V.shape[0])[None, :]
    hi = jax.lax.Precision.HIGHEST
    va = jnp.dot((jnp.where(is_pt, ia, 0)[:, None] == slots).astype(V.dtype), V, precision=hi)
    vb = jnp.dot((jnp.where(is_pt, ib, 0)[:, None] == slots).astype(V.dtype), V, precision=hi)
    h = jnp.where(on_occ, ne, n)
    q = jnp.where(on_occ, e0, p)
    da = jnp.sum((va - q) * h, axis=-1)
    db = jnp.sum((vb - q) * h, axis=-1)
    den = jnp.where(interp, da - db, 1.0)
    x = va + jnp.where(interp, da / den, 0.0)[:, None] * (vb - va)
    x = jnp.where(on_occ, jax.vmap(_project, in_axes=(None, 0, None, None))(p, x, ne, hp), x)
    cr = jnp.cross(planes[jnp.where(is_pt, 0, ia)], planes[jnp.where(is_pt, 1, ib)])
    y = jax.vmap(_crossing_point, in_axes=(None, 0, None, None))(p, cr, ne, hp)
    pts = jnp.where(is_pt[:, None], x, y).astype(dt)
    use = used[:, None]
    return jnp.where(use, pts[:cap], e0[None, :]), jnp.where(use, pts[cap:], e0[None, :]), overflow
