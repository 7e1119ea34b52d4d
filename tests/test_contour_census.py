"""The contour census's certificate (benchmarks/contour_census.py): a piece strictly inside the
projected outline of a set of faces that all face the receiver one way has depth complexity >= 1
on both sides (C >= |winding|), checked against Embree rays on noisy, folded, closed and open
meshes."""

import numpy as np
import pytest

pytest.importorskip("trimesh.ray.ray_pyembree")

from benchmarks.contour_census import EdgeTree, census_receiver  # noqa: E402
from benchmarks.real_meshes import blob  # noqa: E402


def _meshes():
    v, f = blob(4)
    rng = np.random.default_rng(7)
    noisy = v + rng.normal(0, 6e-3, v.shape)  # folds: many small silhouettes
    yield "noisy closed", noisy, f
    keep = noisy[f][:, :, 2].mean(axis=1) > noisy[:, 2].min() + 0.2 * np.ptp(noisy[:, 2])
    yield "noisy open", noisy, f[keep]
    yield "smooth closed", v, f


@pytest.mark.parametrize("case", range(3))
def test_certified_pieces_are_deep(case):
    import trimesh
    import trimesh.ray.ray_pyembree as embree

    name, v, f = list(_meshes())[case]
    tree = EdgeTree(v, f)
    rays = embree.RayMeshIntersector(trimesh.Trimesh(v, f, process=False))
    # Floor receivers under the mesh and under its rim, where the light is partly hidden.
    ang = np.random.default_rng(case).uniform(0, 2 * np.pi, 12)
    r = np.r_[np.full(6, 0.3), np.full(6, 0.55)]
    p = np.c_[r * np.cos(ang), r * np.sin(ang), np.zeros(12)]
    rows = [census_receiver(tree, rays, q) for q in p]
    assert sum(r["pieces"] for r in rows) > 0, name
    assert sum(r["certified_shallow"] for r in rows) == 0, name  # certified => C >= 1 on both sides
    if name != "smooth closed":
        assert sum(r["certified_8"] for r in rows) > 0, name  # the certificate finds some
