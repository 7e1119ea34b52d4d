"""`jaxshadow._cache.affected`: which receivers an edited occluder can shadow.

Independent reference: a linear program (scipy's HiGHS) that looks for a point of the box in the
receiver's illumination region (the convex hull of the receiver and the light, above the
receiver's horizon). `affected` may flag more receivers than that, never fewer: a receiver it
misses would keep a stale value in `ShadowCache.update` and in an illumination mesh's update.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linprog

import jaxshadow as js
from jaxshadow._shadows import cache as _cache

QUAD = np.array([[-0.3, -0.3, 2.0], [-0.3, 0.3, 2.0], [0.3, 0.3, 2.0], [0.3, -0.3, 2.0]])


def meets(p, n, verts, lo, hi) -> bool:
    """A point x = w_0 p + sum w_i v_i (w >= 0, sum w = 1) with lo <= x <= hi and n . (x - p) >= 0."""
    pts = np.vstack([p[None], verts])  # (V + 1, 3): x = pts.T @ w
    a_ub = np.vstack([pts.T, -pts.T, -((pts - p) @ n)[None]])
    b_ub = np.concatenate([hi, -lo, [0.0]])
    res = linprog(np.zeros(len(pts)), A_ub=a_ub, b_ub=b_ub, A_eq=np.ones((1, len(pts))), b_eq=[1.0],
                  bounds=[(0, None)] * len(pts), method="highs")
    return res.status == 0


def receivers(rng, lo, hi, verts, k):
    """Random floor and off-floor receivers, and receivers a hair on either side of the
    separating planes the filter uses (where a wrong sign or margin would show)."""
    p = np.c_[rng.uniform(-3, 3, (k, 2)), rng.choice([0.0, 0.3], k) * rng.uniform(0, 1, k)]
    n = np.c_[rng.normal(0, 0.4, (k, 2)), np.ones(k)]
    s_all = float(max(np.abs(p).max(), np.abs(np.r_[lo, hi]).max(), np.abs(verts).max())) + 1.0
    planes = _cache.separating_planes(verts, lo, hi, s_all)
    extra = []
    for pl in planes:
        # Points of the plane near the box (the box's corners projected), nudged off it.
        c = _cache._box_corners(lo, hi)
        x = c - ((c @ pl[:3]) - pl[3])[:, None] * pl[:3]
        for t in (-3e-6, -1e-6, 0.0, 1e-6):
            extra.append(x + t * s_all * pl[:3][None])
    if extra:
        q = np.concatenate(extra)
        p = np.vstack([p, q])
        n = np.vstack([n, np.tile([0.0, 0.0, 1.0], (q.shape[0], 1))])
    return p, n / np.linalg.norm(n, axis=1, keepdims=True)


@pytest.mark.parametrize("kind", ["polygon", "point", "segment"])
def test_affected_receivers_include_every_receiver_the_box_can_shadow(kind):
    rng = np.random.default_rng(3)
    lights = {"polygon": (js.PolygonLight(QUAD, 1.0), QUAD),
              "point": (js.PointLight([0.1, -0.2, 1.9], 1.0), np.array([[0.1, -0.2, 1.9]])),
              "segment": (js.LinearLight([-0.4, 0.0, 2.0], [0.4, 0.1, 2.0], 1.0), np.array([[-0.4, 0.0, 2.0],
                                                                                           [0.4, 0.1, 2.0]]))}
    light, verts = lights[kind]
    boxes = [(np.array([0.2, -0.5, 0.0]), np.array([0.6, -0.1, 0.9])),   # standing on the floor
             (np.array([-0.2, -0.1, 1.2]), np.array([0.1, 0.2, 1.5])),    # floating under the light
             (np.array([-0.2, -0.1, 1.5]), np.array([0.1, 0.2, 1.99995])),  # closer than 1e-4 scale: no planes
             (np.array([-0.2, -0.1, 1.5]), np.array([0.1, 0.2, 2.0]))]    # touching the light's plane
    n_flagged = n_true = 0
    for lo, hi in boxes:
        p, n = receivers(rng, lo, hi, verts, 150)
        got = _cache.affected(light, p, n, lo, hi)
        want = np.array([meets(p[i], n[i], verts, lo, hi) for i in range(p.shape[0])])
        missed = np.nonzero(want & ~got)[0]
        assert missed.size == 0, (kind, lo, hi, p[missed[:3]])
        n_flagged += int(got.sum())
        n_true += int(want.sum())
    # Not a filter that flags everything: the flagged receivers are mostly truly affected ones.
    assert n_true > 20 and n_flagged <= 1.5 * n_true + 20, (n_flagged, n_true)


def test_separating_planes_separate():
    lo, hi = np.array([0.2, -0.5, 0.0]), np.array([0.6, -0.1, 0.9])
    planes = _cache.separating_planes(QUAD, lo, hi, 5.0)
    assert planes.shape[0] >= 5
    c = _cache._box_corners(lo, hi)
    assert np.all(QUAD @ planes[:, :3].T <= planes[:, 3] + 1e-12)
    assert np.all(c @ planes[:, :3].T >= planes[:, 3] - 1e-12)
    # Nothing separates a box that reaches the light.
    assert _cache.separating_planes(QUAD, np.array([-0.1, -0.1, 1.0]), np.array([0.1, 0.1, 2.5]), 5.0).shape == (0, 4)


def test_cache_with_a_segment_light_and_occluders():
    """A scene with a segment light (whose candidate faces the device kernel clips) beside a
    polygon and a point light: the cache builds (it raised `TypeError` on the segment light's
    missing faces) and its values, before and after moving the occluder, are
    `jaxshadow.irradiance`'s of the same scene."""
    tri = np.array([[-0.2, -0.1, 1.0], [0.3, -0.1, 1.0], [0.0, 0.3, 1.0]])
    lights = [js.LinearLight([-0.5, 0.0, 2.0], [0.5, 0.1, 2.0], power=2.0), js.PolygonLight(QUAD, 1.0),
              js.PointLight([0.1, 0.0, 2.0], 1.0)]
    rng = np.random.default_rng(4)
    p = np.c_[rng.uniform(-1, 1, (60, 2)), np.zeros(60)]
    n = np.tile([0.0, 0.0, 1.0], (60, 1))
    scene = js.Scene(lights, occluders=[tri])
    cache = js.ShadowCache(scene, p, n)
    want = np.asarray(js.irradiance(scene, p, n))
    assert want[:, 0].min() < 0.9 * want[:, 0].max()  # some receivers are shadowed
    np.testing.assert_allclose(cache.irradiance, want, rtol=1e-12, atol=1e-15)
    moved = js.Scene(lights, occluders=[tri + [0.2, 0.1, 0.0]])
    np.testing.assert_allclose(cache.update(moved).irradiance, np.asarray(js.irradiance(moved, p, n)), rtol=1e-12,
                               atol=1e-15)
