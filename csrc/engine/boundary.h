// jaxshadow's shadow engine: boundary (part of `csrc/shadowc.cc`; see its header comment).
#ifndef JAXSHADOW_SHADOWC_BOUNDARY_H_
#define JAXSHADOW_SHADOWC_BOUNDARY_H_

#include "polygon_types.h"

namespace jaxshadow_engine {

// Occluder edges on one line in space. Two planes through p and two occluder edges, each
// through two vertices (PlaneRef kThrough, refs >= K), are the same plane when the four vertices
// lie on one line: a T-junction of a mesh (a vertex of one face inside an edge of its neighbour,
// as `Mesh`'s coplanar merging leaves where it drops a collinear vertex), or faces overlapping
// along an edge. The planes through p are then computed from different pairs of points and
// differ by their rounding, which grows as the edges' angular length seen from p shrinks (a short
// edge far away: 1.6e-14 rad for a 3 cm edge 1.5 m away, beyond the angle test's kCollinearEps
// eps), and the piece's membership in the other region was decided by that rounding. The test in
// space does not depend on p: each vertex within kCollinearEps eps S of the other edge's line
// (S the largest coordinate magnitude of the four vertices and p).
template <class T>
inline bool collinear_in_space(V3<T> a, V3<T> b, V3<T> c, V3<T> d, V3<T> p) {
  const T S = std::max(std::max(std::max(absmax(a), absmax(b)), std::max(absmax(c), absmax(d))), absmax(p));
  const T tau = T(kCollinearEps) * eps_of<T>() * S;
  auto near_line = [tau](V3<T> o, V3<T> q, V3<T> x, V3<T> y) {
    const V3<T> u = q - o;
    const T l2 = dot(u, u);
    if (!(l2 > 0)) return false;
    const V3<T> cx = cross(x - o, u), cy = cross(y - o, u);
    return dot(cx, cx) <= tau * tau * l2 && dot(cy, cy) <= tau * tau * l2;
  };
  return near_line(a, b, c, d) && near_line(c, d, a, b);
}

// The conditioning of the plane through p and the occluder edge `r` (kThrough, both refs
// occluder vertices): |a - p| |b - p| / |(b - p) x (a - p)|, 1 / sin of the angle the edge subtends
// at p (its normal's rounding is about that many epsilons of angle); 0 for other planes.
template <class T>
inline T through_condition(const Occluders<T>& occ, PlaneRef r, V3<T> p) {
  if (r.t != kThrough || r.a < occ.K || r.b < occ.K) return 0;
  const V3<T> a = occ.vref(r.a) - p, b = occ.vref(r.b) - p;
  const T cn = norm(cross(b, a));
  const T c = norm(a) * norm(b) / cn;
  return c == c ? c : std::numeric_limits<T>::infinity();
}

// Split every candidate edge of a penumbra receiver at the regions it enters and leaves and keep
// the free pieces as runs (`_clip._boundary_runs` / `edge_breakpoints`), appended to w.runs.
template <class T>
void boundary_runs(const Occluders<T>& occ, V3<T> p, T tol, const V3<T>* ehv, int nehv, Work<T>& w) {
  std::vector<V3<T>>& planes = w.planes;
  const int32_t n_regions = int32_t(w.regions.size());
  // Unit normals and norms of all planes; regions' boxes (their candidate edges' ends and the
  // E_h vertices inside them).
  const size_t npl = planes.size();
  w.pnorm.resize(npl);
  for (size_t k = 0; k < npl; k++) w.pnorm[k] = norm(planes[k]);
  w.pcond.resize(npl);
  for (size_t k = 0; k < npl; k++) w.pcond[k] = through_condition(occ, w.prefs[k], p);
  // normalize_safe of plane k from its norm (one square root), where a collinearity test needs it.
  auto unit = [&](int32_t k) -> V3<T> { return w.pnorm[k] > 0 ? (T(1) / w.pnorm[k]) * planes[k] : V3<T>{0, 0, 0}; };
  for (int32_t r = 1; r < n_regions; r++)
    for (int d = 0; d < 3; d++) {
      w.regions[r].lo[d] = w.regions[r].xlo[d];
      w.regions[r].hi[d] = w.regions[r].xhi[d];
    }
  for (auto& e : w.edges) {
    const T ca[3] = {e.a.x, e.a.y, e.a.z}, cb[3] = {e.b.x, e.b.y, e.b.z};
    for (int d = 0; d < 3; d++) {
      e.lo[d] = std::min(ca[d], cb[d]);
      e.hi[d] = std::max(ca[d], cb[d]);
      if (e.region > 0) {
        Region<T>& R = w.regions[e.region];
        R.lo[d] = std::min(R.lo[d], e.lo[d]);
        R.hi[d] = std::max(R.hi[d], e.hi[d]);
      }
    }
  }
  // An E_h vertex on a region's boundary plane (a receiver on an event line or plane: an occluder
  // vertex or edge projecting onto a light vertex) is a corner of region ∩ E_h, and its side of
  // that plane is rounding: it counts as inside within the plane's rounding bound ((4 + its
  // conditioning) tol, as the T-junction band below). Left out, the box missed the corner, and an
  // edge crossing the region there was not tested against it: a piece inside the region stayed in
  // the boundary (values up to 1.3x the unoccluded value). A box only filters; a zero plane (a
  // padded edge) bounds nothing.
  for (int i = 0; i < nehv; i++) {
    V3<T> r = ehv[i] - p;
    const T rn = norm(r);
    for (int32_t j = 1; j < n_regions; j++) {
      const Region<T>& R = w.regions[j];
      bool in = true;
      for (int k = 0; k < R.count && in; k++) {
        const int32_t pk = R.first + k;
        in = !nonzero(planes[pk]) || dot(r, planes[pk]) >= -(T(4) + w.pcond[pk]) * tol * w.pnorm[pk] * rn;
      }
      if (in) {
        Region<T>& Rw = w.regions[j];
        const T c[3] = {ehv[i].x, ehv[i].y, ehv[i].z};
        for (int d = 0; d < 3; d++) {
          Rw.lo[d] = std::min(Rw.lo[d], c[d]);
          Rw.hi[d] = std::max(Rw.hi[d], c[d]);
        }
      }
    }
  }

  // Split every candidate edge (_clip._boundary_runs / edge_breakpoints).
  const T big = std::numeric_limits<T>::infinity();
  for (auto* v : {&w.rlo, &w.rhi}) v->resize(n_regions);  // per live region of one edge
  for (auto* v : {&w.rnc, &w.rc, &w.rany}) v->resize(n_regions);
  for (auto* v : {&w.rilo, &w.rihi}) v->resize(n_regions);
  for (const Edge<T>& e : w.edges) {
    V3<T> ap = e.a - p, d = e.b - e.a;
    T apn = norm(ap) + norm(e.b - p);
    T ext = 0;
    for (int dd = 0; dd < 3; dd++) ext = std::max(ext, std::max(std::fabs(e.lo[dd]), std::fabs(e.hi[dd])));
    T bmargin = T(1e3) * eps_of<T>() * (ext + absmax(p)) + w.eh_margin;  // off_plane_margin
    const T econd = through_condition(occ, e.own_ref, p);  // > 0: an occluder edge (collinear_in_space)
    w.live.clear();
    for (int32_t j = 0; j < n_regions; j++) {
      if (j == e.region) continue;
      const Region<T>& R = w.regions[j];
      if (j == 0 && R.active) {
        // An occluder's edge was clipped to E_h's pyramid when it was made: E_h's region can
        // block none of it (only occluder regions block) except by the tie rule, which needs
        // one of its planes to hold the edge. Without such a plane -- both ends clearly off
        // every plane, the test below -- its breakpoints only split free pieces again.
        bool maybe_on = false;
        for (int k = 0; k < R.count && !maybe_on; k++) {
          const V3<T>& N = planes[R.first + k];
          if (!nonzero(N)) continue;
          const T g0 = dot(ap, N), g1 = dot(d, N);
          maybe_on = !(std::fabs(g0) > T(4) * tol * w.pnorm[R.first + k] * apn) &&
                     !(std::fabs(g0 + g1) > T(4) * tol * w.pnorm[R.first + k] * apn);
        }
        if (!maybe_on) continue;
      }
      bool overlap = true;
      const T elo[3] = {e.lo[0], e.lo[1], e.lo[2]}, ehi[3] = {e.hi[0], e.hi[1], e.hi[2]};
      for (int dd = 0; dd < 3 && overlap; dd++)
        overlap = !(ehi[dd] < R.lo[dd] - bmargin || R.hi[dd] < elo[dd] - bmargin);
      if (overlap) w.live.push_back(j);
    }
    const int nl = int(w.live.size());
    for (int li = 0; li < nl; li++) {
      const Region<T>& R = w.regions[w.live[li]];
      T lo = -big, hi = big;
      int ilo = 0, ihi = 0;
      bool have_lo = false, have_hi = false;
      bool c_nc = true, c_c = true, any_c = false;
      for (int k = 0; k < R.count; k++) {
        const int32_t pk = R.first + k;
        const V3<T>& N = planes[pk];
        bool valid = nonzero(N) && R.active;
        T g0 = dot(ap, N), g1 = dot(d, N);
        bool collinear = false;
        if (valid) {
          // Cheap exclusion first: an edge whose start is clearly off the plane is not on its line.
          // (Parallel unit normals put both ends within |x - p| tol of the plane.)
          if (!(std::fabs(g0) > T(4) * tol * w.pnorm[pk] * apn) && !(std::fabs(g0 + g1) > T(4) * tol * w.pnorm[pk] * apn)) {
            V3<T> cr = cross(normalize_safe(e.own), unit(pk));
            collinear = dot(cr, cr) <= tol * tol;
          }
          // Two occluder edges whose planes through p are apart by rounding only (within both
          // planes' rounding bounds, tol times their conditioning): on one line in space, or
          // coplanar with p (their projections on one line) with unit normals parallel within
          // that bound. Taken as crossing, their common line's point would be that of two planes
          // a rounding apart, anywhere on the line or off it (cross(N1, N2) below its rounding):
          // a boundary vertex off both edges, and a wrong region.
          // One end within the band and the other off it: an end clipped where the edge's plane
          // meets a nearly parallel one (p on a face, its neighbour's edge along the horizon) is
          // off that plane by the crossing's rounding, up to eps over the planes' angle; the
          // edges on one line in space are then still one plane (a twin's shared edge).
          if (!collinear && econd > 0 && w.pcond[pk] > 0) {
            const T cb = (T(4) + econd + w.pcond[pk]) * tol;
            const T band = cb * w.pnorm[pk] * apn;
            const bool near0 = !(std::fabs(g0) > band), near1 = !(std::fabs(g0 + g1) > band);
            if (near0 || near1) {
              collinear = collinear_in_space(occ.vref(e.own_ref.a), occ.vref(e.own_ref.b), occ.vref(w.prefs[pk].a),
                                             occ.vref(w.prefs[pk].b), p);
              if (!collinear && near0 && near1) {
                const V3<T> cr = cross(normalize_safe(e.own), unit(pk));
                collinear = dot(cr, cr) <= cb * cb;
              }
            }
          }
        }
        bool generic = valid && !collinear;
        T tc = g1 != 0 ? -g0 / g1 : T(0);
        T tl = (generic && g1 > 0) ? tc : -big;
        T th = (generic && g1 < 0) ? tc : big;
        if (!have_lo || tl > lo) {
          lo = tl;
          ilo = pk;
          have_lo = true;
        }
        if (!have_hi || th < hi) {
          hi = th;
          ihi = pk;
          have_hi = true;
        }
        if (generic && !(g1 != 0 || g0 >= 0)) c_nc = false;
        if (collinear && !(e.sigma * dot(unit(pk), normalize_safe(e.own)) > 0)) c_c = false;  // on the line, other side
        if (collinear) any_c = true;
      }
      w.rlo[li] = lo;
      w.rhi[li] = hi;
      w.rnc[li] = c_nc;
      w.rc[li] = c_c;
      w.rany[li] = any_c;
      w.rilo[li] = ilo;
      w.rihi[li] = ihi;
    }
    // Breakpoints: 0, 1, then lo's and hi's of the live regions (clipped to [0, 1]).
    w.ts.clear();
    w.tcodes.clear();
    w.ts.push_back(0);
    w.tcodes.push_back(e.ca);
    w.ts.push_back(1);
    w.tcodes.push_back(e.cb);
    for (int pass = 0; pass < 2; pass++)
      for (int li = 0; li < nl; li++) {
        T c = pass == 0 ? w.rlo[li] : w.rhi[li];
        int32_t pk = pass == 0 ? w.rilo[li] : w.rihi[li];
        Code cc;
        if (c <= 0) {
          cc = e.ca;
        } else if (c >= 1) {
          cc = e.cb;
        } else {
          cc = code_planes(e.own_ref, w.prefs[pk]);
        }
        w.ts.push_back(std::min(std::max(c, T(0)), T(1)));
        w.tcodes.push_back(cc);
      }
    const int nt = int(w.ts.size());
    w.order.resize(nt);
    for (int i = 0; i < nt; i++) w.order[i] = i;
    // Stable insertion sort by t (a handful of breakpoints; std::stable_sort allocates a buffer).
    for (int i = 1; i < nt; i++) {
      const int32_t x = w.order[i];
      int j = i;
      for (; j > 0 && w.ts[x] < w.ts[w.order[j - 1]]; j--) w.order[j] = w.order[j - 1];
      w.order[j] = x;
    }
    // Pieces [ts[i], ts[i+1]]: free unless inside another region (one-sided) or tied.
    w.free.resize(nt > 0 ? nt - 1 : 0);
    for (int i = 0; i + 1 < nt; i++) {
      T tm = T(0.5) * (w.ts[w.order[i]] + w.ts[w.order[i + 1]]);
      bool blocked = false;
      for (int li = 0; li < nl && !blocked; li++) {
        if (!(w.rlo[li] < tm && tm < w.rhi[li])) continue;
        const int32_t j = w.live[li];
        bool member = w.rnc[li] && w.rc[li] && w.regions[j].active;
        bool tie = w.rnc[li] && w.rany[li] && j < e.region;
        blocked = (member && j > 0) || tie;
      }
      w.free[i] = !blocked;
    }
    // Runs of consecutive free pieces, kept when of positive length.
    for (int i = 0; i + 1 < nt;) {
      if (!w.free[i]) {
        i++;
        continue;
      }
      int j = i;
      while (j + 1 < nt - 1 && w.free[j + 1]) j++;
      if (w.ts[w.order[j + 1]] > w.ts[w.order[i]]) w.runs.push_back(Run{w.tcodes[w.order[i]], w.tcodes[w.order[j + 1]]});
      i = j + 1;
    }
  }
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_BOUNDARY_H_
