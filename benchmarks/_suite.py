"""The benchmark suite: which benchmarks there are, how a run is recorded, what is generated.

A benchmark is a module `benchmarks/<module>.py` that defines

- `run(quick: bool) -> dict`: measure, and return the results (JSON-serialisable: numbers,
  strings, lists, dicts). `quick=True` is a smoke run (seconds to a minute) whose results are
  kept apart and never reach a README.
- optionally `NAME` (default: the module's name) and `DESCRIPTION` (default: the first line of
  the module docstring), shown by `python -m benchmarks --list`;
- optionally `markdown(results: dict) -> str`: the tables of `benchmarks/README.md`;
- optionally `plot(results: dict, path: pathlib.Path) -> None`: one figure, written to `path`
  (`results/NAME.png`; write it with `benchmarks._suite.save_figure`);
- optionally `key_numbers(results: dict) -> list[tuple[str, str]]`: rows `(what, figure)` of
  the key-numbers table in the top-level README (one current figure per cell, each row under
  `MAX_ROW` characters).

It joins the suite with one line in `SUITE` below. `python -m benchmarks NAME` runs it and
writes `results/NAME.json` (`{"benchmark", "meta", "results"}`: `meta` holds the command, the
commit, the date, the machine and the versions), then regenerates `results/NAME.md`,
`results/NAME.png` and both READMEs' generated blocks from the latest results of every
benchmark (`python -m benchmarks --tables` regenerates them without running anything).

`--list` reads the modules' `NAME` and `DESCRIPTION` without importing them (a benchmark may
need an optional extra such as Mitsuba).
"""

from __future__ import annotations

import ast
import importlib
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
QUICK_RESULTS = RESULTS / "quick"  # smoke runs: git-ignored, never in a README
BENCH_README = HERE / "README.md"
TOP_README = ROOT / "README.md"
MAX_ROW = 400  # characters of one generated README table row

# The suite, in the order `--all` runs it: one line per benchmark module.
SUITE: tuple[str, ...] = (
    "throughput",
    "error_vs_time",
    "specular_error",
    "shadow_error_vs_time",
    "shadows_scale",
    "stability_table",
    "inverse_speed",
    "projective_gradient",
    "fit_lights",
    "fit_global",
    "fit_light",
    "illumination_mesh",
    "bake",
    "real_meshes",
    "mesh_robustness",
    "files_io",
    "surfaces_mitsuba",
)


# Records that a benchmark module writes outside the suite's run (inputs the suite does not
# have, such as mesh files a user downloads), committed and shown in the READMEs: record name ->
# (module, its key-numbers function). Their tables are the committed `results/NAME.md`.
EXTRA_RECORDS: dict[str, tuple[str, str]] = {
    "real_meshes_files_acceptance": ("real_meshes", "key_numbers_files"),
}


# --------------------------------------------------------------------------------------
# The registry
# --------------------------------------------------------------------------------------


def _module_constants(module: str) -> dict[str, str]:
    """`NAME`, `DESCRIPTION` (string constants) and the docstring's first line, by parsing."""
    tree = ast.parse((HERE / f"{module}.py").read_text())
    out = {"NAME": module, "DESCRIPTION": (ast.get_docstring(tree) or "").strip().split("\n")[0]}
    for node in tree.body:
        if isinstance(node, ast.Assign) and isinstance(node.value, ast.Constant) and isinstance(node.value.value, str):
            for target in node.targets:
                if isinstance(target, ast.Name) and target.id in ("NAME", "DESCRIPTION"):
                    out[target.id] = node.value.value
    return out


def listing() -> dict[str, tuple[str, str]]:
    """Benchmark name -> `(module, description)`, in suite order."""
    out = {}
    for module in SUITE:
        c = _module_constants(module)
        if c["NAME"] in out:
            raise ValueError(f"two benchmarks are named {c['NAME']!r}")
        out[c["NAME"]] = (module, c["DESCRIPTION"])
    return out


def load(name: str) -> ModuleType:
    """The module of benchmark `name` (imported)."""
    entries = listing()
    if name not in entries:
        raise ValueError(f"unknown benchmark {name!r}; `python -m benchmarks --list` lists them.")
    return importlib.import_module(f"benchmarks.{entries[name][0]}")


# --------------------------------------------------------------------------------------
# Records
# --------------------------------------------------------------------------------------


def commit() -> str:
    """The checkout's commit (short hash, `+dirty` with uncommitted changes), or `unknown`."""
    def git(*args: str) -> str:
        return subprocess.run(["git", *args], capture_output=True, text=True, cwd=ROOT).stdout.strip()

    head = git("rev-parse", "--short", "HEAD")
    if not head:
        return "unknown"
    return head + ("+dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def meta(name: str, quick: bool) -> dict[str, Any]:
    """What a record says about how it was made."""
    import jax
    import numpy as np

    return {
        "command": f"python -m benchmarks {name}" + (" --quick" if quick else ""),
        "commit": commit(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": f"{platform.machine()}, {os.cpu_count()} cores ({platform.processor() or platform.platform()})",
        "load_average": list(os.getloadavg()),
        "python": platform.python_version(),
        "jax": jax.__version__,
        "numpy": np.__version__,
        "devices": str(jax.devices()),
        "quick": quick,
    }


def _json_default(x: Any) -> Any:
    if hasattr(x, "tolist"):
        return x.tolist()
    return float(x)


def write_json(path: Path, data: Any) -> None:
    """`data` as indented JSON at `path` (atomically; NumPy scalars and arrays as lists). A record's
    `meta` (`meta()`, taken at its start) gets `load_average_end`: the load at its end, so that a
    record made while the machine filled up says so."""
    from jaxshadow._core.files import atomic_write

    if isinstance(data, dict) and isinstance(data.get("meta"), dict) and "load_average" in data["meta"]:
        data = {**data, "meta": {**data["meta"], "load_average_end": list(os.getloadavg())}}

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path) as fh:
        json.dump(data, fh, indent=1, default=_json_default)
        fh.write("\n")


def write_text(path: Path, text: str) -> None:
    from jaxshadow._core.files import atomic_write

    with atomic_write(path) as fh:
        fh.write(text)


def save_figure(fig: Any, path: Path, dpi: int = 110) -> None:
    """`fig.savefig(path)` through a temporary file (a benchmark's `plot`)."""
    from jaxshadow._core.files import atomic_write_path

    atomic_write_path(path, lambda tmp: fig.savefig(tmp, dpi=dpi))


def read(name: str, quick: bool = False) -> dict[str, Any] | None:
    """The latest record of benchmark `name` (`{"benchmark", "meta", "results"}`), or None."""
    path = (QUICK_RESULTS if quick else RESULTS) / f"{name}.json"
    if not path.exists():
        return None
    return json.loads(path.read_text())


def run(name: str, quick: bool) -> dict[str, Any]:
    """Run benchmark `name`, write its record, and regenerate its table and figure."""
    mod = load(name)
    info = meta(name, quick)
    t0 = time.perf_counter()
    results = mod.run(quick)
    info["wall_s"] = round(time.perf_counter() - t0, 1)
    record = {"benchmark": name, "meta": info, "results": results}
    out = QUICK_RESULTS if quick else RESULTS
    write_json(out / f"{name}.json", record)
    render(name, record, out)
    return record


# --------------------------------------------------------------------------------------
# Generated tables, figures and README blocks
# --------------------------------------------------------------------------------------


def caption(record: dict[str, Any]) -> str:
    m = record["meta"]
    where = f"commit {m.get('commit', 'unknown')}, {m.get('date', '?')}, {m.get('machine', '?')}"
    return f"`{m.get('command', 'python -m benchmarks ' + record['benchmark'])}` ({where})."


def render(name: str, record: dict[str, Any], out: Path = RESULTS) -> None:
    """`out/NAME.md` and `out/NAME.png` from a record (where the module defines them)."""
    mod = load(name)
    if hasattr(mod, "markdown"):
        write_text(out / f"{name}.md", caption(record) + "\n\n" + mod.markdown(record["results"]).rstrip() + "\n")
    if hasattr(mod, "plot"):
        import matplotlib

        matplotlib.use("Agg")
        mod.plot(record["results"], out / f"{name}.png")


def key_numbers_table() -> str:
    """The top README's key-numbers table, from the latest full results of every benchmark."""
    lines = ["| what | result | from |", "|---|---|---|"]
    for name in listing():
        record = read(name)
        mod = None if record is None else load(name)
        if mod is None or not hasattr(mod, "key_numbers"):
            continue
        for what, figure in mod.key_numbers(record["results"]):
            lines.append(f"| {what} | {figure} | `{name}` ({record['meta'].get('commit', '?')}) |")
    for name, (module, function) in EXTRA_RECORDS.items():
        record = read(name)
        if record is not None:
            for what, figure in getattr(importlib.import_module(f"benchmarks.{module}"), function)(record["results"]):
                lines.append(f"| {what} | {figure} | `{name}` ({record['meta'].get('commit', '?')}) |")
    for row in lines:
        if len(row) > MAX_ROW:
            raise ValueError(f"key-numbers row over {MAX_ROW} characters: {row[:120]}...")
    return "\n".join(lines)


def replace_block(text: str, marker: str, body: str) -> str:
    """`text` with the block between `<!-- marker:start -->` and `<!-- marker:end -->` replaced
    (appended at the end when absent)."""
    start, end = f"<!-- {marker}:start -->", f"<!-- {marker}:end -->"
    block = f"{start}\n{body.rstrip()}\n{end}"
    if start in text and end in text:
        return text[: text.index(start)] + block + text[text.index(end) + len(end):]
    return text.rstrip() + "\n\n" + block + "\n"


def readme_results() -> str:
    """The generated results section of `benchmarks/README.md`: each benchmark's tables."""
    parts = []
    for name, (_, description) in listing().items():
        record = read(name)
        mod = load(name)
        if record is None or not hasattr(mod, "markdown"):
            continue
        parts.append(f"### `{name}`: {description}\n\n{caption(record)}\n\n{mod.markdown(record['results']).rstrip()}")
        if (RESULTS / f"{name}.png").exists():
            parts[-1] += f"\n\n![{name}](results/{name}.png)"
    for name in EXTRA_RECORDS:
        table = RESULTS / f"{name}.md"
        if table.exists():
            parts.append(f"### `{name}`: recorded outside the suite's run\n\n{table.read_text().rstrip()}")
    return "\n\n".join(parts)


def regenerate() -> None:
    """Every table, figure and README block from the latest full results (nothing is run)."""
    for name in listing():
        record = read(name)
        if record is not None:
            render(name, record)
    write_text(BENCH_README, replace_block(BENCH_README.read_text(), "results", readme_results()))
    write_text(TOP_README, replace_block(TOP_README.read_text(), "key numbers", key_numbers_table()))


def main(argv: list[str] | None = None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m benchmarks", description="jaxshadow's benchmark suite.")
    ap.add_argument("names", nargs="*", help="benchmarks to run (see --list)")
    ap.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    ap.add_argument("--all", action="store_true", help="run every benchmark of the suite")
    ap.add_argument("--quick", action="store_true", help="smoke runs: results/quick/, no README change")
    ap.add_argument("--tables", action="store_true", help="regenerate tables, figures and READMEs only")
    args = ap.parse_args(argv)
    entries = listing()
    if args.list:
        width = max(len(n) for n in entries)
        for name, (_, description) in entries.items():
            print(f"{name:{width}s}  {description}")
        return 0
    names = list(entries) if args.all else args.names
    unknown = [n for n in names if n not in entries]
    if unknown:
        ap.error(f"unknown benchmark(s) {unknown}; --list lists them")
    if not names and not args.tables:
        ap.error("name a benchmark, or give --all, --list or --tables")
    for name in names:
        print(f"== {name}", file=sys.stderr, flush=True)
        record = run(name, args.quick)
        print(f"== {name}: {record['meta']['wall_s']} s", file=sys.stderr, flush=True)
    if not args.quick:
        regenerate()
    return 0
