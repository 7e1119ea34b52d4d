"""The global placement's orientation screen (`inverse._orientation_screen`): a polygon's column
at any normal approximated from one computed at a down-facing normal, and the screen's picks for
a quad facing sideways (scene seeds 6 and 9 of `benchmarks.inverse_random_scenes` with a quad, a
point and a segment light: normals 108 and 110 degrees from straight down, which the default
candidate orientations miss and the fit from no start got 46 % and 66 % of the scene wrong)."""

import jax.numpy as jnp
import numpy as np
import pytest

import inverse
import jaxshadow as js
from benchmarks.inverse_random_scenes import random_case
from inverse._global_placement import region_of, rows_at, template_light
from inverse._orientation_screen import (
    oriented_columns,
    oriented_rows,
    rotation_vector,
    row_normals,
)
from inverse._parametrisation import LightParametrisation, rotation_matrix

KINDS = ("polygon", "point", "segment")


def _normal(v):
    n = np.sum(np.cross(v, np.roll(v, -1, axis=0)), axis=0)
    return n / np.linalg.norm(n)


def _column(case, light):
    """The light's shading at the case's targets with nothing else lit, `(3N,)` (the forward model)."""
    s = js.Scene([light], occluders=case.true.occluders, ambient=[0.0, 0.0, 0.0])
    return np.asarray(js.shade(s, case.material, case.points, case.normals, case.eye), np.float64).reshape(-1)


def _cos(a, b):
    return float(a @ b / np.linalg.norm(a) / np.linalg.norm(b))


@pytest.mark.parametrize("seed", [6, 9])
def test_turned_column_matches_the_forward_model(seed):
    """The true quad turned to face straight down about its centre: its column, turned back by
    `oriented_columns` to the true normal, matches the forward model's column at the truth
    (direction within cos 0.999, scale within 3 %); the down-facing column itself does not."""
    case = random_case(seed, KINDS)
    v = np.asarray(case.true.lights[0].vertices, np.float64)
    c, n = v.mean(axis=0), _normal(v)
    down = np.array([0.0, 0.0, -1.0])
    R = np.asarray(rotation_matrix(jnp.asarray(rotation_vector(n, down))))
    a_down = _column(case, js.PolygonLight(c + (v - c) @ R.T, [1.0, 1.0, 1.0]))
    a_true = _column(case, js.PolygonLight(v, [1.0, 1.0, 1.0]))
    got = oriented_columns(a_down[None], c[None], down[None], np.asarray(case.points, np.float64), n[None])[0, 0]
    assert _cos(got, a_true) > 0.999
    assert abs(np.linalg.norm(got) / np.linalg.norm(a_true) - 1.0) < 0.03
    assert _cos(a_down, a_true) < 0.5


def test_screen_picks_the_sideways_quads_normal_with_the_others_held():
    """Seed 9's quad (110 degrees from straight down): down-facing candidates on a 5 x 5 x 2 grid
    over the feasible region and at the truth's centre, the point and segment light's columns
    held: the screen's best pick lies at the truth's centre with a normal within 20 degrees (the screened normals are about 20 degrees apart)."""
    case = random_case(9, KINDS)
    col = _column(case, case.true.lights[1]) + _column(case, case.true.lights[2]) + _column(
        case, case.true.lights[0])
    targets = inverse.PaintedTargets(case.points, case.normals, col.reshape(-1, 3), case.eye)
    region = region_of(case.true, case.points, case.normals)
    template = template_light("polygon", region)
    param = LightParametrisation(template, 0, ("position", "orientation"), None,
                                 inverse.scene_size(js.Scene([template], occluders=case.true.occluders), targets),
                                 "none")
    truth = np.asarray(case.true.lights[0].vertices, np.float64)
    g = np.stack(np.meshgrid(np.linspace(0.1, 0.9, 5), np.linspace(0.1, 0.9, 5), [0.3, 0.7], indexing="ij"),
                 axis=-1).reshape(-1, 3)
    centres = np.concatenate([truth.mean(axis=0)[None], region.world(region.lo + (region.hi - region.lo) * g)])
    rows = rows_at(param, region, centres)
    rows = rows[np.abs(row_normals(param, rows) @ region.axes[2] + 1.0) < 1e-9]  # the down-facing ones
    size = np.exp(np.mean(np.log(np.linalg.norm(truth - truth.mean(axis=0), axis=1))))
    scale = size / np.exp(np.mean(np.log(np.linalg.norm(np.asarray(template.vertices) - np.asarray(
        template.vertices).mean(axis=0), axis=1))))

    def light(r):  # the template scaled to the truth's size: the screen keeps a candidate's size
        lt = param.build(jnp.asarray(r))
        v = np.asarray(lt.vertices, np.float64)
        return js.PolygonLight(v.mean(axis=0) + scale * (v - v.mean(axis=0)), [1.0, 1.0, 1.0])

    cols = np.stack([_column(case, light(r)) for r in rows])
    held = np.stack([_column(case, case.true.lights[1]), _column(case, case.true.lights[2])], axis=1)

    def centre_of(r):
        return np.stack([np.asarray(param.build(jnp.asarray(x)).vertices, np.float64).mean(axis=0) for x in r])

    picked = oriented_rows(param, rows, cols, centre_of, held, col, True, np.asarray(case.points, np.float64),
                           region.axes[2], 0.05 * region.extent)
    assert picked.shape[0] > 0
    best = picked[0]
    assert np.linalg.norm(centre_of(best[None])[0] - truth.mean(axis=0)) < 1e-9
    angle = np.degrees(np.arccos(np.clip(row_normals(param, best[None])[0] @ _normal(truth), -1.0, 1.0)))
    assert angle < 20.0, angle


@pytest.mark.slow
def test_sideways_quad_scene_explained_from_no_start(monkeypatch):
    """Seed 9 with a quad (110 degrees from straight down), a point and a segment light, from no
    start as `benchmarks.fit_global` calls it, with `ORIENTATION_SCREEN` on: the fit explains the targets to round-off (without
    the orientation screen: a loss 3e-8, the quad 66 % of the scene off, flagged "undetermined"
    and "outliers"). The quad lights only 7 of the 60 targets (0.6 % of their colour), too few to
    pin down its position, orientation, size and power: the report says so ("undetermined")."""
    from benchmarks.fit_global import NOISE_FREE_SIGMA
    from inverse import _global_placement

    monkeypatch.setattr(_global_placement, "ORIENTATION_SCREEN", True)
    case = random_case(9, KINDS)
    col = np.asarray(js.shade(case.true, case.material, case.points, case.normals, case.eye), np.float64)
    lit = _column(case, case.true.lights[0]).reshape(-1, 3).sum(axis=1) > 0
    assert lit.sum() == 7
    targets = inverse.PaintedTargets(case.points, case.normals, col, case.eye)
    empty = js.Scene([], occluders=case.true.occluders, ambient=case.true.ambient)
    fit = inverse.fit_lights(empty, targets, case.material, kinds=list(case.kinds), warn=False,
                             noise=NOISE_FREE_SIGMA * float(np.sqrt(np.mean(col ** 2))))
    assert fit.report.loss < 1e-20 * 0.5 * float(np.sum(col ** 2))
    assert "undetermined" in fit.report.quality.flags
