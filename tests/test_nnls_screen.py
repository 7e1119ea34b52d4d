"""The global placement's batched screens (`inverse._nnls_screen`): `nnls_rss` against
`scipy.optimize.nnls` per candidate (candidates whose normal equations give negative powers
included), and `ScreenMemo`'s kept scores against fresh screens after its columns grew."""

import numpy as np
import pytest
from scipy.optimize import nnls

import inverse._nnls_screen as nnls_screen
from inverse._nnls_screen import SUPPORTS_UP_TO, ScreenMemo, nnls_rss, pair_rss


def _columns(rng, n, m):
    """`n` candidate columns of length `m`: non-negative, some nearly parallel to others."""
    c = np.abs(rng.normal(size=(n, m)))
    c[1::3] = c[::3][: c[1::3].shape[0]] + 0.05 * rng.normal(size=(c[1::3].shape[0], m))
    return c


@pytest.mark.parametrize("held", [0, 1, 2, SUPPORTS_UP_TO + 1])
def test_nnls_rss_is_nnls_per_candidate(held):
    rng = np.random.default_rng(held)
    M = 40
    fixed = np.abs(rng.normal(size=(M, held)))
    cand = _columns(rng, 60, M)
    # targets a mix with a negative weight on a held column: many candidates' normal equations
    # give a negative power, so the non-negative solve decides
    y = cand[7] + (fixed @ np.linspace(-0.8, 1.0, held) if held else 0.0) + 0.05 * rng.normal(size=M)
    cand[11, 3] = np.nan
    got = nnls_rss(fixed, cand, y, True)
    for s in range(cand.shape[0]):
        if s == 11:
            assert got[s] == np.inf
            continue
        want = nnls(np.c_[fixed, cand[s]], y)[1] ** 2
        assert got[s] == pytest.approx(want, rel=1e-9, abs=1e-12 * float(y @ y))


def test_nnls_rss_exact_fit_and_zero_column():
    rng = np.random.default_rng(5)
    M = 30
    fixed = np.abs(rng.normal(size=(M, 2)))
    cand = _columns(rng, 10, M)
    cand[4] = 0.0  # a candidate that lights nothing: its power 0, the held columns' fit
    y = fixed @ np.array([0.5, 2.0]) + 3.0 * cand[2]
    got = nnls_rss(fixed, cand, y, True)
    assert got[2] <= 1e-20 * float(y @ y)
    assert got[4] == pytest.approx(nnls(fixed, y)[1] ** 2, rel=1e-9)


def test_screen_memo_matches_fresh_screens_as_columns_grow():
    rng = np.random.default_rng(9)
    M = 36
    cols = [_columns(rng, 50, M), _columns(rng, 40, M), _columns(rng, 30, M)]
    y = 1.5 * cols[0][3] + 0.7 * cols[1][8] + 0.4 * cols[2][1] + 0.01 * rng.normal(size=M)
    memo = ScreenMemo(y, True)
    chosen = {0: 3, 1: 8, 2: 1}
    first = memo.rss(cols, 0, chosen).copy()
    assert np.array_equal(first, nnls_rss(np.stack([cols[1][8], cols[2][1]], axis=1), cols[0], y, True))
    cols[0] = np.concatenate([cols[0], _columns(rng, 17, M)])  # light 0's candidates grow
    grown = memo.rss(cols, 0, chosen)
    fresh = nnls_rss(np.stack([cols[1][8], cols[2][1]], axis=1), cols[0], y, True)
    assert grown.shape == (67,)
    np.testing.assert_allclose(grown, fresh, rtol=1e-12, atol=1e-14 * float(y @ y))
    other = memo.rss(cols, 0, {0: 0, 1: 9, 2: 1})  # another held light: another screen
    np.testing.assert_allclose(other, nnls_rss(np.stack([cols[1][9], cols[2][1]], axis=1), cols[0], y, True),
                               rtol=1e-12, atol=1e-14 * float(y @ y))
    assert memo.pair(cols, 0, 1, chosen) == pair_rss(cols[2][1][:, None], cols[0], cols[1], y, True)
    cols[1] = np.concatenate([cols[1], cols[1][8][None] * 1.01])
    assert memo.pair(cols, 0, 1, chosen) == pair_rss(cols[2][1][:, None], cols[0], cols[1], y, True)


@pytest.mark.parametrize("held", [0, 2])
def test_pair_rss_is_the_best_pair_by_nnls(held, monkeypatch):
    """`pair_rss` against every pair's non-negative least squares (`scipy.optimize.nnls` on the
    pair's columns with the held columns' span projected out), for tiles of the cross Gram from
    one element to the whole block: the same pair at every tile size, its rss the least."""
    rng = np.random.default_rng(7 + held)
    M = 24
    ca, cb = _columns(rng, 37, M), _columns(rng, 29, M)
    cb[5] = cb[3]  # duplicate columns: tied scores
    ca[11] = np.nan  # a candidate whose column is not finite: scored -inf
    fixed = _columns(rng, held, M).T
    y = ca[4] * 1.3 + cb[20] * 0.7 + (fixed.sum(axis=1) if held else 0.0) + 0.01 * rng.normal(size=M)
    q = np.linalg.qr(fixed)[0] if held else np.zeros((M, 0))
    P = np.eye(M) - q @ q.T
    ref = np.full((37, 29), np.inf)
    for s in range(37):
        for t in range(29):
            if np.all(np.isfinite(ca[s])):
                ref[s, t] = nnls(P @ np.stack([ca[s], cb[t]], axis=1), P @ y)[1] ** 2
    out = []
    for tile in (1, 7, 1 << 15):
        monkeypatch.setattr(nnls_screen, "PAIR_TILE", tile)
        out.append(pair_rss(fixed, ca, cb, y, True, block=16))
    assert out[0] == out[1] == out[2]
    f, s, t = out[0]
    assert (s, t) == (4, 20)
    np.testing.assert_allclose(f, ref.min(), rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(ref[s, t], ref.min(), rtol=1e-9, atol=1e-12)
