#!/usr/bin/env bash
# Set up a fresh machine for jaxshadow: Debian's libllvm19 (Mitsuba's llvm_ad_rgb variant
# needs it; the preinstalled LLVM aborts on 'fminimum'), a virtualenv in .venv, and the package
# with every extra CI uses (pip compiles its C extensions). Idempotent.
set -euo pipefail
cd "$(dirname "$0")/.."
if ! ldconfig -p 2>/dev/null | grep -q 'libLLVM.so.19\|libLLVM-19'; then
  if command -v apt-get >/dev/null 2>&1; then
    SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
    $SUDO apt-get update -qq
    DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libllvm19 >/dev/null
  else
    echo "warning: cannot install libllvm19 (no apt-get); Mitsuba's llvm variant may not load" >&2
  fi
fi
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install -q --upgrade pip
.venv/bin/python -m pip install -q -e ".[mitsuba,jaxopt,optimistix,plot,test,docs,bench]"
# The compiled shadow engine (csrc/, built by setup.py with the machine's C++ compiler) is
# optional, but without it scenes with occluders use the device kernels. Its XLA FFI handlers
# are compiled against jaxlib's headers, and pip's isolated build may have picked another jaxlib
# than the one just installed (the module then leaves its handlers unused, with a warning):
# rebuild it without isolation, against this environment's jaxlib.
engine_state() {
  .venv/bin/python -c 'import jaxlib.version
from jaxshadow._shadows import _shadowc as m
print("ok" if m.HAS_FFI and m.JAXLIB_VERSION == jaxlib.version.__version__ else "other-jaxlib")' 2>/dev/null || echo unbuilt
}
if [ "$(engine_state)" != ok ]; then
  .venv/bin/python -m pip install -q "setuptools>=68" wheel
  .venv/bin/python -m pip install -q --no-build-isolation --no-deps -e .
fi
case "$(engine_state)" in
  unbuilt) echo "warning: jaxshadow._shadows._shadowc was not built (no C++ compiler?): exact shadows fall back to the device kernels (slow, memory-hungry with many occluders)" >&2 ;;
  other-jaxlib) echo "warning: jaxshadow._shadows._shadowc has no XLA FFI handlers for this jaxlib: traced programs with occluders use the device kernels" >&2 ;;
esac
echo "jaxshadow set up in .venv"
