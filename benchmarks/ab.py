"""Interleaved fresh-process A/B of `inverse.fit_light`: first call (tracing + compilation + one
solve) and solve, between variants that differ in the checkout, the solver, or a setting.

On a shared machine run-to-run drift is as large as most effects, so every round runs every
case in every variant, each in a fresh process (nothing cached but the OS's files), and the
ratios are taken within a round. A child process times the first `fit_light` call
(`jax.monitoring` splits out tracing, lowering and XLA compilation of every program it
compiled) and the median of three more calls (the solve alone), on
`benchmarks.inverse_scenes.occluded_light_problem` (48 targets, 8 light parameters, float64).

    python -m benchmarks.ab NAME --variant LABEL[@TREE][=SOLVER] ... [--prelude LABEL=CODE]
        [--occluders 8] [--starts 1 64] [--rounds 3]
    python -m benchmarks.ab --tables            # regenerate results/ab/*.md from the JSON

A variant: `LABEL` names it; `@TREE` runs it on another checkout (build its C extensions there:
`python setup.py build_ext --inplace`), e.g. a baseline commit in `git worktree add /tmp/base
COMMIT`; `=SOLVER` is a Python expression evaluated in `inverse`'s namespace, passed as
`fit_light(solver=...)` (e.g. `LM(combinatorics="device")`; without it `fit_light` runs with
its defaults, which also works on checkouts older than the solver objects); `--prelude
LABEL=CODE` runs `CODE` in that variant's process before the fit (e.g. to change a module
constant). The first variant is the reference of the ratio table.

Examples (the A/B runs behind `benchmarks/README.md`'s decisions):

    python -m benchmarks.ab combinatorics --variant 'device=LM(combinatorics="device")' \\
        --variant 'host=LM(combinatorics="host")'
    python -m benchmarks.ab gc_paused --variant base@/tmp/base --variant this
    python -m benchmarks.ab fit_compiler_options --variant defaults --variant options \\
        --prelude 'defaults=import inverse._lm as m; m.FIT_COMPILER_OPTIONS.clear()'

Writes `benchmarks/results/ab/NAME.json` (the suite's record format) and `NAME.md`.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from typing import Any

HERE = os.path.dirname(os.path.abspath(__file__))
METRICS = {"first_call_s": "first call (s)", "trace_s": "trace (s)", "lower_s": "lower (s)",
           "compile_s": "XLA compile (s)", "solve_s": "solve (ms)"}


def _child(spec: dict) -> dict:
    """In a fresh process: time `fit_light` as `spec` says."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from jax._src import monitoring

    if spec.get("prelude"):
        exec(spec["prelude"], {})
    import inverse

    from .inverse_scenes import occluded_light_problem

    _, start, material, targets = occluded_light_problem(spec["occluders"], n_points=48, seed=0)[:4]
    kw: dict[str, Any] = {"starts": spec["starts"]}
    if spec.get("solver"):
        kw["solver"] = eval(spec["solver"], dict(vars(inverse)))
    events: list = []
    monitoring.register_event_duration_secs_listener(lambda name, dur, **_: events.append((name, dur)))

    def call() -> tuple[float, float]:
        t = time.perf_counter()
        fit = inverse.fit_light(start, targets, material, **kw)
        jax.block_until_ready(fit.light.vertices)
        return time.perf_counter() - t, fit.report.loss

    first, loss = call()

    def total(key: str) -> float:
        return sum(d for name, d in events if name.endswith(key))

    stages = {"trace_s": total("jaxpr_trace_duration"), "lower_s": total("jaxpr_to_mlir_module_duration"),
              "compile_s": total("backend_compile_duration")}
    solves = [call()[0] for _ in range(3)]
    return {"first_call_s": first, "solve_s": statistics.median(solves), "loss": loss, "source": inverse.__file__,
            **stages}


def parse_variant(text: str, preludes: dict[str, str]) -> dict:
    """`LABEL[@TREE][=SOLVER]` -> `{"label", "tree", "solver", "prelude"}`."""
    head, _, solver = text.partition("=")
    label, _, tree = head.partition("@")
    root = os.path.abspath(tree) if tree else os.path.dirname(HERE)
    return {"label": label, "tree": root, "solver": solver or None, "prelude": preludes.get(label)}


def run_ab(variants: list[dict], cases: list[dict], rounds: int) -> list[dict]:
    """Rows `{round, case, variant, first_call_s, trace_s, lower_s, compile_s, solve_s, loss}`."""
    rows = []
    for r in range(rounds):
        for case in cases:
            for v in variants:
                spec = {**case, "solver": v["solver"], "prelude": v["prelude"]}
                env = {**os.environ, "PYTHONPATH": v["tree"]}
                out = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", json.dumps(spec)],
                                     capture_output=True, text=True, check=True, env=env, cwd=v["tree"])
                d = json.loads(out.stdout.strip().splitlines()[-1])
                if not d.pop("source").startswith(v["tree"]):
                    raise RuntimeError(f"variant {v['label']} did not import inverse from {v['tree']}")
                rows.append({"round": r, "case": case, "variant": v["label"], **d})
                print(f"round {r} {case} {v['label']}: first call {d['first_call_s']:.2f} s, solve "
                      f"{1e3 * d['solve_s']:.0f} ms", flush=True)
    return rows


def _case_label(case: dict) -> str:
    return ", ".join(f"{k} {v}" for k, v in case.items())


def markdown(results: dict) -> str:
    """Medians per case and variant, and the median of the per-round ratios to the first variant."""
    rows, labels = results["rows"], [v["label"] for v in results["variants"]]
    cases: list[dict] = []
    for r in rows:
        if r["case"] not in cases:
            cases.append(r["case"])
    metrics = [m for m in METRICS if any(m in r for r in rows)]
    extra = sorted({k for r in rows for k, v in r.items() if k.endswith("_s") and k not in METRICS})
    cols = metrics + extra
    head = [METRICS.get(m, m) for m in cols]
    lines = [f"{results['rounds']} interleaved rounds, fresh processes; medians.", "",
             "| case | variant | " + " | ".join(head) + " |", "|---|---|" + "---:|" * len(cols)]

    def pick(case: dict, label: str) -> list[dict]:
        return sorted((r for r in rows if r["case"] == case and r["variant"] == label), key=lambda r: r["round"])

    def fmt(key: str, value: float) -> str:
        return f"{1e3 * value:.0f}" if key == "solve_s" else f"{value:.2f}"

    for case in cases:
        for label in labels:
            xs = pick(case, label)
            cells = [fmt(c, statistics.median(x[c] for x in xs)) if all(c in x for x in xs) else "-" for c in cols]
            lines.append(f"| {_case_label(case)} | {label} | " + " | ".join(cells) + " |")
    if len(labels) > 1:
        ref = labels[0]
        lines += ["", f"Median of the per-round ratios to `{ref}`:", "",
                  "| case | variant | " + " | ".join(h.replace(" (s)", "").replace(" (ms)", "") for h in head) + " |",
                  "|---|---|" + "---:|" * len(cols)]
        for case in cases:
            base = pick(case, ref)
            for label in labels[1:]:
                xs = pick(case, label)
                cells = [f"{statistics.median(x[c] / b[c] for x, b in zip(xs, base, strict=True)):.2f}"
                         if all(c in x for x in xs + base) else "-" for c in cols]
                lines.append(f"| {_case_label(case)} | {label} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write(name: str, record: dict) -> None:
    """`results/ab/NAME.json` and its table `NAME.md`."""
    from benchmarks._suite import RESULTS, caption, write_json, write_text

    write_json(RESULTS / "ab" / f"{name}.json", record)
    write_text(RESULTS / "ab" / f"{name}.md", caption(record) + "\n\n" + markdown(record["results"]) + "\n")


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["--child"]:
        print(json.dumps(_child(json.loads(argv[1]))))
        return 0
    import argparse

    from benchmarks._suite import RESULTS, meta

    ap = argparse.ArgumentParser(prog="python -m benchmarks.ab", description=__doc__.split("\n\n")[0])
    ap.add_argument("name", nargs="?", help="the A/B's name: results/ab/NAME.{json,md}")
    ap.add_argument("--variant", action="append", default=[], help="LABEL[@TREE][=SOLVER] (at least two)")
    ap.add_argument("--prelude", action="append", default=[], help="LABEL=CODE run before that variant's fit")
    ap.add_argument("--occluders", type=int, nargs="+", default=[8])
    ap.add_argument("--starts", type=int, nargs="+", default=[1, 64])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--tables", action="store_true", help="regenerate results/ab/*.md only")
    args = ap.parse_args(argv)
    if args.tables:
        for path in sorted((RESULTS / "ab").glob("*.json")):
            write(path.stem, json.loads(path.read_text()))
        return 0
    if not args.name or len(args.variant) < 2:
        ap.error("give a NAME and at least two --variant")
    preludes = dict(p.split("=", 1) for p in args.prelude)
    variants = [parse_variant(v, preludes) for v in args.variant]
    cases = [{"occluders": o, "starts": s} for o in args.occluders for s in args.starts]
    info = meta(f"ab {args.name}", False)
    info["command"] = "python -m benchmarks.ab " + " ".join(argv)
    t0 = time.perf_counter()
    rows = run_ab(variants, cases, args.rounds)
    info["wall_s"] = round(time.perf_counter() - t0, 1)
    write(args.name, {"benchmark": f"ab/{args.name}", "meta": info,
                      "results": {"variants": variants, "rounds": args.rounds, "rows": rows}})
    print((RESULTS / "ab" / f"{args.name}.md").read_text())
    return 0


if __name__ == "__main__":
    if sys.argv[1:2] != ["--child"]:
        sys.path.insert(0, os.path.dirname(HERE))
    raise SystemExit(main())
