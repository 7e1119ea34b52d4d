"""The global placement's batched screens (`inverse._nnls_screen`): `nnls_rss` against
`scipy.optimize.nnls` per candidate (candidates whose normal equations give negative powers
included), and `ScreenMemo`'s kept scores against fresh screens after its columns grew."""

import numpy as np
import pytest
from scipy.optimize import nnls

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
