r"""The light fit's solvers, as objects: `LM`, `OptimistixLM`, `LBFGSB` (`fit_light(solver=...)`).

Each minimises $\tfrac12|r(\theta)|^2$ of `fit_lights`' problem (`_multilight.LightsProblem`;
`fit_light`'s is its one-light case) from a batch of starts (`_multistart`), first screening
them down to the `refine` best when there are more, and returns a `Solution`: the solved
starts, the best one, the residual and its Jacobian there (for the report), and the light it
builds.

- `LM` (the default): the Levenberg-Marquardt of `_lm.py`, written for this batch, through
  `fit_lights`' own program (`_multilight.solve`, which also screens: `screen_by_solver`): one
  forward-mode Jacobian per iteration for all starts, with the shadow engine inside the
  compiled program (`jaxshadow.traced`: each receiver's visible region from its candidate
  occluders only, at a static capacity of boundary edges chosen from the starting lights; if
  the light moves so that some receiver needs more, the solve is repeated with twice the
  capacity, so the result is always exact).
- `OptimistixLM`: `optimistix.LevenbergMarquardt` under `jax.vmap` on the full model (every
  receiver against every occluder; needs the `optimistix` extra); it traces
  the shadow kernel several times and transposes its linearisation, so it compiles several
  times longer, and its per-start accept/reject branches evaluate both sides under `vmap`
  (`benchmarks/inverse_speed.py` measures both).
- `LBFGSB`: JAXopt's bounded L-BFGS-B on the loss (`_jaxopt.py`; needs the `jaxopt` extra),
  with hard box bounds on the parameters.
"""

from __future__ import annotations

import dataclasses
import warnings
from collections.abc import Callable
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from jaxshadow import ShadowOptions

from . import _projected_lm
from ._lm import fit_jit
from ._multilight import (
    LightsProblem,
    build_lights,
    loss_at,
    projected_residual,
    residual_and_jacobian,
    screen,
    solve,
)
from ._multistart import best_starts, culling_capacity_for_starts, prune_schedule

COMBINATORICS = ("auto", "device", "host")


@dataclasses.dataclass(frozen=True)
class Solution:
    """What a solver found from the (screened) starts. Per solved start: `values (S, P)`,
    `losses (S,)` (as returned: may be non-finite), `converged`, `num_steps`, `abandoned`;
    `best`: the index of the lowest finite loss; `residual (M,)`, `jacobian (M, P)` and `light`
    at the best; `initial_loss`: at the reference start (the first); `retries`: solves repeated
    with a larger shadow capacity; `exact_residual`: `residual` is the full model's, usable
    as the fit's residual; `problem`: as last solved. A projected one-light problem solved by
    `LM` (`_projected_lm`) also has `basis`: `(E, S, dE, dS)` at the best (`_projected_lm.aux_row`),
    and `rows`: its program at other rows (`_projected_lm.BasisRows`); otherwise None."""

    values: np.ndarray
    losses: np.ndarray
    converged: np.ndarray
    num_steps: np.ndarray
    abandoned: np.ndarray
    best: int
    residual: np.ndarray
    jacobian: np.ndarray
    light: Any
    initial_loss: float
    retries: int
    exact_residual: bool
    problem: LightsProblem
    basis: tuple | None = None
    rows: Any = None


class AbstractLightSolver(eqx.Module):
    """A multistart solver for `fit_light`: `minimise(problem, starts) -> Solution`.

    `refine`: solve only from the `refine` starts of lowest loss (Campbell & Fussell §4.4.2's
    screening of a coarse grid); `None`: from every start.

    A solver of one's own subclasses this and writes `minimise`. `problem` is `fit_lights`'
    problem of one fitted light (`inverse._multilight.LightsProblem`; the same object `LM`,
    `OptimistixLM` and `LBFGSB` get): `problem.params[0]` is the light's `LightParametrisation`
    (`names`, `size`), `problem.n_theta` the length of a parameter vector (`size`, then
    $\\log n$ with a fitted exponent), `problem.residual(theta)` the weighted residual
    `(M,)` (traceable), `problem.residual_and_jacobian(theta)` it and its Jacobian `(M, n_theta)`,
    `problem.lights(theta)[0]` the light. `starts`: `(S, n_theta)`, the reference first.
    Return a `Solution` (its `exact_residual=True` when `residual` is `problem.residual` at the
    best, so the report uses it)."""

    name: ClassVar[str] = ""
    box_map: ClassVar[str] = "sigmoid"  # how a Box constraint maps the position parameters

    refine: eqx.AbstractVar[int | None]

    def minimise(self, problem: LightsProblem, starts: Array) -> Solution:
        raise NotImplementedError

    def _screens(self, n_starts: int) -> bool:
        return self.refine is not None and 0 < int(self.refine) < n_starts


class LM(AbstractLightSolver):
    """Levenberg-Marquardt over all starts at once (`inverse/_lm.py`), with the shadow engine in
    its compiled program; exact (the default solver).

    **Arguments:**

    - `refine`: k (default 8): evaluate the loss at every start and solve only from the k best;
      the starts are evaluated by the solver's own program, k at a time, so no second program
      is compiled for the screening. `None`: solve from every start. With 64 starts and 8
      occluders screening is ~20x faster (`benchmarks/inverse_speed.py`).
    - `prune` (several starts): at iterations 4, 8, 16, ... abandon the worse half (by current
      loss) of the starts still running (successive halving), so the cost follows the promising
      starts (`LightReport.abandoned`). False: every start runs to convergence or `max_steps`.
    - `combinatorics`: how soft shadows are evaluated in the solver's program: `"host"`, by the
      shadow engine (compiled C++ called from the program through XLA's FFI: per receiver,
      the visible region of the light from its candidate occluders only, at a capacity sized
      from the starts and doubled when the light moves so that some receiver needs more);
      `"device"`, every receiver against every occluder in XLA (no host code; memory and time
      grow with the number of occluders); `"auto"` (default): `"host"` where the engine is
      built, else `"device"`. The same values to rounding either way.
    - `rtol`, `atol`: termination tolerances (`_lm.batched_levenberg_marquardt`);
      `max_steps`: iterations per start.

    Example:
        ```python
        import inverse

        solver = inverse.LM(refine=8, prune=True)        # the default
        local = inverse.LM(refine=None, max_steps=50)    # every start, fewer iterations
        # inverse.fit_light(scene, targets, material, solver=local)
        ```
    """

    name: ClassVar[str] = "lm"

    refine: int | None = 8
    prune: bool = True
    combinatorics: str = "auto"
    rtol: float = 1e-9
    atol: float = 1e-12
    max_steps: int = 100

    def __check_init__(self) -> None:
        if self.combinatorics not in COMBINATORICS:
            raise ValueError(f"LM: combinatorics must be 'auto', 'device' or 'host', got {self.combinatorics!r}.")

    def uses_engine(self) -> bool:
        """Whether this solver evaluates shadows with the shadow engine (`combinatorics`)."""
        if self.combinatorics != "auto":
            return self.combinatorics == "host"
        return ShadowOptions().use_engine()

    def minimise(self, problem: LightsProblem, starts: Array) -> Solution:
        """`fit_lights`' screening and compiled solver program on the problem (one fitted light,
        `problem.params[0]`; `screen_by_solver`, `_multilight.solve`, every parameter searched
        from the starts), each retried at twice the shadow capacity on overflow."""
        param = problem.params[0]
        ys = np.asarray(starts)
        screens = self._screens(ys.shape[0])
        n_solved = int(self.refine) if screens else int(ys.shape[0])
        sched = prune_schedule(n_solved, self.max_steps) if self.prune else ()
        cap = culling_capacity_for_starts(param, problem.scene, problem.targets, starts) if self.uses_engine() else None
        problem = dataclasses.replace(problem, capacity=cap)
        base, mask = ys[0], np.ones(ys.shape[1], bool)
        initial, retries = None, 0
        # A projected one-light problem: the program that also keeps the basis (`_projected_lm`).
        run = _projected_lm.solve if _projected_lm.keeps_basis(problem) else _solve_without_basis
        if screens:
            losses, problem, retries = screen_by_solver(problem, ys, base, mask, n_solved, self.rtol, self.atol,
                                                        run)
            initial = float(losses[0])
            ys = ys[best_starts(np.where(np.isfinite(losses), losses, np.inf), n_solved)]
        res, problem, r = run(problem, ys, base, mask, rtol=self.rtol, atol=self.atol, max_steps=self.max_steps,
                              prune=sched)
        retries += r
        losses = np.asarray(res.losses, np.float64)
        best = int(np.argmin(np.where(np.isfinite(losses), losses, np.inf)))
        if initial is None:
            initial = float(np.asarray(res.initial_losses)[0])
        values = np.asarray(res.values)
        light = build_lights(problem, jnp.asarray(values[best], ys.dtype))[0]
        kept = res.aux is not None
        return Solution(values, losses, np.asarray(res.converged), np.asarray(res.num_steps),
                        np.asarray(res.abandoned), best, np.asarray(res.residuals, np.float64)[best],
                        np.asarray(res.jacobians, np.float64)[best], light, initial, retries, True, problem,
                        _projected_lm.aux_row(res.aux, best) if kept else None,
                        _projected_lm.BasisRows(problem, ys.shape[0], (self.rtol, self.atol)) if kept else None)


def _solve_without_basis(problem: LightsProblem, starts: np.ndarray, base: np.ndarray, mask: np.ndarray,
                         **lm: Any) -> tuple:
    """`_multilight.solve` by the LM program that keeps no basis (`fit_light`'s report needs none)."""
    return solve(problem, starts, base, mask, keep_basis=False, **lm)


def screen_by_solver(problem: LightsProblem, rows: np.ndarray, base: np.ndarray, mask: np.ndarray,
                     chunk: int, rtol: float, atol: float, run: Callable = solve) -> tuple[np.ndarray, LightsProblem, int]:
    """The loss $\\tfrac12|r|^2$ at every row of `rows (S, P)` (the others held at `base` where
    `mask` is off) by the solver's own program: `_multilight.solve` with no iterations
    (`LMResult.initial_losses`), `chunk` rows a call, with the solve's `rtol` and `atol` (static
    arguments of the program), so that the solve that follows runs the same compiled program.
    Each chunk is evaluated again with twice the shadow capacity while some receiver overflowed
    it. The values of `_multilight.screen` (bit-identical on the demo fit), without its program:
    it evaluates a Jacobian at every row (0.6 s CPU more for 64 starts of the demo fit; for
    `fit_lights`' three mixed lights 96 rows took 3.5 s against 1.0 s wall at a load of 18) but
    a fit's first call traces and compiles one program fewer (`_screen_impl`: 15-23 s wall at
    that load). `run`: the solve (`_multilight.solve`, `fit_lights`' program that keeps the
    basis; `_solve_without_basis`, `fit_light`'s; or `_projected_lm.solve`).
    Returns `(losses (S,), problem used, retries)`."""
    out, retries = [], 0
    for a in range(0, rows.shape[0], chunk):
        part = rows[a:a + chunk]
        part = np.concatenate([part, np.repeat(part[:1], chunk - part.shape[0], axis=0)])
        res, problem, r = run(problem, part, base, mask, rtol=rtol, atol=atol, max_steps=0, prune=())
        out.append(np.asarray(res.initial_losses))
        retries += r
    return np.concatenate(out)[: rows.shape[0]], problem, retries


class OptimistixLM(AbstractLightSolver):
    """`optimistix.LevenbergMarquardt` from every start under `jax.vmap`, on the full model
    (no culling). Several times slower to compile and to run than `LM`
    (`benchmarks/inverse_speed.py`): the reference implementation. Needs the `optimistix` extra
    (`pip install 'jaxshadow[optimistix]'`).

    **Arguments:** `refine` (default 8: the starts are screened by one vectorised loss),
    `rtol`, `atol` (Optimistix's), `max_steps`.

    Example:
        ```python
        import inverse

        solver = inverse.OptimistixLM(rtol=1e-9, atol=1e-12)
        # inverse.fit_light(scene, targets, material, solver=solver)
        ```
    """

    name: ClassVar[str] = "optimistix"

    refine: int | None = 8
    rtol: float = 1e-9
    atol: float = 1e-12
    max_steps: int = 100

    def minimise(self, problem: LightsProblem, starts: Array) -> Solution:
        return _minimise_vectorised(self, problem, starts, lambda pr, y0: _multistart_optx(
            pr, y0, self.rtol, self.atol, int(self.max_steps)))


class LBFGSB(AbstractLightSolver):
    """JAXopt's bounded L-BFGS-B on $\\tfrac12|r|^2$ from every start under `jax.vmap`, with box
    bounds on the parameters (a `Box` constraint maps the position affinely, so its bounds are
    hard). Needs the `jaxopt` extra (`pip install jaxshadow[jaxopt]`).

    **Arguments:** `refine` (default 8: the starts are screened by one vectorised loss), `tol`
    (JAXopt's), `max_steps`.

    Example:
        ```python
        import inverse

        solver = inverse.LBFGSB(tol=1e-12)
        # inverse.fit_light(scene, targets, material, constraints={0: inverse.Box(lo, hi)}, solver=solver)
        ```
    """

    name: ClassVar[str] = "lbfgsb"
    box_map: ClassVar[str] = "affine"

    refine: int | None = 8
    tol: float = 1e-12
    max_steps: int = 100

    def minimise(self, problem: LightsProblem, starts: Array) -> Solution:
        lo, hi = problem.params[0].lbfgsb_bounds(starts.dtype)
        extra = starts.shape[1] - lo.shape[0]  # log n with a fitted exponent: bounded as the others' 1e6
        lo = jnp.concatenate([lo, jnp.full((extra,), -1e6, lo.dtype)])
        hi = jnp.concatenate([hi, jnp.full((extra,), 1e6, hi.dtype)])
        return _minimise_vectorised(self, problem, starts, lambda pr, y0: _multistart_lbfgsb(
            pr, y0, lo, hi, self.tol, int(self.max_steps)))


def _minimise_vectorised(solver: AbstractLightSolver, problem: LightsProblem, starts: Array, run: Any) -> Solution:
    """Screening by one vectorised loss (`fit_lights`' screening, `_multilight.screen`), then
    `run(problem, starts) -> (values, losses, converged, steps)`; the residual and Jacobian at
    the best by a program of their own."""
    initial = None
    if solver._screens(starts.shape[0]):
        ys = np.asarray(starts)
        screen_f = screen(problem, ys, ys[0], np.ones(ys.shape[1], bool), ys.shape[0])[0]
        screen_f = np.where(np.isfinite(screen_f), screen_f, np.inf).astype(np.float64)
        starts = jnp.asarray(np.asarray(starts)[best_starts(screen_f, int(solver.refine))])
        initial = float(screen_f[0])
    values, losses, ok, steps = (np.asarray(x) for x in run(problem, starts))
    losses = losses.astype(np.float64)
    best = int(np.argmin(np.where(np.isfinite(losses), losses, np.inf)))
    theta = jnp.asarray(values[best], starts.dtype)
    r, J = residual_and_jacobian(problem, theta)
    if initial is None:
        initial = float(loss_at(problem, jnp.asarray(np.asarray(starts)[0])))
    light = build_lights(problem, theta)[0]
    return Solution(values, losses, ok, steps, np.zeros(len(losses), bool), best, np.asarray(r, np.float64),
                    np.asarray(J, np.float64), light, initial, 0, False, problem)


def _residual(theta: Array, problem: LightsProblem) -> Array:
    """The weighted residual, every receiver against every occluder (the vectorised solvers'
    model: no capacity)."""
    return projected_residual(theta, problem, None)[0]


def _loss(theta: Array, problem: LightsProblem) -> Array:
    r = _residual(theta, problem)
    return 0.5 * jnp.sum(r * r)


def _optimistix() -> Any:
    try:
        import optimistix
    except ImportError as err:
        raise ImportError("inverse.OptimistixLM needs the optional dependency 'optimistix': install it with "
                          "`pip install 'jaxshadow[optimistix]'`.") from err
    return optimistix


@fit_jit
def _multistart_optx(problem: LightsProblem, starts: Array, rtol: float, atol: float, max_steps: int) -> tuple:
    optx = _optimistix()
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)

    def one(y0: Array) -> tuple:
        sol = optx.least_squares(_residual, solver, y0, args=problem, throw=False, max_steps=max_steps)
        return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]

    values, ok, steps = jax.vmap(one)(starts)
    losses = jax.vmap(_loss, in_axes=(0, None))(values, problem)
    return values, losses, ok, steps


@fit_jit
def _multistart_lbfgsb(problem: LightsProblem, starts: Array, lower: Array, upper: Array, tol: float,
                       max_steps: int) -> tuple:
    from ._jaxopt import lbfgsb_solve

    def one(y0: Array) -> tuple:
        y, _, it = lbfgsb_solve(lambda th: _loss(th, problem), y0, lower, upper, max_steps, tol)
        return y, it

    values, steps = jax.vmap(one)(starts)
    losses = jax.vmap(_loss, in_axes=(0, None))(values, problem)
    return values, losses, steps < max_steps, steps


# --------------------------------------------------------------------------------------
# fit_light's keywords before the solver objects
# --------------------------------------------------------------------------------------

_SOLVERS: dict[str, Callable[[], AbstractLightSolver]] = {"lm": LM, "optimistix": OptimistixLM, "lbfgsb": LBFGSB}
LEGACY_SOLVER_KEYWORDS = ("refine", "prune", "receiver_groups", "combinatorics", "rtol", "atol", "max_steps")


def solver_from_arguments(solver: AbstractLightSolver | str | None, legacy: dict[str, Any]) -> AbstractLightSolver:
    """`fit_light`'s solver: `solver`, `LM()` for None; a solver name (`"lm"`, `"optimistix"`,
    `"lbfgsb"`) and the keywords `refine`, `prune`, `receiver_groups` (no longer used), `combinatorics`, `rtol`,
    `atol`, `max_steps` still work, with a `DeprecationWarning` (options a solver does not have
    are ignored, as they were)."""
    unknown = sorted(set(legacy) - set(LEGACY_SOLVER_KEYWORDS))
    if unknown:
        raise TypeError(f"fit_light() got unexpected keyword argument(s) {unknown}.")
    if isinstance(solver, str) and solver not in _SOLVERS:
        raise ValueError(f"fit_light: solver must be inverse.LM(), OptimistixLM() or LBFGSB(), got {solver!r}.")
    if solver is not None and not isinstance(solver, (str, AbstractLightSolver)):
        raise ValueError(f"fit_light: solver must be inverse.LM(), OptimistixLM() or LBFGSB(), got {solver!r}.")
    if not isinstance(solver, str) and not legacy:
        return LM() if solver is None else solver
    warnings.warn("fit_light(solver='lm', refine=..., prune=..., ...) is deprecated: pass a solver object, "
                  "e.g. solver=inverse.LM(refine=8, prune=True), inverse.OptimistixLM() or inverse.LBFGSB().",
                  DeprecationWarning, stacklevel=4)
    base = _SOLVERS[solver]() if isinstance(solver, str) else (LM() if solver is None else solver)
    kw = dict(legacy)
    if isinstance(base, LBFGSB) and "atol" in kw:
        kw["tol"] = kw["atol"]  # L-BFGS-B used atol as its tolerance
    fields = {f.name for f in dataclasses.fields(base)}
    return dataclasses.replace(base, **{k: v for k, v in kw.items() if k in fields})


def checked_solver(solver: AbstractLightSolver | str | None, who: str, *, several: bool,
                   legacy: dict[str, Any] | None = None) -> AbstractLightSolver:
    """The solver object of a light fit, `LM()` for None (ValueError for anything else than a
    solver object). One light (`fit_light`): any `AbstractLightSolver`, and the deprecated
    names and keywords of `solver_from_arguments`. Several lights (`fit_lights`): `LM`, whose
    compiled program (`_multilight._lm`) searches one light or all of them."""
    if not several:
        return solver_from_arguments(solver, legacy or {})
    solver = LM() if solver is None else solver
    if not isinstance(solver, LM):
        raise ValueError(f"{who}: solver must be an inverse.LM, got {type(solver).__name__}.")
    return solver
