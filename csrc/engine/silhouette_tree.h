// jaxshadow's shadow engine: the silhouette path for large meshes (part of `csrc/shadowc.cc`; see
// its header comment).
//
// Seen from a receiver p, the faces of a mesh that lie strictly between p's level and the
// emitter plane project centrally onto that plane as convex polygons; the number of them covering
// a point q of the emitter plane (the depth complexity C(q), every face counted whichever way it
// faces) is what blocks q: q is visible iff C(q) = 0. Summing the faces' projected boundaries,
// each oriented with its face on the positive side, an edge shared by two faces that lie on
// opposite sides of the plane through p and the edge cancels; what is left are the contour edges
// (silhouette edges, where the two faces lie on the same side, with weight 2; boundary and
// non-manifold edges, weight 1), and C jumps by an edge's weight W across it. So C at any point
// follows from C at one reference point q0 (the faces a ray from p towards q0 crosses) plus the
// signed crossings of the segment q0 -> q with the contour edges (Laine et al. 2005, soft shadow
// volumes), and the visible region's boundary is made of the pieces of contour edges (cut where
// they cross each other) with C = 0 on exactly one side, and of the pieces of E_h's edges with
// C = 0 inside. The contour edges are found with a hierarchy of the mesh's edges whose nodes bound
// their faces' planes (a box of the faces' vertices and a cone of their normals): a node whose
// faces all face p the same way and that holds no boundary, non-manifold or inconsistently
// oriented edge has no contour edge and is skipped with its whole subtree, so the work per
// receiver grows with the contour inside the light's pyramid, not with the faces.
//
// Used for calls with many faces (a convex solid's faces count as faces here), for receivers that every occluder
// vertex lies strictly between (in height above the emitter plane); any decision too close to
// call (a face's plane through p, a reference ray along an edge, crossings at a vertex, collinear
// edges) returns kFallback and the receiver takes the face path (polygon.h), which resolves those.
#ifndef JAXSHADOW_SHADOWC_SILHOUETTE_H_
#define JAXSHADOW_SHADOWC_SILHOUETTE_H_

#include <array>
#include <map>

#include "polygon_types.h"

namespace jaxshadow_engine {

// T-junctions: edges without a twin that overlap along one line, such as an edge a -> c of one
// face and c -> b -> a of faces on the other side (coplanar merging leaves them where it drops a
// straight vertex of the merged face that a neighbour across a crease keeps). Such a group is
// cut at every end of its edges (each cut point within 1e-9 of the line's length of the line),
// and where every piece then runs against exactly one piece of another face, the pieces are
// paired as interior edges, as on a mesh without the junction, instead of boundary edges
// overlapping each other (collinear contour edges that no receiver can decide). Any other group
// is left as it is.
template <class T>
void resolve_t_junctions(const Occluders<T>& occ, std::vector<SEdge>& edges) {
  std::vector<int32_t> open;
  for (size_t k = 0; k < edges.size(); k++)
    if (edges[k].g < 0) open.push_back(int32_t(k));
  if (open.size() < 3) return;
  using Key = std::array<double, 3>;
  auto key = [&](int32_t r) {
    const V3<T> x = occ.vref(r);
    return Key{double(x.x), double(x.y), double(x.z)};
  };
  std::map<Key, std::vector<int32_t>> at;  // untwinned edges by the positions of their ends
  for (const int32_t k : open) {
    at[key(edges[size_t(k)].ra)].push_back(k);
    at[key(edges[size_t(k)].rb)].push_back(k);
  }
  std::vector<uint8_t> done(edges.size(), 0), used(edges.size(), 0);
  std::vector<SEdge> added;
  std::vector<int32_t> group, todo;
  struct Cut {
    double t;
    int32_t ref;
  };
  std::vector<Cut> cuts;
  for (const int32_t x : open) {
    if (done[size_t(x)]) continue;
    const V3<T> a = occ.vref(edges[size_t(x)].ra), ac = occ.vref(edges[size_t(x)].rb) - a;
    const double len2 = double(dot(ac, ac));
    done[size_t(x)] = 1;
    if (!(len2 > 0)) continue;
    auto param = [&](int32_t r, double& t) {  // r's position along a -> c; false: off the line
      const V3<T> ab = occ.vref(r) - a;
      t = double(dot(ab, ac)) / len2;
      const V3<T> off = ab - T(t) * ac;
      return double(dot(off, off)) < 1e-18 * len2;
    };
    // The group: untwinned edges on the line reached through shared end positions.
    group.assign(1, x);
    todo.assign(1, x);
    bool ok = true;
    while (!todo.empty() && ok) {
      const SEdge e = edges[size_t(todo.back())];
      todo.pop_back();
      for (const int32_t r : {e.ra, e.rb})
        for (const int32_t y : at[key(r)]) {
          if (done[size_t(y)]) continue;
          double ta, tb;
          if (!param(edges[size_t(y)].ra, ta) || !param(edges[size_t(y)].rb, tb)) continue;  // another line
          done[size_t(y)] = 1;
          group.push_back(y);
          todo.push_back(y);
          if (group.size() > 256) ok = false;
        }
    }
    if (!ok || group.size() < 3) continue;
    cuts.clear();
    for (const int32_t y : group)
      for (const int32_t r : {edges[size_t(y)].ra, edges[size_t(y)].rb}) {
        double t;
        param(r, t);
        cuts.push_back({t, r});
      }
    std::sort(cuts.begin(), cuts.end(), [](const Cut& u, const Cut& v) { return u.t < v.t; });
    // One cut per position (the first reference of it), all positions apart along the line.
    std::vector<Cut> pts;
    for (const Cut& u : cuts) {
      if (!pts.empty() && key(pts.back().ref) == key(u.ref)) continue;
      if (!pts.empty() && !(u.t > pts.back().t + 1e-9)) {
        ok = false;
        break;
      }
      pts.push_back(u);
    }
    if (!ok) continue;
    auto index_of = [&](int32_t r) {
      const Key kr = key(r);
      for (size_t i = 0; i < pts.size(); i++)
        if (key(pts[i].ref) == kr) return int(i);
      return -1;
    };
    // Per interval between consecutive cuts: the edge running along the line, the one against it.
    const int nI = int(pts.size()) - 1;
    std::vector<int32_t> fwd(size_t(nI), -1), bwd(size_t(nI), -1);
    for (const int32_t y : group) {
      const int ia = index_of(edges[size_t(y)].ra), ib = index_of(edges[size_t(y)].rb);
      if (ia < 0 || ib < 0 || ia == ib) ok = false;
      std::vector<int32_t>& side = ia < ib ? fwd : bwd;
      for (int i = std::min(ia, ib); ok && i < std::max(ia, ib); i++) {
        if (side[size_t(i)] >= 0) ok = false;
        side[size_t(i)] = y;
      }
      if (!ok) break;
    }
    for (int i = 0; ok && i < nI; i++)
      ok = fwd[size_t(i)] >= 0 && bwd[size_t(i)] >= 0 && edges[size_t(fwd[size_t(i)])].f != edges[size_t(bwd[size_t(i)])].f;
    if (!ok) continue;
    // Each interval an interior edge of the face running along the line and the one against it;
    // a piece's ends are its own edge's references where they are its ends.
    for (int i = 0; i < nI; i++) {
      const SEdge& ef = edges[size_t(fwd[size_t(i)])];
      const int32_t ra = index_of(ef.ra) == i ? ef.ra : pts[size_t(i)].ref;
      const int32_t rb = index_of(ef.rb) == i + 1 ? ef.rb : pts[size_t(i + 1)].ref;
      added.push_back(SEdge{ra, rb, ef.f, edges[size_t(bwd[size_t(i)])].f, int8_t(-1)});
    }
    for (const int32_t y : group) used[size_t(y)] = 1;
  }
  if (added.empty()) return;
  std::vector<SEdge> kept;
  kept.reserve(edges.size() + added.size());
  for (size_t k = 0; k < edges.size(); k++)
    if (!used[k]) kept.push_back(edges[k]);
  kept.insert(kept.end(), added.begin(), added.end());
  edges.swap(kept);
}

template <class T>
void build_silhouette_tree(const Occluders<T>& occ, const std::vector<int32_t>& twin, SilhouetteTree& st) {
  st = SilhouetteTree();
  const int64_t M = occ.M, Ko = occ.Ko;
  if (M < kSilhouetteMinFaces || Ko > 64 || twin.size() != size_t(M * Ko)) return;
  st.fn.assign(kFnStride * size_t(M), 0.0);
  for (int64_t f = 0; f < M; f++) {
    V3<T> o = occ.vert(f, 0), n{0, 0, 0};
    for (int64_t i = 0; i < Ko; i++) {
      const V3<T> x = occ.vert(f, i);
      n = n + cross(x - o, occ.vert(f, (i + 1) % Ko) - o);
      if (!(double(absmax(x)) < std::numeric_limits<double>::infinity())) return;
      st.scale = std::max(st.scale, double(absmax(x)));
    }
    const double nn = double(norm(n));
    if (!(nn > 0)) return;  // a degenerate face: the face path
    double* q = st.fn.data() + kFnStride * size_t(f);
    q[0] = n.x, q[1] = n.y, q[2] = n.z, q[3] = o.x, q[4] = o.y, q[5] = o.z;
    q[6] = n.x / nn, q[7] = n.y / nn, q[8] = n.z / nn;
    q[9] = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]);  // as sil_side would compute it
  }
  for (int64_t f = 0; f < M; f++)
    for (int64_t i = 0; i < Ko; i++) {
      if (same(occ.vert(f, i), occ.vert(f, (i + 1) % Ko))) continue;
      const int32_t t = twin[size_t(f * Ko + i)];
      SEdge e{occ.ref(f, i), occ.ref(f, (i + 1) % Ko), int32_t(f), -1, 0};
      if (t >= 0) {
        if ((t >> 1) < f) continue;  // recorded from the other face
        e.g = t >> 1;
        e.dg = (t & 1) ? int8_t(1) : int8_t(-1);
      }
      st.edges.push_back(e);
    }
  resolve_t_junctions(occ, st.edges);
  // Build: sort by the edge midpoints along the box's longest axis, split at the median.
  const int64_t E = int64_t(st.edges.size());
  std::vector<double> mid(size_t(3 * E));
  for (int64_t k = 0; k < E; k++) {
    const V3<T> a = occ.vref(st.edges[k].ra), b = occ.vref(st.edges[k].rb);
    mid[3 * k] = 0.5 * (double(a.x) + double(b.x));
    mid[3 * k + 1] = 0.5 * (double(a.y) + double(b.y));
    mid[3 * k + 2] = 0.5 * (double(a.z) + double(b.z));
  }
  std::vector<int32_t> order(static_cast<size_t>(E));
  for (int64_t k = 0; k < E; k++) order[k] = int32_t(k);
  auto fill = [&](SNode& nd) {  // box, cone and flag from the node's edges' faces
    for (int d = 0; d < 3; d++) {
      nd.box[d] = std::numeric_limits<double>::infinity();
      nd.box[3 + d] = -std::numeric_limits<double>::infinity();
    }
    double ax[3] = {0, 0, 0};
    nd.special = false;
    auto face = [&](int32_t f) {
      for (int64_t i = 0; i < Ko; i++) {
        const V3<T> x = occ.vert(f, i);
        const double c[3] = {double(x.x), double(x.y), double(x.z)};
        for (int d = 0; d < 3; d++) {
          nd.box[d] = std::min(nd.box[d], c[d]);
          nd.box[3 + d] = std::max(nd.box[3 + d], c[d]);
        }
      }
      for (int d = 0; d < 3; d++) ax[d] += st.fn[kFnStride * size_t(f) + 6 + d];
    };
    for (int32_t k = nd.start; k < nd.start + nd.count; k++) {
      const SEdge& e = st.edges[order[k]];
      face(e.f);
      if (e.g >= 0) face(e.g);
      nd.special = nd.special || e.g < 0 || e.dg > 0;
    }
    const double an = std::sqrt(ax[0] * ax[0] + ax[1] * ax[1] + ax[2] * ax[2]);
    nd.cosa = -1;
    nd.sina = 1;
    if (!(an > 0)) return;
    for (int d = 0; d < 3; d++) nd.axis[d] = ax[d] / an;
    double cmin = 1;
    auto cone = [&](int32_t f) {
      const double* u = st.fn.data() + kFnStride * size_t(f) + 6;
      cmin = std::min(cmin, u[0] * nd.axis[0] + u[1] * nd.axis[1] + u[2] * nd.axis[2]);
    };
    for (int32_t k = nd.start; k < nd.start + nd.count; k++) {
      cone(st.edges[order[k]].f);
      if (st.edges[order[k]].g >= 0) cone(st.edges[order[k]].g);
    }
    cmin = std::max(-1.0, std::min(1.0, cmin)) - 1e-12;  // rounding of the unit normals
    nd.cosa = cmin;
    nd.sina = std::sqrt(std::max(0.0, 1 - cmin * cmin)) + 1e-12;
  };
  st.nodes.reserve(size_t(2 * E / 4 + 2));
  struct Job {
    int32_t node, start, count;
  };
  std::vector<Job> jobs;
  st.nodes.push_back(SNode{});
  jobs.push_back({0, 0, int32_t(E)});
  while (!jobs.empty()) {
    const Job jb = jobs.back();
    jobs.pop_back();
    SNode nd{};
    nd.start = jb.start;
    nd.count = jb.count;
    nd.left = nd.right = -1;
    fill(nd);
    if (jb.count > 4) {
      int ax = 0;
      double ext = -1;
      for (int d = 0; d < 3; d++)
        if (nd.box[3 + d] - nd.box[d] > ext) ext = nd.box[3 + d] - nd.box[d], ax = d;
      const int32_t half = jb.count / 2;
      std::nth_element(order.begin() + jb.start, order.begin() + jb.start + half, order.begin() + jb.start + jb.count,
                       [&](int32_t x, int32_t y) { return mid[3 * size_t(x) + ax] < mid[3 * size_t(y) + ax]; });
      nd.left = int32_t(st.nodes.size());
      st.nodes.push_back(SNode{});
      nd.right = int32_t(st.nodes.size());
      st.nodes.push_back(SNode{});
      jobs.push_back({nd.left, jb.start, half});
      jobs.push_back({nd.right, jb.start + half, jb.count - half});
    }
    st.nodes[size_t(jb.node)] = nd;
  }
  std::vector<SEdge> sorted(static_cast<size_t>(E));
  for (int64_t k = 0; k < E; k++) sorted[k] = st.edges[order[k]];
  st.edges.swap(sorted);
  st.f32.resize(size_t(M));
  for (int64_t f = 0; f < M; f++) st.f32[size_t(f)] = float32_face(occ, f);
  st.ok = true;
}

// The occluders' heights above the emitter plane (ne . (x - e0)) for one light: whether the
// silhouette path may serve this call (`call.sil_ok`) and its bounds.
template <class T>
void silhouette_heights(PolyCall<T>& call) {
  call.sil_ok = false;
  if (!call.sil || !call.sil->ok) return;
  // JAXSHADOW_SILHOUETTE=0 switches the path off (every receiver takes the face path): for
  // measuring one against the other, and for tests that compare them. Read per call (the
  // prepared data are cached across calls).
  const char* env = std::getenv("JAXSHADOW_SILHOUETTE");
  if (env && env[0] == '0') return;
  const Occluders<T>& occ = call.occ;
  const V3<T> ne = call.ne_raw, e0 = call.L.v(0);
  double lo = std::numeric_limits<double>::infinity(), hi = -lo;
  for (int64_t k = 0; k < occ.M * occ.Ko; k++) {
    const double h = double(dot(ne, ld(occ.faces + 3 * k) - e0));
    lo = std::min(lo, h);
    hi = std::max(hi, h);
  }
  call.sil_hmin = lo;
  call.sil_hmax = hi;
  call.sil_ok = std::isfinite(lo) && std::isfinite(hi);
}

// Which way face f faces p: +1 when p is in front of its Newell normal... as face_side decides
// (+1: h0 = N . (v0 - p) < 0), 0 when p is within the rounding bound of its plane.
// Within the on-surface distance of the plane of a face of float32 values (kOnSurface of the
// scene's largest coordinate, at least face_side's own bound) it is 0 too: the face path then
// applies the on-surface rule.
inline int sil_side(const SilhouetteTree& st, int32_t f, const double* p) {
  const double* q = st.fn.data() + kFnStride * size_t(f);
  const double r0 = q[3] - p[0], r1 = q[4] - p[1], r2 = q[5] - p[2];
  const double h = q[0] * r0 + q[1] * r1 + q[2] * r2;
  const double nn = q[9];
  const double S = std::max(st.scale, std::max(std::fabs(p[0]), std::max(std::fabs(p[1]), std::fabs(p[2]))));
  const double m = std::max(1e4 * 2.220446049250313e-16 * (std::fabs(r0) + std::fabs(r1) + std::fabs(r2) + S),
                            st.f32[size_t(f)] ? 2 * kOnSurface * S : 0.0) * nn;
  return h < -m ? 1 : (h > m ? -1 : 0);
}

// +1 (-1): every face of the node faces p with side +1 (-1) by a clear margin; 0: not known.
inline int node_side(const SNode& nd, const double* p, double margin) {
  if (!(nd.cosa > 0)) return 0;
  double amin = std::numeric_limits<double>::infinity(), amax = -amin, perp2 = 0;
  for (int c = 0; c < 8; c++) {
    const double d[3] = {p[0] - nd.box[(c & 1) ? 3 : 0], p[1] - nd.box[(c & 2) ? 4 : 1], p[2] - nd.box[(c & 4) ? 5 : 2]};
    const double a = d[0] * nd.axis[0] + d[1] * nd.axis[1] + d[2] * nd.axis[2];
    const double e[3] = {d[0] - a * nd.axis[0], d[1] - a * nd.axis[1], d[2] - a * nd.axis[2]};
    amin = std::min(amin, a);
    amax = std::max(amax, a);
    perp2 = std::max(perp2, e[0] * e[0] + e[1] * e[1] + e[2] * e[2]);
  }
  // The largest |e|: sqrt is correctly rounded, hence monotone, so the root of the largest
  // square is the largest root.
  const double perp = std::sqrt(perp2);
  // n . d with n within the cone and d = p - v over the box: n . d >= a cos - |d_perp| sin.
  // side +1 <=> N . (v - p) < 0 <=> n . d > 0.
  if (amin * nd.cosa - perp * nd.sina > margin) return 1;
  if (amax * nd.cosa + perp * nd.sina < -margin) return -1;
  return 0;
}

// The receiver through the silhouette path: its class with w.runs its boundary, or kFallback.
// `eh` are E_h's edges (polygon_receiver's first edges), `cone` / `prefs` E_h's planes.
template <class T>
int32_t silhouette_receiver(const PolyCall<T>& call, const SilhouetteTree& st, V3<T> p, V3<T> n,
                            const Edge<T>* eh, int neh, const V3<T>* cone, const PlaneRef* prefs, int np0,
                            V3<T> ne, double hp, Work<T>& w) {
  const Occluders<T>& occ = call.occ;
  const double eps = 2.220446049250313e-16;
  const double tol = kCollinearEps * eps;
  const double pd[3] = {p.x, p.y, p.z};
  const double scale = std::max(st.scale, double(absmax(p))) + 1e-300;
  std::vector<SSeg<T>>& segs = w.ssegs;
  segs.clear();
  for (int i = 0; i < neh; i++) {
    SSeg<T> s;
    s.a = eh[i].a, s.b = eh[i].b, s.own = eh[i].own, s.own_ref = eh[i].own_ref, s.ca = eh[i].ca, s.cb = eh[i].cb;
    s.w = 0, s.va = s.vb = -1, s.on_a = s.on_b = -1, s.own_n = norm(s.own), s.q0s = 0;
    segs.push_back(s);
  }
  // Contour edges in the pyramid: the hierarchy walked with the pyramid's half-spaces and the
  // faces' sides.
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
      continue;
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
  w.n_candidates = n_contour;
  // Each E_h edge's cone plane (its plane vector is a copy of one).
  int eh_plane[130];
  for (int i = 0; i < neh; i++) {
    eh_plane[i] = -1;
    for (int k = 0; k < np0 && eh_plane[i] < 0; k++)
      if (same(cone[k], eh[i].own)) eh_plane[i] = k;
    if (eh_plane[i] < 0) return kFallback;
  }
  w.n_regions = 1;
  const int ns = int(segs.size());
  // A clear sign of `x` against the bound `m` (0: too close to call).
  auto sgn = [](double x, double m) { return x > m ? 1 : (x < -m ? -1 : 0); };
  auto side_of = [&](V3<T> x, const SSeg<T>& s) {  // of a point in the emitter plane, against s.own
    const V3<T> r = x - p;
    return sgn(dot(r, s.own), tol * s.own_n * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z)));
  };
  // Reference points inside E_h: its centroid, then points towards its corners.
  V3<T> centre{0, 0, 0};
  for (int i = 0; i < neh; i++) centre = centre + eh[i].a;
  centre = (1.0 / neh) * centre;
  // C at q0: faces crossed by the segment from p to q0, every face counted.
  auto layers = [&](V3<T> q0) -> int {
    const BVH& bvh = *call.bvh;
    const V3<T> r = q0 - p;
    const double o[3] = {p.x, p.y, p.z}, dd[3] = {r.x, r.y, r.z};
    int count = 0;
    int32_t stk[128];
    int sq = 0;
    stk[sq++] = 0;
    while (sq) {
      const Node& nd = bvh.nodes[size_t(stk[--sq])];
      double ta = 0, tb = 1;
      bool hit = true;
      for (int k = 0; k < 3 && hit; k++) {
        const double pad = 1e-9 * (std::fabs(nd.box[k]) + std::fabs(nd.box[3 + k]) + std::fabs(o[k]) + 1e-300);
        const double lo = nd.box[k] - pad, hi = nd.box[3 + k] + pad;
        if (dd[k] == 0) {
          hit = !(o[k] < lo || o[k] > hi);
          continue;
        }
        double x = (lo - o[k]) / dd[k], y = (hi - o[k]) / dd[k];
        if (x > y) std::swap(x, y);
        ta = std::max(ta, x);
        tb = std::min(tb, y);
        hit = ta <= tb;
      }
      if (!hit) continue;
      if (nd.left >= 0) {
        if (sq + 2 > 128) return -1;
        stk[sq++] = nd.left;
        stk[sq++] = nd.right;
        continue;
      }
      for (int32_t i = nd.start; i < nd.start + nd.count; i++) {
        const int32_t item = bvh.items[size_t(i)];
        const int64_t f0 = item >= 0 ? item : occ.solid_faces[2 * (-int64_t(item) - 1)];
        const int64_t f1 = item >= 0 ? item + 1 : occ.solid_faces[2 * (-int64_t(item) - 1) + 1];
        for (int64_t f = f0; f < f1; f++) {
        const int s = sil_side(st, int32_t(f), pd);
        if (s == 0) return -1;
        bool in = true;
        for (int64_t k = 0; k < occ.Ko && in; k++) {
          const V3<T> a = occ.vert(f, k), b = occ.vert(f, (k + 1) % occ.Ko);
          if (same(a, b)) continue;
          const V3<T> pl = double(s) * edge_plane(p, a, b);
          const int c = sgn(dot(pl, r), tol * norm(pl) * norm(r));
          if (c == 0) return -1;
          in = c > 0;
        }
        count += in;  // the face lies between p and q0 (every vertex strictly below the light)
        }
      }
    }
    return count;
  };
  V3<T> q0{};
  int c0 = -1;
  for (int attempt = 0; attempt <= neh && c0 < 0; attempt++) {
    q0 = attempt == 0 ? centre : centre + 0.37 * (eh[attempt - 1].a - centre);
    bool clear = true;
    for (int i = neh; i < ns && clear; i++) clear = side_of(q0, segs[i]) != 0;
    if (clear) c0 = layers(q0);
  }
  if (c0 < 0) return kFallback;
  for (int i = 0; i < ns; i++) segs[size_t(i)].q0s = side_of(q0, segs[size_t(i)]);
  const int kNone = std::numeric_limits<int>::min();
  // The jump of C along the path from -> m (pqm = cross(from - p, m - p), pn its norm) across
  // piece s: 0 when they do not cross, +-W when they do, kNone when a crossing is too close to
  // call.
  // An end of the path on the piece's line (a point of a collinear piece, as along a straight
  // crease of a CAD part) is decided by the piece's ends: both clearly on one side of the path's
  // plane, the piece does not meet the path.
  auto jump_from = [&](const SSeg<T>& s, int sq, V3<T> m, V3<T> pqm, double pn) -> int {
    const int sm = side_of(m, s);
    if (sq != 0 && sm == sq) return 0;
    const V3<T> ra = s.a - p, rb = s.b - p;
    const int ca = sgn(dot(ra, pqm), tol * pn * (std::fabs(ra.x) + std::fabs(ra.y) + std::fabs(ra.z)));
    const int cb = sgn(dot(rb, pqm), tol * pn * (std::fabs(rb.x) + std::fabs(rb.y) + std::fabs(rb.z)));
    if (ca == 0 || cb == 0) return kNone;
    if (ca == cb) return 0;
    if (sq == 0 || sm == 0) return kNone;
    return sm > 0 ? s.w : -s.w;  // from `from`'s side to m's: + W into the positive side
  };
  auto jump = [&](const SSeg<T>& s, V3<T> from, V3<T> m, V3<T> pqm, double pn) -> int {
    return jump_from(s, side_of(from, s), m, pqm, pn);
  };
  // C on the q0 side of point m (in the emitter plane), from the crossings of q0 -> m with every
  // contour edge but `skip`; kNone when a crossing is too close to call.
  auto coverage = [&](V3<T> m, int skip) -> int {
    const V3<T> pqm = cross(q0 - p, m - p);
    const double pn = norm(pqm);
    int c = c0;
    for (int i = neh; i < ns; i++) {
      if (i == skip) continue;
      const int j = jump(segs[size_t(i)], q0, m, pqm, pn);
      if (j == kNone) return kNone;
      c += j;
    }
    return c;
  };
  // The contour pieces on a grid of the emitter plane: a piece's crossing candidates are the
  // pieces registered in the cells its box meets, and C at a point is C at its cell's reference
  // point plus the crossings of the path between them with the cell's pieces (not the path from
  // q0 with every piece): the arrangement costs about O(S sqrt S) for S contour pieces instead of
  // O(S^2). A path between two points of one cell, or of two cells sharing a side (their union is
  // a rectangle), stays in those cells and inside E_h (convex), so only pieces registered there
  // (by their boxes, padded far beyond rounding) can cross it. Any decision too close to call, and
  // any point without a usable cell, takes the path from q0 as above.
  const int nsc = ns - neh;
  int G = 0;
  double umin = 0, vmin = 0, du = 0, dv = 0, gpad = 0;
  double O[3] = {0, 0, 0}, U[3] = {0, 0, 0}, Vv[3] = {0, 0, 0};
  auto uv = [&](V3<T> x, double& u, double& v) {
    const double r[3] = {double(x.x) - O[0], double(x.y) - O[1], double(x.z) - O[2]};
    u = r[0] * U[0] + r[1] * U[1] + r[2] * U[2];
    v = r[0] * Vv[0] + r[1] * Vv[1] + r[2] * Vv[2];
  };
  double ehu[130], ehv[130];
  if (nsc >= kSilGridMin) {
    O[0] = double(centre.x), O[1] = double(centre.y), O[2] = double(centre.z);
    const V3<double> ed = normalize_safe(V3<double>{double(eh[0].b.x) - double(eh[0].a.x), double(eh[0].b.y) - double(eh[0].a.y),
                                                    double(eh[0].b.z) - double(eh[0].a.z)});
    const V3<double> vd = normalize_safe(cross(V3<double>{double(ne.x), double(ne.y), double(ne.z)}, ed));
    U[0] = ed.x, U[1] = ed.y, U[2] = ed.z, Vv[0] = vd.x, Vv[1] = vd.y, Vv[2] = vd.z;
    if (nonzero(ed) && nonzero(vd)) {
      double umax = -std::numeric_limits<double>::infinity(), vmax = umax;
      umin = vmin = std::numeric_limits<double>::infinity();
      for (int k = 0; k < neh; k++) {
        uv(eh[k].a, ehu[k], ehv[k]);
        umin = std::min(umin, ehu[k]), umax = std::max(umax, ehu[k]);
        vmin = std::min(vmin, ehv[k]), vmax = std::max(vmax, ehv[k]);
      }
      G = std::max(2, std::min(kSilGridMax, int(std::ceil(std::sqrt(8.0 * nsc)))));
      du = (umax - umin) / G, dv = (vmax - vmin) / G;
      gpad = 1e-9 * (umax - umin + vmax - vmin) + 64 * eps * scale;
      if (!(du > gpad && dv > gpad)) G = 0;
    }
  }
  auto cell_of = [&](double x, double mn, double d) {
    return std::max(0, std::min(G - 1, int(std::floor(std::min(std::max((x - mn) / d, -1.0), double(G))))));
  };
  std::vector<int32_t>& gs = w.gstart;
  std::vector<int32_t>& gi = w.gitems;
  std::vector<int32_t>& stamp_of = w.gstamp;
  int32_t stamp = 0;
  if (G) {
    // Per piece: the cells its padded (u, v) box meets (ix0, ix1, iy0, iy1).
    std::vector<int32_t>& gc = w.gcells;
    gc.resize(size_t(4 * nsc));
    gs.assign(size_t(G * G + 1), 0);
    for (int i = 0; i < nsc; i++) {
      double ua, va, ub, vb;
      uv(segs[size_t(neh + i)].a, ua, va);
      uv(segs[size_t(neh + i)].b, ub, vb);
      int32_t* r = gc.data() + 4 * i;
      r[0] = cell_of(std::min(ua, ub) - gpad, umin, du), r[1] = cell_of(std::max(ua, ub) + gpad, umin, du);
      r[2] = cell_of(std::min(va, vb) - gpad, vmin, dv), r[3] = cell_of(std::max(va, vb) + gpad, vmin, dv);
      for (int iy = r[2]; iy <= r[3]; iy++)
        for (int ix = r[0]; ix <= r[1]; ix++) gs[size_t(iy * G + ix + 1)]++;
    }
    for (int c = 0; c < G * G; c++) gs[size_t(c + 1)] += gs[size_t(c)];
    gi.resize(size_t(gs[size_t(G * G)]));
    std::vector<int32_t>& cur = w.gcand;
    cur.assign(gs.begin(), gs.end() - 1);
    for (int i = 0; i < nsc; i++) {
      const int32_t* r = gc.data() + 4 * i;
      for (int iy = r[2]; iy <= r[3]; iy++)
        for (int ix = r[0]; ix <= r[1]; ix++) gi[size_t(cur[size_t(iy * G + ix)]++)] = neh + i;
    }
    stamp_of.assign(size_t(ns), 0);
    w.gside.assign(gi.size(), int8_t(2));
  }
  // C at m on the `from` side of piece `skip` (-1: none), from C at `from` and the crossings of
  // from -> m with the pieces registered in cells ca and cb (-1: none). `at_ref`: `from` is ca's
  // reference point (its pieces' sides of it are kept in gside, each computed once).
  auto cross_cells = [&](V3<T> from, int cfrom, V3<T> m, int skip, int ca, int cb, bool at_ref = true) -> int {
    const V3<T> pqm = cross(from - p, m - p);
    const double pn = norm(pqm);
    int c = cfrom;
    stamp++;
    for (int cell : {ca, cb}) {
      if (cell < 0) continue;
      const bool cached = at_ref && cell == ca;
      for (int32_t k = gs[size_t(cell)]; k < gs[size_t(cell + 1)]; k++) {
        const int32_t i = gi[size_t(k)];
        if (i == skip || stamp_of[size_t(i)] == stamp) continue;
        stamp_of[size_t(i)] = stamp;
        int sq;
        if (cached) {
          int8_t& g = w.gside[size_t(k)];
          if (g == 2) g = int8_t(side_of(from, segs[size_t(i)]));
          sq = g;
        } else {
          sq = side_of(from, segs[size_t(i)]);
        }
        const int j = jump_from(segs[size_t(i)], sq, m, pqm, pn);
        if (j == kNone) return kNone;
        c += j;
      }
    }
    return c;
  };
  // Reference points in the cells that hold pieces (the only cells queried): the cell's centre
  // when the cell lies inside E_h, else the mean of the vertices of the cell clipped to E_h, kept
  // when it is clear of E_h's edges by a thousandth of a cell. C there from the previous such cell
  // of its row (the cells between hold no piece), else from the row of such cells below: straight
  // up from the cell below when it has a reference, else through a point of that cell reached
  // along its row from the nearest cell holding pieces; else from q0.
  if (G) {
    w.gref.resize(size_t(G * G));
    w.gcov.assign(size_t(G * G), kNone);
    double cside[130];
    for (int k = 0; k < neh; k++) {
      const int k1 = (k + 1) % neh;
      cside[k] = (ehu[k1] - ehu[k]) * (0 - ehv[k]) - (ehv[k1] - ehv[k]) * (0 - ehu[k]) > 0 ? 1.0 : -1.0;
    }
    const double margin = 1e-3 * std::min(du, dv);
    auto inside = [&](double x, double y) {  // clear of every E_h edge by the margin
      for (int k = 0; k < neh; k++) {
        const int k1 = (k + 1) % neh;
        const double ex = ehu[k1] - ehu[k], ey = ehv[k1] - ehv[k];
        if (!(cside[k] * (ex * (y - ehv[k]) - ey * (x - ehu[k])) > margin * std::sqrt(ex * ex + ey * ey))) return false;
      }
      return true;
    };
    auto cell_point = [&](int ix, int iy, V3<T>& r) -> bool {
      double pu[140], pv[140], qu[140], qv[140];
      pu[0] = umin + ix * du, pv[0] = vmin + iy * dv;
      pu[1] = pu[0] + du, pv[1] = pv[0];
      pu[2] = pu[1], pv[2] = pv[0] + dv;
      pu[3] = pu[0], pv[3] = pv[2];
      double ru = pu[0] + 0.5 * du, rv = pv[0] + 0.5 * dv;
      if (!(inside(pu[0], pv[0]) && inside(pu[1], pv[1]) && inside(pu[2], pv[2]) && inside(pu[3], pv[3]))) {
        int np = 4;
        for (int k = 0; k < neh && np >= 3; k++) {  // Sutherland-Hodgman, E_h's side of edge k
          const int k1 = (k + 1) % neh;
          const double ex = ehu[k1] - ehu[k], ey = ehv[k1] - ehv[k];
          auto f = [&](double x, double y) { return cside[k] * (ex * (y - ehv[k]) - ey * (x - ehu[k])); };
          int nq = 0;
          for (int a = 0; a < np && nq < 136; a++) {
            const int b = (a + 1) % np;
            const double fa = f(pu[a], pv[a]), fb = f(pu[b], pv[b]);
            if (fa >= 0) qu[nq] = pu[a], qv[nq] = pv[a], nq++;
            if ((fa >= 0) != (fb >= 0)) {
              const double t = fa / (fa - fb);
              qu[nq] = pu[a] + t * (pu[b] - pu[a]), qv[nq] = pv[a] + t * (pv[b] - pv[a]), nq++;
            }
          }
          np = nq;
          for (int a = 0; a < np; a++) pu[a] = qu[a], pv[a] = qv[a];
        }
        if (np < 3) return false;
        ru = 0, rv = 0;
        for (int a = 0; a < np; a++) ru += pu[a], rv += pv[a];
        ru /= np, rv /= np;
        if (!inside(ru, rv)) return false;
      }
      r = V3<T>{T(O[0] + ru * U[0] + rv * Vv[0]), T(O[1] + ru * U[1] + rv * Vv[1]), T(O[2] + ru * U[2] + rv * Vv[2])};
      return true;
    };
    auto held = [&](int cell) { return gs[size_t(cell + 1)] > gs[size_t(cell)]; };
    int last_row = -1;  // the last row with a cell holding pieces
    for (int iy = 0; iy < G; iy++) {
      int prev = -1;  // the previous cell of this row holding pieces
      for (int ix = 0; ix < G; ix++) {
        const int cell = iy * G + ix;
        if (!held(cell)) continue;
        const int before = prev;
        prev = cell;
        V3<T> r;
        if (!cell_point(ix, iy, r)) continue;
        w.gref[size_t(cell)] = r;
        int c = kNone;
        if (before >= 0) {
          if (w.gcov[size_t(before)] != kNone) c = cross_cells(w.gref[size_t(before)], w.gcov[size_t(before)], r, -1, before, cell);
        } else if (last_row >= 0) {
          const int below = last_row * G + ix;
          if (w.gcov[size_t(below)] != kNone) {
            c = cross_cells(w.gref[size_t(below)], w.gcov[size_t(below)], r, -1, below, cell);
          } else {
            V3<T> sp;
            if (cell_point(ix, last_row, sp)) {
              for (int dir = -1; dir <= 1 && c == kNone; dir += 2) {
                int k = ix + dir;
                while (k >= 0 && k < G && !held(last_row * G + k)) k += dir;
                if (k < 0 || k >= G) continue;
                const int from = last_row * G + k;
                if (w.gcov[size_t(from)] == kNone) continue;
                const int c1 = cross_cells(w.gref[size_t(from)], w.gcov[size_t(from)], sp, -1, from, below);
                if (c1 != kNone) c = cross_cells(sp, c1, r, -1, below, cell, false);
              }
            }
          }
        }
        if (c == kNone) c = coverage(r, -1);
        w.gcov[size_t(cell)] = c;
      }
      if (prev >= 0) last_row = iy;
    }
  }
  // C on q0's side of contour piece `skip` at point m on it: from m's cell where it can.
  auto coverage_at = [&](V3<T> m, int skip) -> int {
    if (G) {
      double um, vm;
      uv(m, um, vm);
      if (um > umin - gpad && um < umin + G * du + gpad && vm > vmin - gpad && vm < vmin + G * dv + gpad) {
        const int cell = cell_of(vm, vmin, dv) * G + cell_of(um, umin, du);
        if (w.gcov[size_t(cell)] != kNone) {
          const SSeg<T>& s = segs[size_t(skip)];
          const V3<T> r = w.gref[size_t(cell)];
          const int rs = side_of(r, s), qs = s.q0s;
          if (rs != 0 && qs != 0) {
            const int c = cross_cells(r, w.gcov[size_t(cell)], m, skip, cell, -1);
            if (c != kNone) return rs == qs ? c : (qs > 0 ? c + s.w : c - s.w);
          }
        }
      }
    }
    return coverage(m, skip);
  };
  // C at a point m of E_h's boundary (inside E_h's side of every contour piece's plane test):
  // from the reference point of m's cell when the cell holds pieces, else of the nearest cell of
  // its row that does (the cells between hold none, and the path lies in E_h, convex, and in the
  // row); the pieces that can cross that path are the ones registered in that cell.
  auto coverage_eh = [&](V3<T> m) -> int {
    if (G) {
      double um, vm;
      uv(m, um, vm);
      if (um > umin - gpad && um < umin + G * du + gpad && vm > vmin - gpad && vm < vmin + G * dv + gpad) {
        const int iy = cell_of(vm, vmin, dv), ix = cell_of(um, umin, du);
        auto holds = [&](int cell) { return gs[size_t(cell + 1)] > gs[size_t(cell)]; };
        int from = -1;
        if (holds(iy * G + ix)) {
          from = iy * G + ix;
        } else {
          int best = G + 1;
          for (int dir = -1; dir <= 1; dir += 2) {
            int k = ix + dir;
            while (k >= 0 && k < G && !holds(iy * G + k)) k += dir;
            if (k < 0 || k >= G || w.gcov[size_t(iy * G + k)] == kNone || std::abs(k - ix) >= best) continue;
            best = std::abs(k - ix);
            from = iy * G + k;
          }
        }
        if (from >= 0 && w.gcov[size_t(from)] != kNone) {
          const int c = cross_cells(w.gref[size_t(from)], w.gcov[size_t(from)], m, -1, from, -1);
          if (c != kNone) return c;
        }
      }
    }
    return coverage(m, -1);
  };
  // Pieces: every segment cut where another crosses it.
  w.runs.clear();
  bool eh_all = true, eh_any = false;
  std::vector<T>& ts = w.sts;
  std::vector<Code>& tc = w.stc;
  std::vector<int32_t>& td = w.std_;  // per breakpoint: the change of C crossing it along s
  // The segments' boxes in the emitter plane (crossing tests only between overlapping boxes).
  std::vector<T>& bx = w.sbox;
  bx.resize(size_t(6 * ns));
  for (int i = 0; i < ns; i++) {
    const T ca[3] = {segs[i].a.x, segs[i].a.y, segs[i].a.z}, cb[3] = {segs[i].b.x, segs[i].b.y, segs[i].b.z};
    for (int k = 0; k < 3; k++) {
      bx[6 * i + k] = std::min(ca[k], cb[k]) - T(1e-9) * T(scale);
      bx[6 * i + 3 + k] = std::max(ca[k], cb[k]) + T(1e-9) * T(scale);
    }
  }
  bool contour_runs = false;
  for (int i = 0; i < ns; i++) {
    const SSeg<T>& s = segs[size_t(i)];
    const size_t runs_before = w.runs.size();
    ts.clear();
    tc.clear();
    td.clear();
    ts.push_back(0), tc.push_back(s.ca), td.push_back(0);
    ts.push_back(1), tc.push_back(s.cb), td.push_back(0);
    const V3<T> ap = s.a - p, d = s.b - s.a;
    const double apn = std::fabs(ap.x) + std::fabs(ap.y) + std::fabs(ap.z) + std::fabs(d.x) + std::fabs(d.y) + std::fabs(d.z);
    // Crossing candidates: every segment, or for a contour piece on the grid the pieces
    // registered in the cells its box meets (in index order, as the full loop visits them).
    const bool listed = G && i >= neh;
    if (listed) {
      std::vector<int32_t>& cand = w.gcand;
      cand.clear();
      stamp++;
      const int32_t* r = w.gcells.data() + 4 * (i - neh);
      for (int iy = r[2]; iy <= r[3]; iy++)
        for (int ix = r[0]; ix <= r[1]; ix++)
          for (int32_t k = gs[size_t(iy * G + ix)]; k < gs[size_t(iy * G + ix + 1)]; k++) {
            const int32_t j = gi[size_t(k)];
            if (j != i && stamp_of[size_t(j)] != stamp) stamp_of[size_t(j)] = stamp, cand.push_back(j);
          }
      std::sort(cand.begin(), cand.end());
    }
    const int nj = listed ? int(w.gcand.size()) : ns;
    for (int jj = 0; jj < nj; jj++) {
      const int j = listed ? w.gcand[size_t(jj)] : jj;
      if (j == i) continue;
      const SSeg<T>& o = segs[size_t(j)];
      if (i < neh && j < neh) continue;  // E_h's edges meet at its vertices only
      if (i >= neh && j >= neh) {  // boxes apart: no crossing (tested first: the cheaper filter)
        const T* bi = bx.data() + 6 * i;
        const T* bj = bx.data() + 6 * j;
        if (bi[3] < bj[0] || bj[3] < bi[0] || bi[4] < bj[1] || bj[4] < bi[1] || bi[5] < bj[2] || bj[5] < bi[2]) continue;
      }
      if (s.va >= 0 && o.va >= 0 &&
          (same(s.x3a, o.x3a) || same(s.x3a, o.x3b) || same(s.x3b, o.x3a) || same(s.x3b, o.x3b)))
        continue;  // mesh edges with a common end meet there only
      if (i < neh) {
        // An E_h edge: cut where a contour piece was clipped at its plane.
        const int pi = eh_plane[i];
        const bool at_a = o.on_a >= 0 && o.on_a == pi;
        const bool at_b = o.on_b >= 0 && o.on_b == pi;
        if (!at_a && !at_b) continue;
        const double g0 = dot(ap, o.own), g1 = dot(d, o.own);
        if (!(std::fabs(g1) > tol * o.own_n * apn)) return kFallback;
        const double t = -g0 / g1;
        if (!(t >= -1e-9 && t <= 1 + 1e-9)) return kFallback;
        ts.push_back(std::min(1.0, std::max(0.0, t)));
        tc.push_back(at_a ? o.ca : o.cb);
        td.push_back(g1 > 0 ? o.w : -o.w);
        continue;
      }
      if (j < neh) continue;  // a contour piece ends on E_h's boundary, inside it otherwise
      const double on = o.own_n * apn;
      const double g0 = dot(ap, o.own), g1 = dot(d, o.own);
      const int s0 = sgn(g0, tol * on), s1 = sgn(g0 + g1, tol * on);
      if (s0 == s1 && s0 != 0) continue;
      if (s0 == 0 && s1 == 0) {
        // s along o's line (collinear contour edges, as on a straight crease): apart when o's
        // ends lie clearly beyond one end of s along it.
        const double dd = double(dot(d, d));
        const double ta = double(dot(o.a - s.a, d)) / dd, tb = double(dot(o.b - s.a, d)) / dd;
        if ((ta < -1e-6 && tb < -1e-6) || (ta > 1 + 1e-6 && tb > 1 + 1e-6)) continue;
        return kFallback;
      }
      const int ca = side_of(o.a, s), cb = side_of(o.b, s);
      if (ca == cb && ca != 0) continue;  // o on one side of s's line (s's end on o's line or not)
      if (s0 == 0 || s1 == 0) return kFallback;
      if (ca == 0 || cb == 0) return kFallback;
      ts.push_back(-g0 / g1);
      tc.push_back(code_planes(s.own_ref, o.own_ref));
      td.push_back(s1 > 0 ? o.w : -o.w);  // into o's positive side: + W
    }
    const int nt = int(ts.size());
    std::vector<int32_t>& ord = w.sord;
    ord.resize(size_t(nt));
    for (int k = 0; k < nt; k++) ord[size_t(k)] = k;
    std::sort(ord.begin(), ord.end(), [&](int32_t x, int32_t y) { return ts[size_t(x)] < ts[size_t(y)]; });
    // Classify the pieces; a kept piece extends the current run.
    int run_dir = 0;  // +1: a run along s, -1: against it, 0: none open
    Code run_s{}, run_e{};
    auto close_run = [&]() {
      if (run_dir > 0) w.runs.push_back(Run{run_s, run_e});
      if (run_dir < 0) w.runs.push_back(Run{run_e, run_s});
      run_dir = 0;
    };
    // C beside s on q0's side (inside E_h for E_h's edges): computed at the first piece, then
    // carried across the breakpoints, and checked again at the last piece.
    int c = kNone, last = -1;
    for (int k = 0; k + 1 < nt; k++)
      if (ts[size_t(ord[k + 1])] > ts[size_t(ord[k])]) last = k;
    for (int k = 0; k + 1 < nt; k++) {
      if (k > 0 && c != kNone) c += td[size_t(ord[k])];
      const double ta = ts[size_t(ord[k])], tb = ts[size_t(ord[k + 1])];
      if (!(tb > ta)) continue;
      const V3<T> m = s.a + (0.5 * (ta + tb)) * d;
      if (c == kNone || k == last) {
        const int full = i < neh ? coverage_eh(m) : coverage_at(m, i);
        if (full == kNone || (c != kNone && full != c)) return kFallback;
        c = full;
      }
      int dir = 0;
      if (i < neh) {
        if (c < 0) return kFallback;
        eh_any = eh_any || c == 0;
        eh_all = eh_all && c == 0;
        dir = c == 0 ? 1 : 0;
      } else {
        const int q0side = s.q0s;
        if (q0side == 0) return kFallback;
        const int cpos = q0side > 0 ? c : c + s.w, cneg = q0side > 0 ? c - s.w : c;
        if (cpos < 0 || cneg < 0) return kFallback;
        if ((cpos == 0) != (cneg == 0)) dir = cpos == 0 ? 1 : -1;  // R on the positive side: along own's edge
      }
      if (dir != run_dir) {
        close_run();
        if (dir != 0) {
          run_dir = dir;
          run_s = tc[size_t(ord[k])];
        }
      }
      if (dir != 0) run_e = tc[size_t(ord[k + 1])];
    }
    close_run();
    if (i >= neh && w.runs.size() > runs_before) contour_runs = true;
  }
  if (!contour_runs) {
    if (eh_all) return kLit;
    if (!eh_any) {
      w.runs.clear();
      return kUmbra;
    }
    return kFallback;  // parts of E_h's boundary visible but no contour bounds them
  }
  return kPenumbra;
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_SILHOUETTE_H_
