"""The host shadow engine (`csrc/shadowc.cc`): bit-identical results, instructions per receiver.

    .venv/bin/python -m benchmarks.engine_profile --record         # store the reference outputs
    .venv/bin/python -m benchmarks.engine_profile --check          # compare this build against them
    .venv/bin/python -m benchmarks.engine_profile                  # check + callgrind + wall times
    .venv/bin/python -m benchmarks.engine_profile --quick          # fewer receivers (~3 min)

**Identity.** On a fixed set of seeded scenes the engine's outputs are recorded for float32 and
float64: per receiver the class, the statistics (candidates, regions kept), the CSR offsets,
the boundary runs' endpoint codes and their decoded points (`polygon_codes`, both with codes
and with decoded points only, as `host_values` asks for other integrands than Lambert's), each
receiver's Lambert edge sum (as it asks for irradiance); the compiled-program variant
(`traced_polygon_codes`, XLA FFI, a small capacity so that truncation is covered); hard-shadow
visibility and segment-light candidates; and the end-to-end values of `js.irradiance` and an
eager `jax.grad` (the Python side of the host path). A later build must reproduce every array
bit for bit. Scenes: the 180-box mesh field of `benchmarks.scenes` (floor receivers, 5 % grazing,
and receivers on the boxes' faces, edges and corners and inside them), the same boxes as 2 160
independent triangles, one quad occluder, one box (90 % lit), the six boxes of
`tests/test_plan.py` as meshes and as triangles with its mesh cases (shared faces, a
box touching the light), the special configurations of `tests/test_clip.py` (coplanar,
identical and shared-edge occluders, occluders straddling the light's or the receiver's plane,
touching the receiver, lying on the light), random convex occluders of `test_clip.random_scene`
with receivers on the occluders' planes, convex UV spheres (silhouettes above the engine's 16
edges) and an open mesh. The reference lives in a temporary directory (`--ref DIR`, default
`$TMPDIR/jaxshadow-engine-ref`), never in git.

**Instructions.** `valgrind --tool=callgrind` counts the instructions of `jaxshadow_poly_plan`
(one thread, `--toggle-collect`, the hierarchy's build included) on `N` receivers of each scene;
reported per receiver (repeatable to a few parts in 1e5, unlike wall times on a shared machine).
The valgrind'd driver loads the compiled library and `jaxshadow/_shadows/abi.py` by path, without
importing JAX (which alone takes minutes under valgrind). Wall times (best of 3, one thread) are
reported beside them as a secondary, noisy number.

Writes `benchmarks/results/engine_profile[_quick].json`.
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results"
NAME = "engine_profile"
DEFAULT_REF = Path(tempfile.gettempdir()) / "jaxshadow-engine-ref"
# Scenes whose instructions are counted, and their receiver counts (full, quick).
# The function whose instructions are counted: the C entry point's dtype dispatch (a plain call;
# the exported `jaxshadow_poly_plan` tail-calls it, which callgrind's toggle does not follow).
TOGGLE = "*poly_plan_any*"
PROFILED = {"mesh": (5000, 2000), "mesh_tris": (2000, 500), "quad": (5000, 2000), "lit90": (5000, 2000),
            "boxes6": (2000, 1000)}


# --------------------------------------------------------------------------------------
# Scenes (seeded)
# --------------------------------------------------------------------------------------


def _tests_path() -> None:
    if str(ROOT / "tests") not in sys.path:
        sys.path.insert(0, str(ROOT / "tests"))


def _floor(n: int, half: float, seed: int, grazing: float) -> tuple[np.ndarray, np.ndarray]:
    from benchmarks.scenes import floor_receivers

    p, nrm = floor_receivers(n, seed=seed, grazing=grazing)
    p[:, :2] *= half / 4.0
    return p, nrm


def _on_boxes(boxes: list, n_boxes: int) -> tuple[np.ndarray, np.ndarray]:
    """Receivers on the first boxes' top and side faces, edges and corners, at their feet on the
    floor, and inside them."""
    pts, nrm = [], []
    for v, _ in boxes[:n_boxes]:
        lo, hi = v.min(axis=0), v.max(axis=0)
        c = 0.5 * (lo + hi)
        rows = [([c[0], c[1], hi[2]], [0, 0, 1]), ([lo[0], lo[1], hi[2]], [0, 0, 1]),
                ([c[0], hi[1], hi[2]], [0, 0, 1]), ([lo[0], c[1], c[2]], [-1, 0, 0]),
                ([c[0], hi[1], c[2]], [0, 1, 0]), ([hi[0], c[1], 0.0], [0, 0, 1]), ([lo[0], lo[1], 0.0], [0, 0, 1]),
                ([c[0], c[1], c[2]], [0, 0, 1]), ([hi[0], c[1], hi[2]], [0.6, 0, 0.8])]
        for q, m in rows:
            pts.append(q)
            nrm.append(m)
    return np.array(pts, float), np.array(nrm, float)


def _clip_cases() -> list[tuple[np.ndarray, list, np.ndarray, np.ndarray]]:
    """`tests/test_clip.py`'s special configurations: (light, occluders, points, normals)."""
    _tests_path()
    from test_clip import EM, GRID

    up, tilted = np.array([0, 0, 1.0]), np.array([0.6, 0.0, 0.8]) / np.linalg.norm([0.6, 0.0, 0.8])
    a = np.array([[-0.6, -0.5, 1.0], [0.4, -0.5, 1.0], [0.4, 0.5, 1.0], [-0.6, 0.5, 1.0]])
    b = np.array([[-0.2, -0.3, 1.3], [0.8, -0.1, 1.2], [0.5, 0.7, 1.4]])
    q = np.array([[-0.5, -0.4, 1.0], [0.5, -0.4, 1.2], [0.5, 0.6, 1.2], [-0.5, 0.6, 1.0]])
    configs = [
        [a, b, a + np.array([0.3, 0.2, 0.0])],
        [a, a[::-1].copy()],
        [a, np.array([[-0.2, -0.5, 1.0], [0.9, -0.5, 1.0], [0.9, 0.1, 1.0], [-0.2, 0.1, 1.0]])],
        [q[[0, 1, 2]], q[[0, 2, 3]], np.array([q[2], [0.9, 0.9, 1.5], [0.2, 1.0, 1.3]])],
        [np.array([[-0.5, -0.3, 1.5], [0.6, -0.3, 2.6], [0.6, 0.4, 2.6], [-0.5, 0.4, 1.5]])],
        [np.array([[0.2, -2.0, 1.0], [0.2, 2.0, 1.0], [0.2, 2.0, 3.0], [0.2, -2.0, 3.0]])],
        [np.array([[-0.5, -0.3, -0.5], [0.6, -0.3, 1.4], [0.6, 0.4, 1.4], [-0.5, 0.4, -0.5]])],
        [np.array([[-4.0, -0.3, -1.0], [1.0, -0.3, 1.5], [1.0, 0.4, 1.5], [-4.0, 0.4, -1.0]])],
        [np.array([[0.3, -1.0, 0.0], [0.3, 1.0, 0.0], [0.3, 1.0, 1.5], [0.3, -1.0, 1.5]]),
         np.array([[0.0, 0.0, 0.0], [0.8, -0.3, 1.2], [0.5, 0.6, 1.2]])],
        [np.array([[-0.5, -0.5, 1.0], [-0.5, 0.5, 1], [0.5, 0.5, 1], [0.5, -0.5, 1]])],
        [np.array([[-0.5, -0.5, 1.0], [0.0, -0.5, 1], [0.0, 0.5, 1], [-0.5, 0.5, 1]]),
         np.array([[-1.0, -0.5, 1.0], [-0.5, -0.5, 1], [-0.5, 0.5, 1], [-1.0, 0.5, 1]])],
        [np.array([[-1, -1, 2.0], [-1, 1, 2], [0, 1, 2], [0, -1, 2]])],
        [np.array([[-1, -1, 2.0], [-1, 1, 2], [-0.2, 1, 1.2], [-0.2, -1, 1.2]])],
        [np.array([[-0.5, -0.5, 1.0], [0.2, -0.5, 1.0], [0.3, 0.2, 1.4]]),
         np.array([[0.3, 0.3, 2.0], [0.9, 0.0, 1.0], [0.8, 0.8, 1.2]])],
    ]
    extra = np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.3, 0.2, 0], [0.29, 0.2, 0], [0.3000001, 0.2, 0],
                      [-1, 0.2, 0], [0.1, 0.05, 1.0], [0.0, 0.0, 1.0]])
    pts = np.concatenate([np.array(GRID), extra])
    out = []
    for occs in configs:
        for nrm in (up, tilted):
            out.append((EM, occs, pts, np.tile(nrm, (len(pts), 1))))
    return out


def _random_cases(n_seeds: int) -> list[tuple[np.ndarray, list, np.ndarray, np.ndarray]]:
    """`test_clip.random_scene` occluders; receivers on a floor (some grazing) and on the
    occluders' own planes (both sides)."""
    _tests_path()
    from test_clip import random_scene

    out = []
    for seed in range(n_seeds):
        em, occs = random_scene(seed, (1, 2, 4, 8)[seed % 4])
        rng = np.random.default_rng(100 + seed)
        p = np.column_stack([rng.uniform(-2, 2, (60, 2)), rng.choice([0.0, 0.3], 60)])
        nrm = rng.normal(size=(60, 3))
        nrm[:, 2] = np.abs(nrm[:, 2]) + (rng.uniform(size=60) < 0.7) * 2.0
        on, on_n = [], []
        for o in occs:
            w = rng.dirichlet(np.ones(len(o)), 4)
            nn = np.cross(o[1] - o[0], o[2] - o[0])
            for x in w @ o:
                on += [x, x]
                on_n += [nn, -nn]
        p = np.concatenate([p, np.array(on)])
        nrm = np.concatenate([nrm, np.array(on_n)])
        out.append((em, list(occs), p, nrm / np.linalg.norm(nrm, axis=1, keepdims=True)))
    return out


def cases(quick: bool) -> dict:
    """name -> (light (K, 3), occluders (list of arrays / js.Mesh), points, normals, flags) with
    flags a set of {"hard", "ffi", "values"}: what is recorded besides the polygon plan."""
    import jaxshadow as js
    from benchmarks.scenes import box, box_field, floor_receivers

    _tests_path()
    import test_plan as tss

    from benchmarks.scenes import uv_sphere

    out: dict = {}
    bf = box_field(180)
    meshes = [js.Mesh(v, f) for v, f in bf.boxes]
    p, nrm = floor_receivers(4000 if quick else 20000, grazing=0.05)
    out["mesh"] = (bf.light, meshes, p, nrm, {"hard", "values"})
    out["mesh_faces"] = (bf.light, meshes, *_on_boxes(bf.boxes, 60), {"hard"})
    out["mesh_tris"] = (bf.light, list(bf.triangles), *floor_receivers(2000, seed=2, grazing=0.05), {"hard"})
    sq = np.array([[-0.4, -0.4, 1.0], [0.4, -0.4, 1.0], [0.4, 0.4, 1.0], [-0.4, 0.4, 1.0]])
    out["quad"] = (bf.light, [sq], *floor_receivers(5000, seed=3, grazing=0.05), {"hard"})
    v, f = box((-0.15, -0.15, 0.6), (0.15, 0.15, 0.9))
    out["lit90"] = (bf.light, [js.Mesh(v, f)], *floor_receivers(5000, seed=4, grazing=0.05), set())
    fp, fn = tss.floor(2000)
    out["boxes6"] = (tss.LIGHT, [js.Mesh(a, b) for a, b in tss.BXS], fp, fn, {"hard", "ffi", "values"})
    out["boxes6_tris"] = (tss.LIGHT, list(tss.TRIS), fp, fn, {"ffi"})
    shared = [tss.box((-0.3, -0.2, 0.5), (0.0, 0.2, 1.0)), tss.box((0.0, -0.2, 0.5), (0.3, 0.2, 1.0)),
              tss.box((0.25, 0.25, 1.5), (0.45, 0.45, 2.0))]
    sp, sn = _on_boxes(shared, 3)
    gp, gn = _floor(300, 1.0, 5, 0.2)
    out["mesh_cases"] = (tss.LIGHT, [js.Mesh(a, b) for a, b in shared], np.concatenate([sp, gp]),
                         np.concatenate([sn, gn]), {"hard", "ffi"})
    out["mesh_cases_tris"] = (tss.LIGHT, list(np.concatenate([a[b] for a, b in shared])), np.concatenate([sp, gp]),
                              np.concatenate([sn, gn]), {"ffi"})
    for i, (em, occs, q, m) in enumerate(_clip_cases()):
        out[f"clip{i:02d}"] = (em, occs, q, m, {"ffi"})
    for i, (em, occs, q, m) in enumerate(_random_cases(8)):
        out[f"random{i}"] = (em, occs, q, m, {"ffi"})
    sph = [js.Mesh(t.reshape(-1, 3), np.arange(3 * len(t)).reshape(-1, 3)) for t in
           (uv_sphere((0.0, 0.1, 1.0), 0.35, 5, 8), uv_sphere((0.6, -0.3, 0.8), 0.25, 10, 16))]
    half = uv_sphere((-0.6, -0.2, 0.9), 0.3, 6, 8)
    half = half[half[:, :, 2].mean(axis=1) > 0.9]  # an open mesh (a dome)
    sph.append(js.Mesh(half.reshape(-1, 3), np.arange(3 * len(half)).reshape(-1, 3)))
    out["spheres"] = (tss.LIGHT, sph, *_floor(1500, 1.5, 6, 0.2), {"hard", "ffi"})
    return out


# --------------------------------------------------------------------------------------
# Outputs of one case
# --------------------------------------------------------------------------------------


def _host_occ(occluders: list, light: np.ndarray, dt):
    import jaxshadow as js
    from jaxshadow._shadows import binding as vis

    scene = js.Scene([js.PolygonLight(light, 1.0)], occluders=occluders)
    return scene, vis.HostOccluders.of(np.asarray(scene.occluders), scene.occluder_topology, dt)


def outputs(case: tuple, dt) -> dict[str, np.ndarray]:
    """Every recorded array of one case in one dtype."""
    import jax
    import jax.numpy as jnp

    import jaxshadow as js
    from jaxshadow._shadows import binding as vis

    light, occluders, p, nrm, flags = case
    p, nrm, light = p.astype(dt), nrm.astype(dt), np.asarray(light, dt)
    scene, occ = _host_occ(occluders, light, dt)
    out: dict[str, np.ndarray] = {}
    pc = vis.polygon_codes(p, nrm, light, occ, codes=True, decoded=True)
    for k in ("classes", "stats", "offsets", "runs", "points"):
        out[f"poly/{k}"] = getattr(pc, k)
    out["poly/points_only"] = vis.polygon_codes(p, nrm, light, occ, codes=False, decoded=True).points
    out["poly/lambert"] = vis.polygon_codes(p, nrm, light, occ, codes=False, decoded=False, lambert=True).lambert
    if "ffi" in flags and vis.ffi_available():
        cls, cnt, runs = vis.traced_polygon_codes(jnp.asarray(p), jnp.asarray(nrm), jnp.asarray(light),
                                                  jnp.asarray(np.asarray(scene.occluders, dt)), scene.occluder_topology, 16)
        out["ffi/classes"], out["ffi/counts"], out["ffi/runs"] = (np.asarray(x) for x in (cls, cnt, runs))
    if "hard" in flags:
        c = np.asarray(light, float).mean(axis=0)
        out["hard/point"] = vis.hard_visibility(p, (c + [0.05, -0.03, -0.1]).astype(dt), True, occ)
        out["hard/directional"] = vis.hard_visibility(p, np.array([0.2, -0.1, -1.0], dt), False, occ)
        off, faces = vis.segment_candidates(p, (c + [-0.4, 0.1, -0.05]).astype(dt), (c + [0.5, -0.2, 0.0]).astype(dt), occ)
        out["segment/offsets"], out["segment/faces"] = off, faces
    if "values" in flags:
        m = min(len(p), 4000)
        out["values/irradiance"] = np.asarray(js.irradiance(scene, p[:m], nrm[:m]))
        if dt == np.float64:
            q = jnp.asarray(p[:300])
            g = jax.grad(lambda x: js.irradiance(scene, x, jnp.asarray(nrm[:300])).sum())(q)
            out["values/grad_points"] = np.asarray(g)
    return out


def _all_outputs(quick: bool) -> dict[str, np.ndarray]:
    import jax

    jax.config.update("jax_enable_x64", True)
    out = {}
    for name, case in cases(quick).items():
        for dt in (np.float64, np.float32):
            for k, v in outputs(case, dt).items():
                if v is not None:
                    out[f"{name}/{np.dtype(dt).name}/{k}"] = np.ascontiguousarray(v)
    return out


def _ref_file(ref: Path, quick: bool) -> Path:
    return ref / ("outputs_quick.npz" if quick else "outputs.npz")


def record(ref: Path, quick: bool) -> int:
    ref.mkdir(parents=True, exist_ok=True)
    out = _all_outputs(quick)
    np.savez(_ref_file(ref, quick), **out)
    return len(out)


def compare(ref: Path, quick: bool) -> dict:
    """`{"arrays": n, "mismatches": {key: what}}` of this build against the stored reference."""
    want = dict(np.load(_ref_file(ref, quick)))
    got = _all_outputs(quick)
    bad = {}
    for k in sorted(set(want) | set(got)):
        if k not in got or k not in want:
            bad[k] = "missing in " + ("this build" if k not in got else "the reference")
            continue
        a, b = got[k], want[k]
        if a.dtype != b.dtype or a.shape != b.shape:
            bad[k] = f"{a.dtype}{a.shape} vs reference {b.dtype}{b.shape}"
        elif a.tobytes() != b.tobytes():
            diff = a.view(np.uint8).reshape(a.shape[0], -1) != b.view(np.uint8).reshape(b.shape[0], -1) if a.ndim else None
            rows = int(np.any(diff, axis=1).sum()) if diff is not None else 1
            bad[k] = f"{rows} rows differ"
            if a.dtype.kind == "f":
                rel = np.max(np.abs(a - b)) / max(float(np.max(np.abs(b))), np.finfo(b.dtype).tiny)
                bad[k] += f" (max difference {rel:.1e} of the largest value)"
    return {"arrays": len(want), "mismatches": bad}


# --------------------------------------------------------------------------------------
# Instruction counts (callgrind) and wall times
# --------------------------------------------------------------------------------------


def _driver_inputs(name: str, n: int, dt, path: Path) -> None:
    light, occluders, p, nrm, _ = cases(True)[name] if name != "mesh" else cases(False)[name]
    dt = np.dtype(dt)
    _, occ = _host_occ(occluders, np.asarray(light, dt), dt)
    np.savez(path, p=p[:n].astype(dt), n=nrm[:n].astype(dt), v=np.asarray(light, dt), faces=occ.faces,
             n_solids=np.int64(occ.topology.n_solids), **{f"i{k}": a for k, a in enumerate(occ._ints)})


def _load_abi():
    spec = importlib.util.spec_from_file_location("jaxshadow_engine_abi", ROOT / "jaxshadow" / "_shadows" / "abi.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    so = sorted((ROOT / "jaxshadow" / "_shadows").glob("_shadowc*.so"))
    if not so:
        raise RuntimeError("jaxshadow/_shadows/_shadowc*.so is not built (python setup.py build_ext --inplace)")
    return mod, mod.load(str(so[0]))


def driver(path: str, reps: int = 1) -> float:
    """One engine call (one thread, Lambert edge sums as `host_values` asks for irradiance) on saved inputs;
    no JAX import. Returns the best wall time of `reps` calls."""
    abi, lib = _load_abi()
    d = dict(np.load(path))  # the arrays stay alive while the engine reads their pointers
    args = abi.occluder_args(d["faces"], [d[f"i{k}"] for k in range(5)], int(d["n_solids"]))
    best = np.inf
    for _ in range(reps):
        t = time.perf_counter()
        abi.poly_plan(lib, d["p"], d["n"], d["v"], args, 1, False, False, True)
        best = min(best, time.perf_counter() - t)
    return best


def _callgrind(npz: Path, out: Path) -> tuple[int, list[str]]:
    env = dict(os.environ, JAXSHADOW_THREADS="1", PYTHONPATH=str(ROOT))
    cmd = ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", "--collect-atstart=no",
           f"--toggle-collect={TOGGLE}", sys.executable, "-m", "benchmarks.engine_profile", "--driver", str(npz)]
    subprocess.run(cmd, cwd=ROOT, env=env, check=True, capture_output=True)
    total = 0
    for line in out.read_text().splitlines():
        if line.startswith(("summary:", "totals:")):
            total = int(line.split()[1])
    ann = subprocess.run(["callgrind_annotate", "--inclusive=no", str(out)], capture_output=True, text=True, check=False)
    top = [ln.strip() for ln in ann.stdout.splitlines() if "jaxshadow" in ln or "???" in ln or "lib" in ln][:12]
    return total, top


def profile(quick: bool, scenes: list[str] | None = None) -> dict:
    """Instructions per receiver (callgrind) and wall time per receiver (one thread, best of 3)."""
    tmp = Path(tempfile.mkdtemp(prefix="jaxshadow-engine-profile-"))
    have_valgrind = shutil.which("valgrind") is not None
    res = {}
    for name in scenes or list(PROFILED):
        n = PROFILED[name][1 if quick else 0]
        for dt in ("float64", "float32") if name == "mesh" else ("float64",):
            npz = tmp / f"{name}-{dt}.npz"
            _driver_inputs(name, n, dt, npz)
            row: dict = {"receivers": n, "dtype": dt}
            wall = float(subprocess.run([sys.executable, "-m", "benchmarks.engine_profile", "--driver", str(npz), "--reps",
                                         "3"], cwd=ROOT, capture_output=True, text=True, check=True,
                                        env=dict(os.environ, PYTHONPATH=str(ROOT))).stdout.split()[-1])
            row["wall_us_per_receiver"] = 1e6 * wall / n
            if have_valgrind:
                total, top = _callgrind(npz, tmp / f"{name}-{dt}.cg")
                row["instructions"] = total
                row["instructions_per_receiver"] = total / n
                row["top"] = top
            res[f"{name}/{dt}"] = row
            print(json.dumps({k: v for k, v in row.items() if k != "top"} | {"case": f"{name}/{dt}"}), flush=True)
    shutil.rmtree(tmp, ignore_errors=True)
    return res


def run(quick: bool = False, ref: Path = DEFAULT_REF) -> dict:
    """Identity against the stored reference (recorded first when there is none), then the
    instruction and wall-time profile."""
    results: dict = {"name": NAME, "quick": quick, "machine": platform.processor() or platform.machine(),
                     "cpus": os.cpu_count(), "reference": str(_ref_file(ref, quick))}
    if not _ref_file(ref, quick).exists():
        results["recorded"] = record(ref, quick)
    results["identity"] = compare(ref, quick)
    print(json.dumps({"identity": results["identity"]}), flush=True)
    results["profile"] = profile(quick)
    return results


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer receivers")
    ap.add_argument("--ref", type=Path, default=DEFAULT_REF, help="directory of the reference outputs")
    ap.add_argument("--record", action="store_true", help="store this build's outputs as the reference")
    ap.add_argument("--check", action="store_true", help="only compare this build's outputs to the reference")
    ap.add_argument("--profile", nargs="*", metavar="SCENE", help="only the instruction profile (these scenes)")
    ap.add_argument("--driver", help=argparse.SUPPRESS)
    ap.add_argument("--reps", type=int, default=1, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.driver:
        print(driver(args.driver, args.reps))
        return
    if args.record:
        print(f"recorded {record(args.ref, args.quick)} arrays in {_ref_file(args.ref, args.quick)}")
        return
    if args.check:
        res = compare(args.ref, args.quick)
        print(json.dumps(res, indent=1))
        sys.exit(1 if res["mismatches"] else 0)
    if args.profile is not None:
        print(json.dumps(profile(args.quick, args.profile or None), indent=1))
        return
    res = run(args.quick, args.ref)
    import jaxshadow as js

    RESULTS.mkdir(exist_ok=True)
    with js.files.atomic_write(RESULTS / (f"{NAME}_quick.json" if args.quick else f"{NAME}.json")) as fh:
        json.dump(res, fh, indent=1)
    if res["identity"]["mismatches"]:
        sys.exit(1)


if __name__ == "__main__":
    main()
