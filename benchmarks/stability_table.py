"""Stability: the stiff and extreme cases of tests/test_stability.py against mpmath references.

    python -m benchmarks stability_table

References are read from `tests/data/stability_reference.json` (regenerate them with
`python tests/test_stability.py`, ~5 min).
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

DESCRIPTION = "stiff / extreme cases of tests/test_stability.py: errors against mpmath references"
HERE = Path(__file__).resolve().parent


def _tests() -> Any:
    import jax

    jax.config.update("jax_enable_x64", True)
    sys.path.insert(0, str(HERE.parent / "tests"))
    import test_stability

    return test_stability


def run(quick: bool) -> dict:
    """Every case at float64 and float32 (the quick run too: the references are stored)."""
    ts = _tests()
    rows = [*ts.evaluate_all("float64"), *ts.evaluate_all("float32")]
    for r in rows:
        r["known_defect"] = f"{r['dtype']}/{r['case']}" in ts.KNOWN
    if ts.polygon_specular_kernel is not None:
        for method in ("chebyshev", "exact"):
            for dt in ("float64", "float32"):
                rows += [dict(kind="specular", method=method, dtype=dt, n=r[0], value=r[1], reference=r[2],
                              rel_err=r[3], finite=r[4]) for r in ts.specular_rows(method, np.dtype(dt))]
    if ts.visible_form_factor_kernel is not None:
        whats = {c[0]: c[-1] for c in ts._touching_cases()}
        for dt in (np.float64, np.float32):
            rows += [dict(kind="touching", case=r[0], what=whats[r[0]], dtype=np.dtype(dt).name, value=r[1],
                          reference=r[2], unoccluded=r[3], finite=r[4]) for r in ts.touching_rows(dt)]
    return {"rows": rows, "pending": list(ts.PENDING)}


def _e(x: float) -> str:
    return "nan" if x != x else ("0" if x == 0 else f"{x:.1e}")


def markdown(results: dict) -> str:
    rows = results["rows"]
    cases = {(r["case"], r["dtype"]): r for r in rows if "kind" not in r}
    lines = [
        "Max relative error against the mpmath reference (60 digits) of the value and of the "
        "gradient w.r.t. the receiver position and normal; in brackets the error relative to "
        "max(|reference|, |generic case of the same kernel|) (the floor the tests use); "
        "NaN/inf: non-finite entries in value + gradient (float64 / float32).",
        "",
        "| case | what | reference | f64 value | f64 grad | f32 value | f32 grad | NaN/inf |",
        "|---|---|---:|---|---|---|---|---|",
    ]
    for (cid, dt), r64 in cases.items():
        if dt != "float64":
            continue
        r32 = cases[(cid, "float32")]
        known = " (known defect: see `KNOWN` in the test)" if r32.get("known_defect") else ""
        lines.append(
            f"| {cid} | {r64['what']}{known} | {r64['reference']:.6g} "
            f"| {_e(r64['rel_err'])} [{_e(r64['rel_err_floor'])}] "
            f"| {_e(r64['grad_rel_err'])} [{_e(r64['grad_rel_err_floor'])}] "
            f"| {_e(r32['rel_err'])} [{_e(r32['rel_err_floor'])}] "
            f"| {_e(r32['grad_rel_err'])} [{_e(r32['grad_rel_err_floor'])}] "
            f"| {r64['nonfinite']} / {r32['nonfinite']} |"
        )
    lines += [
        "",
        "Cases where the reference is 0 by definition (receiver behind or in the emitter's "
        "plane, end-on cosine tube) are checked for an exact 0; their reference gradient is a "
        "one-sided limit (a kink), so the gradient column there is informative only.",
    ]
    spec = [r for r in rows if r.get("kind") == "specular"]
    if spec:
        exps = sorted({r["n"] for r in spec})
        lines += ["", "Specular (polygon, `_specular.polygon_specular_kernel`), exponent n from 1 to 1e6, lobe "
                  "straddling an edge; reference: mpmath polar integral about R (30 digits):", ""]
        lines += ["| method | dtype | " + " | ".join(f"n={e:g}" for e in exps) + " | NaN/inf |",
                  "|---|---|" + "---|" * (len(exps) + 1)]
        for method in ("chebyshev", "exact"):
            for dt in ("float64", "float32"):
                sel = sorted((r for r in spec if r["method"] == method and r["dtype"] == dt), key=lambda r: r["n"])
                lines.append(f"| {method} | {dt} | " + " | ".join(_e(r["rel_err"]) for r in sel)
                             + f" | {sum(not r['finite'] for r in sel)} |")
    touch = [r for r in rows if r.get("kind") == "touching"]
    if touch:
        lines += ["", "Occluders touching the receiver (`_clip.visible_form_factor_kernel`, unit square light 1 "
                  "above p); reference: mpmath (difference of two form factors):", ""]
        lines += ["| case | what | reference | f64 F | f32 F | finite f64 / f32 |", "|---|---|---:|---:|---:|---|"]
        by = {(r["case"], r["dtype"]): r for r in touch}
        for (cid, dt), a in by.items():
            if dt != "float64":
                continue
            b = by[(cid, "float32")]
            ref = "= unoccluded" if a["reference"] is None else f"{a['reference']:.6g}"
            lines.append(f"| {cid} | {a['what']} | {ref} | {a['value']:.6g} | {b['value']:.6g} | "
                         f"{a['finite']} / {b['finite']} |")
    if results.get("pending"):
        lines += ["", "Pending cases:", "", *[f"- {p}" for p in results["pending"]]]
    return "\n".join(lines)


def key_numbers(results: dict) -> list[tuple[str, str]]:
    cases = [r for r in results["rows"] if "kind" not in r]
    bad = sum(int(r["nonfinite"]) for r in cases)
    worst = max(r["rel_err_floor"] for r in cases if r["dtype"] == "float64")
    return [(f"stability: {len(cases) // 2} singular / extreme cases vs mpmath, float64 and float32",
             f"{bad} non-finite values or gradients; worst float64 value error {worst:.1e} (relative, floored)")]
