"""Light placement from painted colours: nonlinear least squares with a vectorised multistart.

`fit_light` puts the pieces together: the light's parametrisation (`_parametrisation`), the
problem, the starts (`_multistart`, from the `Search` options that `fit_lights` takes too,
`_options`), a solver object (`_solvers`: `LM`, `OptimistixLM`, `LBFGSB`), and the report
(`_identifiability`, `_reports`: a `LightFit` is a `LightsFit` of one light).

The problem is `fit_lights`' (`_multilight.LightsProblem` with one fitted light, its power held,
the other lights' contribution computed once), and the `LM` searches it with `fit_lights`'
compiled program (`_multilight.solve`; the starts screened by the same program with no
iterations, `_solvers.screen_by_solver`), so one light and several are one search (with a
projected material: the same residual in a program that also keeps its basis at the answer,
`_projected_lm`); `OptimistixLM`, `LBFGSB` and a solver of one's own (an
`AbstractLightSolver` subclass) minimise its residual too. A fitted exponent is the last
parameter, a per-receiver material and a projected material beside other lights are the
problem's (`_problem`).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from typing import Any, no_type_check

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

import jaxshadow as js

from . import _projected_lm
from ._diagnostics import (
    FitQualityWarning,
    assess,
    competing_placements,
    invalid_reason,
    noise_weighted,
    row_variance,
    without_invalid_lights,
)
from ._forward import SpecularFn, shade
from ._identifiability import identifiability
from ._lm import ONCE_COMPILER_OPTIONS, fit_jit
from ._multilight import LightsProblem, basis, colour_free_columns, exponent_at, fixed_contribution
from ._multilight_report import LightsReport, correlated_pairs
from ._multistart import distinct_minima, make_starts
from ._options import Search, checked_constraints, search_options
from ._parametrisation import FIT_GROUPS, LightParametrisation, scene_size, with_light
from ._reports import LightFit
from ._solvers import (
    LEGACY_SOLVER_KEYWORDS,
    AbstractLightSolver,
    Solution,
    checked_solver,
)
from ._targets import PaintedTargets

_POSITION_NAMES = ("x", "y", "z", "a", "b")


@dataclasses.dataclass(frozen=True, kw_only=True)
class LightReport(LightsReport):
    """`fit_light`'s report: a `LightsReport` of its one light (names as
    `LightParametrisation.names`, e.g. `x`, `y`, `z`, `ru`, `rv`, `log_length`, and `log_n` last
    with a fitted exponent; positions in m in `std_errors`; `correlated` pairs, `loss`,
    `initial_loss`, `stage_losses` (one stage: the best loss), `starts_solved`, `retries`,
    `scale` (m), `quality`; `suggestions` is empty: `fit_light` evaluates no candidate
    receivers, `fit_lights` and `inverse.design_targets` do), and the solver's multistart:

    - `theta`: the parameter vector at the optimum (positions in units of `scale` m;
      rotations rad; sizes log factors; `log_n` last with a fitted exponent).
    - `best_start`, `start_losses (S,)`, `converged (S,)`, `num_steps (S,)`: the multistart
      (the solved starts; `n_screened` starts were generated, see the solver's `refine`).
    - `n_distinct_minima`: final points more than 1e-3 (parameter units) apart among the
      converged starts within 1 % of the best loss (a measure of ambiguity).
    - `solver` (its name: `"lm"`, `"optimistix"`, `"lbfgsb"`); `abandoned (S,)`: starts stopped
      early by the LM's `prune` (their `converged` is False), or None.
    - `quality`: the checks of `inverse._diagnostics` (`FitQuality`: a wrong minimum, an escaped
      light, outliers, conflicting targets, nearly undetermined parameters); `trusted` is
      `quality.trusted`: False when the answer should not be used as is.
    - `capacity`: the shadow capacity the solve ran at (boundary edges of a receiver's visible
      region, or candidate faces for a segment light, that the compiled program holds: sized from
      the starts on the host, doubled while a receiver overflowed it); None without occluders or
      for a solver that clips every receiver against every occluder.
    """

    theta: np.ndarray
    best_start: int
    start_losses: np.ndarray
    converged: np.ndarray
    num_steps: np.ndarray
    n_distinct_minima: int
    n_screened: int
    solver: str
    abandoned: np.ndarray | None = None
    capacity: int | None = None

    def _headline(self) -> str:
        ok = int(np.count_nonzero(self.converged))
        return (f"light fit ({self.solver}): loss {self.initial_loss:.4g} -> {self.loss:.4g}; "
                f"best start {self.best_start} of {len(self.start_losses)} ({ok} converged, "
                + (f"{int(np.count_nonzero(self.abandoned))} abandoned, " if self.abandoned is not None else "")
                + f"{self.n_distinct_minima} distinct minima near the best)")


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def fit_light(
    scene: js.Scene,
    targets: PaintedTargets,
    material: js.Material,
    light_index: int = 0,
    *,
    fit: tuple = FIT_GROUPS,
    search: Search | None = None,
    constraints: dict | None = None,
    solver: AbstractLightSolver | str | None = None,
    material_mode: str = "fixed",
    fit_exponent: bool = False,
    specular: SpecularFn | None = None,
    noise: Any = None,
    warn: bool = True,
    **options: Any,
) -> LightFit:
    """Place light `light_index` of `scene` so the shading matches painted colours.

    Minimises $\\sum_i w_i |L(x_i) - C_i|^2$ over the light's pose (Poulin §5.2 by nonlinear
    least squares; §5.3.5 uses MINPACK's LM the same way), with the material and every other
    light fixed. The light in `scene` is the reference: its shape, radiance and pose are the
    starting point and the origin of the parametrisation (`LightParametrisation`).

    **Arguments:**

    - `scene` (occluders cast soft shadows), `targets`, `material` (fixed; its coefficients
      `(3,)` or per receiver `(N, 3)`); `light_index`: the
      light to place (PolygonLight, LinearLight or PointLight); `fit`: a subset of
      `("position", "orientation", "size")`; `constraints`: `{light_index: inverse.Plane |
      inverse.Box}` for the light's centre (the dictionary of `fit_lights`).
    - `search`: an `inverse.Search` (the options `fit_lights` takes too), or its fields as
      keywords: `starts` (default 64: the reference first, then a scrambled Sobol stratification
      of the search region; 1 = local solve), `search_radius` (scene sizes),
      `orientation_spread` (rad), `size_spread` (relative): the region's half-widths; `seed`:
      its stratification.
    - `solver`: `LM()` (default: screening to the 8 best starts, successive halving, occluder
      culling; exact), `OptimistixLM()` or `LBFGSB()`, with their options, or a solver of one's
      own (an `AbstractLightSolver` subclass: it gets `fit_lights`' problem of this one light).
    - `material_mode`: `"fixed"` (the material as given) or `"projected"` (joint light and
      material by variable projection: at every trial light $k_a, k_d, k_s$ are the exact,
      unconstrained weighted least-squares solution, so only the light - and with
      `fit_exponent=True` also $\\log n$ - is searched; `LightFit.material` holds them).
      Whether $k_s$ is used follows `material.ks != 0`.
    - `specular`: a callable like `js.specular` (default `js.specular`).
    - `noise`: the painted colours' standard deviation (colour units: a number, `(N,)` or
      `(N, 3)`), `"weights"` (the weights are inverse variances) or None (estimated: 2.5 % of
      the RMS weighted colour); what the checks of the answer compare the residual with
      (`inverse._diagnostics`: a wrong minimum, outliers, conflicting targets). Told standard
      deviations weight the fit by $w/\\sigma^2$ and set its standard errors (as `fit_lights`).
    - `warn`: emit a `FitQualityWarning` when the answer is flagged (a wrong minimum, an
      escaped light, a polygon or segment collapsed to a point, conflicting targets); the
      report's `quality` says so either way (`report.trusted`, `report.quality.reason`).

    The keywords `refine`, `prune`, `receiver_groups` (ignored), `combinatorics`, `rtol`, `atol`,
    `max_steps` and string solvers (`"lm"`, ...) are deprecated: they are the solver's options;
    so is `constraint=c` (now `constraints={light_index: c}`).

    **Returns:** a `LightFit`: a `LightsFit` of one light (`scene`, `lights`, `powers` (ones),
    `material`, `residual`, `report` (a `LightReport`: a `LightsReport` with the solver's
    starts), `theta`, `parametrisations`), with
    `light` and `parametrisation` its one entry's.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js
        import inverse

        material = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
        points = np.c_[np.random.default_rng(0).uniform(-1, 1, (24, 2)), np.zeros(24)]
        normals, eye = np.tile([0.0, 0.0, 1.0], (24, 1)), np.array([0.0, -2.0, 2.0])
        true = js.Scene([js.PointLight([0.2, 0.3, 2.0], 3.0)], ambient=0.05)
        targets = inverse.PaintedTargets(points, normals, js.shade(true, material, points, normals, eye), eye)
        start = js.Scene([js.PointLight([0.0, 0.0, 1.8], 3.0)], ambient=0.05)   # the reference light
        fit = inverse.fit_light(start, targets, material, fit=("position",), starts=4, solver=inverse.LM(refine=2))
        fit.light.position   # ~ [0.2, 0.3, 2.0]; print(fit.report): the parameters, their errors, warnings
        ```
    """
    # Private: how the projected material is computed at the answer (`colour_coefficients`, or
    # `_joint.projected_coefficients` from `fit_light_and_material`, sharing its next program).
    coefficients = options.pop("_projected_coefficients", None)
    # Private: a list the solver's `Solution` is appended to (`fit_light_and_material` runs the
    # LM's program again at the answer, `Solution.rows`).
    kept = options.pop("_solution", None)
    legacy = {k: options.pop(k) for k in list(options) if k in LEGACY_SOLVER_KEYWORDS}
    if "constraint" in options:
        warnings.warn("fit_light(constraint=c) is deprecated: pass constraints={light_index: c} (as fit_lights).",
                      DeprecationWarning, stacklevel=2)
        if constraints is not None:
            raise ValueError("fit_light: give constraints or the deprecated constraint, not both.")
        c = options.pop("constraint")
        constraints = None if c is None else {light_index: c}
    opts = search_options(search, options, "fit_light", several=False)
    starts = int(opts.starts)
    solver = checked_solver(solver, "fit_light", several=False, legacy=legacy)
    fit = _checked_groups(scene, targets, light_index, fit, material_mode)
    constraint = checked_constraints(constraints, [int(light_index)], "fit_light", several=False).get(int(light_index))
    dt = targets.points.dtype
    param = LightParametrisation(scene.lights[light_index], light_index, fit, constraint,
                                 scene_size(scene, targets), solver.box_map)
    with_spec = bool(np.any(np.asarray(material.ks) != 0))
    project = material_mode == "projected"
    fit_n = project and fit_exponent and with_spec
    targets = noise_weighted(targets, noise)  # told noise: each target and channel weighted by 1/sigma^2
    problem = _problem(param, scene, material, targets, specular, with_spec, project, fit_n)
    seed = opts.seed
    y0 = make_starts(param, starts, search_radius=opts.search_radius, orientation_spread=opts.orientation_spread,
                     size_spread=opts.size_spread, seed=seed, dtype=dt)
    if fit_n:  # log n, last: the material's at the reference, spread over a factor 3 elsewhere
        logn = np.full((y0.shape[0], 1), np.log(float(material.exponent)))
        logn[1:, 0] += np.random.default_rng(seed).uniform(-np.log(3.0), np.log(3.0), y0.shape[0] - 1)
        y0 = jnp.concatenate([y0, jnp.asarray(logn, dt)], axis=1)
    sol = solver.minimise(problem, y0)
    if kept is not None:
        kept.append(sol)
    fitted = _light_fit(problem, sol, solver.name, int(y0.shape[0]), noise, coefficients)
    if warn:
        for msg in fitted.report.quality.emitted:
            warnings.warn(msg, FitQualityWarning, stacklevel=2)
    return fitted


def _checked_groups(scene: Any, targets: Any, light_index: Any, fit: Any, material_mode: str) -> tuple:
    """`fit` as a tuple, after the argument checks of `fit_light` (ValueError)."""
    if not isinstance(scene, js.Scene):
        raise ValueError(f"fit_light: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    if not isinstance(targets, PaintedTargets):
        raise ValueError(f"fit_light: targets must be PaintedTargets, got {type(targets).__name__}.")
    if isinstance(light_index, bool) or not isinstance(light_index, (int, np.integer)):
        raise ValueError(f"fit_light: light_index must be an integer, got {light_index!r}.")
    if not 0 <= light_index < len(scene.lights):
        raise ValueError(f"fit_light: light_index {light_index} out of range for {len(scene.lights)} light(s).")
    fit = (fit,) if isinstance(fit, str) else tuple(fit)
    unknown = [g for g in fit if g not in FIT_GROUPS]
    if unknown:
        raise ValueError(f"fit_light: unknown fit group(s) {unknown}; choose from {FIT_GROUPS}.")
    if material_mode not in ("fixed", "projected"):
        raise ValueError(f"fit_light: material_mode must be 'fixed' or 'projected', got {material_mode!r}.")
    return fit


def _problem(param: LightParametrisation, scene: js.Scene, material: js.Material, targets: PaintedTargets,
             specular: Any, with_spec: bool, project: bool, fit_n: bool) -> LightsProblem:
    """The problem every solver runs: `fit_lights`' (`LightsProblem`), one fitted light, its
    power held (`fit_power=False`), searched by the `LM` through the same compiled program as
    `fit_lights`; by `OptimistixLM`, `LBFGSB` and one's own solvers on its residual. The other
    lights' contribution is computed once (`fixed_contribution`), except with a fitted exponent
    and a specular term, where it depends on $n$: they are then in the program, at their given
    power (power-only entries). A projected material (`colour_free`) shares one $k_d$ (and $k_s$)
    between the fitted light and the others, as `js.shade` does."""
    others = [light for k, light in enumerate(scene.lights) if k != param.light_index]
    inside = bool(fit_n and with_spec and others)
    if inside:
        z = jnp.zeros(targets.points.shape, targets.points.dtype)
        e0, s0 = z, z
    else:
        e0, s0 = fixed_contribution(scene, targets, material, others, specular, with_spec)
    n_in = len(others) if inside else 0
    return LightsProblem((param, *[None] * n_in), (scene.lights[param.light_index], *(others if inside else [])),
                         scene, material, targets, e0, s0, (0, *[param.size] * n_in), False, with_spec,
                         bool(others) and not inside, specular, colour_free=project, fit_exponent=fit_n)


def _light_fit(problem: LightsProblem, sol: Solution, solver_name: str, n_screened: int,
               noise: Any = None, coefficients: Any = None) -> LightFit:
    """The fitted scene, residual and report from a solver's `Solution`. `coefficients(problem,
    theta) -> (k (3, 3), n)`: the projected material at the answer (default
    `colour_coefficients`; neither where the solution kept the basis, `Solution.basis`: the
    material and the model's colours are then made of it, `_projected_lm`)."""
    param, t, material = problem.params[0], problem.targets, problem.material
    names = (*param.names, "log_n") if problem.fit_exponent else param.names
    dt = t.points.dtype
    theta = jnp.asarray(sol.values[sol.best], dt)
    losses = np.where(np.isfinite(sol.losses), sol.losses, np.inf)
    ident = identifiability(sol.jacobian, float(sol.residual @ sol.residual), int(np.count_nonzero(np.asarray(t.weights) > 0)),
                            row_variance=row_variance(t.weights, t, noise))
    scale = scene_size(problem.scene, t)
    se = {nm: math.inf if not ok else float(s) * (scale if nm in _POSITION_NAMES else 1.0)
          for nm, s, ok in zip(names, ident.std_errors, ident.determined, strict=True)}
    determined = {nm: bool(ok) for nm, ok in zip(names, ident.determined, strict=True)}
    msgs = [f"light parameter {nm} is not determined by these targets." for nm in names if not determined[nm]]
    if not sol.converged[sol.best]:
        msgs.append("the best start did not report convergence (max_steps reached?).")
    if sol.retries:
        msgs.append(f"the light moved so that some receiver's visible region needed more boundary edges than the "
                    f"shadow capacity (culling capacity); "
                    f"solved again {sol.retries} time(s) with a larger one (the result is exact).")
    new_scene = with_light(problem.scene, param.light_index, sol.light)
    if problem.colour_free and sol.basis is not None:
        kc = _projected_lm.coefficients(sol.problem, sol.basis)
        n_fit = np.exp(np.asarray(theta, np.float64)[-1]) if problem.fit_exponent else np.float64(material.exponent)
    elif problem.colour_free:
        kc, n_fit = (np.asarray(x, np.float64) for x in (coefficients or colour_coefficients)(sol.problem, theta))
    if problem.colour_free:
        if np.any(kc < 0):  # the unconstrained projection: a js.Material holds no negative coefficient
            bad = [f"{'ka kd ks'.split()[i]}[{'rgb'[c]}]" for i, c in zip(*np.nonzero(kc < 0), strict=True)]
            msgs.append(f"the projected material has negative coefficients ({', '.join(bad)}), held at 0 in "
                        f"`material`: these targets are not painted by this light and any material (a wrong "
                        f"minimum?).")
            kc = np.maximum(kc, 0.0)
        material = js.Material(ka=jnp.asarray(kc[0], dt), kd=jnp.asarray(kc[1], dt), ks=jnp.asarray(kc[2], dt),
                               exponent=jnp.asarray(float(n_fit), dt))
    w = np.asarray(t.weights, np.float64)
    valid = invalid_reason(sol.light) is None
    if sol.exact_residual and not problem.colour_free and np.all(w > 0) and valid:
        residual = sol.residual.reshape(-1, 3) / np.sqrt(w)  # r = sqrt(w) (model - colours)
    elif problem.colour_free and sol.basis is not None and valid:
        kk = np.stack([np.asarray(getattr(material, f), np.float64) for f in ("ka", "kd", "ks")])
        residual = _projected_lm.model(sol.problem, sol.basis, kk) - np.asarray(t.colours, np.float64)
    else:
        # A light that collapsed to a degenerate one (`_diagnostics`) shines as no light: `js.shade`
        # would reject it.
        model = shade(without_invalid_lights(new_scene), material, t.points, t.normals, t.eye, problem.specular, problem.with_specular)
        residual = np.asarray(model, np.float64) - np.asarray(t.colours, np.float64)
    theta64 = np.asarray(theta, np.float64)
    values = {nm: float(v) for nm, v in zip(names, theta64, strict=True)}
    light_name = f"light{param.light_index}"
    quality, determined = assess(
        targets=t, residual=residual, noise=noise, n_params=len(names), names=names, std_errors=se, values=values,
        determined=determined, scale=scale, lights={light_name: sol.light}, light_params={light_name: param.names},
        candidates=competing_placements(np.asarray(sol.values, np.float64), losses, names), messages=msgs)
    report = LightReport(
        names=names, values=values, std_errors=se,
        determined=determined, singular_values=ident.singular_values,
        targets_met=None if t.tolerance is None else np.all(np.abs(residual) <= np.asarray(t.tolerance), axis=1),
        warnings=tuple(msgs), correlated=correlated_pairs(np.asarray(sol.jacobian, np.float64), names, ident.determined),
        suggestions={}, suggestion_normals={}, loss=float(losses[sol.best]), initial_loss=sol.initial_loss,
        stage_losses=(float(losses[sol.best]),), starts_solved=int(len(sol.losses)), retries=int(sol.retries),
        scale=scale, quality=quality, theta=theta64, best_start=sol.best, start_losses=sol.losses,
        converged=sol.converged, num_steps=sol.num_steps,
        n_distinct_minima=distinct_minima(sol.values, losses, sol.converged, sol.best), n_screened=n_screened,
        solver=solver_name, abandoned=sol.abandoned, capacity=getattr(sol.problem, "capacity", None),
    )
    return LightFit(scene=new_scene, lights=(sol.light,), powers=np.ones(1), material=material, residual=residual,
                    report=report, theta=theta64[:param.size], parametrisations=(param,))


@fit_jit(options=ONCE_COMPILER_OPTIONS)
def colour_coefficients(problem: LightsProblem, theta: Array) -> tuple[Array, Array]:
    """`((3, 3), n)`: rows $k_a, k_d, k_s$ (RGB columns; $k_s = 0$ without a specular term), the
    per-channel weighted least squares of the targets' colours on the ambient, $E/\\pi$ and $S$
    of every light at `theta` (`_multilight.colour_free_columns` of the one-light problem: the
    projection its search made), and the exponent $n$ there."""
    t = problem.targets
    dt = theta.dtype
    E, S, _ = basis(theta, problem, problem.capacity)
    X = jnp.stack(colour_free_columns(E, S, problem, dt), axis=-1)  # (N, C, m)
    sw = jnp.sqrt(t.weights)

    def channel(Xc: Array, yc: Array, swc: Array) -> Array:
        return jnp.linalg.pinv(Xc * swc[:, None]) @ (yc * swc)

    k = jax.vmap(channel, in_axes=(1, 1, 1), out_axes=1)(X, t.colours, sw)
    if S is None:
        k = jnp.concatenate([k, jnp.zeros((1, 3), dt)], axis=0)
    return k, exponent_at(theta, problem)
