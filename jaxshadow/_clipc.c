/* The host combinatorics of the culled soft-shadow kernel, compiled: `_clip_host.host_culled_codes`
 * (NumPy, the reference) as plain loops over the receivers, in float64 and float32. Called
 * through ctypes (`jaxshadow._clip_host`); the module itself exports nothing to Python.
 *
 * Build with IEEE arithmetic and no contraction of a*b+c into fused multiply-adds
 * (-ffp-contract=off, setup.py): the tests that decide which piece of which edge is visible
 * must round as NumPy's and XLA's do. */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>

#define COLLINEAR_EPS 64.0 /* _clip.COLLINEAR_EPS */

#define REAL double
#define SFX(name) name##_f64
#define EPS_D 2.220446049250313e-16
#define BIAS 1023
#define SQRT sqrt
#define FREXP frexp
#define LDEXP ldexp
#define FABS fabs
#include "_clipc_body.h"
#undef REAL
#undef SFX
#undef EPS_D
#undef BIAS
#undef SQRT
#undef FREXP
#undef LDEXP
#undef FABS

#define REAL float
#define SFX(name) name##_f32
#define EPS_D 1.1920928955078125e-07
#define BIAS 127
#define SQRT sqrtf
#define FREXP frexpf
#define LDEXP ldexpf
#define FABS fabsf
#include "_clipc_body.h"

int jaxshadow_clipc_abi_version(void) { return 2; }

static struct PyModuleDef clipc_module = {PyModuleDef_HEAD_INIT, "_clipc",
                                          "Compiled host combinatorics (ctypes entry points; see _clip_host).", -1,
                                          NULL, NULL, NULL, NULL, NULL};

PyMODINIT_FUNC PyInit__clipc(void) { return PyModule_Create(&clipc_module); }
