"""The search options of the light fits, in one object shared by `fit_light` and `fit_lights`
(`inverse.Search`), and the checks both entry points make of their options (`constraints`).

`fit_light` is the one-light case of the same search: the same starts (`_multistart.make_starts`:
the given pose first, then a scrambled Sobol stratification of the region the spreads span),
the same solver objects (`_solvers`), the same constraint dictionary and the same fit type
(`LightFit` is a `LightsFit` of one light). The options that only several lights have (`sweeps`,
`grid`, `placement`, `search_targets`) are refused by `fit_light` when set.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from ._parametrisation import Box, Outside, Plane

# Starts when `Search.starts` is None: one light is searched from 64 starts (screened to the
# solver's `refine` best); several lights from 16 each (each light's sweeps screen them the same
# way, and the global placement adds its own candidates).
STARTS_ONE_LIGHT = 64
STARTS_PER_LIGHT = 16
PLACEMENTS = ("global", "local")


@dataclasses.dataclass(frozen=True)
class Search:
    """Where and how a light fit searches: one object for `fit_light` and `fit_lights` (each also
    takes these fields as keywords, e.g. `fit_lights(..., starts=8, seed=1)`).

    **Arguments:**

    - `starts`: starts per light (the given pose first, then a Sobol stratification within
      `search_radius` scene sizes, `orientation_spread` rad, `size_spread` relative, seeded by
      `seed`); None: 64 for `fit_light`, 16 per light for `fit_lights`. The solver screens them to
      its `refine` best (`inverse.LM(refine=...)`).
    - `search_radius` (scene sizes), `orientation_spread` (rad), `size_spread` (relative): the
      half-widths of the region the starts stratify; `seed`: its stratification (light `j` of
      `fit_lights` uses `seed + j`).
    - `sweeps` (several lights): how many times each light's own multistart runs (in turn, the
      others at their current best) before the joint refinement; >= 1.
    - `grid` (several lights): positions per light screened in a greedy placement around the
      given poses instead of the global placement; 0: the global placement.
    - `placement` (several lights): `"global"` (screen each light's pose over the whole region
      above the targets, as well as searching from the given poses) or `"local"` (the given poses
      only).
    - `search_targets` (several lights): indices (or an `(N,)` bool mask) of the targets the
      search uses; the joint refinement then uses every target.

    Example:
        ```python
        import inverse

        search = inverse.Search(starts=8, search_radius=0.3, seed=1)
        # inverse.fit_light(scene, targets, material, search=search)
        # inverse.fit_lights(scene, targets, material, search=search, placement="local")  # a field by name
        ```
    """

    starts: int | None = None
    search_radius: float = 0.5
    orientation_spread: float = 0.5
    size_spread: float = 0.5
    seed: int = 0
    sweeps: int = 2
    grid: int = 0
    placement: str = "global"
    search_targets: Any = None


SEARCH_FIELDS = tuple(f.name for f in dataclasses.fields(Search))
_SEVERAL_LIGHTS = ("sweeps", "grid", "placement", "search_targets")


def search_options(search: Any, keywords: dict[str, Any], who: str, *, several: bool) -> Search:
    """`search` (default `Search()`) with the fields given as keywords replaced, checked
    (ValueError, `who` names the entry point), `starts` resolved to its default for one light
    or several (`several`). Keywords that are not fields are a `TypeError`, as Python's own."""
    unknown = sorted(set(keywords) - set(SEARCH_FIELDS))
    if unknown:
        raise TypeError(f"{who}() got unexpected keyword argument(s) {unknown}.")
    if search is None:
        search = Search()
    elif not isinstance(search, Search):
        raise ValueError(f"{who}: search must be an inverse.Search, got {type(search).__name__}.")
    s = dataclasses.replace(search, **keywords)
    if s.starts is None:
        s = dataclasses.replace(s, starts=STARTS_PER_LIGHT if several else STARTS_ONE_LIGHT)
    if int(s.starts) < 1:
        raise ValueError(f"{who}: starts must be >= 1, got {s.starts}.")
    if several:
        if s.placement not in PLACEMENTS:
            raise ValueError(f"{who}: placement must be 'global' or 'local', got {s.placement!r}.")
        if int(s.sweeps) < 1:
            raise ValueError(f"{who}: sweeps must be >= 1, got {s.sweeps}.")
        if int(s.grid) < 0:
            raise ValueError(f"{who}: grid must be >= 0, got {s.grid}.")
    else:
        default = Search()
        set_ = [f for f in _SEVERAL_LIGHTS if f != "search_targets" and getattr(s, f) != getattr(default, f)]
        set_ += ["search_targets"] if s.search_targets is not None else []
        if set_:
            raise ValueError(f"{who}: {', '.join(set_)} apply to several lights (inverse.fit_lights).")
    return s


def checked_constraints(constraints: Any, idx: list[int], who: str, *, several: bool) -> dict:
    """`constraints` (`{light index: Plane | Box | Outside, "budget": B}`, or None) checked
    against the fitted lights `idx` (ValueError): a dict with integer keys and the budget as a
    float. One light (`several=False`): a `Plane` or a `Box`, no budget (its power is not fitted)."""
    cons = {} if constraints is None else dict(constraints)
    if not several:
        if "budget" in cons:
            raise ValueError(f"{who}: a power budget needs several lights' powers (inverse.fit_lights).")
        for c in cons.values():
            if not isinstance(c, (Plane, Box)):
                raise ValueError(f"{who}: a constraint must be inverse.Plane or inverse.Box, got "
                                 f"{type(c).__name__}.")
    for k in cons:
        if k == "budget":
            continue
        if int(k) not in idx:
            raise ValueError(f"{who}: a constraint for light {k}, which is not fitted.")
        if not isinstance(cons[k], (Plane, Box, Outside)):
            raise ValueError(f"{who}: constraints must be inverse.Plane, inverse.Box or inverse.Outside, got "
                             f"{type(cons[k]).__name__}.")
    return {(k if k == "budget" else int(k)): c for k, c in cons.items()}
