r"""Exact shadows for concrete inputs: classify on the host, evaluate only what each receiver needs.

Campbell & Fussell's pipeline (§4.2-4.3), with the host engine of `_visibility` as the shadow
data: for every light, each receiver is classified and gets exactly the work its class needs.

- **Polygon lights.** `LIT` receivers take the unoccluded kernel (`form_factor_kernel`,
  `polygon_specular_kernel`); `UMBRA` ones and receivers behind the light or below its horizon
  get exactly 0 without clipping; `PENUMBRA` receivers integrate over the boundary of their
  visible region, computed by the engine from their candidate occluders only and decoded on the
  host into edges (`_visibility.polygon_codes(decoded=True)`), grouped by edge count into
  power-of-two capacities (one compiled contour integral per capacity and block size). No
  receiver ever needs more than its own edges: memory is bounded by the block sizes, not by the
  number of occluders, and no count of candidates is too large (the engine has no capacity).
- **Point and directional lights.** Hard shadows from the engine's ray tests against the
  hierarchy, times the unoccluded kernel.
- **Segment lights.** The engine lists the faces that meet each receiver's light triangle
  (Poulin §4.2); receivers are grouped by that count, the device kernel clips the segment against
  their own faces only (`_clip.visible_segments`).

Values only: everything here runs from concrete NumPy values (nothing is differentiated; the
traced path is `_shade._irradiance_traced`, whose derivatives follow the same regions). The
results equal the device kernels' with all occluders to rounding (`tests/test_shadows_scale.py`).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from . import _visibility as vis
from ._clip import masked_contour_form_factor, visible_linear_kernel, visible_segments
from ._linear import linear_irradiance_kernel
from ._misc import unit_rows
from ._point import directional_irradiance_kernel, point_irradiance_kernel
from ._polygon import form_factor_kernel
from ._scene import DirectionalLight, LinearLight, PointLight, PolygonLight, Scene
from ._specular import (
    contour_specular_kernel,
    directional_specular_kernel,
    point_specular_kernel,
    polygon_specular_kernel,
    segment_specular_kernel,
)

# Receivers per engine call (bounds the host memory of the codes and edges), and edge slots per
# compiled block (receivers per block = EDGE_BLOCK // capacity).
HOST_CHUNK = 1 << 18
EDGE_BLOCK = 1 << 18
MIN_BLOCK = 64
MIN_CAPACITY = 8


def applicable(scene: Scene, *arrays: Any) -> bool:
    """Whether `scene` has occluders, the engine is built and every input is concrete."""
    if scene.occluders is None or not vis.engine_available():
        return False
    leaves = jax.tree_util.tree_leaves((scene, arrays))
    return not any(isinstance(x, jax.core.Tracer) for x in leaves)


def _next_pow2(n: int, lo: int) -> int:
    c = lo
    while c < n:
        c *= 2
    return c


def _padded_map(fn: Any, arrays: tuple, shared: tuple, rows: int, out_dtype: Any) -> np.ndarray:
    """`fn(*blocks, *shared)` over the leading axis of `arrays` in blocks of at most `rows`, each
    padded (with copies of its first row) to a power of two of at least `MIN_BLOCK` rows, so that
    `fn` compiles for a few shapes only."""
    n = arrays[0].shape[0]
    out = np.empty(n, out_dtype)
    for s in range(0, n, rows):
        e = min(n, s + rows)
        m = e - s
        size = min(rows, _next_pow2(m, MIN_BLOCK)) if rows >= MIN_BLOCK else m
        size = max(size, m)
        blk = []
        for a in arrays:
            b = a[s:e]
            if size > m:
                b = np.concatenate([b, np.broadcast_to(b[:1], (size - m,) + b.shape[1:])])
            blk.append(b)
        out[s:e] = np.asarray(fn(*blk, *shared))[:m]
    return out


def _dense_edges(pc: vis.PolygonCodes, idx: np.ndarray, cap: int, e0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The decoded edges of receivers `idx` as `(n, cap, 3)` starts and ends (unused slots
    zero-length at the light's first vertex `e0`)."""
    counts = pc.counts[idx]
    slot = np.arange(cap)
    used = slot[None, :] < counts[:, None]
    rows = np.where(used, pc.offsets[idx][:, None] + slot[None, :], 0)
    pts = pc.points[rows]  # (n, cap, 2, 3)
    pts = np.where(used[:, :, None, None], pts, e0)
    return np.ascontiguousarray(pts[:, :, 0]), np.ascontiguousarray(pts[:, :, 1])


# --------------------------------------------------------------------------------------
# Compiled integrals (one light, a block of receivers)
# --------------------------------------------------------------------------------------


@jax.jit
def _lambert_lit(p, n, verts):
    return jax.vmap(form_factor_kernel, in_axes=(0, 0, None))(p, n, verts)


@jax.jit
def _lambert_contour(p, n, starts, ends, verts):
    return jax.vmap(masked_contour_form_factor, in_axes=(0, 0, None, 0, 0))(p, n, verts, starts, ends)


@functools.partial(jax.jit, static_argnames=("method", "degree"))
def _phong_lit(p, n, eye, verts, exponent, method, degree):
    k = functools.partial(polygon_specular_kernel, method=method, degree=degree)
    return jax.vmap(k, in_axes=(0, 0, 0, None, None))(p, n, eye, verts, exponent)


@functools.partial(jax.jit, static_argnames=("method", "degree"))
def _phong_contour(p, n, eye, starts, ends, verts, exponent, method, degree):
    k = functools.partial(contour_specular_kernel, method=method, degree=degree)
    return jax.vmap(k, in_axes=(0, 0, 0, 0, 0, None))(p, n, eye, starts, ends, exponent)


@functools.partial(jax.jit, static_argnames=("m",))
def _segment_lit(p, n, a, b, m):
    return jax.vmap(linear_irradiance_kernel, in_axes=(0, 0, None, None, None))(p, n, a, b, m)


@functools.partial(jax.jit, static_argnames=("m",))
def _segment_shadowed(p, n, occ, a, b, m):
    return jax.vmap(visible_linear_kernel, in_axes=(0, 0, None, None, None, 0))(p, n, a, b, m, occ)


@functools.partial(jax.jit, static_argnames=("method", "degree"))
def _segment_phong(p, n, eye, occ, a, b, exponent, prof, method, degree):
    def one(p, n, e, o):
        sa, sb = visible_segments(p, a, b, o)
        piece = lambda u, v: segment_specular_kernel(p, n, e, u, v, exponent, prof, method=method, degree=degree)  # noqa: E731
        return jnp.sum(jax.vmap(piece)(sa, sb))

    return jax.vmap(one)(p, n, eye, occ)


@functools.partial(jax.jit, static_argnames=("method", "degree"))
def _segment_phong_lit(p, n, eye, a, b, exponent, prof, method, degree):
    k = functools.partial(segment_specular_kernel, method=method, degree=degree)
    return jax.vmap(k, in_axes=(0, 0, 0, None, None, None, None))(p, n, eye, a, b, exponent, prof)


@jax.jit
def _point_lit(p, n, x):
    return jax.vmap(point_irradiance_kernel, in_axes=(0, 0, None))(p, n, x)


@jax.jit
def _directional_lit(n, d):
    return jax.vmap(directional_irradiance_kernel, in_axes=(0, None))(n, d)


@jax.jit
def _point_phong(p, n, eye, x, exponent):
    return jax.vmap(point_specular_kernel, in_axes=(0, 0, 0, None, None))(p, n, eye, x, exponent)


@jax.jit
def _directional_phong(p, n, eye, d, exponent):
    return jax.vmap(directional_specular_kernel, in_axes=(0, 0, 0, None, None))(p, n, eye, d, exponent)


@jax.jit
def _unit(n):
    return unit_rows(n)


# --------------------------------------------------------------------------------------
# Per light
# --------------------------------------------------------------------------------------


class _Receivers:
    """Concrete receivers in one dtype (normals made unit as the kernels do), and eyes."""

    def __init__(self, points: Any, normals: Any, eyes: Any = None):
        self.p = np.ascontiguousarray(np.asarray(points))
        self.dtype = self.p.dtype
        self.n = np.ascontiguousarray(np.asarray(_unit(jnp.asarray(normals, self.dtype))))
        self.eye: Any = None if eyes is None else np.ascontiguousarray(np.asarray(eyes, self.dtype))


def _polygon_values(r: _Receivers, verts: np.ndarray, occ: vis.HostOccluders, phong: dict | None) -> np.ndarray:
    """Per receiver: form factor (Lambert) or Phong integral per unit radiance of one polygon
    light, shadows included."""
    n_pts = r.p.shape[0]
    out = np.zeros(n_pts, r.dtype)
    v = np.asarray(verts, r.dtype)
    e0 = v[0]
    for s in range(0, n_pts, HOST_CHUNK):
        e = min(n_pts, s + HOST_CHUNK)
        p, n = r.p[s:e], r.n[s:e]
        pc = vis.polygon_codes(p, n, v, occ, codes=False, decoded=True)
        res = np.zeros(e - s, r.dtype)
        lit = np.nonzero(pc.classes == vis.LIT)[0]
        if lit.size:
            if phong is None:
                res[lit] = _padded_map(_lambert_lit, (p[lit], n[lit]), (v,), EDGE_BLOCK // 8, r.dtype)
            else:
                res[lit] = _padded_map(
                    lambda a, b, c, vv: _phong_lit(a, b, c, vv, phong["exponent"], phong["method"], phong["degree"]),
                    (p[lit], n[lit], r.eye[s:e][lit]), (v,), EDGE_BLOCK // 8, r.dtype)
        pen = np.nonzero(pc.classes == vis.PENUMBRA)[0]
        if pen.size:
            counts = pc.counts[pen]
            caps = np.maximum(MIN_CAPACITY, 2 ** np.ceil(np.log2(np.maximum(counts, 1))).astype(np.int64))
            for cap in np.unique(caps):
                idx = pen[caps == cap]
                starts, ends = _dense_edges(pc, idx, int(cap), e0)
                rows = max(MIN_BLOCK, EDGE_BLOCK // int(cap))
                if phong is None:
                    res[idx] = _padded_map(_lambert_contour, (p[idx], n[idx], starts, ends), (v,), rows, r.dtype)
                else:
                    res[idx] = _padded_map(
                        lambda a, b, c, d, f, vv: _phong_contour(a, b, c, d, f, vv, phong["exponent"], phong["method"],
                                                                 phong["degree"]),
                        (p[idx], n[idx], r.eye[s:e][idx], starts, ends), (v,), rows, r.dtype)
        out[s:e] = res
    return out


def _segment_values(r: _Receivers, light: LinearLight, occ: vis.HostOccluders, phong: dict | None) -> np.ndarray:
    n_pts = r.p.shape[0]
    a = np.asarray(light.start, r.dtype)
    b = np.asarray(light.end, r.dtype)
    m = light.exponent
    prof = None if light.profile == "isotropic" else np.asarray(float(m), r.dtype)
    out = np.zeros(n_pts, r.dtype)
    faces = occ.faces
    for s in range(0, n_pts, HOST_CHUNK):
        e = min(n_pts, s + HOST_CHUNK)
        p, n = r.p[s:e], r.n[s:e]
        eye: Any = None if r.eye is None else r.eye[s:e]
        off, cand = vis.segment_candidates(p, a, b, occ)
        counts = np.diff(off)
        res = np.zeros(e - s, r.dtype)
        free = np.nonzero(counts == 0)[0]
        if free.size:
            if phong is None:
                res[free] = _padded_map(lambda x, y: _segment_lit(x, y, a, b, m), (p[free], n[free]), (), EDGE_BLOCK // 8,
                                        r.dtype)
            else:
                res[free] = _padded_map(
                    lambda x, y, z: _segment_phong_lit(x, y, z, a, b, phong["exponent"], prof, phong["method"],
                                                       phong["degree"]),
                    (p[free], n[free], eye[free]), (), EDGE_BLOCK // 8, r.dtype)
        busy = np.nonzero(counts > 0)[0]
        if busy.size:
            caps = 2 ** np.ceil(np.log2(counts[busy])).astype(np.int64)
            for cap in np.unique(caps):
                idx = busy[caps == cap]
                slot = np.arange(cap)
                used = slot[None, :] < counts[idx][:, None]
                rows_ = np.where(used, off[idx][:, None] + slot[None, :], 0)
                occ_b = np.where(used[:, :, None, None], faces[cand[rows_]], 0.0).astype(r.dtype)
                rows = max(MIN_BLOCK, (EDGE_BLOCK // 16) // int(cap))
                if phong is None:
                    res[idx] = _padded_map(lambda x, y, o: _segment_shadowed(x, y, o, a, b, m), (p[idx], n[idx], occ_b), (),
                                           rows, r.dtype)
                else:
                    res[idx] = _padded_map(
                        lambda x, y, z, o: _segment_phong(x, y, z, o, a, b, phong["exponent"], prof, phong["method"],
                                                          phong["degree"]),
                        (p[idx], n[idx], eye[idx], occ_b), (), rows, r.dtype)
        out[s:e] = res
    return out


def _hard_values(r: _Receivers, light: Any, occ: vis.HostOccluders, phong: dict | None) -> np.ndarray:
    is_point = isinstance(light, PointLight)
    x = np.asarray(light.position if is_point else light.direction, r.dtype)
    visible = vis.hard_visibility(r.p, x, is_point, occ)
    rows = EDGE_BLOCK // 8
    if phong is None:
        if is_point:
            g = _padded_map(_point_lit, (r.p, r.n), (x,), rows, r.dtype)
        else:
            g = _padded_map(_directional_lit, (r.n,), (x,), rows, r.dtype)
    else:
        fn = _point_phong if is_point else _directional_phong
        g = _padded_map(lambda a, b, c, xx: fn(a, b, c, xx, phong["exponent"]), (r.p, r.n, r.eye), (x,), rows, r.dtype)
    return np.where(visible, g, 0.0).astype(r.dtype)


def _light_values(r: _Receivers, light: Any, occ: vis.HostOccluders, phong: dict | None) -> tuple[np.ndarray, np.ndarray]:
    """`(g (N,), emission (3,))` with the light's contribution `g[:, None] * emission[None, :]`."""
    if isinstance(light, PolygonLight):
        g = _polygon_values(r, np.asarray(light.vertices), occ, phong)
        return (g * np.pi if phong is None else g), np.asarray(light.radiance, r.dtype)
    if isinstance(light, LinearLight):
        return _segment_values(r, light, occ, phong), np.asarray(light.power, r.dtype)
    if isinstance(light, PointLight):
        return _hard_values(r, light, occ, phong), np.asarray(light.intensity, r.dtype)
    if isinstance(light, DirectionalLight):
        return _hard_values(r, light, occ, phong), np.asarray(light.irradiance, r.dtype)
    raise TypeError(f"unknown light {type(light).__name__}")


def host_occluders(scene: Scene, dtype: Any) -> vis.HostOccluders:
    return vis.HostOccluders.of(np.asarray(scene.occluders), scene.occluder_topology, dtype)


def irradiance(scene: Scene, points: Any, normals: Any) -> np.ndarray:
    """`(N, 3)` irradiance with exact shadows (concrete inputs, checked by the caller)."""
    r = _Receivers(points, normals)
    occ = host_occluders(scene, r.dtype)
    total = np.zeros(r.p.shape, r.dtype)
    for light in scene.lights:
        g, emission = _light_values(r, light, occ, None)
        total += g[:, None] * emission[None, :]
    return total


def specular(scene: Scene, points: Any, normals: Any, eyes: Any, exponent: Any, method: str, degree: int) -> np.ndarray:
    """`(N, 3)` Phong specular integral with exact shadows (concrete inputs)."""
    r = _Receivers(points, normals, eyes)
    occ = host_occluders(scene, r.dtype)
    phong = {"exponent": np.asarray(exponent, r.dtype), "method": method, "degree": int(degree)}
    total = np.zeros(r.p.shape, r.dtype)
    for light in scene.lights:
        g, emission = _light_values(r, light, occ, phong)
        total += g[:, None] * emission[None, :]
    return total
