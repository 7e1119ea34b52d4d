"""Meshes and point sets in and out: OBJ / PLY / glTF / STL through trimesh, point tables.

trimesh is the mesh library (rather than meshio): it reads the formats scene files use for
surfaces (OBJ, PLY, glTF/GLB, STL, OFF) into one triangle mesh, triangulating polygons and
flattening glTF node transforms, and writes binary PLY with vertex colours *and* extra float
vertex properties, which is what a receiver mesh with its irradiance needs. meshio targets
simulation meshes (cells of many kinds, no glTF, no colours). It is the `mesh` extra.

Receivers read from a mesh are its vertices or its face centres. One convention for every route
(`read_mesh`, `ReceiverMesh(v, f)`, `from_mitsuba`, the commands):

- **Normals.** A face's normal is the right-hand-rule normal of its vertices; a vertex's normal
  is the area-weighted mean of the normals of the faces around it (the normalised sum of their
  edge cross products), computed from the welded geometry. Normals stored in a file are not
  used (pass `vertex_normals=` to `ReceiverMesh` to give others).
- **Welding.** Vertices at exactly equal positions (or within `weld` metres) are merged when a
  mesh is read, unless their normals differ by more than a crease angle (45 degrees: a hard
  edge's copies stay apart), so a surface split along UV seams is one connected surface (one
  normal per point); `ReceiverMesh.n_welded` counts them. Occluders are welded by position.
- **Transforms.** `ReceiverMesh.transformed(matrix)` moves the vertices by an affine map and
  carries normals as normals (by the inverse transpose), reversing the faces of a mirroring map
  so that every normal stays on its side of the surface.

Point tables follow one convention for every command:

- `.csv`: a header row with named columns; `px, py, pz, nx, ny, nz` are required (other columns
  are ignored, so a targets CSV is also a points CSV); values written back get `r, g, b` columns.
- `.npy`: an `(N, 6)` array (points, then normals); `.npz`: arrays `points` and `normals`.
- `.ply` / `.obj` / `.glb` / `.gltf` / `.stl` / `.off`: a mesh, receivers at its vertices or faces.

Every file is written through `jaxshadow._core.files` (a temporary file renamed into place).
"""

from __future__ import annotations

import csv
import io
import math
import os
import re
import warnings
from typing import Any

import numpy as np

from .._core.files import atomic_write, atomic_write_path

MESH_EXTS = (".obj", ".ply", ".glb", ".gltf", ".stl", ".off")
TABLE_EXTS = (".csv", ".npy", ".npz")
POINT_COLUMNS = ("px", "py", "pz", "nx", "ny", "nz")
# The PLY float properties of irradiance, `irradiance_r/g/b`, in every PLY the project writes.
IRRADIANCE_PROPERTY = "irradiance"
# Welding merges the copies of a vertex whose normals (before welding) are within this angle
# (degrees): UV-seam copies on a smooth surface merge, a hard edge's copies stay apart.
CREASE_ANGLE = 45.0
LEGACY_PROPERTY = "value"  # what `write_ply` named them before: still read by `read_ply_values`


def _trimesh() -> Any:
    try:
        import trimesh
    except ImportError as err:
        raise ImportError(
            "reading and writing meshes needs the optional dependency 'trimesh': "
            "install it with `pip install 'jaxshadow[mesh]'`."
        ) from err
    return trimesh


def extension(path: str | os.PathLike) -> str:
    """The lower-case extension of `path` (`".ply"`), `""` when there is none."""
    return os.path.splitext(os.fspath(path))[1].lower()


class ReceiverMesh:
    """A triangle surface whose vertices or face centres are receivers.

    **Arguments:**

    - `vertices`: `(V, 3)` positions (m).
    - `faces`: `(F, 3)` vertex indices of triangles, counter-clockwise seen from the side the
      face normal points to.
    - `vertex_normals`: `(V, 3)` normals, or `None` (default) for the area-weighted mean of the
      normals of the faces around each vertex (the normalised sum of their edge cross products,
      i.e. of twice their area times their unit normal): the convention of `read_mesh` and
      `from_mitsuba` too, so one geometry has one set of normals whatever route built it.
    - `name`: a label (the file or the Mitsuba shape id).

    **Attributes:** `vertices`, `faces`, `vertex_normals` (unit), `face_normals` `(F, 3)` (unit),
    `face_areas` `(F,)` (m^2), `face_centres` `(F, 3)`, `name`, `n_welded` (vertices merged
    into others when the mesh was welded: `read_mesh`, `welded`; 0 otherwise).

    A mesh's vertices are used as given: `welded()` merges duplicates (UV seams, triangle soups),
    `transformed(matrix)` moves the mesh with its normals.

    Raises `ValueError` for non-finite vertices, indices out of range, zero-area faces, and (at
    `receivers("vertices")`) vertices that belong to no face.
    """

    def __init__(self, vertices: Any, faces: Any, vertex_normals: Any = None, name: str = ""):
        v = np.asarray(vertices, dtype=np.float64)
        f = np.asarray(faces)
        if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] < 3:
            raise ValueError(f"ReceiverMesh {name!r}: vertices must have shape (V >= 3, 3), got {v.shape}.")
        if not np.all(np.isfinite(v)):
            raise ValueError(f"ReceiverMesh {name!r}: vertices must be finite.")
        if f.ndim != 2 or f.shape[1] != 3 or f.shape[0] == 0 or not np.issubdtype(f.dtype, np.integer):
            raise ValueError(f"ReceiverMesh {name!r}: faces must be an (F >= 1, 3) integer array, got {f.shape} {f.dtype}.")
        if f.min() < 0 or f.max() >= v.shape[0]:
            raise ValueError(f"ReceiverMesh {name!r}: a face index is out of range [0, {v.shape[0]}).")
        f = f.astype(np.int64)
        cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        area2 = np.linalg.norm(cross, axis=1)
        size = float(np.max(np.ptp(v, axis=0)))
        if not (area2 > 1e-12 * size * size).all():
            raise ValueError(f"ReceiverMesh {name!r}: face {int(np.argmin(area2))} has zero area.")
        self.vertices, self.faces, self.name = v, f, name
        self.n_welded = 0
        self.face_areas = 0.5 * area2
        self.face_normals = cross / area2[:, None]
        self.face_centres = v[f].mean(axis=1)
        self._normals_given = vertex_normals is not None
        if vertex_normals is None:
            acc = np.stack([np.bincount(f.ravel(), np.repeat(cross[:, c], 3), minlength=len(v)) for c in range(3)],
                           axis=1)
        else:
            acc = np.asarray(vertex_normals, dtype=np.float64)
            if acc.shape != v.shape or not np.all(np.isfinite(acc)):
                raise ValueError(f"ReceiverMesh {name!r}: vertex_normals must be finite with shape {v.shape}.")
        length = np.linalg.norm(acc, axis=1)
        self._used = length > 0
        self.vertex_normals = acc / np.where(self._used, length, 1.0)[:, None]

    def __repr__(self) -> str:
        return f"ReceiverMesh({self.name!r}: {len(self.vertices)} vertices, {len(self.faces)} triangles)"

    def receivers(self, at: str = "vertices") -> tuple[np.ndarray, np.ndarray]:
        """`(points (N, 3), normals (N, 3))` at the vertices (`at="vertices"`) or the face
        centres (`at="faces"`), float64."""
        if at == "faces":
            return self.face_centres.copy(), self.face_normals.copy()
        if at != "vertices":
            raise ValueError(f"ReceiverMesh.receivers: at must be 'vertices' or 'faces', got {at!r}.")
        if not self._used.all():
            raise ValueError(f"ReceiverMesh {self.name!r}: {int((~self._used).sum())} vertices belong to "
                             "no face (no normal); use at='faces'.")
        return self.vertices.copy(), self.vertex_normals.copy()

    def sample(self, n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """`n` points uniformly distributed over the surface (by area) with their face normals."""
        if int(n) < 1:
            raise ValueError(f"ReceiverMesh.sample: n must be >= 1, got {n!r}.")
        rng = np.random.default_rng(seed)
        tri = rng.choice(len(self.faces), size=int(n), p=self.face_areas / self.face_areas.sum())
        u, w = rng.random((2, int(n)))
        flip = u + w > 1
        u, w = np.where(flip, 1 - u, u), np.where(flip, 1 - w, w)
        a, b, c = (self.vertices[self.faces[tri, k]] for k in range(3))
        return a + u[:, None] * (b - a) + w[:, None] * (c - a), self.face_normals[tri].copy()

    def occluder(self, merge: bool = True) -> Any:
        """The surface as a `jaxshadow.Mesh` occluder, its vertices at equal positions welded
        (hard edges too: the same points block), so a closed surface is found closed."""
        from .._core.mesh import Mesh

        index, first = weld_vertices(self.vertices)
        return Mesh(self.vertices[first], index[self.faces], merge=merge)

    def welded(self, tol: float = 0.0, crease: float | None = CREASE_ANGLE) -> ReceiverMesh:
        """The same surface with duplicate vertices merged.

        **Arguments:**

        - `tol`: vertices at exactly equal positions (`0`, default) or within `tol` (m,
          transitively) are candidates, merged at the position of the first of them (lowest
          index).
        - `crease`: an angle (degrees, default `CREASE_ANGLE` = 45): candidates are merged only
          when their area-weighted normals before welding (those of the faces each copy belongs
          to) are within it, so a hard edge stored as split vertices (a cube's corners, a mesh
          exported with per-face normals) stays split, while the copies along a UV seam of a
          smooth surface become one vertex; `None` merges every candidate. Vertices with given
          normals (`vertex_normals=`) are merged only when those are equal.

        Computed normals are recomputed (area-weighted) on the welded surface. The occluder
        (`occluder()`) is welded by position whatever the crease: it blocks the same points.

        **Returns:** a `ReceiverMesh` whose `n_welded` is the number of vertices merged away
        (`len(self.vertices) - len(result.vertices)`, plus `self.n_welded`). Faces that a
        tolerance collapses (two corners merged) are dropped; `ValueError` if none is left.
        """
        keys = self.vertex_normals if self._normals_given else None
        index, first = weld_vertices(self.vertices, tol, keys=keys)
        if crease is not None and not self._normals_given and len(first) < len(self.vertices):
            index, first = _split_creases(index, self.vertex_normals, math.cos(math.radians(float(crease))))
        f = index[self.faces]
        keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
        if not keep.any():
            raise ValueError(f"ReceiverMesh {self.name!r}: welding within {tol} collapses every face.")
        out = ReceiverMesh(self.vertices[first], f[keep], self.vertex_normals[first] if self._normals_given else None,
                           name=self.name)
        out.n_welded = self.n_welded + len(self.vertices) - len(first)
        return out

    def transformed(self, matrix: Any = None, *, rotation: Any = None, translation: Any = None,
                    scale: Any = 1.0) -> ReceiverMesh:
        """The mesh moved by an affine map $x \\mapsto A x + t$.

        **Arguments:** either `matrix`, a `(4, 4)` homogeneous (last row `0, 0, 0, 1`), `(3, 4)`
        affine `[A | t]` or `(3, 3)` linear matrix; or `rotation` `(3, 3)`, `translation` `(3,)` (m)
        and `scale` (a scalar or `(3,)`, applied first): $A = R\\,\\mathrm{diag}(s)$.

        **Returns:** a `ReceiverMesh` with vertices $A v + t$. Computed normals are recomputed
        from the moved faces (area-weighted); given normals are carried as normals,
        $A^{-\\top} n$ normalised, which stays perpendicular to the surface under non-uniform
        scaling. A mirroring map ($\\det A < 0$) reverses each face's vertex order, so face and
        vertex normals stay on the same side of the surface. `ValueError` for a singular or
        non-finite map.
        """
        a, t = affine_parts(matrix, rotation=rotation, translation=translation, scale=scale)
        v = self.vertices @ a.T + t
        f = self.faces[:, ::-1] if np.linalg.det(a) < 0 else self.faces
        n = None
        if self._normals_given:
            n = self.vertex_normals @ np.linalg.inv(a)  # (A^-T n) for every row n
            n /= np.maximum(np.linalg.norm(n, axis=1), 1e-300)[:, None]
        out = ReceiverMesh(v, f, n, name=self.name)
        out.n_welded = self.n_welded
        return out


def affine_parts(matrix: Any = None, *, rotation: Any = None, translation: Any = None,
                 scale: Any = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """`(A (3, 3), t (3,))` of an affine map given as a matrix (`(4, 4)`, `(3, 4)` or `(3, 3)`)
    or as `rotation`, `translation` and `scale` ($A = R\\,\\mathrm{diag}(s)$); `ValueError` for a
    singular, non-finite or projective one."""
    if matrix is not None:
        if rotation is not None or translation is not None or not (np.ndim(scale) == 0 and float(scale) == 1.0):
            raise ValueError("transformed: give a matrix, or rotation/translation/scale, not both.")
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape == (4, 4):
            if not np.allclose(m[3], [0, 0, 0, 1], rtol=0, atol=1e-12 * max(1.0, float(np.abs(m[3]).max()))):
                raise ValueError(f"transformed: a (4, 4) matrix must be affine (last row 0, 0, 0, 1), got {m[3]}.")
            a, t = m[:3, :3], m[:3, 3]
        elif m.shape == (3, 4):
            a, t = m[:, :3], m[:, 3]
        elif m.shape == (3, 3):
            a, t = m, np.zeros(3)
        else:
            raise ValueError(f"transformed: matrix must have shape (4, 4), (3, 4) or (3, 3), got {m.shape}.")
    else:
        r = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
        t = np.zeros(3) if translation is None else np.asarray(translation, dtype=np.float64)
        s = np.broadcast_to(np.asarray(scale, dtype=np.float64), (3,))
        if r.shape != (3, 3) or t.shape != (3,):
            raise ValueError(f"transformed: rotation must be (3, 3) and translation (3,), got {r.shape} and {t.shape}.")
        a = r * s[None, :]
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(t))):
        raise ValueError("transformed: the map must be finite.")
    sv = np.linalg.svd(a, compute_uv=False)
    if not sv[-1] > 1e-12 * sv[0]:
        raise ValueError("transformed: the map is singular (it flattens the mesh).")
    return a.copy(), t.copy()


def _split_creases(index: np.ndarray, normals: np.ndarray, cos_min: float) -> tuple[np.ndarray, np.ndarray]:
    """`weld_vertices`' `(index, first)` with each group of merged vertices split where their
    `normals` differ by more than the crease (`cos_min`, the cosine of the angle): a member joins
    the first sub-group whose first member's normal is within it. Groups in order of first use."""
    order = np.argsort(index, kind="stable")
    sizes = np.bincount(index)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    sub = np.zeros(len(index), dtype=np.int64)
    for g in np.flatnonzero(sizes > 1).tolist():
        seeds: list[int] = []
        for m in order[starts[g]:starts[g] + sizes[g]].tolist():
            for k, s in enumerate(seeds):
                if float(normals[m] @ normals[s]) >= cos_min:
                    sub[m] = k
                    break
            else:
                sub[m] = len(seeds)
                seeds.append(m)
    _, first, inv = np.unique(np.stack([index, sub], axis=1), axis=0, return_index=True, return_inverse=True)
    rank_order = np.argsort(first, kind="stable")
    rank = np.empty(len(first), dtype=np.int64)
    rank[rank_order] = np.arange(len(first))
    return rank[inv.reshape(-1)], first[rank_order]


def weld_vertices(vertices: Any, tol: float = 0.0, keys: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Which vertices are one: `(index (V,), first (W,))`, vertex i becoming welded vertex
    `index[i]`, welded vertex j being original vertex `first[j]` (the lowest index of its group;
    groups in the order of their first vertex).

    **Arguments:** `vertices` `(V, 3)`; `tol`: `0` merges exactly equal positions (`-0.0` equals
    `0.0`), `tol > 0` positions within `tol` (m) of each other, transitively; `keys`: optional
    `(V, k)` values that must be equal too (e.g. given normals).
    """
    v = np.asarray(vertices, dtype=np.float64) + 0.0
    if not (np.isfinite(tol) and tol >= 0):
        raise ValueError(f"weld: the tolerance must be a finite number >= 0, got {tol!r}.")
    if tol > 0 and len(v) > 1:
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        pairs = cKDTree(v).query_pairs(float(tol), output_type="ndarray")
        g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(v), len(v)))
        label = connected_components(g, directed=False)[1].astype(np.float64)[:, None]
    else:
        label = v
    if keys is not None:
        label = np.concatenate([label, np.asarray(keys, dtype=np.float64) + 0.0], axis=1)
    _, first, inv = np.unique(label, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    return rank[inv.reshape(-1)], first[order]


def read_mesh(path: str | os.PathLike, *, weld: float | None = 0.0, crease: float | None = CREASE_ANGLE) -> ReceiverMesh:
    """Read a triangle mesh (OBJ, PLY, glTF/GLB, STL, OFF; polygons are triangulated, glTF
    scenes flattened with their transforms) with trimesh.

    **Arguments:**

    - `path`: the file; the format follows its extension.
    - `weld`: vertices at exactly equal positions (`0.0`, default) or within `weld` (m) are
      merged (`ReceiverMesh.welded`): a surface split at UV seams, or stored as a triangle soup
      (STL), is read as one connected surface; `None` keeps the file's vertices as they are.
    - `crease`: copies whose normals differ by more than this angle (degrees) stay apart (a hard
      edge); `None` merges all (`ReceiverMesh.welded`).

    **Returns:** a `ReceiverMesh` (use `.occluder()` for a `jaxshadow.Mesh` occluder,
    `.receivers(at)` for receiver points and normals), with `n_welded` the number of vertices
    merged. Vertex normals are the area-weighted ones of the (welded) faces, as for
    `ReceiverMesh(vertices, faces)`; normals stored in the file are not used.

    Example:
        ```python
        import os, tempfile
        import jaxshadow as js

        path = os.path.join(tempfile.mkdtemp(), "quad.obj")
        js.write_mesh(path, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
        mesh = js.read_mesh(path)
        points, normals = mesh.receivers("faces")   # (2, 3) face centres and normals
        occluder = mesh.occluder()                  # the same mesh as a js.Mesh occluder
        print(points, normals)
        ```
    """
    path = os.fspath(path)
    if extension(path) not in MESH_EXTS:
        raise ValueError(f"{path}: not a mesh file (expected one of {', '.join(MESH_EXTS)}).")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such file.")
    trimesh = _trimesh()
    try:
        m = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # trimesh raises many kinds for malformed files
        raise ValueError(f"{path}: cannot read the mesh ({type(err).__name__}: {err}).") from None
    if not isinstance(m, trimesh.Trimesh) or len(m.faces) == 0:
        raise ValueError(f"{path}: the file holds no triangles.")
    mesh = ReceiverMesh(np.asarray(m.vertices), np.asarray(m.faces), name=os.path.basename(path))
    return mesh if weld is None else mesh.welded(weld, crease)


def tonemap(values: Any, exposure: float | None = None) -> np.ndarray:
    """Linear RGB values `(..., 3)` -> 8-bit sRGB: scaled by `exposure` (default: 1 / the 99th
    percentile of the largest channel), clipped to [0, 1], sRGB transfer curve."""
    x = np.asarray(values, dtype=np.float64)
    if exposure is None:
        top = float(np.percentile(x.max(axis=-1), 99)) if x.size else 0.0
        exposure = 1.0 / top if top > 0 else 1.0
    y = np.clip(x * exposure, 0.0, 1.0)
    srgb = np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1 / 2.4) - 0.055)
    return np.round(255 * srgb).astype(np.uint8)


def write_ply(path: str | os.PathLike, mesh: ReceiverMesh, values: Any, *, at: str = "vertices",
              name: str = IRRADIANCE_PROPERTY, exposure: float | None = None) -> None:
    """Write `mesh` as a binary PLY with `values` as colours and as float properties.

    **Arguments:**

    - `path`: the `.ply` file (written atomically).
    - `mesh`: a `ReceiverMesh`.
    - `values`: `(V, 3)` (`at="vertices"`) or `(F, 3)` (`at="faces"`) linear RGB values, e.g.
      irradiance (W/m^2) or radiance.
    - `name`: the float properties are `{name}_r`, `{name}_g`, `{name}_b` (float64); by default
      `irradiance_r/g/b`, the names every PLY of the project uses for irradiance (the
      `irradiance` and `mesh` commands, `IlluminationMesh.save`). Pass another name for other
      quantities (e.g. `name="radiance"`).
    - `exposure`: tone mapping of the colours (`tonemap`).

    Vertex (or face) colours are 8-bit sRGB, viewable in any mesh viewer.

    Example:
        ```python
        import os, tempfile
        import jaxshadow as js

        folder = tempfile.mkdtemp()
        js.write_mesh(os.path.join(folder, "floor.ply"), [[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]],
                      [[0, 1, 2], [0, 2, 3]])
        mesh = js.read_mesh(os.path.join(folder, "floor.ply"))
        p, n = mesh.receivers("vertices")
        scene = js.Scene([js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=10.0)])
        js.write_ply(os.path.join(folder, "lit.ply"), mesh, js.irradiance(scene, p, n))   # vertex colours
        ```
    """
    trimesh = _trimesh()
    if extension(path) != ".ply":
        raise ValueError(f"{os.fspath(path)}: write_ply writes .ply files.")
    if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", str(name)):
        raise ValueError(f"write_ply: name must be a PLY property name (letters, digits, _), got {name!r}.")
    v = np.asarray(values, dtype=np.float64)
    n = len(mesh.vertices) if at == "vertices" else len(mesh.faces)
    if at not in ("vertices", "faces") or v.shape != (n, 3):
        raise ValueError(f"write_ply: values must have shape ({n}, 3) for at={at!r}, got {v.shape}.")
    rgb = tonemap(v, exposure)
    rgba = np.concatenate([rgb, np.full((n, 1), 255, np.uint8)], axis=1)
    kw = {"vertex_colors": rgba} if at == "vertices" else {"face_colors": rgba}
    m = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False, **kw)
    attrs = m.vertex_attributes if at == "vertices" else m.face_attributes
    for c, ch in enumerate("rgb"):
        attrs[f"{name}_{ch}"] = v[:, c]
    data = m.export(file_type="ply", encoding="binary", include_attributes=True)
    with atomic_write(path, "wb") as fh:
        fh.write(data)


def write_mesh(path: str | os.PathLike, vertices: Any, faces: Any) -> None:
    """Write a triangle mesh (`.ply`, `.obj`, `.glb`, `.stl`, `.off`, by extension) with trimesh,
    vertices and faces in the given order, atomically.

    Example:
        ```python
        import os, tempfile
        import jaxshadow as js

        path = os.path.join(tempfile.mkdtemp(), "quad.ply")
        js.write_mesh(path, [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], [[0, 1, 2], [0, 2, 3]])
        mesh = js.read_mesh(path)   # read back with trimesh
        ```
    """
    trimesh = _trimesh()
    ext = extension(path)
    if ext not in MESH_EXTS or ext == ".gltf":
        raise ValueError(f"{os.fspath(path)}: write_mesh writes .ply, .obj, .glb, .stl or .off files.")
    m = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    data = m.export(file_type=ext[1:])
    with atomic_write(path, "wb" if isinstance(data, bytes) else "w") as fh:
        fh.write(data)


def read_ply_values(path: str | os.PathLike, name: str = IRRADIANCE_PROPERTY, at: str = "vertices") -> np.ndarray:
    """The `(N, 3)` float properties `{name}_r, _g, _b` (default `irradiance_r/g/b`) of a PLY
    written by `write_ply`, the `irradiance` or the `mesh` command. Irradiance in PLY files of
    earlier versions, whose API wrote it as `value_r/g/b`, is read too."""
    trimesh = _trimesh()
    m = trimesh.load(os.fspath(path), process=False)
    data = m.metadata["_ply_raw"]["vertex" if at == "vertices" else "face"]["data"]
    names = data.dtype.names or ()
    if f"{name}_r" not in names and name == IRRADIANCE_PROPERTY and f"{LEGACY_PROPERTY}_r" in names:
        name = LEGACY_PROPERTY
    if f"{name}_r" not in names:
        raise ValueError(f"{os.fspath(path)}: no {at} properties {name}_r/g/b (has {', '.join(names)}).")
    return np.stack([np.asarray(data[f"{name}_{c}"], np.float64) for c in "rgb"], axis=1)


def read_points(path: str | os.PathLike, at: str = "vertices", *,
                weld: float | None = 0.0) -> tuple[np.ndarray, np.ndarray, ReceiverMesh | None]:
    """Receivers from a file, by extension (see the module docstring for the conventions);
    a mesh is read by `read_mesh(path, weld=weld)`.

    **Returns:** `(points (N, 3), normals (N, 3), mesh)`, `mesh` the `ReceiverMesh` when the
    file is a mesh (receivers at its vertices or faces, `at`), else `None`.

    Example:
        ```python
        import os, tempfile
        import numpy as np
        import jaxshadow as js

        path = os.path.join(tempfile.mkdtemp(), "receivers.csv")
        np.savetxt(path, [[0.5, 0.5, 0, 0, 0, 1], [0.2, 0.4, 0, 0, 0, 1]], delimiter=",",
                   header="px,py,pz,nx,ny,nz", comments="")
        points, normals, mesh = js.read_points(path)   # mesh is None for a CSV
        print(points.shape, mesh)
        ```
    """
    path = os.fspath(path)
    ext = extension(path)
    if ext in MESH_EXTS:
        mesh = read_mesh(path, weld=weld)
        p, n = mesh.receivers(at)
        return p, n, mesh
    if ext not in TABLE_EXTS:
        raise ValueError(f"{path}: unknown points format {ext or '(no extension)'!r} "
                         f"(expected one of {', '.join(TABLE_EXTS + MESH_EXTS)}).")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such file.")
    if ext == ".npy":
        a = np.load(path, allow_pickle=False)
        if a.ndim != 2 or a.shape[1] != 6:
            raise ValueError(f"{path}: expected an (N, 6) array (px, py, pz, nx, ny, nz), got shape {a.shape}.")
        p, n = a[:, :3], a[:, 3:]
    elif ext == ".npz":
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in ("points", "normals") if k not in z]
            if missing:
                raise ValueError(f"{path}: missing array(s) {missing} (expected 'points' and 'normals').")
            p, n = z["points"], z["normals"]
        if p.ndim != 2 or p.shape[1] != 3 or n.shape != p.shape:
            raise ValueError(f"{path}: 'points' and 'normals' must both be (N, 3), got {p.shape} and {n.shape}.")
    else:
        table = read_csv(path, POINT_COLUMNS)
        p, n = table[:, :3], table[:, 3:]
    p, n = np.asarray(p, np.float64), np.asarray(n, np.float64)
    if p.shape[0] == 0:
        raise ValueError(f"{path}: no points.")
    if not (np.isfinite(p).all() and np.isfinite(n).all()):
        raise ValueError(f"{path}: points and normals must be finite.")
    return p, n, None


def read_csv(path: str | os.PathLike, columns: tuple[str, ...]) -> np.ndarray:
    """The named `columns` of a CSV file with a header row, as an `(N, len(columns))` float64
    array (other columns are ignored; errors name the file, the row and the column).

    The header is read with the `csv` module, the body with `np.loadtxt` (array speed). With
    columns besides `columns`, a vectorised check of the body's bytes that every row has the
    header's number of fields (`_uniform_rows`) lets `np.loadtxt` convert the named columns only
    (the others are split off, never parsed); otherwise (no other column, a quoted field, blank
    lines, a malformed row) every column is read, and a malformed row is located and named. A header naming one of `columns` twice is a `ValueError` (which of
    the two was meant is not known). Blank lines are skipped; rows count from 1 after the
    header, blank lines not counted.
    """
    path = os.fspath(path)
    with open(path, encoding="utf-8-sig", newline="") as fh:
        head = fh.readline()
        while head and not head.strip():
            head = fh.readline()
        if not head:
            raise ValueError(f"{path}: empty CSV file (expected a header row {','.join(columns)}).")
        raw_header = next(csv.reader([head]))
        header = [h.strip() for h in raw_header]
        missing = [c for c in columns if c not in header]
        if missing:
            raise ValueError(f"{path}: missing CSV column(s) {missing}: the first row must be a header "
                             f"naming the columns, e.g. {','.join(columns)} (got {raw_header[:8]}).")
        repeated = [c for c in columns if header.count(c) > 1]
        if repeated:
            raise ValueError(f"{path}: CSV column(s) {repeated} appear more than once in the header "
                             f"{','.join(header)}; each of {','.join(columns)} must appear once.")
        idx = [header.index(c) for c in columns]
        body_at = fh.tell()
        # With every column used, loadtxt of the whole table checks the field counts itself.
        body = None if len(header) == len(columns) else _body_bytes(path, head)
        body = None if body is None else _uniform_rows(body, len(header))
        if body is not None:
            try:
                table = _loadtxt(io.BytesIO(body), usecols=idx)
            except ValueError:
                pass  # a non-numeric field: the slow route names its row
            else:
                return table.reshape(-1, len(columns))
        try:
            # Every column at once: loadtxt itself refuses rows whose field count changes.
            table = _loadtxt(fh)
        except ValueError:
            table = None
        if table is not None and table.size == 0:
            return np.empty((0, len(columns)))
        if table is not None and table.shape[1] == len(header):
            return table[:, idx]
        # A text column the caller ignores, or a bad row: find the row, then read the columns used.
        fh.seek(body_at)
        for i, row in enumerate((r for r in csv.reader(fh) if r), 1):
            if len(row) != len(header):
                raise ValueError(f"{path}: row {i} has {len(row)} fields, the header has {len(header)}.")
            try:
                [float(row[j]) for j in idx]
            except ValueError:
                raise ValueError(f"{path}: row {i} has a non-numeric value in {columns}: {row}.") from None
        fh.seek(body_at)
        table = _loadtxt(fh, usecols=idx)
    return table.reshape(-1, len(columns))


def _body_bytes(path: str, head: str) -> bytes | None:
    """The bytes of the CSV file `path` after its header line `head` (as the text reader read
    it: a byte-order mark and blank lines before it skipped), or `None` when the header is not
    a `\\n`-terminated line there (the slow route then reads the file)."""
    with open(path, "rb") as raw:
        data = raw.read()
    pos = 3 if data.startswith(b"\xef\xbb\xbf") else 0
    while True:
        nl = data.find(b"\n", pos)
        if nl < 0:
            return None
        line = data[pos:nl + 1]
        pos = nl + 1
        if line.strip():
            break
    try:
        if line.decode("utf-8") != head:
            return None
    except UnicodeDecodeError:
        return None
    return data[pos:]


CSV_CHECK_BYTES = 1 << 23  # the field-count check looks at this many bytes of rows at a time


def _uniform_rows(body: bytes, ncols: int) -> bytes | None:
    """`body` (CSV rows after the header, bytes; CRLF turned into LF) when every row has exactly
    `ncols` comma-separated fields and nothing needs the `csv` module (no quote, no blank line,
    no lone CR), else `None`. Vectorised: the commas between consecutive newlines are counted
    with `np.searchsorted`, a block of about `CSV_CHECK_BYTES` at a time (small index arrays)."""
    if b'"' in body:
        return None
    if b"\r" in body:
        body = body.replace(b"\r\n", b"\n")
        if b"\r" in body:
            return None
    if body and not body.endswith(b"\n"):
        body += b"\n"
    buf = np.frombuffer(body, np.uint8)
    start = 0
    while start < len(buf):
        stop = body.find(b"\n", min(start + CSV_CHECK_BYTES, len(buf) - 1)) + 1
        chunk = buf[start:stop]
        ends = np.flatnonzero(chunk == 10)
        starts = np.concatenate([[0], ends[:-1] + 1])
        if np.any(ends == starts):
            return None  # a blank line: the slow route skips it
        commas = np.flatnonzero(chunk == 44)
        if np.any(np.searchsorted(commas, ends) - np.searchsorted(commas, starts) != ncols - 1):
            return None
        start = stop
    return body


CSV_BLOCK_ROWS = 1 << 15


def write_csv_table(fh: Any, header: list[str], columns: list[Any]) -> None:
    """Write a CSV table to the open text file `fh`: the `header` row, then the rows of the
    `(N, k_i)` arrays `columns` side by side, a block of rows at a time (a block in memory, not
    the whole text).

    Each value is written so that it reads back exactly in its own precision: a float64 value
    as its shortest round-trip repr (`repr(float)`, one string format per block), a float32
    value (an array whose dtype is float32) as `"%.9g"` (9 significant digits, which parse back
    to the same float32). One string format per block of `CSV_BLOCK_ROWS` rows; a column that
    holds one value throughout a block (bit for bit: a plane's height, a shared normal) is
    formatted once, as literal text of that block's row format.
    """
    arrays = [np.asarray(c) for c in columns]
    arrays = [a.reshape(a.shape[0], int(np.prod(a.shape[1:], dtype=np.int64))) for a in arrays]  # (0, k) too
    n = arrays[0].shape[0] if arrays else 0
    if any(a.shape[0] != n for a in arrays):
        raise ValueError(f"write_csv_table: columns have different row counts {[a.shape[0] for a in arrays]}.")
    fmts = [("%.9g" if a.dtype == np.float32 else "%r") for a in arrays for _ in range(a.shape[1])]
    if len(fmts) != len(header):
        raise ValueError(f"write_csv_table: {len(header)} header names for {len(fmts)} columns.")
    fh.write(",".join(header) + "\n")
    for s in range(0, n, CSV_BLOCK_ROWS):
        block = np.concatenate([a[s:s + CSV_BLOCK_ROWS].astype(np.float64) for a in arrays], axis=1)
        # A column with one value in the whole block (a plane's height, a shared normal) is
        # formatted once and written as literal text of the row format.
        bits = block.view(np.int64)  # bit for bit: -0.0 is not 0.0
        same = (bits == bits[:1]).all(axis=0)
        fmt = [(f % float(block[0, j])).replace("%", "%%") if same[j] else f for j, f in enumerate(fmts)]
        row = ",".join(fmt) + "\n"
        fh.write((row * block.shape[0]) % tuple(block[:, ~same].ravel().tolist()))


def _loadtxt(fh: Any, usecols: list[int] | None = None) -> np.ndarray:
    """The rest of `fh` as a float64 table (`np.loadtxt`: comma-separated, `"` quotes, no
    comment character, empty lines skipped); no warning for a header without rows."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="loadtxt: input contained no data", category=UserWarning)
        return np.loadtxt(fh, delimiter=",", usecols=usecols, dtype=np.float64, ndmin=2, comments=None, quotechar='"')


def write_values(path: str | os.PathLike, values: Any, *, points: Any = None, normals: Any = None,
                 mesh: ReceiverMesh | None = None, at: str = "vertices", name: str = IRRADIANCE_PROPERTY) -> None:
    """Write `(N, 3)` values to `path`, by extension, atomically and exactly at `path`.

    - `.npy`: the `(N, 3)` array. `.npz`: `values` (and `points`, `normals` when given).
    - `.csv`: header `px,py,pz,nx,ny,nz,r,g,b` (the receiver columns when `points` and
      `normals` are given), every value exactly (`write_csv_table`).
    - `.ply`: needs `mesh` (receivers read from a mesh): `write_ply`, float properties
      `{name}_r/g/b` (default `irradiance_r/g/b`).

    Example:
        ```python
        import os, tempfile
        import numpy as np
        import jaxshadow as js

        scene = js.Scene([js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=10.0)])
        p = np.array([[0.5, 0.5, 0.0], [2.0, 0.0, 0.0]]); n = np.array([[0.0, 0.0, 1.0]] * 2)
        path = os.path.join(tempfile.mkdtemp(), "irradiance.csv")
        js.write_values(path, js.irradiance(scene, p, n), points=p, normals=n)   # px,...,nz,r,g,b
        print(np.loadtxt(path, delimiter=",", skiprows=1))
        ```
    """
    path = os.fspath(path)
    v = np.asarray(values)
    ext = extension(path)
    if ext == ".ply":
        if mesh is None:
            raise ValueError(f"{path}: PLY output needs receivers read from a mesh.")
        write_ply(path, mesh, v, at=at, name=name)
    elif ext == ".npy":
        with atomic_write(path, "wb") as fh:
            np.save(fh, v)
    elif ext == ".npz":
        arrays = {"values": v}
        if points is not None:
            arrays.update(points=np.asarray(points), normals=np.asarray(normals))
        with atomic_write(path, "wb") as fh:
            np.savez(fh, **arrays)
    elif ext == ".csv":
        cols, header = [v], ["r", "g", "b"]
        if points is not None:
            cols, header = [np.asarray(points), np.asarray(normals), v], [*POINT_COLUMNS, "r", "g", "b"]
        with atomic_write(path, "w", newline="") as fh:
            write_csv_table(fh, header, cols)
    else:
        raise ValueError(f"{path}: unknown output format {ext or '(no extension)'!r} (expected .npy, .npz, .csv or .ply).")



# --------------------------------------------------------------------------------------
# glTF out
# --------------------------------------------------------------------------------------

GLTF_EXTS = (".glb", ".gltf")
AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0),
        "-x": (-1.0, 0.0, 0.0), "-y": (0.0, -1.0, 0.0), "-z": (0.0, 0.0, -1.0)}
# Triangles thinner than this many float32 spacings of the largest coordinate are repaired.
GLTF_SLIVER_ULPS = 1.0
GLTF_COLLAPSE = 1e-3  # a bad triangle's shortest edge up to this fraction of the mesh's size is collapsed


def y_up_rotation(up: Any) -> np.ndarray:
    """The rotation `(3, 3)` taking the unit axis `up` (`"z"`, `"-y"`, ... or a `(3,)`
    vector along a coordinate axis) to +y, glTF's up: its rows are an axis `a` perpendicular to
    `up`, `up`, and `a x up` (z-up -> y-up is `(x, y, z) -> (x, z, -y)`)."""
    if isinstance(up, str) and up not in AXES:
        raise ValueError(f"up must be a coordinate axis ({', '.join(AXES)}), got {up!r}.")
    u = np.asarray(AXES[up] if isinstance(up, str) else up, dtype=np.float64)
    if u.shape != (3,) or np.count_nonzero(u) != 1 or abs(float(np.abs(u).sum()) - 1.0) > 0:
        raise ValueError(f"up must be a coordinate axis ({', '.join(AXES)}), got {up!r}.")
    a = np.array([1.0, 0.0, 0.0]) if u[0] == 0 else np.array([0.0, 0.0, 1.0])
    return np.stack([a, u, np.cross(a, u)])  # rows a, u, a x u: det 1, and r @ u = +y


def write_gltf(path: str | os.PathLike, vertices: Any, faces: Any, *, normals: Any = None, colours: Any = None,
               attributes: dict[str, Any] | None = None, up: Any = "z") -> dict[str, int]:
    """Write a triangle mesh as glTF 2.0 (`.glb` binary, or `.gltf` with embedded buffers) through
    trimesh, y-up as glTF requires, with a clean triangulation in glTF's float32 positions.

    **Arguments:**

    - `vertices` `(V, 3)` (m), `faces` `(F, 3)` counter-clockwise seen from the side the normals
      point to; `normals` `(V, 3)` vertex normals (`NORMAL`) or `None`.
    - `colours`: `(V, 4)` uint8 RGBA display colours (`COLOR_0`) or `None`.
    - `attributes`: float vertex attributes `{name: (V,) or (V, k)}`, written as float32 glTF
      custom attributes (`_NAME`, upper case, as the specification asks), e.g.
      `{"irradiance": E}` -> `_IRRADIANCE`.
    - `up`: the scene's up axis (`"z"` for jaxshadow's scenes, `"y"` for most Mitsuba scenes);
      positions and normals are rotated so that it becomes +y.

    **Clean triangulation.** Positions are rounded to float32 first (glTF's type); vertices that
    become equal are welded (the first keeps its values) and the triangles left with a repeated
    vertex dropped (an edge collapse). A triangle thinner than `GLTF_SLIVER_ULPS` float32
    spacings of the largest coordinate, or turned over by the rounding (its normal against the
    given one), has its longest edge flipped with the neighbour across it when that makes two
    sound triangles, else its shortest edge collapsed when that is at most `GLTF_COLLAPSE` (1e-3)
    of the mesh's size (else the triangle is dropped); a vertex that rounding moved across an
    edge not its own (its triangles turn around it more than once) is collapsed into its nearest
    neighbour. The file thus has no duplicate vertex, no zero-area, inverted or overlapping
    triangle; where a needle is collapsed the surface moves by at most its short edge. Every
    written vertex keeps its own exact attributes.

    **Returns:** `{"vertices", "faces", "welded", "dropped"}`: what was written and removed.
    """
    trimesh = _trimesh()
    ext = extension(path)
    if ext not in GLTF_EXTS:
        raise ValueError(f"{os.fspath(path)}: write_gltf writes .glb or .gltf files.")
    rot = y_up_rotation(up)
    v0 = np.asarray(vertices, dtype=np.float64) @ rot.T
    f0 = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    nv = len(v0)
    cols = {k: np.asarray(a).reshape(nv, -1) for k, a in (attributes or {}).items()}
    if not re.fullmatch(r"[A-Za-z0-9_]*", "".join(cols)):
        raise ValueError(f"write_gltf: attribute names must be letters, digits and _, got {sorted(cols)}.")
    v32 = v0.astype(np.float32).astype(np.float64)
    spacing = GLTF_SLIVER_ULPS * float(np.finfo(np.float32).eps) * max(float(np.abs(v32).max(initial=0.0)), 1e-30)
    index, first = weld_vertices(v32)
    f = index[f0]
    ref = np.cross(v0[f0[:, 1]] - v0[f0[:, 0]], v0[f0[:, 2]] - v0[f0[:, 0]])
    if normals is not None:
        n0 = np.asarray(normals, dtype=np.float64) @ rot.T
        ref = n0[f0].sum(axis=1)
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    extent = float(np.max(np.ptp(v32, axis=0))) if len(v32) else 0.0
    f, ref = _flip_slivers(v32[first], f[keep], ref[keep], spacing, GLTF_COLLAPSE * extent)
    used = np.unique(f)
    local = np.full(len(first), -1, dtype=np.int64)
    local[used] = np.arange(len(used))
    src = first[used]  # original vertex of each written vertex
    kw: dict[str, Any] = {}
    if normals is not None:
        kw["vertex_normals"] = n0[src]
    if colours is not None:
        kw["vertex_colors"] = np.asarray(colours)[src]
    tm = trimesh.Trimesh(v32[src].astype(np.float32), local[f], process=False, **kw)
    for k, a in cols.items():
        tm.vertex_attributes["_" + k.upper()] = np.ascontiguousarray(a[src], np.float32)
    if ext == ".glb":
        atomic_write_path(path, lambda tmp: tm.export(tmp, file_type="glb", include_normals=normals is not None))
    else:
        from trimesh.exchange.gltf import export_gltf

        data = export_gltf(tm.scene(), embed_buffers=True, include_normals=normals is not None)["model.gltf"]
        with atomic_write(path, "wb") as fh:
            fh.write(data)
    return {"vertices": len(used), "faces": len(f), "welded": nv - len(first), "dropped": len(f0) - len(f)}


def _flip_slivers(p: np.ndarray, f: np.ndarray, ref: np.ndarray, spacing: float, collapse_length: float,
                  passes: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """`(faces, reference normals)` with the bad triangles of `f` on positions `p` repaired: a
    triangle is bad when its normal is not along `ref` or its height over its longest edge is at
    most `spacing`. Its longest edge is flipped with the neighbouring triangle across it when both
    new triangles are good; else its shortest edge is collapsed (the second end merged into the
    first, the triangles on that edge removed) when it is at most `collapse_length` long, and the
    triangle is dropped when it is longer. Then a vertex whose triangles turn around it by
    more than a full turn (a fold: rounding moved it across an edge not its own) is collapsed
    into its nearest neighbour. Repeated while anything is left to repair (at most `passes`
    times; bad triangles left then are dropped). Only the neighbourhoods repaired are visited."""

    def is_bad(ff: np.ndarray, rr: np.ndarray) -> np.ndarray:
        cr = np.cross(p[ff[:, 1]] - p[ff[:, 0]], p[ff[:, 2]] - p[ff[:, 0]])
        edge = np.max(np.linalg.norm(p[ff] - p[np.roll(ff, 1, axis=1)], axis=2), axis=1)
        return ~((np.einsum("ij,ij->i", cr, rr) > 0) & (np.linalg.norm(cr, axis=1) > spacing * edge))

    def folded(ff: np.ndarray, rr: np.ndarray) -> np.ndarray:
        unit = rr / np.maximum(np.linalg.norm(rr, axis=1), 1e-300)[:, None]
        turn = np.zeros(len(p))
        for k in range(3):
            x, y = p[ff[:, (k + 1) % 3]] - p[ff[:, k]], p[ff[:, (k + 2) % 3]] - p[ff[:, k]]
            np.add.at(turn, ff[:, k], np.arctan2(np.einsum("ij,ij->i", np.cross(x, y), unit),
                                                 np.einsum("ij,ij->i", x, y)))
        return np.flatnonzero(turn > 2 * np.pi + 1e-9)

    f, ref = f.copy(), ref.copy()
    alive = np.ones(len(f), dtype=bool)
    owner: dict[tuple[int, int], int] = {}  # directed edge -> its triangle, near the repairs
    faces_of: dict[int, set[int]] = {}  # vertex -> its triangles, near the repairs

    def put(i: int, t: list[int]) -> None:
        alive[i] = True
        f[i] = t
        for k in range(3):
            owner[(t[k], t[(k + 1) % 3])] = i
            faces_of.setdefault(t[k], set()).add(i)

    def drop(i: int) -> None:
        alive[i] = False
        t = [int(x) for x in f[i]]
        for k in range(3):
            if owner.get((t[k], t[(k + 1) % 3])) == i:
                del owner[(t[k], t[(k + 1) % 3])]
            faces_of.get(t[k], set()).discard(i)

    def collapse(w: int, u: int) -> None:
        for fi in sorted(faces_of.get(w, set())):
            t = [u if x == w else int(x) for x in f[fi]]
            drop(fi)
            if len(set(t)) == 3:
                put(fi, t)

    for _ in range(passes):
        bad = np.flatnonzero(alive & is_bad(f, ref))
        folds = folded(f[alive], ref[alive]) if not len(bad) else np.zeros(0, np.int64)
        if not len(bad) and not len(folds):
            break
        touched = np.unique(np.concatenate([f[bad].ravel(), folds]))
        near = np.flatnonzero(alive & np.isin(f, touched).any(axis=1))
        owner.clear()
        faces_of.clear()
        for i in near.tolist():
            put(i, [int(x) for x in f[i]])
        for i in bad.tolist():
            if not alive[i] or not is_bad(f[i:i + 1], ref[i:i + 1])[0]:
                continue
            tri = [int(x) for x in f[i]]
            lengths = [float(np.linalg.norm(p[tri[(k + 1) % 3]] - p[tri[k]])) for k in range(3)]
            k = int(np.argmax(lengths))
            b, c, a = tri[k], tri[(k + 1) % 3], tri[(k + 2) % 3]  # longest edge b -> c, apex a
            j = owner.get((c, b))
            if j is not None and alive[j] and j != i:
                d = next(int(x) for x in f[j] if x != b and x != c)
                t1, t2 = [a, b, d], [a, d, c]
                r = ref[i] + ref[j]
                if d not in (a, b, c) and not is_bad(np.array([t1, t2]), np.array([r, r])).any():
                    drop(i)
                    drop(j)
                    put(i, t1)
                    put(j, t2)
                    ref[i] = ref[j] = r
                    continue
            k = int(np.argmin(lengths))
            if lengths[k] <= collapse_length:  # a needle: its short edge goes
                collapse(tri[(k + 1) % 3], tri[k])
            else:  # a cap on the boundary, or no sound flip: the triangle goes
                drop(i)
        for w in folds.tolist():
            around = {int(x) for fi in faces_of.get(w, set()) for x in f[fi]} - {w}
            if around:
                collapse(w, min(around, key=lambda u: float(np.linalg.norm(p[u] - p[w]))))
    keep = alive & ~is_bad(f, ref)
    return f[keep], ref[keep]
