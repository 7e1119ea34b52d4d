"""A/B of the LM's Jacobian: `jax.linearize` (the default) against `jax.jacfwd`, in the light fit.

`inverse._lm.batched_levenberg_marquardt(..., jacobian=)`. Each round runs, for both settings,
one fresh process per case that

- builds the light fit's LM program on the culled soft-shadow residual (as `fit_light` does,
  1 start) and times its stages: tracing, lowering to StableHLO, XLA compilation, and one
  solve after compilation (median of three);
- then times the first `inverse.fit_light` call (tracing + compilation + one solve, every
  program of the fit) with the same setting, in a second fresh process.

Cases: 1 and 8 occluders on `inverse._scenes.occluded_light_problem` (48 targets, 8 light
parameters, float64), with `inverse._lm.FIT_COMPILER_OPTIONS`. Interleaving matters: on this
shared machine run-to-run drift is as large as the effect.

    .venv/bin/python benchmarks/lm_jacobian.py [--rounds 5]

Writes results/lm_jacobian.{json,md}.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time

CASES = (1, 8)
MODES = ("jacfwd", "linearize")


def _stages(n_occ: int, mode: str) -> dict:
    import dataclasses

    import equinox as eqx
    import jax

    from inverse import _lights as L
    from inverse._lm import FIT_COMPILER_OPTIONS, batched_levenberg_marquardt
    from inverse._scenes import occluded_light_problem

    _, start, material, targets = occluded_light_problem(n_occ, n_points=48, seed=0)[:4]
    param = L.LightParametrisation(start.lights[0], 0, ("position", "orientation", "size"), None,
                                   L.scene_size(start, targets), "sigmoid")
    setup = L._Setup(param, start, material, targets, None, False, False, False)
    y0 = L.make_starts(param, 1, search_radius=0.5, orientation_spread=0.5, size_spread=0.5, seed=0,
                       dtype=targets.points.dtype)
    setup = dataclasses.replace(setup, max_active=L.culling_capacity_for_starts(param, start, targets, y0))
    dyn, stat = eqx.partition(setup, eqx.is_array)
    m = 3 * int(targets.points.shape[0])

    def program(dyn, y0):
        return batched_levenberg_marquardt(L._residuals_culled, y0, eqx.combine(dyn, stat), rtol=1e-9,
                                           atol=1e-12, max_steps=100, num_residuals=m, jacobian=mode)

    jf = jax.jit(program, compiler_options=FIT_COMPILER_OPTIONS)
    t0 = time.perf_counter()
    traced = jf.trace(dyn, y0)
    t1 = time.perf_counter()
    lowered = traced.lower()
    t2 = time.perf_counter()
    compiled = lowered.compile()
    t3 = time.perf_counter()
    jax.block_until_ready(compiled(dyn, y0))
    solves = []
    for _ in range(3):
        t = time.perf_counter()
        res = jax.block_until_ready(compiled(dyn, y0))
        solves.append(time.perf_counter() - t)
    hlo = compiled.as_text()
    return {"trace_s": t1 - t0, "lower_s": t2 - t1, "compile_s": t3 - t2, "solve_s": statistics.median(solves),
            "kernels": hlo.count(" fusion(") + hlo.count(" dot("), "steps": int(res.num_steps[0]),
            "loss": float(res.losses[0])}


def _first_call(n_occ: int, mode: str) -> dict:
    import functools

    import jax

    import inverse
    from inverse import _lights
    from inverse._scenes import occluded_light_problem

    _lights.batched_levenberg_marquardt = functools.partial(_lights.batched_levenberg_marquardt, jacobian=mode)
    _, start, material, targets = occluded_light_problem(n_occ, n_points=48, seed=0)[:4]
    t0 = time.perf_counter()
    fit = inverse.fit_light(start, targets, material, starts=1)
    jax.block_until_ready(fit.light.vertices)
    return {"first_call_s": time.perf_counter() - t0}


def _child(what: str, n_occ: int, mode: str) -> None:
    import jax

    jax.config.update("jax_enable_x64", True)
    out = _stages(n_occ, mode) if what == "stages" else _first_call(n_occ, mode)
    print(json.dumps(out))


def _run(what: str, n_occ: int, mode: str) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", what, str(n_occ), mode],
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    if len(sys.argv) == 5 and sys.argv[1] == "--child":
        _child(sys.argv[2], int(sys.argv[3]), sys.argv[4])
        return
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "lm_jacobian.json"))
    args = ap.parse_args()
    rows = []
    for r in range(args.rounds):
        for n_occ in CASES:
            for mode in MODES:
                d = {**_run("stages", n_occ, mode), **_run("first", n_occ, mode)}
                rows.append({"round": r, "occluders": n_occ, "jacobian": mode, **d})
                print(f"round {r} occluders={n_occ} {mode:9s}: trace {d['trace_s']:.2f} s, lower "
                      f"{d['lower_s']:.2f} s, XLA {d['compile_s']:.2f} s, solve {1e3 * d['solve_s']:.0f} ms "
                      f"({d['steps']} steps), {d['kernels']} kernels; fit_light first call "
                      f"{d['first_call_s']:.1f} s", flush=True)
    res = {"load_average_at_end": os.getloadavg(), "rows": rows}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(res, fh, indent=1)

    def med(n_occ: int, mode: str, key: str) -> float:
        return statistics.median(x[key] for x in rows if x["occluders"] == n_occ and x["jacobian"] == mode)

    lines = [f"`benchmarks/lm_jacobian.py`, {args.rounds} interleaved rounds, fresh processes; medians "
             "(LM program with 1 start; `fit_light` first call with 1 start).", "",
             "| occluders | Jacobian | trace (s) | lower (s) | XLA compile (s) | program total (s) | "
             "solve (ms) | kernels | fit_light first call (s) |", "|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
    for n_occ in CASES:
        for mode in MODES:
            tot = statistics.median(x["trace_s"] + x["lower_s"] + x["compile_s"] for x in rows
                                    if x["occluders"] == n_occ and x["jacobian"] == mode)
            lines.append(f"| {n_occ} | {mode} | {med(n_occ, mode, 'trace_s'):.2f} | {med(n_occ, mode, 'lower_s'):.2f} | "
                         f"{med(n_occ, mode, 'compile_s'):.2f} | {tot:.2f} | {1e3 * med(n_occ, mode, 'solve_s'):.0f} | "
                         f"{int(med(n_occ, mode, 'kernels'))} | {med(n_occ, mode, 'first_call_s'):.1f} |")
    with open(os.path.splitext(args.out)[0] + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
