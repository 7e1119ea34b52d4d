"""The escape bound of `fit_lights`' refinements (`inverse._escape`, applied by
`_global_placement.ranking_losses`): a placement in which a light left the region it can light the
targets from (farther than 10 extents from every target, or below the floor the targets lie on)
is not ranked while another keeps every light in bounds; when every placement escaped, the
ranking is left as it is (the report flags the answer)."""

import numpy as np
from position_problems import position_problem

import jaxshadow as js
from inverse._escape import escaped_rows
from inverse._global_placement import ranking_losses

MATERIAL = js.Material(ka=0.2, kd=[0.6, 0.5, 0.4], ks=0.0, exponent=1.0)
TRUE = js.Scene([js.PointLight([-0.6, 0.2, 1.5], 4.0), js.PointLight([0.7, -0.3, 1.2], 2.0)], ambient=0.1)


def _problem():
    problem, _, t, size = position_problem(TRUE, MATERIAL, "none")
    return problem, t, size


def _rows(t, size, centres):
    """Parameter rows (the centres' offsets from the true lights over the scene size) of `centres (S, 2, 3)`."""
    truth = np.stack([np.asarray(light.position, np.float64) for light in TRUE.lights])
    return ((np.asarray(centres, np.float64) - truth) / size).reshape(len(centres), -1)


def test_escaped_rows_are_not_ranked():
    problem, t, size = _problem()
    pts = np.asarray(t.points, np.float64)
    extent = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    floor = float(pts[:, 2].min())
    inside = [[-0.6, 0.2, 1.5], [0.7, -0.3, 1.2]]
    far = [[-0.6, 0.2, 1.5], [0.0, 0.0, 11.0 * extent]]  # beyond 10 extents from every target
    below = [[-0.6, 0.2, floor - 1.0], [0.7, -0.3, 1.2]]  # under the floor: behind every target's plane
    rows = _rows(t, size, [inside, far, below])
    assert escaped_rows(problem, rows).tolist() == [False, True, True]
    f, _ = ranking_losses(problem, np.array([1.0, 0.1, 0.2]), rows)
    assert f.tolist() == [1.0, np.inf, np.inf]


def test_every_row_escaped_leaves_the_ranking():
    problem, t, size = _problem()
    pts = np.asarray(t.points, np.float64)
    extent = float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))
    rows = _rows(t, size, [[[0.0, 0.0, 11.0 * extent], [0.7, -0.3, 1.2]],
                           [[0.0, 0.0, 20.0 * extent], [0.7, -0.3, 1.2]]])
    f, _ = ranking_losses(problem, np.array([0.3, 0.2]), rows)
    assert f.tolist() == [0.3, 0.2]
