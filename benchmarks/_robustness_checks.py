"""The checks of `benchmarks.mesh_robustness`: one scene's values against the tests' brute-force
references, per light kind, and the entry points (plan, cache, mesher, gradients) on it.

References (no code shared with the engine): `test_clip.reference_ff` (exact polygon booleans in
shapely, Lambert's sum in NumPy) over the faces `test_plan.culled` keeps and the documented
on-surface rule leaves (`test_properties_mesh._off_surface`, 2^-44 S for float64 faces); point
and directional lights: `test_clip.ray_blocked_np` on the segment to the light; segment lights:
`test_clip.reference_linear` (Gauss-Legendre on the visible intervals found by bisection on the
same ray test). Errors are `|E - ref| / max(U, 1e-3 max U)`, U the unoccluded value.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

TESTS = str(Path(__file__).resolve().parent.parent / "tests")
ON_SURFACE_64 = 2.0**-44


def refs() -> Any:
    """The tests' reference helpers (`tests/` on the path)."""
    if TESTS not in sys.path:
        sys.path.insert(0, TESTS)
    import test_clip
    import test_plan
    import test_properties_mesh

    return test_clip, test_plan, test_properties_mesh


def pick(cls: np.ndarray, n: int, seed: int = 11) -> np.ndarray:
    """About `n` receiver indices: half penumbra, a fifth umbra, a tenth lit, the rest any."""
    from jaxshadow._shadows import binding as vis

    rng = np.random.default_rng(seed)
    out = []
    for c, k in ((vis.PENUMBRA, n // 2), (vis.UMBRA, n // 5), (vis.LIT, n // 10)):
        idx = np.where(cls == c)[0]
        out.append(rng.choice(idx, min(k, len(idx)), replace=False))
    sel = np.unique(np.concatenate(out)).astype(np.int64)
    rest = np.setdiff1d(np.arange(len(cls)), sel)
    more = rng.choice(rest, min(n - len(sel), len(rest)), replace=False) if n > len(sel) else np.zeros(0, np.int64)
    return np.sort(np.concatenate([sel, more]).astype(np.int64))


def _err(e: np.ndarray, ref: np.ndarray, unocc: np.ndarray) -> float:
    if not len(e):
        return 0.0
    floor = 1e-3 * max(float(np.abs(unocc).max()), 1e-300)
    return float(np.max(np.abs(e - ref) / np.maximum(np.abs(unocc), floor)))


def polygon_reference(light_v: np.ndarray, tris: np.ndarray, p: np.ndarray, n: np.ndarray,
                      batched: bool = True) -> np.ndarray:
    """E / L (pi F) of the visible part of the polygon light at each receiver: `reference_ff` on
    the faces `culled` keeps and `_off_surface` leaves, or (`batched`) `reference_ff_batched`, the
    same computation with the faces clipped and projected as arrays."""
    tc, tp, tm = refs()
    out = np.zeros(len(p))
    for i, (x, y) in enumerate(zip(p, n, strict=True)):
        y = y / np.linalg.norm(y)
        faces = tm._off_surface(x, tp.culled(x, y, light_v, tris), ON_SURFACE_64) if len(tris) else []
        if batched:
            out[i] = np.pi * reference_ff_batched(x, y, light_v, np.asarray(faces, np.float64).reshape(-1, 3, 3))
        else:
            out[i] = np.pi * tc.reference_ff(x, y, light_v, faces)
    return out


def _clip_many(poly: np.ndarray, cnt: np.ndarray, q: np.ndarray, nrm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`scenes.clip_halfspace` (the part with `nrm . (x - q) >= 0`, the same arithmetic in the same
    order) on many polygons at once: `poly (m, k, 3)` holding `cnt (m,)` vertices each. Returns the
    clipped polygons, padded, and their vertex counts."""
    m, k, _ = poly.shape
    d = nrm[0] * (poly[..., 0] - q[0]) + nrm[1] * (poly[..., 1] - q[1]) + nrm[2] * (poly[..., 2] - q[2])
    i = np.arange(k)[None, :]
    valid = i < cnt[:, None]
    nxt = np.where(i + 1 < cnt[:, None], i + 1, 0)
    db = np.take_along_axis(d, nxt, axis=1)
    b = np.take_along_axis(poly, nxt[..., None], axis=1)
    keep_a = (d >= 0) & valid
    cut = ((d >= 0) != (db >= 0)) & valid
    with np.errstate(divide="ignore", invalid="ignore"):  # edges not cut: their t is not used
        t = d / (d - db)
        x = poly + t[..., None] * (b - poly)
    per = keep_a.astype(np.int64) + cut
    start = np.cumsum(per, axis=1) - per
    new = per.sum(axis=1)
    out = np.zeros((m, max(int(new.max(initial=0)), 1), 3))
    r, c = np.nonzero(keep_a)
    out[r, start[r, c]] = poly[r, c]
    r, c = np.nonzero(cut)
    out[r, start[r, c] + keep_a[r, c]] = x[r, c]
    return out, new


def reference_ff_batched(p: np.ndarray, n: np.ndarray, emitter: np.ndarray, tris: np.ndarray) -> float:
    """`test_clip.reference_ff` (form factor of the visible part of `emitter`, float64, exact
    polygon booleans in shapely) with the occluders `tris (m, 3, 3)` clipped to the emitter's lit
    side and the pyramid over the square around it, and projected, as arrays (`_clip_many`) rather
    than one by one: the same polygons up to the rounding of the projection's dot products, then
    the same snap-rounded overlay and Lambert's sum."""
    import shapely


    tc, _, _ = refs()
    p = np.asarray(p, np.float64)
    n = np.asarray(n, np.float64)
    em = np.asarray(emitter, np.float64)
    fr = tc.emitter_frame(p, n, em)
    if fr is None:
        return 0.0
    ne, e0, hp, u, v, corners = fr.ne, fr.e0, fr.hp, fr.u, fr.v, fr.corners
    poly, cnt = _clip_many(np.asarray(tris, np.float64).reshape(-1, 3, 3), np.full(len(tris), 3), e0, ne)
    for i in range(4):
        # Clipped to fewer than three vertices by one of these planes: dropped, as by `reference_ff`.
        a, b = corners[i], corners[(i + 1) % 4]
        poly, cnt = _clip_many(poly, cnt, p, np.cross(b - p, a - p))
        live = cnt >= 3
        poly, cnt = poly[live], cnt[live]
    shadows: list[Any] = []
    if len(poly):
        r = poly[np.arange(poly.shape[1])[None, :] < cnt[:, None]] - p
        proj = p + r * hp / -(r @ ne)[:, None]
        xy = np.stack([(proj - e0) @ u, (proj - e0) @ v], axis=-1)
        q = shapely.polygons(shapely.linearrings(xy, indices=np.repeat(np.arange(len(poly)), cnt)))
        bad = ~shapely.is_valid(q)
        q[bad] = shapely.buffer(q[bad], 0)
        shadows = list(q[shapely.area(q) > 0])
    return tc._visible_lambert(p, n, em, fr.region, shadows, fr.to3, "reference_ff_batched")


def _near_segment(p: np.ndarray, a: np.ndarray, b: np.ndarray, tris: np.ndarray) -> list[np.ndarray]:
    """The triangles not entirely on one side of the plane through p, a, b nor outside the box of
    the triangle p a b (the others cannot meet a segment from p to a point of a b)."""
    nrm = np.cross(a - p, b - p)
    s = (tris - p) @ nrm
    lo, hi = np.minimum(np.minimum(a, b), p), np.maximum(np.maximum(a, b), p)
    keep = ~(np.all(s > 0, axis=1) | np.all(s < 0, axis=1))
    keep &= np.all(tris.max(axis=1) >= lo, axis=1) & np.all(tris.min(axis=1) <= hi, axis=1)
    return list(tris[keep])


def _array(faces: list[np.ndarray]) -> np.ndarray:
    """Triangles as one `(m, 3, 3)` array (`ray_blocked_np` narrows those per ray: for the many rays
    to a segment light; a list is taken as given)."""
    return np.asarray(faces, np.float64).reshape(-1, 3, 3)


def _near_ray(x: np.ndarray, q: np.ndarray, lo: np.ndarray, hi: np.ndarray, margin: float) -> np.ndarray:
    """The triangles whose bounding box (`lo`, `hi`: `(m, 3)`) meets the box of the segment x q
    grown by `margin`: a triangle the segment crosses holds the crossing point, which lies in both
    boxes; the others cannot block it."""
    a, b = np.minimum(x, q) - margin, np.maximum(x, q) + margin
    return np.flatnonzero(np.all(hi >= a, axis=1) & np.all(lo <= b, axis=1))


def kind_reference(kind: str, light: Any, tris: np.ndarray, p: np.ndarray, n: np.ndarray,
                   boxes: bool = True) -> np.ndarray:
    """E per unit emission at each receiver for a point, directional or segment light. Point and
    directional rays: `_may_meet` on the triangles whose boxes meet the ray's (`_near_ray`,
    `boxes`: the others cannot block it, so the answer is the same) or on all of them."""
    tc, _, tm = refs()
    out = np.zeros(len(p))
    size = float(np.abs(tris).max()) if len(tris) else 0.0
    lo, hi = (tris.min(axis=1), tris.max(axis=1)) if len(tris) else (np.zeros((0, 3)), np.zeros((0, 3)))
    margin = 1e-9 * (1.0 + size)
    for i, (x, y) in enumerate(zip(p, n, strict=True)):
        y = y / np.linalg.norm(y)
        if kind in ("point", "directional"):
            if kind == "point":
                q = np.asarray(light.position, float)
                w = q - x
                r = float(np.linalg.norm(w))
                cos = max(0.0, float(w @ y) / r)
                value = cos / r**2
            else:
                d = np.asarray(light.direction, float)
                d = d / np.linalg.norm(d)
                q = x - d * 1e3 * (1 + size)
                cos = max(0.0, float(-d @ y))
                value = cos
            near = tris[_near_ray(x, q, lo, hi, margin)] if boxes else tris
            # Narrowed for this ray already (`_may_meet` needs at least one triangle).
            faces = tm._off_surface(x, near[tc._may_meet(x, q, near)], ON_SURFACE_64) if len(near) else []
            out[i] = 0.0 if cos == 0 or tc.ray_blocked_np(x, q, faces) else value
        else:
            a, b = np.asarray(light.start, float), np.asarray(light.end, float)
            faces = _array(tm._off_surface(x, _near_segment(x, a, b, tris), ON_SURFACE_64))
            m = 0 if light.profile == "isotropic" else int(light.exponent)
            out[i] = tc.reference_linear(x, y, a, b, m, faces)
    return out


def values(scene: Any, p: np.ndarray, n: np.ndarray) -> dict:
    """`js.irradiance` twice (first and second call timed), the unoccluded values and the plan's
    classes, with the sanity counts (finite, negative, above the unoccluded value, umbra not 0,
    lit not the unoccluded value)."""
    import jaxshadow as js
    from jaxshadow._shadows import binding as vis

    t = time.perf_counter()
    e = np.asarray(js.irradiance(scene, p, n))[:, 0]
    first = time.perf_counter() - t
    t = time.perf_counter()
    e = np.asarray(js.irradiance(scene, p, n))[:, 0]
    second = time.perf_counter() - t
    unocc = np.asarray(js.irradiance(js.Scene(scene.lights), p, n))[:, 0]
    cls = js.shadow_plan(scene, p, n).lights[0].classes
    eps = np.finfo(e.dtype).eps
    return {"e": e, "unocc": unocc, "cls": cls, "first_s": first, "second_s": second,
            "nonfinite": int((~np.isfinite(e)).sum()), "negative": int((e < 0).sum()),
            "above_unoccluded": int((e > unocc + 8 * eps * np.pi * np.abs(unocc).max()).sum()),
            "umbra_not_zero": int(((cls == vis.UMBRA) & (e != 0)).sum()),
            "classes": {name: int((cls == k).sum()) for k, name in enumerate(vis.CLASS_NAMES)}}


def exact(scene: Any, light_v: np.ndarray, tris: np.ndarray, p: np.ndarray, n: np.ndarray, n_ref: int,
          kind: str = "polygon") -> dict:
    """`values` plus the error against the brute-force reference on `n_ref` receivers picked by
    class (`pick`)."""
    r = values(scene, p, n)
    sel = pick(r["cls"], n_ref)
    p64, n64 = p[sel].astype(np.float64), n[sel].astype(np.float64)
    t = time.perf_counter()
    if kind == "polygon":
        ref = polygon_reference(light_v, tris, p64, n64)
    else:
        ref = kind_reference(kind, scene.lights[0], tris, p64, n64)
    out = {k: v for k, v in r.items() if k not in ("e", "unocc", "cls")}
    out.update(ref_receivers=int(len(sel)), max_rel_err=_err(r["e"][sel], ref, r["unocc"][sel]),
               reference_s=time.perf_counter() - t)
    if kind in ("point", "directional"):
        # Hard shadows: a receiver on a shadow boundary is decided by rounding either way.
        out["hard_disagree"] = int(np.sum((r["e"][sel] > 0) != (ref > 0)))
        agree = (r["e"][sel] > 0) == (ref > 0)
        out["max_rel_err"] = _err(r["e"][sel][agree], ref[agree], r["unocc"][sel][agree])
    out["_e"], out["_unocc"] = r["e"], r["unocc"]
    return out


def cpu_ratio(make_a: Any, make_b: Any, p: np.ndarray, n: np.ndarray, reps: int = 5) -> dict:
    """CPU seconds of `js.irradiance` on scene `make_b()` over scene `make_a()` (best of `reps`,
    alternating, after one warm-up call each), and their scene build times."""
    import jaxshadow as js

    builds: dict[str, list[float]] = {"a": [], "b": []}
    scenes = {}
    for key, make in (("a", make_a), ("b", make_b)):
        for _ in range(2):
            t = time.process_time()
            scenes[key] = make()
            builds[key].append(time.process_time() - t)
        np.asarray(js.irradiance(scenes[key], p, n))
    best = {"a": np.inf, "b": np.inf}
    for _ in range(reps):
        for key in ("a", "b"):
            t = time.process_time()
            np.asarray(js.irradiance(scenes[key], p, n))
            best[key] = min(best[key], time.process_time() - t)
    return {"mesh_cpu_s": best["a"], "soup_cpu_s": best["b"], "ratio": best["b"] / best["a"],
            "mesh_build_cpu_s": min(builds["a"]), "soup_build_cpu_s": min(builds["b"])}


def gradients(make_scene: Any, light_v: np.ndarray, p: np.ndarray, n: np.ndarray, h: float = 1e-6) -> dict:
    """`jax.grad` of the summed irradiance at `p` with respect to the receivers and to the
    light's vertices (`make_scene(light_vertices)`), against central differences at steps `h`
    and `h / 4`; coordinates where the two differences disagree (a kink within the step) are
    left out. Returns the largest relative difference and how many were compared."""
    import jax
    import jax.numpy as jnp

    import jaxshadow as js

    def total(x: Any, lv: Any) -> Any:
        return js.irradiance(make_scene(lv), x, jnp.asarray(n))[:, 0].sum()

    gp, gl = jax.grad(total, argnums=(0, 1))(jnp.asarray(p), jnp.asarray(light_v))
    out = {}
    for what, g, x0, arg in (("receivers", np.asarray(gp), p, 0), ("light", np.asarray(gl), light_v, 1)):
        fd: dict[float, np.ndarray] = {}
        for step in (h, h / 4):
            d = np.zeros(x0.shape)
            for idx in np.ndindex(*x0.shape):
                dx = np.zeros(x0.shape)
                dx[idx] = step
                args_p = [p, light_v]
                args_m = [p, light_v]
                args_p[arg] = x0 + dx
                args_m[arg] = x0 - dx
                d[idx] = (float(total(*args_p)) - float(total(*args_m))) / (2 * step)
            fd[step] = d
        a, b = fd[h], fd[h / 4]
        smooth = np.abs(a - b) <= 1e-5 * np.abs(a).max() + 1e-3 * np.abs(a)
        scale = max(float(np.abs(a).max()), 1e-300)
        out[what] = {"finite": bool(np.all(np.isfinite(g))), "compared": int(smooth.sum()), "of": int(a.size),
                     "max_rel_diff": float(np.max(np.abs(g - b)[smooth]) / scale) if smooth.any() else None}
    return out


def cache_update(make_scene: Any, moved: Any, p: np.ndarray, n: np.ndarray) -> dict:
    """`ShadowCache(make_scene())` updated to `moved()` against a cache built on `moved()` and
    `js.irradiance(moved())`: bit-identical or not, receivers re-evaluated, seconds."""
    import jaxshadow as js

    cache = js.ShadowCache(make_scene(), p, n)
    t = time.perf_counter()
    up = cache.update(moved())
    sec = time.perf_counter() - t
    fresh = js.ShadowCache(moved(), p, n).irradiance
    direct = np.asarray(js.irradiance(moved(), p, n))
    return {"identical_to_rebuild": bool(np.array_equal(up.irradiance, fresh)),
            "identical_to_irradiance": bool(np.array_equal(up.irradiance, direct)),
            "reevaluated": int(np.sum(np.asarray(up.last_update["receivers"]))), "receivers": int(len(p)), "update_s": sec}


def mesher(scene: Any, tol: float = 2e-2) -> dict:
    """`js.illumination_mesh` of a 3 m floor square under `scene`: size, time, and its vertex
    values against `js.irradiance` at the same vertices (they are exact values)."""
    import warnings

    import jaxshadow as js

    floor = np.array([[-1.5, -1.5, 0.0], [1.5, -1.5, 0.0], [1.5, 1.5, 0.0], [-1.5, 1.5, 0.0]])
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        im = js.illumination_mesh(scene, floor, tol, max_vertices=20000)
    sec = time.perf_counter() - t
    v = np.asarray(im.vertices)
    e = np.asarray(js.irradiance(scene, v, np.tile([0.0, 0.0, 1.0], (len(v), 1))))
    ir = np.asarray(im.irradiance)
    return {"vertices": int(len(v)), "triangles": int(len(im.triangles)), "seconds": sec,
            "finite": bool(np.all(np.isfinite(ir))),
            "max_rel_diff_vs_irradiance": float(np.abs(ir - e).max() / max(np.abs(e).max(), 1e-300))}
