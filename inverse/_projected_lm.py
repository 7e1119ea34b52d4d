r"""The one-light fit with the material projected out (`fit_light(material_mode="projected")`,
`fit_light_and_material`): its LM program also keeps, at every start's accepted point, the
basis the residual was made of and its tangents, so that what the fit needs at the answer
comes from the one compiled program that holds the shadow engine.

The residual of a projected one-light problem is, per channel $c$,
$r_c = \sqrt{w_c}\,(A_c k_c - C_c)$ with the columns $A_c = (L_{a,c}, E_c/\pi, S_c)$ and $k_c$
their least squares (`_multilight._colour_free_rows`). The program returns, beside $r$ and
$\partial r/\partial\theta$, the basis $E, S$ `(J, N, 3)` of the lights in the program and its
tangents $\partial E/\partial\theta, \partial S/\partial\theta$ `(P, J, N, 3)` (one
linearisation: the residual's, with the basis as further outputs). From them, in NumPy:

- the projected material at the answer (`coefficients`: what `_lights.colour_coefficients`
  compiles a program for),
- the model's colours at the answer (the fit's residual),
- evaluated at other rows $(\theta^*, \log n_i)$ (`basis_rows`: the program with no
  iterations), the specular column $S(n)$ and $\partial S/\partial\log n$ of the material fit's
  exponent search, and the Jacobian of the joint light + material residual in every parameter
  (Poulin eq. 5.14 is linear in $k_a, k_d, k_s$: its columns are the basis itself).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

from ._forward import at_capacity
from ._lm import LMResult, batched_levenberg_marquardt, duplicate_sources, fit_jit, prune_array
from ._multilight import LightsProblem, basis, projected_residual


def keeps_basis(problem: LightsProblem) -> bool:
    """Whether `problem` is a one-light projected problem whose LM keeps its basis: the
    colour-free model with the powers as given (`fit_light`'s), no painted ranges or relations,
    no `Outside` rows."""
    return bool(problem.colour_free and not problem.fit_power and not problem.powers_in_theta
                and problem.paint is None and not problem.outside and problem.active is None)


def _basis_lm_impl(problem: LightsProblem, starts: Array, base: Array, mask: Array, rtol: float, atol: float,
                   max_steps: Array, prune: Array, chunk: int | None, mirror: Array) -> LMResult:
    """`_multilight._lm`'s batched LM on the projected residual (the same residual and
    Jacobian, `jax.linearize` on the P basis vectors), with `LMResult.aux = (E, S or None, dE,
    dS or None)` at every start's accepted point: the basis `(J, N, 3)` and its tangents
    `(P, J, N, 3)` (module docstring)."""
    dt = starts.dtype
    P = starts.shape[1]
    N = problem.targets.points.shape[0]
    J = len(problem.params)

    def fn(th: Array, args: tuple) -> tuple[Array, Array]:
        pr, b, m = args
        return projected_residual(jnp.where(m, th, b), pr, pr.capacity)

    def rj(th: Array, args: tuple) -> tuple:
        pr, b, m = args

        def parts(z: Array) -> tuple:
            y = jnp.where(m, z, b)
            E, S, over = basis(y, pr, pr.capacity)
            r, _ = projected_residual(y, pr, pr.capacity, given=(E, S, over))
            return (r, E, S), over

        (r, E, S), lin, over = jax.linearize(parts, th, has_aux=True)
        Jr, dE, dS = jax.vmap(lin, out_axes=(1, 0, 0))(jnp.eye(P, dtype=dt))
        return r, Jr, over, (E, S, dE, dS)

    b = jax.ShapeDtypeStruct((J, N, 3), dt)
    d = jax.ShapeDtypeStruct((P, J, N, 3), dt)
    spec = problem.with_specular
    aux = (b, b if spec else None, d, d if spec else None)
    return batched_levenberg_marquardt(fn, starts, (problem, base, mask), rtol=rtol, atol=atol, max_steps=max_steps,
                                       prune=prune, chunk=chunk, num_residuals=problem.n_residuals, mirror=mirror,
                                       jacobian=rj, aux=aux)


_basis_lm = fit_jit(_basis_lm_impl)


def solve(problem: LightsProblem, starts: np.ndarray, base: np.ndarray, mask: np.ndarray, *, rtol: float,
          atol: float, max_steps: int, prune: tuple[int, ...]) -> tuple[LMResult, LightsProblem, int]:
    """`_multilight.solve` by `_basis_lm` (its `LMResult.aux` the basis at every start):
    one start a chunk, repeated starts solved once, solved again with twice the shadow capacity
    while some receiver overflowed it. Returns `(result, problem used, retries)`."""
    dt = problem.targets.points.dtype
    mirror = jnp.asarray(duplicate_sources(np.asarray(starts, dt)))
    sched = prune_array(prune)

    def run(pr: LightsProblem) -> tuple[LMResult, Any]:
        res = _basis_lm(pr, jnp.asarray(starts, dt), jnp.asarray(base, dt), jnp.asarray(mask), rtol, atol,
                        np.asarray(max_steps, np.int32), sched, 1, mirror)
        return res, res.flag

    return at_capacity(run, problem, "fit_light", "solve")


def aux_row(aux: Any, i: int) -> tuple:
    """`(E, S, dE, dS)` of start `i` from `LMResult.aux`, as float64 NumPy arrays (None kept)."""
    return tuple(None if x is None else np.asarray(x, np.float64)[i] for x in aux)


class BasisRows:
    """The LM program of a solved projected problem evaluated with no iterations at rows
    `(S, n_theta)` of its own start count `S` (`basis_rows`): the same compiled program as the
    fit's. `tolerances`: the solve's `(rtol, atol)` (static arguments of the program). `_run`:
    the program (`solve` here; `fit_lights`' `_multilight.solve` in `_basis_rows.BasisRows`)."""

    _run = staticmethod(solve)

    def __init__(self, problem: LightsProblem, n_starts: int, tolerances: tuple[float, float]):
        self.problem, self.n_starts, self.tolerances = problem, int(n_starts), tolerances

    def __call__(self, rows: np.ndarray) -> list[tuple]:
        """`aux_row` at each of `rows (R, n_theta)`, `n_starts` rows a call (the last padded)."""
        rows = np.asarray(rows, np.float64)
        k = self.n_starts
        mask = np.ones(rows.shape[1], bool)
        out: list[tuple] = []
        for a in range(0, rows.shape[0], k):
            part = rows[a:a + k]
            part = np.concatenate([part, np.repeat(part[:1], k - part.shape[0], axis=0)])
            res, self.problem, _ = self._run(self.problem, part, part[0], mask, rtol=self.tolerances[0],
                                             atol=self.tolerances[1], max_steps=0, prune=())
            out += [aux_row(res.aux, i) for i in range(min(k, rows.shape[0] - a))]
        return out


def totals(problem: LightsProblem, aux: tuple) -> tuple[np.ndarray, np.ndarray | None]:
    """`(E (N, 3), S (N, 3) or None)`: the irradiance and specular integral of every light at
    the row `aux` (`aux_row`): the lights in the program and the fixed ones (`e_fixed`,
    `s_fixed`)."""
    E, S = aux[0].sum(axis=0), None if aux[1] is None else aux[1].sum(axis=0)
    if problem.has_fixed:
        E = E + np.asarray(problem.e_fixed, np.float64)
        if S is not None:
            S = S + np.asarray(problem.s_fixed, np.float64)
    return E, S


def columns(problem: LightsProblem, aux: tuple) -> list[np.ndarray]:
    """The model's `(N, 3)` columns at the row `aux`: the ambient, $E/\\pi$ and (with a specular
    term) $S$ of every light (`_multilight.colour_free_columns` without `fit_power`)."""
    E, S = totals(problem, aux)
    n = E.shape[0]
    La = np.broadcast_to(np.asarray(problem.scene.ambient, np.float64)[None, :], (n, 3))
    return [La, E / np.pi] + ([] if S is None else [S])


def coefficients(problem: LightsProblem, aux: tuple) -> np.ndarray:
    """`(3, 3)` rows $k_a, k_d, k_s$ (RGB columns; $k_s = 0$ without a specular term): the
    per-channel weighted least squares of the targets' colours on `columns` (the projection the
    search made; `_lights.colour_coefficients`'s values, from the program's basis)."""
    t = problem.targets
    X = np.stack(columns(problem, aux), axis=-1)  # (N, 3, m)
    sw = np.sqrt(np.asarray(t.weights, np.float64))
    y = np.asarray(t.colours, np.float64)
    k = np.zeros((3, 3))
    for c in range(3):
        k[:X.shape[2], c] = np.linalg.pinv(X[:, c, :] * sw[:, c:c + 1]) @ (y[:, c] * sw[:, c])
    return k


def model(problem: LightsProblem, aux: tuple, k: np.ndarray) -> np.ndarray:
    """`(N, 3)` colours $k_a L_a + k_d E/\\pi + k_s S$ at the row `aux` for coefficients `k (3, 3)`."""
    cols = columns(problem, aux)
    return sum(k[i][None, :] * col for i, col in enumerate(cols))
