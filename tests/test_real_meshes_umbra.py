"""Umbra receivers of large meshes recognised before the silhouette path's contour work
(`csrc/engine/umbra_sections.h`: cross-sections of each mesh component, capped where it is open,
whose cells of odd parity show the light hidden), against the full path on the same receivers
(the switch JAXSHADOW_UMBRA_SECTIONS=0) and exact polygon booleans (`reference_ff` of
`tests/test_clip.py`, no code shared with the engine).

A receiver the test certifies is reported umbra with no region kept (`kept` 0); the full path
reports it umbra, or (where its silhouette path falls back to the face path, which finds the
light covered by several faces and by no single one) penumbra with an empty boundary: the value
is 0 either way.
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
from test_real_meshes import LIGHT, both_paths, floor  # noqa: E402


def tube(top: bool, sections: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """A vertical tube (radius about 0.3 m, z from 0.4 to 1.0 m, four rings) open at the bottom, and at
    the top too unless `top` (then a low cone closes it: triangles, not one merged polygon): at
    least 256 faces, so on the silhouette path."""
    a = 2 * np.pi * np.arange(sections) / sections
    zs = np.linspace(0.4, 1.0, 4)
    # Each ring turned by half a section against the last: no two triangles coplanar (merged).
    v = np.concatenate([np.c_[0.3 * np.cos(a + r * np.pi / sections), 0.3 * np.sin(a + r * np.pi / sections),
                              np.full(sections, z)] for r, z in enumerate(zs)])
    f = []
    for r in range(len(zs) - 1):
        for i in range(sections):
            j = (i + 1) % sections
            a0, a1, b0, b1 = r * sections + i, r * sections + j, (r + 1) * sections + i, (r + 1) * sections + j
            f += [(a0, a1, b1), (a0, b1, b0)]
    if top:
        v = np.vstack([v, [0.0, 0.0, 1.1]])
        c, base = len(v) - 1, (len(zs) - 1) * sections
        f += [(base + i, base + (i + 1) % sections, c) for i in range(sections)]
    return v, np.asarray(f)


def open_ring(sections: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """A thick ring (outer radius 0.5 m, inner 0.2 m, z from 0.4 to 0.7 m; sides of long thin
    triangles) open at the bottom (its lower annulus removed): light passes through its hole."""
    import trimesh

    m = trimesh.creation.annulus(r_min=0.2, r_max=0.5, height=0.3, sections=sections)
    v = np.asarray(m.vertices, float)
    v[:, 2] += 0.4 - v[:, 2].min()
    f = np.asarray(m.faces)
    return v, f[~np.all(v[f][:, :, 2] == v[:, 2].min(), axis=1)]


def noisy_blob(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The blob with random vertex noise (a closed, non-convex, non-smooth mesh)."""
    v, f = blob(3)
    return v + np.random.default_rng(seed).normal(0, 4e-3, v.shape), f


def plans(scene, p, nrm, monkeypatch):
    """`(plan, E)` with the early umbra test, then without it."""
    return both_paths(scene, p, nrm, monkeypatch, switch="JAXSHADOW_UMBRA_SECTIONS")


MESHES = {"closed": lambda: blob(3), "open": lambda: blob(3, 0.45), "noisy": lambda: noisy_blob(5),
          "capped-tube": lambda: tube(True), "open-ring": open_ring}


@pytest.mark.parametrize("name", list(MESHES))
def test_certified_umbra_is_the_full_paths_umbra(name, monkeypatch):
    """Closed, open (at the base), noisy and tube meshes: most of the full path's umbra receivers
    are certified; every certified one is umbra or zero on the full path and zero for polygon
    booleans; the other receivers keep their class and value bit for bit."""
    v, f = MESHES[name]()
    scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[js.Mesh(v, f)])
    p, nrm = floor(1500, seed=2, half=1.0)
    on, e_on, off, e_off = plans(scene, p, nrm, monkeypatch)
    cert = (on.classes == vis.UMBRA) & (on.kept == 0)
    umbra = off.classes == vis.UMBRA
    assert umbra.sum() >= 20
    assert cert.sum() >= 0.5 * umbra.sum(), (cert.sum(), umbra.sum())
    assert np.all(on.classes[umbra] == vis.UMBRA)
    assert np.array_equal(on.classes[~cert], off.classes[~cert])
    assert np.array_equal(e_on[~cert], e_off[~cert])
    assert np.all(e_on[cert] == 0) and np.all(e_off[cert] == 0)
    assert np.all((off.classes[cert] == vis.UMBRA) | ((off.classes[cert] == vis.PENUMBRA) & (off.offsets[1:] - off.offsets[:-1])[cert] == 0))
    pick = np.where(cert)[0][:: max(1, cert.sum() // 8)]
    tris = list(v[f])
    ref = np.array([reference_ff(q, m, LIGHT, tris) for q, m in zip(p[pick], nrm[pick], strict=True)])
    np.testing.assert_allclose(ref, 0.0, atol=1e-12)


def test_open_tube_certifies_nothing(monkeypatch):
    """A tube open at both ends under a small light (0.2 m): the light shines through it. Its
    cross-sections' cells of odd parity (between the tube and the cone capping both rims, from the
    tube's centre) are wide enough to show the light hidden, but they lie below the upper rim's
    cap, so nothing is certified: the receivers under the tube keep the full path's classes and
    values, and see the light."""
    v, f = tube(False)
    light = 0.25 * LIGHT + np.array([0.0, 0.0, 0.75 * 2.5])
    scene = js.Scene([js.PolygonLight(light, 1.0)], occluders=[js.Mesh(v, f)])
    g = np.linspace(-0.4, 0.4, 21)
    p = np.c_[np.repeat(g, len(g)), np.tile(g, len(g)), np.zeros(len(g) ** 2)]
    nrm = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    on, e_on, off, e_off = plans(scene, p, nrm, monkeypatch)
    assert not np.any((on.classes == vis.UMBRA) & (on.kept == 0))
    assert np.array_equal(on.classes, off.classes) and np.array_equal(e_on, e_off)
    assert np.all(e_on[np.hypot(p[:, 0], p[:, 1]) < 0.15] > 0)


@pytest.mark.parametrize("name", ["closed", "open", "open-ring"])
def test_receivers_by_a_hair_outside_the_umbra_are_not_certified(name, monkeypatch):
    """Along a line from a certified receiver to a lit one, the full path's umbra boundary t*
    (bisected on its value to 1e-13): receivers 1e-8 .. 1e-5 beyond it see the light (positive
    full-path values; polygon booleans resolve it from 1e-6) and are not certified; those as far
    inside get the full path's values (0, or rounding next to the boundary)."""
    v, f = MESHES[name]()
    scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[js.Mesh(v, f)])
    p, nrm = floor(1500, seed=2, half=1.0)
    nrm = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    on = js.shadow_plan(scene, p, nrm).lights[0]
    cert = np.where((on.classes == vis.UMBRA) & (on.kept == 0))[0]
    lit = np.where(on.classes == vis.LIT)[0]
    monkeypatch.setenv("JAXSHADOW_UMBRA_SECTIONS", "0")
    tris = list(v[f])
    checked = 0
    for k in range(3):
        a, b = p[cert[k * 7]], p[lit[k * 11]]
        lo, hi = 0.0, 1.0  # value 0 at lo, positive at hi

        def pts(t, a=a, b=b):
            return a + np.asarray(t)[:, None] * (b - a)

        for _ in range(45):
            mid = 0.5 * (lo + hi)
            e = float(np.asarray(js.irradiance(scene, pts([mid]), nrm[:1]))[0, 0])
            lo, hi = (mid, hi) if e == 0 else (lo, mid)
        d = np.array([1e-8, 1e-7, 1e-6, 1e-5])
        out_t = hi + d / np.linalg.norm(b - a)
        in_t = lo - d / np.linalg.norm(b - a)
        q = pts(np.concatenate([out_t, in_t]))
        qn = np.tile([0.0, 0.0, 1.0], (len(q), 1))
        off = js.shadow_plan(scene, q, qn).lights[0]
        e_off = np.asarray(js.irradiance(scene, q, qn))[:, 0]
        monkeypatch.delenv("JAXSHADOW_UMBRA_SECTIONS")
        on_q = js.shadow_plan(scene, q, qn).lights[0]
        e_on = np.asarray(js.irradiance(scene, q, qn))[:, 0]
        monkeypatch.setenv("JAXSHADOW_UMBRA_SECTIONS", "0")
        n = len(d)
        assert np.all(e_off[:n] > 0)
        ref = np.array([reference_ff(x, m, LIGHT, tris) for x, m in zip(q[2:n], qn[2:n], strict=True)])
        assert np.all(ref > 0)
        assert not np.any(on_q.classes[:n] == vis.UMBRA), on_q.classes
        assert np.array_equal(on_q.classes[:n], off.classes[:n]) and np.array_equal(e_on[:n], e_off[:n])
        assert np.array_equal(e_on[n:], e_off[n:]) and np.all(e_on[n:] < 1e-15)
        checked += 1
    assert checked == 3


@pytest.mark.parametrize("name", ["closed", "open", "noisy", "open-ring"])
def test_cut_segments_certify_beyond_the_body_cells(name, monkeypatch):
    """The test against the cut segments themselves (section_shows_exact) certifies every receiver
    the body cells' test alone (JAXSHADOW_UMBRA_SECTIONS=cells) does, and more (closed, open and
    noisy blobs); each receiver only it certifies is umbra or zero on the full path and zero for
    polygon booleans. Under the open ring's hole the light gets through: nothing certified there."""
    v, f = MESHES[name]()
    scene = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=[js.Mesh(v, f)])
    p, nrm = floor(1500, seed=3, half=1.0)
    on, e_on, off, e_off = plans(scene, p, nrm, monkeypatch)
    monkeypatch.setenv("JAXSHADOW_UMBRA_SECTIONS", "cells")
    cells = js.shadow_plan(scene, p, nrm).lights[0]
    monkeypatch.delenv("JAXSHADOW_UMBRA_SECTIONS")
    cert = (on.classes == vis.UMBRA) & (on.kept == 0)
    cert_cells = (cells.classes == vis.UMBRA) & (cells.kept == 0)
    assert np.all(cert[cert_cells])
    extra = cert & ~cert_cells
    if name != "open-ring":
        assert extra.sum() >= 3, (extra.sum(), cert_cells.sum())
    assert np.all(e_off[extra] == 0) and np.all(e_on[extra] == 0)
    assert np.all((off.classes[extra] == vis.UMBRA) | ((off.classes[extra] == vis.PENUMBRA) & (off.offsets[1:] - off.offsets[:-1])[extra] == 0))
    pick = np.where(extra)[0][:: max(1, extra.sum() // 8)]
    tris = list(v[f])
    ref = np.array([reference_ff(q, m, LIGHT, tris) for q, m in zip(p[pick], nrm[pick], strict=True)])
    np.testing.assert_allclose(ref, 0.0, atol=1e-12)
    if name == "open-ring":
        hole = np.hypot(p[:, 0], p[:, 1]) < 0.1
        assert hole.sum() >= 5 and np.all(e_off[hole] > 0) and not np.any(cert[hole])
