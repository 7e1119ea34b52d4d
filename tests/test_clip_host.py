"""The culled kernel with its combinatorics on the host (`jaxshadow._clip_host`).

Criteria: the host-combinatorics edges give the same form factors as the device kernel
`_bsp.culled_visible_edges` (float64: 1e-14 absolute, form factors are <= 1; float32: 1e-6)
and the same overflow flags, on random scenes with capacities that do and do not overflow, and
on the touching / sliver / grazing configurations of `test_bsp.py`; the same Jacobian with
respect to the light's and the occluders' vertices (forward and reverse mode, 1e-12); the
NumPy occluder counts equal `_bsp.occluder_relevance`'s; the shadowed Phong specular term agrees
(1e-12); a light fit gives the same light with either `combinatorics`. The compiled
combinatorics (`_clipc.c`, what the callback uses when it is built) return exactly the NumPy
reference's codes (every array equal) on random scenes in both precisions, open and closed, with
capacities that do and do not overflow, on the degenerate configurations and on broadcast
batches; the NumPy fallback alone also matches the device kernel.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_bsp import M_OCC, _receivers, _scene
from test_clip import EM, UP, pad, random_scene

import jaxshadow._clip_host as clip_host
from jaxshadow._bsp import culled_visible_edges, edge_capacity, occluder_relevance
from jaxshadow._clip import masked_contour_form_factor
from jaxshadow._clip_host import (
    culled_visible_edges_host,
    host_culled_codes,
    host_culled_codes_c,
    relevant_counts,
)


def _one(edges, cap, p, n, em, occ):
    s, e, over = edges(p, n, em, occ, cap)
    return masked_contour_form_factor(p, n, em, s, e), over


@functools.cache  # one compilation per kernel and capacity for the whole module
def _ff(edges, cap):
    return jax.jit(jax.vmap(functools.partial(_one, edges, cap), in_axes=(0, 0, None, None)))


@pytest.mark.parametrize("seed", [0, 2])
def test_host_equals_device_random(seed):
    em, occ = _scene(seed)
    p, n = _receivers(seed, 64)
    p, n = jnp.asarray(p), jnp.asarray(n)
    for cap in (2, M_OCC):  # 2 overflows for some receivers (their values are then truncated alike)
        fd, od = _ff(culled_visible_edges, cap)(p, n, em, occ)
        fh, oh = _ff(culled_visible_edges_host, cap)(p, n, em, occ)
        np.testing.assert_array_equal(np.asarray(oh), np.asarray(od))
        np.testing.assert_allclose(np.asarray(fh), np.asarray(fd), rtol=0, atol=1e-14)
    assert bool(jnp.any(od)) is False and float(jnp.max(fd)) > 0  # M_OCC never overflows
    _, od2 = _ff(culled_visible_edges, 2)(p, n, em, occ)
    assert bool(jnp.any(od2))  # and the small capacity is exercised


def test_host_equals_device_float32():
    em, occ = _scene(2)
    p, n = _receivers(2, 32)
    args = (jnp.asarray(p, jnp.float32), jnp.asarray(n, jnp.float32), em.astype(jnp.float32), occ.astype(jnp.float32))
    fd, od = _ff(culled_visible_edges, 4)(*args)
    fh, oh = _ff(culled_visible_edges_host, 4)(*args)
    assert fh.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(oh), np.asarray(od))
    np.testing.assert_allclose(np.asarray(fh), np.asarray(fd), rtol=0, atol=1e-6)


def test_host_equals_device_touching_and_grazing():
    p = jnp.zeros(3)
    n = jnp.asarray(UP)
    em = jnp.asarray(EM)

    def strip(x0, z=1.0):
        return np.array([[x0, -0.5, z], [x0 + 1, -0.5, z], [x0 + 1, 0.5, z], [x0, 0.5, z]])

    polys = {
        "sliver": strip(0.5 - 1e-9),
        "touching edge": strip(0.5),
        "just outside": strip(0.5 + 1e-9),
        "vertex on a pyramid plane": np.array([[0.5, 0.0, 1.0], [0.9, 0.2, 1.0], [0.9, -0.2, 1.1]]),
        "vertex on light plane": np.array([[0.0, 0.0, 2.0], [0.2, 0.0, 2.5], [-0.2, 0.1, 2.5]]),
        "receiver in the occluder's plane": strip(-0.5, 0.0),
        "occluder crossing the light's plane": np.array([[-0.2, -0.2, 1.5], [0.3, -0.2, 1.5], [0.3, 0.2, 2.6]]),
    }
    dev = jax.jit(functools.partial(_one, culled_visible_edges, 2))
    host = jax.jit(functools.partial(_one, culled_visible_edges_host, 2))
    for name, poly in polys.items():
        o = jnp.asarray(pad([poly, strip(-1.4, 1.2)], 4))
        (fd, od), (fh, oh) = dev(p, n, em, o), host(p, n, em, o)
        assert not bool(od) and not bool(oh), name
        assert abs(float(fh) - float(fd)) <= 1e-15, name


def _weighted_total(edges, p, n, em, occ):
    f, _ = _ff(edges, 4)(p, n, em, occ)
    return jnp.sum(f * jnp.arange(1.0, 1.0 + f.shape[0]))


def _gradients(argnums):
    em, occ = _scene(1)
    p, n = _receivers(1, 24)
    p, n = jnp.asarray(p), jnp.asarray(n)
    jd = jax.jacfwd(_weighted_total, argnums=argnums)(culled_visible_edges, p, n, em, occ)
    jh = jax.jacfwd(_weighted_total, argnums=argnums)(culled_visible_edges_host, p, n, em, occ)
    gh = jax.grad(_weighted_total, argnums=argnums)(culled_visible_edges_host, p, n, em, occ)
    assert float(jnp.max(jnp.abs(jd))) > 1e-3  # the shadows move with the vertices
    np.testing.assert_allclose(np.asarray(jh), np.asarray(jd), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(gh), np.asarray(jd), rtol=0, atol=1e-12)


def test_host_gradients_match_device_light():
    _gradients(3)  # the light's vertices (what the fits differentiate)


@pytest.mark.slow  # ~40 s: two more forward- and one reverse-mode compilation
def test_host_gradients_match_device_occluders():
    _gradients(4)


def test_relevant_counts_match_device():
    em, occ = _scene(3)
    p, n = _receivers(3, 64)
    dev = jax.vmap(occluder_relevance, in_axes=(0, 0, None, None))(jnp.asarray(p), jnp.asarray(n), em, occ)
    host = relevant_counts(p, n, np.asarray(em)[None], np.asarray(occ))
    np.testing.assert_array_equal(host[0], np.sum(np.asarray(dev), axis=1))
    assert 0 < host.max() < M_OCC


def test_fit_light_host_combinatorics_gives_the_same_light():
    import inverse
    from inverse._scenes import occluded_light_problem

    true, start, material, targets = occluded_light_problem(4, n_points=32, seed=1)[:4]
    fits = {mode: inverse.fit_light(start, targets, material, starts=1, solver=inverse.LM(combinatorics=mode))
            for mode in ("device", "host")}
    dev, host = fits["device"], fits["host"]
    assert dev.report.initial_loss > 1e-4  # the start is far off
    assert host.report.loss < 1e-20 and dev.report.loss < 1e-20
    np.testing.assert_allclose(np.asarray(host.light.vertices), np.asarray(dev.light.vertices), rtol=0, atol=1e-9)
    np.testing.assert_allclose(host.report.singular_values, dev.report.singular_values, rtol=1e-8)
    with pytest.raises(ValueError, match="combinatorics"):
        inverse.LM(combinatorics="gpu")


def test_specular_host_equals_device():
    import jaxshadow as js
    from jaxshadow._shade import _specular_traced

    em, occs = random_scene(0, M_OCC)
    p, n = _receivers(0, 16)
    scene = js.Scene(lights=[js.PolygonLight(vertices=em, radiance=[1.0, 1.0, 1.0])], occluders=occs)
    eyes = jnp.broadcast_to(jnp.asarray([0.3, -2.0, 2.5]), (16, 3))
    out = {host: jax.jit(lambda s, host=host: _specular_traced(s, jnp.asarray(p), jnp.asarray(n), eyes,
                                                               jnp.asarray(20.0), "chebyshev", 6, 4, False, host))(scene)
           for host in (False, True)}
    (sd, od), (sh, oh) = out[False], out[True]
    assert bool(od) == bool(oh)
    assert float(jnp.max(sd)) > 0
    np.testing.assert_allclose(np.asarray(sh), np.asarray(sd), rtol=0, atol=1e-12)


# --------------------------------------------------------------------------------------
# The compiled combinatorics (`_clipc.c`) against the NumPy reference
# --------------------------------------------------------------------------------------

_NAMES = ("idx", "kind", "a", "b", "interp", "used", "overflow")


def _assert_same_codes(args, what):
    ref, got = host_culled_codes(*args), host_culled_codes_c(*args)
    for name, x, y in zip(_NAMES, ref, got, strict=True):
        assert x.shape == y.shape and x.dtype == y.dtype, (what, name, x.shape, y.shape, x.dtype, y.dtype)
        bad = np.argwhere(x != y)
        assert bad.size == 0, (what, name, bad[:5])
    return ref


def test_compiled_kernel_is_built():
    # `pip install -e .` builds it (setup.py); without it the light fits' "host" combinatorics
    # fall back to NumPy (~10x slower a call) and the tests below could not run.
    assert clip_host.compiled_available(), "jaxshadow._clipc was not built: reinstall with a C compiler"


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_compiled_equals_numpy_random(dtype):
    shadowed = overflowed = 0
    for seed in range(8):
        if seed < 4:
            em, occ = map(np.asarray, _scene(seed))
        else:  # other light and occluder counts (1 to 11 occluders, 3 to 6 light vertices)
            em0, occs = random_scene(seed, 1 + (5 * seed) % 11)
            em, occ = pad([em0], 6)[0], pad(occs, 4)
        p, n = _receivers(seed % 4, 96)
        for a in sorted({1, 2, 4, min(8, occ.shape[0])}):
            for closed in (False, True):
                cap = edge_capacity(em.shape[0], occ.shape[1], a)
                args = (p.astype(dtype), n.astype(dtype), em.astype(dtype), occ.astype(dtype), a, cap, closed)
                idx, *_, used, over = _assert_same_codes(args, (seed, a, closed))
                shadowed += int(np.sum(idx[:, 0] < occ.shape[0]))
                overflowed += int(np.sum(over))
    assert shadowed > 1000 and overflowed > 50  # both the shadowed and the overflow paths ran


def test_compiled_equals_numpy_degenerate_and_batched():
    em = np.asarray(EM)

    def strip(x0, z=1.0):
        return np.array([[x0, -0.5, z], [x0 + 1, -0.5, z], [x0 + 1, 0.5, z], [x0, 0.5, z]])

    polys = [strip(0.5 - 1e-9), strip(0.5), strip(0.5 + 1e-9), strip(-0.5, 0.0),
             np.array([[0.5, 0.0, 1.0], [0.9, 0.2, 1.0], [0.9, -0.2, 1.1]]),
             np.array([[0.0, 0.0, 2.0], [0.2, 0.0, 2.5], [-0.2, 0.1, 2.5]]),
             np.array([[-0.2, -0.2, 1.5], [0.3, -0.2, 1.5], [0.3, 0.2, 2.6]]),
             np.array([[-0.3, -0.3, 2.0], [0.3, -0.3, 2.0], [0.3, 0.3, 2.0], [-0.3, 0.3, 2.0]])]  # in the light's plane
    occ = pad(polys + [strip(-1.4, 1.2)], 4)
    # Receivers on grid points, on the occluders' and the light's planes' traces, and one on the
    # light itself and behind it.
    pts = np.array([[x, y, 0.0] for x in (-1.0, -0.5, 0.0, 0.5, 1.0) for y in (-0.5, 0.0, 0.5)]
                   + [[0.0, 0.0, 1.0], [0.5, 0.0, 1.0], [0.0, 0.0, 2.0], [0.0, 0.0, 2.5]])
    nrm = np.broadcast_to(UP, pts.shape)
    cap = edge_capacity(4, 4, 4)
    for dtype in (np.float64, np.float32):
        _assert_same_codes((pts.astype(dtype), nrm.astype(dtype), em.astype(dtype), occ.astype(dtype), 4, cap,
                            False), dtype)
    # Leading batch axes, broadcast: per-receiver lights against one occluder set, and the other way.
    rng = np.random.default_rng(5)
    p, n = _receivers(5, 12)
    lights = em[None] + rng.uniform(-0.1, 0.1, (3, 1, 1, 3))  # (3, 1, 4, 3)
    ref = _assert_same_codes((p.reshape(1, 12, 3), n.reshape(1, 12, 3), lights, occ, 3, cap, True), "batched lights")
    assert ref[1].shape == (3, 12, 2 * cap)
    occs = occ[None] + rng.uniform(-0.05, 0.05, (2, 1, 1, 1))
    _assert_same_codes((p[:, None], n[:, None], em, occs, 2, edge_capacity(4, 4, 2), False), "batched occluders")


def test_numpy_fallback_equals_device(monkeypatch):
    # Where `_clipc` is not built, the callback computes the same codes in NumPy.
    monkeypatch.setattr(clip_host, "compiled_available", lambda: False)

    def not_here(*args):
        raise AssertionError("the compiled combinatorics were called")

    monkeypatch.setattr(clip_host, "_codes_packed_c", not_here)
    em, occ = _scene(2)
    p, n = _receivers(2, 48)
    p, n = jnp.asarray(p), jnp.asarray(n)
    fd, od = _ff(culled_visible_edges, 4)(p, n, em, occ)
    fh, oh = jax.jit(jax.vmap(functools.partial(_one, culled_visible_edges_host, 4), in_axes=(0, 0, None, None)))(
        p, n, em, occ)
    np.testing.assert_array_equal(np.asarray(oh), np.asarray(od))
    np.testing.assert_allclose(np.asarray(fh), np.asarray(fd), rtol=0, atol=1e-14)


def test_auto_combinatorics(monkeypatch):
    # `fit_light`'s default: the host combinatorics on the CPU when the C kernel is built and
    # the LM uses them; the device otherwise.
    import inverse
    from jaxshadow import traced

    assert jax.default_backend() == "cpu"
    assert inverse.LM().host_combinatorics()
    assert not inverse.LM(receiver_groups=True).host_combinatorics()
    assert not inverse.LM(combinatorics="device").host_combinatorics()
    assert inverse.LM(combinatorics="host", receiver_groups=True).host_combinatorics()
    monkeypatch.setattr(traced, "host_combinatorics_available", lambda: False)
    assert not inverse.LM().host_combinatorics()  # NumPy alone: slower solves
