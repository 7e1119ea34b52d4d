"""jaxshadow: exact, differentiable direct illumination in JAX.

Polygon and linear-light form factors, Phong specular integrals, exact soft shadows, and the
Mitsuba 3 bridge used as independent ground truth. See DESIGN.md for the conventions.
"""

from importlib.metadata import PackageNotFoundError, version

from . import files as files
from ._core.mesh import Mesh as Mesh
from ._core.misc import safe_normalize as safe_normalize
from ._core.receivers import ReceiverMesh as ReceiverMesh
from ._illumination.bake import BakedScene as BakedScene
from ._illumination.bake import bake as bake
from ._illumination.mesh import IlluminationMesh as IlluminationMesh
from ._illumination.mesh import illumination_mesh as illumination_mesh
from ._io.meshio import read_mesh as read_mesh
from ._io.meshio import write_mesh as write_mesh
from ._io.meshio import write_ply as write_ply
from ._io.tables import read_points as read_points
from ._io.tables import write_values as write_values
from ._kernels.clip import visible_form_factor as visible_form_factor
from ._kernels.linear import linear_irradiance as linear_irradiance
from ._kernels.polygon import form_factor as form_factor
from ._kernels.spline import shadow_nodes as shadow_nodes
from ._kernels.spline import spline_shadow as spline_shadow
from ._kernels.spline import spline_shadow_faces as spline_shadow_faces
from ._scene.format import load_material as load_material
from ._scene.format import load_scene as load_scene
from ._scene.format import save_scene as save_scene
from ._scene.format import scene_from_dict as scene_from_dict
from ._scene.format import scene_to_dict as scene_to_dict
from ._scene.model import DirectionalLight as DirectionalLight
from ._scene.model import LinearLight as LinearLight
from ._scene.model import Material as Material
from ._scene.model import PointLight as PointLight
from ._scene.model import PolygonLight as PolygonLight
from ._scene.model import Scene as Scene
from ._shading.shade import irradiance as irradiance
from ._shading.shade import shade as shade
from ._shading.shade import specular as specular
from ._shading.sharding import batch_mesh as batch_mesh
from ._shading.sharding import sharded_irradiance as sharded_irradiance
from ._shadows.cache import ShadowCache as ShadowCache
from ._shadows.options import ShadowOptions as ShadowOptions
from ._shadows.plan import ShadowPlan as ShadowPlan
from ._shadows.plan import shadow_plan as shadow_plan

# The file writers live in `jaxshadow.files`; their names at the top are kept, deprecated.
_MOVED = {"atomic_write": "jaxshadow.files", "atomic_write_path": "jaxshadow.files"}


def __getattr__(name: str) -> object:
    if name in _MOVED:
        import warnings

        warnings.warn(f"jaxshadow.{name} is deprecated: use {_MOVED[name]}.{name}.", DeprecationWarning, stacklevel=2)
        return getattr(files, name)
    raise AttributeError(f"module 'jaxshadow' has no attribute {name!r}")


try:
    __version__ = version("jaxshadow")
except PackageNotFoundError:  # pragma: no cover
    __version__ = "0.0.0"
