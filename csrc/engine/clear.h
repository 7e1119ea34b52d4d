// jaxshadow's shadow engine: receivers that see all of the light (part of `csrc/shadowc.cc`; see its
// header comment).
#ifndef JAXSHADOW_SHADOWC_CLEAR_H_
#define JAXSHADOW_SHADOWC_CLEAR_H_

#include "groups.h"

namespace jaxshadow_engine {

// Half-space j of receiver p's light pyramid for the hierarchy's query (polygon_receiver, clear_lit):
// j < call.n_edges the plane through p and light edge call.edge_index[j] (a plain cross product),
// j == call.n_edges p's horizon (normal n through p), j > call.n_edges the emitter plane (normal
// `ne` through the light's first vertex `e0`).
template <class T>
inline HalfSpace pyramid_halfspace(const PolyCall<T>& call, V3<T> p, V3<T> n, V3<T> ne, V3<T> e0, int j) {
  V3<T> nn = n, q = p;
  if (j < call.n_edges) {
    const int64_t K = call.L.K, i = call.edge_index[j];
    nn = cross(call.L.v((i + 1) % K) - p, call.L.v(i) - p);
  } else if (j > call.n_edges) {
    nn = ne;
    q = e0;
  }
  return HalfSpace{{double(nn.x), double(nn.y), double(nn.z)}, {double(q.x), double(q.y), double(q.z)}};
}

// Whether the silhouette path serves receiver p (polygon_receiver): every occluder vertex lies
// strictly between p's level and the emitter plane, by 1e-9 of the scene's size. `hp`: p's height
// above the emitter plane along the light's unscaled Newell normal (call.ne_raw).
template <class T>
inline bool silhouette_serves(const PolyCall<T>& call, V3<T> p, T hp) {
  const double hmargin = 1e-9 * double(norm(call.ne_raw)) * (call.sil->scale + double(absmax(p)) + 1.0);
  return call.sil_ok && call.sil_hmin > hmargin && call.sil_hmax < double(hp) - hmargin;
}

// Whether `clear_lit` may decide receivers: JAXSHADOW_CLEAR=0 switches it off (for comparing it
// with the silhouette path, which then decides every receiver).
inline bool clear_switch() {
  const char* env = std::getenv("JAXSHADOW_CLEAR");
  return !(env && env[0] == '0');
}

// The gap, in eps of |p| + the scene's size, by which a receiver's pyramid must miss every
// hierarchy box for `clear_lit` (the occlusion volume's kMargin: 2.2e-6 in float64).
constexpr double kClearMargin = 1e10;

// A receiver that the silhouette path would serve, with the whole light above its horizon, whose
// pyramid conv({p} ∪ L) clearly misses every occluder: `kLit`, decided before E_h, a contour walk
// or a coverage reference is built for it; -1 for every other receiver (polygon_receiver decides).
// Clearly: p is outside the occlusion volume of the hierarchy's root box (volume.h), or every box of
// the hierarchy (node or item) lies outside one of the pyramid's half-spaces (the planes of
// polygon_receiver's query: through p and each light edge, the horizon, the emitter plane) by
// kClearMargin eps (|p| + the scene's size). Every occluder then lies at least that far from the
// pyramid, far beyond the silhouette path's rounding bounds (1e-9 of the scene's size at most), so
// that path finds no contour edge in the pyramid, counts no layer on its reference ray and returns
// kLit; the statistics are the ones it gives a lit receiver (no contour edge, one region). Not used
// when lit receivers' boundaries are wanted (Work::lit_runs), nor unless `call.clear_ok`
// (`clear_switch`).
template <class T>
int32_t clear_lit(const PolyCall<T>& call, V3<T> p, V3<T> n, Work<T>& w) {
  const int64_t K = call.L.K;
  if (!call.clear_ok || w.lit_runs || !call.sil_ok || call.n_edges == 0 || K > 64 || call.bvh->nodes.empty()) return -1;
  const V3<T> e0 = call.L.v(0);
  const T hp = dot(call.ne_raw, p - e0);
  if (!(hp > 0) || !silhouette_serves(call, p, hp)) return -1;
  for (int64_t i = 0; i < K; i++)
    if (!(dot(call.L.v(i) - p, n) >= 0)) return -1;
  if (!call.volume.outside(p)) {
    double scale = call.item_extent;
    for (int64_t i = 0; i < K; i++) scale = std::max(scale, double(absmax(call.L.v(i))));
    const double margin = kClearMargin * double(eps_of<T>()) * (scale + double(absmax(p)));
    const int ne_edges = call.n_edges;
    auto make = [&](int j) -> HalfSpace { return pyramid_halfspace(call, p, n, call.ne_raw, e0, j); };
    bool any = false;
    traverse_lazy(*call.bvh, ne_edges + 2, margin, make, [&](int32_t) {
      any = true;
      return false;
    });
    if (any) return -1;
  }
  w.runs.clear();
  w.n_candidates = 0;
  w.n_regions = 1;
  return kLit;
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_CLEAR_H_
