"""Build jaxshadow's compiled parts; everything else is in pyproject.toml.

- `jaxshadow._shadows._shadowc` (C++17, `csrc/shadowc.cc` and `csrc/engine/*.h`): the host shadow engine (occluder
  hierarchy, receiver classification, the combinatorics of the visible region's boundary), loaded
  with ctypes and, where jaxlib's XLA FFI headers are found at build time (`jax.ffi.include_dir()`;
  jaxlib is a build requirement), also registered as an XLA FFI target.

It is optional: without a compiler the package installs without it and uses its JAX (device)
kernels, which are exact but slower and need memory that grows with the square of the occluder
count. IEEE arithmetic and no fused multiply-adds (`-ffp-contract=off`): the host decisions must
round as NumPy's and XLA's do.
"""

import glob
import os

from setuptools import Extension, setup


def _ffi_include() -> list[str]:
    try:
        import jaxlib
    except ImportError:
        return []
    inc = os.path.join(os.path.dirname(jaxlib.__file__), "include")
    return [inc] if os.path.exists(os.path.join(inc, "xla", "ffi", "api", "ffi.h")) else []


_FLAGS = ["-O2", "-ffp-contract=off", "-fno-fast-math"]
_INC = _ffi_include()

setup(
    ext_modules=[
        Extension(
            "jaxshadow._shadows._shadowc",
            sources=["csrc/shadowc.cc"],
            depends=sorted(glob.glob("csrc/engine/*.h")),
            include_dirs=_INC,
            define_macros=[("JAXSHADOW_FFI", "1")] if _INC else [],
            extra_compile_args=["-std=c++17", *_FLAGS, "-O3"],
            language="c++",
            optional=True,
        ),
    ]
)
