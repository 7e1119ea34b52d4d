// The inputs of the shadow engine's entry points, as both bindings read them (`shadowc.cc`: the
// host functions; `ffi.h`: the XLA FFI handlers): the occluders as one struct, inputs converted
// to double, and the float32 / float64 dispatch written once. No Python, no XLA.
#ifndef JAXSHADOW_INPUTS_H_
#define JAXSHADOW_INPUTS_H_

#include <type_traits>
#include <vector>

#include "engine/driver.h"

namespace jaxshadow_binding {

using namespace jaxshadow_engine;  // NOLINT: the binding's own namespace, over the engine's


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

// The float32 / float64 dispatch of every entry point (host and FFI): `fn(T{})`, T the inputs' type.
template <class F>
auto by_float(bool f64, F&& fn) {
  return f64 ? fn(double{}) : fn(float{});
}

// The occluder inputs of every entry point: padded convex faces (M, Ko, 3) in the call's float
// type, and the topology (`jaxshadow._core.mesh.OccluderTopology`, int32).
struct OccluderInputs {
  int64_t M = 0, Ko = 0, S = 0;
  const void* faces = nullptr;
  const int32_t* face_solid = nullptr;      // (M,)
  const int32_t* face_closed = nullptr;     // (M,)
  const int32_t* solid_faces = nullptr;     // (S, 2)
  const int32_t* solid_edge_off = nullptr;  // (S + 1,)
  const int32_t* solid_edges = nullptr;     // (E, 4)
};

// The engine's occluders in double (faces of type T converted into `store`); K light vertices
// come before the face refs.
template <class T>
Occluders<double> occ_double(int64_t K, const OccluderInputs& o, std::vector<double>& store) {
  return make_occ<double>(K, o.M, o.Ko, as_double<T>(o.faces, size_t(o.M * o.Ko * 3), store), o.face_solid,
                          o.face_closed, o.S, o.solid_faces, o.solid_edge_off, o.solid_edges);
}

}  // namespace jaxshadow_binding

#endif  // JAXSHADOW_INPUTS_H_
