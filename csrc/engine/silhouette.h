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
//
// The parts: silhouette_tree.h (the hierarchy, its build and its side tests), silhouette_walk.h
// (the contour edges in a receiver's pyramid), silhouette_coverage.h (C from the reference ray and
// the crossings, through a grid of the emitter plane); here the receiver's driver: the contour cut
// into pieces where pieces cross, and the pieces that bound the visible region kept as runs.
#ifndef JAXSHADOW_SHADOWC_SILHOUETTE_H_
#define JAXSHADOW_SHADOWC_SILHOUETTE_H_

#include <algorithm>

#include "silhouette_coverage.h"
#include "silhouette_tree.h"
#include "silhouette_walk.h"

namespace jaxshadow_engine {

// The receiver through the silhouette path: its class with w.runs its boundary, or kFallback.
// `eh` are E_h's edges (polygon_receiver's first edges), `cone` / `prefs` E_h's planes.
template <class T>
int32_t silhouette_receiver(const PolyCall<T>& call, const SilhouetteTree& st, V3<T> p, V3<T> n,
                            const Edge<T>* eh, int neh, const V3<T>* cone, const PlaneRef* prefs, int np0,
                            V3<T> ne, double hp, Work<T>& w) {
  const double eps = 2.220446049250313e-16;
  const double tol = kCollinearEps * eps;
  const double scale = std::max(st.scale, double(absmax(p))) + 1e-300;
  std::vector<SSeg<T>>& segs = w.ssegs;
  segs.clear();
  for (int i = 0; i < neh; i++) {
    SSeg<T> s;
    s.a = eh[i].a, s.b = eh[i].b, s.own = eh[i].own, s.own_ref = eh[i].own_ref, s.ca = eh[i].ca, s.cb = eh[i].cb;
    s.w = 0, s.va = s.vb = -1, s.on_a = s.on_b = -1, s.own_n = norm(s.own), s.q0s = 0;
    segs.push_back(s);
  }
  const int32_t n_contour = contour_edges(call, st, p, cone, prefs, np0, ne, hp, scale, w);
  if (n_contour == kFallback) return kFallback;
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
  using Cov = SilCoverage<T>;
  Cov cov(call, st, w, eh, neh, p, ne, scale);
  if (!cov.reference()) return kFallback;
  cov.build_grid();
  cov.grid_references();
  const int G = cov.G;
  const std::vector<int32_t>& gs = w.gstart;
  const std::vector<int32_t>& gi = w.gitems;
  std::vector<int32_t>& stamp_of = w.gstamp;
  int32_t& stamp = cov.stamp;

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
      const int s0 = Cov::sgn(g0, tol * on), s1 = Cov::sgn(g0 + g1, tol * on);
      if (s0 == s1 && s0 != 0) continue;
      if (s0 == 0 && s1 == 0) {
        // s along o's line (collinear contour edges, as on a straight crease): apart when o's
        // ends lie clearly beyond one end of s along it.
        const double dd = double(dot(d, d));
        const double ta = double(dot(o.a - s.a, d)) / dd, tb = double(dot(o.b - s.a, d)) / dd;
        if ((ta < -1e-6 && tb < -1e-6) || (ta > 1 + 1e-6 && tb > 1 + 1e-6)) continue;
        return kFallback;
      }
      const int ca = cov.side_of(o.a, s), cb = cov.side_of(o.b, s);
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
    int c = Cov::kNone, last = -1;
    for (int k = 0; k + 1 < nt; k++)
      if (ts[size_t(ord[k + 1])] > ts[size_t(ord[k])]) last = k;
    for (int k = 0; k + 1 < nt; k++) {
      if (k > 0 && c != Cov::kNone) c += td[size_t(ord[k])];
      const double ta = ts[size_t(ord[k])], tb = ts[size_t(ord[k + 1])];
      if (!(tb > ta)) continue;
      const V3<T> m = s.a + (0.5 * (ta + tb)) * d;
      if (c == Cov::kNone || k == last) {
        const int full = i < neh ? cov.coverage_eh(m) : cov.coverage_at(m, i);
        if (full == Cov::kNone || (c != Cov::kNone && full != c)) return kFallback;
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
