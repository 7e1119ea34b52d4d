"""`Mesh` construction (vectorised validation, closedness, coplanar merging, convexity): its
results against brute-force definitions on meshes of every kind, and index validation."""

import numpy as np
import pytest
import trimesh

import jaxshadow as js
from jaxshadow._core.faces import _face_loops


def _convex_reference(loops, v, size):
    """The definition: every vertex on or behind every face plane (tolerance 1e-9 size)."""
    for loop in loops:
        pts = v[loop]
        w = np.concatenate([pts[1:], pts[:1]])
        n = np.array([np.sum(pts[:, 1] * w[:, 2] - pts[:, 2] * w[:, 1]), np.sum(pts[:, 2] * w[:, 0] - pts[:, 0] * w[:, 2]),
                      np.sum(pts[:, 0] * w[:, 1] - pts[:, 1] * w[:, 0])])
        if np.max((v - pts[0]) @ (n / np.linalg.norm(n))) > 1e-9 * size:
            return False
    return True


def _closed_reference(loops):
    count = {}
    for loop in loops:
        for k in range(len(loop)):
            e = (loop[k], loop[(k + 1) % len(loop)])
            count[e] = count.get(e, 0) + 1
    return all(c == 1 and count.get((b, a), 0) == 1 for (a, b), c in count.items())


def _displaced(m):
    u = m.vertices / np.linalg.norm(m.vertices, axis=1, keepdims=True)
    return m.vertices * (1 + 0.15 * np.sin(3 * u[:, :1]) * np.cos(2 * u[:, 1:2])), m.faces


def _meshes():
    out = {"box": (trimesh.creation.box().vertices, trimesh.creation.box().faces)}
    for s in (1, 2, 3, 4):
        m = trimesh.creation.icosphere(subdivisions=s)
        out[f"icosphere{s}"] = (m.vertices, m.faces)
    out["displaced"] = _displaced(trimesh.creation.icosphere(subdivisions=3))
    m = trimesh.creation.icosphere(subdivisions=2)
    out["open"] = (m.vertices, m.faces[5:])
    b = trimesh.creation.box().subdivide().subdivide()
    out["subdivided_box"] = (b.vertices, b.faces)
    uv = trimesh.creation.uv_sphere(count=[16, 16])
    out["uv_sphere"] = (uv.vertices, uv.faces)
    out["inward_box"] = (trimesh.creation.box().vertices, trimesh.creation.box().faces[:, ::-1])
    two = trimesh.util.concatenate([trimesh.creation.icosphere(4), trimesh.creation.icosphere(4).apply_translation([3, 0, 0])])
    out["two_spheres"] = (two.vertices, two.faces)  # every edge convex, the whole not
    return out


MESHES = _meshes()
EXPECTED = {"box": (True, True, 6), "icosphere1": (True, True, 80), "icosphere4": (True, True, 5120),
            "displaced": (True, False, 1280), "open": (False, False, 315), "subdivided_box": (True, True, 6),
            "inward_box": (True, True, 6), "two_spheres": (True, False, 10240)}


@pytest.mark.parametrize("name", sorted(MESHES))
def test_mesh_build_matches_definitions(name):
    v, f = MESHES[name]
    m = js.Mesh(v, f)
    v = np.asarray(v, float)
    size = float(np.max(np.ptp(v, axis=0)))
    assert m.closed == _closed_reference(m.loops)
    assert m.convex == (m.closed and _convex_reference(m.loops, v, size))
    if name in EXPECTED:
        assert (m.closed, m.convex, len(m.loops)) == EXPECTED[name]
    # The faces the kernels see are the loops' vertices; merging keeps the area.
    assert all(np.array_equal(p, v[loop]) for p, loop in zip(m.polygons, m.loops, strict=True))
    area = sum(np.linalg.norm(np.cross(v[t[1]] - v[t[0]], v[t[2]] - v[t[0]])) for t in np.asarray(f)) / 2
    merged = sum(np.linalg.norm(sum(np.cross(p[i], p[(i + 1) % len(p)]) for i in range(len(p)))) for p in m.polygons) / 2
    assert merged == pytest.approx(area, rel=1e-9)
    # A list of faces (the generic path) and merge=False build the same mesh.
    lst = js.Mesh(v, np.asarray(f).tolist())
    assert lst.loops == m.loops and lst.closed == m.closed and lst.convex == m.convex and lst.edges == m.edges
    raw = js.Mesh(v, f, merge=False)
    assert raw.closed == m.closed and len(raw.loops) == len(f)
    if m.convex:
        # Each undirected edge once, its two faces on either side.
        assert len(m.edges) == sum(len(loop) for loop in m.loops) // 2
        for fl, ka, kb, fr, a, b in m.edges:
            assert (m.loops[fl][ka], m.loops[fl][kb]) == (a, b)
            assert any((m.loops[fr][k], m.loops[fr][(k + 1) % len(m.loops[fr])]) == (b, a) for k in range(len(m.loops[fr])))


def test_outward_orientation_of_an_inward_mesh():
    v, f = MESHES["inward_box"]
    m = js.Mesh(v, f)
    for p in m.polygons:
        n = sum(np.cross(p[i], p[(i + 1) % len(p)]) for i in range(len(p)))
        assert np.dot(n, p.mean(axis=0) - np.asarray(v).mean(axis=0)) > 0


@pytest.mark.parametrize("faces", [np.array([[0, 1, 2.5]]), [[0, 1, 2.5]], [[0, 1, 2], [0, 2, np.nan]],
                                   [[0, 1, 2, 3.5]], np.array([[0.0, 1.0, 2.0, 3.25]])])
def test_non_integer_face_index_is_refused(faces):
    with pytest.raises(ValueError, match="not an integer"):
        _face_loops(faces, 4)


def test_integral_indices_and_errors():
    assert _face_loops(np.array([[0.0, 1.0, 2.0]]), 3) == [[0, 1, 2]]
    assert _face_loops([[0, 1, 2, 2]], 3) == [[0, 1, 2]]
    with pytest.raises(ValueError, match="face 1 has a vertex index out of range"):
        _face_loops(np.array([[0, 1, 2], [0, 1, 3]]), 3)
    with pytest.raises(ValueError, match="face 0 needs at least three distinct vertices"):
        _face_loops(np.array([[0, 1, 0], [0, 1, 5]]), 3)
    v = [[0, 0, 0], [1, 0, 0], [2, 0, 0], [0, 1, 0]]
    with pytest.raises(ValueError, match="face 1 has zero area"):
        js.Mesh(v, [[0, 1, 3], [0, 1, 2]])
    with pytest.raises(ValueError, match="face 0 is not planar"):
        js.Mesh([[0, 0, 0], [1, 0, 0], [1, 1, 0.5], [0, 1, 0]], [[0, 1, 2, 3]])


def _merge_reference(loops, v, size, rtol=1e-9):
    """Coplanar merging as its definition reads: the greedy queue of shared edges (last in, first
    out), every pair tested and glued with NumPy on the pair's own vertices (no vectorised
    pre-pass, no Python-float shortcuts)."""
    def unit_normal(loop):
        p = v[loop]
        w = np.concatenate([p[1:], p[:1]])
        n = np.array([np.sum(p[:, 1] * w[:, 2] - p[:, 2] * w[:, 1]), np.sum(p[:, 2] * w[:, 0] - p[:, 0] * w[:, 2]),
                      np.sum(p[:, 0] * w[:, 1] - p[:, 1] * w[:, 0])])
        return n / np.sqrt(np.sum(n * n))

    def coplanar(ni, nj, pts, p0):
        d = pts - p0
        off = np.abs(d[:, 0] * ni[0] + d[:, 1] * ni[1] + d[:, 2] * ni[2]).max()
        return not (ni[0] * nj[0] + ni[1] * nj[1] + ni[2] * nj[2] < 1 - 1e-12) and not (off > rtol * size)

    def union(la, lb, a, b, nrm):
        ia, ib = la.index(a), lb.index(b)
        out = (la[ia + 1:] + la[:ia + 1]) + (lb[ib + 1:] + lb[:ib + 1])[1:-1]
        changed = True
        while changed and len(out) > 3:
            changed = False
            for k in range(len(out)):
                p0, p1, p2 = v[out[k - 1]], v[out[k]], v[out[(k + 1) % len(out)]]
                if abs(np.dot(np.cross(p1 - p0, p2 - p1), nrm)) <= 1e-12 * np.linalg.norm(p1 - p0) * np.linalg.norm(p2 - p1):
                    out = out[:k] + out[k + 1:]
                    changed = True
                    break
        if len(out) > 8 or len(set(out)) != len(out):
            return None
        pts = v[out]
        e = np.roll(pts, -1, axis=0) - pts
        c = np.cross(e, np.roll(e, -1, axis=0))
        turn = c[:, 0] * nrm[0] + c[:, 1] * nrm[1] + c[:, 2] * nrm[2]
        return None if np.any(turn <= 0) else out

    loops = [list(x) for x in loops]
    normals = [unit_normal(x) for x in loops]
    alive = [True] * len(loops)
    owner = {}
    for f, loop in enumerate(loops):
        for k in range(len(loop)):
            owner[(loop[k], loop[(k + 1) % len(loop)])] = f
    queue = [e for e in owner if (e[1], e[0]) in owner and e[0] < e[1]]
    while queue:
        a, b = queue.pop()
        i, j = owner.get((a, b)), owner.get((b, a))
        if i is None or j is None or i == j or not (alive[i] and alive[j]):
            continue
        if not coplanar(normals[i], normals[j], v[loops[j]], v[loops[i][0]]):
            continue
        m = union(loops[i], loops[j], a, b, normals[i])
        if m is None:
            continue
        for f in (j, i):
            for k in range(len(loops[f])):
                owner.pop((loops[f][k], loops[f][(k + 1) % len(loops[f])]), None)
        loops[i], alive[j] = m, False
        for k in range(len(m)):
            e = (m[k], m[(k + 1) % len(m)])
            owner[e] = i
            if (e[1], e[0]) in owner:
                queue.append(e)
    return [x for x, keep in zip(loops, alive, strict=True) if keep]


def _merge_cases():
    rng = np.random.default_rng(0)
    out = dict(MESHES)
    ann = trimesh.creation.annulus(r_min=0.3, r_max=0.5, height=0.2, sections=96)
    ann.apply_transform(trimesh.transformations.rotation_matrix(np.radians(30), [1, 0, 0]))
    out["tilted_annulus"] = (ann.vertices, ann.faces)  # coplanar rings whose pairs are not convex
    b = trimesh.creation.box().subdivide().subdivide()
    f = b.faces.copy()
    flip = rng.random(len(f)) < 0.2
    f[flip] = f[flip][:, ::-1]
    out["flipped_faces"] = (b.vertices, f)
    g = trimesh.creation.box().subdivide().subdivide().subdivide()
    out["flat_grid"] = (g.vertices, g.faces[g.vertices[g.faces][:, :, 2].mean(axis=1) > 0.49])  # open, one plane
    soup = trimesh.util.concatenate([trimesh.creation.box(), trimesh.creation.cylinder(0.3, 1, sections=12).apply_translation([3, 0, 0])])
    out["two_components"] = (soup.vertices, soup.faces)
    return out


@pytest.mark.parametrize("name", sorted(_merge_cases()))
def test_merge_matches_the_greedy_definition(name):
    """The vectorised build's merged faces are exactly those of the greedy definition (same loops,
    same order, same starting vertices), on closed, open, flipped, multi-component meshes and
    coplanar groups whose merges stop at non-convex unions."""
    v, f = _merge_cases()[name]
    v = np.asarray(v, float)
    m = js.Mesh(v, f)
    raw = js.Mesh(v, f, merge=False)
    size = float(np.max(np.ptp(v, axis=0)))
    assert m.loops == _merge_reference(raw.loops, v, size)


def test_repeated_faces_are_dropped_and_shadow_the_same():
    """A face repeated from another vertex or in the other direction (double-sided geometry, a
    soup with copies) is dropped: the same point set, so the same shadows, and the mesh keeps
    its closedness (four faces on an edge would make it non-manifold)."""
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.3)
    v = np.asarray(sphere.vertices) + [0.0, 0.0, 1.0]
    f = np.asarray(sphere.faces)
    rng = np.random.default_rng(3)
    pick = rng.choice(len(f), 12, replace=False)
    rolled = np.roll(f[pick[:6]], 1, axis=1)            # same loop, another start
    flipped = f[pick[6:]][:, ::-1]                      # same triangle, other direction
    f2 = np.concatenate([f, rolled, flipped, f[:1]])    # and one exact copy
    plain, doubled = js.Mesh(v, f), js.Mesh(v, f2)
    assert (plain.n_repeated, doubled.n_repeated) == (0, 13)
    assert doubled.closed and doubled.convex == plain.convex
    assert doubled.loops == plain.loops
    # a face sharing all but one vertex with another is not a repeat
    other = np.array([[f[0][0], f[0][1], f[1][2]]])
    assert js.Mesh(v, np.concatenate([f, other])).n_repeated == 0

    light = js.PolygonLight(np.array([[-0.4, -0.4, 2.0], [-0.4, 0.4, 2.0], [0.4, 0.4, 2.0], [0.4, -0.4, 2.0]]), 1.0)
    g = np.linspace(-1.0, 1.0, 9)
    p = np.stack([*np.meshgrid(g, g, indexing="ij"), np.zeros((9, 9))], axis=-1).reshape(-1, 3)
    n = np.tile([0.0, 0.0, 1.0], (len(p), 1))
    e0 = np.asarray(js.irradiance(js.Scene([light], occluders=[plain]), p, n))
    e1 = np.asarray(js.irradiance(js.Scene([light], occluders=[doubled]), p, n))
    soup = v[f2][rng.permutation(len(f2))]
    e2 = np.asarray(js.irradiance(js.Scene([light], occluders=soup), p, n))
    assert np.ptp(e0) > 0.1 * np.max(e0)  # some receivers in shadow
    np.testing.assert_array_equal(e1, e0)
    np.testing.assert_allclose(e2, e0, rtol=1e-12, atol=1e-15)
