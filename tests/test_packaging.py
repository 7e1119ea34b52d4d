"""Dependencies: `import jaxshadow` and `import inverse` need only the core ones; every optional
one, missing, fails with a message that names its extra."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

OPTIONAL = ("jaxopt", "optimistix", "lineax", "matplotlib", "mitsuba", "drjit")
_BLOCK = f"""
import sys

class Block:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in {OPTIONAL!r}:
            raise ImportError(f"blocked: {{name}}")

sys.meta_path.insert(0, Block())
import jaxshadow, jaxshadow.traced, inverse
print(sorted(m for m in sys.modules if m.split(".")[0] in {OPTIONAL!r}))
"""


def test_core_imports_need_no_extra():
    out = subprocess.run([sys.executable, "-c", _BLOCK], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parent.parent)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip() == "[]"


def test_optional_solvers_name_their_extra(monkeypatch):
    from inverse import _jaxopt, _solvers

    monkeypatch.setitem(sys.modules, "jaxopt", None)
    with pytest.raises(ImportError, match=r"jaxshadow\[jaxopt\]"):
        _jaxopt._jaxopt()
    monkeypatch.setitem(sys.modules, "optimistix", None)
    with pytest.raises(ImportError, match=r"jaxshadow\[optimistix\]"):
        _solvers._optimistix()



_UNBUILT = """
import json, sys, types, warnings
import numpy as np

class Block:
    def find_spec(self, name, path=None, target=None):
        if name == "jaxshadow._shadows._shadowc":
            raise ImportError("blocked: the engine is not built")

if sys.argv[1] == "hidden":
    sys.meta_path.insert(0, Block())
else:  # a build of an older interface left in place
    sys.modules["jaxshadow._shadows._shadowc"] = types.SimpleNamespace(
        ABI_VERSION=2, CODE_WIDTH=7, poly_plan=None, __file__="_shadowc.old.so")
import jax
jax.config.update("jax_enable_x64", True)
import jaxshadow as js

quad = js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=1.0)
scene = js.Scene([quad], occluders=[js.Mesh.box([0.3, 0.3, 0.8], [0.6, 0.5, 1.0])])
p = np.array([[0.45, 0.4, 0.0], [0.2, 0.9, 0.0], [3.0, 0.0, 0.0]])
n = np.tile([0.0, 0.0, 1.0], (3, 1))
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    a = np.asarray(js.irradiance(scene, p, n))
    b = np.asarray(js.irradiance(scene, p, n))
dev = np.asarray(js.irradiance(scene, p, n, shadows=js.ShadowOptions(engine="device")))
free = np.asarray(js.irradiance(js.Scene([quad]), p, n))
print(json.dumps({"a": a.tolist(), "b": b.tolist(), "dev": dev.tolist(), "free": free.tolist(),
                  "warnings": [str(w.message) for w in caught]}))
"""


def test_file_writers_have_a_public_module_and_old_names_warn(tmp_path):
    """`jaxshadow.files` is the writers' home; the names once exported at the top still work,
    with a DeprecationWarning; neither is listed at the top any more."""
    import jaxshadow as js
    from jaxshadow import files

    assert files.__all__ == ["atomic_write", "atomic_write_path"]
    assert "atomic_write" not in dir(js) and "atomic_write_path" not in dir(js)
    for name in files.__all__:
        with pytest.warns(DeprecationWarning, match=f"jaxshadow.files.{name}"):
            assert getattr(js, name) is getattr(files, name)
    with files.atomic_write(tmp_path / "a.txt") as fh:
        fh.write("x")
    assert (tmp_path / "a.txt").read_text() == "x"
    with pytest.raises(AttributeError, match="no attribute 'not_a_name'"):
        js.not_a_name  # noqa: B018


@pytest.mark.parametrize("state", ["hidden", "stale"])
def test_unbuilt_engine_falls_back_to_the_device_kernels_with_one_warning(state):
    """With the compiled engine hidden (or a build of another interface version in its place),
    scenes with occluders take the device kernels' values and say so once per process."""
    import json

    out = subprocess.run([sys.executable, "-c", _UNBUILT, state], capture_output=True, text=True,
                         cwd=Path(__file__).resolve().parent.parent)
    assert out.returncode == 0, out.stderr[-3000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["a"] == r["dev"] == r["b"]
    a, free = r["a"], r["free"]
    assert a[0][0] < 0.9 * free[0][0]  # under the box: shadowed
    assert a[2][0] == free[2][0]  # far away: unoccluded
    assert len(r["warnings"]) == 1 and "not built" in r["warnings"][0]
    assert ("stale build" in r["warnings"][0]) == (state == "stale")
