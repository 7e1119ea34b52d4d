// jaxshadow's shadow engine: the silhouette path's contour walk (part of `csrc/shadowc.cc`; see
// silhouette.h): the contour edges a receiver sees inside its pyramid, found with the hierarchy of
// silhouette_tree.h and clipped to the pyramid.
#ifndef JAXSHADOW_SHADOWC_SILHOUETTE_WALK_H_
#define JAXSHADOW_SHADOWC_SILHOUETTE_WALK_H_

#include "silhouette_tree.h"

namespace jaxshadow_engine {

// Contour edges in the pyramid: the hierarchy walked with the pyramid's half-spaces (`cone`, the
// np0 planes of E_h through p, and the emitter plane) and the faces' sides. Each is appended to
// `segs` projected onto the emitter plane and clipped to E_h. Returns how many, or kFallback.
template <class T>
int32_t contour_edges(const PolyCall<T>& call, const SilhouetteTree& st, V3<T> p, const V3<T>* cone,
                      const PlaneRef* prefs, int np0, V3<T> ne, double hp, double scale, std::vector<SSeg<T>>& segs) {
  const Occluders<T>& occ = call.occ;
  const double eps = 2.220446049250313e-16;
  const double tol = kCollinearEps * eps;
  const double pd[3] = {p.x, p.y, p.z};

  double cn[66][3], cq[66][3];
  int nc = 0;
  for (int k = 0; k < np0; k++) {
    if (!nonzero(cone[k])) continue;
    cn[nc][0] = cone[k].x, cn[nc][1] = cone[k].y, cn[nc][2] = cone[k].z;
    cq[nc][0] = p.x, cq[nc][1] = p.y, cq[nc][2] = p.z;
    nc++;
  }
  const V3<T> e0 = call.L.v(0);
  cn[nc][0] = ne.x, cn[nc][1] = ne.y, cn[nc][2] = ne.z;  // the emitter plane: the pyramid on p's side
  cq[nc][0] = e0.x, cq[nc][1] = e0.y, cq[nc][2] = e0.z;
  nc++;
  const double bmargin = 1e3 * eps * scale;
  double cnn[66];
  for (int k = 0; k < nc; k++) cnn[k] = std::fabs(cn[k][0]) + std::fabs(cn[k][1]) + std::fabs(cn[k][2]);
  auto outside = [&](const double* box) {
    for (int k = 0; k < nc; k++) {
      // The box's corner farthest along the plane's normal.
      const double x[3] = {box[cn[k][0] > 0 ? 3 : 0], box[cn[k][1] > 0 ? 4 : 1], box[cn[k][2] > 0 ? 5 : 2]};
      const double best = cn[k][0] * (x[0] - cq[k][0]) + cn[k][1] * (x[1] - cq[k][1]) + cn[k][2] * (x[2] - cq[k][2]);
      if (best < -bmargin * cnn[k]) return true;
    }
    return false;
  };
  const double smargin = 4 * kOnSurface * scale;  // beyond the on-surface distance (sil_side)
  T cone_n[66];
  for (int k = 0; k < np0 && k < 66; k++) cone_n[k] = norm(cone[k]);
  int32_t stack[128];
  int sp = 0;
  stack[sp++] = 0;
  int32_t n_contour = 0;
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
      const int sf = sil_side(st, e.f, pd);
      if (sf == 0) return kFallback;
      int W = sf;
      if (e.g >= 0) {
        const int sg = sil_side(st, e.g, pd);
        if (sg == 0) return kFallback;
        W += sg * e.dg;
      }
      if (W == 0) continue;
      const V3<T> a3 = occ.vref(e.ra), b3 = occ.vref(e.rb);
      {
        // Both ends clearly outside one cone plane: cyrus_beck's interval for that plane is empty
        // (the same g0, g1; beyond its collinear tolerance, as norms are at most 1-norms), so it
        // would return false. Skips the edge's plane and the clipping for most non-contour edges
        // that the hierarchy's boxes let through.
        const V3<T> ap = a3 - p, d = b3 - a3, bp = b3 - p;
        const T apl = std::fabs(ap.x) + std::fabs(ap.y) + std::fabs(ap.z) + std::fabs(bp.x) + std::fabs(bp.y) + std::fabs(bp.z);
        bool out = false;
        for (int k = 0; k < np0 && !out; k++) {
          const T g0 = dot(ap, cone[k]);
          if (!(g0 < 0)) continue;
          const T g1 = dot(d, cone[k]), g01 = g0 + g1;
          const T m = T(8) * T(kCollinearEps) * eps_of<T>() * (std::fabs(cone[k].x) + std::fabs(cone[k].y) + std::fabs(cone[k].z)) * apl;
          out = g01 < 0 && -g0 > m && -g01 > m;
        }
        if (out) continue;
      }
      const V3<T> own = edge_plane(p, a3, b3);
      double t0, t1;
      int i0, i1;
      if (!cyrus_beck(p, a3, b3, cone, np0, own, t0, t1, i0, i1)) continue;
      const PlaneRef oref = through(e.ra, e.rb);
      SSeg<T> s;
      s.own = own, s.own_n = norm(own), s.q0s = 0, s.own_ref = oref, s.w = W, s.va = e.ra, s.vb = e.rb, s.x3a = a3, s.x3b = b3;
      if (t0 > 0) {
        s.a = crossing_point(p, cross(cone[i0], own), ne, hp);
        s.ca = code_planes(prefs[i0], oref);
        s.on_a = i0;
      } else {
        s.a = project(p, a3, ne, hp);
        s.ca = code_point(kProjected, e.ra);
        s.on_a = -1;
      }
      if (t1 < 1) {
        s.b = crossing_point(p, cross(cone[i1], own), ne, hp);
        s.cb = code_planes(prefs[i1], oref);
        s.on_b = i1;
      } else {
        s.b = project(p, b3, ne, hp);
        s.cb = code_point(kProjected, e.rb);
        s.on_b = -1;
      }
      if (same(s.a, s.b)) continue;
      for (int k = 0; k < np0; k++) {  // an unclipped end on E_h's boundary: too close to call
        if (!nonzero(cone[k])) continue;
        const V3<T> ra = s.a - p, rb = s.b - p;
        const T cn1 = cone_n[k];
        if ((s.on_a < 0 && !(std::fabs(dot(ra, cone[k])) > tol * cn1 * (std::fabs(ra.x) + std::fabs(ra.y) + std::fabs(ra.z)))) ||
            (s.on_b < 0 && !(std::fabs(dot(rb, cone[k])) > tol * cn1 * (std::fabs(rb.x) + std::fabs(rb.y) + std::fabs(rb.z)))))
          return kFallback;
      }
      segs.push_back(s);
      n_contour++;
    }
  }
  return n_contour;
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_SILHOUETTE_WALK_H_
