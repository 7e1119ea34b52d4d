"""Painted targets: colours a user paints at scene points (Poulin §5.3, "colour points").

A target set is the data every inverse solver fits: points with their normals, the RGB radiance
painted there, the eye each colour is seen from, per-target weights (Poulin §5.3.5) and an
optional tolerance. It is an equinox Module (a pytree of arrays) with JSON and CSV I/O.
"""

from __future__ import annotations

import csv
import json
import os
from typing import Any

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

import jaxshadow as js

TARGETS_FORMAT = "inverse.targets"
TARGETS_VERSION = 1

_CSV_REQUIRED = ("px", "py", "pz", "nx", "ny", "nz", "r", "g", "b", "ex", "ey", "ez")
_CSV_WEIGHTS = ("wr", "wg", "wb")
_CSV_TOL = ("tr", "tg", "tb")


def _is_concrete(x: Any) -> bool:
    try:
        np.asarray(x)
    except Exception:  # a tracer
        return False
    return True


def _first_bad_row(mask: np.ndarray) -> int:
    return int(np.argwhere(mask.reshape(mask.shape[0], -1).any(axis=1))[0, 0])


def _check_rows(name: str, a: np.ndarray, *, nonneg: bool = False, positive: bool = False) -> None:
    bad = ~np.isfinite(a)
    if bad.any():
        i = _first_bad_row(bad)
        raise ValueError(f"PaintedTargets: {name}[{i}] is not finite: {a[i].tolist()}.")
    if nonneg and (a < 0).any():
        i = _first_bad_row(a < 0)
        raise ValueError(f"PaintedTargets: {name}[{i}] is negative: {a[i].tolist()}.")
    if positive and (a <= 0).any():
        i = _first_bad_row(a <= 0)
        raise ValueError(f"PaintedTargets: {name}[{i}] must be > 0, got {a[i].tolist()}.")


def _unit_rows(v: Array) -> Array:
    """Rows divided by their length. A plain norm where the sum of squares is a normal number
    (so that unit rows come back bit for bit and files round-trip exactly), else scale-free
    (`jaxshadow.safe_normalize`): a normal of length 1e-160 or 1e160 (valid input)
    gave 0/0 = NaN or inf/inf."""
    sq = jnp.sum(v * v, axis=-1, keepdims=True)
    fi = jnp.finfo(v.dtype)
    plain = (sq > fi.tiny) & (sq < fi.max)
    norm = jnp.linalg.norm(jnp.where(plain, v, 1.0), axis=-1, keepdims=True)
    return jnp.where(plain, v / norm, js.safe_normalize(v))


def _per_target_rgb(x: Any, n: int, name: str) -> Array:
    """Broadcast a scalar, `(N,)` or `(N, 3)` per-target quantity to `(N, 3)`."""
    a = x if isinstance(x, jnp.ndarray) else jnp.asarray(x)
    if a.ndim == 0:
        return jnp.broadcast_to(a, (n, 3))
    if a.ndim == 1 and a.shape[0] == n:
        return jnp.broadcast_to(a[:, None], (n, 3))
    if a.ndim == 2 and a.shape == (n, 3):
        return a
    raise ValueError(f"PaintedTargets: {name} must be a scalar, (N,) or (N, 3) with N={n}, got shape {a.shape}.")


class PaintedTargets(eqx.Module):
    """Colours painted at scene points: the data of the inverse problems.

    **Fields:**

    - `points`: `(N, 3)` target points (m).
    - `normals`: `(N, 3)` unit normals (normalised here; zero vectors are an error).
    - `colours`: `(N, 3)` painted RGB radiance (W m^-2 sr^-1, Mitsuba units), >= 0.
    - `eye`: `(N, 3)` eye position each colour is seen from (a `(3,)` eye is broadcast).
    - `weights`: `(N, 3)` least-squares weights (Poulin §5.3.5), >= 0; `None` -> ones,
      `(N,)` -> the same weight for the three channels.
    - `tolerance`: `None` or `(N, 3)` accepted colour error per target (scalar / `(N,)`
      broadcast); reported by the solvers as "targets met", not used by the fit.
    """

    points: Float[Array, "N 3"]
    normals: Float[Array, "N 3"]
    colours: Float[Array, "N 3"]
    eye: Float[Array, "N 3"]
    weights: Float[Array, "N 3"]
    tolerance: Float[Array, "N 3"] | None

    def __init__(self, points: Any, normals: Any, colours: Any, eye: Any, weights: Any = None,
                 tolerance: Any = None):
        arrs = {}
        for name, x in (("points", points), ("normals", normals), ("colours", colours)):
            a = x if isinstance(x, jnp.ndarray) else jnp.asarray(x)
            if a.ndim != 2 or a.shape[-1] != 3:
                raise ValueError(f"PaintedTargets: {name} must have shape (N, 3), got {a.shape}.")
            if not jnp.issubdtype(a.dtype, jnp.floating):
                a = a.astype(jnp.result_type(float))
            arrs[name] = a
        n = arrs["points"].shape[0]
        if n == 0:
            raise ValueError("PaintedTargets: at least one target is needed (N = 0).")
        for name in ("normals", "colours"):
            if arrs[name].shape[0] != n:
                raise ValueError(
                    f"PaintedTargets: {name} has {arrs[name].shape[0]} rows but points has {n}."
                )
        e = eye if isinstance(eye, jnp.ndarray) else jnp.asarray(eye)
        if e.shape == (3,):
            e = jnp.broadcast_to(e, (n, 3))
        elif e.shape != (n, 3):
            raise ValueError(f"PaintedTargets: eye must have shape (3,) or (N, 3) with N={n}, got {e.shape}.")
        dt = arrs["points"].dtype
        w = jnp.ones((n, 3), dt) if weights is None else _per_target_rgb(weights, n, "weights")
        tol = None if tolerance is None else _per_target_rgb(tolerance, n, "tolerance")

        if all(_is_concrete(v) for v in (*arrs.values(), e, w)) and (tol is None or _is_concrete(tol)):
            _check_rows("points", np.asarray(arrs["points"]))
            nn = np.asarray(arrs["normals"])
            _check_rows("normals", nn)
            zero = ~np.any(nn != 0, axis=1)
            if zero.any():
                i = int(np.argmax(zero))
                raise ValueError(f"PaintedTargets: normals[{i}] is the zero vector; a normal needs a direction.")
            _check_rows("colours", np.asarray(arrs["colours"]), nonneg=True)
            _check_rows("eye", np.asarray(e))
            coinc = np.all(np.asarray(e) == np.asarray(arrs["points"]), axis=1)
            if coinc.any():
                i = int(np.argmax(coinc))
                raise ValueError(f"PaintedTargets: eye[{i}] coincides with points[{i}] (no view direction).")
            _check_rows("weights", np.asarray(w), nonneg=True)
            if not np.any(np.asarray(w) > 0):
                raise ValueError("PaintedTargets: every weight is zero; nothing to fit.")
            if tol is not None:
                _check_rows("tolerance", np.asarray(tol), positive=True)
        nrm = arrs["normals"]
        self.points = arrs["points"]
        self.normals = _unit_rows(nrm)
        self.colours = arrs["colours"].astype(dt)
        self.eye = e.astype(dt)
        self.weights = w.astype(dt)
        self.tolerance = None if tol is None else tol.astype(dt)

    def __len__(self) -> int:
        return int(self.points.shape[0])

    @property
    def view_directions(self) -> Array:
        """`(N, 3)` unit vectors from each point to its eye ($\\vec V$ in Poulin eq. 3.12)."""
        return _unit_rows(self.eye - self.points)

    def with_colours(self, colours: Any) -> PaintedTargets:
        """The same targets with other colours (e.g. re-rendered, or with noise added)."""
        return PaintedTargets(self.points, self.normals, colours, self.eye, self.weights, self.tolerance)

    def with_weights(self, weights: Any) -> PaintedTargets:
        """The same targets with other weights."""
        return PaintedTargets(self.points, self.normals, self.colours, self.eye, weights, self.tolerance)

    def subset(self, index: Any) -> PaintedTargets:
        """The targets selected by an index array / boolean mask (NumPy indexing)."""
        idx = np.asarray(index)
        tol = None if self.tolerance is None else self.tolerance[idx]
        return PaintedTargets(self.points[idx], self.normals[idx], self.colours[idx], self.eye[idx],
                              self.weights[idx], tol)

    # ---------------------------------------------------------------- I/O

    def to_dict(self) -> dict:
        """JSON-able dict (schema `inverse.targets`, version 1)."""
        f = lambda x: np.asarray(x, dtype=np.float64).tolist()  # noqa: E731
        d = {
            "format": TARGETS_FORMAT,
            "version": TARGETS_VERSION,
            "points": f(self.points),
            "normals": f(self.normals),
            "colours": f(self.colours),
            "eye": f(self.eye),
            "weights": f(self.weights),
        }
        if self.tolerance is not None:
            d["tolerance"] = f(self.tolerance)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> PaintedTargets:
        """Inverse of `to_dict`; errors name the missing or unknown field."""
        if not isinstance(d, dict):
            raise ValueError("targets: expected a JSON object.")
        if d.get("format", TARGETS_FORMAT) != TARGETS_FORMAT:
            raise ValueError(f"targets: 'format' must be {TARGETS_FORMAT!r}, got {d.get('format')!r}.")
        if d.get("version", TARGETS_VERSION) != TARGETS_VERSION:
            raise ValueError(f"targets: unsupported schema version {d.get('version')!r}.")
        known = {"format", "version", "points", "normals", "colours", "eye", "weights", "tolerance"}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"targets: unknown field(s) {sorted(unknown)}.")
        missing = [k for k in ("points", "normals", "colours", "eye") if k not in d]
        if missing:
            raise ValueError(f"targets: missing field(s) {missing}.")
        g = lambda k: None if d.get(k) is None else np.asarray(d[k], dtype=np.float64)  # noqa: E731
        return cls(g("points"), g("normals"), g("colours"), g("eye"), g("weights"), g("tolerance"))

    def save(self, path: str | os.PathLike) -> None:
        """Write to `.json` or `.csv` (chosen by the extension), through
        `jaxshadow.files.atomic_write`: a failure (serialiser, full disk) leaves an existing
        file as it was."""
        path = os.fspath(path)
        if path.lower().endswith(".csv"):
            cols = [self.points, self.normals, self.colours, self.eye, self.weights]
            header = list(_CSV_REQUIRED) + list(_CSV_WEIGHTS)
            if self.tolerance is not None:
                cols.append(self.tolerance)
                header += list(_CSV_TOL)
            table = np.concatenate([np.asarray(c, dtype=np.float64) for c in cols], axis=1)
            with js.files.atomic_write(path, newline="") as fh:
                w = csv.writer(fh)
                w.writerow(header)
                for row in table:
                    w.writerow([repr(float(x)) for x in row])
        else:
            text = json.dumps(self.to_dict(), indent=1)
            with js.files.atomic_write(path) as fh:
                fh.write(text)

    @classmethod
    def load(cls, path: str | os.PathLike) -> PaintedTargets:
        """Read a `.json` or `.csv` file written by `save` (or by hand, same columns).

        CSV columns: `px py pz nx ny nz r g b ex ey ez` required; `wr wg wb` (or a single
        `w`) and `tr tg tb` (or a single `t`) optional.
        """
        path = os.fspath(path)
        if not path.lower().endswith(".csv"):
            with open(path) as fh:
                return cls.from_dict(json.load(fh))
        with open(path, newline="") as fh:
            rows = list(csv.reader(fh))
        if not rows:
            raise ValueError(f"{path}: empty CSV file.")
        header = [h.strip() for h in rows[0]]
        missing = [c for c in _CSV_REQUIRED if c not in header]
        if missing:
            raise ValueError(f"{path}: missing CSV column(s) {missing} (header: {header}).")
        known = set(_CSV_REQUIRED) | set(_CSV_WEIGHTS) | set(_CSV_TOL) | {"w", "t"}
        unknown = [c for c in header if c not in known]
        if unknown:
            raise ValueError(f"{path}: unknown CSV column(s) {unknown}.")
        data = []
        for i, row in enumerate(rows[1:]):
            if len(row) != len(header):
                raise ValueError(f"{path}: row {i} has {len(row)} fields, the header has {len(header)}.")
            try:
                data.append([float(x) for x in row])
            except ValueError:
                raise ValueError(f"{path}: row {i} has a non-numeric field: {row}.") from None
        table = np.asarray(data, dtype=np.float64).reshape(-1, len(header))
        col = lambda names: table[:, [header.index(c) for c in names]]  # noqa: E731
        weights = col(_CSV_WEIGHTS) if all(c in header for c in _CSV_WEIGHTS) else (
            col(("w",))[:, 0] if "w" in header else None)
        tol = col(_CSV_TOL) if all(c in header for c in _CSV_TOL) else (
            col(("t",))[:, 0] if "t" in header else None)
        return cls(col(_CSV_REQUIRED[0:3]), col(_CSV_REQUIRED[3:6]), col(_CSV_REQUIRED[6:9]),
                   col(_CSV_REQUIRED[9:12]), weights, tol)


def load_targets(path: str | os.PathLike) -> PaintedTargets:
    """Read painted targets from `.json` or `.csv` (see `PaintedTargets.load`).

    Example:
        ```python
        import os, tempfile
        import numpy as np
        import inverse

        path = os.path.join(tempfile.mkdtemp(), "targets.json")
        inverse.save_targets(inverse.PaintedTargets(np.zeros((1, 3)), [[0.0, 0.0, 1.0]], [[0.2, 0.3, 0.4]],
                                                    eye=[0.0, -1.0, 1.0]), path)
        targets = inverse.load_targets(path)
        ```
    """
    return PaintedTargets.load(path)


def save_targets(targets: PaintedTargets, path: str | os.PathLike) -> None:
    """Write painted targets to `.json` or `.csv` (see `PaintedTargets.save`).

    Example:
        ```python
        import os, tempfile
        import numpy as np
        import inverse

        t = inverse.PaintedTargets(np.zeros((1, 3)), [[0.0, 0.0, 1.0]], [[0.2, 0.3, 0.4]], eye=[0.0, -1.0, 1.0])
        inverse.save_targets(t, os.path.join(tempfile.mkdtemp(), "targets.json"))
        ```
    """
    targets.save(path)
