"""Test configuration: float64 available everywhere (float32 tests pass float32 arrays; dtype
follows the inputs), rank promotion is an error, and a fixed set of dtypes to parametrise over."""

import os

os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


@pytest.fixture(params=["float32", "float64"])
def dtype(request):
    import numpy as np

    return np.dtype(request.param)
