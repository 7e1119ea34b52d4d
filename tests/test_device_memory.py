"""The device kernels' memory (`ShadowOptions(engine="device")`): a polygon light's visible
boundary is split, decoded and summed a batch of candidate edges at a time
(`_clip.visible_edge_sums`, a `lax.scan` whose steps are recomputed in reverse mode), so no
array of the program grows with the square of the occluder count, and the values are those of
the whole edge soup (`visible_edges`) up to the order of the additions. A segment light's
pieces are classified by sorted interval counts (`_clip.visible_pieces`) and integrated a batch
at a time (`_clip.visible_segment_sum`), likewise.

References: the largest array of the traced program (its shapes: nothing is run), exact polygon
booleans (`test_clip.reference_ff`), the whole soup's contour sums, the blocked intervals'
comparisons written out, quadrature on a NumPy ray test (`test_clip.reference_linear`), and
finite differences.
"""

from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxshadow as js
from jaxshadow._kernels import clip
from jaxshadow._kernels.clip import (
    _stabbed,
    blocked_intervals,
    visible_edge_sums,
    visible_edges,
    visible_pieces,
    visible_segment_sum,
    visible_segments,
)
from jaxshadow._shadows import compiled
from jaxshadow._shadows.integrands import Lambert, Phong

pytest.importorskip("shapely")
from test_clip import reference_ff, reference_linear  # noqa: E402

LIGHT = np.array([[-0.4, -0.4, 2.5], [-0.4, 0.4, 2.5], [0.4, 0.4, 2.5], [0.4, -0.4, 2.5]])
DEVICE = js.ShadowOptions(engine="device")


def _largest(jaxpr: Any) -> int:
    """The element count of the largest array any equation of `jaxpr` (and of the programs
    inside it: jit, scan, checkpoint, cond bodies) produces."""
    big = 0
    for eqn in jaxpr.eqns:
        for v in eqn.outvars:
            big = max(big, math.prod(getattr(v.aval, "shape", ())))
        for param in eqn.params.values():
            for sub in param if isinstance(param, (tuple, list)) else (param,):
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    big = max(big, _largest(inner))
    return big


def _grid(n: int, z: float = 1.0, half: float = 1.0) -> js.Mesh:
    """An n x n grid of squares (2 n^2 triangles) over [-half, half]^2, its height z bent (faces
    that are coplanar would be merged into one occluder)."""
    x = np.linspace(-half, half, n + 1)
    v = np.stack(np.meshgrid(x, x, indexing="ij"), -1).reshape(-1, 2)
    v = np.c_[v, z + 0.05 * np.random.default_rng(5).uniform(size=len(v))]  # no two faces coplanar
    i = np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]
    a, b, c, d = i.ravel(), i.ravel() + n + 1, i.ravel() + n + 2, i.ravel() + 1
    return js.Mesh(v, np.r_[np.c_[a, b, c], np.c_[a, c, d]])


def test_device_program_has_no_quadratic_intermediate():
    """2048 occluding triangles, 64 receivers: every array of the device program's gradient with
    respect to the receivers (its values included) stays within 8 x `DEVICE_PAIRS` elements (2^21).
    Splitting every candidate edge against every region at once made an array of one
    receiver's (8197 candidate edges) x (2049 regions) x (5 planes) x 2 x 3 shared-vertex tests,
    5e8 elements."""
    scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[_grid(32)])
    rng = np.random.default_rng(0)
    p = jnp.asarray(np.c_[rng.uniform(-2, 2, (64, 2)), np.zeros(64)])
    nrm = jnp.asarray(np.tile([0.0, 0.0, 1.0], (64, 1)))

    def e(q):
        return js.irradiance(scene, q, nrm, shadows=DEVICE)

    assert _largest(jax.make_jaxpr(jax.grad(lambda q: jnp.sum(e(q))))(p).jaxpr) <= 8 * compiled.DEVICE_PAIRS


def _scene_arrays(dtype):
    """A polygon light, 6 overlapping occluders (one reaching past the light's edge, one sharing
    a vertex with another) and receivers in their penumbrae, one lit and one behind the light."""
    occ = np.array(
        [
            [[-0.3, -0.2, 1.2], [0.2, -0.25, 1.1], [0.0, 0.3, 1.3]],
            [[-0.1, -0.4, 1.5], [0.35, 0.0, 1.6], [-0.2, 0.2, 1.4]],
            [[0.1, 0.1, 0.9], [0.5, 0.2, 0.95], [0.2, 0.6, 1.0]],
            [[-0.6, -0.1, 1.8], [-0.2, -0.5, 1.8], [-0.3, 0.1, 1.9]],
            [[0.2, -0.25, 1.1], [0.5, -0.3, 1.0], [0.4, 0.1, 1.2]],
            [[-0.5, 0.3, 0.7], [-0.1, 0.5, 0.8], [-0.4, 0.7, 0.75]],
        ]
    )
    p = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.05], [-0.35, 0.4, 0.0], [0.1, 0.5, 0.1], [3.0, 3.0, 0.0],
                  [0.0, 0.0, 3.0]])
    n = np.array([[0.0, 0.0, 1.0], [0.2, 0.1, 1.0], [-0.3, 0.0, 1.0], [0.0, 0.4, 1.0], [0.0, 0.0, 1.0],
                  [0.0, 0.0, 1.0]])
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    eye = np.array([0.4, -0.3, 1.5])
    return (jnp.asarray(x, dtype) for x in (LIGHT, occ, p, n, eye))


def _value_and_grads(name: str, dtype: Any, pairs: int | None) -> Any:
    """`(light, occluders, receivers, normals, eye) -> (values (N,), gradients)`, compiled: the
    `name` integrand's contour value per receiver from `visible_edge_sums` in batches of `pairs`
    (edge, region plane) pairs (None: the whole soup of `visible_edges`), and its gradients with
    respect to the receiver, the light and the occluders."""
    integ = Lambert() if name == "lambert" else Phong(jnp.asarray(20.0, dtype))

    def one(q, m, e, lv, o):
        e = e if name == "phong" else None
        if pairs is None:
            s, t = visible_edges(q, m, lv, o)
            return integ.contour(q, m, e, lv, s, t)
        sums = visible_edge_sums(q, m, lv, o, lambda s, t: integ.contour_sums(q, m, e, lv, s, t), pairs)
        return integ.contour_total(q, m, e, lv, sums)

    fn = jax.vmap(jax.value_and_grad(one, argnums=(0, 3, 4)), in_axes=(0, 0, None, None, None))
    return jax.jit(lambda lv, o, q, m, e: fn(q, m, e, lv, o))


def _values(pairs: int) -> Any:
    """`(light, occluders, receivers, normals) -> (N,)`: Lambert's contour value per receiver
    from `visible_edge_sums` in batches of `pairs` (edge, region plane) pairs, compiled."""

    def one(q, m, lv, o):
        sums = visible_edge_sums(q, m, lv, o, lambda s, t: Lambert().contour_sums(q, m, None, lv, s, t), pairs)
        return Lambert().contour_total(q, m, None, lv, sums)

    return jax.jit(jax.vmap(one, in_axes=(0, 0, None, None)))


def _check_batched(name: str, dtype: Any, pairs: int) -> None:
    verts, occ, p, n, eye = _scene_arrays(dtype)
    tol = 1e-12 if dtype == np.float64 else 1e-5
    whole, gw = _value_and_grads(name, dtype, None)(verts, occ, p, n, eye)
    assert float(jnp.max(whole)) > 0
    if name == "lambert":
        assert float(jnp.min(whole[:4])) > 0, "penumbra receivers"
    batched = _value_and_grads(name, dtype, pairs)
    got, g = batched(verts, occ, p, n, eye)
    np.testing.assert_allclose(got, whole, rtol=0, atol=tol * float(jnp.max(whole)))
    for a, b in zip(g, gw, strict=True):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(a, b, rtol=0, atol=tol * float(jnp.max(jnp.abs(b))))
    if dtype != np.float64:
        return
    # Directional derivatives against central differences (the batched program at moved inputs).
    rng = np.random.default_rng(3)
    dv, do = (jnp.asarray(rng.normal(size=x.shape)) for x in (verts, occ))
    h = 1e-6
    fd = (batched(verts + h * dv, occ + h * do, p, n, eye)[0] - batched(verts - h * dv, occ - h * do, p, n, eye)[0]) / (2 * h)
    ad = jnp.sum(g[1] * dv[None], axis=(1, 2)) + jnp.sum(g[2] * do[None], axis=(1, 2, 3))
    np.testing.assert_allclose(ad, fd, rtol=0, atol=1e-6 * float(jnp.max(jnp.abs(ad))))
    if name == "lambert":
        ref = [math.pi * reference_ff(q, m, LIGHT, list(np.asarray(occ)))
               for q, m in zip(np.asarray(p), np.asarray(n), strict=True)]
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


# (edge, region plane) pairs per batch: 35 candidate edges split against 7 regions of 5 planes,
# 1 or 3 (the last batch padded) at a time.
PAIRS = (35, 105)


def test_batched_sums_against_polygon_booleans():
    """Lambert (float64) from `visible_edge_sums` in batches of 3 candidate edges (the last one
    padded), at penumbra, lit and back-facing receivers: within 1e-9 of exact polygon booleans.
    Gradients, Phong and float32: `test_batched_sums_match_the_whole_soup` (slow)."""
    verts, occ, p, n, _ = _scene_arrays(np.float64)
    got = _values(PAIRS[1])(p, n, verts, occ)
    ref = [math.pi * reference_ff(q, m, LIGHT, list(np.asarray(occ))) for q, m in zip(np.asarray(p), np.asarray(n),
                                                                                          strict=True)]
    free = [math.pi * reference_ff(q, m, LIGHT, []) for q, m in zip(np.asarray(p), np.asarray(n), strict=True)]
    assert all(0 < a < 0.9 * b for a, b in zip(ref[:4], free[:4], strict=True)), "penumbra receivers"
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


@pytest.mark.slow
@pytest.mark.parametrize("pairs", PAIRS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("name", ["lambert", "phong"])
def test_batched_sums_match_the_whole_soup(name, dtype, pairs):
    """Lambert and Phong from `visible_edge_sums` in batches of 1 and 3 candidate edges (the
    last one padded): the whole soup's values and gradients (receiver, light, occluders) within
    1e-12 (float64; 1e-5 float32) of the largest, none NaN; in float64 directional derivatives
    within 1e-6 of central differences and Lambert within 1e-9 of exact polygon booleans."""
    _check_batched(name, dtype, pairs)


@pytest.mark.slow
def test_device_engine_batches_many_occluders():
    """`js.irradiance(..., engine="device")` with 128 occluding triangles (several batches of
    candidate edges, several chunks of receivers) against the host engine."""
    from jaxshadow._shadows import binding as vis

    if not vis.engine_available():
        pytest.skip("the shadow engine is not built")
    scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[_grid(8, z=1.2, half=0.3)])
    rng = np.random.default_rng(1)
    p = np.c_[rng.uniform(-1.5, 1.5, (40, 2)), np.zeros(40)]
    nrm = np.tile([0.0, 0.0, 1.0], (40, 1))
    assert compiled.device_chunk(128, 3, 4) < 40
    got = np.asarray(js.irradiance(scene, p, nrm, shadows=DEVICE))
    ref = np.asarray(js.irradiance(scene, p, nrm))
    assert ref.max() > 0 and np.any((ref[:, 0] > 0) & (ref[:, 0] < 0.9 * ref.max()))
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * ref.max())


@pytest.mark.parametrize("m", [40, 400], ids=["dense", "sorted"])
def test_stabbed_counts_match_every_comparison(m):
    """`_clip._stabbed` (every point against every interval up to `STAB_DENSE` intervals, sorted
    endpoint counts beyond) against the comparisons written out: intervals with shared and
    infinite ends, empty, reversed and NaN ones, points on interval ends."""
    rng = np.random.default_rng(2)
    grid = np.linspace(0.0, 1.0, 11)
    lo = rng.choice(np.r_[grid, -np.inf, np.nan], m)
    hi = np.where(rng.uniform(size=m) < 0.1, np.inf, rng.choice(np.r_[grid, np.nan], m))
    use = rng.uniform(size=m) < 6 / m
    t = np.r_[grid, rng.uniform(size=40), 0.5 * (grid[1:] + grid[:-1]), -0.5, 1.5]
    want = np.any((lo[None, :] < t[:, None]) & (t[:, None] < hi[None, :]) & use[None, :], axis=1)
    assert 0 < want.sum() < len(t)
    got = jax.jit(_stabbed)(jnp.asarray(lo), jnp.asarray(hi), jnp.asarray(use), jnp.asarray(t))
    np.testing.assert_array_equal(got, want)


# --------------------------------------------------------------------------------------
# Segment lights
# --------------------------------------------------------------------------------------

SEG_A, SEG_B = np.array([-0.5, -0.1, 2.5]), np.array([0.6, 0.2, 2.4])


def test_device_segment_program_has_no_quadratic_intermediate():
    """A segment light over 2048 occluding triangles, 64 receivers: every array of the device
    program's gradient with respect to the light's ends and the occluders' vertices (its values
    included) stays within 8 x `DEVICE_PAIRS` elements (2^21). Testing every piece of the
    segment against every blocked interval made arrays of (16 receivers) x (4097 pieces) x
    (2048 intervals), 1.3e8 elements."""
    faces = jnp.asarray(np.stack(_grid(32).polygons))
    assert faces.shape[0] == 2048
    rng = np.random.default_rng(0)
    p = jnp.asarray(np.c_[rng.uniform(-2, 2, (64, 2)), np.zeros(64)])
    nrm = jnp.asarray(np.tile([0.0, 0.0, 1.0], (64, 1)))

    def e(a, b, o):
        return jnp.sum(js.irradiance(js.Scene([js.LinearLight(a, b, 1.0)], occluders=o), p, nrm, shadows=DEVICE))

    jaxpr = jax.make_jaxpr(jax.grad(e, argnums=(0, 1, 2)))(jnp.asarray(SEG_A), jnp.asarray(SEG_B), faces)
    assert _largest(jaxpr.jaxpr) <= 8 * compiled.DEVICE_PAIRS


def _segment_program(name: str, dtype: Any, pieces: int | None) -> Any:
    """`(a, b, occluders, receivers, normals, eye) -> (values (N,), gradients)`, compiled: the
    `name` integrand summed over a segment light's visible pieces, `pieces` at a time
    (`visible_segment_sum`; None: every piece of `visible_segments` in one sum), and its
    gradients with respect to the receiver, the light's ends and the occluders."""
    integ = Lambert() if name == "lambert" else Phong(jnp.asarray(20.0, dtype))
    prof = js.LinearLight(SEG_A, SEG_B, 1.0)

    def one(q, m, e, a, b, o):
        e = e if name == "phong" else None

        def piece(u, v):
            return integ.segment(q, m, e, u, v, prof)

        if pieces is None:
            return jnp.sum(jax.vmap(piece)(*visible_segments(q, a, b, o)))
        return visible_segment_sum(q, a, b, o, piece, pieces)

    fn = jax.vmap(jax.value_and_grad(one, argnums=(0, 3, 4, 5)), in_axes=(0, 0, None, None, None, None))
    return jax.jit(lambda a, b, o, q, m, e: fn(q, m, e, a, b, o))


def _segment_scene(dtype: Any) -> Any:
    """A segment light, the 6 occluders of `_scene_arrays` (two sharing a vertex) and receivers
    in their penumbrae, one lit and one above the light."""
    _, occ, p, n, eye = _scene_arrays(dtype)
    return (jnp.asarray(SEG_A, dtype), jnp.asarray(SEG_B, dtype), occ, p, n, eye)


@pytest.mark.parametrize("dtype", [np.float32, np.float64], ids=["f32", "f64"])
@pytest.mark.parametrize("name", ["lambert", pytest.param("phong", marks=pytest.mark.slow)])
def test_segment_batches_match_one_sum(name, dtype):
    """Lambert and Phong over a segment light's visible pieces, 3 at a time (13 pieces: 5 batches,
    the last one padded) as the device engine integrates them: the values and gradients (receiver,
    light ends, occluders) of one sum over all the pieces, within 1e-14 (float64; 1e-6 float32)
    of the largest, none NaN. Phong (slow) compiles for longer."""
    args = _segment_scene(dtype)
    whole, gw = _segment_program(name, dtype, None)(*args)
    got, g = _segment_program(name, dtype, 3)(*args)
    t0, t1, keep = jax.jit(jax.vmap(visible_pieces, in_axes=(0, None, None, None)))(args[3], *args[:3])
    seen = np.sum(np.asarray((t1 - t0) * keep), axis=1)
    assert np.all((seen[:4] > 0.01) & (seen[:4] < 0.99)), "receivers in penumbrae"
    tol = 1e-14 if dtype == np.float64 else 1e-6
    np.testing.assert_allclose(got, whole, rtol=0, atol=tol * float(jnp.max(jnp.abs(whole))))
    for x, y in zip(g, gw, strict=True):
        assert np.all(np.isfinite(x))
        np.testing.assert_allclose(x, y, rtol=0, atol=tol * float(jnp.max(jnp.abs(y))))


def test_device_segment_budgets_agree(monkeypatch):
    """Lambert over a segment light from the device engine (values and gradients with respect to
    the light's ends and the occluders, float64): the dense comparisons and one batch of pieces
    that the default budgets choose for 6 occluders, against sorted interval counts and batches
    of 8 pieces (`SEGMENT_DENSE` 0, `SEGMENT_PIECES` 48 shared by the 6 receivers: 13 pieces in
    2 batches), within 1e-14 of the largest, none NaN."""
    a, b, occ, p, n, _ = _segment_scene(np.float64)

    def e(a, b, o):
        vals = js.irradiance(js.Scene([js.LinearLight(a, b, 1.0)], occluders=o), p, n, shadows=DEVICE)[:, 0]
        return jnp.sum(vals * jnp.arange(1.0, 7.0)), vals

    def run():
        return jax.jit(jax.value_and_grad(e, argnums=(0, 1, 2), has_aux=True))(a, b, occ)

    (_, want), gw = run()
    monkeypatch.setattr(clip, "SEGMENT_DENSE", 0)
    monkeypatch.setattr(clip, "SEGMENT_PIECES", 48)
    (_, got), g = run()
    assert np.all(want[:5] > 0)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-14 * float(jnp.max(want)))
    for x, y in zip(g, gw, strict=True):
        assert np.all(np.isfinite(x))
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-14 * float(jnp.max(jnp.abs(y))))


def _crowd(m: int) -> np.ndarray:
    """`m` small random triangles between the segment light and the floor, some crossing the
    light's line, two sharing a vertex."""
    rng = np.random.default_rng(7)
    c = np.c_[rng.uniform(-0.8, 0.8, (m, 2)), rng.uniform(0.5, 2.6, m)]
    tri = c[:, None, :] + rng.normal(scale=0.06, size=(m, 3, 3))
    tri[1, 0] = tri[0, 1]
    return tri


def test_segment_budgets_choose_the_forms():
    """The device engine's choice for a segment light (static, from the shapes): a chunk of 16
    receivers compares every piece with every blocked interval up to 127 occluders and counts
    sorted intervals beyond (`SEGMENT_DENSE`), and integrates every piece in one batch up to
    511 occluders (`SEGMENT_PIECES`)."""
    assert compiled.device_chunk(127, 3, 0) == compiled.device_chunk(2048, 3, 0) == 16
    assert 16 * (2 * 127 + 1) * 127 <= clip.SEGMENT_DENSE < 16 * (2 * 128 + 1) * 128
    assert 2 * 511 + 1 <= clip.SEGMENT_PIECES // 16 < 2 * 512 + 1


@pytest.mark.parametrize("dtype", [np.float32, np.float64], ids=["f32", "f64"])
def test_segment_pieces_match_every_comparison(dtype, monkeypatch):
    """`visible_pieces` beyond its `SEGMENT_DENSE` budget (set to 0: sorted interval counts): the
    same pieces as each piece's midpoint tested against every blocked interval, `(2M + 1) x M`
    comparisons, bit for bit."""
    monkeypatch.setattr(clip, "SEGMENT_DENSE", 0)
    occ = jnp.asarray(_crowd(48), dtype)
    rng = np.random.default_rng(8)
    pts = jnp.asarray(np.c_[rng.uniform(-1.5, 1.5, (12, 2)), np.zeros(12)], dtype)
    a, b = jnp.asarray(SEG_A, dtype), jnp.asarray(SEG_B, dtype)

    def dense(q):
        lo, hi = blocked_intervals(q, a, b, occ)
        t0, t1, _ = visible_pieces(q, a, b, occ)
        tm = 0.5 * (t0 + t1)
        return ~jnp.any((lo[None, :] < tm[:, None]) & (tm[:, None] < hi[None, :]), axis=1) & (t1 > t0)

    got = jax.jit(jax.vmap(lambda q: visible_pieces(q, a, b, occ)))(pts)
    want = jax.jit(jax.vmap(dense))(pts)
    np.testing.assert_array_equal(got[2], want)
    kept = np.sum(np.asarray(want), axis=1)
    assert np.any(kept > 3) and np.all(kept < 2 * occ.shape[0] + 1), "many visible and hidden pieces"


@pytest.mark.parametrize("budget", [None, 0], ids=["dense", "sorted"])
def test_segment_many_occluders_against_quadrature(budget, monkeypatch):
    """Lambert over a segment light behind 48 occluders from `visible_segment_sum`, at most 20
    pieces at a time (97 pieces: 5 batches of 20, the last one padded), each piece's membership
    from every comparison (`SEGMENT_DENSE` as set) or from sorted interval counts (budget 0):
    within 1e-9 of Gauss-Legendre quadrature on the visible intervals found by a NumPy ray test
    (2001 samples: finds every interval wider than 5e-4 of the segment)."""
    if budget is not None:
        monkeypatch.setattr(clip, "SEGMENT_DENSE", budget)
    tri = _crowd(48)
    pts = np.array([[-0.4, 0.0, 0.0], [0.2, 0.3, 0.0], [0.4, -0.3, 0.0]])
    nrm = np.tile([0.0, 0.0, 1.0], (3, 1))
    light = js.LinearLight(SEG_A, SEG_B, 1.0)
    a, b = jnp.asarray(SEG_A), jnp.asarray(SEG_B)

    def one(q, m):
        return visible_segment_sum(q, a, b, jnp.asarray(tri), lambda u, v: Lambert().segment(q, m, None, u, v, light), 20)

    got = np.asarray(jax.jit(jax.vmap(one))(jnp.asarray(pts), jnp.asarray(nrm)))
    ref = np.array([reference_linear(q, m, SEG_A, SEG_B, 0, tri, samples=2001) for q, m in zip(pts, nrm, strict=True)])
    free = np.array([reference_linear(q, m, SEG_A, SEG_B, 0, []) for q, m in zip(pts, nrm, strict=True)])
    assert np.all((ref > 0.05 * free) & (ref < 0.95 * free)), "penumbrae"
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * free.max())


@pytest.mark.slow
@pytest.mark.parametrize("name", ["lambert", "phong"])
def test_segment_batches_finite_differences(name):
    """Directional derivatives of the batched segment sums (3 pieces at a time, float64; light
    ends and occluders moved) within 1e-6 of central differences."""
    a, b, occ, p, n, eye = _segment_scene(np.float64)
    prog = _segment_program(name, np.float64, 3)
    _, g = prog(a, b, occ, p, n, eye)
    rng = np.random.default_rng(4)
    da, db, do = (jnp.asarray(rng.normal(size=x.shape)) for x in (a, b, occ))
    h = 1e-6
    fd = (prog(a + h * da, b + h * db, occ + h * do, p, n, eye)[0]
          - prog(a - h * da, b - h * db, occ - h * do, p, n, eye)[0]) / (2 * h)
    ad = g[1] @ da + g[2] @ db + jnp.sum(g[3] * do[None], axis=(1, 2, 3))
    np.testing.assert_allclose(ad, fd, rtol=0, atol=1e-6 * float(jnp.max(jnp.abs(ad))))
