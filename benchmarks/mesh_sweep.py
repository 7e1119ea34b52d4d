"""Exactness sweep of the shadow engine on mesh files: every light kind, placements and receivers chosen to break it.

Per mesh file (`real_meshes.load_file`: up axis y, 1 m, centred, 0.3 m above the floor) and
placement:

- `above`: as `benchmarks.real_meshes` (the 0.8 m quad light at z = 2.5);
- `on floor`: the mesh lowered onto the floor (its lowest vertices touch it);
- `close`: the light's plane 0.05 m above the mesh's top;
- `large`: a 3 m quad at z = 2.5;
- `tilted`: the quad turned 45 degrees about the x axis;
- `rotated`: the mesh turned by a random rotation about its centre, 0.3 m above the floor;
- `soup`: the mesh as an `(m, 3, 3)` triangle array, faces shuffled, 1 % of them repeated;
- `soup degenerate`: the shuffled soup with five zero-area (collinear) triangles added, which
  `Scene` refuses (an error at build time is the expected result);
- `float32`: the `above` scene with float32 vertices, light and receivers;

and light kind (`quad`: the placement's quad; `segment`: its middle line; `point`: its centre;
`directional`: from its centre towards the mesh, 10 degrees off the vertical), receivers: a floor
grid (a fifth of it with grazing normals), floor points next to the mesh's lowest vertices
(contact, grazing normals), points on the mesh's own surface (face centres and vertices with their
normals, pushed along them by 0 and by 1e-9 m) and points inside the mesh's bounding box (random
normals).

References: quad lights: the engine's face path (`JAXSHADOW_SILHOUETTE=0`: every candidate face
clipped) on every receiver, and exact polygon booleans in shapely (`_robustness_checks`:
`test_clip.reference_ff` on the faces `test_plan.culled` keeps and the on-surface rule leaves) on
the receivers where the two disagree most plus a few penumbra ones; segment lights: the face path
(`JAXSHADOW_SEGMENT_PIECES=0`) on every receiver and the Gauss-Legendre reference
(`test_clip.reference_linear`) on the worst and a few more; point and directional lights: the device
kernel (no engine) on every receiver and the ray test of the tests (`test_clip.ray_blocked_np`) on
the worst. Errors are `|E - ref| / max(U, 1e-3 max U)` (U the unoccluded value); hard shadows
count lit/shadowed disagreements apart (a receiver on a shadow boundary is decided by rounding).
float32 values are compared with the float64 engine on the same rounded inputs, against the
property suite's bound 1e-5 U + 8 eps32 0.1 pi (reported as its share times 1e-5: passes at <= 1e-5).

    python -m benchmarks.mesh_sweep --mesh /work/meshes/stanford-bunny.obj [--mesh ...] [--record]
    python -m benchmarks.mesh_sweep --dir /work/meshes [--receivers 400] [--ref 8] [--record]

Prints one row per case; with `--record` writes `benchmarks/results/mesh_sweep.{json,md}`.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks import _robustness_checks as chk
from benchmarks.real_meshes import LIGHT, load_file

NAME = "mesh_sweep"
PLACEMENTS = ("above", "on floor", "close", "large", "tilted", "rotated", "soup", "soup degenerate", "float32")
# The default run: every placement under the quad light, the others under these (`--full`: all).
OTHER_KINDS_PLACEMENTS = ("above", "on floor", "close", "rotated", "float32")
KINDS = ("quad", "segment", "point", "directional")
TOL = {"float64": 1e-9, "float32": 1e-5}


def _quad(centre: np.ndarray, size: float, tilt_deg: float = 0.0) -> np.ndarray:
    """A square light of side `size` centred at `centre`, emitting downwards (the vertex order of
    `LIGHT`), turned by `tilt_deg` about the x axis."""
    q = LIGHT / 0.8 * size
    q = q - q.mean(axis=0)
    t = np.radians(tilt_deg)
    rot = np.array([[1, 0, 0], [0, np.cos(t), -np.sin(t)], [0, np.sin(t), np.cos(t)]])
    return q @ rot.T + centre


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def placements(v: np.ndarray, f: np.ndarray, which: tuple[str, ...], seed: int = 0) -> dict[str, dict]:
    """The scenes of one mesh: per placement its vertices (float64), faces (or None for a soup,
    then `tris`), quad light and dtype."""
    rng = np.random.default_rng(seed)
    top = float(v[:, 2].max())
    out: dict[str, dict] = {}
    above = {"v": v, "f": f, "quad": LIGHT.copy(), "dtype": np.float64}
    for name in which:
        if name == "above":
            out[name] = above
        elif name == "on floor":
            w = v.copy()
            w[:, 2] -= w[:, 2].min()
            out[name] = dict(above, v=w)
        elif name == "close":
            out[name] = dict(above, quad=_quad(np.array([0.0, 0.0, top + 0.05]), 0.8))
        elif name == "large":
            out[name] = dict(above, quad=_quad(np.array([0.0, 0.0, 2.5]), 3.0))
        elif name == "tilted":
            out[name] = dict(above, quad=_quad(np.array([0.0, 0.0, 2.5]), 0.8, 45.0))
        elif name == "rotated":
            c = (v.max(axis=0) + v.min(axis=0)) / 2
            w = (v - c) @ _random_rotation(rng).T
            w[:, :2] -= (w[:, :2].max(axis=0) + w[:, :2].min(axis=0)) / 2
            w[:, 2] += 0.3 - w[:, 2].min()
            out[name] = dict(above, v=w)
        elif name == "soup":
            t = v[f][rng.permutation(len(f))]
            t = np.concatenate([t, t[rng.choice(len(t), max(1, len(t) // 100), replace=False)]])
            out[name] = dict(above, f=None, tris=t[rng.permutation(len(t))])
        elif name == "soup degenerate":
            # Zero-area triangles (three distinct collinear points on the mesh's own edges) in a
            # shuffled soup: `Scene` refuses them (docs/design.md: degenerate input is an error at
            # build time), so the expected result is that refusal.
            t = v[f][rng.permutation(len(f))]
            a, b = t[:5, 0], t[:5, 1]
            t = np.concatenate([t, np.stack([a, b, (a + b) / 2], axis=1)])
            out[name] = dict(above, f=None, tris=t[rng.permutation(len(t))], expect="error")
        elif name == "float32":
            out[name] = dict(above, v=v.astype(np.float32).astype(np.float64), dtype=np.float32)
        else:
            raise ValueError(f"unknown placement {name!r}")
    return out


def light_of(kind: str, quad: np.ndarray, centre: np.ndarray) -> Any:
    """The light of `kind` made from the placement's quad."""
    import jaxshadow as js

    c = quad.mean(axis=0)
    if kind == "quad":
        return js.PolygonLight(quad, 1.0)
    if kind == "segment":
        return js.LinearLight((quad[0] + quad[1]) / 2, (quad[2] + quad[3]) / 2, 1.0)
    if kind == "point":
        return js.PointLight(c, 1.0)
    d = centre - c
    d = d / np.linalg.norm(d)
    side = np.cross(d, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    t = np.radians(10.0)
    return js.DirectionalLight(np.cos(t) * d + np.sin(t) * side, 1.0)


def receivers(tris: np.ndarray, n: int, seed: int = 0) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Receiver groups for a mesh given as `tris (m, 3, 3)` (float64), about `n` in all: `floor`
    (a grid on [-1.5, 1.5]^2, a fifth of it with grazing normals 60-88 degrees from the vertical),
    `contact` (floor points within 2 cm of the mesh's lowest vertices, grazing normals), `surface 0`
    and `surface 1e-9` (face centres and vertices with their face / area-weighted vertex normals,
    pushed along them by 0 and 1e-9 m), `inside box` (uniform in the mesh's bounding box, random
    normals)."""
    rng = np.random.default_rng(seed)
    out = {}

    def grazing(k: int) -> np.ndarray:
        t, a = np.radians(rng.uniform(60, 88, k)), rng.uniform(0, 2 * np.pi, k)
        return np.stack([np.sin(t) * np.cos(a), np.sin(t) * np.sin(a), np.cos(t)], axis=1)

    k_floor = max(16, int(0.35 * n))
    side = int(np.ceil(np.sqrt(k_floor)))
    g = np.linspace(-1.5, 1.5, side)
    xy = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)[:k_floor] + rng.uniform(-1e-3, 1e-3, (k_floor, 2))
    nf = np.tile([0.0, 0.0, 1.0], (k_floor, 1))
    nf[::5] = grazing(len(nf[::5]))
    out["floor"] = (np.c_[xy, np.zeros(k_floor)], nf)

    k_contact = max(8, n // 10)
    pts = tris.reshape(-1, 3)
    low = pts[pts[:, 2] <= pts[:, 2].min() + 0.01]
    base = low[rng.integers(len(low), size=k_contact)]
    off = rng.normal(size=(k_contact, 2))
    off *= rng.uniform(1e-4, 0.02, (k_contact, 1)) / np.linalg.norm(off, axis=1, keepdims=True)
    out["contact"] = (np.c_[base[:, :2] + off, np.zeros(k_contact)], grazing(k_contact))

    fn = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    area = np.linalg.norm(fn, axis=1)
    good = np.where(area > 0)[0]
    k_face = max(8, n // 10)
    for push, label in ((0.0, "surface 0"), (1e-9, "surface 1e-9")):
        fi = rng.choice(good, min(k_face, len(good)), replace=False)
        nrm = fn[fi] / area[fi, None]
        # Face centres in barycentric coordinates, and the faces' first vertices (mesh vertices).
        c = tris[fi].mean(axis=1)
        vi = tris[rng.choice(good, min(k_face, len(good)), replace=False)]
        vn = np.cross(vi[:, 1] - vi[:, 0], vi[:, 2] - vi[:, 0])
        # The area-weighted normal of the faces around each picked vertex.
        key = {tuple(x): i for i, x in enumerate(vi[:, 0])}
        acc = np.zeros((len(vi), 3))
        for j in range(3):
            hit = np.array([key.get(tuple(x), -1) for x in tris[:, j]])
            m = hit >= 0
            np.add.at(acc, hit[m], fn[m])
        acc = np.where(np.linalg.norm(acc, axis=1, keepdims=True) > 0, acc, vn)
        vnrm = acc / np.linalg.norm(acc, axis=1, keepdims=True)
        p = np.concatenate([c + push * nrm, vi[:, 0] + push * vnrm])
        out[label] = (p, np.concatenate([nrm, vnrm]))

    k_in = max(8, n - sum(len(x[0]) for x in out.values()))
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    nr = rng.normal(size=(k_in, 3))
    out["inside box"] = (rng.uniform(lo, hi, (k_in, 3)), nr / np.linalg.norm(nr, axis=1, keepdims=True))
    return out


def _engine(scene: Any, p: np.ndarray, n: np.ndarray, env: dict[str, str] | None = None,
            device: bool = False) -> tuple[np.ndarray, float]:
    """`js.irradiance` (values, seconds of a second call) with `env` set for the call."""
    import jaxshadow as js

    old = {k: os.environ.get(k) for k in (env or {})}
    os.environ.update(env or {})
    try:
        kw = {"shadows": js.ShadowOptions(engine="device")} if device else {}
        np.asarray(js.irradiance(scene, p, n, **kw))
        t = time.perf_counter()
        e = np.asarray(js.irradiance(scene, p, n, **kw))[:, 0]
        return e, time.perf_counter() - t
    finally:
        for k, x in old.items():
            if x is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = x


FACE_PATH = {"quad": {"JAXSHADOW_SILHOUETTE": "0"}, "segment": {"JAXSHADOW_SEGMENT_PIECES": "0"}}


def _independent(kind: str, light: Any, tris: np.ndarray, p: np.ndarray, n: np.ndarray) -> np.ndarray:
    if kind == "quad":
        return chk.polygon_reference(np.asarray(light.vertices, float), tris, p, n)
    return chk.kind_reference({"segment": "segment", "point": "point", "directional": "directional"}[kind],
                              light, tris, p, n)


def case(tris: np.ndarray, occluders: Any, kind: str, light: Any, groups: dict, dtype: Any,
         n_ref: int, seed: int = 0, scene64: Any = None) -> dict:
    """One mesh, placement and light kind: the engine on every receiver group against the
    brute-force path (face path / device kernel) and the independent reference on `n_ref`
    receivers (the worst disagreements first, then random penumbra ones)."""
    import jaxshadow as js

    names = list(groups)
    p = np.concatenate([groups[k][0] for k in names])
    nrm = np.concatenate([groups[k][1] for k in names])
    label = np.concatenate([[i] * len(groups[k][0]) for i, k in enumerate(names)])
    row: dict[str, Any] = {"receivers": int(len(p))}
    t = time.perf_counter()
    scene = js.Scene([light], occluders=occluders)
    row["build_s"] = time.perf_counter() - t
    if dtype == np.float32:
        p32, n32 = p.astype(np.float32), nrm.astype(np.float32)
        t = time.perf_counter()
        e32 = np.asarray(js.irradiance(scene, p32, n32))[:, 0]
        row["engine_s"] = time.perf_counter() - t
        row["nonfinite"] = int((~np.isfinite(e32)).sum())
        # The same rounded inputs in float64: the light's and occluders' values are float32 values
        # (the scene was built from them), so a float64 scene of the same numbers.
        p, nrm = p32.astype(np.float64), n32.astype(np.float64)
        e64, _ = _engine(scene64, p, nrm)
        unocc = np.asarray(js.irradiance(js.Scene(scene64.lights), p, nrm))[:, 0]
        # The property suite's float32 bound: 1e-5 U plus Lambert's sum's absolute rounding
        # (8 float32 epsilons of 0.1 pi); the share of it used.
        bound = 1e-5 * np.abs(unocc) + 8 * float(np.finfo(np.float32).eps) * 0.1 * np.pi
        err = np.abs(e32 - e64) / bound * TOL["float32"]
        row["max_rel_err"] = float(np.nanmax(err)) if len(err) else 0.0
        row["reference"] = "float64 engine, share of the float32 bound x 1e-5"
        row["by_group"] = {k: float(np.nanmax(err[label == i])) for i, k in enumerate(names)}
        return row
    e, row["engine_s"] = _engine(scene, p, nrm)
    row["nonfinite"] = int((~np.isfinite(e)).sum())
    unocc = np.asarray(js.irradiance(js.Scene([light]), p, nrm))[:, 0]
    floor = 1e-3 * max(float(np.abs(unocc).max()), 1e-300)
    scale = np.maximum(np.abs(unocc), floor)
    if kind in FACE_PATH:
        ref, row["reference_s"] = _engine(scene, p, nrm, env=FACE_PATH[kind])
        row["reference"] = "face path"
    else:
        ref, row["reference_s"] = _engine(scene, p, nrm, device=True)
        row["reference"] = "device kernel"
    err = np.abs(e - ref) / scale
    err[~np.isfinite(err)] = np.inf
    hard = kind in ("point", "directional")
    if hard:
        flip = (e > 0) != (ref > 0)
        row["hard_disagree"] = int(flip.sum())
        err = np.where(flip, 0.0, err)
    row["max_rel_err"] = float(err.max())
    row["by_group"] = {k: float(err[label == i].max()) for i, k in enumerate(names)}
    # The independent reference where the engine and the brute-force path disagree most, and on a
    # few receivers of the shadow's edge (neither 0 nor unoccluded).
    rng = np.random.default_rng(seed)
    worst = np.argsort(-(err + (np.abs(e - ref) / scale if hard else 0)))[: max(1, n_ref // 2)]
    edge = np.where((e > 0) & (e < 0.999 * unocc))[0]
    more = rng.choice(edge, min(len(edge), n_ref - len(worst)), replace=False) if len(edge) else np.zeros(0, int)
    sel = np.unique(np.concatenate([worst, more]).astype(int))
    t = time.perf_counter()
    ind = _independent(kind, light, tris, p[sel], nrm[sel])
    row["independent_s"] = time.perf_counter() - t
    row["independent_receivers"] = int(len(sel))
    ie = np.abs(e[sel] - ind) / scale[sel]
    ir = np.abs(ref[sel] - ind) / scale[sel]
    if hard:
        row["hard_disagree_independent"] = int(np.sum((e[sel] > 0) != (ind > 0)))
        ie = np.where((e[sel] > 0) != (ind > 0), 0.0, ie)
        ir = np.where((ref[sel] > 0) != (ind > 0), 0.0, ir)
    row["max_rel_err_independent"] = float(ie.max()) if len(ie) else 0.0
    row["reference_vs_independent"] = float(ir.max()) if len(ir) else 0.0
    if row["max_rel_err_independent"] > TOL["float64"] or row["max_rel_err"] > TOL["float64"]:
        bad = sel[np.argsort(-ie)[:3]]
        row["worst"] = [{"group": names[label[i]], "p": p[i].tolist(), "n": nrm[i].tolist(), "engine": float(e[i]),
                         "brute_force": float(ref[i]), "unoccluded": float(unocc[i])} for i in bad]
    return row


def run(paths: list[str], n: int, n_ref: int, kinds: tuple[str, ...], which: tuple[str, ...],
        up: str = "y", verbose: bool = True, full: bool = False) -> list[dict]:
    """The sweep's rows: per file, placement (`which`) and light kind (`kinds`; other than `quad`
    only on `OTHER_KINDS_PLACEMENTS` unless `full`), `case` on about `n` receivers (`receivers`)
    with `n_ref` of them checked by the independent reference (2 for segment lights, whose
    reference integrates numerically)."""
    import jax

    import jaxshadow as js

    jax.config.update("jax_enable_x64", True)
    kind_placements = PLACEMENTS if full else OTHER_KINDS_PLACEMENTS
    rows = []
    for path in paths:
        try:
            v, f = load_file(path, up)
        except Exception as ex:  # an unreadable file is a row of the sweep, not its end
            row = {"mesh": Path(path).name, "triangles": 0, "placement": "-", "light": "-", "expect": "ok",
                   "error": f"{type(ex).__name__}: {str(ex)[:200]}", "wall_s": 0.0}
            rows.append(row)
            if verbose:
                print(_line(row), flush=True)
            continue
        for pname, pl in placements(v, f, which).items():
            tris = pl["tris"] if pl["f"] is None else pl["v"][pl["f"]]
            centre = (tris.reshape(-1, 3).max(axis=0) + tris.reshape(-1, 3).min(axis=0)) / 2
            groups = receivers(tris, n)
            for kind in kinds:
                dt = pl["dtype"]
                quad = pl["quad"].astype(dt).astype(np.float64) if dt == np.float32 else pl["quad"]
                light = light_of(kind, quad.astype(dt), centre)
                if kind != "quad" and pname not in kind_placements:
                    continue
                if pl["f"] is None:
                    occ: Any = pl["tris"]
                else:
                    occ = [js.Mesh(pl["v"].astype(dt), pl["f"])]
                # float32: the float64 engine on the same rounded numbers is the reference.
                s64 = js.Scene([light_of(kind, quad, centre)], occluders=[js.Mesh(pl["v"], pl["f"])]) if dt == np.float32 else None
                head = {"mesh": Path(path).name, "triangles": int(len(tris)), "placement": pname, "light": kind}
                t = time.perf_counter()
                try:
                    row = head | case(tris, occ, kind, light, groups, dt, n_ref if kind != "segment" else min(n_ref, 2),
                                      scene64=s64)
                except Exception as ex:  # a crash is a result of the sweep
                    row = head | {"error": f"{type(ex).__name__}: {str(ex)[:200]}"}
                row["expect"] = pl.get("expect", "ok")
                row["wall_s"] = time.perf_counter() - t
                rows.append(row)
                if verbose:
                    print(_line(row), flush=True)
    return rows


def _ok(r: dict) -> bool:
    if r.get("expect") == "error":
        return "error" in r
    if "error" in r or r.get("nonfinite", 0):
        return False
    tol = TOL["float32" if r["placement"] == "float32" else "float64"]
    return r["max_rel_err"] <= tol and r.get("max_rel_err_independent", 0.0) <= tol


def _line(r: dict) -> str:
    cells = [r["mesh"], str(r["triangles"]), r["placement"], r["light"], "pass" if _ok(r) else "FAIL"]
    if "error" in r:
        cells += [r["error"]]
    else:
        ind = r.get("max_rel_err_independent")
        cells += [f"{r['receivers']}", f"{r['max_rel_err']:.1e} ({r['reference']})",
                  f"{ind:.1e} ({r['independent_receivers']})" if ind is not None else "-",
                  str(r["nonfinite"]), str(r.get("hard_disagree", "-")), f"{r['engine_s']:.3f}", f"{r['wall_s']:.1f}"]
    return "| " + " | ".join(cells) + " |"


HEADER = ("| mesh | triangles | placement | light | result | receivers | max rel. err vs brute force | "
          "max rel. err vs independent (receivers) | non-finite | hard-shadow flips | engine s | case s |\n"
          "|---|---:|---|---|---|---:|---|---|---:|---:|---:|---:|")


def main(argv: list[str] | None = None) -> int:
    """`python -m benchmarks.mesh_sweep --mesh FILE [--mesh FILE ...] | --dir DIR [--record]`."""
    import argparse
    import sys

    ap = argparse.ArgumentParser(prog="python -m benchmarks.mesh_sweep", description=__doc__.split("\n")[0])
    ap.add_argument("--mesh", action="append", default=[], help="a mesh file; repeatable")
    ap.add_argument("--dir", default=None, help="every mesh file (.obj, .ply, .stl, .off) in this folder")
    ap.add_argument("--receivers", type=int, default=320, help="receivers per case (default 320)")
    ap.add_argument("--ref", type=int, default=6, help="receivers per case checked by the independent reference (default 6)")
    ap.add_argument("--kinds", default=",".join(KINDS), help="light kinds, comma-separated")
    ap.add_argument("--placements", default=",".join(PLACEMENTS), help="placements, comma-separated")
    ap.add_argument("--full", action="store_true", help="every light kind on every placement")
    ap.add_argument("--up", choices=("x", "y", "z"), default="y")
    ap.add_argument("--record", action="store_true", help="write benchmarks/results/mesh_sweep.{json,md}")
    args = ap.parse_args(argv)
    paths = list(args.mesh)
    if args.dir:
        paths += sorted(str(x) for x in Path(args.dir).iterdir() if x.suffix.lower() in (".obj", ".ply", ".stl", ".off"))
    if not paths:
        ap.error("no mesh: give --mesh or --dir")
    print(HEADER, flush=True)
    t0 = time.perf_counter()
    rows = run(paths, args.receivers, args.ref, tuple(args.kinds.split(",")), tuple(args.placements.split(",")), args.up,
               full=args.full)
    failed = [r for r in rows if not _ok(r)]
    print(f"{len(rows)} cases, {len(failed)} failed, {time.perf_counter() - t0:.0f} s", flush=True)
    if args.record:
        from benchmarks._suite import RESULTS, caption, meta, write_json, write_text

        info = meta(NAME, False)
        info["command"] = "python -m benchmarks.mesh_sweep " + " ".join(sys.argv[1:] if argv is None else argv)
        info["wall_s"] = round(time.perf_counter() - t0, 1)
        record = {"benchmark": NAME, "meta": info, "results": rows}
        write_json(RESULTS / "mesh_sweep.json", record)
        write_text(RESULTS / "mesh_sweep.md", caption(record) + "\n\n" + HEADER + "\n" + "\n".join(_line(r) for r in rows)
                   + f"\n\n{len(rows)} cases, {len(failed)} failed. " + NOTE + "\n")
    return 1 if failed else 0


NOTE = ("Errors: |E - ref| / max(U, 1e-3 max U), U the unoccluded value; bound 1e-9 (float32: against the float64 engine on "
        "the same rounded inputs, the share of the bound 1e-5 U + 8 eps32 0.1 pi, times 1e-5). Brute force: the face path (quad, segment) or the device kernel (point, "
        "directional) on every receiver; independent: polygon booleans in shapely / ray tests on the worst receivers "
        "and a few in the shadow's edge. Hard-shadow flips: receivers whose lit/shadowed decision differs from the device "
        "kernel's (on a shadow boundary: rounding), left out of the errors.")


if __name__ == "__main__":
    raise SystemExit(main())
