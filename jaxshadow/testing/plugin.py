"""The pytest plugin of `jaxshadow.testing` (`-p jaxshadow.testing.plugin`); the code lives in
the top-level module `_jaxshadow_pytest`, which the `pytest11` entry point `jaxshadow` loads
without importing `jaxshadow` (see its docstring)."""

from _jaxshadow_pytest import *  # noqa: F403
from _jaxshadow_pytest import MARKER as MARKER
from _jaxshadow_pytest import SCENES as SCENES
from _jaxshadow_pytest import __all__ as __all__
