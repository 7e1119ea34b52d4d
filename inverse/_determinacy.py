r"""Which parts of a light fit's answer the targets determine: the rules behind the flag
`"undetermined"` and the report's nearly undetermined parameters (`_diagnostics.assess`).

- **Nearly undetermined.** A standard error above `NEAR_POSITION_FRACTION` (1/4) of the scene
  size for a position, `NEAR_ORIENTATION` (30 degrees) for a rotation, `NEAR_LOG_SIZE` (log 2)
  for a log size, or the value itself for a power: the parameter is marked not determined,
  like an exactly undetermined one (`_identifiability`), with its finite error kept.
- **Undetermined position or power.** A light (not escaped, collapsed or unused) whose
  position or emitted power is not determined, exactly or nearly: the answer is one of many
  that paint the targets alike (a quad seen by a few targets only came back 40 % of the scene
  off with an exact fit; a quad 58 % off at a wrong minimum had its power's standard error
  above the power): flagged, not trusted; a `FitQualityWarning` when its whole position is
  undetermined (the report lists the parameters and where to paint either way).

  Judged on what the report vouches for where it is given (`quantities`: a several-light
  fit's centre coordinates and emitted power, `inverse._uncertainty`): such a quantity is not
  determined when it is not estimable (`_identifiability.quantity_error`: its gradient not
  orthogonal to the null directions) or its standard error is above `NEAR_POSITION_FRACTION`
  of the scene size (a centre coordinate) or above its value (the emitted power). A polygon's
  radiance trades with its size and a segment's power per length with its length, so their
  own standard errors may be far above their values while the emitted power is well
  determined (three lights from 30 % with 1 % noise: a quad's radiance standard error 3.9
  times its value, its emitted power's 0.65 times, the truth 0.1 of them from it): that alone
  is no flag. Otherwise (`fit_light`; position parameters the quantities do not cover, as a
  plane constraint's `a`, `b`) the parameters themselves: a position parameter or the power
  not determined, exactly or nearly.
"""

from __future__ import annotations

import math
from typing import Any

NEAR_POSITION_FRACTION = 0.25
NEAR_ORIENTATION = math.radians(30.0)
NEAR_LOG_SIZE = math.log(2.0)

POSITION = ("x", "y", "z", "a", "b")
ORIENTATION = ("rx", "ry", "rz", "ru", "rv")
_CENTRE = ("x", "y", "z")


def nearly_undetermined(names: tuple, std_errors: dict, values: dict, scale: float,
                        determined: dict) -> tuple:
    """The names of determined parameters whose standard error is above the module's limits."""
    out = []
    for nm in names:
        se = std_errors[nm]
        if not determined[nm] or not math.isfinite(se):
            continue
        base = nm.rsplit(".", 1)[-1]
        if base in POSITION:
            limit = NEAR_POSITION_FRACTION * scale
        elif base in ORIENTATION:
            limit = NEAR_ORIENTATION
        elif base.startswith("log_"):
            limit = NEAR_LOG_SIZE
        elif base == "power":
            limit = abs(values[nm])
        else:
            continue
        if se > limit and (base != "power" or values[nm] > 0):
            out.append(nm)
    return tuple(out)


def quantity_determined(name: str, quantity: Any, scale: float) -> bool:
    """Whether a covered quantity (`inverse._uncertainty.Quantity` named `name`) is determined,
    exactly and nearly (module docstring): estimable, and its standard error at most
    `NEAR_POSITION_FRACTION` of the scene size `scale` (m) for a centre coordinate, at most
    its value for a positive emitted power."""
    se = float(quantity.std_error)
    if not quantity.determined or not math.isfinite(se):
        return False
    base = name.rsplit(".", 1)[-1]
    if base in _CENTRE:
        return se <= NEAR_POSITION_FRACTION * scale
    if base == "flux":
        return se <= abs(float(quantity.value)) or not float(quantity.value) > 0
    return True


def quantity_label(name: str, params: tuple) -> str:
    """A covered quantity's name in `FitQuality.undetermined`: a flux with no size fitted (none of
    the light's `params` a log size) is its light's power factor, named as that parameter."""
    light, base = name.rsplit(".", 1)
    if base == "flux" and not any(p.rsplit(".", 1)[-1].startswith("log_") for p in params):
        return f"{light}.power"
    return name


def limit_text(nm: str, scale: float) -> str:
    """The nearly-undetermined limit of parameter or quantity `nm`, in words."""
    base = nm.rsplit(".", 1)[-1]
    if base in POSITION:
        return f"{NEAR_POSITION_FRACTION:g} of the scene size ({NEAR_POSITION_FRACTION * scale:.3g} m)"
    if base in ORIENTATION:
        return f"{math.degrees(NEAR_ORIENTATION):g} degrees"
    if base.startswith("log_"):
        return "a factor 2"
    return "its value"


def undetermined_lights(light_params: dict, determined: dict, near: tuple, scale: float,
                        quantities: dict | None, skip: set, messages: list, emit: list) -> dict:
    """`{light name: what of its position and emitted power is not determined}` by the module's
    rule, for the lights of `light_params` ({light name: its parameter names}) not in `skip`
    (escaped, collapsed, unused); `determined`: the parameters' (nearly undetermined ones,
    `near`, already False); `scale`: the scene size (m); `quantities`: {name: `Quantity`} the
    report covers, or None (judged by the parameters). Appends to `messages` a line for each
    covered quantity that is nearly undetermined (not said already of its parameter), and to
    `messages` and `emit` the warning for a light whose whole position is undetermined."""
    out = {}
    for nm, params in light_params.items():
        if nm in skip:
            continue
        pos = [p for p in params if p.rsplit(".", 1)[-1] in POSITION]
        covered = {q: v for q, v in (quantities or {}).items() if q.rsplit(".", 1)[0] == nm}
        if not covered:
            bad = tuple(p for p in params if (p in pos or p.endswith("power")) and not determined.get(p, True))
        else:
            loose = [q for q, v in covered.items() if not quantity_determined(q, v, scale)]
            for q in loose:
                label = quantity_label(q, params)
                if covered[q].determined and label not in near and determined.get(label, True):
                    messages.append(f"{q} is nearly undetermined by these targets: standard error "
                                    f"{covered[q].std_error:.3g} > {limit_text(q, scale)}.")
            # position parameters the quantities do not cover (a plane constraint's a, b): their own rule
            bad = tuple([quantity_label(q, params) for q in loose]
                        + [p for p in pos if p not in covered and not determined.get(p, True)])
            pos = [p for p in pos if p not in covered] + [q for q in covered if q.rsplit(".", 1)[-1] in _CENTRE]
        if bad:
            out[nm] = bad
            if pos and all(p in bad for p in pos):
                msg = (f"{nm}'s position is not determined by these targets (standard errors infinite or above "
                       f"{limit_text(pos[0], scale)}): it is one of many placements that paint them alike.")
                messages.append(msg)
                emit.append(msg)
    return out
