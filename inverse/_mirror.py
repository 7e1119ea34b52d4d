r"""Mirror placements: where the targets are symmetric under a reflection, the lights reflected
with them explain the targets as well as the answer does (the rival check of `fit_lights`,
`_multilight_result`).

**Symmetry plane.** Lambert shading of a receiver at $x$ with normal $n$ by a light depends on
the light only through distances to $x$ and angles with $n$. When every target's point lies in
one plane $\Pi$ and every normal is parallel to it (targets on a straight line, with normals in
the plane through that line), the reflection $M$ across $\Pi$ keeps every such distance and
angle: a light and its mirror image paint the targets alike, and no target tells them apart.
With a specular term the eye must lie in $\Pi$ as well. `symmetry_plane` finds $\Pi$ (the
points' deviations from their mean and the normals together span at most two dimensions).
Occluders and fixed lights need not be symmetric: the mirrored placement is evaluated on the
scene as it is and competes only where its $\chi^2$ is within the allowance
(`_diagnostics.rival_placements`).

The search never visits the mirror image when the given poses already explain the targets
(an exact fit ends the search before the global placement), so the report adds it:
`mirrored_rows` reflects the answer's lights and returns the parameter vector of that
placement, for the rival check to evaluate like any other.
"""

from __future__ import annotations

from typing import Any

import numpy as np

SYMMETRY_TOL = 1e-9  # the smallest singular value over the largest of the plane's test


def symmetry_plane(points: np.ndarray, normals: np.ndarray, eye: np.ndarray | None = None,
                   tol: float = SYMMETRY_TOL) -> tuple[np.ndarray, np.ndarray] | None:
    """`(point (3,), unit normal (3,))` of the plane $\\Pi$ that holds every target point
    `points (N, 3)` (m) and is parallel to every normal `normals (N, 3)` (and holds `eye (3,)`
    where given), or None when there is none (module docstring). The points are scaled by their
    extent, so the test `tol` is scale-free. Targets on a single point, or all normals parallel
    and the points on a line along them, span less than a plane: any plane through them
    would do, and none is returned (no unique mirror)."""
    p = np.asarray(points, np.float64).reshape(-1, 3)
    n = np.asarray(normals, np.float64).reshape(-1, 3)
    centre = p.mean(axis=0)
    extent = max(float(np.max(np.linalg.norm(p - centre, axis=1))), 1e-300)
    rows = [(p - centre) / extent, n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)]
    if eye is not None:
        rows.append((np.asarray(eye, np.float64).reshape(1, 3) - centre) / extent)
    _, s, vt = np.linalg.svd(np.concatenate(rows), full_matrices=True)
    if s[0] <= 0.0 or s[2] > tol * s[0] or s[1] <= tol * s[0]:
        return None
    return centre, vt[2]


def reflect(x: np.ndarray, plane: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Points `x (..., 3)` (m) reflected across `plane` (`symmetry_plane`'s `(point, normal)`)."""
    c, m = plane
    x = np.asarray(x, np.float64)
    return x - 2.0 * ((x - c) @ m)[..., None] * m


def _turn(v: np.ndarray, m: np.ndarray) -> np.ndarray:
    """A direction `v (3,)` reflected by the plane normal `m` (no translation)."""
    return v - 2.0 * (v @ m) * m


def _position_theta(param: Any, c: np.ndarray) -> np.ndarray | None:
    """The position entries of `param` (a `LightParametrisation`) that put its centre at
    `c (3,)`, or None where its constraint cannot (off its plane, outside its box)."""
    c0, s = np.asarray(param.c0, np.float64), float(np.asarray(param.scale))
    if param.constraint == "plane":
        e = np.asarray(param.plane_e, np.float64)
        z = e @ (c - c0) / s
        return z if np.allclose(c0 + s * (z @ e), c, rtol=0.0, atol=1e-9 * max(s, 1.0)) else None
    if param.constraint == "box":
        lo, hi = np.asarray(param.box_lo, np.float64), np.asarray(param.box_hi, np.float64)
        if np.any(c < lo) or np.any(c > hi):
            return None
        if param.box_map == "sigmoid":
            f = (c - lo) / (hi - lo)
            if np.any(f <= 0.0) or np.any(f >= 1.0):
                return None
            return np.log(f / (1.0 - f))
    return (c - c0) / s


def _rotation_vector(R: np.ndarray) -> np.ndarray:
    """The rotation vector (axis times angle, rad) of a rotation matrix `R (3, 3)`."""
    from scipy.spatial.transform import Rotation

    return np.asarray(Rotation.from_matrix(R).as_rotvec(), np.float64)


def mirrored_theta(param: Any, theta: np.ndarray, light: Any, plane: tuple[np.ndarray, np.ndarray]) -> np.ndarray | None:
    """The parameters `(param.size,)` of `param` (a `LightParametrisation`) that place its light
    at the mirror image of `light` (its fitted light at `theta (param.size,)`) across `plane`,
    or None where the parametrisation cannot (a constraint, a polygon whose mirror image is no
    rotation of it, a directional light: no centre to mirror). Sizes are kept (a reflection
    keeps lengths)."""
    import jaxshadow as js

    if param.kind == "directional":
        return None
    m = plane[1]
    out = np.asarray(theta, np.float64).copy()
    sl = param._slices()
    if isinstance(light, js.PolygonLight):
        v = np.asarray(light.vertices, np.float64)
        c = v.mean(axis=0)
    elif isinstance(light, js.LinearLight):
        a, b = np.asarray(light.start, np.float64), np.asarray(light.end, np.float64)
        c = 0.5 * (a + b)
    else:
        c = np.asarray(light.position, np.float64)
    c_new = reflect(c, plane)
    if "position" in sl:
        z = _position_theta(param, c_new)
        if z is None:
            return None
        out[sl["position"]] = z
    elif not np.allclose(c_new, c, rtol=0.0, atol=1e-12 * max(1.0, float(np.max(np.abs(c))))):
        return None  # its centre is held: the mirror image is out of its reach
    if "orientation" in sl:
        if isinstance(light, js.LinearLight):
            F = np.asarray(param.frame0, np.float64)
            d0 = F[2]
            d = _turn((b - a) / np.linalg.norm(b - a), m)
            axis = np.cross(d0, d)
            sin, cos = float(np.linalg.norm(axis)), float(np.clip(d0 @ d, -1.0, 1.0))
            axis = axis / sin if sin > 1e-12 else F[0]
            omega = np.arctan2(sin, cos) * axis
            out[sl["orientation"]] = F[:2] @ omega
        else:  # a polygon: the rotation (Kabsch) that takes its template to its mirror image
            w = v - c
            ref = w - 2.0 * (w @ m)[:, None] * m  # reflected offsets, winding reversed below
            R0 = np.asarray(param.frame0, np.float64)
            local = np.asarray(param.local, np.float64).copy()
            if "size" in sl:
                f = np.exp(np.asarray(theta, np.float64)[sl["size"]])
                local[:, 0] *= f[0]
                local[:, 1] *= f[1]
            w0 = local @ R0.T  # the template's offsets before the rotation
            best = None
            rev = ref[::-1]
            for shift in range(v.shape[0]):
                tgt = np.roll(rev, shift, axis=0)
                U, _, Vt = np.linalg.svd(tgt.T @ w0)
                R = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
                err = float(np.max(np.abs(w0 @ R.T - tgt)))
                if best is None or err < best[0]:
                    best = (err, R)
            if best is None or best[0] > 1e-9 * max(float(np.max(np.abs(w))), 1e-300):
                return None
            out[sl["orientation"]] = _rotation_vector(best[1])
    return out


def mirrored_rows(problem: Any, theta: np.ndarray, lights: list, with_specular: bool) -> np.ndarray:
    """`(R, n_pose)`: the answer `theta (n_pose,)` with every fitted light (`lights`, its
    fitted lights at reference power, one per `problem.params` entry) mirrored across the
    targets' symmetry plane (`symmetry_plane`; the eye in it too `with_specular`): one row, or
    none where the targets have no symmetry plane or a light's mirror image is out of its
    parametrisation's reach."""
    t = problem.targets
    eye = np.asarray(t.eye, np.float64).reshape(-1, 3)
    if with_specular and not np.allclose(eye, eye[0]):
        return np.zeros((0, problem.n_pose))
    w = np.asarray(t.weights, np.float64).reshape(len(np.asarray(t.points)), -1)
    used = np.any(w > 0, axis=1)
    if used.sum() < 2:
        return np.zeros((0, problem.n_pose))
    plane = symmetry_plane(np.asarray(t.points, np.float64)[used], np.asarray(t.normals, np.float64)[used],
                           eye[0] if with_specular else None)
    if plane is None:
        return np.zeros((0, problem.n_pose))
    row = np.asarray(theta, np.float64)[:problem.n_pose].copy()
    for j, p in enumerate(problem.params):
        if p is None:
            continue
        o = problem.offsets[j]
        new = mirrored_theta(p, row[o:o + p.size], lights[j], plane)
        if new is None:
            return np.zeros((0, problem.n_pose))
        row[o:o + p.size] = new
    if np.max(np.abs(row - np.asarray(theta, np.float64)[:problem.n_pose])) <= 1e-9 * max(1.0, float(np.max(np.abs(row)))):
        return np.zeros((0, problem.n_pose))  # every light in the plane: its own mirror image
    return row[None]
