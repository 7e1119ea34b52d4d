"""Test configuration: float64 available everywhere (float32 tests pass float32 arrays; dtype
follows the inputs), rank promotion is an error, and a fixed set of dtypes to parametrise over."""

import os

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")
# No persistent compilation cache by default (`jaxshadow._core.compile_cache`): tests that count
# compilations must see them, and a test run writes nothing to the home directory.
os.environ.setdefault("JAXSHADOW_COMPILE_CACHE", "off")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


@pytest.fixture(params=["float32", "float64"])
def dtype(request):
    import numpy as np

    return np.dtype(request.param)


# Every compiled XLA CPU program keeps ~6 memory mappings while JAX caches it, and a Linux
# process may hold `vm.max_map_count` (65 530 by default) of them: a test worker that compiles
# ~10 000 programs then fails inside the JIT ("Failed to materialize symbols", then a
# segmentation fault). Between test modules, a worker past MAP_BUDGET mappings drops JAX's
# caches (the programs a later module needs are compiled again).
MAP_BUDGET = 30_000


def _mappings() -> int:
    try:
        with open("/proc/self/maps", "rb") as fh:
            return sum(1 for _ in fh)
    except OSError:  # not Linux
        return 0


@pytest.fixture(autouse=True, scope="module")
def _bounded_mappings():
    yield
    if _mappings() > MAP_BUDGET:
        jax.clear_caches()
