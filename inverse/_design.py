r"""Where to paint targets: choose receivers from a pool so that `fit_lights`' report would give
small standard errors (an experimental design from the report's own Jacobian).

At a scene (the lights as currently estimated), every candidate receiver $i$ has the rows
$J_i$ `(3, P)` of the report's Jacobian (`_multilight.report_parts`: each fitted light's pose
parameters, then its power as a factor of its given radiance). With noise of relative size
$\eta$ on the painted colours, `fit_lights`' report gives, for targets $T$, the covariance
$\hat\sigma^2 (J_T^\top J_T)^{-1}$ with $\hat\sigma^2 = \eta^2 \overline{L^2}$ (the mean
square colour over $T$). The design adds candidates one at a time, each the one that most
lowers $\sum_k (\mathrm{se}_k / \mathrm{tol}_k)^2$ (a weighted A-optimal criterion; the
$3 \times 3$ Woodbury update for every candidate at once), from a small ridge so that the
first picks are defined.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax.numpy as jnp
import numpy as np

import jaxshadow as js
from jaxshadow import traced

from ._multilight import LightsProblem, fixed_contribution, report_parts
from ._parametrisation import LightParametrisation, scene_size
from ._targets import PaintedTargets

_POSITION_NAMES = ("x", "y", "z", "a", "b")


@dataclasses.dataclass(frozen=True)
class TargetDesign:
    """`indices (n,)` into the candidates, in the order chosen; `points`, `normals` `(n, 3)`;
    `names` of the parameters; `std_errors`: name -> the standard error `fit_lights`' report
    would give at the design scene with noise `noise` (positions in m, rotations in rad, log
    sizes, powers as relative factors); `pool_std_errors`: the same with every candidate."""

    indices: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    names: tuple
    std_errors: dict
    pool_std_errors: dict


def candidate_jacobian(scene: js.Scene, material: js.Material, points: Any, normals: Any, eye: Any,
                       lights: Any = None, fit: tuple = ("position", "orientation", "size", "power"),
                       size: float | None = None) -> tuple[np.ndarray, np.ndarray, tuple, np.ndarray]:
    """The report's Jacobian rows at `scene` for receivers `points`, `normals` `(K, 3)`.

    **Returns:** `(J (K, 3, P), colours (K, 3), names (P,), scales (P,))`: the model's derivative
    in every fitted light's pose parameters (positions in units of the scene size, the `scales`)
    and power (as a factor of the light's radiance in `scene`), and the model's colours.
    """
    from ._fit_lights import _groups_for

    pts = np.asarray(points, np.float64)
    nrm = np.asarray(normals, np.float64)
    nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    t = PaintedTargets(pts, nrm, np.zeros_like(pts), np.asarray(eye, np.float64))
    idx = list(range(len(scene.lights))) if lights is None else [int(i) for i in lights]
    s = scene_size(scene, t) if size is None else float(size)
    params, offsets, off = [], [], 0
    for i in idx:
        groups = _groups_for(scene.lights[i], fit)
        params.append(LightParametrisation(scene.lights[i], i, groups, None, s, "sigmoid") if groups else None)
        offsets.append(off)
        off += 0 if params[-1] is None else params[-1].size
    with_spec = bool(np.any(np.asarray(material.ks) != 0))
    fixed = [light for k, light in enumerate(scene.lights) if k not in idx]
    e0, s0 = fixed_contribution(scene, t, material, fixed, None, with_spec)
    cap = None
    if scene.occluders is not None:
        cap = max(8, -(-5 * traced.shadow_capacity(scene, t.points, t.normals,
                                                    lights=[scene.lights[i] for i in idx]) // 4) + 4)
    problem = LightsProblem(tuple(params), tuple(scene.lights[i] for i in idx), scene, material, t, e0, s0,
                            tuple(offsets), "power" in fit, with_spec, bool(fixed), None, capacity=cap,
                            active=jnp.ones(len(idx)))
    ones = jnp.ones(len(idx))
    E, S, Jth = (np.asarray(x, np.float64) for x in report_parts(problem, jnp.zeros(off), ones, material))
    kd, ks = np.asarray(material.kd, np.float64), np.asarray(material.ks, np.float64)
    names, scales = [], []
    for j, p in enumerate(params):
        if p is not None:
            names += [f"light{idx[j]}.{nm}" for nm in p.names]
            scales += [s if nm in _POSITION_NAMES else 1.0 for nm in p.names]
    cols = [Jth]
    if "power" in fit:
        for j in range(len(idx)):
            names.append(f"light{idx[j]}.power")
            scales.append(1.0)
            cols.append((kd / np.pi * E[j] + (ks * S[j] if with_spec else 0.0)).reshape(-1, 1))
    jac = np.concatenate(cols, axis=1).reshape(pts.shape[0], 3, -1)
    ka = np.asarray(material.ka, np.float64)
    La = np.asarray(scene.ambient, np.float64)
    colours = ka * La + kd / np.pi * (np.asarray(e0) + E.sum(axis=0))
    if with_spec:
        colours = colours + ks * (np.asarray(s0) + S.sum(axis=0))
    return jac, colours, tuple(names), np.asarray(scales)


def predicted_std_errors(jac: np.ndarray, colours: np.ndarray, noise: float) -> np.ndarray:
    """`(P,)` the report's standard errors (in the Jacobian's parameter units) for targets with
    Jacobian rows `jac (n, 3, P)` and colours `(n, 3)` under relative noise `noise`."""
    J = jac.reshape(-1, jac.shape[-1])
    sigma2 = noise**2 * float(np.mean(colours**2))
    return np.sqrt(np.maximum(np.diag(sigma2 * np.linalg.pinv(J.T @ J)), 0.0))


def design_targets(scene: js.Scene, material: js.Material, candidates: tuple, n: int, eye: Any, *,
                   lights: Any = None, fit: tuple = ("position", "orientation", "size", "power"),
                   noise: float = 0.01, tolerances: dict | None = None, size: float | None = None,
                   keep: Any = None) -> TargetDesign:
    """Choose `n` of the candidate receivers where painted targets would determine the lights of
    `scene` best (module docstring): the report's standard errors at `scene`, weighted by
    `tolerances`, summed in squares, lowered greedily.

    **Arguments:**

    - `scene`: the lights as estimated (e.g. a first fit's `LightsFit.scene`) with occluders and
      ambient; `material`; `candidates`: `(points (K, 3), normals (K, 3))` where targets could
      be painted; `n` (<= K); `eye (3,)`.
    - `lights`, `fit`: as in `fit_lights`.
    - `noise`: the painted colours' relative noise (scales the standard errors, not the choice).
    - `tolerances`: the wanted standard error per group, `{"position": m, "orientation": rad,
      "size": log factor, "power": relative}` (default: 0.3 % of the scene size, 0.3 deg, 1 %,
      0.6 %: a third of the acceptance of `benchmarks/fit_lights.py`).
    - `size`: the scene size (m) the positions are measured in (default `scene_size`).
    - `keep`: indices of candidates that are targets already (chosen first).

    **Returns:** `TargetDesign`.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js
        import inverse

        scene = js.Scene([js.PointLight([0.3, -0.2, 1.5], 4.0)], ambient=0.05)
        material = js.Material(ka=0.2, kd=0.6, ks=0.0, exponent=1.0)
        rng = np.random.default_rng(0)
        pool = np.c_[rng.uniform(-2.0, 2.0, (60, 2)), np.zeros(60)]
        up = np.tile([0.0, 0.0, 1.0], (60, 1))
        design = inverse.design_targets(scene, material, (pool, up), 12, np.array([0.0, -3.0, 2.0]),
                                        fit=("position", "power"))
        assert design.points.shape == (12, 3)
        ```
    """
    pts, nrm = (np.asarray(x, np.float64) for x in candidates)
    if pts.ndim != 2 or pts.shape[1] != 3 or nrm.shape != pts.shape:
        raise ValueError(f"design_targets: candidates must be (points (K, 3), normals (K, 3)), got {pts.shape}, "
                         f"{nrm.shape}.")
    if not 1 <= int(n) <= pts.shape[0]:
        raise ValueError(f"design_targets: n must be in 1..{pts.shape[0]} (the candidates), got {n}.")
    if not noise > 0:
        raise ValueError(f"design_targets: noise must be > 0, got {noise}.")
    jac, colours, names, scales = candidate_jacobian(scene, material, pts, nrm, eye, lights, fit, size)
    s = float(scales.max()) if size is None else float(size)
    tol = {"position": 0.003 * s, "orientation": np.radians(0.3), "size": 0.01, "power": 0.006}
    tol.update(tolerances or {})
    group = {"x": "position", "y": "position", "z": "position", "a": "position", "b": "position",
             "rx": "orientation", "ry": "orientation", "rz": "orientation", "ru": "orientation",
             "rv": "orientation", "log_sx": "size", "log_sy": "size", "log_length": "size", "power": "power"}
    w = np.array([1.0 / (tol[group[nm.split(".", 1)[1]]] / sc) ** 2 for nm, sc in zip(names, scales, strict=True)])
    K, _, P = jac.shape
    chosen = [int(i) for i in (keep if keep is not None else [])]
    A = np.zeros((P, P))
    for i in chosen:
        A += jac[i].T @ jac[i]
    ridge = 1e-8 * np.einsum("kcp,kcp->p", jac, jac) / K
    A += np.diag(ridge)
    sq = list(np.sum(colours[chosen] ** 2, axis=1)) if chosen else []
    left = np.setdiff1d(np.arange(K), chosen)
    while len(chosen) < int(n):
        M = np.linalg.inv(A)
        U = jac[left]  # (L, 3, P)
        UM = U @ M  # (L, 3, P)
        C = np.eye(3)[None] + UM @ np.swapaxes(U, 1, 2)  # (L, 3, 3)
        # trace(W M_new) = trace(W M) - trace(W M U^T C^-1 U M)
        X = np.linalg.solve(C, UM)  # (L, 3, P)
        drop = np.einsum("lcp,p,lcp->l", UM, w, X)
        tr = float(np.sum(w * np.diag(M))) - drop
        sig = (np.sum(sq) + np.sum(colours[left] ** 2, axis=1)) / (3 * (len(chosen) + 1))
        best = int(np.argmin(sig * tr))
        i = int(left[best])
        chosen.append(i)
        sq.append(float(np.sum(colours[i] ** 2)))
        A += jac[i].T @ jac[i]
        left = np.delete(left, best)
    ix = np.asarray(chosen)
    se = predicted_std_errors(jac[ix], colours[ix], noise) * scales
    se_pool = predicted_std_errors(jac, colours, noise) * scales
    return TargetDesign(indices=ix, points=pts[ix], normals=nrm[ix] / np.linalg.norm(nrm[ix], axis=1, keepdims=True),
                        names=names, std_errors=dict(zip(names, se.tolist(), strict=True)),
                        pool_std_errors=dict(zip(names, se_pool.tolist(), strict=True)))
