"""The light fit's residual: $\\sqrt{w}\\,(L_{model} - L_{painted})$ as a function of the light's
parameters, with the model of `js.shade` (Poulin eq. 5.14; soft shadows included when the scene
has occluders), in the solvers' programs with the shadow engine at a capacity (`_forward.shade_culled`), and with the material projected out
(variable projection, Golub & Pereyra) when it is fitted jointly.

Module-level functions, jitted where a solver calls them from the host: each compiles once per
problem structure.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

import jaxshadow as js
from jaxshadow import traced

from ._forward import SpecularFn, irradiance_culled, shade, shade_culled, specular_culled
from ._lm import fit_jit
from ._parametrisation import LightParametrisation, with_light
from ._targets import PaintedTargets


class LightProblem(eqx.Module):
    """Everything a light fit's residual depends on: the parametrisation of the moving light,
    the scene, the material, the targets, and how the model is evaluated (static)."""

    param: LightParametrisation
    scene: js.Scene
    material: js.Material
    targets: PaintedTargets
    specular: Any = eqx.field(static=True)
    with_specular: bool = eqx.field(static=True)
    project: bool = eqx.field(static=True, default=False)
    fit_exponent: bool = eqx.field(static=True, default=False)
    # The shadow engine's capacity in the solvers' residual (`_forward.shade_culled`); None:
    # every receiver against every occluder.
    capacity: int | None = eqx.field(static=True, default=None)


def pinned(light: Any) -> Any:
    """`light` with each array leaf (vertices, position, ...) the result of a product by the
    identity (`jaxshadow.traced.pin`): the same values, but XLA:CPU then computes the pose from
    the parameters (and its tangents) once, instead of fusing that chain into every loop over
    receivers and edges that reads the light."""
    def pin(x: Any) -> Any:
        if not hasattr(x, "ndim") or x.ndim == 0 or not jnp.issubdtype(x.dtype, jnp.floating):
            return x
        return traced.pin(x)

    return jax.tree_util.tree_map(pin, light)


def projected(theta: Array, problem: LightProblem) -> tuple[Array, Array, Array]:
    """Variable projection (Golub & Pereyra): for the light in `theta` (and $\\log n$ last when
    fitted), the per-channel coefficients $(k_a, k_d, k_s)$ solved by weighted linear least
    squares (pseudo-inverse, differentiable). Returns `(residual (3N,), k (3, C), exponent)`."""
    return projected_flag(theta, problem, None)[:3]


def projected_flag(theta: Array, problem: LightProblem,
                   capacity: int | None) -> tuple[Array, Array, Array, Array]:
    """`projected` plus the capacity overflow flag (`_forward.shade_culled`)."""
    t = problem.targets
    P = problem.param.size
    scene = with_light(problem.scene, problem.param.light_index, pinned(problem.param.build(theta[:P])))
    dt = theta.dtype
    e, over = irradiance_culled(scene, t.points, t.normals, capacity)
    e = e / jnp.pi
    amb = jnp.broadcast_to(scene.ambient.astype(dt)[None, :], e.shape)
    n = jnp.exp(theta[P]) if problem.fit_exponent else problem.material.exponent.astype(dt)
    cols = [amb, e]
    if problem.with_specular:
        sp, over_s = specular_culled(scene, t.points, t.normals, t.eye, n, problem.specular, capacity)
        cols.append(sp)
        over = over | over_s
    X = jnp.stack(cols, axis=-1)  # (N, C, m)
    sw = jnp.sqrt(t.weights)

    def channel(Xc, yc, swc):
        A = Xc * swc[:, None]
        k = jnp.linalg.pinv(A) @ (yc * swc)
        return A @ k - yc * swc, k

    r, k = jax.vmap(channel, in_axes=(1, 1, 1), out_axes=(1, 1))(X, t.colours, sw)
    if not problem.with_specular:
        k = jnp.concatenate([k, jnp.zeros((1, 3), dt)], axis=0)
    return r.reshape(-1), k, n, over


def residuals(theta: Array, problem: LightProblem) -> Array:
    """Weighted residuals `(3N,)` with every receiver against every occluder (no capacity)."""
    return residuals_flag(theta, problem, None)[0]


def residuals_culled(theta: Array, problem: LightProblem) -> tuple[Array, Array]:
    """Residuals with the shadow engine at `problem.capacity` and the overflow flag (the LM)."""
    return residuals_flag(theta, problem, problem.capacity)


def residuals_flag(theta: Array, problem: LightProblem, capacity: int | None) -> tuple[Array, Array]:
    if problem.project:
        r, _, _, over = projected_flag(theta, problem, capacity)
        return r, over
    t = problem.targets
    scene = with_light(problem.scene, problem.param.light_index, pinned(problem.param.build(theta)))
    model, over = shade_culled(scene, problem.material, t.points, t.normals, t.eye, problem.specular,
                               problem.with_specular, capacity)
    return (jnp.sqrt(t.weights) * (model - t.colours)).reshape(-1), over


def loss(theta: Array, problem: LightProblem) -> Array:
    r = residuals(theta, problem)
    return 0.5 * jnp.sum(r * r)


@fit_jit
def jacobian(problem: LightProblem, theta: Array) -> tuple[Array, Array]:
    return residuals(theta, problem), jax.jacfwd(residuals)(theta, problem)


@eqx.filter_jit
def loss_and_grad(problem: LightProblem, theta: Array) -> tuple[Array, Array]:
    """Loss $\\tfrac12|r|^2$ and its gradient in the parameters (reverse mode)."""
    return jax.value_and_grad(loss)(theta, problem)


@fit_jit
def loss_jit(problem: LightProblem, theta: Array) -> Array:
    return loss(theta, problem)


@fit_jit
def projected_jit(problem: LightProblem, theta: Array) -> tuple[Array, Array, Array]:
    return projected(theta, problem)


@fit_jit
def build_light(param: LightParametrisation, theta: Array) -> Any:
    """`param.build(theta)` compiled once per parametrisation shape (eagerly it would dispatch,
    and on the first call compile, a few dozen small operations)."""
    return param.build(theta)


def light_loss(scene: js.Scene, targets: PaintedTargets, material: js.Material, light: Any,
               light_index: int = 0, specular: SpecularFn | None = None) -> Array:
    """$\\tfrac12\\sum_i w_i |L(x_i) - C_i|^2$ with light `light_index` replaced by `light`
    (differentiable in the light's arrays, e.g. `jax.grad` with respect to its vertices).

    Example:
        ```python
        import jax
        import numpy as np
        import jaxshadow as js
        import inverse

        scene = js.Scene([js.PointLight([0.0, 0.0, 2.0], 3.0)])
        material = js.Material(ka=0.0, kd=0.5, ks=0.0, exponent=1.0)
        targets = inverse.PaintedTargets([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], [[0, 0, 1.0], [0, 0, 1.0]],
                                         [[0.10, 0.10, 0.10], [0.05, 0.05, 0.05]], eye=[0.0, -2.0, 2.0])
        grad = jax.grad(lambda pos: inverse.light_loss(scene, targets, material, js.PointLight(pos, 3.0)))
        grad(np.array([0.0, 0.0, 2.0]))   # d(loss)/d(light position)
        ```
    """
    with_spec = bool(np.any(np.asarray(material.ks) != 0))
    s = with_light(scene, light_index, light)
    t = targets
    model = shade(s, material, t.points, t.normals, t.eye, specular, with_spec)
    r = jnp.sqrt(t.weights) * (model - t.colours)
    return 0.5 * jnp.sum(r * r)

