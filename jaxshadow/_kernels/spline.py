r"""Stark et al. shadow equation: exact form factor of a partially occluded polygon (eq. 24).

Setting (Stark, Cohen, Lyche & Riesenfeld, §7). A receiver point $X$ on a horizontal
receiver plane (normal $+z$; $z = 0$ in the paper, here the plane through $X$), a convex
planar emitter $E = \langle e_1..e_m \rangle$ and a convex planar occluder
$O = \langle o_1..o_n \rangle$ above it. Seen from $X$ and projected centrally onto the plane
one unit above $X$, they become the polygons $E^*$ and $O^*$ (eqs. 19-20), and

$$I = S_{E^*} - S_{E^* \cap O^*},\qquad S_{Q^*} = \int_{Q^*} \frac{dz\,dw}{(1+z^2+w^2)^2}
\qquad\text{(eqs. 8-9)}.$$

$S$ is $\int \cos\theta_0\, d\omega$, so the form factor is $F = I / \pi$ and the irradiance from
radiance $L$ is $\pi L F = L I$ (Stark set $K = 1$ in eq. 6). Eq. 23 writes
$S_{E^* \cap O^*}$ as a sum over the vertices of $E^* \cap O^*$: emitter vertices inside
$O^*$ (floor region $O_j$), occluder vertices inside $E^*$ ($E_i$) and edge-edge crossings
($S_{ij}$), each contributing a difference of the twice-integrated density $F(z, u, v)$
(eq. 22) along the outgoing and incoming edge lines $w = u z + v$.

**Homogeneous form (the places where the paper's formulas need care).**

1. *Eq. 22 divides by $e_{i,1}$* (slope $m_i = e_{i,2} / e_{i,1}$; vertical edges in the
   $zw$-plane have $m = \infty$) and eqs. 19-20 divide by the heights $z_i$ (huge when the
   occluder nearly touches the floor, Stark fig. 13). With the point $q = (Q_x, Q_y)/Q_z$ and
   the line through the origin-plane with normal $N$ (for the line $w = u z + v$,
   $N \propto (-u, 1, -v)$), eq. 22 is exactly

   $$F = -\frac{N_z}{2|N|}\operatorname{atan2}\big((Q \times N)_z,\ Q_z |N|\big)
        + \frac{Q_x}{2\rho}\operatorname{atan2}(Q_y, \rho),\quad \rho = \sqrt{Q_x^2+Q_z^2}$$

   (substitute $Q = (z, uz + v, 1)$). It needs neither slopes nor projected coordinates:
   $Q$ is a vertex *direction* $v - X$ and $N$ the normal of the plane through $X$ and an
   edge, so nothing divides by $e_{i,1}$ or by a height. Its first term is $-\tfrac12 \hat N_z$
   times the angle along the edge's great circle: summed over a contour it is Lambert's
   formula, hence `form_factor` when nothing occludes.
2. *Cancellation.* The second term of eq. 22 depends on the evaluation point only; every
   bracket of eqs. 23-24 is a difference of $F$ at one point, so it cancels and we drop it.
   The first term, as written, is measured from the top of the edge's great circle: it is
   $O(1)$ even when the emitter subtends a tiny angle, and the $O(1)$ terms then cancel
   (float32 lost ~4 digits for distant receivers). $F$ is an antiderivative along each line,
   so any per-line constant cancels too (every line enters eqs. 23-24 once with $+$ at the
   start of its piece of the boundary and once with $-$ at its end). We fix it so that $F$
   vanishes at the edge's first vertex: a term becomes one `atan2` of the angle from that
   vertex (`line_antiderivative`), small when the edge looks small.
3. *Eq. 21 and the definition of $b'_j$ have typos*: they read $p_{j,1}, p_{j,2}$ where the
   emitter's $p'_{j,1}, p'_{j,2}$ are meant (solving the two line equations gives the
   corrected form). We do not use $\psi_{ij}$ as such: the crossing direction is
   $Q_{ij} = \pm N_i \times N'_j$ (the common line of the two edge planes, no division).
4. *Eq. 17 is garbled* (`(x, y, 0) . (n_E - (x_1, y_1, z_1)) > 0` mixes a normal and a
   point). We use what it must mean: $X$ lies strictly on the emitting side of $E$'s plane;
   elsewhere the emitter sends nothing and we return 0 (as `form_factor` does).
5. *Orientation.* Stark orients $E$'s normal *against* the emission so that $E^*$ runs
   counter-clockwise; jaxshadow's emitters are counter-clockwise seen from the lit side, so
   the kernel reverses them. $O^*$ must run counter-clockwise too: the kernel orients a single
   occluder per receiver point (an occluder blocks from both sides), and for a polyhedral
   occluder (fig. 14; "if the normals point inward") it orients the faces inward and keeps, per
   point, only the faces whose inward normal points away from $X$ (front faces tile the
   silhouette; back faces are hidden behind them).
6. *Characteristic functions.* $\chi_{\hat O_j}$, $\chi_{\hat E_i}$ and
   $o(S_{ij})\chi_{\hat S_{ij}}$ are point-in-polygon tests of $X$ against the floor
   polygons whose vertices are the shadow nodes $v_{ij}$ (eq. 18), as in the paper: $X$ left
   of the floor edge $v_{ij} \to v_{i+1,j}$ iff $e_j$ is inside edge $i$ of $O^*$, and left of
   $v_{ij} \to v_{i,j+1}$ iff $o_i$ is inside edge $j$ of $E^*$. Each of these $2nm$ side tests
   is computed once, as $\operatorname{cross}(v_a - X, v_b - X)$ on the shared node
   coordinates, and reused by every polygon with that edge: a point at a node or on an edge
   then gets one consistent configuration (an earlier version with independent 3x3
   determinants misclassified points at nodes by O(1)). Nodes are kept homogeneous,
   $v = P / w$ with $w = z'_j - z_i$: where $w = 0$ (an occluder vertex level with an
   emitter vertex) eq. 18 divides by zero, and the node is used as the direction at infinity
   $P$. $O_j$ and $E_i$ are convex (inside = left of every edge). $o(S_{ij})\chi_{\hat S_{ij}}$
   is the signed crossing of $O^*$'s edge $i$ with $E^*$'s edge $j$ (+1 where $O^*$'s edge
   enters $E^*$), made of the four edge tests of the quadrilateral $S_{ij}$, which is valid
   also where $S_{ij}$ is not convex.
7. *Half-open polygons.* Stark drops edges whose angle with the $x$-axis is in $(0, \pi)$;
   read literally that keeps both horizontal edges (angles $0$ and $\pi$), which counts a
   point on a shared horizontal edge twice. We use the consistent version: a point on a
   discontinuity line is classified as the point $X + (\epsilon, \epsilon^2)$ (a zero
   side test is decided by the sign of its $x$-derivative, then its $y$-derivative). For a
   counter-clockwise polygon that keeps the edges at angles in $(\pi, 2\pi) \cup \{0\}$:
   Stark's rule, except that the top edge (angle $\pi$) is dropped. All polygons then describe
   one real nearby point, and as $I$ is continuous its value there is right.
8. *Validity region.* Stark requires $O$ strictly above the floor and $O$'s plane strictly
   below $E$. That is not what makes eq. 23 the occluded part when $O$ is tilted, and it
   excludes the side faces of fig. 14's cube. We require instead (checked in NumPy when the
   inputs are concrete, `ValueError`): every occluder vertex strictly above every receiver
   point and no occluder vertex above the lowest emitter vertex. Then along every ray from
   $X$ the occluder comes first, so $E^* \cap O^*$ is exactly what is hidden, and every
   shadow node (eq. 18) is a forward projection ($w \ge 0$; with $w < 0$ the floor polygons
   would be wrong: a tilted occluder that satisfies Stark's condition can have a vertex
   higher than an emitter vertex, and then its shadow from that vertex is unbounded). Touching from below (an occluder vertex level
   with the emitter) is allowed, but not a vertex shared with the emitter (closer than
   `SHARED_VERTEX_RTOL` times its size): its node is $0/0$ and every polygon through it is
   undefined (an occluder lying on the emitter came out as $-F$). Under tracing (jit/grad of the wrapper) the checks cannot
   run; outside the region the result stays finite with finite gradients but is not
   physically meaningful.
"""

from __future__ import annotations

from typing import Any, no_type_check

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._core.geometry import (
    check_convex_polygon,
    check_finite,
    check_finite_leaves,
    is_concrete,
    on_lit_side,
    strip_padding,
)

# --------------------------------------------------------------------------------------
# Pieces of eqs. 18-24
# --------------------------------------------------------------------------------------


def twice_integrated_density(q: Float[Array, "3"], n: Float[Array, "3"]) -> Float[Array, ""]:
    r"""Stark eq. 22, $F(z, u, v)$, in homogeneous form (module docstring, note 1).

    $F$ is the antiderivative, along the line $w = u z + v$, of
    $\Omega(z, w) = \int_0^w (1 + z^2 + t^2)^{-2} dt$. Here the evaluation point is the
    direction `q` ($z = q_x / q_z$, $w = q_y / q_z$, requires $q_z > 0$) and the line is the
    plane through the origin with normal `n` (any length, either sign). Invariant under positive
    scaling of `q` and any non-zero scaling of `n`. The kernel uses the equivalent
    `line_antiderivative` (note 2); this literal form documents and tests the rewrite.

    **Returns:** the dimensionless value; 0 (zero gradient) where $q_z \le 0$; the first term
    is 0 where $n = 0$ (a zero-length or end-on edge, which contributes nothing).
    """
    unit_z = jnp.zeros_like(q).at[2].set(1)
    n_ok = (q[2] > 0) & (jnp.dot(n, n) > 0)
    qn = jnp.where(n_ok, q, unit_z)
    ns = jnp.where(n_ok, n, unit_z)
    nn = jnp.sqrt(jnp.dot(ns, ns))
    # First term of eq. 22: v atan((uv + z + u^2 z)/R) / 2R with R = sqrt(1 + u^2 + v^2).
    qxn_z = qn[0] * ns[1] - qn[1] * ns[0]
    t1 = -ns[2] * jnp.arctan2(qxn_z, qn[2] * nn) / (2 * nn)
    return jnp.where(n_ok, t1, 0.0) + point_term(q)


def point_term(q: Float[Array, "3"]) -> Float[Array, ""]:
    r"""Second term of eq. 22, $z \arctan(w / \sqrt{1+z^2}) / 2\sqrt{1+z^2}$ at $q$.

    It depends on the point only and cancels from every bracket of eqs. 23-24 (note 2).
    """
    unit_z = jnp.zeros_like(q).at[2].set(1)
    ok = q[2] > 0
    qs = jnp.where(ok, q, unit_z)
    rho = jnp.sqrt(qs[0] * qs[0] + qs[2] * qs[2])
    return jnp.where(ok, qs[0] * jnp.arctan2(qs[1], rho) / (2 * rho), 0.0)


def line_antiderivative(
    q: Float[Array, "3"], r: Float[Array, "3"], n: Float[Array, "3"]
) -> Float[Array, ""]:
    r"""$F(q) - F(r) - [\text{point terms}]$ along one line: eq. 22 with its integration constant
    fixed so that it vanishes at the reference point `r` of the line (note 2).

    Equals $-\tfrac12 \hat n_z$ times the signed angle from `r` to `q` along the great circle
    with normal `n` (one `atan2`, no cancellation between large terms). `q`, `r`: directions on
    the plane through the origin with normal `n`. 0 (zero gradient) where `n = 0`.
    """
    unit_z = jnp.zeros_like(q).at[2].set(1)
    s = jnp.dot(jnp.cross(r, q), n)
    c = jnp.dot(r, q)
    nn2 = jnp.dot(n, n)
    ok = (nn2 > 0) & ((s * s + c * c) > 0)
    ns = jnp.where(ok, n, unit_z)
    nn = jnp.sqrt(jnp.dot(ns, ns))
    s_ok = jnp.where(ok, s, 0.0)
    c_ok = jnp.where(ok, c, 1.0)
    return jnp.where(ok, -ns[2] * jnp.arctan2(s_ok / nn, c_ok) / (2 * nn), 0.0)


def _edge_normals(rel: Float[Array, "k 3"]) -> Float[Array, "k 3"]:
    """Normal of the plane through the receiver (origin) and edge `i -> i+1` of a polygon."""
    return jnp.cross(rel, jnp.roll(rel, -1, axis=0))


def _homogeneous_nodes(
    p: Float[Array, "3"], emitter: Float[Array, "m 3"], occluder: Float[Array, "n 3"]
) -> tuple[Float[Array, "n m 2"], Float[Array, "n m"]]:
    r"""Shadow nodes (eq. 18) on the receiver plane through `p`, homogeneous: $v_{ij} = P / w$.

    $P_{ij} = z'_j o_i - z_i e_j$ (horizontal part), $w_{ij} = z'_j - z_i \ge 0$ (heights above
    the receiver plane). $w = 0$ (an occluder vertex level with an emitter vertex) is a node at
    infinity in the direction $P$, which eq. 18 cannot represent. The nodes do not depend on
    the receiver's $x, y$: they are the spline's fixed knots.
    """
    zo = occluder[:, None, 2] - p[2]
    ze = emitter[None, :, 2] - p[2]
    big_p = ze[..., None] * occluder[:, None, :2] - zo[..., None] * emitter[None, :, :2]
    return big_p, ze - zo


def _floor_side(
    pa: Float[Array, "n m 2"],
    wa: Float[Array, "n m"],
    pb: Float[Array, "n m 2"],
    wb: Float[Array, "n m"],
    x: Float[Array, "2"],
) -> Bool[Array, "n m"]:
    r"""Half-open test (note 7): is the floor point `x` left of the node edge $v_a \to v_b$?

    Finite nodes are divided out first, so the test is $\operatorname{cross}(v_a - x, v_b - x)$
    on the shared node coordinates: at a node, or on an edge, the same floating-point numbers
    decide every polygon that has that node or edge (consistent configuration). A node at
    infinity ($w = 0$) uses its direction $P$ (the $w \to 0$ limit). A zero is decided as at
    $x + (\epsilon, \epsilon^2)$: by the edge direction $d$, left iff $d_y < 0$, or $d_y = 0$
    and $d_x \ge 0$ (a zero-length edge constrains nothing).
    """
    fa, fb = wa > 0, wb > 0
    va = pa / jnp.where(fa, wa, 1.0)[..., None] - x[None, None, :]
    vb = pb / jnp.where(fb, wb, 1.0)[..., None] - x[None, None, :]
    # Rows of the homogeneous determinant: a finite node contributes v - x, an infinite one P.
    ra = jnp.where(fa[..., None], va, pa)
    rb = jnp.where(fb[..., None], vb, pb)
    det = ra[..., 0] * rb[..., 1] - ra[..., 1] * rb[..., 0]
    d = jnp.where(
        (fa & fb)[..., None],
        vb - va,
        jnp.where(fa[..., None], pb, jnp.where(fb[..., None], -pa, 0.0)),
    )
    tie = (d[..., 1] < 0) | ((d[..., 1] == 0) & (d[..., 0] >= 0))
    # A repeated node (padding) must test exactly 0; with fused multiply-adds a*b - b*a need not.
    same = (fa == fb) & jnp.all(ra == rb, axis=-1)
    return same | (det > 0) | ((det == 0) & tie)


Terms = tuple[Float[Array, " t"], Float[Array, "t 3"], Float[Array, "t 3"], Float[Array, "t 3"]]


def _sum_terms(terms: Terms) -> Float[Array, ""]:
    r"""$\sum_t c_t\,F_t$ with $F_t$ = `line_antiderivative(q_t, r_t, n_t)`.

    Every bracket of eqs. 23-24 is gathered into one batch of coefficients and evaluated by a
    single vmapped call: one call site keeps the (second) derivatives small to compile.
    """
    coef, q, r, n = terms
    vals = jax.vmap(line_antiderivative)(q, r, n)
    return jnp.sum(jnp.where(coef != 0, coef * vals, 0.0))


def _vertex_terms(rel: Float[Array, "k 3"], normals: Float[Array, "k 3"], coef) -> Terms:
    r"""$c_j\,[F(v_j, \text{edge}_j) - F(v_j, \text{edge}_{j-1})]$, outgoing minus incoming edge,
    each line's antiderivative vanishing at its edge's first vertex (so the first is 0)."""
    return -coef, rel, jnp.roll(rel, 1, axis=0), jnp.roll(normals, 1, axis=0)


# Terms of several sets, each of its own length (`_t`: not matched across the arguments).
AnyTerms = tuple[Float[Array, " _t"], Float[Array, "_t 3"], Float[Array, "_t 3"], Float[Array, "_t 3"]]


def _concat(*terms: AnyTerms) -> Terms:
    a, b, c, d = (jnp.concatenate(parts, axis=0) for parts in zip(*terms, strict=True))
    return a, b, c, d


def _unoccluded_terms(e_rel: Float[Array, "m 3"]) -> Terms:
    return _vertex_terms(e_rel, _edge_normals(e_rel), jnp.ones(e_rel.shape[:1], e_rel.dtype))


def unoccluded_integral(e_rel: Float[Array, "m 3"]) -> Float[Array, ""]:
    r"""$S_{E^*}$ (eqs. 7-8): the first sum of eq. 24 without $\chi$. `e_rel`: emitter vertices
    minus the receiver point, Stark orientation ($E^*$ counter-clockwise)."""
    return _sum_terms(_unoccluded_terms(e_rel))


def _occluded_terms(
    p: Float[Array, "3"], emitter: Float[Array, "m 3"], occluder: Float[Array, "n 3"]
) -> Terms:
    """Eq. 23 as coefficients times `line_antiderivative` arguments (`m + n + 2 n m` terms)."""
    dt = emitter.dtype
    e_rel = emitter - p[None, :]
    o_rel = occluder - p[None, :]
    ne = _edge_normals(e_rel)  # N'_j
    no = _edge_normals(o_rel)  # N_i
    # Characteristic functions from the floor polygons of shadow nodes (eq. 18, note 6).
    # a_in[i, j]: p left of v_ij -> v_i+1,j (edge i of O_j)  <=>  e_j inside O*'s edge i.
    # b_in[i, j]: p left of v_ij -> v_i,j+1 (edge j of E_i)  <=>  o_i inside E*'s edge j.
    # Only booleans come out of the tests: no tangents through them (smaller derivative graphs).
    sg = jax.lax.stop_gradient
    big_p, w = _homogeneous_nodes(sg(p), sg(emitter), sg(occluder))
    x = sg(p)[:2]
    p_i1, w_i1 = jnp.roll(big_p, -1, axis=0), jnp.roll(w, -1, axis=0)
    p_j1, w_j1 = jnp.roll(big_p, -1, axis=1), jnp.roll(w, -1, axis=1)
    a_in = _floor_side(big_p, w, p_i1, w_i1, x)
    b_in = _floor_side(big_p, w, p_j1, w_j1, x)

    # First sum of eq. 23: emitter vertex j inside O*  <=>  p in O_j.
    chi_o = jnp.all(a_in, axis=0).astype(dt)
    # Second sum: occluder vertex i inside E*  <=>  p in E_i.
    chi_e = jnp.all(b_in, axis=1).astype(dt)
    # Third sum: o(S_ij) chi(S_ij) is the signed crossing of O*'s edge i with E*'s edge j; the
    # four tests are the four edges of the quadrilateral S_ij.
    a_in_next = jnp.roll(a_in, -1, axis=1)  # e_{j+1} inside O*'s edge i
    b_in_next = jnp.roll(b_in, -1, axis=0)  # o_{i+1} inside E*'s edge j
    enters = (~b_in) & b_in_next & a_in & (~a_in_next)  # O*'s edge i enters E* across edge j
    leaves = b_in & (~b_in_next) & (~a_in) & a_in_next
    orient = (enters.astype(dt) - leaves.astype(dt)).reshape(-1)
    # Crossing direction: common line of the two edge planes, pointing up (replaces eq. 21).
    q = jnp.cross(no[:, None, :], ne[None, :, :])
    q = jnp.where(q[..., 2:3] < 0, -q, q).reshape(-1, 3)
    n, m = no.shape[0], ne.shape[0]
    o_side = (
        orient,
        q,
        jnp.repeat(o_rel, m, axis=0),
        jnp.repeat(no, m, axis=0),
    )  # F(psi, m_i, b_i)
    e_side = (-orient, q, jnp.tile(e_rel, (n, 1)), jnp.tile(ne, (n, 1)))  # F(psi, m'_j, b'_j)
    return _concat(_vertex_terms(e_rel, ne, chi_o), _vertex_terms(o_rel, no, chi_e), o_side, e_side)


def occluded_integral(
    p: Float[Array, "3"], emitter: Float[Array, "m 3"], occluder: Float[Array, "n 3"]
) -> Float[Array, ""]:
    r"""$N_{M_O \cap M_E, \omega} = S_{E^* \cap O^*}$ at the receiver point `p`, Stark eq. 23.

    **Arguments:** `p (3,)`; emitter and occluder vertices, both ordered so that $E^*$ and
    $O^*$ run counter-clockwise seen from `p` (padded polygons with repeated vertices are fine).

    **Returns:** $\int_{E^* \cap O^*} (1 + z^2 + w^2)^{-2}\,dz\,dw$ (dimensionless).
    """
    return _sum_terms(_occluded_terms(p, emitter, occluder))


def _negate(terms: Terms) -> Terms:
    return -terms[0], terms[1], terms[2], terms[3]


def _ccw_seen_from(rel: Float[Array, "k 3"]) -> Bool[Array, ""]:
    """True where the polygon (relative to the receiver) projects counter-clockwise: the
    receiver (the origin) is on the side its reversed vertex order's normal points to."""
    return on_lit_side(jnp.zeros_like(rel[0]), rel[::-1])


def spline_shadow_kernel(
    p: Float[Array, "3"], emitter: Float[Array, "m 3"], occluder: Float[Array, "n 3"]
) -> Float[Array, ""]:
    r"""Stark eq. 24 for one receiver point: form factor of the visible part of `emitter`.

    **Arguments:** `p (3,)` receiver point (its receiver plane is horizontal, normal $+z$);
    `emitter (m, 3)` convex, counter-clockwise seen from its lit side; `occluder (n, 3)` convex,
    either orientation (it blocks from both sides). Padded polygons are fine.

    **Returns:** $F = I / \pi$ (dimensionless).
    """
    # Stark orientation (note 5); R_E (eq. 17, note 4): p on the emitting side <=> E* CCW.
    emitter = emitter[::-1]
    e_rel = emitter - p[None, :]
    lit = _ccw_seen_from(e_rel)
    occluder = jnp.where(_ccw_seen_from(occluder - p[None, :]), occluder, occluder[::-1])
    # Eq. 24 = eq. 8 minus eq. 23; the emitter-vertex brackets combine to [1 - chi(O_j)].
    terms = _concat(_unoccluded_terms(e_rel), _negate(_occluded_terms(p, emitter, occluder)))
    return jnp.where(lit, _sum_terms(terms), 0.0) / jnp.pi


def spline_shadow_faces_kernel(
    p: Float[Array, "3"], emitters: Float[Array, "l m 3"], faces: Float[Array, "f k 3"]
) -> Float[Array, ""]:
    r"""Sum over emitters of eq. 24 with a convex polyhedral occluder (Stark fig. 14).

    `faces` must be oriented inward (right-hand normal into the polyhedron); per point only
    the front faces (inward normal pointing away from `p`, i.e. $O^*$ counter-clockwise)
    occlude: they tile the silhouette without overlap.
    """
    front = jax.vmap(_ccw_seen_from)(faces - p[None, None, :])

    def one_emitter(emitter: Float[Array, "m 3"]) -> Terms:
        emitter = emitter[::-1]
        e_rel = emitter - p[None, :]
        lit = _ccw_seen_from(e_rel)
        coef, q, r, n = jax.vmap(_occluded_terms, in_axes=(None, None, 0))(p, emitter, faces)
        coef = jnp.where(front[:, None], -coef, 0.0)
        occ = (coef.reshape(-1), q.reshape(-1, 3), r.reshape(-1, 3), n.reshape(-1, 3))
        coef, q, r, n = _concat(_unoccluded_terms(e_rel), occ)
        return jnp.where(lit, coef, 0.0), q, r, n

    coef, q, r, n = jax.vmap(one_emitter)(emitters)
    flat = (coef.reshape(-1), q.reshape(-1, 3), r.reshape(-1, 3), n.reshape(-1, 3))
    return _sum_terms(flat) / jnp.pi


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def shadow_nodes(
    emitter: Float[ArrayLike, "m 3"], occluder: Float[ArrayLike, "n 3"]
) -> Float[Array, "n m 2"]:
    r"""Shadow nodes $v_{ij}$ (Stark eq. 18) on the floor $z = 0$: where $o_i$ and $e_j$ line up.

    The discontinuity lines of the shadow run between them: $O_j = \langle v_{1j}..v_{nj}\rangle$,
    $E_i = \langle v_{i1}..v_{im}\rangle$, $S_{ij} = \langle v_{ij}, v_{i+1,j}, v_{i+1,j+1},
    v_{i,j+1}\rangle$ (indices in the given vertex orders). Infinite where $z'_j = z_i$. For
    plotting and tests; the kernel uses the homogeneous form (module docstring, note 6).

    Example:
        ```python
        import numpy as np
        import jaxshadow as js

        emitter = np.array([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2.0]])
        occluder = np.array([[0.3, 0.3, 1], [0.7, 0.3, 1], [0.7, 0.7, 1], [0.3, 0.7, 1.0]])
        nodes = js.shadow_nodes(emitter, occluder)   # (4, 4, 2): the shadow's spline nodes on z = 0
        ```
    """
    zo = occluder[:, None, 2:3]
    ze = emitter[None, :, 2:3]
    return (ze * occluder[:, None, :2] - zo * emitter[None, :, :2]) / (ze - zo)


# --------------------------------------------------------------------------------------
# Validation (NumPy, concrete inputs only) and public wrappers
# --------------------------------------------------------------------------------------


def _check_points(points: object, what: str) -> np.ndarray:
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{what}: points must have shape (N, 3), got {pts.shape}.")
    check_finite(pts, what)
    return pts


def _check_validity_region(
    emitters: list[np.ndarray], occluder_verts: np.ndarray, pts: np.ndarray, what: str
) -> None:
    """Module docstring, note 8: receiver plane < occluder <= emitter, in height."""
    if pts.shape[0]:
        top = int(np.argmax(pts[:, 2]))
        low = int(np.argmin(occluder_verts[:, 2]))
        if occluder_verts[low, 2] <= pts[top, 2]:
            raise ValueError(
                f"{what}: the occluder must lie strictly above the receiver plane (validity "
                f"region of the shadow equation, Stark eq. 17): occluder vertex {low} has "
                f"z = {occluder_verts[low, 2]:.6g} <= z = {pts[top, 2]:.6g} of receiver point "
                f"{top}. A touching occluder (Stark fig. 13) can only be approached."
            )
    high = int(np.argmax(occluder_verts[:, 2]))
    for k, e in enumerate(emitters):
        # A shared vertex makes its shadow node 0/0 (eq. 18: P = 0 and w = 0): the node, and
        # the side tests of every floor polygon through it, are undefined (the result was -F
        # for an occluder lying on the emitter).
        size = float(np.max(np.abs(e - e.mean(axis=0))))
        gap = np.max(np.abs(occluder_verts[:, None, :] - e[None, :, :]), axis=-1)
        i, j = np.unravel_index(int(np.argmin(gap)), gap.shape)
        if gap[i, j] <= SHARED_VERTEX_RTOL * size:
            name = "the emitter" if len(emitters) == 1 else f"emitter {k}"
            raise ValueError(
                f"{what}: occluder vertex {i} coincides with vertex {j} of {name} "
                f"({occluder_verts[i].tolist()}): its shadow node (Stark eq. 18) is 0/0, outside "
                "the validity region of the shadow equation. An occluder lying on the emitter "
                "blocks the part it covers: give the emitter without that part instead."
            )
        j = int(np.argmin(e[:, 2]))
        if occluder_verts[high, 2] > e[j, 2]:
            name = "the emitter" if len(emitters) == 1 else f"emitter {k}"
            raise ValueError(
                f"{what}: the occluder must lie between the receiver plane and {name}, "
                f"strictly below it in height (validity region of the shadow equation, Stark "
                f"§7): occluder vertex {high} at z = {occluder_verts[high, 2]:.6g} is above "
                f"emitter vertex {j} at z = {e[j, 2]:.6g}."
            )


#: Occluder and emitter vertices closer than this (times the emitter's size, per coordinate)
#: count as shared. Float32 rounds coordinates to ~6e-8 relative, which decides the direction
#: of a node whose `P` and `w` are that small.
SHARED_VERTEX_RTOL = 1e-6


def _as_float(*xs: object) -> list[Array]:
    arrs = [jnp.asarray(x) for x in xs]
    dt = jnp.promote_types(jnp.result_type(*arrs), jnp.float32)
    return [a.astype(dt) for a in arrs]


@eqx.filter_jit
def _spline_shadow(emitter: Array, occluder: Array, points: Array) -> Array:
    return jax.vmap(spline_shadow_kernel, in_axes=(0, None, None))(points, emitter, occluder)


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def spline_shadow(
    emitter: Float[ArrayLike, "m 3"], occluder: Float[ArrayLike, "n 3"], points: Float[ArrayLike, "N 3"]
) -> Float[Array, " N"]:
    r"""Form factor of the visible part of a polygon emitter behind one polygon occluder.

    Stark et al.'s shadow equation (eq. 24) for a horizontal receiver (normal $+z$; the
    paper's floor $z = 0$, here the horizontal plane through each point). Equals
    `form_factor(points, +z, emitter)` where the occluder's shadow misses the point. The
    irradiance is $E = \pi L F$.

    **Arguments:**

    - `emitter`: `(m, 3)` convex planar polygon, counter-clockwise seen from the side it emits
      to (the receiver side).
    - `occluder`: `(n, 3)` convex planar polygon, any orientation, strictly above every
      receiver point and nowhere above the emitter's lowest vertex (module docstring, note 8).
    - `points`: `(N, 3)` receiver points.

    **Returns:** `(N,)` dimensionless form factors, dtype following the inputs.

    **Raises:** `ValueError` (inputs concrete, i.e. not under jit/grad/vmap) for bad shapes,
    NaN/inf, non-convex or degenerate polygons, and configurations outside the validity region.
    Jitted (`eqx.filter_jit`) below the checks; differentiable in every input.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js

        emitter = np.array([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2.0]])      # emits towards -z
        occluder = np.array([[0.3, 0.3, 1], [0.7, 0.3, 1], [0.7, 0.7, 1], [0.3, 0.7, 1.0]])
        F = js.spline_shadow(emitter, occluder, np.array([[0.5, 0.5, 0.0], [0.9, 0.1, 0.0]]))
        ```
    """
    what = "spline_shadow"
    for name, x, ndim in (
        ("emitter", emitter, 2),
        ("occluder", occluder, 2),
        ("points", points, 2),
    ):
        shape = jnp.shape(x)  # static even under tracing
        if len(shape) != ndim or shape[-1] != 3:
            raise ValueError(f"{what}: {name} must have shape (k, 3), got {shape}.")
    if all(is_concrete(x) for x in (emitter, occluder, points)):
        e = check_convex_polygon(
            strip_padding(np.asarray(emitter, np.float64)), f"{what}: emitter"
        )
        o = check_convex_polygon(
            strip_padding(np.asarray(occluder, np.float64)), f"{what}: occluder"
        )
        pts = _check_points(points, what)
        _check_validity_region([e], o, pts, what)
    else:
        emitter, occluder, points = check_finite_leaves((emitter, occluder, points), what)
    emitter, occluder, points = _as_float(emitter, occluder, points)
    return _spline_shadow(emitter, occluder, points)


@eqx.filter_jit
def _spline_shadow_faces(emitters: Array, faces: Array, points: Array) -> Array:
    # Orient every face inward, towards the mean of all vertices (inside a convex polyhedron).
    centre = jnp.mean(faces.reshape(-1, 3), axis=0)
    inward = jax.vmap(lambda f: on_lit_side(centre, f))(faces)  # translation- and scale-free
    faces = jnp.where(inward[:, None, None], faces, faces[:, ::-1, :])
    return jax.vmap(spline_shadow_faces_kernel, in_axes=(0, None, None))(points, emitters, faces)


def _stack_polygons(polys: Any, what: str) -> tuple[Array, list[np.ndarray] | None]:
    """A `(L, k, 3)` array or a list of `(k_l, 3)` polygons -> padded `(L, K, 3)` JAX array,
    plus the validated NumPy polygons when concrete."""
    if isinstance(polys, (list, tuple)):
        items = list(polys)
    else:
        arr = polys if hasattr(polys, "ndim") else np.asarray(polys)
        if arr.ndim != 3 or arr.shape[-1] != 3:
            raise ValueError(
                f"{what}: expected shape (L, k, 3) or a list of (k, 3), got {arr.shape}."
            )
        items = [arr[i] for i in range(arr.shape[0])]
    if not items:
        raise ValueError(f"{what}: at least one polygon is needed.")
    checked = None
    if all(is_concrete(x) for x in items):
        checked = [
            check_convex_polygon(strip_padding(np.asarray(x, np.float64)), f"{what} {i}")
            for i, x in enumerate(items)
        ]
    k = max(int(jnp.shape(x)[0]) for x in items)
    padded = []
    for x in items:
        x = jnp.asarray(x)
        if x.shape[0] < k:
            x = jnp.concatenate([x, jnp.repeat(x[:1], k - x.shape[0], axis=0)], axis=0)
        padded.append(x)
    return jnp.stack(padded), checked


def _check_closed_convex(faces: list[np.ndarray], what: str) -> None:
    """The faces must bound one convex polyhedron: all vertices on the inner side of every
    face, and the face vector areas (oriented inward) summing to zero (closed surface)."""
    verts = np.concatenate(faces)
    centre = verts.mean(axis=0)
    size = float(np.max(np.linalg.norm(verts - centre, axis=1)))
    total = np.zeros(3)
    scale = 0.0
    for k, f in enumerate(faces):
        n = 0.5 * np.sum(np.cross(f, np.roll(f, -1, axis=0)), axis=0)
        if np.dot(n, centre - f[0]) < 0:
            n = -n
        nhat = n / np.linalg.norm(n)
        d = (verts - f[0]) @ nhat
        if np.min(d) < -1e-9 * size:
            raise ValueError(
                f"{what}: faces do not bound a convex polyhedron: a vertex lies "
                f"{-np.min(d):.3g} outside the plane of face {k}."
            )
        total += n
        scale += np.linalg.norm(n)
    if np.linalg.norm(total) > 1e-9 * scale:
        raise ValueError(
            f"{what}: faces do not close a polyhedron (their vector areas sum to "
            f"{np.linalg.norm(total):.3g}, not 0); give every face of the convex occluder."
        )


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def spline_shadow_faces(
    emitters: Float[ArrayLike, "l m 3"] | list,
    faces: Float[ArrayLike, "f k 3"] | list,
    points: Float[ArrayLike, "N 3"],
) -> Float[Array, " N"]:
    r"""Shadow equation with several emitters and one convex polyhedral occluder (Stark fig. 14).

    Returns $\sum_l F_l$, the summed form factors of the visible parts of the emitters (the
    irradiance is $\pi L \sum_l F_l$ for emitters of equal radiance $L$; call once per emitter
    otherwise). Only the faces that face each point occlude it (module docstring, note 5).

    **Arguments:**

    - `emitters`: `(L, m, 3)` array or a list of `(m_l, 3)` convex polygons, each
      counter-clockwise seen from the side it emits to. Lists are padded by repeating the first
      vertex.
    - `faces`: `(F, k, 3)` array or a list of `(k_f, 3)` convex polygons: all faces of one convex
      polyhedron, any orientation. Same validity region as `spline_shadow` (every face vertex
      strictly above every point, none above any emitter's lowest vertex).
    - `points`: `(N, 3)` receiver points; horizontal receiver plane, normal $+z$.

    **Returns:** `(N,)` dimensionless, dtype following the inputs.

    **Raises:** `ValueError` for invalid inputs (when concrete), as `spline_shadow`, and when
    the faces do not bound a closed convex polyhedron.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js

        emitter = np.array([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2.0]])
        a, b, c, d = [0.3, 0.3, 1.0], [0.7, 0.3, 1.0], [0.5, 0.7, 1.0], [0.5, 0.45, 1.3]   # a tetrahedron
        faces = np.array([[a, c, b], [a, b, d], [b, c, d], [c, a, d]])   # every face of the occluder
        F = js.spline_shadow_faces(emitter[None], faces, np.array([[0.5, 0.5, 0.0]]))
        ```
    """
    what = "spline_shadow_faces"
    em, em_np = _stack_polygons(emitters, f"{what}: emitter")
    fa, fa_np = _stack_polygons(faces, f"{what}: face")
    if em_np is not None and fa_np is not None and is_concrete(points):
        pts = _check_points(points, what)
        _check_closed_convex(fa_np, what)
        _check_validity_region(em_np, np.concatenate(fa_np), pts, what)
    else:
        em, fa, points = check_finite_leaves((em, fa, points), what)
    em, fa, points = _as_float(em, fa, points)
    return _spline_shadow_faces(em, fa, points)
