"""A material per region: targets labelled by the surface (region) they are painted on.

Each region's $k_a, k_d, k_s$ and roughness are fitted from that region's targets alone
(`fit_material`), since the shading model (Poulin eq. 5.14) couples no two regions: the lights
are fixed, and a region's colours depend only on its own material.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

import jaxshadow as js

from ._material import MaterialFit, fit_material
from ._targets import PaintedTargets


@dataclasses.dataclass(frozen=True)
class RegionFit:
    """`materials` (region label -> `js.Material`), `fits` (label -> `MaterialFit`), `residual`
    `(N, 3)` (model - colours, in target order), `labels` `(N,)`; `material_at(labels)` gives the
    per-receiver `js.Material` of points with those labels (regions sharing one exponent)."""

    materials: dict
    fits: dict
    residual: np.ndarray
    labels: np.ndarray

    def material_at(self, labels: Any) -> js.Material:
        """A per-receiver `js.Material` (`(M, 3)` coefficients) for points with region `labels`
        `(M,)`; their regions must share one Phong exponent (`Material.exponent` is a scalar)."""
        lab = np.asarray(labels)
        unknown = sorted(set(lab.tolist()) - set(self.materials))
        if unknown:
            raise ValueError(f"material_at: unknown region label(s) {unknown}.")
        exps = {float(np.asarray(self.materials[x].exponent)) for x in set(lab.tolist())}
        if len(exps) > 1:
            raise ValueError(f"material_at: the regions have different exponents {sorted(exps)}; "
                             "shade each region with its own Material.")
        rows = {f: np.stack([np.asarray(getattr(self.materials[x], f), np.float64) for x in lab.tolist()])
                for f in ("ka", "kd", "ks")}
        return js.Material(rows["ka"], rows["kd"], rows["ks"], exps.pop())

    @property
    def report(self) -> str:
        return "\n".join(f"region {label!r} ({np.sum(self.labels == label)} targets):\n{fit.report}"
                         for label, fit in self.fits.items())


def fit_material_regions(scene: Any, targets: PaintedTargets, regions: Any, **kwargs: Any) -> RegionFit:
    """Fit one Phong material per region (issue 20 item 5).

    **Arguments:**

    - `scene`: a `js.Scene` (fixed).
    - `targets`: `PaintedTargets` (N targets).
    - `regions`: `(N,)` region labels (ints or strings), one per target.
    - `kwargs`: passed to `fit_material` for every region (`exponent`, `bounds`, ...).

    **Returns:** `RegionFit`. Raises `ValueError` when `regions` does not have one label per
    target, or a region has fewer than 3 targets (a region's 3 coefficients per channel need
    at least 3 colours).

    Example:
        ```python
        import numpy as np
        import jaxshadow as js
        import inverse

        scene = js.Scene([js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=10.0)])
        rng = np.random.default_rng(0)
        p = np.c_[rng.uniform(-1, 2, (12, 2)), np.zeros(12)]
        n = np.tile([0.0, 0.0, 1.0], (12, 1))
        eye = np.array([0.5, -2.0, 2.0])
        labels = np.repeat([0, 1], 6)                     # two painted regions
        red, blue = js.Material(kd=[0.7, 0.2, 0.1]), js.Material(kd=[0.1, 0.2, 0.7])
        colours = np.where(labels[:, None] == 0, js.shade(scene, red, p, n, eye), js.shade(scene, blue, p, n, eye))
        fit = inverse.fit_material_regions(scene, inverse.PaintedTargets(p, n, colours, eye), labels, exponent=1.0)
        print(fit.materials[0].kd, fit.materials[1].kd)
        ```
    """
    if not isinstance(targets, PaintedTargets):
        raise ValueError(f"fit_material_regions: targets must be PaintedTargets, got {type(targets).__name__}.")
    labels = np.asarray(regions)
    if labels.shape != (len(targets),):
        raise ValueError(f"fit_material_regions: regions must have shape ({len(targets)},), one label per target, "
                         f"got {labels.shape}.")
    groups = {label: np.flatnonzero(labels == label) for label in dict.fromkeys(labels.tolist())}
    for label, idx in groups.items():
        if idx.size < 3:
            raise ValueError(f"fit_material_regions: region {label!r} has {idx.size} targets; at least 3 are needed.")
    fits: dict[Any, MaterialFit] = {}
    residual = np.zeros((len(targets), 3))
    for label, idx in groups.items():
        fits[label] = fit_material(scene, targets.subset(idx), **kwargs)
        residual[idx] = fits[label].residual
    return RegionFit({k: f.material for k, f in fits.items()}, fits, residual, labels)
