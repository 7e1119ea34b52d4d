r"""Statistical comparison of Monte Carlo estimates with exact references.

A renderer's estimate $\hat x_i$ of a quantity with exact value $x_i$ comes with a standard
error $\sigma_i$. Each entry gets a two-sided z test of $H_0: E[\hat x_i] = x_i$,

$$z_i = \operatorname{sign}(d_i)\,\max(|d_i| - \tau_i, 0) / \sigma_i, \qquad d_i = \hat x_i - x_i,$$

where $\tau_i$ = `atol` + `rtol` $\cdot$ scale is a deterministic allowance (float32 round-off of
the renderer, a known bias bound such as a quadrature error of the reference). When $\sigma_i$ was
estimated from $k$ independent batches, pass `dof = k - 1`: the p-values then come from
Student's t distribution. The family of all entries is tested at a stated family-wise error rate
$\alpha$: Holm's step-down procedure (default) or Bonferroni, both valid under any dependence
between the entries (RGB channels that share samples, parameters that share a seed). A
chi-square summary adds power against small biases spread over many entries: the p-values are
mapped back to standard normal scores, averaged over the axes whose entries may be correlated
(`correlated_axes`; the mean of $c$ correlated standard normals has variance at most 1, so the
test stays at or below its level), and $\sum \bar z^2$ is compared with $\chi^2$ on the number of
groups. With `chi2_axis` (derivatives: the parameter axis) each index along that axis gets its
own chi-square (a bias in one parameter is not diluted by the others), combined by Bonferroni
(valid however the parameters' estimates are correlated). With `chi2=True` the z tests run at
$\alpha/2$ and the chi-square test(s) at $\alpha/2$, so the probability of a false alarm is at
most $\alpha$ (Bonferroni over the two tests).

The tests assume each estimate is close to normal around its mean (the central limit theorem at
the sample count used). Derivative estimators whose samples are rare and large (boundary
samples of a projective estimator, a few per pixel) violate that at low sample counts: their
batch means are skewed or even identical across batches. Use batches with many such samples
each, and measure the false-alarm rate of the whole set-up on a case with a known answer
(`benchmarks/gradient_oracle.py` does, for Mitsuba).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

CHANNELS = "RGB"
METHODS = ("holm", "bonferroni")


def _special() -> Any:
    import scipy.special as sp  # ~10x lighter to import than scipy.stats

    return sp


def _two_sided_p(z: np.ndarray, dof: float | None) -> np.ndarray:
    sp = _special()
    a = np.abs(z)
    if dof is None:
        return np.where(np.isinf(a), 0.0, 2.0 * sp.ndtr(-a))
    return np.where(np.isinf(a), 0.0, 2.0 * sp.stdtr(dof, -a))


def _normal_score(p: np.ndarray, z: np.ndarray) -> np.ndarray:
    """The standard normal score with the same two-sided p-value and sign as `z`."""
    sp = _special()
    with np.errstate(divide="ignore"):
        s = np.where(p <= 0.0, np.inf, -sp.ndtri(np.clip(p, 1e-300, 1.0) / 2.0))
    return np.sign(z) * np.maximum(s, 0.0)


def holm_reject(p: np.ndarray, alpha: float) -> np.ndarray:
    """Holm's step-down rejections of a family of p-values (any shape) at family-wise `alpha`."""
    flat = np.asarray(p, dtype=np.float64).ravel()
    m = flat.size
    order = np.argsort(flat, kind="stable")
    thresholds = alpha / (m - np.arange(m))
    ok = flat[order] <= thresholds
    k = m if ok.all() else int(np.argmin(ok))  # first acceptance stops the procedure
    out = np.zeros(m, bool)
    out[order[:k]] = True
    return out.reshape(np.shape(p))


def bonferroni_reject(p: np.ndarray, alpha: float) -> np.ndarray:
    """Bonferroni rejections: `p <= alpha / m`."""
    p = np.asarray(p, dtype=np.float64)
    return p <= alpha / max(p.size, 1)


@dataclass(frozen=True)
class Comparison:
    """The outcome of `compare`: per-entry statistics and the family verdict.

    **Fields:** `estimate`, `stderr`, `reference`, `tolerance` (the deterministic allowance
    $\\tau$), `z` (signed sigmas beyond the allowance), `p_values` (two-sided), `rejected`
    (entries flagged by the multiple test), `chi2`, `chi2_dof`, `chi2_p` (the summary: the
    statistic, degrees of freedom and p-value of each chi-square group, `(G,)` arrays, and the
    Bonferroni-combined p-value `chi2_p_combined`),
    `alpha`, `alpha_z`, `alpha_chi2` (None when the chi-square test is off), `method`, `dof`,
    `what`; properties `labels` (one text label per entry, e.g. "d/d light.tx, point 3, G"),
    `passed`, `chi2_rejected`, `max_abs_z`.
    """

    estimate: np.ndarray
    stderr: np.ndarray
    reference: np.ndarray
    tolerance: np.ndarray
    z: np.ndarray
    p_values: np.ndarray
    rejected: np.ndarray
    chi2: np.ndarray
    chi2_dof: np.ndarray
    chi2_p: np.ndarray
    alpha: float
    alpha_z: float
    alpha_chi2: float | None
    method: str
    dof: float | None
    what: str
    chi2_names: list[str] | None = field(default=None, repr=False)
    given_labels: list[str] | None = field(default=None, repr=False)
    prefix: list[str] | None = field(default=None, repr=False)

    @property
    def labels(self) -> list[str]:
        """One text label per entry (row-major), made when first needed."""
        if self.given_labels is not None:
            return self.given_labels
        return _entry_labels(self.estimate.shape, self.prefix)

    @property
    def chi2_p_combined(self) -> float:
        return float(min(1.0, np.min(self.chi2_p) * self.chi2_p.size))

    @property
    def chi2_rejected(self) -> bool:
        return self.alpha_chi2 is not None and self.chi2_p_combined <= self.alpha_chi2

    @property
    def passed(self) -> bool:
        return not (bool(self.rejected.any()) or self.chi2_rejected)

    @property
    def max_abs_z(self) -> float:
        return float(np.max(np.abs(self.z), initial=0.0))

    def report(self, worst: int = 10) -> str:
        """A readable report: the verdict, the failing entries (worst first) and the chi-square."""
        n = self.z.size
        test = "t" if self.dof is not None else "z"
        head = (
            f"{self.what}: {int(self.rejected.sum())} of {n} entries differ from the exact "
            f"reference ({self.method.capitalize()} over {n} two-sided {test} tests at "
            f"{self.alpha_z:.3g}"
            + (f", dof {self.dof:g}" if self.dof is not None else "")
            + (f"; chi-square at {self.alpha_chi2:.3g}" if self.alpha_chi2 is not None else "")
            + f"; family-wise false-alarm rate <= {self.alpha:.3g})."
        )
        lines = [head]
        flat_z = self.z.ravel()
        bad = np.flatnonzero(self.rejected.ravel())
        order = bad[np.argsort(-np.abs(flat_z[bad]), kind="stable")]
        est, err, ref, tol = (a.ravel() for a in (self.estimate, self.stderr, self.reference, self.tolerance))
        labels = self.labels
        for i in order[:worst]:
            lines.append(
                f"  {labels[i]}: estimate {est[i]:.6g} +- {err[i]:.3g}, reference "
                f"{ref[i]:.6g} (allowance {tol[i]:.2g}): {flat_z[i]:+.1f} sigma "
                f"(p = {self.p_values.ravel()[i]:.2g})"
            )
        if order.size > worst:
            lines.append(f"  ... and {order.size - worst} more")
        stuck = int(np.sum((self.stderr == 0) & np.isinf(self.z)))
        if stuck:
            lines.append(
                f"  ({stuck} of them with standard error 0: a deterministic estimate that disagrees, or "
                "batches that all gave the same value - too few samples per batch for a t test)"
            )
        if not bad.size and n:
            i = int(np.argmax(np.abs(flat_z)))
            lines.append(f"  largest deviation: {labels[i]}: {flat_z[i]:+.2f} sigma")
        verdict = "fails" if self.chi2_rejected else "passes" if self.alpha_chi2 is not None else "not tested"
        parts = []
        for g in range(self.chi2.size):
            name = "" if self.chi2_names is None else f"{self.chi2_names[g]}: "
            parts.append(f"{name}{self.chi2[g]:.4g} on {self.chi2_dof[g]} (p = {self.chi2_p[g]:.3g})")
        combined = f"; Bonferroni p = {self.chi2_p_combined:.3g}" if self.chi2.size > 1 else ""
        lines.append(f"  chi-square summary: {', '.join(parts)}{combined}: {verdict}")
        return "\n".join(lines)

    def __str__(self) -> str:
        return self.report()


def _entry_labels(shape: tuple[int, ...], prefix: Sequence[str] | None = None) -> list[str]:
    """'point 3, G' for (N, 3); 'pixel (1, 2), G' for (R, R, 3); names for a leading axis."""
    labels = []
    rgb = len(shape) >= 2 and shape[-1] == 3
    for idx in np.ndindex(*shape):
        parts = []
        rest = idx
        if prefix is not None:
            parts.append(prefix[idx[0]])
            rest = idx[1:]
        core = rest[:-1] if rgb else rest
        if len(core) == 1:
            parts.append(f"point {core[0]}")
        elif len(core) == 2:
            parts.append(f"pixel ({core[0]}, {core[1]})")
        elif core:
            parts.append(f"entry {core}")
        if rgb:
            parts.append(CHANNELS[rest[-1]])
        labels.append(", ".join(parts) if parts else "value")
    return labels


def _as_float(x: Any, what: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        a = a.reshape(1)
    return a


def compare(
    estimate: Any,
    stderr: Any,
    reference: Any,
    *,
    alpha: float = 1e-3,
    method: str = "holm",
    dof: int | float | None = None,
    rtol: float = 1e-5,
    atol: Any = 0.0,
    scale: Any = None,
    chi2: bool = True,
    correlated_axes: Sequence[int] | None = None,
    labels: Sequence[str] | None = None,
    what: str = "values",
    prefix: Sequence[str] | None = None,
    chi2_axis: int | None = None,
) -> Comparison:
    r"""Test Monte Carlo estimates against exact references (see the module docstring).

    **Arguments:**

    - `estimate`, `stderr`, `reference`: arrays of one shape (or broadcastable to the
      estimate's): the estimates, their standard errors ($\ge 0$; 0 for a deterministic
      estimate), the exact values.
    - `alpha`: family-wise false-alarm rate of the whole comparison (0 < alpha < 1).
    - `method`: `"holm"` (default) or `"bonferroni"`.
    - `dof`: degrees of freedom of the standard errors when they were estimated from few
      independent batches (`k - 1` for `k` batches): Student-t p-values. `None`: normal.
    - `rtol`, `atol`, `scale`: deterministic allowance $\tau$ = `atol` + `rtol` * `scale`
      per entry; `scale` defaults to `|reference|`. `atol` may be an array (e.g. a known bound
      on the reference's quadrature error).
    - `chi2`: also run the chi-square summary test (alpha split in halves).
    - `correlated_axes`: axes along which entries may be correlated (share samples); the
      chi-square averages the normal scores over them. Default: the last axis when the
      arrays have at least two dimensions (RGB channels), else none.
    - `chi2_axis`: an axis (not among `correlated_axes`) whose indices get separate chi-square
      tests, combined by Bonferroni; default None (one test).
    - `labels`: one label per entry (row-major), for the report; or `prefix`: one name per
      index of the leading axis (e.g. parameter names), the rest labelled by position.
    - `what`: what is compared, for the report.

    **Returns:** a `Comparison` (`.passed`, `.report()`).
    """
    if method not in METHODS:
        raise ValueError(f"compare: method must be one of {METHODS}, got {method!r}.")
    if not 0.0 < float(alpha) < 1.0:
        raise ValueError(f"compare: alpha must be in (0, 1), got {alpha!r}.")
    if dof is not None and not float(dof) > 0:
        raise ValueError(f"compare: dof must be > 0, got {dof!r}.")
    est = _as_float(estimate, "estimate")
    try:
        err = np.broadcast_to(_as_float(stderr, "stderr"), est.shape)
        ref = np.broadcast_to(_as_float(reference, "reference"), est.shape)
    except ValueError:
        raise ValueError(
            f"compare: stderr {np.shape(stderr)} and reference {np.shape(reference)} must "
            f"broadcast to the estimate's shape {est.shape}."
        ) from None
    if not np.all(np.isfinite(ref)):
        raise ValueError("compare: the reference must be finite.")
    if np.any(np.isnan(err)) or np.any(err < 0):
        raise ValueError("compare: stderr must be >= 0 (and not NaN).")
    sc = np.abs(ref) if scale is None else np.broadcast_to(_as_float(scale, "scale"), est.shape)
    tol = np.broadcast_to(_as_float(atol, "atol"), est.shape) + float(rtol) * sc
    d = est - ref
    excess = np.sign(d) * np.maximum(np.abs(d) - tol, 0.0)
    excess = np.where(np.isnan(est), np.inf, excess)  # a NaN estimate always fails
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(err > 0, excess / np.where(err > 0, err, 1.0), np.sign(excess) * np.inf)
    z = np.where(excess == 0.0, 0.0, z)
    p = _two_sided_p(z, None if dof is None else float(dof))
    alpha = float(alpha)
    alpha_z = alpha / 2.0 if chi2 else alpha
    rejected = (holm_reject if method == "holm" else bonferroni_reject)(p, alpha_z)

    if correlated_axes is None:
        correlated_axes = (est.ndim - 1,) if est.ndim >= 2 else ()
    axes = tuple(sorted({a % est.ndim for a in correlated_axes}))
    score = _normal_score(p, z)
    if axes:
        infinite = np.isinf(score).any(axis=axes, keepdims=True)
        score = np.where(infinite, np.inf, np.where(np.isinf(score), 0.0, score).mean(axis=axes, keepdims=True))
    if chi2_axis is None:
        groups = score.reshape(1, -1)
    else:
        g = chi2_axis % est.ndim
        if g in axes:
            raise ValueError("compare: chi2_axis cannot be one of the correlated axes.")
        groups = np.moveaxis(score, g, 0).reshape(score.shape[g], -1)
    stat = np.sum(groups**2, axis=1)
    k = np.full(stat.shape, groups.shape[1])
    chi2_p = np.where(np.isfinite(stat), _special().chdtrc(k, np.where(np.isfinite(stat), stat, 0.0)), 0.0)
    if labels is not None and len(labels) != est.size:
        raise ValueError(f"compare: {len(labels)} labels for {est.size} entries.")
    if prefix is not None and (est.ndim == 0 or len(prefix) != est.shape[0]):
        raise ValueError(f"compare: {len(prefix)} prefixes for a leading axis of {est.shape[:1]}.")
    return Comparison(
        estimate=est, stderr=np.array(err), reference=np.array(ref), tolerance=np.array(tol),
        z=z, p_values=p, rejected=rejected, chi2=stat, chi2_dof=k, chi2_p=chi2_p, alpha=alpha,
        alpha_z=alpha_z, alpha_chi2=alpha / 2.0 if chi2 else None, method=method,
        dof=None if dof is None else float(dof), what=what,
        given_labels=None if labels is None else list(labels), prefix=None if prefix is None else list(prefix),
        chi2_names=None if chi2_axis is None or prefix is None or chi2_axis % est.ndim != 0 else list(prefix),
    )


def assert_values_match(
    estimate: Any,
    stderr: Any,
    reference: Any,
    *,
    alpha: float = 1e-3,
    method: str = "holm",
    dof: int | float | None = None,
    rtol: float = 1e-5,
    atol: Any = 0.0,
    chi2: bool = True,
    correlated_axes: Sequence[int] | None = None,
    labels: Sequence[str] | None = None,
    what: str = "values",
) -> Comparison:
    r"""Assert that Monte Carlo estimates agree with exact values (z tests, Holm, chi-square).

    Raises `AssertionError` with a report naming every failing entry (point, channel) and by
    how many standard errors it is off; the probability of raising when the estimator is
    unbiased and its standard errors are right is at most `alpha`.

    **Arguments:** as `compare`: `estimate`, `stderr`, `reference` arrays of one shape (e.g.
    `(N, 3)` irradiance in W/m^2 and its standard error), `alpha` (family-wise false-alarm
    rate), `method` (`"holm"` or `"bonferroni"`), `dof` (Student-t for batch standard errors),
    `rtol` (relative to `|reference|`) and `atol` (absolute, may be an array): deterministic
    allowances, `chi2`, `correlated_axes`, `labels`, `what`.

    **Returns:** the `Comparison` (when it passes).
    """
    res = compare(
        estimate, stderr, reference, alpha=alpha, method=method, dof=dof, rtol=rtol, atol=atol,
        chi2=chi2, correlated_axes=correlated_axes, labels=labels, what=what,
    )
    if not res.passed:
        raise AssertionError(res.report())
    return res


def _stack_parameters(x: Any, names: Sequence[str] | None, what: str) -> tuple[np.ndarray, list[str] | None]:
    if isinstance(x, Mapping):
        keys = list(x) if names is None else list(names)
        missing = [k for k in keys if k not in x]
        if missing:
            raise ValueError(f"assert_gradient_matches: {what} has no entry for {missing}.")
        return np.stack([np.asarray(x[k], dtype=np.float64) for k in keys]), keys
    return np.asarray(x, dtype=np.float64), None if names is None else list(names)


def assert_gradient_matches(
    estimate: Any,
    stderr: Any,
    reference: Any,
    *,
    parameters: Sequence[str] | None = None,
    alpha: float = 1e-3,
    method: str = "holm",
    dof: int | float | None = None,
    rtol: float = 1e-5,
    atol: Any = 0.0,
    chi2: bool = True,
    correlated_axes: Sequence[int] | None = None,
    what: str = "derivatives",
) -> Comparison:
    r"""Assert that Monte Carlo derivative estimates agree with exact derivatives.

    The same test as `assert_values_match` over the whole family (every parameter, point and
    channel), with two differences suited to derivatives: the relative allowance `rtol` is
    taken of the largest `|reference|` of each parameter (a derivative that crosses zero keeps
    a floor), and the report names the parameter of each failing entry.

    **Arguments:**

    - `estimate`, `stderr`, `reference`: either mappings from parameter name to arrays of one
      shape (e.g. `{"light.tx": (N, 3)}`, dE/dt in W/m^2 per metre), or arrays with the
      parameter as the leading axis (`(P, N, 3)`), then named by `parameters`.
    - `parameters`: names (and order) of the parameters; default: the keys of `reference`.
    - `alpha`, `method`, `dof`, `rtol`, `atol`, `chi2`, `what`: as `assert_values_match`.
    - `correlated_axes`: default: the channel axis (arrays of 3 or more dimensions); each
      parameter gets its own chi-square test (Bonferroni over the parameters), so estimates of
      several parameters may share samples.

    **Returns:** the `Comparison` (when it passes).
    """
    if parameters is None and isinstance(reference, Mapping):
        parameters = list(reference)
    ref, names = _stack_parameters(reference, parameters, "reference")
    est, _ = _stack_parameters(estimate, names, "estimate")
    err, _ = _stack_parameters(stderr, names, "stderr") if isinstance(stderr, Mapping) else (
        np.asarray(stderr, dtype=np.float64), None)
    if ref.ndim == 0:
        raise ValueError("assert_gradient_matches: the reference needs a parameter axis.")
    if names is None:
        names = [f"parameter {i}" for i in range(ref.shape[0])]
    if len(names) != ref.shape[0]:
        raise ValueError(f"assert_gradient_matches: {len(names)} parameter names for {ref.shape[0]} parameters.")
    if est.shape != ref.shape:
        raise ValueError(f"assert_gradient_matches: estimate {est.shape} and reference {ref.shape} differ in shape.")
    per_param = np.max(np.abs(ref.reshape(ref.shape[0], -1)), axis=1, initial=0.0)
    scale = np.broadcast_to(per_param.reshape((-1,) + (1,) * (ref.ndim - 1)), ref.shape)
    if correlated_axes is None:
        correlated_axes = (ref.ndim - 1,) if ref.ndim >= 3 else ()
    res = compare(
        est, err, ref, alpha=alpha, method=method, dof=dof, rtol=rtol, atol=atol, scale=scale,
        chi2=chi2, correlated_axes=correlated_axes, prefix=[f"d/d {n}" for n in names], what=what,
        chi2_axis=0,
    )
    if not res.passed:
        raise AssertionError(res.report())
    return res


def false_alarm_bound(trials: int, alpha: float, confidence: float = 0.999) -> int:
    """The largest number of false alarms in `trials` independent comparisons at level `alpha`
    that is still consistent with a false-alarm rate <= `alpha` (one-sided binomial test at
    `1 - confidence`)."""
    sp = _special()
    k = 0
    while k < trials and sp.bdtrc(k, trials, alpha) > 1.0 - confidence:
        k += 1
    return k


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Two-sided Clopper-Pearson interval of a binomial rate `k / n`."""
    sp = _special()
    a = (1.0 - level) / 2.0
    lo = 0.0 if k == 0 else float(sp.betaincinv(k, n - k + 1, a))
    hi = 1.0 if k == n else float(sp.betaincinv(k + 1, n - k, 1.0 - a))
    return lo, hi


__all__ = [
    "Comparison",
    "assert_gradient_matches",
    "assert_values_match",
    "bonferroni_reject",
    "clopper_pearson",
    "compare",
    "false_alarm_bound",
    "holm_reject",
]
