"""What the fits return: results and reports of one shape for the material and the light fits.

Every report is a `FitReport`: the fitted parameters by name (`names`, `values`), how well the
targets determine them (`std_errors`, `determined`, `singular_values`, from
`_identifiability`), whether the targets are met, and warnings; each fit adds what is its own.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

import jaxshadow as js

from ._parametrisation import LightParametrisation


class UndeterminedParameterWarning(UserWarning):
    """A fitted parameter is not determined by the targets (flat direction of the residual)."""


@dataclasses.dataclass(frozen=True)
class FitReport:
    """What every fit reports.

    - `names`: the fitted parameters; `values`: name -> fitted value.
    - `std_errors`: name -> standard error in the parameter's units ($\\hat\\sigma^2
      (J^TJ)^{-1}$ over the determined parameters; inf when undetermined, 0 when held at a
      bound); `determined`: name -> bool (False for a null direction of the Jacobian).
    - `singular_values`: of the weighted residual Jacobian with unit-norm columns (scale-free;
      a zero means an undetermined combination).
    - `targets_met`: `(N,)` bool, all channels within the targets' tolerance, or None.
    - `warnings`: human-readable messages (undetermined parameters, solver trouble).
    """

    names: tuple
    values: dict
    std_errors: dict
    determined: dict
    singular_values: np.ndarray
    targets_met: np.ndarray | None
    warnings: tuple

    @property
    def trusted(self) -> bool:
        """False when a light fit's checks flagged the answer (`quality.flags`; light fits only)."""
        quality = getattr(self, "quality", None)
        return True if quality is None else bool(quality.trusted)

    def _headline(self) -> str:
        return "fit"

    def _extra_lines(self) -> list[str]:
        return []

    def __str__(self) -> str:
        lines = [self._headline()]
        for nm in self.names:
            flag = "" if self.determined.get(nm, True) else "  UNDETERMINED"
            lines.append(f"  {nm:10s} {self.values[nm]: .6g}  se={self.std_errors[nm]:.3g}{flag}")
        lines += self._extra_lines()
        quality = getattr(self, "quality", None)
        if quality is not None:
            lines += quality.lines()
        lines.append(f"  singular values (unit columns): {np.array2string(self.singular_values, precision=3)}")
        lines += [f"  warning: {w}" for w in self.warnings]
        return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class MaterialReport(FitReport):
    """A material fit (`FitReport`, names `ka[r]` ... `ks[b]` and `n` when fitted), and:

    - `exponent`, `exponent_fitted`: the roughness used, and whether it was searched.
    - `exponent_determined`: False when the targets do not pin $n$ down (the projected residual
      is flat up to a bound of `n_bounds`, or $k_s = 0$ in every channel, or its standard
      error is above 50 %); `exponent_interval`: the $n$ whose projected residual is within
      $4\\hat\\sigma^2$ of the minimum (an approximate 95 % profile interval).
    - `active_bounds`: names of the active constraints per channel, e.g. `ks[g]>=lower`.
    - `singular_values_raw`: of the Jacobian without column scaling.
    - `rss`, `dof`, `sigma`: weighted residual sum of squares, degrees of freedom,
      $\\hat\\sigma = \\sqrt{rss/dof}$.
    - `profile_exponents`, `profile_rss`: the variable-projection profile over the grid.
    - `weights`: the `(N, 3)` weights used.

    `values` also holds `n` when it was not fitted.
    """

    exponent: float
    exponent_fitted: bool
    exponent_determined: bool
    exponent_interval: tuple[float, float] | None
    active_bounds: tuple
    singular_values_raw: np.ndarray
    rss: float
    dof: int
    sigma: float
    profile_exponents: np.ndarray | None
    profile_rss: np.ndarray | None
    weights: np.ndarray

    def _headline(self) -> str:
        return f"material fit: rss={self.rss:.4g} dof={self.dof} sigma={self.sigma:.3g}"

    def _extra_lines(self) -> list[str]:
        return [f"  active: {', '.join(self.active_bounds)}"] if self.active_bounds else []


@dataclasses.dataclass(frozen=True)
class MaterialFit:
    """`material` (a `js.Material`), `residual` `(N, 3)` = model - colours (unweighted),
    `report` (`MaterialReport`)."""

    material: js.Material
    residual: np.ndarray
    report: MaterialReport


@dataclasses.dataclass(frozen=True)
class LightsFit:
    """A light fit (`fit_lights`, and `fit_light`'s one light): `scene` (fitted poses and
    powers), `lights` (the fitted lights, in the order of `fit_lights(lights=...)`), `powers (J,)`
    (factors of the given radiance; 1 where the power is not fitted), `material` (as given, or
    projected), `residual (N, 3)` = model - colours (unweighted; for a target painted as a
    `ColourRange`, the distance outside its range, 0 inside), `report` (a `LightsReport`; from
    `fit_light` its subclass `LightReport`, with the solver's starts as well), `theta (P,)` the
    pose parameters, `parametrisations` (per fitted light, None for a power-only light)."""

    scene: js.Scene
    lights: tuple
    powers: np.ndarray
    material: js.Material
    residual: np.ndarray
    report: FitReport
    theta: np.ndarray
    parametrisations: tuple


@dataclasses.dataclass(frozen=True)
class LightFit(LightsFit):
    """`fit_light`'s answer: a `LightsFit` of one light, with `light` (= `lights[0]`) and
    `parametrisation` (= `parametrisations[0]`); `report` is a `LightReport` (a `LightsReport`
    with the solver's starts, steps and screening as well)."""

    @property
    def light(self) -> Any:
        """The fitted light (`lights[0]`)."""
        return self.lights[0]

    @property
    def parametrisation(self) -> LightParametrisation:
        """The light's parametrisation (`parametrisations[0]`)."""
        return self.parametrisations[0]


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
