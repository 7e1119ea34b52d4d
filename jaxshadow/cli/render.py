r"""Images from a Mitsuba scene's camera: Mitsuba finds what each pixel sees, jaxshadow shades it.

`render` casts one ray through the centre of every pixel of the scene's first (perspective)
sensor with Mitsuba (`Sensor.sample_ray`, `Scene.ray_intersect`): per pixel the hit point, the
geometric and shading normals and the shape hit. Pixels on a light show its emitted radiance
(Mitsuba's `Emitter.eval`: one-sided); pixels on a receiver surface get jaxshadow's exact direct
illumination and Phong shading $k_a L_a + k_d E/\pi + k_s S$ (`js.irradiance`, `js.specular`),
with the surface's `Material` (`from_mitsuba`); a `diffuse` BSDF with a texture gets its
reflectance looked up per pixel by Mitsuba (`BSDF.eval_diffuse_reflectance`), a per-receiver
`Material`. Surfaces seen from behind are black unless their BSDF is `twosided` (as Mitsuba's
one-sided BSDFs). The shading point is the hit point moved off its surface by $10^{-6}$ of the
scene's size along the geometric normal (Mitsuba spawns its shadow rays likewise), and the shading
normal is Mitsuba's (interpolated vertex normals where the mesh has them).

Unlike Mitsuba's film, which averages each pixel over its footprint with a reconstruction filter,
a pixel here is the value at its centre: on smooth regions the two agree to $O(h^2)$, at
silhouettes they differ.

`render_mitsuba` renders the same scene with Mitsuba's `direct` integrator (the reference of the
tests and of `--spp-compare`).
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from .._core.files import atomic_write_path
from .._io.meshio import tonemap
from .common import (
    Progress,
    _say,
    check_input,
    check_output,
    check_outputs_are_not_inputs,
    check_requirements,
    int_at_least,
    positive_int,
)

IMAGE_EXTS = (".exr", ".png")
# Camera rays (pixels x supersample^2) one render may cast: every sample holds ~200 bytes of
# hit data at once (positions, normals, directions, colours), so 2^25 samples are ~7 GB.
MAX_SAMPLES = 1 << 25


def check_film_size(w: int, h: int, supersample: int = 1, max_samples: int = MAX_SAMPLES) -> int:
    """The number of camera samples of a `w x h` film at `supersample`; `ValueError` before any
    allocation when it exceeds `max_samples` (or the film is empty)."""
    n = int(w) * int(h) * int(supersample) ** 2
    if w < 1 or h < 1:
        raise ValueError(f"render: the film is {w}x{h} pixels; it needs at least one.")
    if n > max_samples:
        raise ValueError(f"render: a {w}x{h} film with supersample {supersample} is {n:,} camera samples, "
                         f"more than the {max_samples:,} one render holds in memory (about 200 bytes each); "
                         "lower the film's width/height or --supersample.")
    return n


@dataclass
class Rendering:
    """A rendered image.

    **Fields:** `image` `(H, W, 3)` linear radiance (W m^-2 sr^-1, float64); `surface` `(H, W)`
    int: the receiver index (`from_mitsuba` order) per pixel, -1 on a light, -2 where the ray
    escapes, -3 where a supersampled pixel covers more than one of these; `seconds`: wall time of the rendering (ray casting and shading).
    """

    image: np.ndarray
    surface: np.ndarray
    seconds: float


def _load(source: Any) -> tuple[Any, Any]:
    from .._io.mitsuba_io import import_mitsuba
    from .._io.mitsuba_io import load_mitsuba_scene as load_scene

    mi = import_mitsuba()
    return mi, load_scene(mi, source)


def _camera_rays(mi: Any, sensor: Any, k: int) -> tuple[Any, int, int]:
    """Rays through the centres of the k x k sub-pixels of every pixel, ordered (row, column,
    sub-row, sub-column)."""
    import drjit as dr

    w, h = (int(x) for x in sensor.film().size())
    idx = dr.arange(mi.UInt32, w * h * k * k)
    sub = idx % (k * k)
    pix = idx // (k * k)
    x = (mi.Float(pix % w) + (mi.Float(sub % k) + 0.5) / k) / w
    y = (mi.Float(pix // w) + (mi.Float(sub // k) + 0.5) / k) / h
    ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(x, y), mi.Point2f(0.5, 0.5))
    return ray, w, h


def render(source: Any, *, supersample: int = 1, progress: Any = None, chunk: int = 1 << 14,
           float64: bool = True, shade: bool = True, max_samples: int = MAX_SAMPLES) -> Rendering:
    """Render a Mitsuba scene from its camera with jaxshadow's exact shading.

    **Arguments:**

    - `source`: a Mitsuba XML file, a `mi.load_dict` dictionary or an `mi.Scene` with a
      perspective sensor (its film size is the image size).
    - `supersample`: `k`: each pixel is the mean of its `k x k` sub-pixel centres (a box filter,
      as Mitsuba's `box` rfilter); 1 (default): the pixel centre.
    - `progress`: `None` or an object with `update(n)` (receives shaded sample counts).
    - `chunk`: pixels per jaxshadow evaluation.
    - `float64`: shade in float64 (default) or float32.
    - `shade`: `False` skips the shading (only `surface` and the lights' pixels are computed).
    - `max_samples`: the most camera samples (pixels x `supersample`^2) to allocate;
      `ValueError` above (`check_film_size`).

    **Returns:** a `Rendering`.
    """
    import jax.numpy as jnp

    from .._io.mitsuba_io import convert_scene, textured_diffuse
    from .._shading.shade import irradiance, specular

    t0 = time.perf_counter()
    mi, ms = _load(source)
    if not ms.sensors():
        raise ValueError("render: the scene has no sensor (camera).")
    scene, receivers, materials, shapes = convert_scene(mi, ms, textures=True)
    k = int(supersample)
    if k < 1:
        raise ValueError(f"render: supersample must be >= 1, got {supersample!r}.")
    film_w, film_h = (int(x) for x in ms.sensors()[0].film().size())
    check_film_size(film_w, film_h, k, max_samples)
    ray, w, h = _camera_rays(mi, ms.sensors()[0], k)
    si = ms.ray_intersect(ray)
    valid = np.asarray(si.is_valid(), bool)
    image = np.zeros((w * h * k * k, 3))
    surface = np.full(w * h * k * k, -2, dtype=np.int64)
    emitted = np.asarray(si.emitter(ms).eval(si, si.is_valid()), np.float64).T
    on_light = valid & (np.asarray(si.shape.is_emitter(), bool))
    image[on_light] = emitted[on_light]
    surface[on_light] = -1
    p = np.asarray(si.p, np.float64).T
    ng = np.asarray(si.n, np.float64).T
    ns = np.asarray(si.sh_frame.n, np.float64).T
    d = np.asarray(ray.d, np.float64).T
    eye = np.asarray(ms.sensors()[0].world_transform().translation(), np.float64).ravel()
    bbox = ms.bbox()
    size = float(np.max(np.asarray(bbox.max, np.float64) - np.asarray(bbox.min, np.float64)))
    dt = np.float64 if float64 else np.float32
    shaded = 0
    for index, (shape, material) in enumerate(zip(shapes, materials, strict=True)):
        hit = valid & ~on_light & np.asarray(si.shape == mi.ShapePtr(shape), bool)
        surface[hit] = index
        two_sided = shape.bsdf().class_name() == "TwoSidedBRDF"
        facing = np.sum(d * ns, axis=1) < 0
        flip = np.where(facing, 1.0, -1.0)[:, None]
        lit = hit & (facing | two_sided)
        idx = np.flatnonzero(lit)
        if idx.size == 0 or not shade:
            continue
        kd_tex = None
        if textured_diffuse(mi, shape.bsdf()):
            kd_tex = np.asarray(shape.bsdf().eval_diffuse_reflectance(si), np.float64).T
        gn = ng * np.where(np.sum(d * ng, axis=1) < 0, 1.0, -1.0)[:, None]
        pts = (p + 1e-6 * size * gn).astype(dt)
        nrm = (ns * flip).astype(dt)
        with_spec = bool(np.any(np.asarray(material.ks) > 0))
        for s in range(0, idx.size, int(chunk)):
            j = idx[s:s + int(chunk)]
            pp, nn = jnp.asarray(pts[j]), jnp.asarray(nrm[j])
            e = irradiance(scene, pp, nn)
            spec = None
            if with_spec:
                spec = specular(scene, pp, nn, jnp.asarray(eye, dt), jnp.asarray(material.exponent, dt))
            mat = material if kd_tex is None else type(material)(material.ka, kd_tex[j], material.ks, material.exponent)
            image[j] = np.asarray(mat.radiance(scene.ambient, e, spec), np.float64)
            if progress is not None:
                progress.update(len(j))
                shaded += len(j)
    if progress is not None:
        progress.update(w * h * k * k - shaded)  # background and light samples
    image = image.reshape(h, w, k * k, 3).mean(axis=2)
    # A pixel's surface: the one its samples agree on, else -3 (an edge between surfaces).
    per_sample = surface.reshape(h, w, k * k)
    surface = np.where((per_sample == per_sample[..., :1]).all(axis=2), per_sample[..., 0], -3)
    return Rendering(image, surface, time.perf_counter() - t0)


def render_mitsuba(source: Any, spp: int, seed: int = 0) -> tuple[np.ndarray, float]:
    """Mitsuba's own rendering with its `direct` integrator (emitter and BSDF sampling, MIS).

    **Arguments:** `source` as `render`; `spp` samples per pixel; `seed`.

    **Returns:** `(image (H, W, 3) float64, seconds)`; the time excludes loading the scene and
    includes Mitsuba's kernel compilation when the kernel is not cached yet.
    """
    mi, ms = _load(source)
    integrator = mi.load_dict({"type": "direct"})
    t0 = time.perf_counter()
    img = np.asarray(mi.render(ms, spp=int(spp), seed=int(seed), integrator=integrator), np.float64)
    return img[..., :3], time.perf_counter() - t0


def write_image(path: str | os.PathLike, image: Any, exposure: float | None = None) -> None:
    """Write `(H, W, 3)` linear radiance: `.exr` as float32 linear RGB (Mitsuba's `Bitmap`),
    `.png` tone-mapped to 8-bit sRGB (`jaxshadow._io.meshio.tonemap`, `exposure`); atomically."""
    from .._io.mitsuba_io import import_mitsuba

    mi = import_mitsuba()
    path = os.fspath(path)
    ext = os.path.splitext(path)[1].lower()
    img = np.asarray(image, np.float64)
    if ext == ".exr":
        bitmap = mi.Bitmap(np.ascontiguousarray(img, np.float32))
    elif ext == ".png":
        bitmap = mi.Bitmap(np.ascontiguousarray(tonemap(img, exposure)))
    else:
        raise ValueError(f"{path}: unknown image format {ext or '(no extension)'!r} (expected .exr or .png).")
    atomic_write_path(path, lambda tmp: bitmap.write(tmp))


def _exposure(img: np.ndarray) -> float:
    top = float(np.percentile(img.max(axis=-1), 99))
    return 1.0 / top if top > 0 else 1.0


def write_comparison(path: str | os.PathLike, ours: Rendering, theirs: np.ndarray, seconds: float, spp: int,
                     dpi: int = 100) -> None:
    """Side by side: ours | Mitsuba `direct` | |difference| (PNG at `dpi`, atomically)."""
    from matplotlib.figure import Figure

    exp = _exposure(ours.image)
    diff = np.abs(ours.image - theirs).mean(axis=-1)
    fig = Figure(figsize=(12, 4.4))
    axes = fig.subplots(1, 3)
    axes[0].imshow(tonemap(ours.image, exp))
    axes[0].set_title(f"jaxshadow (exact), {ours.seconds:.1f} s")
    axes[1].imshow(tonemap(theirs, exp))
    axes[1].set_title(f"Mitsuba direct, {spp} spp, {seconds:.1f} s")
    im = axes[2].imshow(diff, cmap="magma", vmin=0, vmax=float(np.percentile(diff, 99.5)) or 1.0)
    axes[2].set_title("|difference| (mean of RGB)")
    fig.colorbar(im, ax=axes[2], fraction=0.046, pad=0.04)
    for ax in axes:
        ax.set_xticks([])
        ax.set_yticks([])
    fig.tight_layout()
    atomic_write_path(path, lambda tmp: fig.savefig(tmp, dpi=dpi))


def equal_time_spp(source: Any, seconds: float, probe_spp: int = 4) -> int:
    """Samples per pixel at which Mitsuba's `direct` integrator takes `seconds` (measured: one
    warm-up render, then a timed render at `probe_spp`)."""
    render_mitsuba(source, 1)
    _, t = render_mitsuba(source, probe_spp)
    return max(1, int(round(probe_spp * seconds / max(t, 1e-9))))


# --------------------------------------------------------------------------------------
# jaxshadow render
# --------------------------------------------------------------------------------------


def cmd_render(args: argparse.Namespace) -> int:
    check_input(args.scene, (".xml",), "scene")
    for out in args.output:
        check_output(out, IMAGE_EXTS)
    compare = None
    check_requirements([("matplotlib", "plot", "--spp-compare's picture")] if args.spp_compare is not None else [])
    if args.spp_compare is not None:
        compare = args.compare_output or os.path.splitext(args.output[0])[0] + "_compare.png"
        check_output(compare, (".png",), "--compare-output")
        check_outputs_are_not_inputs([*args.output, compare], [args.scene])
    import jax

    jax.config.update("jax_enable_x64", True)
    say = _say(args)
    _, ms = _load(args.scene)
    if not ms.sensors():
        raise ValueError(f"{args.scene}: the scene has no sensor (camera).")
    w, h = (int(x) for x in ms.sensors()[0].film().size())
    check_film_size(w, h, args.supersample)
    bar = Progress(w * h * args.supersample**2, "render", quiet=args.quiet)
    result = render(ms, supersample=args.supersample, progress=bar, chunk=args.chunk)
    bar.close()
    for out in args.output:
        write_image(out, result.image, args.exposure)
    say(f"{w}x{h} pixels in {result.seconds:.2f} s -> {', '.join(args.output)}")
    if compare is not None:
        spp = args.spp_compare or equal_time_spp(ms, result.seconds)
        theirs, t = render_mitsuba(ms, spp)
        write_comparison(compare, result, theirs, t, spp)
        say(f"Mitsuba direct: {spp} spp in {t:.2f} s (jaxshadow {result.seconds:.2f} s) -> {compare}")
    return 0


def add_render_command(sub: Any) -> None:
    """Add `jaxshadow render` to the `jaxshadow` sub-parsers."""
    p = sub.add_parser("render", help="an image from a Mitsuba scene's camera, shaded exactly",
                       description="Render a Mitsuba XML scene from its camera: Mitsuba ray casting finds "
                                   "the surface in each pixel, jaxshadow computes its exact direct "
                                   "illumination and Phong shading.")
    p.add_argument("scene", help="Mitsuba XML scene with a perspective sensor (its film size is the image size)")
    p.add_argument("-o", "--output", action="append", required=True,
                   help="image written exactly here, .exr (linear float) or .png (tone-mapped sRGB); repeat for both")
    p.add_argument("--spp-compare", type=int_at_least(0, "an integer >= 0"), default=None, metavar="N",
                   help="also render Mitsuba's direct integrator with N samples per pixel (0: as many as take "
                        "it as long as our render, equal wall time) and write ours | Mitsuba | difference")
    p.add_argument("--compare-output", default=None, metavar="PNG",
                   help="where --spp-compare writes its picture (default: <first output>_compare.png)")
    p.add_argument("--supersample", type=positive_int, default=1, metavar="K",
                   help="average K x K sub-pixel centres per pixel (a box filter; default 1: the pixel centre)")
    p.add_argument("--exposure", type=float, default=None,
                   help="PNG tone mapping: radiance scale before the sRGB curve (default: 1 / 99th percentile)")
    p.add_argument("--chunk", type=positive_int, default=1 << 14, help="pixels per evaluation (default: 16384)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=cmd_render, requires=(("mitsuba", "mitsuba", "render (Mitsuba's ray casting)"),
                                              ("drjit", "mitsuba", "render (Mitsuba's ray casting)")))

