"""What the shadow engine does per call, where a fit calls it thousands of times: every light kind
reads the occluders' prepared data from one cache (`csrc/engine/prepared.h`, counted by
`binding.prepared_stats`), a batched call inside a compiled program (`vmap` over light poses)
looks the shared occluders up once, and a receiver's result does not depend on the batch it comes
in nor on whether its batch shares walks of the silhouette path's hierarchy (tiles,
`JAXSHADOW_SIL_TILES`)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxshadow as js
from jaxshadow._shadows import binding as vis

trimesh = pytest.importorskip("trimesh")
built = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")
with_ffi = pytest.mark.skipif(not vis.ffi_available(), reason="the engine's XLA FFI handlers are not usable")

QUAD = np.array([[-0.25, 0.15, 1.6], [0.25, 0.15, 1.6], [0.25, -0.15, 1.6], [-0.25, -0.15, 1.6]])


def _bumpy_sphere(seed: int, subdivisions: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """A closed non-convex mesh (an icosphere of 20 * 4**subdivisions faces, radii moved by random
    plane waves), 0.3 m across, 0.3-0.9 m above the floor; `seed` makes it unlike any other test's."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    v = np.asarray(m.vertices, np.float64)
    rng = np.random.default_rng(seed)
    k, phase = rng.normal(size=(6, 3)) * 2.5, rng.uniform(0.0, 2 * np.pi, 6)
    v = v * (1.0 + 0.3 * np.sin(v @ k.T + phase).mean(axis=1))[:, None] * 0.3 + np.array([0.0, 0.0, 0.6])
    return v, np.asarray(m.faces)


def _occluders(seed: int) -> tuple[js.Scene, vis.HostOccluders]:
    v, f = _bumpy_sphere(seed)
    scene = js.Scene([js.PolygonLight(QUAD, radiance=1.0)], occluders=[js.Mesh(v, f)])
    return scene, vis.HostOccluders.of(np.asarray(scene.occluders), scene.occluder_topology, np.float64)


def _floor(n: int, half: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return np.c_[rng.uniform(-half, half, (n, 2)), np.zeros(n)], np.tile([0.0, 0.0, 1.0], (n, 1))


def _delta(before: dict) -> dict:
    after = vis.prepared_stats()
    return {k: after[k] - before[k] for k in after}


@built
def test_every_light_kind_reuses_the_prepared_occluders():
    """Point, directional and segment lights build the occluders' hierarchy once and find it
    afterwards, without the parts only polygon lights read; a polygon light then adds those parts
    (once) to the same entry."""
    scene, occ = _occluders(seed=101)
    assert occ.faces.shape[0] >= 1024  # cached sizes
    p, _ = _floor(50, 1.0)
    lamp = np.array([0.1, 0.05, 1.6])

    s = vis.prepared_stats()
    first = vis.hard_visibility(p, lamp, True, occ)
    assert _delta(s) == {"lookups": 1, "hits": 0, "builds": 1, "polygon_builds": 0}
    assert np.any(~first) and np.any(first)

    s = vis.prepared_stats()
    again = vis.hard_visibility(p, lamp, True, occ)
    vis.hard_visibility(p, np.array([0.2, 0.1, -1.0]), False, occ)
    vis.segment_candidates(p, QUAD[0], QUAD[2], occ)
    assert _delta(s) == {"lookups": 3, "hits": 3, "builds": 0, "polygon_builds": 0}
    np.testing.assert_array_equal(again, first)

    s = vis.prepared_stats()
    n = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    vis.polygon_codes(p, n, QUAD, occ)
    vis.polygon_codes(p, n, QUAD + 0.1, occ)
    assert _delta(s) == {"lookups": 2, "hits": 2, "builds": 0, "polygon_builds": 1}


@built
def test_lights_of_other_vertex_counts_do_not_share_polygon_parts():
    """The polygon parts hold vertex references offset by the light's vertex count, so a triangle
    light on occluders a quad light prepared must give what it gives on freshly prepared ones (the
    same occluders again once four other sets have pushed them out of the cache)."""
    scene, occ = _occluders(seed=107)
    p, n = _floor(400, 1.2, seed=3)
    tri = QUAD[:3].copy()
    vis.polygon_codes(p, n, QUAD, occ)
    s = vis.prepared_stats()
    after_quad = vis.polygon_codes(p, n, tri, occ, codes=True)
    assert _delta(s)["builds"] == 0  # the quad's entry
    for seed in (108, 109, 110, 111):  # evict it
        vis.hard_visibility(p[:5], np.array([0.0, 0.0, 1.6]), True, _occluders(seed)[1])
    s = vis.prepared_stats()
    fresh = vis.polygon_codes(p, n, tri, occ, codes=True)
    assert _delta(s)["builds"] == 1  # prepared anew, the triangle first
    assert np.bincount(fresh.classes, minlength=4)[vis.PENUMBRA] > 20
    np.testing.assert_array_equal(after_quad.classes, fresh.classes)
    np.testing.assert_array_equal(after_quad.offsets, fresh.offsets)
    np.testing.assert_array_equal(after_quad.runs, fresh.runs)


@with_ffi
def test_a_batched_call_looks_the_shared_occluders_up_once():
    """`vmap` over 8 light poses with the mesh shared (not batched): one cache lookup per handler
    call, not one per pose; the poses' results are the host calls' of each pose."""
    scene, occ = _occluders(seed=102)
    p, n = _floor(30, 1.0)
    faces = jnp.asarray(occ.faces)
    topo = scene.occluder_topology
    shifts = np.random.default_rng(3).normal(size=(8, 3)) * 0.05
    kinds = {
        "polygon": (lambda d: vis.traced_polygon_codes(jnp.asarray(p), jnp.asarray(n), jnp.asarray(QUAD) + d[None], faces,
                                                       topo, 48)[1],
                    lambda d: vis.polygon_codes(p, n, QUAD + d, occ).counts),
        "point": (lambda d: vis.traced_hard_visibility(jnp.asarray(p), jnp.asarray(QUAD.mean(axis=0)) + d, True, faces,
                                                       topo),
                  lambda d: vis.hard_visibility(p, QUAD.mean(axis=0) + d, True, occ).astype(np.int32)),
        "segment": (lambda d: vis.traced_segment_candidates(jnp.asarray(p), jnp.asarray(QUAD[0]) + d,
                                                            jnp.asarray(QUAD[2]) + d, faces, topo, 64)[0],
                    lambda d: np.diff(vis.segment_candidates(p, QUAD[0] + d, QUAD[2] + d, occ)[0])),
    }
    for kind, (traced, host) in kinds.items():
        fn = jax.jit(jax.vmap(traced))
        jax.block_until_ready(fn(jnp.asarray(shifts)))  # compiled
        s = vis.prepared_stats()
        got = np.asarray(fn(jnp.asarray(shifts)))
        assert _delta(s)["lookups"] == 1, kind
        for b, d in enumerate(shifts):
            want = host(d)
            if kind == "polygon":  # the host plan keeps the boundary of penumbra receivers only
                pen = vis.polygon_codes(p, n, QUAD + d, occ).classes == vis.PENUMBRA
                got_b, want = got[b][pen], want[pen]
            else:
                got_b = got[b]
            np.testing.assert_array_equal(got_b, want, err_msg=kind)


@built
@pytest.mark.parametrize("tiles", ["0", "1", "auto"])
def test_a_receivers_result_is_the_same_alone_and_in_any_batch(tiles, monkeypatch):
    """A dense patch of floor receivers under the mesh (their tiles share walks when allowed) and
    scattered ones (never worth a shared walk): each receiver's class and boundary codes in the
    batch, with tiles never, always or where worth it, equal those of the receiver alone."""
    scene, occ = _occluders(seed=103)
    dense, nd = _floor(160, 0.03, seed=1)
    dense[:, :2] += [0.45, 0.1]  # the mesh's penumbra
    wide, nw = _floor(60, 1.0, seed=2)
    p, n = np.concatenate([dense, wide]), np.concatenate([nd, nw])
    monkeypatch.setenv("JAXSHADOW_SIL_TILES", tiles if tiles != "auto" else "")
    batch = vis.polygon_codes(p, n, QUAD, occ)
    monkeypatch.setenv("JAXSHADOW_SIL_TILES", "0")
    pen = 0
    for i in range(len(p)):
        alone = vis.polygon_codes(p[i:i + 1], n[i:i + 1], QUAD, occ)
        assert batch.classes[i] == alone.classes[0], i
        np.testing.assert_array_equal(batch.runs[batch.offsets[i]:batch.offsets[i + 1]], alone.runs, err_msg=str(i))
        pen += int(alone.classes[0] == vis.PENUMBRA)
    assert pen >= 40 and np.sum(batch.classes[:160] == vis.PENUMBRA) >= 20
