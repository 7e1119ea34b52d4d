"""The global placement's pair moves (`inverse._nnls_screen.pair_rss`): two lights re-chosen
together over every pair of their candidates with the others held, against brute-force
non-negative least squares, and on a placement where moving either light alone makes the fit
worse (two lights standing in for each other's shading)."""

import itertools

import numpy as np
import pytest
from scipy.optimize import nnls

import inverse
import jaxshadow as js
from benchmarks.inverse_random_scenes import light_errors, random_case
from inverse._nnls_screen import nnls_rss, pair_rss


def _brute(fixed, ca, cb, y, fit_power):
    best = (np.inf, -1, -1)
    for s, t in itertools.product(range(ca.shape[0]), range(cb.shape[0])):
        if fit_power:
            f = nnls(np.c_[fixed, ca[s], cb[t]], y)[1] ** 2
        else:
            f = float(np.sum((y - fixed.sum(axis=1) - ca[s] - cb[t]) ** 2))
        if f < best[0]:
            best = (f, s, t)
    return best


@pytest.mark.parametrize("fit_power", [True, False])
def test_pair_rss_is_the_best_pair(fit_power):
    """Without held lights the pair screen is exact: its least residual and its pair are the
    brute-force non-negative least squares over all pairs (candidates that need a zero power,
    anti-correlated columns and a zero column among them)."""
    rng = np.random.default_rng(3)
    M = 30
    u, v = rng.uniform(0.0, 1.0, (2, M))
    y = 1.7 * u + 0.6 * v + 0.05 * rng.normal(size=M)
    ca = np.concatenate([rng.uniform(0.0, 1.0, (7, M)), [u + 0.1 * rng.normal(size=M)], -np.abs(rng.normal(size=(1, M)))])
    cb = np.concatenate([rng.uniform(0.0, 1.0, (6, M)), [v + 0.1 * rng.normal(size=M)], np.zeros((1, M))])
    none = np.zeros((M, 0))
    f, s, t = pair_rss(none, ca, cb, y, fit_power, block=4)  # several blocks
    want = _brute(none, ca, cb, y, fit_power)
    assert (s, t) == want[1:]
    np.testing.assert_allclose(f, want[0], rtol=1e-9, atol=1e-12)


def test_pair_rss_with_held_lights():
    """With held lights whose least-squares powers are positive the pair screen's residual is the
    brute-force NNLS with them."""
    rng = np.random.default_rng(4)
    M = 40
    fixed = rng.uniform(0.0, 1.0, (M, 2))
    u, v = rng.uniform(0.0, 1.0, (2, M))
    y = fixed @ [0.8, 1.1] + u + 2.0 * v
    ca = np.concatenate([rng.uniform(0.0, 1.0, (5, M)), [u]])
    cb = np.concatenate([[v], rng.uniform(0.0, 1.0, (5, M))])
    f, s, t = pair_rss(fixed, ca, cb, y, True)
    assert (s, t) == (5, 0)
    assert f < 1e-12 * float(y @ y)  # exact up to the rounding of |y|^2 - explained
    for fp in (True, False):
        assert pair_rss(fixed, ca, cb, y, fp)[0] <= _brute(fixed, ca, cb, y, fp)[0] + 1e-9


def test_pair_move_leaves_a_placement_single_moves_cannot():
    """Two lights standing in for each other: `w_a + w_b` explains the targets but for a small
    part, and moving either light alone to its true column explains them worse (the coordinate
    descent of the screen stops there); the pair screen finds the true pair."""
    e = np.eye(6)
    u, v = e[0] + 0.2 * e[4], e[1] + 0.3 * e[5]
    y = u + 2.0 * v
    w_a = u + e[2]
    w_b = 2.0 * v - e[2] + 0.1 * e[3]
    ca, cb = np.stack([w_a, u]), np.stack([w_b, v])
    none = np.zeros((6, 0))
    here = nnls_rss(w_a[:, None], cb[:1], y, True)[0]
    assert nnls_rss(w_a[:, None], cb, y, True)[1] > here  # light b moved alone: worse
    assert nnls_rss(w_b[:, None], ca, y, True)[1] > here  # light a moved alone: worse
    f, s, t = pair_rss(none, ca, cb, y, True)
    assert (s, t) == (1, 1) and f < 1e-12 * float(y @ y)


@pytest.mark.slow
def test_three_lights_from_no_start_where_two_stood_in_for_each_other():
    """Scene seed 1 of the benchmark (quad + point + segment, a box occluder, 60 floor targets),
    lights given by kind only: without pair moves the placement keeps the quad and the segment in
    each other's place and the fit ends 18 % of the scene off; with them every light is found."""
    case = random_case(1, ("polygon", "point", "segment"))
    col = js.shade(case.true, case.material, case.points, case.normals, case.eye)
    targets = inverse.PaintedTargets(case.points, case.normals, col, case.eye)
    size = inverse.scene_size(case.true, targets)
    empty = js.Scene([], occluders=case.true.occluders, ambient=case.true.ambient)
    fit = inverse.fit_lights(empty, targets, case.material, kinds=list(case.kinds))
    for got, want in zip(fit.lights, case.true.lights, strict=True):
        pos, power = light_errors(got, want)
        assert pos < 0.005 * size and power < 0.01, (type(want).__name__, pos / size, power)
    assert fit.report.quality.trusted
