"""JAX's persistent compilation cache for jaxshadow's programs.

Compiling is most of a fit's first call (issue 40): a light + material fit compiles five
programs that each hold the shadow engine. With JAX's persistent compilation cache a later
process loads them from disk instead. The `jaxshadow` command turns the cache on
(`--compile-cache DIR`, `--no-compile-cache`); the library's solvers (`inverse.fit_light`,
`fit_lights`, `fit_material`, `fit_light_and_material`) turn it on before their first compile
(`ensure_default_compile_cache`), unless the user configured or declined it:

- `jax_compilation_cache_dir` already set (by `jax.config.update`, or the environment variable
  `JAX_COMPILATION_CACHE_DIR`): JAX's own configuration is used as is;
- `jax_enable_compilation_cache` is False: no cache;
- the environment variable `JAXSHADOW_COMPILE_CACHE`: `0`, `off`, `no` or `false` turns the
  default off; any other value is the directory to use;
- otherwise `~/.cache/jaxshadow/xla` (created private to the user, mode 0700), storing programs
  that take at least `DEFAULT_MIN_COMPILE_S` to compile (or the minimum the user gave JAX,
  `jax_persistent_cache_min_compile_time_secs`, when it is not JAX's default of 1 s).

The cache is process-wide (JAX has one): once on, every program of the process that takes at
least that long to compile is stored. It holds executable code and must stay
private to the user (JAX's documentation); it is not size-limited (remove the directory to
clear it). A directory that cannot be created or written leaves the cache off, with no error.
"""

from __future__ import annotations

import os
import threading
from typing import Any

# Programs that compile in at least this long are written to the cache (JAX's default is 1 s;
# a light fit's small helper programs take 0.2-0.5 s).
DEFAULT_MIN_COMPILE_S = 0.2
ENV = "JAXSHADOW_COMPILE_CACHE"
_OFF = ("0", "off", "no", "false")

_lock = threading.Lock()
_state: dict = {"decided": False, "dir": None}


def default_cache_dir() -> str:
    """`$JAX_COMPILATION_CACHE_DIR`, else `~/.cache/jaxshadow/xla`."""
    return os.environ.get("JAX_COMPILATION_CACHE_DIR") or os.path.join(
        os.path.expanduser("~"), ".cache", "jaxshadow", "xla")


def enable_compile_cache(directory: str | None = None, min_compile_s: float = DEFAULT_MIN_COMPILE_S,
                         who: str = "compile cache") -> str:
    """Turn on JAX's persistent compilation cache in `directory` (default `default_cache_dir()`,
    created with mode 0700): programs that took >= `min_compile_s` seconds to compile are stored
    on disk and reused by later processes. Returns the directory. `PermissionError` (its
    message starting with `who`) when the directory cannot be created or written."""
    import jax

    d = directory or default_cache_dir()
    try:
        os.makedirs(d, mode=0o700, exist_ok=True)
    except OSError as err:
        raise PermissionError(f"{who}: cannot create {d!r} ({err.strerror})") from None
    if not os.access(d, os.W_OK):
        raise PermissionError(f"{who}: {d!r} is not writable")
    jax.config.update("jax_compilation_cache_dir", d)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(min_compile_s))
    return d


def ensure_default_compile_cache() -> str | None:
    """The library's default (module docstring), decided once per process: returns the cache
    directory in use, or None when there is none. Cheap after the first call."""
    if _state["decided"]:
        return _state["dir"]
    with _lock:
        if not _state["decided"]:
            _state["dir"] = _decide()
            _state["decided"] = True
    return _state["dir"]


def _option(name: str) -> Any:
    """JAX's configuration value `name` (its typing stubs do not list the cache's options)."""
    import jax

    return getattr(jax.config, name)


def _decide() -> str | None:
    own = _option("jax_compilation_cache_dir")
    if own:
        return str(own)
    if not _option("jax_enable_compilation_cache"):
        return None
    env = os.environ.get(ENV)
    if env is not None and env.strip().lower() in _OFF:
        return None
    # A minimum compile time the user set is kept (JAX's default is 1 s).
    least = float(_option("jax_persistent_cache_min_compile_time_secs"))
    try:
        return enable_compile_cache(env.strip() if env else None, DEFAULT_MIN_COMPILE_S if least == 1.0 else least)
    except PermissionError:
        return None


def decline_default_compile_cache() -> None:
    """No default cache in this process (`jaxshadow --no-compile-cache`): later calls of
    `ensure_default_compile_cache` leave JAX's configuration as it is."""
    with _lock:
        _state["decided"] = True
        _state["dir"] = None


def reset_default_compile_cache() -> None:
    """Forget the decision of `ensure_default_compile_cache` (tests)."""
    with _lock:
        _state["decided"] = False
        _state["dir"] = None
