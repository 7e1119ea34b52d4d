// The shadow engine's XLA FFI handlers (part of `csrc/shadowc.cc`, which exports them as
// PyCapsules): the polygon codes, hard-shadow visibility and segment-light candidates of inputs
// that are traced, inside a compiled computation. Needs jaxlib's headers (JAXSHADOW_FFI).
#ifndef JAXSHADOW_FFI_H_
#define JAXSHADOW_FFI_H_

#include <deque>
#include <string>
#include <utility>
#include <vector>

#include "inputs.h"
#include "engine/silhouette_segment.h"
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace jaxshadow_binding {
// ----------------------------------------------------------------------------------------------
// XLA FFI handlers: the engine inside a compiled computation
// ----------------------------------------------------------------------------------------------

using S32 = ffi::Buffer<ffi::S32>;

// The occluder topology buffers of a handler (`OccluderInputs`' order), batched like its faces.
struct Topology {
  S32 face_solid, face_closed, solid_faces, solid_edge_off, solid_edges;
};

// A handler's inputs after the prologue every handler shares (`with_inputs`): the batch
// (vmap_method="broadcast_all": points (..., N, 3) and faces (..., M, Ko, 3) share a leading batch
// shape of `nb` axes, B batches of N points), the points and the occluder faces converted to
// double once; T is the inputs' float type. Other batched inputs are converted by `batched`;
// `occluders(b, K)` is batch b's occluders in the engine's form (K light vertices before the faces).
template <class T>
struct Inputs {
  size_t nb = 0;
  int64_t B = 1, N = 0;
  const double* points = nullptr;

  Inputs(ffi::AnyBuffer p, ffi::AnyBuffer faces, const Topology& t) {
    auto pd = p.dimensions();
    auto fd = faces.dimensions();
    nb = pd.size() - 2;
    for (size_t i = 0; i < nb; i++) B *= pd[i];
    N = pd[nb];
    occ_.M = fd[nb];
    occ_.Ko = fd[nb + 1];
    auto sd = t.solid_faces.dimensions();
    occ_.S = sd[sd.size() - 2];
    auto ed = t.solid_edges.dimensions();
    NE_ = ed[ed.size() - 2];
    points = batched(p, N * 3);
    occ_.faces = batched(faces, occ_.M * occ_.Ko * 3);
    occ_.face_solid = t.face_solid.typed_data();
    occ_.face_closed = t.face_closed.typed_data();
    occ_.solid_faces = t.solid_faces.typed_data();
    occ_.solid_edge_off = t.solid_edge_off.typed_data();
    occ_.solid_edges = t.solid_edges.typed_data();
  }

  // A batched input of `per_batch` values per batch, as double (held as long as the inputs are).
  const double* batched(ffi::AnyBuffer x, int64_t per_batch) {
    store_.emplace_back();
    return as_double<T>(x.untyped_data(), size_t(B * per_batch), store_.back());
  }

  // Batch b's occluders (already double), K light vertices before the face refs.
  Occluders<double> occluders(int64_t b, int64_t K = 0) const {
    OccluderInputs o = occ_;
    o.faces = static_cast<const double*>(occ_.faces) + b * o.M * o.Ko * 3;
    o.face_solid += b * o.M;
    o.face_closed += b * o.M;
    o.solid_faces += b * 2 * o.S;
    o.solid_edge_off += b * (o.S + 1);
    o.solid_edges += b * 4 * NE_;
    std::vector<double> none;  // the faces are double: occ_double copies nothing
    return occ_double<double>(K, o, none);
  }

 private:
  OccluderInputs occ_;
  int64_t NE_ = 0;
  std::deque<std::vector<double>> store_;  // converted inputs (a deque: earlier ones never move)
};

inline ffi::Error invalid(const char* name, const char* what) {
  return ffi::Error::InvalidArgument(std::string(name) + ": " + what);
}

// The prologue of every handler: the ranks checked, the float dispatch on the points' element
// type, the inputs converted (`Inputs<T>`); then `body(inputs)`.
template <class F>
ffi::Error with_inputs(const char* name, ffi::AnyBuffer points, ffi::AnyBuffer faces, const Topology& topology,
                       F&& body) {
  auto pd = points.dimensions();
  auto fd = faces.dimensions();
  if (pd.size() < 2 || fd.size() < 3 || fd.size() != pd.size() + 1) return invalid(name, "bad ranks");
  const auto t = points.element_type();
  if (t != ffi::F64 && t != ffi::F32) return invalid(name, "float32 or float64 only");
  return by_float(t == ffi::F64, [&](auto zero) {
    Inputs<decltype(zero)> in(points, faces, topology);
    return body(in);
  });
}

// Polygon codes: points (..., N, 3), normals (..., N, 3), light (..., K, 3), faces (..., M, Ko, 3)
// and the occluder topology. Outputs: classes (..., N), counts (..., N), runs (..., N, cap, 2, 7).
ffi::Error poly_ffi(ffi::AnyBuffer points, ffi::AnyBuffer normals, ffi::AnyBuffer light, ffi::AnyBuffer faces,
                    S32 face_solid, S32 face_closed, S32 solid_faces, S32 solid_edge_off, S32 solid_edges, int64_t cap,
                    int64_t threads, ffi::Result<S32> cls, ffi::Result<S32> counts, ffi::Result<S32> runs) {
  const char* name = "jaxshadow_poly_codes";
  const Topology topology{face_solid, face_closed, solid_faces, solid_edge_off, solid_edges};
  return with_inputs(name, points, faces, topology, [&](auto& in) {
    auto ld_ = light.dimensions();
    if (ld_.size() != in.nb + 2) return invalid(name, "bad ranks");
    const int64_t N = in.N, K = ld_[in.nb];
    const double* Nr = in.batched(normals, N * 3);
    const double* E = in.batched(light, K * 3);
    for (int64_t b = 0; b < in.B; b++) {
      int rc = poly_fixed<double>(N, in.points + b * N * 3, Nr + b * N * 3, K, E + b * K * 3, in.occluders(b, K),
                                  int(threads), cap, cls->typed_data() + b * N, counts->typed_data() + b * N,
                                  runs->typed_data() + b * N * cap * jaxshadow_abi::kRunWidth);
      if (rc) return invalid(name, "light with more than 64 vertices");
    }
    return ffi::Error::Success();
  });
}

// Hard shadows: visible (..., N) int32 (1 visible, 0 blocked) of point lights (is_point = 1: x a
// position) or directional lights (x the direction of travel).
ffi::Error hard_ffi(ffi::AnyBuffer points, ffi::AnyBuffer x, ffi::AnyBuffer faces, S32 face_solid, S32 face_closed,
                    S32 solid_faces, S32 solid_edge_off, S32 solid_edges, int64_t is_point, int64_t threads,
                    ffi::Result<S32> visible) {
  const Topology topology{face_solid, face_closed, solid_faces, solid_edge_off, solid_edges};
  return with_inputs("jaxshadow_hard_visibility", points, faces, topology, [&](auto& in) {
    const int64_t N = in.N;
    const double* X = in.batched(x, 3);
    std::vector<uint8_t> vis(N);
    for (int64_t b = 0; b < in.B; b++) {
      hard_plan<double>(N, in.points + b * N * 3, X + b * 3, int(is_point), in.occluders(b), int(threads), vis.data());
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
  const Topology topology{face_solid, face_closed, solid_faces, solid_edge_off, solid_edges};
  return with_inputs("jaxshadow_segment_candidates", points, faces, topology, [&](auto& in) {
    const int64_t N = in.N;
    const double* AB = in.batched(ends, 6);
    for (int64_t b = 0; b < in.B; b++) {
      const Occluders<double> occ = in.occluders(b);
      BVH bvh = build_bvh(occ);
      V3<double> a = ld(AB + b * 6), bb = ld(AB + b * 6 + 3);
      const double* Pb = in.points + b * N * 3;
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

// Segment-light visible pieces (engine/silhouette_segment.h): classes (..., N), counts (..., N)
// and the first `cap` pieces of each receiver (..., N, cap, 2) as endpoint codes.
ffi::Error segment_pieces_ffi(ffi::AnyBuffer points, ffi::AnyBuffer ends, ffi::AnyBuffer faces, S32 face_solid,
                              S32 face_closed, S32 solid_faces, S32 solid_edge_off, S32 solid_edges, int64_t cap,
                              int64_t threads, ffi::Result<S32> cls, ffi::Result<S32> counts, ffi::Result<S32> pieces) {
  const Topology topology{face_solid, face_closed, solid_faces, solid_edge_off, solid_edges};
  return with_inputs("jaxshadow_segment_pieces", points, faces, topology, [&](auto& in) {
    const int64_t N = in.N;
    const double* AB = in.batched(ends, 6);
    for (int64_t b = 0; b < in.B; b++)
      segment_pieces_fixed<double>(N, in.points + b * N * 3, AB + b * 6, AB + b * 6 + 3, in.occluders(b),
                                   int(threads), cap, cls->typed_data() + b * N, counts->typed_data() + b * N,
                                   pieces->typed_data() + b * N * cap * 2);
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

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxshadowSegmentPieces, jaxshadow_binding::segment_pieces_ffi,
                              jaxshadow_binding::occluder_args(ffi::Ffi::Bind()
                                                                   .Arg<ffi::AnyBuffer>()   // points
                                                                   .Arg<ffi::AnyBuffer>())  // ends (2, 3)
                                  .Attr<int64_t>("cap")
                                  .Attr<int64_t>("threads")
                                  .Ret<S32>()
                                  .Ret<S32>()
                                  .Ret<S32>());

#endif  // JAXSHADOW_FFI_H_
