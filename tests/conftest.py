"""Test configuration: float64 available everywhere (float32 tests pass float32 arrays; dtype
follows the inputs), rank promotion is an error, and a fixed set of dtypes to parametrise over."""

import os

# XLA:CPU code-generator options for the test run: the legacy elemental emitter instead of the
# MLIR fusion emitters, and LLVM without its most expensive passes (the options of the fit
# programs, `inverse._lm.FIT_COMPILER_OPTIONS`). Most of a test's time is compiling: on 149 tests
# of test_clip, test_traced_both, test_spline and test_bad_input (`-n 0`, CPU time per test in
# one sitting) the run takes 155 CPU-s instead of 244 (0.64x). IEEE arithmetic either way; values
# differ by rounding. Users compile with XLA's defaults: tests/test_xla_flags.py compares
# representative kernels compiled both ways, and tests whose outcome depends on the options
# compile with `test_xla_flags.XLA_DEFAULTS` (test_plan's box touching the light, test_lm's
# reference for the fit options).
os.environ.setdefault("XLA_FLAGS", "--xla_force_host_platform_device_count=2 --xla_cpu_use_fusion_emitters=false "
                      "--xla_llvm_disable_expensive_passes=true")
# No persistent compilation cache by default (`jaxshadow._core.compile_cache`): tests that count
# compilations must see them, and a test run writes nothing to the home directory.
os.environ.setdefault("JAXSHADOW_COMPILE_CACHE", "off")

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# One persistent compilation cache for the xdist workers of one run (`pytest -n N`): a program
# that one worker compiled (>= SHARED_CACHE_MIN_S of compile time) is read from disk by the
# other (or by the same worker, for a program traced again from a new function object) instead
# of compiled again. A hit is the same XLA executable, so values are unchanged, and JAX reports
# it as a compilation all the same ("Finished XLA compilation" under `jax.log_compiles`, the
# `backend_compile_duration` event), so the tests that count compilations count the same. An
# entry read while the other worker writes it is a warning (ignored in pyproject.toml's
# filterwarnings) and the program is compiled. The directory is made by the controller, private
# to the run, and removed at its end. Off unless `JAXSHADOW_TEST_SHARED_CACHE=1`: its gain on the
# whole suite is not measured yet.
SHARED_CACHE_ENV = "JAXSHADOW_TEST_XLA_CACHE"
SHARED_CACHE_MIN_S = 1.0


def pytest_configure(config):
    import tempfile

    if os.environ.get("JAXSHADOW_TEST_SHARED_CACHE", "0") != "1":
        return
    if hasattr(config, "workerinput"):  # an xdist worker: use the controller's directory
        d = os.environ.get(SHARED_CACHE_ENV)
        if d and os.path.isdir(d):
            jax.config.update("jax_compilation_cache_dir", d)
            jax.config.update("jax_persistent_cache_min_compile_time_secs", SHARED_CACHE_MIN_S)
    elif (getattr(config.option, "numprocesses", None) or 0) and SHARED_CACHE_ENV not in os.environ:
        # The controller, before it starts the workers (they inherit the environment).
        os.environ[SHARED_CACHE_ENV] = tempfile.mkdtemp(prefix="jaxshadow-test-xla-")
        config._jaxshadow_shared_cache = os.environ[SHARED_CACHE_ENV]


def pytest_unconfigure(config):
    import shutil

    d = getattr(config, "_jaxshadow_shared_cache", None)
    if d:
        shutil.rmtree(d, ignore_errors=True)
        os.environ.pop(SHARED_CACHE_ENV, None)


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
