r"""Mitsuba scenes in and out: `from_mitsuba` through Mitsuba's own loader, the BSDF <-> Material
mapping, and Mitsuba XML written with `xml.etree` (Mitsuba has no XML writer).

**In** (`from_mitsuba`). The scene is loaded by Mitsuba (`mi.load_file` / `mi.load_dict`) and read
back through `mi.traverse` and the shapes' mesh buffers, so whatever Mitsuba accepts is read the
way Mitsuba reads it (includes, defaults, transforms, OBJ/PLY/serialized files):

- an `area` emitter on a mesh (rectangle, cube, OBJ, PLY, ...) becomes polygon lights: its
  triangles grouped by plane, each group whose union is convex one `PolygonLight` (a rectangle's
  two triangles become its quad), other groups split by `jaxshadow.Mesh`'s coplanar merge; on a
  `disk`, a regular `disc_segments`-gon of the disc's area (equal power; the form factor of the
  64-gon differs from the disc's by < 1e-3 relative at the distances of `tests/test_mitsuba_io.py`).
  Vertices are Mitsuba's float32 values, in a canonical order (starting at the smallest vertex),
  so that a scene written and read again is the same scene bit for bit.
- `point` -> `PointLight` (`intensity`, W/sr); `directional` -> `DirectionalLight` (direction
  = `to_world` applied to +z, `irradiance`, W/m^2).
- every other shape is an occluder (a `jaxshadow.Mesh`) and a receiver surface (a
  `ReceiverMesh`, welded, with area-weighted vertex normals like every `ReceiverMesh`);
  `sphere` and `cylinder` are tessellated
  (inscribed, `sphere_segments`), `disk` polygonised as above.
- what cannot be represented (spot and environment emitters, textured radiance, emitters on
  shapes that are not meshes or discs, unknown shapes) raises an `UnsupportedMitsubaElementWarning`
  naming the element; it is never silently dropped.

**BSDF -> Material** (`material_from_bsdf`; Phong as in DESIGN.md, $L = k_a L_a + k_d E/\pi + k_s S$):

| BSDF | Material | loss |
|---|---|---|
| `diffuse` (rgb $\rho$) | $k_d = \rho$ | exact |
| `plastic`, `roughplastic` ($\rho$, $\eta$, $\alpha$) | $k_d = \pi f_d(n, n)$, Mitsuba's own diffuse component at normal incidence ($\rho(1-F_0)^2/(\eta^2(1-F_{dr}))$ by default), $k_s = F_0$, $n = 2/\alpha^2-2$ | $k_d$ exact at normal incidence only; the Fresnel-weighted Beckmann lobe becomes a Phong lobe (Walter et al. 2007) |
| `conductor`, `roughconductor` ($\eta$, $k$, $R$, $\alpha$) | $k_s = R\,F(0)$, $k_d = 0$ | Fresnel at normal incidence only; a smooth one gets $n$ = `SMOOTH_EXPONENT` |
| `twosided` | its inner BSDF | |
| `blendbsdf` of `diffuse` and `roughconductor` (what `material_to_bsdf` writes) | $k_d = (1-w)\rho$, $k_s = wR$ | the lobe's shape as above |
| anything else, or textured parameters | `Material()` and a warning | |

$F_0 = ((\eta-1)/(\eta+1))^2$, $F_{dr}$ Mitsuba's internal diffuse Fresnel reflectance. $k_a$ is 0
(ambient light is not something Mitsuba transports).

**Out.** `material_to_bsdf`: $k_s = 0$ -> `diffuse` (exact); else `blendbsdf` of weight
$w = \max k_s/(\max k_d + \max k_s)$ of a `diffuse` of reflectance $k_d/(1-w)$ and a
`roughconductor` (no Fresnel, Beckmann $\alpha = \sqrt{2/(n+2)}$) of reflectance $k_s/w$. `write_mitsuba_xml` writes a scene file that
`mi.load_file` reads back into the same lights and shapes.
"""

from __future__ import annotations

import math
import os
import warnings
from typing import Any

import numpy as np

from .._scene.model import DirectionalLight, Material, PointLight, PolygonLight, Scene
from .meshio import ReceiverMesh

_VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
_CHUNK_LANES = 1 << 20
DISC_SEGMENTS = 64
SPHERE_SEGMENTS = 24
SMOOTH_EXPONENT = 1000.0


class UnsupportedMitsubaElementWarning(UserWarning):
    """A Mitsuba scene element that jaxshadow cannot represent (named in the message)."""


def _warn(msg: str) -> None:
    warnings.warn(msg, UnsupportedMitsubaElementWarning, stacklevel=3)


def import_mitsuba() -> Any:
    """Import Mitsuba and select an RGB JIT variant; a clear ImportError when it is missing."""
    try:
        import mitsuba as mi
    except ImportError as err:
        raise ImportError(
            "jaxshadow.mitsuba needs the optional dependency 'mitsuba' (Mitsuba 3): "
            "install it with `pip install 'jaxshadow[mitsuba]'`."
        ) from err
    if mi.variant() not in _VARIANTS:
        if "llvm_ad_rgb" in mi.variants():
            mi.set_variant("llvm_ad_rgb")
        else:  # pragma: no cover - depends on the Mitsuba build
            raise ImportError(
                "jaxshadow.mitsuba needs Mitsuba's 'llvm_ad_rgb' variant (vectorised estimators); "
                f"this build offers {mi.variants()}."
            )
    return mi


def load_mitsuba_scene(mi: Any, source: Any) -> Any:
    """An `mi.Scene` from a file path (every shape kept: no merging by BSDF), a scene dict or an
    `mi.Scene` (returned as is); a `FileNotFoundError` / `ValueError` that names the source."""
    if isinstance(source, (str, os.PathLike)):
        path = os.fspath(source)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"{path}: no such Mitsuba scene file.")
        try:
            return mi.load_file(path, optimize=False)  # keep every shape (no merging by BSDF)
        except RuntimeError as err:
            raise ValueError(f"{path}: Mitsuba cannot load the scene: {err}") from None
    if isinstance(source, dict):
        try:
            return mi.load_dict(source, optimize=False)
        except RuntimeError as err:
            raise ValueError(f"Mitsuba cannot load the scene dict: {err}") from None
    if isinstance(source, mi.Scene):
        return source
    raise ValueError(f"from_mitsuba: expected a file path, a scene dict or an mi.Scene, got {type(source).__name__}.")


def _matrix(transform: Any) -> np.ndarray:
    return np.asarray(transform.matrix, dtype=np.float64).reshape(4, 4)


def _f32(x: Any) -> np.ndarray:
    return np.asarray(np.asarray(x, dtype=np.float32), dtype=np.float64)


def _rgb_param(params: Any, key: str) -> np.ndarray | None:
    """A parameter's RGB value, `None` when it is not a plain colour (a texture)."""
    if key not in params.keys():
        return None
    v = np.asarray(params[key], dtype=np.float64).ravel()
    return np.broadcast_to(v, (3,)).copy() if v.size in (1, 3) else None


def _ordered(objects: Any) -> list[tuple[int, Any]]:
    """`(index, object)` with the objects that have an id first, sorted by id, then the others in
    Mitsuba's order (which is not the file's): the order survives writing and reading again."""
    objs = list(enumerate(objects))
    return sorted((x for x in objs if x[1].id()), key=lambda x: x[1].id()) + [x for x in objs if not x[1].id()]


def _name(obj: Any, kind: str, i: int) -> str:
    ident = obj.id()
    return ident if ident else f"{kind}{i}_{obj.class_name()}"


# --------------------------------------------------------------------------------------
# Geometry
# --------------------------------------------------------------------------------------


def _ngon(m: int) -> np.ndarray:
    """A regular m-gon in the xy-plane, counter-clockwise, of the unit disc's area."""
    r = math.sqrt(2 * math.pi / (m * math.sin(2 * math.pi / m)))
    t = 2 * math.pi * np.arange(m) / m
    return np.stack([r * np.cos(t), r * np.sin(t), np.zeros(m)], axis=1)


def _apply(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    return x @ m[:3, :3].T + m[:3, 3]


def _fan(k: int) -> np.ndarray:
    return np.array([[0, i, i + 1] for i in range(1, k - 1)], dtype=np.int64)


def _uv_sphere(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit sphere, `n` segments around and n/2 from pole to pole, outward triangles."""
    n_lat, n_lon = max(n // 2, 2), max(n, 3)
    th = np.pi * np.arange(1, n_lat) / n_lat
    ph = 2 * np.pi * np.arange(n_lon) / n_lon
    ring = np.stack([np.outer(np.sin(th), np.cos(ph)), np.outer(np.sin(th), np.sin(ph)),
                     np.outer(np.cos(th), np.ones(n_lon))], axis=-1).reshape(-1, 3)
    v = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]])
    idx = lambda i, j: 1 + i * n_lon + j % n_lon  # noqa: E731
    faces = [[0, idx(0, j), idx(0, j + 1)] for j in range(n_lon)]
    for i in range(n_lat - 2):
        for j in range(n_lon):
            faces += [[idx(i, j), idx(i + 1, j), idx(i + 1, j + 1)], [idx(i, j), idx(i + 1, j + 1), idx(i, j + 1)]]
    last = len(v) - 1
    faces += [[last, idx(n_lat - 2, j + 1), idx(n_lat - 2, j)] for j in range(n_lon)]
    return v, np.asarray(faces, dtype=np.int64)


def _open_tube(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit cylinder x^2 + y^2 = 1, 0 <= z <= 1, `n` segments, outward triangles (open ends)."""
    t = 2 * np.pi * np.arange(n) / n
    ring = np.stack([np.cos(t), np.sin(t), np.zeros(n)], axis=1)
    v = np.concatenate([ring, ring + [0.0, 0.0, 1.0]])
    faces = [f for j in range(n) for f in ([j, (j + 1) % n, n + (j + 1) % n], [j, n + (j + 1) % n, n + j])]
    return v, np.asarray(faces, dtype=np.int64)


def _oriented(v: np.ndarray, f: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Transform a local mesh by `m`, reversing faces when `m` mirrors (keeps outward normals)."""
    w = _f32(_apply(m, v))
    return w, (f[:, ::-1].copy() if np.linalg.det(m[:3, :3]) < 0 else f)


def shape_geometry(mi: Any, shape: Any, name: str, disc_segments: int = DISC_SEGMENTS,
                   sphere_segments: int = SPHERE_SEGMENTS) -> tuple[np.ndarray, np.ndarray, np.ndarray | None] | None:
    """`(vertices (V, 3), faces (F, 3), vertex_normals or None)` of a Mitsuba shape in world
    space (float32 values as float64), `None` (with a warning) for a shape kind not handled."""
    if shape.is_mesh():
        v = np.asarray(shape.vertex_positions_buffer(), dtype=np.float64).reshape(-1, 3)
        f = np.asarray(shape.faces_buffer(), dtype=np.int64).reshape(-1, 3)
        nrm = None
        if shape.has_vertex_normals():
            nrm = np.asarray(shape.vertex_normals_buffer(), dtype=np.float64).reshape(-1, 3)
        return v, f, nrm
    kind = shape.class_name()
    params = mi.traverse(shape)
    if kind not in ("Disk", "Sphere", "Cylinder") or "to_world" not in params.keys():
        _warn(f"Mitsuba shape {name!r} of kind {kind} is not supported (meshes, disk, sphere and "
              "cylinder are); it is left out of the occluders and receivers.")
        return None
    m = _matrix(params["to_world"])
    if kind == "Disk":
        k = int(disc_segments)
        v, f = _oriented(_ngon(k), _fan(k), m)
    elif kind == "Sphere":
        v, f = _oriented(*_uv_sphere(int(sphere_segments)), m)
    else:
        v, f = _oriented(*_open_tube(int(sphere_segments)), m)
    return v, f, None


def _canonical(poly: np.ndarray) -> np.ndarray:
    """The polygon's vertices from its lexicographically smallest vertex on (same cycle)."""
    i = min(range(len(poly)), key=lambda j: tuple(poly[j]))
    return np.roll(poly, -i, axis=0)


def _hull_2d(x: np.ndarray) -> list[int]:
    """Indices of the convex hull of 2-D points, counter-clockwise, collinear points dropped."""
    order = sorted(range(len(x)), key=lambda i: (x[i, 0], x[i, 1]))
    cross = lambda o, a, b: (x[a, 0] - x[o, 0]) * (x[b, 1] - x[o, 1]) - (x[a, 1] - x[o, 1]) * (x[b, 0] - x[o, 0])  # noqa: E731
    hull: list[int] = []
    for seq in (order, order[::-1]):
        part: list[int] = []
        for i in seq:
            while len(part) >= 2 and cross(part[-2], part[-1], i) <= 0:
                part.pop()
            part.append(i)
        hull += part[:-1]
    return hull


def emitter_polygons(v: np.ndarray, f: np.ndarray) -> list[np.ndarray]:
    """The convex polygons of an emitting triangle mesh: triangles grouped by plane; a group
    whose union is convex (its hull's area equals the triangles' total) becomes that hull,
    oriented like its triangles; other groups are split by `jaxshadow.Mesh`'s coplanar merge."""
    from .._core.mesh import Mesh

    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    cr = np.cross(b - a, c - a)
    area2 = np.linalg.norm(cr, axis=1)
    keep = area2 > 0
    f, cr, area2, a = f[keep], cr[keep], area2[keep], a[keep]
    nrm = cr / area2[:, None]
    size = float(np.max(np.ptp(v, axis=0))) or 1.0
    groups: list[list[int]] = []
    for i in range(len(f)):
        for g in groups:
            j = g[0]
            if nrm[i] @ nrm[j] > 1 - 1e-9 and abs((a[i] - a[j]) @ nrm[j]) <= 1e-7 * size:
                g.append(i)
                break
        else:
            groups.append([i])
    out = []
    for g in groups:
        n = nrm[g[0]]
        e1 = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        ids = np.unique(f[g])
        xy = np.stack([v[ids] @ e1, v[ids] @ e2], axis=1)
        hull = _hull_2d(xy)
        h = xy[hull]
        hull_area = 0.5 * abs(np.sum(h[:, 0] * np.roll(h[:, 1], -1) - np.roll(h[:, 0], -1) * h[:, 1]))
        if abs(hull_area - 0.5 * area2[g].sum()) <= 1e-6 * hull_area:
            out.append(_canonical(v[ids[hull]]))  # counter-clockwise about n = (e1 x e2)
        else:
            sub = f[g]
            mesh = Mesh(v, sub)
            for poly in mesh.polygons:
                pn = np.sum(np.cross(poly, np.roll(poly, -1, axis=0)), axis=0)
                out.append(_canonical(poly if pn @ n > 0 else poly[::-1].copy()))
    return out


# --------------------------------------------------------------------------------------
# BSDF <-> Material
# --------------------------------------------------------------------------------------


def _exponent_from_alpha(alpha: float) -> float:
    return max(2.0 / max(alpha, 1e-12) ** 2 - 2.0, 0.0)


def material_from_bsdf(mi: Any, bsdf: Any, name: str = "bsdf") -> Material:
    """The nearest Phong `Material` of a Mitsuba BSDF (mapping in the module docstring); an
    `UnsupportedMitsubaElementWarning` and `Material()` when there is none."""
    kind = bsdf.class_name()
    p = mi.traverse(bsdf)
    keys = set(p.keys())

    def textured(prefix: str) -> bool:
        return any(k.startswith(prefix + ".") and k != prefix + ".value" for k in keys)

    def fallback(why: str) -> Material:
        _warn(f"BSDF {name!r} ({kind}): {why}; using Material() (k_d = 0.5, no specular).")
        return Material(ka=np.zeros(3), kd=np.full(3, 0.5), ks=np.zeros(3), exponent=1.0)

    if kind == "TwoSidedBRDF":
        inner = {k[len("brdf_0."):]: k for k in keys if k.startswith("brdf_0.")}
        if not inner:
            return fallback("an empty twosided BSDF")
        return material_from_bsdf(mi, _child(bsdf, 0), name)
    if kind == "SmoothDiffuse":
        rho = _rgb_param(p, "reflectance.value")
        if rho is None or textured("reflectance"):
            return fallback("a textured reflectance is not represented")
        return Material(ka=np.zeros(3), kd=rho, ks=np.zeros(3), exponent=1.0)
    if kind in ("SmoothPlastic", "RoughPlastic"):
        rho = _rgb_param(p, "diffuse_reflectance.value")
        if rho is None or textured("diffuse_reflectance"):
            return fallback("a textured diffuse_reflectance is not represented")
        eta = float(np.asarray(p["eta"]).ravel()[0])
        f0 = ((eta - 1) / (eta + 1)) ** 2
        kd = np.pi * _diffuse_at_normal_incidence(mi, bsdf)
        n = SMOOTH_EXPONENT if kind == "SmoothPlastic" else _exponent_from_alpha(float(np.asarray(p["alpha"]).ravel()[0]))
        return Material(ka=np.zeros(3), kd=kd, ks=np.full(3, f0), exponent=n)
    if kind in ("SmoothConductor", "RoughConductor"):
        if any(textured(k) for k in ("eta", "k", "specular_reflectance", "alpha")) or "alpha_u.value" in keys:
            return fallback("textured or anisotropic parameters are not represented")
        eta, k = (np.broadcast_to(np.asarray(p[f"{x}.value"], np.float64).ravel(), (3,)) for x in ("eta", "k"))
        refl = _rgb_param(p, "specular_reflectance.value")
        refl = np.ones(3) if refl is None else refl
        ks = refl * ((eta - 1) ** 2 + k**2) / ((eta + 1) ** 2 + k**2)
        n = SMOOTH_EXPONENT if kind == "SmoothConductor" else _exponent_from_alpha(float(np.asarray(p["alpha.value"]).ravel()[0]))
        return Material(ka=np.zeros(3), kd=np.zeros(3), ks=ks, exponent=n)
    if kind == "BlendBSDF":
        w = np.asarray(p["weight.value"], np.float64).ravel() if "weight.value" in keys else None
        rho = _rgb_param(p, "bsdf_0.reflectance.value")
        refl = _rgb_param(p, "bsdf_1.specular_reflectance.value")
        alpha = np.asarray(p["bsdf_1.alpha.value"], np.float64).ravel() if "bsdf_1.alpha.value" in keys else None
        if w is None or w.size != 1 or rho is None or refl is None or alpha is None or alpha.size != 1:
            return fallback("only the blend of a diffuse and a roughconductor that material_to_bsdf writes is read")
        return Material(ka=np.zeros(3), kd=(1 - w[0]) * rho, ks=w[0] * refl, exponent=_exponent_from_alpha(float(alpha[0])))
    return fallback("no Phong counterpart")


def _diffuse_at_normal_incidence(mi: Any, bsdf: Any) -> np.ndarray:
    """Mitsuba's own value of a BSDF's diffuse component for wi = wo = the normal (RGB)."""
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.wi = mi.Vector3f(0, 0, 1)
    ctx = mi.BSDFContext(mi.TransportMode.Radiance, int(mi.BSDFFlags.DiffuseReflection))
    f = np.asarray(bsdf.eval(ctx, si, mi.Vector3f(0, 0, 1)), np.float64).ravel()
    return np.broadcast_to(f, (3,)).copy()


def _child(bsdf: Any, i: int) -> Any:
    """The i-th nested BSDF of a twosided BSDF (through its object traversal)."""
    import mitsuba as mi

    found: list[Any] = []

    class Collect(mi.TraversalCallback):  # type: ignore[misc, name-defined]
        def put(self, name: str, value: Any, flags: int) -> None:
            if isinstance(value, mi.BSDF):
                found.append(value)

    bsdf.traverse(Collect())
    return found[i]




def from_mitsuba(path_or_dict: Any, *, disc_segments: int = DISC_SEGMENTS, sphere_segments: int = SPHERE_SEGMENTS,
                 weld: float | None = 0.0) -> tuple[Scene, list[ReceiverMesh], list[Material]]:
    """A Mitsuba 3 scene as jaxshadow's: lights, occluders, receiver surfaces and materials.

    **Arguments:**

    - `path_or_dict`: a Mitsuba XML file, a `mi.load_dict` dictionary, or a loaded `mi.Scene`.
    - `disc_segments`: vertices of the regular polygon (of equal area) standing in for a `disk`.
    - `sphere_segments`: segments around a tessellated `sphere` or `cylinder` (inscribed).
    - `weld`: each shape's vertices at equal positions (`0.0`, default) or within `weld` (m)
      are merged unless their normals differ by more than 45 degrees (`ReceiverMesh.welded`;
      `n_welded` counts them), so a mesh split at UV seams is one surface while a cube keeps
      its hard edges; `None` keeps Mitsuba's vertex buffers. The occluders are welded by
      position (closed meshes are found closed).

    Shapes and emitters are taken in id order (those without an id after, in Mitsuba's order):
    area lights first, then point and directional lights. A file is loaded without Mitsuba's
    merging of shapes that share a BSDF, so each shape is one receiver.

    **Returns:** `(scene, receivers, materials)`: a `Scene` (polygon, point and directional
    lights; every non-emitting shape as a `Mesh` occluder; no ambient), a list of
    `ReceiverMesh` (one per non-emitting shape, named by its id; vertex normals area-weighted
    from its welded faces, as for every `ReceiverMesh`) and a list of `Material`
    (`materials[i]` is the nearest Phong material of `receivers[i]`'s BSDF). Elements that
    cannot be represented raise an `UnsupportedMitsubaElementWarning` naming them.
    """
    mi = import_mitsuba()
    scene, receivers, materials, _ = convert_scene(mi, load_mitsuba_scene(mi, path_or_dict), disc_segments, sphere_segments,
                                                   weld=weld)
    return scene, receivers, materials


def convert_scene(mi: Any, ms: Any, disc_segments: int = DISC_SEGMENTS, sphere_segments: int = SPHERE_SEGMENTS,
                  textures: bool = False, weld: float | None = 0.0) -> tuple[Scene, list[ReceiverMesh], list[Material], list[Any]]:
    """`from_mitsuba` of a loaded `mi.Scene`, plus the Mitsuba shape of each receiver. With
    `textures`, a `diffuse` BSDF with a textured reflectance raises no warning (the renderer
    looks the texture up per pixel)."""
    if int(disc_segments) < 3 or int(sphere_segments) < 3:
        raise ValueError("from_mitsuba: disc_segments and sphere_segments must be >= 3.")
    lights: list[Any] = []
    receivers: list[ReceiverMesh] = []
    materials: list[Material] = []
    shapes: list[Any] = []
    for i, shape in _ordered(ms.shapes()):
        name = _name(shape, "shape", i)
        if shape.is_sensor():
            continue
        geom = shape_geometry(mi, shape, name, disc_segments, sphere_segments)
        if shape.is_emitter():
            emitter = shape.emitter()
            radiance = _rgb_param(mi.traverse(emitter), "radiance.value")
            if emitter.class_name() != "AreaLight" or radiance is None:
                _warn(f"emitter on shape {name!r} ({emitter.class_name()}): only area emitters of uniform RGB "
                      "radiance are represented; it is left out.")
                continue
            if not (shape.is_mesh() or shape.class_name() == "Disk"):
                _warn(f"emitter on shape {name!r} (AreaLight on a {shape.class_name()}): only meshes and discs "
                      "become polygon lights; it is left out.")
                continue
            if geom is None:
                continue
            lights += [PolygonLight(poly, radiance) for poly in emitter_polygons(geom[0], geom[1])]
            continue
        if geom is None:
            continue
        v, f, _ = geom
        receiver = ReceiverMesh(v, f, name=name)
        receivers.append(receiver if weld is None else receiver.welded(weld))
        if textures and textured_diffuse(mi, shape.bsdf()):
            materials.append(Material(ka=np.zeros(3), kd=np.full(3, 0.5), ks=np.zeros(3), exponent=1.0))
        else:
            materials.append(material_from_bsdf(mi, shape.bsdf(), f"{name}.bsdf"))
        shapes.append(shape)
    for i, emitter in _ordered(ms.emitters()):
        kind = emitter.class_name()
        if kind == "AreaLight":
            continue  # on a shape: above
        name = _name(emitter, "emitter", i)
        p = mi.traverse(emitter)
        if kind == "PointLight":
            inten = _rgb_param(p, "intensity.value")
            if inten is not None:
                lights.append(PointLight(_f32(np.asarray(p["position"]).ravel()), inten))
                continue
        elif kind == "DirectionalEmitter":
            irr = _rgb_param(p, "irradiance.value")
            if irr is not None:
                d = _matrix(p["to_world"])[:3, 2]
                lights.append(DirectionalLight(_f32(d / np.linalg.norm(d)), irr))
                continue
        _warn(f"emitter {name!r} ({kind}) has no jaxshadow counterpart (point, directional and area "
              "emitters of uniform RGB do); it is left out.")
    occluders = [r.occluder() for r in receivers]
    return Scene(lights, occluders=occluders or None), receivers, materials, shapes


def textured_diffuse(mi: Any, bsdf: Any) -> bool:
    """Whether a BSDF is a `diffuse` (possibly `twosided`) with a textured reflectance."""
    if bsdf.class_name() == "TwoSidedBRDF":
        bsdf = _child(bsdf, 0)
    keys = set(mi.traverse(bsdf).keys())
    return bsdf.class_name() == "SmoothDiffuse" and "reflectance.value" not in keys


def read_sensor(path_or_dict: Any) -> dict | None:
    """The first sensor of a Mitsuba scene as a plain dict (`perspective` only): `fov` (degrees,
    along x), `to_world` `(4, 4)`, `width`, `height`, `near_clip`, `far_clip`, `spp`; `None`
    (with a warning for another kind) when there is none."""
    mi = import_mitsuba()
    ms = load_mitsuba_scene(mi, path_or_dict)
    if not ms.sensors():
        return None
    s = ms.sensors()[0]
    if s.class_name() != "PerspectiveCamera":
        _warn(f"sensor {s.class_name()} is not read (only perspective cameras are).")
        return None
    p = mi.traverse(s)
    size = [int(x) for x in s.film().size()]
    return {"fov": float(np.asarray(p["x_fov"]).ravel()[0]), "to_world": _matrix(p["to_world"]),
            "width": size[0], "height": size[1], "near_clip": float(p["near_clip"]),
            "far_clip": float(p["far_clip"]), "spp": int(s.sampler().sample_count())}
