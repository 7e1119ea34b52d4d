// jaxshadow's shadow engine: the visible pieces of a segment light (part of `csrc/shadowc.cc`; see
// its header comment).
//
// Seen from a receiver p, the part of the segment light a -> b that a convex face hides is one
// interval of the parameter t of x(t) = a + t (b - a) (Poulin §4.2: the face cuts the light
// triangle (p, a, b) in a convex set): x(t) inside the cone of the face's edge planes through p,
// and beyond the face's plane. Each bound of that interval is the crossing of the segment with one
// plane: a plane through p and a face edge, or the face's own plane (a face the segment passes
// through). The hidden part of the segment is the union of the intervals of the faces that meet
// the light triangle (`segment_candidates`); its complement in [0, 1], the visible pieces, is
// bounded by the segment's ends and by crossings with planes through p and *contour* edges of the
// meshes: where two faces of a mesh share an edge and both hide the rays on either side of it,
// their intervals meet at that edge's crossing, computed from the same plane (`edge_plane` is
// bit-identical for the two faces, whichever way the edge runs), and the union closes over it.
// So a receiver's output is the list of visible pieces, each two endpoint codes, whatever the
// number of faces in its light triangle; the device computes each endpoint's t from the code (the
// same plane, differentiably) and integrates the segment's kernel over the pieces. The host work
// can follow the contour too (`segment_pieces_contour`, below): the same pieces from the faces of
// contour edges, the faces the segment passes through, and rays to the middles of the runs between
// their intervals. It is taken for occluder sets of kSegmentContourMinFaces faces or more (where
// it measured faster than visiting the light triangle's faces on every mesh tried);
// `JAXSHADOW_SEGMENT_WALK=1` takes it at any size, `=0` never.
//
// The per-face interval is `_clip.blocked_intervals` test for test, in double (float32 inputs are
// exact in double): the face's side from `face_side` (the on-surface rule included; a face p lies
// in blocks nothing), the oriented edge planes s * edge_plane, an edge plane that is zero (a
// repeated vertex, an edge through p) ignored, and one parallel to the segment (d . plane = 0)
// hiding all or nothing by the sign of (a - p) . plane; then the interval clipped to [0, 1].
// Ties are decided as the device kernel decides them: intervals that touch (the end of one equal
// to the start of the next) leave no visible piece between them, and an interval clipped to zero
// length hides nothing.
//
// Endpoint codes (int32): kSegStart (t = 0), kSegEnd (t = 1), or f * (Ko + 1) + i: the plane
// through p and edge i -> i + 1 of face f (i < Ko), or face f's own plane (i = Ko).
#ifndef JAXSHADOW_SHADOWC_SILHOUETTE_SEGMENT_H_
#define JAXSHADOW_SHADOWC_SILHOUETTE_SEGMENT_H_

#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <memory>
#include <vector>

#include "driver.h"

namespace jaxshadow_engine {

constexpr int32_t kSegStart = -1;
constexpr int32_t kSegEnd = -2;

// One face's hidden interval [lo, hi] of t and the codes of the planes that bound it.
struct SegmentBlock {
  double lo, hi;
  int32_t clo, chi;
};

// The union's order of the intervals: by start, then the longer first, then by codes (a total
// order, so that the pieces' codes do not depend on the order the faces were found in).
inline bool block_before(const SegmentBlock& x, const SegmentBlock& y) {
  if (x.lo != y.lo) return x.lo < y.lo;
  if (x.hi != y.hi) return x.hi > y.hi;
  if (x.clo != y.clo) return x.clo < y.clo;
  return x.chi < y.chi;
}

// A receiver's scratch and result: its candidate faces, their intervals and the visible pieces
// (pairs of endpoint codes, in order along the segment); the contour path's scratch.
struct SegmentWork {
  std::vector<int32_t> faces;
  std::vector<std::pair<int32_t, int32_t>> cand;
  std::vector<SegmentBlock> blocks;
  std::vector<int32_t> pieces;  // 2 codes per piece
  std::vector<double> cuts;     // the contour path's interval ends along t
  std::vector<int32_t> cover;
  std::vector<int32_t> stack;
  int64_t examined = 0;  // faces whose interval the contour path computed
};

// The interval of t that face f hides on a -> b (d = b - a) seen from p, clipped to [0, 1];
// false when it hides nothing there.
template <class T>
bool segment_block(const Occluders<T>& occ, int64_t f, V3<T> p, V3<T> a, V3<T> d, SegmentBlock& out) {
  const int64_t Ko = occ.Ko;
  if (Ko > 64) return false;
  V3<T> rel[64];
  const FaceSide<T> fs = face_side(occ, f, p, rel);
  if (fs.side == 0) return false;  // p in the face's plane: it blocks a zero solid angle
  const T s = T(fs.side);
  const int32_t base = int32_t(f * (Ko + 1));
  double lo = -std::numeric_limits<double>::infinity(), hi = std::numeric_limits<double>::infinity();
  int32_t clo = kSegStart, chi = kSegEnd;
  const V3<T> ap = a - p;
  for (int64_t i = 0; i < Ko; i++) {
    const V3<T> u = occ.vert(f, i), v = occ.vert(f, (i + 1) % Ko);
    if (same(u, v)) continue;
    const V3<T> pl = s * edge_plane(p, u, v);
    if (!nonzero(pl)) continue;
    const T g0 = dot(ap, pl), g1 = dot(d, pl);
    if (g1 > 0) {
      const double t = double(-g0 / g1);
      if (t > lo) lo = t, clo = base + int32_t(i);
    } else if (g1 < 0) {
      const double t = double(-g0 / g1);
      if (t < hi) hi = t, chi = base + int32_t(i);
    } else if (g0 < 0) {
      return false;
    }
  }
  // x(t) strictly beyond the face's plane seen from p: -s no . (x(t) - o_0) > 0.
  const T h0 = -s * dot(fs.no, a - occ.vert(f, 0)), h1 = -s * dot(fs.no, d);
  if (h1 > 0) {
    const double t = double(-h0 / h1);
    if (t > lo) lo = t, clo = base + int32_t(Ko);
  } else if (h1 < 0) {
    const double t = double(-h0 / h1);
    if (t < hi) hi = t, chi = base + int32_t(Ko);
  } else if (!(h0 > 0)) {
    return false;
  }
  if (!(lo > 0)) lo = 0, clo = kSegStart;
  if (!(hi < 1)) hi = 1, chi = kSegEnd;
  if (!(lo < hi)) return false;
  out = SegmentBlock{lo, hi, clo, chi};
  return true;
}

// The visible pieces of a -> b seen from p (`w.pieces`, two codes each) and the receiver's class:
// 1 (LIT: nothing hidden, no piece listed), 2 (UMBRA: all hidden) or 3 (PENUMBRA).
template <class T>
int32_t segment_pieces(const Occluders<T>& occ, const BVH& bvh, V3<T> p, V3<T> a, V3<T> b, SegmentWork& w) {
  w.pieces.clear();
  w.blocks.clear();
  segment_candidates(occ, bvh, p, a, b, w.faces, w.cand);
  const V3<T> d = b - a;
  for (int32_t f : w.faces) {
    SegmentBlock blk;
    if (segment_block(occ, f, p, a, d, blk)) w.blocks.push_back(blk);
  }
  if (w.blocks.empty()) return 1;
  std::sort(w.blocks.begin(), w.blocks.end(), block_before);
  double cur = 0;
  int32_t ccur = kSegStart;
  for (const SegmentBlock& blk : w.blocks) {
    if (blk.lo > cur) {
      w.pieces.push_back(ccur);
      w.pieces.push_back(blk.clo);
    }
    if (blk.hi > cur) cur = blk.hi, ccur = blk.chi;
  }
  if (cur < 1) {
    w.pieces.push_back(ccur);
    w.pieces.push_back(kSegEnd);
  }
  return w.pieces.empty() ? 2 : 3;
}

// ----------------------------------------------------------------------------------------------
// The contour path: the same pieces from the faces of contour edges and pierced faces
// ----------------------------------------------------------------------------------------------
//
// A piece's end is the end of a face's interval that no other interval continues: the crossing
// with the plane through p and a contour edge of the meshes (both faces on one side of that
// plane, sil_side's W != 0: at an edge whose faces lie on either side, the two intervals meet at
// the bit-identical crossing and the union closes over it), or the face's own plane where the
// segment passes through the face. So the pieces are found from (1) the faces of the contour
// edges that meet the light triangle (the silhouette hierarchy walked with the triangle's
// half-spaces, nodes whose faces all face p one way left out: `node_side`), (2) the faces the
// segment meets (the face hierarchy along a -> b), each kept when `segment_candidates` would list
// it (the same box, triangle-plane and back-face tests); their intervals cut [0, 1] into runs,
// and a run that none of them covers is hidden or visible as a ray from p to its middle finds
// (the face hierarchy along that ray: an interval of a face it meets holding the middle). The
// ends of the visible runs take the codes the face path's union would give them (`block_before`
// among the intervals that end or start there).
//
// The walk decides every face it reads by sil_side, whose margin is above near_face_plane's: so
// no listed face of a closed mesh has p in its plane (the face path would then keep the mesh's
// back faces). Any decision too close to call (a face side 0, an end of a visible run that no
// interval of (1)-(2) bounds, a face met by a middle's ray whose interval ends inside the run)
// returns kFallback: the receiver takes the face path, as does a receiver whose light triangle's
// plane holds an occluder vertex (`plane_holds_vertex`: there an edge may lie in the plane, or
// the faces around the vertex leave slivers between their intervals, which no contour edge
// bounds). Scenes with convex solids (their faces are listed as a whole) take the face path.

// The silhouette hierarchy of a call's occluders (its local face f is occluder face st->fglob[f]);
// `st` null: every receiver takes the face path.
// `ang`: the occluders' vertices' angles about the segment's line (mod pi, sorted; the frame
// e1, e2 across it), so that a receiver whose light triangle's plane holds a vertex, where the
// faces around it may leave slivers between their intervals or hide along an edge in that plane,
// is found in log time and takes the face path.
struct SegmentContour {
  const SilhouetteTree* st = nullptr;
  std::vector<double> ang;
  double a[3], e1[3], e2[3], rmin;
  // The hierarchy's edge flags, prepared once per occluder set (`Prepared::segment`): an edge
  // whose faces do not share it (a T-junction's pair) bounds pieces as a contour edge does, and a
  // node above one is not left out by node_side (which proves only that no edge below is a
  // contour edge).
  const SegmentParts* seg = nullptr;
};

// The angle mod pi in [0, pi) of x - a in the frame (e1, e2), and the distance r from the line.
inline double line_angle(const SegmentContour& sc, const double* x, double& r) {
  const double y[3] = {x[0] - sc.a[0], x[1] - sc.a[1], x[2] - sc.a[2]};
  const double u = y[0] * sc.e1[0] + y[1] * sc.e1[1] + y[2] * sc.e1[2];
  const double v = y[0] * sc.e2[0] + y[1] * sc.e2[1] + y[2] * sc.e2[2];
  r = std::sqrt(u * u + v * v);
  double t = std::atan2(v, u);
  if (t < 0) t += M_PI;
  if (t >= M_PI) t -= M_PI;
  return t;
}

constexpr double kSegmentPlaneAngle = 1e-9;  // a vertex this near the light triangle's plane (rad)

// Whether a vertex of the occluders lies within kSegmentPlaneAngle of the plane through the
// segment's line and p (or p is too near the line to tell).
inline bool plane_holds_vertex(const SegmentContour& sc, const double* p) {
  double r;
  const double t = line_angle(sc, p, r);
  if (!(r > sc.rmin)) return true;
  const std::vector<double>& g = sc.ang;
  if (g.empty()) return false;
  const size_t k = size_t(std::lower_bound(g.begin(), g.end(), t) - g.begin());
  auto near = [&](double x) {
    const double dx = std::fabs(x - t);
    return std::min(dx, M_PI - dx) < kSegmentPlaneAngle;
  };
  return near(g[k % g.size()]) || near(g[(k + g.size() - 1) % g.size()]);
}

// Occluder faces from which the contour path is taken by default. Engine call, 5e4 floor
// receivers under a 0.8 m segment, contour path against face visit (CPU time): 1.15x to 2.2x
// faster on meshes of 20k to 270k faces (rocker-arm, bunny, nefertiti, igea), 0.5x to 1.4x on
// those of 2k to 13k (beetle 0.51x, homer 0.79x, cow 0.98x, fandisk 1.38x).
constexpr int64_t kSegmentContourMinFaces = 16384;

// The contour path for `occ` unless the occluders have convex solids, fewer faces than the
// silhouette path serves, or faces of over 64 vertices; JAXSHADOW_SEGMENT_WALK (read per call)
// =1 takes it at any size, =0 never, else from kSegmentContourMinFaces faces.
// A vertex nearer the segment's line than 1e-6 of the scene's scale lies in every receiver's
// plane (or its angle is not known to kSegmentPlaneAngle): every receiver takes the face path.
template <class T>
SegmentContour segment_contour(const Occluders<T>& occ, const Prepared& prep, V3<T> a, V3<T> b) {
  SegmentContour sc;
  const char* env = std::getenv("JAXSHADOW_SEGMENT_WALK");
  const bool forced = env && env[0] == '1', off = env && env[0] == '0';
  if (off || (!forced && occ.M < kSegmentContourMinFaces)) return sc;
  if (occ.S > 0 || occ.M < kSilhouetteMinFaces || occ.Ko > 64) return sc;
  const PolygonParts& parts = prep.polygon(occ);
  const SilhouetteTree& st = parts.sil;
  if (!st.ok || st.floc.size() != size_t(occ.M)) return sc;
  const double ad[3] = {double(a.x), double(a.y), double(a.z)};
  double d[3] = {double(b.x) - ad[0], double(b.y) - ad[1], double(b.z) - ad[2]};
  const double dn = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
  if (!(dn > 0) || !std::isfinite(dn)) return sc;
  for (int k = 0; k < 3; k++) d[k] /= dn, sc.a[k] = ad[k];
  // e1: the unit vector across d from the axis d is least along; e2 = d x e1.
  const int m = std::fabs(d[0]) <= std::fabs(d[1]) && std::fabs(d[0]) <= std::fabs(d[2]) ? 0 : (std::fabs(d[1]) <= std::fabs(d[2]) ? 1 : 2);
  double e[3] = {0, 0, 0};
  e[m] = 1;
  const double de = d[m];
  for (int k = 0; k < 3; k++) e[k] -= de * d[k];
  const double en = std::sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2]);
  for (int k = 0; k < 3; k++) sc.e1[k] = e[k] / en;
  sc.e2[0] = d[1] * sc.e1[2] - d[2] * sc.e1[1];
  sc.e2[1] = d[2] * sc.e1[0] - d[0] * sc.e1[2];
  sc.e2[2] = d[0] * sc.e1[1] - d[1] * sc.e1[0];
  const double scale = std::max(st.scale, std::max(double(absmax(a)), double(absmax(b))));
  sc.rmin = 1e-6 * scale;
  sc.ang.reserve(parts.verts.size());
  for (const int64_t k : parts.verts) {
    const V3<T> x = ld(occ.faces + 3 * k);
    const double xd[3] = {double(x.x), double(x.y), double(x.z)};
    double r;
    const double t = line_angle(sc, xd, r);
    if (!(r > sc.rmin)) return SegmentContour();
    sc.ang.push_back(t);
  }
  std::sort(sc.ang.begin(), sc.ang.end());
  sc.seg = &prep.segment(occ);
  sc.st = &st;
  return sc;
}

// Whether the segment x0 + s (x1 - x0), s in [0, 1], meets the box grown by `pad`.
inline bool segment_meets_box(const double* box, const double* x0, const double* dx, double pad) {
  double s0 = 0, s1 = 1;
  for (int d = 0; d < 3; d++) {
    const double lo = box[d] - pad, hi = box[3 + d] + pad;
    if (dx[d] == 0) {
      if (!(x0[d] >= lo && x0[d] <= hi)) return false;
      continue;
    }
    double ta = (lo - x0[d]) / dx[d], tb = (hi - x0[d]) / dx[d];
    if (ta > tb) std::swap(ta, tb);
    s0 = std::max(s0, ta);
    s1 = std::min(s1, tb);
    if (!(s0 <= s1)) return false;
  }
  return true;
}

// `visit(face)` for each face of the hierarchy (no solids) whose box, grown by `pad`, meets the
// segment x0 -> x1; `visit` returns false to stop. False: the stack overflowed.
template <class F>
bool faces_along(const BVH& bvh, const double* x0, const double* x1, double pad, std::vector<int32_t>& stack, F visit) {
  if (bvh.nodes.empty()) return true;
  const double dx[3] = {x1[0] - x0[0], x1[1] - x0[1], x1[2] - x0[2]};
  stack.clear();
  stack.push_back(0);
  while (!stack.empty()) {
    const Node& nd = bvh.nodes[size_t(stack.back())];
    stack.pop_back();
    if (!segment_meets_box(nd.box, x0, dx, pad)) continue;
    if (nd.left >= 0) {
      stack.push_back(nd.left);
      stack.push_back(nd.right);
      continue;
    }
    for (int32_t i = nd.start; i < nd.start + nd.count; i++) {
      if (!segment_meets_box(bvh.ibox.data() + 6 * size_t(i), x0, dx, pad)) continue;
      if (bvh.items[size_t(i)] >= 0 && !visit(bvh.items[size_t(i)])) return true;
    }
  }
  return true;
}

// The visible pieces of a -> b seen from p by the contour path (above): as segment_pieces, or
// kFallback.
template <class T>
int32_t segment_pieces_contour(const Occluders<T>& occ, const BVH& bvh, const SegmentContour& sc, V3<T> p, V3<T> a,
                               V3<T> b, SegmentWork& w) {
  const SilhouetteTree& st = *sc.st;
  const uint8_t* shared = sc.seg->shared.data();
  const uint8_t* unshared = sc.seg->unshared.data();
  w.pieces.clear();
  w.blocks.clear();
  w.faces.clear();
  w.examined = 0;
  const V3<T> nt = cross(a - p, b - p);
  if (!nonzero(nt)) return kFallback;
  const double pd[3] = {double(p.x), double(p.y), double(p.z)};
  if (plane_holds_vertex(sc, pd)) return kFallback;
  const T tol = T(kCollinearEps) * eps_of<T>();
  HalfSpace hs[5];
  const int nh = segment_triangle_planes(p, a, b, hs);
  const double cmargin = segment_box_margin(p, a, b);
  BoxPlane cand[5], walk[5];
  prepare_planes(hs, nh, cmargin, cand);
  prepare_planes(hs, nh, 4 * cmargin, walk);  // a node outside these holds no listed face
  const double scale = std::max(st.scale, std::max(double(absmax(p)), std::max(double(absmax(a)), double(absmax(b))))) + 1e-300;
  const double smargin = 4 * kOnSurface * scale;
  // segment_candidates' tests of face f (no solids: each face is an item of the hierarchy).
  auto listed = [&](int32_t f) {
    double box[6];
    for (int d = 0; d < 3; d++) box[d] = std::numeric_limits<double>::infinity(), box[3 + d] = -box[d];
    for (int64_t i = 0; i < occ.Ko; i++) {
      const T* v = occ.faces + 3 * (f * occ.Ko + i);
      for (int d = 0; d < 3; d++) box[d] = std::min(box[d], double(v[d])), box[3 + d] = std::max(box[3 + d], double(v[d]));
    }
    for (int k = 0; k < nh; k++)
      if (outside6(box, cand[k])) return false;
    if (off_triangle_plane(occ, f, p, nt, tol)) return false;
    const int32_t mesh = occ.face_closed ? occ.face_closed[f] : -1;
    return !(mesh >= 0 && bvh.outside_mesh(mesh, pd) && behind_face(occ, f, p, tol));
  };
  // (1) The faces of the contour edges in the leaves the walk reaches.
  std::vector<int32_t>& stack = w.stack;
  stack.clear();
  stack.push_back(0);
  while (!stack.empty()) {
    const int32_t stack_node = stack.back();
    const SNode& nd = st.nodes[size_t(stack_node)];
    stack.pop_back();
    bool out = false;
    for (int k = 0; k < nh && !out; k++) out = outside6(nd.box, walk[k]);
    if (out) continue;
    if (!nd.special && !unshared[size_t(stack_node)] && node_side(nd, pd, smargin) != 0) continue;
    if (nd.left >= 0) {
      stack.push_back(nd.left);
      stack.push_back(nd.right);
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
      // Faces on either side of the edge's plane meet at its crossing, bit for bit where both
      // have it as an edge (edge_plane of the same two positions); a T-junction's pair is
      // treated as a contour edge.
      if (W == 0 && shared[size_t(k)]) continue;
      w.faces.push_back(st.fglob[size_t(e.f)]);
      if (e.g >= 0) w.faces.push_back(st.fglob[size_t(e.g)]);
    }
  }
  // (2) The faces the segment meets (their planes may bound an interval).
  const double pad = 1e-9 * scale;
  const double ad[3] = {double(a.x), double(a.y), double(a.z)}, bd[3] = {double(b.x), double(b.y), double(b.z)};
  faces_along(bvh, ad, bd, pad, stack, [&](int32_t f) {
    w.faces.push_back(f);
    return true;
  });
  std::sort(w.faces.begin(), w.faces.end());
  w.faces.erase(std::unique(w.faces.begin(), w.faces.end()), w.faces.end());
  const V3<T> d = b - a;
  for (int32_t f : w.faces) {
    if (!listed(f)) continue;
    w.examined++;
    SegmentBlock blk;
    if (segment_block(occ, f, p, a, d, blk)) w.blocks.push_back(blk);
  }
  // The runs between consecutive interval ends, and which the intervals cover.
  std::vector<double>& cuts = w.cuts;
  cuts.assign({0.0, 1.0});
  for (const SegmentBlock& blk : w.blocks) cuts.push_back(blk.lo), cuts.push_back(blk.hi);
  std::sort(cuts.begin(), cuts.end());
  cuts.erase(std::unique(cuts.begin(), cuts.end()), cuts.end());
  const size_t nr = cuts.size() - 1;
  std::vector<int32_t>& cover = w.cover;
  cover.assign(nr + 1, 0);
  for (const SegmentBlock& blk : w.blocks) {
    const size_t i0 = size_t(std::lower_bound(cuts.begin(), cuts.end(), blk.lo) - cuts.begin());
    const size_t i1 = size_t(std::lower_bound(cuts.begin(), cuts.end(), blk.hi) - cuts.begin());
    cover[i0]++, cover[i1]--;
  }
  for (size_t i = 1; i <= nr; i++) cover[i] += cover[i - 1];
  // Runs no interval covers: hidden when a face met by the ray from p to the run's middle hides
  // part of it (the faces without a contour edge in the triangle cover a run whole or not at
  // all: where their intervals end, the neighbour's across the edge starts).
  for (size_t i = 0; i < nr; i++) {
    if (cover[i] > 0) continue;
    const double u = cuts[i], v = cuts[i + 1], tm = 0.5 * (u + v);
    const double xm[3] = {double(a.x) + tm * double(d.x), double(a.y) + tm * double(d.y), double(a.z) + tm * double(d.z)};
    bool hidden = false;
    faces_along(bvh, pd, xm, pad, stack, [&](int32_t f) {
      if (std::binary_search(w.faces.begin(), w.faces.end(), f) || !listed(f)) return true;
      w.examined++;
      SegmentBlock blk;
      if (!segment_block(occ, f, p, a, d, blk) || !(blk.lo < v && blk.hi > u)) return true;
      hidden = true;
      return false;
    });
    if (hidden) cover[i] = 1;
  }
  // The visible runs' ends, coded as the union of the face path codes them.
  // The code of a run's end at s: the segment's end there, else that of the first (block_before)
  // of the intervals ending at s (a run's start: hi == s, its chi) or starting there (a run's end:
  // lo == s, its clo); false where no interval bounds the run.
  auto run_code = [&](double s, bool start, int32_t& code) {
    if (s == (start ? 0.0 : 1.0)) return code = start ? kSegStart : kSegEnd, true;
    const SegmentBlock* best = nullptr;
    for (const SegmentBlock& blk : w.blocks)
      if ((start ? blk.hi : blk.lo) == s && (!best || block_before(blk, *best))) best = &blk;
    if (!best) return false;
    code = start ? best->chi : best->clo;
    return true;
  };
  for (size_t i = 0; i < nr;) {
    if (cover[i] > 0) {
      i++;
      continue;
    }
    size_t j = i;
    while (j + 1 < nr && cover[j + 1] == 0) j++;
    int32_t c0, c1;
    if (!run_code(cuts[i], true, c0) || !run_code(cuts[j + 1], false, c1)) return kFallback;
    w.pieces.push_back(c0);
    w.pieces.push_back(c1);
    i = j + 1;
  }
  if (w.pieces.size() == 2 && w.pieces[0] == kSegStart && w.pieces[1] == kSegEnd) {
    if (!w.blocks.empty()) return kFallback;  // the face path's blocks would cover part
    w.pieces.clear();
    return 1;
  }
  if (w.blocks.empty() && !w.pieces.empty()) return kFallback;
  return w.pieces.empty() ? 2 : 3;
}

// A receiver's pieces: the contour path where it serves, else the face path. `kept`: the faces
// whose interval was computed (the face path: its candidates).
template <class T>
int32_t segment_pieces_any(const Occluders<T>& occ, const BVH& bvh, const SegmentContour& sc, V3<T> p, V3<T> a, V3<T> b,
                           SegmentWork& w, int32_t& kept) {
  if (sc.st) {
    const int32_t c = segment_pieces_contour(occ, bvh, sc, p, a, b, w);
    if (c != kFallback) {
      kept = int32_t(w.examined);
      return c;
    }
  }
  const int32_t c = segment_pieces(occ, bvh, p, a, b, w);
  kept = int32_t(w.faces.size());
  return c;
}

// Host plan: classes (N,), faces whose interval was computed per receiver (N,), offsets (N + 1,) into the pieces
// (R, 2) int32 (`*pieces_out`, malloc'ed; the caller frees it). Returns 0, or 2 out of memory.
template <class T>
int segment_pieces_plan(int64_t N, const T* P, const T* A, const T* B, const Occluders<T>& occ, int threads,
                        int32_t* cls, int32_t* kept, int64_t* offsets, int32_t** pieces_out) {
  const std::shared_ptr<const Prepared> prep = prepared(occ);  // the cached hierarchy
  const BVH& bvh = prep->bvh;
  const SegmentContour sc = segment_contour(occ, *prep, ld(A), ld(B));
  const V3<T> a = ld(A), b = ld(B);
  std::vector<std::vector<int32_t>> lists(size_t(std::max<int64_t>(N, 0)));
  parallel_for(N, default_threads(threads), [&](int, int64_t s, int64_t e) {
    SegmentWork w;
    for (int64_t i = s; i < e; i++) {
      cls[i] = segment_pieces_any(occ, bvh, sc, ld(P + 3 * i), a, b, w, kept[i]);
      lists[size_t(i)] = w.pieces;
    }
  });
  offsets[0] = 0;
  for (int64_t i = 0; i < N; i++) offsets[i + 1] = offsets[i] + int64_t(lists[size_t(i)].size() / 2);
  int32_t* out = static_cast<int32_t*>(std::malloc(sizeof(int32_t) * size_t(std::max<int64_t>(2 * offsets[N], 1))));
  if (!out) return 2;
  for (int64_t i = 0; i < N; i++)
    if (!lists[size_t(i)].empty())
      std::memcpy(out + 2 * offsets[i], lists[size_t(i)].data(), sizeof(int32_t) * lists[size_t(i)].size());
  *pieces_out = out;
  return 0;
}

// Fixed capacity (the FFI handler's layout): classes (N,), counts (N,) (pieces of a penumbra
// receiver, 0 for the others), pieces (N, cap, 2) with unused slots (kSegStart, kSegStart).
template <class T>
void segment_pieces_fixed(int64_t N, const T* P, const T* A, const T* B, const Occluders<T>& occ, const Prepared& prep,
                          int threads, int64_t cap, int32_t* cls, int32_t* counts, int32_t* pieces) {
  const V3<T> a = ld(A), b = ld(B);
  const SegmentContour sc = segment_contour(occ, prep, a, b);
  parallel_for(N, default_threads(threads), [&](int, int64_t s, int64_t e) {
    SegmentWork w;
    int32_t kept = 0;
    for (int64_t i = s; i < e; i++) {
      cls[i] = segment_pieces_any(occ, prep.bvh, sc, ld(P + 3 * i), a, b, w, kept);
      const int64_t n = int64_t(w.pieces.size() / 2);
      counts[i] = int32_t(n);
      int32_t* out = pieces + i * cap * 2;
      for (int64_t k = 0; k < cap; k++) {
        out[2 * k] = k < n ? w.pieces[size_t(2 * k)] : kSegStart;
        out[2 * k + 1] = k < n ? w.pieces[size_t(2 * k + 1)] : kSegStart;
      }
    }
  });
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_SILHOUETTE_SEGMENT_H_
