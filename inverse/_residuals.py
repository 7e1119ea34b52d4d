"""The light fit's residual pieces shared by the programs: `pinned` (the light's pose computed once
per evaluation inside a compiled program), and the public `light_loss`, the loss of
$\\sqrt{w}\\,(L_{model} - L_{painted})$ with the model of `js.shade` (Poulin eq. 5.14) as a plain
differentiable function of a light. The solvers' residual is `fit_lights`' problem
(`_multilight.LightsProblem`).
"""

from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

import jaxshadow as js
from jaxshadow import traced

from ._forward import SpecularFn, shade
from ._parametrisation import with_light
from ._targets import PaintedTargets


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

