"""The escape bound of `fit_lights`' joint refinements: placements in which a fitted light left
the region it can light the targets from are not ranked while another placement keeps every
light there.

The LM refinements (the global placement's refine-then-rank, `fit_lights`' sweeps and its final
joint solve) start several rows and keep the best by `_global_placement.ranking_losses`. A row can
diverge: a light pushed ever farther while its power grows (a light 3-10 % of the scene off
ending at 496, 1.5e6 and 2e110 times the scene), or below the receivers, where it lights nothing
and the others explain what they can. Such a row says nothing about where the light is, so it is
dropped from the ranking (its loss made infinite) unless every row escaped; an answer that ends
there anyway is flagged by the report (`_diagnostics.escape_reason`, flag `"escaped"`), with the
same bound: a light's centre farther than `ESCAPE_FACTOR` times the targets' extent from every
target, or behind every target's tangent plane.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ._diagnostics import ESCAPE_FACTOR, weighted_targets


def escaped_rows(problem: Any, thetas: np.ndarray) -> np.ndarray:
    """`(S,)` bool: the placements `thetas (S, Pt)` (rows of `problem`'s parameters) in which some
    fitted light with a fitted position has its centre farther than `ESCAPE_FACTOR` times the
    targets' bounding-box diagonal from every target (the targets of positive weight), or behind
    every such target's tangent plane (module docstring); non-finite centres count as escaped."""
    from ._placement_rank import centre_of_row

    p, n, diag = weighted_targets(problem.targets)
    thetas = np.asarray(thetas, np.float64)
    out = np.zeros(thetas.shape[0], bool)
    if p.shape[0] == 0:
        return out
    for j, param in enumerate(problem.params):
        if param is None or "position" not in param._slices() or param.kind == "directional":
            continue
        o = problem.offsets[j]
        c = np.stack([centre_of_row(param, th[o:o + param.size]) for th in thetas])  # (S, 3)
        d = c[:, None] - p[None]  # (S, N, 3)
        far = np.linalg.norm(d, axis=2).min(axis=1) > ESCAPE_FACTOR * diag if diag > 0 else np.zeros(len(c), bool)
        behind = ~np.any(np.einsum("snk,nk->sn", d, n) > 0, axis=1)
        out |= far | behind | ~np.all(np.isfinite(c), axis=1)
    return out
