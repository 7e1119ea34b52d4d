r"""Mitsuba 3 bridge: scenes in and out, and Monte Carlo reference estimators (optional extra).

- In: `from_mitsuba(path_or_dict) -> (Scene, receivers, materials)` reads any Mitsuba scene
  through Mitsuba's own loader (`jaxshadow._io.mitsuba_io`: what maps to what, and what is lost);
  `read_sensor` its camera.
- Out: `to_mitsuba` / `to_mitsuba_dict` (an in-memory Mitsuba scene, with receiver surfaces and
  their materials as BSDFs, and a camera) and `write_mitsuba_xml` (a scene file).
- Reference estimators: `reference_irradiance`, `reference_specular`, `reference_shade`,
  `quick_report` (below); `reference_irradiance(..., mitsuba_scene=...)` runs in the user's own
  Mitsuba scene instead of the twin.

Mitsuba 3 is jaxshadow's independent ground truth. Units are Mitsuba's, so a jaxshadow scene
and its Mitsuba twin must agree with no fudge factor:

- `PolygonLight` -> a fan-triangulated `mi.Mesh` built from arrays with an `area` emitter of
  the same RGB radiance. Mitsuba's area emitter emits on the side of its face normal,
  $(v_1 - v_0)\times(v_2 - v_0)$, which is the right-hand-rule normal of jaxshadow's vertex
  order: one-sided, toward the lit side.
- `PointLight` -> `point` emitter (`intensity`, W/sr); `DirectionalLight` -> `directional`
  emitter (`irradiance`, W/m^2).
- Occluders -> one mesh with a black `diffuse` BSDF. Mitsuba's shadow rays hit either side of a
  triangle, so occluders block from both sides; they never reflect (direct illumination only).
- `LinearLight` has no Mitsuba counterpart; two stand-ins, each exact in the limit:

  * isotropic profile: `segment_points` $M$ `point` emitters at the midpoints of equal
    sub-segments, each of intensity $\Phi\ell/(4\pi M)$ and sampling weight $1/M$: the midpoint
    rule of $E = \int I\cos\theta/r^2\,dl$, bias $O(h^2/d^2)$ with $h = \ell/M$ and $d$ the
    receiver's distance. Measured (segment of length 1.26, receivers at 0.1 to 1.9): max
    relative bias 4e-3 for M = 16, 3.3e-4 for M = 64 (default), 8e-6 for M = 256.
  * cosine profile with $m = 1$ (Poulin §3.2.2): a Lambertian open `cylinder` of radius
    $r$ = `segment_radius` $\times\,\ell$ and radiance $L = \Phi/(2\pi^2 r)$, whose per-length
    intensity is $2rL\cos\beta = \Phi\cos\beta/\pi^2$, exactly jaxshadow's profile in the far
    field. Its near side is closer than the axis, so the bias is first order, $O(r/d)$:
    measured max relative bias 1.2e-2, 1.2e-3, 1.4e-4 for r = 1e-2, 1e-3, 1e-4 (default)
    times the length, same receivers.
  * cosine profile with $m \ge 2$ has no stand-in (`NotImplementedError`).

  The measurements are reproduced by `python tests/test_mitsuba.py`.

jaxshadow's lights never occlude, Mitsuba's light meshes are opaque. The estimators follow
jaxshadow by default: Mitsuba's emitter sampling (`Scene.sample_emitter_direction`), then
Mitsuba's own shadow ray (`Interaction3f.spawn_ray_to`, Mitsuba's ray epsilons) traced
against a scene holding only the occluders; `lights_occlude=True` uses Mitsuba's
`test_visibility=True` in the full scene instead. Everything runs in one Dr.Jit wavefront of
`points x spp` lanes (chunked, float32) and returns the mean with its standard error from the
per-sample variance (accumulated in float64). Receivers are `mi.Interaction3f` records with
`p` and `n`, so they can be anywhere, not only on a Mitsuba surface.

Needs `pip install 'jaxshadow[mitsuba]'`; `import jaxshadow` never imports Mitsuba. The
`llvm_ad_rgb` variant is selected unless an RGB JIT variant (`llvm_ad_rgb`, `cuda_ad_rgb`) is
already active.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from ._core.geometry import strip_padding
from ._io.mitsuba_io import UnsupportedMitsubaElementWarning as UnsupportedMitsubaElementWarning
from ._io.mitsuba_io import from_mitsuba as from_mitsuba
from ._io.mitsuba_io import import_mitsuba
from ._io.mitsuba_io import material_from_bsdf as material_from_bsdf
from ._io.mitsuba_io import read_sensor as read_sensor
from ._io.mitsuba_out import fan_mesh, rgb_dict
from ._io.mitsuba_out import material_to_bsdf as material_to_bsdf
from ._io.mitsuba_out import scene_items as scene_items
from ._io.mitsuba_out import to_mitsuba as to_mitsuba
from ._io.mitsuba_out import to_mitsuba_dict as to_mitsuba_dict
from ._io.mitsuba_out import write_example_scene as write_example_scene
from ._io.mitsuba_out import write_mitsuba_xml as write_mitsuba_xml
from ._scene.model import LinearLight, Material, PolygonLight, Scene

__all__ = [
    "UnsupportedMitsubaElementWarning",
    "from_mitsuba",
    "material_from_bsdf",
    "material_to_bsdf",
    "quick_report",
    "read_sensor",
    "reference_irradiance",
    "reference_shade",
    "reference_specular",
    "scene_items",
    "to_mitsuba",
    "to_mitsuba_dict",
    "write_example_scene",
    "write_mitsuba_xml",
]

_CHUNK_LANES = 1 << 20

# --------------------------------------------------------------------------------------
# Monte Carlo estimators
# --------------------------------------------------------------------------------------


class _Twin:
    """The Mitsuba scene of a jaxshadow scene, plus what the estimators need beside it."""

    def __init__(self, mi: Any, scene: Any, lights_occlude: bool, convert: dict, native: Any = None):
        if not isinstance(scene, Scene):
            raise ValueError(f"expected a jaxshadow.Scene, got {type(scene).__name__}.")
        self.occluders = None
        if native is not None:  # the user's own Mitsuba scene, with Mitsuba's visibility test
            from ._io.mitsuba_io import load_mitsuba_scene

            self.full, self.lights_occlude, self.max_light_hits = load_mitsuba_scene(mi, native), True, 1
            return
        self.full = to_mitsuba(scene, **convert)
        self.lights_occlude = bool(lights_occlude)
        if scene.occluders is not None and not self.lights_occlude:
            props = mi.Properties()
            props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": rgb_dict(mi, 0.0)})
            polys = [strip_padding(p) for p in np.asarray(scene.occluders, dtype=np.float64)]
            self.occluders = mi.load_dict(
                {"type": "scene", "occluders": fan_mesh(mi, "occluders", polys, props)}
            )
        # A ray crosses a convex polygon light at most once and a cylinder at most twice.
        self.max_light_hits = sum(
            1 if isinstance(light, PolygonLight) else 2
            for light in scene.lights
            if isinstance(light, PolygonLight)
            or (isinstance(light, LinearLight) and light.profile == "cosine")
        )


def _points_normals(points: Any, normals: Any) -> tuple[np.ndarray, np.ndarray]:
    p = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    if p.ndim != 2 or p.shape[-1] != 3 or n.shape != p.shape:
        raise ValueError(
            f"points and normals must both have shape (N, 3), got {p.shape} and {n.shape}."
        )
    if not (np.isfinite(p).all() and np.isfinite(n).all()):
        raise ValueError("points and normals must be finite.")
    length = np.linalg.norm(n, axis=1, keepdims=True)
    if (length == 0).any():
        raise ValueError("normals must be non-zero.")
    return p, n / length


def _lanes(
    mi: Any,
    twin: _Twin,
    p: np.ndarray,
    n: np.ndarray,
    eye: np.ndarray | None,
    exponent: float,
    coef_e: np.ndarray,
    coef_s: np.ndarray,
    lane0: int,
    lanes: int,
    spp: int,
    seed: int,
) -> np.ndarray:
    r"""Per-lane samples of `coef_e * E + coef_s * S` for lanes `lane0 .. lane0 + lanes`.

    $E$: one emitter sample, $L\max(0, \cos\theta)/p$. $S$: the same emitter sample and one
    Phong-lobe sample (pdf $=$ the lobe), combined with the balance heuristic; delta emitters
    (point, directional) only through the emitter sample.
    """
    import drjit as dr

    full = twin.full
    idx = dr.arange(mi.UInt32, lane0, lane0 + lanes) // spp
    it = dr.zeros(mi.Interaction3f, lanes)
    it.p = dr.gather(mi.Point3f, mi.Point3f(p.T.astype(np.float32)), idx)
    it.n = dr.gather(mi.Normal3f, mi.Normal3f(n.T.astype(np.float32)), idx)
    sampler = mi.load_dict({"type": "independent", "sample_count": 1})
    state = np.random.SeedSequence([int(seed), lane0 // _CHUNK_LANES]).generate_state(1)[0]
    sampler.seed(int(state), lanes)

    if twin.lights_occlude:
        ds, spec = full.sample_emitter_direction(it, sampler.next_2d(), True)
    else:
        # Mitsuba's shadow ray, traced against the occluders only: lights do not occlude.
        ds, spec = full.sample_emitter_direction(it, sampler.next_2d(), False)
        if twin.occluders is not None:
            blocked = twin.occluders.ray_test(it.spawn_ray_to(ds.p), ds.pdf > 0)
            spec = dr.select(blocked, 0.0, spec)
    cos_n = dr.dot(ds.d, it.n)
    above = cos_n > 0
    total = mi.Color3f(0.0)
    if np.any(coef_e != 0):
        e = dr.select(above, spec * cos_n, 0.0)
        total += mi.Color3f(coef_e.astype(np.float32)) * e
    if np.any(coef_s != 0):
        assert eye is not None
        v = dr.normalize(dr.gather(mi.Point3f, mi.Point3f(eye.T.astype(np.float32)), idx) - it.p)
        r = 2.0 * dr.dot(it.n, v) * it.n - v
        k = dr.opaque(mi.Float, float(exponent))
        norm = (k + 1.0) / (2.0 * math.pi)
        lobe_e = norm * dr.power(dr.maximum(dr.dot(ds.d, r), 0.0), k)
        w_e = dr.select(ds.delta, 1.0, ds.pdf / (ds.pdf + lobe_e))
        s = dr.select(above & (ds.pdf > 0), spec * lobe_e * w_e, 0.0)

        # Lobe sampling: cos(alpha) = u^(1/(k+1)) about R has pdf = the normalised lobe.
        u = sampler.next_2d()
        cos_a = dr.power(u.x, 1.0 / (k + 1.0))
        sin_a = dr.safe_sqrt(1.0 - cos_a * cos_a)
        sp, cp = dr.sincos(2.0 * math.pi * u.y)
        w = mi.Frame3f(r).to_world(mi.Vector3f(sin_a * cp, sin_a * sp, cos_a))
        lobe_b = norm * dr.power(cos_a, k)
        active = (dr.dot(w, it.n) > 0) & (lobe_b > 0)
        ray = it.spawn_ray(w)
        # Walk through the light surfaces along the ray until an occluder (or nothing) is hit;
        # with lights_occlude only the first surface counts.
        hits = 1 if twin.lights_occlude else max(twin.max_light_hits, 1)
        for _ in range(hits):
            si = full.ray_intersect(ray, active)
            active &= si.is_valid() & si.shape.is_emitter()
            radiance = si.emitter(full, active).eval(si, active)
            pdf_e = full.pdf_emitter_direction(it, mi.DirectionSample3f(full, si, it), active)
            s += dr.select(active, radiance * (lobe_b / (lobe_b + pdf_e)), 0.0)
            ray = si.spawn_ray(w)
        total += mi.Color3f(coef_s.astype(np.float32)) * s
    return np.asarray(total, dtype=np.float64)  # (3, lanes)


def _estimate(
    scene: Any,
    points: Any,
    normals: Any,
    spp: int,
    seed: int,
    *,
    eye: Any = None,
    exponent: float = 0.0,
    coef_e: Any = 1.0,
    coef_s: Any = 0.0,
    lights_occlude: bool = False,
    convert: dict | None = None,
    native: Any = None,
) -> tuple[np.ndarray, np.ndarray]:
    mi = import_mitsuba()
    twin = _Twin(mi, scene, lights_occlude, convert or {}, native)
    p, n = _points_normals(points, normals)
    spp = int(spp)
    if spp < 2:
        raise ValueError(f"spp must be >= 2 (the standard error needs a variance), got {spp}.")
    if eye is not None:
        eye = np.broadcast_to(np.asarray(eye, dtype=np.float64), p.shape)
        if (np.linalg.norm(eye - p, axis=1) == 0).any():
            raise ValueError("eye must differ from every point (V is the unit vector to the eye).")
    coef_e = np.broadcast_to(np.asarray(coef_e, dtype=np.float64), (3,))
    coef_s = np.broadcast_to(np.asarray(coef_s, dtype=np.float64), (3,))
    n_pts = p.shape[0]
    total = n_pts * spp
    s1 = np.zeros((3, n_pts))
    s2 = np.zeros((3, n_pts))
    for lane0 in range(0, total, _CHUNK_LANES):
        lanes = min(_CHUNK_LANES, total - lane0)
        vals = _lanes(mi, twin, p, n, eye, exponent, coef_e, coef_s, lane0, lanes, spp, seed)
        which = np.arange(lane0, lane0 + lanes) // spp
        for c in range(3):
            s1[c] += np.bincount(which, weights=vals[c], minlength=n_pts)
            s2[c] += np.bincount(which, weights=vals[c] ** 2, minlength=n_pts)
    mean = s1 / spp
    var = np.maximum(s2 / spp - mean**2, 0.0) * spp / (spp - 1)
    return mean.T.copy(), np.sqrt(var / spp).T.copy()


def reference_irradiance(
    scene: Scene,
    points: Any,
    normals: Any,
    spp: int = 4096,
    seed: int = 0,
    *,
    lights_occlude: bool = False,
    mitsuba_scene: Any = None,
    **convert: Any,
) -> tuple[np.ndarray, np.ndarray]:
    r"""Monte Carlo direct irradiance with Mitsuba's emitter sampling and shadow rays.

    $E \approx \frac1S\sum_s L(\omega_s)\max(0, n\cdot\omega_s)/p(\omega_s)$, the weight
    $L/p$ from `Scene.sample_emitter_direction`, times the visibility of Mitsuba's shadow ray.

    **Arguments:**

    - `scene`: a jaxshadow `Scene`, converted with `to_mitsuba(scene, **convert)`.
    - `points`, `normals`: `(N, 3)` receivers (m) and their normals (normalised here). Points
      need not lie on a Mitsuba surface.
    - `spp`: samples per point (>= 2). `seed`: integer seed (results are deterministic).
    - `lights_occlude`: `False` (default, jaxshadow's model): Mitsuba's shadow rays are traced
      against the occluders only. `True`: Mitsuba's own `test_visibility=True` in the full
      scene, where light meshes are opaque too (one light can shadow another).
    - `mitsuba_scene`: `None`, or the Mitsuba scene `scene` was read from (a file, a dict or an
      `mi.Scene`, see `from_mitsuba`): the estimate then runs in that scene itself, with
      Mitsuba's own `test_visibility=True` (every shape occludes), independent of jaxshadow's
      conversion; `scene` is only checked.
    - `convert`: `segment_points`, `segment_radius` for `to_mitsuba`.

    **Returns:** `(estimate, stderr)`, each an `(N, 3)` float64 NumPy array (W/m^2); `stderr` is
    the standard error of the mean from the per-sample variance (0 where the integrand is
    deterministic, e.g. a single point light).
    """
    return _estimate(
        scene, points, normals, spp, seed, lights_occlude=lights_occlude, convert=convert,
        native=mitsuba_scene,
    )


def reference_specular(
    scene: Scene,
    points: Any,
    normals: Any,
    eye: Any,
    exponent: float,
    spp: int = 4096,
    seed: int = 0,
    *,
    lights_occlude: bool = False,
    **convert: Any,
) -> tuple[np.ndarray, np.ndarray]:
    r"""Monte Carlo Phong specular integral (DESIGN.md "Specular", Poulin eq. 3.12 normalisation).

    $S = \int L_i(\omega)\,\frac{n+1}{2\pi}\max(0, \omega\cdot R)^n\,d\omega$ over visible light
    above the tangent plane, $R = 2(N\cdot V)N - V$, $V$ the unit vector from the point to the
    eye; point and directional lights contribute the lobe times $I/r^2$ and $E_0$. Each sample
    is one Mitsuba emitter sample plus one sample of the lobe (a ray traced into the scene),
    combined with the balance heuristic, so large exponents keep an honest standard error.

    **Arguments:** as `reference_irradiance`, plus `eye`: `(3,)` or `(N, 3)` eye position (m)
    and `exponent`: the Phong exponent $n \ge 0$.

    **Returns:** `(estimate, stderr)`, `(N, 3)` float64 arrays (W m^-2 sr^-1).
    """
    if eye is None:
        raise ValueError("reference_specular: eye is required.")
    if not float(exponent) >= 0:
        raise ValueError(f"reference_specular: exponent must be >= 0, got {exponent!r}.")
    return _estimate(
        scene,
        points,
        normals,
        spp,
        seed,
        eye=eye,
        exponent=float(exponent),
        coef_e=0.0,
        coef_s=1.0,
        lights_occlude=lights_occlude,
        convert=convert,
    )


def reference_shade(
    scene: Scene,
    material: Material,
    points: Any,
    normals: Any,
    eye: Any,
    spp: int = 4096,
    seed: int = 0,
    *,
    lights_occlude: bool = False,
    **convert: Any,
) -> tuple[np.ndarray, np.ndarray]:
    r"""Monte Carlo Phong shading $k_a L_a + \frac{k_d}{\pi}E + k_s S$ (Poulin eq. 5.14).

    $E$ and $S$ come from the same samples (`reference_irradiance`, `reference_specular`);
    the standard error is that of the combined per-sample value ($k_a L_a$ is exact).

    **Arguments:**

    - `scene`: a jaxshadow `Scene` (its `ambient` is $L_a$).
    - `material`: a `Material` (`ka`, `kd`, `ks`, `exponent`).
    - `points`, `normals`, `eye`, `spp`, `seed`, `lights_occlude`, `convert`: as
      `reference_specular`.

    **Returns:** `(estimate, stderr)`, `(N, 3)` float64 arrays (W m^-2 sr^-1).
    """
    if not isinstance(scene, Scene):
        raise ValueError(
            f"reference_shade: expected a jaxshadow.Scene, got {type(scene).__name__}."
        )
    if not isinstance(material, Material):
        raise ValueError(f"reference_shade: expected a Material, got {type(material).__name__}.")
    ka = np.asarray(material.ka, dtype=np.float64)
    kd = np.asarray(material.kd, dtype=np.float64)
    ks = np.asarray(material.ks, dtype=np.float64)
    mean, err = _estimate(
        scene,
        points,
        normals,
        spp,
        seed,
        eye=eye,
        exponent=float(np.asarray(material.exponent)),
        coef_e=kd / math.pi,
        coef_s=ks,
        lights_occlude=lights_occlude,
        convert=convert,
    )
    return mean + ka * np.asarray(scene.ambient, dtype=np.float64), err


def quick_report(scene: Scene, points: Any, normals: Any, spp: int = 4096, seed: int = 0) -> dict:
    r"""jaxshadow's irradiance next to Mitsuba's, point by point (JSON-able).

    **Returns:** a dict with `"ours"`, `"mitsuba"`, `"stderr"`, `"abs_diff"` (`(N, 3)` lists,
    W/m^2), `"sigma"` (`|ours - mitsuba| / stderr` per point and channel; the standard error is
    floored at `1e-6 |value|` for deterministic estimates), `"max_sigma"`, `"max_rel_diff"`,
    `"spp"`, `"seed"`, and timings `"ours_s"`, `"mitsuba_s"`. If jaxshadow cannot evaluate the
    scene (e.g. occluders before exact shadows land), `"ours"` is `None` and `"note"` says why.
    """
    import jax.numpy as jnp

    from ._shading.shade import irradiance

    p, n = _points_normals(points, normals)
    t0 = time.perf_counter()
    ref, err = reference_irradiance(scene, p, n, spp=spp, seed=seed)
    t1 = time.perf_counter()
    out: dict[str, Any] = {
        "mitsuba": ref.tolist(),
        "stderr": err.tolist(),
        "spp": int(spp),
        "seed": int(seed),
        "mitsuba_s": t1 - t0,
    }
    try:
        ours = np.asarray(irradiance(scene, jnp.asarray(p), jnp.asarray(n)), dtype=np.float64)
    except NotImplementedError as exc:
        out.update(ours=None, note=str(exc))
        return out
    t2 = time.perf_counter()
    diff = np.abs(ours - ref)
    sigma = diff / np.maximum(err, 1e-6 * np.abs(ref) + 1e-30)
    out.update(
        ours=ours.tolist(),
        abs_diff=diff.tolist(),
        sigma=sigma.tolist(),
        max_sigma=float(sigma.max(initial=0.0)),
        max_rel_diff=float((diff / np.maximum(np.abs(ref), 1e-30)).max(initial=0.0)),
        ours_s=t2 - t1,
    )
    return out
