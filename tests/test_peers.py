"""The peers' light sources (benchmarks/peers.py): Radiance sources of the same radiometry as
jaxshadow's point, directional and segment lights, checked against `js.irradiance` without and
with an occluder. Needs the `bench` extra (pyradiance); skipped without it."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pyradiance")

import jaxshadow as js  # noqa: E402
from benchmarks.peers import (  # noqa: E402
    RADIANCE_DEFAULT,
    RADIANCE_FINE_THIN,
    Radiance,
    radiance_source,
)
from benchmarks.real_meshes import _radiance_kind_cells, blob, light_kinds  # noqa: E402

# Deterministic (no jitter) and finely subdivided: Radiance's own error is its subdivision's.
FINE_NO_JITTER = ("-ds", "0.01", "-dt", "0", "-dc", "1")


def _receivers(n: int, seed: int = 0, tilt: float = 70.0) -> tuple[np.ndarray, np.ndarray]:
    """Floor points with normals up to `tilt` degrees from the vertical (some see part of a
    segment below their horizon)."""
    rng = np.random.default_rng(seed)
    p = np.c_[rng.uniform(-2, 2, (n, 2)), np.zeros(n)]
    t, a = np.radians(rng.uniform(0, tilt, n)), rng.uniform(0, 2 * np.pi, n)
    return p, np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)


LIGHTS = {
    "point": js.PointLight([0.1, 0.2, 2.5], [1.0, 2.0, 0.5]),
    "directional": js.DirectionalLight([0.2, 0.1, -1.0], [3.0, 1.0, 2.0]),
    "segment isotropic": js.LinearLight([-0.4, -0.1, 2.4], [0.4, 0.1, 2.6], [2.0, 1.0, 0.5]),
    "segment cosine": js.LinearLight([-0.4, -0.1, 2.4], [0.4, 0.1, 2.6], [2.0, 1.0, 0.5], profile="cosine", exponent=1),
}


def _radiance(light, occluders, p, nrm, params):
    with Radiance([radiance_source(light)], occluders) as r:
        return r.irradiance(p, nrm, params)[0]


@pytest.mark.parametrize("name", list(LIGHTS))
def test_unoccluded_radiance_source_has_jaxshadows_radiometry(name):
    """Without occluders Radiance's irradiance from the source equals jaxshadow's (RGB, tilted
    receivers) to Radiance's subdivision error; a factor in the radiance (the cylinder's pi/4
    between the isotropic and cosine profiles, pi r^2, the distant source's solid angle) fails."""
    light = LIGHTS[name]
    p, nrm = _receivers(300)
    ref = np.asarray(js.irradiance(js.Scene([light]), p, nrm))
    got = _radiance(light, np.zeros((0, 3, 3)), p, nrm, FINE_NO_JITTER)
    assert ref.max() > 0 and (ref == 0).sum() < len(ref)
    assert np.abs(got - ref).max() <= 2e-3 * np.abs(ref).max(), name


def test_fine_thin_setting_keeps_the_segment_unbiased():
    """The jittered fine setting used for the segment's thin cylinder aims every shadow ray at the
    tube (a ray past it would read as shadow: values low)."""
    light = LIGHTS["segment isotropic"]
    p, nrm = _receivers(400, seed=1, tilt=0.0)
    ref = np.asarray(js.irradiance(js.Scene([light]), p, nrm))[:, 0]
    got = _radiance(light, np.zeros((0, 3, 3)), p, nrm, RADIANCE_FINE_THIN)[:, 0]
    assert np.sqrt(np.mean((got - ref) ** 2)) <= 2e-3 * np.sqrt(np.mean(ref**2))
    assert np.abs(got - ref).max() <= 1e-2 * ref.max()


SQUARE = np.array([[[-0.25, -0.25, 1.0], [0.25, -0.25, 1.0], [0.25, 0.25, 1.0], [-0.25, 0.25, 1.0]]])


@pytest.mark.parametrize("name", ["point", "directional"])
def test_hard_shadows_agree_away_from_the_shadow_edge(name):
    """Behind a square occluder the hard shadow of the point / directional source falls where
    jaxshadow's does: receivers farther than 2 cm from the shadow's edge agree on lit / shadowed
    and on the value."""
    light = LIGHTS[name]
    rng = np.random.default_rng(2)
    p = np.c_[rng.uniform(-1, 1, (600, 2)), np.zeros(600)]
    nrm = np.tile([0.0, 0.0, 1.0], (600, 1))
    # The shadow: the square projected from the light onto the floor (a convex quadrilateral).
    if name == "point":
        src = np.asarray(light.position)
        corners = src + (SQUARE[0] - src) * (src[2] / (src[2] - SQUARE[0][:, 2]))[:, None]
    else:
        d = np.asarray(light.direction) / np.linalg.norm(light.direction)
        corners = SQUARE[0] - d * (SQUARE[0][:, 2] / d[2])[:, None]
    c2 = corners[:, :2]
    edges = np.roll(c2, -1, axis=0) - c2
    normal = np.stack([edges[:, 1], -edges[:, 0]], axis=1) / np.linalg.norm(edges, axis=1)[:, None]
    dist = np.einsum("nki,ki->nk", p[:, None, :2] - c2[None], normal)  # signed distance to each edge's line
    inside = np.all(dist <= 0, axis=1) | np.all(dist >= 0, axis=1)
    far = np.abs(dist).min(axis=1) > 0.02
    ref = np.asarray(js.irradiance(js.Scene([light], occluders=SQUARE), p, nrm))[:, 0]
    got = _radiance(light, SQUARE, p, nrm, RADIANCE_DEFAULT)[:, 0]
    assert inside[far].sum() > 20 and (~inside[far]).sum() > 20
    np.testing.assert_array_equal(ref[far] == 0, inside[far])
    np.testing.assert_array_equal(got[far] == 0, inside[far])
    assert np.abs(got[far] - ref[far]).max() <= 1e-3 * ref.max()


def test_segment_soft_shadow_within_sampling_error():
    """Behind the square the segment's soft shadow from Radiance's fine setting is within its
    sampling error of jaxshadow's exact values (RMS), and its unoccluded receivers match."""
    light = LIGHTS["segment isotropic"]
    rng = np.random.default_rng(3)
    p = np.c_[rng.uniform(-1.5, 1.5, (800, 2)), np.zeros(800)]
    nrm = np.tile([0.0, 0.0, 1.0], (800, 1))
    ref = np.asarray(js.irradiance(js.Scene([light], occluders=SQUARE), p, nrm))[:, 0]
    free = np.asarray(js.irradiance(js.Scene([light]), p, nrm))[:, 0]
    got = _radiance(light, SQUARE, p, nrm, RADIANCE_FINE_THIN)[:, 0]
    shadowed = ref < free * (1 - 1e-9)
    assert shadowed.sum() > 100  # penumbra and umbra receivers are part of the check
    assert np.sqrt(np.mean((got - ref) ** 2)) <= 1e-2 * np.sqrt(np.mean(ref**2))


def test_radiance_source_rejects_what_a_cylinder_cannot_emit():
    with pytest.raises(ValueError, match="exponent 1"):
        radiance_source(js.LinearLight([0, 0, 1], [1, 0, 1], 1.0, profile="cosine", exponent=2))
    with pytest.raises(ValueError, match="kind"):
        radiance_source(object())


def test_light_kinds_reports_radiance_beside_embree():
    """The benchmark's light-kind rows on a small mesh: Radiance's default and fine runs and the
    unoccluded check are recorded, within their sampling error of jaxshadow's exact values, and
    rendered in the table's cells."""
    pytest.importorskip("embreex")
    pytest.importorskip("trimesh")
    v, f = blob(2)
    rng = np.random.default_rng(4)
    p = np.c_[rng.uniform(-1.5, 1.5, (300, 2)), np.zeros(300)]
    nrm = np.tile([0.0, 0.0, 1.0], (300, 1))
    rows = light_kinds(v, f, p, nrm, 20)
    assert set(rows) == {"point", "directional", "segment"}
    for kind, row in rows.items():
        assert row["shadowed"] > 0.01, kind  # the mesh's shadow is among the receivers
        rad = row["radiance"]
        assert rad["default"]["points_per_s"] > 0 and rad["fine"]["points_per_s"] > 0
        assert row["radiance_unoccluded_receivers"] == 20
        assert max(row["radiance_unoccluded_rel_err"].values()) < 5e-3, kind
        if kind == "segment":
            assert rad["fine"]["params"].startswith("-dj 0.8")
            assert rad["fine"]["rms_rel_err"] < 0.02
        else:
            assert rad["fine"]["rms_rel_err"] < 1e-2 and rad["default"]["disagree"] <= 3, kind
        cells = _radiance_kind_cells(row)
        assert len(cells) == 3 and "-" not in cells
    assert _radiance_kind_cells({}) == ["-", "-", "-"]
