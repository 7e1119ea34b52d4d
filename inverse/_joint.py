"""Light and material together: one projected multistart then the exact bounded material
(`method="projected"`), or block coordinate descent (`method="alternate"`, deprecated); and the joint
standard errors of both halves.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

import jaxshadow as js

from . import _projected_lm
from ._diagnostics import FitQualityWarning, invalid_reason, without_invalid_lights
from ._forward import SpecularFn, at_capacity
from ._identifiability import identifiability
from ._lights import fit_light
from ._lm import ONCE_COMPILER_OPTIONS, fit_jit
from ._material import RowsBasis, fit_material
from ._multilight import LightsProblem, basis
from ._multistart import culling_capacity_for_starts
from ._options import SEARCH_FIELDS, search_options
from ._parametrisation import LightParametrisation
from ._reports import JointFit
from ._targets import PaintedTargets


def joint_std_errors(param: LightParametrisation, theta: Any, scene: js.Scene, material: js.Material,
                     targets: PaintedTargets, *, fit_exponent: bool, specular: SpecularFn | None = None,
                     free_k: Any = None) -> dict:
    r"""Standard errors of a joint light + material fit, from the Jacobian of the weighted
    residual in *all* the fitted parameters at once: the light's `theta` (`param.names`), the
    coefficients $k_a, k_d, k_s$ per channel and, with `fit_exponent`, $\log n$.

    $\hat\sigma^2 (J^\top J)^{-1}$ with $\hat\sigma^2 = |r|^2 / (m - p)$ (Gauss-Markov; a
    linearisation at the optimum). Coefficients outside `free_k` (a `(3, 3)` bool array, rows
    `ka, kd, ks`: False at an active bound, or for $k_s$ of a diffuse fit) are held fixed.
    `theta`: `(P,)` the light's parameters (`param.size` first entries used); `targets`: N of
    them. The Jacobian is one compiled program per problem structure (light kind, N, the
    occluders' count, the shadow capacity rounded up to a multiple of 8), reused by later
    calls with other values (scene, targets, material); the shadow engine at a capacity, run
    again at twice the capacity while some receiver needs more (the retry of every fit; a
    `RuntimeError` beyond 4096 boundary edges).

    **Returns:** name -> standard error: `"x", "y", "z"` (or `"a", "b"` on a plane) in m,
    rotations in rad, log sizes, `"ka[r]"` ... `"ks[b]"` and `"n"` (the exponent itself,
    by the delta method); `inf` for a direction the targets do not determine.

    Example:
        ```python
        # fit_light's problem, repeated: each example runs on its own (tests/test_docs.py)
        import numpy as np
        import jaxshadow as js
        import inverse

        material = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
        points = np.c_[np.random.default_rng(0).uniform(-1, 1, (24, 2)), np.zeros(24)]
        normals, eye = np.tile([0.0, 0.0, 1.0], (24, 1)), np.array([0.0, -2.0, 2.0])
        true = js.Scene([js.PointLight([0.2, 0.3, 2.0], 3.0)], ambient=0.05)
        targets = inverse.PaintedTargets(points, normals, js.shade(true, material, points, normals, eye), eye)
        start = js.Scene([js.PointLight([0.0, 0.0, 1.8], 3.0)], ambient=0.05)   # the reference light
        lf = inverse.fit_light(start, targets, material, fit=("position",), starts=1)
        se = inverse.joint_std_errors(lf.parametrisation, lf.report.theta, start, material, targets,
                                      fit_exponent=False)   # x, y, z (m) and ka[r] ... kd[b]
        ```
    """
    t = targets
    P = param.size
    with_spec = bool(np.any(np.asarray(material.ks) != 0))
    free = np.ones((3, 3), bool) if free_k is None else np.asarray(free_k, bool)
    if not with_spec:
        free[2] = False
    k0 = np.stack([np.broadcast_to(np.asarray(getattr(material, f), np.float64), (3,)) for f in ("ka", "kd", "ks")])
    fit_n = bool(fit_exponent and with_spec)
    n0 = float(material.exponent)
    r, J = _joint_rows(param, np.asarray(theta, np.float64)[:P], scene, k0, n0, t, specular, with_spec)
    return _std_errors(param, np.asarray(r, np.float64), np.asarray(J, np.float64), t, free, fit_n, n0)


def _std_errors(param: LightParametrisation, r: np.ndarray, J: np.ndarray, targets: PaintedTargets,
                free: np.ndarray, fit_n: bool, n0: float) -> dict:
    """`joint_std_errors`' answer from the joint residual `r (3N,)` and its Jacobian `J (3N, P + 10)`
    (columns: the light's P parameters, $k_a, k_d, k_s$ RGB, $\\log n$); `free (3, 3)`: the
    coefficients not held, `fit_n`: whether $\\log n$ is, `n0`: the exponent."""
    t = targets
    P = param.size
    idx = np.flatnonzero(free.reshape(-1))
    keep = np.r_[np.arange(P), P + idx, [P + 9] if fit_n else []].astype(int)
    J = J[:, keep]
    m_eff = int(np.count_nonzero(np.asarray(t.weights) > 0))
    se_all = identifiability(J, float(r @ r), m_eff, cut=1e-10).std_errors
    names = [*param.names, *[f"{'ka kd ks'.split()[i // 3]}[{'rgb'[i % 3]}]" for i in idx]] + (["log_n"] if fit_n else [])
    out = {}
    for nm, se in zip(names, se_all, strict=True):
        if nm in ("x", "y", "z", "a", "b"):
            out[nm] = float(se) * float(param.scale)
        elif nm == "log_n":
            out["n"] = float(se) * n0
        else:
            out[nm] = float(se)
    return out


def _joint_rows(param: LightParametrisation, theta: np.ndarray, scene: js.Scene, k: np.ndarray, n: float,
                targets: PaintedTargets, specular: SpecularFn | None, with_spec: bool) -> tuple[Array, Array]:
    """`(r (3N,), J (3N, P + 10))` of `_joint_residuals` at the light's `theta (P,)`, the
    coefficients `k (3, 3)` (rows `ka, kd, ks`) and the exponent `n`: every coefficient and
    $\\log n$ in the program (one program for every held set of coefficients and for
    `projected_coefficients`). The problem's material is a placeholder of fixed shapes (the
    program reads `phi`), so every material gives the same program."""
    t = targets
    dt = t.points.dtype
    P = param.size
    phi = jnp.asarray(np.concatenate([theta, np.asarray(k, np.float64).reshape(-1), [np.log(n)]]), dt)
    cap = culling_capacity_for_starts(param, scene, t, jnp.asarray(theta[None], dt))
    # `fit_lights`' problem with every light in the program (the exponent moves their specular
    # term): the fitted one, then the others at their given power.
    others = [light for j, light in enumerate(scene.lights) if j != param.light_index]
    z = jnp.zeros(t.points.shape, dt)
    placeholder = js.Material(ka=np.zeros(3), kd=np.zeros(3), ks=np.ones(3) if with_spec else np.zeros(3),
                              exponent=1.0)
    problem = LightsProblem((param, *[None] * len(others)), (scene.lights[param.light_index], *others), scene,
                            placeholder, t, z, z, (0, *[P] * len(others)), False, with_spec, False, specular,
                            capacity=None if cap is None else 8 * -(-cap // 8),  # shared by nearby scenes
                            fit_exponent=True)
    # Twice the capacity while some receiver overflowed it: the one retry of every fit (`at_capacity`).
    (r, J), _, _ = at_capacity(lambda pr: _unpacked(_joint_jacobian(pr, phi)), problem, "joint_std_errors",
                               "Jacobian")
    return r, J


class _AtAnswer:
    r"""A projected one-light fit's LM program (`Solution.rows`, `_projected_lm`) at its answer
    `theta (P + 1,)` (the pose, $\log n$ last) with other exponents: the material fit's
    specular column and the joint Jacobian, with no program of their own. Rows are cached by
    exponent."""

    def __init__(self, sol: Any, theta: np.ndarray):
        self.sol, self.theta = sol, np.asarray(theta, np.float64)
        self.aux: dict[float, tuple] = {}

    def spec_rows(self, exponents: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """`[(S (N, 3), dS/dlog n (N, 3)), ...]` at the answer's pose, per exponent (`RowsBasis`)."""
        rows = np.repeat(self.theta[None], len(exponents), axis=0)
        rows[:, -1] = np.log(np.asarray(exponents, np.float64))
        out = []
        for e, aux in zip(exponents, self.sol.rows(rows), strict=True):
            self.aux[float(e)] = aux
            S = _projected_lm.totals(self.sol.rows.problem, aux)[1]
            assert S is not None  # a fitted exponent: the problem has a specular term
            out.append((S, aux[3][-1].sum(axis=0)))
        return out

    def material_basis(self, scene: js.Scene, targets: PaintedTargets) -> RowsBasis:
        """The material fit's columns at the answer (`fit_material`'s private `_basis`)."""
        E = _projected_lm.totals(self.sol.problem, self.sol.basis)[0]
        return RowsBasis(scene, targets, E / np.pi, self.spec_rows, self.sol.rows.n_starts)

    def joint_rows(self, material: js.Material, targets: PaintedTargets) -> tuple[np.ndarray, np.ndarray]:
        """`_joint_rows`' `(r (3N,), J (3N, P + 10))` at the answer's pose and `material` (its
        exponent evaluated once more where the material fit did not), from the basis."""
        n = float(material.exponent)
        if n not in self.aux:
            self.spec_rows(np.array([n]))
        aux = self.aux[n]
        problem = self.sol.rows.problem
        P = self.theta.size - 1
        k = np.stack([np.broadcast_to(np.asarray(getattr(material, f), np.float64), (3,)) for f in ("ka", "kd", "ks")])
        E, S = _projected_lm.totals(problem, aux)
        assert S is not None  # a fitted exponent: the problem has a specular term
        La = np.broadcast_to(np.asarray(problem.scene.ambient, np.float64)[None, :], E.shape)
        sw = np.sqrt(np.asarray(targets.weights, np.float64))
        model = k[0] * La + k[1] / np.pi * E + k[2] * S
        dE, dS = aux[2].sum(axis=1), aux[3].sum(axis=1)  # (P + 1, N, 3): the pose, then log n
        cols = [(sw * (k[1] / np.pi * dE[p] + k[2] * dS[p])).reshape(-1) for p in range(P)]
        for X in (La, E / np.pi, S):
            for c in range(3):
                col = np.zeros_like(E)
                col[:, c] = sw[:, c] * X[:, c]
                cols.append(col.reshape(-1))
        cols.append((sw * k[2] * dS[P]).reshape(-1))
        r = (sw * (model - np.asarray(targets.colours, np.float64))).reshape(-1)
        return r, np.stack(cols, axis=1)


def projected_coefficients(problem: LightsProblem, theta: Array) -> tuple[np.ndarray, float]:
    """`colour_coefficients` of a one-light projected problem (`fit_light(material_mode=
    "projected")`) by `_joint_jacobian`'s program, which `joint_std_errors` runs next: the
    columns $\\partial r / \\partial k$ of the joint residual are $\\sqrt{w}$ times the ambient,
    $E/\\pi$ and $S$ of every light (the others at their given power) at the light's `theta`
    and $n$, per channel; the coefficients are their weighted least squares on the targets'
    colours. The same values as `colour_coefficients` to rounding (the shadow engine at the
    joint program's capacity, NumPy's least squares); a joint fit traces and compiles one
    program fewer. Returns `(k (3, 3) rows ka, kd, ks; n)`."""
    param, t = problem.params[0], problem.targets
    P = param.size
    theta = np.asarray(theta, np.float64)
    n = float(np.exp(theta[P])) if problem.fit_exponent else float(problem.material.exponent)
    _, J = _joint_rows(param, theta[:P], problem.scene, np.zeros((3, 3)), n, t, problem.specular,
                       problem.with_specular)
    J = np.asarray(J, np.float64)
    y = (np.sqrt(np.asarray(t.weights, np.float64)) * np.asarray(t.colours, np.float64)).reshape(-1)
    rows = 3 if problem.with_specular else 2
    k = np.zeros((3, 3))
    for c in range(3):
        X = J[c::3, [P + 3 * f + c for f in range(rows)]]
        k[:rows, c] = np.linalg.pinv(X) @ y[c::3]
    return k, n


def _unpacked(out: tuple[Array, Array, Array]) -> tuple[tuple[Array, Array], Array]:
    """`((r, J), overflow)` from `_joint_jacobian`'s `(r, J, overflow)` (what `at_capacity` runs)."""
    return out[:2], out[2]


def _joint_residuals(phi: Array, problem: LightsProblem) -> tuple[Array, Array]:
    r"""`(r (3N,), overflow)`: the weighted residual at `phi` = the light's parameters, the nine
    coefficients $k_a, k_d, k_s$ (rows, RGB) and $\log n$, at the problem's shadow capacity
    (Poulin eq. 5.14 with every light of `problem` at its given power)."""
    P = problem.n_pose
    t = problem.targets
    dt = phi.dtype
    k = phi[P:P + 9].reshape(3, 3)
    E, S, over = basis(jnp.concatenate([phi[:P], phi[P + 9:]]), problem, problem.capacity)
    model = k[0][None, :] * problem.scene.ambient.astype(dt)[None, :] + k[1][None, :] / jnp.pi * jnp.sum(E, axis=0)
    if S is not None:
        model = model + k[2][None, :] * jnp.sum(S, axis=0)
    return (jnp.sqrt(t.weights) * (model - t.colours)).reshape(-1), over


@fit_jit(options=ONCE_COMPILER_OPTIONS)
def _joint_jacobian(problem: LightsProblem, phi: Array) -> tuple[Array, Array, Array]:
    """`(r, dr/dphi, overflow)` of `_joint_residuals`: one program per problem structure (the
    parametrisation's kind, the number of targets, occluders and capacity), whatever the scene's,
    targets' and material's values: a module-level function, so later fits reuse it. The
    Jacobian is the linearisation's tangent map on the basis vectors: the residual is traced
    once (`jax.jacfwd` beside a separate primal traced it twice and compiled ~1.3x longer;
    the same values)."""
    r, lin, over = jax.linearize(lambda x: _joint_residuals(x, problem), phi, has_aux=True)
    return r, jax.vmap(lin, out_axes=1)(jnp.eye(phi.shape[0], dtype=phi.dtype)), over


def fit_light_and_material(
    scene: js.Scene,
    targets: PaintedTargets,
    material: js.Material,
    light_index: int = 0,
    *,
    method: str = "projected",
    rounds: int = 4,
    light_kwargs: dict | None = None,
    material_kwargs: dict | None = None,
    specular: SpecularFn | None = None,
    progress: Any = None,
) -> JointFit:
    """Joint light placement and material.

    A light and a material are fitted together one way: the light fit with the material
    projected out (`material_mode="projected"`, the keyword of `fit_light` and `fit_lights`);
    this function is that fit for one light, finished. `method="projected"` (the default): one
    multistart nonlinear least squares over the light pose and $\\log n$ with $k_a, k_d, k_s$
    projected out (`fit_light(..., material_mode="projected", fit_exponent=True)`), then the
    exact bounded `fit_material` at the fitted light (the coefficients then respect `bounds`),
    and the joint standard errors. `material` gives the starting exponent and whether there is
    a specular term ($k_s \\ne 0$).

    `method="alternate"` (deprecated: a second route to the same answer, kept working for now;
    block coordinate descent, `rounds` rounds): each round places the
    light with the material fixed (`fit_light`, the full multistart in the first round;
    afterwards a local solve from the previous light, or, when the light solver screens its
    starts (`light_kwargs={"solver": inverse.LM(refine=k)}`), a multistart in a 4x tighter
    region, same shapes so nothing recompiles), then refits the
    material exactly for that light (`fit_material`). Every half-step cannot increase the
    loss, so the history is non-increasing up to solver tolerance.

    `progress`: `None` or a callable taking a message string (one line per half-step).

    **Returns:** `JointFit`.

    Example:
        ```python
        # fit_light's problem, repeated: each example runs on its own (tests/test_docs.py)
        import numpy as np
        import jaxshadow as js
        import inverse

        material = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
        points = np.c_[np.random.default_rng(0).uniform(-1, 1, (24, 2)), np.zeros(24)]
        normals, eye = np.tile([0.0, 0.0, 1.0], (24, 1)), np.array([0.0, -2.0, 2.0])
        true = js.Scene([js.PointLight([0.2, 0.3, 2.0], 3.0)], ambient=0.05)
        targets = inverse.PaintedTargets(points, normals, js.shade(true, material, points, normals, eye), eye)
        start = js.Scene([js.PointLight([0.0, 0.0, 1.8], 3.0)], ambient=0.05)   # the reference light
        guess = js.Material(ka=0.5, kd=0.5, ks=0.0, exponent=1.0)
        joint = inverse.fit_light_and_material(start, targets, guess, light_kwargs={"fit": ("position",), "starts": 4})
        joint.scene.lights[0].position, joint.material.kd, joint.std_errors
        ```
    """
    lk = dict(light_kwargs or {})
    mk = dict(material_kwargs or {})
    mk.setdefault("warn", False)
    if method not in ("projected", "alternate"):
        raise ValueError(f"fit_light_and_material: method must be 'projected' or 'alternate', got {method!r}.")
    if method == "alternate":
        warnings.warn("fit_light_and_material(method='alternate') is deprecated: a light and a material are fitted "
                      "together by the light fit with the material projected out (method='projected', the default; "
                      "material_mode='projected' of fit_light and fit_lights).", DeprecationWarning, stacklevel=2)
    history = []
    if method == "projected":
        t0 = time.perf_counter()
        kept: list = []
        lf = fit_light(scene, targets, material, light_index, specular=specular, material_mode="projected",
                       fit_exponent=True, _projected_coefficients=projected_coefficients, _solution=kept, **lk)
        sol = kept[0] if kept else None
        # The LM's program at the answer (`_projected_lm`): the material fit's specular column and the
        # joint Jacobian from the one program that holds the shadow engine.
        at = (_AtAnswer(sol, lf.report.theta) if sol is not None and sol.rows is not None
              and sol.problem.fit_exponent and invalid_reason(lf.light) is None else None)
        history.append(lf.report.loss)
        if progress is not None:
            progress(f"  light + projected material: loss {lf.report.loss:.4e}  [{time.perf_counter() - t0:.1f} s]")
        t0 = time.perf_counter()
        if "exponent" not in mk and not bool(np.any(np.asarray(material.ks) != 0)):
            mk["exponent"] = float(material.exponent)
        # A light that collapsed to a degenerate one shines as no light (`_diagnostics`).
        fitted_scene = without_invalid_lights(lf.scene)
        mf = fit_material(fitted_scene, targets, specular=specular, **mk,
                          _basis=None if at is None else at.material_basis(fitted_scene, targets))
        history.append(0.5 * float(np.sum(mf.report.weights * mf.residual**2)))
        if progress is not None:
            progress(f"  exact bounded material at that light: loss {history[-1]:.4e}  [{time.perf_counter() - t0:.1f} s]")
        free = np.ones((3, 3), bool)
        for a in mf.report.active_bounds:  # e.g. "ks[g]>=lower": held at the bound
            if a.endswith(("lower", "upper")):
                free["ka kd ks".split().index(a[:2]), "rgb".index(a[3])] = False
        if at is None:
            se = joint_std_errors(lf.parametrisation, lf.report.theta, scene, mf.material, targets,
                                  fit_exponent="exponent" not in mk, specular=specular, free_k=free)
        else:
            with_spec = bool(np.any(np.asarray(mf.material.ks) != 0))
            free[2] &= with_spec  # as joint_std_errors: no k_s column without a specular term
            r, J = at.joint_rows(mf.material, targets)
            se = _std_errors(lf.parametrisation, r, J, targets, free, "exponent" not in mk and with_spec,
                             float(mf.material.exponent))
        return JointFit(scene=lf.scene, material=mf.material, residual=mf.residual, report=(lf.report, mf.report),
                        history=tuple(history), std_errors=se)
    lf = mf = None
    # The light's search options (`inverse.Search`, or its fields in `light_kwargs`), resolved once.
    search = search_options(lk.pop("search", None), {k: lk.pop(k) for k in SEARCH_FIELDS if k in lk},
                            "fit_light_and_material", several=False)
    for r in range(int(rounds)):
        kw = dict(lk, search=search)
        if r > 0:
            if kw.get("refine", getattr(kw.get("solver"), "refine", None)):
                # Same array shapes as round 1 (no recompilation); a tighter start region.
                kw["search"] = dataclasses.replace(search, search_radius=0.25 * search.search_radius,
                                                   orientation_spread=0.25 * search.orientation_spread)
            else:
                kw["search"] = dataclasses.replace(search, starts=1)
        if r < int(rounds) - 1:  # the material is still being fitted: only the last round's checks speak
            kw["warn"] = False
        t0 = time.perf_counter()
        lf = fit_light(scene, targets, material, light_index, specular=specular, **kw)
        scene = lf.scene
        history.append(lf.report.loss)
        if progress is not None:
            progress(f"  round {r + 1}/{rounds}: light  ({kw['search'].starts} start(s)) loss {lf.report.loss:.4e}"
                     f"  [{time.perf_counter() - t0:.1f} s]")
        t0 = time.perf_counter()
        collapsed = invalid_reason(lf.light) is not None
        mf = fit_material(without_invalid_lights(scene), targets, specular=specular, **mk)
        material = mf.material
        history.append(0.5 * float(np.sum(mf.report.weights * mf.residual**2)))
        if progress is not None:
            progress(f"  round {r + 1}/{rounds}: material loss {history[-1]:.4e}  [{time.perf_counter() - t0:.1f} s]")
        if collapsed:  # no light to place again from: this round's checks speak (its report says it collapsed)
            if not kw.get("warn", True) and lk.get("warn", True):
                for msg in lf.report.quality.emitted:
                    warnings.warn(msg, FitQualityWarning, stacklevel=2)
            break
    assert lf is not None and mf is not None
    return JointFit(scene=scene, material=material, residual=mf.residual, report=(lf.report, mf.report),
                    history=tuple(history))
