"""`fit_lights`: several lights placed at once, with their powers, through the soft shadows.

The given poses are searched first (each light's sweeps, then jointly, below). Unless that
explains the targets exactly (`EXACT_LOSS`), the lights are then placed globally
(`_global_placement`): every pose screened over the region above the targets, the powers by
non-negative least squares, one light at a time on the residual; placements in distinct basins
are ranked by their loss after a short joint refinement; each light is searched from
its best screened poses and its own starts and all poses are refined jointly, and the lower
final loss of the two searches wins. So starts far from the truth, or no start at all
(`kinds=`: the global placement only), are not a local solver's problem, and starts close to
it cost what they did.

The multistart does not multiply. With `grid=`, the lights are instead placed one at a time
from a grid around the given poses (`_multilight_placement.greedy`): the lights not placed yet
are left out of the model,
every unplaced light's grid of positions (a scrambled Sobol stratification,
`_multistart.make_starts`) is screened and the light and position that explain the targets
best are refined and kept; the placed positions are then dealt to the lights in every order
(`swaps`: a small polygon high up passes for a point light lower down). Then each light in turn
is searched again from its own starts and a finer grid around its placed pose, the others held
at their current best and every power projected out, and all poses are refined jointly (sizes
last); the refined positions are dealt once more, and a better deal is swept and refined again.
The cost grows with the number of lights, not exponentially. One compiled program
(`_multilight._lm`) serves every stage.

Every light kind is placed: a polygon (pose and size), a segment (its ends), a point light
(position), a directional light (its direction). What a designer states goes in as well: a
plane or a box for a light's centre, a total power budget (`_powers`), targets painted as a
colour range or as "brighter than" relations (`_painting`), per-target weights.
"""

from __future__ import annotations

import dataclasses
import math
import warnings as _warnings
from typing import Any, no_type_check

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import jaxshadow as js
from jaxshadow import traced

from ._basis_rows import BasisRows
from ._diagnostics import FitQualityWarning, explained_loss, noise_weighted
from ._forward import SpecularFn
from ._global_placement import place, ranking_losses, region_of, template_light
from ._multilight import (
    LightsProblem,
    fixed_contribution,
    report_parts,
    solve,
)
from ._multilight_placement import greedy, pad, stage_mask, swaps
from ._multilight_report import (
    material_of,
    structured_coefficients,
)
from ._multilight_result import RIVAL_ROWS, result
from ._multistart import best_starts, capacity_with_room, make_starts, prune_schedule, start_lights
from ._options import Search, checked_constraints, search_options
from ._painting import Brighter, ColourRange, painting
from ._parametrisation import LightParametrisation, Outside, outside_planes, scene_size
from ._reports import LightsFit
from ._rescreen import noise_rivals
from ._solvers import AbstractLightSolver, checked_solver, screen_by_solver
from ._targets import PaintedTargets

FIT_LIGHTS_GROUPS = ("position", "orientation", "size", "power")
_POSE = ("position", "orientation", "size")
_POSITION_NAMES = ("x", "y", "z", "a", "b")
# Iterations the placement stages run at most (the joint refinement runs `LM.max_steps`).
STAGE_STEPS = 16
# A final loss below this fraction of the targets' energy (1/2 sum w c^2) is an exact fit: the
# global placement is not tried after the given poses' local search reaches it.
EXACT_LOSS = 1e-12
# A final joint solve stopped by max_steps whose loss fell by more than this fraction of it is not
# converged (`report.quality.flags`: "not_converged").
STILL_FALLING = 1e-3
# With told noise and every target searched, a loss that explains the targets within the noise
# (`_diagnostics.explained_loss`) ends the global placement's refine-and-rank and rescreen, skips
# the per-light sweeps after it and the second deal, as an exact fit does: a noisy residual never
# falls to `EXACT_LOSS`. False: those exits at an exact fit only.
EXPLAINED_EXIT = True


def _groups_for(light: Any, fit: tuple) -> tuple:
    """The pose groups of `fit` that this kind of light has."""
    if isinstance(light, js.PointLight):
        return tuple(g for g in fit if g == "position")
    if isinstance(light, (js.PolygonLight, js.LinearLight)):
        return tuple(g for g in fit if g in _POSE)
    return tuple(g for g in fit if g == "orientation")  # a DirectionalLight: its direction


def _checked(scene: Any, targets: Any, material: Any, lights: Any, fit: Any, material_mode: str,
             constraints: Any) -> tuple[list[int], tuple, dict]:
    if not isinstance(scene, js.Scene):
        raise ValueError(f"fit_lights: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    if not isinstance(targets, PaintedTargets):
        raise ValueError(f"fit_lights: targets must be PaintedTargets, got {type(targets).__name__}.")
    if not isinstance(material, js.Material):
        raise ValueError(f"fit_lights: material must be a jaxshadow.Material, got {type(material).__name__}.")
    if np.ndim(material.kd) != 1:
        raise ValueError("fit_lights: a per-receiver material is not supported; pass one (3,) material.")
    idx = list(range(len(scene.lights))) if lights is None else [int(i) for i in lights]
    if not idx or len(set(idx)) != len(idx) or not all(0 <= i < len(scene.lights) for i in idx):
        raise ValueError(f"fit_lights: lights must be distinct indices into the scene's {len(scene.lights)} "
                         f"light(s), got {lights}.")
    fit = (fit,) if isinstance(fit, str) else tuple(fit)
    unknown = [g for g in fit if g not in FIT_LIGHTS_GROUPS]
    if unknown or not fit:
        raise ValueError(f"fit_lights: fit must be a non-empty subset of {FIT_LIGHTS_GROUPS}, got {fit}.")
    if material_mode not in ("fixed", "projected"):
        raise ValueError(f"fit_lights: material_mode must be 'fixed' or 'projected', got {material_mode!r}.")
    cons = {} if constraints is None else dict(constraints)
    budget = cons.pop("budget", None)
    if budget is not None:
        b = np.asarray(budget, np.float64)
        if b.shape != () or not np.isfinite(b) or b <= 0:
            raise ValueError(f"fit_lights: the power budget must be a finite number > 0 (W), got {budget!r}.")
        if "power" not in fit:
            raise ValueError("fit_lights: a power budget needs 'power' in fit.")
        if material_mode == "projected":
            raise ValueError("fit_lights: a power budget needs material_mode='fixed' (a projected material "
                             "holds one power as its scale).")
        kinds = [type(scene.lights[i]).__name__ for i in idx if isinstance(scene.lights[i], js.DirectionalLight)]
        if kinds:
            raise ValueError("fit_lights: a power budget cannot include a DirectionalLight (no finite power); "
                             "leave it out of `lights`.")
        cons["budget"] = float(b)
    return idx, fit, checked_constraints(cons, idx, "fit_lights", several=True)


# Validates its own inputs (ValueError): no runtime annotation check before it.
@no_type_check
def fit_lights(
    scene: js.Scene,
    targets: PaintedTargets,
    material: js.Material,
    lights: Any = None,
    fit: tuple = FIT_LIGHTS_GROUPS,
    *,
    search: Search | None = None,
    constraints: dict | None = None,
    solver: AbstractLightSolver | None = None,
    material_mode: str = "fixed",
    ranges: ColourRange | None = None,
    brighter: Brighter | None = None,
    candidates: Any = None,
    specular: SpecularFn | None = None,
    noise: Any = None,
    warn: bool = True,
    kinds: Any = None,
    **options: Any,
) -> LightsFit:
    """Place several lights of `scene` at once, with their powers, so the shading matches
    painted colours (Poulin ch. 5: lights from diffuse shading, highlights and shadows).

    Minimises $\\sum_i w_i |L(x_i) - C_i|^2$ over the poses of the lights `lights` (soft
    shadows included) with each light's power a non-negative scale of its given radiance (the
    colour is the given one), projected out in the solver (variable projection: the powers enter
    linearly) and finally solved with bounds ($p \\ge 0$). With `material_mode="projected"` the
    material too: with the powers fitted, the search projects out, per channel, $k_a$ and every
    light's coefficient $k_d p_j$ independently (`_multilight._colour_free_rows`: a model that
    contains the structured one, linear in those coefficients), and the material and powers at
    the found poses are the bounded least squares of the structured (bilinear) model; with the
    powers held, alternately the poses at the current material (the solver) and $k_a, k_d, k_s
    \\ge 0$ at the current poses. The given poses are the
    starting point and the origin of each light's parametrisation (`LightParametrisation`).
    Lights not in `lights` are held as given.

    **Global placement (the default).** The given poses need not be close: each light's pose is
    first screened over the region where a light can light the targets (above them along their
    mean normal, up to 0.6 times their and the occluders' extent, inside a `Box` or on a
    `Plane` constraint), 512 Sobol positions plus the rays of `light_from_diffuse_maximum` at
    the brightest targets, a polygon facing the targets' centroid, facing down or as given,
    a segment as given or along three horizontal directions (`inverse._global_placement`).
    The powers are non-negative least squares over the lights' unit contributions (no
    derivative needed); the lights are added one at a time on the residual (a beam of 12
    partial placements), every pair of lights re-chosen together over all pairs of their
    candidates (two lights standing in for each other move at once), the positions dealt to
    the lights in every order, and each light screened again locally around its four best
    distinct candidates. Screened placements are not ranked by their screened residual (at the
    screen's resolution a wrong placement, its lights compensating for each other, can look as
    good as the right one): up to 16 of them in distinct basins are refined jointly for 30
    iterations in one batched solve and ranked by the refined loss; then each light is screened
    again with the others at the best refined placement (their columns no longer a grid step
    off), every pair of lights re-chosen together there, and those placements are refined and
    ranked too, in rounds while a round halves the best loss; the runners-up in distinct basins
    are finished with the best in the joint refinement below. It runs after the search from the given poses
    unless that fit is exact (a final loss below `EXACT_LOSS` = 1e-12 of $\\tfrac12\\sum w c^2$),
    and the lower final loss of the two wins, so starts 10 % away cost what they did. Then each
    light is searched from its best screened poses and its own starts (the others at
    their current best), then every pose jointly (sizes freed last): the starts add up over
    the lights instead of multiplying. Not with `ranges`, `brighter`, `material_mode="projected"`
    or `grid > 0` (those start from the given poses); `placement="local"` switches it off.

    Point and directional lights cast hard shadows: a target that crosses a shadow edge jumps in
    value with no derivative, so their poses come from the lit targets' shading (normals that
    vary), and starts whose shadows fall on the wrong targets can stop at a step of the loss (a
    directional light 4 degrees off on `_scenes.one_light_shadow_case`: recovered exactly with
    its power fitted, 1.7 degrees off with its power held).

    **Arguments:**

    - `scene`, `targets`, `material`; `lights`: indices of the lights to fit (default: all):
      `PolygonLight` (position, orientation, size), `LinearLight` (position, orientation,
      length: its two ends), `PointLight` (position), `DirectionalLight` (orientation: its
      direction, two angles `ru`, `rv` of a rotation perpendicular to the given direction).
    - `fit`: a subset of `("position", "orientation", "size", "power")`, applied to each light
      where its kind has the group (leave out `"size"` to hold the sizes fixed; without
      `"power"` the powers stay as given).
    - `constraints`: `{light index: inverse.Plane | inverse.Box | inverse.Outside}` for the
      light's centre (`Outside`: outside the convex hull of some occluders, a hinge penalty in
      the solve and a final move out through the nearest face: see `inverse.Outside`), and
      `"budget": B` (W, > 0) for the total power: $\\sum_j p_j c_j \\le B$ over the fitted
      lights, $c_j$ the power light $j$ emits at its given radiance, averaged over RGB
      (`_powers.emitted_power`: $\\pi \\bar L A$ for a polygon, $\\bar\\Phi \\ell$ for a segment,
      $4\\pi \\bar I$ for a point light; not with a fitted `DirectionalLight`). It holds in the
      variable projection (the least-squares powers on the plane $c \\cdot p = B$ when the free
      ones exceed it) and exactly in the final solve of the powers (`_powers.constrained_powers`);
      under a budget the solves' rows and the global placement's refined placements are ranked by
      the loss at those final powers (`_global_placement.final_losses`: the variable projection
      allows a negative power, which can meet the budget where no answer with powers >= 0 does).
    - `search`: an `inverse.Search` (where and how the poses are searched: `starts` per light,
      default 16, screened to the solver's `refine` best; `search_radius`, `orientation_spread`,
      `size_spread`, `seed`; `sweeps`; `grid`; `placement`; `search_targets`), or its fields as
      keywords (`starts=8, placement="local"`, which replace those of `search`). `grid > 0`:
      positions per light screened in a greedy placement around the given poses (with two or
      more lights to place; the same grid at a third of its size around each placed light in the
      sweeps; kept only if it explains the targets better than the given poses) instead of the
      global placement.
    - `material_mode`: `"fixed"` (as given) or `"projected"` (fitted jointly, $k \\ge 0$; the
      product $k_d p$ does not separate, so the first fitted light's power is held at 1 unless
      some light of the scene is not fitted, which then sets the scale).
    - `ranges`: an `inverse.ColourRange`: targets painted as a colour range (residual 0 inside,
      the distance outside); `brighter`: an `inverse.Brighter`: "target i at least as bright as
      target j" relations (luminance hinges). With either, the powers are searched with the
      poses ($p = q^2$) instead of projected out, and solved at the end with $p \\ge 0$ (and
      the budget) on the piecewise-linear residual; `material_mode="fixed"` only. The targets'
      weights weight every row (ranges included).
    - `solver`: an `inverse.LM` for its options (`refine`, `prune`, `rtol`, `atol`,
      `max_steps`); default `LM()` (the solver object of `fit_light`; its other solvers search
      one light only). The placement stages (greedy, deals, each light's sweeps)
      run at most `STAGE_STEPS` of the `max_steps` iterations: the joint refinement that
      follows converges from wherever they stop.
    - `candidates`: `(points (K, 3), normals (K, 3))` where new targets could be painted (default:
      a 9 x 9 grid over the targets' bounding box, with their mean normal): the report ranks them
      for each undetermined parameter.
    - `specular`: a callable like `js.specular` (default `js.specular`).
    - `search_targets` (a `Search` field): the targets the search uses (the greedy placement
      and each light's sweeps); the joint refinement then uses every target. For targets painted close to the lights (where the report's standard errors are small,
      `inverse.design_targets`), whose loss from far starts is spiky: search on the far-field
      ones. The others' weights are zero during the search (the same compiled program; the
      report's `initial_loss` and the search's `stage_losses` are over the search targets).
    - `noise`: the painted colours' standard deviation (colour units: a number, `(N,)` or
      `(N, 3)`), `"weights"` (the weights are inverse variances) or None (estimated: 2.5 % of
      the RMS weighted colour); what the checks of the answer compare the residual with
      (`inverse._diagnostics`: a wrong minimum, outliers, conflicting targets). Told standard
      deviations weight the fit, each target and channel by $w/\\sigma^2$ (the weights
      multiply in), and the standard errors are those of that weighted problem under them
      (with the noise estimated: scaled by the residual). A told noise also ends the global
      placement's search early where a refined placement explains the targets within it
      ($\\chi^2 \\le \\nu + \\sqrt{2\\nu}$, `_diagnostics.explained_loss`), as an exact fit does
      (`EXPLAINED_EXIT`): a noisy residual never falls to `EXACT_LOSS`.
    - `warn`: emit a `FitQualityWarning` when the answer is flagged (a wrong minimum, an
      escaped light, a polygon or segment collapsed to a point, a light left with no part in
      the colours, outlier targets (painted wrong or missed by lights in a wrong basin: give
      them weight 0 and fit again to tell), conflicting targets, an all-dark answer to
      "brighter than" relations, a
      joint refinement stopped by `max_steps` short of an exact fit: `"not_converged"`);
      the report's `quality` says so either way (`fit.report.trusted`,
      `fit.report.quality.reason`). To stop on it: `warnings.simplefilter("error",
      inverse.FitQualityWarning)`.
    - `kinds`: lights given by kind only, e.g. `kinds=["polygon", "point"]` (one of
      `"polygon"`, `"point"`, `"segment"`, `"directional"` each): they are added to `scene`
      (which may have no lights; its lights are then held as given) and fitted, with `lights`
      left None. Each starts white at unit power (radiance, intensity, power per length or
      irradiance `[1, 1, 1]`): a polygon a square of a tenth of the targets' and occluders'
      extent, a segment 0.15 of it long, a directional light pointing down. Their colour stays
      white (the fitted power is one grey scale per light): for coloured lights give starts.
    - `placement` (a `Search` field): `"global"` (default: the global placement above) or
      `"local"` (from the given poses only, for starts known to be close).

    **Returns:** `LightsFit(scene, lights, powers, material, residual, report, theta,
    parametrisations)`; `print(fit.report)` lists every parameter with its standard error,
    the pairs that trade off and where to paint targets for an undetermined parameter.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js
        import inverse

        material = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
        rng = np.random.default_rng(0)
        points = np.c_[rng.uniform(-1.5, 1.5, (40, 2)), np.zeros(40)]
        normals, eye = np.tile([0.0, 0.0, 1.0], (40, 1)), np.array([0.0, -3.0, 2.0])
        true = js.Scene([js.PointLight([-0.6, 0.2, 1.5], 4.0), js.PointLight([0.7, -0.3, 1.2], 2.0)], ambient=0.05)
        targets = inverse.PaintedTargets(points, normals, js.shade(true, material, points, normals, eye), eye)
        start = js.Scene([js.PointLight([-0.4, 0.0, 1.8], 3.0), js.PointLight([0.5, 0.0, 1.8], 3.0)], ambient=0.05)
        fit = inverse.fit_lights(start, targets, material, fit=("position", "power"), starts=4)
        fit.lights[0].position, fit.powers * 3.0   # ~ [-0.6, 0.2, 1.5]; ~ [4.0, 2.0]
        print(fit.report)
        ```
    """
    opts = search_options(search, options, "fit_lights", several=True)
    starts, search_radius, orientation_spread, size_spread = (opts.starts, opts.search_radius,
                                                              opts.orientation_spread, opts.size_spread)
    seed, sweeps, grid, placement, search_targets = opts.seed, opts.sweeps, opts.grid, opts.placement, opts.search_targets
    if kinds is not None:
        scene, lights = _with_new_lights(scene, targets, kinds, lights)
    idx, fit, cons = _checked(scene, targets, material, lights, fit, material_mode, constraints)
    targets = noise_weighted(targets, noise)  # told noise: each target and channel weighted by 1/sigma^2
    budget = cons.pop("budget", None)
    paint = painting(len(targets), ranges, brighter, targets.points.dtype)
    if paint is not None and material_mode == "projected":
        raise ValueError("fit_lights: ranges and brighter-than relations need material_mode='fixed'.")
    solver = checked_solver(solver, "fit_lights", several=True)
    t = targets
    dt = t.points.dtype
    size = scene_size(scene, t)
    with_spec = bool(np.any(np.asarray(material.ks) != 0))
    fit_power = "power" in fit
    project = material_mode == "projected"
    params, offsets, off = [], [], 0
    for i in idx:
        groups = _groups_for(scene.lights[i], fit)
        if not groups:
            if i in cons:
                raise ValueError(f"fit_lights: a constraint for light {i}, whose position is not fitted.")
            params.append(None)
        else:
            c = cons.get(i)
            if isinstance(c, Outside) and "position" not in groups:
                raise ValueError(f"fit_lights: inverse.Outside for light {i}, whose position is not fitted.")
            params.append(LightParametrisation(scene.lights[i], i, groups, None if isinstance(c, Outside) else c,
                                               size, solver.box_map))
        offsets.append(off)
        off += 0 if params[-1] is None else params[-1].size
    P = off
    if P == 0 and not fit_power:
        raise ValueError("fit_lights: nothing to fit.")
    if project:  # one dtype and shape for every material the alternation below puts in the problem
        material = material_of(np.stack([np.broadcast_to(np.asarray(getattr(material, f), np.float64), (3,))
                                         for f in ("ka", "kd", "ks")]), float(material.exponent), dt)
    fixed = [light for k, light in enumerate(scene.lights) if k not in idx]
    e0, s0 = fixed_contribution(scene, t, material, fixed, specular, with_spec)
    in_theta = paint is not None and fit_power
    problem = LightsProblem(tuple(params), tuple(scene.lights[i] for i in idx), scene, material, t, e0, s0,
                            tuple(offsets), fit_power, with_spec, bool(fixed), specular, paint=paint,
                            budget=None if budget is None else jnp.asarray(budget, dt), powers_in_theta=in_theta,
                            active=jax.device_put(np.ones(len(idx), dt)),
                            outside=tuple((j, *(jnp.asarray(x, dt) for x in outside_planes(scene, cons[i])),
                                           cons[i].margin) for j, i in enumerate(idx)
                                          if isinstance(cons.get(i), Outside)),
                            colour_free=project and fit_power)
    Pt = problem.n_theta  # poses, then (with ranges or relations) q, p = q^2, from the given powers
    theta0 = np.r_[np.zeros(P), np.ones(Pt - P)]
    per_light = []
    for j, p in enumerate(params):
        if p is None:
            per_light.append(None)
            continue
        y = np.asarray(make_starts(p, int(starts), search_radius=search_radius, orientation_spread=orientation_spread,
                                   size_spread=size_spread, seed=seed + j, dtype=np.float64))
        theta0[offsets[j]:offsets[j] + p.size] = y[0]
        per_light.append(y)
    grid_rows = None
    if int(grid) > 0 and sum(p is not None for p in params) > 1:
        grid_rows = [None if p is None else
                     np.asarray(make_starts(p, int(grid), search_radius=search_radius, orientation_spread=0.0,
                                            size_spread=0.0, seed=seed + 101 + j, dtype=np.float64))
                     for j, p in enumerate(params)]
    problem = _with_capacity(problem, [y if g is None else np.concatenate([y, g]) if y is not None else None
                                       for y, g in zip(per_light, grid_rows or [None] * len(per_light),
                                                       strict=True)], fixed)
    search_w = _search_weights(t, search_targets)
    k = max(1, min(int(solver.refine or starts), int(starts)))
    sched = prune_schedule(k, solver.max_steps) if solver.prune else ()
    lm = dict(rtol=solver.rtol, atol=solver.atol, max_steps=solver.max_steps, prune=sched)
    staged = dict(lm, max_steps=min(int(solver.max_steps), STAGE_STEPS))
    tol = dict(rtol=solver.rtol, atol=solver.atol)  # static arguments of the LM program: the screens run it too
    if project:  # the material (and powers) that best fit the given poses: where the search starts
        problem = dataclasses.replace(problem, material=_material_at(problem, theta0))
    full_w = problem.targets.weights
    problem = _reweighted(problem, search_w)
    stage_losses, n_solved, retries = [], 0, 0
    initial = None
    use_global = (placement == "global" and grid_rows is None and not in_theta and not project
                  and any(p is not None and "position" in p._slices() for p in params))
    # The given poses' local search first; the global placement competes unless that fit is
    # exact already (the lowest final loss wins).
    energy = 0.5 * float(np.sum(np.asarray(full_w) * np.asarray(problem.targets.colours) ** 2))
    # within the told noise (EXPLAINED_EXIT): over every target, so not with search targets
    noise_loss = (explained_loss(full_w, t, noise, P + (len(idx) if fit_power else 0))
                  if EXPLAINED_EXIT and search_w is None else 0.0)
    within = max(EXACT_LOSS * energy, noise_loss)
    best_attempt: tuple | None = None
    screened, more = None, None  # the global placement's candidates, columns, refined placements (`noise_rivals`)
    # Lights given by kind only: their templates are candidates of the global placement already.
    attempts = ("local", "global") if use_global and kinds is None else ("global",) if use_global else ("local",)
    for attempt in attempts:
        problem = _reweighted(problem, search_w)
        base = theta0.copy()
        converged = True
        runner_up: dict = {}
        final = None  # the last joint solve's rows and losses, best first: the competing placements
        placed = grid_rows is not None
        ranked: list = [None] * len(params)
        alternatives: list = []  # the global placement's other refined placements: finished jointly
        best_round: tuple | None = None  # (loss, joint rows, final, converged) of the better round
        if attempt == "global":
            if initial is None:  # the given poses' loss
                f0, problem, r = screen_by_solver(problem, theta0[None], theta0, np.ones(Pt, bool), k, **tol)
                initial, retries = float(f0[0]), retries + r
            pl = place(problem, theta0, per_light, cons, idx, seed, k, lm, noise_loss)
            problem, base, ranked, alternatives = pl.problem, pl.theta, pl.ranked, list(pl.alternatives)
            screened = (pl.rows, pl.cols, pl.refined)
            stage_losses.append(pl.loss)
            placed = True
        elif placed:
            problem, base, initial, n, retries = greedy(problem, base, grid_rows, offsets, P, in_theta, k, staged,
                                                         stage_losses)
            n_solved += n
            problem, base, n, r = swaps(problem, base, offsets, k, staged, stage_losses)
            n_solved += n
            retries += r
            if not stage_losses[-1] < initial:  # the given poses explain the targets better
                base = theta0.copy()
        if P:
            n_sweeps = int(sweeps)
            if attempt == "global" and search_w is None and not stage_losses[-1] > within:
                n_sweeps = 0  # the placement explains the targets (exactly or within the noise): the joint refinement alone
            for rnd in range(2 if placed else 1):
                problem = _reweighted(problem, search_w)
                for sweep, j in ((s, j) for s in range(n_sweeps) for j in range(len(per_light))):
                    y = per_light[j]
                    if y is None:
                        continue
                    sl = slice(offsets[j], offsets[j] + params[j].size)
                    mask = np.zeros(Pt, bool)
                    mask[sl] = stage_mask(params[j])
                    if in_theta:  # its power with it
                        mask[P + j] = True
                    if grid_rows is not None:  # the grid again, a third the size, around the placed pose
                        g = grid_rows[j]
                        y = np.concatenate([y, base[sl][None] + (g - g[:1]) / 3.0])
                    if ranked[j] is not None:  # the global placement's candidates for this light
                        y = np.concatenate([y, ranked[j]])
                    full = np.tile(base, (y.shape[0], 1))
                    full[:, sl] = y
                    if sweep or placed:  # again, with the others placed: from the current pose and the same spread
                        full[0, sl] = base[sl]
                    if full.shape[0] > k:  # screen: the loss by the LM program with no iterations, k starts a call
                        losses, problem, r = screen_by_solver(problem, full, base, mask, k, **tol)
                        retries += r
                        if initial is None and sweep == 0:
                            initial = float(losses[0])  # the given poses (row 0), screened out or not
                        full = full[best_starts(np.where(np.isfinite(losses), losses, np.inf), k)]
                    res, problem, r = solve(problem, full, base, mask, **staged)
                    retries += r
                    n_solved += full.shape[0]
                    # The solved rows hold the starts' values where the mask is off: the residual used `base`.
                    vals = np.where(mask[None], np.asarray(res.values), base[None])
                    f, problem = ranking_losses(problem, res.losses, vals)
                    order = np.argsort(f)
                    if initial is None:
                        initial = float(np.asarray(res.initial_losses)[0]) if np.all(full[0] == theta0) else None
                    base = vals[order[0]].copy()
                    if len(order) > 1 and np.isfinite(f[order[1]]):
                        runner_up[j] = vals[order[1]][sl]
                    stage_losses.append(float(f[order[0]]))
                # the given poses together are a candidate too (the grid's greedy placement replaces them)
                joint = [base] + ([] if grid_rows is not None else [theta0]) + (alternatives if not rnd else [])
                for j, v in runner_up.items():
                    alt = base.copy()
                    alt[offsets[j]:offsets[j] + params[j].size] = v
                    joint.append(alt)
                # Sizes last: free from the start, a polygon trades its size for its power (it shrinks to a
                # bright point or grows dim) before the poses are right.
                sizes = np.concatenate([np.zeros(0, bool)] + [_size_mask(p) for p in params if p is not None]
                                       + [np.zeros(Pt - P, bool)])
                joint = pad(np.stack(joint[:k]), k)
                problem = _reweighted(problem, full_w)  # every target from here on
                for mask in ([~sizes] if sizes.any() else []) + [np.ones(Pt, bool)]:
                    res, problem, r = solve(problem, joint, base, mask, **lm)
                    retries += r
                    n_solved += joint.shape[0]
                    vals = np.where(mask[None], np.asarray(res.values), base[None])
                    f, problem = ranking_losses(problem, res.losses, vals)
                    joint = vals[np.argsort(f)]
                    final = (joint, np.sort(f))
                    stage_losses.append(float(np.min(f)))
                    # Not converged: the best row stopped by max_steps (not by the solver's tolerances or at
                    # round-off) with its loss still falling (by STILL_FALLING of it in this solve); a row
                    # crawling along a flat valley at its minimum is not flagged.
                    b = int(np.argmin(f))
                    f_lm = np.asarray(res.losses, np.float64)
                    f_in = float(np.asarray(res.initial_losses)[b])
                    converged = bool(np.asarray(res.converged)[b]) or not f_in - f_lm[b] > STILL_FALLING * f_lm[b]
                if best_round is None or stage_losses[-1] < best_round[0]:
                    best_round = (stage_losses[-1], joint, final, converged)
                if rnd or not placed or not stage_losses[-1] > within:  # explained: no deal does better
                    break
                # The refined positions dealt again (two lights of similar shading swapped in the first
                # deal under noise): from a better deal, one more sweep and joint refinement.
                problem, dealt, n, r = swaps(problem, joint[0], offsets, k, staged, stage_losses, theta0)
                n_solved += n
                retries += r
                if not stage_losses[-1] < stage_losses[-2] * (1 - 1e-6) - solver.atol:  # not at round-off
                    break
                base, n_sweeps = dealt, 1
            # the better of the two rounds (a deal better in the LM's loss can end worse)
            if best_round is not None and best_round[1] is not joint:
                _, joint, final, converged = best_round
                stage_losses.append(best_round[0])
            theta = joint[0]
            if project and not problem.colour_free:
                problem, theta, n, r = _alternate(problem, theta, joint, base, lm, stage_losses)
                n_solved += n
                retries += r
        else:
            theta = theta0
        loss = stage_losses[-1] if P else math.nan
        # an exact fit has converged whatever stopped the solver
        converged = converged or not loss > EXACT_LOSS * energy
        if best_attempt is None or loss < best_attempt[0]:
            best_attempt = (loss, theta, final, problem, converged)
        if not loss > EXACT_LOSS * energy:
            break
    _, theta, final, problem, converged = best_attempt
    problem = _reweighted(problem, full_w)
    if (screened is not None and noise is not None and search_w is None and not project and paint is None
            and budget is None and fit_power and best_attempt[0] > EXACT_LOSS * energy):
        # competing placements the final joint solve did not refine (`_rescreen.noise_rivals`)
        theta, more, problem = noise_rivals(problem, np.asarray(theta, np.float64), *screened, k, lm, noise, RIVAL_ROWS)
    theta = _moved_outside(problem, np.asarray(theta, np.float64))
    # The report's basis and tangents from the search's own LM program (k rows a call: no new compilation).
    rows_at = BasisRows(problem, k, (solver.rtol, solver.atol)) if P else None
    out = result(problem, np.asarray(theta, np.float64), idx, size, candidates, stage_losses, n_solved,
                  retries, initial, project, noise, final if P else None, converged=converged, rows_at=rows_at,
                  more=more)
    if warn:
        for msg in out.report.quality.emitted:
            _warnings.warn(msg, FitQualityWarning, stacklevel=2)
    return out


def _with_new_lights(scene: Any, targets: Any, kinds: Any, lights: Any) -> tuple[js.Scene, list[int]]:
    """`scene` with one template light per entry of `kinds` appended (`template_light`: white,
    unit power, in the middle of the feasible region) and their indices."""
    if not isinstance(scene, js.Scene):
        raise ValueError(f"fit_lights: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    if not isinstance(targets, PaintedTargets):
        raise ValueError(f"fit_lights: targets must be PaintedTargets, got {type(targets).__name__}.")
    if lights is not None:
        raise ValueError("fit_lights: give either kinds (new lights) or lights (indices of the scene's), not both.")
    kinds = [kinds] if isinstance(kinds, str) else list(kinds)
    if not kinds:
        raise ValueError("fit_lights: kinds must name at least one light kind.")
    region = region_of(scene, np.asarray(targets.points), np.asarray(targets.normals))
    new = [template_light(str(k), region) for k in kinds]
    n = len(scene.lights)
    # the same occluders (and topology) with the new lights: no new Scene built from its arrays
    out = eqx.tree_at(lambda s: s.lights, scene, (*scene.lights, *new))
    return out, list(range(n, n + len(new)))


def _search_weights(targets: PaintedTargets, search: Any) -> Any:
    """The targets' weights with those not in `search` (indices or an `(N,)` bool mask) zeroed;
    None when `search` is None."""
    if search is None:
        return None
    n = len(targets)
    s = np.asarray(search)
    if s.dtype == bool:
        if s.shape != (n,):
            raise ValueError(f"fit_lights: a search_targets mask must have shape ({n},), got {s.shape}.")
        keep = s
    else:
        if s.ndim != 1 or not np.issubdtype(s.dtype, np.integer) or s.size == 0 or s.min() < 0 or s.max() >= n:
            raise ValueError(f"fit_lights: search_targets must be indices into the {n} targets or a bool mask.")
        keep = np.zeros(n, bool)
        keep[s] = True
    if not keep.any():
        raise ValueError("fit_lights: search_targets selects no target.")
    w = np.asarray(targets.weights)
    return jax.device_put(w * keep.astype(w.dtype)[:, None])


def _reweighted(problem: LightsProblem, weights: Any) -> LightsProblem:
    """`problem` with its targets' weights replaced (a leaf: the same compiled program)."""
    if weights is None:
        return problem
    return dataclasses.replace(problem, targets=eqx.tree_at(lambda t: t.weights, problem.targets, weights))


def _moved_outside(problem: LightsProblem, theta: np.ndarray) -> np.ndarray:
    """`theta` with every `Outside`-constrained centre still short of its margin moved out
    through the hull face whose plane it is closest to (`inverse.Outside`: exact up to rounding,
    since that face's value is the largest)."""
    theta = theta.copy()
    for j, A, b, margin in problem.outside:
        p, o = problem.params[j], problem.offsets[j]
        sl = p._slices()["position"]
        c = np.asarray(p.centre_of(jnp.asarray(theta[o:o + p.size])), np.float64)
        A, b = np.asarray(A, np.float64), np.asarray(b, np.float64)
        g = A @ c + b
        f = int(np.argmax(g))
        if g[f] >= margin:
            continue
        c_new = c + (margin - g[f]) * A[f] * (1 + 1e-12)
        theta[o + sl.start:o + sl.stop] += (c_new - c) / float(p.scale)  # an Outside light's centre is free
    return theta


def _size_mask(param: LightParametrisation) -> np.ndarray:
    """Which of a light's parameters are its size."""
    out = np.zeros(param.size, bool)
    sl = param._slices()
    if "size" in sl:
        out[sl["size"]] = True
    return out


def _with_capacity(problem: LightsProblem, per_light: list, fixed: list) -> LightsProblem:
    """The problem with the shadow capacity for every light at every one of its starts."""
    scene, t = problem.scene, problem.targets
    if scene.occluders is None:
        return problem
    cands = list(fixed)
    for j, y in enumerate(per_light):
        p = problem.params[j]
        cands += [problem.refs[j]] if y is None else start_lights(p, y)
    most = traced.shadow_capacity(scene, t.points, t.normals, lights=cands)
    # Rounded up to a power of two: nearby scenes and starts share one compiled program.
    return dataclasses.replace(problem, capacity=capacity_with_room(most))


def _material_at(problem: LightsProblem, theta: np.ndarray) -> js.Material:
    """The structured least-squares material at the poses `theta` (`structured_coefficients`)."""
    t = problem.targets
    dt = t.points.dtype
    gauge = 0 if (problem.fit_power and not problem.has_fixed) else None
    E, S, _ = (np.asarray(x, np.float64) for x in report_parts(problem, jnp.asarray(theta, dt),
                                                                jnp.ones(len(problem.params), dt), problem.material))
    spec = problem.with_specular
    _, k = structured_coefficients(E, S if spec else None, np.asarray(problem.e_fixed, np.float64),
                                   np.asarray(problem.s_fixed, np.float64) if spec else None,
                                   np.asarray(problem.scene.ambient, np.float64), np.asarray(t.colours, np.float64),
                                   np.asarray(t.weights, np.float64), problem.material,
                                   fit_power=problem.fit_power, project=True, gauge=gauge)
    return material_of(k, problem.material.exponent, dt)


def _alternate(problem: LightsProblem, theta: np.ndarray, joint: np.ndarray, base: np.ndarray, lm: dict,
               stage_losses: list, rounds: int = 6) -> tuple[LightsProblem, np.ndarray, int, int]:
    """The projected material: alternately the material and powers at the current poses (structured
    least squares, `structured_coefficients`), then the poses and powers at that material (the
    joint solve again: the material is a leaf of the problem, the program is the same), until the
    loss stops decreasing. Returns `(problem, theta, starts solved, retries)`."""
    n_solved = retries = 0
    best = stage_losses[-1]
    for _ in range(rounds):
        trial = dataclasses.replace(problem, material=_material_at(problem, theta))
        res, trial, r = solve(trial, joint, base, np.ones(len(theta), bool), **lm)
        retries += r
        n_solved += joint.shape[0]
        f = np.where(np.isfinite(np.asarray(res.losses)), np.asarray(res.losses), np.inf)
        stage_losses.append(float(np.min(f)))
        if not np.min(f) < best * (1 - 1e-9):
            break
        best = float(np.min(f))
        problem = trial
        joint = np.asarray(res.values)[np.argsort(f)]
        theta = joint[0]
    return problem, theta, n_solved, retries
