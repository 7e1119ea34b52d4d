r"""What `fit_lights` reports: the powers and material at fitted poses (structured least
squares on the host), and what the targets determine.

The report's parameters are every light's pose parameters, the fitted powers and (with
`material_mode="projected"`) $k_a, k_d, k_s$ per channel; their Jacobian is that of the
structured model (`_multilight.structured_residual`; powers and material by their closed-form
columns), so standard errors, correlations and null directions are those of the joint problem
(`_identifiability`), not of the projected residual alone.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
from scipy.optimize import nnls

import jaxshadow as js

from ._diagnostics import FitQuality
from ._reports import FitReport

CORRELATION_THRESHOLD = 0.95


def structured_coefficients(E: np.ndarray, S: np.ndarray | None, e0: np.ndarray, s0: np.ndarray | None,
                            La: np.ndarray, colours: np.ndarray, weights: np.ndarray, material: Any, *,
                            fit_power: bool, project: bool, gauge: int | None,
                            iterations: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """Powers `(J,)` (>= 0) and material `(3, 3)` (rows $k_a, k_d, k_s$) of the structured model
    at fixed poses, by weighted least squares: with a fixed material, the powers by NNLS (one
    problem for the three channels); with a projected material, alternating least squares
    between the material (per channel, $k$ >= 0) and the powers (NNLS), the power of light
    `gauge` held at 1 (the product $k_d p$ does not separate without it; None: the fixed
    lights set the scale).

    `E`, `S`: `(J, N, 3)`; `e0`, `s0`, `colours`, `weights`: `(N, 3)`; `La`: `(3,)`."""
    J = E.shape[0]
    sw = np.sqrt(weights)
    spec = S is not None
    S = np.zeros_like(E) if S is None else S  # unused without a specular term
    s0 = np.zeros_like(e0) if s0 is None else s0
    k = np.stack([np.broadcast_to(np.asarray(getattr(material, f), np.float64), (3,)) for f in ("ka", "kd", "ks")])
    p = np.ones(J)

    def solve_p(k: np.ndarray) -> np.ndarray:
        cols = k[1] / np.pi * E + (k[2] * S if spec else 0.0)  # (J, N, 3)
        fixed = k[0] * La + k[1] / np.pi * e0 + (k[2] * s0 if spec else 0.0)
        A = (sw[None] * cols).reshape(J, -1).T
        y = (sw * (colours - fixed)).reshape(-1)
        free = np.ones(J, bool)
        if gauge is not None:
            free[gauge] = False
            y = y - A[:, gauge]
        out = np.ones(J)
        out[free] = nnls(A[:, free], y)[0] if free.any() else []
        return out

    def solve_k(p: np.ndarray) -> np.ndarray:
        e = e0 + np.tensordot(p, E, axes=1)
        s = s0 + np.tensordot(p, S, axes=1)
        out = np.zeros((3, 3))
        for c in range(3):
            X = np.stack([np.full(len(e), La[c]), e[:, c] / np.pi] + ([s[:, c]] if spec else []), axis=1)
            out[: X.shape[1], c] = nnls(X * sw[:, c:c + 1], colours[:, c] * sw[:, c])[0]
        return out

    if not project:
        return (solve_p(k) if fit_power else p), k
    if not fit_power:
        return p, solve_k(p)
    for _ in range(iterations):
        k_new = solve_k(p)
        p_new = solve_p(k_new)
        done = np.max(np.abs(p_new - p)) <= 1e-13 * max(np.max(np.abs(p)), 1.0)
        k, p = k_new, p_new
        if done:
            break
    return _polish(E, S if spec else None, e0, s0, La, colours, sw, p, k, gauge)


def _polish(E: np.ndarray, S: np.ndarray | None, e0: np.ndarray, s0: np.ndarray, La: np.ndarray,
            colours: np.ndarray, sw: np.ndarray, p: np.ndarray, k: np.ndarray,
            gauge: int | None) -> tuple[np.ndarray, np.ndarray]:
    """Alternating least squares creeps along the valley of the product $k_d p$: finish with a
    bounded Gauss-Newton (`scipy.optimize.least_squares`, trust region, all >= 0) in the material
    and the free powers together, with the exact Jacobian of the bilinear model."""
    from scipy.optimize import least_squares

    J = E.shape[0]
    spec = S is not None
    S = np.zeros_like(E) if S is None else S
    nk = 9 if spec else 6
    free = np.ones(J, bool)
    if gauge is not None:
        free[gauge] = False

    def unpack(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        kk = np.zeros((3, 3))
        kk[: nk // 3] = x[:nk].reshape(-1, 3)
        pp = np.ones(J)
        pp[free] = x[nk:]
        return kk, pp

    def fun(x: np.ndarray) -> np.ndarray:
        kk, pp = unpack(x)
        e = e0 + np.tensordot(pp, E, axes=1)
        m = kk[0] * La + kk[1] / np.pi * e + (kk[2] * (s0 + np.tensordot(pp, S, axes=1)) if spec else 0.0)
        return (sw * (m - colours)).reshape(-1)

    def jac(x: np.ndarray) -> np.ndarray:
        kk, pp = unpack(x)
        n = colours.shape[0]
        e = e0 + np.tensordot(pp, E, axes=1)
        cols = []
        terms = [np.broadcast_to(La, e.shape), e / np.pi]
        if spec:
            terms.append(s0 + np.tensordot(pp, S, axes=1))
        for b in terms:
            for c in range(3):
                col = np.zeros((n, 3))
                col[:, c] = b[:, c]
                cols.append(col)
        for j in np.flatnonzero(free):
            cols.append(kk[1] / np.pi * E[j] + (kk[2] * S[j] if spec else 0.0))
        return np.stack([(sw * c_).reshape(-1) for c_ in cols], axis=1)

    x0 = np.concatenate([k[: nk // 3].reshape(-1), p[free]])
    sol = least_squares(fun, np.maximum(x0, 0.0), jac=jac, bounds=(0.0, np.inf), xtol=1e-15, ftol=1e-15,
                        gtol=1e-15, max_nfev=200)
    return unpack(sol.x)[::-1]


def material_of(k: np.ndarray, exponent: Any, dtype: Any) -> js.Material:
    """A `js.Material` from rows $k_a, k_d, k_s$ `(3, 3)`."""
    import jax.numpy as jnp

    return js.Material(ka=jnp.asarray(k[0], dtype), kd=jnp.asarray(k[1], dtype), ks=jnp.asarray(k[2], dtype),
                       exponent=jnp.asarray(exponent, dtype))


def correlated_pairs(jacobian: np.ndarray, names: tuple, determined: np.ndarray,
                     threshold: float = CORRELATION_THRESHOLD) -> tuple:
    """`((name_a, name_b, rho), ...)`: pairs of determined parameters whose correlation
    $|\\rho|$ (from $(J^\\top J)^{-1}$ over the determined columns) exceeds `threshold`."""
    idx = np.flatnonzero(determined)
    if idx.size < 2:
        return ()
    Jg = jacobian[:, idx]
    cn = np.linalg.norm(Jg, axis=0)
    cov = np.linalg.pinv((Jg / cn).T @ (Jg / cn))
    d = np.sqrt(np.maximum(np.diag(cov), 1e-300))
    rho = cov / d[:, None] / d[None, :]
    out = []
    for a in range(idx.size):
        for b in range(a + 1, idx.size):
            if abs(rho[a, b]) > threshold:
                out.append((names[idx[a]], names[idx[b]], float(rho[a, b])))
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class LightsReport(FitReport):
    """A joint fit of several lights (`FitReport`; names `light{i}.x`, ..., `light{i}.power`
    for light `i` of the scene, and `ka[r]` ... `ks[b]` with a projected material; positions
    in m in `std_errors`, powers as factors of the given radiance), and:

    - `correlated`: `((name_a, name_b, rho), ...)` determined pairs with $|\\rho| > 0.95$:
      parameters the targets trade off against each other.
    - `suggestions`: name -> `(K, 3)` candidate receiver points (best first) where the model
      changes most along the undetermined direction that involves that parameter: painting
      targets there determines it (empty when determined or no candidates were evaluated);
      `suggestion_normals`: their normals; `suggestion_std_errors`: name -> `(now, predicted)`, its
      standard error now and predicted with the first three suggested targets painted (with the
      targets' median noise): suggestions are kept only where they lower it.
    - `loss`: $\\tfrac12\\sum w r^2$ of the structured model; `initial_loss`: at the given scene
      (powers projected); `stage_losses`: the best loss after each light's multistart, then
      after the joint refinement; `starts_solved`: starts solved in total; `retries`: solves
      repeated with a larger shadow capacity; `scale` (m); `warnings`.
    - `quality`: the checks of `inverse._diagnostics` (`FitQuality`: a wrong minimum with the
      competing placements of the last joint solve, escaped lights, outliers, conflicting
      targets, nearly undetermined parameters, an all-dark answer to relations); `trusted`.
    - `quantities`: `{name: inverse._uncertainty.Quantity}`, what the standard errors cover
      (each light's centre `light{i}.x/.y/.z` in m and its emitted power `light{i}.flux`), with
      their standard errors and the projected joint 95 % intervals that the fit vouches for
      (`_uncertainty`'s docstring). With competing placements (`quality.rivals`, flag
      `"competing_placements"`) the centres', powers' and emitted powers' standard errors here and
      in `std_errors` are widened by the largest distance to a rival along each
      (`_uncertainty.widened`): they cover the placements the targets cannot tell apart, not
      the answer's basin alone.
    """

    correlated: tuple
    suggestions: dict
    suggestion_normals: dict
    loss: float
    initial_loss: float
    stage_losses: tuple
    starts_solved: int
    retries: int
    scale: float
    quality: FitQuality | None = None
    suggestion_std_errors: dict = dataclasses.field(default_factory=dict)
    quantities: dict = dataclasses.field(default_factory=dict)

    def _headline(self) -> str:
        return (f"lights fit: loss {self.initial_loss:.4g} -> {self.loss:.4g} "
                f"(stages {', '.join(f'{x:.3g}' for x in self.stage_losses)}; {self.starts_solved} starts solved)")

    def _extra_lines(self) -> list[str]:
        lines = [f"  trade off: {a} ~ {b} (rho={r:+.3f})" for a, b, r in self.correlated]
        for nm, pts in self.suggestions.items():
            if len(pts):
                where = "; ".join(np.array2string(np.asarray(q), precision=3) for q in pts[:3])
                now, pred = self.suggestion_std_errors.get(nm, (math.nan, math.nan))
                lines.append(f"  to determine {nm}, add targets at {where} (predicted standard error "
                             f"{now:.3g} -> {pred:.3g})")
        return lines


