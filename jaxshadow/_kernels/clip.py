r"""Exact visibility: the visible part of a light as a boundary contour (Campbell & Fussell §3.1, §4.2.2).

**Region.** For a receiver $p$ (normal $n$) and a convex polygon light $E$ the visible region,
in the emitter plane, is

$$R = E_h \setminus \bigcup_j Q_j,\qquad E_h = E \cap \{n\cdot(x-p) \ge 0\},$$

with $Q_j$ the central projection from $p$ onto the emitter plane of the *effective blocker*
of occluder $j$: the part of it on the lit side of the emitter plane (C&F §4.2.2; the part
behind $p$ never reaches the emitter). The form factor is Lambert's contour sum over
$\partial R$ (C&F eq. 11), evaluated by `jaxshadow._kernels.polygon.contour_form_factor`.

**Everything is a plane through p.** A direction $r$ from $p$ (towards the emitter plane) is in
$E_h$ iff $r\cdot N \ge 0$ for the $K$ planes through $p$ and the emitter edges, and for the
horizon plane $N = n$; it is in $Q_j$ iff $r \cdot N \ge 0$ for the planes through $p$ and the
occluder's edges (its sign fixed by the side $p$ is on) and for the plane through $p$ and the
line where the occluder crosses the emitter plane,
$N_L = h_p\,\mathrm{sgn}(d_o)\,N_o + |d_o|\,N_e$ ($h_p = N_e\cdot(p-e_0)$, $d_o = N_o\cdot(o_0-p)$;
it says "the ray meets the occluder before the emitter"). These half-spaces come straight from
the input vertices, so they are as accurate as the data however the regions get clipped;
unbounded projections (occluders reaching behind $p$) never have to be formed. Only the
directions of these normals matter, so each (and $N_e$ with $h_p$) is brought to order one
by an exact power of two: the values are unchanged and nothing under- or overflows in float32,
in the gradients either, for an occluder 1e-9 from $p$. An occluder is ignored when $p$ cannot
be told apart from its plane (it then blocks a zero solid angle); the test compares the
heights of its vertices above $p$ with their own rounding-error bounds (`_occluder_sides`).

**Edge soup.** Candidate edges are the $K+1$ edges of $E_h$ (`horizon_clip_edges`) and, per
occluder, the $K_o+1$ edges of its effective blocker, clipped in 3-D to the pyramid $(p, E_h)$
(Cyrus-Beck, fixed shape) and projected onto the emitter plane (reversed: $R$ lies outside
$Q_j$). Every candidate edge is cut at the parameters where it enters and leaves every other
region ($2$ per region, so all shapes are static) and each piece is kept by a test of its
midpoint *against those same parameters* (so splitting and classification never disagree).
Every crossing vertex is computed once, as the line common to the two planes through $p$
(cross product of their normals, lower plane id first) met with the emitter plane, so the two
edges that meet there share bit-identical endpoints and the contour stays closed even at
grazing crossings (computing each side's parameter separately leaves gaps of order
$\epsilon/\sin\alpha$ that cost ~1e-5 in float32).
The region tested is the one on $R$'s side of the edge, one-sidedly: a piece lying on the
boundary line of another region counts as inside it iff that region's interior is on $R$'s
side (C&F's "omit degenerate planes" made exact).

**Combinatorics and geometry apart.** `_boundary_runs` does the splitting and the membership
tests without gradients and returns, per kept run of consecutive pieces of one candidate edge
(at most $M + 1$ per edge: a region's interval removes one stretch), integer codes for its two
endpoints: a candidate edge's own end, or the crossing of two planes through $p$ (canonical
order). `_decode` recomputes just those points from the inputs; the boundary is piecewise
constant in the inputs, so its derivatives are exactly the endpoints' (what `jax.jacfwd`
differentiates is the few kept edges, not the splitting machinery). The shadow engine
(`csrc/shadowc.cc`, `_shadows.binding`) produces the same codes on the host from each receiver's
candidates only; `_decode`'s twin there recomputes the points the same way.

**Memory.** The edge soup has $M + 1$ slots per candidate edge, $O(M^2)$ per receiver, and
each candidate is split against $M + 1$ regions of $P$ planes. Candidates are split a batch at
a time (`split_batch`, about `SPLIT_PAIRS` (edge, region plane) pairs), a piece's membership
is an interval-stabbing count beyond `STAB_DENSE` regions (`_stabbed`, $O(M \log M)$ per
edge instead of pieces x regions), and `visible_edge_sums` adds a contour's sums batch by batch without forming the
soup (reverse mode recomputes each batch), so a receiver's memory does not grow with $M^2$.
A segment light's $2M + 1$ pieces are classified by the same interval-stabbing counts
(`visible_pieces`) beyond `SEGMENT_DENSE` comparisons and integrated `SEGMENT_PIECES` at a
time (`visible_segment_sum`), $O(M)$ per receiver.

**Tie-break (coincident edges).** Two candidate pieces on the same line (normals of their planes
through $p$ parallel within `64 eps`) that both bound $R$ on the same side describe the same
boundary piece; exactly one is kept, by priority: the emitter's edges first, then occluders in
index order. Concretely: an occluder edge lying on an edge of $E_h$, or on an edge of a
lower-index occluder, is dropped; an emitter edge (or a higher-index occluder edge) under such
a coincident edge is kept or dropped by the one-sided test alone. Opposite-side coincidences
(two mesh triangles sharing an edge) drop both, as they should.

**Float64 rules (the engine's `boundary_runs`).** The planes through $p$ and the edges are
`planes.edge_planes` (no cancellation for a short edge far from $p$; bit-identical for an edge
shared by two faces). Two occluder edges' planes are each off by their rounding, about
`64 eps` times their conditioning (`planes.plane_condition`): within that band of each other
they hold one line (on one line in space, `planes.collinear_in_space`: a T-junction; or unit
normals parallel within the band: edges of different faces coplanar with $p$), not a crossing
placed by rounding. An occluder edge whose end is the projection of a vertex that another
face's edge runs through crosses that face's plane exactly at the end (`_interval_on_region`).
The engine's third rule (a light corner on an occluder region's edge plane counts as inside
within that band) filters its regions' bounding boxes, which the device kernels do not have:
every candidate edge here is split against every region.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._core.geometry import check_finite_leaves, horizon_clip_edges, newell_normal
from .._core.misc import safe_div
from .linear import linear_irradiance_kernel
from .planes import (
    COLLINEAR_EPS,
    _cyrus_beck,
    _edge_planes,
    _eps,
    _interval_on_region,
    _occluder_regions,
    _occluder_sides,
    crossing_point,
    light_edge_point,
    near_planes,
    occluder_edges_point,
    plane_condition,
    pow2_scale,
    project,
    rescale_rows,
)
from .polygon import edge_term, form_factor_kernel

# An occluder within this elevation (radians) of a receiver's horizon blocks nothing
# (`_hugs_horizon`; geometry.h kHorizonBand).
HORIZON_BAND = 1e-7


class _Candidates(NamedTuple):
    """The candidate edges of the boundary of R (module docstring) and the regions' planes."""

    ne: Array  # (3,) emitter normal, scaled to order one
    hp: Array  # height of p above the emitter plane, scaled alike
    in_front: Array  # p strictly in front of the emitter
    e0: Array  # (3,) the emitter's first vertex (where dropped edges collapse)
    starts: Array  # (C, 3) candidate edges (E_h's K + 1, then each occluder's Ko + 1)
    ends: Array  # (C, 3)
    own: Array  # (C, 3) normal of the plane through p and the candidate's line
    own_id: Array  # (C,) its plane id (row of `planes`, flattened)
    sigma: Array  # (C,) +1: R lies on the interior side of `own` (E_h), -1: outside (occluders)
    region: Array  # (C,) 0 for E_h, j for occluder j
    planes: Array  # (M + 1, P, 3) each region's interior plane normals, zero-padded
    reg_valid: Array  # (M + 1, P) real planes of active regions
    reg_active: Array  # (M + 1,) E_h, and the occluders that are not degenerate seen from p
    cond: Array  # (M + 1, P) plane_condition of each occluder edge's plane, 0 for the other planes
    plane_ends: Array  # (M + 1, P, 2, 3) the two vertices of each occluder edge (zeros elsewhere; `_decode`
    # differentiates them, the splitting does not)
    start_pt: Array  # (C, 3) an occluder candidate's start in space (before projection)
    end_pt: Array  # (C, 3)
    start_ok: Array  # (C,) the start is that point's projection (not clipped by the pyramid)
    end_ok: Array  # (C,)
    light: Array  # (K, 3) the emitter's vertices (E_h's plane i < K runs through light edge i)


def _emitter_frame(p: Array, n: Array, verts: Array) -> tuple[Array, Array, Array, Array]:
    """`(e0, ne, hp, e_normals)`: the emitter's first vertex, its normal and the height
    `hp = ne . (p - e0)` of `p` above its plane, both times one exact power of two that brings
    `ne` to order one (only the direction of `ne` matters: small or large lights neither under-
    nor overflow), and the interior normals `(K + 1, 3)` of E_h's planes through `p` (the
    emitter's edges, then the horizon)."""
    e0 = verts[0]
    ne = newell_normal(verts)
    hp = jnp.dot(ne, p - e0)
    e_scale = pow2_scale(jnp.max(jnp.abs(ne)))
    e_normals = rescale_rows(jnp.concatenate([_edge_planes(p, verts), n[None, :]], axis=0))
    return e0, ne * e_scale, hp * e_scale, e_normals


def _region_planes(e_normals: Array, o_normals: Array) -> Array:
    """All regions' planes `(M + 1, P, 3)` (E_h's, then each occluder's), padded with zero
    normals (no constraint) to a common count `P = max(K + 1, Ko + 1)`."""
    n_planes = max(e_normals.shape[0], o_normals.shape[1])
    return jnp.concatenate(
        [
            jnp.pad(e_normals, ((0, n_planes - e_normals.shape[0]), (0, 0)))[None],
            jnp.pad(o_normals, ((0, 0), (0, n_planes - o_normals.shape[1]), (0, 0))),
        ],
        axis=0,
    )


def _hugs_horizon(p: Array, n: Array, occluders: Array) -> Array:
    """Per occluder: whether it stays within `HORIZON_BAND` (radians) of p's horizon. Every
    point of it rises at most `hmax` (its highest vertex) above the horizon plane and lies at
    least the distance d of its plane from p, so its elevation is below asin(hmax / d); within
    the band it blocks a projected solid angle under pi * HORIZON_BAND^2 (a form factor below
    1e-14), and clipping it at the horizon is ill-conditioned (its projection runs along E_h's
    horizon edge). Such occluders, and those wholly at or below the horizon, are dropped (the
    engine's face_status does the same)."""
    occ = jax.lax.stop_gradient(occluders)
    q, m = jax.lax.stop_gradient(p), jax.lax.stop_gradient(n)
    rel = occ - q[None, None, :]
    nh = m / jnp.sqrt(jnp.sum(m * m))
    hmax = jnp.max(jnp.sum(rel * nh[None, None, :], axis=-1), axis=1)  # (M,)
    no = jax.vmap(newell_normal)(rel)
    nn = jnp.sqrt(jnp.sum(no * no, axis=-1))
    d = jnp.abs(jnp.sum(no * rel[:, 0, :], axis=-1)) / jnp.where(nn > 0, nn, 1.0)
    return hmax <= HORIZON_BAND * jnp.where(nn > 0, d, 0.0)


def _cone_crossing(p, verts, cone, i, m, ne, hp):
    """Where the plane through p with normal `m` crosses E_h's plane `i` of `cone (K + 1, 3)`:
    light edge i's where the planes nearly coincide (`light_edge_point`), else the planes'
    common line."""
    k = verts.shape[0]
    on_edge = light_edge_point(p, verts[jnp.minimum(i, k - 1)], verts[(i + 1) % k], m)
    return jnp.where((i < k) & near_planes(cone[i], m), on_edge, crossing_point(p, jnp.cross(cone[i], m), ne, hp))


def _candidates(p: Array, n: Array, verts: Array, occluders: Array) -> _Candidates:
    """E_h's edges and the effective blockers' edges clipped to the pyramid (p, E_h), projected
    onto the emitter plane and reversed (R lies outside each Q_j), with every region's planes
    through p. Needs at least one occluder."""
    dtype = p.dtype
    m_occ, ko = occluders.shape[0], occluders.shape[1]
    k = verts.shape[0]
    e0, ne, hp, e_normals = _emitter_frame(p, n, verts)

    # Region 0: E_h. Its edges (and above, the interior normals of their planes through p).
    e_starts, e_ends = horizon_clip_edges(p, n, verts)

    # Regions 1..M: effective blockers, their edges clipped to the pyramid (p, E_h).
    o_normals, s, active = _occluder_regions(p, occluders, ne, hp)
    active = active & ~_hugs_horizon(p, n, occluders)
    o_s, o_e = jax.vmap(horizon_clip_edges, in_axes=(None, None, 0))(e0, ne, occluders)
    cone = e_normals

    def clip_one(a, b, n_q, act):
        t0, t1, ok, i0, i1 = _cyrus_beck(p, a, b, cone, n_q)
        ok = ok & act
        # A clipped end is the crossing of this edge's plane with an E_h plane (E_h's plane ids
        # come first in the canonical order, see `_decode`).
        a2 = jnp.where(t0 > 0, _cone_crossing(p, verts, cone, i0, n_q, ne, hp), project(p, a, ne, hp))
        b2 = jnp.where(t1 < 1, _cone_crossing(p, verts, cone, i1, n_q, ne, hp), project(p, b, ne, hp))
        return jnp.where(ok, a2, e0), jnp.where(ok, b2, e0), ok & (t0 <= 0), ok & (t1 >= 1)

    a2, b2, a_kept, b_kept = jax.vmap(jax.vmap(clip_one, in_axes=(0, 0, 0, None)))(o_s, o_e, o_normals, active)
    # Reverse: R lies outside Q_j, i.e. on the right of its counter-clockwise-from-p boundary.
    ccw = (s > 0)[:, None, None]
    q_starts = jnp.where(ccw, b2, a2)
    q_ends = jnp.where(ccw, a2, b2)
    # Each end's point in space where the pyramid did not clip it (its projection is the end).
    sv = jnp.where(ccw, o_e, o_s).reshape(-1, 3)
    ev = jnp.where(ccw, o_s, o_e).reshape(-1, 3)
    sv_ok = jnp.where(ccw[..., 0], b_kept, a_kept).reshape(-1)
    ev_ok = jnp.where(ccw[..., 0], a_kept, b_kept).reshape(-1)
    no_pt = jnp.zeros((k + 1, 3), dtype)
    no_ok = jnp.zeros((k + 1,), bool)

    planes = _region_planes(e_normals, o_normals)  # (M+1, P, 3)
    n_planes = planes.shape[1]
    # Occluder edges' conditioning and vertices (the rounding band of `_interval_on_region`).
    o_nxt = jnp.roll(occluders, -1, axis=1)
    o_real = jnp.any(o_nxt != occluders, axis=2)
    o_cond = jnp.where(o_real, plane_condition(p, occluders, o_nxt), 0.0)
    cond = jnp.zeros((m_occ + 1, n_planes), dtype).at[1:, :ko].set(o_cond)
    plane_ends = jnp.zeros((m_occ + 1, n_planes, 2, 3), dtype).at[1:, :ko].set(jnp.stack([occluders, o_nxt], axis=2))
    reg_active = jnp.concatenate([jnp.ones((1,), bool), active])
    reg_valid = jnp.any(planes != 0, axis=-1) & reg_active[:, None]
    reg_ids = jnp.arange((m_occ + 1) * n_planes, dtype=jnp.int32).reshape(m_occ + 1, n_planes)
    return _Candidates(
        ne=ne,
        hp=hp,
        in_front=hp > 0,
        e0=e0,
        starts=jnp.concatenate([e_starts, q_starts.reshape(-1, 3)], axis=0),
        ends=jnp.concatenate([e_ends, q_ends.reshape(-1, 3)], axis=0),
        own=jnp.concatenate([e_normals, o_normals.reshape(-1, 3)], axis=0),
        own_id=jnp.concatenate([reg_ids[0, : k + 1], reg_ids[1:, : ko + 1].reshape(-1)]),
        sigma=jnp.concatenate(
            [jnp.ones((k + 1,), dtype), -jnp.ones((m_occ * (ko + 1),), dtype)], axis=0
        ),
        region=jnp.concatenate(
            [
                jnp.zeros((k + 1,), jnp.int32),
                jnp.repeat(jnp.arange(1, m_occ + 1, dtype=jnp.int32), ko + 1),
            ]
        ),
        planes=planes,
        reg_valid=reg_valid,
        reg_active=reg_active,
        cond=jax.lax.stop_gradient(cond),
        plane_ends=plane_ends,
        start_pt=jax.lax.stop_gradient(jnp.concatenate([no_pt, sv], axis=0)),
        end_pt=jax.lax.stop_gradient(jnp.concatenate([no_pt, ev], axis=0)),
        start_ok=jnp.concatenate([no_ok, sv_ok]),
        end_ok=jnp.concatenate([no_ok, ev_ok]),
        light=verts,
    )


def edge_breakpoints(p, c: _Candidates, m_occ: int, ci, a, b, n_own, i_own, sig, reg) -> tuple:
    r"""Where candidate edge `ci` (`a -> b`, plane `n_own` with id `i_own`, side `sig`, region
    `reg`) enters and leaves every region, unsorted (`_boundary_runs`; no gradient: pass
    stop-gradient inputs).

    **Returns:** `(lo, hi, c_nc, c_c, any_c, other)`, each `(M + 1,)` as `_interval_on_region`
    per region (`other`: not the edge's own region), and the breakpoints `ts (2 + 2 (M + 1),)`
    in [0, 1] (0, 1, then the `lo`s and `hi`s of the other regions; the own region's are 0)
    with their endpoint codes `(2 + 2 (M + 1),)` (`_boundary_runs`)."""
    tol = COLLINEAR_EPS * _eps(p)
    n_cand = c.starts.shape[0]
    n_pl = c.planes.shape[0] * c.planes.shape[1]
    n_tab = 2 * n_cand
    region_ids = jnp.arange(m_occ + 1, dtype=jnp.int32)
    reg_ids = jnp.arange(n_pl, dtype=jnp.int32).reshape(c.planes.shape[:2])
    own_cond = c.cond.reshape(-1)[i_own]
    own_ends = c.plane_ends.reshape(-1, 2, 3)[i_own]
    at = (c.start_pt[ci], c.end_pt[ci], c.start_ok[ci], c.end_ok[ci])
    lo, hi, i_lo, i_hi, c_nc, c_c, any_c = jax.vmap(
        _interval_on_region, in_axes=(None, None, None, None, None, 0, 0, None, None, None, 0, 0, None)
    )(p, a, b - a, n_own, sig, c.planes, c.reg_valid, tol, own_cond, own_ends, c.cond, c.plane_ends, at)
    other = region_ids != reg
    cuts = jnp.concatenate([jnp.where(other, lo, 0.0), jnp.where(other, hi, 0.0)])
    ids = jnp.concatenate([reg_ids[region_ids, i_lo], reg_ids[region_ids, i_hi]])
    cut_codes = n_tab + jnp.minimum(i_own, ids) * n_pl + jnp.maximum(i_own, ids)
    code_a, code_b = ci, n_cand + ci
    cut_codes = jnp.where(cuts <= 0, code_a, jnp.where(cuts >= 1, code_b, cut_codes))
    ts = jnp.concatenate([jnp.zeros((1,), p.dtype), jnp.ones((1,), p.dtype), jnp.clip(cuts, 0.0, 1.0)])
    codes = jnp.concatenate([jnp.stack([code_a, code_b]), cut_codes])
    return lo, hi, c_nc, c_c, any_c, other, ts, codes


def _boundary_runs(
    p: Array, c: _Candidates, m_occ: int, pairs: int | None = None
) -> tuple[Int[Array, " r"], Int[Array, " r"], Bool[Array, " r"]]:
    r"""The combinatorial part of `visible_edges`: which pieces of which candidate edges bound R,
    and what their endpoints are, as integer *endpoint codes* (`_decode` turns them into points).

    Each candidate edge is cut at the parameters where it enters and leaves every other region
    (2 per region) and each piece is kept by a test of its midpoint against those same
    parameters (module docstring: one-sided membership, tie-break). Consecutive kept pieces of
    one edge are merged into a run (Lambert's edge term is additive along a line); a region's
    interval removes at most one stretch of an edge, so an edge has at most `M + 1` runs.

    Endpoint code `c`: `c < C` is candidate `c`'s start, `C <= c < 2C` candidate `c - C`'s
    end, and `2C + i P' + j` (`i < j`, `P' = (M + 1) P`) the crossing of planes `i` and `j`
    (the line common to the two planes through p met with the emitter plane; lower plane id
    first, so that the two edges meeting there compute the same point).

    Piecewise constant in the inputs (no gradient flows through it): the derivatives come from
    the geometry `_decode` turns the codes into. `c` is `_candidates(p, n, verts, occluders)`
    for `m_occ` occluders (computed once and shared with `_decode`). The candidate edges are
    split `split_batch` at a time (`pairs`: its size in (edge, region plane) pairs; static).

    **Returns:** `(start_codes, end_codes, valid)`, each `(C (M + 1),)` (`C` candidate edges).
    """
    n_cand = c.starts.shape[0]
    batch = split_batch(m_occ, c.planes.shape[1], n_cand, pairs)
    if batch >= n_cand:
        sc, ec, valid = _split_candidates(p, c, m_occ, jnp.arange(n_cand, dtype=jnp.int32))
    else:
        # `batch` candidates at a time (`lax.map`; the last batch padded with candidate 0):
        # each candidate's runs depend on it alone, so the codes are those of one batch of all
        # of them, and the intermediates are one batch's.
        idx = _batches(n_cand, batch)[0]
        out = jax.lax.map(lambda i: _split_candidates(p, c, m_occ, i), idx)
        sc, ec, valid = (o.reshape((-1,) + o.shape[2:])[:n_cand] for o in out)
    return sc.reshape(-1), ec.reshape(-1), valid.reshape(-1) & c.in_front


def _split_candidates(p: Array, c: _Candidates, m_occ: int, idx: Int[Array, " b"]) -> tuple[Array, Array, Array]:
    """`_boundary_runs` for the candidate edges `idx`: `(start_codes, end_codes, valid)`, each
    `(b, M + 1)` (`c.in_front` not applied)."""
    p, c = jax.lax.stop_gradient((p, c))
    region_ids = jnp.arange(m_occ + 1, dtype=jnp.int32)

    def split_edge(ci, a, b, n_own, i_own, sig, reg):
        lo, hi, c_nc, c_c, any_c, other, ts_all, codes_all = edge_breakpoints(
            p, c, m_occ, ci, a, b, n_own, i_own, sig, reg
        )
        order = jnp.argsort(ts_all)
        ts = ts_all[order]
        codes = codes_all[order]
        t0 = ts[:-1]
        tm = 0.5 * (t0 + ts[1:])
        # A piece is blocked when its midpoint is inside (lo < tm < hi) a region that removes
        # it: an occluder the edge's side is inside of, or (tie-break) a coincident edge of a
        # higher-priority (lower-index) region. The emitter's edges are kept outside every
        # occluder; an occluder's edges already lie inside E_h (clipped), so only the other
        # occluders and the tie-break remove them.
        member = c_nc & c_c & c.reg_active & (region_ids > 0)
        tie = c_nc & any_c & (region_ids < reg)
        free = ~_stabbed(lo, hi, (member | tie) & other, tm)
        n_pieces = free.shape[0]
        pieces = jnp.arange(n_pieces)
        last = jnp.concatenate([~free[1:], jnp.ones((1,), bool)])  # piece ends its run
        run_end = jax.lax.cummin(jnp.where(last, pieces, n_pieces - 1), reverse=True)
        begins = free & jnp.concatenate([jnp.ones((1,), bool), ~free[:-1]])
        keep = begins & (ts[run_end + 1] > t0)
        end_codes = codes[run_end + 1]
        (sel,) = jnp.nonzero(keep, size=m_occ + 1, fill_value=0)
        valid = jnp.arange(m_occ + 1) < jnp.sum(keep)
        return codes[sel], end_codes[sel], valid

    return jax.vmap(split_edge)(idx, c.starts[idx], c.ends[idx], c.own[idx], c.own_id[idx], c.sigma[idx], c.region[idx])


# Up to this many intervals `_stabbed` compares every point with every interval (on CPU faster
# than sorting them for 80 occluders, slower for 320).
STAB_DENSE = 160


def _stabbed(lo: Array, hi: Array, use: Array, t: Array, dense: bool | None = None) -> Array:
    """For each of the `T` points `t`: whether some open interval `(lo[j], hi[j])` with `use[j]`
    contains it, `any_j use[j] & (lo[j] < t) & (t < hi[j])`. Unless `dense` (static; default:
    up to `STAB_DENSE` intervals) in O((M + T) log M) time and O(M + T) memory instead of
    O(M T): `#{lo < t} - #{hi <= t}` over the used non-empty intervals (an interval with
    `hi <= t` also has `lo < t`), exact counts of the same comparisons. `t` finite."""
    if lo.shape[0] <= STAB_DENSE if dense is None else dense:
        return jnp.any((lo[None, :] < t[:, None]) & (t[:, None] < hi[None, :]) & use[None, :], axis=1)
    use = use & (lo < hi)  # empty (and NaN) intervals contain nothing
    los = jnp.sort(jnp.where(use, lo, jnp.inf))
    his = jnp.sort(jnp.where(use, hi, jnp.inf))
    return jnp.searchsorted(los, t, side="left") > jnp.searchsorted(his, t, side="right")


def _batches(n: int, batch: int) -> tuple[Int[Array, "nb b"], Bool[Array, "nb b"]]:
    """`0 .. n - 1` in rows of `batch` (the last row padded with 0) and which entries are real."""
    n_b = -(-n // batch)
    flat = jnp.arange(n_b * batch, dtype=jnp.int32)
    real = flat < n
    return jnp.where(real, flat, 0).reshape(n_b, batch), real.reshape(n_b, batch)


# (candidate edge, region plane) pairs that `_boundary_runs` and `visible_edge_sums` split at once:
# each pair holds about 100 bytes of intermediates (its crossing parameters, collinearity and
# shared-vertex tests), so a batch holds about 1.6 MiB per receiver (2^14 pairs: on CPU as fast
# as splitting every candidate edge at once for 80 occluders, faster for 160).
SPLIT_PAIRS = 1 << 14


def split_batch(m_occ: int, n_planes: int, n_cand: int, pairs: int | None = None) -> int:
    """Candidate edges `_boundary_runs` splits at once for `m_occ` occluders, `n_planes` planes
    per region and `n_cand` candidate edges: about `pairs` (default `SPLIT_PAIRS`) (edge, region
    plane) pairs, at least one edge, all of them when they fit."""
    return max(1, min(n_cand, (pairs or SPLIT_PAIRS) // ((m_occ + 1) * n_planes)))


def _decode(p: Array, c: _Candidates, codes: Int[Array, " r"]) -> Float[Array, "r 3"]:
    """The points of endpoint codes (`_boundary_runs`), differentiable in the geometry `c`."""
    n_cand = c.starts.shape[0]
    n_tab = 2 * n_cand
    planes = c.planes.reshape(-1, 3)
    n_pl = planes.shape[0]
    is_tab = codes < n_tab
    k = jnp.where(is_tab, 0, codes - n_tab)
    i, j = k // n_pl, k % n_pl
    # Region 0's planes come first: ids below K are the light edges' (`_cone_crossing`).
    lo, hi = jnp.minimum(i, j), jnp.maximum(i, j)
    cond = c.cond.reshape(-1)
    ends = c.plane_ends.reshape(-1, 2, 3)

    def crossing(a, b):
        # Two occluder edges' planes (conditioning > 0) nearly coincident: on one edge's line
        # (`occluder_edges_point`); else `_cone_crossing` (and the edges given are the light's
        # first vertex, in the emitter plane: a finite gradient).
        occ = (cond[a] > 0) & (cond[b] > 0) & near_planes(planes[a], planes[b])
        ea, eb = (jnp.where(occ, ends[r], c.e0[None, :]) for r in (a, b))
        on_line = occluder_edges_point(p, ea[0], ea[1], planes[a], eb[0], eb[1], planes[b], c.ne, c.hp)
        return jnp.where(occ, on_line, _cone_crossing(p, c.light, planes, a, planes[b], c.ne, c.hp))

    y = jax.vmap(crossing)(lo, hi)
    table = jnp.concatenate([c.starts, c.ends], axis=0)
    return jnp.where(is_tab[:, None], table[jnp.where(is_tab, codes, 0)], y)


def _no_occluder_edges(p, n, verts):
    starts, ends = horizon_clip_edges(p, n, verts)
    e0 = verts[0]
    in_front = jnp.dot(newell_normal(verts), p - e0) > 0
    return jnp.where(in_front, starts, e0[None, :]), jnp.where(in_front, ends, e0[None, :])


def visible_edges(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    verts: Float[Array, "k 3"],
    occluders: Float[Array, "m ko 3"],
) -> tuple[Float[Array, "e 3"], Float[Array, "e 3"]]:
    r"""Boundary of the visible part of a polygon light, as an oriented edge soup.

    The region is $E_h \setminus \bigcup_j Q_j$ (module docstring): the emitter clipped to the
    receiver's horizon minus the central projections of the effective blockers. Edges lie in the
    emitter plane, run counter-clockwise seen from `p` (the convention of
    `contour_form_factor`), and unused slots are zero-length, `start == end` (they contribute
    0; `visible_form_factor_kernel` masks them, since a fused multiply-add can leave a 1e-18
    residue in `cross(A, A)`). The combinatorics (`_boundary_runs`) carry no gradient; the
    derivatives are those of the endpoints, recomputed from the inputs (`_decode`).

    **Arguments:** `p (3,)` receiver, `n (3,)` its normal, `verts (K, 3)` padded convex light
    (counter-clockwise seen from its lit side), `occluders (M, Ko, 3)` padded convex polygons.

    **Returns:** `(starts, ends)`, each `(E, 3)` with `E = ((K + 1) + M (Ko + 1)) (M + 1)`
    (`E = K + 1` when `M = 0`); all zero-length when `p` is not in front of the light.
    """
    if occluders.shape[0] == 0:
        return _no_occluder_edges(p, n, verts)
    c = _candidates(p, n, verts, occluders)
    sc, ec, valid = _boundary_runs(p, c, occluders.shape[0])
    return _kept_edges(p, c, sc, ec, valid)


def visible_edge_sums(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    verts: Float[Array, "k 3"],
    occluders: Float[Array, "m ko 3"],
    sums: Callable[[Array, Array], Any],
    pairs: int | None = None,
) -> Any:
    r"""`sums(starts, ends)` over the edge soup of `visible_edges`, without that soup.

    `sums` maps an edge soup `(e, 3), (e, 3)` to a pytree of sums over its edges (zero-length
    edges adding 0: `contour_form_factor_sums`, `specular.contour_specular_sums`), so the
    soup's sums are its parts' sums added up. The soup holds `(M + 1)` slots for each of the
    `C ~ M (K_o + 1)` candidate edges, `O(M^2)` per receiver; here the candidate edges are split
    and decoded `split_batch` at a time (`lax.scan`), so a receiver's memory is one batch's
    (about `SPLIT_PAIRS` (edge, region plane) pairs) however many occluders there are, in
    reverse mode too: each batch is recomputed in the backward pass (`jax.checkpoint`) instead
    of its intermediates being kept. The values are those of `sums(*visible_edges(...))` up to
    the order of the additions (the same when one batch holds every candidate edge). `pairs`:
    the batch's size in (edge, region plane) pairs (`split_batch`; static).
    """
    if occluders.shape[0] == 0:
        return sums(*_no_occluder_edges(p, n, verts))
    m_occ = occluders.shape[0]
    c = _candidates(p, n, verts, occluders)
    n_cand = c.starts.shape[0]
    batch = split_batch(m_occ, c.planes.shape[1], n_cand, pairs)
    if batch >= n_cand:
        return sums(*_kept_edges(p, c, *_boundary_runs(p, c, m_occ, pairs)))

    def step(total, xs):
        idx, real = xs
        sc, ec, valid = _split_candidates(p, c, m_occ, idx)
        valid = valid & real[:, None] & c.in_front
        part = sums(*_kept_edges(p, c, sc.reshape(-1), ec.reshape(-1), valid.reshape(-1)))
        return jax.tree_util.tree_map(jnp.add, total, part), None

    none = jnp.zeros((0, 3), p.dtype)
    total, _ = jax.lax.scan(jax.checkpoint(step), sums(none, none), _batches(n_cand, batch))
    return total


def _kept_edges(p: Array, c: _Candidates, sc: Array, ec: Array, valid: Array) -> tuple[Array, Array]:
    """The edges of endpoint codes `sc -> ec` (`_decode`), zero-length at `c.e0` where not `valid`."""
    s = _decode(p, c, sc)
    e = _decode(p, c, ec)
    return jnp.where(valid[:, None], s, c.e0[None, :]), jnp.where(valid[:, None], e, c.e0[None, :])


def visible_form_factor_kernel(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    verts: Float[Array, "k 3"],
    occluders: Float[Array, "m ko 3"],
) -> Float[Array, ""]:
    r"""Form factor of the visible part of a polygon light (C&F eq. 11 over $\partial R$).

    $E = \pi L F$ with shadows. Exact: no sampling, no tolerance other than the coincident-edge
    test (module docstring).

    **Arguments:** `p (3,)` receiver (m), `n (3,)` unit normal, `verts (K, 3)` padded convex
    light, `occluders (M, Ko, 3)` padded convex occluders (M may be 0).

    **Returns:** dimensionless $F \in [0, F_\text{unoccluded}]$.
    """
    starts, ends = visible_edges(p, n, verts, occluders)
    return masked_contour_form_factor(p, n, verts, starts, ends)


def masked_contour_form_factor(p: Array, n: Array, verts: Array, starts: Array, ends: Array) -> Array:
    """Lambert's contour sum over an edge soup of `visible_edges` (or `visible_edges_compact`):
    zero-length (unused) slots masked, 0 when `p` is not in front of the light `verts`."""
    return contour_form_factor_total(p, verts, contour_form_factor_sums(p, n, starts, ends))


def contour_form_factor_sums(p: Array, n: Array, starts: Array, ends: Array) -> tuple[Array, Array]:
    """The two sums over an edge soup that `masked_contour_form_factor` takes: Lambert's sum of
    edge terms (zero-length slots masked: a fused multiply-add can leave cross(A, A) at 1e-18
    instead of 0) and its rounding bound (`_contour_bound`, no gradient). Sums over parts of a
    soup add up to the whole soup's (`contour_form_factor_total`)."""
    used = jnp.any(starts != ends, axis=1)
    terms = jax.vmap(edge_term, in_axes=(None, None, 0, 0))(p, n, starts, ends)
    return jnp.sum(jnp.where(used, terms, 0.0)), jax.lax.stop_gradient(_contour_bound(p, starts, ends, used))


def contour_form_factor_total(p: Array, verts: Array, sums: tuple[Array, Array]) -> Array:
    """`masked_contour_form_factor` from its soup's `contour_form_factor_sums`."""
    s, bound = sums
    ne = newell_normal(verts)
    in_front = jnp.dot(ne, p - verts[0]) > 0
    # A visible region's form factor is never negative. An all-but-empty region (nearly
    # zero-length runs: a receiver at an umbra's vertex) sums to +-1e-16 of rounding, large
    # against its tiny terms: a negative value within the terms' rounding bound (each end
    # within COLLINEAR_EPS eps S of its exact point, over its distance from p) is that region's
    # 0; a larger one stays visible (the engine's `lambert_rounded`). Zero derivative there.
    f = jnp.where((s > 0) & (s <= bound), 0.0, -s / (2 * jnp.pi))
    return jnp.where(in_front, f, 0.0)


def lit_form_factor(p: Array, n: Array, verts: Array) -> Array:
    """`form_factor_kernel` of the whole (unoccluded) light for a receiver the shadow engine
    found lit, never negative: a light whose horizon-clipped part is all but empty (an edge in
    the receiver's horizon plane: a receiver on a box's side face in the plane of a light edge)
    sums to -1e-17 (float64) or -4e-8 (float32) of rounding. A negative value within the edge
    terms' rounding bound (8 eps S per end, over the light plane's distance from p, for each of
    the clipped polygon's at most K + 1 edges) is 0; a larger one stays visible."""
    f = form_factor_kernel(p, n, verts)
    ne = newell_normal(verts)
    nn = jnp.linalg.norm(ne)
    d = jnp.abs(jnp.dot(ne, p - verts[0])) / jnp.where(nn > 0, nn, 1.0)
    big = jnp.maximum(jnp.max(jnp.abs(verts)), jnp.max(jnp.abs(p)))
    ok = (nn > 0) & (d > 0)
    bound = jnp.where(ok, 8 * _eps(p) * big * 2 * (verts.shape[0] + 1) / jnp.where(ok, d, 1.0), 0.0) / (2 * jnp.pi)
    bound = jax.lax.stop_gradient(bound)
    return jnp.where((f < 0) & (f >= -bound), 0.0, f)


def _contour_bound(p: Array, starts: Array, ends: Array, used: Array) -> Array:
    """The rounding bound of Lambert's sum over the edges `starts -> ends` (`used` ones) from
    their ends' rounding (`masked_contour_form_factor`; the engine's `lambert_term_bound`)."""
    da = jnp.linalg.norm(starts - p[None, :], axis=1)
    db = jnp.linalg.norm(ends - p[None, :], axis=1)
    big = jnp.maximum(jnp.maximum(jnp.max(jnp.abs(starts), axis=1), jnp.max(jnp.abs(ends), axis=1)), jnp.max(jnp.abs(p)))
    ok = used & (da > 0) & (db > 0)
    inv = jnp.where(ok, 1.0 / jnp.where(ok, da, 1.0) + 1.0 / jnp.where(ok, db, 1.0), 0.0)
    return COLLINEAR_EPS * _eps(p) * jnp.sum(big * inv)


@eqx.filter_jit
def visible_form_factor(
    points: Float[Array, "N 3"],
    normals: Float[Array, "N 3"],
    vertices: Float[Array, "k 3"],
    occluders: Float[Array, "m ko 3"],
) -> Float[Array, " N"]:
    r"""Batched `visible_form_factor_kernel`: shadowed form factors of one polygon light.

    **Arguments:** `points (N, 3)`, unit `normals (N, 3)`, `vertices (k, 3)` convex light
    (counter-clockwise seen from its lit side), `occluders (m, ko, 3)` padded convex polygons.

    **Returns:** `(N,)` dimensionless form factors ($E = \pi L F$), dtype following the inputs;
    `ValueError` for a NaN/inf input (traced inputs: an error when the program runs).
    """
    args = check_finite_leaves((points, normals, vertices, occluders), "visible_form_factor")
    points, normals, vertices, occluders = args
    return jax.vmap(visible_form_factor_kernel, in_axes=(0, 0, None, None))(
        points, normals, vertices, occluders
    )


# --------------------------------------------------------------------------------------
# Segment lights: Poulin §4.2-4.3 (light triangle)
# --------------------------------------------------------------------------------------


def blocked_intervals(
    p: Float[Array, "3"],
    a: Float[Array, "3"],
    b: Float[Array, "3"],
    occluders: Float[Array, "m ko 3"],
) -> tuple[Float[Array, " m"], Float[Array, " m"]]:
    r"""Per occluder, the interval `(lo, hi)` of $t$ for which $a + t(b-a)$ is hidden from `p`.

    The occluder cuts Poulin's light triangle $(p, a, b)$ in a convex set; its shadow on the
    segment is one interval: the ray $p \to X(t)$ lies in the cone over the occluder
    (linear in $t$ for each edge plane) and $X(t)$ lies beyond the occluder's plane. Empty
    intervals have `lo >= hi`.
    """
    no, _, s, active, planes, _ = _occluder_sides(p, occluders)
    d = b - a

    def one(pl, nor, o0, sj, act):
        g0 = (a - p) @ pl.T
        g1 = d @ pl.T
        valid = jnp.any(pl != 0, axis=1)
        pos = valid & (g1 > 0)
        neg = valid & (g1 < 0)
        tc = safe_div(-g0, g1)
        lo = jnp.max(jnp.where(pos, tc, -jnp.inf))
        hi = jnp.min(jnp.where(neg, tc, jnp.inf))
        const_ok = jnp.all(~valid | (g1 != 0) | (g0 >= 0))
        # X(t) strictly behind the occluder plane as seen from p.
        h0 = -sj * jnp.dot(nor, a - o0)
        h1 = -sj * jnp.dot(nor, d)
        tb = safe_div(-h0, h1)
        lo = jnp.where(h1 > 0, jnp.maximum(lo, tb), lo)
        hi = jnp.where(h1 < 0, jnp.minimum(hi, tb), hi)
        const_ok = const_ok & ((h1 != 0) | (h0 > 0)) & act
        return jnp.where(const_ok, lo, jnp.inf), jnp.where(const_ok, hi, -jnp.inf)

    return jax.vmap(one)(planes, no, occluders[:, 0], s, active)


def visible_pieces(
    p: Float[Array, "3"],
    a: Float[Array, "3"],
    b: Float[Array, "3"],
    occluders: Float[Array, "m ko 3"],
    receivers: int = 1,
) -> tuple[Float[Array, " s"], Float[Array, " s"], Bool[Array, " s"]]:
    """The segment light `a -> b` seen from `p` cut at every blocked interval's ends
    (`blocked_intervals`, clipped to [0, 1]): `(t0, t1, keep)`, each `(2M + 1,)`, the pieces
    `[t0, t1]` in order along the segment and whether each is visible (non-empty, its midpoint
    in no open blocked interval). A piece's membership compares its midpoint with every
    interval while `receivers` (static: how many receivers the caller classifies at once)
    x `(2M + 1) x M` comparisons fit `SEGMENT_DENSE`, and is an interval-stabbing count beyond
    (`_stabbed`: the same comparisons, `O(M log M)` time and `O(M)` memory); both give the same
    `keep` bit for bit. No gradient flows through `keep`."""
    lo, hi = blocked_intervals(p, a, b, occluders)
    ts = jnp.sort(
        jnp.concatenate(
            [
                jnp.zeros((1,), p.dtype),
                jnp.ones((1,), p.dtype),
                jnp.clip(lo, 0.0, 1.0),
                jnp.clip(hi, 0.0, 1.0),
            ]
        )
    )
    t0 = ts[:-1]
    t1 = ts[1:]
    lo, hi, tm = jax.lax.stop_gradient((lo, hi, 0.5 * (t0 + t1)))
    dense = receivers * tm.shape[0] * lo.shape[0] <= SEGMENT_DENSE
    hidden = _stabbed(lo, hi, jnp.ones(lo.shape, bool), tm, dense)
    return t0, t1, ~hidden & (t1 > t0)


def _piece_ends(a: Array, b: Array, t0: Array, t1: Array, keep: Array) -> tuple[Array, Array]:
    """The points `a + t (b - a)` of pieces `[t0, t1]`, zero-length at `a` where not `keep`."""
    d = b - a
    starts = jnp.where(keep[:, None], a[None, :] + t0[:, None] * d[None, :], a[None, :])
    ends = jnp.where(keep[:, None], a[None, :] + t1[:, None] * d[None, :], a[None, :])
    return starts, ends


def visible_segments(
    p: Float[Array, "3"],
    a: Float[Array, "3"],
    b: Float[Array, "3"],
    occluders: Float[Array, "m ko 3"],
) -> tuple[Float[Array, "s 3"], Float[Array, "s 3"]]:
    """Visible sub-segments of the segment light `a -> b` seen from `p`: `(2M + 1)` pieces,
    dropped ones zero-length at `a`. Ordered along the segment (`visible_pieces`)."""
    return _piece_ends(a, b, *visible_pieces(p, a, b, occluders))


# (receiver, piece, interval) comparisons that `visible_pieces` makes at once (a boolean each):
# beyond, sorted interval counts. On CPU (16 receivers, float64) the comparisons are as fast
# as the counts up to 120 occluders (460k comparisons) and slower from 160 (820k: 1.3x the
# counts' time, 2.6x at 640 occluders), and their memory grows with M^2; 2^19 keeps them
# for up to 127 occluders in a chunk of 16 receivers.
SEGMENT_DENSE = 1 << 19

# (receiver, piece) pairs whose integrand `visible_segment_sum` evaluates at once: a piece's
# gradient program holds about 1 KiB (Lambert) to 2 KiB (Phong's Chebyshev terms) of
# intermediates (XLA's temp memory, 16 receivers x 1281 pieces), so a batch holds 16-32 MiB;
# a chunk of 16 receivers integrates up to 511 occluders' pieces in one batch. More pieces a
# batch were no faster on CPU (1280 occluders: one batch or three, the same time) and hold
# more memory.
SEGMENT_PIECES = 1 << 14


def visible_segment_sum(
    p: Float[Array, "3"],
    a: Float[Array, "3"],
    b: Float[Array, "3"],
    occluders: Float[Array, "m ko 3"],
    piece: Callable[[Array, Array], Any],
    pieces: int | None = None,
    receivers: int = 1,
) -> Any:
    r"""`piece(start, end)` (one sub-segment `(3,), (3,)` to a pytree of arrays) summed over the
    visible sub-segments of `visible_segments`, `pieces` (static; default: `SEGMENT_PIECES`
    shared by the `receivers` (static) that the caller integrates at once) of them at a time.
    One `vmap` over every piece when they fit one batch; otherwise a `lax.scan` whose steps are
    recomputed in reverse mode (`jax.checkpoint`), so a receiver's memory is one batch's
    intermediates and its `O(M)` piece parameters however many occluders there are. The pieces
    are `visible_pieces(p, a, b, occluders, receivers)`; dropped ones (zero-length at `a`) are
    evaluated as in `visible_segments`, so the sum is `sum(vmap(piece)(*visible_segments(...)))`
    up to the order of the additions (the same when one batch holds every piece)."""
    t0, t1, keep = visible_pieces(p, a, b, occluders, receivers)
    n_pieces = t0.shape[0]
    # As few batches as `pieces` allows, of equal size (the last one padded by less than one
    # piece per batch).
    n_batches = -(-n_pieces // max(1, pieces or SEGMENT_PIECES // max(1, receivers)))
    batch = -(-n_pieces // n_batches)

    def part(u0, u1, k, real):
        vals = jax.vmap(piece)(*_piece_ends(a, b, u0, u1, k))
        if real is None:
            return jax.tree_util.tree_map(lambda v: jnp.sum(v, axis=0), vals)
        return jax.tree_util.tree_map(
            lambda v: jnp.sum(jnp.where(real.reshape(real.shape + (1,) * (v.ndim - 1)), v, 0), axis=0), vals
        )

    if batch >= n_pieces:
        return part(t0, t1, keep, None)

    def step(total, xs):
        idx, real = xs
        return jax.tree_util.tree_map(jnp.add, total, part(t0[idx], t1[idx], keep[idx] & real, real)), None

    zero = jax.tree_util.tree_map(lambda s: jnp.zeros(s.shape, s.dtype), jax.eval_shape(piece, a, b))
    total, _ = jax.lax.scan(jax.checkpoint(step), zero, _batches(n_pieces, batch))
    return total


def visible_linear_kernel(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    a: Float[Array, "3"],
    b: Float[Array, "3"],
    m: int,
    occluders: Float[Array, "m ko 3"],
) -> Float[Array, ""]:
    r"""$E/\Phi$ (1/m) at `p` from the visible parts of the segment light `a -> b` (profile
    $\cos^m\beta$, `m` static), Poulin §4.3: the sum of `linear_irradiance_kernel` over the
    visible sub-segments (each horizon-clipped exactly there)."""
    starts, ends = visible_segments(p, a, b, occluders)
    vals = jax.vmap(linear_irradiance_kernel, in_axes=(None, None, 0, 0, None))(
        p, n, starts, ends, m
    )
    return jnp.sum(vals)


# --------------------------------------------------------------------------------------
# Point and directional lights: hard shadows
# --------------------------------------------------------------------------------------


def _ray_blocked(p, r, occluders, limit_point):
    no, _, s, active, planes, _ = _occluder_sides(p, occluders)
    valid = jnp.any(planes != 0, axis=2)
    in_cone = jnp.all(~valid | (planes @ r > 0), axis=1) & active
    if limit_point is not None:
        beyond = -s * jnp.einsum("mi,mi->m", no, limit_point[None, :] - occluders[:, 0]) > 0
        in_cone = in_cone & beyond
    return jnp.any(in_cone)


def point_visibility(
    p: Float[Array, "3"], x: Float[Array, "3"], occluders: Float[Array, "m ko 3"]
) -> Float[Array, ""]:
    """1 if the segment `p -> x` misses every occluder (interiors; grazing counts as visible),
    else 0. Gradient zero."""
    p = jax.lax.stop_gradient(p)
    x = jax.lax.stop_gradient(x)
    occluders = jax.lax.stop_gradient(occluders)
    return jnp.where(_ray_blocked(p, x - p, occluders, x), 0.0, 1.0).astype(p.dtype)


def directional_visibility(
    p: Float[Array, "3"], d: Float[Array, "3"], occluders: Float[Array, "m ko 3"]
) -> Float[Array, ""]:
    """1 if the ray from `p` towards the light (against the travel direction `d`) misses every
    occluder, else 0. Gradient zero."""
    p = jax.lax.stop_gradient(p)
    d = jax.lax.stop_gradient(d)
    occluders = jax.lax.stop_gradient(occluders)
    return jnp.where(_ray_blocked(p, -d, occluders, None), 0.0, 1.0).astype(p.dtype)
