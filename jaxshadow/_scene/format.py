"""The JSON scene format (versioned): scenes, lights and materials to and from dicts and files.

Schema version 1 keeps everything inline in the JSON; version 2 may store meshes' arrays in a
NumPy `.npz` file beside it (`save_scene`), named and hashed in the JSON's `arrays` entry.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from typing import Any, no_type_check

import numpy as np

from .._core.files import atomic_write
from .._core.mesh import Mesh, OccluderTopology, mesh_dicts
from .model import (
    AbstractLight,
    DirectionalLight,
    LinearLight,
    Material,
    PointLight,
    PolygonLight,
    Scene,
)

SCENE_FORMAT = "jaxshadow.scene"
# 1: everything inline in the JSON. 2: meshes may live in a binary `.npz` beside it ("arrays").
SCENE_VERSION = 1
SCENE_VERSION_ARRAYS = 2
READ_VERSIONS = (1, 2)
MESH_ARRAYS_SUFFIX = ".meshes.npz"



def _tolist(x: Any) -> Any:
    return np.asarray(x, dtype=np.float64).tolist()


def light_to_dict(light: Any) -> dict:
    """The JSON-able dict of one light (`{"type": ..., fields}`; `_LIGHT_FIELDS` names them)."""
    if not isinstance(light, AbstractLight):
        raise TypeError(f"not a light: {type(light).__name__}")
    name = _TYPE_OF_KIND[light.kind]
    _, required, optional = _LIGHT_FIELDS[name]
    d: dict[str, Any] = {"type": name}
    fields: Any = light  # a LinearLight's static fields, read when its type names them
    for key in required + optional:
        if key == "profile":
            d[key] = fields.profile
        elif key == "exponent":
            if fields.profile == "cosine":
                d[key] = fields.exponent
        else:
            d[key] = _tolist(getattr(light, key))
    return d


_LIGHT_FIELDS = {
    "polygon": (PolygonLight, ("vertices",), ("radiance",)),
    "linear": (LinearLight, ("start", "end"), ("power", "profile", "exponent")),
    "point": (PointLight, ("position",), ("intensity",)),
    "directional": (DirectionalLight, ("direction",), ("irradiance",)),
}
_TYPE_OF_KIND = {"polygon": "polygon", "segment": "linear", "point": "point", "directional": "directional"}


def _has_bool(v: Any) -> bool:
    if isinstance(v, bool):
        return True
    return isinstance(v, list) and any(_has_bool(x) for x in v)


def _numeric(v: Any, where: str) -> np.ndarray:
    """A JSON value as a float64 array, with an error naming the entry (strings, booleans,
    ragged lists)."""
    if _has_bool(v):
        raise ValueError(f"{where}: expected numbers, got a boolean in {v!r}.")
    try:
        a = np.asarray(v, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{where}: expected numbers (a number or nested lists of equal length), got {v!r}.") from None
    return a


def light_from_dict(d: dict, where: str = "light") -> Any:
    if not isinstance(d, dict) or "type" not in d:
        raise ValueError(f"{where}: expected an object with a 'type' field.")
    kind = d["type"]
    if kind not in _LIGHT_FIELDS:
        raise ValueError(f"{where}: unknown light type {kind!r} (expected one of {sorted(_LIGHT_FIELDS)}).")
    cls, required, optional = _LIGHT_FIELDS[kind]
    unknown = set(d) - {"type", *required, *optional}
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {sorted(unknown)} for a {kind} light.")
    missing = [k for k in required if k not in d]
    if missing:
        raise ValueError(f"{where}: missing field(s) {missing} for a {kind} light.")
    kwargs = {k: d[k] for k in (*required, *optional) if k in d}
    for k, v in list(kwargs.items()):
        if k == "profile" and not isinstance(v, str):
            raise ValueError(f"{where}: 'profile' must be a string, got {v!r}.")
        if k == "exponent" and (isinstance(v, bool) or not isinstance(v, (int, float))):
            raise ValueError(f"{where}: 'exponent' must be a number, got {v!r}.")
        if k not in ("profile", "exponent"):
            kwargs[k] = _numeric(v, f"{where}.{k}")
    try:
        return cls(**kwargs)
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None


def material_to_dict(material: Material) -> dict:
    return {
        "ka": _tolist(material.ka),
        "kd": _tolist(material.kd),
        "ks": _tolist(material.ks),
        "exponent": float(np.asarray(material.exponent)),
    }


def material_from_dict(d: dict, where: str = "material") -> Material:
    unknown = set(d) - {"ka", "kd", "ks", "exponent"}
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {sorted(unknown)}.")
    values = {k: _numeric(v, f"{where}.{k}") for k, v in d.items()}
    try:
        return Material(**values)
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None


def scene_to_dict(scene: Scene, material: Material | None = None) -> dict:
    """The JSON-able dict of a scene (and optionally a material), schema version 1.

    Example:
        ```python
        import jaxshadow as js

        d = js.scene_to_dict(js.Scene([js.PointLight([0, 0, 2.0], 1.0)], ambient=0.05))   # JSON-ready
        ```
    """
    out: dict[str, Any] = {
        "format": SCENE_FORMAT,
        "version": SCENE_VERSION,
        "lights": [light_to_dict(light) for light in scene.lights],
        "occluders": [],
        "ambient": _tolist(scene.ambient),
    }
    if scene.occluders is not None:
        out["occluders"] = _occluder_entries(scene, None)
    if material is not None:
        out["material"] = material_to_dict(material)
    return out


def _occluder_entries(scene: Scene, arrays: dict[str, np.ndarray] | None) -> list[Any]:
    """The JSON `occluders` entries of `scene`, in entry order: `(k, 3)` lists for plain
    polygons; for each mesh, its vertices and faces recovered (vectorised) from the padded faces
    by exact equality of coordinates, vertices in order of first use (`mesh_dicts`' result).
    With `arrays`, each mesh goes there as `meshN_vertices (V, 3)` and `meshN_faces (F, K)`
    (rows padded with -1) and its entry is `{"mesh": {"arrays": "meshN"}}`; else it is
    `{"mesh": {"vertices": [...], "faces": [...]}}`."""
    faces = np.asarray(scene.occluders, dtype=np.float64)
    topo = scene.occluder_topology or OccluderTopology.independent(faces.shape[0])
    objs = np.asarray(topo.face_object)
    starts = np.flatnonzero(np.r_[True, objs[1:] != objs[:-1]]) if len(objs) else np.zeros(0, np.int64)
    ends = np.r_[starts[1:], len(objs)]
    out: list[Any] = []
    for f, g in zip(starts.tolist(), ends.tolist(), strict=True):
        if not topo.from_mesh[f]:
            out.extend(mesh_dicts(faces[f:g], OccluderTopology.independent(g - f)))
            continue
        v, loops = _mesh_arrays(faces[f:g])
        if arrays is not None:
            key = f"mesh{len(arrays) // 2}"
            arrays[f"{key}_vertices"], arrays[f"{key}_faces"] = v, loops
            out.append({"mesh": {"arrays": key}})
        else:
            out.append({"mesh": {"vertices": v.tolist(),
                                 "faces": [row[row >= 0].tolist() for row in loops]}})
    return out


def _mesh_arrays(block: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(vertices (V, 3), faces (G, K))` of one mesh's padded faces `block (G, Ko, 3)`: trailing
    copies of a face's first vertex are padding (a face keeps at least three vertices), equal
    coordinates are one vertex (in order of first use), faces padded with -1."""
    from .._core.welding import weld_vertices

    eq = np.all(block == block[:, :1], axis=2)[:, 1:]  # (G, Ko - 1)
    pad = np.flip(np.cumprod(np.flip(eq, axis=1), axis=1), axis=1).astype(bool)
    pad[:, :2] = False
    real = np.concatenate([np.ones((block.shape[0], 1), bool), ~pad], axis=1)
    k = int(real.sum(axis=1).max())
    pts = block[real]
    index, first = weld_vertices(pts)
    loops = np.full(real.shape, -1, dtype=np.int64)
    loops[real] = index
    return pts[first], loops[:, :k]


def _occluder_from_json(o: Any, where: str, arrays: Any = None) -> Any:
    if isinstance(o, dict):
        if set(o) == {"mesh"} and isinstance(o["mesh"], dict) and set(o["mesh"]) == {"arrays"}:
            return _mesh_from_arrays(o["mesh"]["arrays"], where, arrays)
        if set(o) != {"mesh"} or not isinstance(o["mesh"], dict) or set(o["mesh"]) != {"vertices", "faces"}:
            raise ValueError(f"{where}: a mesh is {{'mesh': {{'vertices': [...], 'faces': [...]}}}} "
                             "or {'mesh': {'arrays': NAME}}.")
        faces = o["mesh"]["faces"]
        if not isinstance(faces, list) or not all(isinstance(f, list) and all(isinstance(i, int) and not isinstance(i, bool) for i in f) for f in faces):
            raise ValueError(f"{where}: mesh faces must be lists of integer vertex indices.")
        try:
            return Mesh(_numeric(o["mesh"]["vertices"], f"{where}.vertices"), faces)
        except ValueError as err:
            raise ValueError(f"{where}: {err}") from None
    return _numeric(o, where)


def _mesh_from_arrays(key: Any, where: str, arrays: Any) -> Mesh:
    """A mesh stored in the scene's arrays file: `{key}_vertices` `(V, 3)` float and
    `{key}_faces` `(F, K)` integer, rows padded at their end with -1."""
    if arrays is None:
        raise ValueError(f"{where}: the mesh is stored in the scene's arrays file; read the scene with "
                         "jaxshadow.load_scene(path), which finds that file beside the JSON.")
    if not isinstance(key, str) or f"{key}_vertices" not in arrays or f"{key}_faces" not in arrays:
        raise ValueError(f"{where}: the arrays file has no mesh {key!r}.")
    v, f = np.asarray(arrays[f"{key}_vertices"]), np.asarray(arrays[f"{key}_faces"])
    if not np.issubdtype(f.dtype, np.integer) or f.ndim != 2 or f.shape[1] < 3:
        raise ValueError(f"{where}: mesh faces must be an (F, K >= 3) array of integer vertex indices, "
                         f"got {f.shape} {f.dtype}.")
    if not np.issubdtype(v.dtype, np.floating) or v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{where}: mesh vertices must be a (V, 3) float array, got {v.shape} {v.dtype}.")
    used = f >= 0
    if np.any(f < -1) or np.any(used[:, 1:] & ~used[:, :-1]):
        raise ValueError(f"{where}: mesh faces: a negative index other than the -1 padding at a row's end.")
    faces: Any = f if used.all() else [row[row >= 0] for row in f]
    try:
        return Mesh(v.astype(np.float64), faces)
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def scene_from_dict(d: dict, arrays: Any = None) -> Scene:
    """Build a Scene from its dict form, with errors naming the offending entry.

    **Arguments:** `d`: the dict (schema version 1, or 2 whose meshes may be stored apart);
    `arrays`: for version 2, the mapping of the scene's arrays file (`load_scene` reads it).

    Example:
        ```python
        import jaxshadow as js

        d = js.scene_to_dict(js.Scene([js.PointLight([0, 0, 2.0], 1.0)]))
        scene = js.scene_from_dict(d)
        ```
    """
    if not isinstance(d, dict):
        raise ValueError("scene: expected a JSON object.")
    if d.get("format") != SCENE_FORMAT:
        raise ValueError(f"scene: 'format' must be {SCENE_FORMAT!r}, got {d.get('format')!r}.")
    version = d.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version not in READ_VERSIONS:
        raise ValueError(
            f"scene: unsupported schema version {d.get('version')!r} (this jaxshadow reads "
            f"{', '.join(map(str, READ_VERSIONS))})."
        )
    known = {"format", "version", "lights", "occluders", "ambient", "material"}
    unknown = set(d) - (known | {"arrays"} if version >= SCENE_VERSION_ARRAYS else known)
    if unknown:
        raise ValueError(f"scene: unknown field(s) {sorted(unknown)}.")
    if "lights" not in d:
        raise ValueError("scene: missing field 'lights' (a list of lights; [] for none).")
    raw_lights = d["lights"]
    if not isinstance(raw_lights, list):
        raise ValueError(f"scene: 'lights' must be a list, got {type(raw_lights).__name__}.")
    lights = [light_from_dict(ld, f"scene.lights[{i}]") for i, ld in enumerate(raw_lights)]
    occl = d.get("occluders") or None
    if occl is not None:
        if not isinstance(occl, list):
            raise ValueError(f"scene: 'occluders' must be a list of polygons, got {type(occl).__name__}.")
        occl = [_occluder_from_json(o, f"scene.occluders[{i}]", arrays) for i, o in enumerate(occl)]
    ambient = _numeric(d.get("ambient", 0.0), "scene.ambient")
    return Scene(lights=lights, occluders=occl, ambient=ambient)


def save_scene(scene: Any, path: str | os.PathLike, material: Any = None) -> None:
    """Write a scene (and optionally a material) to a JSON file.

    A scene without meshes is one JSON file (schema version 1). A scene with `Mesh` occluders
    gets schema version 2: each mesh's vertices and faces go, as arrays, to a NumPy `.npz`
    file beside the JSON, `<stem>.meshes.npz` (its name and SHA-256 in the JSON's `arrays`
    entry), so large meshes are not text; keep the two files together.

    Each file is built first and written through `_files.atomic_write` (a temporary file in
    the same directory, renamed over the target when complete), the arrays before the JSON: a
    bad argument, a failing serialiser or a full disk leaves existing files as they were, and
    a JSON left beside arrays from another save is refused by `load_scene` (the hash differs).

    **Arguments:** `scene` (`Scene`), `path` (file name), `material` (`Material` or `None`).

    Example:
        ```python
        import os, tempfile
        import jaxshadow as js

        scene = js.Scene([js.PointLight([0, 0, 2.0], 1.0)], ambient=0.05)
        path = os.path.join(tempfile.mkdtemp(), "scene.json")
        js.save_scene(scene, path, material=js.Material(ka=0.1, kd=0.6, ks=0.3, exponent=20.0))
        ```
    """
    if not isinstance(scene, Scene):
        raise ValueError(f"save_scene: expected a jaxshadow.Scene, got {type(scene).__name__}.")
    if material is not None and not isinstance(material, Material):
        raise ValueError(f"save_scene: material must be a jaxshadow.Material or None, got {type(material).__name__}.")
    d = scene_to_dict(Scene(scene.lights, None, scene.ambient), material)
    arrays: dict[str, np.ndarray] = {}
    if scene.occluders is not None:
        d["occluders"] = _occluder_entries(scene, arrays)
    if arrays:
        name = arrays_file_name(path)
        buf = io.BytesIO()
        np.savez(buf, **arrays)
        data = buf.getvalue()
        d["version"] = SCENE_VERSION_ARRAYS
        d["arrays"] = {"file": name, "sha256": hashlib.sha256(data).hexdigest()}
        with atomic_write(os.path.join(os.path.dirname(os.path.abspath(path)), name), "wb") as fb:
            fb.write(data)
    text = json.dumps(d, indent=2)
    with atomic_write(path) as f:
        f.write(text)


def arrays_file_name(path: str | os.PathLike) -> str:
    """The name of the arrays file `save_scene` writes beside the scene JSON `path`:
    `scene.json` -> `scene.meshes.npz`."""
    return os.path.splitext(os.path.basename(os.fspath(path)))[0] + MESH_ARRAYS_SUFFIX


def _read_arrays(path: str | os.PathLike, d: Any) -> dict[str, np.ndarray] | None:
    """The arrays file a version-2 scene JSON `d` (read from `path`) names, checked against its
    SHA-256; `None` when `d` names none. `ValueError` naming both files otherwise."""
    if not isinstance(d, dict) or "arrays" not in d:
        return None
    ref = d["arrays"]
    if not isinstance(ref, dict) or set(ref) != {"file", "sha256"} or not all(isinstance(x, str) for x in ref.values()):
        raise ValueError(f"{path}: 'arrays' must be {{'file': NAME, 'sha256': HEX}}, got {ref!r}.")
    name = ref["file"]
    if not name or os.path.basename(name) != name or name in (".", ".."):
        raise ValueError(f"{path}: 'arrays.file' must be a file name in the scene's directory, got {name!r}.")
    full = os.path.join(os.path.dirname(os.path.abspath(path)), name)
    try:
        with open(full, "rb") as fh:
            data = fh.read()
    except FileNotFoundError:
        raise ValueError(f"{path}: its mesh arrays file {name!r} is missing (save_scene writes it beside "
                         "the JSON; copy both files).") from None
    except OSError as err:
        raise ValueError(f"{path}: its mesh arrays file {name!r} cannot be read ({err}).") from None
    if hashlib.sha256(data).hexdigest() != ref["sha256"]:
        raise ValueError(f"{path}: its mesh arrays file {name!r} does not match the scene (corrupt, or "
                         "written by another save); save the scene again.")
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as err:
        raise ValueError(f"{path}: its mesh arrays file {name!r} is not a NumPy .npz file ({err}).") from None


def read_json(path: str | os.PathLike) -> Any:
    """A JSON document from a file, with a `ValueError` naming the path (missing file, a
    directory, unreadable, not JSON) instead of a traceback."""
    try:
        with open(path) as f:
            return json.load(f)
    except json.JSONDecodeError as err:
        raise ValueError(f"{path}: not valid JSON ({err}).") from None
    except IsADirectoryError:
        raise ValueError(f"{path}: is a directory, not a scene file.") from None
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file.") from None
    except (PermissionError, UnicodeDecodeError) as err:
        raise ValueError(f"{path}: cannot be read ({err}).") from None
    except RecursionError:
        raise ValueError(f"{path}: JSON nested too deeply to read.") from None


def load_scene(path: str | os.PathLike) -> Scene:
    """Read a scene from a JSON file written by `save_scene` (or by hand, same schema), with
    its meshes' arrays file when it names one (schema version 2, checked by its SHA-256).

    **Returns:** the `Scene`; `ValueError` naming the path or the offending entry otherwise.

    Example:
        ```python
        import os, tempfile
        import jaxshadow as js

        path = os.path.join(tempfile.mkdtemp(), "scene.json")
        js.save_scene(js.Scene([js.PointLight([0, 0, 2.0], 1.0)]), path)
        scene = js.load_scene(path)
        ```
    """
    d = read_json(path)
    arrays = _read_arrays(path, d)
    try:
        return scene_from_dict(d, arrays=arrays)
    except RecursionError:
        raise ValueError(f"{path}: a value is nested too deeply to be a scene entry.") from None


def load_material(path: str | os.PathLike) -> Material:
    """Read the `material` entry of a scene JSON file.

    Example:
        ```python
        import os, tempfile
        import jaxshadow as js

        path = os.path.join(tempfile.mkdtemp(), "scene.json")
        js.save_scene(js.Scene([js.PointLight([0, 0, 2.0], 1.0)]), path,
                      material=js.Material(ka=0.1, kd=0.6, ks=0.3, exponent=20.0))
        material = js.load_material(path)
        ```
    """
    d = read_json(path)
    if not isinstance(d, dict) or "material" not in d:
        raise ValueError(f"{path}: no 'material' entry.")
    if not isinstance(d["material"], dict):
        raise ValueError(f"{path}: 'material' must be an object, got {type(d['material']).__name__}.")
    return material_from_dict(d["material"])
