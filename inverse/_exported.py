"""Fit programs kept traced between processes (`jax.export`), beside JAX's persistent compilation cache.

With the persistent compilation cache warm, a light fit's first call in a fresh process still
traces its programs (the shadow engine, its linearisation, the LM loop) and lowers them to
StableHLO before the cache can find their executables: seconds of the fit. This module stores
each program of `_lm.fit_jit` once traced (`jax.export`, serialised) in the directory of the
compilation cache, under a key of everything the program was traced from: the function, the
structure of its arguments with their static values (fields of `equinox` modules marked static,
Python numbers, functions of `inverse` and `jaxshadow`), the shapes and dtypes of its arrays,
the compiler options, the versions of jax and jaxlib, and the contents of `inverse`'s and
`jaxshadow`'s sources and built extensions. A later process with the same key loads the
program and skips tracing and lowering; the executable itself comes from the compilation
cache, which the exported program fills the first time (every call runs the exported
program, so both processes compile the same module).

Arguments it cannot key exactly (a function from elsewhere, an object without a value-based
representation) or outputs that are not arrays leave the program to `equinox.filter_jit`, as
does `JAXSHADOW_EXPORT_CACHE=off`, or the absence of the `flatbuffers` package (which
`jax.export` serialises with; a dependency of jaxshadow, so the store is on wherever the
compilation cache is). The store holds code: private to the user like the compilation cache
(`jaxshadow.cli.enable_compile_cache`); like it, it is not size-limited (one file per program and
argument structure, a new one after any change of the sources, the engine or jax).
"""

from __future__ import annotations

import functools
import hashlib
import importlib.util
import os
import pathlib
import pickle
import re
from collections.abc import Callable
from typing import Any

import jax
import numpy as np

ENV = "JAXSHADOW_EXPORT_CACHE"
_SUBDIR = "jaxshadow-exported"
_OFF = ("0", "off", "no", "false")
# The XLA FFI targets of jaxshadow's engine (`csrc/ffi.h`): custom calls without jax's
# compatibility guarantee, which is not needed here (the key holds the engine's build).
ENGINE_TARGETS = ("jaxshadow_poly_codes", "jaxshadow_hard_visibility", "jaxshadow_segment_candidates",
                  "jaxshadow_segment_pieces")


class Unsupported(Exception):
    """The program's arguments or outputs cannot be keyed or exported exactly."""


def _option(name: str) -> Any:
    """JAX's configuration value `name` (its typing stubs do not list these options)."""
    return getattr(jax.config, name)


def store_dir() -> str | None:
    """The directory of exported programs: in JAX's persistent compilation cache directory, or
    None when that cache is off or `JAXSHADOW_EXPORT_CACHE` is `off`."""
    if os.environ.get(ENV, "").strip().lower() in _OFF:
        return None
    if importlib.util.find_spec("flatbuffers") is None:  # jax.export's serialisation needs it
        return None
    if not _option("jax_enable_compilation_cache"):
        return None
    d = _option("jax_compilation_cache_dir")
    return os.path.join(d, _SUBDIR) if d else None


def tree_digest(roots: list[pathlib.Path]) -> str:
    """sha256 of the `.py` sources and built extensions (`.so`, `.pyd`) under each of `roots`
    (their paths relative to the root, and their contents)."""
    h = hashlib.sha256()
    for root in roots:
        h.update(b"\0root\0")
        for p in sorted(root.rglob("*")):
            if p.suffix in (".py", ".so", ".pyd") and p.is_file():
                h.update(str(p.relative_to(root)).encode() + b"\0")
                h.update(hashlib.sha256(p.read_bytes()).digest())
    return h.hexdigest()


@functools.cache
def _sources_digest() -> str:
    """`tree_digest` of `inverse` and `jaxshadow` (the shadow engine's extension included): a
    program traced from other code is never loaded."""
    import inverse
    import jaxshadow

    return tree_digest([pathlib.Path(pkg.__file__).parent for pkg in (inverse, jaxshadow)])


_OURS = ("inverse", "jaxshadow")
_ADDRESS = re.compile(r" at 0x[0-9a-fA-F]+")


def _canonical(x: Any) -> Any:
    """A value-based, process-independent description of a static value; `Unsupported` where
    there is none."""
    if x is None or isinstance(x, (bool, int, float, str, bytes, complex)):
        return (type(x).__name__, repr(x))
    if isinstance(x, (tuple, list)):
        return (type(x).__name__, tuple(_canonical(v) for v in x))
    if isinstance(x, dict):
        return ("dict", tuple((repr(k), _canonical(v)) for k, v in sorted(x.items(), key=lambda kv: repr(kv[0]))))
    if isinstance(x, (np.dtype, type)):
        return ("type", f"{getattr(x, '__module__', '')}.{getattr(x, '__qualname__', repr(x))}")
    if isinstance(x, np.ndarray):
        return ("ndarray", x.dtype.str, x.shape, x.tobytes())
    if isinstance(x, np.generic):
        return ("npscalar", x.dtype.str, x.tobytes())
    if isinstance(x, functools.partial):
        return ("partial", _canonical(x.func), _canonical(x.args), _canonical(x.keywords))
    if callable(x):
        mod = getattr(x, "__module__", None) or ""
        name = getattr(x, "__qualname__", None) or ""
        if mod.split(".")[0] in _OURS and name and "<" not in name:
            return ("fn", f"{mod}.{name}")
        raise Unsupported(f"function {x!r}")
    text = repr(x)
    if _ADDRESS.search(text):
        raise Unsupported(f"object {type(x).__name__}")
    return ("repr", type(x).__module__, type(x).__qualname__, text)


def _treedef_key(treedef: Any) -> Any:
    """The structure of a pytree with its nodes' static data (equinox's static fields), canonical."""
    if treedef.num_nodes == 1 and treedef.num_leaves == 1:
        return "*"
    data = treedef.node_data()
    if data is None:
        return "*"
    kind, aux = data
    return (_canonical(kind), _canonical(aux), tuple(_treedef_key(c) for c in treedef.children()))


def _leaf_key(x: Any) -> Any:
    if isinstance(x, jax.Array) or isinstance(x, np.ndarray):
        return ("array", tuple(x.shape), str(x.dtype), bool(getattr(x, "weak_type", False)))
    return _canonical(x)


def _jaxlib_version() -> str:
    import jaxlib.version

    return str(jaxlib.version.__version__)


def program_key(fun: Callable, options: dict, args: tuple, kwargs: dict) -> tuple[str, list, Any, list[int]]:
    """`(key, leaves, treedef, array positions)` of a call: the sha256 key of everything the
    traced program depends on, the flattened arguments and where the arrays are among them."""
    if (getattr(fun, "__module__", "") or "").split(".")[0] not in _OURS or "<" in fun.__qualname__:
        raise Unsupported(f"{fun!r}: not a module-level function of inverse or jaxshadow (its code is not keyed)")
    leaves, treedef = jax.tree_util.tree_flatten((args, kwargs))
    arrays = [i for i, x in enumerate(leaves) if isinstance(x, (jax.Array, np.ndarray))]
    desc = (f"{fun.__module__}.{fun.__qualname__}", _canonical(options), _treedef_key(treedef),
            tuple(_leaf_key(x) for x in leaves), jax.__version__, _jaxlib_version(), bool(_option("jax_enable_x64")), jax.default_backend(),
            _sources_digest())
    return hashlib.sha256(pickle.dumps(desc)).hexdigest(), leaves, treedef, arrays


class ExportedProgram:
    """One exported program and the structure of its outputs; `__call__(arrays)` runs it compiled
    with `options` (through the persistent compilation cache)."""

    def __init__(self, exported: Any, out_tree: Any, options: dict, name: str):
        self.exported, self.out_tree, self.name = exported, out_tree, name

        def run(*arrays: Any) -> Any:
            return exported.call(*arrays)

        run.__name__ = run.__qualname__ = name  # the program's name in JAX's logs and monitoring
        self._jitted = jax.jit(run, compiler_options=options or None)

    def __call__(self, arrays: list) -> Any:
        return jax.tree_util.tree_unflatten(self.out_tree, self._jitted(*arrays))


def _check_plain(treedef: Any) -> None:
    """`Unsupported` unless the pytree structure is made of tuples, lists, dicts, None and named
    tuples only (what a stored structure can be rebuilt from in another process)."""
    if treedef.num_nodes == 1 and treedef.num_leaves == 1:
        return
    data = treedef.node_data()
    if data is not None:
        kind = data[0]
        plain = kind in (tuple, list, dict, type(None)) or (isinstance(kind, type) and issubclass(kind, tuple)
                                                           and hasattr(kind, "_fields"))
        if not plain:
            raise Unsupported(f"an output of type {getattr(kind, '__name__', kind)}")
    for c in treedef.children():
        _check_plain(c)


def export_program(fun: Callable, options: dict, leaves: list, treedef: Any, arrays: list[int]) -> ExportedProgram:
    """Trace `fun` on the call's arguments (arrays abstract, everything else as given) and export it."""
    from jax import export

    static = list(leaves)
    holder: dict = {}

    def flat(*arrs: Any) -> list:
        full = list(static)
        for i, a in zip(arrays, arrs, strict=True):
            full[i] = a
        args, kwargs = jax.tree_util.tree_unflatten(treedef, full)
        out_leaves, holder["out_tree"] = jax.tree_util.tree_flatten(fun(*args, **kwargs))
        for x in out_leaves:
            if not isinstance(x, jax.Array):
                raise Unsupported("an output that is not an array")
        _check_plain(holder["out_tree"])
        return out_leaves

    flat.__name__ = flat.__qualname__ = fun.__name__

    specs = [jax.ShapeDtypeStruct(np.shape(leaves[i]), jax.dtypes.result_type(leaves[i]),
                                  weak_type=bool(getattr(leaves[i], "weak_type", False))) for i in arrays]
    checks = [export.DisabledSafetyCheck.custom_call(t) for t in ENGINE_TARGETS]
    exp = export.export(jax.jit(flat), disabled_checks=checks)(*specs)
    return ExportedProgram(exp, holder["out_tree"], options, fun.__name__)


def save(path: str, prog: ExportedProgram) -> None:
    """Write `prog` to `path` (whole or not at all)."""
    from jaxshadow.files import atomic_write_path

    data = pickle.dumps({"exported": bytes(prog.exported.serialize()), "out_tree": prog.out_tree, "name": prog.name})
    os.makedirs(os.path.dirname(path), mode=0o700, exist_ok=True)
    atomic_write_path(path, lambda tmp: pathlib.Path(tmp).write_bytes(data))


def load(path: str, options: dict) -> ExportedProgram | None:
    """The program stored at `path`, or None (absent or unreadable)."""
    from jax import export

    try:
        data = pickle.loads(pathlib.Path(path).read_bytes())
        register_engine()
        return ExportedProgram(export.deserialize(bytearray(data["exported"])), data["out_tree"], options,
                               data["name"])
    except Exception:  # a partial or foreign file: trace again
        return None


def register_engine() -> None:
    """Register the shadow engine's XLA FFI handlers before a loaded program calls them: they
    are registered when a program holding the engine is first traced, and a loaded program is
    not traced (`jaxshadow.traced.register_engine`: nothing traced or compiled)."""
    from jaxshadow import traced

    traced.register_engine()
