r"""The catalogue: named reference scenes with exact values and exact derivatives.

Each `ReferenceScene` holds a jaxshadow scene and material, receivers (a 4 x 4 grid on the
plane z = 0, normals +z), an eye, and the exact

- irradiance $E$ (W/m^2, RGB) and radiance $L = k_a L_a + \frac{k_d}{\pi}E + k_s S$
  (W m^-2 sr^-1; `js.shade` with the exact specular method) at the receivers, and
- their derivatives with respect to the parameters of `PARAMETERS` (light translation,
  rotation and scale about its centre, occluder translation, material), computed in forward
  mode by `jax.jvp` through `js.irradiance` / `js.shade` in float64, one tangent per parameter.

The values and derivatives are stored in `jaxshadow/data/testing_catalogue.json`, so a test in
another project reads them without compiling anything; `ReferenceScene.compute()` recomputes
them (about half a minute per scene), and `python -m jaxshadow.testing._catalogue` rewrites the
file. The tests check the stored numbers against the library's values and against float64
central differences.

For renderers that image the receivers, `ReferenceScene.image(...)` computes (live) the exact
pixel means of $E$ over an R x R image of the scene's window and their derivatives, and
`mitsuba_dict(camera=True)` gives the Mitsuba twin with that camera.
"""

from __future__ import annotations

import functools
import json
import math
import os
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .._core.files import atomic_write
from .._scene.format import material_from_dict, scene_from_dict, scene_to_dict
from .._scene.model import LinearLight, Material, Scene
from .._shading.shade import irradiance, shade
from ._scenes import (
    BUILDERS,
    GRID,
    LIGHT_TRANSLATION,
    MATERIAL_PARAMETERS,
    PARAMETERS,
    Spec,
    Window,
    apply_parameters,
    parameters_of,
)

FORMAT = "jaxshadow.testing.catalogue"
VERSION = 1
DATA = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "data", "testing_catalogue.json")


def _f64(x: Any) -> np.ndarray:
    return np.asarray(x, dtype=np.float64)


@dataclass(frozen=True)
class ImageReference:
    r"""Exact pixel means of the irradiance over an R x R image of a scene's window.

    **Fields:** `irradiance` `(R, R, 3)` (W/m^2; row 0 is the +y edge, column 0 the -x edge),
    `d_irradiance` `{parameter: (R, R, 3)}`, `quadrature_error` and `d_quadrature_error`
    (same shapes): |q-point minus q/2-point Gauss-Legendre rule| per pixel, a conservative
    bound on the quadrature error of the q-point values (pass it as `atol`), `quadrature`
    (q, nodes per pixel axis), `pixel_centres` `(R * R, 3)`.
    """

    irradiance: np.ndarray
    d_irradiance: dict[str, np.ndarray]
    quadrature_error: np.ndarray
    d_quadrature_error: dict[str, np.ndarray]
    quadrature: int
    pixel_centres: np.ndarray


class ReferenceScene:
    """One catalogue scene and its exact references (see the module docstring).

    **Attributes:** `name`, `description`, `scene` (`js.Scene`, float64), `material`
    (`js.Material`), `points` `(N, 3)`, `normals` `(N, 3)`, `eye` `(3,)`, `window` (the
    receiver square: `centre`, `half`, `camera_height`), `classes` (`(N,)` "lit" / "penumbra"
    / "umbra"), `parameters` (names, see `PARAMETERS`), `irradiance`, `radiance` `(N, 3)`,
    `d_irradiance` `{parameter: (N, 3)}` (geometric parameters; the irradiance does not depend
    on the material), `d_radiance` `{parameter: (N, 3)}` (all parameters).
    """

    def __init__(self, record: dict):
        self._record = record
        self.name: str = record["name"]
        self.description: str = record["description"]
        self.points = _f64(record["points"])
        self.normals = _f64(record["normals"])
        self.eye = _f64(record["eye"])
        w = record["window"]
        self.window = Window(tuple(w["centre"]), float(w["half"]), float(w["camera_height"]))
        self.classes = np.asarray(record["classes"], dtype=str)
        self.parameters: tuple[str, ...] = tuple(record["parameters"])
        self.irradiance = _f64(record["irradiance"])
        self.radiance = _f64(record["radiance"])
        self.d_irradiance = {k: _f64(v) for k, v in record["d_irradiance"].items()}
        self.d_radiance = {k: _f64(v) for k, v in record["d_radiance"].items()}
        for a in (self.irradiance, self.radiance, *self.d_irradiance.values(), *self.d_radiance.values()):
            a.setflags(write=False)

    def __repr__(self) -> str:
        return f"ReferenceScene({self.name!r}: {self.points.shape[0]} points, {len(self.parameters)} parameters)"

    @functools.cached_property
    def _built(self) -> tuple[Scene, Material]:
        with jax.enable_x64(True):
            return scene_from_dict(self._record["scene"]), material_from_dict(self._record["scene"]["material"])

    @property
    def scene(self) -> Scene:
        """The jaxshadow `Scene` (float64 leaves)."""
        return self._built[0]

    @property
    def material(self) -> Material:
        """The receivers' `Material`."""
        return self._built[1]

    @property
    def geometric_parameters(self) -> tuple[str, ...]:
        return tuple(p for p in self.parameters if p not in MATERIAL_PARAMETERS)

    def gradient(self, quantity: str = "irradiance", parameters: Sequence[str] | None = None) -> np.ndarray:
        """Stacked derivatives `(P, N, 3)` of `"irradiance"` or `"radiance"`."""
        table = {"irradiance": self.d_irradiance, "radiance": self.d_radiance}[quantity]
        names = list(table) if parameters is None else list(parameters)
        return np.stack([table[n] for n in names])

    def perturbed(self, parameter: str, t: float) -> tuple[Scene, Material]:
        """The scene and material with one parameter moved by `t` (units of `PARAMETERS`)."""
        if parameter not in self.parameters:
            raise ValueError(f"{self.name}: no parameter {parameter!r}; it has {list(self.parameters)}.")
        with jax.enable_x64(True):
            return apply_parameters(self.scene, self.material, (parameter,), jnp.asarray([float(t)]))

    def arrays(self) -> dict[str, np.ndarray]:
        """Everything as plain float64 NumPy arrays (no jaxshadow types): light geometry and
        emission, occluder polygons, receivers, eye, material, values and derivatives."""
        light = self.scene.lights[0]
        out: dict[str, np.ndarray] = {}
        if isinstance(light, LinearLight):
            out.update(light_start=_f64(light.start), light_end=_f64(light.end), light_power=_f64(light.power))
        else:
            out.update(light_vertices=_f64(light.vertices), light_radiance=_f64(light.radiance))
        if self.scene.occluders is not None:
            out["occluders"] = _f64(self.scene.occluders)  # (m, K, 3), padded by repeating vertex 0
        out.update(
            ambient=_f64(self.scene.ambient), points=self.points, normals=self.normals, eye=self.eye,
            ka=_f64(self.material.ka), kd=_f64(self.material.kd), ks=_f64(self.material.ks),
            exponent=_f64(self.material.exponent), irradiance=self.irradiance, radiance=self.radiance,
        )
        out.update({f"d_irradiance/{k}": v for k, v in self.d_irradiance.items()})
        out.update({f"d_radiance/{k}": v for k, v in self.d_radiance.items()})
        return out

    def compute(self) -> dict[str, Any]:
        """Recompute values and derivatives live (float64 `jax.jvp`); same keys as the record."""
        return compute_references(self.scene, self.material, self.points, self.normals, self.eye, self.parameters)

    def image(self, resolution: int = 8, quadrature: int = 8, parameters: Sequence[str] = LIGHT_TRANSLATION) -> ImageReference:
        """Exact pixel means of $E$ over a `resolution`^2 image of the window and their derivatives
        (`quadrature` x `quadrature` Gauss-Legendre nodes per pixel, computed live)."""
        return _image_reference(self, int(resolution), int(quadrature), tuple(parameters))

    def mitsuba_dict(self, *, camera: bool = False, resolution: int = 8, reflectance: float = 1.0, **convert: Any) -> dict:
        """The `mi.load_dict` dictionary of the scene (`jaxshadow.mitsuba.to_mitsuba_dict`).

        With `camera=True` it adds the receiver square (a `rectangle` with a `diffuse` BSDF of
        albedo `reflectance`) and a perspective camera straight above the window's centre
        whose `resolution`^2 pixels are the squares of `image(resolution)` (`box` filter): the
        rendered pixel is `reflectance / pi` times the pixel mean of $E$. The light is
        `light_000` (`light_000.vertex_positions`, or `light_000.to_world` for the cylinder that
        stands in for a linear light).
        """
        import mitsuba as mi

        from ..mitsuba import to_mitsuba_dict

        d = to_mitsuba_dict(self.scene, **convert)
        if camera:
            (cx, cy), h, hc = self.window.centre, self.window.half, self.window.camera_height
            r = int(resolution)
            d["receiver"] = {
                "type": "rectangle",
                "to_world": mi.ScalarTransform4f().translate([cx, cy, 0.0]).scale([1.02 * h, 1.02 * h, 1.0]),
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [float(reflectance)] * 3}},
            }
            d["sensor"] = {
                "type": "perspective",
                "near_clip": 0.01 * hc,
                "far_clip": 10.0 * hc,
                "fov": 2.0 * math.degrees(math.atan(h / hc)),
                "fov_axis": "x",
                "to_world": mi.ScalarTransform4f().look_at(origin=[cx, cy, hc], target=[cx, cy, 0.0], up=[0.0, 1.0, 0.0]),
                "film": {
                    "type": "hdrfilm", "width": r, "height": r, "rfilter": {"type": "box"},
                    "pixel_format": "rgb", "sample_border": False,
                },
            }
        return d

    @property
    def mitsuba_light_key(self) -> str:
        """The `mi.traverse` key that moves the light in `mitsuba_dict()`."""
        return "light_000.to_world" if isinstance(self.scene.lights[0], LinearLight) else "light_000.vertex_positions"


def classify(scene: Scene, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """"lit" / "penumbra" / "umbra" per receiver (light 0, against the unoccluded irradiance)."""
    e = _f64(irradiance(scene, points, normals))[:, 0]
    free = _f64(irradiance(Scene(scene.lights), points, normals))[:, 0]
    lit = np.isclose(e, free, rtol=1e-12, atol=0.0)
    umbra = e <= 1e-14 * np.max(free)
    return np.where(lit, "lit", np.where(umbra, "umbra", "penumbra"))


def compute_references(
    scene: Scene, material: Material, points: Any, normals: Any, eye: Any, parameters: Sequence[str]
) -> dict[str, Any]:
    """Values and forward-mode derivatives (float64) of `js.irradiance` and `js.shade`
    (exact specular) at the receivers: `{"irradiance", "radiance": (N, 3), "d_irradiance",
    "d_radiance": {parameter: (N, 3)}}` (`d_irradiance` for the geometric parameters only)."""
    names = tuple(parameters)
    with jax.enable_x64(True):
        p = jnp.asarray(points, jnp.float64)
        n = jnp.asarray(normals, jnp.float64)
        e = jnp.asarray(eye, jnp.float64)

        def f(theta):
            sc, mt = apply_parameters(scene, material, names, theta)
            return irradiance(sc, p, n), shade(sc, mt, p, n, e, method="exact")

        theta0 = jnp.zeros(len(names), jnp.float64)
        jvp = jax.jit(jax.vmap(lambda v: jax.jvp(f, (theta0,), (v,)), in_axes=0))
        (vals_e, vals_l), (de, dl) = jvp(jnp.eye(len(names), dtype=jnp.float64))
    de, dl = _f64(de), _f64(dl)
    return {
        "irradiance": _f64(vals_e[0]),
        "radiance": _f64(vals_l[0]),
        "d_irradiance": {k: de[i] for i, k in enumerate(names) if k not in MATERIAL_PARAMETERS},
        "d_radiance": {k: dl[i] for i, k in enumerate(names)},
    }


def _gauss_nodes(window: Window, r: int, q: int) -> tuple[np.ndarray, np.ndarray]:
    """Nodes `(q*q*r*r, 3)` (node-major) and weights `(q*q,)` of the pixel means."""
    x, w = np.polynomial.legendre.leggauss(q)
    x, w = 0.5 * (x + 1.0), 0.5 * w
    (cx, cy), h = window.centre, window.half
    jj, ii = np.meshgrid(np.arange(r), np.arange(r))
    pts, ws = [], []
    for ya, wa in zip(x, w, strict=True):
        for xb, wb in zip(x, w, strict=True):
            px = cx - h + 2.0 * h * (jj.ravel() + xb) / r
            py = cy + h - 2.0 * h * (ii.ravel() + ya) / r
            pts.append(np.stack([px, py, np.zeros_like(px)], axis=1))
            ws.append(wa * wb)
    return np.concatenate(pts), np.asarray(ws)


@functools.lru_cache(maxsize=32)
def _image_cached(name: str, r: int, q: int, names: tuple[str, ...]) -> ImageReference:
    return _image_reference_uncached(catalogue[name], r, q, names)


def _image_reference(ref: ReferenceScene, r: int, q: int, names: tuple[str, ...]) -> ImageReference:
    if catalogue.get(ref.name) is ref:
        return _image_cached(ref.name, r, q, names)
    return _image_reference_uncached(ref, r, q, names)


def _image_reference_uncached(ref: ReferenceScene, r: int, q: int, names: tuple[str, ...]) -> ImageReference:
    if r < 1 or q < 2:
        raise ValueError(f"image: resolution must be >= 1 and quadrature >= 2, got {r}, {q}.")
    bad = [n for n in names if n not in ref.geometric_parameters]
    if bad:
        raise ValueError(f"image: {ref.name} has no geometric parameter(s) {bad}.")
    out = []
    scene, material = ref.scene, ref.material  # built before tracing: the scene's leaves are constants
    with jax.enable_x64(True):
        for qq in (q, max(q // 2, 1)):
            nodes, weights = _gauss_nodes(ref.window, r, qq)
            p = jnp.asarray(nodes)
            nrm = jnp.zeros_like(p).at[:, 2].set(1.0)
            wj = jnp.asarray(weights)

            def mean_e(theta, p=p, nrm=nrm, wj=wj, qq=qq):
                sc, _ = apply_parameters(scene, material, names, theta)
                e = irradiance(sc, p, nrm).reshape(qq * qq, r * r, 3)
                return jnp.einsum("k,kpc->pc", wj, e).reshape(r, r, 3)

            theta0 = jnp.zeros(len(names), jnp.float64)
            jvp = jax.jit(jax.vmap(lambda v, f=mean_e, t0=theta0: jax.jvp(f, (t0,), (v,)), in_axes=0))
            vals, ders = jvp(jnp.eye(len(names), dtype=jnp.float64))
            out.append((_f64(vals[0]), _f64(ders)))
    (v, dv), (v2, dv2) = out
    return ImageReference(
        irradiance=v,
        d_irradiance={k: dv[i] for i, k in enumerate(names)},
        quadrature_error=np.abs(v - v2),
        d_quadrature_error={k: np.abs(dv[i] - dv2[i]) for i, k in enumerate(names)},
        quadrature=q,
        pixel_centres=ref.window.grid(r),
    )


def build_record(spec: Spec) -> dict:
    """The stored record of one scene: geometry, receivers, classes, values, derivatives."""
    points = spec.window.grid(GRID)
    normals = np.tile([0.0, 0.0, 1.0], (points.shape[0], 1))
    names = parameters_of(spec.scene)
    refs = compute_references(spec.scene, spec.material, points, normals, spec.eye, names)
    tolist = lambda a: _f64(a).tolist()  # noqa: E731
    return {
        "name": spec.name,
        "description": spec.description,
        "scene": scene_to_dict(spec.scene, spec.material),
        "eye": tolist(spec.eye),
        "window": {"centre": list(spec.window.centre), "half": spec.window.half, "camera_height": spec.window.camera_height},
        "points": tolist(points),
        "normals": tolist(normals),
        "classes": classify(spec.scene, points, normals).tolist(),
        "parameters": list(names),
        "irradiance": tolist(refs["irradiance"]),
        "radiance": tolist(refs["radiance"]),
        "d_irradiance": {k: tolist(v) for k, v in refs["d_irradiance"].items()},
        "d_radiance": {k: tolist(v) for k, v in refs["d_radiance"].items()},
    }


def build_spec(name: str) -> Spec:
    """The scene definition behind a catalogue entry, built in float64."""
    with jax.enable_x64(True):
        return BUILDERS[name]()


class Catalogue(Mapping):
    """The reference scenes by name (a read-only mapping, loaded on first use).

    `catalogue["penumbra"]`, `catalogue("penumbra")`, `list(catalogue)`; `catalogue()`
    returns a plain dict of all scenes.
    """

    def __init__(self, path: str = DATA):
        self._path = path
        self._scenes: dict[str, ReferenceScene] | None = None

    def _load(self) -> dict[str, ReferenceScene]:
        if self._scenes is None:
            with open(self._path) as fh:
                data = json.load(fh)
            if data.get("format") != FORMAT or data.get("version") != VERSION:
                raise ValueError(f"{self._path}: not a {FORMAT} file of version {VERSION}.")
            self._scenes = {name: ReferenceScene(rec) for name, rec in data["scenes"].items()}
        return self._scenes

    def __getitem__(self, name: str) -> ReferenceScene:
        scenes = self._load()
        if name not in scenes:
            raise KeyError(f"no catalogue scene {name!r}; the catalogue has {list(scenes)}.")
        return scenes[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._load())

    def __len__(self) -> int:
        return len(self._load())

    def __call__(self, name: str | None = None) -> Any:
        return dict(self._load()) if name is None else self[name]

    def __repr__(self) -> str:
        return f"Catalogue({list(self)})"


catalogue = Catalogue()


def write_catalogue(path: str = DATA, names: Sequence[str] | None = None) -> dict:
    """Recompute every scene (`build_record`) and write the catalogue file atomically."""
    names = list(BUILDERS) if names is None else list(names)
    scenes = {}
    for name in names:
        print(f"computing {name} ...", file=sys.stderr, flush=True)
        scenes[name] = build_record(build_spec(name))
    data = {"format": FORMAT, "version": VERSION, "parameters": PARAMETERS, "scenes": scenes}
    with atomic_write(path) as fh:
        json.dump(data, fh, separators=(",", ":"))
        fh.write("\n")
    return data


if __name__ == "__main__":  # python -m jaxshadow.testing._catalogue [path]
    write_catalogue(sys.argv[1] if len(sys.argv) > 1 else DATA)
