"""Stability table: the cases of tests/test_stability.py, errors against the mpmath reference.

    .venv/bin/python -m benchmarks.stability_table

Writes `benchmarks/results/stability.json` and the table between the `<!-- stability table -->`
markers of `benchmarks/README.md`. References are read from `tests/data/stability_reference.json`
(regenerate with `.venv/bin/python tests/test_stability.py`).
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import jax
import numpy as np

jax.config.update("jax_enable_x64", True)

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent / "tests"))
sys.path.insert(0, str(HERE.parent))

import test_stability as ts  # noqa: E402

from benchmarks.run import write_readme_section  # noqa: E402


def _e(x: float) -> str:
    return "nan" if x != x else ("0" if x == 0 else f"{x:.1e}")


def table() -> tuple[str, list[dict]]:
    rows64 = {r["case"]: r for r in ts.evaluate_all("float64")}
    rows32 = {r["case"]: r for r in ts.evaluate_all("float32")}
    lines = [
        "Max relative error against the mpmath reference (60 digits) of the value and of the "
        "gradient w.r.t. the receiver position and normal; in brackets the error relative to "
        "max(|reference|, |generic case of the same kernel|) (the floor the tests use); "
        "NaN/inf: non-finite entries in value + gradient (float64 / float32). "
        "Command: `.venv/bin/python -m benchmarks.stability_table`.",
        "",
        "| case | what | reference | f64 value | f64 grad | f32 value | f32 grad | NaN/inf |",
        "|---|---|---:|---|---|---|---|---|",
    ]
    for cid, r64 in rows64.items():
        r32 = rows32[cid]
        known = " (known defect: see `KNOWN` in the test)" if f"float32/{cid}" in ts.KNOWN else ""
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
    extra = []
    if ts.polygon_specular_kernel is not None:
        lines += ["", "Specular (polygon, `_specular.polygon_specular_kernel`), exponent n from 1 to 1e6, lobe straddling an edge; reference: mpmath polar integral about R (30 digits):", ""]
        lines += ["| method | dtype | " + " | ".join(f"n={e:g}" for e in ts.SPECULAR_EXPONENTS) + " | NaN/inf |", "|---|---|" + "---|" * (len(ts.SPECULAR_EXPONENTS) + 1)]
        for method in ("chebyshev", "exact"):
            for dt in ("float64", "float32"):
                rows = ts.specular_rows(method, np.dtype(dt))
                extra += [dict(kind="specular", method=method, dtype=dt, n=r[0], value=r[1], reference=r[2], rel_err=r[3], finite=r[4]) for r in rows]
                lines.append(f"| {method} | {dt} | " + " | ".join(_e(r[3]) for r in rows) + f" | {sum(not r[4] for r in rows)} |")
    if ts.visible_form_factor_kernel is not None:
        lines += ["", "Occluders touching the receiver (`_clip.visible_form_factor_kernel`, unit square light 1 above p); reference: mpmath (difference of two form factors):", ""]
        lines += ["| case | what | reference | f64 F | f32 F | finite f64 / f32 |", "|---|---|---:|---:|---:|---|"]
        r64 = ts.touching_rows(np.float64)
        r32 = ts.touching_rows(np.float32)
        whats = {c[0]: c[-1] for c in ts._touching_cases()}
        for a, b in zip(r64, r32, strict=True):
            ref = "= unoccluded" if a[2] is None else f"{a[2]:.6g}"
            lines.append(f"| {a[0]} | {whats[a[0]]} | {ref} | {a[1]:.6g} | {b[1]:.6g} | {a[4]} / {b[4]} |")
            extra += [dict(kind="touching", case=a[0], dtype=dt, value=r[1], reference=r[2], unoccluded=r[3], finite=r[4]) for dt, r in (("float64", a), ("float32", b))]
    if ts.PENDING:
        lines += ["", "Pending cases (kernels owned by other engineers):", ""]
        lines += [f"- {p}" for p in ts.PENDING]
    return "\n".join(lines), [*rows64.values(), *rows32.values(), *extra]


def main() -> None:
    text, rows = table()
    (HERE / "results").mkdir(exist_ok=True)
    (HERE / "results" / "stability.json").write_text(json.dumps(rows, indent=1, default=float))
    write_readme_section(text, "stability table")
    print(text)


if __name__ == "__main__":
    main()
