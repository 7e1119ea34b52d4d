"""`ShadowCache.update` on real meshes: the values after moving one object of a several-object
scene equal a fresh cache's (a rebuild) bit for bit, on receivers the engine's silhouette path
serves (penumbra of a noisy open scan and a torus) as well as the others.

A receiver the edit cannot reach keeps its old value, computed with the other objects where
they were; the silhouette path sums its contour edges in the order its hierarchy walk meets
them, so that order must not depend on where the other objects lie. The reference is a rebuild
of the edited scene (`ShadowCache` from scratch), not the updated cache's own code path.
"""

from __future__ import annotations

import numpy as np
import pytest

import jaxshadow as js
from benchmarks.real_meshes import blob
from jaxshadow._shadows import binding as vis

pytestmark = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")
trimesh = pytest.importorskip("trimesh")

LIGHT = np.array([[-0.4, -0.4, 2.5], [-0.4, 0.4, 2.5], [0.4, 0.4, 2.5], [0.4, -0.4, 2.5]])


def scan(seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A small scan's stand-in (as `benchmarks.real_meshes.scan_like`): the blob at 1 280
    triangles with 1 mm vertex noise, open at the base (its lowest 15 % removed)."""
    v, f = blob(3)
    v = v + np.random.default_rng(seed).normal(0, 1e-3, v.shape)
    keep = v[f][:, :, 2].mean(axis=1) > v[:, 2].min() + 0.15 * np.ptp(v[:, 2])
    return v, f[keep]


def turn(v: np.ndarray, degrees: float) -> np.ndarray:
    """`v` turned about the vertical axis through its centroid."""
    c = v.mean(axis=0)
    a = np.radians(degrees)
    r = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    return (v - c) @ r.T + c


def receivers(n: int = 900, seed: int = 6, half: float = 1.6) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    p = np.c_[rng.uniform(-half, half, (n, 2)), np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    k = n // 5  # grazing normals
    t, a = np.radians(rng.uniform(60, 85, k)), rng.uniform(0, 2 * np.pi, k)
    nrm[:k] = np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)
    return p, nrm


def test_moving_each_object_of_a_mesh_scene_equals_a_rebuild():
    sv, sf = scan()
    tor = trimesh.creation.torus(0.18, 0.06, major_sections=24, minor_sections=10)
    tv, tf = np.asarray(tor.vertices) + [0.75, -0.55, 0.6], np.asarray(tor.faces)
    box = js.Mesh.box([0.75, 0.45, 0.35], [0.95, 0.75, 0.6])
    light = js.PolygonLight(LIGHT, 1.0)

    def scene(scan_v, torus_v, box_shift):
        return js.Scene([light], occluders=[js.Mesh(scan_v, sf), js.Mesh(torus_v, tf),
                                            js.Mesh(box.vertices + box_shift, box.loops)])

    p, nrm = receivers()
    state = {"scan": sv, "torus": tv, "box": np.zeros(3)}
    first = scene(state["scan"], state["torus"], state["box"])
    lp = js.shadow_plan(first, p, nrm).lights[0]
    # Receivers the silhouette path serves in penumbra (one region, contour edges counted).
    sil_pen = (lp.classes == vis.PENUMBRA) & (lp.kept == 1)
    assert sil_pen.sum() > 100, sil_pen.sum()
    cache = js.ShadowCache(first, p, nrm)
    edits = [("box", np.array([0.0, 0.1, 0.0])),            # a small box moves beside the meshes
             ("box", np.array([0.1, 0.1, 0.0])),
             ("scan", sv + [0.05, -0.03, 0.0]),             # the scan moves
             ("torus", turn(tv, 25.0)),                     # the torus turns in place
             ("scan", turn(sv + [0.05, -0.03, 0.0], 10.0)),  # the scan turns
             ("torus", tv + [0.0, 0.0, 0.05])]
    for name, value in edits:
        state[name] = value
        edited = scene(state["scan"], state["torus"], state["box"])
        cache.update(edited)
        n_again = cache.last_update["receivers"][0]
        # Only part of the receivers re-evaluated: the others keep values computed in the old scene.
        assert 0 < n_again < len(p) - 100, (name, n_again)
        fresh = js.ShadowCache(edited, p, nrm)
        bad = np.flatnonzero(np.any(cache.irradiance != fresh.irradiance, axis=1))
        assert bad.size == 0, (name, bad[:10], np.abs(cache.irradiance - fresh.irradiance).max())
    # And the rebuild is the scene's values (the cache's sum is irradiance's).
    np.testing.assert_array_equal(fresh.irradiance, np.asarray(js.irradiance(edited, p, nrm)))


def _two_blobs(shift_second: np.ndarray = np.zeros(3)) -> tuple[np.ndarray, np.ndarray]:
    """One vertex array and face table holding two closed blobs (two connected components of
    one `js.Mesh`): the blob at 320 triangles halved, at (-0.55, -0.1) and (0.5, 0.35), the
    second shifted by `shift_second`."""
    v, f = blob(2)
    v = 0.5 * (v - v.mean(axis=0))
    a, b = v + [-0.55, -0.1, 0.7], v + [0.5, 0.35, 0.6] + shift_second
    return np.concatenate([a, b]), np.concatenate([f, f + len(v)])


def test_moving_a_mesh_of_several_components_equals_a_rebuild():
    """Edits that change what the engine computes over all occluders rather than per component:
    the largest coordinate magnitude (`SilhouetteTree::scale`: the rounding bounds of every
    face-side test, the umbra sections' and the clear test's margins), the occluders' height
    window above the emitter plane (which receivers the silhouette path serves) and the
    item hierarchy's root box. One mesh of two components and a second mesh (the scan) move,
    up, out, down and back, one component alone as well; each time the updated cache equals a
    rebuild bit for bit, and receivers far from the edit keep their old values."""
    sv, sf = scan()
    sv = 0.6 * (sv - sv.mean(axis=0)) + [0.2, -0.75, 0.65]
    tv, tf = _two_blobs()
    light = js.PolygonLight(LIGHT, 1.0)

    def scene(two_v, scan_v):
        return js.Scene([light], occluders=[js.Mesh(two_v, tf), js.Mesh(scan_v, sf)])

    first = scene(tv, sv)
    assert first.occluder_topology.n_solids == 0
    p, nrm = receivers(1200, seed=8, half=2.6)
    lp = js.shadow_plan(first, p, nrm).lights[0]
    assert ((lp.classes == vis.PENUMBRA) & (lp.kept == 1)).sum() > 80
    cache = js.ShadowCache(first, p, nrm)
    top = float(max(tv[:, 2].max(), sv[:, 2].max()))
    scale = float(max(np.abs(tv).max(), np.abs(sv).max()))
    up = tv + [0.0, 0.0, 0.5]                                # the two blobs rise: a new top and scale
    edits = [(up, sv),
             (up, sv + [0.9, -0.3, 0.0]),                    # the scan moves out: a new largest |x|, |y|
             (up, sv + [0.9, -0.3, -0.3]),                   # and down: a new lowest point
             (_two_blobs([0.0, 0.0, 0.8])[0], sv + [0.9, -0.3, -0.3]),  # one component alone rises
             (tv, sv)]                                       # back where they started
    assert float(up[:, 2].max()) > top and float(np.abs(up).max()) > scale
    for two_v, scan_v in edits:
        edited = scene(two_v, scan_v)
        cache.update(edited)
        n_again = cache.last_update["receivers"][0]
        assert 0 < n_again < len(p) - 100, n_again
        fresh = js.ShadowCache(edited, p, nrm)
        bad = np.flatnonzero(np.any(cache.irradiance != fresh.irradiance, axis=1))
        assert bad.size == 0, (bad[:10], np.abs(cache.irradiance - fresh.irradiance).max())
    np.testing.assert_array_equal(cache.irradiance, js.ShadowCache(first, p, nrm).irradiance)
