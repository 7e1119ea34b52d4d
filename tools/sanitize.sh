#!/usr/bin/env bash
# The shadow engine (csrc/) under AddressSanitizer and UndefinedBehaviorSanitizer: build it apart
# (never over the installed jaxshadow/_shadows/_shadowc*.so), then run the engine's tests and a
# bounded fuzzing run (tests/test_engine_fuzz.py) in a Python that loads that build
# (JAXSHADOW_ENGINE_LIBRARY) with the sanitizer runtime preloaded. Any sanitizer report aborts
# the process, and the step fails.
#
#   bash tools/sanitize.sh                 # what .ci/run runs
#   SANITIZE_BUILD=/tmp/x bash tools/sanitize.sh -m slow -k long   # the long fuzzing run
#
# Extra arguments go to pytest (replacing the default selection). Environment: PYTHON (default
# .venv/bin/python), CXX (default g++), SANITIZE_BUILD (build directory, default a fresh mktemp).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
CXX=${CXX:-g++}
OUT=${SANITIZE_BUILD:-$(mktemp -d)}
mkdir -p "$OUT"
LIB="$OUT/_shadowc_asan.so"

# setup.py's flags (IEEE arithmetic, no contraction), the sanitizers, and -O1 for usable reports.
# float-cast-overflow is not part of GCC's "undefined": a NaN or huge double cast to an index.
PYINC=$("$PY" -c "import sysconfig; print(sysconfig.get_paths()['include'])")
FFI=$("$PY" -c "import os, jaxlib; d = os.path.join(os.path.dirname(jaxlib.__file__), 'include'); print(d if os.path.exists(os.path.join(d, 'xla/ffi/api/ffi.h')) else '')")
JAXLIB=$("$PY" -c "import jaxlib.version; print(jaxlib.version.__version__)")
DEFS=(); [ -n "$FFI" ] && DEFS=(-DJAXSHADOW_FFI=1 "-DJAXSHADOW_JAXLIB_VERSION=\"$JAXLIB\"" -I"$FFI")
# The sanitizer runtimes come with the compiler's libasan / libubsan (Debian: libasan8,
# libubsan1, installed with g++); install them when the compiler does not find them.
if [ ! -f "$("$CXX" -print-file-name=libasan.so)" ] && command -v apt-get >/dev/null 2>&1; then
  SUDO=""; [ "$(id -u)" -ne 0 ] && SUDO="sudo"
  $SUDO apt-get update -qq
  DEBIAN_FRONTEND=noninteractive $SUDO apt-get install -y -qq libasan8 libubsan1 >/dev/null
fi
echo "sanitize: building the engine with ASan + UBSan into $LIB"
"$CXX" -std=c++17 -O1 -g -fno-omit-frame-pointer -ffp-contract=off -fno-fast-math \
  -fsanitize=address,undefined,float-cast-overflow -fno-sanitize-recover=all \
  -fPIC -shared -w -I"$PYINC" "${DEFS[@]}" csrc/shadowc.cc -o "$LIB"

# Python is not built with ASan: its runtime must come first (LD_PRELOAD), with libstdc++ so
# that ASan finds the real __cxa_throw (jaxlib throws C++ exceptions while loading).
ASAN_RT=$("$CXX" -print-file-name=libasan.so)
STDCXX=$("$CXX" -print-file-name=libstdc++.so.6)
export LD_PRELOAD="$ASAN_RT $STDCXX"
# Python and jaxlib keep memory to exit (leaks are not what this step is about).
export ASAN_OPTIONS="detect_leaks=0:abort_on_error=1:halt_on_error=1:allocator_may_return_null=1"
export UBSAN_OPTIONS="halt_on_error=1:abort_on_error=1:print_stacktrace=1"
export JAXSHADOW_ENGINE_LIBRARY="$LIB"
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"

# The step must be able to fail: a read past a buffer the engine is handed is reported.
echo "sanitize: checking that a heap overflow in the engine is caught"
if "$PY" - >"$OUT/canary.log" 2>&1 <<'EOF'
import numpy as np
from jaxshadow._shadows import abi, binding
lib = binding._lib()
assert lib.__file__.endswith("_shadowc_asan.so"), lib.__file__
p = np.zeros((1, 3)); n = np.array([[0.0, 0.0, 1.0]]); v = np.array([[0, 0, 1.0], [1, 0, 1], [0, 1, 1]])
faces = np.array([[[0.1, 0.1, 0.5], [0.3, 0.1, 0.5], [0.1, 0.3, 0.5]]])
# The sizes agree (the binding checks them), the contents lie: one solid of faces [0, 1000), 1 given.
i32 = lambda *a: np.array(a, np.int32)
occ = (faces, i32(0), i32(-1), i32([0, 1000]), i32(0, 0), np.zeros((0, 4), np.int32))
abi.poly_plan(lib, p, n, v, occ, 1, True, False)
EOF
then
  echo "sanitize: the sanitizer did not catch an out-of-bounds read (see $OUT/canary.log)" >&2
  exit 1
fi
grep -q "AddressSanitizer" "$OUT/canary.log" || { echo "sanitize: the canary failed without a sanitizer report:" >&2; cat "$OUT/canary.log" >&2; exit 1; }

echo "sanitize: engine tests and fuzzing under the sanitizers"
if [ "$#" -eq 0 ]; then
  # The mesh property suite's gradient check is JAX compilation, not engine work: left out.
  set -- tests/test_engine_fuzz.py tests/test_cache.py tests/test_regions.py tests/test_properties_mesh.py \
    -m "not slow" -k "not gradients"
fi
JAXSHADOW_THREADS=2 "$PY" -m pytest -n 0 -p no:cacheprovider -q "$@"
