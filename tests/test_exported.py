"""Fit programs stored traced (`inverse._exported`): keys, export, the store."""

import functools
import importlib.util

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxshadow as js
from inverse import _exported as ex
from inverse._forward import traced_specular
from inverse._material import _spec_eval
from inverse._targets import PaintedTargets

RAW_SPEC = _spec_eval.__wrapped__  # the function under fit_jit


def _problem(n=6, capacity_shift=0.0):
    light = js.PolygonLight(np.array([[0.0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]]), radiance=2.0)
    occ = np.array([[0.2, 0.2, 1.0 + capacity_shift], [0.7, 0.2, 1.0], [0.7, 0.7, 1.0]])
    scene = js.Scene([light], occluders=[occ], ambient=0.1)
    rng = np.random.default_rng(0)
    points = np.c_[rng.uniform(-0.5, 1.5, (n, 2)), np.zeros(n)]
    normals = np.tile([0.0, 0.0, 1.0], (n, 1))
    targets = PaintedTargets(points, normals, np.ones((n, 3)), np.array([0.5, -2.0, 2.0]))
    return scene, targets


def _key(*args, options=None, fun=RAW_SPEC):
    return ex.program_key(fun, options or {"xla_backend_optimization_level": 0}, args, {})[0]


def test_key_follows_shapes_static_values_and_options_not_array_values():
    jax.config.update("jax_enable_x64", True)
    scene, t = _problem()
    e = jnp.asarray([1.0, 2.0, 4.0, 8.0], jnp.float64)
    k = _key(traced_specular, scene, t, e)
    assert _key(traced_specular, scene, t, 2 * e) == k  # values are arguments of the program
    scene2, t2 = _problem(capacity_shift=0.1)
    assert _key(traced_specular, scene2, t2, e) == k  # so are the scene's arrays
    assert _key(traced_specular, scene, t, e[:3]) != k  # shapes are not
    assert _key(traced_specular, *_problem(n=7), e) != k
    assert _key(traced_specular, scene, t, e.astype(jnp.float32)) != k  # nor dtypes
    assert _key(traced_specular, scene, t, e, options={"xla_backend_optimization_level": 1}) != k
    other = functools.partial(traced_specular)
    assert _key(other, scene, t, e) != k  # static callables are part of the key


def test_key_refuses_what_it_cannot_describe():
    scene, t = _problem()
    e = jnp.ones(4)
    with pytest.raises(ex.Unsupported):
        _key(lambda *a: None, scene, t, e)  # a function of no package of ours: its code is not keyed
    with pytest.raises(ex.Unsupported):
        _key(traced_specular, scene, t, e, fun=lambda *a: a)  # a local function as the program

    class Opaque:
        pass

    with pytest.raises(ex.Unsupported):
        _key(Opaque(), scene, t, e)


def _exported_spec() -> tuple:
    """`(key, leaves, arrays, program, opts, (scene, t, e))`: the specular program exported at -O0."""
    jax.config.update("jax_enable_x64", True)
    scene, t = _problem()
    e = jnp.asarray([1.0, 3.0, 10.0, 30.0], jnp.float64)
    opts = {"xla_backend_optimization_level": 0}
    key, leaves, treedef, arrays = ex.program_key(RAW_SPEC, opts, (traced_specular, scene, t, e), {})
    return key, leaves, arrays, ex.export_program(RAW_SPEC, opts, leaves, treedef, arrays), opts, (scene, t, e)


def test_exported_program_gives_the_jitted_values():
    key, leaves, arrays, prog, opts, (scene, t, e) = _exported_spec()
    got = prog([leaves[i] for i in arrays])
    want = jax.jit(lambda sc, tt, ee: RAW_SPEC(traced_specular, sc, tt, ee), compiler_options=opts)(scene, t, e)
    for a, b in zip(jax.tree_util.tree_leaves(got), jax.tree_util.tree_leaves(want), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert float(np.max(np.abs(np.asarray(got[0])))) > 0  # the specular term is not trivially zero


def test_outputs_other_than_arrays_in_plain_containers_are_refused():
    leaves, treedef = jax.tree_util.tree_flatten((1.0, [2.0, {"a": 3.0}]))
    ex._check_plain(treedef)
    light = js.PointLight([0.0, 0.0, 1.0], 1.0)
    with pytest.raises(ex.Unsupported):
        ex._check_plain(jax.tree_util.tree_structure(light))


@pytest.mark.skipif(importlib.util.find_spec("flatbuffers") is None, reason="jax.export serialises with flatbuffers")
def test_store_round_trip(tmp_path):
    key, leaves, arrays, prog, opts, _ = _exported_spec()
    path = str(tmp_path / f"{key}.bin")
    ex.save(path, prog)
    loaded = ex.load(path, opts)
    assert loaded is not None
    a, b = prog([leaves[i] for i in arrays]), loaded([leaves[i] for i in arrays])
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    (tmp_path / "bad.bin").write_bytes(b"not a program")
    assert ex.load(str(tmp_path / "bad.bin"), opts) is None


def test_key_follows_the_code_the_engine_and_jax(monkeypatch):
    scene, t = _problem()
    e = jnp.ones(4)
    k = _key(traced_specular, scene, t, e)
    assert _key(traced_specular, scene, t, e) == k
    with monkeypatch.context() as m:
        m.setattr(ex, "_sources_digest", lambda: "0" * 64)  # another inverse/jaxshadow source or engine build
        assert _key(traced_specular, scene, t, e) != k
    with monkeypatch.context() as m:
        m.setattr(jax, "__version__", "0.0.1")
        assert _key(traced_specular, scene, t, e) != k
    with monkeypatch.context() as m:
        m.setattr(ex, "_jaxlib_version", lambda: "0.0.1")
        assert _key(traced_specular, scene, t, e) != k


def test_tree_digest_follows_sources_and_extensions(tmp_path):
    root = tmp_path / "pkg"
    (root / "sub").mkdir(parents=True)
    (root / "a.py").write_text("x = 1\n")
    (root / "sub" / "_engine.so").write_bytes(b"\x7fELF one")
    (root / "notes.txt").write_text("not code")
    d0 = ex.tree_digest([root])
    (root / "notes.txt").write_text("still not code")
    assert ex.tree_digest([root]) == d0
    (root / "sub" / "_engine.so").write_bytes(b"\x7fELF two")  # a rebuilt engine
    d1 = ex.tree_digest([root])
    assert d1 != d0
    (root / "a.py").write_text("x = 2\n")  # an edited source
    d2 = ex.tree_digest([root])
    assert d2 not in (d0, d1)
    (root / "a.py").rename(root / "b.py")  # the same contents under another name
    assert ex.tree_digest([root]) != d2


@pytest.mark.skipif(importlib.util.find_spec("flatbuffers") is None, reason="jax.export serialises with flatbuffers")
def test_fit_jit_gives_the_same_values_with_the_store_on_and_off(tmp_path, monkeypatch):
    """A `fit_jit` program through the store (exported in one call, loaded in a later one) and
    without it (`JAXSHADOW_EXPORT_CACHE=off`): bit-identical outputs."""
    from inverse._lm import ONCE_COMPILER_OPTIONS, fit_jit

    scene, t = _problem()
    e = jnp.asarray([1.0, 3.0, 10.0, 30.0], jnp.float64)
    monkeypatch.setenv(ex.ENV, "off")
    off = fit_jit(RAW_SPEC, options=ONCE_COMPILER_OPTIONS)(traced_specular, scene, t, e)
    monkeypatch.delenv(ex.ENV)
    monkeypatch.setattr(ex, "store_dir", lambda: str(tmp_path))
    first = fit_jit(RAW_SPEC, options=ONCE_COMPILER_OPTIONS)(traced_specular, scene, t, e)  # exported, stored
    assert len(list(tmp_path.glob("*.bin"))) == 1
    again = fit_jit(RAW_SPEC, options=ONCE_COMPILER_OPTIONS)(traced_specular, scene, t, e)  # loaded
    for out in (first, again):
        for a, b in zip(jax.tree_util.tree_leaves(out), jax.tree_util.tree_leaves(off), strict=True):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
