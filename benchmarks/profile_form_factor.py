"""Where the time of the batched form factor goes: variants of the same formula, side by side.

    .venv/bin/python -m benchmarks.profile_form_factor [--n 1000000] [--reps 5]

Variants (all float32, the quad light of `benchmarks.run`, same receivers):

- `vmap kernel`: `jit(vmap(form_factor_kernel))`, what `js.form_factor` runs;
- `SoA, (N,3) input`: `soa_prototype.form_factor_soa` (component arrays sliced from (N, 3));
- `SoA, (3,N) input`: the same with the inputs already transposed to (3, N);
- `SoA, no clipping`: the contour sum alone (lower bound: what the clipping costs);
- `NumPy`: `numpy_reference.form_factor_numpy`.

Also prints the fusion/reduction/concatenate counts of the compiled HLO of the vmap kernel.
Writes `benchmarks/results/profile_form_factor.json`.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks import soa_prototype  # noqa: E402
from benchmarks.numpy_reference import form_factor_numpy  # noqa: E402
from benchmarks.run import QUAD, RESULTS, receivers, time_side_by_side  # noqa: E402
from jaxshadow._polygon import form_factor_kernel  # noqa: E402


@jax.jit
def _soa_transposed(pt, nt, verts):
    return soa_prototype.form_factor_soa.__wrapped__(pt.T, nt.T, verts)


@jax.jit
def _soa_no_clip(pt, nt, verts):
    px, py, pz = pt[0], pt[1], pt[2]
    nx, ny, nz = nt[0], nt[1], nt[2]
    k = verts.shape[0]
    total = jnp.zeros_like(px)
    for i in range(k):
        total = total + soa_prototype._edge_term_soa(px, py, pz, nx, ny, nz, verts[i], verts[(i + 1) % k])
    return -total / (2 * jnp.pi)


def hlo_counts(fn, *args) -> dict:
    txt = jax.jit(fn).lower(*args).compile().as_text()
    entry = txt[txt.index("ENTRY") :]
    return {k: entry.count(k) for k in (" fusion(", " reduce(", "concatenate", "dot(", "custom-call")}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=1_000_000)
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args(argv)
    p_np, n_np = receivers(args.n, np.float32)
    p, nr = jnp.asarray(p_np), jnp.asarray(n_np)
    pt, nt = jnp.asarray(p_np.T.copy()), jnp.asarray(n_np.T.copy())
    q = jnp.asarray(QUAD, jnp.float32)
    core = jax.jit(jax.vmap(form_factor_kernel, in_axes=(0, 0, None)))
    t = time_side_by_side(
        {
            "vmap kernel": lambda: core(p, nr, q),
            "SoA, (N,3) input": lambda: soa_prototype.form_factor_soa(p, nr, q),
            "SoA, (3,N) input": lambda: _soa_transposed(pt, nt, q),
            "SoA, no clipping": lambda: _soa_no_clip(pt, nt, q),
            "NumPy": lambda: form_factor_numpy(p_np, n_np, QUAD.astype(np.float32)),
        },
        args.reps,
    )
    ref = np.asarray(core(p, nr, q))
    diff = float(np.max(np.abs(np.asarray(_soa_transposed(pt, nt, q)) - ref)))
    out = {
        "n": args.n,
        "seconds": {k: v["best_s"] for k, v in t.items()},
        "speedup_vs_numpy": {k: t["NumPy"]["best_s"] / v["best_s"] for k, v in t.items()},
        "max_abs_diff_soa_vs_kernel": diff,
        "hlo_vmap_kernel": hlo_counts(lambda a, b: core(a, b, q), p[:1000], nr[:1000]),
        "hlo_soa": hlo_counts(lambda a, b: _soa_transposed(a, b, q), pt[:, :1000], nt[:, :1000]),
    }
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "profile_form_factor.json").write_text(json.dumps(out, indent=1))
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
