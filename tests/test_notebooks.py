"""The notebooks under notebooks/: stored with their outputs (figures included), public API only,
and they run (nbclient; each must finish in well under 60 s on a quiet machine)."""

from __future__ import annotations

import json
import os
import re
import time

import pytest

NOTEBOOKS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "notebooks")
NAMES = ["paint_material.ipynb", "light_from_shadow.ipynb", "checking_shadow_gradients.ipynb"]


@pytest.mark.parametrize("name", NAMES)
def test_notebook_is_stored_with_its_pictures_and_uses_public_api(name):
    with open(os.path.join(NOTEBOOKS, name)) as fh:
        nb = json.load(fh)
    code = "\n".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code")
    assert "matplotlib.use(" not in code  # "Agg" suppresses inline figures
    assert not re.search(r"\b(inverse|jaxshadow)\._", code), "private names in a notebook"
    outputs = [o for c in nb["cells"] if c["cell_type"] == "code" for o in c.get("outputs", [])]
    assert all(c.get("execution_count") for c in nb["cells"] if c["cell_type"] == "code"), "not executed"
    assert any("image/png" in o.get("data", {}) for o in outputs), "no stored figure"
    assert not [o for o in outputs if o["output_type"] == "error"]


@pytest.mark.parametrize("name", NAMES)
def test_notebook_runs(name):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    path = os.path.join(NOTEBOOKS, name)
    nb = nbformat.read(path, as_version=4)
    client = nbclient.NotebookClient(nb, timeout=300, kernel_name="python3",
                                     resources={"metadata": {"path": NOTEBOOKS}})
    t0 = time.perf_counter()
    client.execute()
    elapsed = time.perf_counter() - t0
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors, errors
    print(f"{name}: {elapsed:.1f} s")
