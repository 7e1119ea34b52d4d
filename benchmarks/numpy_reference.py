"""Plain vectorised NumPy implementations of the formulas jaxshadow evaluates (speed baselines).

Each function works on whole arrays of receivers at once (no Python loop over points): the
polygon is clipped exactly to every receiver's horizon and Lambert's contour sum (Campbell &
Fussell eq. 11) is evaluated over the clipped edge soup; the segment light uses the same closed
form as `jaxshadow._kernels.linear` (Poulin eq. 3.10) with horizon clipping of the parameter interval.
Written independently of the JAX code so that the comparison is formula-for-formula.
"""

from __future__ import annotations

import numpy as np


def _horizon_clip_numpy(p: np.ndarray, n: np.ndarray, verts: np.ndarray):
    """Edge soup of `verts (K, 3)` clipped to `n . (x - p) >= 0` for every receiver.

    **Arguments:** `p, n (N, 3)`; `verts (K, 3)`. **Returns:** `starts, ends (N, K + 1, 3)`.
    """
    nxt = np.roll(verts, -1, axis=0)
    dv = np.einsum("kc,nc->nk", verts, n) - np.einsum("nc,nc->n", p, n)[:, None]  # (N, K)
    dn = np.roll(dv, -1, axis=1)
    a_in = dv >= 0
    b_in = dn >= 0
    crossing = a_in != b_in
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(crossing, dv / np.where(crossing, dv - dn, 1.0), 0.0)
    x = verts[None] + t[..., None] * (nxt - verts)[None]  # (N, K, 3)
    start = np.where(a_in[..., None], verts[None], x)
    end = np.where(b_in[..., None], nxt[None], x)
    keep = (a_in | b_in)[..., None]
    start = np.where(keep, start, verts[None])
    end = np.where(keep, end, verts[None])
    exiting = (a_in & ~b_in)[..., None]
    entering = (~a_in & b_in)[..., None]
    exit_pt = np.sum(np.where(exiting, x, 0.0), axis=1)
    entry_pt = np.sum(np.where(entering, x, 0.0), axis=1)
    any_cut = (np.any(exiting[..., 0], axis=1) & np.any(entering[..., 0], axis=1))[:, None]
    close_start = np.where(any_cut, exit_pt, verts[0])
    close_end = np.where(any_cut, entry_pt, verts[0])
    starts = np.concatenate([start, close_start[:, None]], axis=1)
    ends = np.concatenate([end, close_end[:, None]], axis=1)
    return starts, ends


def form_factor_numpy(points: np.ndarray, normals: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """Unoccluded point-to-polygon form factor, `(N,)`, dtype of `points`."""
    p = np.asarray(points)
    n = np.asarray(normals)
    v = np.asarray(verts, dtype=p.dtype)
    ne = np.sum(np.cross(v, np.roll(v, -1, axis=0)), axis=0)
    in_front = (p - v[0]) @ ne > 0
    starts, ends = _horizon_clip_numpy(p, n, v)
    a = starts - p[:, None]
    b = ends - p[:, None]
    c = np.cross(a, b)
    s = np.sqrt(np.sum(c * c, axis=-1))
    d = np.sum(a * b, axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        w = np.where(s > 0, np.arctan2(s, d) / np.where(s > 0, s, 1.0), 0.0)
    terms = w * np.einsum("nkc,nc->nk", c, n)
    f = -np.sum(terms, axis=1) / (2 * np.pi)
    return np.where(in_front, f, 0.0).astype(p.dtype, copy=False)


def linear_irradiance_numpy(
    points: np.ndarray, normals: np.ndarray, a: np.ndarray, b: np.ndarray
) -> np.ndarray:
    """Isotropic segment light, `E / Phi` (1/m), Poulin eq. 3.10 with horizon clipping."""
    p = np.asarray(points)
    n = np.asarray(normals)
    a = np.asarray(a, dtype=p.dtype)
    b = np.asarray(b, dtype=p.dtype)
    e = b - a
    length = np.sqrt(e @ e)
    u = e / length
    ap = a[None] - p
    ta = ap @ u
    tb = ta + length
    h = ap - ta[:, None] * u[None]
    d2 = np.sum(h * h, axis=1)
    hn = np.sum(n * h, axis=1)
    un = n @ u
    with np.errstate(divide="ignore", invalid="ignore"):
        tc = -hn / np.where(un != 0, un, 1.0)
        t0 = np.where(un > 0, np.maximum(ta, tc), ta)
        t1 = np.where(un < 0, np.minimum(tb, tc), tb)
        nonempty = np.where(un != 0, t1 > t0, hn >= 0)
        ra = np.sqrt(t0 * t0 + d2)
        rb = np.sqrt(t1 * t1 + d2)
        same = t0 * t1 > 0
        j1 = np.where(
            same,
            (t1 - t0) * (t1 + t0) / ((t1 * ra + t0 * rb) * ra * rb),
            (t1 / rb - t0 / ra) / d2,
        )
        value = (hn * j1 + un * (1.0 / ra - 1.0 / rb)) / (4 * np.pi)
    return np.where(nonempty, value, 0.0).astype(p.dtype, copy=False)
