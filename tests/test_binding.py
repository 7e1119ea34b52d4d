"""The shadow engine's binding (`csrc/shadowc.cc`, `jaxshadow/_shadows/abi.py`, `binding.py`): one
interface definition, results that own their memory, inputs checked before the engine reads
them, the XLA FFI handlers against the host functions on the same inputs, and the fallbacks
(a stale build, a jaxlib other than the one the handlers were compiled against)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import types
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxshadow as js
from jaxshadow._shadows import abi, segment_pieces
from jaxshadow._shadows import binding as vis

ROOT = Path(__file__).resolve().parent.parent
built = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")
with_ffi = pytest.mark.skipif(not vis.ffi_available(), reason="the engine's XLA FFI handlers are not usable")


def _scene() -> js.Scene:
    """A quad light over a box (a convex solid), a free triangle and a thin slab (open faces)."""
    light = js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=1.0)
    tri = js.Mesh(np.array([[0.6, 0.1, 1.2], [0.9, 0.2, 1.3], [0.7, 0.5, 1.1]]), np.array([[0, 1, 2]]))
    return js.Scene([light], occluders=[js.Mesh.box([0.2, 0.2, 0.6], [0.5, 0.45, 0.9]), tri])


def _receivers(n: int = 96, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    p = np.c_[rng.uniform(-0.5, 1.5, (n, 2)), np.zeros(n)]
    return p, np.tile([0.0, 0.0, 1.0], (n, 1))


def _host(scene: js.Scene, dt) -> tuple[np.ndarray, vis.HostOccluders]:
    verts = np.asarray(scene.lights[0].vertices, dt)
    return verts, vis.HostOccluders.of(np.asarray(scene.occluders), scene.occluder_topology, dt)


# --------------------------------------------------------------------------------------
# One interface definition
# --------------------------------------------------------------------------------------


def _header_constant(name: str) -> int:
    m = re.search(rf"constexpr int {name} = (\d+);", (ROOT / "csrc" / "abi.h").read_text())
    assert m, name
    return int(m.group(1))


def test_the_interface_is_defined_once_in_the_header():
    """Python speaks the header's version and code width; the engine's literal widths are gone."""
    assert abi.ABI_VERSION == _header_constant("kAbiVersion")
    assert abi.CODE_WIDTH == vis.CODE_WIDTH == _header_constant("kCodeWidth")
    driver = (ROOT / "csrc" / "engine" / "driver.h").read_text()
    assert not re.search(r"\b14\b", driver), "driver.h: a literal run width (kRunWidth)"
    for f in (ROOT / "csrc").rglob("*.h"):
        assert "Python.h" not in f.read_text(), f"{f}: only shadowc.cc defines the module"


@built
def test_the_built_module_exports_the_header_interface():
    lib = vis._lib()
    assert lib.ABI_VERSION == _header_constant("kAbiVersion")
    assert lib.CODE_WIDTH == _header_constant("kCodeWidth")
    names = {n for n in dir(lib) if not n.startswith("__")}
    assert names == {"ABI_VERSION", "CODE_WIDTH", "HAS_FFI", "JAXLIB_VERSION", "Owned", "poly_plan", "hard_plan",
                     "segment_plan", "segment_pieces", "prepared_stats", "ffi_handlers"}
    if lib.HAS_FFI:
        assert set(lib.ffi_handlers()) == {vis.FFI_TARGET, vis.FFI_HARD, vis.FFI_SEGMENT, segment_pieces.FFI_PIECES}
    else:
        assert lib.ffi_handlers() == {}


def test_a_stale_build_is_refused():
    old = types.SimpleNamespace(ABI_VERSION=abi.ABI_VERSION - 1, CODE_WIDTH=abi.CODE_WIDTH, poly_plan=None,
                                __file__="old.so")
    assert "stale build" in abi.check(old)
    assert "not the engine's extension module" in abi.check(types.SimpleNamespace(__file__="pkg/_shadowc"))
    ok = types.SimpleNamespace(ABI_VERSION=abi.ABI_VERSION, CODE_WIDTH=abi.CODE_WIDTH, poly_plan=None, __file__="x")
    assert abi.check(ok) is None


@built
def test_another_build_loads_by_path(tmp_path):
    """`abi.load` takes any file name (the sanitizer build, the profiler's JAX-free driver)."""
    copy = tmp_path / "_shadowc_copy.so"
    shutil.copy(vis._lib().__file__, copy)
    mod = abi.load(str(copy))
    assert mod is not None and mod.__file__ == str(copy) and mod.ABI_VERSION == abi.ABI_VERSION


# --------------------------------------------------------------------------------------
# Host functions: owned results, checked inputs
# --------------------------------------------------------------------------------------


@built
@pytest.mark.parametrize("dt", [np.float32, np.float64])
def test_host_results_own_their_memory(dt):
    """Every result is an array over the engine's own allocation (no copy), distinct per call,
    writable, and alive after the call's other results are gone."""
    scene = _scene()
    verts, occ = _host(scene, dt)
    p, n = _receivers()
    a = vis.polygon_codes(p, n, verts, occ, codes=True, decoded=True, lambert=True)
    assert np.any(a.classes == vis.PENUMBRA) and a.runs.shape[0] > 0
    for arr in (a.classes, a.stats, a.offsets, a.runs, a.points, a.lambert):
        assert type(arr.base.obj).__name__ == "Owned" and arr.flags.c_contiguous and arr.flags.writeable
    assert a.points.dtype == dt and a.runs.dtype == np.int32 and a.offsets.dtype == np.int64
    runs = a.runs
    want = runs.copy()
    del a
    b = vis.polygon_codes(p, n, verts, occ, codes=True)
    np.testing.assert_array_equal(runs, want)
    assert not np.shares_memory(runs, b.runs)
    vis_ = vis.hard_visibility(p, verts.mean(axis=0), True, occ)
    off, faces = vis.segment_candidates(p, verts[0], verts[2], occ)
    assert vis_.dtype == bool and off.dtype == np.int64 and faces.dtype == np.int32 and len(faces) == off[-1]
    assert type(faces.base.obj).__name__ == "Owned"


@built
def test_host_inputs_are_checked_before_the_engine_reads_them():
    lib = vis._lib()
    scene = _scene()
    verts, occ = _host(scene, np.float64)
    p, n = _receivers(8)
    args = occ.args()
    with pytest.raises(TypeError, match="float64"):
        lib.poly_plan(p.astype(np.float32), n, verts, args, 1, True, False, False)
    with pytest.raises(TypeError, match="C-contiguous"):
        lib.poly_plan(np.asfortranarray(np.c_[p, p])[:, :3], n, verts, args, 1, True, False, False)
    with pytest.raises(ValueError, match="differ in length"):
        lib.poly_plan(p, n[:5], verts, args, 1, True, False, False)
    with pytest.raises(ValueError, match="topology"):
        lib.poly_plan(p, n, verts, (args[0], args[1][:-1], *args[2:]), 1, True, False, False)
    with pytest.raises(TypeError, match="int32"):
        lib.hard_plan(p, verts[0], True, (args[0], args[1].astype(np.int64), *args[2:]), 1)
    with pytest.raises(TypeError, match="tuple"):
        lib.segment_plan(p, verts[0], verts[2], list(args), 1)
    with pytest.raises(ValueError, match="x must have 3 coordinates"):
        lib.hard_plan(p, verts[:2], True, args, 1)
    with pytest.raises(ValueError, match="b must have 3 coordinates"):
        lib.segment_plan(p, verts[0], verts[:2], args, 1)
    with pytest.raises(TypeError, match="light must be float64"):
        lib.poly_plan(p, n, verts.astype(np.float32), args, 1, True, False, False)
    with pytest.raises(ValueError, match="rows of 3"):
        lib.segment_plan(p, verts[0].ravel()[:2].copy(), verts[2], args, 1)
    with pytest.raises(ValueError, match="64 vertices"):
        many = np.c_[np.cos(np.linspace(0, 2 * np.pi, 70, endpoint=False)),
                     np.sin(np.linspace(0, 2 * np.pi, 70, endpoint=False)), np.full(70, 2.0)][::-1].copy()
        lib.poly_plan(p, n, many, args, 1, True, False, False)


# --------------------------------------------------------------------------------------
# The XLA FFI handlers against the host functions
# --------------------------------------------------------------------------------------


@with_ffi
@pytest.mark.parametrize("dt", [np.float32, np.float64])
def test_ffi_handlers_match_the_host_functions(dt):
    """Inside a compiled program the handlers give the host functions' classes, codes, hard
    visibility and segment candidates on the same inputs (codes truncated at the capacity)."""
    scene = _scene()
    verts, occ = _host(scene, dt)
    faces, topo = occ.faces, scene.occluder_topology
    p, n = (x.astype(dt) for x in _receivers())
    host = vis.polygon_codes(p, n, verts, occ, codes=True)
    cap = 6
    cls, cnt, runs = (np.asarray(x) for x in jax.jit(vis.traced_polygon_codes, static_argnums=(4, 5))(
        jnp.asarray(p), jnp.asarray(n), jnp.asarray(verts), jnp.asarray(faces), topo, cap))
    np.testing.assert_array_equal(cls, host.classes)
    pen = cls == vis.PENUMBRA  # the host plan keeps the boundary of penumbra receivers only
    np.testing.assert_array_equal(cnt[pen], host.counts[pen])
    assert np.any(cnt[pen] > cap) and np.any(cnt[pen] <= cap)
    for i in np.flatnonzero(pen):
        k = min(int(cnt[i]), cap)
        np.testing.assert_array_equal(runs[i, :k], host.runs[host.offsets[i]:host.offsets[i] + k])
        assert np.all(runs[i, k:, :, 0] == vis.K_UNUSED)
    for x, is_point in ((verts.mean(axis=0), True), (np.array([0.1, 0.2, -1.0], dt), False)):
        traced = jax.jit(vis.traced_hard_visibility, static_argnums=(2, 4))(jnp.asarray(p), jnp.asarray(x), is_point,
                                                                            jnp.asarray(faces), topo)
        np.testing.assert_array_equal(np.asarray(traced) == 1, vis.hard_visibility(p, x, is_point, occ))
    off, cand = vis.segment_candidates(p, verts[0], verts[2], occ)
    scnt, scand = (np.asarray(x) for x in jax.jit(vis.traced_segment_candidates, static_argnums=(4, 5))(
        jnp.asarray(p), jnp.asarray(verts[0]), jnp.asarray(verts[2]), jnp.asarray(faces), topo, 8))
    np.testing.assert_array_equal(scnt, np.diff(off))
    for i in range(len(p)):
        k = min(int(scnt[i]), 8)
        np.testing.assert_array_equal(scand[i, :k], cand[off[i]:off[i] + k])


def _assert_codes_match_host(cls, cnt, p, n, verts, occ) -> None:
    host = vis.polygon_codes(p, n, verts, occ, codes=True)
    np.testing.assert_array_equal(cls, host.classes)
    pen = host.classes == vis.PENUMBRA
    assert np.any(pen)
    np.testing.assert_array_equal(cnt[pen], host.counts[pen])


@with_ffi
@pytest.mark.parametrize("dt", [np.float32, np.float64])
def test_ffi_handlers_batch_under_vmap(dt):
    """Under `vmap` (vmap_method="expand_dims": an input not batched along an axis comes with a
    size-1 axis there) each batch element is the host call for its own inputs: over the light,
    over the occluders (a moved mesh, the receivers shared), and nested (lights outer, receiver sets
    inner: each input batched along one axis only); hard shadows, segment candidates and segment
    pieces over the light."""
    scene = _scene()
    verts, occ = _host(scene, dt)
    p, n = _receivers(40)
    p, n = p.astype(dt), n.astype(dt)
    topo = scene.occluder_topology
    faces = jnp.asarray(occ.faces)
    shifts = np.array([[0.0, 0.0, 0.0], [0.3, -0.2, 0.1], [-0.1, 0.25, -0.2]], dt)

    def codes(pp, v, ff):
        return vis.traced_polygon_codes(pp, jnp.asarray(n), v, ff, topo, 32)

    over_light = jax.jit(jax.vmap(lambda v: codes(jnp.asarray(p), v, faces)))
    cls, cnt, _ = (np.asarray(x) for x in over_light(jnp.asarray(verts[None] + shifts[:, None])))
    for b, sh in enumerate(shifts):
        _assert_codes_match_host(cls[b], cnt[b], p, n, verts + sh, occ)

    over_faces = jax.jit(jax.vmap(lambda ff: codes(jnp.asarray(p), jnp.asarray(verts), ff)))
    cls, cnt, _ = (np.asarray(x) for x in over_faces(faces[None] + 0.5 * shifts[:, None, None]))
    for b, sh in enumerate(shifts):
        moved = vis.HostOccluders.of(occ.faces + 0.5 * sh, topo, dt)
        _assert_codes_match_host(cls[b], cnt[b], p, n, verts, moved)

    sets = np.stack([p, p[::-1] + np.array([0.05, -0.05, 0.0], dt)])
    nested = jax.jit(jax.vmap(lambda v: jax.vmap(lambda pp: codes(pp, v, faces))(jnp.asarray(sets))))
    cls, cnt, _ = (np.asarray(x) for x in nested(jnp.asarray(verts[None] + shifts[:, None])))
    assert cls.shape == (len(shifts), len(sets), len(p))
    for b, sh in enumerate(shifts):
        for j, q in enumerate(sets):
            _assert_codes_match_host(cls[b, j], cnt[b, j], q, n, verts + sh, occ)

    lamps = verts.mean(axis=0)[None] + shifts
    vis_fn = jax.jit(jax.vmap(lambda x: vis.traced_hard_visibility(jnp.asarray(p), x, True, faces, topo)))
    visible = np.asarray(vis_fn(jnp.asarray(lamps)))
    for b, x in enumerate(lamps):
        np.testing.assert_array_equal(visible[b] == 1, vis.hard_visibility(p, x, True, occ))
    assert np.any(visible == 0) and np.any(visible == 1)
    seg_fn = jax.jit(jax.vmap(lambda a: vis.traced_segment_candidates(jnp.asarray(p), a, a + verts[2] - verts[0],
                                                                      faces, topo, 8)))
    scnt, scand = (np.asarray(x) for x in seg_fn(jnp.asarray(verts[0][None] + shifts)))
    for b, sh in enumerate(shifts):
        off, cand = vis.segment_candidates(p, verts[0] + sh, verts[2] + sh, occ)
        np.testing.assert_array_equal(scnt[b], np.diff(off))
        assert np.any(scnt[b] > 0)
        for i in range(len(p)):
            k = min(int(scnt[b, i]), 8)
            np.testing.assert_array_equal(scand[b, i, :k], cand[off[i]:off[i] + k])

    pieces_fn = jax.jit(jax.vmap(lambda a: segment_pieces.traced_pieces(jnp.asarray(p), a, a + verts[2] - verts[0],
                                                                        faces, topo, 8)))
    pcls, pcnt, pcodes = (np.asarray(x) for x in pieces_fn(jnp.asarray(verts[0][None] + shifts)))
    for b, sh in enumerate(shifts):
        hcls, _, hoff, hcodes = segment_pieces.host_pieces(p, verts[0] + sh, verts[2] + sh, occ)
        np.testing.assert_array_equal(pcls[b], hcls)
        np.testing.assert_array_equal(pcnt[b], np.diff(hoff))
        assert np.any(hcls == 3)
        for i in range(len(p)):
            k = min(int(pcnt[b, i]), 8)
            np.testing.assert_array_equal(pcodes[b, i, :k], hcodes[hoff[i]:hoff[i] + k])


@with_ffi
def test_traced_irradiance_through_the_handlers_matches_the_host_path(monkeypatch):
    """`js.irradiance` on traced receivers (the FFI handlers) against concrete ones (the host
    functions), float64: the same regions, integrated in another order."""
    scene = _scene()
    p, n = _receivers(64)
    host = np.asarray(js.irradiance(scene, p, n))
    calls = []
    traced_codes = vis.traced_polygon_codes
    monkeypatch.setattr(vis, "traced_polygon_codes", lambda *a: calls.append(1) or traced_codes(*a))
    traced = np.asarray(jax.jit(lambda q: js.irradiance(scene, q, jnp.asarray(n)))(jnp.asarray(p)))
    assert calls, "the traced path did not go through the FFI handlers"
    free = np.asarray(js.irradiance(js.Scene(list(scene.lights)), p, n))
    assert np.any(host < 0.99 * free)  # some receivers are shadowed
    np.testing.assert_allclose(traced, host, rtol=1e-12, atol=1e-15)


# --------------------------------------------------------------------------------------
# Fallbacks
# --------------------------------------------------------------------------------------


_OTHER_JAXLIB = """
import json, warnings
import numpy as np
import jax
import jaxlib.version
jaxlib.version.__version__ = "0.0.0-other"  # as if the handlers had been compiled for another jaxlib
jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import jaxshadow as js
from jaxshadow._shadows import binding as vis
from jaxshadow._shadows import segment_pieces

quad = js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=1.0)
scene = js.Scene([quad], occluders=[js.Mesh.box([0.3, 0.3, 0.8], [0.6, 0.5, 1.0])])
p = np.array([[0.45, 0.4, 0.0], [0.2, 0.9, 0.0], [3.0, 0.0, 0.0]])
n = np.tile([0.0, 0.0, 1.0], (3, 1))
f = jax.jit(lambda q: js.irradiance(scene, q, jnp.asarray(n)))
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    a = np.asarray(f(jnp.asarray(p)))
    b = np.asarray(jax.jit(lambda q: js.irradiance(scene, q, jnp.asarray(n)) * 1.0)(jnp.asarray(p)))
host = np.asarray(js.irradiance(scene, p, n))
dev = np.asarray(js.irradiance(scene, p, n, shadows=js.ShadowOptions(engine="device")))
print(json.dumps({"a": a.tolist(), "b": b.tolist(), "dev": dev.tolist(), "host": host.tolist(),
                  "ffi": vis.ffi_available(), "engine": vis.engine_available(),
                  "warnings": [str(w.message) for w in caught]}))
"""


@built
def test_handlers_for_another_jaxlib_fall_back_to_the_device_kernels_with_one_warning():
    out = subprocess.run([sys.executable, "-c", _OTHER_JAXLIB], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["engine"] and not r["ffi"]  # the host functions stay in use
    assert r["a"] == r["dev"] == r["b"]
    np.testing.assert_allclose(r["a"], r["host"], rtol=1e-12)
    assert len(r["warnings"]) == 1 and "compiled against jaxlib" in r["warnings"][0], r["warnings"]
