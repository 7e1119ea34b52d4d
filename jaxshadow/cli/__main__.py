"""`python -m jaxshadow.cli`: the `jaxshadow` command."""

import sys

from . import main

sys.exit(main())
