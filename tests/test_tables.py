"""Point and value tables in and out (`jaxshadow._io.tables`) at array speed: the CSV reader's
fast route (a vectorised field-count check, then `np.loadtxt` of the named columns) and the block
writer's constant columns, checked against references that do not go through the code under test
(NumPy's parser on the whole table, Python's own per-value formatting). The compiled reader and
writer (`jaxshadow._io._csvc`) against the same references, and the CSV tests run on both routes
(`csv_route`: the compiled one, and the Python one with the module hidden)."""

import io
import os

import numpy as np
import pytest

import jaxshadow as js
from jaxshadow._io import tables as _tables
from jaxshadow._io.tables import POINT_COLUMNS, read_csv, write_csv_table


@pytest.fixture(params=["compiled", "python"])
def csv_route(request, monkeypatch):
    """Run a CSV test through the compiled reader/writer, then with it hidden (the Python route)."""
    if request.param == "compiled":
        if _tables._csvc() is None:
            pytest.skip("jaxshadow._io._csvc is not built")
    else:
        monkeypatch.setattr(_tables, "_csvc", lambda: None)
    return request.param



@pytest.mark.usefixtures("csv_route")
def test_csv_duplicated_column_is_an_error(tmp_path):
    # Two 'px' columns: which one is meant is unknown, so neither is taken silently.
    (tmp_path / "dup.csv").write_text("px,py,pz,nx,ny,nz,px\n0,0,0,0,0,1,5\n")
    with pytest.raises(ValueError, match=r"\['px'\] appear more than once"):
        js.read_points(tmp_path / "dup.csv")
    # a repeated name among the ignored columns does not matter
    (tmp_path / "extra.csv").write_text("w,px,py,pz,nx,ny,nz,w\n9,1,2,3,0,0,1,8\n")
    np.testing.assert_array_equal(js.read_points(tmp_path / "extra.csv")[0], [[1.0, 2.0, 3.0]])


@pytest.mark.usefixtures("csv_route")
def test_csv_columns_by_name_with_text_and_blank_lines(tmp_path):
    # Columns in any order, an ignored text column with a quoted comma, CRLF and blank lines.
    text = ('label,nz,ny,nx,pz,py,px\r\n"a,b",1,0,0,3,2,1\r\n\r\nc,0,1,0,6,5,4\r\n')
    (tmp_path / "t.csv").write_bytes(text.encode())
    p, n, _ = js.read_points(tmp_path / "t.csv")
    np.testing.assert_array_equal(p, [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    np.testing.assert_array_equal(n, [[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])


@pytest.mark.parametrize(("body", "message"), [
    ("1,2,3,0,0,1\n4,5,6,0,0\n", "row 2 has 5 fields, the header has 6"),
    ("1,2,3,0,0,1\n\n4,5,6,0,0,1,7\n", "row 2 has 7 fields, the header has 6"),
    ("1,2,3,0,0,1\n4,x,6,0,0,1\n", r"row 2 has a non-numeric value"),
    ("1,2,3,0,0,1\n4,,6,0,0,1\n", r"row 2 has a non-numeric value"),
])
@pytest.mark.usefixtures("csv_route")
def test_csv_bad_rows_are_named(tmp_path, body, message):
    (tmp_path / "bad.csv").write_text("px,py,pz,nx,ny,nz\n" + body)
    with pytest.raises(ValueError, match=message):
        js.read_points(tmp_path / "bad.csv")


@pytest.mark.usefixtures("csv_route")
def test_csv_header_without_rows_has_no_points(tmp_path):
    (tmp_path / "h.csv").write_text("px,py,pz,nx,ny,nz\n")
    with pytest.raises(ValueError, match="no points"):
        js.read_points(tmp_path / "h.csv")


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
@pytest.mark.usefixtures("csv_route")
def test_fast_route_reads_named_columns_exactly(tmp_path, monkeypatch, newline):
    # Columns in another order, two ignored columns, several check blocks, a BOM: exactly what
    # NumPy reads from the whole table, and the fast route is the one taken.
    monkeypatch.setattr(_tables, "CSV_CHECK_BYTES", 4096)
    rng = np.random.default_rng(5)
    header = ["w", "nz", "px", "ny", "pz", "u", "nx", "py"]
    text = _table_text(rng, 3000, header, newline)
    path = tmp_path / "t.csv"
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    body = text.encode().split(newline.encode(), 1)[1]
    assert _tables._uniform_rows(body, len(header)) is not None
    np.testing.assert_array_equal(read_csv(path, POINT_COLUMNS), _reference_columns(text, POINT_COLUMNS))
    p, n, _ = js.read_points(path)
    np.testing.assert_array_equal(np.c_[p, n], _reference_columns(text, POINT_COLUMNS))


@pytest.mark.usefixtures("csv_route")
def test_text_in_an_ignored_column_is_read_on_the_fast_route(tmp_path):
    text = "label,px,py,pz,nx,ny,nz\nfloor,1,2,3,0,0,1\nwall,4,5,6,1,0,0\n"
    (tmp_path / "t.csv").write_text(text)
    assert _tables._uniform_rows(text.encode().split(b"\n", 1)[1], 7) is not None
    np.testing.assert_array_equal(read_csv(tmp_path / "t.csv", POINT_COLUMNS),
                                  [[1, 2, 3, 0, 0, 1], [4, 5, 6, 1, 0, 0]])


@pytest.mark.parametrize(("bad", "message"), [
    ("1,2,3,0,0,1,7,8", "row 1235 has 8 fields, the header has 7"),   # an extra field, past the columns read
    ("1,2,3,0,0,1,7,", "row 1235 has 8 fields, the header has 7"),    # a trailing comma
    ("1,2,3,0,0,1", "row 1235 has 6 fields, the header has 7"),       # a missing ignored field
    ("1,2,x,0,0,1,7", r"row 1235 has a non-numeric value"),
    ("1,2,3,0,0,1e,7", r"row 1235 has a non-numeric value"),
])
@pytest.mark.usefixtures("csv_route")
def test_a_bad_row_deep_in_the_file_is_named(tmp_path, monkeypatch, bad, message):
    monkeypatch.setattr(_tables, "CSV_CHECK_BYTES", 512)
    rows = ["1,2,3,0,0,1,7"] * 3000
    rows[1234] = bad
    (tmp_path / "bad.csv").write_text("px,py,pz,nx,ny,nz,w\n" + "\n".join(rows) + "\n")
    with pytest.raises(ValueError, match=message):
        js.read_points(tmp_path / "bad.csv")


@pytest.mark.usefixtures("csv_route")
def test_no_trailing_newline_and_a_header_only_file(tmp_path):
    (tmp_path / "a.csv").write_text("px,py,pz,nx,ny,nz\n1,2,3,0,0,1\n4,5,6,0,1,0")
    np.testing.assert_array_equal(read_csv(tmp_path / "a.csv", POINT_COLUMNS), [[1, 2, 3, 0, 0, 1], [4, 5, 6, 0, 1, 0]])
    (tmp_path / "h.csv").write_text("px,py,pz,nx,ny,nz")
    assert read_csv(tmp_path / "h.csv", POINT_COLUMNS).shape == (0, 6)


def _per_value_text(header, table, fmts):
    """The CSV text with each value formatted on its own by Python (the reference layout)."""
    rows = [",".join(f % float(x) for f, x in zip(fmts, row, strict=True)) for row in table]
    return ",".join(header) + "\n" + "".join(r + "\n" for r in rows)


@pytest.mark.usefixtures("csv_route")
def test_constant_columns_are_written_as_each_value_would_be(monkeypatch):
    # A column constant in one block and varying in the next, -0.0 beside 0.0 (bit for bit
    # different), NaN and infinities in constant columns, float64 and float32 side by side.
    monkeypatch.setattr(_tables, "CSV_BLOCK_ROWS", 64)
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


@pytest.mark.usefixtures("csv_route")
def test_written_receivers_round_trip_through_the_reader(tmp_path):
    # The CLI's case: float32 points, normals and values, a plane's height and one normal.
    rng = np.random.default_rng(8)
    n = 2 * _tables.CSV_BLOCK_ROWS + 3
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


@pytest.mark.usefixtures("csv_route")
def test_a_table_without_rows_is_its_header(tmp_path):
    """No receivers: the file is the header line alone."""
    buf = io.StringIO()
    write_csv_table(buf, ["px", "py", "pz", "r"], [np.zeros((0, 3)), np.zeros((0,), np.float32)])
    assert buf.getvalue() == "px,py,pz,r\n"


@pytest.mark.usefixtures("csv_route")
def test_receiver_rows_only_for_plain_point_tables(tmp_path, monkeypatch):
    """`receiver_rows` gives a points CSV's rows as text only when they can stand for the output's
    receiver columns as they are (header exactly px..nz in order, six fields, no quote, no blank
    line); `write_values_beside_rows` refuses a row count that is not the value count."""
    from jaxshadow._io.tables import receiver_rows, write_values_beside_rows

    body = "0.5,0.25,0,0,0,1\n1e-3, 2 ,0,0,0,1\n"
    cases = {"plain.csv": ("px,py,pz,nx,ny,nz\n" + body, body.encode()),
             "bom_crlf.csv": ("\ufeffpx,py,pz,nx,ny,nz\r\n" + body.replace("\n", "\r\n"), body.encode()),
             "order.csv": ("py,px,pz,nx,ny,nz\n" + body, None),
             "extra.csv": ("px,py,pz,nx,ny,nz,label\n" + body.replace("\n", ",a\n"), None),
             "blank.csv": ("px,py,pz,nx,ny,nz\n" + body.replace("\n", "\n\n", 1), None),
             "quoted.csv": ('px,py,pz,nx,ny,nz\n"0.5",0.25,0,0,0,1\n', None)}
    for name, (text, want) in cases.items():
        (tmp_path / name).write_text(text, newline="")
        assert receiver_rows(tmp_path / name) == want, name
    assert receiver_rows(tmp_path / "x.npy") is None
    out = tmp_path / "o.csv"
    write_values_beside_rows(out, body.encode(), np.array([[1.0, 2.0, 3.0], [0.1, 0.2, 0.3]]))
    assert out.read_text() == "px,py,pz,nx,ny,nz,r,g,b\n0.5,0.25,0,0,0,1,1.0,2.0,3.0\n1e-3, 2 ,0,0,0,1,0.1,0.2,0.3\n"
    with pytest.raises(ValueError, match="2 receiver rows for values of shape"):
        write_values_beside_rows(out, body.encode(), np.zeros((3, 3)))
    # Blocks of 3 rows (the last one short) give the table of one block.
    rows = "".join(f"{i},{i / 7!r},0,0,0,1\n" for i in range(10)).encode()
    vals = np.random.default_rng(0).uniform(size=(10, 3)).astype(np.float32)
    write_values_beside_rows(out, rows, vals)
    whole = out.read_text()
    monkeypatch.setattr(_tables, "CSV_BLOCK_ROWS", 3)
    write_values_beside_rows(out, rows, vals)
    assert out.read_text() == whole and whole.count("\n") == 11
    got = np.loadtxt(out, delimiter=",", skiprows=1)
    np.testing.assert_array_equal(got[:, 6:].astype(np.float32), vals)


def test_points_and_their_rows_come_from_one_read(tmp_path, monkeypatch, csv_route):
    """`read_points_with_rows` (the `irradiance` command's CSV -> CSV input) gives
    `read_points`' receivers and `receiver_rows`' text, reading the file's rows once; the
    receivers are NumPy's parse of the file, not the reader's."""
    from jaxshadow._io.tables import read_points_with_rows, receiver_rows

    rng = np.random.default_rng(21)
    table = np.c_[rng.normal(size=(7, 3)), np.tile([0.0, 0.0, 1.0], (7, 1))]
    lines = [",".join(repr(float(x)) for x in row) for row in table]
    body = "\n".join(lines) + "\n"
    cases = {"plain.csv": "px,py,pz,nx,ny,nz\n" + body,
             "spaced_crlf.csv": "\ufeff px, py ,pz,nx,ny,nz\r\n" + body.replace(",", " , ").replace("\n", "\r\n"),
             "order.csv": "py,px,pz,nx,ny,nz\n" + body,
             "extra.csv": "px,py,pz,nx,ny,nz,label\n" + body.replace("\n", ",7\n"),
             "blank.csv": "px,py,pz,nx,ny,nz\n" + body.replace("\n", "\n\n", 1)}
    real = _tables._body_bytes
    calls: list = []

    def counted(*a):
        calls.append(a)
        return real(*a)

    for name, text in cases.items():
        path = tmp_path / name
        path.write_text(text, newline="")
        want_rows = receiver_rows(path)
        calls.clear()
        monkeypatch.setattr(_tables, "_body_bytes", counted)
        p, n, mesh, rows = read_points_with_rows(path)
        monkeypatch.setattr(_tables, "_body_bytes", real)
        assert len(calls) <= 1, name  # the rows' bytes are read once, for the table and the text
        assert rows == want_rows and mesh is None, name
        ref = np.loadtxt(path, delimiter=",", skiprows=1, encoding="utf-8-sig")
        if name == "order.csv":
            ref = ref[:, [1, 0, 2, 3, 4, 5]]
        np.testing.assert_array_equal(np.c_[p, n], ref[:, :6])
        q, m, _ = js.read_points(path)
        np.testing.assert_array_equal(np.c_[q, m], ref[:, :6])
        assert read_points_with_rows(path, rows=False)[3] is None
    assert receiver_rows(tmp_path / "plain.csv") is not None and receiver_rows(tmp_path / "order.csv") is None


# --------------------------------------------------------------------------------------
# The compiled reader and writer (jaxshadow._io._csvc) against NumPy's parser and Python's formatting
# --------------------------------------------------------------------------------------

def _ext():
    ext = _tables._csvc()
    if ext is None:
        pytest.skip("jaxshadow._io._csvc is not built")
    return ext


def _field_texts(rng) -> list[str]:
    """Number texts of every kind a table holds: float64 reprs over the whole exponent range
    (subnormals included), float32 texts ("%.9g"), other precisions and exponent styles,
    infinities and NaNs in any case and sign, signed zeros, a leading '+', blanks around."""
    x = rng.normal(size=400) * 10.0 ** rng.integers(-300, 300, 400)
    sub = rng.uniform(0, 1, 50) * 2.0 ** -1022  # float64 subnormals
    f32 = (rng.normal(size=200) * 10.0 ** rng.integers(-40, 38, 200)).astype(np.float32)
    texts = [repr(float(v)) for v in np.r_[x, sub]]
    texts += [f"{float(v):.9g}" for v in f32]
    texts += [f"{float(v):.17g}" for v in x[:50]] + [f"{float(v):.3E}" for v in x[50:100]]
    texts += [f"{float(v):.25f}" for v in rng.normal(size=20)]
    texts += ["inf", "-inf", "+inf", "Infinity", "-INFINITY", "InF", "nan", "-nan", "+NaN", "NAN",
              "-0", "+0", "-0.0", "0.0", "0", "+1.5", " 1.5", "2.5 ", " \t-3.25\t ", "1.", ".5", "-.5",
              "1E5", "1e+05", "1e-05", "1e-400", "-1e-400", "1e400", "-1e400", "00012", "1e0010",
              "4.9406564584124654e-324", "2.4703282292062328e-324", "2.4703282292062327e-324",
              "1.7976931348623157e308", "1.7976931348623158e308", "9007199254740993",
              "0.1000000000000000055511151231257827021181583404541015625", "3" * 60 + "e-40"]
    # Up to 17 digits, the point anywhere, powers of ten around the exact ones (1e22, 1e-22)
    for _ in range(600):
        nd = int(rng.integers(1, 18))
        digits = "".join(str(d) for d in rng.integers(0, 10, nd))
        cut = int(rng.integers(0, nd + 1))
        mant = (digits[:cut] + "." + digits[cut:]) if cut < nd else digits
        texts.append(mant + (f"e{int(rng.integers(-40, 41))}" if rng.uniform() < 0.7 else ""))
    return texts


@pytest.mark.parametrize("used", ["all", "some"])
def test_compiled_parser_reads_the_bits_loadtxt_reads(tmp_path, used):
    ext = _ext()
    rng = np.random.default_rng(11)
    fields = _field_texts(rng)
    k = 6 if used == "all" else 8
    fields += ["0"] * (-len(fields) % k)
    rng.shuffle(fields)
    body = "".join(",".join(fields[i:i + k]) + "\n" for i in range(0, len(fields), k))
    header = list(POINT_COLUMNS) if k == 6 else ["px", "w", "py", "pz", "nx", "u", "ny", "nz"]
    (tmp_path / "t.csv").write_text(",".join(header) + "\n" + body)
    idx = [header.index(c) for c in POINT_COLUMNS]
    want = np.loadtxt(io.StringIO(body), delimiter=",", ndmin=2)[:, idx]
    out = np.empty(want.shape)
    assert ext.parse(body.encode(), k, idx, out)  # the compiled route reads every field
    got = read_csv(tmp_path / "t.csv", POINT_COLUMNS)
    for a in (out, got):
        assert a.shape == want.shape
        np.testing.assert_array_equal(a.view(np.int64), want.view(np.int64))  # bit for bit, NaN's sign too


@pytest.mark.parametrize("field", ["0x1p3", "1_0", "nan(1)", "", " ", "1e", "1e+", "--1", "+-1", "1 2", "1.5f",
                                   "in", "infinit", "infinityy", "nana", ".", "e5", "1.2.3", "\v1", "١"])
def test_compiled_parser_declines_what_it_does_not_read(tmp_path, field):
    # A field the compiled reader does not take: parse says so, and read_csv gives what NumPy's
    # parser gives (a value, or the row named as non-numeric).
    ext = _ext()
    body = "1,2,3,0,0,1\n4," + field + ",6,0,0,1\n"
    assert not ext.parse(body.encode(), 6, list(range(6)), np.empty((2, 6)))
    (tmp_path / "t.csv").write_text("px,py,pz,nx,ny,nz\n" + body, encoding="utf-8")
    try:
        want = np.loadtxt(io.StringIO(body), delimiter=",", ndmin=2)
    except ValueError:
        # (the Python route's row check is float(), which takes '1_0' and Unicode digits: then
        # NumPy's own message names the field)
        with pytest.raises(ValueError, match=r"row 2 has a non-numeric value|could not convert string"):
            read_csv(tmp_path / "t.csv", POINT_COLUMNS)
    else:
        np.testing.assert_array_equal(read_csv(tmp_path / "t.csv", POINT_COLUMNS), want)


def test_compiled_parser_checks_shapes_and_row_ends():
    ext = _ext()
    out = np.empty((2, 3))
    assert ext.parse(b"1,2,3\n4,5,6\n", 3, [0, 1, 2], out) and out.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert not ext.parse(b"1,2,3\n4,5,6", 3, [0, 1, 2], out)         # no final newline
    assert not ext.parse(b"1,2,3\n4,5,6\n", 3, [0, 1, 2], np.empty((3, 3)))   # fewer rows than room
    assert not ext.parse(b"1,2,3\n4,5,6\n", 3, [0, 1, 2], np.empty((1, 3)))   # more rows than room
    assert not ext.parse(b"1,2,3\n4,5\n", 3, [0, 1, 2], out)
    assert not ext.parse(b"1,2,3\n4,5,6,7\n", 3, [0, 1, 2], out)
    assert not ext.parse(b"1,2,3\r\n4,5,6\n", 3, [0, 1, 2], out)
    with pytest.raises(ValueError):
        ext.parse(b"1,2,3\n", 3, [0, 0], np.empty((1, 2)))
    assert ext.check_rows(b"1,2\n3,4\n", 2) == 2 and ext.check_rows(b"", 2) == 0
    for bad in (b"1,2\n3\n", b"1,2\n\n", b'1,"2"\n', b"1,2\r\n", b"1,2"):
        assert ext.check_rows(bad, 2) == -1, bad


def _awkward_values(rng, n):
    """Values with every formatting case: subnormals (float64 and float32), zeros of both signs,
    1e-5 and 1e20 (where %g changes notation), infinities, NaN, the extremes of both precisions."""
    special = np.array([0.0, -0.0, 1e-5, 1e20, 1e16, 1e-4, 123456789.0, 0.1, np.inf, -np.inf, np.nan,
                        5e-324, -5e-324, 2.2250738585072014e-308, 1.7976931348623157e308,
                        float(np.float32(1e-45)), float(np.finfo(np.float32).max), float(np.finfo(np.float32).tiny)])
    x = rng.normal(size=(n, 3)) * 10.0 ** rng.integers(-320, 300, (n, 3))
    x.flat[rng.choice(x.size, len(special) * 4)] = np.tile(special, 4)
    return x


def test_compiled_writer_writes_python_s_text(tmp_path, monkeypatch):
    # Both kinds of column, every awkward value, blocks that end mid-table: byte for byte the
    # text of Python's own per-value formatting, and of the Python route.
    _ext()
    monkeypatch.setattr(_tables, "CSV_BLOCK_ROWS", 50)
    rng = np.random.default_rng(12)
    a64 = _awkward_values(rng, 173)
    with np.errstate(over="ignore"):
        a32 = _awkward_values(rng, 173).astype(np.float32)  # float32 subnormals, overflow to inf, zeros
    a32[::7, 1] = np.float32(1e-40)
    header = ["a", "b", "c", "d", "e", "f"]
    buf = io.StringIO()
    write_csv_table(buf, header, [a64, a32])
    want = _per_value_text(header, np.concatenate([a64, a32.astype(np.float64)], axis=1), ["%r"] * 3 + ["%.9g"] * 3)
    assert buf.getvalue() == want
    monkeypatch.setattr(_tables, "_csvc", lambda: None)
    slow = io.StringIO()
    write_csv_table(slow, header, [a64, a32])
    assert slow.getvalue() == want


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_compiled_writer_beside_rows_writes_the_python_route_s_bytes(tmp_path, monkeypatch, dtype):
    from jaxshadow._io.tables import write_values_beside_rows

    _ext()
    monkeypatch.setattr(_tables, "CSV_BLOCK_ROWS", 40)
    rng = np.random.default_rng(13)
    n = 101
    rows = "".join(f"{rng.normal()!r}, {i} ,0,-0,0,+1e0\n" for i in range(n)).encode()
    with np.errstate(over="ignore"):
        vals = _awkward_values(rng, n).astype(dtype)
    write_values_beside_rows(tmp_path / "c.csv", rows, vals)
    monkeypatch.setattr(_tables, "_csvc", lambda: None)
    write_values_beside_rows(tmp_path / "p.csv", rows, vals)
    fmt = "%.9g" if dtype == np.float32 else "%r"
    want = "px,py,pz,nx,ny,nz,r,g,b\n" + "".join(
        line + "," + ",".join(fmt % float(x) for x in v) + "\n"
        for line, v in zip(rows.decode().splitlines(), vals, strict=True))
    assert (tmp_path / "c.csv").read_bytes() == want.encode()
    assert (tmp_path / "p.csv").read_bytes() == want.encode()


_HIDDEN = """
import sys, numpy as np

class Block:
    def find_spec(self, name, path=None, target=None):
        if name == "jaxshadow._io._csvc":
            raise ImportError("blocked: the CSV module is not built")

sys.meta_path.insert(0, Block())
import jaxshadow as js
from jaxshadow._io import tables
assert tables._csvc() is None and "jaxshadow._io._csvc" not in sys.modules
folder = sys.argv[1]
p = np.array([[0.5, 0.25, 0.0], [1e-3, 2.0, -0.0]]); n = np.array([[0.0, 0.0, 1.0]] * 2)
js.write_values(folder + "/v.csv", np.float32([[1, 2, 3], [0.1, 0.2, 0.3]]), points=p, normals=n)
q, m, _ = js.read_points(folder + "/v.csv")
assert (q == p).all() and (m == n).all()
rows = tables.receiver_rows(folder + "/v.csv")
assert rows is None  # nine columns: not a points table's rows
print(open(folder + "/v.csv").read(), end="")
"""


def test_csv_without_the_compiled_module(tmp_path):
    # The module hidden from the import system (an install without a compiler): the same files
    # are read and written through NumPy and Python, and the text is the compiled route's.
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", _HIDDEN, str(tmp_path)], capture_output=True, text=True, env=env,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    p = np.array([[0.5, 0.25, 0.0], [1e-3, 2.0, -0.0]])
    n = np.array([[0.0, 0.0, 1.0]] * 2)
    js.write_values(tmp_path / "w.csv", np.float32([[1, 2, 3], [0.1, 0.2, 0.3]]), points=p, normals=n)
    assert r.stdout == (tmp_path / "w.csv").read_text()
