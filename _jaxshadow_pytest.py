"""pytest plugin of `jaxshadow.testing` (registered as the `pytest11` entry point `jaxshadow`;
disable with `-p no:jaxshadow`).

A top-level module of its own, outside the `jaxshadow` package (as `_hypothesis_pytestplugin`
is outside `hypothesis`): pytest imports every entry-point plugin before the test run starts, and
importing `jaxshadow` then would defeat import hooks that must see it first (jaxtyping's runtime
checks, coverage). It imports `jaxshadow.testing` only when a fixture is used.

- Fixture `jaxshadow_catalogue` (session): the `jaxshadow.testing.catalogue` mapping.
- Fixture `jaxshadow_reference`: one `ReferenceScene`; a test that asks for it runs once per
  catalogue scene, or once per scene named by the marker
  `@pytest.mark.jaxshadow_scenes("penumbra", "umbra")`.
- Fixture `jaxshadow_alpha`: the family-wise false-alarm rate to pass to the assertions
  (option `--jaxshadow-alpha`, default 1e-3).
"""

from __future__ import annotations

from typing import Any

import pytest

__all__ = [
    "jaxshadow_alpha",
    "jaxshadow_catalogue",
    "jaxshadow_reference",
    "pytest_addoption",
    "pytest_configure",
    "pytest_generate_tests",
]

MARKER = "jaxshadow_scenes"
SCENES = ("unoccluded", "penumbra", "umbra", "touching", "grazing", "highlight", "linear", "mesh")


def pytest_addoption(parser: Any) -> None:
    group = parser.getgroup("jaxshadow", "jaxshadow gradient oracle")
    group.addoption(
        "--jaxshadow-alpha",
        action="store",
        type=float,
        default=1e-3,
        help="family-wise false-alarm rate for jaxshadow.testing comparisons (default 1e-3)",
    )


def pytest_configure(config: Any) -> None:
    config.addinivalue_line(
        "markers",
        f"{MARKER}(*names): run a test that uses the jaxshadow_reference fixture on these "
        f"catalogue scenes only (default: all of {', '.join(SCENES)})",
    )


def pytest_generate_tests(metafunc: Any) -> None:
    if "jaxshadow_reference" not in metafunc.fixturenames:
        return
    names: list[str] = []
    for mark in metafunc.definition.iter_markers(MARKER):
        names.extend(mark.args)
    unknown = [n for n in names if n not in SCENES]
    if unknown:
        raise pytest.UsageError(f"@pytest.mark.{MARKER}: unknown scene(s) {unknown}; known: {list(SCENES)}")
    metafunc.parametrize("jaxshadow_reference", names or list(SCENES), indirect=True, ids=str)


@pytest.fixture(scope="session")
def jaxshadow_catalogue() -> Any:
    """The catalogue of reference scenes (`jaxshadow.testing.catalogue`)."""
    from jaxshadow.testing import catalogue

    return catalogue


@pytest.fixture
def jaxshadow_reference(request: Any, jaxshadow_catalogue: Any) -> Any:
    """One catalogue scene (`jaxshadow.testing.ReferenceScene`), parametrised by name."""
    return jaxshadow_catalogue[request.param]


@pytest.fixture
def jaxshadow_alpha(request: Any) -> float:
    """The family-wise false-alarm rate from `--jaxshadow-alpha`."""
    # The default also serves a conftest that imports these fixtures after option parsing.
    return float(request.config.getoption("--jaxshadow-alpha", default=1e-3))
