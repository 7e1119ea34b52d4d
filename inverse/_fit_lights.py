"""`fit_lights`: several lights placed at once, with their powers, through the soft shadows.

The given poses are searched first (each light's sweeps, then jointly, below). Unless that
explains the targets exactly (`EXACT_LOSS`), the lights are then placed globally
(`_global_placement`): every pose screened over the region above the targets, the powers by
non-negative least squares, one light at a time on the residual; each light is searched from
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
import jax.numpy as jnp
import numpy as np

import jaxshadow as js
from jaxshadow import traced

from ._diagnostics import (
    FitQualityWarning,
    assess,
    competing_placements,
    dark_answer,
)
from ._forward import SpecularFn
from ._global_placement import place, region_of, template_light
from ._identifiability import identifiability
from ._multilight import (
    LightsProblem,
    build_lights,
    fixed_contribution,
    report_parts,
    scaled_light,
    screen,
    solve,
)
from ._multilight_placement import greedy, pad, stage_mask, swaps
from ._multilight_report import (
    LightsFit,
    LightsReport,
    correlated_pairs,
    material_of,
    null_directions,
    structured_coefficients,
)
from ._multistart import best_starts, make_starts, prune_schedule, start_lights
from ._painting import Brighter, ColourRange, as_numpy, painted_rows, painting
from ._parametrisation import Box, LightParametrisation, Outside, Plane, outside_planes, scene_size
from ._powers import constrained_powers, emitted_power, painted_jacobian
from ._solvers import LM
from ._targets import PaintedTargets

FIT_LIGHTS_GROUPS = ("position", "orientation", "size", "power")
_POSE = ("position", "orientation", "size")
_POSITION_NAMES = ("x", "y", "z", "a", "b")
# Iterations the placement stages run at most (the joint refinement runs `LM.max_steps`).
STAGE_STEPS = 16
# A final loss below this fraction of the targets' energy (1/2 sum w c^2) is an exact fit: the
# global placement is not tried after the given poses' local search reaches it.
EXACT_LOSS = 1e-12


def _groups_for(light: Any, fit: tuple) -> tuple:
    """The pose groups of `fit` that this kind of light has."""
    if isinstance(light, js.PointLight):
        return tuple(g for g in fit if g == "position")
    if isinstance(light, (js.PolygonLight, js.LinearLight)):
        return tuple(g for g in fit if g in _POSE)
    return tuple(g for g in fit if g == "orientation")  # a DirectionalLight: its direction


def _checked(scene: Any, targets: Any, material: Any, lights: Any, fit: Any, starts: int, material_mode: str,
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
    if int(starts) < 1:
        raise ValueError(f"fit_lights: starts must be >= 1, got {starts}.")
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
    for k, c in cons.items():
        if k == "budget":
            continue
        if int(k) not in idx:
            raise ValueError(f"fit_lights: a constraint for light {k}, which is not fitted.")
        if not isinstance(c, (Plane, Box, Outside)):
            raise ValueError("fit_lights: constraints must be inverse.Plane, inverse.Box or inverse.Outside, got "
                             f"{type(c).__name__}.")
    return idx, fit, {(k if k == "budget" else int(k)): c for k, c in cons.items()}


# Validates its own inputs (ValueError): no runtime annotation check before it.
@no_type_check
def fit_lights(
    scene: js.Scene,
    targets: PaintedTargets,
    material: js.Material,
    lights: Any = None,
    fit: tuple = FIT_LIGHTS_GROUPS,
    *,
    constraints: dict | None = None,
    starts: int = 16,
    search_radius: float = 0.5,
    orientation_spread: float = 0.5,
    size_spread: float = 0.5,
    seed: int = 0,
    sweeps: int = 2,
    grid: int = 0,
    material_mode: str = "fixed",
    ranges: ColourRange | None = None,
    brighter: Brighter | None = None,
    solver: LM | None = None,
    candidates: Any = None,
    specular: SpecularFn | None = None,
    search_targets: Any = None,
    noise: Any = None,
    warn: bool = True,
    kinds: Any = None,
    placement: str = "global",
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
    partial placements), the positions dealt to the lights in every order, and each light
    screened again locally around its pose. It runs after the search from the given poses
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
      ones exceed it) and exactly in the final solve of the powers (`_powers.constrained_powers`).
    - `starts`: starts per light (the given pose first, then a Sobol stratification within
      `search_radius` scene sizes, `orientation_spread` rad, `size_spread` relative; `seed`);
      each light's starts are screened to the solver's `refine` best.
    - `sweeps`: how many times each light's own multistart runs (in turn, the others at their
      current best) before the joint refinement.
    - `grid`: positions per light screened in a greedy placement around the given poses
      within `search_radius` (with two or more lights to place; the same grid at a third of
      its size around each placed light in the sweeps; kept only if it explains the targets
      better than the given poses) instead of the global placement; 0 (default): the global
      placement (`placement`).
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
      `max_steps`); default `LM()`. The placement stages (greedy, deals, each light's sweeps)
      run at most `STAGE_STEPS` of the `max_steps` iterations: the joint refinement that
      follows converges from wherever they stop.
    - `candidates`: `(points (K, 3), normals (K, 3))` where new targets could be painted (default:
      a 9 x 9 grid over the targets' bounding box, with their mean normal): the report ranks them
      for each undetermined parameter.
    - `specular`: a callable like `js.specular` (default `js.specular`).
    - `search_targets`: indices (or an `(N,)` bool mask) of the targets the search uses (the
      greedy placement and each light's sweeps); the joint refinement then uses every target.
      For targets painted close to the lights (where the report's standard errors are small,
      `inverse.design_targets`), whose loss from far starts is spiky: search on the far-field
      ones. The others' weights are zero during the search (the same compiled program; the
      report's `initial_loss` and the search's `stage_losses` are over the search targets).
    - `noise`: the painted colours' standard deviation (colour units: a number, `(N,)` or
      `(N, 3)`), `"weights"` (the weights are inverse variances) or None (estimated: 2.5 % of
      the RMS weighted colour); what the checks of the answer compare the residual with
      (`inverse._diagnostics`: a wrong minimum, outliers, conflicting targets).
    - `warn`: emit a `FitQualityWarning` when the answer is flagged (a wrong minimum, an
      escaped light, a polygon or segment collapsed to a point, a light left with no part in
      the colours, conflicting targets, an all-dark answer to "brighter than" relations);
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
    - `placement`: `"global"` (default: the global placement above) or `"local"` (from the
      given poses only: the previous behaviour, for starts known to be close).

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
    if kinds is not None:
        scene, lights = _with_new_lights(scene, targets, kinds, lights)
    if placement not in ("global", "local"):
        raise ValueError(f"fit_lights: placement must be 'global' or 'local', got {placement!r}.")
    idx, fit, cons = _checked(scene, targets, material, lights, fit, starts, material_mode, constraints)
    budget = cons.pop("budget", None)
    paint = painting(len(targets), ranges, brighter, targets.points.dtype)
    if paint is not None and material_mode == "projected":
        raise ValueError("fit_lights: ranges and brighter-than relations need material_mode='fixed'.")
    if int(sweeps) < 1:
        raise ValueError(f"fit_lights: sweeps must be >= 1, got {sweeps}.")
    if int(grid) < 0:
        raise ValueError(f"fit_lights: grid must be >= 0, got {grid}.")
    solver = LM() if solver is None else solver
    if not isinstance(solver, LM):
        raise ValueError(f"fit_lights: solver must be an inverse.LM, got {type(solver).__name__}.")
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
                            active=jnp.ones(len(idx), dt),
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
    energy = 0.5 * float(jnp.sum(full_w * problem.targets.colours ** 2))
    best_attempt: tuple | None = None
    # Lights given by kind only: their templates are candidates of the global placement already.
    attempts = ("local", "global") if use_global and kinds is None else ("global",) if use_global else ("local",)
    for attempt in attempts:
        problem = _reweighted(problem, search_w)
        base = theta0.copy()
        runner_up: dict = {}
        final = None  # the last joint solve's rows and losses, best first: the competing placements
        placed = grid_rows is not None
        ranked: list = [None] * len(params)
        if attempt == "global":
            if initial is None:  # the given poses' loss
                f0, problem, r = screen(problem, theta0[None], theta0, np.ones(Pt, bool), k)
                initial, retries = float(f0[0]), retries + r
            pl = place(problem, theta0, per_light, cons, idx, seed, k)
            problem, base, ranked = pl.problem, pl.theta, pl.ranked
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
                    if full.shape[0] > k:  # screen: the loss alone (no Jacobian), k starts a call
                        losses, problem, r = screen(problem, full, base, mask, k)
                        retries += r
                        if initial is None and sweep == 0:
                            initial = float(losses[0])  # the given poses (row 0), screened out or not
                        full = full[best_starts(np.where(np.isfinite(losses), losses, np.inf), k)]
                    res, problem, r = solve(problem, full, base, mask, **staged)
                    retries += r
                    n_solved += full.shape[0]
                    f = np.where(np.isfinite(np.asarray(res.losses)), np.asarray(res.losses), np.inf)
                    order = np.argsort(f)
                    if initial is None:
                        initial = float(np.asarray(res.initial_losses)[0]) if np.all(full[0] == theta0) else None
                    # The solved rows hold the starts' values where the mask is off: the residual used `base`.
                    vals = np.where(mask[None], np.asarray(res.values), base[None])
                    base = vals[order[0]].copy()
                    if len(order) > 1 and np.isfinite(f[order[1]]):
                        runner_up[j] = vals[order[1]][sl]
                    stage_losses.append(float(f[order[0]]))
                # the given poses together are a candidate too (the grid's greedy placement replaces them)
                joint = [base] + ([] if grid_rows is not None else [theta0])
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
                    f = np.where(np.isfinite(np.asarray(res.losses)), np.asarray(res.losses), np.inf)
                    joint = np.where(mask[None], np.asarray(res.values), base[None])[np.argsort(f)]
                    final = (joint, np.sort(f))
                    stage_losses.append(float(np.min(f)))
                if rnd or not placed:
                    break
                # The refined positions dealt again (two lights of similar shading swapped in the first
                # deal under noise): from a better deal, one more sweep and joint refinement.
                problem, dealt, n, r = swaps(problem, joint[0], offsets, k, staged, stage_losses, theta0)
                n_solved += n
                retries += r
                if not stage_losses[-1] < stage_losses[-2] * (1 - 1e-6) - solver.atol:  # not at round-off
                    break
                base, n_sweeps = dealt, 1
            theta = joint[0]
            if project and not problem.colour_free:
                problem, theta, n, r = _alternate(problem, theta, joint, base, lm, stage_losses)
                n_solved += n
                retries += r
        else:
            theta = theta0
        loss = stage_losses[-1] if P else math.nan
        if best_attempt is None or loss < best_attempt[0]:
            best_attempt = (loss, theta, final, problem)
        if not loss > EXACT_LOSS * energy:
            break
    _, theta, final, problem = best_attempt
    problem = _reweighted(problem, full_w)
    theta = _moved_outside(problem, np.asarray(theta, np.float64))
    out = _result(problem, np.asarray(theta, np.float64), idx, size, candidates, stage_losses, n_solved,
                  retries, initial, project, noise, final if P else None)
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
    out = js.Scene([*scene.lights, *new], occluders=scene.occluders, ambient=scene.ambient)
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
    return targets.weights * jnp.asarray(keep, targets.weights.dtype)[:, None]


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
        cands += [problem.refs[j]] if y is None else start_lights(p, jnp.asarray(y))
    most = traced.shadow_capacity(scene, t.points, t.normals, lights=cands)
    # Rounded up to a multiple of 8: nearby scenes and starts share one compiled program.
    return dataclasses.replace(problem, capacity=8 * -(-max(8, -(-5 * most // 4) + 4) // 8))


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


def _result(problem: LightsProblem, theta: np.ndarray, idx: list, size: float, candidates: Any,
            stage_losses: list, n_solved: int, retries: int, initial: float | None, project: bool,
            noise: Any = None, final: tuple | None = None) -> LightsFit:
    t, m = problem.targets, problem.material
    dt = t.points.dtype
    q = np.asarray(theta[problem.n_pose:], np.float64)  # the searched powers' roots, if any
    theta = theta[:problem.n_pose]
    th = jnp.asarray(theta, dt)
    J = len(idx)
    ones = jnp.ones(J, dt)
    E, S, _ = (np.asarray(x, np.float64) for x in report_parts(problem, th, ones, m))
    colours, w = np.asarray(t.colours, np.float64), np.asarray(t.weights, np.float64)
    La = np.asarray(problem.scene.ambient, np.float64)
    e0, s0 = np.asarray(problem.e_fixed, np.float64), np.asarray(problem.s_fixed, np.float64)
    spec = problem.with_specular
    gauge = 0 if (project and problem.fit_power and not problem.has_fixed) else None
    coef = lambda EE, SS: structured_coefficients(  # noqa: E731
        EE, SS if spec else None, e0, s0 if spec else None, La, colours, w, m, fit_power=problem.fit_power,
        project=project, gauge=gauge)
    powers, k = coef(E, S)
    sw = np.sqrt(w)
    paint = as_numpy(problem.paint)
    per_light = k[1] / np.pi * E + (k[2] * S if spec else 0.0)  # (J, N, 3): the model's power columns
    budget_active = False
    if problem.fit_power and (paint is not None or problem.budget is not None):
        bud = None
        if problem.budget is not None:
            c = np.array([float(emitted_power(x)) for x in build_lights(problem, th)])
            bud = (c, float(problem.budget))
        fixed_part = _model(E, S, e0, s0, La, np.zeros(J), k, spec)
        powers = constrained_powers(fixed_part, per_light, colours, sw, paint, bud, q * q if q.size else powers)
        budget_active = bud is not None and bud[0] @ powers >= bud[1] * (1 - 1e-9)
    mat = material_of(k, m.exponent, dt) if project else m
    _, _, Jth = (np.asarray(x, np.float64) for x in report_parts(problem, th, jnp.asarray(powers, dt), mat))
    model = _model(E, S, e0, s0, La, powers, k, spec)
    residual = model - colours
    rows = painted_rows(model, colours, sw, paint)
    if paint is not None:  # a ranged target's residual: its distance outside the range
        residual = np.where(paint.ranged, np.minimum(model - paint.lower, 0.0) + np.maximum(model - paint.upper, 0.0),
                            residual)
    power_cols = painted_jacobian(model, per_light, sw, paint)
    # The report's parameters: poses, then powers, then the material.
    names, cols, scale_of = [], [], []
    for j, p in enumerate(problem.params):
        if p is not None:
            names += [f"light{idx[j]}.{nm}" for nm in p.names]
            scale_of += [size if nm in _POSITION_NAMES else 1.0 for nm in p.names]
    cols.append(Jth)
    free_p = [j for j in range(J) if problem.fit_power and j != gauge]
    for j in free_p:
        names.append(f"light{idx[j]}.power")
        scale_of.append(1.0)
        cols.append(power_cols[:, j:j + 1])
    if project:
        e_tot = e0 + np.tensordot(powers, E, axes=1)
        s_tot = s0 + np.tensordot(powers, S, axes=1)
        terms = [("ka", np.broadcast_to(La, e_tot.shape)), ("kd", e_tot / np.pi)] + ([("ks", s_tot)] if spec else [])
        for nm, basis_ in terms:
            for c, ch in enumerate("rgb"):
                col = np.zeros_like(e_tot)
                col[:, c] = basis_[:, c]
                names.append(f"{nm}[{ch}]")
                scale_of.append(1.0)
                cols.append((sw * col).reshape(-1, 1))
    jac = np.concatenate(cols, axis=1)
    rss = float(rows @ rows)
    n_pos = int(np.count_nonzero(w > 0))
    ident = identifiability(jac, rss, n_pos)
    names = tuple(names)
    values = list(theta) + [powers[j] for j in free_p]
    if project:
        values += list(k[0]) + list(k[1]) + (list(k[2]) if spec else [])
    se = {nm: math.inf if not ok else float(s) * sc
          for nm, s, ok, sc in zip(names, ident.std_errors, ident.determined, scale_of, strict=True)}
    determined = {nm: bool(ok) for nm, ok in zip(names, ident.determined, strict=True)}
    warnings = [f"{nm} is not determined by these targets." for nm in names if not determined[nm]]
    warnings += [f"the power of light {idx[j]} is at its bound 0 (the targets ask for less than none)."
                 for j in free_p if powers[j] == 0.0]
    if budget_active:
        warnings.append(f"the power budget {float(problem.budget):.6g} W is used up (the powers' standard errors "
                        "ignore it).")
    if retries:
        warnings.append(f"solved again {retries} time(s) with a larger shadow capacity (the result is exact).")
    fitted = build_lights(problem, th)
    out_lights = tuple(scaled_light(light, jnp.asarray(pw, dt)) for light, pw in zip(fitted, powers, strict=True))
    pose_names = names[:problem.n_pose]
    light_params = {f"light{i}": tuple(nm for nm in names if nm.startswith(f"light{i}.")) for i in idx}
    moved = {f"light{idx[j]}": out_lights[j] for j, p in enumerate(problem.params) if p is not None}
    competing = () if final is None else competing_placements(np.asarray(final[0], np.float64)[:, :problem.n_pose],
                                                              np.asarray(final[1], np.float64), pose_names)
    dark = paint is not None and len(paint.pairs) > 0 and dark_answer(
        np.tensordot(powers, per_light, axes=1), colours, w, paint.margin)
    values_d = {nm: float(v) for nm, v in zip(names, values, strict=True)}
    quality, determined = assess(
        targets=t, residual=residual, noise=noise, n_params=len(names), names=names, std_errors=se, values=values_d,
        determined=determined, scale=size, lights=moved, light_params=light_params, candidates=competing,
        messages=warnings, all_dark=dark,
        contributions={f"light{idx[j]}": float(np.sqrt(np.sum(w * (powers[j] * per_light[j]) ** 2)))
                       for j in range(J)} if problem.fit_power else None, determinacy=paint is None)
    fixed = [x for n, x in enumerate(problem.scene.lights) if n not in idx]
    suggestions, sugg_n = _suggest(problem, th, powers, mat, names, jac, ident.determined, candidates, free_p, k,
                                   fixed, project)
    report = LightsReport(
        names=names, values=values_d, std_errors=se,
        determined=determined, singular_values=ident.singular_values,
        targets_met=None if t.tolerance is None else np.all(np.abs(residual) <= np.asarray(t.tolerance), axis=1),
        warnings=tuple(warnings), correlated=correlated_pairs(jac, names, ident.determined),
        suggestions=suggestions, suggestion_normals=sugg_n, loss=0.5 * rss,
        initial_loss=math.nan if initial is None else float(initial), stage_losses=tuple(stage_losses),
        starts_solved=n_solved, retries=retries, scale=size, quality=quality,
    )
    all_lights = list(problem.scene.lights)
    for j, i in enumerate(idx):
        all_lights[i] = out_lights[j]
    new_scene = eqx.tree_at(lambda s: s.lights, problem.scene, tuple(all_lights))
    return LightsFit(scene=new_scene, lights=out_lights, powers=np.asarray(powers), material=mat, residual=residual,
                     report=report, theta=theta, parametrisations=problem.params)


def _model(E: np.ndarray, S: np.ndarray, e0: np.ndarray, s0: np.ndarray, La: np.ndarray, p: np.ndarray,
           k: np.ndarray, spec: bool) -> np.ndarray:
    e = e0 + np.tensordot(p, E, axes=1)
    out = k[0] * La + k[1] / np.pi * e
    if spec:
        out = out + k[2] * (s0 + np.tensordot(p, S, axes=1))
    return out


def _suggest(problem: LightsProblem, th: Any, powers: np.ndarray, mat: Any, names: tuple, jac: np.ndarray,
             determined: np.ndarray, candidates: Any, free_p: list, k: np.ndarray,
             fixed: list, project: bool) -> tuple[dict, dict]:
    """For each undetermined parameter: the candidate receivers, best first, where the model
    changes most along the null direction(s) that involve it."""
    if np.all(determined):
        return {}, {}
    t = problem.targets
    dt = t.points.dtype
    if candidates is None:
        pts = np.asarray(t.points, np.float64)
        nrm = np.asarray(t.normals, np.float64).mean(axis=0)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        ax = np.argsort(hi - lo)[::-1][:2]
        g = np.linspace(0.0, 1.0, 9)
        cp = np.tile(pts.mean(axis=0), (81, 1))
        cp[:, ax[0]] = lo[ax[0]] + (hi - lo)[ax[0]] * np.repeat(g, 9)
        cp[:, ax[1]] = lo[ax[1]] + (hi - lo)[ax[1]] * np.tile(g, 9)
        cn = np.tile(nrm / np.linalg.norm(nrm), (81, 1))
    else:
        cp, cn = (np.asarray(x, np.float64) for x in candidates)
    eye = np.asarray(t.eye, np.float64)[0]
    ct = PaintedTargets(jnp.asarray(cp, dt), jnp.asarray(cn, dt), jnp.zeros(cp.shape, dt), jnp.asarray(eye, dt))
    e0, s0 = fixed_contribution(problem.scene, ct, problem.material, fixed, problem.specular,
                                problem.with_specular)
    cprob = dataclasses.replace(problem, targets=ct, e_fixed=e0, s_fixed=s0, capacity=None, paint=None)
    E, S, Jth = (np.asarray(x, np.float64) for x in report_parts(cprob, th, jnp.asarray(powers, dt), mat))
    spec = problem.with_specular
    cols = [Jth]
    for j in free_p:
        cols.append((k[1] / np.pi * E[j] + (k[2] * S[j] if spec else 0.0)).reshape(-1, 1))
    ncand = cp.shape[0]
    if project:
        e_tot = np.asarray(e0, np.float64) + np.tensordot(powers, E, axes=1)
        s_tot = np.asarray(s0, np.float64) + np.tensordot(powers, S, axes=1)
        La = np.asarray(problem.scene.ambient, np.float64)
        terms = [np.broadcast_to(La, e_tot.shape), e_tot / np.pi] + ([s_tot] if spec else [])
        for b in terms:
            for c in range(3):
                col = np.zeros_like(e_tot)
                col[:, c] = b[:, c]
                cols.append(col.reshape(-1, 1))
    jc = np.concatenate(cols, axis=1)  # (3K, P)
    out, out_n = {}, {}
    for v in null_directions(jac):
        change = np.linalg.norm((jc @ v).reshape(ncand, 3), axis=1)
        order = np.argsort(change)[::-1][:5]
        for nm, comp in zip(names, v * np.linalg.norm(jac, axis=0), strict=True):
            if abs(comp) > 1e-6 and nm not in out:
                out[nm], out_n[nm] = cp[order], cn[order]
    return out, out_n
