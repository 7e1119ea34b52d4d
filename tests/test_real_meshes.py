"""Real meshes in the shadow engine: non-convex closed meshes, open meshes and triangle soups.

The engine leaves out the interior edges of a mesh (an edge whose two faces are both added and
lie on opposite sides of the plane through the receiver and the edge) and recognises a receiver
whose light the mesh hides entirely as umbra without building its boundary; a list of triangles
is welded into meshes at `Scene` build. Independent reference: `reference_ff` of
`tests/test_clip.py` (exact polygon booleans in shapely, no code shared with the engine), and
the device kernel (`ShadowOptions(engine="device")`), which clips every face.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxshadow as js
from benchmarks.real_meshes import blob  # the benchmark's shape: one definition
from jaxshadow._shadows import binding as vis

pytestmark = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")
trimesh = pytest.importorskip("trimesh")
shapely = pytest.importorskip("shapely")
from test_clip import reference_ff  # noqa: E402

LIGHT = np.array([[-0.4, -0.4, 2.5], [-0.4, 0.4, 2.5], [0.4, 0.4, 2.5], [0.4, -0.4, 2.5]])
DEVICE = js.ShadowOptions(engine="device")


def floor(n: int, seed: int = 0, half: float = 1.2) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    p = np.c_[rng.uniform(-half, half, (n, 2)), np.zeros(n)]
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    k = n // 5  # grazing normals
    t, a = np.radians(rng.uniform(60, 88, k)), rng.uniform(0, 2 * np.pi, k)
    nrm[:k] = np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)
    return p, nrm


def both_paths(scene, p, nrm, monkeypatch, switch="JAXSHADOW_SILHOUETTE"):
    """`(plan, E)` of the first light with an engine path on, then with it switched off by the
    environment variable `switch` set to 0 (default: the silhouette path, so the second is the
    face path)."""
    on = js.shadow_plan(scene, p, nrm).lights[0]
    e_on = np.asarray(js.irradiance(scene, p, nrm))[:, 0]
    monkeypatch.setenv(switch, "0")
    off = js.shadow_plan(scene, p, nrm).lights[0]
    e_off = np.asarray(js.irradiance(scene, p, nrm))[:, 0]
    monkeypatch.delenv(switch)
    return on, e_on, off, e_off


def _scene(occluders) -> js.Scene:
    return js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=occluders)


@pytest.mark.parametrize("open_below", [None, 0.6], ids=["closed", "open"])
def test_non_convex_mesh_against_polygon_booleans(open_below):
    """Penumbra, umbra and lit receivers of a non-convex closed mesh and of an open one (which
    blocks from both sides, so no face is culled): within 1e-9 of exact polygon booleans."""
    v, f = blob(2, open_below)
    scene = _scene([js.Mesh(v, f)])
    p, nrm = floor(600)
    cls = js.shadow_plan(scene, p, nrm).lights[0].classes
    pick = np.concatenate([np.where(cls == c)[0][:k] for c, k in ((vis.PENUMBRA, 40), (vis.UMBRA, 10), (vis.LIT, 5))])
    if open_below is None:
        assert (cls == vis.UMBRA).sum() > 0, "the floor under the mesh is umbra"
    got = np.asarray(js.irradiance(scene, p[pick], nrm[pick]))[:, 0]
    tris = v[f]
    ref = np.pi * np.array([reference_ff(q, m, LIGHT, list(tris)) for q, m in zip(p[pick], nrm[pick], strict=True)])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * ref.max())
    assert np.all(got[cls[pick] == vis.UMBRA] == 0)


def test_soup_is_welded_into_the_mesh():
    """A list of triangles becomes one mesh per connected component: the same plan (classes,
    candidates) and values as the `js.Mesh`, and the same values as the unwelded faces through
    the device kernel."""
    v, f = blob(2)
    mesh = _scene([js.Mesh(v, f)])
    soup = _scene([v[t] for t in f])
    assert soup.occluder_topology is not None and soup.occluders.shape == mesh.occluders.shape
    p, nrm = floor(400, seed=1)
    a, b = js.shadow_plan(mesh, p, nrm).lights[0], js.shadow_plan(soup, p, nrm).lights[0]
    np.testing.assert_array_equal(a.classes, b.classes)
    np.testing.assert_array_equal(a.candidates, b.candidates)
    e_mesh = np.asarray(js.irradiance(mesh, p, nrm))
    np.testing.assert_array_equal(np.asarray(js.irradiance(soup, p, nrm)), e_mesh)
    sel = np.where(a.classes == vis.PENUMBRA)[0][:24]
    raw = js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=jnp.asarray(v[f]))  # JAX arrays: not welded
    assert raw.occluder_topology is None
    # The device kernel clips every face against every other for each receiver: its memory grows
    # with the receivers of one call (8.1 GB peak for these 24 at once), so one receiver a call
    # (one compiled program, the same shapes).
    dev = np.concatenate([np.asarray(js.irradiance(raw, p[i:i + 1], nrm[i:i + 1], shadows=DEVICE)) for i in sel])
    np.testing.assert_allclose(e_mesh[sel], dev, rtol=0, atol=1e-9 * e_mesh.max())


def test_two_boxes_as_a_soup_are_two_solids():
    """Two boxes given as 24 triangles are two convex solids (each box a component)."""
    def box(lo, hi):
        return js.Mesh.box(lo, hi)
    b1, b2 = box([-0.5, -0.2, 0.4], [-0.1, 0.2, 0.8]), box([0.2, -0.1, 0.5], [0.5, 0.3, 0.9])
    tris = [b.vertices[t] for b in (b1, b2) for t in np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5],
                                                               [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6],
                                                               [3, 0, 4], [3, 4, 7]])]
    soup = _scene(tris)
    assert soup.occluder_topology.n_solids == 2
    p, nrm = floor(300, seed=2)
    want = np.asarray(js.irradiance(_scene([b1, b2]), p, nrm))  # vertex order may differ: rounding only
    np.testing.assert_allclose(np.asarray(js.irradiance(soup, p, nrm)), want, rtol=0, atol=1e-13 * want.max())


def test_gradients_through_interior_edge_culling():
    """Eager derivatives wrt receivers (planned on the host, interior edges left out) equal the
    device kernel's, which clips every face, on penumbra receivers of a non-convex mesh."""
    v, f = blob(1)
    scene = _scene([js.Mesh(v, f)])
    p, nrm = floor(300, seed=3)
    cls = js.shadow_plan(scene, p, nrm).lights[0].classes
    sel = np.where(cls == vis.PENUMBRA)[0][:12]
    q, m = jnp.asarray(p[sel]), jnp.asarray(nrm[sel])
    g = jax.grad(lambda x: js.irradiance(scene, x, m).sum())(q)
    gd = jax.grad(lambda x: js.irradiance(scene, x, m, shadows=DEVICE).sum())(q)
    np.testing.assert_allclose(np.asarray(g), np.asarray(gd), rtol=1e-7, atol=1e-9 * float(jnp.abs(gd).max()))


def _mixed_scene() -> tuple[js.Scene, list[np.ndarray]]:
    """Plain faces only (no convex solid), over 256 of them: a closed non-convex mesh, an open
    one with a quarter of its faces flipped (inconsistently oriented edges), and loose
    triangles that share no edge."""
    v, f = blob(2)
    vo, fo = blob(2, open_below=0.55)
    vo = vo * 0.6 + np.array([0.9, -0.4, 0.25])
    fo = fo.copy()
    fo[::4] = fo[::4, ::-1]
    rng = np.random.default_rng(5)
    loose = [rng.uniform([-1.2, -1.2, 0.5], [1.2, 1.2, 1.6]) + rng.normal(0, 0.08, (3, 3)) for _ in range(12)]
    polys = list(v[f]) + list(vo[fo]) + loose
    return _scene([js.Mesh(v, f), js.Mesh(vo, fo), *loose]), polys


def test_silhouette_path_against_the_face_path_and_polygon_booleans(monkeypatch):
    """The silhouette path (contour edges and depth complexity) against the face path on the same
    receivers (the switch JAXSHADOW_SILHOUETTE=0), and both against exact polygon booleans."""
    scene, polys = _mixed_scene()
    assert scene.occluders.shape[0] >= 256 and scene.occluder_topology.n_solids == 0
    p, nrm = floor(800, seed=7)
    on, e_on, off, e_off = both_paths(scene, p, nrm, monkeypatch)
    # The same classes, except receivers the face path leaves as penumbra with an empty boundary
    # (its regions cover E_h together, none alone), which the depth complexity finds umbra.
    diff = on.classes != off.classes
    assert np.all(on.classes[diff] == vis.UMBRA) and np.all(off.classes[diff] == vis.PENUMBRA)
    assert np.all(np.diff(off.offsets)[diff] == 0)
    pen = on.classes == vis.PENUMBRA
    assert pen.sum() > 50 and (on.classes == vis.UMBRA).sum() > 0
    # The silhouette path counts contour edges, the face path faces: far fewer.
    assert on.candidates[pen].mean() < 0.5 * off.candidates[pen].mean()
    np.testing.assert_allclose(e_on, e_off, rtol=0, atol=1e-11 * e_off.max())
    pick = np.concatenate([np.where(pen)[0][:30], np.where(on.classes == vis.UMBRA)[0][:5]])
    ref = np.pi * np.array([reference_ff(q, m, LIGHT, polys) for q, m in zip(p[pick], nrm[pick], strict=True)])
    np.testing.assert_allclose(e_on[pick], ref, rtol=0, atol=1e-9 * ref.max())


def test_silhouette_path_float32_and_gradients():
    """float32 inputs (decided in double, as the face path does) stay within float32 rounding;
    eager gradients through the silhouette path's codes equal the device kernel's."""
    v, f = blob(2)
    scene = _scene([js.Mesh(v, f)])
    p, nrm = floor(300, seed=8)
    cls = js.shadow_plan(scene, p, nrm).lights[0].classes
    e64 = np.asarray(js.irradiance(scene, p, nrm))
    e32 = np.asarray(js.irradiance(scene, p.astype(np.float32), nrm.astype(np.float32)))
    assert e32.dtype == np.float32
    np.testing.assert_allclose(e32, e64, rtol=0, atol=2e-5 * e64.max())
    sel = np.where(cls == vis.PENUMBRA)[0][:10]
    q, m = jnp.asarray(p[sel]), jnp.asarray(nrm[sel])
    g = np.asarray(jax.grad(lambda x: js.irradiance(scene, x, m).sum())(q))
    # The device kernel clips every face it is given against every other (its memory grows with
    # the square of the face count: 7.5 GB for these 10 receivers at once). It gets the faces
    # that face at least one of the receivers, which cast the whole shadow of this closed mesh
    # for each of them (a ray from p entering the solid crosses a face with p on its front side;
    # every receiver lies clearly off every face's plane, so the same faces face every point
    # near it and the derivatives are the same), one receiver at a time.
    tri = v[f]
    nf = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    h = np.einsum("fk,nfk->nf", nf, p[sel][:, None, :] - tri[None, :, 0]) / np.linalg.norm(nf, axis=1)
    assert np.abs(h).min() > 1e-6
    front = _scene([js.Mesh(v, f[np.any(h > 0, axis=0)])])
    assert front.occluders.shape[0] < 0.7 * scene.occluders.shape[0]
    gd = np.concatenate([np.asarray(jax.grad(lambda x, i=i: js.irradiance(front, x, m[i:i + 1], shadows=DEVICE).sum())(q[i:i + 1]))
                         for i in range(len(sel))])
    np.testing.assert_allclose(g, gd, rtol=1e-7, atol=1e-9 * np.abs(gd).max())


def in_face_planes(v: np.ndarray, f: np.ndarray, offsets, n_faces: int, seed: int = 0) -> np.ndarray:
    """Floor points (z = 0) in the planes of `n_faces` faces of the mesh (v, f), each moved across
    the plane's trace on the floor by every distance of `offsets` (m, along the floor): for each
    face, the point nearest where the ray from the light's centre through the face's centroid
    meets the floor, so that the face lies in the point's view of the light. Faces steeper than
    17 degrees from the floor's normal whose trace passes within 5 cm of that point."""
    tri = v[f].astype(np.float64)
    c = tri.mean(axis=1)
    nf = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nf /= np.linalg.norm(nf, axis=1, keepdims=True)
    top = np.array([0.0, 0.0, 2.5])
    q = top + (c - top) * (2.5 / (2.5 - c[:, 2]))[:, None]
    nxy = np.linalg.norm(nf[:, :2], axis=1)
    step = np.einsum("fk,fk->f", nf, q - tri[:, 0]) / np.maximum(nxy, 1e-300)  # along the floor to the trace
    u = nf[:, :2] / np.maximum(nxy, 1e-300)[:, None]
    ok = np.where((nxy > 0.3) & (np.abs(step) < 0.05))[0]
    idx = np.random.default_rng(seed).permutation(ok)[:n_faces]
    xy = [q[i, :2] - (step[i] - o / nxy[i]) * u[i] for i in idx for o in offsets]
    return np.c_[np.array(xy), np.zeros(len(xy))]


def test_float32_mesh_takes_the_silhouette_path_in_face_planes(monkeypatch):
    """A mesh of float32 values: floor receivers in (to float32 rounding) or 8e-6 m beside the
    planes of faces they see, inside the band where the silhouette path's own side test cannot
    tell (twice the on-surface distance of the scene's largest coordinate) but where the face path
    decides the face (its side, or dropped by the on-surface rule): the silhouette path takes the
    face path's decision and serves every receiver (fewer candidates than the face path's faces),
    with the face path's classes and values; beside them, floor receivers with grazing normals
    (lit, umbra, penumbra). A few against exact polygon booleans on the float32 geometry."""
    v, f = blob(3)
    v = (v + np.random.default_rng(1).normal(0, 1e-3, v.shape)).astype(np.float32)
    scene = _scene([js.Mesh(v, f)])
    planar = in_face_planes(v, f, [0.0, -8e-6, 8e-6], 40)
    fp, fn = floor(300, seed=4, half=1.6)
    p = np.concatenate([planar, fp]).astype(np.float32)
    nrm = np.concatenate([np.tile([0.0, 0.0, 1.0], (len(planar), 1)), fn]).astype(np.float32)
    on, e_on, off, e_off = both_paths(scene, p, nrm, monkeypatch)
    assert e_on.dtype == np.float32
    pen = off.classes == vis.PENUMBRA
    assert pen[: len(planar)].sum() > 100 and (off.classes == vis.UMBRA).sum() > 0 and (off.classes == vis.LIT).sum() > 0
    # The face path falls back for none: its candidates (contour edges) stay below the faces.
    assert np.all(on.candidates[pen] < off.candidates[pen])
    assert on.candidates[pen].mean() < 0.2 * off.candidates[pen].mean()
    diff = on.classes != off.classes
    assert np.all(on.classes[diff] == vis.UMBRA) and np.all(off.classes[diff] == vis.PENUMBRA)
    np.testing.assert_allclose(e_on.astype(np.float64), e_off, rtol=0, atol=1e-9 * e_off.max())
    pick = np.where(pen[: len(planar)])[0][::40]
    polys = [t for t in v[f].astype(np.float64)]
    ref = np.pi * np.array([reference_ff(q, m, LIGHT, polys) for q, m in zip(p[pick], nrm[pick], strict=True)])
    np.testing.assert_allclose(e_on[pick], ref, rtol=0, atol=1e-6 * ref.max())


def test_silhouette_path_with_convex_solids(monkeypatch):
    """Convex solids (floating boxes) beside a non-convex mesh: their faces join the depth
    complexity as plain faces; the values equal the face path's (which uses the solids' cones)."""
    v, f = blob(2)
    boxes = [js.Mesh.box([-0.9, -0.5, 0.5], [-0.6, -0.2, 0.8]), js.Mesh.box([0.7, 0.3, 0.4], [1.0, 0.7, 1.5])]
    scene = _scene([js.Mesh(v, f), *boxes])
    assert scene.occluder_topology.n_solids == 2 and scene.occluders.shape[0] >= 256
    p, nrm = floor(600, seed=9)
    on = js.shadow_plan(scene, p, nrm).lights[0]
    e_on = np.asarray(js.irradiance(scene, p, nrm))[:, 0]
    monkeypatch.setenv("JAXSHADOW_SILHOUETTE", "0")
    off = js.shadow_plan(scene, p, nrm).lights[0]
    e_off = np.asarray(js.irradiance(scene, p, nrm))[:, 0]
    assert (on.classes == vis.PENUMBRA).sum() > 50
    assert on.candidates[on.classes == vis.PENUMBRA].mean() < off.candidates[off.classes == vis.PENUMBRA].mean()
    np.testing.assert_allclose(e_on, e_off, rtol=0, atol=1e-11 * e_off.max())


def test_long_noisy_contours_on_the_contour_grid(monkeypatch):
    """A noisy (scan-like) surface gives receivers dozens to hundreds of contour pieces, which the
    silhouette path arranges on a grid of the emitter plane (crossing candidates and depth
    complexity from cell reference points): values equal the face path's and exact polygon
    booleans', in float64 and float32, and the gradients central differences."""
    v, f = blob(4)
    v = v + np.random.default_rng(5).normal(0, 8e-3, v.shape)
    scene = _scene([js.Mesh(v, f)])
    p, nrm = floor(400, seed=3, half=0.9)
    on = js.shadow_plan(scene, p, nrm).lights[0]
    pen = on.classes == vis.PENUMBRA
    assert pen.sum() > 150 and (on.candidates[pen] >= 64).sum() > 60  # the grid's range (>= 32 pieces)
    e_on = np.asarray(js.irradiance(scene, p, nrm))[:, 0]
    e32 = np.asarray(js.irradiance(scene, p.astype(np.float32), nrm.astype(np.float32)))[:, 0]
    monkeypatch.setenv("JAXSHADOW_SILHOUETTE", "0")
    e_off = np.asarray(js.irradiance(scene, p, nrm))[:, 0]
    monkeypatch.delenv("JAXSHADOW_SILHOUETTE")
    np.testing.assert_allclose(e_on, e_off, rtol=0, atol=1e-11 * e_off.max())
    np.testing.assert_allclose(e32, e_on, rtol=0, atol=2e-5 * e_on.max())
    tris = v[f]
    pick = np.where(pen & (on.candidates >= 64))[0][:8]
    ref = np.pi * np.array([reference_ff(q, m, LIGHT, list(tris)) for q, m in zip(p[pick], nrm[pick], strict=True)])
    np.testing.assert_allclose(e_on[pick], ref, rtol=0, atol=1e-9 * ref.max())
    # Gradients along the floor against central differences (the device kernel's clipping of
    # every face is too large here).
    q, m = jnp.asarray(p[pick[:4]]), jnp.asarray(nrm[pick[:4]])
    g = np.asarray(jax.grad(lambda x: js.irradiance(scene, x, m)[:, 0].sum())(q))
    h = 1e-6
    for d in (0, 1):
        step = np.zeros(3)
        step[d] = h
        fd = (np.asarray(js.irradiance(scene, p[pick[:4]] + step, nrm[pick[:4]]))[:, 0]
              - np.asarray(js.irradiance(scene, p[pick[:4]] - step, nrm[pick[:4]]))[:, 0]) / (2 * h)
        np.testing.assert_allclose(g[:, d], fd, rtol=1e-5, atol=1e-6 * np.abs(g).max())


def t_junction_prism(n_side: int = 40, seed: int = 5) -> tuple[np.ndarray, np.ndarray]:
    """A square prism (960 triangles) with flat fan caps, whose straight runs coplanar merging
    turns into one face each (dropping the side vertices), and walls that bulge at mid-height
    (no merge): the merged caps' edges meet the walls' vertices in T-junctions."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0, 1, n_side + 1)[:-1]
    sq = np.concatenate([np.c_[t, 0 * t], np.c_[1 + 0 * t, t], np.c_[1 - t, 1 + 0 * t], np.c_[0 * t, 1 - t]]) - 0.5
    n = len(sq)
    bulge = 1 + 0.05 * rng.uniform(0.2, 1, n)
    rings = [np.c_[0.6 * sq, np.zeros(n)], np.c_[0.6 * sq * bulge[:, None], np.full(n, 0.15)], np.c_[0.6 * sq, np.full(n, 0.3)]]
    v = np.concatenate([*rings, [[0, 0, 0.0], [0, 0, 0.3]]])
    f = []
    for r in range(2):
        for i in range(n):
            j = (i + 1) % n
            f += [(r * n + i, r * n + j, (r + 1) * n + j), (r * n + i, (r + 1) * n + j, (r + 1) * n + i)]
    for i in range(n):
        j = (i + 1) % n
        f += [(3 * n, j, i), (3 * n + 1, 2 * n + i, 2 * n + j)]
    a = np.radians(25)
    v = v @ np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]).T
    v[:, 2] += 0.3 - v[:, 2].min()
    return v, np.asarray(f)


def test_t_junctions_take_the_silhouette_path(monkeypatch):
    """Coplanar merging leaves T-junctions (a merged face's edge along which the faces across a
    crease keep vertices): the silhouette path pairs their pieces as interior edges and serves
    most penumbra receivers itself (one region kept each; the face path keeps many), within 1e-9
    of polygon booleans and of the face path."""
    v, f = t_junction_prism()
    mesh = js.Mesh(v, f)
    loops = [list(x) for x in mesh.loops]
    directed = {(x[k], x[(k + 1) % len(x)]) for x in loops for k in range(len(x))}
    assert sum((b, a) not in directed for a, b in directed) > 100, "the merged mesh has T-junctions"
    scene = _scene([mesh])
    p, nrm = floor(400, seed=4)
    lp = js.shadow_plan(scene, p, nrm).lights[0]
    pen = lp.classes == vis.PENUMBRA
    assert pen.sum() > 50
    assert np.mean(lp.kept[pen] == 1) > 0.8  # 0.13 where T-junctions send receivers to the face path
    pick = np.concatenate([np.where(pen)[0][:40], np.where(lp.classes == vis.UMBRA)[0][:10]])
    got = np.asarray(js.irradiance(scene, p[pick], nrm[pick]))[:, 0]
    ref = np.pi * np.array([reference_ff(q, m, LIGHT, list(v[f])) for q, m in zip(p[pick], nrm[pick], strict=True)])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * ref.max())
    monkeypatch.setenv("JAXSHADOW_SILHOUETTE", "0")
    face = np.asarray(js.irradiance(scene, p, nrm))[:, 0]
    monkeypatch.delenv("JAXSHADOW_SILHOUETTE")
    e = np.asarray(js.irradiance(scene, p, nrm))[:, 0]
    np.testing.assert_allclose(e, face, rtol=0, atol=1e-9 * face.max())
