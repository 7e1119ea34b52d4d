"""Stark et al. shadow equation (jaxshadow._kernels.spline) against an independent float64 reference.

The reference shares no code with the kernel: the hidden part of the emitter is cut out in 3-D
on the emitter's own plane (Sutherland-Hodgman against the planes of the occluder's cone from
the receiver point, plain NumPy), and cos.cos / (pi r^2) is integrated over the emitter and the
hidden part with a collapsed 30 x 30 Gauss-Legendre rule on a triangle fan (exact to ~1e-15
for these smooth integrands: orders 20, 30 and 40 agree).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

from benchmarks.scenes import clip_halfspace, random_convex
from jaxshadow._kernels.polygon import form_factor
from jaxshadow._kernels.spline import (
    shadow_nodes,
    spline_shadow,
    spline_shadow_faces,
    twice_integrated_density,
)

# --------------------------------------------------------------------------------------
# Independent reference (NumPy only)
# --------------------------------------------------------------------------------------


def _triangle_rule(order):
    x, w = np.polynomial.legendre.leggauss(order)
    x, w = 0.5 * (x + 1.0), 0.5 * w
    u, v = np.meshgrid(x, x, indexing="ij")
    wu, wv = np.meshgrid(w, w, indexing="ij")
    return u.ravel(), (v * (1.0 - u)).ravel(), (wu * wv * (1.0 - u)).ravel()


_A, _B, _W = _triangle_rule(30)


def _polygon_ff(p, poly, n_emit):
    """Quadrature of cos(theta_r) cos(theta_e) / (pi r^2) over a convex polygon, receiver +z."""
    total = 0.0
    for k in range(1, len(poly) - 1):
        v0, v1, v2 = poly[0], poly[k], poly[k + 1]
        jac = np.linalg.norm(np.cross(v1 - v0, v2 - v0))
        x = v0 + _A[:, None] * (v1 - v0) + _B[:, None] * (v2 - v0)
        d = x - p
        r2 = np.sum(d * d, axis=1)
        total += jac * np.sum(_W * d[:, 2] * (-(d @ n_emit)) / (np.pi * r2 * r2))
    return total


def _cone_planes(p, verts):
    """Inward normals of the facets of the convex cone from p over a point set (brute force)."""
    rel = verts - p
    planes = []
    for a in range(len(rel)):
        for b in range(a + 1, len(rel)):
            n = np.cross(rel[a], rel[b])
            if np.linalg.norm(n) < 1e-12:
                continue
            s = rel @ n
            scale = np.linalg.norm(n) * np.max(np.linalg.norm(rel, axis=1))
            if np.all(s >= -1e-12 * scale):
                planes.append(n)
            elif np.all(s <= 1e-12 * scale):
                planes.append(-n)
    return planes


def reference(p, emitter, occluder_vertices):
    """Form factor of the visible part of `emitter` from p behind the convex hull of the
    occluder vertices (a polygon or a polyhedron); also returns the unoccluded value."""
    n = np.sum(np.cross(emitter, np.roll(emitter, -1, axis=0)), axis=0)
    n /= np.linalg.norm(n)
    if n @ (p - emitter[0]) <= 0:
        return 0.0, 0.0
    full = _polygon_ff(p, emitter, n)
    hidden = emitter
    for plane in _cone_planes(p, occluder_vertices):
        hidden = np.array(clip_halfspace(hidden, p, plane))
        if len(hidden) < 3:
            return full, full
    return full - _polygon_ff(p, hidden, n), full


# --------------------------------------------------------------------------------------
# Scenes
# --------------------------------------------------------------------------------------


def _convex(rng, k, radius, centre, tilt):
    """Random convex k-gon (points of an ellipse), counter-clockwise seen from above."""
    return random_convex(rng, k, lambda r: (radius * r.uniform(0.6, 1.4), radius), centre, tilt)


def random_scene(seed):
    """Tilted convex emitter (lit side down) and occluder (random orientation) between it and
    the floor, with floor points in lit, penumbra and umbra regions."""
    rng = np.random.default_rng(seed)
    while True:
        emitter = _convex(rng, 4, rng.uniform(0.4, 0.8), np.array([0.0, 0.0, 3.0]), 0.4)[::-1]
        centre = np.array([*rng.uniform(-0.3, 0.3, 2), rng.uniform(1.6, 2.2)])
        occluder = _convex(rng, 5, rng.uniform(0.6, 1.1), centre, 0.6)
        if rng.random() < 0.5:
            occluder = occluder[::-1]
        if occluder[:, 2].max() < emitter[:, 2].min() and occluder[:, 2].min() > 0.2:
            break
    xy = np.concatenate([rng.uniform(-0.4, 0.4, (6, 2)), rng.uniform(-3.0, 3.0, (10, 2))])
    points = np.concatenate([xy, np.zeros((16, 1))], axis=1)
    return emitter, occluder, points


def cube_faces(centre, half):
    c = np.asarray(centre, dtype=np.float64)
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    return [c + half * corners[q] for q in quads]


def square(cx, cy, z, h, lit_down=True):
    v = np.array(
        [[cx - h, cy - h, z], [cx + h, cy - h, z], [cx + h, cy + h, z], [cx - h, cy + h, z]]
    )
    return v[::-1] if lit_down else v


UP = np.array([0.0, 0.0, 1.0])
N_POINTS, N_OCC = 96, 5  # fixed shapes: one compilation serves most tests


def shadow(emitter, occluder, points, dtype=np.float64):
    """`spline_shadow` on fixed shapes: the occluder padded to 5 vertices (repeating its first
    vertex, jaxshadow's padding convention) and the points to 96."""
    k = len(occluder)
    occluder = np.concatenate([occluder, np.repeat(occluder[:1], N_OCC - k, axis=0)])
    n = len(points)
    pad = np.repeat(points[-1:], N_POINTS - n, axis=0)
    args = (jnp.asarray(x, dtype=dtype) for x in (emitter, occluder, np.concatenate([points, pad])))
    out = spline_shadow(*args)
    assert out.dtype == dtype
    return out[:n]


def _max_rel_error(values, emitter, occluder_vertices, points):
    errs, kinds = [], set()
    for p, v in zip(points, np.asarray(values, dtype=np.float64), strict=True):
        ref, full = reference(p, emitter, occluder_vertices)
        if full == 0:
            assert v == 0
            continue
        errs.append(abs(v - ref) / full)
        kinds.add(
            "lit" if ref > (1 - 1e-9) * full else "umbra" if ref < 1e-9 * full else "penumbra"
        )
    return max(errs), kinds


# --------------------------------------------------------------------------------------
# Values
# --------------------------------------------------------------------------------------


def test_eq22_homogeneous_form_is_eq22():
    """The division-free form used by the kernel equals Stark's eq. 22 literally, and eq. 22 is
    the antiderivative along the line w = u z + v of Omega = int_0^w (1 + z^2 + t^2)^-2 dt."""
    rng = np.random.default_rng(1)
    z, u, v = rng.normal(size=(3, 50)) * 2

    def eq22(z, u, v):
        r = np.sqrt(1 + u * u + v * v)
        s = np.sqrt(1 + z * z)
        return v * np.arctan((u * v + z + u * u * z) / r) / (2 * r) + z * np.arctan(
            (v + u * z) / s
        ) / (2 * s)

    q = np.stack([z, u * z + v, np.ones_like(z)], 1)
    n = np.stack([-u, np.ones_like(u), -v], 1)
    scale = rng.uniform(0.1, 10, (2, 50, 1))  # degree-0 homogeneous in q and n
    sign = np.where(rng.random((50, 1)) < 0.5, -1.0, 1.0)
    got = jax.vmap(twice_integrated_density)(q * scale[0], n * scale[1] * sign)
    np.testing.assert_allclose(got, eq22(z, u, v), rtol=1e-13, atol=1e-15)

    h = 1e-5
    dfdz = (eq22(z + h, u, v) - eq22(z - h, u, v)) / (2 * h)
    w, s2 = u * z + v, 1 + z * z
    omega = w / (2 * s2 * (s2 + w * w)) + np.arctan(w / np.sqrt(s2)) / (2 * s2**1.5)
    np.testing.assert_allclose(dfdz, omega, rtol=1e-8, atol=1e-10)


def test_shadow_nodes_line_up():
    """Eq. 18: v_ij is on the floor, on the line through o_i and e_j."""
    emitter, occluder, _ = random_scene(3)
    v = np.asarray(shadow_nodes(jnp.asarray(emitter), jnp.asarray(occluder)))
    for i in range(len(occluder)):
        for j in range(len(emitter)):
            node = np.array([*v[i, j], 0.0])
            c = np.cross(occluder[i] - node, emitter[j] - node)
            assert np.linalg.norm(c) < 1e-12 * np.linalg.norm(emitter[j] - node) ** 2


def test_no_shadow_equals_form_factor():
    """Where the occluder's shadow misses the point, eq. 24 reduces to the unoccluded form
    factor (Lambert), also for points beside and behind the tilted emitter (0)."""
    emitter, occluder, _ = random_scene(4)
    occluder = occluder + np.array([6.0, 0.0, 0.0])  # shadow far to the +x side
    rng = np.random.default_rng(4)
    pts = np.concatenate([rng.uniform(-4, 1, (40, 2)), np.zeros((40, 1))], 1)
    # Steeper emitter: its plane meets the floor at x = -5.5; points beyond see its back.
    emitter = np.array([[-0.5, -0.5, 2.5], [-0.5, 0.5, 2.5], [0.5, 0.5, 3.0], [0.5, -0.5, 3.0]])
    pts = np.concatenate([pts, [[-5.6, 0.0, 0.0], [-9.0, 3.0, 0.0], [9.0, -3.0, 0.0]]])
    got = shadow(emitter, occluder, pts)
    want = form_factor(pts, np.tile(UP, (len(pts), 1)), emitter)
    assert np.max(np.abs(np.asarray(got) - np.asarray(want))) <= 1e-12
    assert np.any(np.asarray(want) == 0)  # some points are behind the tilted emitter


@pytest.mark.parametrize("seed", [10, 11, 12, 13])
def test_against_reference(seed, dtype):
    """Random tilted convex emitter/occluder pairs; lit, penumbra and umbra points."""
    emitter, occluder, points = random_scene(seed)
    got = shadow(emitter, occluder, points, dtype)
    err, kinds = _max_rel_error(got, emitter, occluder, points)
    assert err <= (1e-10 if dtype == np.float64 else 1e-5), err
    assert {"lit", "penumbra"} <= kinds


def test_umbra_and_all_regions():
    """A big occluder close to a small emitter: lit, penumbra and umbra in one set."""
    emitter = square(0.0, 0.0, 3.0, 0.3)
    occluder = square(0.1, -0.05, 2.0, 0.8, lit_down=False)
    x = np.linspace(-3.5, 3.5, 15)
    points = np.stack([x, 0.3 * x, 0 * x], 1)
    got = shadow(emitter, occluder, points)
    err, kinds = _max_rel_error(got, emitter, occluder, points)
    assert err <= 1e-10
    assert kinds == {"lit", "penumbra", "umbra"}


def test_cube_occluder_two_emitters():
    """Fig. 14: convex polyhedral occluder (faces in mixed orientation) and a sum of emitters."""
    faces = cube_faces([0.2, -0.1, 1.2], 0.5)
    faces[2] = faces[2][::-1]
    emitters = [square(-0.3, 0.0, 3.0, 0.5), square(0.8, 0.4, 2.5, 0.3)]
    x = np.linspace(-3.0, 3.0, 13)
    points = np.stack([x, 0.4 * x - 0.1, 0 * x], 1)
    got = spline_shadow_faces(emitters, faces, points)
    verts = np.concatenate(faces)
    want = np.zeros(len(points))
    full = np.zeros(len(points))
    for e in emitters:
        r = [reference(p, e, verts) for p in points]
        want += [a for a, _ in r]
        full += [b for _, b in r]
    assert np.max(np.abs(np.asarray(got) - want) / full) <= 1e-10
    assert np.any(want < 0.5 * full) and np.any(want > (1 - 1e-9) * full)
    stacked = spline_shadow_faces(np.stack(emitters), np.stack(faces), points)
    np.testing.assert_allclose(np.asarray(got), np.asarray(stacked), rtol=1e-15)


def test_points_on_discontinuity_lines():
    """Points on shadow-polygon edges and at shadow nodes (eq. 18), and a symmetric scene
    where the side determinants are exactly zero (half-open rule, note 7)."""
    emitter, occluder, _ = random_scene(20)
    v = np.asarray(shadow_nodes(jnp.asarray(emitter), jnp.asarray(occluder)))
    n, m = v.shape[:2]
    on = [v[i, j] for i in range(n) for j in range(m)]
    on += [0.5 * (v[i, j] + v[(i + 1) % n, j]) for i in range(n) for j in range(m)]
    on += [0.3 * v[i, j] + 0.7 * v[i, (j + 1) % m] for i in range(n) for j in range(m)]
    points = np.concatenate([np.array(on), np.zeros((len(on), 1))], 1)
    err, _ = _max_rel_error(shadow(emitter, occluder, points), emitter, occluder, points)
    assert err <= 1e-9

    emitter = square(0.0, 0.0, 3.0, 0.5)
    occluder = square(0.0, 0.0, 1.5, 0.5, lit_down=False)
    g = np.array([-1.5, -1.0, -0.5, -0.25, 0.0, 0.25, 0.5, 1.0, 1.5])
    xx, yy = np.meshgrid(g, g)
    points = np.stack([xx.ravel(), yy.ravel(), 0 * xx.ravel()], 1)
    err, kinds = _max_rel_error(shadow(emitter, occluder, points), emitter, occluder, points)
    assert err <= 1e-10
    assert kinds == {"lit", "penumbra", "umbra"}


def _touching_scene(height):
    """Stark fig. 13: a tilted occluder whose lowest edge nearly touches the floor."""
    emitter = square(0.0, 0.0, 3.0, 0.6)
    occluder = np.array(
        [[-0.7, -0.2, height], [0.7, -0.2, height], [0.7, 0.6, 1.2], [-0.7, 0.6, 1.2]]
    )
    x = np.linspace(-1.0, 1.0, 9)
    points = np.stack([0.37 * x, x - 0.2, 0 * x], 1)  # crosses the line of near-contact
    return emitter, occluder, points


def _vertex_on_emitter_plane_scenes():
    """An occluder vertex level with a horizontal emitter (a shadow node at infinity, eq. 18
    divides by 0), and one on the plane of a tilted emitter (E_i degenerates to a segment)."""
    e1 = square(0.0, 0.0, 3.0, 0.5)
    o1 = np.array([[-0.4, -0.4, 1.5], [0.4, -0.4, 1.5], [0.9, 0.3, 3.0]])
    e2 = np.array([[-0.5, -0.5, 2.5], [-0.5, 0.5, 2.5], [0.5, 0.5, 3.0], [0.5, -0.5, 3.0]])
    o2 = np.array(
        [[-0.5, -0.3, 1.5], [0.3, -0.3, 1.5], [-1.5, 0.2, 2.0]]
    )  # (-1.5, *, 2.0) on E2's plane
    assert abs(np.cross(e2[1] - e2[0], e2[2] - e2[0]) @ (o2[2] - e2[0])) < 1e-15
    x = np.linspace(-2.0, 2.0, 9)
    points = np.stack([x, 0.2 * x + 0.05, 0 * x], 1)
    return [(e1, o1, points), (e2, o2, points)]


@pytest.mark.parametrize("height", [1e-3, 1e-7])
def test_nearly_touching_occluder(height):
    emitter, occluder, points = _touching_scene(height)
    err, kinds = _max_rel_error(shadow(emitter, occluder, points), emitter, occluder, points)
    assert err <= 1e-9
    assert "umbra" in kinds or "penumbra" in kinds


def test_occluder_vertex_on_emitter_plane():
    for emitter, occluder, points in _vertex_on_emitter_plane_scenes():
        got = shadow(emitter, occluder, points)
        err, kinds = _max_rel_error(got, emitter, occluder, points)
        assert err <= 1e-10
        assert "penumbra" in kinds


# --------------------------------------------------------------------------------------
# Gradients
# --------------------------------------------------------------------------------------


def _f(points, emitter, occluder):
    return spline_shadow(emitter, occluder, points)


def test_gradients_generic_penumbra():
    emitter, occluder, _ = random_scene(30)
    points = np.array([[-0.97, -0.34, 0.0], [-1.28, -1.45, 0.0], [-1.25, -0.44, 0.0]])
    # Generic: well inside penumbra and away from every discontinuity line of the nodes.
    v = np.asarray(shadow_nodes(jnp.asarray(emitter), jnp.asarray(occluder)))
    for p in points:
        ref, full = reference(p, emitter, occluder)
        assert 0.1 * full < ref < 0.9 * full
        for a, b in [
            (v[i, j], v[k, l])
            for i in range(5)
            for j in range(4)
            for k in range(5)
            for l in range(4)
            if (k, l) in (((i + 1) % 5, j), (i, (j + 1) % 4))
        ]:
            d = b - a
            dist = abs(d[0] * (p[1] - a[1]) - d[1] * (p[0] - a[0])) / np.linalg.norm(d)
            assert dist > 0.03
    # Jitted so that finite differences do not trip the (concrete-input) planarity checks.
    check_grads(jax.jit(_f), (points, emitter, occluder), order=2, modes=("fwd", "rev"))


@jax.jit
def _value_and_grad_total(points, emitter, occluder):
    total = lambda *a: jnp.sum(spline_shadow(a[1], a[2], a[0]))
    return jax.value_and_grad(total, argnums=(0, 1, 2))(points, emitter, occluder)


def _assert_finite_grads(emitter, occluder, points):
    """Value and reverse-mode gradient in every input are finite (fixed shapes: one compile)."""
    occluder = np.concatenate([occluder, np.repeat(occluder[:1], N_OCC - len(occluder), axis=0)])
    points = np.concatenate([points, np.repeat(points[-1:], N_POINTS - len(points), axis=0)])
    value, grads = _value_and_grad_total(points, emitter, occluder)
    assert np.isfinite(float(value))
    for g in grads:
        assert np.all(np.isfinite(np.asarray(g)))


def test_gradients_finite_at_singular_configurations():
    emitter, occluder, _ = random_scene(20)
    v = np.asarray(shadow_nodes(jnp.asarray(emitter), jnp.asarray(occluder)))
    on = np.concatenate([v[:, 0], 0.5 * (v[:, 1] + np.roll(v[:, 1], -1, axis=0))])
    _assert_finite_grads(emitter, occluder, np.concatenate([on, np.zeros((len(on), 1))], 1))
    sym = square(0.0, 0.0, 1.5, 0.5, lit_down=False)
    grid = np.array([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [1.0, 0.0, 0.0], [0.25, 0.25, 0.0]])
    _assert_finite_grads(square(0.0, 0.0, 3.0, 0.5), sym, grid)
    for height in (1e-3, 1e-7):
        _assert_finite_grads(*_touching_scene(height))
    for scene in _vertex_on_emitter_plane_scenes():
        _assert_finite_grads(*scene)
    # Behind a tilted emitter (value 0) and an occluder seen edge-on.
    tilted = np.array([[-0.5, -0.5, 2.5], [-0.5, 0.5, 2.5], [0.5, 0.5, 3.0], [0.5, -0.5, 3.0]])
    _assert_finite_grads(tilted, occluder - [0, 0, 0.7], np.array([[20.0, 0.0, 0.0]]))
    edge_on = np.array([[0.0, -0.3, 1.0], [0.0, 0.3, 1.0], [0.0, 0.3, 2.0], [0.0, -0.3, 2.0]])
    _assert_finite_grads(square(0.0, 0.0, 3.0, 0.5), edge_on, np.array([[0.0, 0.1, 0.0]]))


@pytest.mark.slow  # a second large compilation (the faces kernel's gradient)
def test_gradients_finite_cube():
    faces = np.stack(cube_faces([0.0, 0.0, 1.0], 0.5))
    emitters = np.stack([square(0.0, 0.0, 3.0, 0.5), square(0.5, 0.5, 2.5, 0.2)])
    points = np.array([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.7, 0.0, 0.0], [0.3, -0.8, 0.0]])

    def total(p, e, f):
        return jnp.sum(spline_shadow_faces(e, f, p))

    for g in jax.grad(total, argnums=(0, 1, 2))(points, emitters, faces):
        assert np.all(np.isfinite(np.asarray(g)))


# --------------------------------------------------------------------------------------
# Validity region and input errors
# --------------------------------------------------------------------------------------


def test_validity_region_errors():
    emitter = square(0.0, 0.0, 3.0, 0.5)
    occluder = square(0.0, 0.0, 1.0, 0.3, lit_down=False)
    pts = np.array([[0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="strictly above the receiver plane"):
        spline_shadow(emitter, occluder - [0, 0, 1.0], pts)
    with pytest.raises(ValueError, match="strictly above the receiver plane"):
        spline_shadow(emitter, occluder, pts + [0, 0, 1.5])
    with pytest.raises(ValueError, match="between the receiver plane and the emitter"):
        spline_shadow(emitter, occluder + [0, 0, 2.5], pts)
    with pytest.raises(ValueError, match="between the receiver plane and emitter 1"):
        spline_shadow_faces([emitter, emitter - [0, 0, 1.85]], cube_faces([0, 0, 1.0], 0.2), pts)
    dented = occluder.copy()
    dented[1, :2] = [-0.1, 0.1]  # pulled inside the square
    with pytest.raises(ValueError, match="non-convex"):
        spline_shadow(emitter, dented, pts)
    with pytest.raises(ValueError, match="shape"):
        spline_shadow(emitter, occluder, pts[0])
    with pytest.raises(ValueError, match="do not close"):
        spline_shadow_faces([emitter], cube_faces([0, 0, 1.0], 0.2)[:5], pts)
    with pytest.raises(ValueError, match="convex polyhedron"):
        faces = cube_faces([0, 0, 1.0], 0.2)
        faces[0] = faces[0] + [0, 0, 0.1]
        spline_shadow_faces([emitter], faces, pts)


def test_traced_inputs_skip_checks_and_stay_finite():
    """Under jit/grad the NumPy checks cannot run; outside the region values stay finite."""
    emitter = square(0.0, 0.0, 3.0, 0.5)
    occluder = square(0.0, 0.0, 1.0, 0.3, lit_down=False) - [0, 0, 1.0]  # through the floor
    _assert_finite_grads(emitter, occluder, np.array([[0.0, 0.0, 0.0], [0.3, 0.3, 0.0]]))
