"""Receivers that see all of the light, decided before the silhouette path's work
(`csrc/engine/clear.h`: the light's pyramid misses every box of the occluders' hierarchy by a
clear gap), against the silhouette path on the same receivers (the switch JAXSHADOW_CLEAR=0) and
exact polygon booleans (`reference_ff` of `tests/test_clip.py`, no code shared with the engine).

The decision must change nothing: the same classes, statistics and values bit for bit; a receiver
whose pyramid only grazes the mesh (the penumbra's outer edge) stays with the silhouette path.
"""

from __future__ import annotations

import numpy as np
import pytest

import jaxshadow as js
from benchmarks.real_meshes import blob
from jaxshadow._shadows import binding as vis

pytestmark = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")
pytest.importorskip("trimesh")
pytest.importorskip("shapely")
from test_clip import reference_ff  # noqa: E402
from test_plan import culled  # noqa: E402
from test_real_meshes import LIGHT, both_paths, floor  # noqa: E402


def meets_box(p: np.ndarray, v: np.ndarray) -> np.ndarray:
    """`(N,)` whether the pyramid conv({p} ∪ LIGHT) of each receiver meets the box of the vertices
    `v` (separating axes: the box's, the pyramid's face normals, and their edges' cross products)."""
    lo, hi = v.min(axis=0), v.max(axis=0)
    corners = np.array([[(hi if c >> d & 1 else lo)[d] for d in range(3)] for c in range(8)])
    pts = np.concatenate([p[:, None, :], np.broadcast_to(LIGHT, (len(p),) + LIGHT.shape)], axis=1)  # (N, 5, 3)
    rays = LIGHT[None] - p[:, None]
    rims = np.broadcast_to(np.roll(LIGHT, -1, axis=0) - LIGHT, rays.shape)
    edges = np.concatenate([rays, rims], axis=1)  # (N, 8, 3)
    eye = np.broadcast_to(np.eye(3), (len(p), 3, 3))
    sides = np.cross(rays, np.roll(rays, -1, axis=1))
    crossed = np.cross(edges[:, :, None, :], eye[:, None, :, :]).reshape(len(p), -1, 3)
    axes = np.concatenate([eye, sides, np.cross(rims[:, 0], rims[:, 1])[:, None], crossed], axis=1)
    a, b = np.einsum("nkd,nad->nka", pts, axes), np.einsum("cd,nad->nca", corners, axes)
    apart = (a.max(axis=1) < b.min(axis=1)) | (b.max(axis=1) < a.min(axis=1))
    return ~np.any(apart, axis=1)


@pytest.mark.parametrize("open_below", [None, 0.6], ids=["closed", "open"])
@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_clear_receivers_as_the_silhouette_path(open_below, dtype, monkeypatch):
    """Floor receivers around a non-convex mesh (1 280 faces: the silhouette path), a fifth with
    grazing normals, and a dense band along the penumbra's outer edge: classes, candidates, kept
    regions and irradiance identical with and without the early decision."""
    v, f = blob(3, open_below)
    scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[js.Mesh(v, f)])
    p, nrm = floor(4000, seed=3, half=1.6)
    # The outer edge of the penumbra along the x axis (lit just beyond it): 400 receivers.
    cls = js.shadow_plan(scene, p, nrm).lights[0].classes
    far = np.max(np.abs(p[cls == vis.PENUMBRA, 0]))
    t = np.linspace(far - 0.05, far + 0.05, 400)
    p = np.concatenate([p, np.c_[t, np.zeros_like(t), np.zeros_like(t)]]).astype(dtype)
    nrm = np.concatenate([nrm, np.tile([0.0, 0.0, 1.0], (len(t), 1))]).astype(dtype)
    on, e_on, off, e_off = both_paths(scene, p, nrm, monkeypatch, switch="JAXSHADOW_CLEAR")
    np.testing.assert_array_equal(on.classes, off.classes)
    np.testing.assert_array_equal(on.candidates, off.candidates)
    np.testing.assert_array_equal(on.kept, off.kept)
    np.testing.assert_array_equal(e_on, e_off)
    lit = on.classes == vis.LIT
    near = meets_box(p.astype(np.float64), v)
    assert np.sum(lit & near) > 50, "lit receivers whose pyramid meets the mesh's box"
    assert np.sum(lit & ~near) > 1000 and np.sum(on.classes == vis.PENUMBRA) > 500


def test_clear_receivers_are_lit():
    """Lit receivers closest to the shadow (their pyramids meet the mesh's box; the nearest to a
    penumbra receiver) against exact polygon booleans: the whole light is seen (within 1e-9)."""
    v, f = blob(3, 0.6)
    scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[js.Mesh(v, f)])
    p, nrm = floor(4000, seed=5, half=1.6)
    nrm[:] = [0.0, 0.0, 1.0]
    cls = js.shadow_plan(scene, p, nrm).lights[0].classes
    lit = np.where(cls == vis.LIT)[0]
    pen = p[cls == vis.PENUMBRA, :2]
    gap = np.min(np.linalg.norm(p[lit, None, :2] - pen[None, :, :], axis=2), axis=1)
    pick = np.concatenate([lit[meets_box(p[lit], v)][:10], lit[np.argsort(gap)[:20]]])
    got = np.asarray(js.irradiance(scene, p[pick], nrm[pick]))[:, 0]
    tris = v[f]
    ref = np.pi * np.array([reference_ff(q, m, LIGHT, culled(q, m, LIGHT, tris)) for q, m in zip(p[pick], nrm[pick], strict=True)])
    unoccluded = np.asarray(js.irradiance(js.Scene([js.PolygonLight(LIGHT, 1.0)]), p[pick], nrm[pick]))[:, 0]
    np.testing.assert_allclose(ref, unoccluded, rtol=0, atol=1e-9 * np.abs(ref).max())
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * np.abs(ref).max())
