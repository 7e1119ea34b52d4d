"""Timing shared by the forward-model benchmarks (`throughput`, `error_vs_time`); their inputs
(the quad, the segment, receivers, occluder grids) live in `benchmarks.scenes`, re-exported here.

Method (docs/design.md, "Measuring"): every JAX function is warmed up (its first call, which
includes tracing and XLA compilation, is reported apart as "compile"); steady-state times are the
best of `reps` calls with `block_until_ready`, JAX and the NumPy reference interleaved in the
same run so that the ratio is measured side by side. Batches above `CHUNK` points are evaluated
in chunks of `CHUNK` (fixed shape: one compilation).
"""

from __future__ import annotations

import time
import tracemalloc

import jax
import jax.numpy as jnp
import numpy as np

import jaxshadow as js

from .scenes import QUAD as QUAD
from .scenes import SEG_A as SEG_A
from .scenes import SEG_B as SEG_B
from .scenes import occluder_grid as occluder_grid
from .scenes import receivers as receivers
from .scenes import regular_polygon as regular_polygon

CHUNK = 1_000_000

def chunked(fn, chunk: int = CHUNK):
    """Apply `fn(points, normals)` in fixed-size chunks (the last one padded)."""

    def run(p, n):
        total = p.shape[0]
        if total <= chunk:
            return fn(p, n)
        outs = []
        for s in range(0, total, chunk):
            pc, nc = p[s : s + chunk], n[s : s + chunk]
            short = chunk - pc.shape[0]
            if short:
                pc = jnp.concatenate([pc, jnp.repeat(pc[:1], short, axis=0)])
                nc = jnp.concatenate([nc, jnp.repeat(nc[:1], short, axis=0)])
            out = fn(pc, nc)
            outs.append(out[: chunk - short] if short else out)
        return jnp.concatenate(outs)

    return run


def numpy_chunked(fn, p, n, *args, chunk: int = CHUNK):
    """NumPy reference in chunks of `chunk` points (its (N, K, 3) temporaries would not fit)."""
    if p.shape[0] <= chunk:
        return fn(p, n, *args)
    return np.concatenate([fn(p[s : s + chunk], n[s : s + chunk], *args) for s in range(0, p.shape[0], chunk)])


def _block(x):
    return jax.block_until_ready(x) if isinstance(x, jax.Array) else x


def time_side_by_side(fns: dict, reps: int) -> dict:
    """Interleaved timing. Returns `{name: {"first_s", "best_s", "median_s"}}`."""
    out = {}
    for name, f in fns.items():
        t0 = time.perf_counter()
        _block(f())
        out[name] = {"first_s": time.perf_counter() - t0, "times": []}
    items = list(fns.items())
    for r in range(reps):
        # Rotate the order each repeat: the call right after a long NumPy call finds XLA's
        # worker threads asleep, and a fixed order would always give that slot to one method.
        for name, f in items[r % len(items):] + items[: r % len(items)]:
            t0 = time.perf_counter()
            _block(f())
            out[name]["times"].append(time.perf_counter() - t0)
    for r in out.values():
        ts = r.pop("times")
        r["best_s"] = min(ts) if ts else r["first_s"]
        r["median_s"] = float(np.median(ts)) if ts else r["first_s"]
    return out


def jax_bytes_per_point(fn, *args) -> float:
    """XLA's own accounting (arguments + outputs + temporaries) of one jitted call, per point."""
    try:
        mem = jax.jit(fn).lower(*args).compile().memory_analysis()
        total = mem.argument_size_in_bytes + mem.output_size_in_bytes + mem.temp_size_in_bytes
        return float(total) / args[0].shape[0]
    except Exception:  # noqa: BLE001 - memory stats are optional on some backends
        return float("nan")


def numpy_bytes_per_point(fn, *args) -> float:
    """Peak of NumPy allocations during one call (tracemalloc), including inputs, per point."""
    inputs = sum(a.nbytes for a in args if isinstance(a, np.ndarray))
    tracemalloc.start()
    fn(*args)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return float(peak + inputs) / args[0].shape[0]


# --------------------------------------------------------------------------------------
# Occluder support (the shadowed scene)
# --------------------------------------------------------------------------------------


def shadowed_evaluator():
    """`(fn, note)`: `fn(points, normals, occluders (m, 4, 3)) -> (N,)` form factors of the
    shadowed quad light through the public `js.irradiance`."""

    def public(p, n, occ):
        scene = js.Scene([js.PolygonLight(jnp.asarray(QUAD, p.dtype), 1.0)], occluders=occ)
        return js.irradiance(scene, p, n)[:, 0] / np.pi

    return public, "js.irradiance(scene with occluders) / (pi L)"


def fmt(x, spec=".3g"):
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else format(x, spec)
