"""Where jaxshadow is used from a source checkout without being pip-installed, its pytest plugin
(normally loaded through the `pytest11` entry point) is not registered: take its hooks and
fixtures from here instead. (`pytest_plugins` cannot be used: pytest rejects it outside the
top-level conftest when collecting from the repository root.)"""

from importlib.metadata import entry_points

if not any(ep.name == "jaxshadow" for ep in entry_points(group="pytest11")):
    from _jaxshadow_pytest import *  # noqa: F403
