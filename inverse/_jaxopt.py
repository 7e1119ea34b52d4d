"""Every JAXopt use lives here, imported lazily (the `jaxopt` extra).

JAXopt is unmaintained and emits a DeprecationWarning on import; nothing else in `inverse`
imports it, and this module imports it only when the bounded solver (`LBFGSB`) is asked for.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from typing import Any


def _jaxopt() -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)
        warnings.simplefilter("ignore", FutureWarning)
        try:
            import jaxopt
        except ImportError as err:
            raise ImportError("inverse.LBFGSB needs the optional dependency 'jaxopt': install it with "
                              "`pip install 'jaxshadow[jaxopt]'`.") from err
    return jaxopt


def lbfgsb_solve(fun: Callable, y0: Any, lower: Any, upper: Any, maxiter: int, tol: float) -> tuple:
    """Minimise a scalar `fun(y)` subject to `lower <= y <= upper` with `jaxopt.LBFGSB`.

    Traceable (use inside `jit`/`vmap`). **Returns:** `(y, fun(y), iterations)`.
    """
    jaxopt = _jaxopt()
    solver = jaxopt.LBFGSB(fun=fun, maxiter=maxiter, tol=tol)
    out = solver.run(y0, bounds=(lower, upper))
    return out.params, out.state.value, out.state.iter_num
