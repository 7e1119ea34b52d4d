"""Build jaxshadow's compiled parts; everything else is in pyproject.toml.

- `jaxshadow._shadows._shadowc` (C++17, `csrc/shadowc.cc`, `csrc/abi.h` and `csrc/engine/*.h`): the
  host shadow engine (occluder hierarchy, receiver classification, the combinatorics of the
  visible region's boundary) as one CPython extension module, with its host entry points and,
  where jaxlib's XLA FFI headers are found at build time, its XLA FFI handlers. The jaxlib whose
  headers were used is recorded in the module (`JAXLIB_VERSION`); at run time the handlers are
  used only under that same jaxlib (`jaxshadow/_shadows/binding.py`). `tools/setup.sh` builds
  against the environment's own jaxlib (`--no-build-isolation`) when pip's isolated build picked
  another.

It is optional: without a compiler the package installs without it and uses its JAX (device)
kernels, which are exact but slower and need memory that grows with the square of the occluder
count. IEEE arithmetic and no fused multiply-adds (`-ffp-contract=off`): the host decisions must
round as NumPy's and XLA's do.

- `jaxshadow._io._csvc` (C99, `csrc/csvtext.c`): numeric CSV tables read (strtod) and written
  (Python's own float formatting) at array speed, for `jaxshadow/_io/meshio.py`. Python headers
  only (buffers through the buffer protocol, no NumPy headers); optional like the engine: without
  it the same tables go through NumPy's `loadtxt` and Python's string formatting.
"""

import glob
import os

from setuptools import Extension, setup


def _jaxlib() -> tuple[list[str], list[tuple[str, str]]]:
    """The XLA FFI include directory and macros (the FFI switch, jaxlib's version), if jaxlib has them."""
    try:
        import jaxlib
        from jaxlib import version
    except ImportError:
        return [], []
    inc = os.path.join(os.path.dirname(jaxlib.__file__), "include")
    if not os.path.exists(os.path.join(inc, "xla", "ffi", "api", "ffi.h")):
        return [], []
    return [inc], [("JAXSHADOW_FFI", "1"), ("JAXSHADOW_JAXLIB_VERSION", f'"{version.__version__}"')]


_INC, _MACROS = _jaxlib()

setup(
    ext_modules=[
        Extension(
            "jaxshadow._shadows._shadowc",
            sources=["csrc/shadowc.cc"],
            depends=sorted(glob.glob("csrc/*.h") + glob.glob("csrc/engine/*.h")),
            include_dirs=_INC,
            define_macros=_MACROS,
            extra_compile_args=["-std=c++17", "-O3", "-ffp-contract=off", "-fno-fast-math"],
            language="c++",
            optional=True,
        ),
        Extension(
            "jaxshadow._io._csvc",
            sources=["csrc/csvtext.c"],
            extra_compile_args=["-std=c99", "-O2"],
            optional=True,
        ),
    ]
)
