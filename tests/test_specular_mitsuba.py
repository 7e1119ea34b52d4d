"""js.specular and js.shade against Mitsuba 3 (its emitter sampling and ray tests; the Phong
lobe evaluated on Mitsuba's samples, MIS with lobe sampling): within 4 standard errors."""

import numpy as np
import pytest

import jaxshadow as js

pytest.importorskip("mitsuba")
from jaxshadow import mitsuba as jm  # noqa: E402

pytestmark = pytest.mark.mitsuba


def _check(ours, ref, err):
    ours, ref, err = (np.asarray(x, dtype=np.float64) for x in (ours, ref, err))
    tol = 4.0 * err + 2e-5 * np.abs(ours) + 1e-12
    z = np.abs(ours - ref) / tol
    assert np.all(z <= 1.0), f"worst |diff|/(4 sigma) = {z.max():.2f}"
    significant = ref > 1e-3 * ref.max()
    assert np.median(err[significant] / ref[significant]) < 0.02  # the comparison means something


def _floor_points(n, rng, half=1.3):
    p = np.concatenate([rng.uniform(-half, half, (n, 2)), np.zeros((n, 1))], axis=1)
    nrm = np.tile([0.0, 0.0, 1.0], (n, 1))
    return p, nrm


def open_scene():
    quad = js.PolygonLight([[-0.6, -0.4, 1.8], [-0.6, 0.4, 1.8], [0.6, 0.4, 1.8], [0.6, -0.4, 1.8]], [3.0, 2.5, 2.0])
    # a tilted pentagon, counter-clockwise seen from below
    ang = np.linspace(0, 2 * np.pi, 6)[:-1]
    pent = np.stack([1.2 + 0.3 * np.cos(ang), 0.5 + 0.3 * np.sin(ang), 1.2 + 0.15 * np.cos(ang)], axis=1)[::-1]
    return js.Scene([quad, js.PolygonLight(pent, 2.0), js.PointLight([-1.0, 1.0, 1.0], 0.5)])


def shadowed_scene():
    from jaxshadow.cli import builtin_scene_path

    return js.load_scene(builtin_scene_path("room"))


@pytest.mark.parametrize("make", [open_scene, shadowed_scene])
@pytest.mark.parametrize("exponent", [8.0, 60.0])
def test_specular_agrees_with_mitsuba(make, exponent):
    scene = make()
    rng = np.random.default_rng(7)
    p, nrm = _floor_points(16, rng)
    eye = np.array([0.4, -2.5, 1.6])
    ours = js.specular(scene, p, nrm, eye, exponent)
    ref, err = jm.reference_specular(scene, p, nrm, eye, exponent, spp=50000, seed=3)
    _check(ours, ref, err)


def test_shade_agrees_with_mitsuba():
    scene = shadowed_scene()
    mat = js.Material(ka=0.2, kd=[0.6, 0.5, 0.4], ks=0.3, exponent=25.0)
    rng = np.random.default_rng(11)
    p, nrm = _floor_points(16, rng)
    eye = np.array([-0.5, -2.0, 2.0])
    ours = js.shade(scene, mat, p, nrm, eye)
    ref, err = jm.reference_shade(scene, mat, p, nrm, eye, spp=50000, seed=5)
    _check(ours, ref, err)
