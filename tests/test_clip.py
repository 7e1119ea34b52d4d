"""Exact soft shadows by occluder clipping (`jaxshadow._kernels.clip`).

The reference shares no code with the kernels: Sutherland-Hodgman clipping in NumPy (emitter to
the receiver's horizon; each occluder to the lit side of the emitter plane and to the pyramid
over a large square around the emitter), central projection, exact polygon booleans in the
emitter plane with `shapely`, and Lambert's contour sum written out here.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads
from scipy import integrate

shapely = pytest.importorskip("shapely")
from shapely.geometry import Polygon  # noqa: E402
from shapely.geometry.polygon import orient  # noqa: E402

from benchmarks import scenes  # noqa: E402
from benchmarks.scenes import clip_halfspace  # noqa: E402
from jaxshadow._kernels.clip import (  # noqa: E402
    directional_visibility,
    point_visibility,
    visible_edges,
    visible_form_factor_kernel,
    visible_linear_kernel,
)

# --------------------------------------------------------------------------------------
# Independent NumPy / shapely reference
# --------------------------------------------------------------------------------------


def _newell(v):
    return np.sum(np.cross(v, np.roll(v, -1, axis=0)), axis=0)


def _lambert(p, n, ring3d):
    """Lambert's contour sum for a closed ring counter-clockwise seen from p."""
    total = 0.0
    k = len(ring3d)
    for i in range(k):
        a = ring3d[i] - p
        b = ring3d[(i + 1) % k] - p
        c = np.cross(b, a)
        s = np.linalg.norm(c)
        if s == 0:
            continue
        total += math.atan2(s, np.dot(a, b)) * np.dot(n, c) / s
    return total / (2 * math.pi)


class EmitterFrame(NamedTuple):
    """The polygon-boolean references' frame of the emitter plane: its unit normal `ne` (Newell),
    origin `e0` (the first vertex), the receiver's height `hp` above it, in-plane axes `u`, `v`,
    `region` (the emitter clipped to the receiver's upper half-space, a shapely polygon in (u, v))
    and `corners`, a square twice the emitter's radius about its centre (the pyramid from p over it
    holds the emitter: projections stay finite, and small beside the overlay grid's range)."""

    ne: np.ndarray
    e0: np.ndarray
    hp: float
    u: np.ndarray
    v: np.ndarray
    region: Any
    corners: list

    def to2(self, x):
        return ((x - self.e0) @ self.u, (x - self.e0) @ self.v)

    def to3(self, xy):
        return self.e0 + xy[0] * self.u + xy[1] * self.v


def emitter_frame(p, n, em):
    """`EmitterFrame` of the emitter `em (k, 3)` seen from `p` with normal `n` (float64), or None
    where nothing of it is visible (p on or behind its plane, or it lies below p's horizon)."""
    ne = _newell(em)
    ne = ne / np.linalg.norm(ne)
    e0 = em[0]
    hp = float(np.dot(ne, p - e0))
    if hp <= 0:
        return None
    u = em[1] - em[0]
    u /= np.linalg.norm(u)
    v = np.cross(ne, u)
    eh = [np.asarray(x) for x in clip_halfspace(list(em), p, n)]
    if len(eh) < 3:
        return None
    region = Polygon([((x - e0) @ u, (x - e0) @ v) for x in eh])
    if region.area == 0:
        return None
    c = em.mean(axis=0)
    big = 2.0 * np.max(np.linalg.norm(em - c, axis=1))
    corners = [c + sx * big * u + sy * big * v for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    return EmitterFrame(ne, e0, hp, u, v, region, corners)


def reference_ff(p, n, emitter, occluders):
    """Form factor of the visible part of `emitter` (float64, exact booleans)."""
    p = np.asarray(p, np.float64)
    n = np.asarray(n, np.float64)
    em = np.asarray(emitter, np.float64)
    fr = emitter_frame(p, n, em)
    if fr is None:
        return 0.0
    ne, e0, hp, corners, to2 = fr.ne, fr.e0, fr.hp, fr.corners, fr.to2
    shadows = []
    for occ in occluders:
        poly = [np.asarray(x) for x in clip_halfspace(list(np.asarray(occ, np.float64)), e0, ne)]
        for i in range(4):
            a, b = corners[i], corners[(i + 1) % 4]
            nrm = np.cross(b - p, a - p)  # interior of the pyramid on the positive side
            poly = [np.asarray(x) for x in clip_halfspace(poly, p, nrm)]
            if len(poly) < 3:
                break
        if len(poly) < 3:
            continue
        proj = []
        for x in poly:
            r = x - p
            proj.append(to2(p + r * hp / -np.dot(r, ne)))
        q = Polygon(proj)
        if not q.is_valid:
            q = q.buffer(0)
        if q.area > 0:
            shadows.append(q)
    return _visible_lambert(p, n, em, fr.region, shadows, fr.to3)


def _visible_lambert(p, n, em, region, shadows, to3, name="reference_ff"):
    """Lambert's sum (`_lambert`) over `region` (a shapely polygon in the emitter plane's 2D frame
    of `to3`) minus the union of the `shadows` polygons, by a snap-rounded overlay."""
    if shadows:
        # Snap-rounded overlay, a grid of 2^-42 of the emitter's radius (every coordinate within
        # 2^44 grid steps): the floating overlay's union of a mesh's projected faces lost 6.6e-6
        # of area on one draw (their exact union: Fractions). Snapping moves a vertex by under a
        # grid step; where GEOS still fails, a 16x coarser grid.
        c = em.mean(axis=0)
        rad = float(np.max(np.linalg.norm(em - c, axis=1)))
        for g in (2.0**-42 * rad, 2.0**-38 * rad):
            try:
                region = shapely.difference(region, shapely.union_all(shadows, grid_size=g), grid_size=g)
                break
            except shapely.errors.GEOSException:
                continue
        else:
            raise AssertionError(f"{name}: the snap-rounded overlay failed")
    total = 0.0
    for g in getattr(region, "geoms", [region]):
        if g.geom_type != "Polygon" or g.area == 0:
            continue
        g = orient(g, 1.0)
        for ring in (g.exterior, *g.interiors):
            total += _lambert(p, n, [to3(xy) for xy in list(ring.coords)[:-1]])
    return total


def _may_meet(p, x, tris):
    """Triangles `(m, 3, 3)` not entirely on one side (beyond 1e-12 of the coordinates' size) of
    either of two orthogonal planes through the segment p x, nor entirely beyond one of its ends:
    the others cannot meet it."""
    r = x - p
    length = np.linalg.norm(r)
    r = r / length
    u = np.cross(r, np.eye(3)[int(np.argmin(np.abs(r)))])
    u /= np.linalg.norm(u)
    d = tris - p
    tol = 1e-12 * max(float(np.abs(d).max()), length)
    keep = np.ones(len(tris), bool)
    for a in (u, np.cross(r, u)):
        s = d @ a
        keep &= ~(np.all(s > tol, axis=1) | np.all(s < -tol, axis=1))
    s = d @ r
    return keep & ~(np.all(s < -tol, axis=1) | np.all(s > length + tol, axis=1))


def ray_blocked_np(p, x, occluders):
    """NumPy: does the open segment p -> x cross the interior of an occluder? (Triangles given as
    one `(m, 3, 3)` array are first narrowed to those that can meet the segment.)"""
    if isinstance(occluders, np.ndarray) and occluders.ndim == 3 and occluders.shape[1] == 3 and len(occluders):
        occluders = occluders[_may_meet(np.asarray(p, np.float64), np.asarray(x, np.float64), occluders)]
    # Orientations only (no intersection point): the signs of det(v_i - p, v_i+1 - p, x - p) decide
    # on which side of each edge the segment passes; well conditioned for a receiver near a face.
    d = np.asarray(x, np.float64) - np.asarray(p, np.float64)
    for occ in occluders:
        occ = np.asarray(occ, np.float64)
        no = _newell(occ)
        dp = np.dot(no, p - occ[0])
        dx = np.dot(no, x - occ[0])
        if dp == 0 or dp * dx >= 0:
            continue
        r = occ - p
        signs = np.dot(np.cross(r, np.roll(r, -1, axis=0)), d)
        if np.all(signs > 0) or np.all(signs < 0):
            return True
    return False


# --------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------


def random_convex(rng, k, size, centre, tilt, facing_down=None):
    v = scenes.random_convex(rng, k, lambda r: size * r.uniform(0.5, 1.0, size=2), centre, tilt, 0.9 * np.pi)
    if facing_down is not None:
        nz = _newell(v)[2]
        if (nz < 0) != facing_down:
            v = v[::-1]
    return v


def pad(polys, k=None):
    k = k or max(len(q) for q in polys)
    return np.stack([np.concatenate([q, np.repeat(q[:1], k - len(q), axis=0)]) for q in polys])


# One padded shape for (almost) every test: compiling this kernel is the slow part. Missing
# occluders are replaced by a dummy triangle far behind the emitter (it blocks nothing).
M_PAD, KO_PAD, K_PAD, N_PAD = 8, 4, 6, 40
_ff_batch = jax.jit(jax.vmap(visible_form_factor_kernel, in_axes=(0, 0, None, None)))
# Compiled as the public entry points run them: called eagerly, a kernel dispatches op by op, one
# small compilation per operation (~100 per kernel and dtype).
_kernel_jit = jax.jit(visible_form_factor_kernel)
_point_vis = jax.jit(point_visibility)
_dir_vis = jax.jit(directional_visibility)


def padded_scene(emitter, occluders, dtype=np.float64, m_pad=M_PAD, k_pad=K_PAD):
    em = np.asarray(emitter, np.float64)
    ne = _newell(em)
    ne /= np.linalg.norm(ne)
    dummy = em[:3].mean(axis=0) - 100.0 * ne + np.array([[0, 0, 0], [1.0, 0, 0], [0, 1.0, 0]])
    occs = [np.asarray(o, np.float64) for o in occluders] + [dummy] * (m_pad - len(occluders))
    return jnp.asarray(pad([em], k_pad)[0], dtype), jnp.asarray(pad(occs, KO_PAD), dtype)


def ff_many(points, normals, emitter, occluders, dtype=np.float64):
    """The kernel at many points, in chunks of the one compiled shape."""
    points = np.atleast_2d(np.asarray(points, np.float64))
    normals = np.broadcast_to(np.asarray(normals, np.float64), points.shape)
    em, oc = padded_scene(emitter, occluders, dtype)
    out = []
    for i in range(0, len(points), N_PAD):
        chunk = points[i : i + N_PAD]
        m = len(chunk)
        pp = np.concatenate([chunk, np.repeat(chunk[:1], N_PAD - m, axis=0)])
        nn = np.concatenate([normals[i : i + m], np.repeat(normals[i : i + 1], N_PAD - m, axis=0)])
        out.append(
            np.asarray(_ff_batch(jnp.asarray(pp, dtype), jnp.asarray(nn, dtype), em, oc))[:m]
        )
    return np.concatenate(out)


def ff(p, n, emitter, occluders, dtype=np.float64):
    return ff_many(p, n, emitter, occluders, dtype)[0]


def random_scene(seed, m_occ):
    rng = np.random.default_rng(seed)
    emitter = random_convex(
        rng, rng.integers(3, 7), 1.0, np.array([0, 0, 3.0]), 0.6, facing_down=True
    )
    occs = []
    for _ in range(m_occ):
        centre = np.array([*rng.uniform(-1.2, 1.2, size=2), rng.uniform(0.6, 2.6)])
        occs.append(random_convex(rng, rng.integers(3, 5), rng.uniform(0.2, 0.7), centre, 1.2))
    return emitter, occs


def unoccluded(p, n, emitter):
    return reference_ff(p, n, emitter, [])


# --------------------------------------------------------------------------------------
# Accuracy against the reference
# --------------------------------------------------------------------------------------


def test_reference_lambert_against_quadrature():
    # Sanity of the reference itself: parallel unit square 1 above the receiver, direct area integral.
    em = np.array([[0, 0, 1.0], [0, 1, 1], [1, 1, 1], [1, 0, 1]])
    p = np.array([0.2, 0.3, 0.0])
    n = np.array([0, 0, 1.0])

    def f(y, x):
        r2 = (x - p[0]) ** 2 + (y - p[1]) ** 2 + 1.0
        return 1.0 / (math.pi * r2 * r2)

    quad, _ = integrate.dblquad(f, 0, 1, 0, 1, epsabs=1e-13, epsrel=1e-13)
    assert abs(reference_ff(p, n, em, []) - quad) < 1e-12


@pytest.mark.parametrize("m_occ", [1, 3, 8])
def test_random_scenes_float64(m_occ):
    worst = 0.0
    kinds = set()
    for seed in range(4):
        emitter, occs = random_scene(100 * m_occ + seed, m_occ)
        rng = np.random.default_rng(seed)
        pts = np.concatenate([rng.uniform(-2.5, 2.5, size=(24, 2)), np.zeros((24, 1))], axis=1)
        nrm = np.tile([0.0, 0.0, 1.0], (24, 1))
        # A few tilted receivers (the horizon cuts the emitter) and raised points (inside the
        # occluders' slab, occluders straddle the receivers' tangent planes).
        nrm[:6] = np.array([[math.sin(a), 0, math.cos(a)] for a in np.linspace(-1.3, 1.3, 6)])
        pts[18:, 2] = rng.uniform(0.3, 1.5, size=6)
        got = ff_many(pts, nrm, emitter, occs)
        for i in range(len(pts)):
            ref = reference_ff(pts[i], nrm[i], emitter, occs)
            free = unoccluded(pts[i], nrm[i], emitter)
            # Relative to the unoccluded F, with a floor: where a steep horizon leaves a sliver
            # of the emitter (F ~ 1e-7), Lambert's sum cancels terms of order 0.1 and what is
            # left is the absolute round-off, ~1e-17 in the kernel and in this reference alike
            # (the unoccluded kernel differs from the reference by as much there).
            err = abs(got[i] - ref) / max(free, 1e-6)
            worst = max(worst, err if free > 0 else abs(got[i]))
            if free > 0:
                kinds.add(
                    "lit" if ref > free * (1 - 1e-12) else "umbra" if ref < 1e-15 else "penumbra"
                )
    assert worst <= 1e-10, worst
    assert "penumbra" in kinds and "lit" in kinds


def test_random_scenes_float32():
    worst = 0.0
    for seed in range(3):
        emitter, occs = random_scene(7 + seed, 4)
        rng = np.random.default_rng(seed)
        pts = np.concatenate([rng.uniform(-2.0, 2.0, size=(24, 2)), np.zeros((24, 1))], axis=1)
        nrm = np.tile([0.0, 0.0, 1.0], (24, 1))
        got = ff_many(pts, nrm, emitter, occs, np.float32)
        assert got.dtype == np.float32
        for i in range(len(pts)):
            free = unoccluded(pts[i], nrm[i], emitter)
            worst = max(worst, abs(got[i] - reference_ff(pts[i], nrm[i], emitter, occs)) / free)
    assert worst <= 1e-5, worst


def test_umbra_and_lit_exact():
    em = np.array([[-1, -1, 2.0], [-1, 1, 2], [1, 1, 2], [1, -1, 2]])  # CCW seen from below
    occ = np.array([[[-3, -3, 1.0], [3, -3, 1], [3, 3, 1], [-3, 3, 1]]])
    n = np.array([0, 0, 1.0])
    assert float(ff([0.1, 0.2, 0], n, em, occ)) == 0.0
    occ_far = occ + np.array([10.0, 0, 0])
    assert float(ff([0.1, 0.2, 0], n, em, occ_far)) == pytest.approx(
        unoccluded([0.1, 0.2, 0], n, em), rel=1e-13
    )
    no_occ = _kernel_jit(
        jnp.array([0.1, 0.2, 0]), jnp.asarray(n), jnp.asarray(em), jnp.zeros((0, 3, 3))
    )
    assert float(no_occ) == pytest.approx(unoccluded([0.1, 0.2, 0], n, em), rel=1e-13)


# --------------------------------------------------------------------------------------
# Special configurations
# --------------------------------------------------------------------------------------

EM = np.array([[-1, -1, 2.0], [-1, 1, 2], [1, 1, 2], [1, -1, 2]])  # z = 2, CCW seen from below
UP = np.array([0, 0, 1.0])
GRID = [np.array([x, y, 0.0]) for x in np.linspace(-2.2, 2.2, 7) for y in np.linspace(-1.9, 2.1, 5)]


def _check_cases(occs, points=GRID, normal=UP, emitter=EM, tol=1e-10):
    worst = 0.0
    got = ff_many(np.array(points), normal, emitter, occs)
    for i, p in enumerate(points):
        ref = reference_ff(p, normal, emitter, occs)
        free = unoccluded(p, normal, emitter)
        worst = max(worst, abs(got[i] - ref) / max(free, 1e-12))
    assert worst <= tol, worst
    return worst


def test_overlapping_occluders():
    a = np.array([[-0.6, -0.5, 1.0], [0.4, -0.5, 1.0], [0.4, 0.5, 1.0], [-0.6, 0.5, 1.0]])
    b = np.array([[-0.2, -0.3, 1.3], [0.8, -0.1, 1.2], [0.5, 0.7, 1.4]])
    c = a + np.array([0.3, 0.2, 0.0])  # same plane, overlapping a
    _check_cases([a, b, c])


def test_identical_occluders_and_coplanar_overlap():
    a = np.array([[-0.6, -0.5, 1.0], [0.4, -0.5, 1.0], [0.4, 0.5, 1.0], [-0.6, 0.5, 1.0]])
    # The same polygon twice (one reversed): all edges coincide, same side.
    _check_cases([a, a[::-1].copy()])
    # Sharing one edge line and overlapping along it.
    b = np.array([[-0.2, -0.5, 1.0], [0.9, -0.5, 1.0], [0.9, 0.1, 1.0], [-0.2, 0.1, 1.0]])
    _check_cases([a, b])


def test_shared_edges_and_vertices():
    # Two triangles of a quad (shared diagonal, opposite sides) and a third sharing a vertex.
    q = np.array([[-0.5, -0.4, 1.0], [0.5, -0.4, 1.2], [0.5, 0.6, 1.2], [-0.5, 0.6, 1.0]])
    t1 = q[[0, 1, 2]]
    t2 = q[[0, 2, 3]]
    t3 = np.array([q[2], [0.9, 0.9, 1.5], [0.2, 1.0, 1.3]])
    _check_cases([t1, t2, t3])
    # The split quad casts the same shadow as the quad.
    for p in GRID[::3]:
        assert float(ff(p, UP, EM, [t1, t2])) == pytest.approx(float(ff(p, UP, EM, [q])), abs=1e-13)


def test_occluder_straddling_emitter_plane():
    occ = np.array([[-0.5, -0.3, 1.5], [0.6, -0.3, 2.6], [0.6, 0.4, 2.6], [-0.5, 0.4, 1.5]])
    _check_cases([occ])
    # Vertical occluder crossing the emitter plane through the emitter.
    wall = np.array([[0.2, -2.0, 1.0], [0.2, 2.0, 1.0], [0.2, 2.0, 3.0], [0.2, -2.0, 3.0]])
    _check_cases([wall])


def test_occluder_straddling_receiver_tangent_plane():
    occ = np.array([[-0.5, -0.3, -0.5], [0.6, -0.3, 1.4], [0.6, 0.4, 1.4], [-0.5, 0.4, -0.5]])
    _check_cases([occ])
    # Tilted receivers: their tangent planes cut both the emitter and the occluder.
    tilted = np.array([0.6, 0.0, 0.8])
    _check_cases([occ], normal=tilted)


def test_occluder_reaching_behind_receiver():
    # Part of the occluder is farther from the emitter plane than the receiver (its central
    # projection is unbounded): only the part between them counts.
    occ = np.array([[-4.0, -0.3, -1.0], [1.0, -0.3, 1.5], [1.0, 0.4, 1.5], [-4.0, 0.4, -1.0]])
    pts = [np.array([x, 0.1, 0.0]) for x in np.linspace(-1.5, 2.0, 8)]
    _check_cases([occ], points=pts)


def test_occluder_touching_receiver():
    # A box-like wall standing on the receiver plane z = 0.
    wall = np.array([[0.3, -1.0, 0.0], [0.3, 1.0, 0.0], [0.3, 1.0, 1.5], [0.3, -1.0, 1.5]])
    # 0.3 is no float32 value: the on-surface rule (faces of float32 values) does not apply, and
    # points 1e-7 from the wall are exact.
    pts = [np.array([x, 0.2, 0.0]) for x in (-1.0, 0.0, 0.29, 0.2999999, 0.3000001, 0.31, 1.0, 2.0)]
    _check_cases([wall], points=pts)
    # Exactly at the foot of the wall: finite (the wall's plane contains p: it blocks nothing).
    got = float(ff([0.3, 0.2, 0.0], UP, EM, [wall]))
    assert got == pytest.approx(unoccluded([0.3, 0.2, 0.0], UP, EM), rel=1e-12)
    # A wall of float32 values: within 2^-18 S of its plane (S = 2: `_clip.ON_SURFACE`) p lies on
    # it, and it blocks nothing.
    w32 = wall.copy()
    w32[:, 0] = 0.25
    for x in (0.25, 0.2499999, 0.2500001):
        got = float(ff([x, 0.2, 0.0], UP, EM, [w32]))
        assert got == pytest.approx(unoccluded([x, 0.2, 0.0], UP, EM), rel=1e-12)
    # A triangle with one vertex on the receiver plane, p elsewhere.
    tri = np.array([[0.0, 0.0, 0.0], [0.8, -0.3, 1.2], [0.5, 0.6, 1.2]])
    _check_cases([tri])


def test_float32_occluder_1e9_above_receiver():
    # An occluder parallel to the receiver's plane 1e-5 above p (p off the origin, so o - p is
    # rounded; beyond the on-surface distance 2^-18 S = 1.5e-6 of `js.irradiance`, within which
    # p would lie on it): float32 tells its side and it shadows everything; a tilted occluder whose plane contains p (not representable in
    # float32: p is within rounding of it) blocks nothing. All kernels; finite gradients.
    f32 = np.float32
    p = np.array([0.3, -0.2, 0.0])
    cover = np.array([[0.2, -0.3, 1e-5], [0.4, -0.3, 1e-5], [0.4, -0.1, 1e-5], [0.2, -0.1, 1e-5]])
    e1, e2 = np.array([0.6, 0.0, 0.8]), np.array([0.0, 1.0, 0.0])
    tilted = p + 0.5 * np.array([-e1 - e2, e1 - e2, e1 + e2, e2 - e1])
    vg = jax.jit(jax.value_and_grad(visible_form_factor_kernel, argnums=(0, 1, 2, 3)))
    a, b = np.array([-1.0, 0.0, 2.0]), np.array([1.0, 0.1, 2.0])
    lin = jax.jit(visible_linear_kernel, static_argnums=4)
    q = jnp.asarray(p, f32)
    for occ, blocks in ((cover, True), (tilted, False)):
        o = jnp.asarray(occ[None], f32)
        val, grads = vg(q, jnp.asarray(UP, f32), jnp.asarray(EM, f32), o)
        for g in grads:
            assert np.all(np.isfinite(np.asarray(g)))
        assert float(_point_vis(q, jnp.array([0.3, -0.2, 2.0], f32), o)) == (not blocks)
        assert float(_dir_vis(q, jnp.array([0.0, 0.0, -1.0], f32), o)) == (not blocks)
        e_lin = float(lin(q, jnp.asarray(UP, f32), jnp.asarray(a, f32), jnp.asarray(b, f32), 1, o))
        if blocks:
            assert float(val) == 0.0
            assert e_lin == 0.0
        else:
            assert float(val) == pytest.approx(unoccluded(p, UP, EM), rel=2e-6)
            assert e_lin == pytest.approx(reference_linear(p, UP, a, b, 1, []), rel=2e-6)


def test_coincident_occluder_and_emitter_edges():
    # Occluder whose projection from (0,0,0) is exactly the emitter: full umbra.
    occ = np.array([[-0.5, -0.5, 1.0], [-0.5, 0.5, 1], [0.5, 0.5, 1], [0.5, -0.5, 1]])
    o = np.zeros(3)
    assert float(ff(o, UP, EM, [occ])) == 0.0
    assert float(ff(o, UP, EM, [occ[::-1].copy()])) == 0.0
    # Projection sharing one edge with the emitter from inside, and one from outside.
    inside = np.array([[-0.5, -0.5, 1.0], [0.0, -0.5, 1], [0.0, 0.5, 1], [-0.5, 0.5, 1]])
    outside = np.array([[-1.0, -0.5, 1.0], [-0.5, -0.5, 1], [-0.5, 0.5, 1], [-1.0, 0.5, 1]])
    for occs in ([inside], [outside], [inside, outside], [outside, inside]):
        _check_cases(occs, points=[o])
    # Occluders lying on the emitter itself, edges on the emitter's edges (shared 3-D edges).
    on_em = np.array([[-1, -1, 2.0], [-1, 1, 2], [0, 1, 2], [0, -1, 2]])
    _check_cases([on_em])
    # An occluder hinged on an emitter edge (its cut with the emitter plane is that edge).
    hinge = np.array([[-1, -1, 2.0], [-1, 1, 2], [-0.2, 1, 1.2], [-0.2, -1, 1.2]])
    _check_cases([hinge])
    # An occluder edge in the plane through p and an emitter edge, and a vertex on the emitter plane.
    p = np.array([0.0, 0.0, 0.0])
    edge_aligned = np.array([[-0.5, -0.5, 1.0], [0.2, -0.5, 1.0], [0.3, 0.2, 1.4]])
    vertex_on_plane = np.array([[0.3, 0.3, 2.0], [0.9, 0.0, 1.0], [0.8, 0.8, 1.2]])
    _check_cases([edge_aligned, vertex_on_plane], points=[p, p + [0.1, 0, 0], p + [0, 0.1, 0]])


def test_visible_edges_shapes_and_orientation():
    occ = np.array([[[-0.3, -0.3, 1.0], [0.3, -0.3, 1], [0.3, 0.3, 1], [-0.3, 0.3, 1]]])
    s, e = jax.jit(visible_edges)(jnp.zeros(3), jnp.asarray(UP), jnp.asarray(EM), jnp.asarray(occ))
    assert s.shape == e.shape == ((4 + 1 + 1 * 5) * (1 + 1), 3)
    # Signed area (seen from p below, i.e. looking up +z) of the soup = emitter minus hole.
    s2, e2 = np.asarray(s)[:, :2], np.asarray(e)[:, :2]
    area = 0.5 * np.sum(s2[:, 0] * e2[:, 1] - s2[:, 1] * e2[:, 0])
    assert abs(abs(area) - (4.0 - 0.36 * 4)) < 1e-12


# --------------------------------------------------------------------------------------
# Cross-validation against the Stark et al. shadow equation
# --------------------------------------------------------------------------------------


def test_against_spline_shadow():
    spline = pytest.importorskip("jaxshadow._kernels.spline")
    worst = 0.0
    for seed in range(6):
        rng = np.random.default_rng(500 + seed)
        em = random_convex(
            rng, rng.integers(3, 6), 1.0, np.array([0, 0, 3.0]), 0.4, facing_down=True
        )
        tilt = 0.0 if seed % 2 == 0 else 0.3
        occ = random_convex(
            rng, rng.integers(3, 5), 0.6, np.array([*rng.uniform(-0.5, 0.5, 2), 1.5]), tilt
        )
        pts = np.concatenate([rng.uniform(-2, 2, size=(20, 2)), np.zeros((20, 1))], axis=1)
        # Points on discontinuity lines: the floor traces of planes through an emitter vertex
        # and an occluder edge (VE events).
        for j in range(3):
            ev = em[j % len(em)]
            oa, ob = occ[j % len(occ)], occ[(j + 1) % len(occ)]
            for t in (0.3, 0.6):
                x = oa + t * (ob - oa)
                pts = np.concatenate([pts, (ev + (x - ev) * ev[2] / (ev[2] - x[2]))[None]], axis=0)
                pts[-1, 2] = 0.0
        got = ff_many(pts, UP, em, [occ])
        want = np.asarray(spline.spline_shadow(jnp.asarray(em), jnp.asarray(occ), jnp.asarray(pts)))
        worst = max(worst, float(np.max(np.abs(got - want))))
    assert worst <= 1e-10, worst


# --------------------------------------------------------------------------------------
# Segment lights
# --------------------------------------------------------------------------------------


def _w(k):
    return integrate.quad(lambda b: math.cos(b) ** k, -math.pi / 2, math.pi / 2, epsabs=1e-14)[0]


def reference_linear(p, n, a, b, m, occluders, samples=301):
    """E/Phi by Gauss-Legendre on the visible intervals, found by bisection on a NumPy ray test
    between `samples` equally spaced points (finds every interval wider than their spacing)."""
    length = np.linalg.norm(b - a)
    u = (b - a) / length
    c_m = 1.0 / (2 * math.pi * _w(m + 1))

    def vis(t):
        return not ray_blocked_np(p, a + t * (b - a), occluders)

    ts = np.linspace(0, 1, samples)
    flags = [vis(t) for t in ts]
    cuts = [0.0]
    for i in range(len(ts) - 1):
        if flags[i] != flags[i + 1]:
            lo, hi = ts[i], ts[i + 1]
            for _ in range(45):
                mid = 0.5 * (lo + hi)
                if vis(mid) == flags[i]:
                    lo = mid
                else:
                    hi = mid
            cuts.append(0.5 * (lo + hi))
    # Horizon crossing (the integrand has a kink there).
    hn0, hn1 = np.dot(n, a - p), np.dot(n, b - p)
    if hn0 * hn1 < 0:
        cuts.append(hn0 / (hn0 - hn1))
    cuts = sorted(cuts + [1.0])
    x, wts = np.polynomial.legendre.leggauss(60)
    total = 0.0
    for t0, t1 in zip(cuts[:-1], cuts[1:], strict=True):
        if t1 <= t0 or not vis(0.5 * (t0 + t1)):
            continue
        for xi, wi in zip(x, wts, strict=True):
            t = t0 + (t1 - t0) * (xi + 1) / 2
            w = a + t * (b - a) - p
            r = np.linalg.norm(w)
            cos_beta = math.sqrt(max(0.0, 1 - (np.dot(u, w) / r) ** 2))
            total += (
                wi * (t1 - t0) / 2 * length * c_m * cos_beta**m * max(0.0, np.dot(n, w) / r) / r**2
            )
    return total


@pytest.mark.parametrize("m", [0, 1, 3])
def test_linear_light_visible_subsegments(m):
    rng = np.random.default_rng(3 + m)
    a = np.array([-1.5, -0.2, 2.0])
    b = np.array([1.5, 0.3, 2.4])
    occs = [
        np.array([[-0.6, -0.5, 1.0], [0.0, -0.5, 1.0], [0.0, 0.5, 1.2], [-0.6, 0.5, 1.2]]),
        np.array([[-0.3, -0.4, 1.5], [0.5, -0.2, 1.4], [0.2, 0.5, 1.6]]),
        np.array(
            [[0.8, -0.5, 2.6], [1.2, -0.5, 1.6], [1.2, 0.5, 1.6], [0.8, 0.5, 2.6]]
        ),  # crosses the segment
    ]
    kern = jax.jit(visible_linear_kernel, static_argnums=4)
    worst = 0.0
    for _ in range(6):
        p = np.array([*rng.uniform(-2, 2, size=2), 0.0])
        n = np.array([0.3 * rng.normal(), 0.3 * rng.normal(), 1.0])
        n /= np.linalg.norm(n)
        got = float(
            kern(
                jnp.asarray(p),
                jnp.asarray(n),
                jnp.asarray(a),
                jnp.asarray(b),
                m,
                jnp.asarray(pad(occs)),
            )
        )
        ref = reference_linear(p, n, a, b, m, occs)
        free = reference_linear(p, n, a, b, m, [])
        worst = max(worst, abs(got - ref) / free)
    assert worst <= 1e-10, worst


# --------------------------------------------------------------------------------------
# Point and directional lights
# --------------------------------------------------------------------------------------


def test_point_and_directional_visibility():
    occs = [np.array([[-0.5, -0.5, 1.0], [0.5, -0.5, 1.0], [0.5, 0.5, 1.0], [-0.5, 0.5, 1.0]])]
    o = jnp.asarray(pad(occs))
    rng = np.random.default_rng(0)
    for _ in range(50):
        p = np.array([*rng.uniform(-1.5, 1.5, size=2), 0.0])
        x = np.array([*rng.uniform(-1.5, 1.5, size=2), rng.uniform(0.5, 2.0)])
        want = 0.0 if ray_blocked_np(p, x, occs) else 1.0
        assert float(_point_vis(jnp.asarray(p), jnp.asarray(x), o)) == want
        d = p - x  # light travelling from x's direction
        far = p - 1e6 * d
        want_d = 0.0 if ray_blocked_np(p, far, occs) else 1.0
        assert float(_dir_vis(jnp.asarray(p), jnp.asarray(d), o)) == want_d
    g = jax.grad(lambda x: _point_vis(jnp.zeros(3), x, o))(jnp.array([0.1, 0.1, 2.0]))
    assert np.all(np.asarray(g) == 0)


# --------------------------------------------------------------------------------------
# Gradients
# --------------------------------------------------------------------------------------

GEN_OCC = np.array([[[-0.4, -0.3, 1.0], [0.5, -0.2, 1.1], [0.4, 0.6, 1.2], [-0.3, 0.5, 1.05]]])
GEN_EM = np.array([[-1, -1, 2.0], [-1.1, 1, 2.1], [1, 1.2, 2.0], [1.1, -1, 1.9]])
PEN = np.array([0.35, 0.55, 0.0])  # penumbra



def _penumbra_grads(order):
    p, n = jnp.asarray(PEN), jnp.asarray(UP)
    em, oc = jnp.asarray(GEN_EM), jnp.asarray(GEN_OCC)
    free = unoccluded(PEN, UP, GEN_EM)
    assert 0.05 * free < float(_kernel_jit(p, n, em, oc)) < 0.95 * free
    # One call over receiver, light and occluder vertices together (each transformation of
    # this kernel costs a compilation).
    check_grads(
        lambda q, v, o: _kernel_jit(q, n, v, o), (p, em, oc), order=order, modes=("fwd", "rev")
    )


def test_gradients_generic_penumbra():
    _penumbra_grads(1)


@pytest.mark.slow
def test_gradients_generic_penumbra_order2():
    # About 3 minutes on a loaded 2-core machine (compiling the second-order transformations).
    _penumbra_grads(2)


_lin_jit = jax.jit(visible_linear_kernel, static_argnums=4)


def _linear_grads(order):
    a, b = jnp.array([-1.5, -0.2, 2.0]), jnp.array([1.5, 0.3, 2.4])
    p, n = jnp.array([0.3, 0.1, 0.0]), jnp.asarray(UP)
    o = jnp.asarray(GEN_OCC)
    val = _lin_jit(p, n, a, b, 1, o)
    assert 0 < float(val) < float(_lin_jit(p, n, a, b, 1, o + 10.0))
    check_grads(
        lambda a, b, o: _lin_jit(p, n, a, b, 1, o), (a, b, o), order=order, modes=("fwd", "rev")
    )


def test_gradients_linear():
    _linear_grads(1)


@pytest.mark.slow
def test_gradients_linear_order2():
    _linear_grads(2)


_grad_all = jax.jit(jax.grad(visible_form_factor_kernel, argnums=(0, 1, 2, 3)))


@jax.jit
def _jvp_all(p, n, em, oc, tp, tn, te, to):
    return jax.jvp(visible_form_factor_kernel, (p, n, em, oc), (tp, tn, te, to))[1]


SINGULAR = {
    # Projection from p = 0 is exactly the emitter, plus a half-size one sharing three edges.
    "coincident": [
        np.array([[-0.5, -0.5, 1.0], [-0.5, 0.5, 1], [0.5, 0.5, 1], [0.5, -0.5, 1]]),
        np.array([[-0.5, -0.5, 1.0], [0.0, -0.5, 1], [0.0, 0.5, 1], [-0.5, 0.5, 1]]),
    ],
    # Projection [0, 1]^2: two edges on the emitter's edge lines, a corner on its corner.
    "on_discontinuity": [np.array([[0.0, 0.0, 1.0], [0.5, 0.0, 1], [0.5, 0.5, 1], [0.0, 0.5, 1]])],
    # Wall standing on the receiver plane, p at its foot.
    "touching": [np.array([[0.0, -1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, 1.5], [0.0, -1.0, 1.5]])],
    "vertex_on_emitter_plane": [np.array([[0.3, 0.3, 2.0], [0.9, 0.0, 1.0], [0.8, 0.8, 1.2]])],
    # Two triangles of a quad (shared edge).
    "shared_edge": [
        np.array([[-0.5, -0.4, 1.0], [0.5, -0.4, 1.2], [0.5, 0.6, 1.2]]),
        np.array([[-0.5, -0.4, 1.0], [0.5, 0.6, 1.2], [-0.5, 0.6, 1.0]]),
    ],
}


@pytest.mark.parametrize("case", sorted(SINGULAR))
def test_gradients_finite_at_singular_configurations(case):
    em, oc = padded_scene(EM, SINGULAR[case], m_pad=2, k_pad=4)
    p, n = jnp.zeros(3), jnp.asarray(UP)
    for g in _grad_all(p, n, em, oc):
        assert np.all(np.isfinite(np.asarray(g)))
    rng = np.random.default_rng(0)
    tangents = [jnp.asarray(rng.normal(size=x.shape)) for x in (p, n, em, oc)]
    assert np.isfinite(float(_jvp_all(p, n, em, oc, *tangents)))
