"""Multi-device evaluation: shard the batch of receivers over every device of a mesh.

Irradiance is independent per receiver, so the batch axis is split over the devices (data
parallelism) and each device evaluates its slice with the same jitted code; no communication
is needed except to return the result. The batch is padded to a multiple of the device count
with copies of its first receiver and the padding is dropped from the result.
"""

from __future__ import annotations

from typing import Any, no_type_check

import equinox as eqx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, Float

from .._core.geometry import check_points_normals
from .._scene.model import Scene
from .shade import irradiance


def batch_mesh(devices: Any = None) -> Mesh:
    """A 1-D `Mesh` with axis name `"points"` over `devices` (default: all of `jax.devices()`).

    Example:
        ```python
        import jaxshadow as js

        mesh = js.batch_mesh()   # every local device on one axis
        ```
    """
    devs = jax.devices() if devices is None else list(devices)
    return Mesh(np.asarray(devs), ("points",))


@eqx.filter_jit
def _irradiance_sharded(scene: Scene, points: Array, normals: Array, sharding: NamedSharding):
    out = irradiance(scene, points, normals)
    return jax.lax.with_sharding_constraint(out, sharding)


# Validates its own inputs (ValueError, docs/design.md): no runtime annotation check before it.
@no_type_check
def sharded_irradiance(
    scene: Scene,
    points: Float[Array, "N 3"],
    normals: Float[Array, "N 3"],
    mesh: Mesh | None = None,
) -> Float[Array, "N 3"]:
    r"""`irradiance(scene, points, normals)` with the batch sharded over the devices of `mesh`.

    Same values as `jaxshadow.irradiance` (W/m^2, RGB); the work is split row-wise over
    `mesh.size` devices (every mesh axis together shards the batch axis).

    **Arguments:**

    - `scene`: a `Scene`.
    - `points`, `normals`: `(N, 3)` receivers (checked as in `irradiance`).
    - `mesh`: a `jax.sharding.Mesh`; default: a 1-D mesh over all devices (`batch_mesh()`).

    **Returns:** `(N, 3)` irradiance, dtype following `points`. When `N` is a multiple of the
    device count the result stays sharded along its first axis (`NamedSharding`); otherwise
    the batch is padded for the computation and the `N` real rows are returned.

    Example:
        ```python
        import numpy as np
        import jaxshadow as js

        scene = js.Scene([js.DirectionalLight([0.0, 0.0, -1.0], 800.0)])
        points = np.random.default_rng(0).uniform(-1, 1, (1024, 3))
        normals = np.tile([0.0, 0.0, 1.0], (1024, 1))
        E = js.sharded_irradiance(scene, points, normals, js.batch_mesh())   # as js.irradiance, split over devices
        ```
    """
    points, normals = check_points_normals(points, normals, "sharded_irradiance")
    mesh = batch_mesh() if mesh is None else mesh
    if not isinstance(mesh, Mesh):
        raise ValueError(
            f"sharded_irradiance: mesh must be a jax.sharding.Mesh, got {type(mesh).__name__}."
        )
    n = points.shape[0]
    ndev = mesh.size
    pad = (-n) % ndev
    if pad:
        # Copies of a real receiver: finite, valid normals, results dropped below.
        points = jax.numpy.concatenate([points, jax.numpy.repeat(points[:1], pad, axis=0)])
        normals = jax.numpy.concatenate([normals, jax.numpy.repeat(normals[:1], pad, axis=0)])
    sharding = NamedSharding(mesh, PartitionSpec(tuple(mesh.axis_names), None))
    points = jax.device_put(points, sharding)
    normals = jax.device_put(normals, sharding)
    out = _irradiance_sharded(scene, points, normals, sharding)
    return out[:n] if pad else out
