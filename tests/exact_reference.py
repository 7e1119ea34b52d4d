r"""Exact reference for shadows of a few dozen triangles under a polygon light.

The float64 inputs are taken as the exact rationals they are (`fractions.Fraction`), and every
step up to the visible region's vertices is exact:

1. the light polygon clipped to the receiver's closed upper half-space `n . (x - p) >= 0`
   (horizon clipping), `R`;
2. the documented on-surface rule (`docs/design.md`, "Receivers on occluding surfaces"): a face
   whose plane is closer to `p` than `tol S` (`S` the largest coordinate magnitude of its vertices
   and `p`; `tol` `2^-18` for a face of float32 values, `2^-44` for other faces) blocks nothing,
   decided here in exact arithmetic;
3. every other triangle clipped to the lit side of the light's plane and to the pyramid from `p`
   over `R` (the part between the receiver and the light, above its horizon; the same region as
   `test_clip.reference_ff`'s clipping to the emitter plane and a pyramid around the emitter),
   then projected centrally from `p` onto the light's plane;
4. `R` minus the union of those projections: convex pieces, each cut by the half-planes of each
   projected triangle's edges.

The form factor of the visible pieces is Lambert's contour sum
$F = \frac{1}{2\pi} \sum_i \gamma_i \, n \cdot (a_{i+1} \times a_i) / |a_{i+1} \times a_i|$ over their
edges ($a_i$ the exact vectors from `p` to the vertices, $\gamma_i$ the angle between them), with
the cross and dot products exact and only the square roots, `atan2` and the quotients in mpmath
at `DIGITS` significant digits. The pieces share edges; their terms cancel in exact arithmetic
and leave 50-digit rounding, so the returned double is the exact value correctly rounded up to
a few units in the last place of a 50-digit sum of at most a few thousand terms.
Radiometry as `js.irradiance`: `E = pi L F`; `irradiance` returns `pi F` (`L = 1`).

Shares no code with the engine nor with `test_clip.reference_ff`.
"""

from __future__ import annotations

from collections.abc import Sequence
from fractions import Fraction

import mpmath
import numpy as np

DIGITS = 50
ON_SURFACE = Fraction(1, 2**18)
ON_SURFACE_64 = Fraction(1, 2**44)

Vec = tuple[Fraction, Fraction, Fraction]
Pt2 = tuple[Fraction, Fraction]


def _q(x: Sequence[float]) -> Vec:
    a, b, c = (Fraction(float(t)) for t in x)
    return (a, b, c)


def _sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a: Vec, b: Vec) -> Fraction:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _lerp(a: Vec, b: Vec, t: Fraction) -> Vec:
    return (a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]), a[2] + t * (b[2] - a[2]))


def clip3(poly: list[Vec], m: Vec, o: Vec) -> list[Vec]:
    """The part of the convex polygon `poly` with `m . (x - o) >= 0` (Sutherland-Hodgman, exact)."""
    out: list[Vec] = []
    k = len(poly)
    s = [_dot(m, _sub(x, o)) for x in poly]
    for i in range(k):
        j = (i + 1) % k
        if s[i] >= 0:
            out.append(poly[i])
        if (s[i] > 0 and s[j] < 0) or (s[i] < 0 and s[j] > 0):
            out.append(_lerp(poly[i], poly[j], s[i] / (s[i] - s[j])))
    return out


def _area2(poly: list[Pt2]) -> Fraction:
    k = len(poly)
    return sum((poly[i][0] * poly[(i + 1) % k][1] - poly[(i + 1) % k][0] * poly[i][1] for i in range(k)), Fraction(0))


def _clip2(poly: list[Pt2], a: Pt2, b: Pt2, keep_left: bool) -> list[Pt2]:
    """The part of the convex polygon `poly` left of the line a -> b (or right, closed)."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    s = [dx * (y - a[1]) - dy * (x - a[0]) for x, y in poly]
    if not keep_left:
        s = [-t for t in s]
    out: list[Pt2] = []
    k = len(poly)
    for i in range(k):
        j = (i + 1) % k
        if s[i] >= 0:
            out.append(poly[i])
        if (s[i] > 0 and s[j] < 0) or (s[i] < 0 and s[j] > 0):
            t = s[i] / (s[i] - s[j])
            out.append((poly[i][0] + t * (poly[j][0] - poly[i][0]), poly[i][1] + t * (poly[j][1] - poly[i][1])))
    return out


def _clean(poly: list[Pt2]) -> list[Pt2]:
    """Without repeated consecutive vertices; empty if it has no area."""
    out: list[Pt2] = []
    for x in poly:
        if not out or out[-1] != x:
            out.append(x)
    while len(out) > 1 and out[0] == out[-1]:
        out.pop()
    return out if len(out) >= 3 and _area2(out) != 0 else []


def _box(poly: list[Pt2]) -> tuple[Fraction, Fraction, Fraction, Fraction]:
    xs, ys = [x for x, _ in poly], [y for _, y in poly]
    return min(xs), min(ys), max(xs), max(ys)


def subtract(pieces: list[list[Pt2]], hole: list[Pt2]) -> list[list[Pt2]]:
    """Convex counter-clockwise `pieces` minus the convex counter-clockwise polygon `hole`, as
    convex counter-clockwise pieces: a piece's part right of the hole's first edge, its part left
    of it and right of the second, and so on; the part left of every edge is removed."""
    hb = _box(hole)
    out = []
    k = len(hole)
    for piece in pieces:
        pb = _box(piece)
        if pb[2] <= hb[0] or hb[2] <= pb[0] or pb[3] <= hb[1] or hb[3] <= pb[1]:
            out.append(piece)
            continue
        rest = piece
        for i in range(k):
            outside = _clean(_clip2(rest, hole[i], hole[(i + 1) % k], keep_left=False))
            if outside:
                out.append(outside)
            rest = _clean(_clip2(rest, hole[i], hole[(i + 1) % k], keep_left=True))
            if not rest:
                break
    return out


def _is_float32(x: np.ndarray) -> bool:
    return bool(np.all(x.astype(np.float32).astype(np.float64) == x))


def on_surface(p: np.ndarray, tri: np.ndarray) -> bool:
    """The documented on-surface rule, exactly: the distance from `p` to the plane of `tri (3, 3)`
    is below `tol S`."""
    v = [_q(x) for x in tri]
    nrm = _cross(_sub(v[1], v[0]), _sub(v[2], v[0]))
    h = _dot(nrm, _sub(_q(p), v[0]))
    s = Fraction(float(max(np.abs(tri).max(), np.abs(p).max())))
    tol = ON_SURFACE if _is_float32(np.asarray(tri, np.float64)) else ON_SURFACE_64
    return h * h < tol * tol * s * s * _dot(nrm, nrm)


def newell(poly: list[Vec]) -> Vec:
    """The exact Newell normal of a polygon (right-hand rule of its vertex order)."""
    k = len(poly)
    c = [_cross(poly[i], poly[(i + 1) % k]) for i in range(k)]
    return (sum((x[0] for x in c), Fraction(0)), sum((x[1] for x in c), Fraction(0)), sum((x[2] for x in c), Fraction(0)))


def visible_region(light: np.ndarray, tris: np.ndarray, p: np.ndarray, n: np.ndarray) -> tuple[list[list[Vec]], Vec]:
    """The visible part of the light polygon `light (k, 3)` seen from `p (3,)` with normal
    `n (3,)` (not necessarily unit) past the triangles `tris (m, 3, 3)`: exact convex pieces in
    3-D (on the light's plane, all with the light's orientation), and `p` as a rational vector.
    None where `p` is not in front of the light (it emits towards its normal, the right-hand rule
    of its vertex order)."""
    em = [_q(x) for x in np.asarray(light, np.float64)]
    P, N = _q(p), _q(n)
    ne = newell(em)
    if any(_dot(ne, _sub(x, em[0])) != 0 for x in em):
        raise ValueError("the light's vertices are not exactly coplanar")
    hp = _dot(ne, _sub(P, em[0]))
    if hp <= 0:  # behind the light, or in its plane: it emits towards its normal only
        return [], P
    region = clip3(em, N, P)
    # 2-D coordinates on the light's plane: drop the axis of the normal's largest component.
    ax = max(range(3), key=lambda i: abs(ne[i]))
    keep = [i for i in range(3) if i != ax]
    c0 = _dot(ne, em[0])

    def to2(x: Vec) -> Pt2:
        return (x[keep[0]], x[keep[1]])

    def to3(u: Pt2) -> Vec:
        out = [Fraction(0)] * 3
        out[keep[0]], out[keep[1]] = u
        out[ax] = (c0 - ne[keep[0]] * u[0] - ne[keep[1]] * u[1]) / ne[ax]
        return (out[0], out[1], out[2])

    r2 = _clean([to2(x) for x in region])
    if not r2:
        return [], P
    flip = _area2(r2) < 0
    if flip:
        r2 = r2[::-1]
    r3 = [to3(u) for u in r2]
    centre = tuple(sum(x[i] for x in r3) / len(r3) for i in range(3))
    planes = []
    for i in range(len(r3)):
        m = _cross(_sub(r3[i], P), _sub(r3[(i + 1) % len(r3)], P))
        if _dot(m, _sub(centre, P)) < 0:  # type: ignore[arg-type]
            m = (-m[0], -m[1], -m[2])
        planes.append(m)
    holes = []
    for tri in np.asarray(tris, np.float64).reshape(-1, 3, 3):
        if on_surface(p, tri):
            continue
        poly = clip3([_q(x) for x in tri], ne, em[0])
        for m in planes:
            if len(poly) < 3:
                break
            poly = clip3(poly, m, P)
        if len(poly) < 3:
            continue
        proj = []
        for x in poly:
            d = _sub(x, P)
            t = -hp / _dot(ne, d)
            proj.append(to2((P[0] + t * d[0], P[1] + t * d[1], P[2] + t * d[2])))
        h = _clean(proj)
        if not h:
            continue
        holes.append(h if _area2(h) > 0 else h[::-1])
    holes.sort(key=lambda h: -_area2(h))
    pieces = [r2]
    for h in holes:
        pieces = subtract(pieces, h)
        if not pieces:
            break
    return [[to3(u) for u in (pc[::-1] if flip else pc)] for pc in pieces], P


def _mp(x: Fraction) -> mpmath.mpf:
    return mpmath.mpf(x.numerator) / x.denominator


def lambert(p: Vec, n: Vec, poly: list[Vec]) -> mpmath.mpf:
    """$2\\pi F$ of the polygon `poly` (exact 3-D vertices, either orientation gives the sign)
    seen from `p` with the normal `n` (not normalised here), at the current mpmath precision."""
    total = mpmath.mpf(0)
    k = len(poly)
    for i in range(k):
        a, b = _sub(poly[i], p), _sub(poly[(i + 1) % k], p)
        c = _cross(b, a)
        cc = _dot(c, c)
        if cc == 0:
            continue
        s = mpmath.sqrt(_mp(cc))
        total += mpmath.atan2(s, _mp(_dot(a, b))) * _mp(_dot(n, c)) / s
    return total


def irradiance(light: np.ndarray, tris: np.ndarray, p: np.ndarray, n: np.ndarray) -> float:
    """`pi F` (E for radiance 1, as `js.irradiance`) of the part of the polygon light
    `light (k, 3)` that `p (3,)` with normal `n (3,)` sees past the triangles `tris (m, 3, 3)`,
    correctly rounded to float64 from a `DIGITS`-digit evaluation of the exact visible region."""
    pieces, P = visible_region(light, tris, p, n)
    if not pieces:
        return 0.0
    with mpmath.workdps(DIGITS):
        N = _q(n)
        nn = mpmath.sqrt(_mp(_dot(N, N)))
        total = sum((lambert(P, N, pc) for pc in pieces), mpmath.mpf(0))
        return float(total / (2 * nn))


def irradiance_many(light: np.ndarray, tris: np.ndarray, p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """`irradiance` at each receiver of `p (N, 3)`, `n (N, 3)`."""
    return np.array([irradiance(light, tris, x, y) for x, y in zip(np.asarray(p, np.float64),
                                                                     np.asarray(n, np.float64), strict=True)])
