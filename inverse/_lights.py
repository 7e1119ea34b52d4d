"""Light placement from painted colours: nonlinear least squares with a vectorised multistart.

A polygon light is moved as a rigid body and stretched in its own plane: centre $c$, rotation
vector $\\omega$ (Rodrigues) applied to its initial frame, and log-scales $(s_x, s_y)$ of its
initial width and height (any convex polygon, a quad being the usual case). A segment light: its
midpoint, its direction (two rotation angles about axes perpendicular to it) and its log length.
A point light: its position. Positions are measured in units of the scene size so every
parameter is O(1) for the solver.

The residual is $\\sqrt{w}\\,(L_{model} - L_{painted})$ with the model of `js.shade` (Poulin
eq. 5.14; soft shadows included when the scene has occluders). Multistart (Campbell & Fussell
§4.4.2): the starting points stratify the search region (a scrambled Sobol sequence, one point
per cell of a coarse grid in the limit), all solved at once; the lowest residual wins.

Solvers. The default is a Levenberg-Marquardt written for this batch (`inverse/_lm.py`): one
forward-mode Jacobian per iteration for all starts, and each receiver sees only the occluders
that can shadow it (`jaxshadow._bsp` culling at a static capacity chosen from the starting
lights; if the light moves so that some receiver needs more, the solve is repeated with a
larger capacity, so the result is always that of the full model). `optimistix.LevenbergMarquardt`
under `jax.vmap` (`solver="optimistix"`) fits the same residual with the full model; it traces the
shadow kernel several times and transposes its linearisation, which made it ~35 s to compile and
per-start vmapped branches evaluate both sides (`benchmarks/inverse_speed.py` measures both).
Bounded L-BFGS-B (JAXopt, `inverse/_jaxopt.py`) is the alternative with hard box bounds.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, Float

import jaxshadow as js
from jaxshadow._clip_host import _pinned as _pinned_array
from jaxshadow._clip_host import compiled_available, relevant_counts

from ._forward import SpecularFn, irradiance_culled, shade, shade_culled, specular_culled
from ._lm import HOST_FIT_COMPILER_OPTIONS, LMResult, batched_levenberg_marquardt, fit_jit
from ._targets import PaintedTargets

FIT_GROUPS = ("position", "orientation", "size")


class Plane(eqx.Module):
    """Constrain the light centre to a plane (a ceiling): `point (3,)`, `normal (3,)`."""

    point: Float[Array, "3"]
    normal: Float[Array, "3"]

    def __init__(self, point: Any, normal: Any):
        p = np.asarray(point, np.float64)
        n = np.asarray(normal, np.float64)
        if p.shape != (3,) or n.shape != (3,) or not (np.all(np.isfinite(p)) and np.all(np.isfinite(n))):
            raise ValueError(f"Plane: point and normal must be finite 3-vectors, got {p.tolist()}, {n.tolist()}.")
        if np.linalg.norm(n) == 0:
            raise ValueError("Plane: the normal is the zero vector.")
        self.point = jnp.asarray(p)
        self.normal = jnp.asarray(n / np.linalg.norm(n))


class Box(eqx.Module):
    """Constrain the light centre to an axis-aligned box `lower (3,) <= c <= upper (3,)`."""

    lower: Float[Array, "3"]
    upper: Float[Array, "3"]

    def __init__(self, lower: Any, upper: Any):
        lo = np.asarray(lower, np.float64)
        hi = np.asarray(upper, np.float64)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
            raise ValueError("Box: lower and upper must be finite 3-vectors.")
        if np.any(hi <= lo):
            raise ValueError(f"Box: need lower < upper in every axis, got {lo.tolist()} and {hi.tolist()}.")
        self.lower = jnp.asarray(lo)
        self.upper = jnp.asarray(hi)


# --------------------------------------------------------------------------------------
# Parametrisation
# --------------------------------------------------------------------------------------


def _rodrigues_coefficients(omega: Float[Array, "3"]) -> tuple[Array, Array]:
    """$a = \\sin t / t$, $b = (1 - \\cos t)/t^2$ with $t = |\\omega|$; smooth (and NaN-free in
    their derivatives) at $\\omega = 0$ via a double `where` onto the Taylor series."""
    t2 = jnp.sum(omega * omega)
    small = t2 < 1e-8
    t2s = jnp.where(small, 1.0, t2)
    t = jnp.sqrt(t2s)
    a = jnp.where(small, 1.0 - t2 / 6.0 + t2 * t2 / 120.0, jnp.sin(t) / t)
    b = jnp.where(small, 0.5 - t2 / 24.0 + t2 * t2 / 720.0, (1.0 - jnp.cos(t)) / t2s)
    return a, b


def rotation_matrix(omega: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Rodrigues: the rotation by angle $|\\omega|$ about $\\omega$, $I + aK + bK^2$
    (`_rodrigues_coefficients`; smooth at $\\omega = 0$)."""
    a, b = _rodrigues_coefficients(omega)
    K = jnp.array([[0.0, -omega[2], omega[1]], [omega[2], 0.0, -omega[0]], [-omega[1], omega[0], 0.0]],
                  dtype=omega.dtype)
    return jnp.eye(3, dtype=omega.dtype) + a * K + b * (K @ K)


def _cross_rows(o: Float[Array, "3"], w: Float[Array, "K 3"]) -> Float[Array, "K 3"]:
    """$\\omega \\times w_i$ for each row, elementwise (no `jnp.cross`, no dot)."""
    wx, wy, wz = w[:, 0], w[:, 1], w[:, 2]
    return jnp.stack([o[1] * wz - o[2] * wy, o[2] * wx - o[0] * wz, o[0] * wy - o[1] * wx], axis=-1)


def rotate_rows(omega: Float[Array, "3"], w: Float[Array, "K 3"]) -> Float[Array, "K 3"]:
    """`w @ rotation_matrix(omega).T`, as $w + a\\,\\omega\\times w + b\\,\\omega\\times(\\omega\\times w)$
    in elementwise operations: inside a fit this runs under `jvp` and the batching of the
    tangents, where matrix products of 3-vectors compile to one small kernel each
    (benchmarks/README.md, Session 7)."""
    a, b = _rodrigues_coefficients(omega)
    c1 = _cross_rows(omega, w)
    return w + a * c1 + b * _cross_rows(omega, c1)


def _frame(light: Any) -> tuple[np.ndarray, np.ndarray]:
    """Centre and orthonormal frame (columns u, v, normal) of a polygon light."""
    v = np.asarray(light.vertices, np.float64)
    c = v.mean(axis=0)
    nrm = np.sum(np.cross(v, np.roll(v, -1, axis=0)), axis=0)
    nrm /= np.linalg.norm(nrm)
    e = v[1] - v[0]
    u = e - (e @ nrm) * nrm
    u /= np.linalg.norm(u)
    return c, np.stack([u, np.cross(nrm, u), nrm], axis=1)


def _perp_basis(d: np.ndarray) -> np.ndarray:
    a = np.eye(3)[int(np.argmin(np.abs(d)))]
    u = np.cross(d, a)
    u /= np.linalg.norm(u)
    return np.stack([u, np.cross(d, u)], axis=0)  # (2, 3)


class LightParametrisation(eqx.Module):
    """Flat parameter vector <-> light, for one light of a scene. Built by `fit_light`.

    `names` lists the parameters; positions are in units of `scale` (m) relative to the
    reference (or the plane origin / box), rotations in radians, sizes as log factors.
    """

    kind: str = eqx.field(static=True)
    fit: tuple = eqx.field(static=True)
    constraint: str = eqx.field(static=True)
    box_map: str = eqx.field(static=True)  # "sigmoid" (LM) or "affine" (L-BFGS-B bounds)
    light_index: int = eqx.field(static=True)
    names: tuple = eqx.field(static=True)
    template: Any
    c0: Array
    frame0: Array
    local: Array
    scale: Array
    plane_e: Array
    box_lo: Array
    box_hi: Array

    def __init__(self, light: Any, light_index: int, fit: tuple, constraint: Any, scale: float,
                 box_map: str):
        self.light_index = light_index
        self.fit = tuple(g for g in FIT_GROUPS if g in fit)
        self.box_map = box_map
        self.template = light
        self.scale = jnp.asarray(scale)
        if isinstance(light, js.PolygonLight):
            self.kind = "polygon"
            c, R = _frame(light)
            self.local = jnp.asarray((np.asarray(light.vertices, np.float64) - c) @ R)
            self.frame0 = jnp.asarray(R)
        elif isinstance(light, js.LinearLight):
            self.kind = "linear"
            a, b = np.asarray(light.start, np.float64), np.asarray(light.end, np.float64)
            c = 0.5 * (a + b)
            d = (b - a) / np.linalg.norm(b - a)
            self.frame0 = jnp.asarray(np.concatenate([_perp_basis(d), d[None]], axis=0))  # rows u, v, d
            self.local = jnp.asarray(np.linalg.norm(b - a))
        elif isinstance(light, js.PointLight):
            self.kind = "point"
            c = np.asarray(light.position, np.float64)
            self.frame0 = jnp.asarray(np.eye(3))
            self.local = jnp.asarray(np.zeros(()))
            bad = [g for g in self.fit if g != "position"]
            if bad:
                raise ValueError(f"fit_light: a point light has only a position; cannot fit {bad}.")
        else:
            raise ValueError(
                f"fit_light: light {light_index} is a {type(light).__name__}; only PolygonLight, "
                "LinearLight and PointLight can be placed."
            )
        # Host arrays put on the device (eager jnp.zeros/ones would compile one op each).
        self.box_lo = jnp.asarray(np.zeros(3))
        self.box_hi = jnp.asarray(np.ones(3))
        self.plane_e = jnp.asarray(np.zeros((2, 3)))
        if constraint is None:
            self.constraint = "none"
        elif isinstance(constraint, Plane):
            self.constraint = "plane"
            m = np.asarray(constraint.normal)
            p0 = np.asarray(constraint.point)
            c = c - ((c - p0) @ m) * m  # project the reference centre onto the plane
            self.plane_e = jnp.asarray(_perp_basis(m))
        elif isinstance(constraint, Box):
            self.constraint = "box"
            self.box_lo = constraint.lower
            self.box_hi = constraint.upper
            c = np.clip(c, np.asarray(constraint.lower), np.asarray(constraint.upper))
        else:
            raise ValueError(f"fit_light: constraint must be None, Plane or Box, got {type(constraint).__name__}.")
        self.c0 = jnp.asarray(c)
        names = []
        if "position" in self.fit:
            names += ["a", "b"] if self.constraint == "plane" else ["x", "y", "z"]
        if "orientation" in self.fit:
            names += ["rx", "ry", "rz"] if self.kind == "polygon" else ["ru", "rv"]
        if "size" in self.fit:
            names += ["log_sx", "log_sy"] if self.kind == "polygon" else ["log_length"]
        if not names:
            raise ValueError(f"fit_light: nothing to fit; fit must be a non-empty subset of {FIT_GROUPS}.")
        self.names = tuple(names)

    @property
    def size(self) -> int:
        return len(self.names)

    def _slices(self) -> dict:
        out, i = {}, 0
        for g in self.fit:
            k = {"position": 2 if self.constraint == "plane" else 3,
                 "orientation": 3 if self.kind == "polygon" else 2,
                 "size": 2 if self.kind == "polygon" else 1}[g]
            out[g] = slice(i, i + k)
            i += k
        return out

    def centre_of(self, theta: Array) -> Array:
        dt = theta.dtype
        c0, s = self.c0.astype(dt), self.scale.astype(dt)
        sl = self._slices()
        if "position" not in sl:
            return c0
        z = theta[sl["position"]]
        if self.constraint == "plane":
            return c0 + s * (z @ self.plane_e.astype(dt))
        if self.constraint == "box" and self.box_map == "sigmoid":
            lo, hi = self.box_lo.astype(dt), self.box_hi.astype(dt)
            return lo + (hi - lo) * jax.nn.sigmoid(z)
        return c0 + s * z

    def theta0(self, dtype: Any) -> Array:
        """Parameters of the reference light (all zeros except a sigmoid box position)."""
        th = np.zeros(self.size)
        sl = self._slices()
        if "position" in sl and self.constraint == "box" and self.box_map == "sigmoid":
            lo, hi = np.asarray(self.box_lo), np.asarray(self.box_hi)
            f = np.clip((np.asarray(self.c0) - lo) / (hi - lo), 1e-3, 1 - 1e-3)
            th[sl["position"]] = np.log(f / (1 - f))
        return jnp.asarray(th, dtype=dtype)

    def build(self, theta: Array) -> Any:
        """The light for parameters `theta (P,)` (traceable)."""
        dt = theta.dtype
        sl = self._slices()
        c = self.centre_of(theta)
        if self.kind == "point":
            return js.PointLight(c, self.template.intensity.astype(dt))
        if self.kind == "polygon":
            # verts = c + rotate(R0 (f * local)): the frame's columns weighted by the local
            # coordinates, as broadcasts (no matrix products; see `rotate_rows`).
            R0 = self.frame0.astype(dt)
            local = self.local.astype(dt)
            lx, ly = local[:, 0:1], local[:, 1:2]
            if "size" in sl:
                f = jnp.exp(theta[sl["size"]])
                lx, ly = lx * f[0], ly * f[1]
            w = lx * R0[:, 0][None, :] + ly * R0[:, 1][None, :] + local[:, 2:3] * R0[:, 2][None, :]
            if "orientation" in sl:
                w = rotate_rows(theta[sl["orientation"]], w)
            return js.PolygonLight(c[None, :] + w, self.template.radiance.astype(dt))
        F = self.frame0.astype(dt)
        d = F[2]
        if "orientation" in sl:
            d = rotation_matrix(theta[sl["orientation"]] @ F[:2]) @ d
        length = self.local.astype(dt)
        if "size" in sl:
            length = length * jnp.exp(theta[sl["size"]][0])
        half = 0.5 * length * d
        t = self.template
        return js.LinearLight(c - half, c + half, t.power.astype(dt), t.profile, t.exponent)

    def lbfgsb_bounds(self, dtype: Any) -> tuple[Array, Array]:
        lo = np.full(self.size, -np.inf)
        hi = np.full(self.size, np.inf)
        sl = self._slices()
        if "position" in sl and self.constraint == "box":
            s = float(self.scale)
            lo[sl["position"]] = (np.asarray(self.box_lo) - np.asarray(self.c0)) / s
            hi[sl["position"]] = (np.asarray(self.box_hi) - np.asarray(self.c0)) / s
        if "orientation" in sl:
            lo[sl["orientation"]], hi[sl["orientation"]] = -np.pi, np.pi
        if "size" in sl:
            lo[sl["size"]], hi[sl["size"]] = np.log(1e-3), np.log(1e3)
        big = 1e6
        return jnp.asarray(np.clip(lo, -big, big), dtype), jnp.asarray(np.clip(hi, -big, big), dtype)


def with_light(scene: js.Scene, index: int, light: Any) -> js.Scene:
    """The scene with light `index` replaced."""
    return eqx.tree_at(lambda s: s.lights[index], scene, light)


def scene_size(scene: js.Scene, targets: PaintedTargets) -> float:
    """Diagonal (m) of the bounding box of targets, lights and occluders."""
    pts = [np.asarray(targets.points, np.float64)]
    for light in scene.lights:
        if isinstance(light, js.PolygonLight):
            pts.append(np.asarray(light.vertices, np.float64))
        elif isinstance(light, js.LinearLight):
            pts.append(np.stack([np.asarray(light.start), np.asarray(light.end)]).astype(np.float64))
        elif isinstance(light, js.PointLight):
            pts.append(np.asarray(light.position, np.float64)[None])
    if scene.occluders is not None:
        pts.append(np.asarray(scene.occluders, np.float64).reshape(-1, 3))
    p = np.concatenate(pts)
    return float(np.linalg.norm(p.max(axis=0) - p.min(axis=0)))


# --------------------------------------------------------------------------------------
# Residual and solvers (module-level jitted functions: compiled once per structure)
# --------------------------------------------------------------------------------------


class _Setup(eqx.Module):
    param: LightParametrisation
    scene: js.Scene
    material: js.Material
    targets: PaintedTargets
    specular: Any = eqx.field(static=True)
    with_specular: bool = eqx.field(static=True)
    project: bool = eqx.field(static=True, default=False)
    fit_exponent: bool = eqx.field(static=True, default=False)
    # Occluder-culling capacity for the LM's residual (`_forward.shade_culled`); None = full.
    max_active: int | None = eqx.field(static=True, default=None)
    # Receivers that get `max_active` in the irradiance (the rest 1); None = all.
    n_wide: int | None = eqx.field(static=True, default=None)
    # The culled kernel's combinatorics in NumPy on the host (`jaxshadow._clip_host`).
    host_combinatorics: bool = eqx.field(static=True, default=False)


def _pinned(light: Any) -> Any:
    """`light` with each array leaf (vertices, position, ...) the result of a product by the
    identity: the same values, but XLA:CPU then computes the pose from the parameters (and its
    tangents) once, instead of fusing that chain into every loop over receivers and edges that
    reads the light (~10% of an evaluation of the residual and its Jacobian with the device
    combinatorics, ~3% with the host's: `benchmarks/README.md`, Session 10)."""
    def pin(x: Any) -> Any:
        if not hasattr(x, "ndim") or x.ndim == 0 or not jnp.issubdtype(x.dtype, jnp.floating):
            return x
        return _pinned_array(x)

    return jax.tree_util.tree_map(pin, light)


def _projected(theta: Array, setup: _Setup) -> tuple[Array, Array, Array]:
    """Variable projection (Golub & Pereyra): for the light in `theta` (and $\\log n$ last when
    fitted), the per-channel coefficients $(k_a, k_d, k_s)$ solved by weighted linear least
    squares (pseudo-inverse, differentiable). Returns `(residual (3N,), k (3, C), exponent)`."""
    return _projected_flag(theta, setup, None)[:3]


def _projected_flag(theta: Array, setup: _Setup, max_active: int | None,
                    n_wide: int | None = None) -> tuple[Array, Array, Array, Array]:
    """`_projected` plus the culling overflow flag (`_forward.shade_culled`)."""
    t = setup.targets
    P = setup.param.size
    scene = with_light(setup.scene, setup.param.light_index, _pinned(setup.param.build(theta[:P])))
    dt = theta.dtype
    host = setup.host_combinatorics
    e, over = irradiance_culled(scene, t.points, t.normals, max_active, n_wide, host)
    e = e / jnp.pi
    amb = jnp.broadcast_to(scene.ambient.astype(dt)[None, :], e.shape)
    n = jnp.exp(theta[P]) if setup.fit_exponent else setup.material.exponent.astype(dt)
    cols = [amb, e]
    if setup.with_specular:
        sp, over_s = specular_culled(scene, t.points, t.normals, t.eye, n, setup.specular, max_active, host)
        cols.append(sp)
        over = over | over_s
    X = jnp.stack(cols, axis=-1)  # (N, C, m)
    sw = jnp.sqrt(t.weights)

    def channel(Xc, yc, swc):
        A = Xc * swc[:, None]
        k = jnp.linalg.pinv(A) @ (yc * swc)
        return A @ k - yc * swc, k

    r, k = jax.vmap(channel, in_axes=(1, 1, 1), out_axes=(1, 1))(X, t.colours, sw)
    if not setup.with_specular:
        k = jnp.concatenate([k, jnp.zeros((1, 3), dt)], axis=0)
    return r.reshape(-1), k, n, over


def _residuals(theta: Array, setup: _Setup) -> Array:
    """Weighted residuals `(3N,)` with the full (uncull'd) model."""
    return _residuals_flag(theta, setup, None)[0]


def _residuals_culled(theta: Array, setup: _Setup) -> tuple[Array, Array]:
    """Residuals with occluder culling at `setup.max_active` and the overflow flag (the LM)."""
    return _residuals_flag(theta, setup, setup.max_active, setup.n_wide)


def _residuals_flag(theta: Array, setup: _Setup, max_active: int | None,
                    n_wide: int | None = None) -> tuple[Array, Array]:
    if setup.project:
        r, _, _, over = _projected_flag(theta, setup, max_active, n_wide)
        return r, over
    t = setup.targets
    scene = with_light(setup.scene, setup.param.light_index, _pinned(setup.param.build(theta)))
    model, over = shade_culled(scene, setup.material, t.points, t.normals, t.eye, setup.specular,
                               setup.with_specular, max_active, n_wide, setup.host_combinatorics)
    return (jnp.sqrt(t.weights) * (model - t.colours)).reshape(-1), over


def _loss(theta: Array, setup: _Setup) -> Array:
    r = _residuals(theta, setup)
    return 0.5 * jnp.sum(r * r)


def _multistart_lm_impl(setup: _Setup, starts: Array, rtol: float, atol: float, max_steps: int,
                        prune: tuple[int, ...] = (), chunk: int | None = None) -> tuple[LMResult, Any]:
    """Levenberg-Marquardt from every start at once (`_lm.batched_levenberg_marquardt`) on the
    culled residual; `LMResult.flag` is the culling overflow (then retry, `_solve_lm`). Also
    returns the light built at every start's solution (a batched light pytree): built here, in
    the program that is compiled anyway, instead of by a program of its own (`_build_light`:
    ~0.15 s more of a one-start fit's first call)."""
    res = batched_levenberg_marquardt(_residuals_culled, starts, setup, rtol=rtol, atol=atol,
                                      max_steps=max_steps, prune=prune, chunk=chunk,
                                      num_residuals=3 * int(setup.targets.points.shape[0]))
    size = setup.param.size
    return res, jax.vmap(lambda th: setup.param.build(th[:size]))(res.values)


_multistart_lm = fit_jit(_multistart_lm_impl)
# The same program with the host combinatorics: other XLA options (`_lm.HOST_FIT_COMPILER_OPTIONS`).
_multistart_lm_host = fit_jit(_multistart_lm_impl, options=HOST_FIT_COMPILER_OPTIONS)


def prune_schedule(n_starts: int, max_steps: int) -> tuple[int, ...]:
    """Iterations 4, 8, 16, ... (below `max_steps`) at which the worse half of the running starts
    is abandoned (`_lm`'s successive halving); empty for one start."""
    if n_starts <= 1:
        return ()
    out, it = [], 4
    while it < max_steps:
        out.append(it)
        it *= 2
    return tuple(out)


@fit_jit
def _multistart_optx(setup: _Setup, starts: Array, rtol: float, atol: float, max_steps: int) -> tuple:
    """`optimistix.LevenbergMarquardt` from every start under `jax.vmap` (`solver="optimistix"`)."""
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol)

    def one(y0):
        sol = optx.least_squares(_residuals, solver, y0, args=setup, throw=False, max_steps=max_steps)
        return sol.value, sol.result == optx.RESULTS.successful, sol.stats["num_steps"]

    values, ok, steps = jax.vmap(one)(starts)
    losses = jax.vmap(_loss, in_axes=(0, None))(values, setup)
    return values, losses, ok, steps


@fit_jit
def _build_light(param: LightParametrisation, theta: Array) -> Any:
    """`param.build(theta)` compiled once per parametrisation shape (eagerly it would dispatch,
    and on the first call compile, a few dozen small operations)."""
    return param.build(theta)


@fit_jit
def _light_vertices(param: LightParametrisation, thetas: Array) -> Array:
    """`(S, K, 3)` vertices of the polygon light for each row of `thetas (S, >=P)` (compiled
    once per parametrisation shape, not per call)."""
    return jax.vmap(lambda th: param.build(th[: param.size]).vertices)(thetas)


def _start_counts(param: LightParametrisation, scene: js.Scene, targets: PaintedTargets, starts: Array) -> np.ndarray:
    """`(L, N)` relevant-occluder counts (`jaxshadow._bsp.occluder_relevance`) of every receiver
    for the light at each start and for the other polygon lights where they are."""
    assert scene.occluders is not None
    others = [np.asarray(light.vertices, np.float64) for i, light in enumerate(scene.lights)
              if i != param.light_index and isinstance(light, js.PolygonLight)]
    th = np.asarray(starts)[:, : param.size]
    if th.shape[0] == 1 and param.constraint != "box" and not np.any(th):
        # The reference light itself (a one-start fit): its vertices, without compiling
        # `_light_vertices` (~0.15 s of the first call). Equal to build(0) up to rounding; the
        # counts only size the capacity, and an overflow is caught and retried (`_solve_lm`).
        moving = np.asarray(param.template.vertices, np.float64)[None]
    else:
        moving = np.asarray(_light_vertices(param, starts), np.float64)
    emitters = [*moving, *others]
    k = max(e.shape[0] for e in emitters)
    padded = np.stack([np.concatenate([e, np.repeat(e[:1], k - e.shape[0], axis=0)]) for e in emitters])
    nrm = np.asarray(targets.normals, np.float64)
    nrm = nrm / np.linalg.norm(nrm, axis=1, keepdims=True)
    # In NumPy (`jaxshadow._clip_host`), not `_bsp._counts`: nothing to compile for a count.
    return relevant_counts(np.asarray(targets.points, np.float64), nrm, padded,
                           np.asarray(scene.occluders, np.float64))


def culling_capacity_for_starts(param: LightParametrisation, scene: js.Scene, targets: PaintedTargets,
                                starts: Array) -> int | None:
    """The occluder-culling capacity for an LM from `starts`: enough for every receiver with the
    light at any start and the other polygon lights where they are, plus one (None when culling
    cannot pay: fewer than 4 occluders, or not a polygon light). The light moves during the
    solve; a receiver that then sees more occluders (or a visible region with more edges than
    `_bsp.edge_capacity`) raises the overflow flag and `_solve_lm` retries."""
    occ = scene.occluders
    if occ is None or occ.shape[0] < 4 or param.kind != "polygon":
        return None
    counts = _start_counts(param, scene, targets, starts)
    # One spare (the light moves); not rounded to a power of two: the kernel's cost grows with it.
    return min(int(counts.max(initial=0)) + 1, int(occ.shape[0]))


def wide_group_for_starts(param: LightParametrisation, scene: js.Scene, targets: PaintedTargets,
                          starts: Array, max_active: int | None) -> int | None:
    """How many receivers get the full culling capacity in the irradiance (the others get 1,
    `jaxshadow._bsp.grouped_culled_form_factor`): twice the number that see two or more
    occluders from some light at some start, at least a quarter of them, a multiple of 8; None
    (no split) when that is all of them. Too few raises the overflow flag (`_solve_lm` retries
    without the split)."""
    n = int(targets.points.shape[0])
    if scene.occluders is None or max_active is None or max_active <= 1 or param.kind != "polygon":
        return None
    counts = _start_counts(param, scene, targets, starts)
    many = int(np.count_nonzero(counts.max(axis=0) >= 2))
    wide = -(-max(2 * many, n // 4, 1) // 8) * 8
    return None if wide >= n else wide


def _run_lm(setup: _Setup, starts: Any, rtol: float, atol: float, max_steps: int,
            prune: tuple[int, ...]) -> tuple[LMResult, Any]:
    """`_multistart_lm` (`_multistart_lm_host` with the host combinatorics) from `starts (S, P)`,
    several starts one at a time (`chunk=1`), `max_steps` as an array (traced): the one call
    that the screening (`_screen_with_lm`, 0 steps) and the solve (`_solve_lm`) both make, so
    that they run one compiled program."""
    lm = _multistart_lm_host if setup.host_combinatorics else _multistart_lm
    chunk = 1 if starts.shape[0] > 1 else None
    return lm(setup, starts, rtol, atol, np.asarray(max_steps, np.int32), prune, chunk)


def _solve_lm(setup: _Setup, starts: Array, rtol: float, atol: float, max_steps: int,
              prune: tuple[int, ...] = ()) -> tuple[LMResult, Any, _Setup, int]:
    """`_multistart_lm`, retried with twice the culling capacity (at last none) while some
    receiver overflowed it, so the result is exact. Returns `(result, lights at the solutions,
    setup used, retries)`.
    Several starts are evaluated one at a time (`chunk=1`): finished and abandoned ones cost
    nothing."""
    retries = 0
    while True:
        res, lights = _run_lm(setup, starts, rtol, atol, max_steps, prune)
        active = setup.max_active
        if active is None or not bool(res.flag):
            return res, lights, setup, retries
        assert setup.scene.occluders is not None  # a capacity is only set with occluders
        m = int(setup.scene.occluders.shape[0])
        if setup.n_wide is not None:  # first drop the two-group split
            setup = dataclasses.replace(setup, n_wide=None)
        else:
            setup = dataclasses.replace(setup, max_active=None if active >= m else min(2 * active, m))
        retries += 1


def _screen_with_lm(setup: _Setup, starts: Array, k: int, rtol: float, atol: float,
                    prune: tuple[int, ...]) -> np.ndarray:
    """$\\tfrac12|r|^2$ at every row of `starts (S, P)` (inf where not finite), evaluated by the
    program that then solves from the `k` best (`_multistart_lm` with `k` starts and no
    iterations: its first, evaluation-only iteration), `k` starts a call, the last call padded
    with the first start. A program of its own (`_screen_losses`, one vectorised loss) took
    25-40% of a 64-start fit's first call (`benchmarks/README.md`, Session 11); this costs a
    Jacobian per screened start instead (~1-3 ms). Should the culling overflow at some start
    (a visible region with more edges than `_bsp.edge_capacity`), the losses are the full
    model's instead (exact either way)."""
    ys = np.asarray(starts)
    S = ys.shape[0]
    calls = -(-S // k)
    ys = np.concatenate([ys, np.repeat(ys[:1], calls * k - S, axis=0)])
    results = [_run_lm(setup, ys[i * k: (i + 1) * k], rtol, atol, 0, prune)[0] for i in range(calls)]
    if setup.max_active is not None and any(bool(r.flag) for r in results):
        losses = np.asarray(_screen_losses(dataclasses.replace(setup, max_active=None, n_wide=None), starts))
    else:
        losses = np.concatenate([np.asarray(r.initial_losses) for r in results])[:S]
    losses = losses.astype(np.float64)
    return np.where(np.isfinite(losses), losses, np.inf)


@fit_jit
def _multistart_lbfgsb(setup: _Setup, starts: Array, lower: Array, upper: Array, tol: float,
                       max_steps: int) -> tuple:
    from ._jaxopt import lbfgsb_solve

    def one(y0):
        y, _, it = lbfgsb_solve(lambda th: _loss(th, setup), y0, lower, upper, max_steps, tol)
        return y, it

    values, steps = jax.vmap(one)(starts)
    losses = jax.vmap(_loss, in_axes=(0, None))(values, setup)
    return values, losses, steps < max_steps, steps


@fit_jit
def _jacobian(setup: _Setup, theta: Array) -> tuple[Array, Array]:
    return _residuals(theta, setup), jax.jacfwd(_residuals)(theta, setup)


@eqx.filter_jit
def loss_and_grad(setup: _Setup, theta: Array) -> tuple[Array, Array]:
    """Loss $\\tfrac12|r|^2$ and its gradient in the parameters (reverse mode)."""
    return jax.value_and_grad(_loss)(theta, setup)


# --------------------------------------------------------------------------------------
# Public API
# --------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class LightReport:
    """What a light fit found and how well the targets determine it.

    - `names`, `theta`: parameter names and values at the optimum (positions in units of
      `scale` m; rotations rad; sizes log factors).
    - `loss`: $\\tfrac12\\sum w r^2$ at the optimum; `initial_loss` at the reference light.
    - `best_start`, `start_losses (S,)`, `converged (S,)`, `num_steps (S,)`: the multistart
      (the solved starts; `n_screened` starts were generated, see `refine`).
    - `n_distinct_minima`: final points more than 1e-3 (parameter units) apart among the
      converged starts within 1 % of the best loss (a measure of ambiguity).
    - `singular_values`: of the weighted residual Jacobian with unit-norm columns;
      `std_errors`: name -> standard error in the parameter's units ($\\hat\\sigma^2
      (J^TJ)^{-1}$); `determined`: name -> bool (False for a null direction of $J$).
    - `targets_met`: `(N,)` bool within the targets' tolerance, or None.
    - `solver`, `scale`, `warnings`; `abandoned (S,)`: starts stopped early by `prune` (their
      `converged` is False).
    """

    names: tuple
    theta: np.ndarray
    loss: float
    initial_loss: float
    best_start: int
    start_losses: np.ndarray
    converged: np.ndarray
    num_steps: np.ndarray
    n_distinct_minima: int
    n_screened: int
    singular_values: np.ndarray
    std_errors: dict
    determined: dict
    targets_met: np.ndarray | None
    solver: str
    scale: float
    warnings: tuple
    abandoned: np.ndarray | None = None

    def __str__(self) -> str:
        ok = int(np.count_nonzero(self.converged))
        lines = [
            f"light fit ({self.solver}): loss {self.initial_loss:.4g} -> {self.loss:.4g}; "
            f"best start {self.best_start} of {len(self.start_losses)} ({ok} converged, "
            + (f"{int(np.count_nonzero(self.abandoned))} abandoned, " if self.abandoned is not None else "")
            + f"{self.n_distinct_minima} distinct minima near the best)"
        ]
        for nm, v in zip(self.names, self.theta, strict=True):
            flag = "" if self.determined[nm] else "  UNDETERMINED"
            lines.append(f"  {nm:10s} {v: .6g}  se={self.std_errors[nm]:.3g}{flag}")
        lines.append(f"  singular values (unit columns): {np.array2string(self.singular_values, precision=3)}")
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class LightFit:
    """`scene` (with the fitted light), `light`, `residual (N, 3)` = model - colours
    (unweighted), `report` (`LightReport`), `parametrisation`, `material` (the material used:
    as given, or the projected one with `material_mode="projected"`)."""

    scene: js.Scene
    light: Any
    residual: np.ndarray
    report: LightReport
    parametrisation: LightParametrisation
    material: js.Material


def make_starts(param: LightParametrisation, starts: int, *, search_radius: float, orientation_spread: float,
                size_spread: float, seed: int, dtype: Any) -> Array:
    """`(starts, P)` starting parameters: the reference first, then a scrambled Sobol
    stratification of the search region (Campbell & Fussell §4.4.2's coarse-grid multistart).

    Positions within `search_radius` (in scene-size units) of the reference (the whole box for
    a box constraint), rotation vectors within `orientation_spread` rad, log-sizes within
    `log(1 + size_spread)`.
    """
    th0 = np.asarray(param.theta0(np.float64))
    if starts <= 1:
        return jnp.asarray(th0[None], dtype)
    # Imported here, after the one-start return: scipy.stats takes ~1.3 s to import, which was
    # a seventh of a one-start fit's first call (`benchmarks/README.md`, Session 8).
    from scipy.stats import qmc

    P = param.size
    m = max(int(math.ceil(math.log2(starts - 1))), 0)
    u = qmc.Sobol(P, scramble=True, seed=seed).random_base2(m)[: starts - 1] * 2.0 - 1.0  # [-1, 1)
    th = np.tile(th0, (starts - 1, 1))
    sl = param._slices()
    if "position" in sl:
        if param.constraint == "box" and param.box_map == "sigmoid":
            f = np.clip(0.5 * (u[:, sl["position"]] + 1.0), 0.02, 0.98)
            th[:, sl["position"]] = np.log(f / (1 - f))
        elif param.constraint == "box":
            lo, hi = param.lbfgsb_bounds(np.float64)
            lo_, hi_ = np.asarray(lo)[sl["position"]], np.asarray(hi)[sl["position"]]
            th[:, sl["position"]] = lo_ + (hi_ - lo_) * 0.5 * (u[:, sl["position"]] + 1.0)
        else:
            th[:, sl["position"]] += search_radius * u[:, sl["position"]]
    if "orientation" in sl:
        th[:, sl["orientation"]] += orientation_spread * u[:, sl["orientation"]]
    if "size" in sl:
        th[:, sl["size"]] += math.log1p(size_spread) * u[:, sl["size"]]
    return jnp.asarray(np.concatenate([th0[None], th]), dtype)


def resolve_combinatorics(combinatorics: str, solver: str = "lm", receiver_groups: bool = False) -> str:
    """What `fit_light(combinatorics="auto")` runs: `"host"` on the CPU backend when the compiled
    host combinatorics are built (`jaxshadow._clip_host.compiled_available`) and the LM solver
    uses them (`solver="lm"`, no `receiver_groups`), else `"device"`; other values unchanged.
    With both on this machine the host's first call is about half as long and every solve
    faster (`benchmarks/combinatorics.py`); on an accelerator the host round trip would not pay."""
    if combinatorics != "auto":
        return combinatorics
    usable = solver == "lm" and not receiver_groups and jax.default_backend() == "cpu"
    return "host" if usable and compiled_available() else "device"


def fit_light(
    scene: js.Scene,
    targets: PaintedTargets,
    material: js.Material,
    light_index: int = 0,
    *,
    fit: tuple = ("position", "orientation", "size"),
    constraint: Plane | Box | None = None,
    starts: int = 64,
    refine: int | None = 8,
    solver: str = "lm",
    search_radius: float = 0.5,
    orientation_spread: float = 0.5,
    size_spread: float = 0.5,
    rtol: float = 1e-9,
    atol: float = 1e-12,
    max_steps: int = 100,
    seed: int = 0,
    material_mode: str = "fixed",
    fit_exponent: bool = False,
    specular: SpecularFn | None = None,
    prune: bool = True,
    receiver_groups: bool = False,
    combinatorics: str = "auto",
) -> LightFit:
    """Place light `light_index` of `scene` so the shading matches painted colours.

    Minimises $\\sum_i w_i |L(x_i) - C_i|^2$ over the light's pose (Poulin §5.2 by nonlinear
    least squares; §5.3.5 uses MINPACK's LM the same way), with the material and every other
    light fixed. The light in `scene` is the reference: its shape, radiance and pose are the
    starting point and the origin of the parametrisation (see `LightParametrisation`).

    **Arguments:**

    - `scene`, `targets`, `material`: the scene (occluders cast soft shadows), the painted
      targets and the (fixed) material.
    - `light_index`: which light to place (PolygonLight, LinearLight or PointLight).
    - `fit`: subset of `("position", "orientation", "size")`.
    - `constraint`: `None`, `Plane(point, normal)` (centre on a plane) or `Box(lower, upper)`.
    - `starts`: number of multistart points (vectorised with `jax.vmap`); 1 = local solve.
    - `refine`: k (default 8): evaluate the loss at every start and solve only from the k
      best (Campbell & Fussell §4.4.2's screening of a coarse grid); `None`: solve from every
      start (successive halving, `prune`, still applies). With 64 starts and 8 occluders
      screening is ~20x faster (`benchmarks/inverse_speed.py`); with `starts <= k` it does
      nothing. With `solver="lm"` the starts are evaluated by the solver's own program, k at
      a time (no program is compiled for the screening alone: the first call of a 64-start
      fit is ~25% shorter, `benchmarks/README.md`, Session 11); with the other solvers by
      one vectorised loss.
    - `solver`: `"lm"` (default: Levenberg-Marquardt over all starts at once, `inverse/_lm.py`,
      with per-receiver occluder culling; exact), `"optimistix"` (`optimistix.LevenbergMarquardt`
      under `jax.vmap`, the full model; several times slower to compile and to run, see
      `benchmarks/inverse_speed.py`) or `"lbfgsb"` (JAXopt L-BFGS-B on $\\tfrac12|r|^2$ with
      box bounds).
    - `search_radius`: half-width of the start region, in units of the scene size.
    - `orientation_spread` (rad), `size_spread` (relative): the start region's other axes.
    - `rtol`, `atol`, `max_steps`: solver tolerances; `seed`: of the start stratification.
    - `material_mode`: `"fixed"` (the material as given) or `"projected"` (joint light and
      material by variable projection: at every trial light the coefficients $k_a, k_d, k_s$
      are the exact, unconstrained weighted least-squares solution, so only the light - and
      with `fit_exponent=True` also $\\log n$ - is searched; `LightFit.material` holds them).
      Whether $k_s$ is used follows `material.ks != 0`.
    - `specular`: a callable like `js.specular` (default `js.specular`); unused when the
      material has $k_s = 0$.
    - `prune` (`solver="lm"` with several starts): at iterations 4, 8, 16, ... abandon the
      worse half (by current loss) of the starts still running (successive halving), so the
      cost follows the promising starts; `LightReport.abandoned` lists them. False: every
      start runs to convergence or `max_steps`.
    - `receiver_groups` (`solver="lm"` with occluder culling): give the full culling capacity
      only to the receivers that need it and capacity 1 to the rest
      (`jaxshadow._bsp.grouped_culled_form_factor`): each solve is about 1.6x faster with 8
      occluders, but the shadow kernel is compiled twice (about twice the first-call time;
      `benchmarks/inverse_speed.py`). Worth it for many solves; exact either way.
    - `combinatorics` (`solver="lm"` with occluder culling): where the soft-shadow kernel's
      combinatorics run (which occluders, which pieces of which edges bound the visible
      region). `"device"`: in the compiled program (`jaxshadow._clip`). `"host"`: on the host,
      called back from the compiled solver once per evaluation (`jaxshadow._clip_host`; compiled
      C, `_clipc.c`, or its NumPy reference where the extension is not built): the compiled
      program holds only the geometry and its derivatives. With the C kernel, 8 occluders and
      48 targets the first call is about half as long and each solve ~20% (1 start) to ~40% (64
      starts) shorter; with NumPy each solve is ~2x longer (`benchmarks/combinatorics.py`).
      `"auto"` (default): `resolve_combinatorics` (host on the CPU with the C kernel). The same
      values to rounding either way; `receiver_groups=True` always uses the device.

    **Returns:** `LightFit(scene, light, residual, report, parametrisation)`.
    """
    if not isinstance(scene, js.Scene):
        raise ValueError(f"fit_light: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    if not isinstance(targets, PaintedTargets):
        raise ValueError(f"fit_light: targets must be PaintedTargets, got {type(targets).__name__}.")
    if isinstance(light_index, bool) or not isinstance(light_index, (int, np.integer)):
        raise ValueError(f"fit_light: light_index must be an integer, got {light_index!r}.")
    if not 0 <= light_index < len(scene.lights):
        raise ValueError(f"fit_light: light_index {light_index} out of range for {len(scene.lights)} light(s).")
    if isinstance(fit, str):
        fit = (fit,)
    unknown = [g for g in fit if g not in FIT_GROUPS]
    if unknown:
        raise ValueError(f"fit_light: unknown fit group(s) {unknown}; choose from {FIT_GROUPS}.")
    if solver not in ("lm", "optimistix", "lbfgsb"):
        raise ValueError(f"fit_light: solver must be 'lm', 'optimistix' or 'lbfgsb', got {solver!r}.")
    if int(starts) < 1:
        raise ValueError(f"fit_light: starts must be >= 1, got {starts}.")
    if material_mode not in ("fixed", "projected"):
        raise ValueError(f"fit_light: material_mode must be 'fixed' or 'projected', got {material_mode!r}.")
    if combinatorics not in ("auto", "host", "device"):
        raise ValueError(f"fit_light: combinatorics must be 'auto', 'device' or 'host', got {combinatorics!r}.")
    host = resolve_combinatorics(combinatorics, solver, receiver_groups) == "host"
    dt = targets.points.dtype
    size = scene_size(scene, targets)
    param = LightParametrisation(scene.lights[light_index], light_index, fit, constraint, size,
                                 "affine" if solver == "lbfgsb" else "sigmoid")
    with_spec = bool(np.any(np.asarray(material.ks) != 0))
    spec_fn = specular
    project = material_mode == "projected"
    fit_n = project and fit_exponent and with_spec
    setup = _Setup(param, scene, material, targets, spec_fn, with_spec, project, fit_n, host_combinatorics=host)
    y0 = make_starts(param, int(starts), search_radius=search_radius, orientation_spread=orientation_spread,
                     size_spread=size_spread, seed=seed, dtype=dt)
    names = param.names
    theta_ref = param.theta0(dt)
    if fit_n:
        logn = np.full((y0.shape[0], 1), np.log(float(material.exponent)))
        logn[1:, 0] += np.random.default_rng(seed).uniform(-np.log(3.0), np.log(3.0), y0.shape[0] - 1)
        y0 = jnp.concatenate([y0, jnp.asarray(logn, dt)], axis=1)
        names = (*names, "log_n")
        theta_ref = jnp.concatenate([theta_ref, jnp.asarray([np.log(float(material.exponent))], dt)])
    n_screened = int(y0.shape[0])
    ref_row = 0  # make_starts puts the reference first; screening may drop it
    initial_loss = None
    screening = refine is not None and 0 < int(refine) < n_screened
    n_solved = int(refine) if screening else n_screened
    sched = prune_schedule(n_solved, int(max_steps)) if prune and solver == "lm" else ()
    cap = culling_capacity_for_starts(param, scene, targets, y0) if solver == "lm" else None
    if screening:
        if solver == "lm":
            # The capacity holds every receiver's relevant occluders at these very lights.
            screen = _screen_with_lm(dataclasses.replace(setup, max_active=cap), y0, n_solved, rtol, atol, sched)
        else:
            screen = np.asarray(_screen_losses(setup, y0), np.float64)
        order = np.sort(np.argsort(np.where(np.isfinite(screen), screen, np.inf), kind="stable")[: int(refine)])
        y0 = jnp.asarray(np.asarray(y0)[order])  # on the host: an eager gather compiles ~8 small programs
        initial_loss = float(screen[0])
        ref_row = int(np.searchsorted(order, 0)) if 0 in order else -1
    retries = 0
    abandoned = np.zeros(int(y0.shape[0]), bool)
    if solver == "lm":
        # After screening the capacity stays the one for all the screened starts (enough for the
        # solved ones too): the solve then runs the very program that screened them.
        setup = dataclasses.replace(setup, max_active=cap,
                                    n_wide=wide_group_for_starts(param, scene, targets, y0, cap)
                                    if receiver_groups else None)
        res, lm_lights, setup, retries = _solve_lm(setup, y0, rtol, atol, int(max_steps), sched)
        values, losses, ok, steps = res.values, res.losses, res.converged, res.num_steps
        abandoned = np.asarray(res.abandoned)
    elif solver == "optimistix":
        values, losses, ok, steps = _multistart_optx(setup, y0, rtol, atol, int(max_steps))
    else:
        lo, hi = param.lbfgsb_bounds(dt)
        values, losses, ok, steps = _multistart_lbfgsb(setup, y0, lo, hi, atol, int(max_steps))
    values, losses = np.asarray(values), np.asarray(losses, np.float64)
    ok, steps = np.asarray(ok), np.asarray(steps)
    losses_ = np.where(np.isfinite(losses), losses, np.inf)
    best = int(np.argmin(losses_))
    theta = jnp.asarray(values[best], dt)
    if solver == "lm":
        # The solver's own residual and Jacobian at the optimum (exact: no culling overflow).
        r, J = np.asarray(res.residuals, np.float64)[best], np.asarray(res.jacobians, np.float64)[best]
        if initial_loss is None and ref_row >= 0:
            initial_loss = float(np.asarray(res.initial_losses)[ref_row])
    else:
        r, J = _jacobian(setup, theta)
        r, J = np.asarray(r, np.float64), np.asarray(J, np.float64)
    if initial_loss is None:
        initial_loss = float(_loss_jit(setup, theta_ref))

    # Identifiability: SVD of the column-normalised Jacobian, standard errors.
    m = int(np.count_nonzero(np.asarray(targets.weights) > 0))
    n_par = len(names)
    dof = max(m - n_par, 1)
    sigma2 = float(r @ r) / dof
    cn = np.linalg.norm(J, axis=0)
    Jn = J / np.where(cn > 0, cn, 1.0)
    _, sv, vt = np.linalg.svd(Jn, full_matrices=False)
    null = vt[sv <= 1e-8 * max(sv.max(), 1e-300)]
    bad = (np.any(np.abs(null) > 1e-6, axis=0) if len(null) else np.zeros(n_par, bool)) | (cn == 0)
    se = {}
    cov = sigma2 * np.linalg.pinv(Jn[:, ~bad].T @ Jn[:, ~bad]) if (~bad).any() else np.zeros((0, 0))
    sd = np.sqrt(np.maximum(np.diag(cov), 0.0)) / cn[~bad] if (~bad).any() else np.zeros(0)
    it = iter(sd)
    for j, nm in enumerate(names):
        se[nm] = math.inf if bad[j] else float(next(it)) * (size if nm in ("x", "y", "z", "a", "b") else 1.0)
    determined = {nm: not bad[j] for j, nm in enumerate(names)}
    msgs = [f"light parameter {nm} is not determined by these targets." for nm in names if not determined[nm]]
    near = np.flatnonzero(ok & (losses_ <= losses_[best] * 1.01 + 1e-30))
    reps: list[np.ndarray] = []
    for i in near:
        if all(np.max(np.abs(values[i] - q)) > 1e-3 for q in reps):
            reps.append(values[i])
    if not ok[best]:
        msgs.append("the best start did not report convergence (max_steps reached?).")
    if retries:
        msgs.append(f"the light moved so that some receiver saw more occluders than the culling capacity; "
                    f"solved again {retries} time(s) with a larger one (the result is exact).")

    if solver == "lm":
        # On the host: eager indexing of a device array would compile a gather per leaf.
        light = jax.tree_util.tree_map(lambda x: jnp.asarray(np.asarray(x)[best]), lm_lights)
    else:
        light = _build_light(param, theta[: param.size])
    new_scene = with_light(scene, light_index, light)
    if project:
        _, kc, n_fit = _projected_jit(setup, theta)
        kc = np.asarray(kc, np.float64)
        material = js.Material(ka=jnp.asarray(kc[0], dt), kd=jnp.asarray(kc[1], dt), ks=jnp.asarray(kc[2], dt),
                               exponent=jnp.asarray(float(n_fit), dt))
    t = targets
    w = np.asarray(t.weights, np.float64)
    if solver == "lm" and not project and np.all(w > 0):
        residual = r.reshape(-1, 3) / np.sqrt(w)  # r = sqrt(w) (model - colours)
    else:
        model = shade(new_scene, material, t.points, t.normals, t.eye, spec_fn, with_spec)
        residual = np.asarray(model, np.float64) - np.asarray(t.colours, np.float64)
    met = None if t.tolerance is None else np.all(np.abs(residual) <= np.asarray(t.tolerance), axis=1)
    report = LightReport(
        names=names,
        theta=np.asarray(theta, np.float64),
        loss=float(losses_[best]),
        initial_loss=initial_loss,
        best_start=best,
        start_losses=losses,
        converged=ok,
        num_steps=steps,
        n_distinct_minima=max(len(reps), 1),
        n_screened=n_screened,
        singular_values=sv,
        std_errors=se,
        determined=determined,
        targets_met=met,
        solver=solver,
        scale=size,
        warnings=tuple(msgs),
        abandoned=abandoned,
    )
    return LightFit(scene=new_scene, light=light, residual=residual, report=report, parametrisation=param,
                    material=material)


@fit_jit
def _loss_jit(setup: _Setup, theta: Array) -> Array:
    return _loss(theta, setup)


@fit_jit
def _projected_jit(setup: _Setup, theta: Array) -> tuple[Array, Array, Array]:
    return _projected(theta, setup)


@fit_jit
def _screen_losses(setup: _Setup, starts: Array) -> Array:
    """$\\tfrac12|r|^2$ at every start, one vectorised loss (culled at `setup.max_active`: the
    caller sizes it for these starts, so nothing overflows): the screening of the Optimistix
    and L-BFGS-B solvers (the LM screens with its own program, `_screen_with_lm`)."""

    def loss(theta: Array) -> Array:
        r = _residuals_culled(theta, setup)[0]
        return 0.5 * jnp.sum(r * r)

    return jax.vmap(loss)(starts)


def light_loss(scene: js.Scene, targets: PaintedTargets, material: js.Material, light: Any,
               light_index: int = 0, specular: SpecularFn | None = None) -> Array:
    """$\\tfrac12\\sum_i w_i |L(x_i) - C_i|^2$ with light `light_index` replaced by `light`
    (differentiable in the light's arrays, e.g. `jax.grad` with respect to its vertices)."""
    with_spec = bool(np.any(np.asarray(material.ks) != 0))
    s = with_light(scene, light_index, light)
    t = targets
    model = shade(s, material, t.points, t.normals, t.eye, specular, with_spec)
    r = jnp.sqrt(t.weights) * (model - t.colours)
    return 0.5 * jnp.sum(r * r)


@dataclasses.dataclass(frozen=True)
class JointFit:
    """`scene`, `material`, `residual (N, 3)`, `report = (LightReport, MaterialReport)` of the
    last round, `history`: the loss after each half-step, `std_errors`: name -> joint standard
    error (`joint_std_errors`; the two reports' errors are each conditional on the other half)."""

    scene: js.Scene
    material: js.Material
    residual: np.ndarray
    report: tuple
    history: tuple
    std_errors: dict = dataclasses.field(default_factory=dict)


def joint_std_errors(param: LightParametrisation, theta: Any, scene: js.Scene, material: js.Material,
                     targets: PaintedTargets, *, fit_exponent: bool, specular: SpecularFn | None = None,
                     free_k: Any = None) -> dict:
    r"""Standard errors of a joint light + material fit, from the Jacobian of the weighted
    residual in *all* the fitted parameters at once: the light's `theta` (`param.names`), the
    coefficients $k_a, k_d, k_s$ per channel and, with `fit_exponent`, $\log n$.

    $\hat\sigma^2 (J^\top J)^{-1}$ with $\hat\sigma^2 = |r|^2 / (m - p)$ (Gauss-Markov; a
    linearisation at the optimum). Coefficients outside `free_k` (a `(3, 3)` bool array, rows
    `ka, kd, ks`: False at an active bound, or for $k_s$ of a diffuse fit) are held fixed.

    **Returns:** name -> standard error: `"x", "y", "z"` (or `"a", "b"` on a plane) in m,
    rotations in rad, log sizes, `"ka[r]"` ... `"ks[b]"` and `"n"` (the exponent itself,
    by the delta method); `inf` for a direction the targets do not determine.
    """
    t = targets
    dt = t.points.dtype
    P = param.size
    with_spec = bool(np.any(np.asarray(material.ks) != 0))
    free = np.ones((3, 3), bool) if free_k is None else np.asarray(free_k, bool)
    if not with_spec:
        free[2] = False
    k0 = np.stack([np.asarray(material.ka, np.float64), np.asarray(material.kd, np.float64),
                   np.asarray(material.ks, np.float64)])
    idx = np.flatnonzero(free.reshape(-1))
    fit_n = bool(fit_exponent and with_spec)
    n0 = float(material.exponent)
    phi0 = np.concatenate([np.asarray(theta, np.float64)[:P], k0.reshape(-1)[idx], [np.log(n0)] if fit_n else []])

    def resid(phi: Array) -> Array:
        k = jnp.asarray(k0, dt).reshape(-1).at[jnp.asarray(idx)].set(phi[P:P + len(idx)]).reshape(3, 3)
        n = jnp.exp(phi[-1]) if fit_n else jnp.asarray(n0, dt)
        sc = with_light(scene, param.light_index, param.build(phi[:P]))
        m = js.Material(ka=k[0], kd=k[1], ks=k[2], exponent=n)
        model = shade(sc, m, t.points, t.normals, t.eye, specular, with_spec)
        return (jnp.sqrt(t.weights) * (model - t.colours)).reshape(-1)

    phi = jnp.asarray(phi0, dt)
    r, J = jax.jit(lambda f: (resid(f), jax.jacfwd(resid)(f)))(phi)
    r, J = np.asarray(r, np.float64), np.asarray(J, np.float64)
    m_eff = int(np.count_nonzero(np.asarray(t.weights) > 0))
    sigma2 = float(r @ r) / max(m_eff - J.shape[1], 1)
    cn = np.linalg.norm(J, axis=0)
    Jn = J / np.where(cn > 0, cn, 1.0)
    _, sv, _ = np.linalg.svd(Jn, full_matrices=False)
    ok = (cn > 0) & (sv.min() > 1e-10 * sv.max())
    cov = np.linalg.pinv(Jn.T @ Jn) * sigma2
    se_all = np.where(ok, np.sqrt(np.maximum(np.diag(cov), 0.0)) / np.where(cn > 0, cn, 1.0), np.inf)
    names = [*param.names, *[f"{'ka kd ks'.split()[i // 3]}[{'rgb'[i % 3]}]" for i in idx]] + (["log_n"] if fit_n else [])
    out = {}
    for nm, se in zip(names, se_all, strict=True):
        if nm in ("x", "y", "z", "a", "b"):
            out[nm] = float(se) * float(param.scale)
        elif nm == "log_n":
            out["n"] = float(se) * n0
        else:
            out[nm] = float(se)
    return out


def fit_light_and_material(
    scene: js.Scene,
    targets: PaintedTargets,
    material: js.Material,
    light_index: int = 0,
    *,
    method: str = "projected",
    rounds: int = 4,
    light_kwargs: dict | None = None,
    material_kwargs: dict | None = None,
    specular: SpecularFn | None = None,
    progress: Any = None,
) -> JointFit:
    """Joint light placement and material.

    `method="projected"` (default, "stack"): one multistart nonlinear least squares over the
    light pose and $\\log n$ with $k_a, k_d, k_s$ projected out (`fit_light(...,
    material_mode="projected", fit_exponent=True)`), then the exact bounded `fit_material` at the
    fitted light (the coefficients then respect `bounds`). `material` gives the starting
    exponent and whether there is a specular term ($k_s \\ne 0$).

    `method="alternate"` (block coordinate descent, `rounds` rounds): each round places the light with the material fixed (`fit_light`, the full multistart in
    the first round; afterwards a local solve from the previous light, or with `refine` a
    multistart in a 4x tighter region, same shapes so nothing recompiles), then refits the
    material exactly for that light (`fit_material`). Every half-step cannot increase the
    loss, so the history is non-increasing up to solver tolerance.

    `progress`: `None` or a callable taking a message string (one line per half-step).

    **Returns:** `JointFit`.
    """
    import time

    from ._material import fit_material

    lk = dict(light_kwargs or {})
    mk = dict(material_kwargs or {})
    mk.setdefault("warn", False)
    if method not in ("projected", "alternate"):
        raise ValueError(f"fit_light_and_material: method must be 'projected' or 'alternate', got {method!r}.")
    history = []
    if method == "projected":
        t0 = time.perf_counter()
        lf = fit_light(scene, targets, material, light_index, specular=specular, material_mode="projected",
                       fit_exponent=True, **lk)
        history.append(lf.report.loss)
        if progress is not None:
            progress(f"  light + projected material: loss {lf.report.loss:.4e}  [{time.perf_counter() - t0:.1f} s]")
        t0 = time.perf_counter()
        if "exponent" not in mk and not bool(np.any(np.asarray(material.ks) != 0)):
            mk["exponent"] = float(material.exponent)
        mf = fit_material(lf.scene, targets, specular=specular, **mk)
        history.append(0.5 * float(np.sum(mf.report.weights * mf.residual**2)))
        if progress is not None:
            progress(f"  exact bounded material at that light: loss {history[-1]:.4e}  [{time.perf_counter() - t0:.1f} s]")
        free = np.ones((3, 3), bool)
        for a in mf.report.active_bounds:  # e.g. "ks[g]>=lower": held at the bound
            if a.endswith(("lower", "upper")):
                free["ka kd ks".split().index(a[:2]), "rgb".index(a[3])] = False
        se = joint_std_errors(lf.parametrisation, lf.report.theta, scene, mf.material, targets,
                              fit_exponent="exponent" not in mk, specular=specular, free_k=free)
        return JointFit(scene=lf.scene, material=mf.material, residual=mf.residual, report=(lf.report, mf.report),
                        history=tuple(history), std_errors=se)
    lf = mf = None
    for r in range(int(rounds)):
        kw = dict(lk)
        if r > 0:
            if kw.get("refine"):
                # Same array shapes as round 1 (no recompilation); a tighter start region.
                kw["search_radius"] = 0.25 * kw.get("search_radius", 0.5)
                kw["orientation_spread"] = 0.25 * kw.get("orientation_spread", 0.5)
            else:
                kw["starts"] = 1
        t0 = time.perf_counter()
        lf = fit_light(scene, targets, material, light_index, specular=specular, **kw)
        scene = lf.scene
        history.append(lf.report.loss)
        if progress is not None:
            progress(f"  round {r + 1}/{rounds}: light  ({kw.get('starts', 64)} start(s)) loss {lf.report.loss:.4e}"
                     f"  [{time.perf_counter() - t0:.1f} s]")
        t0 = time.perf_counter()
        mf = fit_material(scene, targets, specular=specular, **mk)
        material = mf.material
        history.append(0.5 * float(np.sum(mf.report.weights * mf.residual**2)))
        if progress is not None:
            progress(f"  round {r + 1}/{rounds}: material loss {history[-1]:.4e}  [{time.perf_counter() - t0:.1f} s]")
    assert lf is not None and mf is not None
    return JointFit(scene=scene, material=material, residual=mf.residual, report=(lf.report, mf.report),
                    history=tuple(history))
