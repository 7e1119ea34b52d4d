r"""Study (not library code): the culled soft-shadow kernel by inclusion-exclusion, without the
sort, the runs and the compaction of `jaxshadow._clip`.

The visible region is $R = E_h \setminus \bigcup_j Q_j$ (`jaxshadow._clip` module docstring);
every region is a convex cone of planes through the receiver $p$. Its form factor is

$$F(R) = \sum_{S \subseteq \{1..A\}} (-1)^{|S|} F\big(E_h \cap \textstyle\bigcap_{j \in S} Q_j\big),$$

and the boundary of an intersection of convex regions is the union of each region's edges
clipped to all the others (Cyrus-Beck against their planes, one interval per edge): a static
edge list of $\sum_S [(K+1) + |S|(K_o+1)]$ edges (100 for a quad light, quad occluders and
$A = 3$), with no sorting and no compaction. Candidate edges, planes, the one-sided interval
test and the crossing points are `_clip`'s own (`_candidates`, `_interval_on_region`,
`_crossing_point`, so shared endpoints are bit-identical); coincident edges follow `_clip`'s
priority (a region's edge on another region's same-side plane counts only in the lower-index
region; opposite sides drop both).

Measured here: agreement with `_bsp.culled_visible_edges` on random receivers, and the
compile time of the light fit's residual and Jacobian (`jax.linearize` + the linear map on the
basis, as `inverse/_lm.py`) with either kernel, in fresh interleaved processes. Result
(`benchmarks/README.md`, Session 9): the same values to ~5e-17, but only ~10-15% less XLA
compile time, because most of the program is the regions, the intervals and the geometry's
tangents, which both kernels share; so it was not adopted.

    .venv/bin/python benchmarks/inclusion_exclusion.py [--rounds 2]

Writes results/inclusion_exclusion.{json,md}.
"""

from __future__ import annotations

import argparse
import functools
import itertools
import json
import os
import statistics
import subprocess
import sys
import time

import numpy as np


@functools.cache
def _tables(k: int, ko: int, a: int) -> tuple[np.ndarray, ...]:
    """Static edge list: per edge its candidate index (`_clip._candidates` numbering), the regions
    that clip it, its sign $(-1)^{|S|}$ (times -1 for occluder candidates, which `_candidates`
    reverses) and the regions of its subset (all must be active)."""
    n_reg = a + 1
    cand, mask, sign, subset = [], [], [], []
    for size in range(a + 1):
        for s in itertools.combinations(range(1, a + 1), size):
            t = (0, *s)
            for x in t:
                idx = range(k + 1) if x == 0 else range(k + 1 + (x - 1) * (ko + 1), k + 1 + x * (ko + 1))
                m = np.array([y in t and y != x for y in range(n_reg)])
                for c in idx:
                    cand.append(c)
                    mask.append(m)
                    sign.append((-1) ** size * (1 if x == 0 else -1))
                    subset.append(np.array([y in t for y in range(n_reg)]))
    return np.asarray(cand, np.int32), np.asarray(mask), np.asarray(sign), np.asarray(subset)


def ie_visible_edges(p, n, verts, occ):
    """The visible region's boundary by inclusion-exclusion for the selected occluders `occ (A, Ko,
    3)` (all-zero dummies are inactive): `(starts, ends)`, each `(E, 3)`, dropped edges at e0."""
    import jax
    import jax.numpy as jnp

    from jaxshadow._clip import (
        COLLINEAR_EPS,
        _candidates,
        _crossing_point,
        _eps,
        _interval_on_region,
    )

    a_occ, ko, k = occ.shape[0], occ.shape[1], verts.shape[0]
    c = _candidates(p, n, verts, occ)
    cand, mask, sign, subset = _tables(k, ko, a_occ)
    n_reg, n_planes = a_occ + 1, c.planes.shape[1]
    sp, sc = jax.lax.stop_gradient((p, c))
    one = jnp.ones((), p.dtype)

    def per_cand(a, b, own):
        return jax.vmap(_interval_on_region, in_axes=(None, None, None, None, None, 0, 0, None))(
            sp, a, b - a, own, one, sc.planes, sc.reg_valid, COLLINEAR_EPS * _eps(p))

    lo, hi, i_lo, i_hi, cnc, cc, anyc = jax.vmap(per_cand)(sc.starts, sc.ends, sc.own)  # (C, R)
    reg = np.concatenate([np.zeros(k + 1, np.int32), np.repeat(np.arange(1, n_reg), ko + 1)])
    earlier = reg[:, None] < np.arange(n_reg)[None, :]
    ok = cnc & (~anyc | (cc & earlier)) & sc.reg_active[None, :]
    # Occluder candidates are already clipped to E_h; only a coincidence with its planes drops them.
    occ_c = reg > 0
    lo = lo.at[:, 0].set(jnp.where(occ_c, -jnp.inf, lo[:, 0]))
    hi = hi.at[:, 0].set(jnp.where(occ_c, jnp.inf, hi[:, 0]))
    ok = ok.at[:, 0].set(jnp.where(occ_c, ~anyc[:, 0], ok[:, 0]))
    m = jnp.asarray(mask)
    lo_e = jnp.where(m, lo[cand], -jnp.inf)
    hi_e = jnp.where(m, hi[cand], jnp.inf)
    r_lo, r_hi = jnp.argmax(lo_e, axis=1), jnp.argmin(hi_e, axis=1)
    t0 = jnp.take_along_axis(lo_e, r_lo[:, None], 1)[:, 0]
    t1 = jnp.take_along_axis(hi_e, r_hi[:, None], 1)[:, 0]
    keep = jnp.all(~m | ok[cand], axis=1) & (jnp.maximum(t0, 0.0) < jnp.minimum(t1, 1.0))
    keep = keep & jnp.all(~jnp.asarray(subset) | sc.reg_active[None, :], axis=1) & sc.in_front
    own_id, planes = c.own_id[cand], c.planes.reshape(-1, 3)

    def crossing(pid):
        i, j = jnp.minimum(own_id, pid), jnp.maximum(own_id, pid)
        return jax.vmap(_crossing_point, in_axes=(None, 0, None, None))(
            p, jnp.cross(planes[i], planes[j]), c.ne, c.hp)

    s = jnp.where((t0 > 0)[:, None], crossing(r_lo * n_planes + i_lo[cand, r_lo]), c.starts[cand])
    e = jnp.where((t1 < 1)[:, None], crossing(r_hi * n_planes + i_hi[cand, r_hi]), c.ends[cand])
    neg = jnp.asarray(sign < 0)[:, None]
    s, e = jnp.where(neg, e, s), jnp.where(neg, s, e)
    return jnp.where(keep[:, None], s, c.e0[None]), jnp.where(keep[:, None], e, c.e0[None])


def ie_culled_visible_edges(p, n, verts, occluders, max_active, closed=False, host=False):
    """Drop-in for `jaxshadow._bsp.culled_visible_edges` (the same selection)."""
    from jaxshadow._bsp import select_occluders

    active, _, overflow = select_occluders(p, n, verts, occluders, max_active, closed)
    s, e = ie_visible_edges(p, n, verts, active)
    return s, e, overflow


def _agreement() -> list[dict]:
    import jax
    import jax.numpy as jnp

    from inverse._scenes import occluded_light_problem
    from jaxshadow._bsp import culled_visible_edges, occluder_relevance
    from jaxshadow._clip import masked_contour_form_factor

    def ff(edges, cap):
        def one(p, n, em, occ):
            s, e, over = edges(p, n, em, occ, cap)
            return masked_contour_form_factor(p, n, em, s, e), over
        return jax.jit(jax.vmap(one, in_axes=(0, 0, None, None)))

    rows = []
    for seed in range(4):
        scene = occluded_light_problem(8, n_points=8, seed=seed)[0]
        em, occ = jnp.asarray(scene.lights[0].vertices), jnp.asarray(scene.occluders)
        rng = np.random.default_rng(seed)
        p = np.c_[rng.uniform(-1.2, 1.2, (512, 2)), rng.uniform(-0.2, 0.3, 512)]
        nrm = rng.normal(size=(512, 3))
        nrm[:, 2] = np.abs(nrm[:, 2]) + 0.3
        p, nrm = jnp.asarray(p), jnp.asarray(nrm / np.linalg.norm(nrm, axis=1, keepdims=True))
        counts = np.sum(np.asarray(jax.vmap(occluder_relevance, in_axes=(0, 0, None, None))(p, nrm, em, occ)), 1)
        for cap in (2, 3, 4):
            fd, od = ff(culled_visible_edges, cap)(p, nrm, em, occ)
            fi, oi = ff(ie_culled_visible_edges, cap)(p, nrm, em, occ)
            good = ~np.asarray(od)
            assert np.array_equal(np.asarray(oi), np.asarray(od))
            rows.append({"seed": seed, "capacity": cap, "receivers": int(good.sum()),
                         "shadowed": int(np.sum(good & (counts > 0))), "max_relevant": int(counts.max()),
                         "max_abs_diff": float(np.max(np.abs(np.asarray(fi) - np.asarray(fd))[good]))})
    return rows


def _child(kernel: str) -> dict:
    import dataclasses

    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import inverse._lights as lights
    import jaxshadow._bsp as bsp
    from inverse._lm import FIT_COMPILER_OPTIONS
    from inverse._scenes import occluded_light_problem

    if kernel == "inclusion-exclusion":
        bsp.culled_visible_edges = ie_culled_visible_edges
    _, start, material, targets = occluded_light_problem(8, n_points=48, seed=0)[:4]
    param = lights.LightParametrisation(start.lights[0], 0, ("position", "orientation", "size"), None,
                                        lights.scene_size(start, targets), "sigmoid")
    setup = lights._Setup(param, start, material, targets, None, False, False, False)
    setup = dataclasses.replace(setup, max_active=3)  # the capacity the 48-target fit uses
    y = param.theta0(jnp.float64)

    def rj(th):
        r, lin, flag = jax.linearize(lambda z: lights._residuals_culled(z, setup), th, has_aux=True)
        return r, jax.vmap(lin, out_axes=1)(jnp.eye(th.shape[0], dtype=th.dtype)), flag

    t0 = time.perf_counter()
    traced = jax.jit(rj).trace(y)
    t1 = time.perf_counter()
    lowered = traced.lower()
    t2 = time.perf_counter()
    compiled = lowered.compile(FIT_COMPILER_OPTIONS)
    t3 = time.perf_counter()
    jax.block_until_ready(compiled(y))
    ts = []
    for _ in range(20):
        t = time.perf_counter()
        jax.block_until_ready(compiled(y))
        ts.append(time.perf_counter() - t)
    return {"trace_s": t1 - t0, "lower_s": t2 - t1, "compile_s": t3 - t2, "call_ms": 1e3 * statistics.median(ts)}


KERNELS = ("runs (library)", "inclusion-exclusion")


def main() -> None:
    if len(sys.argv) == 3 and sys.argv[1] == "--child":
        print(json.dumps(_child(sys.argv[2])))
        return
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "results", "inclusion_exclusion.json"))
    args = ap.parse_args()
    import jax

    jax.config.update("jax_enable_x64", True)
    agree = _agreement()
    print(f"max |F_ie - F_runs| over {len(agree)} scene x capacity cases: "
          f"{max(r['max_abs_diff'] for r in agree):.2e}", flush=True)
    rows = []
    for r in range(args.rounds):
        for kernel in KERNELS:
            out = subprocess.run([sys.executable, __file__, "--child", kernel], capture_output=True, text=True,
                                 check=True)
            d = json.loads(out.stdout.strip().splitlines()[-1])
            rows.append({"round": r, "kernel": kernel, **d})
            print(f"round {r} {kernel:20s}: trace {d['trace_s']:.2f} s, lower {d['lower_s']:.2f} s, "
                  f"XLA {d['compile_s']:.2f} s, call {d['call_ms']:.1f} ms", flush=True)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump({"agreement": agree, "compile": rows, "load_average_at_end": os.getloadavg()}, fh, indent=1)
    lines = [f"`benchmarks/inclusion_exclusion.py`: float64 form factors of 512 random receivers x 4 scenes "
             f"(8 occluders) x capacities 2-4, max |F_ie - F_runs| = "
             f"{max(r['max_abs_diff'] for r in agree):.1e} (identical overflow flags); the light fit's residual "
             f"and Jacobian (48 targets, 8 occluders, capacity 3), {args.rounds} interleaved rounds of fresh "
             "processes, medians:", "",
             "| kernel | trace (s) | lower (s) | XLA compile (s) | one call (ms) |", "|---|---:|---:|---:|---:|"]
    for kernel in KERNELS:
        xs = [x for x in rows if x["kernel"] == kernel]

        def med(key: str, xs: list = xs) -> float:
            return statistics.median(x[key] for x in xs)

        lines.append(f"| {kernel} | {med('trace_s'):.2f} | {med('lower_s'):.2f} | {med('compile_s'):.2f} | "
                     f"{med('call_ms'):.1f} |")
    with open(os.path.splitext(args.out)[0] + ".md", "w") as fh:
        fh.write("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
