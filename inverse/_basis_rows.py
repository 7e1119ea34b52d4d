"""`fit_lights`' LM program (`_multilight.solve` with `keep_basis`) evaluated with no
iterations at given rows: the basis (each fitted light's irradiance and specular integral at
reference power) and its tangents in the parameters, at the answer, at the competing
placements and at other receivers (the report's candidate targets), from the compiled program
of the search instead of a program of their own (`_multilight.report_parts`).
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from . import _projected_lm
from ._multilight import solve


class BasisRows(_projected_lm.BasisRows):
    """`fit_lights`' LM program (`solve` with `keep_basis`) evaluated with no iterations at rows
    `(R, n_theta)`, `n_starts` rows a call (its own start count: the compiled program of the
    search, padding solved once), with the search's `(rtol, atol)` (static arguments of the
    program): each row's `(E (J, N, 3), S or None, dE (n_theta, J, N, 3), dS or None)` as float64
    NumPy arrays. What the report needs at the answer and at competing placements, without a
    program of its own. `problem`: the latest one used (its shadow capacity may have doubled)."""

    _run = staticmethod(solve)

    def at_receivers(self, row: np.ndarray, points: np.ndarray, normals: np.ndarray) -> tuple:
        """`(E (J, K, 3), S or None, dE (n_theta, J, K, 3), dS or None)` at the row `row (n_theta,)`
        for other receivers `points, normals (K, 3)` (seen from the targets' first eye): the
        program run on the problem with its targets' positions replaced, N at a time (the
        targets' count: the same shapes, the same compiled program; the last chunk padded)."""
        t = self.problem.targets
        n, dt = t.points.shape[0], t.points.dtype
        eye = jnp.asarray(np.broadcast_to(np.asarray(t.eye)[0], t.eye.shape), dt)
        parts = []
        for a in range(0, points.shape[0], n):
            cp, cn = points[a:a + n], normals[a:a + n]
            m = cp.shape[0]
            cp, cn = (np.concatenate([x, np.repeat(x[:1], n - m, axis=0)]) for x in (cp, cn))
            tg = eqx.tree_at(lambda x: (x.points, x.normals, x.eye), t,
                             (jnp.asarray(cp, dt), jnp.asarray(cn, dt), eye))
            sub = BasisRows(dataclasses.replace(self.problem, targets=tg), self.n_starts, self.tolerances)
            E, S, dE, dS = sub(np.asarray(row, np.float64)[None])[0]
            parts.append((E[:, :m], None if S is None else S[:, :m], dE[:, :, :m], None if dS is None else dS[:, :, :m]))
        return tuple(None if parts[0][i] is None else np.concatenate([p[i] for p in parts], axis=1 if i < 2 else 2)
                     for i in range(4))

