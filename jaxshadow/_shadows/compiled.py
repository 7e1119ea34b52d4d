"""Exact shadows inside a compiled program: the values are abstract (`jax.jit`, `jax.vmap`).

- `traced_values`: the plan of `_shadows` with the engine inside the program (XLA FFI) and a
  static number of boundary edges (or a segment light's visible pieces) per receiver; a receiver over it is
  reported (`overflow`), never silently truncated.
- `device_values`: without the engine, every receiver clipped against every occluder by the
  JAX kernels of `_clip` (no build needed; time grows with the square of the occluder count,
  memory is bounded: a chunk of receivers, each a batch of candidate edges at a time).
"""

from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._kernels.clip import directional_visibility, point_visibility, split_batch, visible_edge_sums
from .._scene.model import Scene
from . import binding as vis
from . import segment_pieces
from .integrands import segment_visible
from .plan import EDGE_BLOCK, MIN_BLOCK, occluders_of, segment_profile

# --------------------------------------------------------------------------------------
# Abstract values: the engine inside the compiled program (XLA FFI), static capacities
# --------------------------------------------------------------------------------------


def _traced_polygon(light: Any, integ: Any, p, n, e, faces, topo, capacity: int) -> tuple[Any, Any]:
    verts = light.vertices.astype(p.dtype)
    _, cnt, runs = vis.traced_polygon_codes(p, n, verts, faces, topo, capacity)
    fn, f0 = vis.face_frames(faces)
    table = vis.vertex_table(verts, faces)

    def one(p_, n_, e_, r_):
        s, t = vis.edges_from_codes(p_, n_, verts, table, fn, f0, r_)
        return integ.contour(p_, n_, e_, verts, s, t)

    return jax.vmap(one)(p, n, e, runs), jnp.any(cnt > capacity)


def _traced_segment(light: Any, integ: Any, p, n, e, faces, topo, capacity: int) -> tuple[Any, Any]:
    dt = p.dtype
    a, b = light.start.astype(dt), light.end.astype(dt)
    prof = segment_profile(light)
    if segment_pieces.enabled(traced=True):
        # Visible pieces (`segment_pieces`): the capacity holds pieces, not candidate faces.
        cls, cnt, codes = segment_pieces.traced_pieces(p, a, b, faces, topo, capacity)
        shadowed = jax.vmap(segment_pieces.pieces_value, in_axes=(None, 0, 0, 0, None, None, None, None, 0))(
            integ, p, n, e, a, b, prof, faces, codes)
        free = jax.vmap(integ.segment, in_axes=(0, 0, 0, None, None, None))(p, n, e, a, b, prof)
        out = jnp.where(_per_value(cls == vis.LIT, integ), free,
                        jnp.where(_per_value(cls == vis.PENUMBRA, integ), shadowed, 0.0))
        return out, jnp.any(cnt > capacity)
    cnt, cand = vis.traced_segment_candidates(p, a, b, faces, topo, capacity)
    # Unused slots repeat the first candidate (or face 0 where there is none: then the
    # unoccluded value is taken).
    first = jnp.where(cand[:, :1] >= 0, cand[:, :1], 0)
    fidx = jnp.where(cand >= 0, cand, first)
    occ = jnp.take(faces, fidx.reshape(-1), axis=0).reshape(fidx.shape + faces.shape[1:])
    shadowed = jax.vmap(segment_visible, in_axes=(None, 0, 0, 0, None, None, None, 0))(integ, p, n, e, a, b, prof, occ)
    free = jax.vmap(integ.segment, in_axes=(0, 0, 0, None, None, None))(p, n, e, a, b, prof)
    return jnp.where(_per_value(cnt > 0, integ), shadowed, free), jnp.any(cnt > capacity)


def _traced_hard(light: Any, integ: Any, p, n, e, faces, topo, capacity: int) -> tuple[Any, Any]:
    x = light.geometry[0].astype(p.dtype)
    visible = vis.traced_hard_visibility(p, x, light.kind == "point", faces, topo)
    g = jax.vmap(getattr(integ, light.kind), in_axes=(0, 0, 0, None))(p, n, e, x)
    return jnp.where(_per_value(visible > 0, integ), g, 0.0), jnp.zeros((), bool)


def _per_value(mask: Any, integ: Any) -> Any:
    """A per-receiver `(n,)` mask broadcast over each receiver's value (`integ.shape`)."""
    return mask.reshape(mask.shape + (1,) * len(integ.shape))


# `(g (n,), overflow)` of one light for a block of receivers, inside a compiled program, by kind.
_TRACED = {"polygon": _traced_polygon, "segment": _traced_segment, "point": _traced_hard, "directional": _traced_hard}


def traced_values(scene: Scene, integ: Any, points: Any, normals: Any, eyes: Any, capacity: int,
                  chunk: int | None = None) -> tuple[Any, Any]:
    """`((N, *integ.shape, 3), overflow)`: every light's contribution with exact shadows, traceable (unit
    `normals`; `eyes` `(N, 3)`, or None for an integrand that reads none). `overflow` is True when a receiver needed more than `capacity` boundary edges
    (or visible pieces of a segment light): the values are then not exact. Receivers are processed `chunk` at a
    time (`lax.map`), which bounds the memory of the decoded boundaries. Without the engine's
    XLA FFI handlers (built without them, or for another jaxlib) the device kernels' values, with
    one warning."""
    if not vis.ffi_available():
        vis.warn_no_ffi()
        return device_values(scene, integ, points, normals, eyes), jnp.zeros((), bool)
    dt = points.dtype
    faces = occluders_of(scene).astype(dt)
    topo = scene.occluder_topology
    chunk = chunk or max(MIN_BLOCK, EDGE_BLOCK // (4 * capacity))

    def block(args):
        p, n, ee = args
        total = jnp.zeros((p.shape[0], *integ.shape, 3), dt)
        over = jnp.zeros((), bool)
        for light in scene.lights:
            g, o = _TRACED[light.kind](light, integ, p, n, ee, faces, topo, capacity)
            total = total + g[..., None] * light.emission(dt).reshape((1,) * g.ndim + (3,))
            over = over | o
        return total, over

    return lax_chunks(block, (points, normals, eyes), chunk)


def lax_chunks(block: Any, arrays: tuple, chunk: int) -> tuple[Any, Any]:
    """`block(arrays) -> (out (n, ...), flag)` over the leading axis `chunk` rows at a time
    (`lax.map`, the last chunk padded with copies of the first row): traceable, and the memory
    of one chunk's intermediates bounds the whole call's. A None in `arrays` (no eyes) stays None."""
    n_pts = arrays[0].shape[0]
    if n_pts <= chunk:
        return block(arrays)
    nb = -(-n_pts // chunk)
    pad = nb * chunk - n_pts
    arrs = tuple(jnp.concatenate([a, jnp.broadcast_to(a[:1], (pad,) + a.shape[1:])]) if pad and a is not None else a
                 for a in arrays)
    out, flag = jax.lax.map(block, tuple(None if a is None else a.reshape((nb, chunk) + a.shape[1:]) for a in arrs))
    return out.reshape((nb * chunk,) + out.shape[2:])[:n_pts], jnp.any(flag)


# --------------------------------------------------------------------------------------
# Without the engine: every receiver against every occluder (device kernels)
# --------------------------------------------------------------------------------------


def _device_polygon(light: Any, integ: Any, p, n, e, faces) -> Any:
    verts = light.vertices.astype(p.dtype)

    def one(p_, n_, e_):
        # The boundary's sums batch by batch of candidate edges: its O(M^2) edge soup never whole.
        sums = visible_edge_sums(p_, n_, verts, faces, lambda s, t: integ.contour_sums(p_, n_, e_, verts, s, t))
        return integ.contour_total(p_, n_, e_, verts, sums)

    return jax.vmap(one)(p, n, e)


def _device_segment(light: Any, integ: Any, p, n, e, faces) -> Any:
    a, b = light.start.astype(p.dtype), light.end.astype(p.dtype)
    # The chunk's receivers share the budgets of `visible_segment_sum` (static: `p`'s shape).
    one = functools.partial(segment_visible, receivers=p.shape[0])
    return jax.vmap(one, in_axes=(None, 0, 0, 0, None, None, None, None))(
        integ, p, n, e, a, b, segment_profile(light), faces)


def _device_hard(light: Any, integ: Any, p, n, e, faces) -> Any:
    x = light.geometry[0].astype(p.dtype)
    vis_fn = point_visibility if light.kind == "point" else directional_visibility
    g = jax.vmap(getattr(integ, light.kind), in_axes=(0, 0, 0, None))(p, n, e, x)
    return g * jax.vmap(vis_fn, in_axes=(0, None, None))(p, x, faces)


_DEVICE = {"polygon": _device_polygon, "segment": _device_segment, "point": _device_hard,
           "directional": _device_hard}


def device_chunk(n_faces: int, ko: int, k: int) -> int:
    """Receivers per chunk of the device kernels for `n_faces` occluders of `ko` vertices and
    polygon lights of up to `k` vertices: a receiver's intermediates are one batch of its
    candidate edges split against every region (`_clip.visible_edge_sums`: about `SPLIT_PAIRS`
    (edge, region plane) pairs, ~100 bytes each; fewer when all its candidate edges fit in one
    batch); about `DEVICE_PAIRS` pairs a chunk. A segment light's receiver holds its `O(M)`
    blocked intervals and one batch of its `2M + 1` pieces (`_clip.visible_segment_sum`, whose
    budgets the chunk's receivers share)."""
    m = max(1, n_faces)
    n_planes = max(k, ko) + 1  # `_clip._region_planes`
    n_cand = k + 1 + m * (ko + 1)
    per = split_batch(m, n_planes, n_cand) * (m + 1) * n_planes
    return int(min(4096, max(1, 2 ** int(np.log2(max(1, DEVICE_PAIRS // per))))))


# (candidate edge, region plane) pairs of one chunk of receivers of the device kernels: ~25 MiB.
DEVICE_PAIRS = 1 << 18


def device_values(scene: Scene, integ: Any, points: Any, normals: Any, eyes: Any) -> Any:
    """`(N, 3)` with exact shadows from the device kernels: each receiver clipped against every
    occluder (`_clip.visible_edge_sums`; segment lights `_clip.visible_segment_sum`), no
    engine, traceable, chunked: receivers `device_chunk` at a time, each a batch of its
    candidate edges (or of a segment's pieces) at a time, so that memory stays about
    `DEVICE_PAIRS` (edge, region plane) pairs however many occluders there are (unit
    `normals`; `eyes` as for `traced_values`)."""
    dt = points.dtype
    faces = occluders_of(scene).astype(dt)

    def block(args):
        p, n, ee = args
        total = jnp.zeros(p.shape, dt)
        for light in scene.lights:
            total = total + _DEVICE[light.kind](light, integ, p, n, ee, faces)[:, None] * light.emission(dt)[None, :]
        return total, jnp.zeros((), bool)

    k = max([light.vertices.shape[0] for light in scene.lights if light.kind == "polygon"], default=0)
    chunk = device_chunk(faces.shape[0], faces.shape[1], k)
    # Several chunks: each recomputed in reverse mode (`jax.checkpoint`). Under the chunks'
    # `lax.map`, reverse mode otherwise keeps the residuals of every batch of candidate edges of
    # a chunk (`visible_edge_sums`'s own checkpoint notwithstanding), O(M^2) per receiver again.
    return lax_chunks(jax.checkpoint(block) if points.shape[0] > chunk else block, (points, normals, eyes), chunk)[0]
