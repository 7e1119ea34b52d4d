// The shadow engine's XLA FFI handlers (part of `csrc/shadowc.cc`, which exports them as
// PyCapsules): the polygon codes, hard-shadow visibility and segment-light candidates of inputs
// that are traced, inside a compiled computation. Needs jaxlib's headers (JAXSHADOW_FFI).
#ifndef JAXSHADOW_FFI_H_
#define JAXSHADOW_FFI_H_

#include <algorithm>
#include <deque>
#include <initializer_list>
#include <memory>
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

// The batch of a handler's call. Under `vmap` (vmap_method="expand_dims") every input carries the
// same number `nb` of leading batch axes, each of the batch's size along it, or 1 where the input
// is not batched along it (the mesh and the receivers of a fit over many light poses): such an
// input is read by every batch element, not copied B times. `BatchMap` takes the call's flat batch
// index b (row-major over the batch shape) to an input's own.
struct BatchMap {
  std::vector<int64_t> dims, stride;  // the batch shape; per axis the input's stride (0: not batched)
  bool identity = true;

  BatchMap() = default;
  BatchMap(const std::vector<int64_t>& batch, ffi::AnyBuffer::Dimensions xd) : dims(batch), stride(batch.size(), 0) {
    int64_t st = 1;
    for (size_t a = batch.size(); a-- > 0;) {
      if (xd[a] != 1 || batch[a] == 1) stride[a] = st;
      identity = identity && xd[a] == batch[a];
      st *= xd[a];
    }
  }
  int64_t operator()(int64_t b) const {
    if (identity) return b;
    int64_t at = 0;
    for (size_t a = dims.size(); a-- > 0;) {
      at += (b % dims[a]) * stride[a];
      b /= dims[a];
    }
    return at;
  }
};

// A handler's inputs after the prologue every handler shares (`with_inputs`): the batch (points
// (..., N, 3), faces (..., M, Ko, 3), the topology and the handler's further inputs share `nb`
// leading batch axes, broadcast as `BatchMap` says: B batch elements of N points), the points
// converted to double (one row block per batch element) and the occluder faces converted to double
// once (per distinct batch index of theirs); T is the inputs' float type. Other batched inputs are
// converted by `batched`; `occluders(b, K)` is batch element b's occluders in the engine's form
// (K light vertices before the faces), and `occluder_index(b)` tells elements with the same
// occluder buffers apart from others (one prepared lookup each: `prepared_for`). `error` is set when
// the batch axes do not broadcast.
template <class T>
struct Inputs {
  size_t nb = 0;
  int64_t B = 1, N = 0;
  const double* points = nullptr;
  const char* error = nullptr;

  Inputs(ffi::AnyBuffer p, ffi::AnyBuffer faces, const Topology& t, std::initializer_list<ffi::AnyBuffer> more = {}) {
    auto pd = p.dimensions();
    auto fd = faces.dimensions();
    nb = pd.size() - 2;
    const ffi::AnyBuffer::Dimensions tdims[5] = {t.face_solid.dimensions(), t.face_closed.dimensions(),
                                                 t.solid_faces.dimensions(), t.solid_edge_off.dimensions(),
                                                 t.solid_edges.dimensions()};
    std::vector<ffi::AnyBuffer::Dimensions> all = {pd, fd};
    for (const auto& d : tdims) all.push_back(d);
    for (const ffi::AnyBuffer& x : more) all.push_back(x.dimensions());
    batch_.assign(nb, 1);
    for (const auto& d : all) {
      if (d.size() < nb) {
        error = "bad ranks";
        return;
      }
      for (size_t a = 0; a < nb; a++) batch_[a] = std::max(batch_[a], d[a]);
    }
    for (const auto& d : all)
      for (size_t a = 0; a < nb; a++)
        if (d[a] != 1 && d[a] != batch_[a]) error = "batch axes that do not broadcast";
    if (error) return;
    for (size_t a = 0; a < nb; a++) B *= batch_[a];
    N = pd[nb];
    occ_.M = fd[nb];
    occ_.Ko = fd[nb + 1];
    auto sd = t.solid_faces.dimensions();
    occ_.S = sd[sd.size() - 2];
    auto ed = t.solid_edges.dimensions();
    NE_ = ed[ed.size() - 2];
    points = batched(p, N * 3);
    faces_map_ = BatchMap(batch_, fd);
    store_.emplace_back();
    int64_t nf = 1;
    for (size_t a = 0; a < nb; a++) nf *= fd[a];
    occ_.faces = as_double<T>(faces.untyped_data(), size_t(nf * occ_.M * occ_.Ko * 3), store_.back());
    for (int k = 0; k < 5; k++) topo_map_[k] = BatchMap(batch_, tdims[k]);
    occ_.face_solid = t.face_solid.typed_data();
    occ_.face_closed = t.face_closed.typed_data();
    occ_.solid_faces = t.solid_faces.typed_data();
    occ_.solid_edge_off = t.solid_edge_off.typed_data();
    occ_.solid_edges = t.solid_edges.typed_data();
  }

  // A batched input of `per_batch` values per batch element, as double, B blocks (held as long as
  // the inputs are; copied where it is converted or broadcast).
  const double* batched(ffi::AnyBuffer x, int64_t per_batch) {
    const BatchMap map(batch_, x.dimensions());
    store_.emplace_back();
    if (map.identity) return as_double<T>(x.untyped_data(), size_t(B * per_batch), store_.back());
    std::vector<double>& out = store_.back();
    out.resize(size_t(B * per_batch));
    const T* src = static_cast<const T*>(x.untyped_data());
    for (int64_t b = 0; b < B; b++) {
      const T* from = src + map(b) * per_batch;
      std::copy(from, from + per_batch, out.begin() + b * per_batch);
    }
    return out.data();
  }

  // Batch element b's occluders (already double), K light vertices before the face refs.
  Occluders<double> occluders(int64_t b, int64_t K = 0) const {
    OccluderInputs o = occ_;
    o.faces = static_cast<const double*>(occ_.faces) + faces_map_(b) * o.M * o.Ko * 3;
    o.face_solid += topo_map_[0](b) * o.M;
    o.face_closed += topo_map_[1](b) * o.M;
    o.solid_faces += topo_map_[2](b) * 2 * o.S;
    o.solid_edge_off += topo_map_[3](b) * (o.S + 1);
    o.solid_edges += topo_map_[4](b) * 4 * NE_;
    std::vector<double> none;  // the faces are double: occ_double copies nothing
    return occ_double<double>(K, o, none);
  }

  // Whether batch elements a and b read the same occluder buffers (then the same occluders).
  bool same_occluders(int64_t a, int64_t b) const {
    if (faces_map_(a) != faces_map_(b)) return false;
    for (const BatchMap& m : topo_map_)
      if (m(a) != m(b)) return false;
    return true;
  }

  // The prepared data of batch element b's occluders `occ` (`occluders(b, K)`), looked up again
  // only where b reads other occluder buffers than b - 1 (call with b = 0, 1, ... in order).
  const Prepared& prepared_for(int64_t b, const Occluders<double>& occ) {
    if (!prep_ || !same_occluders(b, b - 1)) prep_ = prepared(occ);
    return *prep_;
  }

 private:
  std::vector<int64_t> batch_;
  OccluderInputs occ_;
  int64_t NE_ = 0;
  BatchMap faces_map_, topo_map_[5];
  std::shared_ptr<const Prepared> prep_;  // of the last batch element `prepared_for` was asked
  std::deque<std::vector<double>> store_;  // converted inputs (a deque: earlier ones never move)
};

inline ffi::Error invalid(const char* name, const char* what) {
  return ffi::Error::InvalidArgument(std::string(name) + ": " + what);
}

// The prologue of every handler: the ranks checked, the float dispatch on the points' element
// type, the inputs converted (`Inputs<T>`; `more`: the handler's further batched inputs, which
// take part in the batch shape); then `body(inputs)`.
template <class F>
ffi::Error with_inputs(const char* name, ffi::AnyBuffer points, ffi::AnyBuffer faces, const Topology& topology,
                       std::initializer_list<ffi::AnyBuffer> more, F&& body) {
  auto pd = points.dimensions();
  auto fd = faces.dimensions();
  if (pd.size() < 2 || fd.size() < 3 || fd.size() != pd.size() + 1) return invalid(name, "bad ranks");
  const auto t = points.element_type();
  if (t != ffi::F64 && t != ffi::F32) return invalid(name, "float32 or float64 only");
  return by_float(t == ffi::F64, [&](auto zero) {
    Inputs<decltype(zero)> in(points, faces, topology, more);
    if (in.error) return invalid(name, in.error);
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
  return with_inputs(name, points, faces, topology, {normals, light}, [&](auto& in) {
    auto ld_ = light.dimensions();
    if (ld_.size() != in.nb + 2 || normals.dimensions().size() != in.nb + 2) return invalid(name, "bad ranks");
    const int64_t N = in.N, K = ld_[in.nb];
    const double* Nr = in.batched(normals, N * 3);
    const double* E = in.batched(light, K * 3);
    for (int64_t b = 0; b < in.B; b++) {
      const Occluders<double> occ = in.occluders(b, K);
      const Prepared& prep = in.prepared_for(b, occ);
      int rc = poly_fixed<double>(N, in.points + b * N * 3, Nr + b * N * 3, K, E + b * K * 3, occ, prep,
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
  return with_inputs("jaxshadow_hard_visibility", points, faces, topology, {x}, [&](auto& in) {
    const int64_t N = in.N;
    const double* X = in.batched(x, 3);
    std::vector<uint8_t> vis(N);
    for (int64_t b = 0; b < in.B; b++) {
      const Occluders<double> occ = in.occluders(b);
      const Prepared& prep = in.prepared_for(b, occ);
      hard_plan<double>(N, in.points + b * N * 3, X + b * 3, int(is_point), occ, prep.bvh, int(threads), vis.data());
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
  return with_inputs("jaxshadow_segment_candidates", points, faces, topology, {ends}, [&](auto& in) {
    const int64_t N = in.N;
    const double* AB = in.batched(ends, 6);
    for (int64_t b = 0; b < in.B; b++) {
      const Occluders<double> occ = in.occluders(b);
      const Prepared& prep = in.prepared_for(b, occ);
      const BVH& bvh = prep.bvh;
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
  return with_inputs("jaxshadow_segment_pieces", points, faces, topology, {ends}, [&](auto& in) {
    const int64_t N = in.N;
    const double* AB = in.batched(ends, 6);
    for (int64_t b = 0; b < in.B; b++) {
      const Occluders<double> occ = in.occluders(b);
      const Prepared& prep = in.prepared_for(b, occ);
      segment_pieces_fixed<double>(N, in.points + b * N * 3, AB + b * 6, AB + b * 6 + 3, occ, prep, int(threads), cap,
                                   cls->typed_data() + b * N, counts->typed_data() + b * N,
                                   pieces->typed_data() + b * N * cap * 2);
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
