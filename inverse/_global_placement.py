r"""`fit_lights`' global placement: every light's pose screened over the whole feasible region,
its power by non-negative least squares, one light at a time on the residual (matching
pursuit), before the local solver refines.

The powers enter the model linearly (`_multilight`): for fixed poses the best powers are one
non-negative least squares over the lights' unit contributions $a_j$ (the weighted model
column of light $j$ at its reference power, `(3N,)`). So the screen needs no derivative:

1. **Region.** Light centres lie above the receivers: with $u$ the targets' mean normal
   ("up"), between `HEIGHT_MIN` and `HEIGHT_MAX` times the extent $D$ (the diagonal of the
   targets' and occluders' bounding box) above the highest target, and laterally within the
   targets' extent plus `LATERAL_MARGIN` $D$; inside the box of an `inverse.Box` constraint,
   on the plane of an `inverse.Plane` (an `inverse.Outside` hull is left to the solver's
   penalty: a light inside closed occluders lights nothing and is never chosen).
2. **Candidates.** `POSITIONS` centres per light from a scrambled Sobol set over the region
   (`scipy.stats.qmc`), plus points on the rays of `light_from_diffuse_maximum` at the
   brightest targets (Poulin ch. 5's closed form), plus the light's own multistart rows
   around the given pose (`_multistart.make_starts`: the given pose first). A polygon is
   tried facing the targets' centroid, facing down ($-u$), as given and, with `POLYGON_TILTS`,
   with its normal tilted from $-u$ on rings of azimuths; with `ORIENTATION_SCREEN` (off by default), also at the
   (centre, normal) pairs its orientation screen picks (`_orientation_screen`: every down-facing
   candidate's column turned to normals up to 126 deg from $-u$ without the forward model), here
   with nothing held and in every local screen (steps 6 and 8) with the other lights held; a segment as given
   and along three horizontal directions; sizes as given.
3. **Unit contributions.** One compiled program per light kind evaluates the forward model
   (`_multilight._parts`: soft shadows, the shadow engine at the fit's capacity; `_placement_rank`) at `CHUNK`
   candidates at once (`jax.vmap`).
4. **Matching pursuit.** Starting from no light, each step tries every candidate of every
   unplaced light with the placed ones, powers by NNLS, and places the best (a beam of `BEAM`
   partial placements); then each light in turn is re-chosen with the others held (coordinate
   descent) until nothing changes.
5. **Pair moves.** Two lights can stand in for each other's shading (a quad where a segment
   is and the segment beside it): moving either alone makes the fit worse. So every pair of
   lights is re-chosen together over all pairs of their candidates with the others held
   (`_nnls_screen.pair_rss`: one cross Gram matrix, two-column non-negative least squares), then single
   moves again, until nothing improves. The screens' scores are kept (`_nnls_screen.ScreenMemo`):
   a light's candidates with the same lights held are scored once.
6. **Local screen.** Around each light's `LOCAL_SEEDS` best distinct candidates (the others
   held), `REFINE_POINTS` candidates in position, orientation and log size, `LOCAL_LEVELS`
   levels with the radius halved at each, around each seed's best so far; then the pair moves
   again.
7. **Refine, then rank.** At grid resolution (the Sobol spacing is ~10 % of the scene) the
   right configuration, each light a few % off, explains the targets no better than a wrong one
   where the lights compensate for each other. So the placements found above (the beam's, the
   deals, the locally screened ones, and each of those with one light moved to another of its
   best distinct candidates) are not ranked by their screened residual: up to `BASINS` of them
   that lie in distinct basins (`distinct_basins`: some light's centre more than
   `BASIN_DISTANCE` of the extent away, or its orientation more than `BASIN_TURN`) are refined
   jointly for `BASIN_STEPS` iterations as the rows of `fit_lights`' batched LM program (the
   program of its joint refinement: rows padded to its batch, no new compilation), and ranked
   by the refined loss (`refine_and_rank`; under a power budget at the powers the final fit
   solves there, `final_losses`: $p \ge 0$ and the budget, not the LM's signed projection).
8. **Screen again at the refined placement** (`_rescreen`). The screens above hold the other
   lights at grid resolution, where their columns are a few % of the scene off and a light's
   residual is theirs too. With the best refined placement's columns held instead, each light's
   candidates are ranked and locally screened again (step 6's screen), every pair of lights is
   re-chosen together (step 5's pair move), and the placements so moved are refined and ranked
   as in step 7 (up to a batch of them, in basins distinct from those refined already); in
   rounds while a round improves the best refined loss (`RESCREEN`: coordinate descent over
   single lights and pairs at refined resolution). In each round the light that explains least
   is also re-placed on the residual and the lights' centres dealt in every order (`dealt`): a
   light that fell where it lights a few targets holds a slot the others need.
   A refined placement that explains the targets exactly (`EXACT`), or within the told noise
   (`place`'s `explained`), ends steps 7 and 8: the batches after its own are not refined,
   nothing is re-screened.

The result is the best refined placement (`theta`, the poses), the other refined placements in distinct basins
(`alternatives`, up to `ALTERNATIVES`, best first: `fit_lights` finishes them with its joint refinement, where
distinct placements of about equal loss are reported as competing) and, per light, its
candidates ranked with the others at the winning grid placement: the starts of `fit_lights`'
per-light solves, which then refine all poses jointly (the given poses compete there as one
more start).
"""

from __future__ import annotations

import dataclasses
import itertools
from typing import Any

import numpy as np

import jaxshadow as js

from ._closed_forms import light_from_diffuse_maximum
from ._multilight import LightsProblem
from ._nnls_screen import ScreenMemo, nnls_rss
from ._orientation_screen import oriented_rows
from ._orientation_screen import rotation_vector as _rotation_vector
from ._parametrisation import LightParametrisation
from ._placement_rank import (  # noqa: F401  (re-exported: fit_lights, tests)
    BASIN_DISTANCE,
    BASIN_STEPS,
    BASIN_TURN,
    CHUNK,
    centre_of_row,
    distinct_basins,
    final_losses,
    ranking_losses,
    refine_and_rank,
    unit_columns,
    weighted_rest,
)
from ._rescreen import rescreen

POSITIONS = 512
REFINE_POINTS = 64
LOCAL_SEEDS, LOCAL_LEVELS = 4, 4
ORIENTATION_SPREAD = 0.5  # rad: about half the screen's step between segment directions
BEAM, PER_PARENT, REFINED = 12, 3, 2
HEIGHT_MIN, HEIGHT_MAX = 0.02, 0.6
LATERAL_MARGIN = 0.1
DIFFUSE_MAXIMA = 3
# Polygon normals tilted from straight down, as (tilt from -u in rad, number of azimuths) rings:
# extra orientation variants of every polygon candidate (step 2). Off by default (empty).
POLYGON_TILTS: tuple = ()
# A polygon's candidates also at the normals its orientation screen picks (`_orientation_screen`),
# with nothing held before the pursuit and with the others held in every local screen (steps 6, 8).
# Off by default: from no start it recovered held-out seed 11 but left seed 15 9.6 % off unflagged.
ORIENTATION_SCREEN = False
# Refine, then rank (module docstring, step 7; `_placement_rank`): at most BASINS placements;
# ALTERNATIVES refined runners-up handed on.
BASINS = 16
ALTERNATIVES = 3
# Step 8 (module docstring): every light screened again at the best refined placement.
RESCREEN = True
SPLIT_RADIUS = 0.15  # of the extent: step 8's least useful light re-placed this near another light (`_rescreen`)
# Steps 7 and 8 stop at a refined placement that explains the targets exactly: its loss at most
# EXACT of theirs ($\tfrac12|y|^2$); no other placement can explain them better.
EXACT = 1e-12


@dataclasses.dataclass(frozen=True)
class Region:
    """The feasible region of light centres: `origin (3,)` (the targets' centroid), `axes (3, 3)`
    rows $e_1, e_2, u$ (u the targets' mean normal), `lo (3,)`, `hi (3,)` the box in those
    coordinates (m), `extent` (m: the targets' and occluders' bounding-box diagonal)."""

    origin: np.ndarray
    axes: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    extent: float

    def world(self, local: np.ndarray) -> np.ndarray:
        return self.origin + local @ self.axes


def region_of(scene: js.Scene, points: np.ndarray, normals: np.ndarray) -> Region:
    """The feasible region (module docstring, step 1) for receivers `points`, `normals` `(N, 3)`."""
    pts = np.asarray(points, np.float64)
    up = np.asarray(normals, np.float64).mean(axis=0)
    up = up / np.linalg.norm(up) if np.linalg.norm(up) > 1e-9 else np.array([0.0, 0.0, 1.0])
    a = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    axes = np.stack([e1, np.cross(up, e1), up])
    allp = np.concatenate([pts] + ([np.asarray(scene.occluders, np.float64).reshape(-1, 3)]
                                   if scene.occluders is not None else []))
    allp = allp[np.all(np.isfinite(allp), axis=1)]
    extent = float(np.linalg.norm(allp.max(axis=0) - allp.min(axis=0)))
    origin = pts.mean(axis=0)
    loc = (pts - origin) @ axes.T
    m = LATERAL_MARGIN * extent
    top = loc[:, 2].max()
    lo = np.r_[loc[:, 0].min() - m, loc[:, 1].min() - m, top + HEIGHT_MIN * extent]
    hi = np.r_[loc[:, 0].max() + m, loc[:, 1].max() + m, top + HEIGHT_MAX * extent]
    return Region(origin, axes, lo, hi, extent)


def template_light(kind: str, region: Region) -> Any:
    """A light of `kind` (`"polygon"`, `"point"`, `"segment"`, `"directional"`) at the middle of
    the region's top half, white at unit power (radiance, intensity, power per length,
    irradiance 1): a square of side a tenth of the extent facing down, a segment of 0.15
    extents along $e_1$, a direction straight down."""
    c = region.world(np.r_[0.5 * (region.lo[:2] + region.hi[:2]), 0.5 * (region.lo[2] + region.hi[2])])
    e1, e2, up = region.axes
    if kind == "polygon":
        h = 0.05 * region.extent
        # counter-clockwise seen from below: the normal points down
        v = np.stack([c - h * e1 - h * e2, c - h * e1 + h * e2, c + h * e1 + h * e2, c + h * e1 - h * e2])
        return js.PolygonLight(v, [1.0, 1.0, 1.0])
    if kind == "point":
        return js.PointLight(c, [1.0, 1.0, 1.0])
    if kind == "segment":
        h = 0.075 * region.extent
        return js.LinearLight(c - h * e1, c + h * e1, [1.0, 1.0, 1.0])
    if kind == "directional":
        return js.DirectionalLight(-up, [1.0, 1.0, 1.0])
    raise ValueError(f"fit_lights: kinds must be 'polygon', 'point', 'segment' or 'directional', got {kind!r}.")


def _centres(region: Region, constraint: Any, n: int, seed: int, targets: Any) -> np.ndarray:
    """`(M, 3)` candidate centres (world, m): a Sobol set over the region (or a constraint's
    box, or the region's points projected onto a constraint's plane) and points on the
    diffuse-maximum rays of the brightest targets."""
    from scipy.stats import qmc

    u = qmc.Sobol(3, scramble=True, seed=seed).random_base2(int(np.ceil(np.log2(n))))[:n]
    if constraint is not None and hasattr(constraint, "lower"):  # a Box
        lo, hi = np.asarray(constraint.lower, np.float64), np.asarray(constraint.upper, np.float64)
        return lo + (hi - lo) * u
    c = region.world(region.lo + (region.hi - region.lo) * u)
    pts = np.asarray(targets.points, np.float64)
    nrm = np.asarray(targets.normals, np.float64)
    lum = (np.asarray(targets.colours, np.float64) * (np.asarray(targets.weights) > 0)).sum(axis=1)
    rays = []
    for i in np.argsort(lum)[::-1][:DIFFUSE_MAXIMA]:
        ray = light_from_diffuse_maximum(pts[i], nrm[i])
        o, d = np.asarray(ray.origin, np.float64), np.asarray(ray.direction, np.float64)
        for h in np.linspace(region.lo[2], region.hi[2], 6):
            up_d = d @ region.axes[2]
            if up_d > 1e-3:
                rays.append(o + d * (h - (o - region.origin) @ region.axes[2]) / up_d)
    c = np.concatenate([c, np.asarray(rays).reshape(-1, 3)])
    if constraint is not None and hasattr(constraint, "normal"):  # a Plane
        m, p0 = np.asarray(constraint.normal, np.float64), np.asarray(constraint.point, np.float64)
        c = c - ((c - p0) @ m)[:, None] * m
    return c


def candidate_rows(param: LightParametrisation, region: Region, constraint: Any, targets: Any, seed: int,
                   n: int = POSITIONS) -> np.ndarray:
    """`(M, P)` parameter rows of light `param` at candidate poses (module docstring, step 2;
    sizes as given); empty `(0, P)` for a light whose position is not fitted."""
    if "position" not in param._slices():
        return np.zeros((0, param.size))
    return rows_at(param, region, _centres(region, constraint, n, seed, targets))


def rows_at(param: LightParametrisation, region: Region, centres: np.ndarray) -> np.ndarray:
    """`(M, P)` rows of light `param` centred at each of `centres (C, 3)` (m) in each of its
    orientation variants (module docstring, step 2), sizes as given."""
    sl = param._slices()
    s, c0 = float(param.scale), np.asarray(param.c0, np.float64)
    if param.constraint == "plane":
        pos = (centres - c0) @ np.asarray(param.plane_e, np.float64).T / s
    elif param.constraint == "box" and param.box_map == "sigmoid":
        lo, hi = np.asarray(param.box_lo, np.float64), np.asarray(param.box_hi, np.float64)
        f = np.clip((centres - lo) / (hi - lo), 1e-3, 1 - 1e-3)
        pos = np.log(f / (1 - f))
    elif param.constraint == "box":
        lo, hi = np.asarray(param.box_lo, np.float64), np.asarray(param.box_hi, np.float64)
        pos = (np.clip(centres, lo, hi) - c0) / s
    else:
        pos = (centres - c0) / s
    orients: list[Any] = [None]
    if "orientation" in sl and param.kind == "polygon":
        n0 = np.asarray(param.frame0, np.float64)[:, 2]
        orients = [np.zeros(3), -region.axes[2], "centroid"]
        e1, e2, up = region.axes
        orients += [-np.cos(t) * up + np.sin(t) * (np.cos(a) * e1 + np.sin(a) * e2)
                    for t, k in POLYGON_TILTS for a in 2 * np.pi * np.arange(k) / k]
    elif "orientation" in sl and param.kind == "linear":
        F = np.asarray(param.frame0, np.float64)
        e1, e2 = region.axes[0], region.axes[1]
        dirs = [np.cos(a) * e1 + np.sin(a) * e2 for a in (0.0, np.pi / 3, 2 * np.pi / 3)]
        orients = [np.zeros(2)]
        for d in dirs:
            d = d if d @ F[2] >= 0 else -d
            w = _rotation_vector(F[2], d)
            orients.append(np.array([w @ F[0], w @ F[1]]))
    rows = []
    for o in orients:
        r = np.zeros((centres.shape[0], param.size))
        r[:, sl["position"]] = pos
        if o is not None:
            if isinstance(o, str):  # facing the targets' centroid from each centre
                look = region.origin - centres
                look /= np.linalg.norm(look, axis=1, keepdims=True)
                r[:, sl["orientation"]] = np.stack([_rotation_vector(n0, d) for d in look])
            elif param.kind == "polygon":
                r[:, sl["orientation"]] = _rotation_vector(n0, o) if np.any(o) else 0.0
            else:
                r[:, sl["orientation"]] = o
        rows.append(r)
    return np.concatenate(rows)


def dealt(params: tuple, offsets: tuple, region: Region, movable: list[int], theta: np.ndarray) -> np.ndarray:
    """`(D, Pt)`: the placement `theta (Pt,)` with the centres of the `movable` lights dealt to
    them in every other order (up to 4 lights; beyond, each exchange of two); a light given
    another's centre takes it at its first orientation variant (as given) and its given size
    (`rows_at`), a light keeping its own centre keeps its row."""
    if len(movable) < 2:
        return np.zeros((0, theta.shape[0]))
    if len(movable) <= 4:
        deals = [q for q in itertools.permutations(movable) if q != tuple(movable)]
    else:
        deals = []
        for a, b in itertools.combinations(range(len(movable)), 2):
            q = list(movable)
            q[a], q[b] = q[b], q[a]
            deals.append(tuple(q))
    sl = {j: slice(offsets[j], offsets[j] + params[j].size) for j in movable}
    where = {j: centre_of_row(params[j], theta[sl[j]]) for j in movable}
    out = np.tile(np.asarray(theta, np.float64), (len(deals), 1))
    for r, q in enumerate(deals):
        for j, src in zip(movable, q, strict=True):
            if src != j:
                out[r, sl[j]] = rows_at(params[j], region, where[src][None])[0]
    return out


@dataclasses.dataclass
class Placement:
    """What `place` found: `theta (P,)` the poses, `loss` ($\\tfrac12$ rss at NNLS powers),
    `ranked[j]` light j's candidate rows, best first with the others at `theta` (None for a
    light whose pose is not fitted), `problem` (its capacity possibly raised)."""

    theta: np.ndarray
    loss: float
    ranked: list
    problem: LightsProblem
    alternatives: np.ndarray  # (A, P): other refined placements, best first
    rows: list | None = None  # rows[j] (M_j, P_j): light j's screened candidates (None: pose not fitted)
    cols: list | None = None  # cols[j] (M_j, 3N): their weighted unit columns
    refined: tuple | None = None  # (values (R, P), losses (R,)): every placement refined in steps 7-8


def _distinct_best(f: np.ndarray, pos: np.ndarray, k: int, spacing: float) -> list[int]:
    """Up to `k` candidates in increasing `f` (finite only), each farther than `spacing` from
    every one picked before it (`pos`: the candidates' centres)."""
    picked: list[int] = []
    for c in np.argsort(f, kind="stable"):
        if len(picked) == k or not np.isfinite(f[c]):
            break
        if all(np.linalg.norm(pos[c] - pos[q]) > spacing for q in picked):
            picked.append(int(c))
    return picked


def place(problem: LightsProblem, theta0: np.ndarray, local_rows: list, constraints: dict, idx: list,
          seed: int, keep: int, lm: dict | None = None, explained: float = 0.0) -> Placement:
    """Global placement (module docstring): `theta0 (Pt,)` the given poses, `local_rows[j]` light
    j's multistart rows around its given pose (None for a light whose pose is not fitted),
    `constraints` by scene light index, `idx` the fitted lights' scene indices; `keep` ranked
    rows per light and the batch of the LM program; `lm`: the LM's `rtol`, `atol` for the
    refinement of the competing placements (step 7; None: ranked by the screened residual
    alone); `explained`: a refined loss at or below it explains the targets within the told
    noise (`_diagnostics.explained_loss`) and ends steps 7 and 8 as an exact one does."""
    t = problem.targets
    params = problem.params
    J = len(params)
    region = region_of(problem.scene, np.asarray(t.points), np.asarray(t.normals))
    y = weighted_rest(problem)
    rows: list = [None] * J
    cols: list = [None] * J
    for j, p in enumerate(params):
        if p is None:
            continue
        glob = candidate_rows(p, region, constraints.get(idx[j]), t, seed + 7 * j)
        r = np.concatenate([np.asarray(local_rows[j], np.float64), glob])
        rows[j] = r
        cols[j], problem = unit_columns(problem, j, r)
    todo = [j for j in range(J) if rows[j] is not None]
    spacing = (region.hi - region.lo).max() / POSITIONS ** (1 / 3)  # m: between neighbouring candidates

    def turned(j: int, B: np.ndarray) -> None:
        """A polygon's candidates at the normals its orientation screen picks with the columns `B`
        held (`_orientation_screen`; module docstring, step 2), appended to its candidates."""
        nonlocal problem
        p = params[j]
        if p.kind != "polygon" or "orientation" not in p._slices() or not ORIENTATION_SCREEN:
            return
        new = oriented_rows(p, rows[j], cols[j], lambda r: np.stack([centre_of_row(p, x) for x in r]), B, y,
                            problem.fit_power, np.asarray(t.points, np.float64), region.axes[2], spacing)
        if new.shape[0]:
            ct, problem = unit_columns(problem, j, new)
            rows[j], cols[j] = np.concatenate([rows[j], new]), np.concatenate([cols[j], ct])

    for j in todo:
        turned(j, np.zeros((y.shape[0], 0)))

    memo = ScreenMemo(y, problem.fit_power)  # the screens' scores, kept while the columns only grow

    def rss_for(j: int, chosen: dict) -> np.ndarray:
        return memo.rss(cols, j, chosen)

    def centres(j: int, r: np.ndarray) -> np.ndarray:
        sl = params[j]._slices().get("position", slice(0, 0))
        return r[:, sl] * float(params[j].scale)

    def descend(chosen: dict) -> tuple[float, dict]:
        """Each light re-chosen with the others held, until nothing changes."""
        chosen = dict(chosen)
        f = np.full(1, np.inf)
        for _ in range(4):
            changed = False
            for j in todo:
                f = rss_for(j, chosen)
                c = int(np.argmin(f))
                changed |= c != chosen[j]
                chosen[j] = c
            if not changed:
                break
        return float(np.min(f)), chosen

    def pairs(chosen: dict, f: float) -> tuple[float, dict]:
        """Two lights re-chosen together over all pairs of their candidates with the others held
        (`pair_rss`), then each light alone (`descend`), until nothing improves: two lights that
        stand in for each other's shading move at once."""
        chosen = dict(chosen)
        for _ in range(4):
            improved = False
            for a, b in itertools.combinations(todo, 2):
                _, s, t = memo.pair(cols, a, b, chosen)
                if s < 0 or (s, t) == (chosen[a], chosen[b]):
                    continue
                trial = {**chosen, a: s, b: t}
                g = float(rss_for(b, trial)[t])  # exact: the NNLS with every placed light
                if g < f * (1 - 1e-9):
                    g, trial = descend(trial)
                    if g < f:
                        f, chosen, improved = g, trial, True
            if not improved:
                break
        return f, chosen

    # Matching pursuit with a beam: every kept partial placement tries every candidate of every
    # unplaced light on its residual; the BEAM best (a few distinct ones per light and parent)
    # are kept for the next light.
    beams: list = [(float(y @ y), {})]
    for _ in todo:
        pool = []
        for _, ch in beams:
            for j in (j for j in todo if j not in ch):
                f = rss_for(j, ch)
                pos = centres(j, rows[j])
                picked = _distinct_best(f, pos, PER_PARENT, spacing)
                pool += [(float(f[c]), {**ch, j: c}) for c in picked]
        pool.sort(key=lambda x: x[0])
        beams, seen = [], set()
        for f, ch in pool:
            key = tuple(sorted(ch.items()))
            if key not in seen:
                seen.add(key)
                beams.append((f, ch))
            if len(beams) == BEAM:
                break
    finals = sorted((pairs(*descend(ch)[::-1]) for _, ch in beams), key=lambda x: x[0])
    distinct: list = []
    for f, ch in finals:
        if all(ch != c for _, c in distinct):
            distinct.append((f, ch))
    # The positions dealt to the lights in every order (a small quad passes for a point), for the
    # lights whose centre is free (a Plane or a Box keeps its own).
    movable = [j for j in todo if "position" in params[j]._slices() and params[j].constraint == "none"]
    if len(movable) > 1:
        for _, ch in list(distinct[:REFINED]):
            where = {j: centre_of_row(params[j], rows[j][ch[j]]) for j in movable}
            perms = [q for q in itertools.permutations(movable) if q != tuple(movable)]
            first: dict = {}
            for j in movable:
                new = [rows_at(params[j], region, where[q[movable.index(j)]][None]) for q in perms]
                first[j] = rows[j].shape[0] + np.cumsum([0] + [r.shape[0] for r in new[:-1]])
                ct, problem = unit_columns(problem, j, np.concatenate(new))
                rows[j] = np.concatenate([rows[j], *new])
                cols[j] = np.concatenate([cols[j], ct])
            for n in range(len(perms)):
                distinct.append(descend({**ch, **{j: int(first[j][n]) for j in movable}}))
        distinct.sort(key=lambda x: x[0])
    rng = np.random.default_rng(seed + 11)

    def local_screen(j: int, B: np.ndarray) -> list[int]:
        """Light j's `LOCAL_SEEDS` best distinct candidates with the other lights' columns `B`
        held, each screened locally (`LOCAL_LEVELS` levels of `REFINE_POINTS` candidates, the
        radius halved at each, around the seed's best so far; added to light j's candidates):
        their indices."""
        nonlocal problem
        p = params[j]
        sl = p._slices()
        spread = np.zeros(p.size)
        if "position" in sl:
            spread[sl["position"]] = spacing / float(p.scale)
        if "orientation" in sl:
            spread[sl["orientation"]] = ORIENTATION_SPREAD
        if "size" in sl:  # log sizes: a given or default size is a guess
            spread[sl["size"]] = 0.4
        turned(j, B)
        seeds = _distinct_best(nnls_rss(B, cols[j], y, problem.fit_power), centres(j, rows[j]), LOCAL_SEEDS,
                               spacing)
        for level in range(LOCAL_LEVELS):
            trial = (rows[j][seeds][:, None] + spread / 2 ** level
                     * rng.uniform(-1.0, 1.0, (len(seeds), REFINE_POINTS, p.size)))
            ct, problem = unit_columns(problem, j, trial.reshape(-1, p.size))
            n0 = rows[j].shape[0]
            rows[j] = np.concatenate([rows[j], trial.reshape(-1, p.size)])
            cols[j] = np.concatenate([cols[j], ct])
            for i, c in enumerate(seeds):
                idx_i = np.r_[c, n0 + i * REFINE_POINTS + np.arange(REFINE_POINTS)]
                seeds[i] = int(idx_i[int(np.argmin(nnls_rss(B, cols[j][idx_i], y, problem.fit_power)))])
        return seeds

    screened: list = []  # the locally screened placements
    for _, chosen in distinct[:REFINED]:
        # A local screen around each light's LOCAL_SEEDS best distinct candidates (the others held),
        # its radius halved at each level around each seed's best so far: the coarse screen's
        # nearest candidate to a light can rank below a wrong one until both are refined.
        chosen = dict(chosen)
        for j in todo:
            others = [cols[i][chosen[i]] for i in chosen if i != j]
            B = np.stack(others, axis=1) if others else np.zeros((y.shape[0], 0))
            local_screen(j, B)
            chosen[j] = int(np.argmin(rss_for(j, chosen)))
        screened.append(pairs(*descend(chosen)[::-1]))
    screened.sort(key=lambda x: x[0])

    def theta_of(chosen: dict) -> np.ndarray:
        th = np.asarray(theta0, np.float64).copy()
        for j in todo:
            o = problem.offsets[j]
            th[o:o + params[j].size] = rows[j][chosen[j]]
        return th

    # The placements whose basins compete (module docstring, step 7): the locally screened ones,
    # each of them with one light moved to another of its best distinct candidates (the others
    # held), the beam's finals and deals; best screened residual first.
    contenders: list = list(screened)
    for _, chosen in screened:
        for j in todo:
            f = rss_for(j, chosen)
            for c in _distinct_best(f, centres(j, rows[j]), LOCAL_SEEDS, spacing):
                if c != chosen[j]:
                    contenders.append((float(f[c]), {**chosen, j: c}))
    contenders += [x for x in distinct if all(x[1] != c for _, c in screened)]
    contenders += [(f, ch) for f, ch in beams if len(ch) == len(todo)]
    contenders = contenders[:1] + sorted(contenders[1:], key=lambda x: x[0])
    best_f, best_ch = screened[0]
    thetas = np.stack([theta_of(ch) for _, ch in contenders])
    picked = distinct_basins(params, problem.offsets, thetas, region.extent, BASINS)
    alternatives = np.zeros((0, thetas.shape[1]))
    refined = None
    if lm is not None and len(picked) > 1:
        exact = max(EXACT * 0.5 * float(y @ y), float(explained))
        values, losses, problem = refine_and_rank(problem, thetas[picked], lm, keep, exact)
        win = picked[int(np.argmin(losses))]  # the losses are in `picked`'s order
        best_ch = contenders[win][1]
        if RESCREEN and not float(np.min(losses)) <= exact:  # step 8: the lights screened again at the best refined placement (`_rescreen`)
            def columns(j: int, r: np.ndarray) -> np.ndarray:
                nonlocal problem
                a, problem = unit_columns(problem, j, r)
                return a

            def refine(th: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
                nonlocal problem
                v, f, problem = refine_and_rank(problem, th, lm, keep, exact)
                return v, f

            def near(j: int, th: np.ndarray, B: np.ndarray) -> list[int]:
                """Light j's best candidate (columns `B` held) within `SPLIT_RADIUS` extents of each
                other light's centre in `th`."""
                f = nnls_rss(B, cols[j], y, problem.fit_power)
                pos = np.stack([centre_of_row(params[j], r) for r in rows[j]])
                out = []
                for i in todo:
                    if i != j:
                        c = centre_of_row(params[i], th[problem.offsets[i]:problem.offsets[i] + params[i].size])
                        g = np.where(np.linalg.norm(pos - c, axis=1) < SPLIT_RADIUS * region.extent, f, np.inf)
                        if np.isfinite(g).any():
                            out.append(int(np.argmin(g)))
                return out

            values, losses = rescreen(
                values, losses, todo, problem.offsets, [0 if p is None else p.size for p in params], rows, cols, y,
                problem.fit_power, columns, local_screen, refine,
                lambda th, k: distinct_basins(params, problem.offsets, th, region.extent, k), keep,
                deal=lambda th: dealt(params, problem.offsets, region, movable, th), near=near)
        refined = (values, losses)
        order = np.argsort(losses, kind="stable")
        best_f = 2.0 * float(losses[order[0]])
        theta = values[order[0]]
        fin = order[np.isfinite(losses[order])]  # the runners-up in basins distinct from the best and each other
        alternatives = values[fin[distinct_basins(params, problem.offsets, values[fin], region.extent,
                                                  1 + ALTERNATIVES)[1:]]]
    else:
        theta = theta_of(best_ch)
    ranked: list = [None] * J
    for j in todo:
        ranked[j] = rows[j][np.argsort(rss_for(j, best_ch), kind="stable")[:keep]]
    return Placement(theta, 0.5 * best_f, ranked, problem, alternatives, rows, cols, refined)

