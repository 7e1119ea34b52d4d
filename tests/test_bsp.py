"""Occluder culling (`jaxshadow._bsp`): the culled kernel equals the full one.

Criteria: culled == full clipping kernel within 1e-12 (float64, absolute; form factors are
<= 1) on random scenes, with capacities that do and do not overflow; every occluder the
selection drops blocks nothing on its own (checked one by one against the unoccluded value,
1e-14); touching occluders are kept; closed meshes (front faces only) and merged coplanar
meshes match the full kernel / the shapely reference of `test_clip.py`.
"""


import jax
import jax.numpy as jnp
import numpy as np
import pytest
from shapes import uv_sphere
from test_clip import EM, UP, pad, random_scene, reference_ff

import jaxshadow as js
from jaxshadow._bsp import (
    capacity_for,
    culled_form_factor_kernel,
    max_relevant,
    merge_coplanar,
    occluder_relevance,
    prune_occluders,
    select_occluders,
    visible_form_factor_culled,
)
from jaxshadow._clip import visible_form_factor, visible_form_factor_kernel

M_OCC = 10


def _receivers(seed, count):
    rng = np.random.default_rng(seed)
    p = np.c_[rng.uniform(-1.6, 1.6, (count, 2)), rng.uniform(-0.3, 0.5, count)]
    n = rng.normal(size=(count, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.3
    return p, n / np.linalg.norm(n, axis=1, keepdims=True)


def _scene(seed):
    em, occs = random_scene(seed, M_OCC)
    return jnp.asarray(pad([em], 6)[0]), jnp.asarray(pad(occs, 4))


_relevance = jax.jit(jax.vmap(occluder_relevance, in_axes=(0, 0, None, None)))
_single = jax.jit(
    jax.vmap(
        jax.vmap(visible_form_factor_kernel, in_axes=(None, None, None, 0)),
        in_axes=(0, 0, None, None),
    )
)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_culled_equals_full_random(seed):
    em, occ = _scene(seed)
    p, n = _receivers(seed, 64)
    p, n = jnp.asarray(p), jnp.asarray(n)
    full = np.asarray(visible_form_factor(p, n, em, occ))
    count = max_relevant(p, n, em[None], occ)
    assert 0 < count < M_OCC  # the culling does something, and something is left
    for cap in (3, M_OCC):  # 3 overflows somewhere (fallback), M_OCC never does
        got = np.asarray(visible_form_factor_culled(p, n, em, occ, cap))
        np.testing.assert_allclose(got, full, rtol=0, atol=1e-12)
    select = jax.jit(jax.vmap(lambda p, n, em, occ: select_occluders(p, n, em, occ, 3), in_axes=(0, 0, None, None)))
    _, counts, over = select(p, n, em, occ)
    assert int(jnp.max(counts)) == count
    assert bool(jnp.any(over)) == (count > 3)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_dropped_occluders_block_nothing(seed):
    em, occ = _scene(seed)
    p, n = _receivers(seed + 100, 64)
    p, n = jnp.asarray(p), jnp.asarray(n)
    rel = np.asarray(_relevance(p, n, em, occ))  # (N, M)
    alone = np.asarray(_single(p, n, em, occ[:, None]))  # (N, M): one occluder at a time
    free = np.asarray(visible_form_factor_kernel_batch(p, n, em))
    dropped = ~rel
    assert dropped.mean() > 0.3
    np.testing.assert_allclose(
        alone[dropped], np.broadcast_to(free[:, None], alone.shape)[dropped], atol=1e-14
    )
    # And the converse is not vacuous: most kept occluders do block something.
    blocks = alone < free[:, None] - 1e-14
    assert np.all(rel[blocks])


@jax.jit
def visible_form_factor_kernel_batch(p, n, em):
    return jax.vmap(visible_form_factor_kernel, in_axes=(0, 0, None, None))(
        p, n, em, jnp.zeros((0, 4, 3), p.dtype)
    )


def test_touching_and_sliver_occluders():
    # Square light at z = 2 over [-1, 1]^2, receiver at the origin: the pyramid plane through
    # the light's edge x = 1 is x = z / 2; at z = 1 it is x = 0.5.
    p = jnp.zeros(3)
    n = jnp.asarray(UP)
    em = jnp.asarray(EM)

    def strip(x0):  # a rectangle at z = 1 with its left edge at x = x0
        return np.array([[x0, -0.5, 1.0], [x0 + 1, -0.5, 1.0], [x0 + 1, 0.5, 1.0], [x0, 0.5, 1.0]])

    cases = {
        "sliver": (strip(0.5 - 1e-9), True),
        "touching edge": (strip(0.5), True),
        "just outside": (strip(0.5 + 1e-9), None),  # may be kept or dropped; blocks nothing
        "vertex on a pyramid plane": (
            np.array([[0.5, 0.0, 1.0], [0.9, 0.2, 1.0], [0.9, -0.2, 1.1]]),
            True,
        ),
        "vertex on light plane, behind": (
            np.array([[0.0, 0.0, 2.0], [0.2, 0.0, 2.5], [-0.2, 0.1, 2.5]]),
            True,
        ),
        "wholly behind light": (
            np.array([[0.0, 0.0, 2.1], [0.2, 0.0, 2.5], [-0.2, 0.1, 2.5]]),
            False,
        ),
        "below horizon": (np.array([[0.0, 0.3, -0.1], [0.2, 0.3, -0.5], [-0.2, 0.3, -0.5]]), False),
    }
    # Compiled once for all the cases (op by op, the kernels compile each primitive on its own).
    relevance = jax.jit(occluder_relevance)
    visible = jax.jit(visible_form_factor_kernel)
    culled = jax.jit(lambda p, n, em, o: culled_form_factor_kernel(p, n, em, o, 1))
    free = float(visible(p, n, em, jnp.zeros((0, 4, 3))))
    for name, (poly, expect) in cases.items():
        o = jnp.asarray(pad([poly], 4))
        rel = bool(relevance(p, n, em, o)[0])
        if expect is not None:
            assert rel == expect, name
        full = float(visible(p, n, em, o))
        got, over = culled(p, n, em, o)
        assert not bool(over)
        assert abs(float(got) - full) <= 1e-15, name
        if name == "sliver":
            assert full < free - 1e-11  # it does block something, so dropping it would be wrong
        if not rel:
            assert full == pytest.approx(free, abs=1e-15), name




def test_closed_mesh_front_faces():
    tris = uv_sphere([0.1, 0.0, 1.0], 0.45, 5, 8)  # 64 triangles
    assert tris.shape == (64, 3, 3)
    em = jnp.asarray(EM)
    occ = jnp.asarray(tris)
    pts = np.array(
        [[0.0, 0.0, 0.0], [0.6, 0.2, 0.0], [1.2, -0.3, 0.0], [1.9, 0.4, 0.0], [-1.0, 0.8, 0.1]]
    )
    nrm = np.tile(UP, (len(pts), 1))
    nrm[-1] = [0.3, 0.0, 1.0]
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    count_open = max_relevant(pts, nrm, em[None], occ)
    count_closed = max_relevant(pts, nrm, em[None], occ, closed=True)
    assert count_closed < 0.6 * count_open
    cap = capacity_for(count_closed, tris.shape[0])
    got = np.asarray(
        visible_form_factor_culled(
            jnp.asarray(pts), jnp.asarray(nrm), em, occ, cap, closed=True, batch_size=1
        )
    )
    ref = np.array([reference_ff(p, q, EM, list(tris)) for p, q in zip(pts, nrm, strict=True)])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10)
    free = np.asarray(visible_form_factor_kernel_batch(jnp.asarray(pts), jnp.asarray(nrm), em))
    assert got[0] < 0.5 * free[0]  # deep in the shadow


def test_merge_coplanar_grid():
    # A flat 3 x 3 grid of squares at z = 1, each split into two triangles (18 triangles).
    xs = np.linspace(-0.6, 0.6, 4)
    tris = []
    for i in range(3):
        for j in range(3):
            a = [xs[i], xs[j], 1.0]
            b = [xs[i + 1], xs[j], 1.0]
            c = [xs[i + 1], xs[j + 1], 1.0]
            d = [xs[i], xs[j + 1], 1.0]
            tris += [np.array([a, b, c]), np.array([a, c, d])]
    merged = merge_coplanar(tris, max_vertices=4)
    assert len(merged) <= 3
    assert sum(abs(np.sum(np.cross(m, np.roll(m, -1, 0)), 0)[2]) for m in merged) == pytest.approx(
        2 * 1.2**2
    )
    # A non-convex union is never formed: an L of three squares stays split.
    ell = [tris[0], tris[1], tris[2], tris[3], tris[6], tris[7]]
    for m in merge_coplanar(ell):
        e = np.roll(m, -1, 0) - m
        assert np.all(
            np.cross(e, np.roll(e, -1, 0))[:, 2] * np.sign(np.cross(e[0], e[1])[2]) >= -1e-15
        )
    pts = jnp.asarray(
        np.array([[x, y, 0.0] for x in (-1.5, -0.3, 0.4, 1.2) for y in (-0.9, 0.0, 1.3)])
    )
    nrm = jnp.tile(jnp.asarray(UP), (pts.shape[0], 1))
    a = np.asarray(visible_form_factor(pts, nrm, jnp.asarray(EM), jnp.asarray(pad(merged, 4))))
    b = np.asarray(
        visible_form_factor_culled(pts, nrm, jnp.asarray(EM), jnp.asarray(np.array(tris)), 18)
    )
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


def test_prune_occluders():
    em, occ = _scene(5)
    far = np.asarray(occ[:3]) + np.array([0.0, 0.0, 10.0])  # above (behind) the light
    side = np.asarray(occ[:3]) + np.array([30.0, 0.0, 0.0])  # far beside, same height
    allocc = np.concatenate([np.asarray(occ), far, side])
    p, n = _receivers(7, 32)
    keep = prune_occluders(allocc, [np.asarray(em)], p)
    assert set(keep.tolist()) <= set(range(M_OCC)) and len(keep) >= M_OCC - 2
    p, n = jnp.asarray(p), jnp.asarray(n)
    a = visible_form_factor(p, n, em, occ)
    b = visible_form_factor(p, n, em, jnp.asarray(allocc[keep]))
    np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=0, atol=1e-12)


@pytest.mark.slow  # ~70 s: two reverse-mode compilations of the clipping kernel
def test_gradients_match_full():
    em, occ = _scene(1)
    p, n = _receivers(1, 64)
    rel = np.asarray(_relevance(jnp.asarray(p), jnp.asarray(n), em, occ)).sum(1)
    full_free = np.asarray(visible_form_factor_kernel_batch(jnp.asarray(p), jnp.asarray(n), em))
    full = np.asarray(visible_form_factor(jnp.asarray(p), jnp.asarray(n), em, occ))
    i = int(np.argmax((rel >= 2) & (full < full_free - 1e-3) & (full > 1e-3)))  # penumbra
    args = (jnp.asarray(p[i]), jnp.asarray(n[i]), em, occ)
    g_full = jax.grad(visible_form_factor_kernel, argnums=(0, 2, 3))(*args)
    g_cull = jax.grad(lambda *a: culled_form_factor_kernel(*a, 4)[0], argnums=(0, 2, 3))(*args)
    for a, b in zip(g_full, g_cull, strict=True):
        assert np.all(np.isfinite(np.asarray(b)))
        np.testing.assert_allclose(np.asarray(b), np.asarray(a), rtol=1e-9, atol=1e-12)


def test_float32_follows_dtype():
    em, occ = _scene(2)
    p, n = _receivers(2, 16)
    p32, n32 = jnp.asarray(p, jnp.float32), jnp.asarray(n, jnp.float32)
    got = visible_form_factor_culled(p32, n32, em.astype(jnp.float32), occ.astype(jnp.float32), 4)
    assert got.dtype == jnp.float32
    ref = visible_form_factor(jnp.asarray(p), jnp.asarray(n), em, occ)
    np.testing.assert_allclose(np.asarray(got, np.float64), np.asarray(ref), atol=2e-5)


def test_public_entry_points_inside_a_callers_jit_with_concrete_inputs():
    """Receivers and occluders closed over by a user's `jax.jit` are concrete but their jnp
    results are traced: validation and culling planning must still work (regression: a
    TracerBoolConversionError), and agree with the eager call."""
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (10, 2)), np.zeros(10)]
    nrm = np.tile([0.0, 0.0, 1.0], (10, 1))
    occ = [np.array([[x, y, 0.5], [x + 0.1, y, 0.5], [x + 0.1, y + 0.1, 0.5], [x, y + 0.1, 0.5]])
           for x in np.linspace(-1, 1, 3) for y in np.linspace(-1, 1, 3)]
    sq = jnp.array([[-0.5, -0.5, 1.0], [-0.5, 0.5, 1.0], [0.5, 0.5, 1.0], [0.5, -0.5, 1.0]])

    def total(z):
        s = js.Scene([js.PolygonLight(sq + jnp.array([[0.0, 0.0, 1.0]]) * z, 1.0)], occluders=occ)
        return js.irradiance(s, jnp.asarray(pts), jnp.asarray(nrm)).sum()

    np.testing.assert_allclose(float(jax.jit(total)(0.1)), float(total(0.1)), rtol=1e-6)
    s = js.Scene([js.PolygonLight(sq, 1.0)], occluders=occ)
    eager = js.irradiance(s, pts, nrm)
    inside = jax.jit(lambda: js.irradiance(s, jnp.asarray(pts), jnp.asarray(nrm)))()
    np.testing.assert_allclose(np.asarray(inside), np.asarray(eager), rtol=1e-6)
