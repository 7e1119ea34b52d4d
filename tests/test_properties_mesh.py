r"""Property-based tests (hypothesis) of shadows cast by meshes, against exact polygon booleans.

What is drawn (`tests/random_meshes.py`; a NumPy seed plus a few choices per example): closed
trimesh shapes (icosphere, UV sphere, capsule, torus, subdivided box, cylinder, annulus), most
of them displaced along their normals (non-convex), randomly rotated; open versions (faces cut
below a height or at random, a fifth of them flipped); two or three components side by side;
shapes touching the floor or the light's plane; triangle soups of them with a fifth of the faces
duplicated exactly (some reversed), welded by `Scene`. Receivers: on the floor in penumbra,
umbra and light (picked by the engine's plan from a random set, so that all three are present
when they exist), on the floor at event lines (through a light vertex and an occluder vertex or
edge), inside the meshes' faces and on their edges with the face's normal (the documented
on-surface rule). float32 and float64.
Fine meshes (`path="silhouette"`, hundreds to a thousand faces floating between floor and light)
take the engine's silhouette path for floor receivers; every such case is also evaluated with
`JAXSHADOW_SILHOUETTE=0` (the face path).

Reference: `test_clip.reference_ff` (shapely booleans of the occluders' central projections,
Lambert's sum in NumPy; no code shared with the engine), in float64 at the dtype-rounded inputs,
over the faces that can meet the receiver's view of the light (a face entirely outside one of
the planes through the receiver and a light edge projects outside the light: left out, exactly);
it follows the documented on-surface rule (`_off_surface`: 2^-18 S for float32 faces, 2^-44 S
for float64 ones).

Asserted at every receiver: the value is finite, never below 0 and never above the unoccluded
value (up to 8 rounding units of pi: two different contour sums, whose error is absolute in
the form factor), and within float64 `1e-9 U`
/ float32 `1e-5 U` of the reference, `U = max(unoccluded, 1e-3)`; in umbra exactly 0. Gradients
with respect to the receivers against central differences at penumbra receivers (float64; one case in CI, where its compilation takes most of a minute, the others
under `-m slow`).

Profiles: CI runs `CI_EXAMPLES` derandomized draws of `RECEIVERS` receivers each (>= 200 mesh
cases); `-m slow` runs `LONG_EXAMPLES` random draws.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import jaxshadow as js
from jaxshadow._shadows import binding as vis

pytestmark = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")
pytest.importorskip("trimesh")
pytest.importorskip("shapely")
import random_meshes as rm  # noqa: E402
from test_clip import reference_ff  # noqa: E402

CI_EXAMPLES = 36
LONG_EXAMPLES = 400
RECEIVERS = 7
F32, F64 = np.float32, np.float64


CI = rm.profile(CI_EXAMPLES, True)
LONG = rm.profile(LONG_EXAMPLES, False)


@st.composite
def mesh_draws(draw):
    """`(seed, kind, dtype, path)`; the scene is built by `build` outside the strategy (trimesh
    touches the `random` module)."""
    path = draw(st.sampled_from(["face", "face", "silhouette"]))
    kinds = ["closed", "open", "components"] if path == "silhouette" else ["closed", "open", "components", "floor",
                                                                          "light", "soup"]
    return draw(st.integers(0, 2**32 - 1)), draw(st.sampled_from(kinds)), draw(st.sampled_from([F32, F64])), path


def build(seed: int, kind: str, dt: type, path: str, shapes: tuple[str, ...] | None = None):
    """`(light (K, 3), occluders for Scene, triangles (T, 3, 3) float64, points, normals, labels)`,
    all in `dt` (the triangles are the dtype-rounded ones, in float64, for the reference)."""
    rng = np.random.default_rng(seed)
    light = rm.light(rng).astype(dt)
    if shapes is None:  # a subdivided box merges back into a few faces: not a fine mesh
        shapes = rm.SHAPES if path == "face" else tuple(x for x in rm.SHAPES if x != "box")
    meshes = rm.mesh_scene(rng, "components" if kind == "soup" else kind, fine=path == "silhouette", shapes=shapes)
    meshes = [(v.astype(dt), f) for v, f in meshes]
    if kind == "soup":
        tris = rm.soup(rng, [(v.astype(F64), f) for v, f in meshes], duplicates=0.2).astype(dt)
        occluders: list = list(tris)
    else:
        occluders = [js.Mesh(v, f) for v, f in meshes]
        tris = np.concatenate([v[f] for v, f in meshes])
    t64 = tris.astype(F64)
    scene = js.Scene([js.PolygonLight(light, 1.0)], occluders=occluders)
    # Floor receivers: penumbra, umbra and lit ones, as the plan finds them.
    fp, fn = rm.floor_receivers(rng, 64)
    fp, fn = fp.astype(dt), fn.astype(dt)
    cls = js.shadow_plan(scene, fp, fn).lights[0].classes
    pick = np.concatenate([np.where(cls == vis.PENUMBRA)[0][:3], np.where(cls == vis.UMBRA)[0][:1],
                           np.where(cls == vis.LIT)[0][:1]])
    pick = np.concatenate([pick, np.setdiff1d(np.arange(64), pick)])[:4]
    parts = [(fp[pick], fn[pick], ["floor"] * 4), (*rm.event_receivers(rng, light.astype(F64), t64, 1), ["event"])]
    if kind != "soup":
        # On surfaces (the documented on-surface rule, `_off_surface`). Not on a soup's faces:
        # its duplicated faces have either orientation.
        parts += [(*rm.surface_receivers(rng, t64, 1, "face"), ["face"]), (*rm.surface_receivers(rng, t64, 1, "edge"), ["edge"])]
    else:
        parts += [(*rm.floor_receivers(rng, 2), ["floor", "floor"])]
    p = np.concatenate([x[0] for x in parts]).astype(dt)
    n = np.concatenate([x[1] for x in parts]).astype(dt)
    labels = sum((x[2] for x in parts), [])
    return scene, light, t64, p, n, labels


def _culled(p: np.ndarray, light: np.ndarray, tris: np.ndarray) -> list[np.ndarray]:
    """The triangles not entirely outside a plane through `p` and a light edge (those project
    outside the light)."""
    keep = np.ones(len(tris), bool)
    c = light.mean(axis=0)
    for i in range(len(light)):
        a, b = light[i], light[(i + 1) % len(light)]
        nrm = np.cross(a - p, b - p)
        if nrm @ (c - p) < 0:
            nrm = -nrm
        keep &= np.any((tris - p) @ nrm > 0, axis=1)
    return list(tris[keep])


def _off_surface(p: np.ndarray, tris: np.ndarray, tol: float) -> list[np.ndarray]:
    """The faces whose plane is at least `tol S` from the receiver (`S` the largest coordinate
    magnitude of their vertices and the receiver): the others hold it, and block nothing for it
    (`docs/design.md`, "Receivers on occluding surfaces": `2^-18` for float32 faces)."""
    if not len(tris):
        return []
    t = np.asarray(tris)
    nrm = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    dist = np.abs(np.einsum("td,td->t", nrm, p - t[:, 0]))
    s = np.maximum(np.abs(t).max(axis=(1, 2)), np.abs(p).max())
    return list(t[dist >= tol * s])


def _check(scene, light, tris, p, n, labels, what) -> None:
    dt = p.dtype
    e = np.asarray(js.irradiance(scene, p, n))[:, 0]
    unocc = np.asarray(js.irradiance(js.Scene(scene.lights), p, n))[:, 0]
    cls = js.shadow_plan(scene, p, n).lights[0].classes
    l64 = light.astype(F64)
    rtol = 1e-9 if dt == F64 else 1e-5
    eps = np.finfo(dt).eps
    for i in range(len(p)):
        info = (what, i, labels[i], int(cls[i]), float(e[i]), float(unocc[i]))
        assert np.isfinite(e[i]), info
        assert e[i] >= 0, info  # `test_found_negative_value_near_umbra`
        assert e[i] <= unocc[i] + 8 * eps * np.pi, info  # Lambert's sums round absolutely (F <= 1)
        if cls[i] == vis.UMBRA:
            assert e[i] == 0, info
        p64, n64 = p[i].astype(F64), n[i].astype(F64)
        faces = _off_surface(p64, _culled(p64, l64, tris), 2.0**-18 if dt == F32 else 2.0**-44)
        ref = np.pi * reference_ff(p64, n64 / np.linalg.norm(n64), l64, faces)
        assert abs(e[i] - ref) <= rtol * max(unocc[i], 1e-3), (*info, ref)


def _run(draw, monkeypatch) -> None:
    seed, kind, dt, path = draw
    case = build(seed, kind, dt, path)
    _check(*case, what=draw)
    if path == "silhouette":
        monkeypatch.setenv("JAXSHADOW_SILHOUETTE", "0")
        try:
            _check(*case, what=(*draw, "face path"))
        finally:
            monkeypatch.delenv("JAXSHADOW_SILHOUETTE")


@CI
@given(mesh_draws())
def test_mesh_shadows_against_polygon_booleans(draw):
    with pytest.MonkeyPatch.context() as mp:
        _run(draw, mp)


@pytest.mark.slow
@LONG
@given(mesh_draws())
def test_mesh_shadows_against_polygon_booleans_long(draw):
    with pytest.MonkeyPatch.context() as mp:
        _run(draw, mp)


def test_silhouette_draws_take_the_silhouette_path():
    """The fine draws are what the silhouette path serves: over 256 faces, every vertex strictly
    between the floor and the light; the two paths plan different candidate counts there."""
    for seed in range(3):
        scene, *_ = build(seed, "closed", F64, "silhouette")
        occ = np.asarray(scene.occluders)
        assert occ.shape[0] >= 256 and 0 < occ[..., 2].min() and occ[..., 2].max() < rm.LIGHT_Z
    p, n = rm.floor_receivers(np.random.default_rng(0), 200)
    on = js.shadow_plan(scene, p, n).lights[0]
    os.environ["JAXSHADOW_SILHOUETTE"] = "0"
    try:
        off = js.shadow_plan(scene, p, n).lights[0]
    finally:
        del os.environ["JAXSHADOW_SILHOUETTE"]
    pen = on.classes == vis.PENUMBRA
    assert pen.sum() > 10 and on.candidates[pen].mean() < off.candidates[pen].mean()


@pytest.mark.parametrize("seed,kind,path", [(1, "closed", "face"), pytest.param(2, "open", "face", marks=pytest.mark.slow),
                                             pytest.param(3, "closed", "silhouette", marks=pytest.mark.slow)])
def test_mesh_shadow_gradients_against_finite_differences(seed, kind, path):
    """d E / d p (eager, codes from the host engine) against central differences of the values
    at penumbra floor receivers, float64; where the two step sizes' differences disagree the
    boundary's combinatorics changed within the step (a kink): those receivers are left out."""
    scene, light, tris, _, _, _ = build(seed, kind, F64, path)
    p, n = rm.floor_receivers(np.random.default_rng(seed), 200)
    cls = js.shadow_plan(scene, p, n).lights[0].classes
    sel = np.where(cls == vis.PENUMBRA)[0][:8]
    assert len(sel) >= 4
    q, m = jnp.asarray(p[sel]), jnp.asarray(n[sel])
    g = np.asarray(jax.grad(lambda x: js.irradiance(scene, x, m)[:, 0].sum())(q))
    assert np.all(np.isfinite(g))

    def fd(h):
        out = np.zeros((len(sel), 2))
        for k in range(2):
            d = np.zeros(3)
            d[k] = h
            up = np.asarray(js.irradiance(scene, p[sel] + d, n[sel]))[:, 0]
            dn = np.asarray(js.irradiance(scene, p[sel] - d, n[sel]))[:, 0]
            out[:, k] = (up - dn) / (2 * h)
        return out

    a, b = fd(1e-5), fd(2e-6)
    smooth = np.all(np.abs(a - b) <= 1e-6 + 1e-4 * np.abs(a), axis=1)
    assert smooth.sum() >= 3
    np.testing.assert_allclose(g[smooth, :2], a[smooth], rtol=1e-4, atol=1e-6 * np.abs(a).max())


def _t_junction_strip(rng: np.random.Generator, size: float) -> list[np.ndarray]:
    """A small planar strip of `size` at a random place and orientation between the floor and the
    light: a quad `A B D E` and, across its edge `E -> A`, the triangle `C E F` whose vertex `C`
    is the midpoint of `A E` (rounded): a T-junction, the two faces meeting along `C E` with
    different edges, as `Mesh`'s coplanar merging leaves them."""
    u, w = rm.rotate(rng, np.eye(3))[:2]
    o = np.r_[rng.uniform(-0.3, 0.3, 2), rng.uniform(0.8, 1.5)]
    x = lambda s, t: o + size * (s * u + t * w)  # noqa: E731
    a, b, d, e = x(0, 0), x(1, 0.1), x(1.1, 1.0), x(0, 1)
    c = 0.5 * (a + e)
    f = x(-0.8, 0.6)
    return [np.stack([a, b, d, e]), np.stack([c, e, f])]


@pytest.mark.parametrize("seed", range(4))
def test_t_junctions_on_short_edges(seed):
    """Faces meeting in a T-junction (an edge of one along part of an edge of the other), small
    and far from the receivers, so that the planes through a receiver and the two edges differ by
    more rounding than the angle test's collinear tolerance: the shared piece bounds nothing (a
    test of the edges' line in space decides); exact polygon booleans as the reference, float64,
    the faces as given and reversed."""
    rng = np.random.default_rng(seed)
    light = rm.light(rng)
    strips = [_t_junction_strip(rng, rng.uniform(0.005, 0.05)) for _ in range(24)]
    polys = [q for s in strips for q in s]
    p, n = rm.floor_receivers(rng, 48)
    ref = np.pi * np.array([reference_ff(q, m / np.linalg.norm(m), light, polys) for q, m in zip(p, n, strict=True)])
    unocc = np.asarray(js.irradiance(js.Scene([js.PolygonLight(light, 1.0)]), p, n))[:, 0]
    assert np.ptp(ref - unocc) > 1e-3  # the strips cast shadows on these receivers
    for occ in (polys, [q[::-1].copy() for q in polys]):
        got = np.asarray(js.irradiance(js.Scene([js.PolygonLight(light, 1.0)], occluders=occ), p, n))[:, 0]
        err = np.abs(got - ref) / np.maximum(unocc, 1e-3)
        assert err.max() <= 1e-9, (err.max(), int(np.argmax(err)))


@pytest.mark.parametrize("dt", [F32, F64])
def test_receivers_on_faces_of_touching_boxes(dt):
    """Boxes side by side sharing a face (and coplanar tops), a box standing on another:
    receivers on their faces and edges with either normal (on a shared face the other box's
    coincident face holds them too, and blocks nothing for them), against polygon booleans with
    the on-surface rule; never negative, never above the unoccluded values. (float32: the
    kernels' sums round absolutely, terms of order 1: within 1e-5 of max(U, 1e-2).)"""
    from test_plan import LIGHT, box

    boxes = [box((-0.3, -0.2, 0.5), (0.0, 0.2, 1.0)), box((0.0, -0.2, 0.5), (0.3, 0.2, 1.0)),
             box((-0.25, -0.1, 1.0), (-0.05, 0.1, 1.3))]
    boxes = [(v.astype(dt), f) for v, f in boxes]
    tris = np.concatenate([v[f] for v, f in boxes]).astype(F64)
    light = LIGHT.astype(dt)
    rng = np.random.default_rng(2)
    p, n = rm.surface_receivers(rng, tris, 80, "face")
    n[::2] = -n[::2]
    q, m = rm.surface_receivers(rng, tris, 20, "edge")
    p, n = np.concatenate([p, q]), np.concatenate([n, m])
    p, n = p.astype(dt), n.astype(dt)
    scene = js.Scene([js.PolygonLight(light, 1.0)], occluders=[js.Mesh(v, f) for v, f in boxes])
    got = np.asarray(js.irradiance(scene, p, n))[:, 0]
    unocc = np.asarray(js.irradiance(js.Scene(scene.lights), p, n))[:, 0]
    eps = np.finfo(dt).eps
    tol = 2.0**-18 if dt == F32 else 2.0**-44
    l64 = light.astype(F64)
    ref = np.array([np.pi * reference_ff(a, b / np.linalg.norm(b), l64, _off_surface(a, _culled(a, l64, tris), tol))
                    for a, b in zip(p.astype(F64), n.astype(F64), strict=True)])
    assert np.count_nonzero(ref > 1e-3) >= 10 and np.count_nonzero(ref < unocc - 1e-3) >= 5  # lit and shadowed ones
    assert np.all(got >= 0) and np.all(got <= unocc + 8 * eps * np.pi)
    err = np.abs(got - ref) / np.maximum(unocc, 1e-2 if dt == F32 else 1e-3)
    assert err.max() <= (1e-5 if dt == F32 else 1e-9), (err.max(), int(np.argmax(err)), p[np.argmax(err)])


# --------------------------------------------------------------------------------------
# Failures the suite found (strict xfails: fixing one makes it fail here; then drop the mark)
# --------------------------------------------------------------------------------------


def test_found_float64_receivers_on_mesh_faces():
    """Receivers inside the faces of a closed displaced float64 mesh (random barycentric points,
    off the face's plane by rounding, 1e-16 S), with the face's normal: the value on the surface
    is the limit from the side the normal points to (the faces holding the receiver dropped from
    the reference). Without an on-surface distance for float64 faces (`kOnSurface64`), whose
    rounding bound follows the face's size, not the coordinates', some were behind their own
    face (0 where the limit is 0.27 in the draw the suite found, or -6e-16)."""
    scene, light, tris, *_ = build(13993, "closed", F64, "silhouette")
    p, n = rm.surface_receivers(np.random.default_rng(0), tris, 24, "face")
    got = np.asarray(js.irradiance(scene, p, n))[:, 0]
    ref = np.pi * np.array([reference_ff(q, m, light, _off_surface(q, _culled(q, light, tris), 1e-13))
                            for q, m in zip(p, n, strict=True)])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * ref.max())


def test_found_open_box_with_flipped_faces():
    """An open, partly flipped subdivided box over 256 faces (`build(7139986, "open", ...)`):
    exact polygon booleans and an independent 1.4M-ray grid give 0.025283. `Mesh`'s coplanar
    merging drops a vertex lying (to rounding) inside a merged edge, so the neighbouring face's
    edge meets it in a T-junction: two occluder edges on one line, whose planes through the
    receiver differ by 1.6e-14 rad of rounding (a short edge seen from afar), beyond the angle
    test, and the shared piece was left in the boundary (0.00613)."""
    rng = np.random.default_rng(7139986)
    light = rm.light(rng)
    meshes = rm.mesh_scene(rng, "open", fine=True)
    (v, f), = meshes
    p = np.array([-0.58071631, -0.75821798, 0.0])
    n = np.array([0.14106764, -0.21589429, 0.96617264])
    n /= np.linalg.norm(n)
    ref = np.pi * reference_ff(p, n, light, list(v[f]))
    got = float(np.asarray(js.irradiance(js.Scene([js.PolygonLight(light, 1.0)], occluders=[js.Mesh(v, f)]), p[None], n[None]))[0, 0])
    assert abs(got - ref) <= 1e-9 * ref


def test_found_negative_value_near_umbra():
    """A floor receiver the plan puts in penumbra under a closed displaced mesh (the draw
    `(256, "closed", float64, "silhouette")`): its visible region is all but empty (polygon
    booleans: 0; nine runs of length 1e-16) and Lambert's sum over its boundary rounded to
    -4.7e-16. Irradiance is never negative: a sum within its rounding bound is 0, on the host
    path and on the differentiable one (finite gradient)."""
    scene, light, tris, p, n, labels = build(256, "closed", F64, "silhouette")
    e = np.asarray(js.irradiance(scene, p[:1], n[:1]))[0, 0]
    assert js.shadow_plan(scene, p[:1], n[:1]).lights[0].classes[0] == vis.PENUMBRA
    assert e >= 0, e
    assert reference_ff(p[0], n[0], light, list(tris)) < 1e-12
    q, m = jnp.asarray(p[:1]), jnp.asarray(n[:1])
    val, g = jax.value_and_grad(lambda x: js.irradiance(scene, x, m)[:, 0].sum())(q)
    assert float(val) >= 0 and np.all(np.isfinite(np.asarray(g))), (float(val), g)


# float64 penumbra receivers where the engine and polygon booleans disagree (found by the long
# profile; the engine gives the same values with and without the on-surface and T-junction
# fixes): event-line, floor and edge receivers of open and multi-component meshes, 0.0038 where
# the reference says 7.6e-5, and one value above its unoccluded value (that one is the engine's
# fault whatever the reference). Not yet diagnosed which side is wrong in the others.
FOUND_F64 = [
    (2497178190, "open", F64, "silhouette"),
    (3419883616, "components", F64, "face"),
    (2795171778, "open", F64, "silhouette"),
    (761648817, "closed", F64, "face"),
    (506704453, "open", F64, "silhouette"),
    (3120723001, "components", F64, "face"),
    (729964239, "components", F64, "silhouette"),
]


@pytest.mark.parametrize("draw", FOUND_F64, ids=[f"{d[0]}-{d[1]}-{d[3]}" for d in FOUND_F64])
@pytest.mark.xfail(strict=True, reason="engine vs polygon booleans: float64 penumbra receivers disagree (undiagnosed)")
def test_found_float64_penumbra_on_event_lines(draw):
    with pytest.MonkeyPatch.context() as mp:
        _run(draw, mp)
