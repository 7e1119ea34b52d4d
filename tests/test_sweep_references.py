"""The array forms of the sweep's independent references (`benchmarks._robustness_checks`) against
the tests' own: `reference_ff_batched` (occluders clipped and projected as arrays) against
`test_clip.reference_ff` (one by one), the point and directional ray references with and without
the bounding-box narrowing, and the capped choice of receivers for the polygon booleans
(`benchmarks.mesh_sweep._polygon_checked`)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import jaxshadow as js
from benchmarks import _robustness_checks as chk
from benchmarks import mesh_sweep as ms

jax.config.update("jax_enable_x64", True)
pytest.importorskip("shapely")
pytest.importorskip("trimesh")
from test_clip import random_scene, reference_ff  # noqa: E402
from test_plan import culled  # noqa: E402
from test_properties_mesh import _off_surface  # noqa: E402


@pytest.fixture(scope="module")
def fins() -> tuple[np.ndarray, np.ndarray, dict]:
    g = ms.generated(("fins",), subdivisions=2)["fins"]
    tris = g["v"][g["f"]]
    return tris, g["quad"], ms.receivers(tris, 60)


def test_batched_polygon_reference_equals_reference_ff(fins) -> None:
    """Every receiver group of a mesh with fins (floor, grazing contact, on its surface at 0 and
    1e-9 m, inside its box) under the quad light, and the light crossing the mesh: the batched
    form gives `reference_ff`'s value to 1e-14 of the unoccluded one (the same polygons, up to the
    rounding of the projection)."""
    tris, quad, groups = fins
    p = np.concatenate([g[0] for g in groups.values()])
    n = np.concatenate([g[1] for g in groups.values()])
    low = quad - [0.0, 0.0, 2.5 - 0.9]  # through the mesh's top: faces on both sides of its plane
    pen = 0
    for light in (quad, low):
        unocc = np.asarray(js.irradiance(js.Scene([js.PolygonLight(light, 1.0)]), p, n))[:, 0] / np.pi
        for i in range(0, len(p), 3):
            y = n[i] / np.linalg.norm(n[i])
            faces = _off_surface(p[i], culled(p[i], y, light, tris), chk.ON_SURFACE_64)
            want = reference_ff(p[i], y, light, faces)
            got = chk.reference_ff_batched(p[i], y, light, np.asarray(faces).reshape(-1, 3, 3))
            assert abs(got - want) <= 1e-14 * max(unocc[i], 1e-3 * unocc.max()), (i, got, want)
            pen += 0 < want < 0.999 * unocc[i]
    assert pen >= 10  # partly shadowed receivers: the booleans matter


@pytest.mark.parametrize("seed", range(3))
def test_batched_polygon_reference_random_scenes(seed) -> None:
    """Random convex occluders (`test_clip.random_scene`, as triangle fans) over floor receivers,
    tilted ones (the horizon cuts the emitter) and raised ones (occluders across their horizon)."""
    em, occs = random_scene(700 + seed, 8)
    tris = np.concatenate([np.stack([np.broadcast_to(o[0], (len(o) - 2, 3)), o[1:-1], o[2:]], axis=1) for o in occs])
    rng = np.random.default_rng(seed)
    pts = np.c_[rng.uniform(-2.5, 2.5, (18, 2)), np.zeros(18)]
    nrm = np.tile([0.0, 0.0, 1.0], (18, 1))
    nrm[:5] = np.c_[np.sin(np.linspace(-1.3, 1.3, 5)), np.zeros(5), np.cos(np.linspace(-1.3, 1.3, 5))]
    pts[13:, 2] = rng.uniform(0.3, 1.5, 5)
    pen = 0
    for p, y in zip(pts, nrm, strict=True):
        want = reference_ff(p, y, em, list(tris))
        assert abs(chk.reference_ff_batched(p, y, em, tris) - want) <= 1e-14
        pen += want > 1e-6 and chk.reference_ff_batched(p, y, em, tris[:0]) > want * (1 + 1e-9)
    assert pen >= 2


@pytest.mark.parametrize("kind", ["point", "directional"])
def test_ray_reference_box_narrowing(fins, kind) -> None:
    """The ray references give the same values with and without the bounding-box narrowing, on
    every receiver (on the surface, grazing, inside the box): shadowed and lit ones both."""
    tris, quad, groups = fins
    p = np.concatenate([g[0] for g in groups.values()])
    n = np.concatenate([g[1] for g in groups.values()])
    centre = (tris.reshape(-1, 3).max(axis=0) + tris.reshape(-1, 3).min(axis=0)) / 2
    light = ms.light_of(kind, quad, centre)
    a = chk.kind_reference(kind, light, tris, p, n, boxes=True)
    b = chk.kind_reference(kind, light, tris, p, n, boxes=False)
    np.testing.assert_array_equal(a, b)
    assert 0 < np.sum(a == 0) < len(a)


def test_polygon_checked_face_cap(fins) -> None:
    """The capped choice: the first receiver is always checked; one whose faces would take the
    total over the cap is left out and counted; the values are the polygon booleans'."""
    tris, quad, groups = fins
    p, n = groups["floor"][0], groups["floor"][1]
    light = js.PolygonLight(quad, 1.0)
    y = n / np.linalg.norm(n, axis=1, keepdims=True)
    faces = np.array([len(_off_surface(p[i], culled(p[i], y[i], quad, tris), chk.ON_SURFACE_64)) for i in range(len(p))])
    big = np.argsort(-faces)[:3]
    assert faces[big[-1]] > 0
    order = [("worst", int(big[0])), ("contact", int(big[1])), ("penumbra", int(big[2]))]
    done, vals, count = ms._polygon_checked(light, tris, p, n, order, cap=int(faces[big[0]] + faces[big[2]]))
    assert done.tolist() == [big[0], big[2]]
    assert count == {"worst": [1, 0], "contact": [0, 1], "penumbra": [1, 0]}
    np.testing.assert_allclose(vals, chk.polygon_reference(quad, tris, p[done], n[done], batched=False), rtol=1e-14)
    done, _, count = ms._polygon_checked(light, tris, p, n, order, cap=None)
    assert len(done) == 3 and count["contact"] == [1, 0]
