r"""Competing placements of a light fit (the rule is `inverse._diagnostics`' "Competing
placements"): which other refined placements explain the targets about as well as the answer."""

from __future__ import annotations

import math

import numpy as np

RIVAL_DISTANCE = 0.01
RIVAL_SIGMAS = 3.0
RIVAL_TURN = math.radians(5.0)
_ORIENTATION = ("rx", "ry", "rz", "ru", "rv")


def rival_allowance(n_params: int) -> float:
    r"""How much more $\chi^2$ than the answer's a placement may have and still compete with it
    (module docstring): $n + 3\sqrt{2n}$ for $n$ fitted parameters."""
    n = max(int(n_params), 1)
    return n + 3.0 * math.sqrt(2.0 * n)


def _turn(a: np.ndarray, b: np.ndarray, signed: bool) -> float:
    """The angle (rad) between unit vectors `a`, `b`; `signed=False`: between their lines."""
    c = float(a @ b)
    return math.atan2(float(np.linalg.norm(np.cross(a, b))), c if signed else abs(c))


def rival_placements(answer: dict, others: list, chi2: float, n_params: int, scale: float,
                     std_errors: dict, light_params: dict) -> tuple:
    r"""The competing placements (module docstring) among `others`.

    **Arguments:** `answer`: {light name: pose}, a pose a dict with `kind` (the
    parametrisation's), `centre (3,)` (m), `axis (3,)` or None (a polygon's unit normal, a
    segment's unit direction), `power` (a factor of the given emission); `others`: `[(chi2,
    {light name: pose}), ...]` the other refined placements with their $\chi^2$; `chi2`: the
    answer's; `n_params`; `scale` (m); `std_errors`, `light_params` as in `assess`.

    **Returns:** `((excess chi2, {light name: pose}, (names of the lights that differ)), ...)`,
    least excess first."""
    allowed = rival_allowance(n_params)

    def se_of(nm: str, bases: tuple) -> float:
        s = [std_errors.get(p, math.inf) for p in light_params.get(nm, ()) if p.rsplit(".", 1)[-1] in bases]
        return math.sqrt(sum(x * x for x in s)) if s else 0.0

    out = []
    for c2, poses in others:
        if not (math.isfinite(c2) and c2 - chi2 <= allowed):
            continue
        differ = []
        for nm, pose in poses.items():
            mates = [m for m, q in answer.items() if q["kind"] == pose["kind"]]
            if not mates:
                continue
            d = [float(np.linalg.norm(np.asarray(pose["centre"]) - np.asarray(answer[m]["centre"]))) for m in mates]
            mate = mates[int(np.argmin(d))]
            se_c = se_of(mate, ("x", "y", "z", "a", "b"))
            moved = math.isfinite(se_c) and min(d) > max(RIVAL_DISTANCE * scale, RIVAL_SIGMAS * se_c)
            a, b = pose.get("axis"), answer[mate].get("axis")
            if a is not None and b is not None:
                se_r = max([std_errors.get(p, math.inf) for p in light_params.get(mate, ())
                            if p.rsplit(".", 1)[-1] in _ORIENTATION] or [0.0])
                turn = _turn(np.asarray(a, np.float64), np.asarray(b, np.float64), pose["kind"] == "polygon")
                moved |= math.isfinite(se_r) and turn > max(RIVAL_TURN, RIVAL_SIGMAS * se_r)
            if moved:
                differ.append(nm)
        if differ:
            out.append((float(c2 - chi2), poses, tuple(differ)))
    return tuple(sorted(out, key=lambda x: x[0]))
