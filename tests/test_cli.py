"""The `jaxshadow` command: its conventions (issue 20 item 6: --version, help texts, one CSV
convention, formats by extension, the output path exactly as given, checks before computing,
atomic outputs, exit codes), batched irradiance and the fit command (plumbing; the accuracy of
the fits against Mitsuba targets is tested in test_inverse.py)."""

import ast
import os
import signal
import subprocess
import sys
import time
from importlib import metadata

import numpy as np
import pytest

import inverse
import jaxshadow as js
import jaxshadow.cli as cli
from jaxshadow.cli import build_parser, builtin_scene_path, main

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
NC = "--no-compile-cache"
ROOM = builtin_scene_path("room")


def _points_csv(path, n=37, seed=0):
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    with open(path, "w") as fh:
        fh.write("px,py,pz,nx,ny,nz,label\n")
        for p, q in zip(pts, nrm, strict=True):
            fh.write(",".join(repr(float(x)) for x in (*p, *q)) + ",7\n")
    return pts, nrm


def _run(argv, capsys):
    """(exit code, stderr) of `main(argv)`, argparse's SystemExit included."""
    try:
        rc = main(argv)
    except SystemExit as err:
        rc = err.code
    return rc, capsys.readouterr().err


def test_irradiance_command_matches_the_library(tmp_path):
    pts, nrm = _points_csv(tmp_path / "pts.csv")
    ref = np.asarray(js.irradiance(js.load_scene(ROOM), pts, nrm))
    for name in ("e.npy", "e.csv", "e.npz", "E"):
        out = tmp_path / name
        rc = main([NC, "irradiance", ROOM, str(tmp_path / "pts.csv"), "-o", str(out), "--chunk", "16", "--float64", "-q"])
        if name == "E":
            assert rc == 2 and not out.exists()
            continue
        assert rc == 0
        assert not [f for f in os.listdir(tmp_path) if f.startswith(".")]  # no temporary file left
        if name.endswith(".npy"):
            got = np.load(out)
        elif name.endswith(".npz"):
            got = np.load(out)["values"]
        else:
            with open(out) as fh:
                header = fh.readline().strip()
            assert header == "px,py,pz,nx,ny,nz,r,g,b"
            got = np.loadtxt(out, delimiter=",", skiprows=1)[:, 6:]
        np.testing.assert_allclose(got, ref, rtol=1e-12)
    assert not (tmp_path / "e.npy.npy").exists()


def test_output_path_is_exactly_the_given_one(tmp_path, capsys):
    """`-o E.txt` used to write `E.txt.npy`: now an unknown extension is a usage error (exit 2)
    and a known one is written at exactly that path."""
    _points_csv(tmp_path / "pts.csv", n=5)
    rc, err = _run([NC, "irradiance", ROOM, str(tmp_path / "pts.csv"), "-o", str(tmp_path / "E.txt")], capsys)
    assert rc == 2 and "unknown format '.txt'" in err and "expected .npy, .npz, .csv, .ply" in err
    assert os.listdir(tmp_path) == ["pts.csv"]
    assert main([NC, "irradiance", ROOM, str(tmp_path / "pts.csv"), "-o", str(tmp_path / "E.NPY"), "-q"]) == 0
    assert sorted(os.listdir(tmp_path)) == ["E.NPY", "pts.csv"]


def test_version(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0
    assert capsys.readouterr().out.strip() == f"jaxshadow {metadata.version('jaxshadow')}"


def test_every_option_has_help_text():
    parser = build_parser()
    subs = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    assert {"irradiance", "render", "report", "fit", "demo"} <= set(subs.choices)
    names = {a.dest: a.help for a in subs._choices_actions}
    for name, sp in [("jaxshadow", parser), *subs.choices.items()]:
        if name != "jaxshadow":
            assert names.get(name), f"command {name} has no help"
        for action in sp._actions:
            if action.dest in ("help", "cmd"):
                continue
            assert action.help and len(action.help) > 8, f"{name}: option {action.option_strings or action.dest} has no help"
    assert "Exit codes" in parser.description and "2 usage error" in parser.description


def test_headerless_csv_and_unknown_formats_are_usage_errors(tmp_path, capsys):
    np.savetxt(tmp_path / "bare.csv", np.zeros((3, 6)), delimiter=",")
    rc, err = _run([NC, "irradiance", ROOM, str(tmp_path / "bare.csv"), "-o", str(tmp_path / "o.npy")], capsys)
    assert rc == 2 and "missing CSV column(s) ['px', 'py', 'pz', 'nx', 'ny', 'nz']" in err and "header" in err
    (tmp_path / "p.txt").write_text("1,2,3\n")
    rc, err = _run([NC, "irradiance", ROOM, str(tmp_path / "p.txt"), "-o", str(tmp_path / "o.npy")], capsys)
    assert rc == 2 and "points" in err and "unknown format '.txt'" in err
    np.save(tmp_path / "p4.npy", np.zeros((3, 4)))
    rc, err = _run([NC, "irradiance", ROOM, str(tmp_path / "p4.npy"), "-o", str(tmp_path / "o.npy")], capsys)
    assert rc == 2 and "expected an (N, 6) array" in err
    rc, err = _run([NC, "irradiance", str(tmp_path / "missing.json"), str(tmp_path / "p4.npy"), "-o", str(tmp_path / "o.npy")], capsys)
    assert rc == 2 and "no such file" in err
    _points_csv(tmp_path / "pts.csv", n=4)
    rc, err = _run([NC, "irradiance", ROOM, str(tmp_path / "pts.csv"), "-o", str(tmp_path / "o.ply")], capsys)
    assert rc == 2 and "a .ply output needs mesh receivers" in err
    assert not (tmp_path / "o.npy").exists() and not (tmp_path / "o.ply").exists()


@pytest.mark.parametrize("chunk", ["-5", "0", "x"])
def test_chunk_must_be_positive(tmp_path, capsys, chunk):
    """Issue 25 row 4: `--chunk -5` exited 0 writing uninitialised memory, `--chunk 0` raised
    `range() arg 3 must not be zero`. Now a usage error naming the option, nothing written."""
    _points_csv(tmp_path / "pts.csv", n=4)
    rc, err = _run([NC, "irradiance", ROOM, str(tmp_path / "pts.csv"), "-o", str(tmp_path / "o.npy"), "--chunk", chunk], capsys)
    assert rc == 2
    assert f"argument --chunk: must be a positive integer, got '{chunk}'" in err
    assert os.listdir(tmp_path) == ["pts.csv"]


def test_arguments_are_checked_before_any_computation(tmp_path, capsys, monkeypatch):
    def forbidden(*args, **kw):
        raise AssertionError("computed before the arguments were checked")

    monkeypatch.setattr(js, "irradiance", forbidden)
    _points_csv(tmp_path / "pts.csv", n=4)
    rc, err = _run([NC, "irradiance", ROOM, str(tmp_path / "pts.csv"), "-o", str(tmp_path / "no" / "dir" / "o.npy")], capsys)
    assert rc == 2 and "does not exist" in err
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        if not os.access(ro, os.W_OK):  # root can write anywhere
            rc, err = _run([NC, "irradiance", ROOM, str(tmp_path / "pts.csv"), "-o", str(ro / "o.npy")], capsys)
            assert rc == 2 and "not writable" in err
    finally:
        ro.chmod(0o700)
    rc, err = _run([NC, "irradiance", ROOM, str(tmp_path / "pts.csv"), "-o", str(tmp_path)], capsys)
    assert rc == 2 and "unknown format" in err
    rc, err = _run([NC, "report", "--out", str(tmp_path / "a" / "b")], capsys)
    assert rc == 2 and "does not exist" in err


def test_failing_run_keeps_the_old_output_and_exits_1(tmp_path, capsys, monkeypatch):
    """Issue 25 row 5 (CLI part): outputs are written to a temporary file renamed into place, so
    a run that fails leaves the previous output intact; an unexpected exception is an internal
    error (exit 1), reported as such."""
    _points_csv(tmp_path / "pts.csv", n=40)
    out = tmp_path / "o.csv"
    out.write_text("old results\n")
    calls = []

    def fails_on_second_chunk(scene, p, n):
        calls.append(len(p))
        if len(calls) == 2:
            raise RuntimeError("boom")
        return np.zeros((len(p), 3))

    monkeypatch.setattr(js, "irradiance", fails_on_second_chunk)
    rc, err = _run([NC, "irradiance", ROOM, str(tmp_path / "pts.csv"), "-o", str(out), "--chunk", "16"], capsys)
    assert rc == 1 and "internal error: RuntimeError: boom" in err
    assert out.read_text() == "old results\n"
    assert sorted(os.listdir(tmp_path)) == ["o.csv", "pts.csv"]


def test_killed_run_leaves_no_partial_output(tmp_path):
    """`kill -9` in the middle of `jaxshadow irradiance`: the old output is intact and no
    partial or temporary file is left beside it."""
    n = 30_000
    rng = np.random.default_rng(3)
    a = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n), np.tile([0.0, 0.0, 1.0], (n, 1))]
    np.save(tmp_path / "pts.npy", a)
    out = tmp_path / "e.npy"
    out.write_bytes(b"previous")
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([ROOT, os.environ.get("PYTHONPATH", "")]))
    proc = subprocess.Popen(
        [sys.executable, "-m", "jaxshadow.cli", NC, "irradiance", ROOM, str(tmp_path / "pts.npy"), "-o", str(out),
         "--chunk", "300", "--float64"], stderr=subprocess.PIPE, text=True, env=env)
    lines = []
    t0 = time.monotonic()
    while time.monotonic() - t0 < 120:
        line = proc.stderr.readline()
        lines.append(line)
        if "irradiance:  10%" in line or not line:
            break
    assert proc.poll() is None, "".join(lines)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    proc.stderr.close()
    assert "irradiance:  10%" in lines[-1] and "\r" not in "".join(lines)  # plain lines in a pipe
    assert out.read_bytes() == b"previous"
    assert sorted(os.listdir(tmp_path)) == ["e.npy", "pts.npy"]


def _progress_lines(err):
    """(percent, done, total) of each plain progress line."""
    import re

    return [tuple(int(x) for x in re.match(r"\w+: +(\d+)% \((\d+)/(\d+)\)", line).groups())
            for line in err.splitlines()]


def test_progress_is_plain_lines_off_a_terminal(capsys):
    bar = cli.Progress(100, "work")
    for _ in range(20):
        bar.update(5)
    bar.close()
    err = capsys.readouterr().err
    # the first update, then one line per tenth reached
    assert "\r" not in err and err.count("\n") == 11 and err.startswith("work:   5% (5/100)") and "work: 100% (100/100)" in err
    quiet = cli.Progress(100, "work", quiet=True)
    quiet.update(100)
    assert capsys.readouterr().err == ""


def test_progress_lines_state_the_true_count(capsys):
    # Uneven blocks: each line's percentage is its own count's, never "20% (262144/1000000)".
    bar = cli.Progress(1_000_000, "irradiance")
    for n in (262144, 262144, 262144, 213568):
        bar.update(n)
    lines = _progress_lines(capsys.readouterr().err)
    assert [line[1] for line in lines] == [262144, 524288, 786432, 1000000]
    for pct, done, total in lines:
        assert pct == 100 * done // total


def test_irradiance_progress_from_the_first_chunk(tmp_path, capsys):
    _points_csv(tmp_path / "pts.csv", n=40)
    rc = main([NC, "irradiance", ROOM, str(tmp_path / "pts.csv"), "-o", str(tmp_path / "e.npy"), "--chunk", "16"])
    assert rc == 0
    lines = _progress_lines("\n".join(x for x in capsys.readouterr().err.splitlines() if x.startswith("irradiance:")))
    assert [line[1] for line in lines] == [16, 32, 40]


def test_short_version_flag_and_plain_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["-V"])
    assert exc.value.code == 0 and capsys.readouterr().out.strip() == f"jaxshadow {metadata.version('jaxshadow')}"
    parser = build_parser()
    text = parser.format_help()
    assert "`" not in text and "Exit codes" in text
    subs = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    for name, sp in subs.choices.items():
        assert sp.description and len(sp.description) > 30, f"{name} --help has no description"
        assert "-q" in sp._option_string_actions, f"{name} has no -q"


def test_fit_quiet_prints_no_progress(tmp_path, capsys):
    name = _write_fit_inputs(tmp_path)
    args = [NC, "fit", str(tmp_path / "scene.json"), str(tmp_path / name), "-o", str(tmp_path / "f.json")]
    assert main(args) == 0
    assert "material fit on 20 targets" in capsys.readouterr().err
    assert main([*args, "-q"]) == 0
    assert "material fit" not in capsys.readouterr().err and (tmp_path / "f.json").exists()


def test_mesh_receivers_in_ply_out(tmp_path):
    pytest.importorskip("trimesh")
    import trimesh

    box = trimesh.creation.box(extents=(0.4, 0.4, 0.4))
    box.apply_translation([0.3, 0.2, 0.2])
    box.export(tmp_path / "box.obj")
    assert main([NC, "irradiance", ROOM, str(tmp_path / "box.obj"), "-o", str(tmp_path / "e.ply"), "--float64", "-q"]) == 0
    mesh = js.read_mesh(tmp_path / "box.obj")
    p, n = mesh.receivers("vertices")
    ref = np.asarray(js.irradiance(js.load_scene(ROOM), p, n))
    from jaxshadow._io.meshio import read_ply_values

    np.testing.assert_allclose(read_ply_values(tmp_path / "e.ply", "irradiance"), ref, rtol=1e-12)
    back = trimesh.load(tmp_path / "e.ply", process=False)
    assert back.visual.vertex_colors.shape == (len(p), 4) and len(back.faces) == len(mesh.faces)
    assert main([NC, "irradiance", ROOM, str(tmp_path / "box.obj"), "-o", str(tmp_path / "f.ply"), "--at", "faces", "-q"]) == 0
    assert read_ply_values(tmp_path / "f.ply", "irradiance", at="faces").shape == (len(mesh.faces), 3)


def test_cli_layering():
    """The forward model never imports the solvers (issue 22): `jaxshadow` has no import of
    `inverse`, and `inverse`'s command module imports no private name of `jaxshadow`."""
    for fn in os.listdir(os.path.join(ROOT, "jaxshadow")):
        if fn.endswith(".py"):
            with open(os.path.join(ROOT, "jaxshadow", fn)) as fh:
                tree = ast.parse(fh.read())
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    assert not any(a.name.split(".")[0] == "inverse" for a in node.names), fn
                if isinstance(node, ast.ImportFrom):
                    assert (node.module or "").split(".")[0] != "inverse", fn
    for fn in ("cli.py",):
        with open(os.path.join(ROOT, "inverse", fn)) as fh:
            tree = ast.parse(fh.read())
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("jaxshadow"):
                assert not any(part.startswith("_") for part in node.module.split(".")), node.module
                assert not any(a.name.startswith("_") for a in node.names), node.module
    eps = cli.plugin_commands()
    assert eps["fit"].value == "inverse.cli:add_fit_command" and eps["demo"].value == "inverse.cli:add_demo_command"


def _write_fit_inputs(tmp_path, csv=False):
    """`scene.json` (the room's first light) and targets (20 floor points of a known material)."""
    scene = js.Scene(js.load_scene(ROOM).lights[:1], ambient=0.1)
    js.save_scene(scene, tmp_path / "scene.json")
    rng = np.random.default_rng(1)
    p = np.c_[rng.uniform(-1, 1, (20, 2)), np.zeros(20)]
    n = np.tile([0.0, 0.0, 1.0], (20, 1))
    eye = np.array([0.3, -1.5, 1.5])
    truth = js.Material(ka=0.2, kd=[0.5, 0.4, 0.3], ks=0.3, exponent=20.0)
    name = "t.csv" if csv else "t.json"
    inverse.PaintedTargets(p, n, np.asarray(js.shade(scene, truth, p, n, eye)), eye).save(tmp_path / name)
    return name


@pytest.mark.parametrize("csv", [False, True], ids=["json", "csv"])
def test_fit_command_writes_the_fitted_material(tmp_path, csv):
    name = _write_fit_inputs(tmp_path, csv)
    assert main([NC, "fit", str(tmp_path / "scene.json"), str(tmp_path / name), "-o", str(tmp_path / "f.json")]) == 0
    fitted = js.load_material(tmp_path / "f.json")
    np.testing.assert_allclose(np.asarray(fitted.kd), [0.5, 0.4, 0.3], atol=1e-6)
    np.testing.assert_allclose(float(fitted.exponent), 20.0, rtol=1e-5)


def test_fit_command_checks_its_arguments_first(tmp_path, capsys, monkeypatch):
    name = _write_fit_inputs(tmp_path)
    import inverse.cli as icli

    monkeypatch.setattr(icli, "fit_material", lambda *a, **k: (_ for _ in ()).throw(AssertionError("computed")))
    args = [NC, "fit", str(tmp_path / "scene.json"), str(tmp_path / name)]
    rc, err = _run([*args, "-o", str(tmp_path / "f.txt")], capsys)
    assert rc == 2 and "unknown format '.txt'" in err and ".json, .xml" in err
    rc, err = _run([*args, "-o", str(tmp_path / "x" / "f.json")], capsys)
    assert rc == 2 and "does not exist" in err
    rc, err = _run([*args, "-o", str(tmp_path / "f.json"), "--light", "3"], capsys)
    assert rc == 2 and "--light 3: the scene has 1 lights" in err
    (tmp_path / "t.txt").write_text("")
    rc, err = _run([NC, "fit", str(tmp_path / "scene.json"), str(tmp_path / "t.txt"), "-o", str(tmp_path / "f.json")], capsys)
    assert rc == 2 and "targets" in err and "expected .csv, .json" in err
    assert not (tmp_path / "f.json").exists()


def test_fit_command_passes_combinatorics(tmp_path, monkeypatch, capsys):
    """`jaxshadow fit --light 0 --combinatorics host` asks `fit_light` for host combinatorics
    (stubbed here: the light fit itself is tested in test_inverse / test_lm); an unknown
    value is refused by the parser."""
    import inverse.cli as icli

    _write_fit_inputs(tmp_path)
    seen = {}

    def fake_fit(scene, targets, material, light_index=0, light_kwargs=None, **kw):
        seen.update(light_kwargs, light_index=light_index)
        raise ValueError("stub")  # main() reports ValueErrors with exit status 2

    monkeypatch.setattr(icli, "fit_light_and_material", fake_fit)
    args = [NC, "fit", str(tmp_path / "scene.json"), str(tmp_path / "t.json"),
            "-o", str(tmp_path / "f.json"), "--light", "0"]
    assert main([*args, "--combinatorics", "host"]) == 2
    solver = seen.pop("solver")
    assert seen == {"light_index": 0, "fit": ("position", "orientation"), "starts": 64}
    assert solver.combinatorics == "host" and solver.refine == 8
    seen.clear()
    assert main(args) == 2
    assert seen["solver"].combinatorics == "auto"
    with pytest.raises(SystemExit) as exc:
        main([*args, "--combinatorics", "gpu"])
    assert exc.value.code == 2
    seen.clear()
    assert main([*args, "--fit", "position,size"]) == 2 and seen["fit"] == ("position", "size")
    rc, err = _run([*args, "--fit", "position,colour"], capsys)
    assert rc == 2 and "--fit: expected a comma-separated subset of position,orientation,size" in err


def test_compile_cache_option(tmp_path, monkeypatch):
    """`--compile-cache DIR` turns on JAX's persistent cache there (programs taking >= 0.2 s to
    compile are written); the option is reset afterwards so other tests are unaffected. An
    unwritable cache directory is a usage error, not a traceback."""
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
    (tmp_path / "file").write_text("")
    with pytest.raises(PermissionError, match="--compile-cache: cannot create"):
        enable_compile_cache(str(tmp_path / "file" / "xla"))


def test_an_output_that_is_an_input_is_refused(tmp_path, capsys, monkeypatch):
    def forbidden(*args, **kw):
        raise AssertionError("computed before the arguments were checked")

    monkeypatch.setattr(js, "irradiance", forbidden)
    monkeypatch.setattr(js, "illumination_mesh", forbidden)
    import inverse.cli as icli

    monkeypatch.setattr(icli, "fit_material", forbidden)
    p = np.zeros((3, 6))
    np.save(tmp_path / "pts.npy", p)
    scene = tmp_path / "scene.json"
    js.save_scene(js.load_scene(ROOM), scene)
    (tmp_path / "scene.xml").write_text("<scene version='3.0.0'/>")
    before = {f: (tmp_path / f).read_bytes() for f in os.listdir(tmp_path)}
    os.symlink(tmp_path / "pts.npy", tmp_path / "link.npy")
    cases = [
        (["irradiance", str(scene), str(tmp_path / "pts.npy"), "-o", str(tmp_path / "pts.npy")], "pts.npy"),
        (["irradiance", str(scene), str(tmp_path / "pts.npy"), "-o", str(tmp_path / "link.npy")], "pts.npy"),
        (["irradiance", str(scene), str(tmp_path / "pts.npy"), "-o", str(tmp_path / "." / "scene.json")], "scene.json"),
        (["render", str(tmp_path / "scene.xml"), "-o", str(tmp_path / "scene.xml")], "scene.xml"),
        (["render", str(tmp_path / "scene.xml"), "-o", str(tmp_path / "a.png"), "-o", str(tmp_path / "a.png")], "a.png"),
        (["mesh", str(scene), "-o", str(scene)], "scene.json"),
        (["fit", str(scene), str(tmp_path / "pts.npy"), "-o", str(scene)], "scene.json"),
    ]
    for argv, name in cases:
        rc, err = _run([NC, *argv], capsys)
        assert rc == 2, (argv, err)
        assert "the same file" in err or ("writing it would destroy the input" in err and name in err), (argv, err)
    # an input scene's arrays file is an input too
    js.save_scene(js.Scene([], occluders=[js.Mesh([[0, 0, 1], [1, 0, 1], [0, 1, 1]], [[0, 1, 2]])]), scene)
    before = {f: (tmp_path / f).read_bytes() for f in os.listdir(tmp_path) if f != "link.npy"}
    rc, err = _run([NC, "irradiance", str(scene), str(tmp_path / "pts.npy"), "-o", str(tmp_path / "scene.meshes.npz")], capsys)
    assert rc == 2 and "scene.meshes.npz" in err and "destroy the input" in err
    assert {f: (tmp_path / f).read_bytes() for f in os.listdir(tmp_path) if f != "link.npy"} == before


def test_readme_names_every_extra():
    import re

    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as fh:
        extras = set(tomllib.load(fh)["project"]["optional-dependencies"])
    with open(os.path.join(ROOT, "README.md")) as fh:
        readme = fh.read()
    paragraph = readme[readme.index("`pip install jaxshadow` needs only"):]
    paragraph = paragraph[:paragraph.index("\n\n")]
    assert extras <= set(re.findall(r"`(\w+)`", paragraph)), extras - set(re.findall(r"`(\w+)`", paragraph))


@pytest.mark.parametrize(("argv", "missing", "extra"), [
    (["demo", "--out", "{tmp}"], "matplotlib", "plot"),
    (["report", "--out", "{tmp}"], "mitsuba", "mitsuba"),
    (["report", "--out", "{tmp}"], "matplotlib", "plot"),
    (["render", "{tmp}/s.xml", "-o", "{tmp}/a.png"], "mitsuba", "mitsuba"),
    (["render", "{tmp}/s.xml", "-o", "{tmp}/a.png", "--spp-compare", "4"], "matplotlib", "plot"),
    (["mesh", ROOM, "-o", "{tmp}/m.ply"], "shapely", "mesh"),
])
def test_missing_optional_dependency_is_found_before_computing(tmp_path, capsys, monkeypatch, argv, missing, extra):
    import importlib.util

    import inverse.cli as icli
    from jaxshadow.cli import render as _render

    def forbidden(*a, **k):
        raise AssertionError("computed before the optional dependencies were checked")

    for mod, name in ((icli, "run_demo"), (js, "load_scene"), (_render, "_load")):
        monkeypatch.setattr(mod, name, forbidden)
    (tmp_path / "s.xml").write_text("<scene version='3.0.0'/>")
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == missing else real(name, *a))
    rc, err = _run([NC, *[a.replace("{tmp}", str(tmp_path)) for a in argv]], capsys)
    assert rc == 2 and repr(missing) in err and f"jaxshadow[{extra}]" in err, err
    assert sorted(os.listdir(tmp_path)) == ["s.xml"]


@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_csv_to_csv_repeats_the_receivers_as_written(tmp_path, newline):
    """CSV in, CSV out: the receiver columns of the output are the input rows' own text (spaces,
    integers, exponents and all, CRLF read as LF), the values those of the library to the last
    bit; a CSV that needs the csv module (a blank line) gets the same table formatted."""
    rng = np.random.default_rng(4)
    pts = np.c_[rng.uniform(-1, 1, (23, 2)), np.zeros(23)]
    rows = [f"{x!r}, {y!r},0,0,0,1" if i % 3 else f"{x:.3e},{y!r},0.0, 0.0,0.0,1e0"
            for i, (x, y) in enumerate(pts[:, :2].tolist())]
    pts[::3, 0] = [float(f"{x:.3e}") for x in pts[::3, 0]]
    nrm = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    src = tmp_path / "pts.csv"
    src.write_bytes((newline.join(["px, py,pz,nx,ny,nz", *rows]) + newline).encode())
    ref = np.asarray(js.irradiance(js.load_scene(ROOM), pts, nrm))
    out = tmp_path / "e.csv"
    assert main([NC, "irradiance", ROOM, str(src), "-o", str(out), "--chunk", "16", "--float64", "-q"]) == 0
    lines = out.read_text().splitlines()
    assert lines[0] == "px,py,pz,nx,ny,nz,r,g,b"
    assert [ln.rsplit(",", 3)[0] for ln in lines[1:]] == rows
    got = np.loadtxt(out, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(got[:, :6], np.c_[pts, nrm])
    np.testing.assert_array_equal(got[:, 6:], ref)
    # float32: the values are the library's float32 ones, the receivers still the input's text.
    assert main([NC, "irradiance", ROOM, str(src), "-o", str(out), "--chunk", "16", "-q"]) == 0
    ref32 = np.asarray(js.irradiance(js.load_scene(ROOM), pts.astype(np.float32), nrm.astype(np.float32)))
    got = np.loadtxt(out, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(got[:, 6:].astype(np.float32), ref32)
    assert [ln.rsplit(",", 3)[0] for ln in out.read_text().splitlines()[1:]] == rows
    # A blank line: read by the csv route, written formatted; the same numbers.
    src.write_text("px,py,pz,nx,ny,nz\n" + "\n".join(rows[:5]) + "\n\n" + "\n".join(rows[5:]) + "\n")
    assert main([NC, "irradiance", ROOM, str(src), "-o", str(out), "--chunk", "16", "--float64", "-q"]) == 0
    lines = out.read_text().splitlines()
    assert lines[1] != rows[0]  # formatted again (repr), not echoed
    np.testing.assert_array_equal(np.loadtxt(out, delimiter=",", skiprows=1), np.c_[pts, nrm, ref])
