"""Receiver tables at array speed: the CSV reader's fast route (a vectorised field-count check,
then `np.loadtxt` of the named columns) and the block writer's constant columns, checked against
references that do not go through the code under test (NumPy's parser on the whole table, Python's
own per-value formatting)."""

import io

import numpy as np
import pytest

import jaxshadow as js
from jaxshadow._io import meshio as _meshio
from jaxshadow._io.meshio import POINT_COLUMNS, read_csv, write_csv_table


def _reference_columns(text: str, columns) -> np.ndarray:
    """The named columns of an all-numeric CSV text, by NumPy's parser on every column."""
    lines = [line for line in text.splitlines() if line.strip()]
    header = lines[0].split(",")
    table = np.loadtxt(io.StringIO("\n".join(lines[1:])), delimiter=",", ndmin=2)
    return table[:, [header.index(c) for c in columns]]


def _table_text(rng, n, header, newline="\n"):
    cols = rng.normal(size=(n, len(header))) * 10.0 ** rng.integers(-20, 20, (n, len(header)))
    rows = [",".join(repr(float(x)) for x in row) for row in cols]
    return newline.join([",".join(header), *rows]) + newline


@pytest.mark.parametrize("newline", ["\n", "\r\n"])
def test_fast_route_reads_named_columns_exactly(tmp_path, monkeypatch, newline):
    # Columns in another order, two ignored columns, several check blocks, a BOM: exactly what
    # NumPy reads from the whole table, and the fast route is the one taken.
    monkeypatch.setattr(_meshio, "CSV_CHECK_BYTES", 4096)
    rng = np.random.default_rng(5)
    header = ["w", "nz", "px", "ny", "pz", "u", "nx", "py"]
    text = _table_text(rng, 3000, header, newline)
    path = tmp_path / "t.csv"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    body = text.encode().split(newline.encode(), 1)[1]
    assert _meshio._uniform_rows(body, len(header)) is not None
    np.testing.assert_array_equal(read_csv(path, POINT_COLUMNS), _reference_columns(text, POINT_COLUMNS))
    p, n, _ = js.read_points(path)
    np.testing.assert_array_equal(np.c_[p, n], _reference_columns(text, POINT_COLUMNS))


def test_text_in_an_ignored_column_is_read_on_the_fast_route(tmp_path):
    text = "label,px,py,pz,nx,ny,nz\nfloor,1,2,3,0,0,1\nwall,4,5,6,1,0,0\n"
    (tmp_path / "t.csv").write_text(text)
    assert _meshio._uniform_rows(text.encode().split(b"\n", 1)[1], 7) is not None
    np.testing.assert_array_equal(read_csv(tmp_path / "t.csv", POINT_COLUMNS),
                                  [[1, 2, 3, 0, 0, 1], [4, 5, 6, 1, 0, 0]])


@pytest.mark.parametrize(("bad", "message"), [
    ("1,2,3,0,0,1,7,8", "row 1235 has 8 fields, the header has 7"),   # an extra field, past the columns read
    ("1,2,3,0,0,1,7,", "row 1235 has 8 fields, the header has 7"),    # a trailing comma
    ("1,2,3,0,0,1", "row 1235 has 6 fields, the header has 7"),       # a missing ignored field
    ("1,2,x,0,0,1,7", r"row 1235 has a non-numeric value"),
    ("1,2,3,0,0,1e,7", r"row 1235 has a non-numeric value"),
])
def test_a_bad_row_deep_in_the_file_is_named(tmp_path, monkeypatch, bad, message):
    monkeypatch.setattr(_meshio, "CSV_CHECK_BYTES", 512)
    rows = ["1,2,3,0,0,1,7"] * 3000
    rows[1234] = bad
    (tmp_path / "bad.csv").write_text("px,py,pz,nx,ny,nz,w\n" + "\n".join(rows) + "\n")
    with pytest.raises(ValueError, match=message):
        js.read_points(tmp_path / "bad.csv")


def test_no_trailing_newline_and_a_header_only_file(tmp_path):
    (tmp_path / "a.csv").write_text("px,py,pz,nx,ny,nz\n1,2,3,0,0,1\n4,5,6,0,1,0")
    np.testing.assert_array_equal(read_csv(tmp_path / "a.csv", POINT_COLUMNS), [[1, 2, 3, 0, 0, 1], [4, 5, 6, 0, 1, 0]])
    (tmp_path / "h.csv").write_text("px,py,pz,nx,ny,nz")
    assert read_csv(tmp_path / "h.csv", POINT_COLUMNS).shape == (0, 6)


def _per_value_text(header, table, fmts):
    """The CSV text with each value formatted on its own by Python (the reference layout)."""
    rows = [",".join(f % float(x) for f, x in zip(fmts, row, strict=True)) for row in table]
    return ",".join(header) + "\n" + "".join(r + "\n" for r in rows)


def test_constant_columns_are_written_as_each_value_would_be(monkeypatch):
    # A column constant in one block and varying in the next, -0.0 beside 0.0 (bit for bit
    # different), NaN and infinities in constant columns, float64 and float32 side by side.
    monkeypatch.setattr(_meshio, "CSV_BLOCK_ROWS", 64)
    rng = np.random.default_rng(7)
    n = 64 * 3 + 5
    a64 = np.zeros((n, 4))
    a64[:, 0] = rng.normal(size=n)
    a64[64:, 1] = rng.normal(size=n - 64)          # constant (0.0) in the first block only
    a64[:, 2] = 0.0
    a64[100, 2] = -0.0                             # equal to 0.0, not the same bits
    a64[:, 3] = np.nan
    b32 = np.empty((n, 2), np.float32)
    b32[:, 0] = np.float32(1 / 3)
    b32[:, 1] = np.inf
    b32[70:, 1] = -np.inf
    header = ["a", "b", "c", "d", "e", "f"]
    buf = io.StringIO()
    write_csv_table(buf, header, [a64, b32])
    table = np.concatenate([a64, b32.astype(np.float64)], axis=1)
    assert buf.getvalue() == _per_value_text(header, table, ["%r"] * 4 + ["%.9g"] * 2)
    assert buf.getvalue().splitlines()[101].split(",")[2] == "-0.0"


def test_written_receivers_round_trip_through_the_reader(tmp_path):
    # The CLI's case: float32 points, normals and values, a plane's height and one normal.
    rng = np.random.default_rng(8)
    n = 2 * _meshio.CSV_BLOCK_ROWS + 3
    p = np.c_[rng.uniform(-1, 1, (n, 2)), np.full(n, 0.25)].astype(np.float32)
    nrm = np.tile(np.float32([0, 0, 1]), (n, 1))
    v = (rng.uniform(0, 5, (n, 3)) * 10.0 ** rng.integers(-30, 30, (n, 1))).astype(np.float32)
    js.write_values(tmp_path / "v.csv", v, points=p, normals=nrm)
    raw = np.loadtxt(tmp_path / "v.csv", delimiter=",", skiprows=1)
    np.testing.assert_array_equal(raw.astype(np.float32), np.c_[p, nrm, v])
    got_p, got_n, _ = js.read_points(tmp_path / "v.csv")
    np.testing.assert_array_equal(got_p.astype(np.float32), p)
    np.testing.assert_array_equal(got_n.astype(np.float32), nrm)
    np.testing.assert_array_equal(read_csv(tmp_path / "v.csv", ("r", "g", "b")).astype(np.float32), v)


def test_a_table_without_rows_is_its_header(tmp_path):
    """No receivers: the file is the header line alone."""
    buf = io.StringIO()
    write_csv_table(buf, ["px", "py", "pz", "r"], [np.zeros((0, 3)), np.zeros((0,), np.float32)])
    assert buf.getvalue() == "px,py,pz,r\n"
