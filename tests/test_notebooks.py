"""The notebooks under notebooks/: stored with their outputs (figures included), public API only,
text that matches the stored outputs, and they run (nbclient; each must finish in well under 60 s
on a quiet machine).

Text against outputs: every number quoted in a markdown cell (outside math `$...$`, code spans
and references such as "§5.3" or "eq. 5.14") must appear in the notebook's stored outputs or in
its code (an input the text describes), to the precision it is quoted with (within half a unit of
its last digit: "30.8" matches 30.761, "1e-3" matches 0.001); and each sentence in `CLAIMS` must
come with its output."""

from __future__ import annotations

import json
import os
import re
import time

import numpy as np
import pytest

NOTEBOOKS = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "notebooks")
NAMES = ["paint_material.ipynb", "light_from_shadow.ipynb", "checking_shadow_gradients.ipynb", "bake_a_scene.ipynb"]
# (notebook, words in a markdown cell, text its stored outputs must then hold)
CLAIMS = [("paint_material.ipynb", "reported as undetermined", "n determined: False")]
NUMBER = re.compile(r"(?<![\w.])[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?(?!\w)")


def _numbers(text):
    """`(text, value, half a unit of the last digit)` of each number in `text`."""
    out = []
    for m in NUMBER.finditer(text):
        q = m.group(0).rstrip(".")
        mantissa, _, exp = q.lower().partition("e")
        digits = len(mantissa.partition(".")[2])
        out.append((q, float(q), 0.5 * 10.0 ** ((int(exp) if exp else 0) - digits)))
    return out


def _prose(markdown):
    """A markdown cell without math, code spans, link targets and section/equation references."""
    text = re.sub(r"\$\$.*?\$\$|\$[^$]*\$", " ", markdown, flags=re.S)
    text = re.sub(r"`[^`]*`", " ", text)
    text = re.sub(r"\]\([^)]*\)", "]", text)
    return re.sub(r"§\s*[\d.]+|\beqs?\.\s*[\d.]+|\(\d+(\.\d+)*\)", " ", text)


def text_against_outputs(nb, name):
    """The quoted numbers of `nb`'s markdown not found in its outputs or code, and the `CLAIMS`
    whose output is missing (empty lists when the text matches)."""
    markdown = ["".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "markdown"]
    shown = []
    for c in nb["cells"]:
        if c["cell_type"] == "code":
            shown.append("".join(c["source"]))
            for o in c.get("outputs", []):
                shown.append("".join(o.get("text", "")) + "".join(o.get("data", {}).get("text/plain", "")))
    have = np.array([v for _, v, _ in _numbers("\n".join(shown))])
    missing = [q for cell in markdown for q, v, tol in _numbers(_prose(cell))
               if not np.any(np.abs(have - v) <= tol * (1 + 1e-9))]
    claims = [(words, needed) for nb_name, words, needed in CLAIMS
              if nb_name == name and any(words in cell for cell in markdown)
              and not any(needed in text for text in shown)]
    return missing, claims


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
def test_notebook_text_matches_its_stored_outputs(name):
    with open(os.path.join(NOTEBOOKS, name)) as fh:
        nb = json.load(fh)
    missing, claims = text_against_outputs(nb, name)
    assert not missing, f"{name}: numbers in the text that no output or code shows: {missing}"
    assert not claims, f"{name}: the text says {claims[0][0]!r} but no output shows {claims[0][1]!r}"


def test_text_check_catches_a_mismatch():
    """The check itself: a number the outputs do not show, one quoted more precisely than shown,
    and a claim whose output says otherwise are caught; math, code spans and references are not
    read as quoted numbers."""
    def nb(markdown, output, code="x = 1"):
        return {"cells": [{"cell_type": "markdown", "source": [markdown]},
                          {"cell_type": "code", "source": [code], "outputs": [{"output_type": "stream", "text": [output]}]}]}

    assert text_against_outputs(nb("n is fitted as 30.8.", "n fitted 30.761"), "x") == ([], [])
    assert text_against_outputs(nb("n is fitted as 30.9.", "n fitted 30.761"), "x")[0] == ["30.9"]
    assert text_against_outputs(nb("n is fitted as 30.76.", "n fitted 30.8"), "x")[0] == ["30.76"]
    assert text_against_outputs(nb("a 1e-3 cut", "kept 0.001"), "x")[0] == []
    assert text_against_outputs(nb("Poulin §5.3, eq. 5.14, $k = 7$ and `h = 9`", "nothing"), "x")[0] == []
    assert text_against_outputs(nb("with 12 samples", "nothing", code="samples = 12"), "x")[0] == []
    claim = nb("then $n$ is reported as undetermined", "n determined: True")
    assert text_against_outputs(claim, "paint_material.ipynb")[1] == [("reported as undetermined", "n determined: False")]


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
