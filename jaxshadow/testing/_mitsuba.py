r"""Mitsuba 3 images of catalogue scenes and their derivatives, as estimates with standard errors.

`render_estimates` renders a scene's window (`ReferenceScene.mitsuba_dict(camera=True)`) with a
Mitsuba integrator and differentiates the image with respect to a translation of the light, in
forward mode (`dr.forward_to`, one pass per parameter) or in reverse mode (`dr.backward` of a
weighted sum of the pixels). Standard errors come from `batches` independent renders (seeds):
compare with `dof = batches - 1`. Pixel values are converted to irradiance (times
$\pi$ / reflectance), so they estimate `ReferenceScene.image(...).irradiance` and its derivatives.

The light moves through the documented route for derived parameters: a translation `t`
(`mi.Vector3f`, gradient enabled) is applied to `light_000.vertex_positions` (or composed with
`light_000.to_world` for the cylinder standing in for a linear light), its tangent is pushed to the
scene parameter with `dr.forward_to(..., flags=dr.ADFlag.ClearEdges)` before rendering, and the
image's gradient is read after `dr.forward_to(image)`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from ._catalogue import ReferenceScene
from ._scenes import LIGHT_TRANSLATION

AXES = {"light.tx": 0, "light.ty": 1, "light.tz": 2}


def _mi() -> tuple[Any, Any]:
    from .._io.mitsuba_io import import_mitsuba as select_variant

    mi = select_variant()
    import drjit as dr

    return mi, dr


KINDS = ("direct", "direct_emitter", "direct_projective")


def integrator(kind: str, **options: Any) -> Any:
    """A Mitsuba integrator by kind: `"direct"` (Mitsuba's C++ direct integrator, differentiated
    by plain AD; emitter and BSDF samples combined by MIS), `"direct_emitter"` (the same with
    emitter samples only: `bsdf_samples = 0`), or `"direct_projective"` (projective sampling of
    the visibility boundary; `sppp = 0` since the camera sees no moving silhouette, `guiding`
    default `"none"`)."""
    mi, _ = _mi()
    if kind == "direct":
        return mi.load_dict({"type": "direct", **options})
    if kind == "direct_emitter":
        return mi.load_dict({"type": "direct", "emitter_samples": 1, "bsdf_samples": 0, **options})
    if kind == "direct_projective":
        it = mi.load_dict({"type": "direct_projective", "sppp": 0, "guiding": "none", **options})
        it.sample_border_warning = False  # nothing enters or leaves the view
        return it
    raise ValueError(f"integrator: kind must be one of {KINDS}, got {kind!r}.")


@dataclass
class ImageEstimates:
    """Per-pixel means over `batches` renders and their standard errors (irradiance units):
    `irradiance`, `irradiance_err` `(R, R, 3)`; `d_irradiance`, `d_irradiance_err`
    `{parameter: (R, R, 3)}`; `dof` = batches - 1; `seconds` per batch (all passes)."""

    irradiance: np.ndarray
    irradiance_err: np.ndarray
    d_irradiance: dict[str, np.ndarray]
    d_irradiance_err: dict[str, np.ndarray]
    dof: int
    seconds: float


class _Twin:
    """A loaded Mitsuba twin of a reference scene with a movable light."""

    def __init__(self, ref: ReferenceScene, resolution: int, reflectance: float):
        mi, dr = _mi()
        self.mi, self.dr = mi, dr
        self.scene = mi.load_dict(ref.mitsuba_dict(camera=True, resolution=resolution, reflectance=reflectance))
        self.params = mi.traverse(self.scene)
        self.key = ref.mitsuba_light_key
        self.transform = self.key.endswith("to_world")
        self.initial = mi.Transform4f(self.params[self.key]) if self.transform else dr.unravel(mi.Point3f, self.params[self.key])
        self.scale = math.pi / reflectance

    def move(self, tangent: tuple[float, float, float] | None) -> Any:
        """Attach the light to a translation `t` = 0 (with `tangent` pushed to the scene
        parameter in forward mode); returns `t`."""
        mi, dr = self.mi, self.dr
        t = mi.Vector3f(0.0)
        dr.enable_grad(t)
        self.params[self.key] = (
            mi.Transform4f().translate(t) @ self.initial if self.transform else dr.ravel(self.initial + t)
        )
        if tangent is not None:
            dr.set_grad(t, mi.Vector3f(*tangent))
            dr.forward_to(self.params[self.key], flags=dr.ADFlag.ClearEdges)
        self.params.update()
        return t

    def reset(self) -> None:
        self.params[self.key] = self.initial if self.transform else self.dr.ravel(self.initial)
        self.params.update()

    def render(self, integ: Any, spp: int, seed: int) -> Any:
        return self.mi.render(self.scene, self.params, integrator=integ, spp=spp, seed=seed, seed_grad=seed + 7919)


def render_estimates(
    ref: ReferenceScene,
    integ: Any,
    *,
    spp: int = 256,
    batches: int = 16,
    resolution: int = 8,
    parameters: tuple[str, ...] = LIGHT_TRANSLATION,
    seed: int = 0,
    reflectance: float = 1.0,
) -> ImageEstimates:
    """Forward-mode estimates of the pixel means of $E$ and of their derivatives with respect to
    the light translations in `parameters` (see the module docstring).

    **Arguments:** `ref` (a catalogue scene), `integ` (a Mitsuba integrator, e.g.
    `integrator("direct")`), `spp` per render, `batches` independent renders (seeds
    `seed .. seed + batches - 1`, >= 2), `resolution` (pixels per side), `parameters`
    (a subset of `LIGHT_TRANSLATION`), `reflectance` of the receiver.

    **Returns:** `ImageEstimates`.
    """
    bad = [p for p in parameters if p not in AXES]
    if bad or batches < 2:
        raise ValueError(f"render_estimates: parameters must be light translations and batches >= 2 (got {bad}, {batches}).")
    twin = _Twin(ref, resolution, reflectance)
    dr = twin.dr
    values, derivs = [], {p: [] for p in parameters}
    t0 = time.perf_counter()
    for b in range(batches):
        for i, p in enumerate(parameters):
            tangent = [0.0, 0.0, 0.0]
            tangent[AXES[p]] = 1.0
            twin.move(tuple(tangent))
            img = twin.render(integ, spp, seed + b)
            dr.forward_to(img)
            derivs[p].append(np.asarray(dr.grad(img), np.float64) * twin.scale)
            if i == 0:
                values.append(np.asarray(img, np.float64) * twin.scale)
            twin.reset()
    seconds = (time.perf_counter() - t0) / batches

    def stats(xs: list) -> tuple[np.ndarray, np.ndarray]:
        a = np.stack(xs)
        return a.mean(axis=0), a.std(axis=0, ddof=1) / math.sqrt(a.shape[0])

    v, ve = stats(values)
    d = {p: stats(derivs[p]) for p in parameters}
    return ImageEstimates(v, ve, {p: m for p, (m, _) in d.items()}, {p: e for p, (_, e) in d.items()}, batches - 1, seconds)


def backward_estimates(
    ref: ReferenceScene,
    integ: Any,
    weights: np.ndarray,
    *,
    spp: int = 256,
    batches: int = 16,
    resolution: int = 8,
    seed: int = 0,
    reflectance: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, float]:
    r"""Reverse-mode estimate of $\partial(\sum_{pixels} w \cdot E)/\partial t$ for the light
    translation $t$ (3 components) by `dr.backward`: `(mean (3,), stderr (3,), seconds per
    batch)` over `batches` renders; `weights` `(R, R, 3)`."""
    mi = _mi()[0]
    twin = _Twin(ref, resolution, reflectance)
    dr = twin.dr
    w = mi.TensorXf(np.asarray(weights, np.float32))
    grads = []
    t0 = time.perf_counter()
    for b in range(batches):
        t = twin.move(None)
        img = twin.render(integ, spp, seed + b)
        dr.backward(dr.sum(img * w, axis=None) * twin.scale)
        grads.append(np.asarray(dr.grad(t), np.float64).ravel())
        twin.reset()
    a = np.stack(grads)
    return a.mean(axis=0), a.std(axis=0, ddof=1) / math.sqrt(batches), (time.perf_counter() - t0) / batches
