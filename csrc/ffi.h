// The shadow engine's XLA FFI handlers (part of `csrc/shadowc.cc`, which exports them as
// PyCapsules): the polygon codes, hard-shadow visibility and segment-light candidates of inputs
// that are traced, inside a compiled computation. Needs jaxlib's headers (JAXSHADOW_FFI).
#ifndef JAXSHADOW_FFI_H_
#define JAXSHADOW_FFI_H_

#include <string>
#include <utility>

#include "inputs.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace jaxshadow_binding {
// ----------------------------------------------------------------------------------------------
// XLA FFI handlers: the engine inside a compiled computation
// ----------------------------------------------------------------------------------------------

using S32 = ffi::Buffer<ffi::S32>;

// A handler's occluder inputs, batched like its points: faces (..., M, Ko, 3), converted to double
// once, and the topology arrays (batched alike); `at(b)` is batch b's OccluderInputs.
struct FfiOccluders {
  OccluderInputs first;
  int64_t NE = 0;
  std::vector<double> store;
  template <class T>
  FfiOccluders(T, int64_t B, size_t nb, ffi::AnyBuffer faces, S32 fsolid, S32 fclosed, S32 sfaces, S32 soff,
               S32 sedges) {
    auto fd = faces.dimensions();
    first.M = fd[nb];
    first.Ko = fd[nb + 1];
    auto sd = sfaces.dimensions();
    first.S = sd[sd.size() - 2];
    auto ed = sedges.dimensions();
    NE = ed[ed.size() - 2];
    first.faces = as_double<T>(faces.untyped_data(), size_t(B * first.M * first.Ko * 3), store);
    first.face_solid = fsolid.typed_data();
    first.face_closed = fclosed.typed_data();
    first.solid_faces = sfaces.typed_data();
    first.solid_edge_off = soff.typed_data();
    first.solid_edges = sedges.typed_data();
  }
  OccluderInputs at(int64_t b) const {
    OccluderInputs o = first;
    o.faces = static_cast<const double*>(first.faces) + b * o.M * o.Ko * 3;
    o.face_solid += b * o.M;
    o.face_closed += b * o.M;
    o.solid_faces += b * 2 * o.S;
    o.solid_edge_off += b * (o.S + 1);
    o.solid_edges += b * 4 * NE;
    return o;
  }
};

// The batch of a handler's inputs (vmap_method="broadcast_all": a common leading batch shape):
// points (..., N, 3) and faces (..., M, Ko, 3); B batches of N points.
struct Batch {
  size_t nb = 0;
  int64_t B = 1, N = 0;
};

bool batch_of(ffi::AnyBuffer points, ffi::AnyBuffer faces, Batch* out) {
  auto pd = points.dimensions();
  auto fd = faces.dimensions();
  if (pd.size() < 2 || fd.size() < 3 || fd.size() != pd.size() + 1) return false;
  out->nb = pd.size() - 2;
  for (size_t i = 0; i < out->nb; i++) out->B *= pd[i];
  out->N = pd[out->nb];
  return true;
}

// The float dispatch of a handler, on its points' element type.
template <class F>
ffi::Error ffi_by_float(ffi::AnyBuffer points, const char* name, F&& fn) {
  const auto t = points.element_type();
  if (t != ffi::F64 && t != ffi::F32) return ffi::Error::InvalidArgument(std::string(name) + ": float32 or float64 only");
  return by_float(t == ffi::F64, fn);
}

// Polygon codes: points (..., N, 3), normals (..., N, 3), light (..., K, 3), faces (..., M, Ko, 3)
// and the occluder topology. Outputs: classes (..., N), counts (..., N), runs (..., N, cap, 2, 7).
ffi::Error poly_ffi(ffi::AnyBuffer points, ffi::AnyBuffer normals, ffi::AnyBuffer light, ffi::AnyBuffer faces,
                    S32 face_solid, S32 face_closed, S32 solid_faces, S32 solid_edge_off, S32 solid_edges, int64_t cap,
                    int64_t threads, ffi::Result<S32> cls, ffi::Result<S32> counts, ffi::Result<S32> runs) {
  const char* name = "jaxshadow_poly_codes";
  Batch bt;
  auto ld_ = light.dimensions();
  if (!batch_of(points, faces, &bt) || ld_.size() != bt.nb + 2)
    return ffi::Error::InvalidArgument(std::string(name) + ": bad ranks");
  return ffi_by_float(points, name, [&](auto zero) {
    using T = decltype(zero);
    const int64_t B = bt.B, N = bt.N, K = ld_[bt.nb];
    const FfiOccluders fo(zero, B, bt.nb, faces, face_solid, face_closed, solid_faces, solid_edge_off, solid_edges);
    std::vector<double> sp, sn, se, unused;
    const double* P = as_double<T>(points.untyped_data(), size_t(B * N * 3), sp);
    const double* Nr = as_double<T>(normals.untyped_data(), size_t(B * N * 3), sn);
    const double* E = as_double<T>(light.untyped_data(), size_t(B * K * 3), se);
    for (int64_t b = 0; b < B; b++) {
      const Occluders<double> occ = occ_double<double>(K, fo.at(b), unused);
      int rc = poly_fixed<double>(N, P + b * N * 3, Nr + b * N * 3, K, E + b * K * 3, occ, int(threads), cap,
                                  cls->typed_data() + b * N, counts->typed_data() + b * N,
                                  runs->typed_data() + b * N * cap * jaxshadow_abi::kRunWidth);
      if (rc) return ffi::Error::InvalidArgument(std::string(name) + ": light with more than 64 vertices");
    }
    return ffi::Error::Success();
  });
}

// Hard shadows: visible (..., N) int32 (1 visible, 0 blocked) of point lights (is_point = 1: x a
// position) or directional lights (x the direction of travel).
ffi::Error hard_ffi(ffi::AnyBuffer points, ffi::AnyBuffer x, ffi::AnyBuffer faces, S32 face_solid, S32 face_closed,
                    S32 solid_faces, S32 solid_edge_off, S32 solid_edges, int64_t is_point, int64_t threads,
                    ffi::Result<S32> visible) {
  const char* name = "jaxshadow_hard_visibility";
  Batch bt;
  if (!batch_of(points, faces, &bt)) return ffi::Error::InvalidArgument(std::string(name) + ": bad ranks");
  return ffi_by_float(points, name, [&](auto zero) {
    using T = decltype(zero);
    const int64_t B = bt.B, N = bt.N;
    const FfiOccluders fo(zero, B, bt.nb, faces, face_solid, face_closed, solid_faces, solid_edge_off, solid_edges);
    std::vector<double> sp, sx, unused;
    const double* P = as_double<T>(points.untyped_data(), size_t(B * N * 3), sp);
    const double* X = as_double<T>(x.untyped_data(), size_t(B * 3), sx);
    std::vector<uint8_t> vis(N);
    for (int64_t b = 0; b < B; b++) {
      const Occluders<double> occ = occ_double<double>(0, fo.at(b), unused);
      hard_plan<double>(N, P + b * N * 3, X + b * 3, int(is_point), occ, int(threads), vis.data());
      int32_t* out = visible->typed_data() + b * N;
      for (int64_t i = 0; i < N; i++) out[i] = vis[i];
    }
    return ffi::Error::Success();
  });
}

// Segment-light candidates: counts (..., N) and the first `cap` candidate faces of each receiver
// (..., N, cap), -1 in unused slots.
ffi::Error segment_ffi(ffi::AnyBuffer points, ffi::AnyBuffer ends, ffi::AnyBuffer faces, S32 face_solid,
                       S32 face_closed, S32 solid_faces, S32 solid_edge_off, S32 solid_edges, int64_t cap,
                       int64_t threads, ffi::Result<S32> counts, ffi::Result<S32> cand) {
  const char* name = "jaxshadow_segment_candidates";
  Batch bt;
  if (!batch_of(points, faces, &bt)) return ffi::Error::InvalidArgument(std::string(name) + ": bad ranks");
  return ffi_by_float(points, name, [&](auto zero) {
    using T = decltype(zero);
    const int64_t B = bt.B, N = bt.N;
    const FfiOccluders fo(zero, B, bt.nb, faces, face_solid, face_closed, solid_faces, solid_edge_off, solid_edges);
    std::vector<double> sp, sab, unused;
    const double* P = as_double<T>(points.untyped_data(), size_t(B * N * 3), sp);
    const double* AB = as_double<T>(ends.untyped_data(), size_t(B * 6), sab);
    for (int64_t b = 0; b < B; b++) {
      const Occluders<double> occ = occ_double<double>(0, fo.at(b), unused);
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
  });
}

// The occluder arguments of every handler, after its own: faces, then the topology arrays in
// `OccluderInputs`' order.
template <class Binding>
auto occluder_args(Binding binding) {
  return std::move(binding)
      .template Arg<ffi::AnyBuffer>()
      .template Arg<S32>()
      .template Arg<S32>()
      .template Arg<S32>()
      .template Arg<S32>()
      .template Arg<S32>();
}

}  // namespace jaxshadow_binding

using jaxshadow_binding::S32;

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxshadowPolyCodes, jaxshadow_binding::poly_ffi,
                              jaxshadow_binding::occluder_args(ffi::Ffi::Bind()
                                                                   .Arg<ffi::AnyBuffer>()   // points
                                                                   .Arg<ffi::AnyBuffer>()   // normals
                                                                   .Arg<ffi::AnyBuffer>())  // light
                                  .Attr<int64_t>("cap")
                                  .Attr<int64_t>("threads")
                                  .Ret<S32>()
                                  .Ret<S32>()
                                  .Ret<S32>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxshadowHardVisibility, jaxshadow_binding::hard_ffi,
                              jaxshadow_binding::occluder_args(ffi::Ffi::Bind()
                                                                   .Arg<ffi::AnyBuffer>()   // points
                                                                   .Arg<ffi::AnyBuffer>())  // x
                                  .Attr<int64_t>("is_point")
                                  .Attr<int64_t>("threads")
                                  .Ret<S32>());

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxshadowSegmentCandidates, jaxshadow_binding::segment_ffi,
                              jaxshadow_binding::occluder_args(ffi::Ffi::Bind()
                                                                   .Arg<ffi::AnyBuffer>()   // points
                                                                   .Arg<ffi::AnyBuffer>())  // ends (2, 3)
                                  .Attr<int64_t>("cap")
                                  .Attr<int64_t>("threads")
                                  .Ret<S32>()
                                  .Ret<S32>());

#endif  // JAXSHADOW_FFI_H_
