"""Docs: every public function of `jaxshadow`, `jaxshadow.traced` and `inverse` has a usage
example in its docstring (`Example:` with a ```python block, rendered by the API reference),
and every example runs."""

from __future__ import annotations

import inspect
import re
from pathlib import Path

import pytest

import inverse
import jaxshadow
from jaxshadow import traced

# Public functions whose docstrings live in the shadow engine (the lead's files): their
# examples are on the API reference page instead (docs/api/jaxshadow.md).
EXAMPLE_ON_THE_PAGE = {"jaxshadow.visible_form_factor"}
_BLOCK = re.compile(r"Example:\n\s*```python\n(.*?)\n\s*```", re.S)


def _public_functions():
    out = {}
    for mod in (jaxshadow, traced, inverse):
        for name in dir(mod):
            obj = getattr(mod, name)
            if name.startswith("_") or inspect.ismodule(obj) or inspect.isclass(obj) or not callable(obj):
                continue
            home = getattr(obj, "__module__", "") or ""
            if home.split(".")[0] in ("jaxshadow", "inverse"):
                out[f"{mod.__name__}.{name}"] = obj
    return out


def _examples():
    out = {}
    for name, obj in _public_functions().items():
        m = _BLOCK.search(inspect.getdoc(obj) or "")
        if m:
            out[name] = inspect.cleandoc(m.group(1))
    for name in ("LM", "OptimistixLM", "LBFGSB"):
        m = _BLOCK.search(inspect.getdoc(getattr(inverse, name)) or "")
        out[f"inverse.{name}"] = inspect.cleandoc(m.group(1))
    page = (Path(__file__).resolve().parent.parent / "docs" / "api" / "jaxshadow.md").read_text()
    for name in EXAMPLE_ON_THE_PAGE:
        m = re.search(rf"::: {re.escape(name)}\n\nExample:\n\n```python\n(.*?)\n```", page, re.S)
        assert m, f"no example for {name} on docs/api/jaxshadow.md"
        out[name] = m.group(1)
    return out


def test_every_public_function_has_an_example():
    functions = _public_functions()
    assert len(functions) >= 35
    missing = sorted(set(functions) - set(_examples()) - EXAMPLE_ON_THE_PAGE)
    assert not missing, f"public functions without an `Example:` section: {missing}"


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(_examples()))
def test_example_runs(name):
    exec(compile(_examples()[name], f"<example of {name}>", "exec"), {})
