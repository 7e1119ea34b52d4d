"""Fuzzing the compiled shadow engine (`csrc/`) through its bindings and the public entry points.

The engine is C++ called through ctypes and XLA FFI: a memory error there kills the process, so
`tools/sanitize.sh` runs this module (and the engine's other tests) against a build under
AddressSanitizer and UndefinedBehaviorSanitizer, where any invalid access, overflow or undefined
operation aborts the run. Under the normal build the same cases check what the engine returns.

What is drawn (a NumPy seed plus a few choices per example; `tests/random_meshes.py`): closed,
open and multi-component meshes (welded, with the engine's solids, closed-mesh culling and edge
twins), triangle soups with exact duplicates and reversed copies, degenerate faces (repeated
vertices, collinear, zero size) that only the raw binding accepts, hundreds to thousands of
stacked and coincident occluders, meshes touching the floor or the light's plane, whole scenes
scaled by 1e-30..1e30 (float32) or 1e-150..1e150 (float64) and moved far from the origin;
receivers on the floor, on event planes and lines (through a light vertex and an occluder vertex
or edge), inside faces and on edges, on the light's plane and above it. Point, directional and
segment lights go through their entry points too: segment lights' candidate faces and visible
pieces, also for degenerate segments (zero length, between two occluder vertices, along an
occluder edge), on the host and through the XLA FFI handler.

Checked: no crash; classes and endpoint codes in range (every vertex, edge and face reference
inside its table, the segment pieces' plane codes too); offsets consistent; the FFI handlers'
segment pieces those of the host plan; decoded boundary points, Lambert sums and the public
values finite. And the public entry points (`Scene`, `Mesh`, `PolygonLight`, `irradiance`,
`shadow_plan`, `ShadowCache`) refuse NaN and infinite coordinates with a `ValueError` before any
C++ runs.

Profiles: CI runs `CI_EXAMPLES` derandomized draws of the engine property (30 through the
public values, 8 through the FFI handlers); `-m slow` runs `JAXSHADOW_FUZZ_EXAMPLES` (default
3000) random draws.
"""

from __future__ import annotations

import os

import jax
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import jaxshadow as js
from jaxshadow._core.mesh import OccluderTopology
from jaxshadow._shadows import binding as vis
from jaxshadow._shadows import segment_pieces

pytest.importorskip("trimesh")
pytestmark = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")
import random_meshes as rm  # noqa: E402

CI_EXAMPLES = 150
LONG_EXAMPLES = int(os.environ.get("JAXSHADOW_FUZZ_EXAMPLES", "3000"))
F32, F64 = np.float32, np.float64


CI = rm.profile(CI_EXAMPLES, True)
LONG = rm.profile(LONG_EXAMPLES, False)


# --------------------------------------------------------------------------------------
# Scenes at the binding level: padded faces and a topology, anything finite
# --------------------------------------------------------------------------------------


def _pad(polys: list[np.ndarray], ko: int) -> np.ndarray:
    """Polygons padded to `ko` vertices by repeating their first vertex (the `Scene` convention)."""
    return np.stack([np.concatenate([q, np.repeat(q[:1], ko - len(q), axis=0)]) for q in polys])


def _degenerate(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    out = []
    for _ in range(n):
        c = rng.uniform([-0.8, -0.8, 0.3], [0.8, 0.8, 1.8])
        d = rng.normal(size=3) * 0.3
        kind = rng.integers(4)
        if kind == 0:  # repeated vertex
            out.append(np.stack([c, c, c + d]))
        elif kind == 1:  # collinear
            out.append(np.stack([c, c + d, c + 2.5 * d]))
        elif kind == 2:  # a point
            out.append(np.stack([c, c, c]))
        else:  # a quad folded onto a segment
            out.append(np.stack([c, c + d, c, c + d]))
    return out


def _stacked(rng: np.random.Generator, n: int) -> list[np.ndarray]:
    """`n` horizontal quads over the same spot, many at exactly the same height and some exact
    copies: depth complexity in the thousands."""
    heights = rng.choice(np.linspace(0.4, 1.6, max(2, n // 8)), n)
    out = []
    for z in heights:
        x0, y0 = rng.uniform(-0.5, 0.1, 2)
        w, h = rng.uniform(0.2, 0.8, 2)
        q = np.array([[x0, y0, z], [x0 + w, y0, z], [x0 + w, y0 + h, z], [x0, y0 + h, z]])
        out.append(q if rng.random() < 0.5 else q[::-1].copy())
    dup = rng.integers(0, n, n // 10)
    return out + [out[i].copy() for i in dup]


@st.composite
def engine_scenes(draw):
    """The draw: `(seed, kind, dtype, scale exponent, offset)` (the scene is built from them by
    `build_scene`, outside the strategy: trimesh touches the `random` module)."""
    seed = draw(st.integers(0, 2**32 - 1))
    kind = draw(st.sampled_from(["closed", "open", "components", "floor", "light", "soup", "degenerate", "stacked"]))
    dt = draw(st.sampled_from([F32, F64]))
    lim = 30 if dt == F32 else 150
    exp = draw(st.sampled_from([0, 0, 0, 1, -3, 6, -lim // 2, lim // 2, -lim, lim]))
    return seed, kind, dt, exp, draw(st.sampled_from([0.0, 0.0, 1.0, 1e3, 1e5]))


def build_scene(seed: int, kind: str, dt: type, exp: int, far: float):
    """`(light (K, 3), faces (M, Ko, 3), topology, points (N, 3), normals (N, 3), what)` in one
    float dtype: float32 keeps its range, float64 goes to 1e+-150 (squares still finite)."""
    rng = np.random.default_rng(seed)
    light = rm.light(rng)
    topo = None
    if kind == "stacked":
        polys = _stacked(rng, int(rng.choice([300, 1000, 2500])))
        faces, topo = _pad(polys, 4), OccluderTopology.independent(len(polys))
        tris = faces[:, :3]
    else:
        meshes = rm.mesh_scene(rng, kind if kind in ("closed", "open", "components", "floor", "light") else "components",
                               fine=bool(rng.random() < 0.15))
        if kind in ("soup", "degenerate"):
            tris = rm.soup(rng, meshes, duplicates=0.2)
            polys = list(tris)
            if kind == "degenerate":
                polys = polys + _degenerate(rng, max(3, len(polys) // 10))
                polys = [polys[i] for i in rng.permutation(len(polys))]
            ko = max(len(q) for q in polys)
            faces, topo = _pad(polys, ko), OccluderTopology.independent(len(polys))
        else:
            scene = js.Scene([js.PolygonLight(light, 1.0)], occluders=[js.Mesh(v, f) for v, f in meshes])
            faces, topo = np.asarray(scene.occluders), scene.occluder_topology
            tris = np.concatenate([v[f] for v, f in meshes])
    n = 48 if len(faces) < 1000 or kind != "stacked" else 8  # O(k^2) work per receiver there
    parts = [rm.floor_receivers(rng, n // 2), rm.event_receivers(rng, light, tris, n // 4),
             rm.surface_receivers(rng, tris, n // 8, "face"), rm.surface_receivers(rng, tris, n // 8, "edge")]
    p = np.concatenate([x[0] for x in parts])
    nrm = np.concatenate([x[1] for x in parts])
    # A few on the light's plane, above it, at an occluder vertex, with random normals.
    p[:3] = [[0.05, 0.02, rm.LIGHT_Z], [0.3, -0.2, rm.LIGHT_Z + 0.5], tris[0, 0]]
    nrm[:3] = rng.normal(size=(3, 3))
    nrm[rng.random(len(nrm)) < 0.1] = rng.normal(size=3)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    scale = 10.0 ** exp
    offset = far * scale * rng.normal(size=3)
    light, faces, p = ((x * scale + offset).astype(dt) for x in (light, faces, p))
    return light, np.ascontiguousarray(faces), topo, p, nrm.astype(dt), (kind, seed, dt.__name__, exp, far)


def _check_codes(runs: np.ndarray, k: int, m: int, ko: int) -> None:
    nv = k + m * ko
    c = runs.reshape(-1, vis.CODE_WIDTH)
    kind = c[:, 0]
    assert np.all((kind >= vis.K_UNUSED) & (kind <= vis.K_PLANES)), np.unique(kind)
    lightv = kind == vis.K_LIGHT
    assert np.all((c[lightv, 1] >= 0) & (c[lightv, 1] < k))
    hor = kind == vis.K_HORIZON
    assert np.all((c[hor, 1] >= 0) & (c[hor, 1] < k))
    proj = kind == vis.K_PROJECTED
    assert np.all((c[proj, 1] >= k) & (c[proj, 1] < nv))
    cross = kind == vis.K_EMITTER_CROSS
    assert np.all((c[cross, 1:3] >= k) & (c[cross, 1:3] < nv))
    for t, a, b in ((1, 2, 3), (4, 5, 6)):
        pl = c[kind == vis.K_PLANES]
        ty = pl[:, t]
        assert np.all((ty >= 0) & (ty <= 2))
        through = pl[ty == 0]
        assert np.all((through[:, [a, b]] >= 0) & (through[:, [a, b]] < nv))
        cut = pl[ty == 2]
        assert np.all((cut[:, a] >= 0) & (cut[:, a] < m))


def _check_engine(light, faces, topo, p, nrm, what) -> None:
    occ = vis.HostOccluders.of(faces, topo, faces.dtype)
    m, ko = faces.shape[:2]
    pc = vis.polygon_codes(p, nrm, light, occ, codes=True, decoded=True, lambert=True)
    n = len(p)
    assert pc.classes.shape == (n,) and np.all((pc.classes >= vis.ZERO) & (pc.classes <= vis.PENUMBRA)), what
    assert np.all(pc.stats >= 0), what
    off = pc.offsets
    assert off[0] == 0 and np.all(np.diff(off) >= 0), what
    total = int(off[-1])
    assert (pc.runs is None and total == 0) or pc.runs.shape == (total, 2, vis.CODE_WIDTH), what
    if total:
        _check_codes(pc.runs, len(light), m, ko)
        assert np.all(np.isfinite(pc.points)), what
    assert np.all(np.isfinite(pc.lambert)), what
    # The plan without codes (another allocation pattern) classifies alike.
    again = vis.polygon_codes(p, nrm, light, occ, codes=False)
    np.testing.assert_array_equal(again.classes, pc.classes, err_msg=str(what))
    # Hard shadows and segment lights over the same occluders.
    vis.hard_visibility(p, light.mean(axis=0), True, occ)
    vis.hard_visibility(p, np.array([0.1, 0.2, -1.0], faces.dtype), False, occ)
    soff, sfaces = vis.segment_candidates(p, light[0], light[2], occ)
    assert soff[0] == 0 and np.all(np.diff(soff) >= 0) and len(sfaces) == soff[-1], what
    assert np.all((sfaces >= 0) & (sfaces < m)), what
    _check_pieces(p, light[0], light[2], occ, m, ko, what, np.diff(soff))
    for a, b in _segments(light, faces):
        _check_pieces(p, a, b, occ, m, ko, what)


def _segments(light: np.ndarray, faces: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Degenerate segment lights over the scene: zero length (at a light vertex), from one
    occluder vertex to another (through or along the meshes: face-plane ends, ends on faces), and
    along an occluder edge."""
    v = faces.reshape(-1, 3)
    return [(light[1], light[1].copy()), (v[0], v[len(v) // 2]), (faces[0, 0], faces[0, 1])]


def _check_pieces(p, a, b, occ, m, ko, what, kept_want=None) -> None:
    """The segment light's visible pieces (`segment_pieces.host_pieces`): the contour path's those
    of the face path (`JAXSHADOW_SEGMENT_WALK=1` against `=0`); classes 1..3, offsets consistent, endpoint
    codes -1, -2 or a plane of an occluder face (f (Ko + 1) + i < m (Ko + 1)), a penumbra receiver
    with at least one piece and the others with none; `kept_want`: the face path's candidate
    counts, those of `segment_candidates`."""
    os.environ["JAXSHADOW_SEGMENT_WALK"] = "0"
    try:
        faces_path = segment_pieces.host_pieces(p, a, b, occ)
    finally:
        del os.environ["JAXSHADOW_SEGMENT_WALK"]
    os.environ["JAXSHADOW_SEGMENT_WALK"] = "1"
    try:
        cls, kept, off, pieces = segment_pieces.host_pieces(p, a, b, occ)
    finally:
        del os.environ["JAXSHADOW_SEGMENT_WALK"]
    # The contour path (where it serves) gives the face path's pieces.
    for x, y in ((cls, faces_path[0]), (off, faces_path[2]), (pieces, faces_path[3])):
        np.testing.assert_array_equal(x, y, err_msg=str(what))
    n = len(p)
    assert cls.shape == (n,) and np.all((cls >= 1) & (cls <= 3)), what
    assert off.shape == (n + 1,) and off[0] == 0 and np.all(np.diff(off) >= 0) and len(pieces) == off[-1], what
    assert np.all(((pieces >= 0) & (pieces < m * (ko + 1))) | (pieces == -1) | (pieces == -2)), what
    np.testing.assert_array_equal(np.diff(off) > 0, cls == 3, err_msg=str(what))
    assert np.all(kept >= 0), what
    if kept_want is not None:
        np.testing.assert_array_equal(faces_path[1], kept_want, err_msg=str(what))


def _run_engine(data) -> None:
    _check_engine(*build_scene(*data.draw(engine_scenes())))


@CI
@given(st.data())
def test_engine_survives_random_scenes(data):
    _run_engine(data)


@pytest.mark.slow
@LONG
@given(st.data())
def test_engine_survives_random_scenes_long(data):
    _run_engine(data)


def test_engine_silhouette_path_with_stacked_components():
    """Over 256 faces with every vertex between the floor and the light (the silhouette path),
    several components, receivers on event lines: the face path (`JAXSHADOW_SILHOUETTE=0`)
    classifies the same receivers with the same or a finer class, and both are well formed."""
    rng = np.random.default_rng(11)
    meshes = rm.mesh_scene(rng, "components", fine=True)
    scene = js.Scene([js.PolygonLight(rm.light(rng), 1.0)], occluders=[js.Mesh(v, f) for v, f in meshes])
    faces, topo = np.asarray(scene.occluders), scene.occluder_topology
    assert faces.shape[0] >= 256
    light = np.asarray(scene.lights[0].vertices)
    tris = np.concatenate([v[f] for v, f in meshes])
    p, nrm = (np.concatenate(x) for x in zip(rm.floor_receivers(rng, 300), rm.event_receivers(rng, light, tris, 300),
                                             strict=True))
    _check_engine(light, faces, topo, p, nrm, "silhouette")
    os.environ["JAXSHADOW_SILHOUETTE"] = "0"
    try:
        _check_engine(light, faces, topo, p, nrm, "face path")
    finally:
        del os.environ["JAXSHADOW_SILHOUETTE"]


# --------------------------------------------------------------------------------------
# The XLA FFI handlers (traced receivers)
# --------------------------------------------------------------------------------------


@rm.profile(8, True)
@given(engine_scenes())
def test_ffi_handlers_survive_random_scenes(draw):
    light, faces, topo, p, nrm, what = build_scene(*draw)
    if not vis.ffi_available():
        pytest.skip("the engine was built without its XLA FFI handlers")
    cap = 16
    fn = jax.jit(vis.traced_polygon_codes, static_argnums=(4, 5))
    cls, counts, runs = (np.asarray(x) for x in fn(p, nrm, light, faces, topo, cap))
    assert np.all((cls >= 0) & (cls <= 3)) and np.all(counts >= 0), what
    used = np.arange(cap)[None, :] < np.minimum(counts, cap)[:, None]
    _check_codes(runs[used], len(light), faces.shape[0], faces.shape[1])
    hard = jax.jit(vis.traced_hard_visibility, static_argnums=(2, 4))(p, light.mean(axis=0), True, faces, topo)
    assert set(np.unique(np.asarray(hard))) <= {0, 1}, what
    cnt, seg = jax.jit(vis.traced_segment_candidates, static_argnums=(4, 5))(p, light[0], light[2], faces, topo, cap)
    seg = np.asarray(seg)
    assert np.all((seg >= -1) & (seg < faces.shape[0])), what
    # The segment pieces' handler gives the host plan's pieces (those that fit the capacity).
    occ = vis.HostOccluders.of(faces, topo, faces.dtype)
    pieces = jax.jit(segment_pieces.traced_pieces, static_argnums=(4, 5))
    for a, b in [(light[0], light[2])] + _segments(light, faces):
        hcls, _, hoff, hpieces = segment_pieces.host_pieces(p, a, b, occ)
        tcls, tcounts, tpieces = (np.asarray(x) for x in pieces(p, a, b, faces, topo, cap))
        np.testing.assert_array_equal(tcls, hcls, err_msg=str(what))
        np.testing.assert_array_equal(tcounts, np.diff(hoff), err_msg=str(what))
        for i in range(len(p)):
            k = min(int(tcounts[i]), cap)
            np.testing.assert_array_equal(tpieces[i, :k], hpieces[hoff[i]:hoff[i] + k], err_msg=str(what))
            assert np.all(tpieces[i, k:] == -1), what


# --------------------------------------------------------------------------------------
# The public entry points: NaN and infinities never reach the engine
# --------------------------------------------------------------------------------------


BAD = (np.nan, np.inf, -np.inf)


def _poison(x: np.ndarray, rng: np.random.Generator, value: float) -> np.ndarray:
    y = np.array(x, np.float64)
    y.reshape(-1)[rng.integers(y.size)] = value
    return y


@CI
@given(st.integers(0, 2**32 - 1), st.sampled_from(["light", "mesh", "polygons", "array", "points", "normals"]),
       st.sampled_from(BAD), st.sampled_from(["irradiance", "shadow_plan", "cache"]))
def test_public_entry_points_refuse_non_finite_input(seed, where, value, entry):
    rng = np.random.default_rng(seed)
    light = rm.light(rng)
    (v, f), = rm.mesh_scene(rng, "closed")
    p, nrm = rm.floor_receivers(rng, 8)
    poisoned = {"light": lambda: _poison(light, rng, value), "mesh": lambda: _poison(v, rng, value),
                "polygons": lambda: _poison(v[f], rng, value), "array": lambda: _poison(v[f], rng, value),
                "points": lambda: _poison(p, rng, value), "normals": lambda: _poison(nrm, rng, value)}[where]()

    def call():
        lt = poisoned if where == "light" else light
        if where == "mesh":
            occ: object = [js.Mesh(poisoned, f)]
        elif where == "polygons":
            occ = list(poisoned)
        elif where == "array":
            occ = poisoned
        else:
            occ = [js.Mesh(v, f)]
        scene = js.Scene([js.PolygonLight(lt, 1.0)], occluders=occ)
        pp = poisoned if where == "points" else p
        nn = poisoned if where == "normals" else nrm
        if entry == "irradiance":
            return js.irradiance(scene, pp, nn)
        if entry == "shadow_plan":
            return js.shadow_plan(scene, pp, nn)
        return js.ShadowCache(scene, pp, nn)

    with pytest.raises(ValueError, match="finite"):
        call()


@rm.profile(30, True)  # each new occluder count compiles the value kernels once
@given(engine_scenes())
def test_public_values_are_finite_on_random_meshes(draw):
    """Scenes the public entry points accept (degenerate faces are refused with a ValueError)
    give finite values; the plan and the values agree on which receivers are in umbra."""
    seed, kind, dt, exp, far = draw
    # Scenes beyond 1e+-30 overflow the validation's own float64 products (a ValueError then, but
    # naming a wrong reason); the engine's range is fuzzed above.
    light, faces, topo, p, nrm, what = build_scene(seed, kind, dt, int(np.clip(exp, -30, 30)), far)
    try:
        sc = js.Scene([js.PolygonLight(light, 1.0)], occluders=list(faces))
    except ValueError as err:
        assert what[0] == "degenerate" or "coincide" in str(err) or "non-planar" in str(err), (what, err)
        return
    cls = js.shadow_plan(sc, p, nrm).lights[0].classes
    e = np.asarray(js.irradiance(sc, p, nrm))
    assert e.dtype == p.dtype and np.all(np.isfinite(e)), what
    assert np.all(e[cls == vis.UMBRA] == 0), what


# --------------------------------------------------------------------------------------
# Cases the fuzzing found
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize("scale", [1e-25, 1e-20, 1e20, 1e30])
def test_found_float32_penumbra_values_at_extreme_scales(scale):
    """A float32 scene scaled by 1e20 (or 1e-20) gave 0 at every penumbra receiver: the host
    path's lit-side test took the light's Newell normal from raw coordinates, whose products
    overflow (underflow) float32. Form factors are scale-free: the values at scale 1 hold."""
    light = np.array([[-0.4, -0.4, 2.0], [-0.4, 0.4, 2.0], [0.4, 0.4, 2.0], [0.4, -0.4, 2.0]])
    occ = np.array([[-0.2, -0.2, 1.0], [0.2, -0.2, 1.0], [0.2, 0.2, 1.0], [-0.2, 0.2, 1.0]])
    p = np.array([[0.3, 0.0, 0.0], [0.35, 0.1, 0.0], [-0.3, 0.2, 0.0]])
    n = np.tile(np.float32([0, 0, 1]), (3, 1))

    def values(s):
        sc = js.Scene([js.PolygonLight((light * s).astype(F32), 1.0)], occluders=[(occ * s).astype(F32)])
        assert np.all(js.shadow_plan(sc, (p * s).astype(F32), n).lights[0].classes == vis.PENUMBRA)
        return np.asarray(js.irradiance(sc, (p * s).astype(F32), n))[:, 0]

    ref = values(1.0)
    assert np.all(ref > 0.05)
    np.testing.assert_allclose(values(scale), ref, rtol=1e-5)
