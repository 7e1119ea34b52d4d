"""A/B of `inverse._lm.FIT_COMPILER_OPTIONS`: the light fit's first call and its solves, compiled
with XLA:CPU's defaults and with the fit options, in fresh processes, interleaved.

Each round runs, for both settings, a fresh process per case that times the first
`inverse.fit_light` call (tracing + compilation + one solve) and the median of three more
(the solve). Cases: 1 occluder / 1 start, 8 occluders / 1 start, 8 occluders / 64 starts
screened to 8 (the default) on `inverse._scenes.occluded_light_problem` (48 targets, 8 light
parameters, float64). Interleaving matters: on this shared machine run-to-run drift is of
the same size as the effect.

    .venv/bin/python benchmarks/fit_compiler_options.py [--rounds 3]

Writes results/fit_compiler_options.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

CASES = ((1, 1), (8, 1), (8, 64))


def _child(n_occ: int, starts: int, defaults: bool) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    import numpy as np

    from inverse import _lm

    if defaults:
        _lm.FIT_COMPILER_OPTIONS = {}
    import inverse
    from inverse._scenes import occluded_light_problem

    _, start, material, targets = occluded_light_problem(n_occ, n_points=48, seed=0)[:4]
    times = []
    for _ in range(4):
        t0 = time.perf_counter()
        fit = inverse.fit_light(start, targets, material, starts=starts)
        jax.block_until_ready(fit.light.vertices)
        times.append(time.perf_counter() - t0)
    print(json.dumps({"first_call_s": times[0], "solve_s": float(np.median(times[1:]))}))


def main() -> None:
    if len(sys.argv) == 5 and sys.argv[1] == "--child":
        _child(int(sys.argv[2]), int(sys.argv[3]), sys.argv[4] == "defaults")
        return
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "fit_compiler_options.json"))
    args = ap.parse_args()
    from inverse._lm import FIT_COMPILER_OPTIONS

    rows = []
    for r in range(args.rounds):
        for setting in ("defaults", "fit options"):
            for n_occ, starts in CASES:
                out = subprocess.run([sys.executable, __file__, "--child", str(n_occ), str(starts),
                                      "defaults" if setting == "defaults" else "fit"],
                                     capture_output=True, text=True, check=True)
                d = json.loads(out.stdout.strip().splitlines()[-1])
                rows.append({"round": r, "setting": setting, "occluders": n_occ, "starts": starts, **d})
                print(f"round {r} {setting:11s} occluders={n_occ} starts={starts}: first call "
                      f"{d['first_call_s']:.1f} s, solve {1e3 * d['solve_s']:.0f} ms", flush=True)
    res = {"fit_compiler_options": FIT_COMPILER_OPTIONS, "load_average_at_end": os.getloadavg(), "rows": rows}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(res, fh, indent=1)
    lines = [f"`benchmarks/fit_compiler_options.py`, {args.rounds} interleaved rounds, fresh process per "
             f"entry; fit options {FIT_COMPILER_OPTIONS}.", "",
             "| occluders | starts | first call, defaults (s) | first call, fit options (s) | "
             "solve, defaults (ms) | solve, fit options (ms) |", "|---:|---:|---|---|---|---|"]
    def col(setting, key, scale, fmt, n_occ, starts):
        vals = [scale * x[key] for x in rows if x["setting"] == setting and x["occluders"] == n_occ
                and x["starts"] == starts]
        return " / ".join(fmt.format(v) for v in vals)

    for n_occ, starts in CASES:
        case = (n_occ, starts)
        start_label = "64 -> best 8" if starts == 64 else str(starts)
        lines.append(f"| {n_occ} | {start_label} | {col('defaults', 'first_call_s', 1, '{:.1f}', *case)} | "
                     f"{col('fit options', 'first_call_s', 1, '{:.1f}', *case)} | "
                     f"{col('defaults', 'solve_s', 1e3, '{:.0f}', *case)} | "
                     f"{col('fit options', 'solve_s', 1e3, '{:.0f}', *case)} |")
    with open(os.path.splitext(args.out)[0] + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
