"""The answer of `fit_lights` at the poses its search found: the powers (bounded least squares,
with a budget or painted ranges and relations where given), the material (as given or the
structured least squares), the residual, the identifiability report of every fitted parameter
and, for each undetermined one, where to paint targets that would determine it.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ._basis_rows import BasisRows
from ._diagnostics import (
    COLLAPSE_CHI2,
    COLLAPSE_WIDTH_FRACTION,
    RIVAL_SIGMAS,
    assess,
    collapse_reason,
    competing_placements,
    dark_answer,
    light_width,
    noise_sigma,
    quantity_determined,
    rival_allowance,
    rival_placements,
    rival_turns,
    row_variance,
    turned_widened,
)
from ._identifiability import identifiability, quantity_error
from ._mirror import mirrored_rows
from ._multilight import (
    LightsProblem,
    build_lights,
    fixed_contribution,
    report_parts,
    scaled_light,
)
from ._multilight_report import (
    LightsReport,
    correlated_pairs,
    material_of,
    structured_coefficients,
)
from ._painting import as_numpy, painted_rows
from ._powers import constrained_powers, emitted_power, painted_jacobian
from ._reports import LightsFit
from ._targets import PaintedTargets
from ._uncertainty import Quantity, joint_factor, light_quantities, widened

_POSITION_NAMES = ("x", "y", "z", "a", "b")


def result(problem: LightsProblem, theta: np.ndarray, idx: list, size: float, candidates: Any,
            stage_losses: list, n_solved: int, retries: int, initial: float | None, project: bool,
            noise: Any = None, final: tuple | None = None, converged: bool = True,
            rows_at: BasisRows | None = None, more: tuple | None = None) -> LightsFit:
    """The `LightsFit` at the poses `theta (n_theta,)` (module docstring). `rows_at`: the search's
    LM program at given rows (`_basis_rows.BasisRows`), which gives the basis and its tangents
    at the answer and at the competing placements; None: `report_parts` computes them. `more`:
    `(rows (R, n_theta), losses (R,))` more placements for the rival check besides the final
    joint solve's rows `final` (`_rescreen.noise_rivals`), or None."""
    t, m = problem.targets, problem.material
    dt = t.points.dtype
    full_theta = np.asarray(theta, np.float64)
    q = np.asarray(theta[problem.n_pose:], np.float64)  # the searched powers' roots, if any
    theta = theta[:problem.n_pose]
    th = jnp.asarray(theta, dt)
    J = len(idx)
    ones = jnp.ones(J, dt)
    if rows_at is not None:
        E, S, dE, dS = rows_at(full_theta[None])[0]
        S = np.zeros_like(E) if S is None else S
        dE, dS = dE[:problem.n_pose], None if dS is None else dS[:problem.n_pose]
    else:
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
    model = _model(E, S, e0, s0, La, powers, k, spec)
    if rows_at is not None:  # the structured residual's Jacobian in theta, by the chain rule through the basis
        Jth = painted_jacobian(model, _model_tangents(mat, powers, dE, dS, spec, colours.shape), sw, paint)
    else:
        _, _, Jth = (np.asarray(x, np.float64) for x in report_parts(problem, th, jnp.asarray(powers, dt), mat))
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
    # told noise: the standard errors of this weighted problem under it (none with ranges or relations)
    ident = identifiability(jac, rss, n_pos, row_variance=None if paint is not None else row_variance(w, t, noise))
    names = tuple(names)
    values = list(theta) + [powers[j] for j in free_p]
    if project:
        values += list(k[0]) + list(k[1]) + (list(k[2]) if spec else [])
    se = {nm: math.inf if not ok else float(s) * sc
          for nm, s, ok, sc in zip(names, ident.std_errors, ident.determined, scale_of, strict=True)}
    determined = {nm: bool(ok) for nm, ok in zip(names, ident.determined, strict=True)}
    warnings = [f"{nm} is not determined by these targets." for nm in names if not determined[nm]]
    values_d = {nm: float(v) for nm, v in zip(names, values, strict=True)}
    quantities = _quantities(problem, theta, names, values_d, ident, scale_of, idx)
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
    rivals: tuple = ()
    # the other rows of the last joint solve, powers (and material) solved there as here; not under a
    # budget or painted ranges / relations (their powers are another problem's)
    if final is not None and paint is None and problem.budget is None and problem.fit_power:
        # told noise: chi-square under it; estimated: at the residual's scale, as the standard errors
        chi2_of = _chi2(t, noise) if noise is not None else _chi2_at_residual(w, ident.sigma2, colours, len(names))
        poses = lambda th_, p_: {f"light{idx[j]}": _pose(x, problem.params[j], p_[j])  # noqa: E731
                                 for j, x in enumerate(build_lights(problem, th_)) if problem.params[j] is not None}
        others = []
        rows_r = _rival_rows(np.asarray(final[0], np.float64)[:, :problem.n_pose], np.asarray(final[1], np.float64),
                             np.asarray(theta, np.float64), chi2_of, w, len(names))
        if more is not None and len(more[1]):  # in distinct basins, lowest loss first; the same rule
            rows_r += _rival_rows(np.asarray(more[0], np.float64)[:, :problem.n_pose], np.asarray(more[1], np.float64),
                                  np.asarray(theta, np.float64), chi2_of, w, len(names), best=float(np.min(final[1])))
        # the lights mirrored across the targets' symmetry plane (`_mirror`): as good as the answer
        # where the targets cannot tell them apart, a placement the search never visits after an exact fit
        rows_r += list(mirrored_rows(problem, np.asarray(theta, np.float64), build_lights(problem, th), spec))
        at_rows = rows_at(np.asarray(rows_r)) if rows_at is not None and rows_r else []
        for i, row in enumerate(rows_r):
            th_r = jnp.asarray(row, dt)
            if rows_at is not None:
                E_r, S_r = at_rows[i][0], (np.zeros_like(at_rows[i][0]) if at_rows[i][1] is None else at_rows[i][1])
            else:
                E_r, S_r, _ = (np.asarray(x, np.float64) for x in report_parts(problem, th_r, ones, m))
            p_r, k_r = coef(E_r, S_r)
            others.append((chi2_of(_model(E_r, S_r, e0, s0, La, p_r, k_r, spec) - colours), poses(th_r, p_r)))
        answer = poses(th, powers)
        chi2 = chi2_of(residual)
        rivals = rival_placements(answer, others, chi2, len(names), size, se, light_params)
        # placements that only turn a light: its rotation's standard errors widened (`rival_turns`)
        se = turned_widened(se, rival_turns(answer, others, chi2, len(names), se, light_params), light_params)
        se, quantities = widened(se, quantities, answer, rivals)  # the rivals' spread (`_uncertainty.widened`)
    size_free = None
    if paint is None and problem.budget is None and problem.fit_power:
        chi2_c = _chi2(t, noise) if noise is not None else _chi2_at_residual(w, ident.sigma2, colours, len(names))

        def step_at(E_r: np.ndarray, S_r: np.ndarray | None, dE_r: np.ndarray, dS_r: np.ndarray | None,
                    hold: list) -> np.ndarray:
            # one Gauss-Newton step in the poses (less `hold`) and the free powers from a basis and its tangents
            S_r = np.zeros_like(E_r) if S_r is None else S_r
            p_r, k_r = coef(E_r, S_r)
            model_r = _model(E_r, S_r, e0, s0, La, p_r, k_r, spec)
            mat_r = material_of(k_r, m.exponent, dt) if project else m
            tang = _model_tangents(mat_r, p_r, dE_r[:problem.n_pose], None if dS_r is None else dS_r[:problem.n_pose],
                                   spec, colours.shape)
            keep = [i for i in range(problem.n_pose) if i not in hold]
            A = np.concatenate([painted_jacobian(model_r, tang, sw, None)[:, keep],
                                painted_jacobian(model_r, k_r[1] / np.pi * E_r + (k_r[2] * S_r if spec else 0.0), sw,
                                                 None)[:, free_p]], axis=1)
            d = np.linalg.lstsq(A, -(sw * (model_r - colours)).reshape(-1), rcond=None)[0]
            out = np.zeros(problem.n_pose)
            out[keep] = d[:len(keep)]
            return out

        size_free = collapse_within_noise(
            problem, np.asarray(theta, np.float64), pose_names, idx, size, chi2_c, chi2_c(residual),
            lambda EE, SS: _model(EE, SS, e0, s0, La, *coef(EE, SS), spec) - colours, rows_at, step_at, se)
    quality, determined = assess(
        targets=t, residual=residual, noise=noise, n_params=len(names), names=names, std_errors=se, values=values_d,
        determined=determined, scale=size, lights=moved, light_params=light_params, candidates=competing,
        messages=warnings, all_dark=dark,
        contributions={f"light{idx[j]}": float(np.sqrt(np.sum(w * (powers[j] * per_light[j]) ** 2)))
                       for j in range(J)} if problem.fit_power else None, determinacy=paint is None,
        converged=converged, rivals=rivals, quantities=quantities, size_free=size_free)
    fixed = [x for n, x in enumerate(problem.scene.lights) if n not in idx]
    rv = row_variance(w, t, noise) if noise is not None and paint is None else None
    rv = np.full(w.size, ident.sigma2 if ident.sigma2 > 0 else 1.0) if rv is None else rv
    suggestions, sugg_n, sugg_se = _suggest(problem, th, powers, mat, names, jac, determined, candidates, free_p, k,
                                            fixed, project, rv, scale_of, rows_at, full_theta)
    report = LightsReport(
        names=names, values=values_d, std_errors=se,
        determined=determined, singular_values=ident.singular_values,
        targets_met=None if t.tolerance is None else np.all(np.abs(residual) <= np.asarray(t.tolerance), axis=1),
        warnings=tuple(warnings), correlated=correlated_pairs(jac, names, ident.determined),
        suggestions=suggestions, suggestion_normals=sugg_n, suggestion_std_errors=sugg_se, loss=0.5 * rss,
        initial_loss=math.nan if initial is None else float(initial), stage_losses=tuple(stage_losses),
        starts_solved=n_solved, retries=retries, scale=size, quality=quality,
        quantities={nm: dataclasses.replace(qv, determined=_still_determined(nm, qv, determined, quality, size))
                    for nm, qv in quantities.items()},
    )
    all_lights = list(problem.scene.lights)
    for j, i in enumerate(idx):
        all_lights[i] = out_lights[j]
    new_scene = eqx.tree_at(lambda s: s.lights, problem.scene, tuple(all_lights))
    return LightsFit(scene=new_scene, lights=out_lights, powers=np.asarray(powers), material=mat, residual=residual,
                     report=report, theta=theta, parametrisations=problem.params)


def _still_determined(name: str, q: Quantity, determined: dict, quality: Any, scale: float) -> bool:
    """Whether a covered quantity stays determined after the checks: its light not escaped,
    collapsed or unused, and the quantity determined exactly and nearly
    (`_diagnostics.quantity_determined`: estimable, a centre coordinate's standard error at most
    a quarter of the scene size `scale`, a flux's at most its value)."""
    light = name.rsplit(".", 1)[0]
    gone = light in quality.escaped or light in quality.collapsed or light in quality.unused
    return not gone and quantity_determined(name, q, scale)


def _quantities(problem: LightsProblem, theta: np.ndarray, names: tuple, values: dict, ident: Any,
                scale_of: list, idx: list) -> dict:
    """The covered quantities of `inverse._uncertainty` (`{name: Quantity}`, `determined` by the
    identifiability's rule for quantities, `_identifiability.quantity_error`: orthogonal to every
    null direction; the report narrows it): values (centres in m), delta-method standard errors
    and projected joint intervals (positions in m)."""
    pos = {nm: i for i, nm in enumerate(names)}
    factor = joint_factor(int(np.count_nonzero(ident.free)) - len(ident.null_space))
    dt = problem.targets.points.dtype
    centres = {f"light{idx[j]}": _pose(x, problem.params[j], 1.0)["centre"]
               for j, x in enumerate(build_lights(problem, jnp.asarray(theta, dt))) if problem.params[j] is not None}
    out = {}
    for nm, (val, grad) in light_quantities(names, values, idx).items():
        if nm.rsplit(".", 1)[-1] in ("x", "y", "z"):
            val = float(centres[nm.rsplit(".", 1)[0]]["xyz".index(nm[-1])])
        g = np.zeros(len(names))
        for p, d in grad.items():
            g[pos[p]] = d
        ok, se = quantity_error(ident, g)
        if not ok:
            out[nm] = Quantity(val, math.inf, math.inf, False)
            continue
        se *= scale_of[pos[nm]] if nm in pos else 1.0
        out[nm] = Quantity(val, se, factor * se, True)
    return out


RIVAL_ROWS = 8  # the final joint solve's rows checked as competing placements at most


def _chi2(targets: Any, noise: Any) -> Any:
    r"""$\chi^2 = \sum (r/\sigma)^2$ of a residual `r (N, 3)` under the fit's noise (`noise_sigma`),
    over the entries of positive weight."""
    sigma, _ = noise_sigma(targets, noise)
    ok = np.isfinite(sigma)
    return lambda r: float(np.sum(np.where(ok, (np.asarray(r, np.float64) / np.where(ok, sigma, 1.0)) ** 2, 0.0)))


def collapse_within_noise(problem: LightsProblem, theta: np.ndarray, pose_names: tuple, idx: list, size: float,
                          chi2_of: Any, chi2: float, residual_at: Any, rows_at: BasisRows | None,
                          step_at: Any, std_errors: dict) -> dict:
    r"""`{light name: chi2 excess}` for the collapsed lights (`_diagnostics.collapse_reason`) that
    explain the targets within `COLLAPSE_CHI2` of the answer's $\chi^2$ at the collapse limit
    (`_diagnostics`, collapsed light): each such light widened to `COLLAPSE_WIDTH_FRACTION` of the
    scene size `size` (m), by raising one of its log sizes (a polygon's two tried, the lower
    excess kept; a segment's log length), every other pose parameter of `theta (n_pose,)` as
    fitted; `residual_at(E, S)`: the residual with the powers and material solved at that basis
    (as at the answer); `chi2_of`: the fit's $\chi^2$ of a residual; `chi2`: the answer's.

    A widened light that fits as well may still sit elsewhere: at the collapse the centre's
    linearised standard errors ignore the size (its column vanishes), so one Gauss-Newton step
    from the widened pose with the size held (`step_at(E, S, dE, dS, held indices)`: the pose
    change) estimates where a fit at that size puts the light; a centre coordinate moved by more
    than `RIVAL_SIGMAS` of its standard error (`std_errors`) keeps the collapse flagged. Without
    the search's rows (`rows_at` None) none is within the noise."""
    dt = problem.targets.points.dtype
    fitted = build_lights(problem, jnp.asarray(theta, dt))
    limit = COLLAPSE_WIDTH_FRACTION * size
    rows, owners = [], []
    for j, light in enumerate(fitted):
        nm = f"light{idx[j]}"
        if problem.params[j] is None or collapse_reason(light, size) is None:
            continue
        width = max(light_width(light)[0], 1e-12 * size)  # type: ignore[index]
        for k, p in enumerate(pose_names):
            if p.startswith(nm + ".") and p.rsplit(".", 1)[-1].startswith("log_"):
                row = np.array(theta, np.float64)
                row[k] += math.log(1.05 * limit / width)
                rows.append(row)
                owners.append((j, nm))
    if not rows or rows_at is None:
        return {}
    at = rows_at(np.asarray(rows))
    out: dict = {}
    for i, (row, (j, nm)) in enumerate(zip(rows, owners, strict=True)):
        if collapse_reason(build_lights(problem, jnp.asarray(row, dt))[j], size) is not None:
            continue  # this size does not widen its narrow side
        E_r, S_r = at[i][0], (np.zeros_like(at[i][0]) if at[i][1] is None else at[i][1])
        excess = chi2_of(residual_at(E_r, S_r)) - chi2
        if not (math.isfinite(excess) and excess <= COLLAPSE_CHI2):
            continue
        held = [k for k, p in enumerate(pose_names) if p.startswith(nm + ".") and p.rsplit(".", 1)[-1].startswith("log_")]
        step = step_at(E_r, at[i][1], at[i][2], at[i][3], held)
        moved = False
        for ax in "xyz":
            k = pose_names.index(f"{nm}.{ax}") if f"{nm}.{ax}" in pose_names else None
            se = std_errors.get(f"{nm}.{ax}", math.inf)
            moved |= k is not None and not abs(float(step[k])) * size <= RIVAL_SIGMAS * se  # theta: scene sizes
        if not moved:
            out[nm] = min(out.get(nm, math.inf), float(excess))
    return out


def _chi2_at_residual(w: np.ndarray, sigma2: float, colours: np.ndarray, n_params: int) -> Any:
    r"""$\chi^2 = \sum w r^2 / s^2$ of a residual `r (N, 3)` with the weights `w (N, 3)` as
    given: the rival check's scale when the noise is estimated (`_diagnostics`, competing
    placements). $s^2$ is the residual's variance estimate of a weighted row, `sigma2`
    (`Identifiability.sigma2`), floored at an exact fit's: $S_0 / a$, $S_0 = 2\,$`EXACT_LOSS`
    $\cdot \tfrac12 \sum w c^2$ (`_fit_lights`: a loss below it is an exact fit) and $a$ the
    allowance (`rival_allowance(n_params)`), so that a placement whose residual sum of squares
    exceeds an exact answer's by at most $S_0$ (exact itself: two placements that paint the
    targets alike, each converged to its own rounding) still competes, and one that misses the
    targets beyond rounding does not."""
    from ._fit_lights import EXACT_LOSS

    exact_rss = EXACT_LOSS * float(np.sum(w * np.asarray(colours, np.float64) ** 2))
    s2 = np.float64(max(float(sigma2), exact_rss / rival_allowance(n_params), 1e-300))

    def chi2(r: Any) -> float:
        with np.errstate(over="ignore"):
            return float(np.sum(w * np.asarray(r, np.float64) ** 2) / s2)

    return chi2


def _row_noise(chi2_of: Any, w: np.ndarray) -> float:
    r"""A weighted row's noise variance $w\sigma^2$ under `chi2_of` (`_chi2`): the $\chi^2$ of a
    residual $1/\sqrt{w}$ at the first entry of positive weight `w (N, 3)` is $1/(w\sigma^2)$
    (0.0 when no entry has a positive weight)."""
    if not (w > 0).any():
        return 0.0
    unit = np.zeros(w.shape)
    i = tuple(np.argwhere(w > 0)[0])
    unit[i] = 1.0 / math.sqrt(w[i])
    return 1.0 / max(chi2_of(unit), 1e-300)


def _rival_rows(rows: np.ndarray, losses: np.ndarray, theta: np.ndarray, chi2_of: Any, w: np.ndarray,
                n_params: int, best: float | None = None) -> list:
    r"""The rows of the final joint solve `rows (S, P)` (its `losses`, $\tfrac12\sum w r^2$) that
    may compete with the answer `theta`: not the answer itself, not a repeat, and a loss whose
    excess over the lowest, in $\chi^2$ units of a typical weighted row's variance, is within
    four times the allowance (`rival_allowance`); at most `RIVAL_ROWS`, lowest loss first. `best`:
    the lowest loss to measure the excess from (None: the lowest of `losses`)."""
    pos = w > 0
    if not pos.any():
        return []
    v = _row_noise(chi2_of, w)
    f = np.where(np.isfinite(losses), losses, np.inf)
    if not np.isfinite(f).any():
        return []
    best = min(float(np.min(f)), np.inf if best is None else best)
    out: list = []
    for r in np.argsort(f, kind="stable"):
        if not 2.0 * (f[r] - best) / v <= 4.0 * rival_allowance(n_params) or len(out) == RIVAL_ROWS:
            break
        if not np.all(np.isfinite(rows[r])) or np.max(np.abs(rows[r] - theta)) <= 1e-9 * max(1.0, np.max(np.abs(theta))):
            continue
        if any(np.max(np.abs(rows[r] - q)) <= 1e-9 * max(1.0, np.max(np.abs(q))) for q in out):
            continue
        out.append(rows[r])
    return out


def _pose(light: Any, param: Any, power: float) -> dict:
    """A fitted light's pose for `rival_placements`: kind, centre (m), axis, power (a factor of
    the given emission) and `emitted` (W at that power; 0 for a directional light)."""
    import jaxshadow as js

    axis = None
    if isinstance(light, js.PolygonLight):
        v = np.asarray(light.vertices, np.float64)
        centre = v.mean(axis=0)
        n = np.cross(v[1] - v[0], v[2] - v[0])
        axis = n / max(float(np.linalg.norm(n)), 1e-300)
    elif isinstance(light, js.LinearLight):
        a, b = np.asarray(light.start, np.float64), np.asarray(light.end, np.float64)
        centre = 0.5 * (a + b)
        axis = (b - a) / max(float(np.linalg.norm(b - a)), 1e-300)
    elif isinstance(light, js.PointLight):
        centre = np.asarray(light.position, np.float64)
    else:
        centre, axis = np.zeros(3), np.asarray(light.direction, np.float64)
    emitted = float(emitted_power(light)) * float(power) if not isinstance(light, js.DirectionalLight) else 0.0
    return {"kind": param.kind, "centre": tuple(float(x) for x in centre),
            "axis": None if axis is None else tuple(float(x) for x in axis), "power": float(power),
            "emitted": emitted}


def _model(E: np.ndarray, S: np.ndarray, e0: np.ndarray, s0: np.ndarray, La: np.ndarray, p: np.ndarray,
           k: np.ndarray, spec: bool) -> np.ndarray:
    e = e0 + np.tensordot(p, E, axes=1)
    out = k[0] * La + k[1] / np.pi * e
    if spec:
        out = out + k[2] * (s0 + np.tensordot(p, S, axes=1))
    return out


def _candidates(t: Any) -> tuple[np.ndarray, np.ndarray]:
    """`(points (81, 3), normals (81, 3))`: a 9 x 9 grid over the receiver region of targets `t`
    (the plane through their centroid across their mean normal), spanning their extent along
    each in-plane axis but never less than half their diagonal: targets on a line still get
    candidates off it."""
    pts = np.asarray(t.points, np.float64)
    nrm = np.asarray(t.normals, np.float64).mean(axis=0)
    up = nrm / max(float(np.linalg.norm(nrm)), 1e-300)
    a = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    centre = pts.mean(axis=0)
    diag = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    g = np.linspace(-0.5, 0.5, 9)
    axes = []
    for e in (e1, e2):
        u = (pts - centre) @ e
        mid, span = 0.5 * (u.max() + u.min()), max(float(u.max() - u.min()), 0.5 * diag)
        axes.append(mid + span * g)
    cp = centre + np.repeat(axes[0], 9)[:, None] * e1 + np.tile(axes[1], 9)[:, None] * e2
    return cp, np.tile(up, (81, 1))


def _model_tangents(mat: Any, powers: np.ndarray, dE: np.ndarray, dS: np.ndarray | None, spec: bool,
                    shape: tuple) -> np.ndarray:
    r"""`(P, N, 3)`: the model colours' tangents in the poses, from the basis tangents `dE`, `dS`
    `(P, J, N, 3)` at the lights' `powers (J,)` (Lambert $k_d/\pi$, plus $k_s$ where specular);
    `shape` the colours' `(N, 3)`."""
    kd, ks = (np.broadcast_to(np.asarray(x, np.float64), shape) for x in (mat.kd, mat.ks))
    d_model = kd / np.pi * np.einsum("j,pjnc->pnc", powers, dE)
    if spec and dS is not None:
        d_model = d_model + ks * np.einsum("j,pjnc->pnc", powers, dS)
    return d_model


def _suggest(problem: LightsProblem, th: Any, powers: np.ndarray, mat: Any, names: tuple, jac: np.ndarray,
             determined: dict, candidates: Any, free_p: list, k: np.ndarray, fixed: list, project: bool,
             row_var: np.ndarray, scale_of: list, rows_at: BasisRows | None = None,
             full_theta: np.ndarray | None = None) -> tuple[dict, dict, dict]:
    """For each parameter not determined (exactly or nearly): the candidate receivers (up to 5,
    best first) that most lower its predicted standard error when painted, kept only where they
    lower it. Returns `(points, normals, {name: (standard error now, predicted with its first 3
    candidates painted)})`.

    The prediction is the identifiability rule (`_identifiability`: an exact null direction
    gives an infinite error) on the report's Jacobian with each row over its noise's standard
    deviation (`row_var`, `(3N,)`), with a candidate's three rows (its model derivatives, painted
    with the targets' median noise) appended; positions in m (`scale_of`). The candidates'
    basis and tangents come from the search's LM program (`rows_at.at_receivers` at `full_theta`)
    where given, else from `report_parts`."""
    bad = [i for i, nm in enumerate(names) if not determined[nm]]
    if not bad:
        return {}, {}, {}
    t = problem.targets
    dt = t.points.dtype
    cp, cn = _candidates(t) if candidates is None else (np.asarray(x, np.float64) for x in candidates)
    eye = np.asarray(t.eye, np.float64)[0]
    ct = PaintedTargets(jnp.asarray(cp, dt), jnp.asarray(cn, dt), jnp.zeros(cp.shape, dt), jnp.asarray(eye, dt))
    e0, s0 = fixed_contribution(problem.scene, ct, problem.material, fixed, problem.specular,
                                problem.with_specular)
    spec = problem.with_specular
    if rows_at is not None and full_theta is not None:
        E, S, dE, dS = rows_at.at_receivers(full_theta, cp, np.asarray(ct.normals, np.float64))
        S = np.zeros_like(E) if S is None else S
        d_model = _model_tangents(mat, powers, dE[:problem.n_pose], None if dS is None else dS[:problem.n_pose], spec,
                                  cp.shape)
        Jth = d_model.reshape(d_model.shape[0], -1).T  # (3K, P): the candidates' unit weights
    else:
        cprob = dataclasses.replace(problem, targets=ct, e_fixed=e0, s_fixed=s0, capacity=None, paint=None)
        E, S, Jth = (np.asarray(x, np.float64) for x in report_parts(cprob, th, jnp.asarray(powers, dt), mat))
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
    jc = np.concatenate(cols, axis=1).reshape(ncand, 3, -1)  # (K, 3, P): a candidate's rows
    w = np.asarray(t.weights, np.float64).reshape(-1)
    pos = (w > 0) & (row_var > 0)
    base = jac[:w.size][pos] / np.sqrt(row_var[pos])[:, None]  # the data rows (penalty rows past them)
    s_new = math.sqrt(float(np.median(row_var[pos] / w[pos])))  # a new target's colour noise
    sc = np.asarray(scale_of, np.float64)

    def se_with(extra: np.ndarray) -> np.ndarray:
        A = np.concatenate([base, extra.reshape(-1, base.shape[1]) / s_new])
        ident = identifiability(A, 0.0, A.shape[0], row_variance=np.ones(A.shape[0]))
        return np.where(ident.determined, ident.std_errors, np.inf) * sc

    now = se_with(np.zeros((0, base.shape[1])))
    each = np.stack([se_with(jc[c]) for c in range(ncand)])  # (K, P)
    out, out_n, pred = {}, {}, {}
    for i in bad:
        gain = each[:, i] < now[i] * (1.0 - 1e-3)
        if not gain.any():
            continue
        order = [int(c) for c in np.argsort(each[:, i], kind="stable") if gain[c]][:5]
        nm = names[i]
        out[nm], out_n[nm] = cp[order], cn[order]
        pred[nm] = (float(now[i]), float(se_with(jc[order[:3]])[i]))
    return out, out_n, pred
