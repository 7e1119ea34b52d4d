"""A/B of `inverse.fit_light` between this tree and another checkout (a baseline commit):
first call (tracing + compilation + one solve) and solve, in fresh processes, interleaved.

Each round runs, for every case and both trees, one fresh process that times `fit_light`'s
first call (`jax.monitoring` splits out the tracing, the lowering and XLA's compilation of
every program it compiled) and then the median of three more calls (the solve alone). Cases:
8 occluders on `inverse._scenes.occluded_light_problem` (48 targets, 8 light parameters,
float64), 1 start and 64 starts screened to 8 (the default), with `combinatorics="host"` (the
default on the CPU) and `"device"`. On this shared machine run-to-run drift is as large as the
effects: compare within a round.

    git worktree add /tmp/base <commit> && (cd /tmp/base && python setup.py build_ext --inplace)
    .venv/bin/python benchmarks/fit_ab.py --baseline /tmp/base [--tree DIR] [--rounds 3] [--name NAME]

`--tree` (default: this checkout) is the tree under test, e.g. a worktree with a prototype
applied (`benchmarks/prototypes/*.patch`; build its C extension there too).

Writes results/NAME.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

CASES = ((1, "host"), (64, "host"), (1, "device"), (64, "device"))
HERE = os.path.dirname(os.path.abspath(__file__))


def _child(starts: int, mode: str) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    from jax._src import monitoring

    import inverse
    from inverse._scenes import occluded_light_problem

    _, start, material, targets = occluded_light_problem(8, n_points=48, seed=0)[:4]
    events: list = []
    monitoring.register_event_duration_secs_listener(lambda name, dur, **kw: events.append((name, dur)))

    def call() -> tuple[float, float]:
        t = time.perf_counter()
        fit = inverse.fit_light(start, targets, material, starts=starts, combinatorics=mode)
        jax.block_until_ready(fit.light.vertices)
        return time.perf_counter() - t, fit.report.loss

    first, loss = call()

    def total(key: str) -> float:
        return sum(d for name, d in events if name.endswith(key))

    stages = {"trace_s": total("jaxpr_trace_duration"), "lower_s": total("jaxpr_to_mlir_module_duration"),
              "compile_s": total("backend_compile_duration")}
    solves = [call()[0] for _ in range(3)]
    return {"first_call_s": first, "solve_s": statistics.median(solves), "loss": loss,
            "source": inverse.__file__, **stages}


def main() -> None:
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        print(json.dumps(_child(int(sys.argv[2]), sys.argv[3])))
        return
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--baseline", required=True, help="root of a checkout of the baseline commit")
    ap.add_argument("--tree", default=os.path.dirname(HERE), help="root of the checkout under test")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--name", default="fit_ab")
    args = ap.parse_args()
    trees = {"this": os.path.abspath(args.tree), "baseline": os.path.abspath(args.baseline)}
    rows = []
    for r in range(args.rounds):
        for starts, mode in CASES:
            for tree, root in trees.items():
                env = {**os.environ, "PYTHONPATH": root}
                out = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", str(starts), mode],
                                     capture_output=True, text=True, check=True, env=env, cwd=root)
                d = json.loads(out.stdout.strip().splitlines()[-1])
                assert d["source"].startswith(root), (d["source"], root)
                rows.append({"round": r, "starts": starts, "combinatorics": mode, "tree": tree, **d})
                print(f"round {r} starts={starts:2d} {mode:6s} {tree:8s}: first call {d['first_call_s']:.2f} s "
                      f"(trace {d['trace_s']:.2f}, lower {d['lower_s']:.2f}, XLA {d['compile_s']:.2f}), "
                      f"solve {1e3 * d['solve_s']:.0f} ms, loss {d['loss']:.1e}", flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=trees["baseline"]).stdout.strip()
    res = {"baseline_commit": commit, "load_average_at_end": os.getloadavg(), "rows": rows}
    out_json = os.path.join(HERE, "results", f"{args.name}.json")
    with open(out_json, "w") as fh:
        json.dump(res, fh, indent=1)

    def pick(starts: int, mode: str, tree: str) -> list:
        return sorted((x for x in rows if x["starts"] == starts and x["combinatorics"] == mode and x["tree"] == tree),
                      key=lambda x: x["round"])

    lines = [f"`benchmarks/fit_ab.py --baseline` (commit {commit}), {args.rounds} interleaved rounds, fresh "
             "processes, 8 occluders, 48 targets; medians. Compile = first call - solve.", "",
             "| starts | combinatorics | tree | first call (s) | trace (s) | lower (s) | XLA (s) | compile, by round (s) "
             "| solve, by round (ms) |", "|---|---|---|---:|---:|---:|---:|---|---|"]
    for starts, mode in CASES:
        for tree in trees:
            xs = pick(starts, mode, tree)

            def med(key: str, xs: list = xs) -> float:
                return statistics.median(x[key] for x in xs)

            comp = " / ".join(f"{x['first_call_s'] - x['solve_s']:.1f}" for x in xs)
            sol = " / ".join(f"{1e3 * x['solve_s']:.0f}" for x in xs)
            label = "1" if starts == 1 else f"{starts} -> best 8"
            lines.append(f"| {label} | {mode} | {tree} | {med('first_call_s'):.2f} | {med('trace_s'):.2f} | "
                         f"{med('lower_s'):.2f} | {med('compile_s'):.2f} | {comp} | {sol} |")
    lines += ["", "Median of the per-round ratios this / baseline:", "",
              "| starts | combinatorics | first call | compile | solve |", "|---|---|---:|---:|---:|"]
    for starts, mode in CASES:
        a, b = pick(starts, mode, "this"), pick(starts, mode, "baseline")

        def ratio(fn, a: list = a, b: list = b) -> float:
            return statistics.median(fn(x) / fn(y) for x, y in zip(a, b, strict=True))

        label = "1" if starts == 1 else f"{starts} -> best 8"
        lines.append(f"| {label} | {mode} | {ratio(lambda x: x['first_call_s']):.2f} | "
                     f"{ratio(lambda x: x['first_call_s'] - x['solve_s']):.2f} | {ratio(lambda x: x['solve_s']):.2f} |")
    with open(os.path.splitext(out_json)[0] + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
