"""Files at array speed: receiver tables (CSV vs .npy, read, written, and a whole `jaxshadow irradiance` run) and a 76 152-triangle scene saved and loaded.

- **Tables**, 10^6 receivers (10^5 with `--quick`): `read_points` of a points CSV (the six
  receiver columns `px..nz`, float64 reprs; header check, field-count check, then NumPy's
  parser) against the same points as `.npy`; `write_values` of the CSV output against
  the writer it replaced (a `csv.writer` row of `repr` strings per receiver), in the same run,
  and the command's CSV-to-CSV writer (`write_values_beside_rows`: the receiver columns are the
  input rows' own text, only `r, g, b` formatted); a whole `jaxshadow irradiance` run in a
  fresh process (a quad light, one triangle occluder, float32) from `.csv` to `.csv` and from
  `.npy` to `.npy`, wall time and peak RSS (the child's `VmHWM`), best of two interleaved runs.
  The CSV reader and writers go through the compiled `jaxshadow._io._csvc` when it is built;
  each is also timed on the Python route (the module hidden: `np.loadtxt` and Python's string
  formatting), the whole command too (a third interleaved run, the module blocked in the child).
- **Scene**: `benchmarks.real_meshes.scan_like()` (76 152 triangles, open, float32 coordinates)
  as one `js.Mesh` occluder: `save_scene` (JSON and the `.meshes.npz` beside it) and `load_scene`,
  best of three, and the inline JSON of schema 1 (`scene_to_dict` dumped with indent, as files
  were written before) for comparison, with file sizes.
"""

from __future__ import annotations

import csv
import io
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

NAME = "files_io"
ROOT = Path(__file__).resolve().parent.parent


def _best(fn: Any, reps: int = 3) -> float:
    best = float("inf")
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def _old_csv_writer(path: str, table: np.ndarray, header: list[str]) -> None:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(header)
    w.writerows([[repr(float(x)) for x in row] for row in table])
    with open(path, "w", newline="") as fh:
        fh.write(buf.getvalue())


# The child reports its own peak (VmHWM: its address space's high-water mark). Not ru_maxrss:
# Linux carries a forked child's ru_maxrss over from the parent (this process holds the tables).
_CHILD = """import os, runpy, sys
class Block:
    def find_spec(self, name, path=None, target=None):
        if name == "jaxshadow._io._csvc":
            raise ImportError("hidden: the Python route")
if os.environ.get("JAXSHADOW_BENCH_HIDE_CSVC"):
    sys.meta_path.insert(0, Block())
sys.argv = ["jaxshadow", *sys.argv[1:]]
try:
    runpy.run_module("jaxshadow.cli.__main__", run_name="__main__")
finally:
    hwm = [line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM")]
    print("maxrss_kb", hwm[0] if hwm else -1, file=sys.stderr)
"""


def _cli(args: list[str], hide_csvc: bool = False) -> tuple[float, float]:
    """Wall time (s) and peak RSS (MB) of `jaxshadow ARGS` in a fresh process (`hide_csvc`: with
    the compiled CSV module blocked)."""
    t = time.perf_counter()
    env = dict(os.environ, PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("JAXSHADOW_BENCH_HIDE_CSVC", None)
    if hide_csvc:
        env["JAXSHADOW_BENCH_HIDE_CSVC"] = "1"
    r = subprocess.run([sys.executable, "-c", _CHILD, "--no-compile-cache", *args], env=env, capture_output=True,
                       text=True)
    wall = time.perf_counter() - t
    if r.returncode != 0:
        raise RuntimeError(f"jaxshadow {' '.join(args)} failed: {r.stderr[-2000:]}")
    kb = [int(line.split()[1]) for line in r.stderr.splitlines() if line.startswith("maxrss_kb")]
    return wall, kb[-1] / 1024.0


def tables(n: int, folder: str) -> dict:
    import jaxshadow as js
    from jaxshadow._io import tables as tables_io
    from jaxshadow._io.tables import (
        POINT_COLUMNS,
        receiver_rows,
        write_csv_table,
        write_values_beside_rows,
    )

    rng = np.random.default_rng(0)
    p = np.c_[rng.uniform(-1, 1, (n, 2)), np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    csv_in, npy_in = os.path.join(folder, "pts.csv"), os.path.join(folder, "pts.npy")
    with open(csv_in, "w", newline="") as fh:  # a points CSV: the six receiver columns, float64
        write_csv_table(fh, list(POINT_COLUMNS), [p, nrm])
    np.save(npy_in, np.c_[p, nrm])
    out: dict[str, Any] = {"n": n, "csvc_built": tables_io._csvc() is not None}
    out["read_csv_s"] = _best(lambda: js.read_points(csv_in), 2)
    compiled = tables_io._csvc

    def python_route(fn: Any) -> Any:
        def run() -> None:
            tables_io._csvc = lambda: None  # type: ignore[assignment]
            try:
                fn()
            finally:
                tables_io._csvc = compiled  # type: ignore[assignment]
        return run

    out["read_csv_python_s"] = _best(python_route(lambda: js.read_points(csv_in)), 2)
    out["read_npy_s"] = _best(lambda: js.read_points(npy_in), 2)
    vals = rng.uniform(0, 5, (n, 3)).astype(np.float32)
    p32, n32 = p.astype(np.float32), nrm.astype(np.float32)
    out["write_csv_s"] = _best(lambda: js.write_values(os.path.join(folder, "w.csv"), vals, points=p32, normals=n32), 2)
    out["write_csv_python_s"] = _best(python_route(
        lambda: js.write_values(os.path.join(folder, "w.csv"), vals, points=p32, normals=n32)), 2)
    table = np.concatenate([p32, n32, vals], axis=1).astype(np.float64)
    out["write_csv_before_s"] = _best(lambda: _old_csv_writer(os.path.join(folder, "w0.csv"), table,
                                                              [*POINT_COLUMNS, "r", "g", "b"]), 2)
    rows = receiver_rows(csv_in)
    out["write_csv_rows_s"] = _best(lambda: write_values_beside_rows(os.path.join(folder, "w1.csv"), rows, vals), 2)
    out["write_csv_rows_python_s"] = _best(python_route(
        lambda: write_values_beside_rows(os.path.join(folder, "w1.csv"), rows, vals)), 2)
    out["write_npy_s"] = _best(lambda: js.write_values(os.path.join(folder, "w.npy"), vals), 2)
    light = js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], 10.0)
    scene = js.Scene([light], occluders=[np.array([[0.2, 0.2, 1.0], [0.6, 0.2, 1.0], [0.6, 0.6, 1.0]])])
    sp = os.path.join(folder, "scene.json")
    js.save_scene(scene, sp)
    runs: dict[str, list] = {"npy": [], "csv": [], "csv_python": []}
    for _ in range(2):  # interleaved: the shared machine's speed drifts
        for key in runs:
            ext = key.split("_")[0]
            runs[key].append(_cli(["irradiance", sp, os.path.join(folder, f"pts.{ext}"),
                                   "-o", os.path.join(folder, f"out.{ext}"), "-q"], hide_csvc=key == "csv_python"))
    for key in runs:
        out[f"cli_{key}_s"] = min(w for w, _ in runs[key])
        out[f"cli_{key}_rss_mb"] = max(r for _, r in runs[key])
    out["cli_csv_over_npy"] = out["cli_csv_s"] / out["cli_npy_s"]
    out["cli_csv_python_over_npy"] = out["cli_csv_python_s"] / out["cli_npy_s"]
    return out


def scene_files(folder: str, subdivisions: int) -> dict:
    import jaxshadow as js
    from benchmarks.real_meshes import scan_like
    from jaxshadow._scene.format import arrays_file_name

    v, f = scan_like(subdivisions)
    v = v.astype(np.float32).astype(np.float64)
    t = time.perf_counter()
    mesh = js.Mesh(v, f)
    build = time.perf_counter() - t
    scene = js.Scene([js.PointLight([0, 0, 3.0], 1.0)], occluders=[mesh])
    path = os.path.join(folder, "scene.json")
    save = _best(lambda: js.save_scene(scene, path))
    load = _best(lambda: js.load_scene(path))
    back = js.load_scene(path)
    assert np.array_equal(np.asarray(back.occluders), np.asarray(scene.occluders))
    size = os.path.getsize(path) + os.path.getsize(os.path.join(folder, arrays_file_name(path)))
    old = os.path.join(folder, "inline.json")

    def save_inline() -> None:
        with open(old, "w") as fh:
            fh.write(json.dumps(js.scene_to_dict(scene), indent=2))

    save_v1 = _best(save_inline, 1)
    load_v1 = _best(lambda: js.load_scene(old), 1)
    return {"triangles": int(len(f)), "mesh_build_s": build, "save_s": save, "load_s": load, "bytes": size,
            "inline_save_s": save_v1, "inline_load_s": load_v1, "inline_bytes": os.path.getsize(old)}


def run(quick: bool) -> dict:
    with tempfile.TemporaryDirectory() as folder:
        t = tables(10**5 if quick else 10**6, folder)
        s = scene_files(folder, 4 if quick else 6)
    return {"tables": t, "scene": s}


def markdown(results: dict) -> str:
    t, s = results["tables"], results["scene"]
    n = f"{t['n']:.0e}"
    py = "Python route (module hidden)"
    route = "compiled `_csvc`" if t.get("csvc_built") else "Python route (`_csvc` not built)"
    rows = [
        f"CSV rows through the {route}.",
        "",
        "| what | time (s) | beside it |",
        "|---|---:|---|",
        f"| read {n} receivers, CSV | {t['read_csv_s']:.2f} | .npy {t['read_npy_s']:.3f} s"
        + (f"; {py} {t['read_csv_python_s']:.2f} s" if "read_csv_python_s" in t else "") + " |",
        f"| write {n} values, CSV (block format) | {t['write_csv_s']:.2f} | per-value repr writer "
        f"{t['write_csv_before_s']:.2f} s; .npy {t['write_npy_s']:.3f} s"
        + (f"; {py} {t['write_csv_python_s']:.2f} s" if "write_csv_python_s" in t else "") + " |",
        *([f"| write {n} values, CSV beside the input's rows (the command's CSV -> CSV) | "
           f"{t['write_csv_rows_s']:.2f} | "
           + (f"{py} {t['write_csv_rows_python_s']:.2f} s" if "write_csv_rows_python_s" in t else "") + " |"]
          if "write_csv_rows_s" in t else []),
        f"| `jaxshadow irradiance`, {n} receivers, .csv -> .csv | {t['cli_csv_s']:.1f} | .npy -> .npy "
        f"{t['cli_npy_s']:.1f} s ({t['cli_csv_over_npy']:.2f}x); peak RSS {t['cli_csv_rss_mb']:.0f} MB vs "
        f"{t['cli_npy_rss_mb']:.0f} MB"
        + (f"; {py} {t['cli_csv_python_s']:.1f} s ({t['cli_csv_python_over_npy']:.2f}x), "
           f"{t['cli_csv_python_rss_mb']:.0f} MB" if "cli_csv_python_s" in t else "") + " |",
        f"| `save_scene`, {s['triangles']} triangles | {s['save_s']:.2f} | inline JSON (schema 1) "
        f"{s['inline_save_s']:.2f} s; {s['bytes'] / 1e6:.1f} MB vs {s['inline_bytes'] / 1e6:.1f} MB |",
        f"| `load_scene`, {s['triangles']} triangles | {s['load_s']:.2f} | inline JSON {s['inline_load_s']:.2f} s; "
        f"`js.Mesh` build alone {s['mesh_build_s']:.2f} s |",
    ]
    return "\n".join(rows) + "\n"


def key_numbers(results: dict) -> list[tuple[str, str]]:
    t, s = results["tables"], results["scene"]
    return [("receiver files", f"`jaxshadow irradiance` on {t['n']:.0e} CSV receivers {t['cli_csv_over_npy']:.2f}x "
                               f"the .npy run; a {s['triangles']}-triangle scene saved in {s['save_s']:.2f} s, "
                               f"loaded in {s['load_s']:.2f} s")]
