"""Receivers on a scene's own surfaces against Mitsuba at 2^20 samples per point: the Cornell box's face centres, vertices, random points and edges, and a scan-like mesh's own vertices.

Two scenes, each read by `from_mitsuba` from a Mitsuba scene, every shape an occluder and a
receiver surface (`ReceiverMesh`):

- **Cornell box**: Mitsuba's own `mi.cornell_box()` (floor, ceiling, back and side walls, two
  boxes, the ceiling light). Receivers on every surface: the face centres, the vertices (with
  the surface's vertex normals), random points on the faces (by area), and a random point on
  every edge of every face (with that face's normal): the floor's and walls' outer edges are
  where two surfaces meet, the boxes' lower edges stand on the floor.
- **Scan-like meshes**: `benchmarks.real_meshes.scan_like` (an open, noisy, non-convex shape)
  written as PLY and loaded by Mitsuba as a `ply` shape on a floor under a rectangle light:
  1 m across with 4 756 triangles (subdivision 4, median edge 34 mm), and 0.15 m across with
  19 021 triangles (subdivision 5, median edge 2.5 mm: a scan's size, at a resolution a few
  times coarser than the Stanford bunny's); receivers: a random subset of its own vertices, with
  its (area-weighted) vertex normals.

Per receiver and channel: `js.irradiance` (the C++ engine, float64 receivers) against
`jaxshadow.mitsuba.reference_irradiance(..., mitsuba_scene=...)`, Mitsuba's own emitter
sampling and `test_visibility=True` shadow rays in the Mitsuba scene itself (`llvm_ad_rgb`),
at `SPP` samples per point: z = (ours - Mitsuba) / (Mitsuba's standard error); a value where
Mitsuba's standard error is 0 (every sample equal: fully shadowed) counts as |z| = 0 when
ours is within 1e-12 of it, else infinite. Reported: max |z|, the number of values beyond 4
(with the count expected from Gaussian noise alone, 6.3e-5 per value), negative values of
ours, and the independent polygon-boolean reference (`tests/test_planes.py`: shapely booleans
of the occluders minus the faces the receiver lies on, Lambert's sum; first channel) as the
largest relative error max |ours - ref| / max(|ref|, 1e-3 max unoccluded).

The receivers beyond 4 sigma are examined (`compare`): whether they touch another surface
(`Contacts`); ours with the visibility from where Mitsuba's shadow rays start (Mitsuba moves a
ray's origin along the receiver's normal by (1 + max |p_i|) RayEpsilon, RayEpsilon = 8.9e-5:
about 0.1 mm, a few percent of the small scan's edges); and both again with the receivers lifted
off the surfaces they touch by 10 times that offset.

`--quick`: 2^14 samples per point and fewer receivers (a smoke run).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

NAME = "surfaces_mitsuba"
SPP = 1 << 20
QUICK_SPP = 1 << 14
Z_LIMIT = 4.0
P_BEYOND = 6.334e-5  # P(|N(0, 1)| > 4)


def _tests_path() -> None:
    root = str(Path(__file__).resolve().parent.parent / "tests")
    if root not in sys.path:
        sys.path.insert(0, root)


def edge_points(mesh: Any, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A random point (10 % to 90 % along) on every distinct edge of `mesh`'s faces, with the
    normal of the first face that has the edge."""
    f = np.asarray(mesh.faces)
    e = np.stack([f, np.roll(f, -1, axis=1)], axis=2).reshape(-1, 2)
    face = np.repeat(np.arange(len(f)), f.shape[1])
    _, first = np.unique(np.sort(e, axis=1), axis=0, return_index=True)
    e, face = e[first], face[first]
    t = rng.uniform(0.1, 0.9, len(e))[:, None]
    v = mesh.vertices
    return v[e[:, 0]] + t * (v[e[:, 1]] - v[e[:, 0]]), mesh.face_normals[face].copy()


def cornell_receivers(receivers: list, n_random: int, seed: int = 0) -> dict[str, tuple]:
    """Receivers on every surface of the Cornell box, by kind: `{kind: (points, normals, surface names)}`."""
    rng = np.random.default_rng(seed)
    out: dict[str, list] = {"face centres": [], "vertices": [], "random points": [], "edges": []}
    for r in receivers:
        got = {"face centres": r.receivers("faces"), "vertices": r.receivers("vertices"),
               "random points": r.sample(n_random, seed=int(rng.integers(1 << 31))), "edges": edge_points(r, rng)}
        for kind, (p, n) in got.items():
            out[kind].append((p, n, [r.name] * len(p)))
    return {k: (np.concatenate([a[0] for a in v]), np.concatenate([a[1] for a in v]),
                sum((a[2] for a in v), [])) for k, v in out.items()}


def boolean_reference(scene: Any, points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """pi L F (first channel) from exact polygon booleans, excluding the faces each receiver
    lies on (`tests/test_planes.py`'s rule), over the faces that can block (`tests/test_plan.py`)."""
    _tests_path()
    from test_clip import reference_ff
    from test_plan import culled
    from test_planes import _central, _on_face

    occ = np.asarray(scene.occluders, np.float64)
    out = np.zeros(len(points))
    for light in scene.lights:
        lv = np.asarray(light.vertices, np.float64)
        rad = float(np.asarray(light.radiance)[0])
        for i, (p, n) in enumerate(zip(points, normals, strict=True)):
            em = _central(p, lv)
            keep = [o for o in culled(p, n, em, occ) if not _on_face(p, o)]
            out[i] += np.pi * rad * reference_ff(p, n, em, keep)
    return out


class Contacts:
    """Which occluder faces of `scene` a receiver touches besides its own surface's: faces that
    hold the point (within 2^-18 of the scene's size of their plane, inside their polygon to 1e-9
    of it) and are not faces of the receiver's own surface (a box standing on the floor, a wall
    meeting the floor; on a closed or open scan, nothing)."""

    def __init__(self, scene: Any, surfaces: dict[str, Any]):
        from jaxshadow._core.geometry import strip_padding

        self.faces = np.asarray(scene.occluders, np.float64)  # (M, K, 3), padded with a repeated vertex
        self.edges = np.roll(self.faces, -1, axis=1) - self.faces
        no = np.cross(self.faces, np.roll(self.faces, -1, axis=1)).sum(axis=1)
        self.normals = no / np.linalg.norm(no, axis=1, keepdims=True)

        def key(poly: Any) -> frozenset:
            return frozenset(map(tuple, np.asarray(strip_padding(np.asarray(poly, np.float64))).tolist()))

        keys = [key(f) for f in self.faces]
        self.own = {}
        for name, mesh in surfaces.items():
            mine = {key(q) for q in mesh.occluder().polygons}
            self.own[name] = np.array([k in mine for k in keys])

    def normals_at(self, point: np.ndarray, surface: str) -> np.ndarray:
        """`(k, 3)` unit normals of the other surfaces' faces that hold `point`."""
        f = self.faces
        s = np.maximum(np.abs(f).max(axis=(1, 2)), np.abs(point).max())
        dist = np.abs(np.einsum("mj,mj->m", point - f[:, 0], self.normals))
        side = np.einsum("mkj,mj->mk", np.cross(self.edges, point - f), self.normals)
        inside = (side >= -1e-9 * s[:, None] * np.linalg.norm(self.edges, axis=2)).all(axis=1)
        return self.normals[(dist <= 2.0**-18 * s) & inside & ~self.own[surface]]


def mitsuba_offset(point: np.ndarray) -> float:
    """How far Mitsuba moves a shadow ray's origin off its point along the normal
    (`Interaction3f.offset_p`: (1 + max |p_i|) RayEpsilon)."""
    from jaxshadow._io.mitsuba_io import import_mitsuba

    return float((1.0 + np.abs(point).max()) * import_mitsuba().math.RayEpsilon)


def lifted(scene: Any, contacts: Contacts, points: np.ndarray, normals: np.ndarray, surfaces: list[str],
           factor: float = 10.0) -> np.ndarray:
    """`points` moved off every surface they touch by `factor` times Mitsuba's ray offset, along
    the sum of their normal and the touched faces' normals (each turned to the light's side)."""
    c = np.mean([np.asarray(light.vertices, np.float64).mean(axis=0) for light in scene.lights], axis=0)
    out = points.copy()
    for i, (p, n) in enumerate(zip(points, normals, strict=True)):
        d = n.copy()
        for m in contacts.normals_at(p, surfaces[i]):
            d += m if np.dot(m, c - p) >= 0 else -m
        out[i] = p + factor * mitsuba_offset(p) * d / np.linalg.norm(d)
    return out


def compare(scene: Any, mitsuba_scene: Any, points: np.ndarray, normals: np.ndarray, spp: int, seed: int,
            contacts: Contacts, surfaces: list[str], diagnose: bool = True) -> dict:
    """Ours against Mitsuba (z per value) and against the boolean reference, on `points` (on
    the named `surfaces`); with `diagnose`, the receivers beyond 4 sigma again, lifted off the
    surfaces they touch (`lifted`)."""
    import jax

    import jaxshadow as js
    from jaxshadow import mitsuba as jm

    jax.config.update("jax_enable_x64", True)
    t = time.perf_counter()
    ours = np.asarray(js.irradiance(scene, points, normals), np.float64)
    t_ours = time.perf_counter() - t
    free = np.asarray(js.irradiance(js.Scene(scene.lights), points, normals), np.float64)
    t = time.perf_counter()
    mit, err = jm.reference_irradiance(scene, points, normals, spp=spp, seed=seed, mitsuba_scene=mitsuba_scene)
    t_mit = time.perf_counter() - t
    t = time.perf_counter()
    ref = boolean_reference(scene, points, normals)
    t_ref = time.perf_counter() - t
    d = ours - mit
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(err > 0, d / err, np.where(np.abs(d) <= 1e-12, 0.0, np.inf))
    rel = np.abs(ours[:, 0] - ref) / np.maximum(np.abs(ref), 1e-3 * free[:, 0].max())
    beyond = np.abs(z) > Z_LIMIT
    touch = np.array([len(contacts.normals_at(p, s)) > 0 for p, s in zip(points, surfaces, strict=True)])
    diag: dict[str, Any] = {}
    bad = np.flatnonzero(beyond.any(axis=1))
    if diagnose and len(bad):
        q = lifted(scene, contacts, points[bad], normals[bad], [surfaces[i] for i in bad])
        again = compare(scene, mitsuba_scene, q, normals[bad], spp, seed + 1, contacts, [surfaces[i] for i in bad],
                        diagnose=False)
        moved = np.abs(again["_ours"] - ours[bad]).max() / np.abs(ours[bad]).max()
        # Mitsuba's estimate: the light sampled from the point, the shadow ray traced from the point
        # moved along its normal by Mitsuba's offset (of its float32 position). Ours alike, to first
        # order: ours at that origin times the unoccluded value at the point over that at the origin.
        origin = points[bad] + normals[bad] * np.array([[mitsuba_offset(q.astype(np.float32))] for q in points[bad]])
        free_o = np.asarray(js.irradiance(js.Scene(scene.lights), origin, normals[bad]), np.float64)
        at_origin = np.asarray(js.irradiance(scene, origin, normals[bad]), np.float64) * np.divide(
            free[bad], free_o, out=np.ones_like(free_o), where=free_o > 0)
        d0 = at_origin - mit[bad]
        with np.errstate(divide="ignore", invalid="ignore"):
            dz = np.where(err[bad] > 0, d0 / err[bad], np.where(np.abs(d0) <= 1e-12, 0.0, np.inf))
        diag = {"receivers": int(len(bad)), "touching_another_surface": int(touch[bad].sum()),
                "mitsuba_all_samples_blocked": int((err[bad] == 0).all(axis=1).sum()),
                "lift_m": float(np.max(np.linalg.norm(q - points[bad], axis=1))),
                "lifted_max_abs_z": again["max_abs_z"], "lifted_beyond_4": again["beyond_4"],
                "lifted_values": again["values"], "ours_moved_by_lift_rel": float(moved),
                "at_ray_origin_receivers": int((~touch[bad]).sum()),
                "at_ray_origin_max_abs_z": float(np.abs(dz[~touch[bad]]).max(initial=0.0)),
                "at_ray_origin_beyond_4": int((np.abs(dz[~touch[bad]]) > Z_LIMIT).sum())}
    return {
        "receivers": int(len(points)), "values": int(z.size), "spp": int(spp),
        "max_abs_z": float(np.abs(z).max()), "beyond_4": int(beyond.sum()),
        "contacts": int(touch.sum()), "max_abs_z_off_contacts": float(np.abs(z[~touch]).max(initial=0.0)),
        "beyond_4_off_contacts": int(beyond[~touch].sum()),
        "receivers_beyond_4": int(beyond.any(axis=1).sum()), "expected_beyond_4": float(z.size * P_BEYOND),
        "negative": int((ours < 0).sum()), "min_ours": float(ours.min()),
        "above_unoccluded": int((ours > free * (1 + 1e-12) + 1e-15).sum()),
        "max_rel_err_boolean": float(rel.max()), "lit_fraction": float((ours[:, 0] > 1e-3 * free[:, 0].max()).mean()),
        "mitsuba_zero_se": int((err == 0).sum()), "beyond_4_diagnosis": diag,
        "seconds": {"ours": t_ours, "mitsuba": t_mit, "boolean": t_ref},
        "_z": z, "_ours": ours, "_mit": mit, "_err": err,
    }


def _worst(res: dict, names: list, points: np.ndarray, k: int = 3) -> list[dict]:
    z = np.abs(res.pop("_z")).max(axis=1)
    ours, mit, err = res.pop("_ours"), res.pop("_mit"), res.pop("_err")
    idx = np.argsort(-z)[:k]
    return [{"surface": names[i], "point": points[i].tolist(), "abs_z": float(z[i]), "ours": ours[i].tolist(),
             "mitsuba": mit[i].tolist(), "stderr": err[i].tolist()} for i in idx]


def cornell(spp: int, n_random: int, seed: int) -> dict:
    from jaxshadow._io.mitsuba_io import import_mitsuba
    from jaxshadow.mitsuba import from_mitsuba

    mi = import_mitsuba()
    scene, receivers, _ = from_mitsuba(mi.cornell_box())
    kinds = cornell_receivers(receivers, n_random, seed)
    contacts = Contacts(scene, {r.name: r for r in receivers})
    out = {}
    for i, (kind, (p, n, names)) in enumerate(kinds.items()):
        res = compare(scene, mi.cornell_box(), p, n, spp, seed + 100 * i, contacts, names)
        res["worst"] = _worst(res, names, p)
        out[kind] = res
    return out


def scan_scene(folder: str, subdivisions: int, size: float = 1.0) -> dict:
    """A Mitsuba scene dict: the scan-like mesh (PLY, `size` m across) on a floor under a
    rectangle light (the scene scaled with it)."""
    import trimesh

    from benchmarks.real_meshes import scan_like
    from jaxshadow._io.mitsuba_io import import_mitsuba

    mi = import_mitsuba()
    v, f = scan_like(subdivisions)
    v = v * size
    path = os.path.join(folder, "scan.ply")
    m = trimesh.Trimesh(v, f, process=False)
    m.remove_unreferenced_vertices()  # the base's vertices, left by the opening
    m.export(path)
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "light": {"type": "rectangle", "to_world": T().scale(size).translate([0.3, 0.2, 2.5]).rotate([1, 0, 0], 180)
                  .scale(0.4), "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [4.0, 3.0, 2.0]}}},
        "floor": {"type": "rectangle", "to_world": T().scale(3.0 * size)},
        "scan": {"type": "ply", "filename": path, "face_normals": True},
    }


def scan(spp: int, count: int, subdivisions: int, seed: int, size: float = 1.0) -> dict:
    from jaxshadow.mitsuba import from_mitsuba

    with tempfile.TemporaryDirectory() as folder:
        d = scan_scene(folder, subdivisions, size)
        scene, receivers, _ = from_mitsuba(d)
        mesh = next(r for r in receivers if r.name == "scan")
        p, n = mesh.receivers("vertices")
        pick = np.sort(np.random.default_rng(seed).choice(len(p), min(count, len(p)), replace=False))
        res = compare(scene, d, p[pick], n[pick], spp, seed, Contacts(scene, {r.name: r for r in receivers}),
                      ["scan"] * len(pick))
        res["worst"] = _worst(res, ["scan"] * len(pick), p[pick])
        res["triangles"] = int(len(mesh.faces))
        res["mesh_vertices"] = int(len(mesh.vertices))
        res["size_m"] = size
        res["median_edge_m"] = float(np.median(np.linalg.norm(
            mesh.vertices[mesh.faces] - mesh.vertices[np.roll(mesh.faces, 1, axis=1)], axis=2)))
    return res


def run(quick: bool) -> dict:
    spp = QUICK_SPP if quick else SPP
    t = time.perf_counter()
    c = cornell(spp, 4 if quick else 12, seed=1)
    s = scan(spp, 40 if quick else 200, 3 if quick else 4, seed=2)
    # A scan's size (0.15 m, 2.5 mm edges): Mitsuba's ray offset (1e-4 m) is a few percent of an edge.
    small = scan(spp, 40 if quick else 200, 4 if quick else 5, seed=3, size=0.15)
    return {"spp": spp, "cornell": c, "scan": s, "scan_small": small, "seconds": time.perf_counter() - t}


def _row(what: str, r: dict) -> str:
    return (f"| {what} | {r['receivers']} | {r['contacts']} | {r['max_abs_z_off_contacts']:.2f} | "
            f"{r['beyond_4_off_contacts']} of {r['values'] - 3 * r['contacts']} | {r['max_abs_z']:.2f} | "
            f"{r['beyond_4']} of {r['values']} (noise alone: {r['expected_beyond_4']:.2f}) | {r['negative']} | "
            f"{r['max_rel_err_boolean']:.1e} | {r['lit_fraction']:.2f} |")


def _scans(results: dict) -> list[tuple[str, dict]]:
    return [(f"scan-like mesh, {r['size_m']:g} m, {r['triangles']} triangles (median edge "
             f"{r['median_edge_m'] * 1e3:.2g} mm), own vertices", r)
            for r in (results.get("scan"), results.get("scan_small")) if r is not None]


def markdown(results: dict) -> str:
    rows = [f"Mitsuba (`llvm_ad_rgb`, its own scene and shadow rays) at {results['spp']} samples per point; "
            f"ours: `js.irradiance` (C++ engine); z per receiver and channel; contacts: receivers that also lie "
            f"in a face of another surface (a box's foot on the floor, a floor edge on a wall); boolean: exact "
            f"polygon booleans, first channel. Whole run {results['seconds']:.0f} s.", "",
            "| receivers | n | contacts | max \\|z\\| off contacts | beyond 4 sigma off contacts | max \\|z\\| "
            "| beyond 4 sigma, all | negative | max rel. err vs booleans | lit fraction |",
            "|---|---:|---:|---:|---|---:|---|---:|---:|---:|"]
    groups = [*((f"Cornell box, {k}", r) for k, r in results["cornell"].items()), *_scans(results)]
    rows += [_row(what, r) for what, r in groups]
    rows.append("")
    for what, r in groups:
        d = r["beyond_4_diagnosis"]
        if d:
            rows.append(f"- {what}: {d['receivers']} receivers beyond 4 sigma, {d['touching_another_surface']} of them "
                        f"contacts, {d['mitsuba_all_samples_blocked']} with every Mitsuba sample blocked. Ours with the "
                        f"visibility from where Mitsuba's shadow rays start (the point moved along its normal by "
                        f"Mitsuba's offset; `compare`), at the "
                        f"{d.get('at_ray_origin_receivers', 0)} that are not contacts: max |z| "
                        f"{d.get('at_ray_origin_max_abs_z', float('nan')):.2f}, "
                        f"{d.get('at_ray_origin_beyond_4', -1)} values beyond 4 sigma. Both lifted off the surfaces "
                        f"they touch by {d['lift_m']:.1e} m (10x Mitsuba's ray offset): max |z| "
                        f"{d['lifted_max_abs_z']:.2f}, {d['lifted_beyond_4']} of {d['lifted_values']} values beyond "
                        f"4 sigma (ours moves by {d['ours_moved_by_lift_rel']:.1e} relative).")
    rows.append("")
    worst = max((r for _, r in groups), key=lambda r: r["max_abs_z"])["worst"][0]
    rows.append(f"Largest |z|: {worst['abs_z']:.2f} on {worst['surface']} at "
                f"({', '.join(f'{x:.4g}' for x in worst['point'])}): ours {worst['ours'][0]:.6g}, Mitsuba "
                f"{worst['mitsuba'][0]:.6g} +- {worst['stderr'][0]:.2g} (first channel).")
    return "\n".join(rows) + "\n"


def key_numbers(results: dict) -> list[tuple[str, str]]:
    all_ = [*results["cornell"].values(), *(r for _, r in _scans(results))]
    n = sum(r["receivers"] for r in all_)
    c = sum(r["contacts"] for r in all_)
    diag = [r["beyond_4_diagnosis"] for r in all_ if r["beyond_4_diagnosis"]]
    return [("receivers on surfaces vs Mitsuba",
             f"{n} receivers on the Cornell box's and scans' own surfaces, {results['spp']} spp: off the {c} "
             f"contacts max z {max(r['max_abs_z_off_contacts'] for r in all_):.2f}, "
             f"{sum(r['beyond_4_off_contacts'] for r in all_)} values beyond 4 sigma, every one within "
             f"{max([d.get('at_ray_origin_max_abs_z', 0.0) for d in diag] or [0.0]):.1f}"
             f" sigma at Mitsuba's ray origin; {sum(d['touching_another_surface'] for d in diag)} "
             f"contacts where Mitsuba blocks every ray, within "
             f"{max([d['lifted_max_abs_z'] for d in diag], default=0.0):.1f} sigma lifted by 10x its ray offset; "
             f"{sum(r['negative'] for r in all_)} negative; max {max(r['max_rel_err_boolean'] for r in all_):.0e} "
             f"from exact booleans")]
