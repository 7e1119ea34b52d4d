"""Test helper: the several-light problem of fitting only the lights' positions to noise-free
targets painted by a known scene over 40 floor points (`inverse._multilight.LightsProblem`)."""

import jax.numpy as jnp

import inverse
import jaxshadow as js
from benchmarks.inverse_scenes import THREE_LIGHTS_EYE as EYE
from benchmarks.inverse_scenes import floor_receivers
from inverse._multilight import LightsProblem
from inverse._parametrisation import LightParametrisation


def position_problem(true: js.Scene, material: js.Material, bound: str):
    """`(problem, params, targets, size)`: the lights of `true` fitted by position only, each
    parameter the centre's offset from the true light over the scene size (0 is the truth),
    bounded by `bound` (`LightParametrisation`'s "sigmoid" or "none")."""
    pts, nrm = floor_receivers(40, seed=2)
    t = inverse.PaintedTargets(pts, nrm, js.shade(true, material, pts, nrm, EYE), EYE)
    size = inverse.scene_size(true, t)
    params = tuple(LightParametrisation(light, i, ("position",), None, size, bound)
                   for i, light in enumerate(true.lights))
    z = jnp.zeros((len(t), 3))
    problem = LightsProblem(params, tuple(true.lights), true, material, t, z, z, (0, 3), True, False, False, None)
    return problem, params, t, size
