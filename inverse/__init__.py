"""inverse: painted targets and the solvers that run jaxshadow backwards.

Material ($k_a, k_d, k_s$, Phong roughness) from painted colours, light placement from painted
shading, highlights and shadows (Poulin ch. 5), with identifiability reports.
"""

from importlib.metadata import PackageNotFoundError, version

from ._closed_forms import LightRay as LightRay
from ._closed_forms import exponent_from_highlight as exponent_from_highlight
from ._closed_forms import intersect_plane as intersect_plane
from ._closed_forms import light_from_diffuse_maximum as light_from_diffuse_maximum
from ._closed_forms import light_from_highlight as light_from_highlight
from ._closed_forms import light_from_shadow as light_from_shadow
from ._closed_forms import mirror_direction as mirror_direction
from ._closed_forms import point_from_shadows as point_from_shadows
from ._demo_scene import demo_configuration as demo_configuration
from ._demo_scene import pose_errors as pose_errors
from ._design import TargetDesign as TargetDesign
from ._design import design_targets as design_targets
from ._diagnostics import FitQuality as FitQuality
from ._diagnostics import FitQualityWarning as FitQualityWarning
from ._fit_lights import fit_lights as fit_lights
from ._joint import fit_light_and_material as fit_light_and_material
from ._joint import joint_std_errors as joint_std_errors
from ._lights import LightReport as LightReport
from ._lights import fit_light as fit_light
from ._material import bounded_lstsq as bounded_lstsq
from ._material import fit_material as fit_material
from ._multilight_report import LightsReport as LightsReport
from ._options import Search as Search
from ._painting import Brighter as Brighter
from ._painting import ColourRange as ColourRange
from ._painting import load_painted as load_painted
from ._painting import save_painted as save_painted
from ._parametrisation import Box as Box
from ._parametrisation import LightParametrisation as LightParametrisation
from ._parametrisation import Outside as Outside
from ._parametrisation import Plane as Plane
from ._parametrisation import rotation_matrix as rotation_matrix
from ._parametrisation import scene_size as scene_size
from ._plots import plot_residuals as plot_residuals
from ._regions import RegionFit as RegionFit
from ._regions import fit_material_regions as fit_material_regions
from ._reports import FitReport as FitReport
from ._reports import JointFit as JointFit
from ._reports import LightFit as LightFit
from ._reports import LightsFit as LightsFit
from ._reports import MaterialFit as MaterialFit
from ._reports import MaterialReport as MaterialReport
from ._reports import UndeterminedParameterWarning as UndeterminedParameterWarning
from ._residuals import light_loss as light_loss
from ._solvers import LBFGSB as LBFGSB
from ._solvers import LM as LM
from ._solvers import AbstractLightSolver as AbstractLightSolver
from ._solvers import OptimistixLM as OptimistixLM
from ._targets import PaintedTargets as PaintedTargets
from ._targets import load_targets as load_targets
from ._targets import save_targets as save_targets

try:
    __version__ = version("jaxshadow")
except PackageNotFoundError:  # pragma: no cover
    __version__ = "0.0.0"
