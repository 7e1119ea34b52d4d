r"""Exact shadows at scale: plan on the host, then integrate only what each receiver needs.

Campbell & Fussell's pipeline (§4.2-4.3) with the shadow engine of `binding` (`csrc/shadowc.cc`)
as the shadow data. For every light the engine classifies each receiver and returns exactly the
visibility information its class needs, and one integrand (`Lambert` for irradiance, `Phong` for
the specular term) consumes it:

- **Polygon lights.** `LIT` receivers take the unoccluded kernel; `UMBRA` receivers and those
  behind the light or below its horizon (`ZERO`) get exactly 0 without clipping; `PENUMBRA`
  receivers integrate over the boundary of their visible region, computed by the engine from
  their candidate occluders only, grouped by edge count into power-of-two capacities (one
  compiled contour integral per capacity and block size). Memory is bounded by the block sizes,
  not by the number of occluders, and no receiver has too many candidates (the engine has no
  capacity).
- **Segment lights.** The engine takes the faces that meet each receiver's light triangle
  (Poulin §4.2), unites the intervals of the segment they hide and returns the visible pieces,
  each bounded by the crossing of a contour edge's plane through the receiver (or a face plane,
  or the segment's end): receivers are grouped by their number of pieces, and JAX integrates
  the segment's kernel over them (`segment_pieces`). With `JAXSHADOW_SEGMENT_PIECES=0` (the
  reference path) receivers are grouped by their candidate faces and the segment is clipped
  against those faces (`_clip.visible_segments`).
- **Point and directional lights.** Hard shadows from the engine's ray tests against its
  hierarchy, times the unoccluded kernel.

Three ways to run the same plan, chosen once by `evaluators.choose` from what the inputs are:

- `host_values`: every input concrete and nothing differentiated. The engine also decodes the
  boundary's points (in C++, with the formulas of `binding.decode_endpoints`), JAX only
  integrates.
- `planned_values`: the inputs carry derivatives but have concrete values (`jax.grad` or
  `jax.jacfwd` called eagerly). The engine plans from the values; the boundary's points are
  decoded from its codes in JAX, so derivatives flow to receivers, normals, light and occluder
  vertices (the codes, piecewise constant, carry none).
- `traced_values` (`compiled`): the values are abstract (inside `jax.jit` or `jax.vmap`). The engine runs
  inside the compiled program (XLA FFI) with a static number of boundary edges per receiver
  (`ShadowOptions.capacity`); receivers over it are reported (`overflow`), never silently
  truncated: the public functions raise, the inverse solvers retry with a larger capacity.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._scene.model import LinearLight, Scene
from . import binding as vis
from . import segment_pieces
from .integrands import PRODUCE, segment_visible

# Receivers per engine call (bounds the host memory of codes and edges) and edge (or occluder)
# slots per compiled block: receivers per block = EDGE_BLOCK // capacity.
HOST_CHUNK = 1 << 18
EDGE_BLOCK = 1 << 18
MIN_BLOCK = 64
MIN_CAPACITY = 8


def occluders_of(scene: Scene) -> Any:
    """The scene's padded occluder faces `(m, K, 3)` (the shadow engine needs a scene with them)."""
    assert scene.occluders is not None, "the shadow engine needs a scene with occluders"
    return scene.occluders


# --------------------------------------------------------------------------------------
# The plan (host)
# --------------------------------------------------------------------------------------

KIND_CLASSES = {"polygon": vis.CLASS_NAMES, "segment": ("zero", "free", "hidden", "candidates"),
                "point": ("", "visible", "blocked", ""), "directional": ("", "visible", "blocked", "")}


@dataclass
class LightPlan:
    """The engine's answer for one light and a batch of receivers.

    `classes (N,)`: polygon lights `ZERO` (0: behind the light or below the horizon), `LIT` (1),
    `UMBRA` (2), `PENUMBRA` (3); segment lights 1 (nothing hidden), 2 (all hidden: visible
    pieces only) or 3 (visible pieces: `runs (R, 2)` endpoint codes, `segment_pieces`; or, on the
    reference path, some face meets the light triangle: candidate `faces`);
    point and directional lights 1 (visible) or 2 (blocked). `candidates (N,)`: items the
    hierarchy returned for the receiver (polygon lights; a convex closed mesh counts once; on the
    face path, those of its receiver group's list that pass its own tests: the count, unlike the
    classes and boundaries, may differ with `JAXSHADOW_THREADS`, as groups end at the engine's
    blocks of receivers), or,
    for receivers the engine's silhouette path served (large meshes without convex solids, every
    occluder between the receiver and the light), the contour edges in its pyramid; `kept (N,)`:
    occluder regions kept after the exact tests (1 on the silhouette path; 0 for an umbra
    receiver that a body inside a mesh showed umbra before any region was built) or faces that
    meet the light triangle (segment lights). Polygon lights: penumbra receiver i's boundary edges
    are rows `offsets[i]:offsets[i + 1]` of `runs (R, 2, 7)` (endpoint codes) and/or `points
    (R, 2, 3)`; receivers of the other classes have none (a lit one takes the unoccluded kernel)."""

    kind: str
    classes: np.ndarray
    candidates: np.ndarray | None = None
    kept: np.ndarray | None = None
    offsets: np.ndarray | None = None
    runs: Any = None
    points: Any = None
    faces: Any = None  # segment lights: candidate faces (CSR with `offsets`), np.ndarray
    lambert: Any = None  # polygon lights with `points`: each receiver's sum of Lambert's edge terms
    seconds: float = 0.0
    produce: str = "classes"  # what was asked for (`integrands.PRODUCE`)

    @property
    def on_host(self) -> bool:
        """The plan was made for concrete values, nothing differentiated (`host_values`): the
        values it leads to are NumPy arrays and polygon boundaries come decoded (or summed)."""
        return self.produce != "codes"

    @property
    def counts(self) -> np.ndarray:
        assert self.offsets is not None
        return np.diff(self.offsets)


@dataclass
class ShadowPlan:
    """What the shadow engine decided for a scene and a batch of receivers (`shadow_plan`).

    `lights`: one `LightPlan` per light of the scene, in order. `n_faces`: occluder faces after
    mesh merging; `n_solids`: convex closed meshes (each tested as one blocker through its
    silhouette); `seconds`: engine time of the whole plan."""

    lights: list[LightPlan]
    n_receivers: int
    n_faces: int
    n_solids: int
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def classes(self) -> list[np.ndarray]:
        return [lp.classes for lp in self.lights]

    def summary(self) -> dict:
        """Counts and fractions per class, candidate-list and boundary sizes, per light."""
        out: dict[str, Any] = {"receivers": self.n_receivers, "faces": self.n_faces, "solids": self.n_solids,
                               "seconds": self.seconds, "lights": []}
        for lp in self.lights:
            names = KIND_CLASSES[lp.kind]
            counts = np.bincount(lp.classes, minlength=4)
            d: dict = {"kind": lp.kind, "seconds": lp.seconds,
                       "classes": {names[c]: int(counts[c]) for c in range(4) if names[c]},
                       "fractions": {names[c]: float(counts[c]) / max(1, self.n_receivers) for c in range(4) if names[c]}}
            for key, arr in (("candidates", lp.candidates), ("kept", lp.kept)):
                if arr is not None and arr.size:
                    d[key] = {"mean": float(arr.mean()), "max": int(arr.max())}
            if lp.kind == "segment" and lp.faces is None and lp.offsets is not None:
                pen = lp.counts[lp.classes == vis.PENUMBRA]
                d["penumbra_pieces"] = {"mean": float(pen.mean()) if pen.size else 0.0,
                                        "max": int(pen.max()) if pen.size else 0}
            if lp.kind == "polygon" and lp.offsets is not None:
                c = lp.counts
                pen = c[lp.classes == vis.PENUMBRA]
                d["penumbra_edges"] = {"mean": float(pen.mean()) if pen.size else 0.0, "max": int(pen.max()) if pen.size else 0}
            out["lights"].append(d)
        return out


def host_occluders(scene: Scene, dtype: Any) -> vis.HostOccluders:
    return vis.HostOccluders.of(np.asarray(scene.occluders), scene.occluder_topology, dtype)


def _plan_polygon(light: Any, points: np.ndarray, normals: np.ndarray, occ: vis.HostOccluders,
                  produce: str) -> LightPlan:
    pc = vis.polygon_codes(points, normals, np.asarray(light.vertices, points.dtype), occ, codes=produce == "codes",
                           decoded=produce == "points", lambert=produce == "lambert")
    return LightPlan("polygon", pc.classes, pc.stats[:, 0], pc.stats[:, 1], pc.offsets, pc.runs, pc.points,
                     lambert=pc.lambert, produce=produce)


def _plan_segment(light: Any, points: np.ndarray, normals: np.ndarray, occ: vis.HostOccluders,
                  produce: str) -> LightPlan:
    dt = points.dtype
    a, b = np.asarray(light.start, dt), np.asarray(light.end, dt)
    if segment_pieces.enabled():
        cls, kept, off, pieces = segment_pieces.host_pieces(points, a, b, occ)
        return LightPlan("segment", cls, kept=kept, offsets=off, runs=pieces, produce=produce)
    off, faces = vis.segment_candidates(points, a, b, occ)
    cnt = np.diff(off).astype(np.int32)
    cls = np.where(cnt > 0, vis.PENUMBRA, vis.LIT).astype(np.int32)
    return LightPlan("segment", cls, kept=cnt, offsets=off, faces=faces, produce=produce)


def _plan_hard(light: Any, points: np.ndarray, normals: np.ndarray, occ: vis.HostOccluders,
               produce: str) -> LightPlan:
    x = np.asarray(light.geometry[0], points.dtype)
    visible = vis.hard_visibility(points, x, light.kind == "point", occ)
    return LightPlan(light.kind, np.where(visible, vis.LIT, vis.UMBRA).astype(np.int32), produce=produce)


# What the engine computes for each kind of light (`AbstractLight.kind`).
_PLANNERS = {"polygon": _plan_polygon, "segment": _plan_segment, "point": _plan_hard, "directional": _plan_hard}


def plan(scene: Scene, points: np.ndarray, normals: np.ndarray, *, produce: str,
         lights: Sequence[Any] | None = None) -> ShadowPlan:
    """Run the engine for every light of `scene` (or `lights`) on concrete receivers (unit
    `normals`); `produce` (`integrands.PRODUCE`): what polygon lights' plans carry for their
    penumbra receivers."""
    assert produce in PRODUCE, produce
    occ = host_occluders(scene, points.dtype)
    t_all = time.perf_counter()
    out = []
    for light in scene.lights if lights is None else lights:
        t = time.perf_counter()
        lp = _PLANNERS[light.kind](light, points, normals, occ, produce)
        lp.seconds = time.perf_counter() - t
        out.append(lp)
    return ShadowPlan(out, points.shape[0], occ.faces.shape[0], occ.topology.n_solids, time.perf_counter() - t_all)


# --------------------------------------------------------------------------------------
# Blocks: few compiled shapes, bounded memory
# --------------------------------------------------------------------------------------


def _next_pow2(n: int, lo: int) -> int:
    c = lo
    while c < n:
        c *= 2
    return c


def capacity_groups(counts: np.ndarray, idx: np.ndarray) -> list[tuple[int, np.ndarray]]:
    """Receivers `idx` grouped by the power of two (>= `MIN_CAPACITY`) that holds their count."""
    if idx.size == 0:
        return []
    c = np.maximum(counts[idx], 1)
    caps = np.maximum(MIN_CAPACITY, 2 ** np.ceil(np.log2(c)).astype(np.int64))
    return [(int(cap), idx[caps == cap]) for cap in np.unique(caps)]


def _blocks(n: int, rows: int) -> list[tuple[int, int, int]]:
    """`(start, stop, padded size)` blocks of at most `rows` rows, sizes powers of two >= MIN_BLOCK."""
    out = []
    for s in range(0, n, rows):
        e = min(n, s + rows)
        size = max(e - s, min(rows, _next_pow2(e - s, MIN_BLOCK)))
        out.append((s, e, size))
    return out


def _pad_rows(a: Any, size: int) -> Any:
    if a is None:
        return None
    m = a.shape[0]
    if size == m:
        return a
    xp = jnp if isinstance(a, jax.Array) else np
    return xp.concatenate([a, xp.broadcast_to(a[:1], (size - m,) + a.shape[1:])])


def _dispatch_blocks(fn: Any, arrays: tuple, rows: int) -> Any:
    """Dispatch `fn(*blocks)` over the leading axis of NumPy `arrays` in padded blocks now
    (JAX runs them asynchronously); the returned function waits for them and joins the
    unpadded results as one NumPy array."""
    n = arrays[0].shape[0]
    pending = [(e - s, fn(*(_pad_rows(_rows(a, slice(s, e)), size) for a in arrays)))
               for s, e, size in _blocks(n, rows)]

    def result() -> np.ndarray:
        outs = [np.asarray(out)[:m] for m, out in pending]
        if not outs:
            return np.zeros((0,), arrays[0].dtype)
        return outs[0] if len(outs) == 1 else np.concatenate(outs)

    return result


def _map_blocks(fn: Any, arrays: tuple, rows: int) -> Any:
    """`fn(*blocks)` over the leading axis in padded blocks; concatenated, unpadded. With NumPy
    inputs (concrete values) the results are cut and joined in NumPy: slicing a JAX array
    compiles a slice for every distinct block length."""
    if all(isinstance(a, np.ndarray) for a in arrays if a is not None):
        return _dispatch_blocks(fn, arrays, rows)()
    n = arrays[0].shape[0]
    outs = []
    for s, e, size in _blocks(n, rows):
        outs.append(fn(*(_pad_rows(_rows(a, slice(s, e)), size) for a in arrays))[: e - s])
    if not outs:
        return jnp.zeros((0,), arrays[0].dtype)
    return outs[0] if len(outs) == 1 else jnp.concatenate(outs)


def _dense_rows(offsets: np.ndarray, idx: np.ndarray, cap: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows into a CSR table for receivers `idx`, `(n, cap)`, and the mask of used slots."""
    counts = np.diff(offsets)[idx]
    slot = np.arange(cap)
    used = slot[None, :] < counts[:, None]
    return np.where(used, offsets[idx][:, None] + slot[None, :], 0), used


# Compiled pieces, one light and one block. Each is jitted once per (integrand type, shapes).


def _on_lit_side_host(p: np.ndarray, verts: np.ndarray) -> np.ndarray:
    """`_geometry.on_lit_side` for concrete receivers `(N, 3)`, in float64: the light's normal
    from its vertices relative to the first, each set divided by its largest component (raw
    products overflowed in float32 beyond 1e19 and underflowed below 1e-19: penumbra values 0)."""
    v = np.asarray(verts, np.float64)
    rel = v - v[0]
    rel = rel / max(float(np.max(np.abs(rel))), np.finfo(np.float64).tiny)
    ne = np.sum(np.cross(rel, np.roll(rel, -1, axis=0)), axis=0)
    w = np.asarray(p, np.float64) - v[0]
    t = np.max(np.abs(w), axis=1, keepdims=True)
    return (w / np.where(t > 0, t, 1.0)) @ ne > 0


@jax.jit
def _lit_block(integ, p, n, e, verts):
    return jax.vmap(integ.polygon, in_axes=(0, 0, 0, None))(p, n, e, verts)


@jax.jit
def _contour_block(integ, p, n, e, verts, starts, ends):
    return jax.vmap(integ.contour, in_axes=(0, 0, 0, None, 0, 0))(p, n, e, verts, starts, ends)


@jax.jit
def _decoded_block(integ, p, n, e, verts, faces, runs):
    fn, f0 = vis.face_frames(faces)
    table = vis.vertex_table(verts, faces)

    def one(p_, n_, e_, r_):
        s, t = vis.edges_from_codes(p_, n_, verts, table, fn, f0, r_)
        return integ.contour(p_, n_, e_, verts, s, t)

    return jax.vmap(one)(p, n, e, runs)


@functools.partial(jax.jit, static_argnames=("light",))
def _segment_free_block(integ, light, p, n, e, a, b):
    return jax.vmap(integ.segment, in_axes=(0, 0, 0, None, None, None))(p, n, e, a, b, light)


@functools.partial(jax.jit, static_argnames=("light",))
def _segment_block(integ, light, p, n, e, a, b, occ):
    return jax.vmap(segment_visible, in_axes=(None, 0, 0, 0, None, None, None, 0))(integ, p, n, e, a, b, light, occ)


@functools.partial(jax.jit, static_argnames=("light",))
def _pieces_block(integ, light, p, n, e, a, b, faces, codes):
    return jax.vmap(segment_pieces.pieces_value, in_axes=(None, 0, 0, 0, None, None, None, None, 0))(
        integ, p, n, e, a, b, light, faces, codes)


@functools.partial(jax.jit, static_argnames=("kind",))
def _hard_block(integ, p, n, e, x, visible, kind):
    kern = getattr(integ, kind)  # the integrand's method for this kind of light
    g = jax.vmap(kern, in_axes=(0, 0, 0, None))(p, n, e, x)
    return jnp.where(visible, g, 0.0)


# jit with a static `light` needs it hashable: LinearLight is an eqx.Module of arrays, so pass
# a hashable stand-in carrying what the integrands read (profile and exponent).
@dataclass(frozen=True)
class SegmentProfile:
    profile: str
    exponent: int


def segment_profile(light: LinearLight) -> SegmentProfile:
    """The hashable stand-in of a segment light that jitted blocks take as a static argument."""
    return SegmentProfile(light.profile, int(light.exponent))


# --------------------------------------------------------------------------------------
# Evaluation from a plan (eager: concrete values, possibly carrying derivatives)
# --------------------------------------------------------------------------------------


def _scatter(n: int, dt: Any, parts: list[tuple[Any, Any]], concrete: bool) -> Any:
    if concrete:
        out = np.zeros(n, dt)
        for idx, vals in parts:
            out[idx] = np.asarray(vals)
        return out
    res = jnp.zeros(n, dt)
    for idx, vals in parts:
        res = res.at[jnp.asarray(idx)].set(vals)
    return res


def _take(a: Any, idx: np.ndarray) -> Any:
    # np.take: rows of an (N, 3) array gathered ~4x faster than a[idx]. None (no eyes) stays None.
    if a is None:
        return None
    return np.take(a, idx, axis=0) if isinstance(a, np.ndarray) else jnp.take(a, jnp.asarray(idx), axis=0)


def _rows(a: Any, key: Any) -> Any:
    """`a[key]`, None for None (the eyes of an integrand that reads none)."""
    return None if a is None else a[key]


def _polygon_values(lp: LightPlan, light: Any, integ: Any, p: Any, n: Any, e: Any, faces: Any,
                    unoccluded: Any, parts: list) -> None:
    N = lp.classes.shape[0]
    dt = p.dtype
    concrete = lp.on_host
    rows = EDGE_BLOCK // 8
    verts = np.asarray(light.vertices, dt) if concrete else light.vertices.astype(dt)
    is_lit = lp.classes == vis.LIT
    lit = np.nonzero(is_lit)[0] if unoccluded is None else None
    if unoccluded is not None:
        # Dispatched before the engine ran (they overlap); a receiver that is not lit is
        # masked (and a penumbra receiver overwritten below).
        parts.append((slice(None), np.where(is_lit, unoccluded(), 0.0)))
    elif concrete and 2 * np.count_nonzero(is_lit) > N:
        # Mostly lit: the unoccluded kernel on every receiver costs less than gathering the
        # lit ones (a gather moves as many bytes as the kernel reads); the others are masked
        # (and the penumbra receivers overwritten below). Not with derivatives: a masked
        # receiver's cotangent is zero, but 0 * a singular kernel derivative is not.
        every = _map_blocks(lambda a, b, c: _lit_block(integ, a, b, c, verts), (p, n, e), rows)
        parts.append((np.arange(N), np.where(is_lit, np.asarray(every), 0.0)))
    elif lit is not None and lit.size:
        parts.append((lit, _map_blocks(lambda a, b, c: _lit_block(integ, a, b, c, verts),
                                       (_take(p, lit), _take(n, lit), _take(e, lit)), rows)))
    pen = np.nonzero(lp.classes == vis.PENUMBRA)[0]
    if lp.produce == "lambert" and pen.size:
        # Lambert's contour sum is a sum of edge terms (Lambert.contour = pi * (-sum / 2 pi)):
        # the engine adds them up, in double, as it decodes the edges (`edge_term`'s formula).
        assert lp.lambert is not None
        f = lp.lambert[pen]
        lit_side = _on_lit_side_host(np.asarray(_take(p, pen)), np.asarray(verts))
        parts.append((pen, np.where(lit_side, -0.5 * f, 0.0).astype(dt)))
        pen = pen[:0]
    for cap, idx in capacity_groups(lp.counts, pen):
        r, used = _dense_rows(lp.offsets, idx, cap)
        rb = max(MIN_BLOCK, EDGE_BLOCK // cap)
        if concrete:
            pts = np.where(used[:, :, None, None], lp.points[r], np.asarray(verts)[0])
            fn = lambda a, b, c, s, t: _contour_block(integ, a, b, c, verts, s, t)  # noqa: E731
            vals = _map_blocks(fn, (p[idx], n[idx], _rows(e, idx), np.ascontiguousarray(pts[:, :, 0]),
                                    np.ascontiguousarray(pts[:, :, 1])), rb)
        else:
            runs = np.where(used[:, :, None, None], lp.runs[r], vis.unused_code())
            fn = lambda a, b, c, rr: _decoded_block(integ, a, b, c, verts, faces, rr)  # noqa: E731
            vals = _map_blocks(fn, (_take(p, idx), _take(n, idx), _take(e, idx), runs), rb)
        parts.append((idx, vals))


def _segment_values(lp: LightPlan, light: Any, integ: Any, p: Any, n: Any, e: Any, faces: Any,
                    unoccluded: Any, parts: list) -> None:
    dt = p.dtype
    rows = EDGE_BLOCK // 8
    a, b = light.start.astype(dt), light.end.astype(dt)
    prof = segment_profile(light)
    free = np.nonzero(lp.classes == vis.LIT)[0]
    if free.size:
        parts.append((free, _map_blocks(lambda x, y, z: _segment_free_block(integ, prof, x, y, z, a, b),
                                        (_take(p, free), _take(n, free), _take(e, free)), rows)))
    pen = np.nonzero(lp.classes == vis.PENUMBRA)[0]
    if lp.faces is None:
        # Visible pieces (`segment_pieces`): umbra receivers keep their 0.
        fj = jnp.asarray(faces)
        for cap, idx in capacity_groups(lp.counts, pen):
            r, used = _dense_rows(lp.offsets, idx, cap)
            codes = np.where(used[:, :, None], lp.runs[r], segment_pieces.START).astype(np.int32)
            rb = max(MIN_BLOCK, (EDGE_BLOCK // 8) // cap)
            parts.append((idx, _map_blocks(lambda x, y, z, c: _pieces_block(integ, prof, x, y, z, a, b, fj, c),
                                           (_take(p, idx), _take(n, idx), _take(e, idx), codes), rb)))
        return
    for cap, idx in capacity_groups(lp.kept, pen):
        r, used = _dense_rows(lp.offsets, idx, cap)
        # Unused slots repeat the receiver's first candidate: the union of the blocked
        # intervals, and so the value and its derivatives, are unchanged.
        fidx = lp.faces[np.where(used, r, r[:, :1])]
        occ = _take(faces, fidx.reshape(-1)).reshape(fidx.shape + faces.shape[1:])
        rb = max(MIN_BLOCK, (EDGE_BLOCK // 16) // cap)
        parts.append((idx, _map_blocks(lambda x, y, z, o: _segment_block(integ, prof, x, y, z, a, b, o),
                                       (_take(p, idx), _take(n, idx), _take(e, idx), occ), rb)))


def _hard_values(lp: LightPlan, light: Any, integ: Any, p: Any, n: Any, e: Any, faces: Any,
                 unoccluded: Any, parts: list) -> None:
    x = light.geometry[0].astype(p.dtype)
    visible = lp.classes == vis.LIT
    vals = _map_blocks(lambda a, b, c, v: _hard_block(integ, a, b, c, x, v, lp.kind), (p, n, e, visible),
                       EDGE_BLOCK // 8)
    parts.append((np.arange(lp.classes.shape[0]), vals))


_VALUES = {"polygon": _polygon_values, "segment": _segment_values, "point": _hard_values,
           "directional": _hard_values}


def light_values(lp: LightPlan, light: Any, integ: Any, p: Any, n: Any, e: Any, faces: Any,
                 unoccluded: Any = None) -> Any:
    """`(N,)` contribution per unit emission of one light, from its plan.

    A plan made on the host (`lp.on_host`: every input a NumPy array, nothing differentiated)
    holds the engine's Lambert edge sums (`"lambert"`) or decoded points (`"points"`); the result
    is a NumPy array. `e`: `(N, 3)` eyes, or None for an integrand that reads none. Otherwise
    (`"codes"`) `p`, `n`, `e`, the light and `faces` may carry
    derivatives and polygon boundaries are decoded from the plan's codes in JAX. `unoccluded`
    (host polygon lights): a function that returns the unoccluded values of every receiver,
    dispatched before the plan was made (`_dispatch_blocks`)."""
    parts: list[tuple[Any, Any]] = []  # (receiver indices, or a slice of all when concrete; values)
    _VALUES[lp.kind](lp, light, integ, p, n, e, faces, unoccluded, parts)
    return _scatter(lp.classes.shape[0], p.dtype, parts, lp.on_host)


@jax.jit
def _weighted_sum(gs: Any, emissions: Any) -> Any:
    total = jnp.zeros((gs.shape[1], 3), gs.dtype)
    for light in range(gs.shape[0]):
        total = total + gs[light][:, None] * emissions[light][None, :]
    return jnp.where(total == 0, jnp.zeros_like(total), total)


def sum_lights(gs: np.ndarray, lights: Sequence[Any], dt: Any) -> Any:
    """`(N, 3)` JAX array: `sum_l gs[l, :, None] * emission_l` for concrete per-light values
    `gs (L, N)`, accumulated from zero in light order in one compiled call; a zero is +0 (as
    NumPy's `0 + x` gives it)."""
    emissions = np.asarray([np.asarray(light.emission(dt)) for light in lights], dt).reshape(-1, 3)
    return _weighted_sum(gs, emissions)


def host_values(scene: Scene, integ: Any, points: np.ndarray, normals: np.ndarray, eyes: np.ndarray | None) -> Any:
    """`(N, 3)` JAX array for concrete inputs, nothing differentiated (unit `normals`; `eyes`
    `(N, 3)` for the integrands that read an eye, None for the others)."""
    dt = points.dtype
    faces = np.asarray(scene.occluders, dt)
    gs = np.zeros((len(scene.lights), points.shape[0]), dt)
    rows = EDGE_BLOCK // 8
    for s in range(0, points.shape[0], HOST_CHUNK):
        sl = slice(s, min(points.shape[0], s + HOST_CHUNK))
        # Every polygon light's unoccluded values, dispatched first: JAX computes them while the
        # engine (which releases the GIL) classifies the receivers.
        early = {}
        for j, light in enumerate(scene.lights):
            if light.kind == "polygon":
                verts = np.asarray(light.vertices, dt)
                early[j] = _dispatch_blocks(lambda a, b, c, v=verts: _lit_block(integ, a, b, c, v),
                                            (points[sl], normals[sl], _rows(eyes, sl)), rows)
        pl = plan(scene, points[sl], normals[sl], produce=integ.host_plan)
        for j, (lp, light) in enumerate(zip(pl.lights, scene.lights, strict=True)):
            gs[j, sl] = np.asarray(light_values(lp, light, integ, points[sl], normals[sl], _rows(eyes, sl), faces,
                                                early.get(j)))
    return sum_lights(gs, scene.lights, dt)


def planned_values(scene: Scene, value_scene: Scene, integ: Any, points: Any, normals: Any, eyes: Any,
                   values: tuple) -> Any:
    """`(N, 3)` for inputs that carry derivatives but have concrete values (`value_scene`: the
    scene with NumPy leaves; `values`: points and unit normals as NumPy arrays): the engine
    plans from the values, JAX differentiates `scene`, `points`, `normals`, `eyes` (None for an
    integrand that reads no eye)."""
    p_val, n_val = values
    dt = points.dtype
    faces = occluders_of(scene).astype(dt)
    total = jnp.zeros(points.shape, dt)
    for s in range(0, points.shape[0], HOST_CHUNK):
        stop = min(points.shape[0], s + HOST_CHUNK)
        pl = plan(value_scene, p_val[s:stop], n_val[s:stop], produce="codes")
        part = jnp.zeros((stop - s, 3), dt)
        for lp, light in zip(pl.lights, scene.lights, strict=True):
            g = light_values(lp, light, integ, points[s:stop], normals[s:stop], _rows(eyes, slice(s, stop)), faces)
            part = part + g[:, None] * light.emission(dt)[None, :]
        total = total.at[s:stop].set(part) if points.shape[0] > HOST_CHUNK else part
    return total


def shadow_plan(scene: Scene, points: Any, normals: Any) -> ShadowPlan:
    """What the shadow engine decides for `scene` at concrete receivers: per light, the class
    of every receiver, its candidate occluders and the size of its visible region's boundary.

    **Arguments:**

    - `scene`: a `Scene` with occluders.
    - `points`, `normals`: `(N, 3)` concrete receivers and normals (any length, not zero).

    **Returns:** `ShadowPlan` (`.lights[i].classes`, `.summary()` with counts and fractions per
    class, candidate-list and boundary sizes, and the engine's time).

    Raises `ValueError` without occluders or for traced inputs, `RuntimeError` when the engine
    (`jaxshadow._shadows._shadowc`) is not built.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js

        light = js.PolygonLight([[0, 0, 2], [0, 1, 2], [1, 1, 2], [1, 0, 2]], radiance=1.0)
        scene = js.Scene([light], occluders=[[[0.2, 0.2, 1.0], [0.8, 0.2, 1.0], [0.8, 0.8, 1.0], [0.2, 0.8, 1.0]]])
        xy = np.stack(np.meshgrid(np.linspace(-1, 2, 30), np.linspace(-1, 2, 30)), -1).reshape(-1, 2)
        p = np.c_[xy, np.zeros(len(xy))]; n = np.tile([0.0, 0.0, 1.0], (len(p), 1))
        plan = js.shadow_plan(scene, p, n)
        print(plan.summary())   # receivers per class (lit / umbra / penumbra), candidates, boundary sizes
        ```
    """
    from .._core.geometry import check_points_normals

    if not isinstance(scene, Scene):
        raise ValueError(f"shadow_plan: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    if scene.occluders is None:
        raise ValueError("shadow_plan: the scene has no occluders.")
    p, n = check_points_normals(points, normals, "shadow_plan")
    leaves = jax.tree_util.tree_leaves((scene, p, n))
    if any(isinstance(x, jax.core.Tracer) for x in leaves):
        raise ValueError("shadow_plan: needs concrete values (it runs on the host, before any compiled code).")
    p = np.asarray(p)
    n = np.asarray(n)
    n = n / np.linalg.norm(n, axis=1, keepdims=True)
    return plan(scene, p, n, produce="classes")
