"""A receiver on a mesh face beside a slight concave fold, under a near quad light.

The receiver p is the centre of a face C of a mesh (its normal C's normal); the neighbour f1 shares
C's edge D-B, which lies in p's horizon plane, and rises from it by a dihedral angle of about 1e-3
rad to its apex A; f0 shares f1's edge A-B and falls steeply below the horizon. Seen from p, f1 is
a sliver along the horizon and f0 blocks a thin strip above it: together they hide almost nothing
of the light (a 0.8 m quad 0.07 m above p). C itself is left out (p lies on it: the on-surface
rule). `benchmarks.mesh_sweep` found this on the teapot's receivers on its own surface under the
`close` light (engine 0.272, exact 0.457); random configurations of this kind fail in about one
case in eight. The geometry below is one of them, generated (an edge of 5 mm, rotated, 0.77 m up).
"""

from __future__ import annotations

import os
import sys

import jax
import numpy as np
import pytest

import jaxshadow as js

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, os.path.dirname(__file__))
from test_clip import reference_ff  # noqa: E402

F1 = np.array([[-0.03757561209420661, -0.07063815842500158, 0.7743260949026625],
               [-0.039379278184253574, -0.0655990473058113, 0.7737871470956715],
               [-0.04, -0.07, 0.77]])
F0 = np.array([[-0.039379278184253574, -0.0655990473058113, 0.7737871470956715],
               [-0.03757561209420661, -0.07063815842500158, 0.7743260949026625],
               [-0.03696591990640484, -0.061523379990851564, 0.7695629626061079]])
P = np.array([[-0.03850726346773308, -0.07191437858662156, 0.7717704999435466]])
N = np.array([[-0.8582308787892784, -0.25984095034989946, 0.4426312677769657]])
QUAD = np.array([[-0.4, -0.4, 0.84], [-0.4, 0.4, 0.84], [0.4, 0.4, 0.84], [0.4, -0.4, 0.84]])


def _exact() -> float:
    return float(np.pi * reference_ff(P[0], N[0] / np.linalg.norm(N[0]), QUAD, [F1, F0]))


def test_fold_device_kernel_matches_reference() -> None:
    scene = js.Scene([js.PolygonLight(QUAD, 1.0)], occluders=[F1, F0])
    dev = float(np.asarray(js.irradiance(scene, P, N, shadows=js.ShadowOptions(engine="device")))[0, 0])
    assert abs(dev - _exact()) <= 1e-9 * abs(_exact())


@pytest.mark.xfail(strict=True, reason=(
    "open: the host engine (silhouette and face path alike) hides 23 % of the light here; each face alone "
    "is exact, the pair sharing the edge A-B is not (a boundary vertex at the zenith's projection)"))
@pytest.mark.parametrize("occluders", ["faces", "mesh"])
def test_fold_engine_matches_reference(occluders: str) -> None:
    occ = [F1, F0] if occluders == "faces" else [js.Mesh(np.concatenate([F1, F0[2:]]), np.array([[0, 1, 2], [1, 0, 3]]))]
    scene = js.Scene([js.PolygonLight(QUAD, 1.0)], occluders=occ)
    e = float(np.asarray(js.irradiance(scene, P, N))[0, 0])
    assert abs(e - _exact()) <= 1e-9 * abs(_exact())
