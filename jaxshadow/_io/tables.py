"""Point tables and value tables in and out: receivers from CSV / `.npy` / `.npz` (or a mesh, by
`jaxshadow._io.meshio`), irradiance values to CSV / `.npy` / `.npz` / PLY.

Point tables follow one convention for every command:

- `.csv`: a header row with named columns; `px, py, pz, nx, ny, nz` are required (other columns
  are ignored, so a targets CSV is also a points CSV); values written back get `r, g, b` columns.
- `.npy`: an `(N, 6)` array (points, then normals); `.npz`: arrays `points` and `normals`.
- `.ply` / `.obj` / `.glb` / `.gltf` / `.stl` / `.off`: a mesh, receivers at its vertices or faces.

CSV text is read and written at array speed by the compiled `jaxshadow._io._csvc` when it is
built (the same values and the same text as the Python routes). Every file is written through
`jaxshadow._core.files` (a temporary file renamed into place).
"""

from __future__ import annotations

import csv
import io
import os
import warnings
from typing import Any

import numpy as np

from .._core.files import atomic_write
from .._core.receivers import ReceiverMesh
from .meshio import IRRADIANCE_PROPERTY, MESH_EXTS, extension, read_mesh, write_ply

TABLE_EXTS = (".csv", ".npy", ".npz")
POINT_COLUMNS = ("px", "py", "pz", "nx", "ny", "nz")


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
    p, n, mesh, _ = read_points_with_rows(path, at, weld=weld, rows=False)
    return p, n, mesh


def read_points_with_rows(path: str | os.PathLike, at: str = "vertices", *, weld: float | None = 0.0,
                          rows: bool = True) -> tuple[np.ndarray, np.ndarray, ReceiverMesh | None,
                                                      bytes | bytearray | None]:
    """`read_points(path, at, weld=weld)` and, with `rows`, `receiver_rows(path)` from the same
    read of the file (the `irradiance` command's CSV -> CSV route): `(points, normals, mesh,
    rows)`, `rows` `None` unless the file is a plain points CSV (see `receiver_rows`)."""
    path = os.fspath(path)
    ext = extension(path)
    if ext in MESH_EXTS:
        mesh = read_mesh(path, weld=weld)
        p, n = mesh.receivers(at)
        return p, n, mesh, None
    if ext not in TABLE_EXTS:
        raise ValueError(f"{path}: unknown points format {ext or '(no extension)'!r} "
                         f"(expected one of {', '.join(TABLE_EXTS + MESH_EXTS)}).")
    if not os.path.isfile(path):
        raise FileNotFoundError(f"{path}: no such file.")
    text: bytes | bytearray | None = None
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
        table, text = _read_csv(path, POINT_COLUMNS, rows)
        p, n = table[:, :3], table[:, 3:]
    p, n = np.asarray(p, np.float64), np.asarray(n, np.float64)
    if p.shape[0] == 0:
        raise ValueError(f"{path}: no points.")
    if not (np.isfinite(p).all() and np.isfinite(n).all()):
        raise ValueError(f"{path}: points and normals must be finite.")
    return p, n, None, text


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
    return _read_csv(path, columns, False)[0]


def _read_csv(path: str | os.PathLike, columns: tuple[str, ...],
              rows: bool) -> tuple[np.ndarray, bytes | bytearray | None]:
    """`read_csv(path, columns)`, and with `rows` the file's `receiver_rows` from the same read
    (else `None`)."""
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
        keep = rows and _points_header(head)  # the rows are wanted as text too: the bytes are read
        # With every column used, loadtxt of the whole table checks the field counts itself.
        body = None if len(header) == len(columns) and ext is None and not keep else _body_bytes(path, head)
        if body is not None and ext is not None:
            table = _parse_body(ext, body, len(header), idx)
            if table is not None:
                return table, (_uniform_rows(body, len(header)) if keep else None)
            body = None if len(header) == len(columns) and not keep else body
        body = None if body is None else _uniform_rows(body, len(header))
        text = body if keep else None
        if body is not None:
            try:
                table = _loadtxt(io.BytesIO(body), usecols=idx)
            except ValueError:
                pass  # a non-numeric field: the slow route names its row
            else:
                return table.reshape(-1, len(columns)), text
        try:
            # Every column at once: loadtxt itself refuses rows whose field count changes.
            table = _loadtxt(fh)
        except ValueError:
            table = None
        if table is not None and table.size == 0:
            return np.empty((0, len(columns))), text
        if table is not None and table.shape[1] == len(header):
            return table[:, idx], text
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
    return table.reshape(-1, len(columns)), text


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
    if not _points_header(head):
        return None
    body = _body_bytes(path, head)
    return None if body is None else _uniform_rows(body, len(POINT_COLUMNS))


def _points_header(head: str) -> bool:
    """Whether the CSV header line `head` is exactly `px,py,pz,nx,ny,nz` (spaces around the names
    allowed, no quote): the rows under it can stand for an output table's receiver columns."""
    return '"' not in head and tuple(h.strip() for h in head.split(",")) == POINT_COLUMNS


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
