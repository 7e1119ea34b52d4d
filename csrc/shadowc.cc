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
// Build: plain C++17, no dependencies; IEEE arithmetic without contraction into fused
// multiply-adds (setup.py passes -ffp-contract=off), so that the decisions round as NumPy's do.
// With JAXSHADOW_FFI (setup.py defines it when jaxlib's XLA FFI headers are found) the polygon
// combinatorics are also exported as an XLA FFI handler, for programs that compute them inside a
// compiled computation (traced receivers, light fits); otherwise only the C entry points exist

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <type_traits>

#include "engine/driver.h"

using namespace jaxshadow_engine;  // NOLINT: this file only binds the engine to C and XLA

// ----------------------------------------------------------------------------------------------
// C entry points (ctypes)
// ----------------------------------------------------------------------------------------------

#define JS_OCC_ARGS                                                                                           \
  int64_t M, int64_t Ko, const void *faces, const int32_t *face_solid, const int32_t *face_closed, int64_t S, \
      const int32_t *solid_faces, const int32_t *solid_edge_off, const int32_t *solid_edges
#define JS_OCC_PARAMS JS_OCC_ARGS

namespace {

// Every decision is made in double precision, whatever the inputs' dtype: float32 inputs are
// exact in double, and the combinatorics (which occluders, which pieces of which edges) are then
// those of the exact float32 geometry, resolved far below float32's rounding (a receiver 1e-6
// under a light, an occluder 5e-7 under it: float32 planes through the receiver differ by less
// than its own collinearity tolerance). Only the points the JAX side integrates are float32.
template <class T>
const double* as_double(const void* x, size_t n, std::vector<double>& store) {
  if (std::is_same<T, double>::value) return static_cast<const double*>(x);
  const T* t = static_cast<const T*>(x);
  store.assign(t, t + n);
  return store.data();
}

struct Inputs {
  std::vector<double> p, n, e, f;
};

template <class T>
Occluders<double> occ_double(int64_t K, JS_OCC_PARAMS, Inputs& in) {
  return make_occ<double>(K, M, Ko, as_double<T>(faces, size_t(M * Ko * 3), in.f), face_solid, face_closed, S,
                          solid_faces, solid_edge_off, solid_edges);
}

template <class T>
int poly_plan_any(int64_t N, const void* P, const void* Nrm, int64_t K, const void* E, JS_OCC_PARAMS, int threads,
                  int32_t* cls, int32_t* stats, int64_t* offsets, int32_t** runs, void** points, int64_t* nruns,
                  double* lambert) {
  Inputs in;
  auto occ = occ_double<T>(K, M, Ko, faces, face_solid, face_closed, S, solid_faces, solid_edge_off, solid_edges, in);
  double* pts = nullptr;
  int rc = poly_plan<double>(N, as_double<T>(P, size_t(3 * N), in.p), as_double<T>(Nrm, size_t(3 * N), in.n), K,
                             as_double<T>(E, size_t(3 * K), in.e), occ, threads, cls, stats, offsets, runs,
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

}  // namespace

extern "C" {

int jaxshadow_shadowc_abi(void) { return 2; }

void jaxshadow_free(void* p) { std::free(p); }

// `lambert` (N doubles, or null): each receiver's sum of Lambert's edge terms over its boundary
// (driver.h, lambert_edge).
int jaxshadow_poly_plan(int is_f64, int64_t N, const void* P, const void* Nrm, int64_t K, const void* E, JS_OCC_ARGS,
                        int threads, int32_t* cls, int32_t* stats, int64_t* offsets, int32_t** runs, void** points,
                        int64_t* nruns, double* lambert) {
  auto fn = is_f64 ? poly_plan_any<double> : poly_plan_any<float>;
  return fn(N, P, Nrm, K, E, M, Ko, faces, face_solid, face_closed, S, solid_faces, solid_edge_off, solid_edges,
            threads, cls, stats, offsets, runs, points, nruns, lambert);
}

int jaxshadow_poly_fixed(int is_f64, int64_t N, const void* P, const void* Nrm, int64_t K, const void* E, JS_OCC_ARGS,
                         int threads, int64_t cap, int32_t* cls, int32_t* counts, int32_t* runs) {
  Inputs in;
  auto occ = is_f64 ? occ_double<double>(K, M, Ko, faces, face_solid, face_closed, S, solid_faces, solid_edge_off,
                                         solid_edges, in)
                    : occ_double<float>(K, M, Ko, faces, face_solid, face_closed, S, solid_faces, solid_edge_off,
                                        solid_edges, in);
  auto cv = is_f64 ? as_double<double> : as_double<float>;
  return poly_fixed<double>(N, cv(P, size_t(3 * N), in.p), cv(Nrm, size_t(3 * N), in.n), K, cv(E, size_t(3 * K), in.e),
                            occ, threads, cap, cls, counts, runs);
}

int jaxshadow_hard_plan(int is_f64, int64_t N, const void* P, const void* X, int is_point, int64_t K_unused,
                        JS_OCC_ARGS, int threads, uint8_t* visible) {
  (void)K_unused;
  Inputs in;
  auto occ = is_f64 ? occ_double<double>(0, M, Ko, faces, face_solid, face_closed, S, solid_faces, solid_edge_off,
                                         solid_edges, in)
                    : occ_double<float>(0, M, Ko, faces, face_solid, face_closed, S, solid_faces, solid_edge_off,
                                        solid_edges, in);
  auto cv = is_f64 ? as_double<double> : as_double<float>;
  return hard_plan<double>(N, cv(P, size_t(3 * N), in.p), cv(X, 3, in.e), is_point, occ, threads, visible);
}

int jaxshadow_segment_plan(int is_f64, int64_t N, const void* P, const void* A, const void* B, JS_OCC_ARGS,
                           int threads, int64_t* offsets, int32_t** faces_out) {
  Inputs in;
  auto occ = is_f64 ? occ_double<double>(0, M, Ko, faces, face_solid, face_closed, S, solid_faces, solid_edge_off,
                                         solid_edges, in)
                    : occ_double<float>(0, M, Ko, faces, face_solid, face_closed, S, solid_faces, solid_edge_off,
                                        solid_edges, in);
  auto cv = is_f64 ? as_double<double> : as_double<float>;
  std::vector<double> b;
  return segment_plan<double>(N, cv(P, size_t(3 * N), in.p), cv(A, 3, in.e), cv(B, 3, b), occ, threads, offsets,
                              faces_out);
}

}  // extern "C"

// ----------------------------------------------------------------------------------------------
// XLA FFI handler: the polygon combinatorics inside a compiled computation
// ----------------------------------------------------------------------------------------------
#ifdef JAXSHADOW_FFI
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

// A handler's occluder inputs, batched like its points: faces (..., M, Ko, 3), converted to double
// once, and the topology arrays; `at(b)` is batch b's Occluders (light vertices K before the faces).
template <class T>
struct FfiOccluders {
  int64_t K, M, Ko, S, NE;
  std::vector<double> store;
  const double* F;
  const int32_t *face_solid, *face_closed, *solid_faces, *solid_edge_off, *solid_edges;
  FfiOccluders(int64_t K_, int64_t B, size_t nb, ffi::AnyBuffer faces, ffi::Buffer<ffi::S32> fsolid,
               ffi::Buffer<ffi::S32> fclosed, ffi::Buffer<ffi::S32> sfaces, ffi::Buffer<ffi::S32> soff,
               ffi::Buffer<ffi::S32> sedges)
      : K(K_) {
    auto fd = faces.dimensions();
    M = fd[nb];
    Ko = fd[nb + 1];
    auto sd = sfaces.dimensions();
    S = sd[sd.size() - 2];
    auto ed = sedges.dimensions();
    NE = ed[ed.size() - 2];
    F = as_double<T>(faces.untyped_data(), size_t(B * M * Ko * 3), store);
    face_solid = fsolid.typed_data();
    face_closed = fclosed.typed_data();
    solid_faces = sfaces.typed_data();
    solid_edge_off = soff.typed_data();
    solid_edges = sedges.typed_data();
  }
  Occluders<double> at(int64_t b) const {
    return make_occ<double>(K, M, Ko, F + b * M * Ko * 3, face_solid + b * M, face_closed + b * M, S,
                            solid_faces + b * 2 * S, solid_edge_off + b * (S + 1), solid_edges + b * 4 * NE);
  }
};

// Inputs with a common leading batch shape (vmap_method="broadcast_all"): points (..., N, 3),
// normals (..., N, 3), light (..., K, 3), faces (..., M, Ko, 3), and the occluder topology
// (int32, batched alike). Outputs: classes (..., N), counts (..., N), runs (..., N, cap, 2, 7).
template <class T>
ffi::Error poly_ffi_typed(ffi::AnyBuffer points, ffi::AnyBuffer normals, ffi::AnyBuffer light, ffi::AnyBuffer faces,
                          ffi::Buffer<ffi::S32> face_solid, ffi::Buffer<ffi::S32> face_closed,
                          ffi::Buffer<ffi::S32> solid_faces, ffi::Buffer<ffi::S32> solid_edge_off,
                          ffi::Buffer<ffi::S32> solid_edges, int64_t cap, int64_t threads,
                          ffi::Result<ffi::Buffer<ffi::S32>> cls, ffi::Result<ffi::Buffer<ffi::S32>> counts,
                          ffi::Result<ffi::Buffer<ffi::S32>> runs) {
  auto pd = points.dimensions();
  auto ld_ = light.dimensions();
  auto fd = faces.dimensions();
  if (pd.size() < 2 || ld_.size() < 2 || fd.size() < 3) return ffi::Error::InvalidArgument("jaxshadow_poly_codes: bad ranks");
  const size_t nb = pd.size() - 2;
  if (ld_.size() != nb + 2 || fd.size() != nb + 3) return ffi::Error::InvalidArgument("jaxshadow_poly_codes: batch ranks differ");
  int64_t B = 1;
  for (size_t i = 0; i < nb; i++) B *= pd[i];
  const int64_t N = pd[nb], K = ld_[nb];
  const FfiOccluders<T> fo(K, B, nb, faces, face_solid, face_closed, solid_faces, solid_edge_off, solid_edges);
  std::vector<double> sp, sn, se;
  const double* P = as_double<T>(points.untyped_data(), size_t(B * N * 3), sp);
  const double* Nr = as_double<T>(normals.untyped_data(), size_t(B * N * 3), sn);
  const double* E = as_double<T>(light.untyped_data(), size_t(B * K * 3), se);
  for (int64_t b = 0; b < B; b++) {
    auto occ = fo.at(b);
    int rc = poly_fixed<double>(N, P + b * N * 3, Nr + b * N * 3, K, E + b * K * 3, occ, int(threads), cap,
                           cls->typed_data() + b * N, counts->typed_data() + b * N, runs->typed_data() + b * N * cap * 14);
    if (rc) return ffi::Error::InvalidArgument("jaxshadow_poly_codes: light with more than 64 vertices");
  }
  return ffi::Error::Success();
}

ffi::Error poly_ffi(ffi::AnyBuffer points, ffi::AnyBuffer normals, ffi::AnyBuffer light, ffi::AnyBuffer faces,
                    ffi::Buffer<ffi::S32> face_solid, ffi::Buffer<ffi::S32> face_closed,
                    ffi::Buffer<ffi::S32> solid_faces, ffi::Buffer<ffi::S32> solid_edge_off,
                    ffi::Buffer<ffi::S32> solid_edges, int64_t cap, int64_t threads,
                    ffi::Result<ffi::Buffer<ffi::S32>> cls, ffi::Result<ffi::Buffer<ffi::S32>> counts,
                    ffi::Result<ffi::Buffer<ffi::S32>> runs) {
  if (points.element_type() == ffi::F64)
    return poly_ffi_typed<double>(points, normals, light, faces, face_solid, face_closed, solid_faces, solid_edge_off,
                                  solid_edges, cap, threads, cls, counts, runs);
  if (points.element_type() == ffi::F32)
    return poly_ffi_typed<float>(points, normals, light, faces, face_solid, face_closed, solid_faces, solid_edge_off,
                                 solid_edges, cap, threads, cls, counts, runs);
  return ffi::Error::InvalidArgument("jaxshadow_poly_codes: float32 or float64 only");
}


// Hard shadows inside a compiled computation: visible (..., N) int32 (1 visible, 0 blocked) of
// point lights (is_point = 1: x a position) or directional lights (x the direction of travel).
template <class T>
ffi::Error hard_ffi_typed(ffi::AnyBuffer points, ffi::AnyBuffer x, ffi::AnyBuffer faces, ffi::Buffer<ffi::S32> face_solid,
                          ffi::Buffer<ffi::S32> face_closed, ffi::Buffer<ffi::S32> solid_faces,
                          ffi::Buffer<ffi::S32> solid_edge_off, ffi::Buffer<ffi::S32> solid_edges, int64_t is_point,
                          int64_t threads, ffi::Result<ffi::Buffer<ffi::S32>> visible) {
  auto pd = points.dimensions();
  auto fd = faces.dimensions();
  if (pd.size() < 2 || fd.size() < 3) return ffi::Error::InvalidArgument("jaxshadow_hard_visibility: bad ranks");
  const size_t nb = pd.size() - 2;
  int64_t B = 1;
  for (size_t i = 0; i < nb; i++) B *= pd[i];
  const int64_t N = pd[nb];
  const FfiOccluders<T> fo(0, B, nb, faces, face_solid, face_closed, solid_faces, solid_edge_off, solid_edges);
  std::vector<double> sp, sx;
  const double* P = as_double<T>(points.untyped_data(), size_t(B * N * 3), sp);
  const double* X = as_double<T>(x.untyped_data(), size_t(B * 3), sx);
  std::vector<uint8_t> vis(N);
  for (int64_t b = 0; b < B; b++) {
    auto occ = fo.at(b);
    hard_plan<double>(N, P + b * N * 3, X + b * 3, int(is_point), occ, int(threads), vis.data());
    int32_t* out = visible->typed_data() + b * N;
    for (int64_t i = 0; i < N; i++) out[i] = vis[i];
  }
  return ffi::Error::Success();
}

ffi::Error hard_ffi(ffi::AnyBuffer points, ffi::AnyBuffer x, ffi::AnyBuffer faces, ffi::Buffer<ffi::S32> face_solid,
                    ffi::Buffer<ffi::S32> face_closed, ffi::Buffer<ffi::S32> solid_faces,
                    ffi::Buffer<ffi::S32> solid_edge_off, ffi::Buffer<ffi::S32> solid_edges, int64_t is_point,
                    int64_t threads, ffi::Result<ffi::Buffer<ffi::S32>> visible) {
  if (points.element_type() == ffi::F64)
    return hard_ffi_typed<double>(points, x, faces, face_solid, face_closed, solid_faces, solid_edge_off, solid_edges,
                                  is_point, threads, visible);
  if (points.element_type() == ffi::F32)
    return hard_ffi_typed<float>(points, x, faces, face_solid, face_closed, solid_faces, solid_edge_off, solid_edges,
                                 is_point, threads, visible);
  return ffi::Error::InvalidArgument("jaxshadow_hard_visibility: float32 or float64 only");
}

// Segment-light candidates inside a compiled computation: counts (..., N) and the first `cap`
// candidate faces of each receiver (..., N, cap), -1 in unused slots.
template <class T>
ffi::Error segment_ffi_typed(ffi::AnyBuffer points, ffi::AnyBuffer ends, ffi::AnyBuffer faces,
                             ffi::Buffer<ffi::S32> face_solid, ffi::Buffer<ffi::S32> face_closed,
                             ffi::Buffer<ffi::S32> solid_faces, ffi::Buffer<ffi::S32> solid_edge_off,
                             ffi::Buffer<ffi::S32> solid_edges, int64_t cap, int64_t threads,
                             ffi::Result<ffi::Buffer<ffi::S32>> counts, ffi::Result<ffi::Buffer<ffi::S32>> cand) {
  auto pd = points.dimensions();
  auto fd = faces.dimensions();
  if (pd.size() < 2 || fd.size() < 3) return ffi::Error::InvalidArgument("jaxshadow_segment_candidates: bad ranks");
  const size_t nb = pd.size() - 2;
  int64_t B = 1;
  for (size_t i = 0; i < nb; i++) B *= pd[i];
  const int64_t N = pd[nb];
  const FfiOccluders<T> fo(0, B, nb, faces, face_solid, face_closed, solid_faces, solid_edge_off, solid_edges);
  std::vector<double> sp, sab;
  const double* P = as_double<T>(points.untyped_data(), size_t(B * N * 3), sp);
  const double* AB = as_double<T>(ends.untyped_data(), size_t(B * 6), sab);
  for (int64_t b = 0; b < B; b++) {
    auto occ = fo.at(b);
    BVH bvh = build_bvh(occ);
    V3<double> a = ld(AB + b * 6), bb = ld(AB + b * 6 + 3);
    const double* Pb = P + b * N * 3;
    int32_t* cnt = counts->typed_data() + b * N;
    int32_t* out = cand->typed_data() + b * N * cap;
    parallel_for(N, default_threads(int(threads)), [&](int, int64_t s, int64_t e) {
      std::vector<std::pair<int32_t, int32_t>> scratch;
      std::vector<int32_t> list;
      for (int64_t i = s; i < e; i++) {
        list.clear();
        segment_candidates(occ, bvh, ld(Pb + 3 * i), a, bb, list, scratch);
        cnt[i] = int32_t(list.size());
        for (int64_t k = 0; k < cap; k++) out[i * cap + k] = k < int64_t(list.size()) ? list[k] : -1;
      }
    });
  }
  return ffi::Error::Success();
}

ffi::Error segment_ffi(ffi::AnyBuffer points, ffi::AnyBuffer ends, ffi::AnyBuffer faces, ffi::Buffer<ffi::S32> face_solid,
                       ffi::Buffer<ffi::S32> face_closed, ffi::Buffer<ffi::S32> solid_faces,
                       ffi::Buffer<ffi::S32> solid_edge_off, ffi::Buffer<ffi::S32> solid_edges, int64_t cap,
                       int64_t threads, ffi::Result<ffi::Buffer<ffi::S32>> counts,
                       ffi::Result<ffi::Buffer<ffi::S32>> cand) {
  if (points.element_type() == ffi::F64)
    return segment_ffi_typed<double>(points, ends, faces, face_solid, face_closed, solid_faces, solid_edge_off,
                                     solid_edges, cap, threads, counts, cand);
  if (points.element_type() == ffi::F32)
    return segment_ffi_typed<float>(points, ends, faces, face_solid, face_closed, solid_faces, solid_edge_off,
                                    solid_edges, cap, threads, counts, cand);
  return ffi::Error::InvalidArgument("jaxshadow_segment_candidates: float32 or float64 only");
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxshadowPolyCodes, poly_ffi,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Attr<int64_t>("cap")
                                  .Attr<int64_t>("threads")
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxshadowHardVisibility, hard_ffi,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Attr<int64_t>("is_point")
                                  .Attr<int64_t>("threads")
                                  .Ret<ffi::Buffer<ffi::S32>>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxshadowSegmentCandidates, segment_ffi,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Attr<int64_t>("cap")
                                  .Attr<int64_t>("threads")
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>());

extern "C" int jaxshadow_has_ffi(void) { return 1; }
#else
extern "C" int jaxshadow_has_ffi(void) { return 0; }
#endif

// An importable (empty) module, so that the package can locate the shared library.
static struct PyModuleDef shadowc_module = {PyModuleDef_HEAD_INIT, "_shadowc",
                                            "jaxshadow's shadow engine (ctypes and XLA FFI entry points).", -1,
                                            nullptr, nullptr, nullptr, nullptr, nullptr};
PyMODINIT_FUNC PyInit__shadowc(void) { return PyModule_Create(&shadowc_module); }
