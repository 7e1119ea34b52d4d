"""The silhouette path's cull: contour segments that certainly bound nothing are neither cut nor
classified (silhouette.h, `SilCoverage::lower_bounds`).

Per receiver, each cell of the contour grid gets a lower bound of the depth complexity C over the
whole cell (C at its reference point minus what crossing the cell's pieces can take away); a
contour segment whose every cell has C >= 1 lies where the light is covered on both of its sides,
so it bounds nothing and is dropped before the crossing pass. Wrongly dropped boundary pieces
(a wrong sign of a piece's jump, a bound that forgets a piece, a cell the segment meets but that
is not checked) open or close parts of the visible region: values against the face path
(`JAXSHADOW_SILHOUETTE=0`, which shares no coverage code) on every receiver and against exact
polygon booleans on a subset. The meshes have many contour segments inside their own shadow
(enough for the contour grid, which the cull needs): nested closed shells, a scan-like jittered
closed shape, open bowls (boundary edges of weight 1, no closedness to lean on) with and without
a body inside, overlapping bumpy components.
"""

from __future__ import annotations

import numpy as np
import pytest

from jaxshadow._shadows import binding as vis

pytestmark = pytest.mark.skipif(not vis.engine_available(), reason="the shadow engine is not built")
trimesh = pytest.importorskip("trimesh")
pytest.importorskip("shapely")
from test_real_meshes_coverage import _check, union  # noqa: E402


def bumpy(centre, radius: float, subdivisions: int, jitter: float = 0.0, seed: int = 0, amp: float = 0.2):
    """A closed non-convex icosphere displaced by a smooth bump field (and optionally jittered
    along the normal, like a scan's noise: many small contour loops inside its own shadow)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions)
    u = np.asarray(m.vertices, float)
    d = 1 + amp * np.sin(5 * u[:, 0] + 1) * np.cos(4 * u[:, 1]) + 0.5 * amp * np.sin(6 * u[:, 2])
    if jitter:
        d = d + np.random.default_rng(seed).normal(0, jitter, len(u))
    return np.asarray(centre, float) + radius * u * d[:, None], np.asarray(m.faces, np.int64)


def bowl(v: np.ndarray, f: np.ndarray, z: float, up: bool) -> tuple[np.ndarray, np.ndarray]:
    """The part of a mesh above (`up`) or below height z: an open shell."""
    c = v[f][:, :, 2].mean(axis=1)
    return v, f[c > z] if up else f[c < z]


def test_nested_closed_shells(monkeypatch):
    """A closed body inside a closed shell: every contour segment of the inner one lies where the
    shell covers the light twice, on both of its sides."""
    outer = bumpy([0.0, 0.0, 0.95], 0.45, 3, amp=0.15)
    inner = bumpy([0.05, -0.02, 0.95], 0.2, 3, amp=0.3)
    _check(*union(outer, inner), monkeypatch, seed=31, n=400, n_ref=20)


def test_jittered_closed_shape(monkeypatch):
    """Scan-like noise on a closed non-convex shape: most contour loops are small folds inside the
    shape's own shadow."""
    _check(*bumpy([0.0, 0.0, 0.9], 0.4, 4, jitter=0.01, seed=5), monkeypatch, seed=32, n=300, n_ref=16)


@pytest.mark.parametrize("up", [True, False], ids=["cap", "cup"])
def test_open_jittered_bowl(monkeypatch, up):
    """An open shell (the bunny's base is open): its rim is made of boundary edges (weight 1), the
    covering there is one layer, not two, and nothing may lean on closedness. Seen from below,
    the cup's jittered rim sends about 4 % of the penumbra receivers to the face path (as it did
    before the cull)."""
    v, f = bumpy([0.0, 0.0, 0.9], 0.4, 4, jitter=0.008, seed=6)
    _check(*bowl(v, f, 0.85, up), monkeypatch, seed=33, n=300, n_ref=16, fallbacks=0.02 if up else 0.06)


def test_body_inside_open_bowl(monkeypatch):
    """A closed body inside an open cap (a rim of weight 1 over the body's weight 2 contour):
    the cap's single layer covers the body's contour from some receivers and not from others."""
    cap = bowl(*bumpy([0.0, 0.0, 0.9], 0.45, 3, jitter=0.005, seed=7), 0.8, True)
    body = bumpy([0.08, 0.0, 0.95], 0.18, 3, jitter=0.01, seed=8)
    _check(*union(cap, body), monkeypatch, seed=34, n=400, n_ref=20)


def test_overlapping_bumpy_components(monkeypatch):
    """Interpenetrating jittered components: contour loops of one inside and across the other's
    shadow, layers from 0 to 6."""
    parts = [bumpy([-0.15, 0.0, 0.85], 0.3, 3, jitter=0.01, seed=9), bumpy([0.15, 0.1, 1.0], 0.28, 3, jitter=0.01, seed=10),
             bumpy([0.0, -0.1, 1.2], 0.22, 3, jitter=0.01, seed=11)]
    _check(*union(*parts), monkeypatch, seed=35, n=400, n_ref=20)
