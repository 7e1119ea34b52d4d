"""Mitsuba 3 as ground truth: jaxshadow's closed forms against Mitsuba's Monte Carlo estimators.

Agreement criterion: |ours - Mitsuba| <= 4 standard errors (+ a float32 floor of 2e-5 |value|
for estimates that are almost deterministic, e.g. one point light) at every point and channel.
Seeds are fixed, so the tests are deterministic. Segment lights: Mitsuba has none; the
stand-ins of `jaxshadow.mitsuba` carry a stated bias, added to the tolerance.
"""

import sys

import numpy as np
import pytest

import jaxshadow as js
from benchmarks.scenes import rotation as _rot
from benchmarks.scenes import unit as _unit

pytest.importorskip("mitsuba")
from jaxshadow import mitsuba as jm  # noqa: E402

pytestmark = pytest.mark.mitsuba

FLOOR = 2e-5


def _assert_agree(ours, ref, err, extra=0.0, what=""):
    ours, ref, err = (np.asarray(x, dtype=np.float64) for x in (ours, ref, err))
    tol = 4.0 * err + FLOOR * np.abs(ours) + extra * np.abs(ours) + 1e-12
    bad = np.abs(ours - ref) > tol
    assert not bad.any(), (
        f"{what}: {bad.sum()} disagreements; "
        f"worst |diff|/tol = {np.max(np.abs(ours - ref) / tol):.2f}\n"
        f"ours={ours[bad]}\nref={ref[bad]}\nerr={err[bad]}"
    )
    return float(np.max(np.abs(ours - ref) / np.maximum(err, 1e-30)))






def _facing(verts, target):
    """Reorder a polygon so its right-hand-rule normal points toward `target`."""
    n = np.sum(np.cross(verts, np.roll(verts, -1, axis=0)), axis=0)
    return verts if np.dot(n, target - verts.mean(axis=0)) > 0 else verts[::-1].copy()


def _plane_cuts(p, n, verts):
    s = (verts - p) @ n
    return bool(s.max() > 0 and s.min() < 0)


def _receivers(seed, count, lo, hi):
    rng = np.random.default_rng(seed)
    p = rng.uniform(lo, hi, (count, 3))
    n = rng.normal(size=(count, 3))
    n[:, 2] = np.abs(n[:, 2]) + 0.2
    return p, _unit(n)


QUAD = np.array([[0.0, 0.0, 2.0], [0.0, 1.0, 2.0], [1.0, 1.0, 2.0], [1.0, 0.0, 2.0]])  # faces -z


def _scene_quad():
    lights = [
        js.PolygonLight(QUAD, [2.0, 1.0, 0.5]),
        js.PointLight([1.5, -0.5, 1.2], [3.0, 2.0, 1.0]),
        js.DirectionalLight([0.3, 0.2, -1.0], [0.5, 0.6, 0.7]),
    ]
    p, n = _receivers(1, 16, [-0.5, -0.5, -0.3], [1.5, 1.5, 1.2])
    # Tilted receivers whose tangent plane cuts the quad.
    p_cut = np.array([[0.5, 0.5, 1.0], [0.2, 0.8, 1.5], [1.2, 0.5, 1.0], [0.5, -0.3, 1.4]])
    n_cut = _unit([[1.0, 0.0, 0.3], [0.3, -1.0, 0.5], [-1.0, 0.2, 0.6], [0.0, 1.0, 0.1]])
    return js.Scene(lights), np.concatenate([p, p_cut]), np.concatenate([n, n_cut])


def _scene_tilted():
    ang = 2 * np.pi * np.arange(5) / 5
    penta = np.stack([0.5 * np.cos(ang), 0.5 * np.sin(ang), np.zeros(5)], axis=1)
    penta = penta @ _rot([1.0, 0.3, 0.0], 0.6).T + np.array([0.0, 0.0, 2.0])
    tri = np.array([[0.0, 0.0, 0.0], [0.6, 0.0, 0.0], [0.1, 0.5, 0.0]])
    tri = tri @ _rot([0.0, 1.0, 0.0], 1.2).T + np.array([-1.5, 0.2, 1.0])
    centre = np.array([0.0, 0.0, 0.5])
    lights = [
        js.PolygonLight(_facing(penta, centre), [1.0, 1.5, 2.0]),
        js.PolygonLight(_facing(tri, centre), [4.0, 3.0, 1.0]),
        js.PointLight([1.0, 1.0, 1.5], [1.0, 1.0, 2.0]),
    ]
    p, n = _receivers(2, 16, [-1.0, -1.0, -0.2], [1.0, 1.0, 1.2])
    p_cut = np.array([[0.0, 0.0, 1.4], [0.3, -0.2, 1.6], [-1.0, 0.3, 0.8], [-0.4, 0.0, 1.2]])
    n_cut = _unit([[1.0, 0.2, 0.2], [-0.5, 1.0, 0.3], [0.3, 0.2, 1.0], [-1.0, 0.0, 0.2]])
    return js.Scene(lights), np.concatenate([p, p_cut]), np.concatenate([n, n_cut])


@pytest.mark.parametrize("make", [_scene_quad, _scene_tilted], ids=["quad", "tilted"])
def test_irradiance_agrees_with_mitsuba(make):
    scene, p, n = make()
    polys = [
        np.asarray(light.vertices) for light in scene.lights if isinstance(light, js.PolygonLight)
    ]
    cuts = sum(any(_plane_cuts(p[i], n[i], v) for v in polys) for i in range(len(p)))
    assert cuts >= 4
    ours = np.asarray(js.irradiance(scene, p, n))
    ref, err = jm.reference_irradiance(scene, p, n, spp=60_000, seed=7)
    lit = ours > 0.05 * ours.max()
    assert np.median(err[lit] / ours[lit]) < 0.01
    _assert_agree(ours, ref, err, what=make.__name__)


def test_area_emitter_is_one_sided():
    scene = js.Scene([js.PolygonLight(QUAD, 1.0)])
    p = np.array([[0.5, 0.5, 1.0], [0.5, 0.5, 3.0]])
    n = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
    ref, err = jm.reference_irradiance(scene, p, n, spp=20_000, seed=1)
    ours = np.asarray(js.irradiance(scene, p, n))
    assert ours[1].max() == 0.0 and ref[1].max() == 0.0  # behind the emitter
    _assert_agree(ours, ref, err, what="one-sided")


def _chain_irradiance(p, n, a, b, m):
    """Exact expectation of the isotropic stand-in: M point lights of intensity Phi l/(4 pi M)."""
    x = a + (np.arange(m)[:, None] + 0.5) / m * (b - a)
    w = x[None] - p[:, None]
    r2 = np.sum(w * w, axis=-1)
    cos = np.maximum(np.sum(w * n[:, None], axis=-1), 0.0) / np.sqrt(r2)
    return np.linalg.norm(b - a) / (4 * np.pi * m) * np.sum(cos / r2, axis=1)


SEG_A = np.array([-0.5, 0.2, 1.5])
SEG_B = np.array([0.7, 0.4, 1.8])


def _segment_receivers():
    p, n = _receivers(3, 14, [-0.6, -0.4, 0.0], [0.8, 0.8, 0.8])
    p_cut = np.array([[0.1, 0.3, 1.3], [0.0, 0.6, 1.6]])  # tangent planes cut the segment
    n_cut = _unit([[1.0, 0.0, 0.2], [0.0, -1.0, 0.1]])
    return np.concatenate([p, p_cut]), np.concatenate([n, n_cut])


def test_segment_point_chain_stand_in():
    p, n = _segment_receivers()
    phi = np.array([1.0, 2.0, 3.0])
    scene = js.Scene([js.LinearLight(SEG_A, SEG_B, phi, profile="isotropic")])
    ours = np.asarray(js.irradiance(scene, p, n))
    # The midpoint-rule bias of the 64-point chain, computed exactly (deterministic).
    chain = _chain_irradiance(p, n, SEG_A, SEG_B, 64)[:, None] * phi
    lit = ours > 0
    assert lit.sum() >= 30 and np.all(chain[~lit] < 1e-3 * ours.max())
    assert np.max(np.abs(chain - ours)[lit] / ours[lit]) < 1e-3
    ref, err = jm.reference_irradiance(scene, p, n, spp=40_000, seed=3, segment_points=64)
    _assert_agree(chain, ref, err, what="chain vs its expectation")
    _assert_agree(ours, ref, err, extra=1e-3, what="chain vs closed form")


def test_segment_cylinder_stand_in():
    p, n = _segment_receivers()
    phi = np.array([1.0, 2.0, 3.0])
    scene = js.Scene([js.LinearLight(SEG_A, SEG_B, phi, profile="cosine", exponent=1)])
    ours = np.asarray(js.irradiance(scene, p, n))
    ref, err = jm.reference_irradiance(scene, p, n, spp=100_000, seed=4, segment_radius=1e-4)
    # Bias of the r = 1e-4 l cylinder, O(r/d): 1.4e-4 at most here (`_measure`).
    _assert_agree(ours, ref, err, extra=1e-3, what="cylinder vs closed form")


def test_segment_stand_in_rejects_higher_cosine():
    scene = js.Scene([js.LinearLight(SEG_A, SEG_B, 1.0, profile="cosine", exponent=2)])
    with pytest.raises(NotImplementedError, match="exponent 2"):
        jm.to_mitsuba(scene)


def test_occluder_blocks_from_both_sides():
    big = np.array([[-2.0, -2.0, 1.0], [3.0, -2.0, 1.0], [3.0, 3.0, 1.0], [-2.0, 3.0, 1.0]])
    lights = [
        js.PolygonLight(QUAD, 1.0),
        js.PointLight([0.5, 0.5, 1.8], 1.0),
        js.DirectionalLight([0.1, 0.0, -1.0], 1.0),
    ]
    p = np.array([[0.5, 0.5, 0.0], [0.0, 0.3, 0.5], [9.0, 0.5, 0.0]])
    n = _unit([[0.0, 0.0, 1.0], [0.3, 0.0, 1.0], [-1.0, 0.0, 1.0]])
    for occ in (big, big[::-1].copy()):
        ref, err = jm.reference_irradiance(js.Scene(lights, occluders=[occ]), p, n, spp=20_000)
        assert np.all(ref[:2] == 0.0) and np.all(err[:2] == 0.0)
        eye = np.array([0.5, -0.5, 0.5])
        for occlude in (False, True):
            spec, _ = jm.reference_specular(
                js.Scene(lights, occluders=[occ]),
                p[:2],
                n[:2],
                eye,
                5.0,
                spp=5_000,
                lights_occlude=occlude,
            )
            assert np.all(spec == 0.0)
        # Outside the occluder's shadow: the unoccluded value.
        ours = np.asarray(js.irradiance(js.Scene(lights), p[2:], n[2:]))
        _assert_agree(ours, ref[2:], err[2:], what="beside the occluder")


def test_lights_do_not_occlude_unless_asked():
    scene = js.Scene([js.PolygonLight(QUAD, 1.0), js.DirectionalLight([0.0, 0.0, -1.0], 1.0)])
    p = np.array([[0.5, 0.5, 0.0]])
    n = np.array([[0.0, 0.0, 1.0]])
    ours = np.asarray(js.irradiance(scene, p, n))
    ref, err = jm.reference_irradiance(scene, p, n, spp=20_000, seed=5)
    _assert_agree(ours, ref, err, what="lights transparent")
    ref, err = jm.reference_irradiance(scene, p, n, spp=20_000, seed=5, lights_occlude=True)
    only_quad = np.asarray(js.irradiance(js.Scene(scene.lights[:1]), p, n))
    _assert_agree(only_quad, ref, err, what="Mitsuba's opaque light mesh")


# ------------------------------------------------------------------------------------
# Specular and shading
# ------------------------------------------------------------------------------------


def _lobe(w, r, k):
    return (k + 1) / (2 * np.pi) * np.maximum(np.sum(w * r, axis=-1), 0.0) ** k


def _reflect(p, n, eye):
    v = _unit(eye - p)
    return 2 * np.sum(n * v, axis=-1, keepdims=True) * n - v


def _triangle_nodes(a, b, c, g):
    """Centroids and areas of the g^2 congruent sub-triangles of (a, b, c)."""
    i, j = np.meshgrid(np.arange(g), np.arange(g), indexing="ij")
    up = (i + j) < g
    dn = (i + j) < g - 1
    uv = (
        np.concatenate(
            [
                np.stack([i[up] + 1 / 3, j[up] + 1 / 3], axis=1),
                np.stack([i[dn] + 2 / 3, j[dn] + 2 / 3], axis=1),
            ]
        )
        / g
    )
    x = a + uv[:, :1] * (b - a) + uv[:, 1:] * (c - a)
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a)) / g**2
    return x, np.full(len(x), area)


def _specular_quadrature(light, p, n, eye, k, g=200):
    """Float64 quadrature of S over a polygon light (no occluders), Poulin eq. 3.12."""
    v = np.asarray(light.vertices)
    nl = np.asarray(light.normal)
    nodes = [_triangle_nodes(v[0], v[i], v[i + 1], g) for i in range(1, len(v) - 1)]
    x = np.concatenate([xs for xs, _ in nodes])
    wa = np.concatenate([ws for _, ws in nodes])
    r = _reflect(p, n, eye)
    out = np.empty(len(p))
    for i in range(len(p)):
        d = x - p[i]
        dist = np.linalg.norm(d, axis=1)
        w = d / dist[:, None]
        cos_l = np.maximum(-(w @ nl), 0.0)
        above = (w @ n[i]) > 0
        out[i] = np.sum(wa * cos_l / dist**2 * above * _lobe(w, r[i], k))
    return out[:, None] * np.asarray(light.radiance)


def test_specular_delta_lights_closed_form():
    x, inten = np.array([0.3, -0.4, 1.5]), np.array([2.0, 1.0, 3.0])
    d, e0 = _unit([0.2, 0.1, -1.0]), np.array([0.5, 0.4, 0.3])
    scene = js.Scene([js.PointLight(x, inten), js.DirectionalLight(d, e0)])
    p, n = _receivers(5, 10, [-0.5, -0.5, 0.0], [0.5, 0.5, 0.5])
    eye = np.array([0.1, 1.5, 1.0])
    k = 8.0
    r = _reflect(p, n, eye)
    wl = x - p
    r2 = np.sum(wl * wl, axis=1)
    wl = wl / np.sqrt(r2)[:, None]
    expect = ((np.sum(wl * n, axis=1) > 0) * _lobe(wl, r, k) / r2)[:, None] * inten
    expect += ((-(n @ d)) > 0)[:, None] * _lobe(-d, r, k)[:, None] * e0
    ref, err = jm.reference_specular(scene, p, n, eye, k, spp=20_000, seed=6)
    _assert_agree(expect, ref, err, what="specular, delta lights")


def _highlight_receivers(light, eye, count=12, seed=10):
    """Receivers whose mirror direction R points at (or, for every other one, near) the light."""
    rng = np.random.default_rng(seed)
    v = np.asarray(light.vertices)
    p = rng.uniform([-0.6, -0.6, 0.0], [0.6, 0.6, 0.5], (count, 3))
    t = v.mean(axis=0) + 0.7 * (v[rng.integers(0, len(v), count)] - v.mean(axis=0))
    n = _unit(_unit(eye - p) + _unit(t - p))
    n[1::2] = _unit(n[1::2] + rng.normal(scale=0.1, size=(count // 2, 3)))
    return p, n


@pytest.mark.parametrize("k", [1.0, 30.0, 300.0])
def test_specular_polygon_quadrature(k):
    light = _scene_tilted()[0].lights[0]
    eye = np.array([0.4, -1.2, 1.0])
    p, n = _highlight_receivers(light, eye)
    expect = _specular_quadrature(light, p, n, eye, k)
    ref, err = jm.reference_specular(js.Scene([light]), p, n, eye, k, spp=30_000, seed=8)
    lit = expect > 0.05 * expect.max()
    assert lit.sum() >= 12 and np.median(err[lit] / expect[lit]) < 0.01
    _assert_agree(expect, ref, err, extra=2e-3, what=f"specular k={k}")


def test_shade_combines_irradiance_and_specular():
    scene, p, n = _scene_tilted()
    scene = js.Scene(scene.lights, ambient=[0.1, 0.2, 0.3])
    material = js.Material(
        ka=[0.2, 0.3, 0.4], kd=[0.5, 0.4, 0.3], ks=[0.3, 0.3, 0.3], exponent=20.0
    )
    eye = np.array([0.4, -1.2, 1.0])
    spp, seed = 20_000, 9
    shade, err = jm.reference_shade(scene, material, p, n, eye, spp=spp, seed=seed)
    e, _ = jm.reference_irradiance(scene, p, n, spp=spp, seed=seed)
    s, _ = jm.reference_specular(scene, p, n, eye, 20.0, spp=spp, seed=seed)
    ka, kd, ks = (np.asarray(x) for x in (material.ka, material.kd, material.ks))
    # Same seed -> same samples: the shading estimate is exactly the combination.
    np.testing.assert_allclose(
        shade, ka * 0.1 * np.array([1, 2, 3]) + kd / np.pi * e + ks * s, rtol=1e-5
    )
    assert np.all(err > 0)


def test_quick_report():
    scene, p, n = _scene_quad()
    rep = jm.quick_report(scene, p[:5], n[:5], spp=5_000)
    assert set(rep) >= {"ours", "mitsuba", "stderr", "sigma", "max_sigma", "spp"}
    assert np.asarray(rep["ours"]).shape == (5, 3) and rep["max_sigma"] < 5.0


def test_missing_mitsuba_is_a_clear_import_error(monkeypatch):
    monkeypatch.setitem(sys.modules, "mitsuba", None)
    with pytest.raises(ImportError, match=r"jaxshadow\[mitsuba\]"):
        jm.to_mitsuba(js.Scene([]))


# ------------------------------------------------------------------------------------
# Measurements for the report: `.venv/bin/python tests/test_mitsuba.py`
# ------------------------------------------------------------------------------------


def _cylinder_expectation(p, n, a, b, radius, nt=4000, nphi=256):
    """Float64 quadrature of the irradiance from the Lambertian cylinder stand-in (Phi = 1)."""
    length = np.linalg.norm(b - a)
    u = (b - a) / length
    e1 = _unit(np.cross(u, [0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0]))
    e2 = np.cross(u, e1)
    t = (np.arange(nt) + 0.5) / nt * length
    phi = (np.arange(nphi) + 0.5) / nphi * 2 * np.pi
    nc = np.cos(phi)[:, None] * e1 + np.sin(phi)[:, None] * e2  # (nphi, 3)
    x = (a + t[:, None, None] * u + radius * nc[None]).reshape(-1, 3)
    nc = np.broadcast_to(nc, (nt, nphi, 3)).reshape(-1, 3)
    da = radius * (2 * np.pi / nphi) * (length / nt)
    rad = 1.0 / (2 * np.pi**2 * radius)
    out = np.empty(len(p))
    for i in range(len(p)):
        w = x - p[i]
        r2 = np.sum(w * w, axis=1)
        cos_p = np.maximum(w @ n[i], 0.0) / np.sqrt(r2)
        cos_c = np.maximum(-np.sum(w * nc, axis=1), 0.0) / np.sqrt(r2)
        out[i] = rad * da * np.sum(cos_p * cos_c / r2)
    return out


def _measure():
    import time

    import jax

    jax.config.update("jax_enable_x64", True)
    rows = []

    def row(name, ours, ref, err, dt):
        lit = ours > 0.05 * ours.max()
        z = np.abs(ours - ref) / np.maximum(err, 1e-30)
        z = np.where(np.abs(ours - ref) <= FLOOR * np.abs(ours), 0.0, z)
        rows.append((name, z.max(), np.median(err[lit] / ours[lit]), dt))

    for make, seed in ((_scene_quad, 7), (_scene_tilted, 7)):
        scene, p, n = make()
        ours = np.asarray(js.irradiance(scene, p, n))
        t = time.perf_counter()
        ref, err = jm.reference_irradiance(scene, p, n, spp=60_000, seed=seed)
        row(f"irradiance {make.__name__}", ours, ref, err, time.perf_counter() - t)
    p, n = _segment_receivers()
    for prof in ("isotropic", "cosine"):
        scene = js.Scene([js.LinearLight(SEG_A, SEG_B, 1.0, profile=prof, exponent=1)])
        ours = np.asarray(js.irradiance(scene, p, n))[:, 0]
        lit = ours > 0
        if prof == "isotropic":
            for m in (16, 64, 256):
                bias = np.abs(_chain_irradiance(p, n, SEG_A, SEG_B, m) - ours)[lit] / ours[lit]
                print(
                    f"point chain M={m}: max rel bias {bias.max():.2e}, "
                    f"median {np.median(bias):.2e}"
                )
        else:
            for r in (1e-2, 1e-3, 1e-4):
                cyl = _cylinder_expectation(p, n, SEG_A, SEG_B, r * np.linalg.norm(SEG_B - SEG_A))
                bias = np.abs(cyl - ours)[lit] / ours[lit]
                print(
                    f"cylinder r={r}*l: max rel bias {bias.max():.2e}, median {np.median(bias):.2e}"
                )
        t = time.perf_counter()
        ref, err = jm.reference_irradiance(scene, p, n, spp=100_000, seed=4)
        row(
            f"segment {prof} stand-in",
            ours[:, None],
            ref[:, :1],
            err[:, :1],
            time.perf_counter() - t,
        )
    eye = np.array([0.4, -1.2, 1.0])
    light = _scene_tilted()[0].lights[0]
    hp, hn = _highlight_receivers(light, eye)
    for k in (1.0, 30.0, 300.0):
        expect = _specular_quadrature(light, hp, hn, eye, k)
        t = time.perf_counter()
        ref, err = jm.reference_specular(js.Scene([light]), hp, hn, eye, k, spp=30_000, seed=8)
        row(f"specular k={k:g} (vs quadrature)", expect, ref, err, time.perf_counter() - t)
        # Honesty of the standard error: z-scores over 8 seeds should have unit spread.
        zs = []
        for s in range(8):
            ref, err = jm.reference_specular(
                js.Scene([light]), hp, hn, eye, k, spp=5_000, seed=100 + s
            )
            ok = expect > 0.05 * expect.max()
            zs.append(((ref - expect) / err)[ok])
        zs = np.concatenate(zs)
        print(
            f"specular k={k:g}: z-score mean {zs.mean():+.2f}, std {zs.std():.2f} "
            f"({zs.size} values)"
        )
    print(f"{'case':40s} {'max|diff|/se':>12s} {'median se/value':>16s} {'time s':>8s}")
    for name, z, rel, dt in rows:
        print(f"{name:40s} {z:12.2f} {rel:16.4f} {dt:8.2f}")


if __name__ == "__main__":
    _measure()
