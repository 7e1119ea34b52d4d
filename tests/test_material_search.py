"""The material fit's exponent search (`inverse._material._section_search`): batched section steps."""

import math

import numpy as np
import pytest

from inverse._material import SPEC_CHUNK, _section_search


@pytest.mark.parametrize("x_min", [0.2, 0.31415, 0.0, 1.0])
def test_section_search_finds_the_minimum_of_a_unimodal_function_within_tol(x_min):
    calls = []

    def f(xs):
        calls.append(np.asarray(xs).copy())
        return [(x - x_min) ** 2 + 0.1 * abs(x - x_min) for x in xs]  # unimodal, kinked at x_min

    a, b, tol = 0.0, 1.0, 1e-6
    x = _section_search(f, a, b, f([a])[0], f([b])[0], 0.5, f([0.5])[0], tol)
    calls = calls[3:]
    assert abs(x - x_min) <= tol
    assert all(len(c) == SPEC_CHUNK for c in calls)  # one batch of the compiled program per step
    # the bracket shrinks by (SPEC_CHUNK + 1) / 2 per step
    assert len(calls) <= math.ceil(math.log((b - a) / tol) / math.log((SPEC_CHUNK + 1) / 2))


def test_section_search_returns_the_known_point_when_it_is_lowest():
    # a flat function: nothing evaluated is lower than the point already known, which is kept
    x = _section_search(lambda xs: [1.0] * len(xs), 0.0, 1.0, 1.0, 1.0, 0.5, 1.0, 1e-3)
    assert x == 0.5
