r"""Integrands: what a light contributes per unit emission at a receiver, given its visibility.

An integrand has one method per light kind (`AbstractLight.kind`): `polygon` (the whole light
seen), `contour` (a polygon light's visible region, given by its boundary edges; also as
`contour_total(..., contour_sums(..., starts, ends))`, where `contour_sums` is a pytree of sums
over the edges, so a boundary can be given in parts and their sums added), `segment`,
`point`, `directional`; each takes one receiver `p (3,)`, its unit normal `n (3,)` and the eye
`e (3,)`, read by `Phong` only: an integrand that reads none (`reads_eye = False`) is given
None. It also declares what it needs: what the shadow engine must hand it on the host
(`host_plan`: `Lambert`'s contour sum is a sum of edge terms that the engine adds up itself,
`"lambert"`; other integrands need the boundary's decoded points, `"points"`), and whether it
reads the eye (`reads_eye`).
"""

from __future__ import annotations

from typing import Any, ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._kernels.clip import (
    contour_form_factor_sums,
    contour_form_factor_total,
    lit_form_factor,
    masked_contour_form_factor,
    visible_segment_sum,
)
from .._kernels.linear import linear_irradiance_kernel
from .._kernels.point import directional_irradiance_kernel, point_irradiance_kernel
from .._kernels.specular import (
    DEFAULT_DEGREE,
    contour_specular_kernel,
    contour_specular_sums,
    contour_specular_total,
    directional_specular_kernel,
    point_specular_kernel,
    polygon_specular_kernel,
    segment_specular_kernel,
)

# What a plan carries for polygon lights' penumbra receivers (`plan(..., produce=...)`):
# "classes" nothing but the classes and counts; "codes" the boundary's endpoint codes (decoded
# in JAX: derivatives flow); "points" the decoded points; "lambert" each receiver's Lambert sum.
PRODUCE = ("classes", "codes", "points", "lambert")


class AbstractIntegrand(eqx.Module):
    """The integrand interface (see the module docstring). `shape`: the shape of one receiver's
    value per light (`()`: a scalar; `Both`: `(2,)`)."""

    host_plan: ClassVar[str] = "points"
    reads_eye: ClassVar[bool] = True
    shape: ClassVar[tuple[int, ...]] = ()


class Lambert(AbstractIntegrand):
    """Irradiance per unit emission: $\\pi F$ for polygons (per unit radiance), $E/\\Phi$ for
    segments, $E/I$ for point lights, $E/E_0$ for directional lights."""

    host_plan: ClassVar[str] = "lambert"
    reads_eye: ClassVar[bool] = False

    def polygon(self, p, n, e, verts):
        return jnp.pi * lit_form_factor(p, n, verts)

    def contour(self, p, n, e, verts, starts, ends):
        return jnp.pi * masked_contour_form_factor(p, n, verts, starts, ends)

    def contour_sums(self, p, n, e, verts, starts, ends):
        return contour_form_factor_sums(p, n, starts, ends)

    def contour_total(self, p, n, e, verts, sums):
        return jnp.pi * contour_form_factor_total(p, verts, sums)

    def segment(self, p, n, e, a, b, light):
        return linear_irradiance_kernel(p, n, a, b, light.exponent)

    def point(self, p, n, e, x):
        return point_irradiance_kernel(p, n, x)

    def directional(self, p, n, e, d):
        return directional_irradiance_kernel(n, d)


class Phong(AbstractIntegrand):
    """Phong-lobe integral per unit emission (Poulin eqs. 3.11, 3.12): `exponent` differentiable,
    `method` and `degree` static."""

    exponent: Any
    method: str = eqx.field(static=True, default="chebyshev")
    degree: int = eqx.field(static=True, default=DEFAULT_DEGREE)

    def polygon(self, p, n, e, verts):
        return polygon_specular_kernel(p, n, e, verts, self.exponent, method=self.method, degree=self.degree)

    def contour(self, p, n, e, verts, starts, ends):
        return contour_specular_kernel(p, n, e, starts, ends, self.exponent, method=self.method, degree=self.degree)

    def contour_sums(self, p, n, e, verts, starts, ends):
        return contour_specular_sums(p, n, e, starts, ends, self.exponent, method=self.method, degree=self.degree)

    def contour_total(self, p, n, e, verts, sums):
        return contour_specular_total(p, n, e, sums)

    def segment(self, p, n, e, a, b, light):
        prof = None if light.profile == "isotropic" else jnp.asarray(float(light.exponent), p.dtype)
        return segment_specular_kernel(p, n, e, a, b, self.exponent, prof, method=self.method, degree=self.degree)

    def point(self, p, n, e, x):
        return point_specular_kernel(p, n, e, x, self.exponent)

    def directional(self, p, n, e, d):
        return directional_specular_kernel(p, n, e, d, self.exponent)


class Both(AbstractIntegrand):
    """`Lambert` and `Phong` at once: each method returns `(2,)`, the irradiance integrand then
    the specular one, from one visibility (one engine call and one decoding of the visible
    region's boundary per receiver instead of two). Inside compiled programs only
    (`compiled.traced_values`)."""

    phong: Phong
    shape: ClassVar[tuple[int, ...]] = (2,)

    def _two(self, name: str, *args: Any) -> Array:
        return jnp.stack([getattr(Lambert(), name)(*args), getattr(self.phong, name)(*args)])

    def polygon(self, p, n, e, verts):
        return self._two("polygon", p, n, e, verts)

    def contour(self, p, n, e, verts, starts, ends):
        return self._two("contour", p, n, e, verts, starts, ends)

    def contour_sums(self, p, n, e, verts, starts, ends):
        return Lambert().contour_sums(p, n, e, verts, starts, ends), self.phong.contour_sums(p, n, e, verts, starts, ends)

    def contour_total(self, p, n, e, verts, sums):
        return jnp.stack([Lambert().contour_total(p, n, e, verts, sums[0]), self.phong.contour_total(p, n, e, verts, sums[1])])

    def segment(self, p, n, e, a, b, light):
        return self._two("segment", p, n, e, a, b, light)

    def point(self, p, n, e, x):
        return self._two("point", p, n, e, x)

    def directional(self, p, n, e, d):
        return self._two("directional", p, n, e, d)


def segment_visible(integ: Any, p: Float[Array, "3"], n: Float[Array, "3"], e: Float[Array, "3"] | None,
                    a: Float[Array, "3"], b: Float[Array, "3"], light: Any, occ: Float[Array, "m k 3"],
                    pieces: int | None = None, receivers: int = 1) -> Array:
    """The segment integrand summed over the visible pieces of `a -> b` (occluders `occ`), a batch
    of `pieces` at a time (`visible_segment_sum`; static, by default sized for `receivers`, the
    receivers the caller evaluates at once)."""
    return visible_segment_sum(p, a, b, occ, lambda u, v: integ.segment(p, n, e, u, v, light), pieces, receivers)
