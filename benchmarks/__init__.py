"""jaxshadow's benchmarks: `python -m benchmarks --list` (the suite is defined in `_suite.py`)."""
