r"""Which fitted parameters the targets determine, and how well: one rule for every fit.

From the Jacobian $J$ of the weighted residual at the optimum (a linearisation: Gauss-Markov),
with unit-norm columns $J_n = J D^{-1}$ (so the test is scale-free):

- a parameter is **undetermined** when its column is zero, or when it takes part (a component
  above 1e-6) in a null direction of $J_n$ (a right singular vector whose singular value is at
  most `cut` times the largest);
- the standard errors of the others are $\sqrt{\operatorname{diag}(\hat\sigma^2 (J_g^\top
  J_g)^{+})} / d$ over the determined columns $J_g$, with $\hat\sigma^2 = |r|^2 / \max(m - p, 1)$
  for $m$ residuals of positive weight and $p$ free parameters, when the noise is estimated
  from the residual; when it is told (each weighted residual row's variance $v$ known: the
  painted colours' standard deviations times the square roots of the weights), the linearised
  covariance of the weighted least-squares estimate,
  $(J_g^\top J_g)^{+} J_g^\top \operatorname{diag}(v) J_g (J_g^\top J_g)^{+}$ (the sandwich; with
  weights $1/\sigma^2$, $v = 1$ and it is $(J_g^\top J_g)^{+}$), with no residual scale.

Parameters held fixed (at an active bound) are left out of $J$'s null space and of the degrees
of freedom; their standard error is 0.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Identifiability:
    """`singular_values`: of the unit-column Jacobian, all columns; `std_errors (P,)`: in the
    parameters' own units (0 where held fixed, inf where undetermined); `determined (P,)`;
    `sigma2`: the residual variance estimate; `dof`: its degrees of freedom; `covariance (P, P)`:
    the linearised covariance in the parameters' own units (0 in the rows and columns of the
    parameters held fixed or undetermined; `std_errors` is the root of its diagonal elsewhere)."""

    singular_values: np.ndarray
    std_errors: np.ndarray
    determined: np.ndarray
    sigma2: float
    dof: int
    covariance: np.ndarray


def identifiability(jacobian: np.ndarray, rss: float, n_residuals: int, free: np.ndarray | None = None,
                    cut: float = 1e-8, row_variance: np.ndarray | None = None) -> Identifiability:
    """The rule of the module docstring.

    **Arguments:** `jacobian (M, P)` of the weighted residual; `rss` = $|r|^2$ at the optimum;
    `n_residuals`: how many residuals have positive weight; `free (P,)` bool (default: all);
    `cut`: relative singular value below which a direction counts as null; `row_variance (M,)`:
    the variance of each row of the weighted residual when the noise is told (None: estimated
    from the residual, $\\hat\\sigma^2$); rows past its length (penalty rows) carry no noise.

    **Returns:** `Identifiability`.
    """
    J = np.asarray(jacobian, np.float64)
    n_par = J.shape[1]
    free = np.ones(n_par, bool) if free is None else np.asarray(free, bool)
    dof = max(int(n_residuals) - int(free.sum()), 1)
    sigma2 = float(rss) / dof
    colnorm = np.linalg.norm(J, axis=0)
    Jn = J / np.where(colnorm > 0, colnorm, 1.0)
    se = np.zeros(n_par)
    covariance = np.zeros((n_par, n_par))
    determined = np.ones(n_par, bool)
    free_idx = np.flatnonzero(free)
    sv = None
    if free_idx.size:
        _, svf, vt = np.linalg.svd(Jn[:, free_idx], full_matrices=False)
        if free_idx.size == n_par:
            sv = svf
        null = vt[svf <= cut * max(svf.max(), 1e-300)]
        bad = np.any(np.abs(null) > 1e-6, axis=0) if len(null) else np.zeros(free_idx.size, bool)
        bad |= colnorm[free_idx] == 0
        good = free_idx[~bad]
        if good.size:
            Jg = Jn[:, good]
            inv = np.linalg.pinv(Jg.T @ Jg)
            if row_variance is None:
                cov = sigma2 * inv
            else:
                v = np.asarray(row_variance, np.float64).reshape(-1)
                v = np.pad(v, (0, Jg.shape[0] - v.size))  # rows past the data (penalties) carry no noise
                cov = inv @ (Jg.T @ (v[:, None] * Jg)) @ inv
            se[good] = np.sqrt(np.maximum(np.diag(cov), 0.0)) / colnorm[good]
            covariance[np.ix_(good, good)] = cov / np.outer(colnorm[good], colnorm[good])
        se[free_idx[bad]] = np.inf
        determined[free_idx[bad]] = False
    if sv is None:
        sv = np.linalg.svd(Jn, compute_uv=False)
    return Identifiability(singular_values=sv, std_errors=se, determined=determined, sigma2=sigma2, dof=dof,
                           covariance=covariance)
