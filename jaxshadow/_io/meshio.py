"""Meshes in and out: OBJ / PLY / glTF / STL through trimesh, glTF written for viewers.

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

Point tables (CSV, `.npy`, `.npz`) and value tables are read and written by
`jaxshadow._io.tables`.

Every file is written through `jaxshadow._core.files` (a temporary file renamed into place).
"""

from __future__ import annotations

import os
import re
from typing import Any

import numpy as np

from .._core.files import atomic_write, atomic_write_path
from .._core.receivers import CREASE_ANGLE, ReceiverMesh, nonzero_area
from .._core.welding import weld_vertices

MESH_EXTS = (".obj", ".ply", ".glb", ".gltf", ".stl", ".off")
# The PLY float properties of irradiance, `irradiance_r/g/b`, in every PLY the project writes.
IRRADIANCE_PROPERTY = "irradiance"
LEGACY_PROPERTY = "value"  # what `write_ply` named them before: still read by `read_ply_values`


def import_trimesh() -> Any:
    """The `trimesh` module; an ImportError that names the `mesh` extra when it is missing."""
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



def read_mesh(path: str | os.PathLike, *, weld: float | None = 0.0, crease: float | None = CREASE_ANGLE) -> ReceiverMesh:
    """Read a triangle mesh (OBJ, PLY, glTF/GLB, STL, OFF; polygons are triangulated, glTF
    scenes flattened with their transforms) with trimesh; PLY files of triangle strips (the
    Stanford scans) with `ply_triangle_strips`.

    **Arguments:**

    - `path`: the file; the format follows its extension.
    - `weld`: vertices at exactly equal positions (`0.0`, default) or within `weld` (m) are
      merged (`ReceiverMesh.welded`): a surface split at UV seams, or stored as a triangle soup
      (STL), is read as one connected surface; `None` keeps the file's vertices as they are.
    - `crease`: copies whose normals differ by more than this angle (degrees) stay apart (a hard
      edge); `None` merges all (`ReceiverMesh.welded`).

    **Returns:** a `ReceiverMesh` (use `.occluder()` for a `jaxshadow.Mesh` occluder,
    `.receivers(at)` for receiver points and normals), with `n_welded` the number of vertices
    merged and `n_dropped` the number of zero-area faces left out (a repeated vertex or
    collinear corners, as scanners and exporters leave them: they bound no surface and block
    nothing; `ValueError` when no other face is left). Vertex normals are the area-weighted ones of the (welded) faces, as for
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
    trimesh = import_trimesh()
    try:
        m = trimesh.load(path, force="mesh", process=False)
    except Exception as err:  # trimesh raises many kinds for malformed files
        raise ValueError(f"{path}: cannot read the mesh ({type(err).__name__}: {err}).") from None
    if isinstance(m, trimesh.Trimesh) and len(m.faces):
        v, f = np.asarray(m.vertices), np.asarray(m.faces)
    elif extension(path) == ".ply" and (strips := ply_triangle_strips(path)) is not None:
        v, f = strips
    else:
        raise ValueError(f"{path}: the file holds no triangles.")
    keep = nonzero_area(v, f) if len(f) else np.zeros(0, bool)
    if not keep.any():
        raise ValueError(f"{path}: the file holds no triangles of nonzero area ({len(f)} of zero area).")
    mesh = ReceiverMesh(v, f[keep], name=os.path.basename(path))
    out = mesh if weld is None else mesh.welded(weld, crease)
    out.n_dropped = int(len(f) - keep.sum())
    return out


def ply_triangle_strips(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray] | None:
    """The vertices `(V, 3)` and triangles `(F, 3)` of a PLY file whose faces are triangle
    strips (an `element tristrips` with one `vertex_indices` list, -1 ending a strip: the format
    of the Stanford scans, which trimesh does not read), read with `plyfile`, binary or ASCII;
    `None` for any other PLY. Strips alternate their winding (the odd triangles of a strip are
    `b a c`); the triangles that repeat a vertex (joins of strips) are left out."""
    try:
        import plyfile
    except ImportError:
        raise ImportError("reading a PLY of triangle strips needs plyfile: pip install 'jaxshadow[mesh]'") from None
    try:
        ply = plyfile.PlyData.read(os.fspath(path))
    except Exception:  # not a PLY plyfile can read: the caller reports no triangles
        return None
    names = [e.name for e in ply.elements]
    if names != ["vertex", "tristrips"] or [q.name for q in ply["tristrips"].properties] != ["vertex_indices"]:
        return None
    vert = ply["vertex"]
    if not {"x", "y", "z"} <= {q.name for q in vert.properties}:
        return None
    v = np.stack([np.asarray(vert[c], dtype=np.float64) for c in "xyz"], axis=1)
    nv = len(v)
    # Every list ended by -1, so a strip never runs from one list into the next; strips are the
    # runs of non-negative indices, and a triangle starts at each position whose next two are in
    # its run, odd or even by its place in the run.
    parts = [np.asarray(x, dtype=np.int64) for x in ply["tristrips"]["vertex_indices"]]
    lens = np.fromiter((len(x) for x in parts), dtype=np.int64, count=len(parts))
    flat = np.concatenate(parts) if parts else np.zeros(0, np.int64)
    idx = np.full(len(flat) + len(parts), -1, dtype=np.int64)
    idx[np.arange(len(flat)) + np.repeat(np.arange(len(parts)), lens)] = flat  # part k moved by its k ends before it
    pos = np.arange(len(idx))
    run_start = np.maximum.accumulate(np.where(idx < 0, pos + 1, 0)) if len(idx) else pos
    j = np.flatnonzero((idx[:-2] >= 0) & (idx[1:-1] >= 0) & (idx[2:] >= 0)) if len(idx) >= 3 else pos[:0]
    if not len(j):
        return None
    a, b, c = idx[j], idx[j + 1], idx[j + 2]
    odd = (j - run_start[j]) % 2 == 1
    f = np.stack([np.where(odd, b, a), np.where(odd, a, b), c], axis=1)
    f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
    if len(f) and (f.max() >= nv):
        raise ValueError(f"{os.fspath(path)}: a triangle strip index is out of range [0, {nv}).")
    return v, f


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
    trimesh = import_trimesh()
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
    trimesh = import_trimesh()
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
    trimesh = import_trimesh()
    m = trimesh.load(os.fspath(path), process=False)
    data = m.metadata["_ply_raw"]["vertex" if at == "vertices" else "face"]["data"]
    names = data.dtype.names or ()
    if f"{name}_r" not in names and name == IRRADIANCE_PROPERTY and f"{LEGACY_PROPERTY}_r" in names:
        name = LEGACY_PROPERTY
    if f"{name}_r" not in names:
        raise ValueError(f"{os.fspath(path)}: no {at} properties {name}_r/g/b (has {', '.join(names)}).")
    return np.stack([np.asarray(data[f"{name}_{c}"], np.float64) for c in "rgb"], axis=1)




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
    trimesh = import_trimesh()
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
