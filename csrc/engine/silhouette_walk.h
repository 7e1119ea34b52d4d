// jaxshadow's shadow engine: the silhouette path's contour walk (part of `csrc/shadowc.cc`; see
// silhouette.h): the contour edges a receiver sees inside its pyramid, found with the hierarchy of
// silhouette_tree.h and clipped to the pyramid.
#ifndef JAXSHADOW_SHADOWC_SILHOUETTE_WALK_H_
#define JAXSHADOW_SHADOWC_SILHOUETTE_WALK_H_

#include <cstring>

#include "silhouette_tree.h"

namespace jaxshadow_engine {

// Receiver coherence: a tile's receivers (the driver's SilTile, its box B = pc +- hb) share one
// walk of the hierarchy (tile_walk). Each test of that walk bounds the per-receiver test of the
// contour walk below over every p in B, with a margin above both computations' rounding, so a
// node or edge it drops is one that the walk of every receiver of the tile drops (or skips without
// effect); each receiver then runs the unchanged per-receiver tests over what is left, in the same
// order, and finds the same contour edges in the same order (or falls back where it would).
struct TileBox {
  double pc[3], hb[3];
  double hb1, hb2;  // |hb|_1, |hb|_2
  double smax;      // max(st.scale, the box's largest coordinate magnitude)
  double d1;        // a bound of the 1-norm of any difference of two points of the scene and B
};

// A light edge a -> b's plane through p, c(p) = (b - p) x (a - p) = b x a + (a - b) x p (edge_plane's
// direction; `cone`'s planes are positive multiples of it), over the tile.
struct TilePlane {
  double ba[3], u[3], cc[3];  // b x a, a - b, c(pc)
  double au[3], acc[3];       // |u|, |cc| (per component)
  double cn1;                 // a bound of |c(p)|_1 over B
  double safety;              // above the rounding of c(p) . (x - p) in either computation
  double spread;              // a bound of tile_plane_inf_best's spread term for any x of the scene
  int edge;                   // the light's edge (the receivers' cone plane)
};

// An upper bound over p in B of c(p) . (x - p) for x in the box xc +- hx: with p = pc + s and
// x = xc + t, c(p) . (x - p) = g(pc, xc) + c(pc) . t + s . (xc x u - b x a) + s . (t x u).
inline double tile_plane_sup(const TilePlane& q, const TileBox& tb, const double* xc, const double* hx) {
  const double* u = q.u;
  const double w0 = xc[1] * u[2] - xc[2] * u[1] - q.ba[0];
  const double w1 = xc[2] * u[0] - xc[0] * u[2] - q.ba[1];
  const double w2 = xc[0] * u[1] - xc[1] * u[0] - q.ba[2];
  const double* hb = tb.hb;
  double g = q.ba[0] * xc[0] + q.ba[1] * xc[1] + q.ba[2] * xc[2] + tb.pc[0] * w0 + tb.pc[1] * w1 + tb.pc[2] * w2;
  const double* au = q.au;
  g += q.acc[0] * hx[0] + q.acc[1] * hx[1] + q.acc[2] * hx[2];
  g += std::fabs(w0) * hb[0] + std::fabs(w1) * hb[1] + std::fabs(w2) * hb[2];
  g += hb[0] * (hx[1] * au[2] + hx[2] * au[1]) + hb[1] * (hx[2] * au[0] + hx[0] * au[2]) + hb[2] * (hx[0] * au[1] + hx[1] * au[0]);
  return g;
}

// tile_plane_sup (upper) and tile_plane_inf_best (lower) for a point x (a box of half extents 0):
// the same values, without the terms in the box's extents (zeros there).
template <bool upper>
inline double tile_point_bound(const TilePlane& q, const TileBox& tb, const double* x) {
  const double* u = q.u;
  const double w0 = x[1] * u[2] - x[2] * u[1] - q.ba[0];
  const double w1 = x[2] * u[0] - x[0] * u[2] - q.ba[1];
  const double w2 = x[0] * u[1] - x[1] * u[0] - q.ba[2];
  const double g = q.ba[0] * x[0] + q.ba[1] * x[1] + q.ba[2] * x[2] + tb.pc[0] * w0 + tb.pc[1] * w1 + tb.pc[2] * w2;
  const double spread = std::fabs(w0) * tb.hb[0] + std::fabs(w1) * tb.hb[1] + std::fabs(w2) * tb.hb[2];
  return upper ? g + spread : g - spread;
}

// sil_side over the tile: +1 (-1) when sil_side(st, f, p) is +1 (-1) for every p in B, 0 otherwise.
inline int tile_side(const SilhouetteTree& st, int32_t f, const TileBox& tb) {
  const double* q = st.fn.data() + kFnStride * size_t(f);
  const double r0 = q[3] - tb.pc[0], r1 = q[4] - tb.pc[1], r2 = q[5] - tb.pc[2];
  const double hc = q[0] * r0 + q[1] * r1 + q[2] * r2;
  const double nn = q[9];
  const double spread = std::fabs(q[0]) * tb.hb[0] + std::fabs(q[1]) * tb.hb[1] + std::fabs(q[2]) * tb.hb[2];
  const double S = tb.smax;
  const double m = std::max(1e4 * 2.220446049250313e-16 * (std::fabs(r0) + std::fabs(r1) + std::fabs(r2) + tb.hb1 + S),
                            st.f32[size_t(f)] ? 2 * kOnSurface * S : 0.0) * nn;
  const double slack = spread + m * (1 + 1e-6) + 1e-12 * nn * tb.d1;
  return hc + slack < 0 ? 1 : (hc - slack > 0 ? -1 : 0);
}

// node_side over the tile, for the prune test and for the entry: returns nonzero when
// node_side(nd, p, margin(p)) is that for every p in B (margin(p) <= margin: the node's box grown
// by B's as seen from pc), and sets `none` to whether node_side(nd, p, margin(p)) is 0 for every
// p in B (margin(p) >= margin_none: the node is not pruned by its faces' sides for any receiver
// of the tile).
inline int tile_node_sides(const SNode& nd, const TileBox& tb, double margin, double margin_none, bool& none) {
  none = true;
  if (!(nd.cosa > 0)) return 0;
  const double d[3] = {tb.pc[0] - 0.5 * (nd.box[0] + nd.box[3]), tb.pc[1] - 0.5 * (nd.box[1] + nd.box[4]),
                       tb.pc[2] - 0.5 * (nd.box[2] + nd.box[5])};
  const double a = d[0] * nd.axis[0] + d[1] * nd.axis[1] + d[2] * nd.axis[2];
  const double e[3] = {d[0] - a * nd.axis[0], d[1] - a * nd.axis[1], d[2] - a * nd.axis[2]};
  const double en = std::sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2]);
  {  // none
    const double perp = std::max(0.0, en - tb.hb2) + nd.hrad;
    const double ab = std::fabs(nd.axis[0]) * tb.hb[0] + std::fabs(nd.axis[1]) * tb.hb[1] + std::fabs(nd.axis[2]) * tb.hb[2];
    const double m = margin_none - 1e-12 * tb.d1;
    none = (a + ab - nd.arad) * nd.cosa - perp * nd.sina < m && (a - ab + nd.arad) * nd.cosa + perp * nd.sina > -m;
  }
  const double perp = en + nd.hrad + tb.hb2;
  const double arad = nd.arad + std::fabs(nd.axis[0]) * tb.hb[0] + std::fabs(nd.axis[1]) * tb.hb[1] + std::fabs(nd.axis[2]) * tb.hb[2];
  const double m = margin + 1e-12 * tb.d1;
  if ((a - arad) * nd.cosa - perp * nd.sina > m) return 1;
  if ((a + arad) * nd.cosa + perp * nd.sina < -m) return -1;
  return 0;
}

// A lower bound over p in B of the largest c(p) . (x - p) over the box's corners x (at the corner
// farthest along c(pc)).
inline double tile_plane_inf_best(const TilePlane& q, const TileBox& tb, const double* box) {
  const double x[3] = {box[q.cc[0] > 0 ? 3 : 0], box[q.cc[1] > 0 ? 4 : 1], box[q.cc[2] > 0 ? 5 : 2]};
  const double* u = q.u;
  const double w0 = x[1] * u[2] - x[2] * u[1] - q.ba[0];
  const double w1 = x[2] * u[0] - x[0] * u[2] - q.ba[1];
  const double w2 = x[0] * u[1] - x[1] * u[0] - q.ba[2];
  const double g = q.ba[0] * x[0] + q.ba[1] * x[1] + q.ba[2] * x[2] + tb.pc[0] * w0 + tb.pc[1] * w1 + tb.pc[2] * w2;
  return g - (std::fabs(w0) * tb.hb[0] + std::fabs(w1) * tb.hb[1] + std::fabs(w2) * tb.hb[2]);
}

// A tile's walk: `tc` (named `id`) gets the hierarchy's nodes and edges that some receiver in the
// box [blo, bhi] may need (see TileBox); `same_n`: every such receiver has the normal `bn`. With
// `parent` (a walk built for a box holding this one), its entries are walked instead of the
// hierarchy: what it dropped, every receiver of its box drops, so the result serves the same
// receivers the same way. False: not built (every receiver walks the hierarchy itself).
// `serves`: receivers walk the result (false: a parent, which only tiles' walks refine; what
// only receivers read is left out of it).
template <class T>
bool tile_walk(const PolyCall<T>& call, const SilhouetteTree& st, V3<T> ne, int64_t id, const double* blo, const double* bhi,
               bool same_n, const double* bn, const SilTileCache* parent, SilTileCache& tc, bool serves) {
  tc.id = id;
  tc.tree = &st;
  tc.ok = false;
  tc.entries.clear();
  tc.edges.clear();
  tc.nids = 0;
  const size_t nfaces = st.fn.size() / kFnStride;
  if (tc.slot.size() != nfaces) {
    tc.slot.assign(nfaces, -1);
  } else {
    for (const int32_t f : tc.faces) tc.slot[size_t(f)] = -1;
  }
  tc.faces.clear();
  if (tc.fside.size() != nfaces) {
    tc.fside.assign(nfaces, int8_t(2));
  } else {
    for (const int32_t f : tc.fside_set) tc.fside[size_t(f)] = 2;
  }
  tc.fside_set.clear();
  for (std::vector<double>& v : tc.fq) v.clear();
  tc.fnn.clear();
  tc.f32.clear();
  const double eps = 2.220446049250313e-16;
  const double epsT = double(eps_of<T>());
  TileBox tb;
  double amax = 0;
  for (int d = 0; d < 3; d++) {
    const double lo = blo[d], hi = bhi[d];
    if (!(lo <= hi) || !std::isfinite(lo) || !std::isfinite(hi)) return false;
    tb.pc[d] = 0.5 * (lo + hi);
    tb.hb[d] = std::max(hi - tb.pc[d], tb.pc[d] - lo) * (1 + 1e-12);
    amax = std::max(amax, std::max(std::fabs(lo), std::fabs(hi)));
  }
  tb.hb1 = tb.hb[0] + tb.hb[1] + tb.hb[2];
  tb.hb2 = std::sqrt(tb.hb[0] * tb.hb[0] + tb.hb[1] * tb.hb[1] + tb.hb[2] * tb.hb[2]);
  tb.smax = std::max(st.scale, amax);
  const int64_t K = call.L.K;
  double lmax = 0;
  for (int64_t i = 0; i < K; i++) lmax = std::max(lmax, double(absmax(call.L.v(i))));
  const double S3 = std::max(tb.smax, lmax) + 1e-300;
  tb.d1 = 6 * S3;
  // The receivers' margins at their largest (the scale of silhouette_receiver over B).
  const double scale_max = tb.smax + 1e-300;
  const double bmargin = 1e3 * eps * scale_max;
  const double smargin = 4 * kOnSurface * scale_max;
  // The light's edge planes (`cone`'s first K; the horizon's plane is left out: no receiver's
  // walk is bounded by it here) and the emitter plane, as the walk tests it.
  TilePlane tp[64];
  int ntp = 0;
  for (int64_t i = 0; i < K; i++) {
    const V3<T> av = call.L.v(i), bv = call.L.v((i + 1) % K);
    if (same(av, bv)) continue;  // its plane is zero: no receiver's walk tests it
    const double a[3] = {double(av.x), double(av.y), double(av.z)}, b[3] = {double(bv.x), double(bv.y), double(bv.z)};
    TilePlane& q = tp[ntp++];
    q.edge = int(i);
    q.ba[0] = b[1] * a[2] - b[2] * a[1], q.ba[1] = b[2] * a[0] - b[0] * a[2], q.ba[2] = b[0] * a[1] - b[1] * a[0];
    for (int d = 0; d < 3; d++) q.u[d] = a[d] - b[d];
    const double* u = q.u;
    const double* pc = tb.pc;
    q.cc[0] = q.ba[0] + u[1] * pc[2] - u[2] * pc[1];
    q.cc[1] = q.ba[1] + u[2] * pc[0] - u[0] * pc[2];
    q.cc[2] = q.ba[2] + u[0] * pc[1] - u[1] * pc[0];
    for (int d = 0; d < 3; d++) q.au[d] = std::fabs(u[d]), q.acc[d] = std::fabs(q.cc[d]);
    const double* hb = tb.hb;
    q.cn1 = (std::fabs(q.cc[0]) + std::fabs(q.cc[1]) + std::fabs(q.cc[2]) + std::fabs(u[1]) * hb[2] + std::fabs(u[2]) * hb[1] +
             std::fabs(u[2]) * hb[0] + std::fabs(u[0]) * hb[2] + std::fabs(u[0]) * hb[1] + std::fabs(u[1]) * hb[0]) *
            (1 + 1e-12);
    const double u1 = std::fabs(u[0]) + std::fabs(u[1]) + std::fabs(u[2]);
    const double ba1 = std::fabs(q.ba[0]) + std::fabs(q.ba[1]) + std::fabs(q.ba[2]);
    q.safety = 256 * epsT * (u1 + ba1 / S3) * tb.d1 * tb.d1;
    // |x x u - b x a|_i <= X (|u_i+1| + |u_i+2|) + |(b x a)_i| for |x|_inf <= X = tb.smax.
    const double X = tb.smax;
    q.spread = (hb[0] * (X * (q.au[1] + q.au[2]) + std::fabs(q.ba[0])) + hb[1] * (X * (q.au[2] + q.au[0]) + std::fabs(q.ba[1])) +
                hb[2] * (X * (q.au[0] + q.au[1]) + std::fabs(q.ba[2]))) *
               (1 + 1e-9);
  }
  const V3<T> e0 = call.L.v(0);
  const double en[3] = {double(ne.x), double(ne.y), double(ne.z)}, eq[3] = {double(e0.x), double(e0.y), double(e0.z)};
  const double enn = std::fabs(en[0]) + std::fabs(en[1]) + std::fabs(en[2]);
  // The horizon's plane where every receiver of the tile has the same normal (the same vector
  // in every receiver's walk).
  double hn[3] = {0, 0, 0};
  const bool horizon = same_n;
  if (horizon) {
    const V3<T> n = rescale(V3<T>{T(bn[0]), T(bn[1]), T(bn[2])});
    hn[0] = n.x, hn[1] = n.y, hn[2] = n.z;
  }
  const double hnn = std::fabs(hn[0]) + std::fabs(hn[1]) + std::fabs(hn[2]);
  const double smargin_min = 4 * kOnSurface * (st.scale + 1e-300);
  // The planes of the receivers' walks that may prune the node (STEntry::planes): all but those
  // it lies inside of, by a margin, for every receiver of the tile. Bits as the receivers' walk
  // numbers its planes: cone plane k (the light's edge k for k < K, the horizon's K), the emitter
  // plane K + 1. A bit clear in `inherit` (the parent's entry: its box holds the tile's) stays
  // clear: the parent proved the node inside that plane for every receiver of its box.
  const bool masked = K + 2 <= 64;
  auto planes_left = [&](const SNode& nd, uint64_t inherit) -> uint64_t {
    if (!masked) return ~uint64_t(0);
    uint64_t m = 0;
    const double* box = nd.box;
    if ((inherit >> (K + 1)) & 1) {
      const double x[3] = {box[en[0] > 0 ? 3 : 0], box[en[1] > 0 ? 4 : 1], box[en[2] > 0 ? 5 : 2]};
      if (!(en[0] * (x[0] - eq[0]) + en[1] * (x[1] - eq[1]) + en[2] * (x[2] - eq[2]) > 1e-12 * enn * tb.d1)) m |= uint64_t(1) << (K + 1);
    }
    if (horizon) {
      const double x[3] = {box[hn[0] > 0 ? 3 : 0], box[hn[1] > 0 ? 4 : 1], box[hn[2] > 0 ? 5 : 2]};
      const double lo = hn[0] * (x[0] - tb.pc[0]) + hn[1] * (x[1] - tb.pc[1]) + hn[2] * (x[2] - tb.pc[2]) -
                        (std::fabs(hn[0]) * tb.hb[0] + std::fabs(hn[1]) * tb.hb[1] + std::fabs(hn[2]) * tb.hb[2]);
      if (!(lo > 1e-12 * hnn * tb.d1)) m |= uint64_t(1) << K;
    } else {
      m |= uint64_t(1) << K;
    }
    for (int k = 0; k < ntp; k++) {
      if (!((inherit >> tp[k].edge) & 1)) continue;
      // c(pc) . (x - pc) at the corner tile_plane_inf_best takes: its value is that (up to both
      // computations' rounding, some 100 eps of the plane's scale, far below safety / 2) less its
      // spread term (nonnegative, at most tp's spread), so it is decided without it where this is
      // at most safety / 2 (not above safety) or above the spread bound plus 1.5 safety (above).
      const TilePlane& q = tp[k];
      const double* cc = q.cc;
      const double g = cc[0] * (box[cc[0] > 0 ? 3 : 0] - tb.pc[0]) + cc[1] * (box[cc[1] > 0 ? 4 : 1] - tb.pc[1]) +
                       cc[2] * (box[cc[2] > 0 ? 5 : 2] - tb.pc[2]);
      if (g <= 0.5 * q.safety) {
        m |= uint64_t(1) << q.edge;
      } else if (!(g > q.spread + 1.5 * q.safety) && !(tile_plane_inf_best(q, tb, box) > q.safety)) {
        m |= uint64_t(1) << q.edge;
      }
    }
    return m;
  };
  // The entry of node nd: its planes left, and its faces' sides unless every receiver's node_side
  // is 0 (`side_in` false: the parent proved that for its box). `none`: the no-prune test's
  // value (tile_node_sides) where nd is not special and side_in.
  auto entry = [&](int32_t node, const SNode& nd, uint64_t inherit, bool side_in, bool none) {
    STEntry en{node, -1, -1, -1, false, !nd.special && side_in, planes_left(nd, inherit)};
    if (en.side) en.side = !none;
    en.sure = horizon && en.planes == 0 && !en.side;
    return en;
  };
  // Whether every receiver of the tile prunes a node of this box by one of the planes in `planes`
  // (STEntry::planes' bits; a plane the parent proved the node inside of cannot prune it).
  auto outside = [&](const double* box, uint64_t planes) {
    if (((planes >> (K + 1)) & 1) || !masked) {  // the emitter plane, as the walk computes it (the same for every receiver)
      const double x[3] = {box[en[0] > 0 ? 3 : 0], box[en[1] > 0 ? 4 : 1], box[en[2] > 0 ? 5 : 2]};
      const double best = en[0] * (x[0] - eq[0]) + en[1] * (x[1] - eq[1]) + en[2] * (x[2] - eq[2]);
      if (best < -bmargin * enn) return true;
    }
    const double xc[3] = {0.5 * (box[0] + box[3]), 0.5 * (box[1] + box[4]), 0.5 * (box[2] + box[5])};
    const double hx[3] = {(box[3] - box[0]) * (0.5 + 1e-12), (box[4] - box[1]) * (0.5 + 1e-12), (box[5] - box[2]) * (0.5 + 1e-12)};
    for (int k = 0; k < ntp; k++) {
      if (!(((planes >> tp[k].edge) & 1) || !masked)) continue;
      // c(pc) . (xc - pc) is a term of tile_plane_sup's value and the rest add up nonnegative, so
      // where it is above -safety / 2 (both computations' rounding is some 100 eps of the
      // plane's scale, the safety term ~1e4) the test below cannot prune: it is skipped (most
      // nodes the walk keeps have their centre inside every plane).
      const double* cc = tp[k].cc;
      if (cc[0] * (xc[0] - tb.pc[0]) + cc[1] * (xc[1] - tb.pc[1]) + cc[2] * (xc[2] - tb.pc[2]) >= -0.5 * tp[k].safety) continue;
      if (tile_plane_sup(tp[k], tb, xc, hx) + bmargin * tp[k].cn1 + tp[k].safety < 0) return true;
    }
    return false;
  };
  // An edge whose ends lie beyond one light plane for every receiver (the walk's test before
  // edge_plane, its margin at its largest over B).
  auto edge_out = [&](const double* a, const double* b) {
    const double apl = std::fabs(a[0] - tb.pc[0]) + std::fabs(a[1] - tb.pc[1]) + std::fabs(a[2] - tb.pc[2]) + std::fabs(b[0] - tb.pc[0]) +
                       std::fabs(b[1] - tb.pc[1]) + std::fabs(b[2] - tb.pc[2]) + 2 * tb.hb1;
    for (int k = 0; k < ntp; k++) {
      const double m = 8 * kCollinearEps * epsT * tp[k].cn1 * apl * (1 + 1e-6) + tp[k].safety;
      if (tile_point_bound<true>(tp[k], tb, a) + m < 0 && tile_point_bound<true>(tp[k], tb, b) + m < 0) return true;
    }
    return false;
  };
  // An end inside a plane of every receiver's pyramid (a light's edge plane or, where the tile's
  // receivers share their normal, the horizon's), by a margin of 1e-9 (or 1024 epsT) of the
  // plane's scale times tb.d1, far above both the rounding of the walk's g = cone . (x - p) (tp's
  // safety) and its test of an unclipped end against E_h's boundary (tol times the end's 1-norm
  // from p, plus the rounding of its projection: a few eps of S3). Where both ends of an edge are
  // inside plane k so, every receiver of the box computes g >= 0 at both ends for it: cyrus_beck's
  // interval for that plane is [0, 1], the out test cannot drop the edge by it, and neither end
  // is too close to E_h's boundary along it: contour_edges skips those tests for plane k
  // (STEdge::inm), and all of them where that holds for every plane (STEdge::in).
  const double inmarg = (1e-9 + 1024 * epsT) * tb.d1;
  // The planes an end is inside of, as bits of STEntry::planes (cone plane k: the light's edge k
  // for k < K, the horizon's K); without `masked`, ~0 where it is inside every plane, else 0.
  uint64_t all_in = masked && horizon ? uint64_t(1) << K : 0;
  for (int k = 0; k < ntp && masked; k++) all_in |= uint64_t(1) << tp[k].edge;
  if (!masked) all_in = ~uint64_t(0);
  auto end_planes = [&](const double* x) -> uint64_t {
    const double lo = hn[0] * (x[0] - tb.pc[0]) + hn[1] * (x[1] - tb.pc[1]) + hn[2] * (x[2] - tb.pc[2]) -
                      (std::fabs(hn[0]) * tb.hb[0] + std::fabs(hn[1]) * tb.hb[1] + std::fabs(hn[2]) * tb.hb[2]);
    const bool hz = lo > inmarg * hnn;
    if (!masked && !hz) return 0;
    uint64_t m = masked && hz ? uint64_t(1) << K : 0;
    for (int k = 0; k < ntp; k++) {
      const bool in = tile_point_bound<false>(tp[k], tb, x) > tp[k].safety + inmarg * tp[k].cn1;
      if (masked && in) m |= uint64_t(1) << tp[k].edge;
      if (!masked && !in) return 0;
    }
    return masked ? m : ~uint64_t(0);
  };
  // An edge's planes (both ends'), each end's made once per position: kept by position id in
  // tc.pos_in (1 tested, -1 not yet) and tc.pos_m.
  tc.pos_in.assign(size_t(parent && parent->ok && parent->tree == &st ? parent->nids : 0), int8_t(-1));
  tc.pos_m.resize(tc.pos_in.size());
  auto edge_in = [&](const double* a, const double* b, int32_t ia, int32_t ib) -> uint64_t {
    if (!serves) return 0;
    uint64_t m = ~uint64_t(0);
    for (int j = 0; j < 2; j++) {
      const int32_t id = j ? ib : ia;
      if (size_t(id) >= tc.pos_in.size()) {
        tc.pos_in.resize(std::max(2 * tc.pos_in.size(), size_t(id) + 1), int8_t(-1));
        tc.pos_m.resize(tc.pos_in.size());
      }
      if (tc.pos_in[size_t(id)] < 0) {
        tc.pos_in[size_t(id)] = 1;
        tc.pos_m[size_t(id)] = end_planes(j ? b : a);
      }
      m &= tc.pos_m[size_t(id)];
    }
    return m;
  };
  const Occluders<T>& occ = call.occ;
  // Preorder, right subtree first (the walk's stack order); an entry that keeps nothing is dropped.
  struct Rec {
    const SilhouetteTree& st;
    SilTileCache& tc;
    const decltype(outside)& out;
    const decltype(edge_out)& eout;
    const decltype(entry)& make_entry;
    const decltype(edge_in)& ein;
    const TileBox& tb;
    const Occluders<T>& occ;
    double smargin, smargin_min;
    bool serves;
    bool deep;
    uint64_t all_in;  // end_planes' bits of every plane tested
    bool masked, horizon;
    bool visit(int32_t k, int depth) {
      const SNode& nd = st.nodes[size_t(k)];
      if (out(nd.box, ~uint64_t(0))) return false;
      bool none = true;
      if (!nd.special && tile_node_sides(nd, tb, smargin, smargin_min, none) != 0) return false;
      const size_t me = tc.entries.size();
      tc.entries.push_back(make_entry(k, nd, ~uint64_t(0), true, none));
      if (nd.left >= 0) {
        if (depth > 60) deep = true;  // deeper than the walk's stack allows
        const bool r = visit(nd.right, depth + 1);
        const bool l = visit(nd.left, depth + 1);
        if (!r && !l) {
          tc.entries.pop_back();
          return false;
        }
      } else {
        const int32_t e0 = int32_t(tc.edges.size());
        for (int32_t j = nd.start; j < nd.start + nd.count; j++) keep(st.edges[size_t(j)], nullptr);
        if (!leaf_done(me, e0)) return false;
      }
      tc.entries[me].skip = int32_t(tc.entries.size());
      return true;
    }
    // The id of position x (equal positions, as same() compares them, get one id).
    int32_t pos_id(const double* x) {
      std::vector<SilTileCache::Slot>& tab = tc.idtab;
      if (size_t(2 * (tc.nids + 1)) > tab.size()) {  // grow (and rehash) at half full
        std::vector<SilTileCache::Slot> old;
        old.swap(tab);
        tab.assign(std::max<size_t>(1024, 2 * old.size()), SilTileCache::Slot{0, 0, 0, -1});
        for (const SilTileCache::Slot& o : old)
          if (o.id >= 0) tab[slot(o.x, o.y, o.z)] = o;
      }
      const size_t k = slot(x[0], x[1], x[2]);
      if (tab[k].id < 0) tab[k] = SilTileCache::Slot{x[0], x[1], x[2], tc.nids++};
      return tab[k].id;
    }
    // x's slot in tc.idtab: the one holding x, or the empty one where it goes.
    size_t slot(double x, double y, double z) const {
      auto bits = [](double v) {
        uint64_t u;
        v += 0.0;  // -0 as +0 (same() counts them equal)
        std::memcpy(&u, &v, sizeof(u));
        return u;
      };
      const std::vector<SilTileCache::Slot>& tab = tc.idtab;
      const size_t mask = tab.size() - 1;
      uint64_t h = bits(x) * 0x9E3779B97F4A7C15ull ^ bits(y) * 0xC2B2AE3D27D4EB4Full ^ bits(z) * 0x165667B19E3779F9ull;
      h ^= h >> 29;
      for (size_t k = size_t(h) & mask;; k = (k + 1) & mask) {
        const SilTileCache::Slot& t = tab[k];
        if (t.id < 0 || (t.x == x && t.y == y && t.z == z)) return k;
      }
    }
    // tile_side of face f, once per walk (tc.fside: 2 where not yet computed).
    int face_side(int32_t f) {
      int8_t& s = tc.fside[size_t(f)];
      if (s == 2) {
        s = int8_t(tile_side(st, f, tb));
        tc.fside_set.push_back(f);
      }
      return s;
    }
    // A leaf's edge e: kept unless every receiver of the box drops it, with its coverage jump
    // where every receiver sees both faces on known sides. `from`: the parent's kept edge (its
    // box holds the tile's: a jump W it knows holds here too), or null for an edge of the
    // hierarchy (its ends, position ids, fwd and dir are set here where it is kept).
    void keep(const SEdge& e, const STEdge* from) {
      int W = from ? from->w : 0;
      if (W == 0) {
        const int sf = face_side(e.f);
        const int sg = e.g >= 0 ? face_side(e.g) : 0;
        if (sf != 0 && (e.g < 0 || sg != 0)) {
          W = sf + (e.g >= 0 ? sg * e.dg : 0);
          if (W == 0) return;  // no receiver's contour edge, none falls back on it
        }
      }
      double a[3], b[3];
      if (from) {
        std::copy_n(from->a, 3, a);
        std::copy_n(from->b, 3, b);
      } else {
        const V3<T> a3 = occ.vref(e.ra), b3 = occ.vref(e.rb);
        a[0] = double(a3.x), a[1] = double(a3.y), a[2] = double(a3.z);
        b[0] = double(b3.x), b[1] = double(b3.y), b[2] = double(b3.z);
      }
      if (W != 0 && eout(a, b)) return;
      if (from) {
        tc.edges.push_back(*from);
      } else {
        tc.edges.emplace_back();
        STEdge& te = tc.edges.back();
        te.e = e;
        std::copy_n(a, 3, te.a);
        std::copy_n(b, 3, te.b);
        te.ia = pos_id(a);
        te.ib = pos_id(b);
        const V3<T> a3{T(a[0]), T(a[1]), T(a[2])}, b3{T(b[0]), T(b[1]), T(b[2])};
        te.fwd = lex_less(a3, b3);
        const V3<T> d = rescale(te.fwd ? b3 - a3 : a3 - b3);
        te.dir[0] = double(d.x), te.dir[1] = double(d.y), te.dir[2] = double(d.z);
      }
      STEdge& te = tc.edges.back();
      te.w = int8_t(W);
      const uint64_t m = ein(a, b, te.ia, te.ib);
      te.in = m == all_in && horizon;
      te.inm = masked ? m : 0;
      te.lf = te.lg = -1;
      if (W == 0 && serves) {
        te.lf = face_slot(e.f);
        if (e.g >= 0) te.lg = face_slot(e.g);
      }
    }
    // Face f's slot in tc.faces (added with its record on first use).
    int32_t face_slot(int32_t f) {
      int32_t& k = tc.slot[size_t(f)];
      if (k < 0) {
        k = int32_t(tc.faces.size());
        tc.faces.push_back(f);
        const double* q = st.fn.data() + kFnStride * size_t(f);
        for (int d = 0; d < 6; d++) tc.fq[d].push_back(q[d]);
        tc.fnn.push_back(q[9]);
        tc.f32.push_back(st.f32[size_t(f)] ? 1.0 : 0.0);
      }
      return k;
    }
    bool leaf_done(size_t me, int32_t e0) {
      if (int32_t(tc.edges.size()) == e0) {
        tc.entries.pop_back();
        return false;
      }
      tc.entries[me].e0 = e0;
      tc.entries[me].e1 = int32_t(tc.edges.size());
      return true;
    }
    // The parent's entry i and its subtree (its entries up to skip), in the parent's order.
    bool visit_list(const SilTileCache& par, int32_t i) {
      const STEntry& pe = par.entries[size_t(i)];
      const SNode& nd = st.nodes[size_t(pe.node)];
      // No prune test by the planes (outside): over a tile inside the parent's box it drops few
      // entries (~2 %), each of which every receiver drops itself by the planes its entry keeps
      // (planes_left), and it costs more than those receivers' tests.
      bool none = true;
      if (!nd.special && pe.side && tile_node_sides(nd, tb, smargin, smargin_min, none) != 0) return false;
      const size_t me = tc.entries.size();
      tc.entries.push_back(make_entry(pe.node, nd, pe.planes, pe.side, none));
      if (pe.e0 >= 0) {
        const int32_t e0 = int32_t(tc.edges.size());
        for (int32_t k = pe.e0; k < pe.e1; k++) keep(par.edges[size_t(k)].e, &par.edges[size_t(k)]);
        if (!leaf_done(me, e0)) return false;
      } else {
        bool any = false;
        for (int32_t j = i + 1; j < pe.skip; j = par.entries[size_t(j)].skip) any = visit_list(par, j) || any;
        if (!any) {
          tc.entries.pop_back();
          return false;
        }
      }
      tc.entries[me].skip = int32_t(tc.entries.size());
      return true;
    }
  };
  Rec rec{st, tc, outside, edge_out, entry, edge_in, tb, occ, smargin, smargin_min, serves, false, all_in, masked, horizon};
  if (parent && parent->ok && parent->tree == &st) {
    tc.nids = parent->nids;  // the parent's edges keep their ids
    if (!parent->entries.empty()) rec.visit_list(*parent, 0);
  } else {
    tc.idtab.clear();
    rec.visit(0, 0);
  }
  if (rec.deep) return false;
  tc.side.resize(tc.faces.size());
  if (serves) {
    // Inner entries no receiver prunes (sure) are left out: a receiver's walk only steps over
    // them. An entry's skip then names the first entry kept at or after it.
    std::vector<STEntry>& en = tc.entries;
    const size_t n = en.size();
    std::vector<int32_t>& at = tc.remap;
    at.resize(n + 1);
    int32_t m = 0;
    for (size_t i = 0; i < n; i++) {
      at[i] = m;
      m += int32_t(!en[i].sure || en[i].e0 >= 0);
    }
    at[n] = m;
    for (size_t i = 0; i < n; i++)
      if (!en[i].sure || en[i].e0 >= 0) {
        STEntry x = en[i];
        x.skip = at[size_t(x.skip)];
        en[size_t(at[i])] = x;
      }
    en.resize(size_t(m));
  }
  tc.ok = true;
  return true;
}

// The sides of the faces a tile left to its receivers (SilTileCache::faces), from pd with
// S = sil_scale(st, pd), into tc.side: sil_side's operations on the faces' records, in arrays
// (vectorized; the comparisons as selects of +-1 and 0).
inline void tile_side_values(size_t nf, const double* __restrict q0, const double* __restrict q1, const double* __restrict q2,
                             const double* __restrict q3, const double* __restrict q4, const double* __restrict q5,
                             const double* __restrict nn, const double* __restrict f32, double* __restrict side, double p0, double p1,
                             double p2, double S) {
  const double k32 = 2 * kOnSurface * S;
  for (size_t i = 0; i < nf; i++) {
    const double r0 = q3[i] - p0, r1 = q4[i] - p1, r2 = q5[i] - p2;
    const double h = q0[i] * r0 + q1[i] * r1 + q2[i] * r2;
    const double m = std::max(1e4 * 2.220446049250313e-16 * (std::fabs(r0) + std::fabs(r1) + std::fabs(r2) + S), f32[i] != 0 ? k32 : 0.0) * nn[i];
    side[i] = (h < -m ? 1.0 : 0.0) - (h > m ? 1.0 : 0.0);
  }
}
__attribute__((noinline)) inline void tile_sides(SilTileCache& tc, const double* pd, double S) {
  tile_side_values(tc.faces.size(), tc.fq[0].data(), tc.fq[1].data(), tc.fq[2].data(), tc.fq[3].data(), tc.fq[4].data(),
                   tc.fq[5].data(), tc.fnn.data(), tc.f32.data(), tc.side.data(), pd[0], pd[1], pd[2], S);
}

// Contour edges in the pyramid: the hierarchy walked with the pyramid's half-spaces (`cone`, the
// np0 planes of E_h through p, and the emitter plane) and the faces' sides. Each is appended to
// `w.ssegs` projected onto the emitter plane and clipped to E_h. Returns how many, or kFallback.
// A receiver of a tile (w.tile) walks the tile's part of the hierarchy (tile_walk), built by the
// first receiver of the tile that gets here.
template <class T>
int32_t contour_edges(const PolyCall<T>& call, const SilhouetteTree& st, V3<T> p, const V3<T>* cone,
                      const PlaneRef* prefs, int np0, V3<T> ne, double hp, double scale, Work<T>& w) {
  std::vector<SSeg<T>>& segs = w.ssegs;
  const Occluders<T>& occ = call.occ;
  const double eps = 2.220446049250313e-16;
  const double tol = kCollinearEps * eps;
  const double pd[3] = {p.x, p.y, p.z};
  const double side_scale = sil_scale(st, pd);

  // The pyramid's planes: cone plane k at k < np0 (cz: zero, never tested), the emitter plane at
  // np0 (the pyramid on p's side).
  double cn[66][3], cq[66][3];
  bool cz[66];
  const int nc = std::min(np0, 65) + 1;
  for (int k = 0; k + 1 < nc; k++) {
    cz[k] = !nonzero(cone[k]);
    cn[k][0] = cone[k].x, cn[k][1] = cone[k].y, cn[k][2] = cone[k].z;
    cq[k][0] = p.x, cq[k][1] = p.y, cq[k][2] = p.z;
  }
  const V3<T> e0 = call.L.v(0);
  cz[nc - 1] = false;
  cn[nc - 1][0] = ne.x, cn[nc - 1][1] = ne.y, cn[nc - 1][2] = ne.z;
  cq[nc - 1][0] = e0.x, cq[nc - 1][1] = e0.y, cq[nc - 1][2] = e0.z;
  const double bmargin = 1e3 * eps * scale;
  double cnn[66];
  for (int k = 0; k < nc; k++) cnn[k] = std::fabs(cn[k][0]) + std::fabs(cn[k][1]) + std::fabs(cn[k][2]);
  auto out_by = [&](const double* box, int k) {
    // The box's corner farthest along the plane's normal.
    const double x[3] = {box[cn[k][0] > 0 ? 3 : 0], box[cn[k][1] > 0 ? 4 : 1], box[cn[k][2] > 0 ? 5 : 2]};
    const double best = cn[k][0] * (x[0] - cq[k][0]) + cn[k][1] * (x[1] - cq[k][1]) + cn[k][2] * (x[2] - cq[k][2]);
    return best < -bmargin * cnn[k];
  };
  auto outside = [&](const double* box) {
    for (int k = 0; k < nc; k++)
      if (!cz[k] && out_by(box, k)) return true;
    return false;
  };
  // Only the planes a tile's entry names (STEntry::planes; its bits number the planes as here
  // when np0 is the light's vertex count plus one).
  const bool by_mask = np0 == call.L.K + 1 && np0 + 1 <= 64;
  auto outside_of = [&](const double* box, uint64_t planes) {
    if (!by_mask) return outside(box);
    for (uint64_t m = planes & ((uint64_t(1) << nc) - 1); m; m &= m - 1) {
      const int k = __builtin_ctzll(m);
      if (!cz[k] && out_by(box, k)) return true;
    }
    return false;
  };
  const double smargin = 4 * kOnSurface * scale;  // beyond the on-surface distance (sil_side)
  T cone_n[66];
  for (int k = 0; k < np0 && k < 66; k++) cone_n[k] = norm(cone[k]);
  int32_t n_contour = 0;
  // One edge of a leaf the walk reached: appended when it is a contour edge in the pyramid; W
  // nonzero: its coverage jump, known (the faces' sides as sil_side gives them, or face_path_side
  // where it cannot tell). False: fall back.
  // `in`: the tile proved both ends inside every cone plane with a margin (STEdge::in): the
  // clipping keeps the whole edge and the end tests below pass, so they are skipped. `inm`: the
  // cone planes it proved that for (STEdge::inm; bit k: plane k): their tests are skipped.
  // `side_f`, `side_g`: sil_side of e.f and e.g (called where W is 0); `own_of`: edge_plane(p, a3, b3).
  // `ends(a3, b3)` sets the edge's ends (read once W is known nonzero).
  auto edge = [&](const SEdge& e, int W, bool in, uint64_t inm, int32_t ia, int32_t ib, auto side_f, auto side_g, auto ends,
                  auto own_of) __attribute__((always_inline)) -> bool {
    if (W == 0) {
      int sf = side_f();
      if (sf == 0 && !face_path_side(occ, st, e.f, p, sf)) return false;
      W = sf;
      if (e.g >= 0) {
        int sg = side_g();
        if (sg == 0 && !face_path_side(occ, st, e.g, p, sg)) return false;
        W += sg * e.dg;
      }
      if (W == 0) return true;
    }
    V3<T> a3, b3;
    ends(a3, b3);
    bool whole = in;
    if (!in) {
      // Both ends clearly outside one cone plane: cyrus_beck's interval for that plane is empty
      // (the same g0, g1; beyond its collinear tolerance, as norms are at most 1-norms), so it
      // would return false. Skips the edge's plane and the clipping for most non-contour edges
      // that the hierarchy's boxes let through.
      // `whole`: g0 > 0 and g0 + g1 > 0 for every nonzero plane (cyrus_beck's own g0, g1): each
      // plane's t_lo is at most 0 and its t_hi at least 1 (the sum's sign is exact, so g0 > -g1),
      // or 0 and 1 where the collinear test zeroes them, so cyrus_beck would return true with
      // t0 <= 0 and t1 = 1: both ends unclipped. It is skipped.
      const V3<T> ap = a3 - p, d = b3 - a3, bp = b3 - p;
      const T apl = std::fabs(ap.x) + std::fabs(ap.y) + std::fabs(ap.z) + std::fabs(bp.x) + std::fabs(bp.y) + std::fabs(bp.z);
      whole = true;
      for (int k = 0; k < np0; k++) {
        if (k < 64 && ((inm >> k) & 1)) continue;  // inside it for every receiver of the tile (STEdge::inm)
        const T g0 = dot(ap, cone[k]), g1 = dot(d, cone[k]), g01 = g0 + g1;
        if (g0 < 0) {
          const T m = T(8) * T(kCollinearEps) * eps_of<T>() * (std::fabs(cone[k].x) + std::fabs(cone[k].y) + std::fabs(cone[k].z)) * apl;
          if (g01 < 0 && -g0 > m && -g01 > m) return true;
        }
        whole = whole && ((g0 > 0 && g01 > 0) || cz[k]);
      }
    }
    const V3<T> own = own_of(a3, b3);
    T t0 = 0, t1 = 1;
    int i0 = 0, i1 = 0;
    if (!whole && !cyrus_beck(p, a3, b3, cone, np0, own, t0, t1, i0, i1)) return true;
    const PlaneRef oref = through(e.ra, e.rb);
    SSeg<T>& s = segs.emplace_back();  // built in place (SSeg's constructor leaves it unset)
    s.own = own, s.own_n = norm(own), s.q0s = 0, s.own_ref = oref, s.w = W, s.va = e.ra, s.vb = e.rb, s.x3a = a3, s.x3b = b3;
    s.ia = ia, s.ib = ib;
    // An end: where the edge leaves the pyramid through cone plane i (clipped), or its vertex's projection.
    const auto end = [&](bool clipped, int i, V3<T> x3, int32_t ref, V3<T>& at, decltype(s.ca)& code, decltype(s.on_a)& on) {
      if (clipped) {
        at = eh_crossing(call.L, prefs[i], p, cone[i], own, ne, hp);
        code = code_planes(prefs[i], oref);
        on = i;
      } else {
        at = project(p, x3, ne, hp);
        code = code_point(kProjected, ref);
        on = -1;
      }
    };
    end(t0 > 0, i0, a3, e.ra, s.a, s.ca, s.on_a);
    end(t1 < 1, i1, b3, e.rb, s.b, s.cb, s.on_b);
    if (same(s.a, s.b)) {
      segs.pop_back();
      return true;
    }
    for (int k = 0; k < np0 && !in; k++) {  // an unclipped end on E_h's boundary: too close to call
      if (cz[k] || (k < 64 && ((inm >> k) & 1))) continue;
      const V3<T> ra = s.a - p, rb = s.b - p;
      const T cn1 = cone_n[k];
      if ((s.on_a < 0 && !(std::fabs(dot(ra, cone[k])) > tol * cn1 * (std::fabs(ra.x) + std::fabs(ra.y) + std::fabs(ra.z)))) ||
          (s.on_b < 0 && !(std::fabs(dot(rb, cone[k])) > tol * cn1 * (std::fabs(rb.x) + std::fabs(rb.y) + std::fabs(rb.z)))))
        return false;
    }
    n_contour++;
    return true;
  };
  bool in_tile = w.tile.id >= 0;
  for (int d = 0; d < 3 && in_tile; d++) in_tile = pd[d] >= w.tile.lo[d] && pd[d] <= w.tile.hi[d];
  if (in_tile && (w.sil_tile.id != w.tile.id || w.sil_tile.tree != &st)) {
    const SilTileCache* parent = nullptr;
    if (w.tile.pid >= 0) {
      if (w.sil_parent.id != w.tile.pid || w.sil_parent.tree != &st)
        tile_walk(call, st, ne, w.tile.pid, w.tile.plo, w.tile.phi, false, w.tile.n, nullptr, w.sil_parent, false);
      if (w.sil_parent.ok) parent = &w.sil_parent;
    }
    tile_walk(call, st, ne, w.tile.id, w.tile.lo, w.tile.hi, w.tile.same_n, w.tile.n, parent, w.sil_tile, true);
  }
  if (in_tile && w.sil_tile.ok) {
    SilTileCache& tc = w.sil_tile;
    tile_sides(tc, pd, side_scale);
    const double* side = tc.side.data();
    const STEntry* entries = tc.entries.data();
    const STEdge* edges = tc.edges.data();
    const int32_t n = int32_t(tc.entries.size());
    for (int32_t i = 0; i < n;) {
      const STEntry& en = entries[i];
      if (!en.sure) {
        const SNode& nd = st.nodes[size_t(en.node)];
        if (outside_of(nd.box, en.planes) || (en.side && node_side(nd, pd, smargin) != 0)) {
          i = en.skip;
          continue;
        }
      }
      const int32_t e1 = en.e1;
      for (int32_t k = en.e0; k < e1; k++) {  // a leaf's edges (an inner node has none)
        const STEdge& te = edges[k];
        const auto ends = [&](V3<T>& a3, V3<T>& b3) __attribute__((always_inline)) {
          a3 = V3<T>{T(te.a[0]), T(te.a[1]), T(te.a[2])}, b3 = V3<T>{T(te.b[0]), T(te.b[1]), T(te.b[2])};
        };
        const auto own_of = [&](V3<T> a3, V3<T> b3) __attribute__((always_inline)) {
          const V3<T> lo = te.fwd ? a3 : b3, hi = te.fwd ? b3 : a3;
          const V3<T> rl = lo - p, rh = hi - p;
          const V3<T> dir{T(te.dir[0]), T(te.dir[1]), T(te.dir[2])};
          // edge_plane: rescale(c) negated where !fwd, as one product by the signed power of 2
          const V3<T> c = cross(dir, rescale(dot(rh, rh) < dot(rl, rl) ? rh : rl));
          const T sc = pow2_scale(absmax(c));
          return (te.fwd ? sc : -sc) * c;
        };
        if (!edge(te.e, te.w, te.in, te.inm, te.ia, te.ib, [&]() { return int(side[te.lf]); }, [&]() { return int(side[te.lg]); }, ends, own_of))
          return kFallback;
      }
      i++;
    }
    return n_contour;
  }
  int32_t stack[128];
  int sp = 0;
  stack[sp++] = 0;
  while (sp) {
    const SNode& nd = st.nodes[size_t(stack[--sp])];
    if (outside(nd.box)) continue;
    if (!nd.special && node_side(nd, pd, smargin) != 0) continue;
    if (nd.left >= 0) {
      if (sp + 2 > 128) return kFallback;
      stack[sp++] = nd.left;
      stack[sp++] = nd.right;
      // The walk is bound by memory: the left child (visited after the right subtree, which
      // follows this node in memory) is fetched while the right one is tested.
      __builtin_prefetch(&st.nodes[size_t(nd.left)]);
      continue;
    }
    for (int32_t k = nd.start; k < nd.start + nd.count; k++) {  // the leaf's faces, fetched at once
      const SEdge& e = st.edges[size_t(k)];
      __builtin_prefetch(st.fn.data() + kFnStride * size_t(e.f));
      if (e.g >= 0) __builtin_prefetch(st.fn.data() + kFnStride * size_t(e.g));
    }
    for (int32_t k = nd.start; k < nd.start + nd.count; k++) {
      const SEdge& e = st.edges[size_t(k)];
      if (!edge(e, 0, false, 0, -1, -1, [&]() { return sil_side(st, e.f, pd, side_scale); },
                [&]() { return sil_side(st, e.g, pd, side_scale); }, [&](V3<T>& a3, V3<T>& b3) { a3 = occ.vref(e.ra), b3 = occ.vref(e.rb); },
                [&](V3<T> a3, V3<T> b3) { return edge_plane(p, a3, b3); }))
        return kFallback;
    }
  }
  return n_contour;
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_SILHOUETTE_WALK_H_
