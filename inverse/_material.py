"""Material from painted colours (Poulin §5.3.3-5.3.5): $k_a, k_d, k_s$ and the Phong roughness.

Per RGB channel the shading (Poulin eq. 5.14, DESIGN.md) is linear in the coefficients,

$$ L_c = k_{a,c} L_{a,c} + k_{d,c} E_c/\\pi + k_{s,c} S_c(n), $$

so for a fixed roughness $n$ the weighted least-squares fit with box bounds (Poulin eq. 5.16's
domain constraints; §5.3.5 replaces them by penalties, here they are exact) is a 3-unknown convex
quadratic programme, solved **exactly** by enumerating active sets (every face of the feasible
polytope; the optimum is the unconstrained minimiser of its face). The roughness is found by
variable projection: a 1-D search over $\\log n$ of the projected residual (grid, then a batched
section search in the best bracket), the linear coefficients re-solved exactly at every trial $n$.
"""

from __future__ import annotations

import itertools
import math
import warnings
from typing import Any, no_type_check

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

import jaxshadow as js
from jaxshadow.cli import ensure_default_compile_cache

from ._forward import EngineSpecular, SpecularFn, material_specular
from ._identifiability import identifiability
from ._lm import ONCE_COMPILER_OPTIONS, fit_jit
from ._reports import MaterialFit, MaterialReport, UndeterminedParameterWarning
from ._targets import PaintedTargets

PARAM_NAMES = tuple(f"{k}[{c}]" for k in ("ka", "kd", "ks") for c in "rgb")


# --------------------------------------------------------------------------------------
# Exact bounded linear least squares (3 unknowns, a few linear inequalities)
# --------------------------------------------------------------------------------------


def bounded_lstsq(X: np.ndarray, y: np.ndarray, w: np.ndarray, lo: Any, hi: Any,
                  sum_le_1: bool = False) -> tuple[np.ndarray, float, np.ndarray]:
    """Exact solution of $\\min_k \\sum_i w_i (X_i k - y_i)^2$ s.t. $lo \\le k \\le hi$
    (and $k_1 + k_2 \\le 1$ with `sum_le_1`).

    A convex QP in 3 unknowns: its minimiser is the unconstrained least-squares minimiser of
    the face of the feasible polytope it lies on. Every face is tried (each unknown free, at
    its lower or at its upper bound; with `sum_le_1` also $k_1 + k_2 = 1$ active, eliminated by
    substitution), the free unknowns solved by least squares on unit-norm columns (minimum-norm
    on rank-deficient faces), infeasible candidates dropped, and the lowest objective wins.

    **Arguments:** `X (N, 3)`, `y (N,)`, `w (N,)` >= 0, bounds `(3,)` (or scalars).

    **Returns:** `(k (3,), objective, active (7,) bool)`: active constraints in the order
    `k0>=lo, k0<=hi, k1>=lo, k1<=hi, k2>=lo, k2<=hi, k1+k2<=1`.

    Example:
        ```python
        import numpy as np
        import inverse

        X = np.random.default_rng(0).uniform(0, 1, (10, 3))
        y = X @ np.array([0.2, 0.9, -0.1])
        k, objective, active = inverse.bounded_lstsq(X, y, np.ones(10), 0.0, 1.0)   # k[2] held at 0
        ```
    """
    X = np.asarray(X, np.float64)
    y = np.asarray(y, np.float64)
    sw = np.sqrt(np.asarray(w, np.float64))
    lo = np.broadcast_to(np.asarray(lo, np.float64), (3,))
    hi = np.broadcast_to(np.asarray(hi, np.float64), (3,))
    Xw, yw = X * sw[:, None], y * sw
    tol = 1e-10 * (1.0 + np.maximum(np.abs(lo), np.abs(hi)))
    best_k, best_obj = None, np.inf
    for states in itertools.product((0, 1, 2), repeat=3):  # free, at lower, at upper
        for sum_active in ((False, True) if sum_le_1 else (False,)):
            k = np.array([(0.0, lo[i], hi[i])[st] for i, st in enumerate(states)])
            free = [i for i, st in enumerate(states) if st == 0]
            cols = {i: Xw[:, i] for i in free}
            rhs = yw - Xw[:, [i for i in range(3) if i not in free]] @ k[[i for i in range(3) if i not in free]]
            dep = None  # (dependent index, independent index or None)
            if sum_active:
                if 1 not in free and 2 not in free:
                    if abs(k[1] + k[2] - 1.0) > 1e-12:
                        continue
                elif 1 in free and 2 in free:
                    # k2 = 1 - k1: column k1 becomes X1 - X2, rhs loses X2.
                    cols[1] = Xw[:, 1] - Xw[:, 2]
                    rhs = rhs - Xw[:, 2]
                    del cols[2]
                    dep = (2, 1)
                else:
                    f, g = (1, 2) if 1 in free else (2, 1)
                    k[f] = 1.0 - k[g]
                    del cols[f]
                    rhs = rhs - Xw[:, f] * k[f]
                    dep = (f, None)
            idx = list(cols)
            if idx:
                M = np.stack([cols[i] for i in idx], axis=1)
                sc = np.linalg.norm(M, axis=0)
                sc = np.where(sc > 0, sc, 1.0)
                sol = np.linalg.lstsq(M / sc, rhs, rcond=None)[0] / sc
                k[idx] = sol
            if dep is not None and dep[1] is not None:
                k[dep[0]] = 1.0 - k[dep[1]]
            if not np.all(np.isfinite(k)):
                continue
            if np.any(k < lo - tol) or np.any(k > hi + tol):
                continue
            if sum_le_1 and k[1] + k[2] > 1.0 + 1e-10:
                continue
            r = Xw @ k - yw
            obj = float(r @ r)
            if obj < best_obj:
                best_k, best_obj = k, obj
    if best_k is None:  # pragma: no cover - the all-at-lower vertex is feasible
        raise RuntimeError("bounded_lstsq: no feasible point (bounds inconsistent?)")
    k = np.clip(best_k, lo, hi)
    active = np.zeros(7, bool)
    active[0:6:2] = np.abs(k - lo) <= tol
    active[1:6:2] = np.abs(k - hi) <= tol
    active[6] = sum_le_1 and abs(k[1] + k[2] - 1.0) <= 1e-10
    return k, best_obj, active


# --------------------------------------------------------------------------------------
# The fit
# --------------------------------------------------------------------------------------


def _np(x: Any) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


# Exponents per call of `_spec_eval`: the grid search, the section search (a batch per step) and
# the standard errors all run one compiled program of this batch.
SPEC_CHUNK = 8


@fit_jit(options=ONCE_COMPILER_OPTIONS)
def _spec_eval(specular: Any, scene: Any, targets: PaintedTargets, exponents: Array) -> tuple[Array, Array, Array]:
    """`(S(n), n dS/dn, overflow)` at each of `exponents (SPEC_CHUNK,)`: one program for values
    and derivatives (the derivative's program holds the value's); `overflow` (bool scalar): an
    `EngineSpecular` receiver needed more than its capacity (always False for other functions)."""
    t = targets

    def one(e: Array) -> tuple[Array, Array, Array]:
        if isinstance(specular, EngineSpecular):
            (s, over), (ds, _) = jax.jvp(lambda x: specular.with_overflow(scene, t.points, t.normals, t.eye, x),
                                         (e,), (e,))  # d/dlog n = n d/dn
            return s, ds, over
        s, ds = jax.jvp(lambda x: specular(scene, t.points, t.normals, t.eye, x), (e,), (e,))
        return s, ds, jnp.zeros((), bool)

    val, der, over = jax.vmap(one)(exponents)
    return val, der, jnp.any(over)


class _Basis:
    """Columns of eq. 5.14 at the targets: ambient, $E/\\pi$, and $S(n)$ on demand."""

    def __init__(self, scene: Any, targets: PaintedTargets, specular: SpecularFn | None):
        self.scene, self.targets, self.specular = scene, targets, specular
        n = len(targets)
        self.ambient = np.broadcast_to(_np(scene.ambient), (n, 3)).copy()
        self.diffuse = _np(js.irradiance(scene, targets.points, targets.normals)) / np.pi
        self._cache: dict[float, tuple[np.ndarray, np.ndarray]] = {}

    def spec(self, exponent: float) -> np.ndarray:
        key = float(exponent)
        if key not in self._cache:
            self.spec_many(np.array([key]))
        return self._cache[key][0]

    def spec_many(self, exponents: np.ndarray) -> np.ndarray:
        """`S(n)` at each exponent, `SPEC_CHUNK` at a time (the last chunk padded)."""
        exponents = np.asarray(exponents, np.float64)
        k = -(-len(exponents) // SPEC_CHUNK) * SPEC_CHUNK
        padded = np.concatenate([exponents, np.repeat(exponents[-1:], k - len(exponents))])
        for i in range(0, k, SPEC_CHUNK):
            es = jnp.asarray(padded[i: i + SPEC_CHUNK], dtype=self.targets.points.dtype)
            val, der, over = _spec_eval(self.specular, self.scene, self.targets, es)
            if bool(over):  # the capacity was counted for these receivers: not expected
                raise RuntimeError("fit_material: a receiver's visible region needs more boundary edges than the "
                                   "shadow capacity counted for it.")
            for e, v, d in zip(padded[i: i + SPEC_CHUNK], _np(val), _np(der), strict=True):
                self._cache.setdefault(float(e), (v, d))
        return np.stack([self._cache[float(e)][0] for e in exponents])

    def dspec_dlogn(self, exponent: float) -> np.ndarray:
        key = float(exponent)
        if key not in self._cache:
            self.spec_many(np.array([key]))
        return self._cache[key][1]

    def design(self, c: int, s: np.ndarray | None) -> np.ndarray:
        spec = np.zeros(len(self.ambient)) if s is None else s[:, c]
        return np.stack([self.ambient[:, c], self.diffuse[:, c], spec], axis=1)


class RowsBasis(_Basis):
    r"""`_Basis` from values computed elsewhere: the ambient and $E/\pi$ columns given, $S(n)$ and
    $\partial S/\partial\log n$ from `spec_rows(exponents (k,)) -> [(S (N, 3), dS (N, 3)), ...]`,
    called with at most `chunk` exponents not evaluated yet (`fit_light_and_material`: the light
    fit's own program at the fitted light, `_projected_lm.BasisRows`)."""

    def __init__(self, scene: Any, targets: PaintedTargets, diffuse: np.ndarray, spec_rows: Any, chunk: int):
        self.scene, self.targets, self.specular = scene, targets, None
        self.ambient = np.broadcast_to(_np(scene.ambient), (len(targets), 3)).copy()
        self.diffuse = _np(diffuse)
        self._cache = {}
        self._rows, self._chunk = spec_rows, int(chunk)

    def spec_many(self, exponents: np.ndarray) -> np.ndarray:
        exponents = np.asarray(exponents, np.float64)
        todo = list(dict.fromkeys(float(e) for e in exponents if float(e) not in self._cache))
        for i in range(0, len(todo), self._chunk):
            part = todo[i:i + self._chunk]
            for e, (v, d) in zip(part, self._rows(np.asarray(part)), strict=True):
                self._cache[e] = (_np(v), _np(d))
        return np.stack([self._cache[float(e)][0] for e in exponents])


def _section_search(f: Any, a: float, b: float, fa: float, fb: float, x0: float, f0: float,
                    tol: float) -> float:
    """The minimiser of a unimodal `f` on `[a, b]` to within `tol`: each step evaluates `f` at
    `SPEC_CHUNK` equally spaced interior points (`f(xs (SPEC_CHUNK,)) -> (SPEC_CHUNK,)` values: one
    call of `_spec_eval`'s program) and keeps the two intervals beside the lowest value (ends
    included), so the bracket shrinks by `(SPEC_CHUNK + 1) / 2` per step (golden section: 1.618
    per evaluation, one evaluation per call). `fa`, `fb`: `f` at the ends; `(x0, f0)`: a point
    already evaluated (the grid's best). Returns the evaluated point of lowest value (the first
    of ties)."""
    best_x, best_f = x0, f0
    for x, v in ((a, fa), (b, fb)):
        if v < best_f:
            best_x, best_f = x, v
    while b - a > tol:
        xs = a + (b - a) * np.arange(1, SPEC_CHUNK + 1) / (SPEC_CHUNK + 1)
        fs = np.asarray(f(xs), np.float64)
        pts_x = np.concatenate([[a], xs, [b]])
        pts_f = np.concatenate([[fa], fs, [fb]])
        j = int(np.argmin(pts_f))
        if pts_f[j] < best_f:
            best_x, best_f = float(pts_x[j]), float(pts_f[j])
        lo_j, hi_j = max(j - 1, 0), min(j + 1, SPEC_CHUNK + 1)
        a, b, fa, fb = float(pts_x[lo_j]), float(pts_x[hi_j]), float(pts_f[lo_j]), float(pts_f[hi_j])
    return best_x


def _solve_channels(basis: _Basis, s: np.ndarray | None, y: np.ndarray, w: np.ndarray, lo, hi,
                    sum_le_1: bool) -> tuple[np.ndarray, float, list]:
    ks, total, actives = [], 0.0, []
    for c in range(3):
        k, obj, act = bounded_lstsq(basis.design(c, s), y[:, c], w[:, c], lo, hi, sum_le_1)
        ks.append(k)
        total += obj
        actives.append(act)
    return np.stack(ks, axis=1), total, actives  # k: (3 params, 3 channels)


def _poulin_weights(basis: _Basis, s: np.ndarray | None, k: np.ndarray, n: int) -> np.ndarray:
    """Poulin §5.3.5: targets in shadow (ambient only) x100, diffuse-dominated x10, highlights x1."""
    diff = basis.diffuse * k[1][None, :]
    spec = np.zeros_like(diff) if s is None else s * k[2][None, :]
    lit = basis.diffuse.max(axis=1) > 1e-3 * max(basis.diffuse.max(), 1e-300)
    highlight = spec.sum(axis=1) > 0.1 * diff.sum(axis=1)
    w = np.where(~lit, 100.0, np.where(highlight, 1.0, 10.0))
    return np.broadcast_to(w[:, None], (n, 3)).copy()


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def fit_material(
    scene: Any,
    targets: PaintedTargets,
    *,
    exponent: float | None = None,
    bounds: tuple = (0.0, 1.0),
    kd_plus_ks_le_1: bool = False,
    weighting: str | None = None,
    n_bounds: tuple[float, float] = (1.0, 1e4),
    n_grid: int = 41,
    n_tol: float = 1e-6,
    specular: SpecularFn | None = None,
    warn: bool = True,
    _basis: _Basis | None = None,
) -> MaterialFit:
    """Fit $k_a, k_d, k_s$ (RGB) and optionally the Phong exponent $n$ to painted colours.

    Poulin eq. 5.14 per channel; bounded linear least squares solved exactly (active-set
    enumeration) for the coefficients; variable projection over $\\log n$ (a grid of `n_grid`
    values over `n_bounds`, then `_section_search` in the best bracket down to `n_tol` in
    $\\log n$) for the roughness.

    **Arguments:**

    - `scene`: a `js.Scene` (lights, occluders, ambient) - fixed.
    - `targets`: `PaintedTargets`.
    - `exponent`: `None` to fit $n$; a number to keep it fixed.
    - `bounds`: `(lower, upper)` for every coefficient; scalars or `(3,)` arrays ordered
      `(ka, kd, ks)`.
    - `kd_plus_ks_le_1`: also impose $k_d + k_s \\le 1$ per channel (energy).
    - `weighting`: `None` (the targets' weights) or `"poulin"` (§5.3.5: x100 for targets in
      shadow, x10 diffuse, x1 highlight; multiplied into the targets' weights, classified from
      a first unweighted fit).
    - `n_bounds`, `n_grid`, `n_tol`: the roughness search.
    - `specular`: a callable like `js.specular` (default `js.specular`).
    - `warn`: emit `UndeterminedParameterWarning` for undetermined parameters (the report
      flags them either way).

    **Returns:** `MaterialFit(material, residual (N, 3), report)`.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js
        import inverse

        scene = js.Scene([js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=4.0)], ambient=0.2)
        rng = np.random.default_rng(0)
        points = np.c_[rng.uniform(-0.5, 1.5, (20, 2)), np.zeros(20)]
        normals = np.tile([0.0, 0.0, 1.0], (20, 1))
        eye = np.array([0.5, -2.0, 2.0])
        true = js.Material(ka=0.2, kd=0.6, ks=0.3, exponent=20.0)
        targets = inverse.PaintedTargets(points, normals, js.shade(scene, true, points, normals, eye), eye)
        fit = inverse.fit_material(scene, targets, exponent=20.0)
        print(fit.report)   # k_a, k_d, k_s per channel with standard errors
        ```
    """
    if not isinstance(scene, js.Scene):
        raise ValueError(f"fit_material: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    if not isinstance(targets, PaintedTargets):
        raise ValueError(f"fit_material: targets must be PaintedTargets, got {type(targets).__name__}.")
    ensure_default_compile_cache()  # before the irradiance's compile, not only the fit programs'
    if exponent is not None:
        try:
            e = np.asarray(exponent, dtype=np.float64)
        except (TypeError, ValueError):
            e = np.asarray(np.nan)
        if isinstance(exponent, bool) or e.shape != () or not np.isfinite(e) or e < 0:
            raise ValueError(f"fit_material: exponent must be None (fit it) or a finite number >= 0, got {exponent!r}.")
    if weighting not in (None, "poulin"):
        raise ValueError(f"fit_material: weighting must be None or 'poulin', got {weighting!r}.")
    lo = np.broadcast_to(_np(bounds[0]), (3,))
    hi = np.broadcast_to(_np(bounds[1]), (3,))
    if np.any(lo > hi) or not np.all(np.isfinite(lo)) or not np.all(np.isfinite(hi)):
        raise ValueError(f"fit_material: bounds must be finite with lower <= upper, got {bounds}.")
    if kd_plus_ks_le_1 and lo[1] + lo[2] > 1:
        raise ValueError("fit_material: kd_plus_ks_le_1 is infeasible with the lower bounds.")
    n_lo, n_hi = float(n_bounds[0]), float(n_bounds[1])
    if not (0 < n_lo < n_hi and np.isfinite(n_hi)):
        raise ValueError(f"fit_material: n_bounds must satisfy 0 < lower < upper, got {n_bounds}.")
    fit_n = exponent is None
    # Private `_basis`: the columns at `scene` computed already (`RowsBasis`, `fit_light_and_material`).
    if _basis is not None:
        spec_fn, basis = js.specular if specular is None else specular, _basis
    else:
        spec_fn = material_specular(scene, targets.points, targets.normals) if specular is None else specular
        basis = _Basis(scene, targets, spec_fn)
    y = _np(targets.colours)
    w = _np(targets.weights)
    npts = len(targets)

    def profile(wts: np.ndarray) -> tuple:
        if not fit_n:
            s = None if spec_fn is None else basis.spec(float(exponent))
            k, rss, act = _solve_channels(basis, s, y, wts, lo, hi, kd_plus_ks_le_1)
            return float(exponent), k, rss, act, None, None
        grid = np.exp(np.linspace(np.log(n_lo), np.log(n_hi), n_grid))
        sgrid = basis.spec_many(grid)
        rss_grid = np.array([_solve_channels(basis, s, y, wts, lo, hi, kd_plus_ks_le_1)[1] for s in sgrid])
        i = int(np.argmin(rss_grid))
        t_best = _section_search(
            lambda ts: [_solve_channels(basis, s, y, wts, lo, hi, kd_plus_ks_le_1)[1]
                        for s in basis.spec_many(np.array([math.exp(t) for t in ts]))],
            math.log(grid[max(i - 1, 0)]), math.log(grid[min(i + 1, n_grid - 1)]),
            float(rss_grid[max(i - 1, 0)]), float(rss_grid[min(i + 1, n_grid - 1)]),
            math.log(grid[i]), float(rss_grid[i]), n_tol)
        n_best = math.exp(t_best)
        k, rss, act = _solve_channels(basis, basis.spec(n_best), y, wts, lo, hi, kd_plus_ks_le_1)
        return n_best, k, rss, act, grid, rss_grid

    n_best, k, rss, act, grid, rss_grid = profile(w)
    if weighting == "poulin":
        s0 = None if spec_fn is None else basis.spec(n_best)
        w = w * _poulin_weights(basis, s0, k, npts)
        n_best, k, rss, act, grid, rss_grid = profile(w)

    s = None if spec_fn is None else basis.spec(n_best)
    model = np.stack([basis.design(c, s) @ k[:, c] for c in range(3)], axis=1)
    residual = model - y

    # ---------------- identifiability: Jacobian of the weighted residual
    sw = np.sqrt(w)
    cols = []
    for p in range(3):
        for c in range(3):
            col = np.zeros((npts, 3))
            col[:, c] = basis.design(c, s)[:, p] * sw[:, c]
            cols.append(col.reshape(-1))
    names = list(PARAM_NAMES)
    if fit_n:
        ds = basis.dspec_dlogn(n_best) * k[2][None, :] * sw
        cols.append(ds.reshape(-1))
        names.append("n")
    J = np.stack(cols, axis=1)
    active_names, at_bound = [], np.zeros(len(names), bool)
    for c in range(3):
        ch = "rgb"[c]
        for j, on in enumerate(act[c]):
            if not on:
                continue
            if j < 6:
                pname = ("ka", "kd", "ks")[j // 2]
                active_names.append(f"{pname}[{ch}]{'>=lower' if j % 2 == 0 else '<=upper'}")
                at_bound[(j // 2) * 3 + c] = True
            else:
                active_names.append(f"kd[{ch}]+ks[{ch}]<=1")
    ident = identifiability(J, rss, int(np.count_nonzero(w > 0)), free=~at_bound)
    sigma2, dof = ident.sigma2, ident.dof
    sv_raw = np.linalg.svd(J, compute_uv=False)
    se = {nm: float(v) for nm, v in zip(names, ident.std_errors, strict=True)}
    determined = {nm: bool(ok) for nm, ok in zip(names, ident.determined, strict=True)}

    msgs = []
    n_interval = None
    n_determined = True
    if fit_n:
        se_n = se["n"]  # standard error of log n
        floor = 1e-10 * float(np.sum(w * y * y))
        thr = rss + max(4.0 * sigma2, floor)
        inside = grid[rss_grid <= thr]
        lo_i = float(min(inside.min(), n_best)) if inside.size else n_best
        hi_i = float(max(inside.max(), n_best)) if inside.size else n_best
        n_interval = (lo_i, hi_i)
        reasons = []
        if np.all(k[2] <= lo[2] + 1e-12) and lo[2] == 0:
            reasons.append("k_s = 0 in every channel (no specular contribution)")
        elif lo[2] == 0:
            # Is the specular term significant at all? Refit without it (k_s = 0).
            hi0 = hi.copy()
            hi0[2] = 0.0
            rss0 = _solve_channels(basis, None, y, w, lo, hi0, kd_plus_ks_le_1)[1]
            if rss0 - rss < max(25.0 * sigma2, floor):
                reasons.append(
                    f"the specular term is not significant (it lowers the residual by "
                    f"{(rss0 - rss) / max(sigma2, 1e-300):.3g} sigma^2 < 25)")
        if hi_i >= grid[-1] * (1 - 1e-9) or lo_i <= grid[0] * (1 + 1e-9):
            reasons.append(
                f"the projected residual is flat up to an end of n_bounds (n in [{lo_i:.3g}, {hi_i:.3g}] "
                "fit as well): no target is near the highlight")
        if not determined["n"] or se_n > 0.5:
            reasons.append(f"relative standard error of n is {se_n:.3g}")
        if reasons:
            n_determined = False
            determined["n"] = False
            se["n"] = math.inf if not np.isfinite(se_n) else se_n * n_best
            msgs.append("roughness n is not determined by these targets: " + "; ".join(reasons) + ".")
        else:
            se["n"] = se_n * n_best
    for nm in names[:9]:
        if not determined[nm]:
            msgs.append(f"{nm} is not determined by these targets (its column is zero or "
                        "collinear with others).")
    if warn:
        for msg in msgs:
            warnings.warn(msg, UndeterminedParameterWarning, stacklevel=2)

    met = None
    if targets.tolerance is not None:
        met = np.all(np.abs(residual) <= _np(targets.tolerance), axis=1)
    dt = targets.points.dtype
    material = js.Material(
        ka=jnp.asarray(k[0], dt), kd=jnp.asarray(k[1], dt), ks=jnp.asarray(k[2], dt),
        exponent=jnp.asarray(n_best, dt),
    )
    report = MaterialReport(
        names=tuple(names),
        exponent=float(n_best),
        exponent_fitted=fit_n,
        exponent_determined=n_determined,
        exponent_interval=n_interval,
        determined=determined,
        active_bounds=tuple(active_names),
        singular_values=ident.singular_values,
        singular_values_raw=sv_raw,
        std_errors=se,
        values={**{nm: float(k[j // 3, j % 3]) for j, nm in enumerate(PARAM_NAMES)}, "n": float(n_best)},
        rss=float(rss),
        dof=dof,
        sigma=math.sqrt(sigma2),
        profile_exponents=grid,
        profile_rss=rss_grid,
        weights=w,
        targets_met=met,
        warnings=tuple(msgs),
    )
    return MaterialFit(material=material, residual=residual, report=report)
