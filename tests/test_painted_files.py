"""Painted targets saved and loaded with their colour ranges and "brighter than" relations
(`inverse.save_painted` / `load_painted`): JSON and CSV round trips, one-sided ranges, errors."""

import json

import numpy as np
import pytest

import inverse


def _painted():
    rng = np.random.default_rng(3)
    n = 6
    t = inverse.PaintedTargets(rng.uniform(-1, 1, (n, 3)), np.tile([0.0, 0.0, 1.0], (n, 1)),
                               rng.uniform(0, 1, (n, 3)), [0.0, -3.0, 2.0], weights=rng.uniform(0.5, 2, (n, 3)))
    ranges = inverse.ColourRange([1, 4], [[0.1, 0.2, 0.3], [0.5, -np.inf, 0.0]],
                                 [[0.2, 0.3, 0.4], [np.inf, 0.7, 0.25]])
    rel = inverse.Brighter([[0, 5], [2, 3], [4, 1]], weight=[1.0, 2.5, 0.0], margin=[0.0, 0.01, 0.125])
    return t, ranges, rel


@pytest.mark.parametrize("ext", ["json", "csv"])
def test_round_trip(tmp_path, ext):
    t, ranges, rel = _painted()
    path = tmp_path / f"painted.{ext}"
    inverse.save_painted(path, t, ranges, rel)
    t2, r2, b2 = inverse.load_painted(path)
    for f in ("points", "normals", "colours", "eye", "weights"):
        np.testing.assert_array_equal(np.asarray(getattr(t2, f)), np.asarray(getattr(t, f)))
    np.testing.assert_array_equal(r2.index, ranges.index)
    np.testing.assert_array_equal(r2.lower, ranges.lower)  # -inf kept
    np.testing.assert_array_equal(r2.upper, ranges.upper)  # +inf kept
    for f in ("pairs", "weight", "margin"):
        np.testing.assert_array_equal(getattr(b2, f), getattr(rel, f))


@pytest.mark.parametrize("ext", ["json", "csv"])
def test_without_painting_reads_as_plain_targets(tmp_path, ext):
    t, _, _ = _painted()
    path = tmp_path / f"plain.{ext}"
    inverse.save_painted(path, t)
    t2, r2, b2 = inverse.load_painted(path)
    assert r2 is None and b2 is None
    np.testing.assert_array_equal(np.asarray(t2.colours), np.asarray(t.colours))
    # and the targets' own reader reads it
    np.testing.assert_array_equal(np.asarray(inverse.PaintedTargets.load(path).points), np.asarray(t.points))


def test_json_is_strict_and_errors_are_clear(tmp_path):
    t, ranges, rel = _painted()
    path = tmp_path / "p.json"
    inverse.save_painted(path, t, ranges, rel)
    d = json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"non-standard JSON constant {c}"))
    assert d["ranges"]["lower"][1][1] is None
    with pytest.raises(ValueError, match="out of range|index"):
        inverse.save_painted(tmp_path / "bad.json", t, inverse.ColourRange([9], 0.0, 1.0))
    assert not (tmp_path / "bad.json").exists()
    bad = tmp_path / "bad.csv"
    inverse.save_painted(bad, t, None, rel)
    bad.write_text(bad.read_text().replace("i,j,weight,margin", "a,b,c,d"))
    with pytest.raises(ValueError, match="relations' header"):
        inverse.load_painted(bad)
