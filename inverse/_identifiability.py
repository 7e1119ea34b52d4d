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

**Quantities** (functions $q(\theta)$ of the parameters, `quantity_error`): with gradient $g$,
unit-column gradient $g_n = D^{-1} g$ and $N$ the null directions above, $q$ is **determined**
when $g_n$ is orthogonal to the null space, $|N g_n| \le$ `ESTIMABLE_TOL` $|g_n|$ (an
estimable function: every parameter vector the targets cannot tell apart gives it the same
value, to first order), however many parameters it involves take part in a null direction (a
polygon's emitted power $p\,s_x s_y$ when its radiance $p$ trades with its size). Its standard
error is $\sqrt{g_n^\top C_n g_n}$, $C_n$ the covariance above over *all* free columns with the
null directions cut (the pseudo-inverse on their complement: `estimable_covariance`), which
for an estimable $q$ does not depend on how the null directions are resolved (Rao, *Linear
Statistical Inference and Its Applications*, 1973, sec. 4a.2: estimable functions of a
rank-deficient linear model). For a parameter, $q = \theta_i$, the test is the rule above (the
projection's norm for its largest component); its standard error above is conditional on the
undetermined parameters (their columns left out), this one marginal over the estimable
directions: the two agree where nothing is undetermined.
"""

from __future__ import annotations

import dataclasses

import numpy as np

ESTIMABLE_TOL = 1e-6  # a quantity's unit-column gradient projected on the null space, relative


@dataclasses.dataclass(frozen=True)
class Identifiability:
    """`singular_values`: of the unit-column Jacobian, all columns; `std_errors (P,)`: in the
    parameters' own units (0 where held fixed, inf where undetermined); `determined (P,)`;
    `sigma2`: the residual variance estimate; `dof`: its degrees of freedom; `covariance (P, P)`:
    the linearised covariance in the parameters' own units (0 in the rows and columns of the
    parameters held fixed or undetermined; `std_errors` is the root of its diagonal elsewhere);
    `free (P,)`: the parameters not held fixed; `null_space (K, P)`: the null directions of the
    unit-column Jacobian over the free columns (unit rows, 0 at the parameters held fixed);
    `column_norms (P,)`: $D$; `estimable_covariance (P, P)`: $C_n$ of the module docstring, in
    unit-column coordinates (0 in the rows and columns of the parameters held fixed)."""

    singular_values: np.ndarray
    std_errors: np.ndarray
    determined: np.ndarray
    sigma2: float
    dof: int
    covariance: np.ndarray
    free: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, bool))
    null_space: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))
    column_norms: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    estimable_covariance: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0)))


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
    null_space = np.zeros((0, n_par))
    est_cov = np.zeros((n_par, n_par))
    v_rows = None if row_variance is None else np.asarray(row_variance, np.float64).reshape(-1)
    if free_idx.size:
        _, svf, vt = np.linalg.svd(Jn[:, free_idx], full_matrices=False)
        if free_idx.size == n_par:
            sv = svf
        is_null = svf <= cut * max(svf.max(), 1e-300)
        null = vt[is_null]
        null_space = np.zeros((len(null), n_par))
        null_space[:, free_idx] = null
        vr, sr = vt[~is_null], svf[~is_null]
        pinv = (vr.T / sr ** 2) @ vr  # (J_n^T J_n)^+ on the complement of the null space
        if v_rows is None:
            cov_n = sigma2 * pinv
        else:
            Jf = Jn[:, free_idx]
            v = np.pad(v_rows, (0, Jf.shape[0] - v_rows.size))  # rows past the data (penalties) carry no noise
            cov_n = pinv @ (Jf.T @ (v[:, None] * Jf)) @ pinv
        est_cov[np.ix_(free_idx, free_idx)] = cov_n
        bad = np.any(np.abs(null) > 1e-6, axis=0) if len(null) else np.zeros(free_idx.size, bool)
        bad |= colnorm[free_idx] == 0
        good = free_idx[~bad]
        if good.size:
            Jg = Jn[:, good]
            inv = np.linalg.pinv(Jg.T @ Jg)
            if v_rows is None:
                cov = sigma2 * inv
            else:
                v = np.pad(v_rows, (0, Jg.shape[0] - v_rows.size))  # rows past the data (penalties) carry no noise
                cov = inv @ (Jg.T @ (v[:, None] * Jg)) @ inv
            se[good] = np.sqrt(np.maximum(np.diag(cov), 0.0)) / colnorm[good]
            covariance[np.ix_(good, good)] = cov / np.outer(colnorm[good], colnorm[good])
        se[free_idx[bad]] = np.inf
        determined[free_idx[bad]] = False
    if sv is None:
        sv = np.linalg.svd(Jn, compute_uv=False)
    return Identifiability(singular_values=sv, std_errors=se, determined=determined, sigma2=sigma2, dof=dof,
                           covariance=covariance, free=free, null_space=null_space,
                           column_norms=colnorm, estimable_covariance=est_cov)


def quantity_error(ident: Identifiability, gradient: np.ndarray, tol: float = ESTIMABLE_TOL) -> tuple[bool, float]:
    """`(determined, standard error)` of a quantity with `gradient (P,)` (d quantity / d
    parameter, in the parameters' own units) by the module docstring's rule; the standard error
    in the quantity's units, inf when not determined. Components at parameters held fixed count
    as known (0)."""
    g = np.asarray(gradient, np.float64).reshape(-1)
    d = ident.column_norms
    gn = np.where(ident.free, g / np.where(d > 0, d, 1.0), 0.0)  # a zero column is a null direction itself
    size = float(np.linalg.norm(gn))
    if size == 0.0:
        return True, 0.0
    if ident.null_space.size and float(np.linalg.norm(ident.null_space @ gn)) > tol * size:
        return False, float("inf")
    return True, float(np.sqrt(max(float(gn @ ident.estimable_covariance @ gn), 0.0)))
