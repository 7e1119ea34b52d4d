"""The silhouette path's depth complexity on meshes whose contours cross and chain: C carried
along chains of contour segments from one coverage query per chain (silhouette.h).

Where contour segments meet at the projection of a mesh vertex, C on both sides of one follows
from C on both sides of the other (two segments), or of its neighbours in their order about the
vertex (three or more, as where a jittered surface folds); a wrong carry (a sign, a side, an end,
the order) changes which pieces bound the visible region. Generated closed non-convex meshes (a
torus knot tube, which hides itself in many layers; overlapping closed components; components
that touch at one vertex, where four contour segments meet) and an open one (boundary
edges, weight 1, meeting silhouette edges, weight 2): the values against the face path
(`JAXSHADOW_SILHOUETTE=0`, which clips faces and shares no coverage code) on every receiver and
against exact polygon booleans (`reference_ff` of `tests/test_clip.py`) on a subset.
"""

from __future__ import annotations

import numpy as np
import pytest

import jaxshadow as js
from jaxshadow._shadows import binding as vis

pytestmark = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")
shapely = pytest.importorskip("shapely")
from test_clip import reference_ff  # noqa: E402
from test_real_meshes import both_paths, floor  # noqa: E402

LIGHT = np.array([[-0.4, -0.4, 2.5], [-0.4, 0.4, 2.5], [0.4, 0.4, 2.5], [0.4, -0.4, 2.5]])


def tube(curve: np.ndarray, radius: float, sides: int) -> tuple[np.ndarray, np.ndarray]:
    """A closed tube (a torus topologically) of `sides`-gons swept along the closed polyline
    `curve (n, 3)`, outward triangles."""
    n = len(curve)
    t = np.roll(curve, -1, axis=0) - np.roll(curve, 1, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    ref = np.array([0.3, 0.5, 0.8])
    a = np.cross(t, ref)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(t, a)
    ang = 2 * np.pi * np.arange(sides) / sides
    v = curve[:, None, :] + radius * (np.cos(ang)[None, :, None] * a[:, None, :] + np.sin(ang)[None, :, None] * b[:, None, :])
    idx = np.arange(n * sides).reshape(n, sides)
    i0, i1 = idx, np.roll(idx, -1, axis=0)
    j0, j1 = i0, np.roll(i0, -1, axis=1)
    k0, k1 = i1, np.roll(i1, -1, axis=1)
    f = np.concatenate([np.stack([j0, k0, k1], -1).reshape(-1, 3), np.stack([j0, k1, j1], -1).reshape(-1, 3)])
    # Outward: the first face's normal away from the curve.
    c = v.reshape(-1, 3)
    tri = c[f[0]]
    if np.dot(np.cross(tri[1] - tri[0], tri[2] - tri[0]), tri.mean(0) - curve[0]) < 0:
        f = f[:, ::-1]
    return c, f


def torus_knot(p: int = 2, q: int = 3, n: int = 120, sides: int = 8, radius: float = 0.09) -> tuple[np.ndarray, np.ndarray]:
    """A (p, q) torus knot tube about 1 m across, 0.5 m to 1.1 m above the floor."""
    s = 2 * np.pi * np.arange(n) / n
    r = 0.32 + 0.14 * np.cos(q * s)
    curve = np.stack([r * np.cos(p * s), r * np.sin(p * s), 0.8 + 0.16 * np.sin(q * s)], axis=1)
    return tube(curve, radius, sides)


def icosphere(centre, radius: float, subdivisions: int = 2) -> tuple[np.ndarray, np.ndarray]:
    trimesh = pytest.importorskip("trimesh")
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(m.vertices) + np.asarray(centre, float), np.asarray(m.faces, np.int64)


def union(*parts: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, off = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + off)
        off += len(v)
    return np.concatenate(vs), np.concatenate(fs)




def _check(v: np.ndarray, f: np.ndarray, monkeypatch, seed: int, n: int = 500, n_ref: int = 24,
           fallbacks: float = 0.02) -> np.ndarray:
    """Silhouette path against the face path on `n` floor receivers and against polygon booleans
    on `n_ref` penumbra receivers (at most a `fallbacks` fraction of the penumbra receivers
    handed to the face path); returns the silhouette path's classes."""
    assert len(f) >= 256, "enough faces for the silhouette path"
    scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[js.Mesh(v, f)])
    p, nrm = floor(n, seed, 1.1)
    on, e_on, off, e_off = both_paths(scene, p, nrm, monkeypatch)
    pen = on.classes == vis.PENUMBRA
    assert pen.sum() > 40
    # The silhouette path was taken: contour edges, not faces, counted per penumbra receiver. A
    # receiver it hands to the face path reports the face path's count; an inconsistent carry
    # (caught where a chain closes) would send most receivers there, exact but slow.
    assert on.candidates[pen].mean() < off.candidates[pen].mean()
    assert (on.candidates[pen] == off.candidates[pen]).mean() <= fallbacks
    np.testing.assert_allclose(e_on, e_off, rtol=0, atol=1e-11 * e_off.max())
    pick = np.where(pen)[0][:n_ref]
    ref = np.pi * np.array([reference_ff(q, m, LIGHT, list(v[f])) for q, m in zip(p[pick], nrm[pick], strict=True)])
    np.testing.assert_allclose(e_on[pick], ref, rtol=0, atol=1e-9 * ref.max())
    return on.classes


def test_torus_knot_tube(monkeypatch):
    """A knotted tube hides itself in up to four layers: contours cross and chain everywhere."""
    v, f = torus_knot()
    cls = _check(v, f, monkeypatch, seed=21)
    assert (cls == vis.UMBRA).sum() + (cls == vis.PENUMBRA).sum() > 100


def test_torus_knot_tube_fine_and_noisy(monkeypatch):
    """Finer tessellation with the vertices jittered: long chains of short contour segments, many
    of them inside the shadow (C >= 1 on both sides), on the contour grid."""
    v, f = torus_knot(3, 4, n=240, sides=10, radius=0.07)
    v = v + np.random.default_rng(3).normal(0, 2e-3, v.shape)
    _check(v, f, monkeypatch, seed=22, n=400, n_ref=16)


def test_overlapping_closed_components(monkeypatch):
    """Spheres that overlap in projection and in space (one mesh, three closed components, two of
    them interpenetrating): C counts every layer of each."""
    v, f = union(icosphere([-0.15, 0.0, 0.8], 0.3), icosphere([0.2, 0.1, 1.0], 0.25), icosphere([0.05, -0.1, 1.35], 0.2))
    _check(v, f, monkeypatch, seed=23)


def test_components_touching_at_a_vertex(monkeypatch):
    """Two tubes sharing one vertex position (a non-manifold vertex: four contour segments can meet
    there, C carried across it in their order about it) and an open tube (its cut ends are
    boundary edges of weight 1 that meet silhouette edges of weight 2)."""
    v1, f1 = torus_knot(2, 3, n=60, sides=6, radius=0.08)
    v2, f2 = v1 * np.array([-1.0, 1.0, 1.0]), f1[:, ::-1]
    # Move the second so that its vertex 0 lands exactly on the first's vertex 0.
    v2 = v2 + (v1[0] - v2[0])
    v3, f3 = torus_knot(3, 2, n=80, sides=7, radius=0.07)
    v3 = v3 * 0.8 + np.array([0.1, 0.2, 0.45])
    keep = np.ones(len(f3), bool)
    keep[: 2 * 7] = False  # drop a ring of faces: an open tube
    keep[len(f3) // 2 : len(f3) // 2 + 7] = False
    v, f = union((v1, f1), (v2, f2), (v3, f3[keep]))
    _check(v, f, monkeypatch, seed=24)
