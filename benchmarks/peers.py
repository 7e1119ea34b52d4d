"""The renderers a user would otherwise pick, driven on the same scenes as jaxshadow.

Radiance through pyradiance (the `bench` extra): `rtrace -I -ab 0` gives the irradiance at ray
origins (the ray direction is the surface normal) from light sources only, sampling area sources
by subdividing them (`-ds`, `-dj`, `-dt`, `-dc` set the accuracy). Occluders are black plastic
polygons: with `-ab 0` nothing but the light sources contributes. jaxshadow's other light kinds
become Radiance sources of equal radiometry (`radiance_point`, `radiance_directional`,
`radiance_segment`, or `radiance_source` for a jaxshadow light): a tiny `sphere`, a distant
`source` of small angle, a thin `cylinder`; each docstring derives its radiance.

Embree through embreex (the `bench` extra): shadow rays from each receiver to stratified jittered
samples of a polygon light (Monte Carlo estimate of the irradiance; error falls as 1/samples), or
stratified points along a segment light, or one ray to a point / along a directional light (hard
shadows, exact up to float32 ray tests).
"""

from __future__ import annotations

import os
import tempfile
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

# Radiance's defaults, and a fine source subdivision (jittered, no shadow-test threshold).
RADIANCE_DEFAULT: tuple[str, ...] = ()
RADIANCE_FINE: tuple[str, ...] = ("-dj", "1", "-ds", "0.01", "-dt", "0", "-dc", "1")
# The fine setting for a thin cylinder source: jitter 0.8 instead of 1. Radiance jitters a
# cylinder's shadow-ray targets over a square of half-side 0.856 r across the axis, which reaches
# 1.21 r from it, so with `-dj 1` rays aimed past a thin tube miss it and count as shadowed (an
# unoccluded 0.8 m segment: 2-3 % RMS low, single receivers up to 18 %); at 0.8 the square stays
# within 0.97 r (0.03 % RMS, as `-dj 0.5`).
RADIANCE_FINE_THIN: tuple[str, ...] = ("-dj", "0.8", "-ds", "0.01", "-dt", "0", "-dc", "1")
# A source's size relative to the 1 m scenes: small enough that its own penumbra and its
# distance to the tube's axis are far below Radiance's sampling error, above its FTINY (1e-6).
SOURCE_RADIUS = 1e-4
SOURCE_ANGLE_DEG = 0.01
# Directions within this sine of a segment's axis get the isotropic factor of this sine.
_MIN_SINE = 1e-3


def _polygon(mat: str, name: str, pts: np.ndarray) -> str:
    flat = " ".join(f"{x:.17g}" for x in np.asarray(pts, float).reshape(-1))
    return f"{mat} polygon {name}\n0\n0\n{3 * len(pts)} {flat}\n"


def _rgb(x: Any) -> np.ndarray:
    return np.broadcast_to(np.asarray(x, float).reshape(-1), (3,)).astype(float)


def _light_material(name: str, radiance: np.ndarray, modifier: str = "void") -> str:
    r = _rgb(radiance)
    return f"{modifier} light {name}\n0\n0\n3 {r[0]:.17g} {r[1]:.17g} {r[2]:.17g}\n"


def _floats(*xs: Any) -> str:
    flat = np.concatenate([np.asarray(x, float).reshape(-1) for x in xs])
    return f"{len(flat)} " + " ".join(f"{x:.17g}" for x in flat)


@dataclass(frozen=True)
class RadianceSource:
    """One Radiance light source: scene text whose names start with `{name}` (filled in per
    light), and the function files it reads (`{files}` in the text: the directory they are
    written to)."""

    text: str
    files: dict[str, str] = field(default_factory=dict)

    def render(self, name: str, files_dir: str) -> str:
        return self.text.replace("{name}", name).replace("{files}", files_dir)


def radiance_point(position: Any, intensity: Any, radius: float = SOURCE_RADIUS) -> RadianceSource:
    """jaxshadow's `PointLight(position, intensity I)` (W/sr, `E = I cos(theta) / r^2`): a sphere of
    `radius` (m) and `light` radiance `L = I / (pi radius^2)`.

    A sphere's intensity in every direction is its radiance times its projected disk,
    `L pi radius^2 = I`; Radiance samples a sphere source with solid angle `pi radius^2 / d^2`, so
    `E = L pi radius^2 cos(theta) / d^2 = I cos(theta) / d^2`. Unoccluded it agrees with
    `js.irradiance` to ~1e-4 / d (d in m) at any radius: a fixed offset of Radiance's, not
    sampling."""
    lum = _rgb(intensity) / (np.pi * radius**2)
    return RadianceSource(_light_material("{name}_mat", lum)
                          + f"{{name}}_mat sphere {{name}}\n0\n0\n{_floats(position, radius)}\n")


def radiance_directional(direction: Any, irradiance: Any, angle_deg: float = SOURCE_ANGLE_DEG) -> RadianceSource:
    """jaxshadow's `DirectionalLight(direction d, irradiance E0)` (`E = E0 max(0, -n . d)`): a
    distant `source` towards `-d` of full angle `angle_deg` and radiance `L = E0 / Omega`,
    `Omega = 2 pi (1 - cos(angle / 2))` (the solid angle Radiance gives a `source`), so
    `E = L Omega cos(theta) = E0 cos(theta)`. Unoccluded: exact to Radiance's float precision
    (~1e-7) without jitter."""
    d = -np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    omega = 2 * np.pi * (1 - np.cos(np.radians(angle_deg) / 2))
    return RadianceSource(_light_material("{name}_mat", _rgb(irradiance) / omega)
                          + f"{{name}}_mat source {{name}}\n0\n0\n{_floats(d, angle_deg)}\n")


# An isotropic line from a cylinder: radiance scaled by 1 / sin(alpha), alpha from the axis (A1-A3).
_ISOTROPIC_CAL = "isotropic_line = 1 / max(sqrt(max(1 - (Dx*A1 + Dy*A2 + Dz*A3)^2, 0)), {min_sine});\n"


def radiance_segment(start: Any, end: Any, power: Any, profile: str = "isotropic",
                     radius: float = SOURCE_RADIUS) -> RadianceSource:
    """jaxshadow's `LinearLight(start, end, power Phi)` (W/m), profile `"isotropic"` or `"cosine"`
    with exponent 1: a `cylinder` of `radius` (m) along the segment (no end caps).

    A length dl of the cylinder seen at angle alpha from its axis shows the projected area
    `2 radius sin(alpha) dl`, so radiance L gives the per-length intensity
    `2 radius L sin(alpha) = 2 radius L cos(beta)`, beta from the plane perpendicular to the axis:
    jaxshadow's cosine profile with m = 1, `I(beta) = C cos(beta)` with `C = Phi / pi^2` (its
    power per length, `integral C cos(beta) 2 pi cos(beta) dbeta` over beta in [-pi/2, pi/2], is
    `pi^2 C = Phi`); hence `L = Phi / (2 pi^2 radius)`. The isotropic profile (per-length
    intensity `Phi / (4 pi)`) needs `L(alpha) = Phi / (8 pi radius sin(alpha))`: the cylinder's
    light material is modified by a `brightfunc` `1 / sin(alpha)` (clamped at sin(alpha) >= 1e-3,
    directions within 0.06 degrees of the axis), with `L0 = Phi / (8 pi radius)`. Unoccluded
    agreement with `js.irradiance` (0.8 m segment 2.5 m over receivers): 0.2 % RMS at Radiance's
    default, 6e-5 with `-ds 0.01`, 0.03 % with `RADIANCE_FINE_THIN`; use that setting, not
    `RADIANCE_FINE`, whose full jitter misses the thin tube."""
    s, e = np.asarray(start, float), np.asarray(end, float)
    surface = f"{{name}}_mat cylinder {{name}}\n0\n0\n{_floats(s, e, radius)}\n"
    if profile == "cosine":
        return RadianceSource(_light_material("{name}_mat", _rgb(power) / (2 * np.pi**2 * radius)) + surface)
    if profile != "isotropic":
        raise ValueError(f"radiance_segment: profile {profile!r}: 'isotropic' or 'cosine' (exponent 1)")
    axis = (e - s) / np.linalg.norm(e - s)
    pattern = (f"void brightfunc {{name}}_iso\n2 isotropic_line {{files}}/isotropic_line.cal\n0\n"
               f"{_floats(axis)}\n")
    return RadianceSource(pattern + _light_material("{name}_mat", _rgb(power) / (8 * np.pi * radius), "{name}_iso")
                          + surface, {"isotropic_line.cal": _ISOTROPIC_CAL.format(min_sine=_MIN_SINE)})


def radiance_source(light: Any) -> RadianceSource:
    """The Radiance source of a jaxshadow light (`js.PointLight`, `js.DirectionalLight`,
    `js.LinearLight` isotropic or cosine with exponent 1, `js.PolygonLight`), by its `kind`."""
    kind = getattr(light, "kind", None)
    if kind == "point":
        return radiance_point(light.position, light.intensity)
    if kind == "directional":
        return radiance_directional(light.direction, light.irradiance)
    if kind == "segment":
        if light.profile == "cosine" and light.exponent != 1:
            raise ValueError("radiance_source: a cosine segment light needs exponent 1 (a cylinder's profile)")
        return radiance_segment(light.start, light.end, light.power, light.profile)
    if kind == "polygon":
        return RadianceSource(_light_material("{name}_mat", light.radiance)
                              + _polygon("{name}_mat", "{name}", np.asarray(light.vertices, float)))
    raise ValueError(f"radiance_source: no Radiance source for a light of kind {kind!r}")


Lights = list[tuple[np.ndarray, np.ndarray] | RadianceSource]


def radiance_scene(lights: Lights, occluders: np.ndarray, files_dir: str = ".") -> str:
    """Radiance scene text: `lights` as `(vertices (k, 3) counter-clockwise seen from the lit
    side, radiance (3,))` polygons of `light` material or as `RadianceSource`s (their function
    files in `files_dir`), `occluders (m, k, 3)` black polygons."""
    out = ["void plastic black\n0\n0\n5 0 0 0 0 0\n"]
    for i, light in enumerate(lights):
        if isinstance(light, RadianceSource):
            out.append(light.render(f"light{i}", files_dir))
            continue
        verts, rad = light
        out.append(_light_material(f"lmat{i}", rad))
        out.append(_polygon(f"lmat{i}", f"light{i}", verts))
    for j, poly in enumerate(occluders):
        out.append(_polygon("black", f"occ{j}", poly))
    return "".join(out)


class Radiance:
    """A compiled octree of one scene; `irradiance(points, normals, params)` runs rtrace."""

    def __init__(self, lights: Lights, occluders: np.ndarray):
        import pyradiance as pr

        self._pr = pr
        self._dir = tempfile.TemporaryDirectory(prefix="jaxshadow-radiance-")
        for light in lights:
            for fname, text in (light.files.items() if isinstance(light, RadianceSource) else ()):
                with open(os.path.join(self._dir.name, fname), "w") as fh:
                    fh.write(text)
        rad = os.path.join(self._dir.name, "scene.rad")
        with open(rad, "w") as fh:
            fh.write(radiance_scene(lights, occluders, self._dir.name))
        t = time.perf_counter()
        octree = pr.oconv(rad, warning=False)
        self.oconv_seconds = time.perf_counter() - t
        self.octree = os.path.join(self._dir.name, "scene.oct")
        with open(self.octree, "wb") as fh:
            fh.write(octree)

    def irradiance(self, points: np.ndarray, normals: np.ndarray, params: tuple[str, ...] = RADIANCE_DEFAULT,
                   nproc: int = 2) -> tuple[np.ndarray, float]:
        """`(E (N, 3) W/m^2, seconds)`: rtrace's wall time, binary float64 in and out."""
        rays = np.ascontiguousarray(np.concatenate([points, normals], axis=1), np.float64)
        t = time.perf_counter()
        out = self._pr.rtrace(rays.tobytes(), self.octree, header=False, inform="d", outform="d", irradiance=True,
                              nproc=nproc, params=["-ab", "0", *params])
        seconds = time.perf_counter() - t
        e = np.frombuffer(out, np.float64).reshape(-1, 3)
        if e.shape[0] != points.shape[0]:
            raise RuntimeError(f"rtrace returned {e.shape[0]} values for {points.shape[0]} rays")
        return e.copy(), seconds

    def close(self) -> None:
        self._dir.cleanup()

    def __enter__(self) -> Radiance:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class Embree:
    """Embree's occlusion rays against `triangles (m, 3, 3)` (float32, as Embree stores them)."""

    def __init__(self, triangles: np.ndarray):
        from embreex import mesh_construction, rtcore_scene

        t = time.perf_counter()
        self._scene = rtcore_scene.EmbreeScene()
        self._mesh = mesh_construction.TriangleMesh(self._scene, np.ascontiguousarray(triangles, np.float32))
        self._occluded(np.zeros((1, 3)), np.ones((1, 3)))  # Embree builds its hierarchy on the first query
        self.build_seconds = time.perf_counter() - t

    def _occluded(self, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
        """Whether each ray origin + t direction, 0 < t < 1, hits a triangle (bool (n,))."""
        hit = self._scene.run(np.ascontiguousarray(origins, np.float32), np.ascontiguousarray(directions, np.float32),
                              dists=np.ones(len(origins), np.float32), query="OCCLUDED")
        return np.asarray(hit) >= 0

    def polygon_irradiance(self, points: np.ndarray, normals: np.ndarray, quad: np.ndarray, radiance: float,
                           samples: int, seed: int = 0) -> tuple[np.ndarray, float]:
        """`(E (N,) W/m^2, seconds)` from a parallelogram light `quad (4, 3)` (counter-clockwise
        seen from the lit side) of uniform radiance, `samples` (a square number) stratified
        jittered shadow rays per receiver; origins lifted 1e-6 m along the receiver normal."""
        k = int(round(np.sqrt(samples)))
        rng = np.random.default_rng(seed)
        e0, e1, e3 = quad[0], quad[1] - quad[0], quad[3] - quad[0]
        nl = np.cross(e1, e3)  # the emitting side (right-hand rule of the vertex order)
        area = np.linalg.norm(nl)
        nl = nl / area
        gi, gj = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
        out = np.empty(len(points))
        block = max(1, 2**16 // (k * k))  # receivers per batch of rays (batches of ~65k rays)
        t = time.perf_counter()
        for s in range(0, len(points), block):
            p, n = points[s:s + block], normals[s:s + block]
            u = (gi.reshape(-1)[None, :] + rng.random((len(p), k * k))) / k
            v = (gj.reshape(-1)[None, :] + rng.random((len(p), k * k))) / k
            q = e0 + u[..., None] * e1 + v[..., None] * e3  # (b, k*k, 3)
            d = q - p[:, None, :]
            r2 = np.einsum("bsi,bsi->bs", d, d)
            cos_p = np.einsum("bsi,bi->bs", d, n) / np.sqrt(r2)
            cos_l = -np.einsum("bsi,i->bs", d, nl) / np.sqrt(r2)
            w = np.where((cos_p > 0) & (cos_l > 0), cos_p * cos_l / r2, 0.0)
            o = np.repeat(p + 1e-6 * n, k * k, axis=0)
            blocked = self._occluded(o, d.reshape(-1, 3)).reshape(len(p), k * k)
            out[s:s + block] = radiance * area * np.where(blocked, 0.0, w).mean(axis=1)
        return out, time.perf_counter() - t

    def segment_irradiance(self, points: np.ndarray, normals: np.ndarray, start: np.ndarray, end: np.ndarray,
                           power: float, samples: int, seed: int = 0) -> tuple[np.ndarray, float]:
        """`(E (N,) W/m^2, seconds)` from an isotropic segment light of power `power` per unit
        length (per-length intensity Phi / (4 pi)): `samples` stratified jittered points along
        it per receiver; origins lifted 1e-6 m along the receiver normal."""
        rng = np.random.default_rng(seed)
        length = float(np.linalg.norm(end - start))
        block = max(1, 2**16 // samples)  # receivers per batch of rays (batches of ~65k rays)
        out = np.empty(len(points))
        t = time.perf_counter()
        for s in range(0, len(points), block):
            q, n = points[s:s + block], normals[s:s + block]
            u = (np.arange(samples)[None, :] + rng.random((len(q), samples))) / samples
            d = start + u[..., None] * (end - start) - q[:, None, :]
            r2 = np.einsum("bsi,bsi->bs", d, d)
            cos_p = np.maximum(np.einsum("bsi,bi->bs", d, n) / np.sqrt(r2), 0.0)
            blocked = self._occluded(np.repeat(q + 1e-6 * n, samples, axis=0), d.reshape(-1, 3)).reshape(len(q), samples)
            out[s:s + block] = power / (4 * np.pi) * length * np.where(blocked, 0.0, cos_p / r2).mean(axis=1)
        return out, time.perf_counter() - t

    def hard_visibility(self, points: np.ndarray, normals: np.ndarray, towards: np.ndarray) -> tuple[np.ndarray, float]:
        """`(visible (N,) bool, seconds)`: one ray per receiver along `towards (N, 3)` (to a
        point light: its position minus the receiver; a directional light: a long vector against
        its direction), origins lifted 1e-6 m along the normal."""
        t = time.perf_counter()
        vis = ~self._occluded(points + 1e-6 * normals, towards)
        return vis, time.perf_counter() - t
