// The host side of jaxshadow's exact shadows: per receiver, which occluders can block the light
// (a bounding-volume hierarchy queried with the receiver's illumination pyramid) and the
// combinatorics of the visible region's boundary, as integer endpoint codes that the JAX side turns
// into points (and differentiates): `jaxshadow/_shadows/binding.py`.
//
// Polygon lights (Campbell & Fussell §3.1, §4.2-4.3). For a receiver p with normal n the visible
// region is R = E_h \ U_j Q_j in the emitter plane: E_h the light clipped to p's horizon, Q_j the
// central projection of what occluder j blocks. Every region is an intersection of half-spaces
// bounded by planes through p, and R's boundary consists of pieces of the regions' edges. An
// occluder j can block part of the light seen from p iff the pyramid conv(p, E_h) meets it, i.e.
// iff p lies in the occlusion volume of (E, j) (C&F Theorem 2, evaluated here in that dual form);
// p is in the umbra of j iff E_h lies inside Q_j (C&F Theorem 3's volume, same duality). So each
// receiver is classified
//   LIT       no occluder meets the pyramid: the unoccluded form factor is exact;
//   UMBRA     one occluder (a face, or a convex solid through its silhouette) hides all of E_h: 0;
//   PENUMBRA  the boundary of R is computed from the candidates only;
// and the hierarchy makes the candidate search O(log M + k) instead of O(M).
//
// The combinatorics follow `jaxshadow._clip` (the device kernel) test for test: candidate edges
// (E_h's, and each occluder's effective-blocker edges clipped in 3-D to the pyramid and projected),
// cut at the parameters where they enter and leave every other region, pieces kept by a one-sided
// midpoint test with the coincident-edge tie-break (emitter first, then occluders in index order),
// kept pieces merged into runs. Regions whose bounding boxes in the emitter plane do not meet an
// edge are skipped (they cannot contain any of it). A convex closed mesh ("solid") strictly on the
// receiver's side of the emitter plane, with p strictly outside it, is one region: the planes
// through p and its silhouette edges (the cone it blocks), so that a box costs one hexagon. A
// face whose plane holds p (a box resting on the receiver's floor) is a back face there: it
// blocks a zero solid angle, and every silhouette edge then borders a strictly front face.
// Receivers that no item's box can reach are classified before any other work (lit, or zero
// below their horizon) where the caller evaluates lit receivers with the unoccluded kernel;
// before the hierarchy is queried, a receiver outside the occlusion volume of the root's box
// (planes computed once per call, `engine/volume.h`) is known to be such a receiver. A receiver
// strictly inside a convex solid's umbra volume (C&F §3.1.3, `engine/umbra.h`) is umbra as soon
// as the query meets that solid. Large batches are ordered by grid cell and each group of nearby
// receivers queries the hierarchy once with the hull of its box and the light; each receiver then
// filters that list (C&F §4.1/§4.3 occluder lists refined down the receivers, `engine/groups.h`).
// For Lambert's integrand the host path takes each penumbra receiver's contour sum from the engine
// (edge terms added up as the boundary is decoded, in double).
//
// Point and directional lights: hard-shadow ray tests against the hierarchy. Segment lights: the
// occluders that meet the light triangle (p, a, b) (Poulin §4.2), for the device kernel to clip.
//
// The binding: one CPython extension module, `jaxshadow._shadows._shadowc` (setup.py), which
// `jaxshadow/_shadows/abi.py` loads and `binding.py` wraps:
//   poly_plan, hard_plan, segment_plan   the host entry points: C-contiguous buffers in (NumPy
//                                        arrays), results as `Owned` buffers (the engine's own
//                                        allocations, freed with the last array that views them);
//   ffi_handlers()                       the XLA FFI handlers (`ffi.h`) as PyCapsules, for traced
//                                        programs;
//   prepared_stats()                     the counts of the prepared-occluder cache (engine/prepared.h);
//   ABI_VERSION, CODE_WIDTH              from `abi.h`, the one definition of the interface;
//   HAS_FFI, JAXLIB_VERSION              whether the FFI handlers were compiled, and the jaxlib
//                                        whose headers they were compiled against.
// Both bindings read the occluders through one struct and dispatch on the float type once
// (`inputs.h`), and each binding's entry points share one prologue (here `parse_host` and
// `with_host_inputs`; `with_inputs` in `ffi.h`); only this file includes Python's headers. Plain C++17; IEEE arithmetic without
// contraction into fused multiply-adds (setup.py passes -ffp-contract=off), so that the decisions
// round as NumPy's do. With JAXSHADOW_FFI (setup.py defines it, and JAXSHADOW_JAXLIB_VERSION,
// when jaxlib's XLA FFI headers are found) the handlers are compiled; otherwise `ffi_handlers()`
// is empty.

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <deque>
#include <initializer_list>
#include <type_traits>

#include "abi.h"
#include "inputs.h"
#include "engine/silhouette_segment.h"
#ifdef JAXSHADOW_FFI
#include "ffi.h"
#endif

using namespace jaxshadow_binding;  // NOLINT: this file only binds the engine to Python
using jaxshadow_abi::kAbiVersion;

namespace {

// ----------------------------------------------------------------------------------------------
// Python: results that own their memory, inputs read through the buffer protocol
// ----------------------------------------------------------------------------------------------

// A C-contiguous array the engine allocated (malloc): exposed with the buffer protocol (format,
// shape), freed when the last view of it goes (`np.asarray(owned)` views it without a copy).
struct Owned {
  PyObject_HEAD
  void* data;
  int ndim;
  Py_ssize_t itemsize;
  Py_ssize_t shape[3];
  Py_ssize_t strides[3];
  char format[2];
};

PyTypeObject OwnedType = {PyVarObject_HEAD_INIT(nullptr, 0)};

int owned_getbuffer(PyObject* self, Py_buffer* view, int flags) {
  static double empty[1];  // a valid address for arrays of no elements
  auto* o = reinterpret_cast<Owned*>(self);
  Py_ssize_t n = 1;
  for (int d = 0; d < o->ndim; d++) n *= o->shape[d];
  view->buf = o->data ? o->data : static_cast<void*>(empty);
  view->obj = self;
  Py_INCREF(self);
  view->len = n * o->itemsize;
  view->readonly = 0;
  view->itemsize = o->itemsize;
  view->format = (flags & PyBUF_FORMAT) ? o->format : nullptr;
  view->ndim = o->ndim;
  view->shape = (flags & PyBUF_ND) ? o->shape : nullptr;
  view->strides = ((flags & PyBUF_STRIDES) == PyBUF_STRIDES) ? o->strides : nullptr;
  view->suboffsets = nullptr;
  view->internal = nullptr;
  return 0;
}

void owned_dealloc(PyObject* self) {
  std::free(reinterpret_cast<Owned*>(self)->data);
  Py_TYPE(self)->tp_free(self);
}

PyBufferProcs owned_buffer_procs = {owned_getbuffer, nullptr};

// Takes ownership of `data` (freed here if the object cannot be made).
PyObject* owned(void* data, char format, Py_ssize_t itemsize, std::initializer_list<int64_t> shape) {
  Owned* o = PyObject_New(Owned, &OwnedType);
  if (!o) {
    std::free(data);
    return nullptr;
  }
  o->data = data;
  o->ndim = int(shape.size());
  o->itemsize = itemsize;
  o->format[0] = format;
  o->format[1] = 0;
  int d = 0;
  for (int64_t s : shape) o->shape[d++] = Py_ssize_t(s);
  Py_ssize_t stride = itemsize;
  for (d = o->ndim - 1; d >= 0; d--) {
    o->strides[d] = stride;
    stride *= o->shape[d];
  }
  return reinterpret_cast<PyObject*>(o);
}

// A zeroed Owned array (the entry points' fixed-size outputs), with its data pointer.
template <class X>
PyObject* zeros(char format, std::initializer_list<int64_t> shape, X** data) {
  int64_t n = 1;
  for (int64_t s : shape) n *= s;
  *data = static_cast<X*>(std::calloc(size_t(std::max<int64_t>(n, 1)), sizeof(X)));
  if (!*data) return PyErr_NoMemory();
  return owned(*data, format, Py_ssize_t(sizeof(X)), shape);
}

// An input buffer, held for the duration of a call.
struct View {
  Py_buffer b{};
  bool held = false;
  View() = default;
  View(const View&) = delete;
  View& operator=(const View&) = delete;
  ~View() {
    if (held) PyBuffer_Release(&b);
  }
  int64_t size() const { return b.itemsize ? int64_t(b.len / b.itemsize) : 0; }
};

// 'd' float64, 'f' float32, 'i' int32, 0 anything else (native byte order only).
char kind_of(const Py_buffer& b) {
  const char* f = b.format ? b.format : "B";
  if (*f == '<' || *f == '=' || *f == '@') f++;
  if (f[0] == 0 || f[1] != 0) return 0;
  if (*f == 'd' && b.itemsize == 8) return 'd';
  if (*f == 'f' && b.itemsize == 4) return 'f';
  if ((*f == 'i' || *f == 'l') && b.itemsize == 4) return 'i';
  return 0;
}

bool get(PyObject* obj, View& v, const char* what, char kind) {
  if (PyObject_GetBuffer(obj, &v.b, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) {
    PyErr_Format(PyExc_TypeError, "jaxshadow engine: %s is not a C-contiguous array", what);
    return false;
  }
  v.held = true;
  if (kind_of(v.b) != kind) {
    PyErr_Format(PyExc_TypeError, "jaxshadow engine: %s must be %s", what,
                 kind == 'i' ? "int32" : kind == 'd' ? "float64 (as the occluders)" : "float32 (as the occluders)");
    return false;
  }
  return true;
}

// A float array of points (rows of 3) in the call's float type `dt`.
bool rows3(PyObject* obj, View& v, const char* what, char dt, int64_t* rows) {
  if (!get(obj, v, what, dt)) return false;
  if (v.size() % 3) {
    PyErr_Format(PyExc_ValueError, "jaxshadow engine: %s must have rows of 3 coordinates", what);
    return false;
  }
  *rows = v.size() / 3;
  return true;
}

// The occluders argument: (faces (M, Ko, 3), face_solid (M,), face_closed (M,), solid_faces
// (S, 2), solid_edge_off (S + 1,), solid_edges (E, 4)); faces set the call's float type.
struct OccluderViews {
  View faces, ints[5];
  OccluderInputs in;
};

bool parse_occluders(PyObject* obj, OccluderViews& ov, char* dt) {
  if (!PyTuple_Check(obj) || PyTuple_GET_SIZE(obj) != 6) {
    PyErr_SetString(PyExc_TypeError, "jaxshadow engine: occluders must be a tuple (faces (M, Ko, 3), face_solid (M,), "
                                     "face_closed (M,), solid_faces (S, 2), solid_edge_off (S + 1,), solid_edges (E, 4))");
    return false;
  }
  if (PyObject_GetBuffer(PyTuple_GET_ITEM(obj, 0), &ov.faces.b, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT) < 0) return false;
  ov.faces.held = true;
  *dt = kind_of(ov.faces.b);
  if ((*dt != 'd' && *dt != 'f') || ov.faces.b.ndim != 3 || ov.faces.b.shape[2] != 3) {
    PyErr_SetString(PyExc_TypeError, "jaxshadow engine: faces must be float32 or float64 of shape (M, Ko, 3)");
    return false;
  }
  static const char* names[5] = {"face_solid", "face_closed", "solid_faces", "solid_edge_off", "solid_edges"};
  for (int k = 0; k < 5; k++)
    if (!get(PyTuple_GET_ITEM(obj, k + 1), ov.ints[k], names[k], 'i')) return false;
  OccluderInputs& in = ov.in;
  in.M = ov.faces.b.shape[0];
  in.Ko = ov.faces.b.shape[1];
  in.S = ov.ints[2].size() / 2;
  if (ov.ints[0].size() != in.M || ov.ints[1].size() != in.M || ov.ints[2].size() != 2 * in.S ||
      ov.ints[3].size() != in.S + 1 || ov.ints[4].size() % 4) {
    PyErr_SetString(PyExc_ValueError, "jaxshadow engine: the occluder topology's sizes do not match the faces");
    return false;
  }
  in.faces = ov.faces.b.buf;
  const int32_t* p[5];
  for (int k = 0; k < 5; k++) p[k] = static_cast<const int32_t*>(ov.ints[k].b.buf);
  in.face_solid = p[0];
  in.face_closed = p[1];
  in.solid_faces = p[2];
  in.solid_edge_off = p[3];
  in.solid_edges = p[4];
  return true;
}

Py_ssize_t float_size(char dt) { return dt == 'd' ? 8 : 4; }

// ----------------------------------------------------------------------------------------------
// The prologue every host entry point shares (as `with_inputs` is the FFI handlers')
// ----------------------------------------------------------------------------------------------

constexpr int64_t kOnePerPoint = -1;  // a row array with one row per point
constexpr int64_t kAnyRows = -2;      // a row array of any length (a light's vertices)

// A further input of a host entry point: rows of 3 coordinates in the call's float type, `rows`
// of them (a count, `kOnePerPoint` or `kAnyRows`).
struct RowsSpec {
  PyObject* obj;
  const char* what;
  int64_t rows;
};

// A host call's arguments, checked and held as buffers for the call (`parse_host`): the occluders
// (their faces set the call's float type `dt`), the points (N, 3), and up to two further row
// arrays (`RowsSpec`) in that type.
struct HostArgs {
  OccluderViews occ;
  View points, more[2];
  int64_t n = 0, nmore[2] = {0, 0};
  char dt = 0;
};

bool parse_host(PyObject* occluders, PyObject* points, std::initializer_list<RowsSpec> more, HostArgs& a) {
  if (more.size() > 2) {
    PyErr_SetString(PyExc_SystemError, "jaxshadow engine: at most two row arrays besides the points");
    return false;
  }
  if (!parse_occluders(occluders, a.occ, &a.dt) || !rows3(points, a.points, "points", a.dt, &a.n)) return false;
  int k = 0;
  for (const RowsSpec& s : more) {
    if (!rows3(s.obj, a.more[k], s.what, a.dt, &a.nmore[k])) return false;
    if (s.rows == kOnePerPoint && a.nmore[k] != a.n) {
      PyErr_Format(PyExc_ValueError, "jaxshadow engine: points and %s differ in length", s.what);
      return false;
    }
    if (s.rows >= 0 && a.nmore[k] != s.rows) {
      PyErr_Format(PyExc_ValueError, "jaxshadow engine: %s must have %d coordinates", s.what, int(3 * s.rows));
      return false;
    }
    k++;
  }
  return true;
}

// A host call's inputs as the engine reads them, T the call's float type: the points, the further
// row arrays (in `parse_host`'s order) and the occluders (K light vertices before the face refs),
// converted to double when asked for (`as_double`: no copy for float64), held as long as this is.
template <class T>
class HostInputs {
 public:
  using Float = T;
  explicit HostInputs(const HostArgs& a) : a_(a) {}
  int64_t N() const { return a_.n; }
  int64_t count(int k) const { return a_.nmore[k]; }
  const double* points() { return convert(a_.points); }
  const double* rows(int k) { return convert(a_.more[k]); }
  Occluders<double> occluders(int64_t K = 0) {
    store_.emplace_back();
    return occ_double<T>(K, a_.occ.in, store_.back());
  }

 private:
  const double* convert(const View& v) {
    store_.emplace_back();
    return as_double<T>(v.b.buf, size_t(v.size()), store_.back());
  }
  const HostArgs& a_;
  std::deque<std::vector<double>> store_;  // converted inputs (a deque: earlier ones never move)
};

// The float32 / float64 dispatch of a host call with its inputs: `body(HostInputs<T>&)`. Called
// with the GIL released (nothing here touches a Python object).
template <class F>
auto with_host_inputs(const HostArgs& a, F&& body) {
  return by_float(a.dt == 'd', [&](auto zero) {
    HostInputs<decltype(zero)> in(a);
    return body(in);
  });
}

// The polygon plan on inputs of type T (the function `benchmarks/engine_profile.py` counts the
// instructions of: not inlined; the inputs are converted to double in here). Points decoded for
// float32 inputs are returned as float32.
template <class In>
__attribute__((noinline)) int poly_plan_any(In& in, int threads, int32_t* cls, int32_t* stats,
                                            int64_t* offsets, int32_t** runs, void** points, int64_t* nruns,
                                            double* lambert) {
  using T = typename In::Float;
  const double* P = in.points();
  const double* Nrm = in.rows(0);
  const double* E = in.rows(1);
  const int64_t K = in.count(1);
  double* pts = nullptr;
  int rc = poly_plan<double>(in.N(), P, Nrm, K, E, in.occluders(K), threads, cls, stats, offsets, runs,
                             points ? &pts : nullptr, nruns, lambert);
  if (points && pts) {
    if (std::is_same<T, double>::value) {
      *points = pts;
    } else {
      const int64_t m = 6 * std::max<int64_t>(*nruns, 1);
      T* out = static_cast<T*>(std::malloc(sizeof(T) * m));
      if (!out) {
        std::free(pts);
        return 2;
      }
      for (int64_t i = 0; i < 6 * *nruns; i++) out[i] = T(pts[i]);
      std::free(pts);
      *points = out;
    }
  }
  return rc;
}

const char kPolyPlanDoc[] =
    "poly_plan(points, normals, light, occluders, threads, codes, decoded, lambert)\n--\n\n"
    "The polygon plan: points, normals (N, 3), light (K, 3) in the faces' float type. Returns "
    "(classes (N,) int32, stats (N, 2) int32, offsets (N + 1,) int64, runs (R, 2, CODE_WIDTH) int32 or "
    "None, points (R, 2, 3) or None, lambert (N,) float64 or None).";

PyObject* py_poly_plan(PyObject*, PyObject* args) {
  PyObject *po, *no, *lo, *oo;
  int threads, codes, decoded, lambert;
  if (!PyArg_ParseTuple(args, "OOOOippp:poly_plan", &po, &no, &lo, &oo, &threads, &codes, &decoded, &lambert))
    return nullptr;
  HostArgs h;
  if (!parse_host(oo, po, {{no, "normals", kOnePerPoint}, {lo, "light", kAnyRows}}, h)) return nullptr;
  const int64_t N = h.n;
  const char dt = h.dt;
  int32_t *cls, *stats;
  int64_t* off;
  double* lam = nullptr;
  PyObject* cls_o = zeros('i', {N}, &cls);
  PyObject* stats_o = cls_o ? zeros('i', {N, 2}, &stats) : nullptr;
  PyObject* off_o = stats_o ? zeros('q', {N + 1}, &off) : nullptr;
  PyObject* lam_o = !off_o ? nullptr : lambert ? zeros('d', {N}, &lam) : (Py_INCREF(Py_None), Py_None);
  if (!lam_o) {
    Py_XDECREF(cls_o);
    Py_XDECREF(stats_o);
    Py_XDECREF(off_o);
    return nullptr;
  }
  int32_t* runs = nullptr;
  void* pts = nullptr;
  int64_t nr = 0;
  int rc;
  Py_BEGIN_ALLOW_THREADS
  rc = with_host_inputs(h, [&](auto& in) {
    return poly_plan_any(in, threads, cls, stats, off, codes ? &runs : nullptr, decoded ? &pts : nullptr, &nr, lam);
  });
  Py_END_ALLOW_THREADS
  PyObject* runs_o = nullptr;
  PyObject* pts_o = nullptr;
  if (rc) {
    std::free(runs);
    std::free(pts);
    if (rc == 2)
      PyErr_SetString(PyExc_MemoryError, "jaxshadow shadow engine: out of memory for the boundary codes");
    else
      PyErr_SetString(PyExc_ValueError, "jaxshadow shadow engine: a light has more than 64 vertices");
  } else {
    runs_o = runs ? owned(runs, 'i', 4, {nr, 2, jaxshadow_abi::kCodeWidth}) : (Py_INCREF(Py_None), Py_None);
    pts_o = !runs_o ? (std::free(pts), nullptr) : pts ? owned(pts, dt, float_size(dt), {nr, 2, 3}) : (Py_INCREF(Py_None), Py_None);
  }
  if (!runs_o || !pts_o) {
    Py_XDECREF(runs_o);
    Py_DECREF(cls_o);
    Py_DECREF(stats_o);
    Py_DECREF(off_o);
    Py_DECREF(lam_o);
    return nullptr;
  }
  return Py_BuildValue("(NNNNNN)", cls_o, stats_o, off_o, runs_o, pts_o, lam_o);
}

const char kHardPlanDoc[] =
    "hard_plan(points, x, is_point, occluders, threads)\n--\n\n"
    "Hard-shadow visibility (N,) bool of the point light at x (is_point) or the directional light "
    "travelling along x; points (N, 3), x (3,) in the faces' float type.";

PyObject* py_hard_plan(PyObject*, PyObject* args) {
  PyObject *po, *xo, *oo;
  int is_point, threads;
  if (!PyArg_ParseTuple(args, "OOpOi:hard_plan", &po, &xo, &is_point, &oo, &threads)) return nullptr;
  HostArgs h;
  if (!parse_host(oo, po, {{xo, "x", 1}}, h)) return nullptr;
  const int64_t N = h.n;
  uint8_t* vis;
  PyObject* vis_o = zeros('?', {N}, &vis);
  if (!vis_o) return nullptr;
  Py_BEGIN_ALLOW_THREADS
  with_host_inputs(h, [&](auto& in) {
    const Occluders<double> occ = in.occluders();
    hard_plan<double>(N, in.points(), in.rows(0), is_point, occ, prepared(occ)->bvh, threads, vis);
    return 0;
  });
  Py_END_ALLOW_THREADS
  return vis_o;
}

const char kSegmentPlanDoc[] =
    "segment_plan(points, a, b, occluders, threads)\n--\n\n"
    "The faces that may block part of the segment light a -> b seen from each point: "
    "(offsets (N + 1,) int64, faces (C,) int32).";

PyObject* py_segment_plan(PyObject*, PyObject* args) {
  PyObject *po, *ao, *bo, *oo;
  int threads;
  if (!PyArg_ParseTuple(args, "OOOOi:segment_plan", &po, &ao, &bo, &oo, &threads)) return nullptr;
  HostArgs h;
  if (!parse_host(oo, po, {{ao, "a", 1}, {bo, "b", 1}}, h)) return nullptr;
  const int64_t N = h.n;
  int64_t* off;
  PyObject* off_o = zeros('q', {N + 1}, &off);
  if (!off_o) return nullptr;
  int32_t* faces = nullptr;
  int rc;
  Py_BEGIN_ALLOW_THREADS
  rc = with_host_inputs(h, [&](auto& in) {
    return segment_plan<double>(N, in.points(), in.rows(0), in.rows(1), in.occluders(), threads, off, &faces);
  });
  Py_END_ALLOW_THREADS
  if (rc) {
    std::free(faces);
    Py_DECREF(off_o);
    PyErr_SetString(PyExc_MemoryError, "jaxshadow shadow engine: out of memory for the segment candidates");
    return nullptr;
  }
  PyObject* faces_o = owned(faces, 'i', 4, {off[N]});
  if (!faces_o) {
    Py_DECREF(off_o);
    return nullptr;
  }
  return Py_BuildValue("(NN)", off_o, faces_o);
}

const char kSegmentPiecesDoc[] =
    "segment_pieces(points, a, b, occluders, threads)\n--\n\n"
    "The visible pieces of the segment light a -> b seen from each point (engine/silhouette_segment.h): "
    "(classes (N,) int32, candidate faces (N,) int32, offsets (N + 1,) int64, pieces (R, 2) int32 endpoint codes).";

PyObject* py_segment_pieces(PyObject*, PyObject* args) {
  PyObject *po, *ao, *bo, *oo;
  int threads;
  if (!PyArg_ParseTuple(args, "OOOOi:segment_pieces", &po, &ao, &bo, &oo, &threads)) return nullptr;
  HostArgs h;
  if (!parse_host(oo, po, {{ao, "a", 1}, {bo, "b", 1}}, h)) return nullptr;
  const int64_t N = h.n;
  int32_t *cls, *kept;
  int64_t* off;
  PyObject* cls_o = zeros('i', {N}, &cls);
  PyObject* kept_o = cls_o ? zeros('i', {N}, &kept) : nullptr;
  PyObject* off_o = kept_o ? zeros('q', {N + 1}, &off) : nullptr;
  if (!off_o) {
    Py_XDECREF(cls_o);
    Py_XDECREF(kept_o);
    return nullptr;
  }
  int32_t* pieces = nullptr;
  int rc;
  Py_BEGIN_ALLOW_THREADS
  rc = with_host_inputs(h, [&](auto& in) {
    return segment_pieces_plan<double>(N, in.points(), in.rows(0), in.rows(1), in.occluders(), threads, cls, kept,
                                       off, &pieces);
  });
  Py_END_ALLOW_THREADS
  if (rc) {
    std::free(pieces);
    Py_DECREF(cls_o);
    Py_DECREF(kept_o);
    Py_DECREF(off_o);
    PyErr_SetString(PyExc_MemoryError, "jaxshadow shadow engine: out of memory for the segment pieces");
    return nullptr;
  }
  PyObject* pieces_o = owned(pieces, 'i', 4, {off[N], 2});
  if (!pieces_o) {
    Py_DECREF(cls_o);
    Py_DECREF(kept_o);
    Py_DECREF(off_o);
    return nullptr;
  }
  return Py_BuildValue("(NNNN)", cls_o, kept_o, off_o, pieces_o);
}

PyObject* py_prepared_stats(PyObject*, PyObject*) {
  const PreparedStats& s = prepared_stats();
  return Py_BuildValue("{s:L,s:L,s:L,s:L}", "lookups", (long long)s.lookups.load(), "hits", (long long)s.hits.load(),
                       "builds", (long long)s.builds.load(), "polygon_builds", (long long)s.polygon_builds.load());
}

}  // namespace

namespace {

// {target name: PyCapsule} of the XLA FFI handlers (empty without JAXSHADOW_FFI).
PyObject* py_ffi_handlers(PyObject*, PyObject*) {
  PyObject* d = PyDict_New();
  if (!d) return nullptr;
#ifdef JAXSHADOW_FFI
  const std::pair<const char*, void*> handlers[] = {
      {"jaxshadow_poly_codes", reinterpret_cast<void*>(JaxshadowPolyCodes)},
      {"jaxshadow_hard_visibility", reinterpret_cast<void*>(JaxshadowHardVisibility)},
      {"jaxshadow_segment_candidates", reinterpret_cast<void*>(JaxshadowSegmentCandidates)},
      {"jaxshadow_segment_pieces", reinterpret_cast<void*>(JaxshadowSegmentPieces)},
  };
  for (const auto& h : handlers) {
    PyObject* cap = PyCapsule_New(h.second, nullptr, nullptr);
    if (!cap || PyDict_SetItemString(d, h.first, cap) < 0) {
      Py_XDECREF(cap);
      Py_DECREF(d);
      return nullptr;
    }
    Py_DECREF(cap);
  }
#endif
  return d;
}

PyMethodDef shadowc_methods[] = {
    {"poly_plan", py_poly_plan, METH_VARARGS, kPolyPlanDoc},
    {"hard_plan", py_hard_plan, METH_VARARGS, kHardPlanDoc},
    {"segment_plan", py_segment_plan, METH_VARARGS, kSegmentPlanDoc},
    {"segment_pieces", py_segment_pieces, METH_VARARGS, kSegmentPiecesDoc},
    {"prepared_stats", py_prepared_stats, METH_NOARGS,
     "prepared_stats()\n--\n\nThe prepared-occluder cache's counts since the process started (engine/prepared.h): "
     "{'lookups', 'hits', 'builds', 'polygon_builds'}."},
    {"ffi_handlers", py_ffi_handlers, METH_NOARGS,
     "ffi_handlers()\n--\n\n{XLA FFI target name: PyCapsule} of the engine's handlers (empty when built without them)."},
    {nullptr, nullptr, 0, nullptr},
};

PyModuleDef shadowc_module = {PyModuleDef_HEAD_INIT, "_shadowc",
                              "jaxshadow's shadow engine: host entry points and XLA FFI handlers (csrc/shadowc.cc).",
                              -1, shadowc_methods, nullptr, nullptr, nullptr, nullptr};

}  // namespace

PyMODINIT_FUNC PyInit__shadowc(void) {
  if (!OwnedType.tp_name) {
    OwnedType.tp_name = "jaxshadow._shadows._shadowc.Owned";
    OwnedType.tp_basicsize = sizeof(Owned);
    OwnedType.tp_flags = Py_TPFLAGS_DEFAULT;
    OwnedType.tp_dealloc = owned_dealloc;
    OwnedType.tp_as_buffer = &owned_buffer_procs;
    OwnedType.tp_doc = "An array the shadow engine allocated, freed with its last view (buffer protocol).";
  }
  if (PyType_Ready(&OwnedType) < 0) return nullptr;
  PyObject* m = PyModule_Create(&shadowc_module);
  if (!m) return nullptr;
#ifdef JAXSHADOW_FFI
  const bool has_ffi = true;
#ifdef JAXSHADOW_JAXLIB_VERSION
  PyObject* jaxlib_version = PyUnicode_FromString(JAXSHADOW_JAXLIB_VERSION);
#else
  PyObject* jaxlib_version = (Py_INCREF(Py_None), Py_None);
#endif
#else
  const bool has_ffi = false;
  PyObject* jaxlib_version = (Py_INCREF(Py_None), Py_None);
#endif
  Py_INCREF(&OwnedType);
  if (PyModule_AddIntConstant(m, "ABI_VERSION", kAbiVersion) < 0 ||
      PyModule_AddIntConstant(m, "CODE_WIDTH", jaxshadow_abi::kCodeWidth) < 0 ||
      PyModule_AddObject(m, "HAS_FFI", PyBool_FromLong(has_ffi)) < 0 || !jaxlib_version ||
      PyModule_AddObject(m, "JAXLIB_VERSION", jaxlib_version) < 0 ||
      PyModule_AddObject(m, "Owned", reinterpret_cast<PyObject*>(&OwnedType)) < 0) {
    Py_DECREF(m);
    return nullptr;
  }
  return m;
}
