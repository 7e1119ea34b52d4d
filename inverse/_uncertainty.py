r"""What a several-light fit's uncertainties cover and mean (`LightsReport.quantities`).

**Covered quantities.** The targets see a light through where it is and how much it emits;
its radiance alone trades with its size (a quad twice as large at half the radiance paints the
far targets alike), a segment's power per length with its length. Per fitted light $i$:

- its centre `light{i}.x`, `.y`, `.z` (m: a polygon's vertex mean, a segment's midpoint, a
  point light's position);
- its emitted power `light{i}.flux`, as a factor of the given (start) light's emitted power:
  $p\,e^{\sum_k \log s_k}$, $p$ the power factor and $\log s_k$ its fitted log sizes (a
  polygon's two, a segment's length; none for a point light). Only where the power is fitted
  and not a gauge. The power factor itself (`light{i}.power`, the radiance or power per
  length) is not covered: where the size is fitted it trades with it, and its linearised
  standard error can be many times too small (a segment's power 8 standard errors off at 1 %
  noise, its emitted power within one).

**Standard error** (`std_error`): the delta method on the fit's linearised covariance $C$
(`_identifiability`, over the estimable directions), $s_q = \sqrt{g^\top C g}$, $g$ the quantity's gradient in the fitted
parameters; infinite when $g$ is not orthogonal to the null directions (not estimable:
`_identifiability.quantity_error`; a flux stays determined where radiance and size trade
exactly, the trade leaving it unchanged). It is the marginal
linearised error: $\hat q \pm 2 s_q$ covers the truth 95 % of the time only where the model is
close to linear over that interval.

**Interval** (`interval`, the half-width): the linearised 95 % joint confidence region of all
$p$ fitted parameters, $\{\delta: \delta^\top C^{+} \delta \le \chi^2_{p,0.95}\}$, projected on the
quantity: $\hat q \pm \sqrt{\chi^2_{p,0.95}}\, s_q$ (Bates and Watts, *Nonlinear Regression
Analysis and Its Applications*, 1988, sec. 2.3: linearised joint regions; a projection of the
joint region is a simultaneous interval, Scheffe's method). With 95 % probability (for a model
linear over the region) the truth lies in the joint region, and then every covered quantity of
the fit lies within its interval at once. Where the residual is curved along a nearly flat
direction (the size/radiance trade; an undetermined direction of a segment) the marginal
$\pm 2 s_q$ is too short, while the joint region, $\sqrt{\chi^2_{p,0.95}} / 2$ times wider
(2.9 for $p = 20$), still covers the truth: this is the interval a fit of several lights
vouches for. $p$ counts the directions the targets determine: the free parameters less the null
directions (`_identifiability`).

**Competing placements** (flag `"competing_placements"`, `_diagnostics.rival_placements`):
another placement of the lights explains the targets within the noise, and the linearisation
at the answer knows nothing of it (the truth was 4.9 and 12 standard errors from an answer
whose $\chi^2$ was below the truth's). Then every light's centre coordinate, power and
emitted power has its standard error and interval widened by the largest distance, along that
quantity, from the answer to a rival: $s' = s + \max_r |q_r - \hat q|$, likewise the
interval's half-width (`widened`). If the truth lies in a rival's basin, its error is about
$|q_r - \hat q|$ plus that placement's own noise (about $2 s$ at 95 %), at most $2 s'$: the
stated $\pm 2 s'$ covers the answer's and the rival's intervals together. Chosen over
profile-likelihood intervals because the rivals are already refined minima (no more solves) and
a union of basins is not one interval anyway; the flag tells the user the answer is one of
several.
"""

from __future__ import annotations

import dataclasses
import math

from scipy.stats import chi2

LEVEL = 0.95  # the joint region's confidence level


@dataclasses.dataclass(frozen=True)
class Quantity:
    """A covered quantity (module docstring): `value` (centres in m); `std_error` (the marginal
    linearised standard error, positions in m; inf when undetermined); `interval`: the half-width
    of its projected joint 95 % region (inf when undetermined); `determined` (False when
    undetermined, exactly or nearly: the report's `determined` of the parameters it involves)."""

    value: float
    std_error: float
    interval: float
    determined: bool


def joint_factor(n_params: int, level: float = LEVEL) -> float:
    """$\\sqrt{\\chi^2_{p}(\\text{level})}$: an interval's half-width over the standard error
    for the projection of the `level` joint region of `n_params` parameters (1.96 for one)."""
    return math.sqrt(float(chi2.ppf(level, max(int(n_params), 1))))


def light_quantities(names: tuple, values: dict, idx: list) -> dict[str, tuple[float, dict[str, float]]]:
    """`{quantity name: (value, {parameter name: d quantity / d parameter})}` for the covered
    quantities of the lights `idx` (module docstring), in the fit's own parameters (the report's
    `values`: a position's value and gradient in the parameter vector's units)."""
    out: dict = {}
    for i in idx:
        own = [nm for nm in names if nm.startswith(f"light{i}.")]
        for ax in "xyz":
            nm = f"light{i}.{ax}"
            if nm in own:
                out[nm] = (values[nm], {nm: 1.0})
        pw = f"light{i}.power"
        if pw not in own:
            continue
        sizes = [nm for nm in own if nm.rsplit(".", 1)[-1].startswith("log_")]
        f = math.exp(sum(values[nm] for nm in sizes))
        grad = {pw: f}
        grad.update({nm: values[pw] * f for nm in sizes})
        out[f"light{i}.flux"] = (values[pw] * f, grad)
    return out


def widened(std_errors: dict, quantities: dict, answer: dict, rivals: tuple) -> tuple[dict, dict]:
    """`(std_errors, quantities)` widened over the competing placements (module docstring).

    `std_errors`: the report's `{name: standard error}` (`light{i}.x`, ..., `light{i}.power`;
    centres in m); `quantities`: `{name: Quantity}`; `answer`: `{light name: pose}` and each
    rival `(excess chi2, {light name: pose}, differing lights)` (`_diagnostics.rival_placements`):
    a pose's `centre (3,)` (m), `power` (a factor of the given emission) and `emitted` (its emitted
    power, W). Lights are matched by name; unchanged when there are no rivals."""
    if not rivals:
        return std_errors, quantities
    se, q = dict(std_errors), dict(quantities)
    for nm, pose in answer.items():
        spread = {ax: max(abs(float(r[1][nm]["centre"][c]) - float(pose["centre"][c])) for r in rivals
                          if nm in r[1]) if any(nm in r[1] for r in rivals) else 0.0
                  for c, ax in enumerate("xyz")}
        spread["power"] = max([abs(float(r[1][nm]["power"]) - float(pose["power"])) for r in rivals if nm in r[1]]
                              or [0.0])
        ratio = max([abs(float(r[1][nm]["emitted"]) / float(pose["emitted"]) - 1.0) for r in rivals
                     if nm in r[1] and float(pose["emitted"]) > 0] or [0.0])
        for key, d in spread.items():
            if f"{nm}.{key}" in se:
                se[f"{nm}.{key}"] = se[f"{nm}.{key}"] + d
        for key in ("x", "y", "z", "flux"):
            name = f"{nm}.{key}"
            if name in q:
                d = spread[key] if key != "flux" else ratio * abs(q[name].value)
                q[name] = dataclasses.replace(q[name], std_error=q[name].std_error + d, interval=q[name].interval + d)
    return se, q
