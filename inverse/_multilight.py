r"""Several lights at once: the residual of `fit_lights` and its Levenberg-Marquardt program.

The model (Poulin eq. 5.14, every light summed) is written with each fitted light's power as a
scale $p_j$ of its given radiance (intensity, power, irradiance):

$$L_c = k_{a,c} L_{a,c} + \frac{k_{d,c}}{\pi} \Big(E^{0}_c + \sum_j p_j E^{j}_c\Big)
      + k_{s,c} \Big(S^{0}_c + \sum_j p_j S^{j}_c\Big),$$

$E^j, S^j$ the irradiance and specular integral of fitted light $j$ at its reference power and
the pose of the parameters $\theta_j$ (soft shadows included), $E^0, S^0$ those of the lights
that are not fitted (concrete: computed once). The powers enter linearly, so they are
projected out (variable projection, Golub & Pereyra): $p$ is the weighted linear least-squares
solution shared by the three channels (the $3N \times J$ design of columns
$k_d/\pi\,E^j + k_s S^j$) at the problem's material. (A fitted material is a leaf of the
problem, updated between solves: `_fit_lights`.)

Only the poses (and, with `fit_exponent`, the Phong exponent as $\log n$) are searched. The
shadow engine runs inside the compiled program at a capacity (`jaxshadow.traced`); the
program's `mask` and `base` let one compiled program search one light (the others held at
`base`) or all of them. `fit_light` is the one-light case (`_lights._problem`): every light
solver (`_solvers`) runs this problem.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array

import jaxshadow as js

from ._forward import SpecularFn, at_capacity, irradiance_culled, irradiance_specular_culled
from ._lm import LMResult, batched_levenberg_marquardt, duplicate_sources, fit_jit, prune_array
from ._painting import painted_rows
from ._residuals import pinned
from ._targets import PaintedTargets


def scaled_light(light: Any, p: Any) -> Any:
    """`light` with its radiance / power / intensity / irradiance multiplied by `p`."""
    if isinstance(light, js.PolygonLight):
        return eqx.tree_at(lambda x: x.radiance, light, light.radiance * p)
    if isinstance(light, js.LinearLight):
        return eqx.tree_at(lambda x: x.power, light, light.power * p)
    if isinstance(light, js.PointLight):
        return eqx.tree_at(lambda x: x.intensity, light, light.intensity * p)
    return eqx.tree_at(lambda x: x.irradiance, light, light.irradiance * p)


class LightsProblem(eqx.Module):
    """What the joint residual depends on. `params[j]`: the `LightParametrisation` of fitted
    light `j` (None: only its power is fitted, `refs[j]` is the light); `offsets[j]`: where its
    parameters start in $\\theta$; `e_fixed`, `s_fixed` `(N, 3)`: the lights that are not fitted."""

    params: tuple
    refs: tuple
    scene: js.Scene  # occluders and ambient (its lights are not used)
    material: js.Material
    targets: PaintedTargets
    e_fixed: Array
    s_fixed: Array
    offsets: tuple = eqx.field(static=True)
    fit_power: bool = eqx.field(static=True)
    with_specular: bool = eqx.field(static=True)
    has_fixed: bool = eqx.field(static=True)
    specular: Any = eqx.field(static=True, default=None)
    capacity: int | None = eqx.field(static=True, default=None)
    # Painted ranges and relations (`_painting.Painting`), a power budget (W, scalar array).
    paint: Any = None
    budget: Any = None
    # The powers are parameters of the search (the last J entries of theta, p = q^2) instead of
    # projected out: with ranges or relations the residual is not linear in them.
    powers_in_theta: bool = eqx.field(static=True, default=False)
    # (J,) 1 where a fitted light is in the model, 0 where it is left out (the greedy placement
    # of `_fit_lights`: lights not placed yet do not pollute the others' search). None: all in.
    active: Any = None
    # `Outside` constraints: ((j, hull normals (F, 3), offsets (F,), margin), ...) for fitted light j.
    outside: tuple = ()
    # A projected material: the search projects out, per channel, k_a and every light's (and the
    # fixed lights') coefficient k_d p_j / pi independently (`_colour_free_rows`), not the material;
    # without `fit_power` (the powers as given: `fit_light`) one k_d (and k_s) shared by every light.
    colour_free: bool = eqx.field(static=True, default=False)
    # The Phong exponent is searched: log n is the last entry of theta (`fit_light(fit_exponent=True)`).
    fit_exponent: bool = eqx.field(static=True, default=False)

    @property
    def n_pose(self) -> int:
        """Pose parameters (the first entries of theta)."""
        return int(sum(0 if p is None else p.size for p in self.params))

    @property
    def n_theta(self) -> int:
        return self.n_pose + (len(self.params) if self.powers_in_theta else 0) + (1 if self.fit_exponent else 0)

    @property
    def n_residuals(self) -> int:
        n = 3 * int(self.targets.points.shape[0])
        n += 0 if self.paint is None else int(self.paint.pairs.shape[0])
        return n + (1 if self.powers_in_theta and self.budget is not None else 0) + len(self.outside)

    def residual(self, theta: Array) -> Array:
        """The weighted residual `(n_residuals,)` at `theta (n_theta,)`, every receiver against
        every occluder (no capacity: exact, traceable; what `OptimistixLM` and `LBFGSB` minimise)."""
        return projected_residual(theta, self, None)[0]

    def residual_and_jacobian(self, theta: Array) -> tuple[Array, Array]:
        """`(residual (M,), Jacobian (M, n_theta))` at `theta`, by one compiled program per
        problem structure (forward mode, as `residual`)."""
        return residual_and_jacobian(self, theta)

    def lights(self, theta: Array) -> list[Any]:
        """The fitted lights at `theta` (at their reference power), compiled once per structure."""
        return build_lights(self, theta)


def lights_at(theta: Array, problem: LightsProblem) -> list[Any]:
    """The fitted lights at reference power for parameters `theta (P,)` (traceable)."""
    out = []
    for j, p in enumerate(problem.params):
        if p is None:
            out.append(problem.refs[j])
        else:
            o = problem.offsets[j]
            out.append(p.build(theta[o:o + p.size]))
    return out


def one_light_scene(scene: js.Scene, light: Any) -> js.Scene:
    """`scene` (occluders, ambient) lit by `light` alone."""
    return eqx.tree_at(lambda s: s.lights, scene, (light,))


def exponent_at(theta: Array, problem: LightsProblem) -> Array:
    """The Phong exponent at `theta`: $e^{\\theta_{-1}}$ when it is searched
    (`problem.fit_exponent`), else the material's."""
    if problem.fit_exponent:
        return jnp.exp(theta[-1])
    return problem.material.exponent.astype(problem.targets.points.dtype)


def coefficient_rows(k: Array, dt: Any) -> Array:
    """A material coefficient `(3,)` as `(1, 3)`, or per receiver `(N, 3)` as is: rows that
    broadcast against `(N, 3)` values."""
    k = k.astype(dt)
    return k if k.ndim == 2 else k[None, :]


def _one_basis(light: Any, problem: LightsProblem, capacity: int | None,
               exponent: Array) -> tuple[Array, Array | None, Array]:
    """`(E (N, 3), S (N, 3) or None, overflow)` of one light at reference power."""
    t = problem.targets
    sc = one_light_scene(problem.scene, pinned(light))
    if not problem.with_specular:
        e, over = irradiance_culled(sc, t.points, t.normals, capacity)
        return e, None, over
    return irradiance_specular_culled(sc, t.points, t.normals, t.eye, exponent, problem.specular, capacity)


def same_kind_groups(lights: list) -> list[list[int]]:
    """Indices of `lights` grouped by pytree structure and leaf shapes and dtypes (first
    appearance order): the lights of one group can be stacked and run through one copy of the
    shadow engine (`jax.vmap`)."""
    groups: dict = {}
    for j, light in enumerate(lights):
        leaves, tdef = jax.tree_util.tree_flatten(light)
        key = (tdef, tuple((jnp.shape(x), jnp.result_type(x)) for x in leaves))
        groups.setdefault(key, []).append(j)
    return list(groups.values())


def basis(theta: Array, problem: LightsProblem, capacity: int | None,
          given: tuple | None = None) -> tuple[Array, Array | None, Array]:
    """`(E (J, N, 3), S (J, N, 3) or None, overflow)`: each fitted light's irradiance and
    specular integral at reference power (`jaxshadow.traced`, at `capacity`). Lights of the
    same kind and shape share one traced copy of the shadow engine (`jax.vmap` over them): the
    compiled program holds one engine per kind, not one per light. `given`: that triple, already
    computed (`structured_jacobian`): returned as is."""
    if given is not None:
        return given
    lights = lights_at(theta, problem)
    n = exponent_at(theta, problem)
    es: list = [None] * len(lights)
    ss: list = [None] * len(lights)
    over = jnp.zeros((), bool)
    for group in same_kind_groups(lights):
        if len(group) == 1:
            e, s, o = _one_basis(lights[group[0]], problem, capacity, n)
            e, s, o = e[None], None if s is None else s[None], o
        else:
            stacked = jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *(lights[j] for j in group))
            e, s, o = jax.vmap(lambda light: _one_basis(light, problem, capacity, n))(stacked)
        over = over | jnp.any(o)
        for i, j in enumerate(group):
            es[j] = e[i]
            ss[j] = None if s is None else s[i]
    return jnp.stack(es), (jnp.stack(ss) if problem.with_specular else None), over


def _lstsq(A: Array, y: Array) -> tuple[Array, Array]:
    """`(A k - y, k)` for the least-squares `k` (pseudo-inverse: differentiable)."""
    k = jnp.linalg.pinv(A) @ y
    return A @ k - y, k


def _parts(theta: Array, problem: LightsProblem, capacity: int | None,
           given: tuple | None = None) -> tuple[Array, Array, Array]:
    """`(fixed (N, 3), per_light (J, N, 3), overflow)`: the model is `fixed + sum_j p_j per_light[j]`."""
    t = problem.targets
    dt = theta.dtype
    E, S, over = basis(theta, problem, capacity, given)
    m = problem.material
    La = jnp.broadcast_to(problem.scene.ambient.astype(dt)[None, :], t.colours.shape)
    kd, ks, ka = coefficient_rows(m.kd, dt), coefficient_rows(m.ks, dt), coefficient_rows(m.ka, dt)
    ef, sf = problem.e_fixed.astype(dt), problem.s_fixed.astype(dt)
    fixed = ka * La + kd / jnp.pi * ef + (ks * sf if problem.with_specular else 0.0)
    per_light = kd[None] / jnp.pi * E + (ks[None] * S if S is not None else 0.0)  # (J, N, 3)
    if problem.active is not None:
        per_light = per_light * problem.active.astype(dt)[:, None, None]
    return fixed, per_light, over


def budget_coefficients(theta: Array, problem: LightsProblem) -> Array:
    """`(J,)` the emitted power (W) of each fitted light at its reference radiance and the pose
    `theta` (`_powers.emitted_power`): the budget is `c . p <= B`."""
    from ._powers import emitted_power

    return jnp.stack([emitted_power(light) for light in lights_at(theta, problem)]).astype(theta.dtype)


def _data_residual(theta: Array, problem: LightsProblem, capacity: int | None,
                   given: tuple | None = None) -> tuple[Array, Array]:
    """`(r, overflow)`: $\\sqrt{w}(L_{model} - C)$ `(3N,)` row-major `(N, 3)` at the problem's
    material with the powers projected out (module docstring); under a budget `B` the projection
    is the least-squares solution on the plane `c . p = B` when the free one exceeds it. With
    painted ranges or relations (`problem.powers_in_theta`) the powers are the last J entries
    `q` of `theta`, `p = q^2`, and `r` is `_painting.painted_rows` (plus, under a budget, a
    penalty row $\\sqrt{\\sum w}\\max(0, c\\cdot p / B - 1)$: the final solve keeps it exactly)."""
    t = problem.targets
    sw = jnp.sqrt(t.weights)
    if problem.colour_free and not problem.powers_in_theta:
        return _colour_free_rows(theta, problem, capacity, given)
    fixed, per_light, over = _parts(theta, problem, capacity, given)
    if problem.powers_in_theta:
        q = theta[problem.n_pose:problem.n_pose + len(problem.params)]
        p = q * q
        r = painted_rows(fixed + jnp.tensordot(p, per_light, axes=1), t.colours, sw, problem.paint)
        if problem.budget is not None:
            b = problem.budget.astype(theta.dtype)
            g = budget_coefficients(theta, problem) @ p / b - 1.0
            r = jnp.concatenate([r, jnp.sqrt(jnp.sum(t.weights))[None] * jnp.where(g > 0, g, 0.0)[None]])
        return r, over
    if not problem.fit_power:
        return painted_rows(fixed + jnp.sum(per_light, axis=0), t.colours, sw, problem.paint), over
    y = (sw * (t.colours - fixed)).reshape(-1)
    A = (sw[None] * per_light).reshape(per_light.shape[0], -1).T  # (3N, J)
    if problem.budget is None:
        return _lstsq(A, y)[0], over
    Ap = jnp.linalg.pinv(A)
    p = Ap @ y
    c = budget_coefficients(theta, problem)
    Gc = Ap @ (Ap.T @ c)  # (A^T A)^+ c
    excess = c @ p - problem.budget.astype(theta.dtype)
    p = jnp.where(excess > 0, p - Gc * excess / (c @ Gc), p)
    return A @ p - y, over


def _colour_free_rows(theta: Array, problem: LightsProblem, capacity: int | None,
                      given: tuple | None = None) -> tuple[Array, Array]:
    r"""`(r (3N,), overflow)` of the model with every coefficient free per channel $c$:

    $$L_c = a_c L_{a,c} + \sum_j b_{j,c} E^j_c / \pi + b_{0,c} E^0_c / \pi
          \; (+ \textstyle\sum_j d_{j,c} S^j_c + d_{0,c} S^0_c),$$

    $a, b, d$ projected out by linear least squares per channel. The structured model (one
    material, one power per light: $a = k_a$, $b_{j,c} = k_{d,c} p_j$, $d_{j,c} = k_{s,c} p_j$) is
    the special case, so at noise-free targets its optimum is this one's; with the material in
    the search, its product with the powers ($k_d p$: one scale per light and channel) makes a
    long curved valley that alternating material and poses stalls in, while here the poses alone
    are searched."""
    t = problem.targets
    dt = theta.dtype
    E, S, over = basis(theta, problem, capacity, given)
    if problem.active is not None:  # lights left out of the model: zero columns (pinv ignores them)
        E = E * problem.active.astype(dt)[:, None, None]
        S = None if S is None else S * problem.active.astype(dt)[:, None, None]
    cols = colour_free_columns(E, S, problem, dt)
    sw = jnp.sqrt(t.weights)  # (N, 3)
    A = jnp.stack(cols, axis=-1) * sw[:, :, None]  # (N, 3, m)
    A = jnp.moveaxis(A, 1, 0)  # (3, N, m)
    y = (sw * t.colours).T[:, :, None]  # (3, N, 1)
    k = jnp.linalg.pinv(A) @ y
    r = (A @ k - y)[:, :, 0].T  # (N, 3)
    return r.reshape(-1), over


def colour_free_columns(E: Array, S: Array | None, problem: LightsProblem, dt: Any) -> list[Array]:
    """The `(N, 3)` columns of `_colour_free_rows`: the ambient, each fitted light's $E^j/\\pi$
    and the fixed lights' $E^0/\\pi$, then (with a specular term) $S^j$ and $S^0$. Without
    `fit_power` (the powers as given) the lights share one coefficient: one column
    $(\\sum_j E^j + E^0)/\\pi$ (and $\\sum_j S^j + S^0$), whose coefficients are $k_a, k_d, k_s$."""
    n = problem.targets.points.shape[0]
    La = jnp.broadcast_to(problem.scene.ambient.astype(dt)[None, :], (n, 3))
    if not problem.fit_power:
        e = E[0] if E.shape[0] == 1 else jnp.sum(E, axis=0)
        e = e + problem.e_fixed.astype(dt) if problem.has_fixed else e
        cols = [La, e / jnp.pi]
        if S is not None:
            s = S[0] if S.shape[0] == 1 else jnp.sum(S, axis=0)
            cols.append(s + problem.s_fixed.astype(dt) if problem.has_fixed else s)
        return cols
    cols = [La, *(E[j] / jnp.pi for j in range(E.shape[0]))]
    if problem.has_fixed:
        cols.append(problem.e_fixed.astype(dt) / jnp.pi)
    if S is not None:
        cols += [S[j] for j in range(S.shape[0])] + ([problem.s_fixed.astype(dt)] if problem.has_fixed else [])
    return cols


def outside_depth(theta: Array, problem: LightsProblem) -> Array:
    """`(len(problem.outside),)` how far (m) each `Outside`-constrained light's centre is short of
    its margin outside the hull: `margin - max_f(n_f . c + b_f)` (<= 0 where it is met)."""
    out = []
    for j, A, b, margin in problem.outside:
        p = problem.params[j]
        o = problem.offsets[j]
        c = p.centre_of(theta[o:o + p.size])
        out.append(margin - jnp.max(A.astype(theta.dtype) @ c + b.astype(theta.dtype)))
    return jnp.stack(out)


def projected_residual(theta: Array, problem: LightsProblem, capacity: int | None,
                       given: tuple | None = None) -> tuple[Array, Array]:
    r"""`_data_residual` (the targets' rows) and, for every `Outside` constraint, a hinge row
    $\sqrt{\sum w}\,10^3 \max(0, \text{depth}) / s$ (depth `outside_depth`, $s$ the scene size):
    a centre 1 % of the scene size inside adds a hundred times the loss of a unit residual at
    every target. `given`: the basis at `theta`, already computed (`basis`)."""
    r, over = _data_residual(theta, problem, capacity, given)
    if not problem.outside:
        return r, over
    d = outside_depth(theta, problem)
    s = problem.params[problem.outside[0][0]].scale.astype(theta.dtype)
    rows = jnp.sqrt(jnp.sum(problem.targets.weights)) * 1e3 * jnp.where(d > 0, d, 0.0) / s
    return jnp.concatenate([r, rows.astype(r.dtype)]), over


def structured_residual(theta: Array, problem: LightsProblem, powers: Array, material: js.Material) -> Array:
    """$\\sqrt{w}(L_{model} - C)$ `(3N,)` at given powers `(J,)` and material (no projection; the
    shadow engine at `problem.capacity`, which the solve checked): the report's Jacobian in $\\theta$."""
    return _structured(theta, problem, powers, material)[0]


def _structured(theta: Array, problem: LightsProblem, powers: Array, material: js.Material) -> tuple:
    """`(structured_residual, (E, S or zeros))`: the rows and the basis they were made of."""
    t = problem.targets
    dt = theta.dtype
    E, S, _ = basis(theta, problem, problem.capacity)
    p = powers.astype(dt)[:, None, None]
    La = problem.scene.ambient.astype(dt)[None, :]
    e = problem.e_fixed.astype(dt) + jnp.sum(p * E, axis=0)
    model = coefficient_rows(material.ka, dt) * La + coefficient_rows(material.kd, dt) / jnp.pi * e
    if S is not None:
        model = model + coefficient_rows(material.ks, dt) * (problem.s_fixed.astype(dt) + jnp.sum(p * S, axis=0))
    rows = painted_rows(model, t.colours, jnp.sqrt(t.weights), problem.paint)
    return rows, (E, jnp.zeros_like(E) if S is None else S)


@fit_jit
def report_parts(problem: LightsProblem, theta: Array, powers: Array, material: js.Material) -> tuple:
    """`(E, S, J_theta (3N, P))` at `theta`: the basis and the structured residual's Jacobian,
    from one linearisation (`jax.linearize`, the tangent map on the P basis vectors, as the
    solver's Jacobian): the shadow engine is traced once, its primal shared by E, S and J. A
    program of its own, for the projected material's alternation and `design_targets`;
    `fit_lights`' report takes the same from its LM program (`_basis_rows`)."""
    rows, lin, (E, S) = jax.linearize(lambda th: _structured(th, problem, powers, material), theta, has_aux=True)
    J = jax.vmap(lin, out_axes=1)(jnp.eye(theta.shape[0], dtype=theta.dtype))
    return E, S, J


@fit_jit
def build_lights(problem: LightsProblem, theta: Array) -> list[Any]:
    """The fitted lights at reference power, compiled once per problem structure."""
    return lights_at(theta, problem)


@fit_jit
def residual_and_jacobian(problem: LightsProblem, theta: Array) -> tuple[Array, Array]:
    """`LightsProblem.residual_and_jacobian`: the residual with no capacity and its forward-mode
    Jacobian."""
    def fn(th: Array) -> Array:
        return projected_residual(th, problem, None)[0]

    return fn(theta), jax.jacfwd(fn)(theta)


@fit_jit
def loss_at(problem: LightsProblem, theta: Array) -> Array:
    """$\\tfrac12|r|^2$ of `LightsProblem.residual` at `theta`."""
    r = projected_residual(theta, problem, None)[0]
    return 0.5 * jnp.sum(r * r)


def _own_columns(problem: LightsProblem, j: int) -> list[int]:
    """The entries of $\\theta$ light `j`'s basis depends on: its pose's, and $\\log n$ when the
    exponent is searched and there is a specular term."""
    p = problem.params[j]
    cols = [] if p is None else list(range(problem.offsets[j], problem.offsets[j] + p.size))
    if problem.fit_exponent and problem.with_specular:
        cols.append(problem.n_theta - 1)
    return cols


def structured_jacobian(theta: Array, problem: LightsProblem, capacity: int | None,
                        with_basis: bool = False) -> tuple:
    r"""`(r (M,), J (M, P), overflow)` of `projected_residual` at `theta`, by its structure: each
    light's basis (`_one_basis`: the shadow engine) depends only on its own parameters
    (`_own_columns`), so its tangents are taken along those alone (`jax.linearize`, the linear
    map on their basis vectors), and the rest of the residual (the projection of the powers or
    the material, the painted rows, the constraints' rows), cheap, is linearised in the basis
    and $\theta$ and applied to every column. `jax.linearize` of the whole residual on the P
    basis vectors (`_lm`'s default) sends all P tangents through every light's engine: with
    several lights most of them are zero. The same Jacobian to round-off. Lights of one kind share
    one traced copy of the engine in `basis` (compile time): when some do, the whole residual is
    linearised instead. `with_basis`: also `(E (J, N, 3), S (J, N, 3) or None, dE (P, J, N, 3),
    dS or None)`, the basis the residual was made of and its tangents (a fourth value)."""
    dt = theta.dtype
    if any(len(g) > 1 for g in same_kind_groups(lights_at(theta, problem))):
        if with_basis:
            return linearised_with_basis(theta, problem, capacity)
        r, lin, over = jax.linearize(lambda th: projected_residual(th, problem, capacity), theta, has_aux=True)
        return r, jax.vmap(lin, out_axes=1)(jnp.eye(theta.shape[0], dtype=dt)), over
    P = theta.shape[0]
    J = len(problem.params)
    N = problem.targets.points.shape[0]
    spec = problem.with_specular
    Es, Ss, over = [], [], jnp.zeros((), bool)
    dE = jnp.zeros((P, J, N, 3), dt)
    dS = jnp.zeros((P, J, N, 3), dt) if spec else None
    for j in range(J):
        cols = _own_columns(problem, j)
        idx = jnp.asarray(cols, jnp.int32)

        def one(z: Array, j: int = j, idx: Array = idx) -> tuple[tuple[Array, Array], Array]:
            th = theta.at[idx].set(z) if z.shape[0] else theta
            e, sp, o = _one_basis(lights_at(th, problem)[j], problem, capacity, exponent_at(th, problem))
            return (e, jnp.zeros_like(e) if sp is None else sp), o

        if cols:
            (e, sp), lin, o = jax.linearize(one, theta[idx], has_aux=True)
            de, ds = jax.vmap(lin)(jnp.eye(len(cols), dtype=dt))
            dE = dE.at[idx, j].set(de)
            if dS is not None:
                dS = dS.at[idx, j].set(ds)
        else:
            (e, sp), o = one(theta[:0])
        Es.append(e)
        Ss.append(sp)
        over = over | o
    E = jnp.stack(Es)
    S = jnp.stack(Ss) if spec else None

    def rest(E: Array, S: Array | None, th: Array) -> Array:
        return projected_residual(th, problem, capacity, given=(E, S, over))[0]

    if S is None:
        r, lin = jax.linearize(lambda E, th: rest(E, None, th), E, theta)
        Jt = jax.vmap(lin)(dE, jnp.eye(P, dtype=dt))
    else:
        r, lin = jax.linearize(rest, E, S, theta)
        Jt = jax.vmap(lin)(dE, dS, jnp.eye(P, dtype=dt))
    if with_basis:
        return r, Jt.T, over, (E, S, dE, dS)
    return r, Jt.T, over


def linearised_with_basis(theta: Array, problem: LightsProblem, capacity: int | None) -> tuple:
    """`(r (M,), J (M, P), overflow, (E, S or None, dE, dS or None))` of `projected_residual` at
    `theta` by one linearisation of the whole residual with the basis (`basis`) as further
    outputs: its tangents `(P, J, N, 3)` on the P basis vectors come from the same linear map."""
    def parts(z: Array) -> tuple:
        E, S, over = basis(z, problem, capacity)
        r, _ = projected_residual(z, problem, capacity, given=(E, S, over))
        return (r, E, S), over

    (r, E, S), lin, over = jax.linearize(parts, theta, has_aux=True)
    Jr, dE, dS = jax.vmap(lin, out_axes=(1, 0, 0))(jnp.eye(theta.shape[0], dtype=theta.dtype))
    return r, Jr, over, (E, S, dE, dS)


def _lm_impl(problem: LightsProblem, starts: Array, base: Array, mask: Array, rtol: float, atol: float,
             max_steps: Array, prune: Array, chunk: int | None, mirror: Array, keep_basis: bool = False) -> LMResult:
    """Batched LM (`_lm`) on the projected residual, searching only where `mask` (the other
    parameters held at `base`): one program serves each light's multistart and the joint
    refinement. `mirror`: `duplicate_sources` of the starts (a repeated start is solved once).
    `keep_basis` (static): `LMResult.aux = (E, S or None, dE, dS or None)` at every start's
    accepted point, the basis `(J, N, 3)` and its tangents `(P, J, N, 3)` (zero where `mask` is
    off): what `fit_lights`' report needs at the answer, from this program (`_basis_rows`)."""
    def fn(th: Array, args: tuple) -> tuple[Array, Array]:
        pr, b, m = args
        return projected_residual(jnp.where(m, th, b), pr, pr.capacity)

    def searched_only(jac: Any) -> Any:
        """`jac(theta, problem)` (`(r, J, overflow[, (E, S, dE, dS)])`) at the searched
        parameters (`mask`; the others at `base`), its Jacobian and tangents zero elsewhere."""
        def rj(th: Array, args: tuple) -> tuple:
            pr, b, m = args
            out = jac(jnp.where(m, th, b), pr)
            mj = m.astype(out[1].dtype)
            head = (out[0], out[1] * mj[None, :], out[2])
            if len(out) == 3:
                return head
            E, S, dE, dS = out[3]
            masked = lambda d: None if d is None else d * mj[:, None, None, None]  # noqa: E731
            return (*head, (E, S, masked(dE), masked(dS)))
        return rj

    rj = searched_only(lambda th, pr: structured_jacobian(th, pr, pr.capacity, with_basis=keep_basis))
    rj_whole = searched_only(lambda th, pr: linearised_with_basis(th, pr, pr.capacity))

    # The per-light Jacobian where it saves work and was checked against the whole residual's:
    # several lights of distinct kinds, powers projected (not the per-channel colour-free model,
    # whose projection is ill-conditioned enough that the two differ at ~1e-5 relative).
    lights = lights_at(starts[0], problem)
    structured = (len(lights) > 1 and not problem.colour_free
                  and all(len(g) == 1 for g in same_kind_groups(lights)))
    aux = None
    if keep_basis:
        dt, P, N, J = starts.dtype, starts.shape[1], problem.targets.points.shape[0], len(problem.params)
        b = jax.ShapeDtypeStruct((J, N, 3), dt)
        d = jax.ShapeDtypeStruct((P, J, N, 3), dt)
        spec = problem.with_specular
        aux = (b, b if spec else None, d, d if spec else None)
    return batched_levenberg_marquardt(fn, starts, (problem, base, mask), rtol=rtol, atol=atol,
                                       max_steps=max_steps, prune=prune, chunk=chunk,
                                       num_residuals=problem.n_residuals, mirror=mirror,
                                       jacobian=rj if structured else rj_whole if keep_basis else "linearize",
                                       aux=aux)


_lm = fit_jit(_lm_impl)


def solve(problem: LightsProblem, starts: np.ndarray, base: np.ndarray, mask: np.ndarray, *, rtol: float,
          atol: float, max_steps: int, prune: tuple[int, ...],
          keep_basis: bool = True) -> tuple[LMResult, LightsProblem, int]:
    """`_lm` from `starts (S, P)` (one start a chunk; repeated starts, e.g. padding, solved once:
    the same result), solved again with twice the shadow capacity while some receiver overflowed
    it (exact). `keep_basis`: the program that also keeps the basis at the answer (`_lm_impl`;
    `fit_lights`' one program for the search and the report); False: without (`fit_light`'s).
    Returns `(result, problem used, retries)`."""
    dt = problem.targets.points.dtype
    mirror = jax.device_put(duplicate_sources(np.asarray(starts, dt)))
    sched = prune_array(prune)  # traced: every stage's schedule runs the same program

    def run(pr: LightsProblem) -> tuple[LMResult, Any]:
        res = _lm(pr, jax.device_put(np.asarray(starts, dt)), jax.device_put(np.asarray(base, dt)),
                  jax.device_put(np.asarray(mask)), rtol, atol,
                  np.asarray(max_steps, np.int32), sched, 1, mirror, keep_basis)
        return res, res.flag

    return at_capacity(run, problem, "fit_lights", "solve")


def _screen_impl(problem: LightsProblem, rows: Array, base: Array, mask: Array) -> tuple[Array, Array]:
    """`(losses (S,), overflow)`: $\tfrac12|r|^2$ of the projected residual at every row (the
    others held at `base` where `mask` is off), one row at a time: no Jacobian (the solver's
    program with no iterations computes one at every start)."""
    def one(th: Array) -> tuple[Array, Array]:
        r, over = projected_residual(jnp.where(mask, th, base), problem, problem.capacity)
        return 0.5 * jnp.sum(r * r), over

    f, over = jax.lax.map(one, rows)
    return f, jnp.any(over)


_screen = fit_jit(_screen_impl)


def screen(problem: LightsProblem, rows: np.ndarray, base: np.ndarray, mask: np.ndarray,
           chunk: int) -> tuple[np.ndarray, LightsProblem, int]:
    """The losses (`LMResult.initial_losses` of `solve` with no iterations) at `rows (S, P)`,
    `chunk` rows a call (one compiled program for any S), again with twice the shadow capacity
    while some receiver overflowed it: the vectorised solvers' screening (`_solvers`; `fit_lights`
    and `LM` screen by their LM program, `_solvers.screen_by_solver`). Returns `(losses (S,),
    problem used, retries)`."""
    dt = problem.targets.points.dtype

    def run(pr: LightsProblem) -> tuple[np.ndarray, bool]:
        out, over = [], False
        for a in range(0, rows.shape[0], chunk):
            part = rows[a:a + chunk]
            part = np.concatenate([part, np.repeat(part[:1], chunk - part.shape[0], axis=0)])
            f, o = _screen(pr, jax.device_put(np.asarray(part, dt)), jax.device_put(np.asarray(base, dt)),
                           jax.device_put(np.asarray(mask)))
            out.append(np.asarray(f))
            over = over or bool(o)
        return np.concatenate(out)[: rows.shape[0]], over

    return at_capacity(run, problem, "fit_lights", "screening")


def fixed_contribution(scene: js.Scene, targets: PaintedTargets, material: js.Material, fixed: list[Any],
                       specular: SpecularFn | None, with_specular: bool) -> tuple[Array, Array]:
    """`(E0, S0)` `(N, 3)` of the lights that are not fitted (the public entry points: concrete)."""
    t = targets
    dt = t.points.dtype
    if not fixed:
        z = jnp.zeros(t.points.shape, dt)
        return z, z
    sc = eqx.tree_at(lambda s: s.lights, scene, tuple(fixed))
    e = js.irradiance(sc, t.points, t.normals)
    if not with_specular:
        return e, jnp.zeros_like(e)
    eyes = jnp.broadcast_to(t.eye, t.points.shape)
    fn = js.specular if specular is None else specular
    return e, fn(sc, t.points, t.normals, eyes, material.exponent.astype(dt))
