r"""The fitted lights' powers at fixed poses under what a designer states: painted ranges and
"brighter than" relations (`_painting`) and a total power budget.

The model is linear in the powers $p$ (`(J,)`, factors of the given radiance):
$L = L_{fixed} + \sum_j p_j\,L^j$. Without ranges, relations or budget the powers are a
non-negative least-squares problem (`scipy.optimize.nnls`, in `_multilight_report`). With them
the residual is piecewise linear in $p$ (`_painting.painted_rows`) and the budget is one
linear inequality $c \cdot p \le B$ ($c_j$ the emitted power of light $j$ at its given
radiance, `emitted_power`): solved by SLSQP (`scipy.optimize.minimize`) with the exact
gradient, then finished exactly on its active set (a KKT system with the active bounds and the
budget as equalities) when that keeps the same active pieces and is feasible.
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array
from scipy.optimize import minimize, nnls

import jaxshadow as js

from ._painting import LUMINANCE, Painting, painted_rows


def emitted_power(light: Any) -> Array | np.ndarray:
    """The power (W) a light emits at its given radiance, averaged over the RGB channels
    (traceable): a polygon $\\pi \\bar L A$ (one-sided Lambertian emitter of area $A$), a
    segment $\\bar\\Phi \\ell$ (power per unit length times length), a point light
    $4\\pi \\bar I$. A directional light has no finite power (ValueError). A light with
    concrete arrays is summed in NumPy (same formula): eager `jnp` operations on the host
    compile one small XLA program each in a fresh process."""
    if isinstance(light, js.DirectionalLight):
        raise ValueError("a power budget: a DirectionalLight has no finite emitted power.")
    traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(light))
    xp: Any = jnp if traced else np
    if isinstance(light, js.PolygonLight):
        v = xp.asarray(light.vertices)
        w = xp.roll(v, -1, axis=0)
        n = xp.sum(xp.stack([v[:, 1] * w[:, 2] - v[:, 2] * w[:, 1], v[:, 2] * w[:, 0] - v[:, 0] * w[:, 2],
                             v[:, 0] * w[:, 1] - v[:, 1] * w[:, 0]], axis=-1), axis=0)
        out, dtype = xp.pi * xp.mean(xp.asarray(light.radiance)) * 0.5 * xp.sqrt(xp.sum(n * n)), v.dtype
    elif isinstance(light, js.LinearLight):
        d = xp.asarray(light.end) - xp.asarray(light.start)
        out, dtype = xp.mean(xp.asarray(light.power)) * xp.sqrt(xp.sum(d * d)), d.dtype
    elif isinstance(light, js.PointLight):
        i = xp.asarray(light.intensity)
        out, dtype = 4.0 * xp.pi * xp.mean(i), i.dtype
    else:
        raise ValueError("a power budget: a DirectionalLight has no finite emitted power.")
    return out if traced else np.asarray(out, dtype)


def painted_jacobian(model: np.ndarray, cols: np.ndarray, sw: np.ndarray, paint: Painting | None) -> np.ndarray:
    """$\\partial r / \\partial p$ `(3N + M, J)` of `painted_rows` at `model (N, 3)`, for the
    model's columns `cols (J, N, 3)` (its derivative in each power); a hinge's inactive side
    has derivative 0."""
    J = cols.shape[0]
    if paint is None:
        return (sw[None] * cols).reshape(J, -1).T
    active = (model < paint.lower) | (model > paint.upper)
    keep = np.where(paint.ranged, active, True)
    out = (sw[None] * np.where(keep[None], cols, 0.0)).reshape(J, -1).T
    if paint.pairs.shape[0] == 0:
        return out
    y = model @ LUMINANCE
    g = y[paint.pairs[:, 1]] - y[paint.pairs[:, 0]] + paint.margin
    yc = cols @ LUMINANCE  # (J, N)
    dg = (yc[:, paint.pairs[:, 1]] - yc[:, paint.pairs[:, 0]]).T  # (M, J)
    return np.concatenate([out, (paint.pair_sw * (g > 0))[:, None] * dg])


def constrained_powers(fixed: np.ndarray, cols: np.ndarray, colours: np.ndarray, sw: np.ndarray,
                       paint: Painting | None, budget: tuple[np.ndarray, float] | None,
                       p0: np.ndarray) -> np.ndarray:
    """Powers `(J,)` minimising $\\tfrac12|r(p)|^2$ (`painted_rows` of the model
    `fixed + sum_j p_j cols[j]`) subject to $p \\ge 0$ and, with `budget = (c (J,), B)`,
    $c \\cdot p \\le B$; from `p0`. All arrays float64 NumPy: `fixed`, `colours`, `sw` `(N, 3)`,
    `cols (J, N, 3)`."""
    J = cols.shape[0]

    def model(p: np.ndarray) -> np.ndarray:
        return fixed + np.tensordot(p, cols, axes=1)

    def fun(p: np.ndarray) -> tuple[float, np.ndarray]:
        m = model(p)
        r = painted_rows(m, colours, sw, paint)
        return 0.5 * float(r @ r), painted_jacobian(m, cols, sw, paint).T @ r

    if paint is None:  # the least-squares start: NNLS, which is the answer when it keeps the budget
        A = painted_jacobian(model(np.zeros(J)), cols, sw, None)
        p0 = nnls(A, (sw * (colours - fixed)).reshape(-1))[0]
        if budget is None or budget[0] @ p0 <= budget[1]:
            return p0
    cons = [] if budget is None else [{"type": "ineq", "fun": lambda p: budget[1] - budget[0] @ p,
                                       "jac": lambda p: -budget[0]}]
    start = np.maximum(np.asarray(p0, np.float64), 0.0)
    if budget is not None and budget[0] @ start > budget[1]:
        start = start * budget[1] / (budget[0] @ start)
    # SLSQP's tolerances are absolute on the objective: scale it by its value with the lights
    # off (the size of the data), not at the start (which may already be ~0).
    f0 = max(fun(np.zeros(J))[0], fun(start)[0], 1e-300)
    sol = minimize(lambda p: tuple(x / f0 for x in fun(p)), start, jac=True, method="SLSQP",
                   bounds=[(0.0, None)] * J, constraints=cons, options={"ftol": 1e-16, "maxiter": 1000})
    p = np.maximum(sol.x, 0.0)
    if budget is not None and budget[0] @ p > budget[1]:
        p = p * budget[1] / (budget[0] @ p)
    if not fun(p)[0] <= fun(start)[0]:  # never worse than where it started (feasible)
        p = start
    return _polish(p, fun, model, cols, colours, sw, paint, budget)


def _polish(p: np.ndarray, fun: Any, model: Any, cols: np.ndarray, colours: np.ndarray, sw: np.ndarray,
            paint: Painting | None, budget: tuple[np.ndarray, float] | None) -> np.ndarray:
    """The exact optimum on SLSQP's active set: the residual is linear, $r(p) = r_0 + G(p - p_0)$,
    while no hinge changes side; minimise it with the powers at 0 held there and the budget (when
    within 1e-7 of its bound) as an equality (a KKT system). Kept when feasible, on the same
    pieces, and no worse."""
    m = model(p)
    r0 = painted_rows(m, colours, sw, paint)
    G = painted_jacobian(m, cols, sw, paint)
    free = p > 1e-12 * max(np.max(p), 1e-300)
    if not free.any():
        return p
    Gf = G[:, free]
    on_budget = budget is not None and budget[0] @ p >= budget[1] * (1 - 1e-7)
    nf = int(free.sum())
    K = np.zeros((nf + on_budget, nf + on_budget))
    K[:nf, :nf] = Gf.T @ Gf
    rhs = np.zeros(nf + on_budget)
    rhs[:nf] = -Gf.T @ r0
    if on_budget:
        assert budget is not None
        K[:nf, nf] = K[nf, :nf] = budget[0][free]
        rhs[nf] = budget[1] - budget[0] @ p
    try:
        d = np.linalg.solve(K, rhs)[:nf]
    except np.linalg.LinAlgError:
        return p
    q = p.copy()
    q[free] = p[free] + d
    q[~free] = 0.0
    if np.any(q < 0) or (budget is not None and budget[0] @ q > budget[1] * (1 + 1e-12)):
        return p
    same = np.allclose(painted_rows(model(q), colours, sw, paint), r0 + G @ (q - p), rtol=1e-9,
                       atol=1e-12 * max(float(np.max(np.abs(r0))), 1e-300))
    return q if same and fun(q)[0] <= fun(p)[0] * (1 + 1e-12) + 1e-300 else p
