r"""Exact visibility at mesh scale: the host shadow engine and the JAX geometry it drives.

The visible part of a polygon light seen from a receiver is a region $R$ of the light's plane
(`jaxshadow._kernels.clip` module docstring); its boundary is a set of edges whose endpoints are a light
vertex, a light edge's crossing with the receiver's horizon, a projected occluder vertex, an
occluder edge's crossing with the light's plane, or the line common to two planes through the
receiver. Which pieces of which edges bound $R$ is combinatorics: piecewise constant in the
inputs, carrying no gradient. The points themselves, and Lambert's and Phong's contour integrals
over them, are geometry: what is differentiated.

`csrc/shadowc.cc` (compiled by `setup.py`, C++17) does the combinatorics on the host for a whole batch:
for each receiver it queries a bounding-volume hierarchy of the occluders with the receiver's
illumination pyramid (Campbell & Fussell §4.3's "bounding volume enclosing the light source and
receiver", one per receiver), tests the candidates exactly (C&F Theorem 2's occlusion volume and
Theorem 3's umbra volume, in their dual form: does the pyramid meet the occluder; does the
occluder's projection cover the light) in double precision whatever the inputs' dtype (float32
values are exact in double, so the decisions are those of the exact float32 geometry; only the
points that JAX integrates are float32), classifies the receiver (`ZERO` behind the light or
below its horizon, `LIT`, `UMBRA`, `PENUMBRA`) and, in penumbra, splits the candidate edges exactly
as the device kernel `_clip._boundary_runs` does, with the candidates only. It returns per
receiver a list of *runs*, each two endpoint codes of 7 int32 (`decode_endpoints`). Convex solids
(`_mesh.Mesh`) enter as one region, the cone through their silhouette.

This module binds the engine (one extension module, `abi`: host functions for planning from
concrete values; XLA FFI handlers for programs that need the codes of traced values, e.g. a
light fit) and turns codes into
differentiable edges. It never changes a result: a receiver's region, and so its value, is the
same as the device kernel's with all occluders (tests: 1e-15 agreement), and the hierarchy only
decides which occluders are looked at.
"""

from __future__ import annotations

import functools
import os
from dataclasses import dataclass
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .._core.geometry import newell_normal
from .._core.mesh import OccluderTopology
from .._kernels.planes import crossing_point as _crossing_point
from .._kernels.planes import edge_planes as edge_planes
from .._kernels.planes import light_edge_point as _light_edge_point
from .._kernels.planes import near_planes as _near_planes
from .._kernels.planes import occluder_edges_point as _occluder_edges_point
from .._kernels.planes import pow2_scale as _pow2_scale
from .._kernels.planes import project as _project
from .._kernels.planes import rescale_rows as _rescale_rows
from . import abi as _abi

ZERO, LIT, UMBRA, PENUMBRA = 0, 1, 2, 3
CLASS_NAMES = ("zero", "lit", "umbra", "penumbra")
CODE_WIDTH = _abi.CODE_WIDTH
# Endpoint kinds (`csrc/engine/geometry.h`); FFI target names (`csrc/shadowc.cc`, `ffi_handlers`).
K_UNUSED, K_LIGHT, K_HORIZON, K_PROJECTED, K_EMITTER_CROSS, K_PLANES = -1, 0, 1, 2, 3, 4
FFI_TARGET = "jaxshadow_poly_codes"
FFI_HARD = "jaxshadow_hard_visibility"
FFI_SEGMENT = "jaxshadow_segment_candidates"


# --------------------------------------------------------------------------------------
# The compiled engine
# --------------------------------------------------------------------------------------


@functools.cache
def _loaded() -> tuple[Any, str]:
    """`(module, "")`, or `(None, why)` where the extension is not built or not loadable.

    `JAXSHADOW_ENGINE_LIBRARY`, when set, names another build of the same sources to load instead
    (`tools/sanitize.sh` runs the tests with one built under AddressSanitizer); a path that does
    not load is an error, not a silent fallback to the device kernels."""
    override = os.environ.get("JAXSHADOW_ENGINE_LIBRARY")
    if override:
        try:
            built = _abi.load(override)
        except ImportError as e:
            raise RuntimeError(f"JAXSHADOW_ENGINE_LIBRARY={override}: not loadable ({e})") from e
        if built is None:
            raise RuntimeError(f"JAXSHADOW_ENGINE_LIBRARY={override}: not the engine's ABI version {_abi.ABI_VERSION}")
        return built, ""
    try:
        from . import _shadowc as mod  # type: ignore[attr-defined]
    except ImportError as e:
        return None, f"not built: {e}"
    why = _abi.check(mod)
    return (None, why) if why else (mod, "")


def _lib() -> Any:
    """The engine's extension module, or None where it is not built (or is a stale build)."""
    return _loaded()[0]


@functools.cache
def warn_unbuilt() -> None:
    """One warning per process that exact shadows fall back to the device kernels."""
    import warnings

    warnings.warn("jaxshadow: the compiled shadow engine (jaxshadow._shadows._shadowc) is not built or "
                  f"not loadable ({_loaded()[1]}); exact shadows use the device kernels (same values, but time "
                  "and memory grow with the number of occluders). Reinstall jaxshadow with a C++ compiler.",
                  RuntimeWarning, stacklevel=4)


def engine_available() -> bool:
    """Whether the compiled shadow engine (`jaxshadow._shadows._shadowc`) is built and loadable."""
    return _lib() is not None


@functools.cache
def _ffi_status() -> tuple[bool, str]:
    """`(True, "")` once the engine's XLA FFI handlers are registered, or `(False, why not)`: the
    engine is not built, was built without jaxlib's FFI headers, or against another jaxlib than
    this process runs (the handlers are compiled against one version of XLA's FFI)."""
    lib = _lib()
    if lib is None:
        return False, "the engine is not built"
    if not lib.HAS_FFI:
        return False, "the engine was built without jaxlib's XLA FFI headers"
    import jaxlib.version

    if lib.JAXLIB_VERSION != jaxlib.version.__version__:
        return False, (f"the engine's XLA FFI handlers were compiled against jaxlib {lib.JAXLIB_VERSION}, this "
                       f"process runs jaxlib {jaxlib.version.__version__}; rebuild jaxshadow in this environment "
                       "(tools/setup.sh, or pip install --no-build-isolation)")
    for name, capsule in lib.ffi_handlers().items():
        jax.ffi.register_ffi_target(name, capsule, platform="cpu")
    return True, ""


def ffi_available() -> bool:
    """Whether the engine's XLA FFI handlers are usable (built, for this jaxlib) and registered."""
    return _ffi_status()[0]


@functools.cache
def warn_no_ffi() -> None:
    """One warning per process that traced programs use the device kernels (engine built, handlers not usable)."""
    import warnings

    warnings.warn(f"jaxshadow: {_ffi_status()[1]}. Exact shadows inside traced programs use the device kernels "
                  "(same values, but time and memory grow with the number of occluders).", RuntimeWarning,
                  stacklevel=4)


def prepared_stats() -> dict[str, int]:
    """The counts of the engine's cache of prepared occluder sets (`csrc/engine/prepared.h`) since
    the process started: `lookups` of sets large enough to be cached, `hits` among them, `builds`
    of a set's hierarchy (any size), `polygon_builds` of what only polygon lights read (edge twins,
    the silhouette path's hierarchy, ...). Raises where the engine is not built."""
    return dict(_require().prepared_stats())


def threads() -> int:
    """Host threads the engine uses (`JAXSHADOW_THREADS`, default: all cores)."""
    try:
        return max(0, int(os.environ.get("JAXSHADOW_THREADS", "0")))
    except ValueError:
        return 0


@dataclass
class HostOccluders:
    """Occluders as the engine reads them: padded faces in one float dtype and the topology."""

    faces: np.ndarray  # (M, Ko, 3)
    topology: OccluderTopology

    def __post_init__(self) -> None:
        t = self.topology
        # Contiguous int32 copies, made once for every call that reads these occluders.
        self._ints = [np.ascontiguousarray(a, np.int32) for a in (t.face_solid, t.face_closed, t.solid_faces,
                                                                 t.solid_edge_off, t.solid_edges)]

    @staticmethod
    def of(occluders: Any, topology: OccluderTopology | None, dtype: Any) -> HostOccluders:
        f = np.ascontiguousarray(np.asarray(occluders, dtype=dtype))
        topo = topology if topology is not None else OccluderTopology.independent(f.shape[0])
        return HostOccluders(f, topo)

    def args(self) -> tuple:
        """The engine's occluders argument (`abi.occluder_args`)."""
        return _abi.occluder_args(self.faces, self._ints, self.topology.n_solids)


def _require() -> Any:
    lib = _lib()
    if lib is None:
        raise RuntimeError("jaxshadow._shadows._shadowc is not built: reinstall jaxshadow with a C++ compiler available")
    return lib


def unused_code() -> np.ndarray:
    """One endpoint code of an unused slot (kind `K_UNUSED`, decoded as the light's first vertex)."""
    c = np.zeros(CODE_WIDTH, np.int32)
    c[0] = K_UNUSED
    return c


@dataclass
class PolygonCodes:
    """The engine's result for one polygon light: `classes (N,)` (`ZERO`, `LIT`, `UMBRA`,
    `PENUMBRA`), `stats (N, 2)` (occluders the hierarchy returned, occluder regions kept;
    the first counts, on the face path, the items of the receiver's group's list that pass its own
    tests, and groups end at the engine's blocks of receivers, which depend on `JAXSHADOW_THREADS`:
    it may differ with the thread count, unlike everything else here),
    `offsets (N + 1,)`; receiver i's boundary edges are rows `offsets[i]:offsets[i + 1]` of
    `runs (R, 2, 7)` (endpoint codes) and/or `points (R, 2, 3)` (their points, decoded on the host);
    for `LIT` receivers, the edges of the horizon-clipped light. `lambert (N,)` float64 (when
    asked for): each receiver's sum of Lambert's edge terms over its boundary (`edge_term`,
    computed on the host in double), so that its form factor is `-lambert / (2 pi)`."""

    classes: np.ndarray
    stats: np.ndarray
    offsets: np.ndarray
    runs: Any  # np.ndarray or None
    points: Any  # np.ndarray or None
    lambert: Any = None  # np.ndarray or None

    @property
    def counts(self) -> np.ndarray:
        return np.diff(self.offsets)


def polygon_codes(points: np.ndarray, normals: np.ndarray, verts: np.ndarray, occ: HostOccluders,
                  codes: bool = True, decoded: bool = False, lambert: bool = False) -> PolygonCodes:
    """Classify receivers and compute the boundary of their visible regions (host, C++).

    **Arguments:** `points`, `normals` `(N, 3)` (unit normals), `verts (K, 3)` padded convex light,
    `occ` the occluders; float32 or float64 (all in `occ.faces`' dtype); `codes`: return the endpoint
    codes; `decoded`: return the endpoints' points (decoded on the host, for values that are not
    differentiated); `lambert`: return each receiver's sum of Lambert's edge terms (`lambert`).

    **Returns:** `PolygonCodes`.
    """
    lib = _require()
    dt = occ.faces.dtype
    p = np.ascontiguousarray(points, dt)
    n = np.ascontiguousarray(normals, dt)
    v = np.ascontiguousarray(verts, dt)
    return PolygonCodes(*_abi.poly_plan(lib, p, n, v, occ.args(), threads(), codes, decoded, lambert))


def hard_visibility(points: np.ndarray, x: np.ndarray, is_point: bool, occ: HostOccluders) -> np.ndarray:
    """`(N,)` bool: the segment from each point to the point light `x` (or the ray towards the
    directional light travelling along `x`) misses every occluder (`_clip.point_visibility`'s
    test, through the hierarchy)."""
    lib = _require()
    dt = occ.faces.dtype
    p = np.ascontiguousarray(points, dt)
    xx = np.ascontiguousarray(x, dt)
    return np.asarray(lib.hard_plan(p, xx, bool(is_point), occ.args(), threads()))


def segment_candidates(points: np.ndarray, a: np.ndarray, b: np.ndarray, occ: HostOccluders) -> tuple[np.ndarray, np.ndarray]:
    """Faces that may block part of the segment light `a -> b` seen from each point (they meet
    the light triangle; back faces of closed meshes dropped): `(offsets (N + 1,) int64, faces (C,)
    int32)`."""
    lib = _require()
    dt = occ.faces.dtype
    p = np.ascontiguousarray(points, dt)
    aa, bb = np.ascontiguousarray(a, dt), np.ascontiguousarray(b, dt)
    off, faces = lib.segment_plan(p, aa, bb, occ.args(), threads())
    return np.asarray(off), np.asarray(faces)


# --------------------------------------------------------------------------------------
# Codes -> points (JAX, differentiable)
# --------------------------------------------------------------------------------------


class VertexTable(NamedTuple):
    """The table the codes' global vertex refs index, `[light; faces.reshape(-1, 3)]`, kept as
    its two parts: under `vmap` over light poses the faces are not copied per pose."""

    light: Array  # (K, 3)
    faces: Array  # (M * Ko, 3)


def vertex_table(verts: Array, faces: Array) -> VertexTable:
    """The table the codes' global vertex refs index (`VertexTable`: `verts`, then the faces'
    vertices row by row)."""
    return VertexTable(verts, faces.reshape(-1, 3))


def _vertex(V: Array | VertexTable, idx: Array) -> Array:
    """Rows `idx` (clipped to the table) of `V`: an array `(v, 3)` or a `VertexTable`."""
    if not isinstance(V, VertexTable):
        return jnp.take(V, jnp.clip(idx, 0, V.shape[0] - 1), axis=0)
    k, nf = V.light.shape[0], V.faces.shape[0]
    light = jnp.take(V.light, jnp.clip(idx, 0, k - 1), axis=0)
    if nf == 0:
        return light
    face = jnp.take(V.faces, jnp.clip(idx - k, 0, nf - 1), axis=0)
    return jnp.where((idx < k)[..., None], light, face)


def face_frames(faces: Float[Array, "m ko 3"]) -> tuple[Array, Array]:
    """Per face its Newell normal (from coordinates relative to its first vertex) and first
    vertex: what the emitter-plane cut planes of `decode_endpoints` need, computed once a call."""
    first = faces[:, 0]
    return jax.vmap(newell_normal)(faces - first[:, None, :]), first


def decode_endpoints(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    verts: Float[Array, "k 3"],
    V: Float[Array, "v 3"] | VertexTable,
    face_n: Float[Array, "m 3"],
    face_0: Float[Array, "m 3"],
    codes: Int[Array, "e 7"],
) -> Float[Array, "e 3"]:
    r"""The points named by endpoint codes (`csrc/shadowc.cc`), as `jaxshadow._kernels.clip` computes them.

    `V = [verts; faces.reshape(-1, 3)]` is the table the global vertex refs index (an array, or
    the same as a `VertexTable`: `vertex_table`); `face_n`,
    `face_0` from `face_frames`. Codes: `[kind, ...]` with kind 0 a light vertex, 1 a light edge's
    horizon crossing (as `horizon_clip_edges`), 2 a vertex projected from `p` onto the light's
    plane (`_clip._project`), 3 an occluder edge's crossing with that plane, projected, 4 the line
    common to two planes through `p` met with the light's plane (`_clip._crossing_point`; for two
    planes through occluder edges with one common end, the line from `p` through that end; for a
    light edge's plane and another nearly coincident, where that plane meets the edge; for two
    nearly coincident planes through occluder edges, where one meets the other's edge,
    projected: `_kernels.planes.occluder_edges_point`); a
    plane is `(0, a, b)` through `V[a]`, `V[b]`, `(1, ., .)` the horizon, `(2, f, .)` face `f`'s
    cut $N_L = h_p\,\mathrm{sgn}(d_o) N_o + |d_o| N_e$ (`_clip._occluder_regions`). Unused slots
    (kind -1) give the light's first vertex. Differentiable in `p`, `n`, `verts`, `V` (the codes
    carry no gradient).
    """
    k = verts.shape[0]
    vert = functools.partial(_vertex, V)
    e0 = verts[0]
    ne = newell_normal(verts)
    scale = _pow2_scale(jnp.max(jnp.abs(ne)))
    ne = ne * scale
    hp = jnp.dot(ne, p - e0)
    codes = jax.lax.stop_gradient(codes)
    kind = codes[:, 0]

    def take(table: Array, idx: Array) -> Array:
        return jnp.take(table, jnp.clip(idx, 0, table.shape[0] - 1), axis=0)

    i1, i2 = codes[:, 1], codes[:, 2]
    va = vert(i1)
    vb = vert(jnp.where(kind == K_HORIZON, (i1 + 1) % k, i2))
    on_light = (kind == K_HORIZON)[:, None]
    h = jnp.where(on_light, n[None, :], ne[None, :])
    q = jnp.where(on_light, p[None, :], e0[None, :])
    da = jnp.sum((va - q) * h, axis=-1)
    db = jnp.sum((vb - q) * h, axis=-1)
    cross_ok = da != db
    t = jnp.where(cross_ok, da / jnp.where(cross_ok, da - db, 1.0), 0.0)
    x = va + t[:, None] * (vb - va)
    to_project = jnp.where((kind == K_PROJECTED)[:, None], va, x)
    projected = jax.vmap(_project, in_axes=(None, 0, None, None))(p, to_project, ne, hp)
    x = jnp.where(((kind == K_PROJECTED) | (kind == K_EMITTER_CROSS))[:, None], projected,
                  jnp.where((kind == K_LIGHT)[:, None], va, x))

    def plane(t_: Array, a: Array, b: Array) -> Array:
        through = edge_planes(p, vert(a), vert(b))
        fn, f0 = take(face_n, a), take(face_0, a)
        d = jnp.sum(fn * (f0 - p[None, :]), axis=-1)
        cut = (hp * jnp.sign(d))[:, None] * fn + jnp.abs(d)[:, None] * ne[None, :]
        out = jnp.where((t_ == 0)[:, None], through, jnp.where((t_ == 1)[:, None], n[None, :], cut))
        return _rescale_rows(out)

    n1 = plane(codes[:, 1], codes[:, 2], codes[:, 3])
    n2 = plane(codes[:, 4], codes[:, 5], codes[:, 6])
    # Two planes through p and occluder edges with one common end cross on the line from p through
    # it, which their normals' cross product finds only to eps over their angle (`decode.h`).
    a1, b1, a2, b2 = (vert(codes[:, i]) for i in (2, 3, 5, 6))
    same = [jnp.all(u == w, axis=-1).astype(jnp.int32) for u, w in ((a1, a2), (a1, b2), (b1, a2), (b1, b2))]
    common = (codes[:, 1] == 0) & (codes[:, 4] == 0) & (same[0] + same[1] + same[2] + same[3] == 1)
    line = jnp.where(common[:, None], jnp.where((same[0] + same[1] > 0)[:, None], a1, b1) - p[None, :], jnp.cross(n1, n2))
    y = jax.vmap(_crossing_point, in_axes=(None, 0, None, None))(p, line, ne, hp)
    # A light edge's plane through p (the first plane: the engine sorts them) and another nearly
    # coincident with it cross on the edge (`light_edge_point`).
    near = jax.vmap(_near_planes)(n1, n2)
    light = (codes[:, 1] == 0) & (codes[:, 3] < k) & near
    on_edge = jax.vmap(_light_edge_point, in_axes=(None, 0, 0, 0))(p, a1, b1, n2)
    y = jnp.where(light[:, None], on_edge, y)
    # Two occluder edges' planes through p, nearly coincident: on one edge's line
    # (`occluder_edges_point`).
    occ_refs = jnp.all(codes[:, jnp.array([2, 3, 5, 6])] >= k, axis=-1)
    occ = (codes[:, 1] == 0) & (codes[:, 4] == 0) & occ_refs & ~common & near
    # Other rows meet at the light's first vertex (in the emitter plane: a finite gradient).
    a1o, b1o, a2o, b2o = (jnp.where(occ[:, None], x_, e0[None, :]) for x_ in (a1, b1, a2, b2))
    on_line = jax.vmap(_occluder_edges_point, in_axes=(None, 0, 0, 0, 0, 0, 0, None, None))(
        p, a1o, b1o, n1, a2o, b2o, n2, ne, hp
    )
    y = jnp.where(occ[:, None], on_line, y)
    out = jnp.where((kind == K_PLANES)[:, None], y, x)
    return jnp.where((kind == K_UNUSED)[:, None], e0[None, :], out)


def edges_from_codes(
    p: Float[Array, "3"],
    n: Float[Array, "3"],
    verts: Float[Array, "k 3"],
    V: Float[Array, "v 3"] | VertexTable,
    face_n: Float[Array, "m 3"],
    face_0: Float[Array, "m 3"],
    runs: Int[Array, "c 2 7"],
) -> tuple[Float[Array, "c 3"], Float[Array, "c 3"]]:
    """`(starts, ends)` of a receiver's boundary runs (unused slots zero-length at the light's
    first vertex): the edge soup `masked_contour_form_factor` and `contour_specular_kernel` take."""
    pts = decode_endpoints(p, n, verts, V, face_n, face_0, runs.reshape(-1, CODE_WIDTH)).reshape(runs.shape[0], 2, 3)
    return pts[:, 0], pts[:, 1]


# --------------------------------------------------------------------------------------
# Codes inside a compiled program (XLA FFI)
# --------------------------------------------------------------------------------------


def _topology_arrays(topo: OccluderTopology) -> tuple[Array, ...]:
    return tuple(jnp.asarray(a, jnp.int32) for a in (topo.face_solid, topo.face_closed, topo.solid_faces,
                                                      topo.solid_edge_off, topo.solid_edges))


def traced_polygon_codes(
    points: Float[Array | np.ndarray, "N 3"],
    normals: Float[Array | np.ndarray, "N 3"],
    verts: Float[Array | np.ndarray, "k 3"],
    faces: Float[Array | np.ndarray, "m ko 3"],
    topology: OccluderTopology | None,
    capacity: int,
) -> tuple[Int[Array, " N"], Int[Array, " N"], Int[Array, "N c 2 7"]]:
    """`polygon_codes` inside a compiled computation (the engine's XLA FFI handler), for inputs
    that are traced: `(classes (N,), counts (N,), runs (N, capacity, 2, 7))`. Receivers whose
    boundary has more than `capacity` (static) edges have `counts > capacity` and only their first
    `capacity` runs: the caller must detect that (the result is then not exact). Carries no
    gradient (its inputs are stop-gradient'ed). Under `vmap` an input that is not batched is passed
    once (a batch axis of size 1, `vmap_method="expand_dims"`), not copied per batch element."""
    _require_ffi()
    topo = topology if topology is not None else OccluderTopology.independent(faces.shape[0])
    sg = jax.lax.stop_gradient
    n_pts = points.shape[0]
    dt = points.dtype
    call = jax.ffi.ffi_call(
        FFI_TARGET,
        (jax.ShapeDtypeStruct((n_pts,), jnp.int32), jax.ShapeDtypeStruct((n_pts,), jnp.int32),
         jax.ShapeDtypeStruct((n_pts, capacity, 2, CODE_WIDTH), jnp.int32)),
        vmap_method="expand_dims",
    )
    out: Any = call(sg(points), sg(normals.astype(dt)), sg(verts.astype(dt)), sg(faces.astype(dt)), *_topology_arrays(topo),
                cap=np.int64(capacity), threads=np.int64(threads()))
    return out[0], out[1], out[2]


def _require_ffi() -> None:
    ok, why = _ffi_status()
    if not ok:
        raise RuntimeError(f"jaxshadow's XLA FFI handlers are not usable: {why}")


def traced_hard_visibility(
    points: Float[Array | np.ndarray, "N 3"],
    x: Float[Array | np.ndarray, "3"],
    is_point: bool,
    faces: Float[Array | np.ndarray, "m ko 3"],
    topology: OccluderTopology | None,
) -> Int[Array, " N"]:
    """`hard_visibility` inside a compiled computation: `(N,)` int32, 1 where the point light at
    `x` (or the directional light travelling along `x`) is visible. No gradient."""
    _require_ffi()
    topo = topology if topology is not None else OccluderTopology.independent(faces.shape[0])
    sg = jax.lax.stop_gradient
    dt = points.dtype
    call = jax.ffi.ffi_call(FFI_HARD, jax.ShapeDtypeStruct((points.shape[0],), jnp.int32),
                            vmap_method="expand_dims")
    return call(sg(points), sg(x.astype(dt)), sg(faces.astype(dt)), *_topology_arrays(topo),
                is_point=np.int64(bool(is_point)), threads=np.int64(threads()))


def traced_segment_candidates(
    points: Float[Array | np.ndarray, "N 3"],
    a: Float[Array | np.ndarray, "3"],
    b: Float[Array | np.ndarray, "3"],
    faces: Float[Array | np.ndarray, "m ko 3"],
    topology: OccluderTopology | None,
    capacity: int,
) -> tuple[Int[Array, " N"], Int[Array, "N c"]]:
    """`segment_candidates` inside a compiled computation: `(counts (N,), faces (N, capacity))`
    with -1 in unused slots; receivers with `counts > capacity` have only their first
    `capacity` faces (the caller must detect that). No gradient."""
    _require_ffi()
    topo = topology if topology is not None else OccluderTopology.independent(faces.shape[0])
    sg = jax.lax.stop_gradient
    dt = points.dtype
    n_pts = points.shape[0]
    call = jax.ffi.ffi_call(
        FFI_SEGMENT,
        (jax.ShapeDtypeStruct((n_pts,), jnp.int32), jax.ShapeDtypeStruct((n_pts, capacity), jnp.int32)),
        vmap_method="expand_dims",
    )
    ends = jnp.stack([a.astype(dt), b.astype(dt)])
    out: Any = call(sg(points), sg(ends), sg(faces.astype(dt)), *_topology_arrays(topo), cap=np.int64(capacity),
                    threads=np.int64(threads()))
    return out[0], out[1]
