r"""Painted targets as a user makes them (Poulin §5.3: painting is approximate): a colour
*range* instead of a colour, and "brighter here than there" relations.

`ColourRange` gives some targets a range $[l, u]$ per channel: their residual is zero inside
and the distance to the range outside (so the fit is pulled in, not to a point).
`Brighter` relates targets by their luminance $Y = 0.2126 R + 0.7152 G + 0.0722 B$ (Rec. 709,
linear RGB): a hinge $\sqrt{w}\max(0, Y_j - Y_i + \text{margin})$ for each pair $(i, j)$ that asks
$Y_i \ge Y_j + \text{margin}$. Both are rows of the weighted residual of `fit_lights`
(`painted_rows`), with the targets' per-channel weights for the ranges.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np

import jaxshadow as js

LUMINANCE = np.array([0.2126, 0.7152, 0.0722])
"""Rec. 709 luminance weights of linear RGB (Mitsuba's `luminance`)."""

_BIG = 1e30  # an absent bound (inf) in the dense arrays: finite in float32 and float64


def _indices(x: Any, what: str, ndim: int) -> np.ndarray:
    a = np.asarray(x)
    if a.size == 0:
        a = a.reshape((0,) * 1 if ndim == 1 else (0, 2))
    if a.ndim != ndim or (ndim == 2 and a.shape[1] != 2):
        raise ValueError(f"{what} must have shape {'(K,)' if ndim == 1 else '(M, 2)'}, got {a.shape}.")
    if a.size and not np.issubdtype(a.dtype, np.integer):
        if not np.all(np.isfinite(a)) or np.any(a != np.round(a)):
            raise ValueError(f"{what} must be integer target indices, got {a.tolist()}.")
    return a.astype(np.int64)


@dataclasses.dataclass(frozen=True, init=False, eq=False)
class ColourRange:
    """Targets painted as a colour range: for target `index[k]`, channel `c`, any colour in
    `[lower[k, c], upper[k, c]]` fits exactly (residual 0), outside it the residual is the
    distance to the range times $\\sqrt{w}$ (the targets' weights). The painted colour of a
    ranged target is not used.

    **Arguments:**

    - `index`: `(K,)` distinct indices into the `PaintedTargets`.
    - `lower`, `upper`: `(K, 3)`, `(K,)` (grey) or scalar, radiance (W m^-2 sr^-1, the units of
      the colours); `-inf` / `inf` for a one-sided range; `lower <= upper`.

    Example:
        ```python
        import inverse

        # targets 3 and 7: anything between 0.2 and 0.3 in every channel; target 9: at least 0.5
        ranges = inverse.ColourRange([3, 7, 9], [0.2, 0.2, 0.5], [0.3, 0.3, float("inf")])
        # inverse.fit_lights(scene, targets, material, ranges=ranges)
        ```
    """

    index: np.ndarray
    lower: np.ndarray
    upper: np.ndarray

    def __init__(self, index: Any, lower: Any, upper: Any):
        idx = _indices(index, "ColourRange: index", 1)
        if len(np.unique(idx)) != len(idx):
            raise ValueError(f"ColourRange: index has repeated targets: {idx.tolist()}.")
        k = len(idx)
        out = []
        for name, x in (("lower", lower), ("upper", upper)):
            a = np.asarray(x, np.float64)
            if a.ndim == 0:
                a = np.full((k, 3), float(a))
            elif a.shape == (k,):
                a = np.repeat(a[:, None], 3, axis=1)
            elif a.shape != (k, 3):
                raise ValueError(f"ColourRange: {name} must be a scalar, (K,) or (K, 3) with K={k}, got {a.shape}.")
            if np.any(np.isnan(a)):
                raise ValueError(f"ColourRange: {name} has NaN.")
            out.append(a)
        lo, hi = out
        if np.any(lo > hi):
            i, c = np.argwhere(lo > hi)[0]
            raise ValueError(f"ColourRange: lower > upper for target {int(idx[i])}, channel {'RGB'[c]}: "
                             f"{lo[i, c]} > {hi[i, c]}.")
        if np.any(lo == np.inf) or np.any(hi == -np.inf):
            raise ValueError("ColourRange: a lower bound of +inf or an upper bound of -inf admits no colour.")
        for name, v in (("index", idx), ("lower", lo), ("upper", hi)):
            object.__setattr__(self, name, v)


@dataclasses.dataclass(frozen=True, init=False, eq=False)
class Brighter:
    """"Brighter here than there": for each pair `(i, j)` of `pairs`, the luminance
    $Y = 0.2126 R + 0.7152 G + 0.0722 B$ of the model at target `i` should be at least that at
    target `j` plus `margin`: a hinge residual $\\sqrt{w}\\,\\max(0, Y_j - Y_i + \\text{margin})$
    (a soft constraint: zero when met).

    **Arguments:**

    - `pairs`: `(M, 2)` target indices `(i, j)`, `i != j`.
    - `weight`: scalar or `(M,)`, >= 0 (the weight of the squared hinge, as a target weight).
    - `margin`: scalar or `(M,)`, radiance (W m^-2 sr^-1) by which `i` should be brighter.

    Example:
        ```python
        import inverse

        relations = inverse.Brighter([[0, 5], [2, 5]], weight=10.0)   # 0 and 2 brighter than 5
        # inverse.fit_lights(scene, targets, material, brighter=relations)
        ```
    """

    pairs: np.ndarray
    weight: np.ndarray
    margin: np.ndarray

    def __init__(self, pairs: Any, weight: Any = 1.0, margin: Any = 0.0):
        p = _indices(pairs, "Brighter: pairs", 2)
        if np.any(p[:, 0] == p[:, 1]):
            i = int(np.argmax(p[:, 0] == p[:, 1]))
            raise ValueError(f"Brighter: pair {i} relates target {int(p[i, 0])} to itself.")
        out = []
        for name, x in (("weight", weight), ("margin", margin)):
            a = np.asarray(x, np.float64)
            a = np.full(len(p), float(a)) if a.ndim == 0 else a
            if a.shape != (len(p),) or not np.all(np.isfinite(a)):
                raise ValueError(f"Brighter: {name} must be a finite scalar or (M,) with M={len(p)}, got {x!r}.")
            out.append(a)
        if np.any(out[0] < 0):
            raise ValueError(f"Brighter: weights must be >= 0, got {out[0].tolist()}.")
        for name, v in (("pairs", p), ("weight", out[0]), ("margin", out[1])):
            object.__setattr__(self, name, v)


class Painting(eqx.Module):
    """The dense form of `ColourRange` and `Brighter` for `n` targets, as the residual uses it:
    `ranged (N, 3)` bool, `lower`, `upper (N, 3)` (absent bounds as +-1e30), `pairs (M, 2)`,
    `pair_sw (M,)` $\\sqrt{w}$, `margin (M,)`."""

    ranged: Any  # a jax array (NumPy in `as_numpy`)
    lower: Any  # a jax array (NumPy in `as_numpy`)
    upper: Any  # a jax array (NumPy in `as_numpy`)
    pairs: Any  # a jax array (NumPy in `as_numpy`)
    pair_sw: Any  # a jax array (NumPy in `as_numpy`)
    margin: Any  # a jax array (NumPy in `as_numpy`)


def painting(n: int, ranges: Any, brighter: Any, dtype: Any) -> Painting | None:
    """`Painting` for `n` targets, or None when neither is given. ValueError for an index out of
    range."""
    if ranges is None and brighter is None:
        return None
    if ranges is not None and not isinstance(ranges, ColourRange):
        raise ValueError(f"fit_lights: ranges must be an inverse.ColourRange, got {type(ranges).__name__}.")
    if brighter is not None and not isinstance(brighter, Brighter):
        raise ValueError(f"fit_lights: brighter must be an inverse.Brighter, got {type(brighter).__name__}.")
    ranged = np.zeros((n, 3), bool)
    lo, hi = np.zeros((n, 3)), np.zeros((n, 3))
    if ranges is not None:
        bad = ranges.index[(ranges.index < 0) | (ranges.index >= n)]
        if bad.size:
            raise ValueError(f"ColourRange: index {int(bad[0])} out of range for {n} targets.")
        ranged[ranges.index] = True
        lo[ranges.index] = np.clip(ranges.lower, -_BIG, _BIG)
        hi[ranges.index] = np.clip(ranges.upper, -_BIG, _BIG)
    pairs, sw, margin = np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0)
    if brighter is not None:
        bad = brighter.pairs[(brighter.pairs < 0) | (brighter.pairs >= n)]
        if bad.size:
            raise ValueError(f"Brighter: index {int(bad[0])} out of range for {n} targets.")
        pairs, sw, margin = brighter.pairs, np.sqrt(brighter.weight), brighter.margin
    return Painting(jnp.asarray(ranged), jnp.asarray(lo, dtype), jnp.asarray(hi, dtype), jnp.asarray(pairs),
                    jnp.asarray(sw, dtype), jnp.asarray(margin, dtype))


def painted_rows(model: Any, colours: Any, sw: Any, paint: Painting | None) -> Any:
    """The weighted residual `(3N + M,)` of a model `(N, 3)`: $\\sqrt{w}(L - C)$ row-major for
    exact targets, $\\sqrt{w}$ times the distance outside the range for ranged ones, then one
    hinge per `Brighter` pair (traceable; NumPy arrays in, NumPy out as well)."""
    xp = jnp if isinstance(model, jnp.ndarray) else np
    d = model - colours
    if paint is None:
        return (sw * d).reshape(-1)
    below, above = model - paint.lower, model - paint.upper
    h = xp.where(below < 0, below, 0.0) + xp.where(above > 0, above, 0.0)
    r = (sw * xp.where(paint.ranged, h, d)).reshape(-1)
    if paint.pairs.shape[0] == 0:
        return r
    y = model @ xp.asarray(LUMINANCE, model.dtype)
    g = y[paint.pairs[:, 1]] - y[paint.pairs[:, 0]] + paint.margin
    return xp.concatenate([r, paint.pair_sw * xp.where(g > 0, g, 0.0)])


def as_numpy(paint: Painting | None) -> Painting | None:
    """`paint` with NumPy (float64) arrays, for the host-side solves."""
    if paint is None:
        return None
    f = lambda x: np.asarray(x, np.float64)  # noqa: E731
    return Painting(np.asarray(paint.ranged), f(paint.lower), f(paint.upper), np.asarray(paint.pairs),
                    f(paint.pair_sw), f(paint.margin))


def _bound_list(a: np.ndarray) -> list:
    """A bound array as JSON (an absent bound, +-inf, as null)."""
    return [[None if not np.isfinite(x) else float(x) for x in row] for row in a]


def save_painted(path: Any, targets: Any, ranges: ColourRange | None = None, brighter: Brighter | None = None) -> None:
    """Write painted targets with their colour ranges and "brighter than" relations to `.json`
    or `.csv` (by the extension), atomically (`jaxshadow.files.atomic_write`).

    JSON: the targets' object (`PaintedTargets.to_dict`) with `"ranges": {"index", "lower",
    "upper"}` (an absent bound as `null`) and `"brighter": {"pairs", "weight", "margin"}`. CSV:
    the targets' columns and `lr lg lb ur ug ub` (empty for a target without a range,
    `inf`/`-inf` for one-sided ranges); then, after an empty line, the relations as `i,j,weight,margin`.

    **Arguments:** `path`; `targets` (`inverse.PaintedTargets`); `ranges`, `brighter` (or None).
    Read back with `load_painted`.

    Example:
        ```python
        import os, tempfile
        import numpy as np
        import inverse

        t = inverse.PaintedTargets(np.zeros((3, 3)), [[0.0, 0.0, 1.0]] * 3, np.full((3, 3), 0.3), [0.0, -3.0, 2.0])
        path = os.path.join(tempfile.mkdtemp(), "painted.json")
        inverse.save_painted(path, t, inverse.ColourRange([1], 0.2, float("inf")), inverse.Brighter([[0, 2]]))
        ```
    """
    import csv
    import json
    import os

    from ._targets import _CSV_REQUIRED, _CSV_TOL, _CSV_WEIGHTS

    n = int(targets.points.shape[0])
    painting(n, ranges, brighter, np.float64)  # index checks
    path = os.fspath(path)
    if not path.lower().endswith(".csv"):
        d = targets.to_dict()
        if ranges is not None:
            d["ranges"] = {"index": ranges.index.tolist(), "lower": _bound_list(ranges.lower),
                           "upper": _bound_list(ranges.upper)}
        if brighter is not None:
            d["brighter"] = {"pairs": brighter.pairs.tolist(), "weight": brighter.weight.tolist(),
                             "margin": brighter.margin.tolist()}
        text = json.dumps(d, indent=1, allow_nan=False)
        with js.files.atomic_write(path) as fh:
            fh.write(text)
        return
    cols = [targets.points, targets.normals, targets.colours, targets.eye, targets.weights]
    header = list(_CSV_REQUIRED) + list(_CSV_WEIGHTS)
    if targets.tolerance is not None:
        cols.append(targets.tolerance)
        header += list(_CSV_TOL)
    table = np.concatenate([np.asarray(c, np.float64) for c in cols], axis=1)
    bounds: list[list[str]] = [[""] * 6 for _ in range(n)]
    if ranges is not None:
        header += list(_CSV_RANGE)
        for i, lo, hi in zip(ranges.index, ranges.lower, ranges.upper, strict=True):
            bounds[int(i)] = [repr(float(x)) for x in (*lo, *hi)]
    with js.files.atomic_write(path, newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        for row, b in zip(table, bounds, strict=True):
            w.writerow([repr(float(x)) for x in row] + (b if ranges is not None else []))
        if brighter is not None:
            w.writerow([])
            w.writerow(list(_CSV_BRIGHTER))
            for (i, j), wt, m in zip(brighter.pairs, brighter.weight, brighter.margin, strict=True):
                w.writerow([int(i), int(j), repr(float(wt)), repr(float(m))])


_CSV_RANGE = ("lr", "lg", "lb", "ur", "ug", "ub")
_CSV_BRIGHTER = ("i", "j", "weight", "margin")


def load_painted(path: Any) -> tuple[Any, ColourRange | None, Brighter | None]:
    """Read a file written by `save_painted` (a plain targets file too).

    **Arguments:** `path` (`.json` or `.csv`).

    **Returns:** `(PaintedTargets, ColourRange or None, Brighter or None)`.

    Example:
        ```python
        import os, tempfile
        import numpy as np
        import inverse

        t = inverse.PaintedTargets(np.zeros((3, 3)), [[0.0, 0.0, 1.0]] * 3, np.full((3, 3), 0.3), [0.0, -3.0, 2.0])
        path = os.path.join(tempfile.mkdtemp(), "painted.csv")
        inverse.save_painted(path, t, ranges=inverse.ColourRange([1], 0.2, 0.4))
        targets, ranges, brighter = inverse.load_painted(path)   # brighter is None
        ```
    """
    import csv
    import io
    import json
    import os
    import tempfile

    from ._targets import PaintedTargets

    path = os.fspath(path)
    if not path.lower().endswith(".csv"):
        with open(path) as fh:
            d = json.load(fh)
        if not isinstance(d, dict):
            raise ValueError(f"{path}: expected a JSON object.")
        r, b = d.pop("ranges", None), d.pop("brighter", None)
        unb = lambda x, s: np.array([[s * np.inf if v is None else v for v in row] for row in x], float)  # noqa: E731
        ranges = None if r is None else ColourRange(r["index"], unb(r["lower"], -1), unb(r["upper"], 1))
        rel = None if b is None else Brighter(np.asarray(b["pairs"]).reshape(-1, 2), b["weight"], b["margin"])
        return PaintedTargets.from_dict(d), ranges, rel
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    split = next((i for i, row in enumerate(rows) if not row), len(rows))
    main, rel_rows = rows[:split], rows[split + 1:]
    header = [h.strip() for h in main[0]] if main else []
    ranged = all(c in header for c in _CSV_RANGE)
    keep = [k for k, h in enumerate(header) if h not in _CSV_RANGE]
    buf = io.StringIO()
    csv.writer(buf).writerows([[row[k] for k in keep] for row in main])
    with tempfile.TemporaryDirectory() as tmp:  # the targets' own reader, on their columns
        p = os.path.join(tmp, "targets.csv")
        with js.files.atomic_write(p, newline="") as fh:
            fh.write(buf.getvalue())
        targets = PaintedTargets.load(p)
    ranges = None
    if ranged:
        at = [header.index(c) for c in _CSV_RANGE]
        idx = [i for i, row in enumerate(main[1:]) if any(row[k].strip() for k in at)]
        vals = np.array([[float(main[1 + i][k]) for k in at] for i in idx], float).reshape(-1, 6)
        ranges = ColourRange(idx, vals[:, :3], vals[:, 3:])
    rel = None
    if rel_rows:
        if [h.strip() for h in rel_rows[0]] != list(_CSV_BRIGHTER):
            raise ValueError(f"{path}: the relations' header must be {','.join(_CSV_BRIGHTER)}, got {rel_rows[0]}.")
        v = np.array([[float(x) for x in row] for row in rel_rows[1:] if row], float).reshape(-1, 4)
        rel = Brighter(v[:, :2].astype(np.int64), v[:, 2], v[:, 3])
    return targets, ranges, rel
