"""Receiver meshes: a triangle surface whose vertices or face centres are receivers, with one
normal convention (area-weighted vertex normals) for every route that builds one (`read_mesh`,
`ReceiverMesh(v, f)`, `from_mitsuba`, the commands; `jaxshadow._io.meshio` module docstring)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .welding import affine_parts, weld_vertices

# Welding merges the copies of a vertex whose normals (before welding) are within this angle
# (degrees): UV-seam copies on a smooth surface merge, a hard edge's copies stay apart.
CREASE_ANGLE = 45.0


ZERO_AREA_RTOL = 1e-12  # a face of |(b - a) x (c - a)| <= this times size^2 has zero area


def nonzero_area(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """`(F,)` bool: the triangles `faces (F, 3)` of `vertices (V, 3)` that `ReceiverMesh`
    accepts (twice the area above `ZERO_AREA_RTOL` times the squared largest extent)."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    area2 = np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)
    size = float(np.max(np.ptp(v, axis=0))) if len(v) else 0.0
    return area2 > ZERO_AREA_RTOL * size * size


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
    into others when the mesh was welded: `read_mesh`, `welded`; 0 otherwise), `n_dropped`
    (zero-area faces of the file `read_mesh` left out; 0 otherwise).

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
        if not (area2 > ZERO_AREA_RTOL * size * size).all():
            raise ValueError(f"ReceiverMesh {name!r}: face {int(np.argmin(area2))} has zero area.")
        self.vertices, self.faces, self.name = v, f, name
        self.n_welded = 0
        self.n_dropped = 0
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
        from .mesh import Mesh

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
        out.n_dropped = self.n_dropped
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
        out.n_dropped = self.n_dropped
        return out


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
