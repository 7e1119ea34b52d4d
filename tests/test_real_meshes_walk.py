"""Real-mesh build path: coplanar merging on large meshes where few faces merge (a scan's flat
patches) or many do (a terrain of plateaus), with duplicated and reversed faces, against the
greedy definition of the merge (`test_mesh._merge_reference`)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import jaxshadow as js

sys.path.insert(0, str(Path(__file__).parent))
from test_mesh import _merge_reference  # noqa: E402

trimesh = pytest.importorskip("trimesh")


def _flattened_sphere(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A noisy icosphere with a few caps pressed flat: mostly non-coplanar neighbours (a scan's
    surface), a few coplanar patches whose merges then reach faces no vectorised test paired."""
    rng = np.random.default_rng(seed)
    m = trimesh.creation.icosphere(subdivisions=4)
    v = m.vertices * (1 + 0.01 * rng.standard_normal((len(m.vertices), 1)))
    for _ in range(4):
        d = rng.standard_normal(3)
        d /= np.linalg.norm(d)
        h = v @ d
        cut = 0.8 + 0.1 * rng.random()
        over = h > cut
        v[over] -= (h[over] - cut)[:, None] * d  # onto the plane h = cut
    return v, m.faces


def _terrain(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A height field (open) with plateaus and terraces: many coplanar neighbours."""
    rng = np.random.default_rng(seed)
    n = 40
    x, y = np.meshgrid(np.linspace(0, 1, n), np.linspace(0, 1, n))
    z = np.round(3 * np.sin(3 * x) * np.cos(2 * y) + rng.normal(0, 0.02, x.shape)) / 10
    rough = rng.random(x.shape) < 0.3
    z = np.where(rough, z + rng.normal(0, 0.01, x.shape), z)
    v = np.c_[x.ravel(), y.ravel(), z.ravel()]
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    f = np.r_[np.c_[a, b, c], np.c_[a, c, d]]
    return v, f[rng.permutation(len(f))]


def _cases() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    out = {}
    for s in range(2):
        out[f"flattened_sphere_{s}"] = _flattened_sphere(s)
        out[f"terrain_{s}"] = _terrain(s)
    v, f = _flattened_sphere(7)
    rng = np.random.default_rng(7)
    dup = rng.choice(len(f), 40, replace=False)
    out["duplicated_faces"] = (v, np.r_[f, f[dup]])  # non-manifold: edges run twice the same way
    out["reversed_copies"] = (v, np.r_[f, f[dup][:, ::-1]])  # and faces running them both ways
    vt, ft = _terrain(3)
    out["terrain_with_duplicates"] = (vt, np.r_[ft, ft[: len(ft) // 3]])
    return out


@pytest.mark.parametrize("name", sorted(_cases()))
def test_merge_of_large_meshes_matches_the_greedy_definition(name):
    """The merged faces are exactly the greedy definition's (same loops, order, starting vertex)
    where the build visits only the queue entries a merge can change."""
    v, f = _cases()[name]
    v = np.asarray(v, float)
    m = js.Mesh(v, f)
    raw = js.Mesh(v, f, merge=False)
    size = float(np.max(np.ptp(v, axis=0)))
    ref = _merge_reference(raw.loops, v, size)
    assert len(ref) < len(raw.loops)  # the case merges something
    assert m.loops == ref
