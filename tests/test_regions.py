"""A material per region (`inverse.fit_material_regions`): targets on a floor and on a wall of
different materials, each region's material recovered from its own targets."""

import numpy as np
import pytest

import inverse
import jaxshadow as js


def _targets():
    scene = js.Scene([js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], [6.0, 5.0, 4.0])], ambient=0.2)
    rng = np.random.default_rng(0)
    floor_p = np.c_[rng.uniform(-0.5, 1.5, (12, 2)), np.zeros(12)]
    wall_p = np.c_[np.full(10, -0.5), rng.uniform(-0.5, 1.5, 10), rng.uniform(0.1, 1.5, 10)]
    p = np.concatenate([floor_p, wall_p])
    n = np.concatenate([np.tile([0.0, 0, 1], (12, 1)), np.tile([1.0, 0, 0], (10, 1))])
    eye = np.array([2.0, -1.0, 1.5])
    mats = {"floor": js.Material(ka=0.1, kd=[0.6, 0.5, 0.4], ks=0.0), "wall": js.Material(ka=0.3, kd=[0.2, 0.3, 0.5], ks=0.0)}
    labels = np.array(["floor"] * 12 + ["wall"] * 10)
    colours = np.concatenate([np.asarray(js.shade(scene, mats[k], p[labels == k], n[labels == k], eye)) for k in ("floor", "wall")])
    return scene, inverse.PaintedTargets(p, n, colours, eye), labels, mats


@pytest.mark.slow
def test_each_region_gets_its_material():
    scene, targets, labels, mats = _targets()
    fit = inverse.fit_material_regions(scene, targets, labels, exponent=1.0, bounds=((0, 0, 0), (1, 1, 0)), warn=False)
    assert list(fit.materials) == ["floor", "wall"]
    for k in ("floor", "wall"):
        for f in ("ka", "kd"):
            np.testing.assert_allclose(np.asarray(getattr(fit.materials[k], f)), np.asarray(getattr(mats[k], f)) * np.ones(3), atol=1e-7)
    assert np.abs(fit.residual).max() < 1e-7 and "region 'wall' (10 targets)" in fit.report
    per_point = fit.material_at(labels)
    assert per_point.receivers == 22
    np.testing.assert_allclose(np.asarray(per_point.kd)[15], [0.2, 0.3, 0.5], atol=1e-7)


def test_region_errors():
    scene = js.Scene([js.PointLight([0, 0, 2], 1.0)])
    p = np.c_[np.arange(22.0), np.zeros((22, 2))]
    targets = inverse.PaintedTargets(p, np.tile([0.0, 0, 1], (22, 1)), np.ones((22, 3)), [0, -1.0, 1])
    labels = np.array(["floor"] * 12 + ["wall"] * 10)
    with pytest.raises(ValueError, match=r"one label per target"):
        inverse.fit_material_regions(scene, targets, labels[:5])
    with pytest.raises(ValueError, match="region 'x' has 2 targets"):
        inverse.fit_material_regions(scene, targets, np.r_[labels[:20], ["x", "x"]])
