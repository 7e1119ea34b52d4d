# ruff: noqa: E501  (one table row per case reads better than wrapped lines)
r"""Stiff and extreme configurations: values and gradients against an independent mpmath reference.

Kernels covered: polygon form factor (`form_factor_kernel`), linear (segment) lights
(`linear_irradiance_kernel`, m = 0, 1, 4), point lights (`point_irradiance_kernel`), float32
and float64. The references below are written from the definitions, in mpmath at 60 digits:

- polygon: Sutherland-Hodgman clipping of the emitter to the receiver's horizon, then
  Lambert's contour sum (a different clipping algorithm and arithmetic from the JAX code);
  the regular 64-gon is also checked against its own closed form and the coaxial disk
  $F = R^2 / (R^2 + h^2)$;
- segment: `mpmath.quad` of $C_m \cos^m\beta\, \max(0, n\cdot(x - p)) / r^3$ along the segment,
  $C_m = 1 / (2\pi\int_{-\pi/2}^{\pi/2}\cos^{m+1})$ integrated numerically too;
- point: $\max(0, n\cdot w) / |w|^3$.

Gradients (w.r.t. the receiver position and normal) are checked against mpmath central
differences with a step of 1e-20 times the scene scale. The float32 reference is evaluated at
the float32-rounded inputs, so the errors measure the kernel, not the rounding of the data.

`benchmarks/stability_table.py` reuses `evaluate_all` to write the table in benchmarks/README.md.
"""

from __future__ import annotations

import functools
import json
from pathlib import Path

import jax
import jax.numpy as jnp
import mpmath as mp
import numpy as np
import pytest

from benchmarks.scenes import clip_halfspace
from jaxshadow._kernels.linear import linear_irradiance_kernel
from jaxshadow._kernels.point import point_irradiance_kernel
from jaxshadow._kernels.polygon import form_factor_kernel

DPS = 60

# --------------------------------------------------------------------------------------
# Cases
# --------------------------------------------------------------------------------------


def _unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v)


def _rect(x0, x1, y0, y1, z, facing_down=True):
    """Axis-aligned rectangle in the plane z, counter-clockwise seen from below (or above)."""
    v = np.array([[x0, y0, z], [x0, y1, z], [x1, y1, z], [x1, y0, z]], dtype=np.float64)
    return v if facing_down else v[::-1].copy()


def _regular_polygon(k, radius, z):
    """Regular k-gon inscribed in a circle of `radius` at height z, facing down (-z)."""
    t = -2 * np.pi * np.arange(k) / k
    return np.stack([radius * np.cos(t), radius * np.sin(t), np.full(k, z)], axis=1)


SQUARE = _rect(-0.5, 0.5, -0.5, 0.5, 1.0)
GENERIC = (np.array([0.1, -0.2, 0.0]), _unit([0.1, 0.2, 1.0]), SQUARE)

# id -> (p, n, verts, what is stiff about it)
POLYGON_CASES = {
    "generic": (*GENERIC, "reference configuration"),
    "plane-1e-9-centre": (np.zeros(3), np.array([0.0, 0.0, 1.0]), _rect(-0.5, 0.5, -0.5, 0.5, 1e-9), "receiver 1e-9 below the emitter's plane, under it (F -> 1)"),
    "plane-1e-9-beside": (np.array([1.5, 0.2, 0.0]), _unit([-1.0, 0.0, 1.0]), _rect(-0.5, 0.5, -0.5, 0.5, 1e-9), "receiver 1e-9 below the emitter's plane, beside it (F ~ 1e-9)"),
    "edge-line-1e-9": (np.array([2.0, 0.0, 1e-9]), _unit([-1.0, 0.0, 0.5]), _rect(0.0, 1.0, 0.0, 1.0, 0.0, facing_down=False), "receiver 1e-9 from the supporting line of an edge (edge seen end-on)"),
    "edge-line-exact": (np.array([2.0, 0.0, 0.0]), _unit([-1.0, 0.0, 0.5]), _rect(0.0, 1.0, 0.0, 1.0, 0.0, facing_down=False), "receiver exactly on an edge's line (in the emitter's plane: F = 0)"),
    "grazing-edge-1e-7": (np.zeros(3), np.array([0.0, 1.0, 0.0]), _rect(-0.5, 0.5, 1e-7, 1.0, 1.0), "an emitter edge 1e-7 above the receiver's horizon"),
    "grazing-far": (np.zeros(3), np.array([0.0, 0.0, 1.0]), np.array([[10.0, -0.5, 0.1], [10.0, 0.5, 0.1], [10.0, 0.5, 1e-6], [10.0, -0.5, 1e-6]]), "emitter near the horizon, 10 away"),
    "horizon-cuts": (np.zeros(3), _unit([1.0, 0.0, 1e-3]), SQUARE, "horizon (nearly vertical) cuts the emitter in half"),
    "behind": (np.array([0.0, 0.0, 2.0]), np.array([0.0, 0.0, -1.0]), SQUARE, "receiver behind the emitter (F = 0 exactly)"),
    "scale-1e-6": (GENERIC[0] * 1e-6, GENERIC[1], GENERIC[2] * 1e-6, "whole scene scaled by 1e-6 (F is scale-free)"),
    "scale-1e6": (GENERIC[0] * 1e6, GENERIC[1], GENERIC[2] * 1e6, "whole scene scaled by 1e6"),
    "sliver-1e-6": (np.array([0.1, 0.05, 0.0]), np.array([0.0, 0.0, 1.0]), _rect(-0.5, 0.5, -5e-7, 5e-7, 1.0), "emitter of aspect ratio 1e-6"),
    "64-gon-coaxial": (np.zeros(3), np.array([0.0, 0.0, 1.0]), _regular_polygon(64, 1.0, 0.7), "regular 64-gon, coaxial, parallel (vs disk)"),
    "64-gon-off-axis": (np.array([0.6, -0.3, 0.0]), _unit([0.2, 0.0, 1.0]), _regular_polygon(64, 1.0, 0.7), "regular 64-gon, off axis, tilted receiver"),
    "64-gon-cut": (np.array([0.2, 0.1, 0.0]), _unit([1.0, 0.0, 0.3]), _regular_polygon(64, 1.0, 0.7), "regular 64-gon cut by the horizon"),
}

A0, B0 = np.array([-1.0, 0.3, 1.0]), np.array([1.0, 0.5, 1.2])
# id -> (p, n, a, b, what)
LINEAR_CASES = {
    "generic": (np.zeros(3), _unit([0.1, 0.0, 1.0]), A0, B0, "reference configuration"),
    "end-on-exact": (np.zeros(3), _unit([0.0, 0.3, 1.0]), np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 2.0]), "receiver on the supporting line, outside the segment"),
    "end-on-1e-9": (np.array([1e-9, 0.0, 0.0]), _unit([0.0, 0.3, 1.0]), np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 2.0]), "receiver 1e-9 from the supporting line, outside"),
    "line-1e-6-inside": (np.array([1e-6, 0.0, 1.5]), np.array([-1.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 2.0]), "receiver 1e-6 from the segment (foot inside; E ~ 1/d)"),
    "grazing-1e-7": (np.zeros(3), np.array([0.0, 0.0, 1.0]), np.array([-1.0, 0.5, 1e-7]), np.array([1.0, 0.7, 1e-7]), "segment 1e-7 above the horizon"),
    "horizon-cuts": (np.zeros(3), np.array([0.0, 0.0, 1.0]), np.array([-1.0, 0.2, -0.5]), np.array([1.0, 0.2, 0.5]), "horizon cuts the segment"),
    "scale-1e-6": (np.zeros(3), _unit([0.1, 0.0, 1.0]), A0 * 1e-6, B0 * 1e-6, "scene scaled by 1e-6 (E/Phi ~ 1/scale)"),
    "scale-1e6": (np.zeros(3), _unit([0.1, 0.0, 1.0]), A0 * 1e6, B0 * 1e6, "scene scaled by 1e6"),
    "long-1e6": (np.zeros(3), _unit([0.1, 0.0, 1.0]), np.array([-1e6, 0.0, 1.0]), np.array([1e6, 0.0, 1.0]), "segment 1e6 times longer than its distance"),
    "behind": (np.zeros(3), np.array([0.0, 0.0, -1.0]), A0, B0, "segment below the horizon (0 exactly)"),
}
LINEAR_EXPONENTS = (0, 1, 4)

# id -> (p, n, x, what)
POINT_CASES = {
    "generic": (np.zeros(3), _unit([0.1, 0.2, 1.0]), np.array([0.3, -0.2, 1.0]), "reference configuration"),
    "grazing-1e-9": (np.zeros(3), np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.3, 1e-9]), "light 1e-9 above the horizon"),
    "scale-1e-6": (np.zeros(3), _unit([0.1, 0.2, 1.0]), np.array([0.3, -0.2, 1.0]) * 1e-6, "light 1e-6 away (E ~ 1e12)"),
    "scale-1e6": (np.zeros(3), _unit([0.1, 0.2, 1.0]), np.array([0.3, -0.2, 1.0]) * 1e6, "light 1e6 away (E ~ 1e-12)"),
    "behind": (np.zeros(3), np.array([0.0, 0.0, -1.0]), np.array([0.3, -0.2, 1.0]), "light below the horizon (0 exactly)"),
}


# --------------------------------------------------------------------------------------
# mpmath references (independent code)
# --------------------------------------------------------------------------------------


def _mpv(x):
    return [c if isinstance(c, mp.mpf) else mp.mpf(float(c)) for c in x]


def _sub(a, b):
    return [x - y for x, y in zip(a, b, strict=True)]


def _dot(a, b):
    return sum(x * y for x, y in zip(a, b, strict=True))


def _cross(a, b):
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def mp_form_factor(p, n, verts):
    """Unoccluded form factor at 60 digits (n used as given, like the kernel)."""
    with mp.workdps(DPS):
        p, n = _mpv(p), _mpv(n)
        v = [_mpv(x) for x in verts]
        k = len(v)
        ne = [mp.mpf(0)] * 3
        for i in range(k):
            c = _cross(v[i], v[(i + 1) % k])
            ne = [x + y for x, y in zip(ne, c, strict=True)]
        if _dot(ne, _sub(p, v[0])) <= 0:
            return mp.mpf(0)
        poly = clip_halfspace(v, p, n)
        total = mp.mpf(0)
        for i in range(len(poly)):
            a, b = _sub(poly[i], p), _sub(poly[(i + 1) % len(poly)], p)
            c = _cross(a, b)
            s = mp.sqrt(_dot(c, c))
            if s == 0:
                continue
            total += mp.atan2(s, _dot(a, b)) * _dot(n, c) / s
        return -total / (2 * mp.pi)


def mp_regular_polygon_coaxial(k, radius, h):
    r"""Closed form for a receiver on the axis of a parallel regular k-gon (per-edge Lambert term):
    $F = \frac{k}{\pi}\arctan(a/s)\,\rho/s$, $\rho = R\cos(\pi/k)$, $a = R\sin(\pi/k)$, $s^2 = \rho^2+h^2$."""
    with mp.workdps(DPS):
        r, h = mp.mpf(radius), mp.mpf(h)
        rho, a = r * mp.cos(mp.pi / k), r * mp.sin(mp.pi / k)
        s = mp.sqrt(rho**2 + h**2)
        return k / mp.pi * mp.atan(a / s) * rho / s


@functools.cache
def _mp_profile_constant(m):
    with mp.workdps(DPS):
        w = mp.quad(lambda b: mp.cos(b) ** (m + 1), [-mp.pi / 2, mp.pi / 2])
        return 1 / (2 * mp.pi * w)


def mp_linear(p, n, a, b, m):
    r"""$E/\Phi$ of a segment light by adaptive quadrature along it (breakpoints at the foot of
    the perpendicular and at the horizon crossing)."""
    with mp.workdps(DPS):
        p, n, a, b = _mpv(p), _mpv(n), _mpv(a), _mpv(b)
        e = _sub(b, a)
        length = mp.sqrt(_dot(e, e))
        u = [x / length for x in e]
        c_m = _mp_profile_constant(m)

        def f(t):
            x = [ai + t * ui for ai, ui in zip(a, u, strict=True)]
            w = _sub(x, p)
            r2 = _dot(w, w)
            r = mp.sqrt(r2)
            cos_theta = _dot(n, w)
            if cos_theta <= 0:
                return mp.mpf(0)
            along = _dot(w, u)
            d = mp.sqrt(max(r2 - along**2, 0))
            return c_m * (d / r) ** m * cos_theta / (r2 * r)

        cuts = {mp.mpf(0), length}
        foot = -_dot(_sub(a, p), u)
        if 0 < foot < length:
            cuts.add(foot)
        un = _dot(n, u)
        if un != 0:
            tc = -_dot(n, _sub(a, p)) / un
            if 0 < tc < length:
                cuts.add(tc)
        pts = sorted(cuts)
        # Extra breakpoints geometrically graded towards the foot (the peak has width d there).
        if 0 < foot < length:
            d = mp.sqrt(max(_dot(_sub(a, p), _sub(a, p)) - foot**2, 0))
            if d > 0:
                for j in range(1, 40):
                    for s in (-1, 1):
                        t = foot + s * d * mp.mpf(4) ** j
                        if 0 < t < length:
                            cuts.add(t)
                pts = sorted(cuts)
        return mp.quad(f, pts)


def mp_point(p, n, x):
    with mp.workdps(DPS):
        p, n, x = _mpv(p), _mpv(n), _mpv(x)
        w = _sub(x, p)
        r2 = _dot(w, w)
        c = _dot(n, w)
        return max(c, mp.mpf(0)) / (r2 * mp.sqrt(r2))


def mp_gradient(f, p, n, scale):
    """Central differences of f(p, n) in p and n at 60 digits, step 1e-20 * scale (for p)."""
    with mp.workdps(DPS):
        out = []
        for which, base, h in ((0, p, mp.mpf(10) ** -20 * scale), (1, n, mp.mpf(10) ** -20)):
            for i in range(3):
                hi = [mp.mpf(float(c)) for c in base]
                lo = list(hi)
                hi[i] += h
                lo[i] -= h
                if which == 0:
                    fp, fm = f(hi, n), f(lo, n)
                else:
                    fp, fm = f(p, hi), f(p, lo)
                out.append((fp - fm) / (2 * h))
        return out


# --------------------------------------------------------------------------------------
# JAX side: value and gradient (w.r.t. p and n) of every case, batched per kernel
# --------------------------------------------------------------------------------------


def _value_and_grad(kernel, *extra):
    def f(p, n, *args):
        val, (gp, gn) = jax.value_and_grad(kernel, argnums=(0, 1))(p, n, *args)
        return val, jnp.concatenate([gp, gn])

    return jax.jit(jax.vmap(f, in_axes=(0, 0, *extra)))


def _scale_of(*xs):
    return max(float(np.max(np.abs(x))) for x in xs) or 1.0


def _rel_err(got, ref, floor=0.0):
    """max |got - ref| / max(max |ref|, floor) (relative error with a floor; 0/0 -> 0)."""
    got = np.asarray(got, dtype=np.float64)
    ref = np.asarray(ref, dtype=np.float64)
    den = max(float(np.max(np.abs(ref))), floor)
    err = float(np.max(np.abs(got - ref)))
    return err / den if den > 0 else err


REFERENCE_FILE = Path(__file__).parent / "data" / "stability_reference.json"


def _all_inputs(dtype):
    """`{row id: (kind, m, what, inputs...)}` with inputs rounded to `dtype`."""
    out = {}
    for cid, (p, n, v, what) in POLYGON_CASES.items():
        out[f"polygon/{cid}"] = ("polygon", None, what, *(np.asarray(x).astype(dtype) for x in (p, n, v)))
    for m in LINEAR_EXPONENTS:
        for cid, (p, n, a, b, what) in LINEAR_CASES.items():
            out[f"linear-m{m}/{cid}"] = ("linear", m, what, *(np.asarray(x).astype(dtype) for x in (p, n, a, b)))
    for cid, (p, n, x, what) in POINT_CASES.items():
        out[f"point/{cid}"] = ("point", None, what, *(np.asarray(y).astype(dtype) for y in (p, n, x)))
    return out


def _mp_reference(kind, m, *inputs):
    """(value, gradient w.r.t. p and n) at 60 digits, as floats."""
    if kind == "polygon":
        p, n, v = inputs
        f = lambda pp, nn: mp_form_factor(pp, nn, v)
        scale = _scale_of(p, v)
    elif kind == "linear":
        p, n, a, b = inputs
        f = lambda pp, nn: mp_linear(pp, nn, a, b, m)
        scale = 1.0 if np.max(np.abs(b - a)) > 1e3 else _scale_of(p, a, b)
    else:
        p, n, x = inputs
        f = lambda pp, nn: mp_point(pp, nn, x)
        scale = _scale_of(p, x)
    return float(f(p, n)), [float(g) for g in mp_gradient(f, p, n, scale)]


def compute_references():
    """All mpmath references for float32 and float64 inputs (slow: about 5 min)."""
    out = {}
    for dt in ("float32", "float64"):
        for rid, (kind, m, _, *inputs) in _all_inputs(np.dtype(dt)).items():
            val, grad = _mp_reference(kind, m, *inputs)
            out[f"{dt}/{rid}"] = {"value": val, "grad": grad}
    return out


@functools.cache
def _references():
    if REFERENCE_FILE.exists():
        return json.loads(REFERENCE_FILE.read_text())
    return compute_references()


def _evaluate(dtype):
    """JAX value and gradient of every row at one dtype, batched per kernel (one jit per shape)."""
    inputs = _all_inputs(dtype)
    got = {}
    groups = {}
    for rid, (kind, m, _, *xs) in inputs.items():
        key = (kind, m, xs[-1].shape if kind == "polygon" else None)
        groups.setdefault(key, []).append((rid, xs))
    for (kind, m, _), items in groups.items():
        if kind == "polygon":
            fn = _value_and_grad(form_factor_kernel, 0)
        elif kind == "linear":
            fn = _value_and_grad(functools.partial(linear_irradiance_kernel, m=m), 0, 0)
        else:
            fn = _value_and_grad(point_irradiance_kernel, 0)
        args = [np.stack([xs[j] for _, xs in items]) for j in range(len(items[0][1]))]
        vals, grads = fn(*args)
        for i, (rid, _) in enumerate(items):
            got[rid] = (float(vals[i]), np.asarray(grads[i], dtype=np.float64))
    return inputs, got


def _generic_row(rid):
    return rid.split("/")[0] + "/generic"


@functools.cache
def evaluate_all(dtype_name):
    """Rows of the stability table at one dtype (cached): one dict per case with the value,
    the reference, the relative error of the value and of the gradient (pure, and with a floor
    at the magnitude of the same kernel's generic case), and the number of NaN/inf."""
    refs = _references()
    inputs, got = _evaluate(np.dtype(dtype_name))
    rows = []
    for rid, (_, _, what, *_) in inputs.items():
        ref = refs[f"{dtype_name}/{rid}"]
        gen = refs[f"{dtype_name}/{_generic_row(rid)}"]
        val, grad = got[rid]
        nonfinite = int(np.sum(~np.isfinite(val)) + np.sum(~np.isfinite(grad)))
        scale_case = "/scale-" in rid
        floor_v = 0.0 if scale_case else abs(gen["value"])
        floor_g = 0.0 if scale_case else float(np.max(np.abs(gen["grad"])))
        rows.append(
            dict(
                case=rid,
                what=what,
                dtype=dtype_name,
                value=val,
                reference=ref["value"],
                rel_err=_rel_err(val, ref["value"]),
                rel_err_floor=_rel_err(val, ref["value"], floor_v),
                grad_rel_err=_rel_err(grad, ref["grad"]) if not nonfinite else float("nan"),
                grad_rel_err_floor=_rel_err(grad, ref["grad"], floor_g) if not nonfinite else float("nan"),
                nonfinite=nonfinite,
            )
        )
    return tuple(rows)


# Tolerances on the relative error with a floor (value, gradient). The floor is the magnitude
# of the same kernel's generic case, so a tiny value (F ~ 1e-10 seen edge-on) is held to an
# absolute accuracy on the scale of ordinary values. Measured maxima: benchmarks/README.md.
TOL = {"float64": (1e-13, 1e-9), "float32": (2e-6, 2e-4)}
EXACT_ZERO = {"polygon/edge-line-exact", "polygon/behind"}

# Known defects (strict xfail: fixing them makes the test XPASS and fail; then drop the entry).
KNOWN: dict[str, str] = {}


def _all_row_ids():
    return list(_all_inputs(np.float64))


@pytest.mark.parametrize("dtype_name", ["float64", "float32"])
@pytest.mark.parametrize("rid", _all_row_ids())
def test_stiff_case_against_mpmath(rid, dtype_name, request):
    key = f"{dtype_name}/{rid}"
    if key in KNOWN:
        request.applymarker(pytest.mark.xfail(strict=True, reason=KNOWN[key]))
    row = next(r for r in evaluate_all(dtype_name) if r["case"] == rid)
    assert row["nonfinite"] == 0, f"{row['nonfinite']} NaN/inf in value or gradient"
    if row["reference"] == 0.0 and (rid in EXACT_ZERO or rid.endswith("/behind")):
        assert row["value"] == 0.0
        return
    tv, tg = TOL[dtype_name]
    assert row["rel_err_floor"] <= tv, row
    assert row["grad_rel_err_floor"] <= tg, row


def test_stored_references_match_live_mpmath():
    # The stored JSON is regenerated by `python tests/test_stability.py`; spot-check it.
    refs = _references()
    inputs = _all_inputs(np.float64)
    for rid in ("polygon/edge-line-1e-9", "point/grazing-1e-9", "linear-m1/end-on-1e-9"):
        kind, m, _, *xs = inputs[rid]
        val, grad = _mp_reference(kind, m, *xs)
        assert val == pytest.approx(refs[f"float64/{rid}"]["value"], rel=1e-14, abs=1e-300)
        np.testing.assert_allclose(grad, refs[f"float64/{rid}"]["grad"], rtol=1e-12, atol=1e-300)


def test_64_gon_against_disk_closed_form():
    # The kernel matches the exact regular-polygon value, and differs from the disk
    # F = R^2 / (R^2 + h^2) by exactly the polygon-vs-disk difference.
    radius, h = 1.0, 0.7
    verts = _regular_polygon(64, radius, h)
    exact_poly = mp_regular_polygon_coaxial(64, radius, h)
    disk = radius**2 / (radius**2 + h**2)
    assert abs(float(mp_form_factor(np.zeros(3), np.array([0.0, 0.0, 1.0]), verts)) - float(exact_poly)) < 1e-13
    for dt, tol in ((np.float64, 1e-13), (np.float32, 2e-6)):
        f = float(jax.jit(form_factor_kernel)(jnp.zeros(3, dt), jnp.array([0.0, 0.0, 1.0], dt), jnp.asarray(verts, dt)))
        exact_f32 = float(mp_form_factor(np.zeros(3), np.array([0.0, 0.0, 1.0]), verts.astype(dt)))
        assert abs(f - exact_f32) < tol
        gap = abs(float(exact_poly) - disk)  # ~ 1.6e-3 for k = 64
        assert abs(abs(f - disk) - gap) < 10 * tol + abs(exact_f32 - float(exact_poly))


def test_scale_invariance_of_form_factor(dtype):
    p, n, v = GENERIC
    vals = []
    for s in (1e-6, 1.0, 1e6):
        vals.append(float(jax.jit(form_factor_kernel)(jnp.asarray(p * s, dtype), jnp.asarray(n, dtype), jnp.asarray(v * s, dtype))))
    rtol = 1e-14 if dtype == np.float64 else 2e-6
    np.testing.assert_allclose(vals, vals[1], rtol=rtol)


if __name__ == "__main__":
    import jax as _jax

    _jax.config.update("jax_enable_x64", True)
    REFERENCE_FILE.parent.mkdir(exist_ok=True)
    REFERENCE_FILE.write_text(json.dumps(compute_references(), indent=1, sort_keys=True))
    print(f"wrote {REFERENCE_FILE}")


# --------------------------------------------------------------------------------------
# Other engineers' kernels: specular (Phong lobe, n = 1 .. 1e6) and occluders touching the
# receiver. Skipped when the module is absent; listed in PENDING for the table otherwise.
# --------------------------------------------------------------------------------------

PENDING = []
try:
    from jaxshadow._kernels.specular import polygon_specular_kernel
except ImportError:  # pragma: no cover - depends on the other engineers' progress
    polygon_specular_kernel = None
    PENDING.append("specular exponent n = 1 .. 1e6 (jaxshadow/_kernels/specular.py absent)")
try:
    from jaxshadow._kernels.clip import visible_form_factor_kernel
except ImportError:  # pragma: no cover
    visible_form_factor_kernel = None
    PENDING.append("occluders almost / exactly touching the receiver (jaxshadow/_kernels/clip.py absent)")


def mp_polygon_specular(p, n, eye, verts, expo):
    r"""Phong-lobe integral per unit radiance in polar coordinates about $R$ (independent of the
    edge-sum formula): $S = \frac{1}{2\pi}\int_0^{2\pi} 1 - \cos^{n+1}\theta_{max}(\phi)\,d\phi$,
    $\theta_{max}$ the first great circle of the (convex, fully visible) spherical polygon hit
    going out from $R$ in azimuth $\phi$. Requires R inside the polygon and the polygon above
    the horizon (asserted)."""
    with mp.workdps(30):
        p, n, eye, v = _mpv(p), _mpv(n), _mpv(eye), [_mpv(x) for x in verts]
        norm = lambda x: [c / mp.sqrt(_dot(x, x)) for c in x]  # noqa: E731
        n = norm(n)
        view = norm(_sub(eye, p))
        r = [2 * _dot(n, view) * nc - vc for nc, vc in zip(n, view, strict=True)]
        w = [norm(_sub(x, p)) for x in v]
        assert all(_dot(n, x) > 0 for x in w), "reference needs the polygon above the horizon"
        k = len(w)
        planes = [norm(_cross(w[(i + 1) % k], w[i])) for i in range(k)]  # inward for CCW from below
        sides = [_dot(m, r) for m in planes]
        assert all(s > 0 for s in sides) or all(s < 0 for s in sides), "R must be inside"
        e1 = norm(_cross(r, [mp.mpf(1), mp.mpf(0.3), mp.mpf(0.1)]))
        e2 = _cross(r, e1)

        def theta_max(phi):
            d = [mp.cos(phi) * a + mp.sin(phi) * b for a, b in zip(e1, e2, strict=True)]
            best = mp.pi
            for m in planes:
                a_, b_ = _dot(m, r), _dot(m, d)
                best = min(best, mp.atan2(abs(a_), -mp.sign(a_) * b_))
            return min(best, mp.pi / 2)

        def f(phi):
            return 1 - mp.cos(theta_max(phi)) ** (mp.mpf(expo) + 1)

        # Breakpoints at the vertex azimuths (where the nearest great circle changes).
        cuts = sorted({mp.atan2(_dot(x, e2), _dot(x, e1)) % (2 * mp.pi) for x in w} | {mp.mpf(0), 2 * mp.pi})
        return mp.quad(f, cuts) / (2 * mp.pi)


SPECULAR_EXPONENTS = (1.0, 10.0, 1e2, 1e3, 1e4, 1e6)


def _specular_case(expo):
    """Receiver at the origin, square light above; R inside, at angle min(0.3, 1/sqrt(n)) from the
    great circle of the edge x = 0.5 (the lobe straddles the edge for every n)."""
    alpha = min(0.3, 1.0 / np.sqrt(expo))
    ang = np.arctan(0.5) - alpha
    r = np.array([np.sin(ang), 0.0, np.cos(ang)])
    eye = np.array([-r[0], -r[1], r[2]]) * 3.0
    return np.zeros(3), np.array([0.0, 0.0, 1.0]), eye, SQUARE


def specular_rows(method, dtype):
    """`(n, S, reference, rel err, finite value and gradients)` for every exponent."""
    rows = []
    for expo in SPECULAR_EXPONENTS:
        p, n, eye, v = (np.asarray(x, dtype) for x in _specular_case(expo))
        ref = float(mp_polygon_specular(p, n, eye, v, expo))
        args = tuple(jnp.asarray(x) for x in (p, n, eye, v)) + (jnp.asarray(expo, dtype),)
        # _specular.py:319 broadcasts (K+1, 3) - (3,); reported to its owner. Allowed here so
        # that this test measures stability, not the rank-promotion setting.
        with jax.numpy_rank_promotion("allow"):
            val, grads = _specular_value_and_grads(args, method)
        finite = bool(np.isfinite(float(val))) and all(bool(np.all(np.isfinite(np.asarray(g)))) for g in grads)
        rows.append((expo, float(val), ref, abs(float(val) - ref) / abs(ref), finite))
    return rows


SPECULAR_TOL = {("chebyshev", "float64"): 1e-5, ("exact", "float64"): 1e-9, ("chebyshev", "float32"): 1e-4, ("exact", "float32"): 1e-4}


@pytest.mark.slow  # ~40-70 s each on the shared 2-core machine (compilation + mpmath)
@pytest.mark.skipif(polygon_specular_kernel is None, reason="jaxshadow/_kernels/specular.py absent")
@pytest.mark.parametrize("method", ["chebyshev", "exact"])
def test_specular_exponent_1_to_1e6(method, dtype):
    rows = specular_rows(method, dtype)
    bad = [r for r in rows if not r[4]]
    assert not bad, f"NaN/inf in value or gradient at n = {[r[0] for r in bad]}"
    tol = SPECULAR_TOL[(method, np.dtype(dtype).name)]
    worst = max(rows, key=lambda r: r[3])
    assert worst[3] <= tol, f"n = {worst[0]}: S = {worst[1]!r}, reference {worst[2]!r}, rel err {worst[3]:.2e}"


def _specular_value_and_grads(args, method):
    if method == "exact":  # forward mode only (lax.while_loop)
        val = polygon_specular_kernel(*args, method=method)
        grads = jax.jacfwd(lambda *a: polygon_specular_kernel(*a, method=method), argnums=(0, 1, 2, 4))(*args)
    else:
        val, grads = jax.value_and_grad(lambda *a: polygon_specular_kernel(*a, method=method), argnums=(0, 1, 2, 3, 4))(*args)
    return val, grads


def _touching_cases():
    """(id, p, n, occluders (m, 4, 3), reference F (mpmath), what)."""
    p, n = np.zeros(3), np.array([0.0, 0.0, 1.0])
    f_all = mp_form_factor(p, n, SQUARE)
    f_hidden = mp_form_factor(p, n, _rect(-0.2, 0.2, -0.2, 0.2, 1.0))
    big = 2e-10  # half-width at height 1e-9 projects to half-width 0.2 on the light's plane
    return [
        ("occluder-1e-9-above-hides-centre", p, n, _rect(-big, big, -big, big, 1e-9)[None], f_all - f_hidden, "occluder 1e-9 above p, projecting onto the centre 0.4 x 0.4 of the light"),
        ("occluder-1e-9-above-hides-all", p, n, _rect(-0.1, 0.1, -0.1, 0.1, 1e-9)[None], mp.mpf(0), "occluder 1e-9 above p covering the whole light"),
        ("occluder-through-p-edge-on", p, n, np.array([[[0.0, -2.0, 0.0], [0.0, 2.0, 0.0], [0.0, 2.0, 0.9], [0.0, -2.0, 0.9]]]), f_all, "occluder plane through p (seen edge-on: blocks nothing)"),
        ("occluder-vertex-at-p", p, n, np.array([[[0.0, 0.0, 0.0], [0.3, -0.2, 0.5], [0.3, 0.2, 0.5], [0.0, 0.0, 0.0]]]), f_all, "triangle with a vertex exactly at p (p in its plane: blocks nothing)"),
        ("occluder-in-tangent-plane", p, n, _rect(-1.0, 1.0, -1.0, 1.0, 0.0)[None], f_all, "occluder in the receiver's tangent plane, containing p"),
    ]


@pytest.mark.slow  # ~45 s per dtype (compilation of the clipping kernel)
@pytest.mark.skipif(visible_form_factor_kernel is None, reason="jaxshadow/_kernels/clip.py absent")
def test_occluders_touching_the_receiver(dtype):
    failures = []
    for cid, val, ref, unocc, finite in touching_rows(dtype):
        if not finite:
            failures.append(f"{cid}: NaN/inf (value {val!r})")
            continue
        if not -1e-7 <= val <= unocc * (1 + 1e-6) + 1e-7:
            failures.append(f"{cid}: F = {val!r} outside [0, unoccluded {unocc!r}]")
        if ref is not None:
            tol = 1e-12 if dtype == np.float64 else 2e-6
            if abs(val - ref) > tol:
                failures.append(f"{cid}: F = {val!r}, reference {ref!r}")
    assert not failures, "\n".join(failures)


def touching_rows(dtype):
    """`(id, F, reference or None, unoccluded F, finite value and gradients)` per case."""
    rows = []
    for cid, p, n, occ, ref, _ in _touching_cases():
        args = tuple(jnp.asarray(x, dtype) for x in (p, n, SQUARE, occ))
        val, grads = jax.value_and_grad(visible_form_factor_kernel, argnums=(0, 1, 2, 3))(*args)
        unocc = float(form_factor_kernel(*args[:3]))
        finite = bool(np.isfinite(float(val))) and all(bool(np.all(np.isfinite(np.asarray(g)))) for g in grads)
        rows.append((cid, float(val), None if ref is None else float(ref), unocc, finite))
    return rows
