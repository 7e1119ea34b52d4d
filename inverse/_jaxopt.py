"""Every JAXopt use lives here, imported lazily.

JAXopt is unmaintained and emits a DeprecationWarning on import; nothing else in `inverse`
imports it, and this module imports it only when the bounded solver is asked for.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any


def _jaxopt() -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        import jaxopt
    return jaxopt


def lbfgsb_solve(fun: Callable, y0: Any, lower: Any, upper: Any, maxiter: int, tol: float) -> tuple:
    """Minimise a scalar `fun(y)` subject to `lower <= y <= upper` with `jaxopt.LBFGSB`.

    Traceable (use inside `jit`/`vmap`). **Returns:** `(y, fun(y), iterations)`.
    """
    jaxopt = _jaxopt()
    solver = jaxopt.LBFGSB(fun=fun, maxiter=maxiter, tol=tol)
    out = solver.run(y0, bounds=(lower, upper))
    return out.params, out.state.value, out.state.iter_num


def levenberg_marquardt_solve(residual: Callable, y0: Any, maxiter: int, tol: float) -> tuple:
    """`jaxopt.LevenbergMarquardt` on a pytree parameter: JAXopt's LM takes flat arrays
    only, so the pytree is flattened with `jax.flatten_util.ravel_pytree` and rebuilt.

    **Returns:** `(y, 0.5 |residual(y)|^2, iterations)`.
    """
    from jax.flatten_util import ravel_pytree

    jaxopt = _jaxopt()
    flat0, unravel = ravel_pytree(y0)
    solver = jaxopt.LevenbergMarquardt(residual_fun=lambda f: residual(unravel(f)), maxiter=maxiter,
                                       tol=tol)
    out = solver.run(flat0)
    return unravel(out.params), out.state.value, out.state.iter_num
