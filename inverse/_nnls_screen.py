"""Non-negative least squares over candidate columns, batched: what the global placement
(`_global_placement`) screens with. A light's unit contribution at a candidate pose is one
column; for fixed poses the best powers are one non-negative least squares over the columns
(the powers enter the model linearly), so every candidate of a light, or every pair of
candidates of two lights, is scored by normal equations batched over the candidates.
"""

from __future__ import annotations

import numpy as np


def nnls_rss(fixed: np.ndarray, cand: np.ndarray, y: np.ndarray, fit_power: bool) -> np.ndarray:
    """`(S,)` the least residual sum of squares $|y - B p - a_s q|^2$ over $p, q \\ge 0$ for
    every candidate column `cand[s] (M,)`, `fixed (M, m)` the placed lights' columns: the
    normal equations batched over the candidates, `scipy.optimize.nnls` where they give a
    negative power. Without `fit_power` the powers are 1 (as given)."""
    if not fit_power:
        r = y - fixed.sum(axis=1) if fixed.size else y
        d = r[None] - cand
        return np.einsum("sm,sm->s", d, d)
    from scipy.optimize import nnls

    ok = np.all(np.isfinite(cand), axis=1)
    cand = np.where(ok[:, None], cand, 0.0)
    S, m = cand.shape[0], fixed.shape[1]
    A = np.concatenate([np.broadcast_to(fixed[None], (S, *fixed.shape)), cand[:, :, None]], axis=2)  # (S, M, m+1)
    G = np.einsum("smi,smj->sij", A, A)
    b = np.einsum("smi,m->si", A, y)
    d = np.einsum("sii->si", G)
    scale = np.sqrt(np.where(d > 0, d, 1.0))
    Gn = G / (scale[:, :, None] * scale[:, None, :]) + 1e-12 * np.eye(m + 1)  # a zero column: its power 0
    p = np.linalg.solve(Gn, (b / scale)[:, :, None])[:, :, 0] / scale
    rss = float(y @ y) - 2 * np.einsum("si,si->s", p, b) + np.einsum("si,sij,sj->s", p, G, p)
    for s in np.flatnonzero(ok & (np.any(p < 0, axis=1) | ~np.isfinite(rss))):
        rss[s] = nnls(A[s], y)[1] ** 2
    rss[~ok] = np.inf
    return np.maximum(rss, 0.0)


def pair_rss(fixed: np.ndarray, ca: np.ndarray, cb: np.ndarray, y: np.ndarray, fit_power: bool,
             block: int = 512) -> tuple[float, int, int]:
    """`(rss, s, t)`: the least residual sum of squares over every pair of candidate columns
    `ca[s] (M,)`, `cb[t] (M,)` with the placed columns `fixed (M, m)`, and the best pair. With
    `fit_power` the powers of the pair are non-negative least squares on the residual left
    after projecting out the span of `fixed` (their powers free: the caller checks the best
    pair with `nnls_rss`); without, every power is 1. Batched over `block` rows of `ca` at a
    time: the cross Gram `ca cb^T` is one matrix product."""
    okb = np.all(np.isfinite(cb), axis=1)
    cb = np.where(okb[:, None], cb, 0.0)
    if fit_power:
        if fixed.size:
            q, _ = np.linalg.qr(fixed)
            r = y - q @ (q.T @ y)
            cb = cb - (cb @ q) @ q.T
        else:
            q, r = np.zeros((y.shape[0], 0)), y
        gbb, yb = np.einsum("tm,tm->t", cb, cb), cb @ r
        one_b = np.where((yb > 0) & (gbb > 0), yb ** 2 / np.where(gbb > 0, gbb, 1.0), 0.0)
    else:
        r = y - fixed.sum(axis=1) if fixed.size else y
        gbb, yb = np.einsum("tm,tm->t", cb, cb), cb @ r
    rr = float(r @ r)
    best: tuple[float, int, int] = (np.inf, -1, -1)
    for a0 in range(0, ca.shape[0], block):
        a = ca[a0:a0 + block]
        oka = np.all(np.isfinite(a), axis=1)
        a = np.where(oka[:, None], a, 0.0)
        if fit_power and q.shape[1]:
            a = a - (a @ q) @ q.T
        gaa, ya, gab = np.einsum("sm,sm->s", a, a), a @ r, a @ cb.T
        if fit_power:
            det = gaa[:, None] * gbb[None] - gab ** 2
            good = det > 1e-12 * gaa[:, None] * gbb[None]
            det = np.where(good, det, 1.0)
            p = (gbb[None] * ya[:, None] - gab * yb[None]) / det
            u = (gaa[:, None] * yb[None] - gab * ya[:, None]) / det
            both = (gbb[None] * ya[:, None] ** 2 - 2 * gab * ya[:, None] * yb[None] + gaa[:, None] * yb[None] ** 2) / det
            one_a = np.where((ya > 0) & (gaa > 0), ya ** 2 / np.where(gaa > 0, gaa, 1.0), 0.0)
            single = np.maximum(one_a[:, None], one_b[None])
            explained = np.where(good & (p >= 0) & (u >= 0), np.maximum(both, single), single)
            f = rr - explained
        else:
            f = rr - 2 * ya[:, None] - 2 * yb[None] + gaa[:, None] + gbb[None] + 2 * gab
        f = np.where(oka[:, None] & okb[None], f, np.inf)
        s, t = np.unravel_index(int(np.argmin(f)), f.shape)
        if f[s, t] < best[0]:
            best = (float(f[s, t]), a0 + int(s), int(t))
    return best
