"""`jaxshadow._core.geometry`: the polygon geometry under the kernels (Newell's normal, the lit
side, the horizon clip) and the NumPy checks and padding of polygons, against references written
here (shoelace areas, shapely's clipping, hand-made polygons). Entry-point validation through
the public functions is in tests/test_bad_input.py."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxshadow._core import geometry as g

SQUARE = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [1.0, 1.0, 1.0], [0.0, 1.0, 1.0]])  # normal +z


def _rotation(seed: int) -> np.ndarray:
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_newell_normal_is_twice_the_vector_area(dtype):
    """A rotated, shifted pentagon: Newell's sum equals twice its shoelace area along the
    rotated +z (right-hand rule), padding (repeated first vertex) changes nothing."""
    ang = np.sort(np.random.default_rng(0).uniform(0, 2 * np.pi, 5))
    xy = np.c_[np.cos(ang), 0.5 * np.sin(ang)]
    area = 0.5 * np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])
    R = _rotation(1)
    v = (np.c_[xy, np.zeros(5)] @ R.T + [0.3, -0.2, 0.7]).astype(dtype)
    tol = 1e-5 if dtype == np.float32 else 1e-12
    got = np.asarray(g.newell_normal(jnp.asarray(v)))
    assert got.dtype == dtype
    np.testing.assert_allclose(got, 2 * area * R[:, 2], atol=tol)
    padded = g.pad_polygon(v, 8)
    np.testing.assert_allclose(np.asarray(jax.jit(g.newell_normal)(jnp.asarray(padded))), got, atol=tol)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_lit_side_far_from_the_origin(dtype):
    """The side the right-hand normal points to, for a unit square 1e5 from the origin in
    float32 (where the absolute Newell sum is rounding noise), under jit and vmap."""
    far = (SQUARE + [1e5, -1e5, 0.0]).astype(dtype)
    centre = far.mean(axis=0)
    pts = np.array([centre + [0, 0, 0.5], centre - [0, 0, 0.5], centre + [0.2, 0.1, 1e-2]], dtype)
    got = jax.jit(jax.vmap(lambda p: g.on_lit_side(p, jnp.asarray(far))))(jnp.asarray(pts))
    np.testing.assert_array_equal(np.asarray(got), [True, False, True])
    assert not bool(g.on_lit_side(jnp.asarray(pts[0]), jnp.asarray(far[::-1].copy())))  # reversed: other side


def test_horizon_clip_is_shapely_intersection():
    """The clipped polygon's edges (edge soup plus the closing horizon edge) enclose the part of
    the polygon above the plane: its area (Green's theorem over the soup) equals shapely's
    intersection of the polygon with the half-plane, and every edge of nonzero length lies on or
    above it."""
    shapely = pytest.importorskip("shapely.geometry")
    v = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.2, 1.0, 0.0], [-0.8, 1.1, 0.0]])
    for offset in (-2.0, -0.3, 0.0, 0.4, 2.0):  # the plane y = offset, normal +y (kept above)
        p, n = np.array([0.0, offset, 0.0]), np.array([0.0, 1.0, 0.0])
        s, e = (np.asarray(x) for x in g.horizon_clip_edges(jnp.asarray(p), jnp.asarray(n), jnp.asarray(v)))
        assert s.shape == e.shape == (5, 3)
        real = np.linalg.norm(e - s, axis=1) > 0  # an edge wholly below collapses to a point (no length)
        assert np.all(s[real, 1] >= offset - 1e-12) and np.all(e[real, 1] >= offset - 1e-12)
        area = 0.5 * np.sum(s[:, 0] * e[:, 1] - e[:, 0] * s[:, 1])
        half = shapely.box(-10, offset, 10, 10)
        want = shapely.Polygon(v[:, :2]).intersection(half).area
        assert area == pytest.approx(want, abs=1e-12), offset


def test_convex_polygon_check_names_what_is_wrong():
    """A valid square passes (as float64); each defect raises naming it."""
    out = g.check_convex_polygon(SQUARE.astype(np.float32), "light")
    assert out.dtype == np.float64 and out.shape == (4, 3)
    bad = {
        "shape": SQUARE[:, :2],
        "coincide": np.r_[SQUARE[:2], SQUARE[1:]],
        "collinear": np.array([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]]),
        "non-planar": SQUARE + [[0, 0, 0], [0, 0, 0], [0, 0, 0.1], [0, 0, 0]],
        "non-convex": np.array([[0.0, 0, 0], [2, 0, 0], [1, 0.3, 0], [1, 2, 0]]),
        "winds": np.array([[np.cos(a), np.sin(a), 0.0] for a in 4 * np.pi / 5 * np.arange(5)]),  # a pentagram
    }
    for word, v in bad.items():
        with pytest.raises(ValueError, match=word):
            g.check_convex_polygon(v, "light")


def test_padding_round_trip():
    """Padding repeats the first vertex; stripping undoes it; the JAX stack pads each polygon
    to the largest and keeps traced leaves differentiable."""
    tri = SQUARE[:3]
    padded = g.pad_polygon(tri, 5)
    np.testing.assert_array_equal(padded[3:], np.repeat(tri[:1], 2, axis=0))
    np.testing.assert_array_equal(g.strip_padding(padded), tri)
    with pytest.raises(ValueError, match="cannot pad"):
        g.pad_polygon(SQUARE, 3)
    stacked = np.asarray(g.pad_polygons_jax([tri, SQUARE]))
    np.testing.assert_array_equal(stacked, np.stack([g.pad_polygon(tri, 4), SQUARE]))
    grad = jax.grad(lambda x: jnp.sum(g.pad_polygons_jax([x, jnp.asarray(SQUARE)])[0]))(jnp.asarray(tri))
    np.testing.assert_array_equal(np.asarray(grad), [[2.0] * 3, [1.0] * 3, [1.0] * 3])  # vertex 0 twice (one pad)
