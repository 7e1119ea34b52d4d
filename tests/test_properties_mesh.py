r"""Property-based tests (hypothesis) of shadows cast by meshes, against exact polygon booleans.

What is drawn (`tests/random_meshes.py`; a NumPy seed plus a few choices per example): closed
trimesh shapes (icosphere, UV sphere, capsule, torus, subdivided box, cylinder, annulus), most
of them displaced along their normals (non-convex), randomly rotated; open versions (faces cut
below a height or at random, a fifth of them flipped); two or three components side by side;
shapes touching the floor or the light's plane; triangle soups of them with a fifth of the faces
duplicated exactly (some reversed), welded by `Scene`. Receivers: on the floor in penumbra,
umbra and light (picked by the engine's plan from a random set, so that all three are present
when they exist), on the floor at event lines (through a light vertex and an occluder vertex or
edge), inside the meshes' faces and on their edges with the face's normal (float32 scenes: the
documented on-surface rule). float32 and float64. Subdivided boxes are drawn only by the
`test_found_*` cases below (their cut, partly flipped versions are a known failure).
Fine meshes (`path="silhouette"`, hundreds to a thousand faces floating between floor and light)
take the engine's silhouette path for floor receivers; every such case is also evaluated with
`JAXSHADOW_SILHOUETTE=0` (the face path).

Reference: `test_clip.reference_ff` (shapely booleans of the occluders' central projections,
Lambert's sum in NumPy; no code shared with the engine), in float64 at the dtype-rounded inputs,
over the faces that can meet the receiver's view of the light (a face entirely outside one of
the planes through the receiver and a light edge projects outside the light: left out, exactly);
for float32 faces it follows the documented on-surface rule (`_off_surface`).

Asserted at every receiver: the value is finite, never below -8 rounding units of pi (exactly
>= 0 is still open: `test_found_negative_value_near_umbra`) and never above the unoccluded
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


def build(seed: int, kind: str, dt: type, path: str, shapes: tuple[str, ...] = tuple(x for x in rm.SHAPES if x != "box")):
    """`(light (K, 3), occluders for Scene, triangles (T, 3, 3) float64, points, normals, labels)`,
    all in `dt` (the triangles are the dtype-rounded ones, in float64, for the reference)."""
    rng = np.random.default_rng(seed)
    light = rm.light(rng).astype(dt)
    # Without subdivided boxes by default: their cut, partly flipped versions are a known
    # failure (`test_found_open_box_with_flipped_faces`).
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
    if kind != "soup" and dt == F32:
        # On surfaces in float32 only (the documented on-surface rule); float64 faces keep the
        # exact treatment, and a float64 point on a face self-shadows when rounding puts it
        # behind (`test_found_float64_receivers_on_mesh_faces`). Not on a soup's faces: its
        # duplicated faces have either orientation.
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
        # Exactly >= 0 is the requirement (`test_found_negative_value_near_umbra`, a strict
        # xfail); the suite holds the rounding of Lambert's sum meanwhile.
        assert e[i] >= -8 * eps * np.pi, info
        assert e[i] <= unocc[i] + 8 * eps * np.pi, info  # Lambert's sums round absolutely (F <= 1)
        if cls[i] == vis.UMBRA:
            assert e[i] == 0, info
        p64, n64 = p[i].astype(F64), n[i].astype(F64)
        faces = _culled(p64, l64, tris)
        if dt == F32:
            faces = _off_surface(p64, faces, 2.0**-18)
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


# --------------------------------------------------------------------------------------
# Failures the suite found (strict xfails: fixing one makes it fail here; then drop the mark)
# --------------------------------------------------------------------------------------


@pytest.mark.xfail(strict=True, reason="engine: float64 receivers on a float64 mesh's faces self-shadow")
def test_found_float64_receivers_on_mesh_faces():
    """Receivers inside the faces of a closed displaced float64 mesh (random barycentric points,
    off the face's plane by rounding), with the face's normal: the value on the surface is the
    limit from the side the normal points to (the faces holding the receiver dropped from the
    reference); the engine's exact treatment of float64 faces puts some of them behind their own
    face (umbra, 0 where the limit is 0.10 in the draw the suite found)."""
    scene, light, tris, *_ = build(13993, "closed", F64, "silhouette")
    p, n = rm.surface_receivers(np.random.default_rng(0), tris, 24, "face")
    got = np.asarray(js.irradiance(scene, p, n))[:, 0]
    ref = np.pi * np.array([reference_ff(q, m, light, _off_surface(q, _culled(q, light, tris), 1e-13))
                            for q, m in zip(p, n, strict=True)])
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9 * ref.max())


@pytest.mark.xfail(strict=True, reason="engine: an open subdivided box with flipped faces, tilted receiver: 2.8% low")
def test_found_open_box_with_flipped_faces():
    """An open, partly flipped subdivided box over 256 faces (`build(7139986, "open", ...)`, the
    draw before boxes left the profile): the `Mesh` gives 0.024563 where exact polygon booleans
    and an independent 1.4M-ray grid give 0.025283 (the same triangles unwelded through the host
    engine: 0.025284; through the device kernel: 0.024998)."""
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


@pytest.mark.xfail(strict=True, reason="engine: -4.7e-16 at a penumbra receiver next to the umbra")
def test_found_negative_value_near_umbra():
    """A floor receiver the plan puts in penumbra under a closed displaced mesh (the draw
    `(256, "closed", float64, "silhouette")`): its visible region is all but empty and
    Lambert's sum over its boundary rounds to -4.7e-16; irradiance must never be negative."""
    scene, light, tris, p, n, labels = build(256, "closed", F64, "silhouette")
    e = np.asarray(js.irradiance(scene, p[:1], n[:1]))[0, 0]
    assert js.shadow_plan(scene, p[:1], n[:1]).lights[0].classes[0] == vis.PENUMBRA
    assert e >= 0, e
