"""The shadow engine's C ABI (`csrc/shadowc.cc`, ctypes): signatures and the polygon-plan call.

NumPy and ctypes only (no JAX): `binding` binds the engine through this module, and a
profiler can drive the compiled library alone, loading this file by path, without importing
the package (`benchmarks/engine_profile.py` counts the engine's instructions under valgrind,
where importing JAX alone takes minutes).
"""

from __future__ import annotations

import ctypes
from typing import Any

import numpy as np

ABI_VERSION = 2
CODE_WIDTH = 7


def load(path: str) -> Any:
    """The engine library at `path` with its argument types set, or None for another ABI."""
    lib = ctypes.CDLL(path)
    if lib.jaxshadow_shadowc_abi() != ABI_VERSION:
        return None
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    occ: list[Any] = [i64, i64, p, p, p, i64, p, p, p]
    lib.jaxshadow_poly_plan.argtypes = [i32, i64, p, p, i64, p, *occ, i32, p, p, p, p, p, ctypes.POINTER(i64), p]
    lib.jaxshadow_poly_fixed.argtypes = [i32, i64, p, p, i64, p, *occ, i32, i64, p, p, p]
    lib.jaxshadow_hard_plan.argtypes = [i32, i64, p, p, i32, i64, *occ, i32, p]
    lib.jaxshadow_segment_plan.argtypes = [i32, i64, p, p, p, *occ, i32, p, ctypes.POINTER(p)]
    for f in (lib.jaxshadow_poly_plan, lib.jaxshadow_poly_fixed, lib.jaxshadow_hard_plan, lib.jaxshadow_segment_plan):
        f.restype = i32
    lib.jaxshadow_free.argtypes = [p]
    lib.jaxshadow_free.restype = None
    return lib


def ptr(a: np.ndarray) -> int | None:
    """The data pointer of a contiguous array (None when it is empty)."""
    return a.ctypes.data if a.size else None


def occluder_args(faces: np.ndarray, ints: list[np.ndarray], n_solids: int) -> list:
    """The occluder arguments of every entry point: padded faces `(M, Ko, 3)` (contiguous, the
    call's float dtype) and the topology's contiguous int32 arrays `face_solid, face_closed,
    solid_faces, solid_edge_off, solid_edges` (`_mesh.OccluderTopology`)."""
    m, ko = faces.shape[:2]
    return [m, ko, ptr(faces), ptr(ints[0]), ptr(ints[1]), n_solids, ptr(ints[2]), ptr(ints[3]), ptr(ints[4])]


def take_buffer(lib: Any, buf: ctypes.c_void_p, ctype: Any, shape: tuple) -> np.ndarray | None:
    """Copy a buffer the engine malloc'd into a NumPy array of `shape` and free it."""
    if not buf.value:
        return None
    n = int(np.prod(shape))
    arr = np.ctypeslib.as_array(ctypes.cast(buf, ctypes.POINTER(ctype)), shape=(max(n, 1),))[:n].copy()
    lib.jaxshadow_free(buf)
    return arr.reshape(shape)


def poly_plan(lib: Any, p: np.ndarray, n: np.ndarray, v: np.ndarray, occ_args: list, threads: int, codes: bool,
              decoded: bool, lambert: bool = False) -> tuple:
    """`jaxshadow_poly_plan` on contiguous `p`, `n (N, 3)`, `v (K, 3)` of one float dtype:
    `(classes (N,), stats (N, 2), offsets (N + 1,), runs (R, 2, 7) or None, points (R, 2, 3) or
    None, lambert (N,) float64 or None)`; with `lambert`, each receiver's sum of Lambert's edge
    terms over its boundary (`_polygon.edge_term`, in double; 0 without a boundary). Raises
    `MemoryError` / `ValueError` as the engine reports."""
    dt = p.dtype
    N, K = p.shape[0], v.shape[0]
    cls = np.zeros(N, np.int32)
    stats = np.zeros((N, 2), np.int32)
    off = np.zeros(N + 1, np.int64)
    runs, pts = ctypes.c_void_p(), ctypes.c_void_p()
    nr = ctypes.c_int64()
    lam = np.zeros(N, np.float64) if lambert else None
    rc = lib.jaxshadow_poly_plan(int(dt == np.float64), N, ptr(p), ptr(n), K, ptr(v), *occ_args, threads, ptr(cls),
                                 ptr(stats), ptr(off), ctypes.byref(runs) if codes else None,
                                 ctypes.byref(pts) if decoded else None, ctypes.byref(nr),
                                 None if lam is None else ptr(lam))
    total = nr.value
    code_arr = take_buffer(lib, runs, ctypes.c_int32, (total, 2, CODE_WIDTH))
    ctype = ctypes.c_double if dt == np.float64 else ctypes.c_float
    pt_arr = take_buffer(lib, pts, ctype, (total, 2, 3))
    if rc == 2:
        raise MemoryError("jaxshadow shadow engine: out of memory for the boundary codes")
    if rc:
        raise ValueError("jaxshadow shadow engine: a light has more than 64 vertices")
    return cls, stats, off, code_arr, pt_arr, lam
