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


ROOT = Path(__file__).resolve().parent.parent


def _public_names(module) -> list[str]:
    """`__all__`, else the names the module defines or re-exports from the two packages."""
    names = getattr(module, "__all__", None)
    if names is not None:
        return list(names)
    return [n for n in dir(module) if not n.startswith("_") and not inspect.ismodule(getattr(module, n))
            and (getattr(getattr(module, n), "__module__", "") or "").split(".")[0] in ("jaxshadow", "inverse")]


def test_every_public_name_has_a_page():
    """Every public name of `jaxshadow`, `jaxshadow.traced`, `jaxshadow.testing` and `inverse` is
    rendered by the API reference: an entry `::: module.name`, or its module's own `::: module`."""
    import jaxshadow.testing

    pages = "".join(p.read_text() for p in (ROOT / "docs" / "api").glob("*.md"))
    entries = set(re.findall(r"^::: ([\w.]+)\s*$", pages, re.M))
    missing = [f"{m.__name__}.{n}" for m in (jaxshadow, traced, jaxshadow.testing, inverse)
               for n in _public_names(m) if m.__name__ not in entries and f"{m.__name__}.{n}" not in entries]
    assert not missing, f"public names without an API page entry: {missing}"


def test_cli_page_is_the_parsers_help():
    """docs/cli.md is what `python tools/cli_docs.py` writes from the parser (every command)."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, str(ROOT / "tools" / "cli_docs.py"), "--check"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


def test_built_site_renders_math(tmp_path):
    """The built documentation has no raw `$` outside code (formulas go through arithmatex and
    MathJax), and the formulas of the docstrings are marked for MathJax."""
    pytest.importorskip("mkdocs")
    pytest.importorskip("pymdownx")
    import subprocess
    import sys

    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(site)], cwd=ROOT,
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    raw = {}
    for f in site.rglob("*.html"):
        text = re.sub(r"<pre.*?</pre>|<code.*?</code>|<script.*?</script>", "", f.read_text(), flags=re.S)
        if "$" in text:
            raw[str(f.relative_to(site))] = text[text.index("$") - 60:text.index("$") + 40]
    assert not raw, raw
    assert 'class="arithmatex"' in (site / "api" / "jaxshadow" / "index.html").read_text()
