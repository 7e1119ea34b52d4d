"""What the mesh robustness sweep (`benchmarks/mesh_robustness.py`) found, one fast test each:
generated meshes and files only.

- A mesh file with a zero-area face (a repeated vertex, collinear corners: scanners and
  exporters leave them) could not be read at all (`ReceiverMesh ... has zero area`):
  `read_mesh` now leaves such faces out and counts them (`n_dropped`).
- A PLY of triangle strips (the Stanford scans' format) read as "no triangles".
- Sliver triangles (a face split at a point 1e-8 of its height off an edge): `js.Mesh` refused
  them as "zero area" (its test was relative to the whole mesh's size, not the face's, unlike a
  polygon given to `Scene`), and `Scene` refused the same triangles in a soup as "non-planar"
  (Newell's normal from absolute coordinates cancels for a small face away from the origin).

Independent reference: `test_clip.reference_ff` (exact polygon booleans in shapely).
"""

from __future__ import annotations

import struct

import numpy as np
import pytest

import jaxshadow as js
from benchmarks.mesh_robustness import slivers
from benchmarks.real_meshes import LIGHT, blob
from jaxshadow._shadows import binding as vis

trimesh = pytest.importorskip("trimesh")
shapely = pytest.importorskip("shapely")
from test_clip import reference_ff  # noqa: E402
from test_plan import culled  # noqa: E402

BOX_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float)
BOX_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                  [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])


def _obj(path, v, f) -> None:
    lines = [f"v {x:.17g} {y:.17g} {z:.17g}" for x, y, z in v] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in f]
    path.write_text("\n".join(lines) + "\n")


def test_read_mesh_drops_zero_area_faces(tmp_path):
    """A closed box with a repeated-vertex face and a face of three collinear corners (one more
    vertex, the midpoint of an edge, exactly representable): read, the two faces left out and
    counted, the occluder closed and the same as the box's."""
    v = np.concatenate([BOX_V, [[0.5, 0.0, 0.0]]])
    f = np.concatenate([BOX_F, [[0, 0, 1], [0, 8, 1]]])
    _obj(tmp_path / "box.obj", v, f)
    m = js.read_mesh(tmp_path / "box.obj")
    assert m.n_dropped == 2 and len(m.faces) == 12
    assert sorted(map(tuple, np.sort(m.faces, axis=1))) == sorted(map(tuple, np.sort(BOX_F, axis=1)))
    occ = m.occluder()
    assert occ.closed and occ.convex
    _obj(tmp_path / "flat.obj", v[[0, 1, 8]], np.array([[0, 2, 1]]))
    with pytest.raises(ValueError, match="no triangles of nonzero area"):
        js.read_mesh(tmp_path / "flat.obj")
    assert js.read_mesh(tmp_path / "box.obj", weld=None).n_dropped == 2  # without welding too
    assert js.ReceiverMesh(BOX_V, BOX_F).n_dropped == 0


def _strips(faces: np.ndarray) -> list[int]:
    """`faces` as strips: pairs of faces sharing an edge as one 4-index strip where they can
    be (the second face then read with the alternating winding), every other face alone; -1
    between strips."""
    out: list[int] = []
    k = 0
    while k < len(faces):
        paired = False
        for r in range(3) if k + 1 < len(faces) else ():
            # Strip a b c d gives (a b c) and, the odd triangle flipped, (c b d).
            a, b, c = (int(x) for x in np.roll(faces[k], -r))
            d = [int(x) for x in faces[k + 1] if x not in (b, c)]
            if len(d) == 1 and any(tuple(np.roll(faces[k + 1], q)) == (c, b, d[0]) for q in range(3)):
                out += [a, b, c, d[0], -1]
                paired = True
                break
        if paired:
            k += 2
            continue
        out += [int(x) for x in faces[k]] + [-1]
        k += 1
    return out


@pytest.mark.parametrize("fmt", ["binary_little_endian", "ascii"])
def test_read_mesh_reads_ply_triangle_strips(tmp_path, fmt):
    """A PLY of the box's triangles as strips (one with an extra vertex property): the same
    triangles with their orientation, found closed."""
    s = _strips(BOX_F)
    assert len(s) < 4 * len(BOX_F)  # some faces did pair up into 4-index strips
    head = ["ply", f"format {fmt} 1.0", f"element vertex {len(BOX_V)}", "property float x", "property float y",
            "property float z", "property uchar confidence", "element tristrips 1",
            "property list int int vertex_indices", "end_header"]
    path = tmp_path / "box.ply"
    if fmt == "ascii":
        body = "".join(f"{x} {y} {z} 7\n" for x, y, z in BOX_V) + f"{len(s)} " + " ".join(map(str, s)) + "\n"
        path.write_text("\n".join(head) + "\n" + body)
    else:
        body = b"".join(struct.pack("<fffB", *p, 7) for p in BOX_V) + struct.pack(f"<i{len(s)}i", len(s), *s)
        path.write_bytes(("\n".join(head) + "\n").encode() + body)
    m = js.read_mesh(path)
    np.testing.assert_array_equal(m.vertices, BOX_V)
    canon = sorted(tuple(np.roll(x, -int(np.argmin(x)))) for x in BOX_F)
    assert sorted(tuple(np.roll(x, -int(np.argmin(x)))) for x in m.faces) == canon
    assert m.occluder().closed


def test_sliver_triangles_in_a_mesh_and_a_soup():
    """Faces split at a point 1e-8 of their height off an edge (a sliver of that relative area):
    `js.Mesh` builds, closed; the soup of the same triangles is welded into one mesh; both give
    the exact values (polygon booleans) on penumbra and umbra floor receivers, through the
    silhouette path (the mesh has more than 256 faces)."""
    v, f = blob(2)
    vs, fs = slivers(v, f, every=3, off=1e-8)
    assert len(fs) >= 256
    mesh = js.Mesh(vs, fs)
    assert mesh.closed
    light = js.PolygonLight(LIGHT, 1.0)
    s_mesh = js.Scene([light], occluders=[mesh])
    s_soup = js.Scene([light], occluders=vs[fs])
    assert s_soup.occluder_topology is not None and s_soup.occluder_topology.from_mesh.all()
    rng = np.random.default_rng(2)
    p = np.c_[rng.uniform(-1.0, 1.0, (200, 2)), np.zeros(200)]
    n = np.tile([0.0, 0.0, 1.0], (200, 1))
    cls = js.shadow_plan(s_mesh, p, n).lights[0].classes
    sel = np.r_[np.where(cls == vis.PENUMBRA)[0][:8], np.where(cls == vis.UMBRA)[0][:2]]
    assert len(sel) == 10
    tris = vs[fs]
    ref = np.array([np.pi * reference_ff(x, y, LIGHT, culled(x, y, LIGHT, tris)) for x, y in zip(p[sel], n[sel], strict=True)])
    for scene in (s_mesh, s_soup):
        e = np.asarray(js.irradiance(scene, p[sel], n[sel]))[:, 0]
        np.testing.assert_allclose(e, ref, rtol=0, atol=1e-9 * np.pi)


def test_sliver_triangles_are_planar():
    """A triangle is planar: slivers of relative area 1e-8 (5 cm long, 5e-10 m high) in random
    orientations about 1.3 m from the origin are accepted as polygons and as mesh faces (7 of
    these 8 were "non-planar", 3e-8 m off their own plane); a non-planar quad is still refused."""
    rng = np.random.default_rng(0)
    light = js.PolygonLight(LIGHT, 1.0)
    for _ in range(8):
        a = np.array([0.3, -0.4, 1.2]) + rng.normal(0, 0.1, 3)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        w = np.cross(u, rng.normal(size=3))
        w /= np.linalg.norm(w)
        b = a + 0.05 * u
        tri = np.array([a, b, (a + b) / 2 + 5e-10 * w])
        js.Scene([light], occluders=[tri])
        js.Mesh(tri, [[0, 1, 2]])
    quad = np.array([a, b, b + 0.05 * w, a + 0.05 * w + 1e-4 * np.cross(u, w)])
    with pytest.raises(ValueError, match="non-planar"):
        js.Scene([light], occluders=[quad])
    with pytest.raises(ValueError, match="not planar"):
        js.Mesh(quad, [[0, 1, 2, 3]])


@pytest.mark.parametrize("bad", ["repeated", "collinear", "nan"])
def test_soup_with_one_bad_triangle_names_it(bad):
    """Scene checks a soup's triangles together (one vectorised pass) and falls back to the
    one-by-one check, which names the polygon, when any triangle is in doubt."""
    v, f = blob(2)
    tris = v[f].copy()
    if bad == "repeated":
        tris[200, 2] = tris[200, 0]
        msg = r"Scene.occluders\[200\]: a polygon needs at least 3 distinct vertices"
    elif bad == "collinear":
        tris[200, 2] = 0.25 * tris[200, 0] + 0.75 * tris[200, 1]
        msg = r"Scene.occluders\[200\]: zero area"
    else:
        tris[200, 1, 2] = np.nan
        msg = r"Scene.occluders\[200\]"
    with pytest.raises(ValueError, match=msg):
        js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=tris)
    with pytest.raises(ValueError, match=msg):
        js.Scene([js.PolygonLight(LIGHT, 1.0)], occluders=list(tris))


def test_ply_triangle_strips_runs_and_lists(tmp_path):
    """Strips end at -1 and at the end of each list (no triangle joins two lists); a strip of two
    indices gives none; odd triangles of a strip run `b a c`; triangles repeating a vertex go."""
    from jaxshadow._io.meshio import ply_triangle_strips

    lists = [[0, 1, 2, 3, -1, 4, 5], [6, 7, 8, 9, -1, 1, 1, 2, 0]]
    v = np.random.default_rng(0).uniform(0, 1, (10, 3))
    head = ["ply", "format ascii 1.0", "element vertex 10", "property float x", "property float y", "property float z",
            "element tristrips 2", "property list int int vertex_indices", "end_header"]
    body = "".join(f"{x} {y} {z}\n" for x, y, z in v) + "".join(f"{len(x)} " + " ".join(map(str, x)) + "\n" for x in lists)
    path = tmp_path / "strips.ply"
    path.write_text("\n".join(head) + "\n" + body)
    _, f = ply_triangle_strips(path)
    assert f.tolist() == [[0, 1, 2], [2, 1, 3], [6, 7, 8], [8, 7, 9], [2, 1, 0]]
