"""The shadow engine's Python interface (`csrc/shadowc.cc`, one extension module): loading and
the polygon-plan call.

NumPy only (no JAX): `binding` binds the engine through this module, and a profiler can drive
the compiled module alone, loading this file by path, without importing the package
(`benchmarks/engine_profile.py` counts the engine's instructions under valgrind, where
importing JAX alone takes minutes).

The interface is defined once, in `csrc/abi.h`; the module exports it (`ABI_VERSION`,
`CODE_WIDTH`). `ABI_VERSION` and `CODE_WIDTH` here are the interface this file and `binding`
speak (`binding.decode_endpoints` reads the code layout of version 3): a module that exports
others (a stale build) is refused, not misread; `tests/test_binding.py` checks them against the
header.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
from typing import Any

import numpy as np

ABI_VERSION = 3
CODE_WIDTH = 7
MODULE = "jaxshadow._shadows._shadowc"


def check(mod: Any) -> str | None:
    """Why the module `mod` cannot be used (None when it can): not an extension module, or another ABI."""
    version = getattr(mod, "ABI_VERSION", None)
    if version is None or not hasattr(mod, "poly_plan"):
        return f"{getattr(mod, '__file__', mod)} is not the engine's extension module"
    if version != ABI_VERSION or getattr(mod, "CODE_WIDTH", None) != CODE_WIDTH:
        return (f"{mod.__file__} has ABI version {version} (code width {getattr(mod, 'CODE_WIDTH', None)}), "
                f"this jaxshadow speaks {ABI_VERSION} ({CODE_WIDTH}): a stale build")
    return None


def load(path: str) -> Any:
    """The engine's extension module built at `path` (any file name), or None for another ABI."""
    loader = importlib.machinery.ExtensionFileLoader(MODULE, path)
    spec = importlib.util.spec_from_file_location(MODULE, path, loader=loader)
    assert spec is not None
    mod = importlib.util.module_from_spec(spec)
    loader.exec_module(mod)
    return None if check(mod) else mod


def occluder_args(faces: np.ndarray, ints: list[np.ndarray], n_solids: int) -> tuple:
    """The occluders argument of every entry point: padded faces `(M, Ko, 3)` (contiguous, the
    call's float dtype) and the topology's contiguous int32 arrays `face_solid, face_closed,
    solid_faces (n_solids, 2), solid_edge_off, solid_edges` (`_core.mesh.OccluderTopology`)."""
    if ints[2].size != 2 * n_solids:
        raise ValueError(f"solid_faces has {ints[2].size // 2} solids, not {n_solids}")
    return (faces, *ints)


def poly_plan(lib: Any, p: np.ndarray, n: np.ndarray, v: np.ndarray, occ_args: tuple, threads: int, codes: bool,
              decoded: bool, lambert: bool = False) -> tuple:
    """The engine's polygon plan on contiguous `p`, `n (N, 3)`, `v (K, 3)` of the faces' float
    dtype: `(classes (N,), stats (N, 2), offsets (N + 1,), runs (R, 2, CODE_WIDTH) or None,
    points (R, 2, 3) or None, lambert (N,) float64 or None)`, arrays that own the engine's
    memory (no copy); with `lambert`, each receiver's sum of Lambert's edge terms over its
    boundary (`_kernels.polygon.edge_term`, in double; 0 without a boundary). Raises
    `MemoryError` / `ValueError` as the engine reports."""
    out = lib.poly_plan(p, n, v, occ_args, threads, codes, decoded, lambert)
    return tuple(None if a is None else np.asarray(a) for a in out)
