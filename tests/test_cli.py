"""The `jaxshadow` command: batched irradiance and the fit command (plumbing; the accuracy of
the fits against Mitsuba targets is tested in test_inverse.py)."""

import os

import numpy as np

import inverse
import jaxshadow as js
from jaxshadow.cli import builtin_scene_path, main


def test_irradiance_command_matches_the_library(tmp_path):
    rng = np.random.default_rng(0)
    pts = np.c_[rng.uniform(-1, 1, (37, 2)), np.zeros(37)]
    nrm = np.tile([0.0, 0.0, 1.0], (37, 1))
    np.savetxt(tmp_path / "pts.csv", np.c_[pts, nrm], delimiter=",")
    out = tmp_path / "e.npy"
    rc = main(["--no-compile-cache", "irradiance", builtin_scene_path("room"), str(tmp_path / "pts.csv"), "-o", str(out), "--chunk", "16", "--float64"])
    assert rc == 0
    got = np.load(out)
    ref = np.asarray(js.irradiance(js.load_scene(builtin_scene_path("room")), pts, nrm))
    np.testing.assert_allclose(got, ref, rtol=1e-12)


def test_irradiance_command_rejects_bad_points(tmp_path, capsys):
    np.savetxt(tmp_path / "bad.csv", np.zeros((3, 4)), delimiter=",")
    try:
        main(["--no-compile-cache", "irradiance", builtin_scene_path("room"), str(tmp_path / "bad.csv"), "-o", str(tmp_path / "o.npy")])
    except SystemExit as err:
        assert "expected N rows of 6 columns" in str(err)
    else:  # pragma: no cover
        raise AssertionError("bad point file accepted")


def _write_fit_inputs(tmp_path):
    """`scene.json` (the room's first light) and `t.json` (20 floor targets of a known material)."""
    scene = js.Scene(js.load_scene(builtin_scene_path("room")).lights[:1], ambient=0.1)
    js.save_scene(scene, tmp_path / "scene.json")
    rng = np.random.default_rng(1)
    p = np.c_[rng.uniform(-1, 1, (20, 2)), np.zeros(20)]
    n = np.tile([0.0, 0.0, 1.0], (20, 1))
    eye = np.array([0.3, -1.5, 1.5])
    truth = js.Material(ka=0.2, kd=[0.5, 0.4, 0.3], ks=0.3, exponent=20.0)
    inverse.PaintedTargets(p, n, np.asarray(js.shade(scene, truth, p, n, eye)), eye).save(tmp_path / "t.json")


def test_fit_command_writes_the_fitted_material(tmp_path):
    _write_fit_inputs(tmp_path)
    assert main(["--no-compile-cache", "fit", str(tmp_path / "scene.json"), str(tmp_path / "t.json"), "-o", str(tmp_path / "f.json")]) == 0
    fitted = js.load_material(tmp_path / "f.json")
    np.testing.assert_allclose(np.asarray(fitted.kd), [0.5, 0.4, 0.3], atol=1e-6)
    np.testing.assert_allclose(float(fitted.exponent), 20.0, rtol=1e-5)


def test_fit_command_passes_combinatorics(tmp_path, monkeypatch):
    """`jaxshadow fit --light 0 --combinatorics host` asks `fit_light` for host combinatorics
    (stubbed here: the light fit itself is tested in test_inverse / test_clip_host); an unknown
    value is refused by the parser."""
    import inverse._cli as icli

    _write_fit_inputs(tmp_path)
    seen = {}

    def fake_fit_light(scene, targets, material, light_index=0, **kw):
        seen.update(kw, light_index=light_index)
        raise ValueError("stub")  # main() reports ValueErrors with exit status 2

    monkeypatch.setattr(icli, "fit_light", fake_fit_light)
    args = ["--no-compile-cache", "fit", str(tmp_path / "scene.json"), str(tmp_path / "t.json"),
            "-o", str(tmp_path / "f.json"), "--light", "0"]
    assert main([*args, "--combinatorics", "host"]) == 2
    assert seen == {"light_index": 0, "solver": inverse.LM(combinatorics="host")}
    seen.clear()
    assert main(args) == 2
    assert seen["solver"].combinatorics == "auto"
    try:
        main([*args, "--combinatorics", "gpu"])
    except SystemExit as err:
        assert err.code == 2
    else:  # pragma: no cover
        raise AssertionError("unknown --combinatorics accepted")


def test_compile_cache_option(tmp_path, monkeypatch):
    """`--compile-cache DIR` turns on JAX's persistent cache there (programs taking >= 0.2 s to
    compile are written); the option is reset afterwards so other tests are unaffected."""
    import jax
    from jax.experimental.compilation_cache import compilation_cache

    from jaxshadow.cli import enable_compile_cache

    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    try:
        d = enable_compile_cache(str(tmp_path / "xla"))
        assert os.path.isdir(d) and jax.config.jax_compilation_cache_dir == d
    finally:
        jax.config.update("jax_compilation_cache_dir", None)
        compilation_cache.reset_cache()
