"""`unique_rows` (the row deduplication of `weld_vertices` and `weld_polygons`) against
`np.unique(axis=0)`, and a soup given as one array welded as the same list of triangles."""

import numpy as np
import pytest

import jaxshadow as js
from jaxshadow._core.welding import unique_rows, weld_vertices


@pytest.mark.parametrize("cols", [1, 3, 6])
def test_unique_rows_matches_numpy(cols):
    rng = np.random.default_rng(cols)
    base = rng.integers(-3, 4, size=(400, cols)).astype(np.float64) * 0.25
    base[rng.random(base.shape) < 0.1] = -0.0  # -0.0 and 0.0 are one value
    a = base[rng.integers(0, 400, 2000)]
    rows, first, inv = unique_rows(a)
    u, f, i = np.unique(a, axis=0, return_index=True, return_inverse=True)
    np.testing.assert_array_equal(rows, u)
    np.testing.assert_array_equal(first, f)
    np.testing.assert_array_equal(inv, i.reshape(-1))
    np.testing.assert_array_equal(rows[inv], a)


def test_unique_rows_empty_and_single():
    rows, first, inv = unique_rows(np.zeros((0, 3)))
    assert rows.shape == (0, 3) and first.shape == (0,) and inv.shape == (0,)
    rows, first, inv = unique_rows(np.ones((1, 3)))
    assert rows.tolist() == [[1.0, 1.0, 1.0]] and first.tolist() == [0] and inv.tolist() == [0]


def test_weld_vertices_groups_in_first_order():
    v = np.array([[1.0, 0, 0], [0, 0, 0], [1.0, 0, 0], [-0.0, 0, 0], [2.0, 0, 0]])
    index, first = weld_vertices(v)
    assert index.tolist() == [0, 1, 0, 1, 2] and first.tolist() == [0, 1, 4]


def test_soup_array_welds_as_list():
    box = js.Mesh.box([0, 0, 0.3], [0.2, 0.1, 0.5])
    tris = np.concatenate([box.vertices[np.asarray(box.loops)] + [0.3 * i, 0, 0] for i in range(3)])
    light = js.PolygonLight([[-0.4, -0.4, 2.5], [-0.4, 0.4, 2.5], [0.4, 0.4, 2.5], [0.4, -0.4, 2.5]], 1.0)
    a = js.Scene([light], occluders=tris.reshape(-1, 4, 3))
    b = js.Scene([light], occluders=list(tris.reshape(-1, 4, 3)))
    assert a.occluder_topology == b.occluder_topology
    np.testing.assert_array_equal(np.asarray(a.occluders), np.asarray(b.occluders))
    assert a.occluder_topology.n_solids == 3  # three closed convex boxes found by welding
