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
