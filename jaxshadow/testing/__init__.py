r"""A gradient oracle for renderer tests: exact reference values and derivatives.

Monte Carlo estimators of derivatives through visibility are easy to get wrong (a missing
boundary term from a moving shadow edge is the classic bias). `jaxshadow.testing` gives a test
suite the exact answers and the statistics to compare against them:

- `catalogue`: named reference scenes (`"unoccluded"`, `"penumbra"`, `"umbra"`, `"touching"`,
  `"grazing"`, `"highlight"`, `"linear"`, `"mesh"`) with exact irradiance and radiance at given
  receivers and their exact derivatives with respect to light translation, rotation and scale,
  occluder translation and material parameters (`PARAMETERS`); each as a jaxshadow scene,
  plain NumPy arrays (`.arrays()`) and a Mitsuba 3 scene dict (`.mitsuba_dict()`).
- `assert_values_match(estimate, stderr, reference, alpha=...)` and
  `assert_gradient_matches(...)`: z tests with a stated family-wise false-alarm rate (Holm or
  Bonferroni over the points) and a chi-square summary; failures name the points and the
  sigmas. `compare` returns the statistics without asserting.
- A pytest plugin (entry point `pytest11`, loaded automatically once jaxshadow is installed):
  fixtures `jaxshadow_catalogue` and `jaxshadow_reference` (one test per catalogue scene,
  selected with the marker `@pytest.mark.jaxshadow_scenes("penumbra", ...)`), and
  `jaxshadow_alpha` (option `--jaxshadow-alpha`).

```python
from jaxshadow.testing import assert_gradient_matches, catalogue

ref = catalogue["penumbra"]
est, err = my_renderer_dE_dlight_x(ref.arrays())          # (N, 3) each
assert_gradient_matches({"light.tx": est}, {"light.tx": err},
                        {"light.tx": ref.d_irradiance["light.tx"]}, alpha=1e-3)
```
"""

from ._catalogue import Catalogue as Catalogue
from ._catalogue import ImageReference as ImageReference
from ._catalogue import ReferenceScene as ReferenceScene
from ._catalogue import catalogue as catalogue
from ._scenes import LIGHT_TRANSLATION as LIGHT_TRANSLATION
from ._scenes import PARAMETERS as PARAMETERS
from ._stats import Comparison as Comparison
from ._stats import assert_gradient_matches as assert_gradient_matches
from ._stats import assert_values_match as assert_values_match
from ._stats import clopper_pearson as clopper_pearson
from ._stats import compare as compare
from ._stats import false_alarm_bound as false_alarm_bound

__all__ = [
    "LIGHT_TRANSLATION",
    "PARAMETERS",
    "Catalogue",
    "Comparison",
    "ImageReference",
    "ReferenceScene",
    "assert_gradient_matches",
    "assert_values_match",
    "catalogue",
    "clopper_pearson",
    "compare",
    "false_alarm_bound",
]
