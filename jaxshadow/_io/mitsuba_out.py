r"""A jaxshadow scene as a Mitsuba 3 scene (`to_mitsuba`, `to_mitsuba_dict`, `scene_items`), and
the selection of Mitsuba's variant (`import_mitsuba`). What maps to what (lights, occluders, the linear
light's stand-ins and their measured bias) is documented in `jaxshadow.mitsuba`'s docstring."""

from __future__ import annotations

import math
import os
import re
import xml.etree.ElementTree as ET
from typing import Any

import numpy as np

from .._core.files import atomic_write
from .._core.geometry import strip_padding
from .._scene.model import DirectionalLight, LinearLight, Material, PointLight, PolygonLight, Scene
from .meshio import write_mesh
from .mitsuba_io import _warn, import_mitsuba


def rgb_dict(mi: Any, x: Any) -> dict:
    """A Mitsuba `rgb` property of a scalar or `(3,)` colour (float64 components)."""
    v = np.broadcast_to(np.asarray(x, dtype=np.float64), (3,))
    return {"type": "rgb", "value": [float(c) for c in v]}


def _mi_mesh(mi: Any, name: str, vertices: np.ndarray, faces: np.ndarray, props: Any) -> Any:
    """An `mi.Mesh` from vertex and triangle arrays (face normals only)."""
    import drjit as dr

    v = np.asarray(vertices, np.float32)
    f = np.asarray(faces, np.uint32)
    mesh = mi.Mesh(name, v.shape[0], f.shape[0], props=props)
    params = mi.traverse(mesh)
    params["vertex_positions"] = dr.ravel(mi.Point3f(v.T))
    params["faces"] = dr.ravel(mi.Vector3u(f.T))
    params.update()
    return mesh


def _fan_arrays(polygons: list) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and fan triangles of convex polygons."""
    verts: list[np.ndarray] = []
    faces: list[tuple[int, int, int]] = []
    base = 0
    for poly in polygons:
        poly = np.asarray(poly, dtype=np.float64)
        k = poly.shape[0]
        verts.append(poly)
        faces.extend((base, base + i, base + i + 1) for i in range(1, k - 1))
        base += k
    return np.concatenate(verts), np.asarray(faces, dtype=np.int64)


def fan_mesh(mi: Any, name: str, polygons: list, props: Any) -> Any:
    """One `mi.Mesh` holding the fan triangulations of convex polygons (face normals only)."""
    return _mi_mesh(mi, name, *_fan_arrays(polygons), props)


def _surface_ids(names: list[str]) -> list[str]:
    """Ids `s000_<name>` (characters other than letters, digits, `_.-` replaced): sorted, they
    keep the receivers' order (`from_mitsuba` reads shapes in id order)."""
    return [f"s{i:03d}_" + re.sub(r"[^A-Za-z0-9_.-]", "_", re.sub(r"^s\d{3}_", "", n)) for i, n in enumerate(names)]


def scene_items(scene: Scene, receivers: Any = (), materials: Any = (), *, segment_points: int = 64,
                segment_radius: float = 1e-4) -> list[tuple[str, dict]]:
    """`(name, plugin dict)` of every Mitsuba object of a scene, meshes as `{"type": "_mesh",
    "vertices", "faces", "emitter" | "bsdf"}` (`to_mitsuba_dict` makes them `mi.Mesh` objects,
    `write_mitsuba_xml` PLY files). Arguments as `to_mitsuba_dict`."""
    if not isinstance(scene, Scene):
        raise ValueError(f"to_mitsuba: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    if int(segment_points) < 1:
        raise ValueError(f"to_mitsuba: segment_points must be >= 1, got {segment_points!r}.")
    if not segment_radius > 0:
        raise ValueError(f"to_mitsuba: segment_radius must be > 0, got {segment_radius!r}.")
    receivers, materials = list(receivers), list(materials)
    if len(materials) > len(receivers):
        raise ValueError(f"to_mitsuba: {len(materials)} materials for {len(receivers)} receivers.")
    rgb = lambda x: rgb_dict(None, x)  # noqa: E731
    out: list[tuple[str, dict]] = []
    for i, light in enumerate(scene.lights):
        if isinstance(light, PolygonLight):
            v, f = _fan_arrays([np.asarray(light.vertices)])
            out.append((f"light_{i:03d}", {"type": "_mesh", "vertices": v, "faces": f,
                                       "emitter": {"type": "area", "radiance": rgb(light.radiance)}}))
        elif isinstance(light, PointLight):
            out.append((f"light_{i:03d}", {
                "type": "point",
                "position": [float(c) for c in np.asarray(light.position, dtype=np.float64)],
                "intensity": rgb(light.intensity),
            }))
        elif isinstance(light, DirectionalLight):
            d = np.asarray(light.direction, dtype=np.float64)
            out.append((f"light_{i:03d}", {
                "type": "directional",
                "direction": [float(c) for c in d / np.linalg.norm(d)],
                "irradiance": rgb(light.irradiance),
            }))
        elif isinstance(light, LinearLight):
            a = np.asarray(light.start, dtype=np.float64)
            b = np.asarray(light.end, dtype=np.float64)
            phi = np.asarray(light.power, dtype=np.float64)
            length = float(np.linalg.norm(b - a))
            if light.profile == "isotropic":
                m = int(segment_points)
                for j in range(m):
                    x = a + (j + 0.5) / m * (b - a)
                    out.append((f"light_{i:03d}_{j:03d}", {
                        "type": "point",
                        "position": [float(c) for c in x],
                        "intensity": rgb(phi * length / (4.0 * math.pi * m)),
                        "sampling_weight": 1.0 / m,
                    }))
            elif light.exponent == 1:
                r = float(segment_radius) * length
                out.append((f"light_{i:03d}", {
                    "type": "cylinder",
                    "p0": [float(c) for c in a],
                    "p1": [float(c) for c in b],
                    "radius": r,
                    "emitter": {"type": "area", "radiance": rgb(phi / (2.0 * math.pi**2 * r))},
                }))
            else:
                raise NotImplementedError(
                    f"to_mitsuba: scene.lights[{i}] is a cosine LinearLight with exponent "
                    f"{light.exponent}; Mitsuba has a stand-in only for m = 1 (a Lambertian "
                    "cylinder) "
                    "and the isotropic profile (a chain of point lights)."
                )
        else:  # pragma: no cover - Scene validates its lights
            raise ValueError(f"to_mitsuba: unsupported light {type(light).__name__}.")
    if receivers:

        names = _surface_ids([r.name for r in receivers])
        for k, (name, r) in enumerate(zip(names, receivers, strict=True)):
            mat = materials[k] if k < len(materials) else Material()
            out.append((name, {"type": "_mesh", "vertices": r.vertices, "faces": r.faces,
                               "bsdf": material_to_bsdf(mat)}))
    elif scene.occluders is not None:
        v, f = _fan_arrays([strip_padding(p) for p in np.asarray(scene.occluders, dtype=np.float64)])
        out.append(("occluders", {"type": "_mesh", "vertices": v, "faces": f,
                                  "bsdf": {"type": "diffuse", "reflectance": rgb(0.0)}}))
    return out


def to_mitsuba_dict(
    scene: Scene, *, receivers: Any = (), materials: Any = (), sensor: dict | None = None,
    segment_points: int = 64, segment_radius: float = 1e-4
) -> dict:
    r"""The `mi.load_dict` dictionary of a jaxshadow scene (see the module docstring).

    **Arguments:**

    - `scene`: a jaxshadow `Scene`. Ambient radiance is not part of it (it is not light that
      Mitsuba transports; `reference_shade` adds $k_a L_a$ itself).
    - `receivers`, `materials`: receiver surfaces (`ReceiverMesh`, e.g. from `from_mitsuba`) and
      their `Material`s, written as meshes with the nearest BSDF (`material_to_bsdf`); when any
      are given they are the occluders (as in `from_mitsuba`), else `scene.occluders` are
      written as one black mesh.
    - `sensor`: a camera as `read_sensor` returns it, or `None`.
    - `segment_points`: number $M$ of point emitters standing in for an isotropic `LinearLight`.
    - `segment_radius`: radius of the Lambertian cylinder standing in for a cosine ($m = 1$)
      `LinearLight`, as a fraction of its length.

    **Returns:** a dict with `"type": "scene"`; meshes are `mi.Mesh` objects, so build a fresh
    dict for every `mi.load_dict`.
    """
    mi = import_mitsuba()
    out: dict[str, Any] = {"type": "scene"}
    for name, d in scene_items(scene, receivers, materials, segment_points=segment_points,
                               segment_radius=segment_radius):
        if d["type"] == "_mesh":
            props = mi.Properties()
            for k in ("emitter", "bsdf"):
                if k in d:
                    props[k] = mi.load_dict(d[k])
            out[name] = _mi_mesh(mi, name, d["vertices"], d["faces"], props)
        else:
            out[name] = d
    if sensor is not None:
        out["sensor"] = {
            "type": "perspective", "fov": float(sensor["fov"]), "fov_axis": "x",
            "to_world": mi.ScalarTransform4f(np.asarray(sensor["to_world"], np.float64).tolist()),
            "film": {"type": "hdrfilm", "width": int(sensor["width"]), "height": int(sensor["height"]),
                     "rfilter": {"type": "box"}},
            "sampler": {"type": "independent", "sample_count": int(sensor.get("spp", 16))},
        }
    return out


def to_mitsuba(scene: Scene, *, receivers: Any = (), materials: Any = (), sensor: dict | None = None,
               segment_points: int = 64, segment_radius: float = 1e-4) -> Any:
    """The Mitsuba twin of a jaxshadow scene: `mi.load_dict(to_mitsuba_dict(scene, ...))`.

    **Arguments:** as `to_mitsuba_dict`.

    **Returns:** an `mi.Scene` (variant `llvm_ad_rgb`).
    """
    mi = import_mitsuba()
    return mi.load_dict(
        to_mitsuba_dict(scene, receivers=receivers, materials=materials, sensor=sensor,
                        segment_points=segment_points, segment_radius=segment_radius)
    )


def _alpha_from_exponent(n: float) -> float:
    return math.sqrt(2.0 / (n + 2.0))



def material_to_bsdf(material: Material) -> dict:
    """A Mitsuba BSDF dict for a `Material` (module docstring): `diffuse` when $k_s = 0$, else a
    `blendbsdf` of a diffuse and a Fresnel-free Beckmann `roughconductor`. $k_a$ has no
    counterpart (Mitsuba does not transport ambient light)."""
    kd = np.broadcast_to(np.asarray(material.kd, np.float64), (3,))
    ks = np.broadcast_to(np.asarray(material.ks, np.float64), (3,))
    rgb = lambda x: {"type": "rgb", "value": [float(c) for c in x]}  # noqa: E731
    if not np.any(ks > 0):
        return {"type": "diffuse", "reflectance": rgb(kd)}
    n = float(np.asarray(material.exponent))
    # Mitsuba's RGB reflectances must lie in [0, 1]: weight w with k_d/(1-w), k_s/w <= 1 when
    # max k_d + max k_s <= 1; beyond that the material reflects more than it receives.
    a, b = float(kd.max()), float(ks.max())
    if a + b > 1:
        _warn(f"Material with max k_d + max k_s = {a + b:.4g} > 1 has no Mitsuba BSDF; scaled down to 1.")
        kd, ks, a, b = kd / (a + b), ks / (a + b), a / (a + b), b / (a + b)
    w = b / (a + b)
    return {
        "type": "blendbsdf",
        "weight": w,
        "bsdf_0": {"type": "diffuse", "reflectance": rgb(kd / (1 - w) if w < 1 else np.zeros(3))},
        "bsdf_1": {"type": "roughconductor", "material": "none", "distribution": "beckmann",
                   "alpha": _alpha_from_exponent(n), "specular_reflectance": rgb(ks / w)},
    }


# --------------------------------------------------------------------------------------
# from_mitsuba


# --------------------------------------------------------------------------------------
# XML out
# --------------------------------------------------------------------------------------

_TAGS = {"diffuse": "bsdf", "blendbsdf": "bsdf", "roughconductor": "bsdf", "area": "emitter", "point": "emitter",
         "directional": "emitter", "ply": "shape", "cylinder": "shape", "perspective": "sensor",
         "hdrfilm": "film", "independent": "sampler", "box": "rfilter", "direct": "integrator"}
_POINTS = {"position", "p0", "p1"}
_VECTORS = {"direction"}


def _xml_value(parent: ET.Element, name: str, value: Any) -> None:
    def nums(x: Any) -> str:
        return ", ".join(repr(float(c)) for c in np.ravel(x))

    if isinstance(value, dict) and value.get("type") == "rgb":
        ET.SubElement(parent, "rgb", name=name, value=nums(value["value"]))
    elif isinstance(value, dict):
        _xml_plugin(parent, value)  # nested plugins are read in order (blendbsdf: bsdf_0, bsdf_1)
    elif name == "to_world":
        t = ET.SubElement(parent, "transform", name=name)
        ET.SubElement(t, "matrix", value=" ".join(repr(float(c)) for c in np.ravel(value)))
    elif name in _POINTS or name in _VECTORS:
        x, y, z = (repr(float(c)) for c in value)
        ET.SubElement(parent, "point" if name in _POINTS else "vector", name=name, x=x, y=y, z=z)
    elif isinstance(value, bool):
        ET.SubElement(parent, "boolean", name=name, value=str(value).lower())
    elif isinstance(value, (int, np.integer)):
        ET.SubElement(parent, "integer", name=name, value=str(int(value)))
    elif isinstance(value, (float, np.floating)):
        ET.SubElement(parent, "float", name=name, value=repr(float(value)))
    elif isinstance(value, str):
        ET.SubElement(parent, "string", name=name, value=value)
    else:
        raise ValueError(f"write_mitsuba_xml: cannot write {name!r} = {value!r}.")


def _xml_plugin(parent: ET.Element, d: dict, ident: str | None = None) -> ET.Element:
    tag = _TAGS.get(d["type"])
    if tag is None:
        raise ValueError(f"write_mitsuba_xml: no XML tag known for plugin type {d['type']!r}.")
    el = ET.SubElement(parent, tag, type=d["type"])
    if ident is not None:
        el.set("id", ident)
    for k, v in d.items():
        if k != "type":
            _xml_value(el, k, v)
    return el


def write_mitsuba_xml(path: str | os.PathLike, scene: Scene, receivers: Any = (), materials: Any = (), *,
                      sensor: dict | None = None, integrator: str = "direct", segment_points: int = 64,
                      segment_radius: float = 1e-4) -> None:
    """Write a jaxshadow scene as a Mitsuba 3 XML file (`mi.load_file` reads it back).

    **Arguments:**

    - `path`: the `.xml` file. Meshes go to PLY files in the directory `<stem>_meshes` beside it
      (created); every file is written atomically.
    - `scene`: lights as in `to_mitsuba_dict`. Occluders: the `receivers` when any are given
      (`from_mitsuba` makes every receiver surface an occluder), else `scene.occluders` (one
      black mesh).
    - `receivers`, `materials`: `ReceiverMesh` surfaces and their `Material` (as a BSDF,
      `material_to_bsdf`; a missing material is `Material()`).
    - `sensor`: a `read_sensor` dict, or `None` for no camera.
    - `integrator`: the integrator plugin (default `direct`).
    - `segment_points`, `segment_radius`: the stand-ins of linear lights (`to_mitsuba_dict`).
    """
    path = os.fspath(path)
    if not path.lower().endswith(".xml"):
        raise ValueError(f"{path}: write_mitsuba_xml writes .xml files.")
    directory = os.path.dirname(os.path.abspath(path))
    stem = os.path.splitext(os.path.basename(path))[0]
    mesh_dir = os.path.join(directory, f"{stem}_meshes")
    receivers, materials = list(receivers), list(materials)
    items = scene_items(scene, receivers, materials, segment_points=segment_points, segment_radius=segment_radius)
    root = ET.Element("scene", version="3.0.0")
    if integrator:
        ET.SubElement(root, "integrator", type=integrator)
    if sensor is not None:
        sd = {"type": "perspective", "fov": float(sensor["fov"]), "fov_axis": "x",
              "near_clip": float(sensor.get("near_clip", 0.01)), "far_clip": float(sensor.get("far_clip", 1e4)),
              "to_world": np.asarray(sensor["to_world"], np.float64),
              "sampler": {"type": "independent", "sample_count": int(sensor.get("spp", 16))},
              "film": {"type": "hdrfilm", "width": int(sensor["width"]), "height": int(sensor["height"]),
                       "rfilter": {"type": "box"}}}
        _xml_plugin(root, sd)
    os.makedirs(mesh_dir, exist_ok=True)
    for name, d in items:
        if d["type"] == "_mesh":
            ply = os.path.join(mesh_dir, f"{name}.ply")
            write_mesh(ply, d["vertices"], d["faces"])
            shape = {"type": "ply", "filename": os.path.relpath(ply, directory).replace(os.sep, "/"),
                     "face_normals": d.get("vertex_normals") is None}
            for k in ("bsdf", "emitter"):
                if k in d:
                    shape[k] = d[k]
            _xml_plugin(root, shape, name)
        else:
            _xml_plugin(root, d, name)
    ET.indent(root)
    text = ET.tostring(root, encoding="unicode")
    with atomic_write(path) as fh:
        fh.write('<?xml version="1.0" encoding="utf-8"?>\n<!-- written by jaxshadow -->\n' + text + "\n")



_EXAMPLE = """<?xml version="1.0" encoding="utf-8"?>
<!-- jaxshadow's example scene: a rectangle light, a torus (OBJ, {faces} triangles) and a floor -->
<scene version="3.0.0">
  <integrator type="direct"/>
  <sensor type="perspective">
    <float name="fov" value="40"/>
    <transform name="to_world"><lookat origin="0, -3.4, 2.6" target="0, 0, 0.3" up="0, 0, 1"/></transform>
    <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>
    <film type="hdrfilm">
      <integer name="width" value="{res}"/><integer name="height" value="{res}"/><rfilter type="box"/>
    </film>
  </sensor>
  <shape type="rectangle" id="lamp">
    <transform name="to_world">
      <scale x="0.3" y="0.3"/><rotate x="1" angle="180"/><translate x="0.15" y="0.1" z="1.6"/>
    </transform>
    <emitter type="area"><rgb name="radiance" value="8, 8, 8"/></emitter>
  </shape>
  <shape type="obj" id="torus">
    <string name="filename" value="torus.obj"/>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.3, 0.2"/></bsdf>
  </shape>
  <shape type="rectangle" id="floor">
    <transform name="to_world"><scale x="2" y="2"/></transform>
    <bsdf type="diffuse"><rgb name="reflectance" value="0.6, 0.6, 0.6"/></bsdf>
  </shape>
</scene>
"""


def write_example_scene(directory: str | os.PathLike, resolution: int = 256, spp: int = 16) -> str:
    """Write jaxshadow's example Mitsuba scene into `directory`: `scene.xml` (a 0.6 m square
    light 1.6 m above a 4 m floor, a tilted torus of 768 triangles, `torus.obj`, between them; a
    camera of `resolution` x `resolution` pixels with a box filter, `spp` samples per pixel).

    **Returns:** the path of `scene.xml`.
    """
    from .meshio import import_trimesh, write_mesh

    trimesh = import_trimesh()
    directory = os.fspath(directory)
    torus = trimesh.creation.torus(0.35, 0.12, major_sections=32, minor_sections=12)
    torus.apply_transform(trimesh.transformations.rotation_matrix(np.radians(20), [1, 0, 0]))
    torus.apply_translation([0.1, 0.0, 0.6])
    write_mesh(os.path.join(directory, "torus.obj"), torus.vertices, torus.faces)
    path = os.path.join(directory, "scene.xml")
    with atomic_write(path) as fh:
        fh.write(_EXAMPLE.format(faces=len(torus.faces), res=int(resolution), spp=int(spp)))
    return path
