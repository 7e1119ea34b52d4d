"""The global placement's polygon orientation variants (`inverse._global_placement.POLYGON_TILTS`):
a quad light whose normal is tilted far from straight down (scene seed 8 of
`benchmarks.inverse_random_scenes` with a quad, a point and a segment light: 71 degrees) has no
candidate orientation near its own at its own centre by default; with the tilted rings it has."""

import jax.numpy as jnp
import numpy as np

import inverse
import jaxshadow as js
from benchmarks.inverse_random_scenes import random_case
from inverse import _global_placement
from inverse._global_placement import region_of, rows_at, template_light
from inverse._parametrisation import LightParametrisation


def _normal(v):
    n = np.sum(np.cross(v, np.roll(v, -1, axis=0)), axis=0)
    return n / np.linalg.norm(n)


def _closest_angle(monkeypatch, tilts):
    monkeypatch.setattr(_global_placement, "POLYGON_TILTS", tilts)
    case = random_case(8, ("polygon", "point", "segment"))
    targets = inverse.PaintedTargets(case.points, case.normals, np.ones((len(case.points), 3)), case.eye)
    region = region_of(case.true, case.points, case.normals)
    truth = np.asarray(case.true.lights[0].vertices, np.float64)
    template = template_light("polygon", region)
    param = LightParametrisation(template, 0, ("position", "orientation", "size"), None,
                                 inverse.scene_size(js.Scene([template], occluders=case.true.occluders), targets),
                                 "sigmoid")
    rows = rows_at(param, region, truth.mean(axis=0)[None])
    normals = np.stack([_normal(np.asarray(param.build(jnp.asarray(r)).vertices)) for r in rows])
    return float(np.degrees(np.min(np.arccos(np.clip(normals @ _normal(truth), -1.0, 1.0))))), normals, region


def test_default_variants_miss_a_steeply_tilted_quad(monkeypatch):
    angle, _, _ = _closest_angle(monkeypatch, ())
    assert angle > 40.0


def test_tilted_rings_hold_a_steeply_tilted_quad(monkeypatch):
    angle, normals, region = _closest_angle(monkeypatch, ((0.6, 4), (1.15, 6)))
    assert angle < 30.0
    assert len(normals) == 3 + 10
    assert np.all(normals @ region.axes[2] < 0)  # every variant lights the side the targets are on
