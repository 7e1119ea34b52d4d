"""Build the one compiled part of jaxshadow: `jaxshadow._clipc`, the host combinatorics of the
culled soft-shadow kernel (`jaxshadow/_clipc.c`, loaded with ctypes by `jaxshadow._clip_host`).

Everything else is in pyproject.toml. The extension is optional: without a C compiler the
package installs without it and `_clip_host` uses its NumPy version of the same code.
IEEE arithmetic and no fused multiply-adds (`-ffp-contract=off`): its tests must round as
NumPy's and XLA's do.
"""

from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "jaxshadow._clipc",
            sources=["jaxshadow/_clipc.c"],
            depends=["jaxshadow/_clipc_body.h"],
            extra_compile_args=["-O2", "-std=c11", "-ffp-contract=off", "-fno-fast-math"],
            optional=True,
        )
    ]
)
