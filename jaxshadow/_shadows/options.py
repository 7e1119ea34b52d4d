"""How exact shadows are evaluated: `ShadowOptions` (which engine, the compiled capacity), the one
setting every shadow entry point takes (`js.irradiance`, `js.specular`, `js.shade`,
`jaxshadow.traced`), and `DEFAULT_OPTIONS`. `evaluators.choose` turns it into an evaluator."""

from __future__ import annotations

from dataclasses import dataclass

from . import binding as vis


@dataclass(frozen=True)
class ShadowOptions:
    """How exact shadows are evaluated (static: part of a compiled program's identity).

    - `engine`: `"auto"` (the compiled host engine when it is built, else the device kernels),
      `"host"` (the engine; an error if it is not built) or `"device"` (JAX kernels that clip
      every receiver against every occluder: no build needed, time grows with the square of
      the occluder count, memory stays bounded: receivers and their candidate edges are
      processed a batch at a time, `compiled.device_values`).
    - `capacity`: boundary edges (polygon lights) or visible pieces (segment lights) per
      receiver when the values are abstract (inside `jax.jit`/`jax.vmap`) and the engine runs in
      the compiled program. A receiver that needs more is an error, never a truncation. Eager
      calls (including eager `jax.grad`) plan from the values and have no capacity.
    """

    engine: str = "auto"
    capacity: int = 64

    def __post_init__(self) -> None:
        if self.engine not in ("auto", "host", "device"):
            raise ValueError(f"ShadowOptions: engine must be 'auto', 'host' or 'device', got {self.engine!r}.")
        if not isinstance(self.capacity, int) or isinstance(self.capacity, bool) or not 1 <= self.capacity <= 1 << 16:
            raise ValueError(f"ShadowOptions: capacity must be an integer in [1, 65536], got {self.capacity!r}.")

    def use_engine(self) -> bool:
        """Whether the compiled host engine evaluates shadows under these options: False for
        `"device"`, and (with one warning) for `"auto"` when the engine is not built; an error for
        `"host"` when it is not built."""
        if self.engine == "device":
            return False
        if self.engine == "host" and not vis.engine_available():
            raise RuntimeError("ShadowOptions(engine='host'): jaxshadow._shadows._shadowc is not built "
                               "(reinstall jaxshadow with a C++ compiler available).")
        if not vis.engine_available():
            vis.warn_unbuilt()
            return False
        return True


DEFAULT_OPTIONS = ShadowOptions()
