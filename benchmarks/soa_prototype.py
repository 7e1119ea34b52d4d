r"""Prototype: the Lambert contour sum in structure-of-arrays form (a proposal, not library code).

`jaxshadow.form_factor` vmaps a per-point kernel whose data are `(K, 3)` arrays; after `vmap`
XLA:CPU sees `(N, K, 3)` tensors whose minor axis has length 3. Every `jnp.dot`/`jnp.cross`/
`jnp.roll`/`concatenate` over that axis becomes a separate `dot_general`, reduce or concatenate
that is materialised in memory (about 20 fusions of `(N, K, 3)` / `(N, K + 1, 3)` arrays for a
quad). Here the three components are separate `(N,)` arrays and the `K` edges are unrolled in
Python (K is static), so the whole computation is one elementwise loop over N that XLA fuses
into a single kernel: no intermediate array is ever written to memory.

Numerically it is the same formula as `_polygon.form_factor_kernel` (exact horizon clipping,
`atan2(|a x b|, a . b)`, the `angle_over_sin` series for tiny angles), so its values agree with
`js.form_factor` to rounding (checked in `benchmarks.run`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxshadow._misc import angle_over_sin


def _edge_term_soa(px, py, pz, nx, ny, nz, a, b):
    ax, ay, az = a[0] - px, a[1] - py, a[2] - pz
    bx, by, bz = b[0] - px, b[1] - py, b[2] - pz
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    s2 = cx * cx + cy * cy + cz * cz
    d = ax * bx + ay * by + az * bz
    return angle_over_sin(s2, d) * (nx * cx + ny * cy + nz * cz)


@jax.jit
def form_factor_soa(points, normals, verts):
    """`(N,)` unoccluded form factor of the convex polygon `verts (K, 3)`; SoA, edges unrolled."""
    px, py, pz = points[:, 0], points[:, 1], points[:, 2]
    nx, ny, nz = normals[:, 0], normals[:, 1], normals[:, 2]
    k = verts.shape[0]
    v = [(verts[i, 0], verts[i, 1], verts[i, 2]) for i in range(k)]
    ne = jnp.sum(jnp.cross(verts, jnp.roll(verts, -1, axis=0)), axis=0)
    in_front = (px - v[0][0]) * ne[0] + (py - v[0][1]) * ne[1] + (pz - v[0][2]) * ne[2] > 0
    pn = px * nx + py * ny + pz * nz
    dist = [vx * nx + vy * ny + vz * nz - pn for (vx, vy, vz) in v]
    total = jnp.zeros_like(px)
    exit_pt = [jnp.zeros_like(px)] * 3
    entry_pt = [jnp.zeros_like(px)] * 3
    any_exit = jnp.zeros(px.shape, bool)
    any_entry = jnp.zeros(px.shape, bool)
    for i in range(k):
        j = (i + 1) % k
        da, db = dist[i], dist[j]
        a_in, b_in = da >= 0, db >= 0
        crossing = a_in != b_in
        t = jnp.where(crossing, da / jnp.where(crossing, da - db, 1.0), 0.0)
        x = [v[i][c] + t * (v[j][c] - v[i][c]) for c in range(3)]
        keep = a_in | b_in
        start = [jnp.where(keep & a_in, v[i][c], jnp.where(keep, x[c], v[i][c])) for c in range(3)]
        end = [jnp.where(keep & b_in, v[j][c], jnp.where(keep, x[c], v[i][c])) for c in range(3)]
        total = total + _edge_term_soa(px, py, pz, nx, ny, nz, start, end)
        exiting = a_in & ~b_in
        entering = ~a_in & b_in
        exit_pt = [jnp.where(exiting, x[c], exit_pt[c]) for c in range(3)]
        entry_pt = [jnp.where(entering, x[c], entry_pt[c]) for c in range(3)]
        any_exit = any_exit | exiting
        any_entry = any_entry | entering
    cut = any_exit & any_entry
    cs = [jnp.where(cut, exit_pt[c], v[0][c]) for c in range(3)]
    ce = [jnp.where(cut, entry_pt[c], v[0][c]) for c in range(3)]
    total = total + _edge_term_soa(px, py, pz, nx, ny, nz, cs, ce)
    return jnp.where(in_front, -total / (2 * jnp.pi), 0.0)
