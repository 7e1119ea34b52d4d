"""Segment lights on meshes through their visible pieces (`jaxshadow._shadows.segment_pieces`,
`csrc/engine/silhouette_segment.h`).

Reference: the device kernels (`ShadowOptions(engine="device")`: every receiver's segment clipped
against every face, `_clip.visible_segments`; no engine code) and the engine's face path
(`JAXSHADOW_SEGMENT_PIECES=0`: candidate faces clipped on the device). Meshes are generated
(trimesh): a displaced icosphere, a torus, two shapes touching, an open bowl, a triangle soup;
receivers on a floor (lit, penumbra, umbra) with grazing normals, and beside the meshes.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxshadow as js
from jaxshadow import traced
from jaxshadow._shadows import binding as vis
from jaxshadow._shadows import segment_pieces

trimesh = pytest.importorskip("trimesh")

pytestmark = pytest.mark.skipif(not segment_pieces.enabled(traced=True),
                                reason="the shadow engine with its segment pieces is not built")

DEVICE = js.ShadowOptions(engine="device")
A, B = np.array([-1.2, -0.3, 2.4]), np.array([1.1, 0.4, 2.6])


def _icosphere(seed=0, sub=2, r=0.5, centre=(0.0, 0.0, 1.1), amp=0.2):
    m = trimesh.creation.icosphere(subdivisions=sub, radius=r)
    rng = np.random.default_rng(seed)
    v = m.vertices * (1 + amp * rng.uniform(-1, 1, len(m.vertices)))[:, None] + np.asarray(centre)
    return v, np.asarray(m.faces)


def _torus():
    m = trimesh.creation.torus(0.45, 0.15, major_sections=24, minor_sections=10)
    rot = trimesh.transformations.rotation_matrix(0.5, [1, 0.3, 0])
    m.apply_transform(rot)
    return m.vertices + [0.0, 0.0, 1.1], np.asarray(m.faces)


def _touching():
    # A box and a displaced sphere resting on its top face, and a second box sharing a face.
    b1 = trimesh.creation.box(extents=[0.5, 0.4, 0.3])
    b1.apply_translation([-0.25, 0.0, 0.8])
    b2 = trimesh.creation.box(extents=[0.5, 0.4, 0.3])
    b2.apply_translation([0.25, 0.0, 0.8])
    v, f = _icosphere(seed=3, sub=2, r=0.25, centre=(0.0, 0.0, 1.2), amp=0.05)
    v[:, 2] += 0.95 - v[:, 2].min()  # touches the boxes' top face (z = 0.95)
    return [(b1.vertices, b1.faces), (b2.vertices, b2.faces), (v, f)]


def _bowl():
    v, f = _icosphere(seed=1, sub=3, r=0.5, centre=(0.1, 0.0, 1.0), amp=0.05)
    keep = v[f].mean(axis=1)[:, 2] < 1.05  # the lower part: open, its rim a boundary
    return v, f[keep]


def _soup(n=120, seed=2):
    rng = np.random.default_rng(seed)
    c = rng.uniform([-0.6, -0.6, 0.7], [0.6, 0.6, 1.5], (n, 1, 3))
    return c + rng.normal(0, 0.12, (n, 3, 3))


def _scene(kind, light):
    if kind == "soup":
        return js.Scene([light], occluders=jnp.asarray(_soup()))
    parts = {"icosphere": lambda: [_icosphere()], "torus": lambda: [_torus()], "touching": _touching,
             "bowl": lambda: [_bowl()]}[kind]()
    return js.Scene([light], occluders=[js.Mesh(v, f) for v, f in parts])


def _receivers(n=160, seed=5):
    rng = np.random.default_rng(seed)
    p = np.c_[rng.uniform(-1.6, 1.6, (n, 2)), np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    k = n // 4  # grazing: the segment crosses their horizon
    t, a = np.radians(rng.uniform(70, 89, k)), rng.uniform(0, 2 * np.pi, k)
    nrm[:k] = np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)
    # Beside the meshes, facing sideways (mesh vertices above and below them).
    side = np.c_[rng.uniform(-1.4, 1.4, (16, 1)), np.full((16, 1), -1.3), rng.uniform(0.6, 1.6, (16, 1))]
    return np.r_[p, side], np.r_[nrm, np.tile([0.0, 1.0, 0.3], (16, 1))]


P, N = _receivers()


def _light(profile="isotropic", a=A, b=B):
    return js.LinearLight(a, b, power=[1.0, 2.0, 0.5], profile=profile, exponent=2)


def _face_path(monkeypatch, fn):
    with monkeypatch.context() as m:
        m.setenv("JAXSHADOW_SEGMENT_PIECES", "0")
        return fn()


def _close(got, want, rtol=1e-9, scale=None):
    """Within `rtol` of the largest reference value (or of `scale`: the unoccluded one)."""
    got, want = np.asarray(got), np.asarray(want)
    assert np.all(np.isfinite(got))
    err = np.abs(got - want).max()
    assert err <= rtol * (np.abs(want).max() if scale is None else scale), err


@pytest.mark.parametrize("kind", ["icosphere", "torus", "touching", "bowl", "soup"])
def test_values_equal_the_brute_force_path(kind):
    prof = "cosine" if kind in ("torus", "soup") else "isotropic"
    scene = _scene(kind, _light(prof))
    lp = js.shadow_plan(scene, P, N).lights[0]
    assert lp.faces is None  # the pieces path, not the candidate faces
    assert {1, 2, 3} <= set(lp.classes.tolist()) or kind not in ("icosphere", "touching")
    assert 3 in set(lp.classes.tolist())
    got = np.asarray(js.irradiance(scene, P, N))
    _close(got, js.irradiance(scene, P, N, shadows=DEVICE))
    assert np.all(got[lp.classes == 2] == 0)
    # Fewer pieces than candidate faces: the capacity follows the silhouette.
    assert lp.counts.max() < lp.kept.max()


def test_face_path_and_specular(monkeypatch):
    scene = _scene("icosphere", _light())
    _close(js.irradiance(scene, P, N), _face_path(monkeypatch, lambda: js.irradiance(scene, P, N)))
    # Specular (Chebyshev lobe fits): within the fits' error, which depends on how a visible
    # piece is split (the face path also splits pieces at the ends of empty intervals).
    eye = np.array([0.3, -2.0, 1.5])
    spec = lambda: js.specular(scene, P, N, eye, 15.0)  # noqa: E731
    _close(spec(), _face_path(monkeypatch, spec), rtol=1e-7)


def test_traced_jit_vmap_and_capacity(monkeypatch):
    scene = _scene("icosphere", _light())
    want = np.asarray(js.irradiance(scene, P, N, shadows=DEVICE))
    cap = traced.shadow_capacity(scene, P, N)
    faces_cap = _face_path(monkeypatch, lambda: traced.shadow_capacity(scene, P, N))
    assert 1 <= cap < faces_cap  # pieces, not the faces in the light triangle
    n = jnp.asarray(N)
    f = jax.jit(lambda q: traced.irradiance(scene, q, n, capacity=cap))
    e, over = f(jnp.asarray(P))
    assert not bool(over)
    _close(e, want)
    _, over = jax.jit(lambda q: traced.irradiance(scene, q, n, capacity=max(1, cap - 1)))(jnp.asarray(P))
    assert bool(over)

    def at(dz):
        light = js.LinearLight(jnp.asarray(A) + jnp.array([0, 0, 1.0]) * dz, jnp.asarray(B), power=[1.0, 2.0, 0.5])
        sc = js.Scene([light], occluders=[js.Mesh(*_icosphere())])
        return traced.irradiance(sc, jnp.asarray(P), jnp.asarray(N), capacity=cap + 4)

    e2, over2 = jax.jit(jax.vmap(at))(jnp.array([0.0, 0.1]))
    assert not bool(jnp.any(over2))
    _close(e2[0], want)
    moved = js.Scene([_light(a=A + [0, 0, 0.1])], occluders=[js.Mesh(*_icosphere())])
    _close(e2[1], js.irradiance(moved, P, N, shadows=DEVICE))


def _fd(f, x, h=1e-6):
    g = np.zeros(x.size)
    for i in range(x.size):
        d = np.zeros(x.size)
        d[i] = h
        g[i] = (f(x + d.reshape(x.shape)) - f(x - d.reshape(x.shape))) / (2 * h)
    return g.reshape(x.shape)


V, F = _icosphere()
MESH = js.Mesh(V, F)


def _penumbra(k=24):
    lp = js.shadow_plan(js.Scene([_light()], occluders=[MESH]), P, N).lights[0]
    idx = np.nonzero(lp.classes == 3)[0][:k]
    return P[idx], N[idx]


@pytest.mark.slow  # four compiled programs (planned, face path, traced, values): 140 s at load 22 on 2 cores
def test_gradients_wrt_the_light_ends(monkeypatch):
    p, n = _penumbra()

    def of_ends(ab):
        light = js.LinearLight(ab[0], ab[1], power=[1.0, 2.0, 0.5])
        return js.irradiance(js.Scene([light], occluders=[MESH]), p, n).sum()

    ab = np.stack([A, B])
    g = np.asarray(jax.grad(of_ends)(jnp.asarray(ab)))
    g_faces = _face_path(monkeypatch, lambda: np.asarray(jax.grad(of_ends)(jnp.asarray(ab))))
    np.testing.assert_allclose(g, g_faces, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(g, _fd(lambda x: float(of_ends(x)), ab), rtol=1e-5, atol=1e-7)
    g_jit = np.asarray(jax.jit(jax.grad(of_ends))(jnp.asarray(ab)))  # the traced path
    np.testing.assert_allclose(g_jit, g, rtol=1e-10, atol=1e-12)


@pytest.mark.slow  # 110 s at load 22 on 2 cores
def test_gradients_wrt_the_occluder_vertices(monkeypatch):
    p, n = _penumbra()

    def of_shift(t):  # every vertex of the mesh moved by t
        scene = js.Scene([_light()], occluders=[MESH.with_vertices(jnp.asarray(V) + t[None, :])])
        return js.irradiance(scene, p, n).sum()

    t0 = np.zeros(3)
    gs = np.asarray(jax.grad(of_shift)(jnp.asarray(t0)))
    gs_faces = _face_path(monkeypatch, lambda: np.asarray(jax.grad(of_shift)(jnp.asarray(t0))))
    np.testing.assert_allclose(gs, gs_faces, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(gs, _fd(lambda x: float(of_shift(x)), t0), rtol=1e-5, atol=1e-7)
    assert np.abs(gs).max() > 0


def test_float32_is_decided_in_double(monkeypatch):
    scene = _scene("torus", _light())
    s32 = js.Scene([js.LinearLight(A.astype(np.float32), B.astype(np.float32), power=[1.0, 2.0, 0.5])],
                   occluders=[js.Mesh(np.asarray(_torus()[0], np.float32), _torus()[1])])
    p32, n32 = P.astype(np.float32), N.astype(np.float32)
    got = np.asarray(js.irradiance(s32, p32, n32))
    assert got.dtype == np.float32
    faces32 = _face_path(monkeypatch, lambda: np.asarray(js.irradiance(s32, p32, n32)))
    _close(got, faces32, rtol=2e-5)
    _close(got, js.irradiance(scene, P, N, shadows=DEVICE), rtol=2e-5)


def _box(lo, hi):
    m = trimesh.creation.box(bounds=[lo, hi])
    return js.Mesh(m.vertices, m.faces)


@pytest.mark.parametrize("case", ["plane-through-end", "edge-towards-receiver", "vertex-on-segment", "pierced"])
def test_degenerate_configurations(case, monkeypatch):
    p = np.array([[0.0, 0.0, 0.0], [0.05, 0.0, 0.0], [0.0, 0.02, 0.0]])
    n = np.tile([0.0, 0.0, 1.0], (3, 1))
    if case == "plane-through-end":
        # The plane through p[0] and the box's bottom edge along x (y = 0) holds a exactly.
        occ, a, b = [_box([-0.5, 0.0, 1.0], [0.5, 0.4, 1.2])], [0.0, 0.0, 2.0], [0.0, 1.0, 2.0]
    elif case == "edge-towards-receiver":
        # A vertical box edge on the line through p[0] (its plane through p[0] is zero).
        occ, a, b = [_box([0.0, 0.0, 1.0], [0.3, 0.3, 1.5])], [-0.5, 0.1, 2.0], [0.8, 0.2, 2.0]
    elif case == "vertex-on-segment":
        # A mesh vertex exactly on the segment (the segment touches the mesh there).
        v, f = _icosphere(sub=1, amp=0.0, centre=(0.0, 0.0, 1.5))
        top = v[np.argmax(v[:, 2])]
        occ, a, b = [js.Mesh(v, f)], list(top - [0.6, 0.0, 0.0]), list(top + [0.6, 0.0, 0.0])
    else:
        # The segment passes through the mesh: face planes bound the pieces.
        v, f = _icosphere(amp=0.1, centre=(0.0, 0.0, 1.6))
        occ, a, b = [js.Mesh(v, f)], [-1.0, 0.05, 1.6], [1.0, -0.05, 1.7]
    scene = js.Scene([js.LinearLight(np.array(a, float), np.array(b, float), power=1.0)], occluders=occ)
    got = np.asarray(js.irradiance(scene, p, n))
    free = float(np.abs(np.asarray(js.irradiance(js.Scene(scene.lights), p, n))).max())
    _close(got, js.irradiance(scene, p, n, shadows=DEVICE), scale=free)
    _close(got, _face_path(monkeypatch, lambda: js.irradiance(scene, p, n)), scale=free)

    def total(ab):
        light = js.LinearLight(ab[0], ab[1], power=1.0)
        return js.irradiance(js.Scene([light], occluders=occ), p, n).sum()

    ab = jnp.asarray([a, b], float)
    g = np.asarray(jax.grad(total)(ab))
    assert np.all(np.isfinite(g))
    if case == "pierced":  # face-plane ends: the derivatives of the face path's
        np.testing.assert_allclose(g, _face_path(monkeypatch, lambda: np.asarray(jax.grad(total)(ab))), rtol=1e-9,
                                   atol=1e-12)


def test_switch_and_summary(monkeypatch):
    scene = _scene("icosphere", _light())
    s = js.shadow_plan(scene, P, N).summary()["lights"][0]
    assert s["penumbra_pieces"]["max"] >= 1 and "hidden" in s["classes"]
    lp = _face_path(monkeypatch, lambda: js.shadow_plan(scene, P, N).lights[0])
    assert lp.faces is not None and "penumbra_pieces" not in _face_path(
        monkeypatch, lambda: js.shadow_plan(scene, P, N).summary()["lights"][0])
    assert vis.engine_available()


def _host(monkeypatch, walk, *args):
    with monkeypatch.context() as m:
        m.setenv("JAXSHADOW_SEGMENT_WALK", "1" if walk else "0")
        return segment_pieces.host_pieces(*args)


@pytest.mark.parametrize("kind", ["icosphere", "bowl", "fine"])
@pytest.mark.parametrize("dt", [np.float64, np.float32])
def test_contour_path_gives_the_face_path_pieces(kind, dt, monkeypatch):
    """The contour path (faces of contour edges in the light triangle and faces the segment meets;
    the rest by rays to the middles of the runs between their intervals) returns the face path's
    pieces, codes and order (`JAXSHADOW_SEGMENT_WALK=0`: every face in the light triangle), for
    segments over, through and along the mesh, receivers on the floor, on the segment's symmetry
    plane and beside the mesh, and computes fewer faces' intervals."""
    v, f = {"icosphere": _icosphere, "bowl": _bowl, "fine": lambda: _icosphere(seed=4, sub=3, amp=0.1)}[kind]()
    scene = js.Scene([_light()], occluders=[js.Mesh(v, f)])
    assert scene.occluders.shape[0] >= 256  # the contour path serves
    occ = vis.HostOccluders.of(np.asarray(scene.occluders), scene.occluder_topology, dt)
    rng = np.random.default_rng(7)
    on_axis = np.c_[rng.uniform(-1.5, 1.5, 40), np.zeros(40), np.zeros(40)]  # y = 0: symmetric
    p = np.r_[P, on_axis].astype(dt)
    tri = np.asarray(scene.occluders)[0]
    segments = [(A, B), ([-0.4, 0.0, 2.5], [0.4, 0.0, 2.5]), ([-1.0, 0.05, 1.1], [1.0, -0.05, 1.2]),
                (tri[0], tri[1]), (tri[0], tri[0] + [0.0, 0.0, 1.5])]
    examined = np.zeros(2, np.int64)
    for a, b in segments:
        a, b = np.asarray(a, dt), np.asarray(b, dt)
        want = _host(monkeypatch, False, p, a, b, occ)
        got = _host(monkeypatch, True, p, a, b, occ)
        for x, y in zip(got[:1] + got[2:], want[:1] + want[2:], strict=True):
            np.testing.assert_array_equal(x, y)
        examined += [got[1].sum(), want[1].sum()]
    assert examined[0] < examined[1], examined


@pytest.mark.parametrize("dt", [np.float64, np.float32])
def test_contour_path_at_t_junctions(dt, monkeypatch):
    """Faces meeting in T-junctions (a merged cap's edge along several wall faces' edges: their
    intervals need not meet bit for bit, so the contour path bounds pieces by such a pair as by a
    contour edge and walks into the nodes above it): the face path's pieces, codes and order, the
    contour path serving most penumbra receivers."""
    from test_real_meshes import t_junction_prism

    v, f = t_junction_prism(n_side=20)
    scene = js.Scene([_light()], occluders=[js.Mesh(v, f)])
    faces = np.asarray(scene.occluders)
    assert faces.shape[0] >= 256 and faces.shape[1] <= 64  # the contour path serves
    occ = vis.HostOccluders.of(faces, scene.occluder_topology, dt)
    rng = np.random.default_rng(3)
    p = np.r_[P, np.c_[rng.uniform(-0.8, 0.8, (200, 2)), np.zeros(200)]].astype(dt)
    for a, b in [(A, B), ([-0.4, 0.0, 2.5], [0.4, 0.0, 2.5]), ([-0.1, -0.5, 1.5], [0.1, 0.5, 1.6])]:
        a, b = np.asarray(a, dt), np.asarray(b, dt)
        want = _host(monkeypatch, False, p, a, b, occ)
        got = _host(monkeypatch, True, p, a, b, occ)
        for x, y in zip(got[:1] + got[2:], want[:1] + want[2:], strict=True):
            np.testing.assert_array_equal(x, y)
        pen = want[0] == 3
        assert pen.sum() > 20
        assert np.mean(got[1][pen] != want[1][pen]) > 0.3  # faces examined: the contour path served


def _host_env(monkeypatch, walk, *args):
    with monkeypatch.context() as m:
        if walk is None:
            m.delenv("JAXSHADOW_SEGMENT_WALK", raising=False)
        else:
            m.setenv("JAXSHADOW_SEGMENT_WALK", walk)
        return segment_pieces.host_pieces(*args)


@pytest.mark.parametrize("sub", [5, 3])
def test_default_path_by_face_count(sub, monkeypatch):
    """Without `JAXSHADOW_SEGMENT_WALK` the engine takes the contour path on occluder sets of 16 384
    faces or more (20 480 here: its faces examined are those of `=1`) and the face path below
    (1 280: its candidates are those of `=0`); the pieces, codes and order are the face path's
    either way."""
    v, f = _icosphere(seed=6, sub=sub, amp=0.05)
    scene = js.Scene([_light()], occluders=[js.Mesh(v, f)])
    occ = vis.HostOccluders.of(np.asarray(scene.occluders), scene.occluder_topology, np.float64)
    p = P.astype(np.float64)
    face = _host_env(monkeypatch, "0", p, A, B, occ)
    walk = _host_env(monkeypatch, "1", p, A, B, occ)
    auto = _host_env(monkeypatch, None, p, A, B, occ)
    for got in (walk, auto):
        for x, y in zip(got[:1] + got[2:], face[:1] + face[2:], strict=True):
            np.testing.assert_array_equal(x, y)
    assert np.sum(face[0] == 3) > 10 and not np.array_equal(walk[1], face[1])
    np.testing.assert_array_equal(auto[1], walk[1] if len(f) >= 16384 else face[1])
