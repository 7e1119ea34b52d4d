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
import os
import re
import warnings
from typing import Any

import numpy as np

from .._core.files import atomic_write, atomic_write_path
from .._core.receivers import CREASE_ANGLE, ReceiverMesh
from .._core.welding import weld_vertices

MESH_EXTS = (".obj", ".ply", ".glb", ".gltf", ".stl", ".off")
TABLE_EXTS = (".csv", ".npy", ".npz")
POINT_COLUMNS = ("px", "py", "pz", "nx", "ny", "nz")
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
    trimesh = import_trimesh()
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

    The header is read with the `csv` module. The body, when the compiled reader
    (`jaxshadow._io._csvc`) is built and every row is plain numbers (`_parse_body`: no quote,
    no blank line, one field count), is parsed by it at array speed (strtod, GIL released; the
    same float64 values as `np.loadtxt`, bit for bit); else it is read with `np.loadtxt`. There,
    with columns besides `columns`, a vectorised check of the body's bytes that every row has
    the header's number of fields (`_uniform_rows`) lets `np.loadtxt` convert the named columns
    only (the others are split off, never parsed); otherwise (no other column, a quoted field,
    blank lines, a malformed row) every column is read, and a malformed row is located and
    named. A header naming one of `columns` twice is a `ValueError` (which of the two was meant
    is not known). Blank lines are skipped; rows count from 1 after the header, blank lines not
    counted.
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
        ext = _csvc()
        # With every column used, loadtxt of the whole table checks the field counts itself.
        body = None if len(header) == len(columns) and ext is None else _body_bytes(path, head)
        if body is not None and ext is not None:
            table = _parse_body(ext, body, len(header), idx)
            if table is not None:
                return table
            body = None if len(header) == len(columns) else body
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


def _body_bytes(path: str, head: str) -> bytearray | None:
    """The bytes of the CSV file `path` after its header line `head` (as the text reader read
    it: a byte-order mark and blank lines before it skipped), or `None` when the header is not
    a `\\n`-terminated line there (the slow route then reads the file)."""
    with open(path, "rb") as raw:
        data = bytearray(os.fstat(raw.fileno()).st_size)
        del data[raw.readinto(data):]  # a file that shrank meanwhile
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
    del data[:pos]  # in place: a bytearray drops its head without copying the rest
    return data


def _csvc() -> Any:
    """The compiled CSV reader and writer (`jaxshadow._io._csvc`, `csrc/csvtext.c`), or `None`
    when it is not built (the Python routes then do the same work)."""
    try:
        from . import _csvc as mod  # type: ignore[attr-defined]
    except ImportError:
        return None
    return mod


def _parse_body(ext: Any, body: bytearray, ncols: int, idx: list[int]) -> np.ndarray | None:
    """Columns `idx` of the CSV rows `body` (bytes after the header; `ncols` fields a row) as an
    `(N, len(idx))` float64 array, parsed by the compiled reader `ext`; `None` when a row is not
    plain numbers (a quote, a blank line, a lone CR, a field count that changes, a field that
    is not a decimal number, inf or nan), for the caller's `np.loadtxt` route to read or name."""
    if b"\r" in body:
        body = body.replace(b"\r\n", b"\n")  # CRLF rows read as LF rows (a lone CR declines)
    if body and not body.endswith(b"\n"):
        body += b"\n"
    out = np.empty((body.count(b"\n"), len(idx)), np.float64)
    return out if ext.parse(body, ncols, idx, out) else None


CSV_CHECK_BYTES = 1 << 23  # the field-count check looks at this many bytes of rows at a time


def _uniform_rows(body: bytes | bytearray, ncols: int) -> bytes | bytearray | None:
    """`body` (CSV rows after the header, bytes; CRLF turned into LF) when every row has exactly
    `ncols` comma-separated fields and nothing needs the `csv` module (no quote, no blank line,
    no lone CR), else `None`. Vectorised: the commas between consecutive newlines are counted
    with `np.searchsorted`, a block of about `CSV_CHECK_BYTES` at a time (small index arrays),
    or in one pass by the compiled `_csvc.check_rows` when it is built."""
    if b'"' in body:
        return None
    if b"\r" in body:
        body = body.replace(b"\r\n", b"\n")
        if b"\r" in body:
            return None
    if body and not body.endswith(b"\n"):
        body += b"\n"
    ext = _csvc()
    if ext is not None:
        return body if ext.check_rows(body, ncols) >= 0 else None
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
    formatted once, as literal text of that block's row format. With the compiled writer
    (`jaxshadow._io._csvc`) built, the rows are formatted by it, with Python's own float
    formatting (`PyOS_double_to_string`): the same text.
    """
    arrays, fmts, n = _csv_columns(header, columns)
    fh.write(",".join(header) + "\n")
    ext = _csvc()
    for s in range(0, n, CSV_BLOCK_ROWS):
        if ext is not None:
            fh.write(ext.format(_block_values(arrays, s), _kinds(fmts), None).decode("ascii"))
        else:
            fh.write(_csv_block(arrays, fmts, s))


def _csv_columns(header: list[str], columns: list[Any]) -> tuple[list[np.ndarray], list[str], int]:
    """`write_csv_table`'s columns as 2-D arrays, their formats and the row count (checked)."""
    arrays = [np.asarray(c) for c in columns]
    arrays = [a.reshape(a.shape[0], int(np.prod(a.shape[1:], dtype=np.int64))) for a in arrays]  # (0, k) too
    n = arrays[0].shape[0] if arrays else 0
    if any(a.shape[0] != n for a in arrays):
        raise ValueError(f"write_csv_table: columns have different row counts {[a.shape[0] for a in arrays]}.")
    fmts = [("%.9g" if a.dtype == np.float32 else "%r") for a in arrays for _ in range(a.shape[1])]
    if len(fmts) != len(header):
        raise ValueError(f"write_csv_table: {len(header)} header names for {len(fmts)} columns.")
    return arrays, fmts, n


def _block_values(arrays: list[np.ndarray], s: int) -> np.ndarray:
    """Rows `s .. s + CSV_BLOCK_ROWS` of the columns side by side, float64, C order."""
    return np.ascontiguousarray(np.concatenate([a[s:s + CSV_BLOCK_ROWS].astype(np.float64) for a in arrays], axis=1))


def _kinds(fmts: list[str]) -> bytes:
    """`_csvc.format`'s kinds of the formats `fmts`: `g` for `"%.9g"`, `r` for `"%r"`."""
    return "".join("g" if f == "%.9g" else "r" for f in fmts).encode("ascii")


def _csv_block(arrays: list[np.ndarray], fmts: list[str], s: int) -> str:
    """The text of rows `s .. s + CSV_BLOCK_ROWS` (each ending in a newline)."""
    block = _block_values(arrays, s)
    # A column with one value in the whole block (a plane's height, a shared normal) is
    # formatted once and written as literal text of the row format.
    bits = block.view(np.int64)  # bit for bit: -0.0 is not 0.0
    same = (bits == bits[:1]).all(axis=0)
    fmt = [(f % float(block[0, j])).replace("%", "%%") if same[j] else f for j, f in enumerate(fmts)]
    row = ",".join(fmt) + "\n"
    return (row * block.shape[0]) % tuple(block[:, ~same].ravel().tolist())


def receiver_rows(path: str | os.PathLike) -> bytes | bytearray | None:
    """The data rows of the points CSV `path` as its own text (`\\n`-terminated lines, CRLF
    turned into LF), when they can stand for the receiver columns of an output table as they
    are: the header is exactly `px,py,pz,nx,ny,nz` (spaces around the names allowed), every row
    has six fields, and nothing needs the `csv` module (no quote, no blank line); else `None`.
    Row i of the text is receiver i of `read_points(path)`."""
    path = os.fspath(path)
    if extension(path) != ".csv":
        return None
    with open(path, encoding="utf-8-sig", newline="") as fh:
        head = fh.readline()
        while head and not head.strip():
            head = fh.readline()
    if '"' in head or tuple(h.strip() for h in head.split(",")) != POINT_COLUMNS:
        return None
    body = _body_bytes(path, head)
    return None if body is None else _uniform_rows(body, len(POINT_COLUMNS))


def write_values_beside_rows(path: str | os.PathLike, rows: bytes | bytearray, values: Any) -> None:
    """Write the `.csv` output of `write_values` with the receiver columns taken as text from
    `rows` (`receiver_rows` of the points file: one line per receiver, `px,...,nz`) instead of
    formatted again: the same table (header `px,py,pz,nx,ny,nz,r,g,b`, the receivers exactly as
    the input gave them), about half the time of formatting all nine columns. The compiled
    writer (`jaxshadow._io._csvc`), when built, joins each row's text and its values (the same
    bytes as the Python route)."""
    path = os.fspath(path)
    v = np.asarray(values)
    view = np.frombuffer(rows, np.uint8)  # newlines found a window at a time: no (len,) temporary
    ends = np.concatenate([np.flatnonzero(view[a:a + CSV_CHECK_BYTES] == 10) + a
                           for a in range(0, len(view), CSV_CHECK_BYTES)] or [np.zeros(0, np.intp)])
    if v.ndim != 2 or v.shape[1] != 3 or len(ends) != v.shape[0]:
        raise ValueError(f"{path}: {len(ends)} receiver rows for values of shape {v.shape}.")
    arrays, fmts, n = _csv_columns(["r", "g", "b"], [v])
    ext = _csvc()
    if ext is not None:
        with atomic_write(path, "wb") as fb, memoryview(rows) as mv:
            fb.write((",".join([*POINT_COLUMNS, "r", "g", "b"]) + "\n").encode("utf-8"))
            for s in range(0, n, CSV_BLOCK_ROWS):
                e = min(n, s + CSV_BLOCK_ROWS)
                fb.write(ext.format(_block_values(arrays, s), _kinds(fmts), mv[0 if s == 0 else ends[s - 1] + 1:ends[e - 1] + 1]))
        return
    with atomic_write(path, "w", newline="") as fh:
        fh.write(",".join([*POINT_COLUMNS, "r", "g", "b"]) + "\n")
        for s in range(0, n, CSV_BLOCK_ROWS):
            e = min(n, s + CSV_BLOCK_ROWS)
            lead = rows[0 if s == 0 else ends[s - 1] + 1:ends[e - 1]].decode("utf-8").split("\n")
            tail = _csv_block(arrays, fmts, s).split("\n")
            fh.write("\n".join(map(",".join, zip(lead, tail, strict=False))))
            fh.write("\n")


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
