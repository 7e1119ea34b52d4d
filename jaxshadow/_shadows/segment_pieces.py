r"""Segment lights through their visible pieces: the engine decides, JAX integrates.

Seen from a receiver $p$, each convex face hides one interval of the parameter $t$ of
$x(t) = a + t\,(b - a)$ (Poulin §4.2; `_clip.blocked_intervals`), bounded by the crossings of the
segment with planes through $p$ and the face's edges, or with the face's own plane. The engine
(`csrc/engine/silhouette_segment.h`) forms the union of the intervals of the faces that meet the
light triangle $(p, a, b)$, in double, and returns the *visible pieces*: for each, the codes of
the two planes whose crossings bound it (or the segment's own ends). Where two faces of a mesh
share an edge, their intervals meet at that edge's crossing and the union closes over it, so
only contour edges (silhouette and boundary edges seen from $p$) and faces the segment passes
through bound pieces: a receiver needs as many slots as it has visible pieces, not as many as
there are faces in its light triangle.

On the device each endpoint is recomputed from its code, differentiably in $p$, $a$, $b$ and the
face's vertices: for an edge $u \to v$, $t = -\frac{(a - p)\cdot N}{(b - a)\cdot N}$ with
$N$ = `_planes.edge_planes(p, u, v)` (the device kernel's plane, so values and derivatives are
those of the face path); for a face plane, the same with its Newell normal about $o_0$. The
segment's kernel (`integ.segment`, horizon clipping included) is summed over the pieces.

Codes (int32): -1 ($t = 0$), -2 ($t = 1$), or $f\,(K_o + 1) + i$: edge $i \to i + 1$ of face
$f$ ($i < K_o$) or face $f$'s plane ($i = K_o$). `JAXSHADOW_SEGMENT_PIECES=0` switches the path
off (segment lights then clip every candidate face on the device: the reference it is tested
against).

On the host, a receiver's pieces come from the faces of the contour edges in its light triangle
(the silhouette hierarchy), the faces the segment passes through, and rays from $p$ to the middles
of the runs between their intervals, so that its work follows the contour rather than the faces
in the triangle; receivers where a decision is too close to call (and scenes with convex solids)
take the face path, every face in the light triangle. Both give the same pieces, codes and order.
The contour path is taken for occluder sets of 16 384 faces or more, where it measured faster than
the face path on every mesh tried (scans and CAD parts of 20k to 270k faces: 1.15x to 2.2x in the
engine); `JAXSHADOW_SEGMENT_WALK=1` takes it at any size, `=0` never.
"""

from __future__ import annotations

import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._core.mesh import OccluderTopology
from .._core.misc import safe_div
from .._kernels.planes import _occluder_sides
from . import binding as vis

FFI_PIECES = "jaxshadow_segment_pieces"
START, END = -1, -2


def enabled(traced: bool = False) -> bool:
    """Whether segment lights take the visible-pieces path: the engine has it (and, `traced`,
    its XLA FFI handler is registered) and `JAXSHADOW_SEGMENT_PIECES` is not `0`."""
    if os.environ.get("JAXSHADOW_SEGMENT_PIECES", "1") == "0":
        return False
    lib = vis._lib()
    if lib is None or not hasattr(lib, "segment_pieces"):
        return False
    if traced:
        return vis.ffi_available() and FFI_PIECES in lib.ffi_handlers()
    return True


def host_pieces(points: np.ndarray, a: np.ndarray, b: np.ndarray,
                occ: vis.HostOccluders) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The engine's visible pieces at concrete receivers: `(classes (N,) int32` (1 lit: nothing
    hidden; 2 umbra: all hidden; 3 penumbra), `kept (N,) int32` (faces whose hidden interval was
    computed: the candidates that meet the light triangle on the face path, the contour path's
    faces and those its rays met on the contour path), `offsets (N + 1,) int64`, `pieces (R, 2) int32` endpoint codes of the
    penumbra receivers' pieces, in order along the segment)."""
    lib = vis._require()
    dt = occ.faces.dtype
    p = np.ascontiguousarray(points, dt)
    aa, bb = np.ascontiguousarray(a, dt), np.ascontiguousarray(b, dt)
    cls, kept, off, pieces = lib.segment_pieces(p, aa, bb, occ.args(), vis.threads())
    return np.asarray(cls), np.asarray(kept), np.asarray(off), np.asarray(pieces).reshape(-1, 2)


def traced_pieces(
    points: Float[Array | np.ndarray, "N 3"],
    a: Float[Array | np.ndarray, "3"],
    b: Float[Array | np.ndarray, "3"],
    faces: Float[Array | np.ndarray, "m ko 3"],
    topology: OccluderTopology | None,
    capacity: int,
) -> tuple[Int[Array, " N"], Int[Array, " N"], Int[Array, "N c 2"]]:
    """`host_pieces` inside a compiled computation (XLA FFI): `(classes (N,), counts (N,),
    pieces (N, capacity, 2))`, unused slots `(-1, -1)` (a zero-length piece at `a`). A receiver
    with `counts > capacity` has only its first `capacity` pieces: the caller reports it. No
    gradient (the inputs are stop-gradient'ed). Under `vmap` an input that is not batched is passed
    once (a batch axis of size 1, `vmap_method="expand_dims"`), not copied per batch element."""
    topo = topology if topology is not None else OccluderTopology.independent(faces.shape[0])
    sg = jax.lax.stop_gradient
    dt = points.dtype
    n_pts = points.shape[0]
    call = jax.ffi.ffi_call(
        FFI_PIECES,
        (jax.ShapeDtypeStruct((n_pts,), jnp.int32), jax.ShapeDtypeStruct((n_pts,), jnp.int32),
         jax.ShapeDtypeStruct((n_pts, capacity, 2), jnp.int32)),
        vmap_method="expand_dims",
    )
    ends = jnp.stack([a.astype(dt), b.astype(dt)])
    out: Any = call(sg(points), sg(ends), sg(faces.astype(dt)), *vis._topology_arrays(topo),
                    cap=np.int64(capacity), threads=np.int64(vis.threads()))
    return out[0], out[1], out[2]


def piece_parameters(p: Array, a: Array, b: Array, faces: Array, codes: Array) -> Array:
    """`t (c, 2)` in [0, 1] of each endpoint code `codes (c, 2)` int32 seen from `p (3,)`, for the
    segment `a -> b (3,)` and the occluder faces `(m, Ko, 3)` (module docstring):
    differentiable in `p`, `a`, `b` and the faces' vertices."""
    ko = faces.shape[1]
    flat = codes.reshape(-1)
    is_plane = flat >= 0
    f = jnp.where(is_plane, flat // (ko + 1), 0)
    slot = jnp.where(is_plane, flat % (ko + 1), 0)
    occ = jnp.take(faces, f, axis=0)  # (2c, ko, 3)
    no, _, _, _, planes, _ = _occluder_sides(p, occ)
    d = b - a
    pl = jnp.take_along_axis(planes, jnp.minimum(slot, ko - 1)[:, None, None], axis=1)[:, 0]
    t_edge = safe_div(-(pl @ (a - p)), pl @ d)
    t_face = safe_div(-jnp.sum(no * (a[None, :] - occ[:, 0]), axis=-1), no @ d)
    t = jnp.where(slot == ko, t_face, t_edge)
    t = jnp.where(flat == START, 0.0, jnp.where(flat == END, 1.0, jnp.clip(t, 0.0, 1.0)))
    return t.astype(p.dtype).reshape(codes.shape)


def pieces_value(integ: Any, p: Array, n: Array, e: Any, a: Array, b: Array, light: Any, faces: Array,
                 codes: Array) -> Array:
    """The segment integrand `integ.segment` summed over the visible pieces `codes (c, 2)` of
    `a -> b (3,)` seen from `p (3,)` with unit normal `n (3,)` and eye `e` (or None); `faces
    (m, Ko, 3)` the occluder faces the codes index. Unused slots `(-1, -1)` are zero-length
    pieces at `a` and add nothing. Returns `integ.shape`."""
    t = piece_parameters(p, a, b, faces, codes)
    d = b - a
    starts = a[None, :] + t[:, 0:1] * d[None, :]
    ends = a[None, :] + t[:, 1:2] * d[None, :]
    # A piece from 0 to 1 is the whole segment: its ends exactly (a + 1 (b - a) may round).
    starts = jnp.where((codes[:, 0:1] == START), a[None, :], starts)
    ends = jnp.where((codes[:, 1:2] == END), b[None, :], jnp.where(codes[:, 1:2] == START, a[None, :], ends))
    return jnp.sum(jax.vmap(lambda u, v: integ.segment(p, n, e, u, v, light))(starts, ends), axis=0)
