"""A/B of `fit_light(combinatorics=)`: the soft-shadow kernel's combinatorics in the compiled
program (`"device"`, the default) or in NumPy on the host (`"host"`, `jaxshadow._clip_host`).

Each round runs, for both settings, one fresh process per case that times `inverse.fit_light`'s
first call (tracing + compilation + one solve; `jax.monitoring` splits out the tracing, the
lowering and XLA's compilation of every program it compiled) and then the median of three more
calls (the solve alone). Cases: 8 occluders on `inverse._scenes.occluded_light_problem` (48
targets, 8 light parameters, float64; culling needs >= 4 occluders, so with fewer the setting
changes nothing), with 1 start and with 64 starts screened to 8 (the default). Interleaved
rounds: on this shared machine run-to-run drift is as large as the effects.

    .venv/bin/python benchmarks/combinatorics.py [--rounds 3]

Writes results/combinatorics.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

CASES = ((8, 1), (8, 64))
MODES = ("device", "host")


def _child(n_occ: int, starts: int, mode: str) -> dict:
    import jax

    jax.config.update("jax_enable_x64", True)
    from jax._src import monitoring

    import inverse
    from inverse._scenes import occluded_light_problem

    _, start, material, targets = occluded_light_problem(n_occ, n_points=48, seed=0)[:4]
    events: list = []
    monitoring.register_event_duration_secs_listener(lambda name, dur, **kw: events.append((name, dur)))

    def call() -> float:
        t = time.perf_counter()
        fit = inverse.fit_light(start, targets, material, starts=starts, combinatorics=mode)
        jax.block_until_ready(fit.light.vertices)
        return time.perf_counter() - t

    first = call()

    def total(key: str) -> float:
        return sum(d for name, d in events if name.endswith(key))

    stages = {"trace_s": total("jaxpr_trace_duration"), "lower_s": total("jaxpr_to_mlir_module_duration"),
              "compile_s": total("backend_compile_duration")}
    solves = [call() for _ in range(3)]
    return {"first_call_s": first, "solve_s": statistics.median(solves), **stages}


def main() -> None:
    if len(sys.argv) == 5 and sys.argv[1] == "--child":
        print(json.dumps(_child(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4])))
        return
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "combinatorics.json"))
    args = ap.parse_args()
    rows = []
    for r in range(args.rounds):
        for n_occ, starts in CASES:
            for mode in MODES:
                out = subprocess.run([sys.executable, __file__, "--child", str(n_occ), str(starts), mode],
                                     capture_output=True, text=True, check=True)
                d = json.loads(out.stdout.strip().splitlines()[-1])
                rows.append({"round": r, "occluders": n_occ, "starts": starts, "combinatorics": mode, **d})
                print(f"round {r} occluders={n_occ} starts={starts} {mode:6s}: first call {d['first_call_s']:.2f} s "
                      f"(trace {d['trace_s']:.2f}, lower {d['lower_s']:.2f}, XLA {d['compile_s']:.2f}), "
                      f"solve {1e3 * d['solve_s']:.0f} ms", flush=True)
    res = {"load_average_at_end": os.getloadavg(), "rows": rows}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(res, fh, indent=1)

    def pick(n_occ: int, starts: int, mode: str) -> list:
        return sorted((x for x in rows if x["occluders"] == n_occ and x["starts"] == starts
                       and x["combinatorics"] == mode), key=lambda x: x["round"])

    lines = [f"`benchmarks/combinatorics.py`, {args.rounds} interleaved rounds, fresh processes, medians; "
             "`fit_light`'s first call split by `jax.monitoring` (all programs it compiled); solve = median of "
             "the next three calls.", "",
             "| occluders | starts | combinatorics | first call (s) | trace (s) | lower (s) | XLA compile (s) | "
             "solve (ms) |", "|---:|---|---|---:|---:|---:|---:|---:|"]
    for n_occ, starts in CASES:
        for mode in MODES:
            xs = pick(n_occ, starts, mode)

            def med(key: str, xs: list = xs) -> float:
                return statistics.median(x[key] for x in xs)

            label = "1" if starts == 1 else f"{starts} -> best 8"
            lines.append(f"| {n_occ} | {label} | {mode} | {med('first_call_s'):.1f} | {med('trace_s'):.2f} | "
                         f"{med('lower_s'):.2f} | {med('compile_s'):.2f} | {1e3 * med('solve_s'):.0f} |")
    lines += ["", "Median of the per-round ratios host / device:", "", "| occluders | starts | first call | XLA compile | "
              "solve |", "|---:|---|---:|---:|---:|"]
    for n_occ, starts in CASES:
        dev, host = pick(n_occ, starts, "device"), pick(n_occ, starts, "host")

        def ratio(key: str, dev: list = dev, host: list = host) -> float:
            return statistics.median(h[key] / d[key] for h, d in zip(host, dev, strict=True))

        label = "1" if starts == 1 else f"{starts} -> best 8"
        lines.append(f"| {n_occ} | {label} | {ratio('first_call_s'):.2f} | {ratio('compile_s'):.2f} | "
                     f"{ratio('solve_s'):.2f} |")
    with open(os.path.splitext(args.out)[0] + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
