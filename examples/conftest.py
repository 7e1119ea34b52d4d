"""Load the jaxshadow.testing pytest plugin where jaxshadow is used from a source checkout (an
installed jaxshadow registers it through its `pytest11` entry point, and this line is then a
no-op)."""

pytest_plugins = ["jaxshadow.testing.plugin"]
