r"""A polygon light's orientation screened at fixed centres, without the forward model: how the
global placement (`_global_placement`, steps 2 and 6) finds a quad that faces sideways.

The placement's candidates hold a polygon facing a few fixed ways (down, as given, towards the
targets' centroid); a quad turned far from those has no candidate near its own pose, and at a
wrong orientation the candidates nearest its centre rank among the worst (a quad tilted 46-66 deg
from straight down: its neighbourhood ranked 1850th and 2033rd of 2048 at the down-facing
orientation, 1st and 3rd at its own). Screening every centre at many orientations through the
forward model multiplies the polygon's screen by their number.

For a fixed centre $c$ the contribution of a small polygon of normal $n$ to receiver $q$ is
(its projected area seen from $q$) $a_q(n) = g_q \max(0, n \cdot d_q)$, $d_q$ the unit vector
from $c$ to the receiver and $g_q \ge 0$ everything else (distance, the receiver's cosine and
visibility, the diffuse and specular terms): the form factor of a small emitter
$F \approx A \cos\theta_e \cos\theta_r / (\pi r^2)$ (Poulin ch. 5's point-source limit), the
same projected-area factor in the specular integral. So one column computed by the forward model
at a centre, at a normal $n_0$ facing the receivers, gives $g_q = a_q(n_0) / (n_0 \cdot d_q)$, and
with it the approximate column at any normal (`oriented_columns`). Every down-facing candidate
centre is so scored at `NORMALS` normals (a Fibonacci set within `MAX_TILT` of straight down) by
the same non-negative least squares as the screen (`_nnls_screen.nnls_rss`, the other lights'
columns held). At the `TOP` best distinct centres the `PER_POSITION` best distinct normals are
refined on `LEVELS` rings of normals around each (radius `REFINE_TURN`, halved at each level: the
Fibonacci set is ~30 deg coarse and a sideways quad's residual is steep in its normal); the
best refined (centre, normal) pairs at `POSITIONS` distinct centres become candidates, their
columns then computed exactly by the caller. The approximation is checked against the forward
model in `tests/test_fit_global_orientation.py` (a quad turned 108 and 110 deg from straight down:
the column turned from the down-facing one has cosine > 0.999 to the exact one).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from ._nnls_screen import nnls_rss

NORMALS = 48  # Fibonacci directions on the sphere, those within MAX_TILT of straight down kept
MAX_TILT = 2.2  # rad (126 deg) from straight down
POSITIONS, PER_POSITION = 4, 2
TOP = 16  # centres whose normals are refined: LEVELS rings of 8 normals, radius REFINE_TURN halved at each
LEVELS, REFINE_TURN = 4, 0.25
NORMAL_SEPARATION = 0.35  # rad between the normals kept at one centre
COS_MIN = 0.05  # receivers more grazing than this to the computed column's emitter are left dark
DOWN_WITHIN = 0.05  # rad: the computed columns used (normal this close to straight down)
CHUNK = 64  # centres per batch


def rotation_vector(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation vector of the smallest rotation taking unit `a` to unit `b`."""
    axis = np.cross(a, b)
    s, c = np.linalg.norm(axis), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.zeros(3)
        p = np.eye(3)[int(np.argmin(np.abs(a)))]
        axis = np.cross(a, p)
        return np.pi * axis / np.linalg.norm(axis)
    return axis / s * np.arctan2(s, c)


def row_normals(param: Any, rows: np.ndarray) -> np.ndarray:
    """`(S, 3)` the unit normal of polygon light `param` at parameter rows `rows (S, P)`:
    its frame's normal turned by each row's rotation vector (Rodrigues)."""
    n0 = np.asarray(param.frame0, np.float64)[:, 2]
    w = np.asarray(rows, np.float64)[:, param._slices()["orientation"]]
    t = np.linalg.norm(w, axis=1, keepdims=True)
    k = np.where(t > 1e-15, w / np.where(t > 1e-15, t, 1.0), 0.0)
    return (n0 * np.cos(t) + np.cross(k, n0) * np.sin(t) + k * (k @ n0)[:, None] * (1.0 - np.cos(t)))


def down_normals(up: np.ndarray, n: int = NORMALS, max_tilt: float = MAX_TILT) -> np.ndarray:
    """`(K, 3)` unit normals of a Fibonacci set of `n` on the sphere within `max_tilt` (rad) of
    `-up`, straight down first."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (1.0 + 5 ** 0.5) * i
    s = np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)  # z: the cosine to straight down
    a = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    world = s[:, :1] * e1 + s[:, 1:2] * e2 - s[:, 2:3] * up
    keep = np.arccos(np.clip(s[:, 2], -1.0, 1.0)) <= max_tilt
    return np.concatenate([-up[None], world[keep]])


def oriented_columns(cols: np.ndarray, centres: np.ndarray, normals0: np.ndarray, points: np.ndarray,
                     normals: np.ndarray) -> np.ndarray:
    """`(S, K, 3N)` approximate columns (module docstring) of a polygon at `centres (S, 3)` (m)
    with each of `normals (K, 3)`, from its columns `cols (S, 3N)` (row-major `(N, 3)`)
    computed at normals `normals0 (S, 3)`; receivers at `points (N, 3)`."""
    S = cols.shape[0]
    d = points[None] - centres[:, None]
    d /= np.linalg.norm(d, axis=2, keepdims=True)  # (S, N, 3)
    cos0 = np.einsum("snc,sc->sn", d, normals0)
    g = np.where((cos0 > COS_MIN)[..., None], cols.reshape(S, -1, 3) / np.maximum(cos0, COS_MIN)[..., None], 0.0)
    cosk = np.maximum(np.einsum("snc,kc->skn", d, normals), 0.0)
    return (g[:, None] * cosk[..., None]).reshape(S, normals.shape[0], -1)


def oriented_rows(param: Any, rows: np.ndarray, cols: np.ndarray, centre_of: Callable[[np.ndarray], np.ndarray],
                  held: np.ndarray, y: np.ndarray, fit_power: bool, points: np.ndarray, up: np.ndarray,
                  spacing: float) -> np.ndarray:
    """`(M, P)` new candidate rows of polygon light `param` (module docstring): its candidates
    `rows (S, P)` with columns `cols (S, 3N)` (`centre_of(rows (M, P)) -> (M, 3)`: their centres,
    m) that face straight down (`up`: the targets' mean normal) give the approximate columns at every screened normal,
    scored with the columns `held (3N, m)` of the other lights against `y (3N,)` (`fit_power`:
    powers by NNLS, else 1); the best `POSITIONS` centres at least `spacing` (m) apart, at their
    `PER_POSITION` best normals each (rows as the candidate's, the orientation replaced);
    empty where no candidate faces down. Receivers at `points (N, 3)`."""
    nrm = row_normals(param, rows)
    down = np.flatnonzero(nrm @ -up > np.cos(DOWN_WITHIN))
    if down.size == 0:
        return np.zeros((0, rows.shape[1]))
    c = centre_of(rows[down])
    _, first = np.unique(np.round(c / max(spacing, 1e-12) * 1e3), axis=0, return_index=True)
    first = np.sort(first)
    down, c = down[first], c[first]  # one computed column per centre
    normals = down_normals(up)
    f = np.concatenate([
        nnls_rss(held, oriented_columns(cols[down[s]], c[s], nrm[down[s]], points, normals).reshape(
            -1, cols.shape[1]), y, fit_power).reshape(len(s), -1)
        for s in np.array_split(np.arange(down.size), max(1, -(-down.size // CHUNK)))])  # (S', K)
    f = np.where(np.isfinite(f), f, np.inf)

    def score(s: int, cand: np.ndarray) -> np.ndarray:  # centre s at normals cand (K', 3)
        a = oriented_columns(cols[down[s]][None], c[s][None], nrm[down[s]][None], points, cand)[0]
        g = nnls_rss(held, a, y, fit_power)
        return np.where(np.isfinite(g), g, np.inf)

    # the TOP best distinct centres, each at its PER_POSITION best distinct normals, refined
    found = []  # (rss, centre index, normal)
    for s in _distinct(f.min(axis=1), c, TOP, spacing):
        for k in _distinct(f[s], normals, PER_POSITION, NORMAL_SEPARATION, angular=True):
            n, g = normals[k], float(f[s, k])
            for level in range(LEVELS):
                cand = np.concatenate([n[None], _ring(n, REFINE_TURN / 2 ** level)])
                h = score(s, cand)
                if h.min() < g:
                    n, g = cand[int(np.argmin(h))], float(h.min())
            found.append((g, s, n))
    found.sort(key=lambda x: x[0])
    picked = _distinct(np.array([x[0] for x in found]), c[[x[1] for x in found]], POSITIONS, spacing) if found else []
    n0 = np.asarray(param.frame0, np.float64)[:, 2]
    sl = param._slices()["orientation"]
    out = []
    for i in picked:
        _, s, _ = found[i]
        for _, s2, n in found:  # this centre's refined normals, best first
            if s2 == s:
                r = rows[down[s]].copy()
                r[sl] = rotation_vector(n0, n)
                out.append(r)
    return np.asarray(out).reshape(-1, rows.shape[1])


def _ring(n: np.ndarray, radius: float, k: int = 8) -> np.ndarray:
    """`(k, 3)` unit normals `radius` (rad) from unit `n`, at `k` azimuths."""
    a = np.eye(3)[int(np.argmin(np.abs(n)))]
    e1 = np.cross(n, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    phi = 2 * np.pi * np.arange(k) / k
    return (np.cos(radius) * n + np.sin(radius) * (np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2))


def _distinct(f: np.ndarray, pos: np.ndarray, k: int, apart: float, angular: bool = False) -> list[int]:
    """Up to `k` indices in increasing finite `f`, each farther than `apart` from every one picked
    before it: `pos` points (m), or with `angular` unit vectors (`apart` in rad)."""
    picked: list[int] = []
    for i in np.argsort(f, kind="stable"):
        if len(picked) == k or not np.isfinite(f[i]):
            break
        gaps = (np.arccos(np.clip(pos[picked] @ pos[i], -1.0, 1.0)) if angular
                else np.linalg.norm(pos[picked] - pos[i], axis=1)) if picked else np.zeros(0)
        if np.all(gaps > apart):
            picked.append(int(i))
    return picked
