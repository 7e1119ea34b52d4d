r"""Illumination extrema by optimisation (Campbell & Fussell §3.3, §4.4.1-4.4.2), batched.

C&F find the extrema of the irradiance on a receiver region by local optimisation from starting
points chosen on a coarse grid: the grid cells whose sample is larger (smaller) than all their
neighbours' (their clustering multistart, §4.4.2), then a quasi-Newton method in the interior
(§4.4.1: "if any step moves outside the boundary, there is no interior extremum") and a 1-D
search along edges. Here every start advances in lock step, so that each iteration is one batched
call of the exact irradiance (`js.irradiance` on the host engine) rather than one call per start:

- `ascend`: projected BFGS ascent in 2-D with a batched backtracking line search. The gradient is
  central differences of exact values (`difference_gradient`, the default) or the exact one
  (`jax.grad` of the traced irradiance).
- `golden_section`: the 1-D search along tile edges.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

Values = Callable[[np.ndarray], np.ndarray]  # (n, 2) -> (n,)
Gradient = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]  # (n, 2) -> ((n,), (n, 2))

LINE_SEARCH_STEPS = 10
ARMIJO = 1e-4


def difference_gradient(f: Values, h: float) -> Gradient:
    """Value and central-difference gradient of `f` with step `h` (m), in one batched call."""

    def vg(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = x.shape[0]
        off = np.array([[0.0, 0.0], [h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]])
        y = f((x[:, None, :] + off[None]).reshape(-1, 2)).reshape(n, 5)
        g = np.stack([(y[:, 1] - y[:, 2]) / (2 * h), (y[:, 3] - y[:, 4]) / (2 * h)], axis=1)
        return y[:, 0], g

    return vg


def ascend(f: Values, vg: Gradient, x0: np.ndarray, lo: np.ndarray, hi: np.ndarray, sign: np.ndarray,
           xtol: np.ndarray, max_iter: int = 60) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximise `sign * f` from each start `x0 (n, 2)` inside its box `[lo, hi] (n, 2)`.

    **Returns:** `(x, value, interior)`: the points, `f` there, and whether each ended strictly
    inside its box (an interior local extremum; a point stopped by the box is not one)."""
    n = x0.shape[0]
    x = np.clip(x0, lo, hi)
    val, g = vg(x)
    F, gF = sign * val, sign[:, None] * g
    H = np.broadcast_to(np.eye(2), (n, 2, 2)).copy()
    scale0 = 0.25 * np.min(hi - lo, axis=1) / np.maximum(np.linalg.norm(gF, axis=1), 1e-300)
    H *= scale0[:, None, None]
    active = np.ones(n, bool)
    alphas = 0.5 ** np.arange(LINE_SEARCH_STEPS)
    for _ in range(max_iter):
        idx = np.nonzero(active)[0]
        if idx.size == 0:
            break
        d = np.einsum("nij,nj->ni", H[idx], gF[idx])
        trial = np.clip(x[idx, None, :] + alphas[None, :, None] * d[:, None, :], lo[idx, None], hi[idx, None])
        ft = sign[idx, None] * f(trial.reshape(-1, 2)).reshape(idx.size, LINE_SEARCH_STEPS)
        gain = np.einsum("nk,nak->na", gF[idx], trial - x[idx, None, :])
        ok = ft >= F[idx, None] + ARMIJO * gain
        ok &= np.linalg.norm(trial - x[idx, None, :], axis=2) > 0
        first = np.argmax(ok, axis=1)
        found = ok[np.arange(idx.size), first]
        stop = idx[~found]
        active[stop] = False
        idx, first = idx[found], first[found]
        if idx.size == 0:
            break
        xn = trial[found][np.arange(idx.size), first]
        vn, gn = vg(xn)
        Fn, gFn = sign[idx] * vn, sign[idx, None] * gn
        s = xn - x[idx]
        y = -(gFn - gF[idx])  # gradient change of the minimised function -F
        sy = np.sum(s * y, axis=1)
        upd = sy > 1e-300
        if np.any(upd):
            Hi, si, yi, r = H[idx][upd], s[upd], y[upd], 1.0 / sy[upd]
            eye = np.eye(2)[None]
            A = eye - r[:, None, None] * si[:, :, None] * yi[:, None, :]
            Hn = A @ Hi @ np.transpose(A, (0, 2, 1)) + r[:, None, None] * si[:, :, None] * si[:, None, :]
            sel = idx[upd]
            H[sel] = Hn
        x[idx], F[idx], gF[idx] = xn, Fn, gFn
        small = np.linalg.norm(s, axis=1) < xtol[idx]
        active[idx[small]] = False
    margin = xtol[:, None]
    interior = np.all((x > lo + margin) & (x < hi - margin), axis=1)
    return x, sign * F, interior


def golden_section(f: Values, a: np.ndarray, b: np.ndarray, sign: np.ndarray, iters: int = 48) -> tuple[np.ndarray, np.ndarray]:
    """Maximise `sign * f(t)` over `t in [a, b]` (arrays `(n,)`), with `f` taking `(n, 1)`
    parameters as `(n, 2)` columns `[t, row]` so the caller can map each row to its edge.

    **Returns:** `(t, f(t))`."""
    n = a.shape[0]
    rows = np.arange(n, dtype=np.float64)
    r = (np.sqrt(5.0) - 1) / 2
    lo, hi = a.copy(), b.copy()
    c = hi - r * (hi - lo)
    d = lo + r * (hi - lo)
    fc = sign * f(np.stack([c, rows], axis=1))
    fd = sign * f(np.stack([d, rows], axis=1))
    for _ in range(iters):
        left = fc > fd  # the maximum is in [lo, d]
        hi = np.where(left, d, hi)
        lo = np.where(left, lo, c)
        nc = np.where(left, hi - r * (hi - lo), d)
        nd = np.where(left, c, lo + r * (hi - lo))
        probe = np.where(left, nc, nd)
        fp = sign * f(np.stack([probe, rows], axis=1))
        fc, fd = np.where(left, fp, fd), np.where(left, fc, fp)
        c, d = nc, nd
    t = np.where(fc > fd, c, d)
    return t, sign * np.maximum(fc, fd)
