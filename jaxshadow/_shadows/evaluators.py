r"""One front door to the shadow engine: receivers checked once, an evaluator chosen once.

The public entry points (`jaxshadow.irradiance`, `specular`, `shade`) and the traced model
(`jaxshadow.traced`) build `Receivers` at their entrance (checked, normals made unit, the
concrete values kept when they are known) and pick one evaluator for a scene, an integrand and
those receivers (`choose`):

- `HostEngine`: every input concrete, nothing differentiated: the engine plans and decodes on
  the host, JAX integrates (`plan.host_values`).
- `Planned`: the inputs carry derivatives but their values are known (an eager `jax.grad`):
  the engine plans from the values, JAX decodes and differentiates (`plan.planned_values`).
- `TracedEngine(capacity)`: the values are abstract (inside `jax.jit` / `jax.vmap`): the engine
  runs inside the compiled program with a static capacity (`compiled.traced_values`).
- `DeviceKernels`: no engine: every receiver clipped against every occluder in JAX
  (`compiled.device_values`).

Each is called as `evaluator(scene, integrand, receivers) -> (values (N, 3), overflow)`;
`overflow` says some receiver needed more than the capacity: a bool array for `TracedEngine`,
`False` for the others (they have no capacity). The integrand (`integrands.Lambert`, `integrands.Phong`) declares what the
engine must produce for it; no flag rides beside the data.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import equinox as eqx
import jax
import numpy as np

from .._core.geometry import check_values_eagerly, inputs_ok, raise_if_bad
from .._core.misc import unit_rows, unit_rows_host
from .._scene.model import Scene
from .compiled import device_values, traced_values
from .options import ShadowOptions
from .plan import host_values, planned_values


def _is_traced(tree: Any) -> bool:
    return any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(tree))


def _value_of(x: Any) -> Any:
    """`x` as a NumPy array when its value is known (concrete, or a tracer of an eager
    `jax.grad`/`jax.jacfwd` that carries its primal), else None."""
    if not isinstance(x, jax.core.Tracer):
        return np.asarray(x)
    try:
        return np.asarray(jax.extend.core.concrete_or_error(None, x))
    except jax.errors.ConcretizationTypeError:
        return None


def known_values(tree: Any) -> Any:
    """`tree` with every array leaf replaced by its NumPy value, or None if one is abstract."""
    leaves, treedef = jax.tree_util.tree_flatten(tree)
    vals = []
    for leaf in leaves:
        v = _value_of(leaf) if isinstance(leaf, (jax.Array, np.ndarray, jax.core.Tracer)) else leaf
        if v is None:
            return None
        vals.append(v)
    return jax.tree_util.tree_unflatten(treedef, vals)


@jax.jit
def _checked_unit_rows(points: Any, normals: Any) -> tuple[Any, Any]:
    """`inputs_ok(points, normals)` and `unit_rows(normals)` (as `unit_rows_host` computes them)."""
    return inputs_ok(points, normals), unit_rows(normals)


@dataclass(frozen=True)
class Receivers:
    """Receivers as the evaluators take them, built once at the entrance (`receivers`).

    - `points`: `(N, 3)` as given (NumPy, JAX or traced); `normals`: `(N, 3)` unit (JAX);
      `eyes`: `(N, 3)` eye per receiver, or None (the entry point has none: `irradiance`).
    - `values`: `(points, unit normals, eyes)` as NumPy arrays when their values are known
      (concrete, or carried by an eager `jax.grad`'s tracers; eyes None when there are none or
      they are traced), else None.
    - `ok`: for abstract values, the traced flag `inputs_ok` (finite, no zero normal) that the
      caller turns into a run-time error; None when the values were checked on the host.
    - `concrete`: points and normals are plain arrays (no tracer).
    """

    points: Any
    normals: Any
    eyes: Any
    values: tuple[np.ndarray, np.ndarray, np.ndarray | None] | None
    ok: Any
    concrete: bool

    @property
    def dtype(self) -> Any:
        return self.points.dtype

    def eyes_for(self, integ: Any) -> Any:
        """The eyes `integ` is given: `(N, 3)` when it reads an eye (`integ.reads_eye`), else
        None (`Lambert`: nothing rides beside the points)."""
        if not integ.reads_eye:
            return None
        if self.eyes is None:
            raise ValueError(f"{type(integ).__name__} reads an eye per receiver; none was given.")
        return self.eyes

    def eye_values_for(self, integ: Any) -> np.ndarray | None:
        """`eyes_for(integ)`'s NumPy values (`values` known)."""
        assert self.values is not None
        e = self.values[2]
        if integ.reads_eye and e is None:
            raise ValueError(f"{type(integ).__name__} reads an eye per receiver; none is known.")
        return e if integ.reads_eye else None


def receivers(points: Any, normals: Any, eyes: Any, what: str) -> Receivers:
    """`Receivers` from an entry point's `(N, 3)` points and normals (shapes and dtypes already
    checked) and eyes (`(N, 3)` or None). Known values are checked here (`ValueError` naming
    `what`), concrete ones, even when a caller's `jit` closes over them, in one compiled call
    that also normalises the normals; abstract ones carry their check (`ok`)."""
    if not _is_traced((points, normals)):
        with jax.ensure_compile_time_eval():
            good, unit = _checked_unit_rows(points, normals)  # one compiled call
        raise_if_bad(good, points, normals, what)
        p = np.asarray(points)
        e = None if eyes is None or _is_traced(eyes) else np.asarray(eyes)
        return Receivers(points, unit, eyes, (p, np.asarray(unit), e), None, True)
    val = known_values((points, normals))
    if val is not None:
        p, n = val
        check_values_eagerly(p, n, what)
        return Receivers(points, unit_rows(normals), eyes, (p, unit_rows_host(n), None), None, False)
    return Receivers(points, unit_rows(normals), eyes, None, inputs_ok(points, normals), False)


def traced_receivers(points: Any, normals: Any, eyes: Any) -> Receivers:
    """`Receivers` for a caller that validated its inputs before tracing (`jaxshadow.traced`):
    normals made unit, nothing checked, values not looked for."""
    return Receivers(points, unit_rows(normals), eyes, None, None, False)


class AbstractEvaluator(eqx.Module):
    """`evaluator(scene, integrand, receivers) -> (values (N, 3), overflow)` (module docstring)."""

    def __call__(self, scene: Scene, integ: Any, rx: Receivers) -> tuple[Any, Any]:
        raise NotImplementedError


class HostEngine(AbstractEvaluator):
    """Concrete inputs, nothing differentiated: plan and decode on the host, integrate in JAX."""

    def __call__(self, scene: Scene, integ: Any, rx: Receivers) -> tuple[Any, Any]:
        assert rx.values is not None
        p, n, _ = rx.values
        return host_values(scene, integ, p, n, rx.eye_values_for(integ)), False


class Planned(AbstractEvaluator):
    """Inputs that carry derivatives but have known values: the engine plans from the values,
    JAX decodes the boundaries and differentiates."""

    def __call__(self, scene: Scene, integ: Any, rx: Receivers) -> tuple[Any, Any]:
        assert rx.values is not None
        value_scene = known_values(scene)
        p, n, _ = rx.values
        return planned_values(scene, value_scene, integ, rx.points, rx.normals, rx.eyes_for(integ), (p, n)), False


class TracedEngine(AbstractEvaluator):
    """Abstract values: the engine inside the compiled program (XLA FFI), at most `capacity`
    boundary edges (candidate faces) per receiver; `overflow` says some receiver needed more."""

    capacity: int = eqx.field(static=True)

    def __call__(self, scene: Scene, integ: Any, rx: Receivers) -> tuple[Any, Any]:
        return traced_values(scene, integ, rx.points, rx.normals, rx.eyes_for(integ), self.capacity)


_device_compiled = eqx.filter_jit(device_values)


class DeviceKernels(AbstractEvaluator):
    """No engine: every receiver clipped against every occluder by the JAX kernels; `compiled`:
    as one compiled call (the public entry points), else traced into the caller's program."""

    compiled: bool = eqx.field(static=True, default=True)

    def __call__(self, scene: Scene, integ: Any, rx: Receivers) -> tuple[Any, Any]:
        fn = _device_compiled if self.compiled else device_values
        return fn(scene, integ, rx.points, rx.normals, rx.eyes_for(integ)), False


def choose(options: ShadowOptions, scene: Scene, integ: Any, rx: Receivers) -> AbstractEvaluator:
    """The evaluator for `scene`, `integ` and `rx` under `options` (module docstring): the
    device kernels when the engine is not used; the host engine when nothing is traced; the
    planned path when the values are known; else the engine in the compiled program."""
    if not options.use_engine():
        return DeviceKernels()
    if rx.concrete and not _is_traced((scene, integ, rx.eyes_for(integ))):
        return HostEngine()
    if rx.values is not None and known_values(scene) is not None:
        return Planned()
    return TracedEngine(options.capacity)
