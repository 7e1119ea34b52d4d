// jaxshadow's shadow engine: receiver groups (part of `csrc/shadowc.cc`; see its header comment).
#ifndef JAXSHADOW_SHADOWC_GROUPS_H_
#define JAXSHADOW_SHADOWC_GROUPS_H_

#include "polygon_types.h"

namespace jaxshadow_engine {

// Occluder lists refined down the receivers (Campbell & Fussell §4.1, §4.3): receivers are
// ordered by the cell of a uniform grid over their bounding box, and each run of at most
// kGroupSize receivers of one cell queries the hierarchy once, with the convex hull of its
// points' box and the light. Every receiver's pyramid conv({p} ∪ L) lies in that hull, so the
// list holds every item that can meet it; each receiver then tests only the listed items' boxes
// against its own pyramid (filter_lazy) instead of walking the hierarchy. The hull query keeps a
// wide margin (kHullMargin of the scene's size, above the hull planes' rounding), so an item the
// receiver's own query would return and that meets its pyramid is always listed; an item only
// the receiver's half-space tests let through (outside the pyramid near one of its edges) may
// be missing from the list, and the exact tests downstream drop such items anyway.
constexpr int kGroupSize = 128;
constexpr int kGroupMinItems = 8;  // fewer items: the hierarchy walk costs about what a list does

// A permutation of the N receivers that puts receivers of one grid cell next to each other (a
// counting sort; about kGroupSize / 2 receivers per cell on average), and each position's cell.
// The box of the finite coordinates of N points P (N, 3) (lo > hi on an axis with none).
template <class T>
void finite_box(int64_t N, const T* P, double lo[3], double hi[3]) {
  for (int d = 0; d < 3; d++) {
    lo[d] = std::numeric_limits<double>::infinity();
    hi[d] = -std::numeric_limits<double>::infinity();
  }
  for (int64_t i = 0; i < N; i++)
    for (int d = 0; d < 3; d++) {
      const double x = double(P[3 * i + d]);
      if (!std::isfinite(x)) continue;
      lo[d] = std::min(lo[d], x);
      hi[d] = std::max(hi[d], x);
    }
}

template <class T>
void receiver_order(int64_t N, const T* P, std::vector<int64_t>& perm, std::vector<int64_t>& cell) {
  double lo[3], hi[3];
  finite_box(N, P, lo, hi);
  double ext[3], vol = 1, size = 0;
  int dims = 0;
  for (int d = 0; d < 3; d++) {
    ext[d] = hi[d] > lo[d] ? hi[d] - lo[d] : 0.0;
    size = std::max(size, ext[d]);
  }
  for (int d = 0; d < 3; d++)
    if (ext[d] > 1e-6 * size) {
      vol *= ext[d];
      dims++;
    }
  const double cells = std::max(1.0, double(N) / (kGroupSize / 2));
  const double h = dims ? std::pow(vol / cells, 1.0 / dims) : 1.0;
  int64_t nc[3];
  for (int d = 0; d < 3; d++)
    nc[d] = (dims && ext[d] > 1e-6 * size && h > 0) ? std::max<int64_t>(1, std::min<int64_t>(4096, int64_t(std::ceil(ext[d] / h)))) : 1;
  const int64_t G = nc[0] * nc[1] * nc[2];
  std::vector<int64_t> id(N), start(G + 1, 0);
  for (int64_t i = 0; i < N; i++) {
    int64_t c = 0;
    for (int d = 0; d < 3; d++) {
      const double x = double(P[3 * i + d]);
      int64_t k = (std::isfinite(x) && ext[d] > 0) ? int64_t((x - lo[d]) / ext[d] * double(nc[d])) : 0;
      k = std::min<int64_t>(nc[d] - 1, std::max<int64_t>(0, k));
      c = c * nc[d] + k;
    }
    id[i] = c;
    start[c + 1]++;
  }
  for (int64_t g = 0; g < G; g++) start[g + 1] += start[g];
  perm.resize(N);
  cell.resize(N);
  for (int64_t i = 0; i < N; i++) {
    const int64_t k = start[id[i]]++;
    perm[k] = i;
    cell[k] = id[i];
  }
}

// The item slots, in the hierarchy's depth-first order, whose boxes are not strictly outside the
// convex hull of the box [lo, hi] and the light (its supporting planes through a light edge and a
// box corner, a box edge and a light vertex, the light's plane and the box's faces).
template <class T>
void group_items(const PolyCall<T>& call, const double* lo, const double* hi, std::vector<int32_t>& out) {
  constexpr double kSupport = 1e3, kHullMargin = 1e6;  // times eps
  out.clear();
  const BVH& bvh = *call.bvh;
  const int64_t K = call.L.K;
  const double eps = double(eps_of<T>());
  // The points whose hull it is: the box's distinct corners (a flat box, e.g. receivers on a
  // floor, has four) and the light's vertices (a light of more than 64 is refused per receiver).
  const int64_t nl = std::min<int64_t>(K, 64);
  double lv[3 * 64];
  for (int64_t i = 0; i < 3 * nl; i++) lv[i] = double(call.L.E[i]);
  V3<double> pts[8 + 64];
  int np = 0;
  for (int c = 0; c < 8; c++) {
    const V3<double> x = box_corner(lo, hi, c);
    bool dup = false;
    for (int j = 0; j < np && !dup; j++) dup = same(x, pts[j]);
    if (!dup) pts[np++] = x;
  }
  for (int64_t i = 0; i < nl; i++) pts[np++] = ld(lv + 3 * i);
  double scale = call.item_extent;
  for (int i = 0; i < np; i++) scale = std::max(scale, absmax(pts[i]));
  scale += 1.0;
  std::vector<HalfSpace> hs;
  // A plane through q with normal n: kept (the hull on its positive side) when it supports the hull.
  auto support = [&](V3<double> n, V3<double> q) {
    const double len = norm(n);
    if (!(len > 1e-12 * scale * scale)) return;
    const double tol = kSupport * eps * scale * len;
    bool pos = true, neg = true;
    for (int i = 0; i < np && (pos || neg); i++) {
      const double h = dot(n, pts[i] - q);
      pos = pos && h >= -tol;
      neg = neg && h <= tol;
    }
    if (pos == neg) return;  // neither, or every point on the plane
    const double sg = pos ? 1.0 : -1.0;
    hs.push_back(HalfSpace{{sg * n.x, sg * n.y, sg * n.z}, {q.x, q.y, q.z}});
  };
  extremal_planes(lo, hi, lv, nl, [&](V3<double> a, V3<double> b, V3<double> c) { support(cross(b - a, c - a), a); });
  // The light's plane and the box's faces.
  support(V3<double>{double(call.ne_raw.x), double(call.ne_raw.y), double(call.ne_raw.z)}, ld(lv));
  for (int d = 0; d < 3; d++) {
    const V3<double> e{d == 0 ? 1.0 : 0.0, d == 1 ? 1.0 : 0.0, d == 2 ? 1.0 : 0.0};
    support(e, ld(lo));
    support(e, ld(hi));
  }
  if (hs.empty()) {
    for (size_t i = 0; i < bvh.items.size(); i++) out.push_back(int32_t(i));
    return;
  }
  traverse_lazy(bvh, int(hs.size()), kHullMargin * eps * scale, [&](int i) { return hs[i]; }, [&](int32_t i) {
    out.push_back(i);
    return true;
  });
}

// The items of group `g` (group_items over its box, listed once), or null without a group.
template <class T>
const std::vector<int32_t>* group_list(const PolyCall<T>& call, GroupList* g) {
  if (!g) return nullptr;
  if (!g->listed) {
    group_items(call, g->lo, g->hi, g->items);
    g->listed = true;
  }
  return &g->items;
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_GROUPS_H_
