r"""A batched Levenberg-Marquardt solver for many starts at once (the light-placement multistart).

Why not `optimistix.LevenbergMarquardt` under `jax.vmap`: the residual here is a soft-shadow
kernel whose forward-mode Jacobian is most of the compile and run time. Optimistix traces the
residual several times (the linearisation, the accepted-step evaluation, the termination
test), and under `vmap` its accept/reject branches become selects that evaluate both sides.
This loop evaluates the residual and its Jacobian exactly once per iteration, for all starts
together, as one `jax.jacfwd` instance in the program; the first iteration evaluates the
starts themselves (the state begins at an infinite loss), so nothing is traced twice. Starts
that have converged are frozen (masked); the loop ends when all have.

The step is the classical damped Gauss-Newton step with Marquardt's diagonal scaling (Moré,
"The Levenberg-Marquardt algorithm: implementation and theory", 1978: the running maximum of
the Jacobian's column norms) and Nielsen's update of the damping $\lambda$ (H. B. Nielsen,
"Damping parameter in Marquardt's method", IMM-REP-1999-05):

$$(J^\top J + \lambda D)\,\delta = -J^\top r,\qquad
\rho = \frac{f(y) - f(y+\delta)}{-\delta^\top J^\top r - \tfrac12 \delta^\top J^\top J \delta},$$

accepted when $\rho > 10^{-4}$; then $\lambda \leftarrow \lambda \max(\tfrac13, 1-(2\rho-1)^3)$,
$\nu = 2$, else $\lambda \leftarrow \nu\lambda$, $\nu \leftarrow 2\nu$. A start has converged
when an accepted step moved every parameter by at most `atol + rtol |y|_inf` *and* changed the
loss by at most `atol + rtol f` (the Cauchy test Optimistix uses), or when no step can
decrease the loss any more (the predicted decrease is at round-off level).

**Many starts.** With `prune` (iterations, e.g. `(4, 8, 16, 32)`), at each of those
iterations the worse half of the starts still running (by their current loss) is abandoned:
successive halving (Jamieson & Talwalkar 2016), so that one hopeless start does not keep the
whole batch running to `max_steps`. With `chunk`, the starts are evaluated `chunk` at a time
(`lax.map`), running ones first, and chunks with none running are skipped (`lax.cond`): the
cost of an iteration follows the number of starts still running instead of the batch size.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import inspect
import os
from collections.abc import Callable
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from jaxshadow.cli import ensure_default_compile_cache

# XLA:CPU options for the programs that hold the soft-shadow residual and its Jacobian (the
# light-placement fits). Their first call is dominated by XLA compiling a few hundred small
# fused loops; the legacy elemental emitter instead of the MLIR fusion emitters, and LLVM
# without its most expensive passes, compile the LM program in ~35% less time (a fit's whole
# first call is 0.69-0.81x) and the solves run as fast or faster
# (`benchmarks/results/ab/fit_compiler_options.md`). Options of the code generator only:
# IEEE arithmetic, no fast-math.
FIT_COMPILER_OPTIONS = {"xla_cpu_use_fusion_emitters": False, "xla_llvm_disable_expensive_passes": True}

# The same, with LLVM's code generation at -O0, for the programs a fit runs a handful of times
# (the colour coefficients at the answer, the specular values of the material fit, the joint
# Jacobian of the standard errors): their compilation is 2.5-3x shorter and their execution
# ~3x longer, which for them is milliseconds to a second. The LM program, the screening and
# the global placement's columns, which run for most of a fit (seconds each with three
# lights), keep `FIT_COMPILER_OPTIONS`. IEEE arithmetic at both levels; the values agree to
# rounding.
ONCE_COMPILER_OPTIONS = {**FIT_COMPILER_OPTIONS, "xla_backend_optimization_level": 0}


@contextlib.contextmanager
def gc_paused() -> Any:
    """Python's cyclic garbage collector off for the block, then as it was. Tracing, lowering
    and compiling a light fit's program allocate enough objects to set off ~100 collections
    (0.24-0.29 s of a one-start fit's first call with 8 occluders); without them the first call
    is ~10% shorter (`benchmarks/results/ab/gc_paused.md`). Nothing is leaked: what the block
    left unreachable is collected by the next collection after it."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def fit_jit(fun: Callable | None = None, *, options: dict | None = None) -> Any:
    """`equinox.filter_jit(fun)` compiled with `options` (default `FIT_COMPILER_OPTIONS`) on
    the CPU backend (other backends: the defaults); `fit_jit(options=...)` is the decorator.
    The backend is looked up at the first call, not at import. A jaxlib that does not know one
    of the options (the supported `jax` range is wide) gets the defaults instead: the first
    compile that names an option in its error is retried without them. Calls run with the
    garbage collector paused (`gc_paused`: compiling is ~10% shorter). Before its first
    compile, JAX's persistent compilation cache is turned on unless the user configured or
    declined it (`jaxshadow.cli.ensure_default_compile_cache`): a later
    process loads the program instead of compiling it."""
    if fun is None:
        return functools.partial(fit_jit, options=options)
    opts = FIT_COMPILER_OPTIONS if options is None else options
    jitted: list = []
    # key -> loaded or exported program (`_exported`), None for keys it cannot serve; False: off
    # for this function (a jaxlib that refused the options).
    exported: dict | bool = {}

    @functools.wraps(fun)
    def call(*args: Any, **kwargs: Any) -> Any:
        with gc_paused():
            return _call(*args, **kwargs)

    def _call(*args: Any, **kwargs: Any) -> Any:
        nonlocal exported
        if not jitted:
            ensure_default_compile_cache()
        if exported is not False:
            out = _exported_call(fun, opts, exported, args, kwargs)
            if out is not _NOT_EXPORTED:
                return out
        if not jitted:  # the jitted function, made once
            cpu = jax.default_backend() == "cpu" and "compiler_options" in inspect.signature(jax.jit).parameters
            if cpu:
                # `filter_jit` forwards its extra keywords to `jax.jit` (its stubs do not list them).
                fast = eqx.filter_jit(fun, compiler_options=opts)  # type: ignore[call-overload]
                try:
                    out = fast(*args, **kwargs)
                except Exception as err:  # an unknown option surfaces at the first compile
                    if not any(key in str(err) for key in opts):
                        raise
                    jitted.append(eqx.filter_jit(fun))
                    exported = False
                else:
                    jitted.append(fast)
                    return out
            else:
                jitted.append(eqx.filter_jit(fun))
        return jitted[0](*args, **kwargs)

    return call


_NOT_EXPORTED = object()


def _exported_call(fun: Callable, opts: dict, programs: Any, args: tuple, kwargs: dict) -> Any:
    """`fun(*args, **kwargs)` by its exported program (`_exported`: loaded from the store, or
    traced, exported and stored), or `_NOT_EXPORTED` when there is no store (the compilation
    cache is off), the call cannot be keyed exactly, or exporting failed: the caller then uses
    `equinox.filter_jit`."""
    from . import _exported as ex

    store = ex.store_dir()
    if store is None or jax.default_backend() != "cpu":
        return _NOT_EXPORTED
    try:
        key, leaves, treedef, arrays = ex.program_key(fun, opts, args, kwargs)
    except ex.Unsupported:
        return _NOT_EXPORTED
    if key not in programs:
        path = os.path.join(store, key + ".bin")
        prog = ex.load(path, opts) if os.path.exists(path) else None
        if prog is None:
            try:
                prog = ex.export_program(fun, opts, leaves, treedef, arrays)
            except Exception:  # not exportable (e.g. an output that is not an array): filter_jit
                prog = None
            else:
                with contextlib.suppress(OSError):
                    ex.save(path, prog)
        programs[key] = prog
    prog = programs[key]
    if prog is None:
        return _NOT_EXPORTED
    try:
        return prog([leaves[i] for i in arrays])
    except Exception as err:  # a jaxlib that does not know one of the options: filter_jit's fallback
        if not any(k in str(err) for k in opts):
            raise
        programs[key] = None
        return _NOT_EXPORTED


class LMResult(NamedTuple):
    """Per start: `values (S, P)`, `losses (S,)` ($\\tfrac12|r|^2$), `converged (S,)`,
    `num_steps (S,)`; `residuals (S, M)` and `jacobians (S, M, P)` at `values`;
    `initial_losses (S,)` at the starts; `flag` (bool
    scalar): the residual function's auxiliary flag was raised at some evaluated point (the
    light-placement fit uses it for a culling overflow); `abandoned (S,)`: stopped by `prune`;
    `aux`: what a `jacobian` callable returned beside the Jacobian, per start `(S, ...)` at
    `values` (None without one)."""

    values: Float[Array, "S P"]
    losses: Float[Array, " S"]
    converged: Bool[Array, " S"]
    num_steps: Int[Array, " S"]
    residuals: Float[Array, "S M"]
    jacobians: Float[Array, "S M P"]
    initial_losses: Float[Array, " S"]
    flag: Bool[Array, ""]
    abandoned: Bool[Array, " S"]
    aux: Any = None


def batched_levenberg_marquardt(
    fn: Callable[[Array, Any], tuple[Array, Array]],
    y0: Float[Array, "S P"],
    args: Any,
    *,
    rtol: float,
    atol: float,
    max_steps: int | Array,
    lambda0: float = 1e-3,
    prune: tuple[int, ...] | Int[Array, " K"] = (),
    chunk: int | None = None,
    num_residuals: int | None = None,
    jacobian: str | Callable[[Array, Any], tuple[Array, Array, Array]] = "linearize",
    mirror: Int[Array, " S"] | None = None,
    aux: Any = None,
) -> LMResult:
    """Minimise $\\tfrac12|r(y)|^2$ from every row of `y0` at once (traceable; jit the caller).

    **Arguments:**

    - `fn(y (P,), args) -> (r (M,), flag (bool scalar))`: the residual and a flag that is OR-ed
      over every evaluation (returned as `LMResult.flag`).
    - `y0`: `(S, P)` starting points; `args`: passed to `fn`.
    - `rtol`, `atol`: termination tolerances (module docstring); `max_steps`: iterations after
      the evaluation of the starts (an int, or an int32 scalar array so that one compiled
      program serves any count: 0 only evaluates the starts, `LMResult.initial_losses`);
      `lambda0`: initial damping relative to the scaling.
    - `prune`: iterations at which the worse half of the running starts is abandoned (module
      docstring): a tuple (static), or an int32 array padded with -1 (`prune_array`: one
      compiled program serves every schedule of that length); `chunk`: evaluate the starts this many at a time, skipping finished ones
      (None: all at once).
    - `num_residuals`: the length M of `r`, when the caller knows it (static int). Without
      it the residual is traced once more (`jax.eval_shape`) just to learn M; with the
      soft-shadow residual that extra trace was about a third of the first call's tracing.
    - `jacobian` (static): `"linearize"` (default: `jax.linearize`, then the linear map on the
      basis vectors) or `"jacfwd"` (`jax.jacfwd`, and `jax.vmap` over the starts even for one).
      The same Jacobian to round-off; the first is cheaper to trace and compile
      (`benchmarks/results/ab/lm_jacobian.md`). Or a callable `(y (P,), args) -> (r (M,),
      J (M, P), flag)` that knows the residual's structure (`_multilight`'s per-light Jacobian).
    - `mirror`: `(S,)` for each start the index of the first start equal to it (`mirror[i] <= i`;
      `duplicate_sources`), or None. A start with `mirror[i] != i` is not evaluated: it takes
      its source's residual and Jacobian at every iteration. It starts where its source does, so
      it follows the same iterates and stops at the same iteration (successive halving ranks ties
      by index: the source first), and the result is the one of evaluating it; padding rows cost
      nothing. Only with `chunk` (chunks with no evaluated start are skipped).
    - `aux`: with a `jacobian` callable that returns a fourth value `(r, J, flag, aux)`, the
      shapes and dtypes of that value for one start (a pytree of `jax.ShapeDtypeStruct`): it is
      kept for every start at its accepted point (`LMResult.aux`), e.g. quantities the
      residual was made of, for a caller that needs them at the answer without a program of its
      own. None: the callable returns three values.

    **Returns:** `LMResult`.
    """
    S, P = y0.shape
    dt = y0.dtype

    if not callable(jacobian) and jacobian not in ("linearize", "jacfwd"):
        raise ValueError(f"batched_levenberg_marquardt: jacobian must be 'linearize' or 'jacfwd', got {jacobian!r}.")

    def resid_aux(y: Array) -> tuple[Array, tuple[Array, Array]]:
        r, flag = fn(y, args)
        return r, (r, flag)

    with_aux = aux is not None
    if with_aux and not callable(jacobian):
        raise ValueError("batched_levenberg_marquardt: aux needs a jacobian callable that returns it.")

    def rj_one(y: Array) -> tuple:
        # `jax.linearize` and the linear map on the P basis vectors, not `jax.jacfwd` (a `vmap`
        # of `jvp` over the basis): the residual is traced once under `jvp` alone and only its
        # tangent equations are batched. With the soft-shadow residual the LM program traces
        # and lowers ~25% faster (`benchmarks/results/ab/lm_jacobian.md`).
        if callable(jacobian):
            return tuple(jacobian(y, args))
        if jacobian == "jacfwd":
            J, (r, flag) = jax.jacfwd(resid_aux, has_aux=True)(y)
            return r, J, flag
        r, lin, flag = jax.linearize(lambda z: fn(z, args), y, has_aux=True)
        J = jax.vmap(lin, out_axes=1)(jnp.eye(P, dtype=dt))
        return r, J, flag

    def rj_all(ys: Array) -> tuple:
        # One start (or chunks of one): no batching layer in the trace.
        if ys.shape[0] == 1 and (callable(jacobian) or jacobian == "linearize"):
            return jax.tree_util.tree_map(lambda x: x[None], rj_one(ys[0]))
        return jax.vmap(rj_one)(ys)

    def zeros(n: int) -> tuple:
        """What `rj_all` returns for `n` starts, as zeros (chunks with no start to evaluate)."""
        out = (jnp.zeros((n, M), dt), jnp.zeros((n, M, P), dt), jnp.zeros((n,), bool))
        if with_aux:
            out += (jax.tree_util.tree_map(lambda a: jnp.zeros((n, *a.shape), a.dtype), aux),)
        return out

    M = num_residuals if num_residuals is not None else jax.eval_shape(lambda y: fn(y, args)[0], y0[0]).shape[0]
    eps = jnp.finfo(dt).eps

    def rj(ys: Array, need: Array) -> tuple:
        """Residuals, Jacobians, flags (and `aux`) at `ys`; rows where `need` is False may be zeros."""
        if chunk is None or chunk >= S:
            return rj_all(ys)
        if mirror is not None:
            src = jnp.asarray(mirror, jnp.int32)
            out = rj_chunked(ys, need & (src == jnp.arange(S)))
            return jax.tree_util.tree_map(lambda x: x[src], out)
        return rj_chunked(ys, need)

    def rj_chunked(ys: Array, need: Array) -> tuple:
        assert chunk is not None
        n_chunks = -(-S // chunk)
        pad = n_chunks * chunk - S
        order = jnp.argsort(~need, stable=True)  # the needed rows first
        inv = jnp.argsort(order)
        ys_o = jnp.concatenate([ys[order], jnp.broadcast_to(ys[:1], (pad, P))])
        need_o = jnp.concatenate([need[order], jnp.zeros((pad,), bool)])

        def one(a: tuple[Array, Array]) -> tuple:
            yc, go = a
            return jax.lax.cond(go, rj_all, lambda y: zeros(chunk), yc)

        out = jax.lax.map(one, (ys_o.reshape(n_chunks, chunk, P), jnp.any(need_o.reshape(n_chunks, chunk), axis=1)))
        return jax.tree_util.tree_map(lambda x: x.reshape(-1, *x.shape[2:])[:S][inv], out)

    if isinstance(prune, (tuple, list)):
        prune_at = jnp.asarray(sorted(set(int(i) for i in prune)) or [-1], jnp.int32)
    else:  # an int32 array (traced: one program for any schedule), padded with -1
        prune_at = jnp.asarray(prune, jnp.int32).reshape(-1)

    def cond(state: tuple) -> Array:
        it, done = state[0], state[8]
        return (it <= max_steps) & ~jnp.all(done)

    def body(state: tuple) -> tuple:
        it, y, r, J, f, f0, lam, nu, done, ok, steps, dmax, flag, gone, ax = state
        init = it == 0
        g = jnp.einsum("smp,sm->sp", J, r)
        A = jnp.einsum("smp,smq->spq", J, J)
        diag = jnp.maximum(dmax, jnp.diagonal(A, axis1=1, axis2=2))
        scale = jnp.maximum(diag, eps * jnp.max(diag, axis=1, keepdims=True) + jnp.finfo(dt).tiny)
        Ad = A + (lam[:, None] * scale)[:, :, None] * jnp.eye(P, dtype=dt)[None]
        # Ad is symmetric positive definite (lam * scale > 0 on the diagonal): Cholesky, which
        # compiles to a fraction of a general LU solve. A failed factorisation (round-off) gives
        # a non-finite step: it is rejected (the damping grows), never taken for a stall.
        chol = jax.lax.linalg.cholesky(Ad, symmetrize_input=False)
        delta = -jax.lax.linalg.triangular_solve(
            chol, jax.lax.linalg.triangular_solve(chol, g[..., None], left_side=True, lower=True),
            left_side=True, lower=True, transpose_a=True)[..., 0]
        step_ok = jnp.all(jnp.isfinite(delta), axis=1)
        delta = jnp.where(step_ok[:, None] & ~init, delta, 0.0)
        y_try = y + delta
        r_t, J_t, flag_t, *ax_t = rj(y_try, ~done)
        f_t = 0.5 * jnp.sum(r_t * r_t, axis=1)
        pred = -jnp.sum(g * delta, axis=1) - 0.5 * jnp.einsum("sp,spq,sq->s", delta, A, delta)
        rho = (f - f_t) / jnp.where(pred > 0, pred, 1.0)
        finite = jnp.isfinite(f_t) & jnp.all(jnp.isfinite(J_t), axis=(1, 2))
        live = ~done
        accept = live & finite & (init | ((pred > 0) & (rho > 1e-4)))
        # Termination (never on the first, evaluation-only iteration).
        small_step = jnp.max(jnp.abs(delta), axis=1) <= atol + rtol * jnp.max(jnp.abs(y), axis=1)
        small_f = jnp.abs(f - f_t) <= atol + rtol * f
        conv = ~init & accept & small_step & small_f
        stall = ~init & live & ~accept & step_ok & (pred <= 4 * eps * f)
        dead = ~init & live & (lam > 1e16)
        bad_start = init & ~finite  # a start where the model is not finite: nothing to do
        a = accept[:, None]
        y = jnp.where(a, y_try, y)
        r = jnp.where(a, r_t, r)
        J = jnp.where(a[:, :, None], J_t, J)
        if with_aux:
            ax = jax.tree_util.tree_map(lambda new, old: jnp.where(accept.reshape(-1, *[1] * (new.ndim - 1)), new, old),
                                        ax_t[0], ax)
        f = jnp.where(accept, f_t, f)
        dmax = jnp.where(a, jnp.maximum(dmax, jnp.sum(J_t * J_t, axis=1)), dmax)
        factor = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
        lam = jnp.where(init | ~live, lam, jnp.where(accept, lam * factor, lam * nu))
        nu = jnp.where(accept, 2.0, jnp.where(live, 2.0 * nu, nu))
        f0 = jnp.where(init, f_t, f0)
        newly = conv | stall | dead | bad_start
        ok = ok | conv | stall
        steps = steps + (live & ~init).astype(steps.dtype)
        done = done | (newly & live)
        flag = flag | jnp.any(flag_t & live)
        # Successive halving: keep the better half (rounded up) of the starts still running.
        if len(prune) and S > 1:  # static: no sorting in the program otherwise
            running = ~done
            n_run = jnp.sum(running.astype(jnp.int32))
            rank = jnp.argsort(jnp.argsort(jnp.where(running, f, jnp.inf), stable=True), stable=True)
            drop = running & (rank >= (n_run + 1) // 2) & jnp.any(it == prune_at)
            done = done | drop
            gone = gone | drop
        return it + 1, y, r, J, f, f0, lam, nu, done, ok, steps, dmax, flag, gone, ax

    state = (
        jnp.zeros((), jnp.int32),
        y0,
        jnp.zeros((S, M), dt),
        jnp.zeros((S, M, P), dt),
        jnp.full((S,), jnp.inf, dt),
        jnp.full((S,), jnp.inf, dt),
        jnp.full((S,), lambda0, dt),
        jnp.full((S,), 2.0, dt),
        jnp.zeros((S,), bool),
        jnp.zeros((S,), bool),
        jnp.zeros((S,), jnp.int32),
        jnp.zeros((S, P), dt),
        jnp.zeros((), bool),
        jnp.zeros((S,), bool),
        zeros(S)[3] if with_aux else None,
    )
    _, y, r, J, f, f0, _, _, _, ok, steps, _, flag, gone, ax = jax.lax.while_loop(cond, body, state)
    return LMResult(y, f, ok, steps, r, J, f0, flag, gone, ax)


# The length `prune_array` pads a successive-halving schedule to.
PRUNE_SLOTS = 8


def prune_array(prune: tuple[int, ...]) -> Any:
    """`prune` (iterations, at most `PRUNE_SLOTS`) as `batched_levenberg_marquardt`'s traced
    schedule: an int32 NumPy array of `PRUNE_SLOTS` entries padded with -1, so that the schedule
    is an input of the compiled program and not part of its signature."""
    import numpy as np

    it = sorted(set(int(i) for i in prune))
    if len(it) > PRUNE_SLOTS:
        raise ValueError(f"prune_array: at most {PRUNE_SLOTS} pruning iterations, got {len(it)}.")
    return np.asarray(it + [-1] * (PRUNE_SLOTS - len(it)), np.int32)


def duplicate_sources(rows: Any) -> Any:
    """`(S,)` int32: for each row of `rows (S, P)` (NumPy) the index of the first row equal to it
    (`batched_levenberg_marquardt`'s `mirror`)."""
    import numpy as np

    rows = np.asarray(rows)
    _, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    return first[np.reshape(inverse, -1)].astype(np.int32)
