"""Non-negative least squares over candidate columns, batched: what the global placement
(`_global_placement`) screens with. A light's unit contribution at a candidate pose is one
column; for fixed poses the best powers are one non-negative least squares over the columns
(the powers enter the model linearly), so every candidate of a light, or every pair of
candidates of two lights, is scored by normal equations batched over the candidates.
`ScreenMemo` keeps the scores of one placement's screens (its columns only grow), so that a
screen repeated with the same lights held is not computed again.
"""

from __future__ import annotations

import itertools

import numpy as np

# Held columns up to which a candidate whose normal equations give a negative power is solved
# by trying every support (2^(m+1) - 1 of them, batched); beyond, `scipy.optimize.nnls` per candidate.
SUPPORTS_UP_TO = 5


def _solve_scaled(G: np.ndarray, b: np.ndarray) -> np.ndarray:
    """`(S, k)` the solutions of the normal equations `G (S, k, k)`, `b (S, k)`, Jacobi-scaled,
    with a `1e-12` ridge on the scaled Gram (a zero column: its power 0)."""
    d = np.einsum("sii->si", G)
    scale = np.sqrt(np.where(d > 0, d, 1.0))
    Gn = G / (scale[:, :, None] * scale[:, None, :]) + 1e-12 * np.eye(G.shape[1])
    return np.linalg.solve(Gn, (b / scale)[:, :, None])[:, :, 0] / scale


def _nnls_by_supports(A: np.ndarray, G: np.ndarray, b: np.ndarray, y: np.ndarray) -> np.ndarray:
    """`(S,)` the non-negative least squares' residual sum of squares $\\min_{p \\ge 0}|y - A_s p|^2$
    for `A (S, M, k)` (Gram `G (S, k, k)`, `b = A^T y (S, k)`): the least squares on every
    support whose solution is non-negative, the best one (the optimum's support is one of them:
    its KKT conditions), its residual computed directly."""
    S, _, k = A.shape
    best = np.full(S, float(y @ y))
    best_p = np.zeros((S, k))
    for n in range(1, k + 1):
        for sup in itertools.combinations(range(k), n):
            ix = np.asarray(sup)
            p = _solve_scaled(G[:, ix[:, None], ix[None, :]], b[:, ix])
            rss = float(y @ y) - 2 * np.einsum("si,si->s", p, b[:, ix]) + np.einsum(
                "si,sij,sj->s", p, G[:, ix[:, None], ix[None, :]], p)
            take = np.all(p >= 0, axis=1) & (rss < best)
            best = np.where(take, rss, best)
            full = np.zeros((S, k))
            full[:, ix] = p
            best_p = np.where(take[:, None], full, best_p)
    r = y[None] - np.einsum("smi,si->sm", A, best_p)
    return np.einsum("sm,sm->s", r, r)


def nnls_rss(fixed: np.ndarray, cand: np.ndarray, y: np.ndarray, fit_power: bool) -> np.ndarray:
    """`(S,)` the least residual sum of squares $|y - B p - a_s q|^2$ over $p, q \\ge 0$ for
    every candidate column `cand[s] (M,)`, `fixed (M, m)` the placed lights' columns: the
    normal equations batched over the candidates (the placed columns' Gram once, the
    candidates' products with them as one matrix product); where they give a negative power,
    every support's least squares (`_nnls_by_supports`, up to `SUPPORTS_UP_TO` placed
    columns) or `scipy.optimize.nnls`. Without `fit_power` the powers are 1 (as given)."""
    if not fit_power:
        r = y - fixed.sum(axis=1) if fixed.size else y
        d = r[None] - cand
        return np.einsum("sm,sm->s", d, d)
    ok = np.all(np.isfinite(cand), axis=1)
    cand = np.where(ok[:, None], cand, 0.0)
    S, m = cand.shape[0], fixed.shape[1]
    G = np.empty((S, m + 1, m + 1))
    G[:, :m, :m] = fixed.T @ fixed
    G[:, :m, m] = G[:, m, :m] = cand @ fixed
    G[:, m, m] = np.einsum("sm,sm->s", cand, cand)
    b = np.empty((S, m + 1))
    b[:, :m] = fixed.T @ y
    b[:, m] = cand @ y
    p = _solve_scaled(G, b)
    rss = float(y @ y) - 2 * np.einsum("si,si->s", p, b) + np.einsum("si,sij,sj->s", p, G, p)
    bad = np.flatnonzero(ok & (np.any(p < 0, axis=1) | ~np.isfinite(rss)))
    if bad.size:
        A = np.concatenate([np.broadcast_to(fixed[None], (bad.size, *fixed.shape)), cand[bad, :, None]], axis=2)
        if m < SUPPORTS_UP_TO:
            rss[bad] = _nnls_by_supports(A, G[bad], b[bad], y)
        else:
            from scipy.optimize import nnls

            rss[bad] = [nnls(a, y)[1] ** 2 for a in A]
    rss[~ok] = np.inf
    return np.maximum(rss, 0.0)


# Elements of the cross Gram `pair_rss` scores at a time: its dozen temporaries stay in the cache.
PAIR_TILE = 1 << 15


def _pair_tile(gab: np.ndarray, gaa: np.ndarray, ya: np.ndarray, one_a: np.ndarray | None, oka: np.ndarray,
               gbb: np.ndarray, yb: np.ndarray, one_b: np.ndarray | None, okb: np.ndarray,
               buf: list) -> tuple[float, int, int]:
    """`(explained, s, t)`: the largest residual reduction over the pairs of the rows `s` of a
    tile of the cross Gram `gab (S, T)` and every column `t`, at its first position in row-major
    order (`np.argmax`'s), written into the scratch arrays `buf` (each at least `(S, T)`). With
    `one_a` (`fit_power`), the pair's non-negative least squares (`pair_rss`); without, powers 1."""
    S = gab.shape[0]
    if one_a is not None and one_b is not None:
        gg, det, pn, un, both = (x[:S] for x in buf[:5])
        good = buf[5][:S]
        np.multiply.outer(gaa, gbb, out=gg)
        np.multiply(gab, gab, out=det)
        np.subtract(gg, det, out=det)
        gg *= 1e-12
        np.greater(det, gg, out=good)
        # the pair's powers (pn, un) / det where both are non-negative, else the better single column
        np.multiply.outer(ya, gbb, out=pn)
        np.multiply(gab, yb[None], out=both)
        pn -= both
        np.multiply.outer(gaa, yb, out=un)
        np.multiply(gab, ya[:, None], out=both)
        un -= both
        good &= pn >= 0
        good &= un >= 0
        np.multiply(ya[:, None], pn, out=both)
        np.multiply(yb[None], un, out=pn)
        both += pn
        np.copyto(det, 1.0, where=~good)
        both /= det
        explained = gg
        np.maximum.outer(one_a, one_b, out=explained)
        np.maximum(explained, both, out=explained, where=good)
    else:
        explained, tmp = buf[0][:S], buf[1][:S]
        np.add.outer(2 * ya, 2 * yb, out=explained)
        explained -= gaa[:, None]
        explained -= gbb[None]
        np.multiply(gab, 2, out=tmp)
        explained -= tmp
    explained[~oka] = -np.inf
    explained[:, ~okb] = -np.inf
    s, t = divmod(int(np.argmax(explained)), explained.shape[1])
    return float(explained[s, t]), s, t


def pair_rss(fixed: np.ndarray, ca: np.ndarray, cb: np.ndarray, y: np.ndarray, fit_power: bool,
             block: int = 512) -> tuple[float, int, int]:
    """`(rss, s, t)`: the least residual sum of squares over every pair of candidate columns
    `ca[s] (M,)`, `cb[t] (M,)` with the placed columns `fixed (M, m)`, and the best pair. With
    `fit_power` the powers of the pair are non-negative least squares on the residual left
    after projecting out the span of `fixed` (their powers free: the caller checks the best
    pair with `nnls_rss`); without, every power is 1. Batched over `block` rows of `ca` at a
    time: the cross Gram `ca cb^T` is one matrix product, scored in tiles of `PAIR_TILE`
    elements (`_pair_tile`); the first best pair in row-major order within a block, the first
    block with the least rss."""
    okb = np.all(np.isfinite(cb), axis=1)
    cb = np.where(okb[:, None], cb, 0.0)
    one_b = None
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
    tile = min(block, max(1, PAIR_TILE // max(cb.shape[0], 1)))
    buf = [np.empty((tile, cb.shape[0])) for _ in range(5)] + [np.empty((tile, cb.shape[0]), bool)]
    best: tuple[float, int, int] = (np.inf, -1, -1)
    for a0 in range(0, ca.shape[0], block):
        a = ca[a0:a0 + block]
        oka = np.all(np.isfinite(a), axis=1)
        a = np.where(oka[:, None], a, 0.0)
        if fit_power and q.shape[1]:
            a = a - (a @ q) @ q.T
        gaa, ya, gab = np.einsum("sm,sm->s", a, a), a @ r, a @ cb.T
        one_a = np.where((ya > 0) & (gaa > 0), ya ** 2 / np.where(gaa > 0, gaa, 1.0), 0.0) if fit_power else None
        e, s, t = np.nan, -1, -1
        for i0 in range(0, a.shape[0], tile):
            sl = slice(i0, i0 + tile)
            ei, si, ti = _pair_tile(gab[sl], gaa[sl], ya[sl], None if one_a is None else one_a[sl], oka[sl],
                                    gbb, yb, one_b, okb, buf)
            # np.argmax over the block: the first NaN, else the first largest
            if s < 0 or (np.isnan(ei) and not np.isnan(e)) or (not np.isnan(e) and ei > e):
                e, s, t = ei, i0 + si, ti
        f = rr - e
        if f < best[0]:
            best = (f, a0 + s, t)
    return best


class ScreenMemo:
    """The screens of one placement (`_global_placement.place`) against `y (M,)`: each light's
    candidate columns `cols[j] (S_j, M)` only grow (appended), so the scores of light `j`'s
    candidates with the other lights held at `chosen` (`rss`) and of light pairs (`pair`) are
    kept by what they depend on (the held candidates' indices, the columns' counts) and a longer
    column list adds only its new candidates' scores."""

    def __init__(self, y: np.ndarray, fit_power: bool) -> None:
        self.y, self.fit_power = y, fit_power
        self._rss: dict = {}
        self._pairs: dict = {}

    def _held(self, cols: list, chosen: dict, skip: tuple) -> tuple[tuple, np.ndarray]:
        held = tuple(sorted((i, int(c)) for i, c in chosen.items() if i not in skip))
        B = np.stack([cols[i][c] for i, c in held], axis=1) if held else np.zeros((self.y.shape[0], 0))
        return held, B

    def rss(self, cols: list, j: int, chosen: dict) -> np.ndarray:
        """`(S_j,)` `nnls_rss` of light `j`'s candidates with the others held at `chosen`
        (light index -> candidate index; light `j`'s own entry ignored). Not to be modified."""
        held, B = self._held(cols, chosen, (j,))
        key = (j, held)
        n = cols[j].shape[0]
        old = self._rss.get(key)
        if old is not None and old.shape[0] == n:
            return old
        done = 0 if old is None else old.shape[0]
        new = nnls_rss(B, cols[j][done:], self.y, self.fit_power)
        out = new if old is None else np.concatenate([old, new])
        self._rss[key] = out
        return out

    def pair(self, cols: list, a: int, b: int, chosen: dict) -> tuple[float, int, int]:
        """`pair_rss` of lights `a` and `b`'s candidates with the others held at `chosen`."""
        held, B = self._held(cols, chosen, (a, b))
        key = (a, b, held, cols[a].shape[0], cols[b].shape[0])
        if key not in self._pairs:
            self._pairs[key] = pair_rss(B, cols[a], cols[b], self.y, self.fit_power)
        return self._pairs[key]
