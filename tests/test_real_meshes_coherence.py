"""Receiver coherence in the silhouette path: receivers share one walk of the mesh-edge hierarchy per
tile.

The engine orders a call's receivers in space and lets tiles of neighbouring receivers walk the
hierarchy once (silhouette_walk.h); each receiver then runs its own exact tests over what the
tile kept, so its contour edges, their order, its class and its value are those of the receiver
processed alone. A call of one receiver has no tile: those calls are the per-receiver reference
here. Independent reference: `reference_ff` of `tests/test_clip.py` (exact polygon booleans in
shapely, no code shared with the engine).
"""

from __future__ import annotations

import numpy as np
import pytest

import jaxshadow as js
from benchmarks.real_meshes import blob
from jaxshadow._shadows import binding as vis

pytestmark = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")
trimesh = pytest.importorskip("trimesh")
shapely = pytest.importorskip("shapely")
from test_clip import reference_ff  # noqa: E402

LIGHT = np.array([[-0.4, -0.4, 2.5], [-0.4, 0.4, 2.5], [0.4, 0.4, 2.5], [0.4, -0.4, 2.5]])


def _meshes() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Non-convex closed, open, noisy open (scan-like) and a tilted ring (CAD-like, long thin
    triangles), each well over the silhouette path's 256 faces."""
    out = {"closed": blob(3), "open": blob(3, open_below=0.55)}
    v, f = blob(3)
    v = v + np.random.default_rng(4).normal(0, 4e-3, v.shape)
    out["noisy_open"] = (v, f[v[f][:, :, 2].mean(axis=1) > 0.45])
    m = trimesh.creation.annulus(r_min=0.25, r_max=0.45, height=0.15, sections=96)
    m.apply_transform(trimesh.transformations.rotation_matrix(np.radians(35), [1, 0, 0]))
    v = np.asarray(m.vertices, float)
    v[:, 2] += 0.35 - v[:, 2].min()
    out["ring"] = (v, np.asarray(m.faces))
    return out


MESHES = _meshes()


def _receivers(n: int, seed: int, grazing: bool) -> tuple[np.ndarray, np.ndarray]:
    """Dense floor receivers under the mesh (so that tiles hold near neighbours); with `grazing`,
    a third of them with normals 60-88 degrees from the vertical (tiles of mixed normals)."""
    rng = np.random.default_rng(seed)
    p = np.c_[rng.uniform(-0.8, 0.8, (n, 2)), np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    if grazing:
        k = rng.random(n) < 1 / 3
        t, a = np.radians(rng.uniform(60, 88, k.sum())), rng.uniform(0, 2 * np.pi, k.sum())
        nrm[k] = np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)
    return p, nrm


def _scene(v: np.ndarray, f: np.ndarray) -> js.Scene:
    return js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[js.Mesh(v, f)])


@pytest.mark.parametrize("grazing", [False, True], ids=["up", "grazing"])
@pytest.mark.parametrize("name", list(MESHES))
def test_tiles_give_each_receiver_its_own_answer(name, grazing):
    """A batch (tiled) against every sampled receiver alone (no tile): the same class and number
    of contour edges, values equal to 1e-12; the batch shuffled: the same, receiver by receiver."""
    v, f = MESHES[name]
    scene = _scene(v, f)
    p, nrm = _receivers(1500, seed=len(name), grazing=grazing)
    lp = js.shadow_plan(scene, p, nrm).lights[0]
    cls, cand = lp.classes, lp.candidates
    assert (cls == vis.PENUMBRA).sum() > 150, "penumbra receivers in tiles"
    e = np.asarray(js.irradiance(scene, p, nrm))[:, 0]
    scale = np.abs(e).max()
    # Shuffled: other tiles, the same answers.
    perm = np.random.default_rng(1).permutation(len(p))
    ls = js.shadow_plan(scene, p[perm], nrm[perm]).lights[0]
    np.testing.assert_array_equal(ls.classes, cls[perm])
    np.testing.assert_array_equal(ls.candidates, cand[perm])
    es = np.asarray(js.irradiance(scene, p[perm], nrm[perm]))[:, 0]
    np.testing.assert_allclose(es, e[perm], rtol=0, atol=1e-12 * scale)
    # Alone: penumbra (most), umbra and lit receivers.
    rng = np.random.default_rng(2)
    pick = np.concatenate([rng.choice(np.where(cls == c)[0], min(k, (cls == c).sum()), replace=False)
                           for c, k in ((vis.PENUMBRA, 40), (vis.UMBRA, 8), (vis.LIT, 4))])
    for i in pick:
        one = js.shadow_plan(scene, p[i : i + 1], nrm[i : i + 1]).lights[0]
        assert one.classes[0] == cls[i] and one.candidates[0] == cand[i], i
    alone = np.array([np.asarray(js.irradiance(scene, p[i : i + 1], nrm[i : i + 1]))[0, 0] for i in pick[:16]])
    np.testing.assert_allclose(e[pick[:16]], alone, rtol=0, atol=1e-12 * scale)


@pytest.mark.parametrize("name", ["open", "noisy_open", "ring"])
def test_tiled_values_against_polygon_booleans(name):
    """Tiled receivers (penumbra, umbra and grazing) within 1e-9 of exact polygon booleans."""
    v, f = MESHES[name]
    scene = _scene(v, f)
    p, nrm = _receivers(1200, seed=7, grazing=True)
    cls = js.shadow_plan(scene, p, nrm).lights[0].classes
    e = np.asarray(js.irradiance(scene, p, nrm))[:, 0]
    rng = np.random.default_rng(3)
    pick = np.concatenate([rng.choice(np.where(cls == c)[0], min(k, (cls == c).sum()), replace=False)
                           for c, k in ((vis.PENUMBRA, 16), (vis.UMBRA, 3))])
    tris = list(v[f])
    ref = np.pi * np.array([reference_ff(q, m, LIGHT, tris) for q, m in zip(p[pick], nrm[pick], strict=True)])
    np.testing.assert_allclose(e[pick], ref, rtol=0, atol=1e-9 * ref.max())


def test_tiles_in_float32():
    """float32 receivers: the tile's bounds take float32 rounding; each receiver's class and
    contour edges as alone."""
    v, f = MESHES["noisy_open"]
    scene = _scene(v, f)
    p, nrm = _receivers(1000, seed=5, grazing=True)
    p32, n32 = p.astype(np.float32), nrm.astype(np.float32)
    lp = js.shadow_plan(scene, p32, n32).lights[0]
    assert (lp.classes == vis.PENUMBRA).sum() > 100
    pick = np.where(lp.classes == vis.PENUMBRA)[0][:30]
    for i in pick:
        one = js.shadow_plan(scene, p32[i : i + 1], n32[i : i + 1]).lights[0]
        assert one.classes[0] == lp.classes[i] and one.candidates[0] == lp.candidates[i], i
