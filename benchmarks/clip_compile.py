"""Compile time of the shadow kernel's Jacobian: the clipping kernel as it is, and a sort-free
formulation of the same boundary (session 6's experiment, kept so that it can be re-run).

Why this exists: a light fit's first call is dominated by XLA:CPU compiling the residual's
forward-mode Jacobian, and sessions 3-5 traced that to the clipping kernel's sorts, cumulative
minima, `nonzero` compactions and gathers. `sort_free_form_factor` below removes all of them:
on the line of each candidate edge the visible part of [0, 1] is [0, 1] minus the blocking
intervals, and since Lambert's edge term G is additive along a line, its contribution is
sum_b s_b G(t_b) over the breakpoints {0, 1, lo_k, hi_k} with s_b = [free just left of t_b] -
[free just right] (+1 where a free run ends, -1 where one starts), counting equal breakpoints
once. That needs only pairwise comparisons, no order. It agrees with
`_clip.visible_form_factor_kernel` to 1e-16 (checked here) but compiles no faster: XLA:CPU's
fused-loop count stays at ~200, because its fusion pass refuses to duplicate the many
intermediates that several consumers read ("code duplication too high", "fusion is not
profitable" for divisions and square roots), not because of the sorts.

    .venv/bin/python benchmarks/clip_compile.py [--occluders 1 3]

Each (kernel, occluder count) is timed in a fresh process: trace + lowering, XLA compile,
number of fused loops, and one evaluation of value + Jacobian (6 light parameters, 48
receivers, float64).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from jaxshadow._bsp import culled_form_factor_kernel  # noqa: E402
from jaxshadow._clip import (  # noqa: E402
    _candidates,
    _decode,
    edge_breakpoints,
    visible_form_factor_kernel,
)
from jaxshadow._geometry import newell_normal  # noqa: E402
from jaxshadow._polygon import edge_term  # noqa: E402

LIGHT = np.array([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2.0]])


def sort_free_form_factor(p, n, verts, occluders):
    """`_clip.visible_form_factor_kernel` by the telescoped breakpoint sum (module docstring),
    with `_clip`'s candidates, intervals, one-sided membership, tie-break and endpoint codes."""
    m_occ = occluders.shape[0]
    c = _candidates(p, n, verts, occluders)
    ps, cs = jax.lax.stop_gradient((p, c))
    dtype = p.dtype
    region_ids = jnp.arange(m_occ + 1, dtype=jnp.int32)

    def weights(ci, a, b, n_own, i_own, sig, reg):
        lo, hi, c_nc, c_c, any_c, other, ts, codes = edge_breakpoints(ps, cs, m_occ, ci, a, b, n_own, i_own,
                                                                      sig, reg)
        member = c_nc & c_c & cs.reg_active & (region_ids > 0)
        tie = c_nc & any_c & (region_ids < reg)
        blocks = other & (member | tie)
        on = jnp.concatenate([jnp.ones((2,), bool), blocks, blocks])
        t = ts[:, None]
        left_in = jnp.any(blocks[None, :] & (lo[None, :] < t) & (t <= hi[None, :]), axis=1)
        right_in = jnp.any(blocks[None, :] & (lo[None, :] <= t) & (t < hi[None, :]), axis=1)
        idx = jnp.arange(ts.shape[0])
        dup = jnp.any((ts[None, :] == ts[:, None]) & on[None, :] & (idx[None, :] < idx[:, None]), axis=1)
        s = ((ts > 0) & ~left_in).astype(jnp.int32) - ((ts < 1) & ~right_in).astype(jnp.int32)
        return codes, jnp.where(on & ~dup, s, 0)

    codes, s = jax.vmap(weights)(jnp.arange(cs.starts.shape[0], dtype=jnp.int32), cs.starts, cs.ends, cs.own, cs.own_id,
                                 cs.sigma, cs.region)
    s = jnp.where(cs.in_front, s, 0)
    x = _decode(p, c, codes.reshape(-1)).reshape(codes.shape + (3,))
    term = jax.vmap(jax.vmap(edge_term, in_axes=(None, None, None, 0)), in_axes=(None, None, 0, 0))
    f = -jnp.sum(jnp.where(s != 0, s.astype(dtype) * term(p, n, c.starts, x), 0.0)) / (2 * jnp.pi)
    return jnp.where(jnp.dot(newell_normal(verts), p - verts[0]) > 0, f, 0.0)


def _occluders(rng, m):
    out = []
    for centre in rng.uniform([-0.2, -0.2, 0.8], [1.2, 1.2, 1.6], (m, 3)):
        rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
        sq = np.array([[-0.2, -0.2, 0], [0.2, -0.2, 0], [0.2, 0.2, 0], [-0.2, 0.2, 0]]) * rng.uniform(0.5, 2)
        out.append(centre + sq @ rot.T * np.array([1, 1, 0.3]))
    return jnp.asarray(np.array(out))


def agreement(trials=20, n_points=200):
    """Max |sort-free - `_clip`| over random receivers and occluder sets (M = 1, 2, 3, 5)."""
    rng = np.random.default_rng(1)
    worst = 0.0
    a_fn = jax.jit(jax.vmap(visible_form_factor_kernel, in_axes=(0, 0, None, None)))
    b_fn = jax.jit(jax.vmap(sort_free_form_factor, in_axes=(0, 0, None, None)))
    for m in (1, 2, 3, 5):
        for _ in range(trials):
            occ = _occluders(rng, m)
            pts = jnp.asarray(rng.uniform([-0.5, -0.5, -0.2], [1.5, 1.5, 0.3], (n_points, 3)))
            nrm = rng.normal(size=(n_points, 3)) * 0.3 + np.array([0, 0, 1])
            nrm = jnp.asarray(nrm / np.linalg.norm(nrm, axis=1, keepdims=True))
            worst = max(worst, float(jnp.max(jnp.abs(a_fn(pts, nrm, jnp.asarray(LIGHT), occ)
                                                     - b_fn(pts, nrm, jnp.asarray(LIGHT), occ)))))
    return worst


def _child(which, m):
    rng = np.random.default_rng(1)
    occ = jnp.asarray(np.array([[[0.3, 0.3, 1.2], [0.6, 0.3, 1.2], [0.6, 0.6, 1.25], [0.3, 0.6, 1.25]]] * m)
                      + rng.uniform(-0.3, 0.3, (m, 1, 3)))
    pts = jnp.asarray(rng.uniform([-0.5, -0.5, -0.2], [1.5, 1.5, 0.3], (48, 3)))
    nrm = jnp.tile(jnp.array([0, 0, 1.0]), (48, 1))
    kern = {"clip (full soup)": lambda p, q, v: visible_form_factor_kernel(p, q, v, occ),
            "clip, culled + compacted": lambda p, q, v: culled_form_factor_kernel(p, q, v, occ, m)[0],
            "sort-free": lambda p, q, v: sort_free_form_factor(p, q, v, occ)}[which]
    light = jnp.asarray(LIGHT)

    def f(theta):
        v = light + theta[:3][None, :] + theta[3:6][None, :] * light
        return jax.vmap(kern, in_axes=(0, 0, None))(pts, nrm, v)

    fn = jax.jit(lambda th: (f(th), jax.jacfwd(f)(th)))
    th = jnp.zeros(6)
    t0 = time.perf_counter()
    lowered = fn.trace(th).lower()
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    jax.block_until_ready(compiled(th))
    t3 = time.perf_counter()
    for _ in range(20):
        jax.block_until_ready(compiled(th))
    run = (time.perf_counter() - t3) / 20
    print(json.dumps({"kernel": which, "occluders": m, "trace_lower_s": t1 - t0, "compile_s": t2 - t1,
                      "fusions": compiled.as_text().count(" fusion("), "run_ms": 1e3 * run}))


def main():
    if len(sys.argv) == 4 and sys.argv[1] == "--child":
        _child(sys.argv[2], int(sys.argv[3]))
        return
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--occluders", type=int, nargs="+", default=[1, 3])
    args = ap.parse_args()
    print(f"sort-free vs _clip, max |difference| of F: {agreement():.1e}")
    print("| kernel | occluders | trace + lower (s) | XLA compile (s) | fused loops | value + Jacobian (ms) |")
    print("|---|---:|---:|---:|---:|---:|")
    for which in ("clip (full soup)", "clip, culled + compacted", "sort-free"):
        for m in args.occluders:
            r = subprocess.run([sys.executable, __file__, "--child", which, str(m)], capture_output=True, text=True,
                               check=True)
            d = json.loads(r.stdout.strip().splitlines()[-1])
            print(f"| {which} | {m} | {d['trace_lower_s']:.1f} | {d['compile_s']:.1f} | {d['fusions']} | "
                  f"{d['run_ms']:.1f} |", flush=True)


if __name__ == "__main__":
    main()
