// jaxshadow's shadow engine: the silhouette path's coverage (part of `csrc/shadowc.cc`; see
// silhouette.h): C, the number of mesh layers that cover a point of the emitter plane as seen from
// the receiver, from one reference count (a ray from p to q0) and the signed crossings of the
// contour pieces, directly or through a grid of the emitter plane.
#ifndef JAXSHADOW_SHADOWC_SILHOUETTE_COVERAGE_H_
#define JAXSHADOW_SHADOWC_SILHOUETTE_COVERAGE_H_

#include <cstdlib>
#include <limits>

#include "silhouette_tree.h"

namespace jaxshadow_engine {

// The lazily computed grid references' scratch (per thread): per cell the previous cell of its
// row holding pieces, per row the last row below it holding any, and the stack of cells being
// computed (grid_cov: `state` is how far the cell's recurrence got, `c` its value so far, `dir`
// and `from` the row below's cell it is reached through, `r` and `sp` its reference point and
// the point of the cell below).
template <class T>
struct SilGridFrame {
  int32_t cell, state, c, dir, from;
  V3<T> r, sp;
};
template <class T>
struct SilGridScratch {
  std::vector<int32_t> prev, below;
  std::vector<SilGridFrame<T>> frames;
};
template <class T>
inline SilGridScratch<T>& sil_grid_scratch() {
  static thread_local SilGridScratch<T> s;
  return s;
}

// What the crossing tests (silhouette.h) and jump_from read of a segment, packed: its plane (own, |own|), its ends as
// SilCoverage::side_of reads them (a - p, b - p and their |.|_1), its direction and scale (d,
// apn), its mesh vertex (va, -1 for E_h's edges) and its ends' position ids.
template <class T>
struct SilHot {
  V3<T> own, ra, rb, d;  // d = b - a
  T own_n;
  double la, lb, apn;    // apn = |a - p|_1 + |d|_1 (summed in T)
  int32_t va, ia, ib;
};

// One receiver's coverage: `segs` are E_h's `neh` edges followed by the contour pieces
// (silhouette_walk.h); the grid's arrays live in `w`.
template <class T>
struct SilCoverage {
  static constexpr int kNone = std::numeric_limits<int>::min();  // a decision too close to call
  static constexpr int kUnset = kNone + 1;                         // a grid cell's C not computed yet
  const PolyCall<T>& call;
  const Occluders<T>& occ;
  const SilhouetteTree& st;
  std::vector<SSeg<T>>& segs;
  Work<T>& w;
  const Edge<T>* eh;
  const int neh, ns;
  const V3<T> p, ne;
  const double pd[3];
  const double eps = 2.220446049250313e-16;
  const double tol = kCollinearEps * eps;
  const double scale;
  V3<T> centre{0, 0, 0};  // E_h's centroid
  V3<T> q0{};             // the reference point, and C there
  int c0 = -1;
  // The grid (G = 0: none): cells of (du, dv) from (umin, vmin) in the frame (O; U, Vv) of the
  // emitter plane; E_h's vertices in it (ehu, ehv); gpad pads the pieces' boxes.
  int G = 0;
  double umin = 0, vmin = 0, du = 0, dv = 0, gpad = 0;
  double O[3] = {0, 0, 0}, U[3] = {0, 0, 0}, Vv[3] = {0, 0, 0};
  double ehu[130], ehv[130];
  double cside[130], eex[130], eey[130], emarg[130];  // per E_h edge in (u, v): side of its centre, direction, margin
  std::vector<int32_t>& gs;
  std::vector<int32_t>& gi;
  std::vector<int32_t>& stamp_of;
  int32_t stamp = 0;  // the current query (stamp_of: the last query that tested a piece)
  SilGridScratch<T>* gscratch = nullptr;  // the grid references' scratch (grid_references)
  const SilHot<T>* hot = nullptr;  // the pieces' packed copies, where silhouette_receiver made them

  SilCoverage(const PolyCall<T>& call_, const SilhouetteTree& st_, Work<T>& w_, const Edge<T>* eh_, int neh_, V3<T> p_,
              V3<T> ne_, double scale_)
      : call(call_), occ(call_.occ), st(st_), segs(w_.ssegs), w(w_), eh(eh_), neh(neh_), ns(int(w_.ssegs.size())), p(p_),
        ne(ne_), pd{p_.x, p_.y, p_.z}, scale(scale_), gs(w_.gstart), gi(w_.gitems), stamp_of(w_.gstamp) {
    // Reference points inside E_h: its centroid, then points towards its corners.
    for (int i = 0; i < neh; i++) centre = centre + eh[i].a;
    centre = (1.0 / neh) * centre;
  }

  // A clear sign of `x` against the bound `m` (0: too close to call).
  static int sgn(double x, double m) { return int(x > m) - int(x < -m); }
  // A point x of the emitter plane as side_of reads it: r = x - p and |r|_1 (summed x, y, z).
  struct At {
    V3<T> r;
    double l1;
  };
  At at(V3<T> x) const {
    const V3<T> r = x - p;
    return At{r, std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z)};
  }
  int side_of(const At& x, const SSeg<T>& s) const { return sgn(dot(x.r, s.own), tol * s.own_n * x.l1); }
  int side_of(V3<T> x, const SSeg<T>& s) const {  // of a point in the emitter plane, against s.own
    return side_of(at(x), s);
  }

  // C at q0: faces crossed by the segment from p to q0, every face counted.
  int layers(V3<T> q) const {
    const BVH& bvh = *call.bvh;
    const V3<T> r = q - p;
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
        int s = sil_side(st, st.floc[size_t(f)], pd);
        if (s == 0 && !face_path_side(occ, st, st.floc[size_t(f)], p, s)) return -1;
        if (s == 0) continue;  // dropped by the face path: covers nothing
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
  }

  // q0 and C there (E_h's centroid, else a point towards one of its corners, clear of every
  // contour piece's line), and every piece's side of q0. false: none could be decided.
  bool reference() {
    for (int attempt = 0; attempt <= neh && c0 < 0; attempt++) {
      q0 = attempt == 0 ? centre : centre + 0.37 * (eh[attempt - 1].a - centre);
      const At aq = at(q0);
      bool clear = true;
      for (int i = neh; i < ns && clear; i++) {
        segs[size_t(i)].q0s = side_of(aq, segs[size_t(i)]);
        clear = segs[size_t(i)].q0s != 0;
      }
      if (clear) c0 = layers(q0);
    }
    if (c0 < 0) return false;
    // (the contour pieces' sides were set by the last attempt, the one whose q0 this is)
    const At aq = at(q0);
    for (int i = 0; i < neh; i++) segs[size_t(i)].q0s = side_of(aq, segs[size_t(i)]);
    return true;
  }

  // The jump of C along the path from -> m (pqm = cross(from - p, m - p), pn its norm) across
  // piece s: 0 when they do not cross, +-W when they do, kNone when a crossing is too close to
  // call.
  // An end of the path on the piece's line (a point of a collinear piece, as along a straight
  // crease of a CAD part) is decided by the piece's ends: both clearly on one side of the path's
  // plane, the piece does not meet the path.
  int jump_from(const SSeg<T>& s, int sq, const At& m, V3<T> pqm, double pn) const {
    return jump_from(s, sq, side_of(m, s), pqm, pn);
  }
  // The same with m's side of the piece given (sm = side_of(m, s)).
  int jump_from(const SSeg<T>& s, int sq, int sm, V3<T> pqm, double pn) const {
    if (sq != 0 && sm == sq) return 0;
    int ca, cb;
    if (hot) {  // the same ends and |.|_1, made once
      const SilHot<T>& h = hot[&s - segs.data()];
      ca = sgn(dot(h.ra, pqm), tol * pn * h.la);
      cb = sgn(dot(h.rb, pqm), tol * pn * h.lb);
    } else {
      const V3<T> ra = s.a - p, rb = s.b - p;
      ca = sgn(dot(ra, pqm), tol * pn * (std::fabs(ra.x) + std::fabs(ra.y) + std::fabs(ra.z)));
      cb = sgn(dot(rb, pqm), tol * pn * (std::fabs(rb.x) + std::fabs(rb.y) + std::fabs(rb.z)));
    }
    if (ca == 0 || cb == 0) return kNone;
    if (ca == cb) return 0;
    if (sq == 0 || sm == 0) return kNone;
    return sm > 0 ? s.w : -s.w;  // from `from`'s side to m's: + W into the positive side
  }
  // C on the q0 side of point m (in the emitter plane), from the crossings of q0 -> m with every
  // contour edge but `skip` (q0's sides of them are their q0s); kNone when a crossing is too close
  // to call.
  int coverage(V3<T> m, int skip) const {
    const V3<T> pqm = cross(q0 - p, m - p);
    const double pn = norm(pqm);
    const At am = at(m);
    int c = c0;
    for (int i = neh; i < ns; i++) {
      if (i == skip) continue;
      const int j = jump_from(segs[size_t(i)], segs[size_t(i)].q0s, am, pqm, pn);
      if (j == kNone) return kNone;
      c += j;
    }
    return c;
  }
  // coverage(m, skip) through the grid: the same sum over only the pieces registered in the cells
  // the segment q0 -> m passes, widened by gpad on every side (a piece that crosses the segment
  // is registered in every cell its box padded by gpad meets; the rounding of the segment's
  // (u, v) and of the cells' bounds is far below gpad). kNone as coverage().
  int coverage_path(V3<T> m, int skip) {
    double u0, v0, u1, v1;
    uv(q0, u0, v0);
    uv(m, u1, v1);
    const V3<T> pqm = cross(q0 - p, m - p);
    const double pn = norm(pqm);
    const At am = at(m);
    int c = c0;
    stamp++;
    const int iy0 = cell_of(std::min(v0, v1) - gpad, vmin, dv), iy1 = cell_of(std::max(v0, v1) + gpad, vmin, dv);
    const double dvp = v1 - v0;
    for (int iy = iy0; iy <= iy1; iy++) {
      // The segment's u over the row's v range (all of it where the segment runs along the rows).
      double ua = std::min(u0, u1), ub = std::max(u0, u1);
      if (std::fabs(dvp) > 1e-3 * dv) {
        const double ta = std::min(1.0, std::max(0.0, (vmin + iy * dv - gpad - v0) / dvp));
        const double tb = std::min(1.0, std::max(0.0, (vmin + (iy + 1) * dv + gpad - v0) / dvp));
        const double xa = u0 + ta * (u1 - u0), xb = u0 + tb * (u1 - u0);
        ua = std::min(xa, xb), ub = std::max(xa, xb);
      }
      const int ix0 = cell_of(ua - gpad, umin, du), ix1 = cell_of(ub + gpad, umin, du);
      for (int ix = ix0; ix <= ix1; ix++) {
        const int cell = iy * G + ix;
        for (int32_t k = gs[size_t(cell)]; k < gs[size_t(cell + 1)]; k++) {
          const int32_t i = gi[size_t(k)];
          if (i == skip || stamp_of[size_t(i)] == stamp) continue;
          stamp_of[size_t(i)] = stamp;
          const int j = jump_from(segs[size_t(i)], segs[size_t(i)].q0s, am, pqm, pn);
          if (j == kNone) return kNone;
          c += j;
        }
      }
    }
    return c;
  }
  void uv(V3<T> x, double& u, double& v) const {
    const double r[3] = {double(x.x) - O[0], double(x.y) - O[1], double(x.z) - O[2]};
    u = r[0] * U[0] + r[1] * U[1] + r[2] * U[2];
    v = r[0] * Vv[0] + r[1] * Vv[1] + r[2] * Vv[2];
  }
  int cell_of(double x, double mn, double d) const {
    // floor((x - mn) / d) clamped to [0, G - 1]: below 1 the first cell, from G - 1 the last,
    // truncation (floor for the positive values between) otherwise.
    const double y = (x - mn) / d;
    if (!(y >= 1)) return 0;
    return y >= double(G - 1) ? G - 1 : int(y);
  }

  // The contour pieces on a grid of the emitter plane: a piece's crossing candidates are the
  // pieces registered in the cells its box meets, and C at a point is C at q0 plus the crossings
  // of the path from q0 with the pieces of the cells along it (coverage_path), or C at its cell's
  // reference point plus the crossings of the path between them with the cell's pieces (not the
  // path from q0 with every piece): the arrangement costs about O(S sqrt S) for S contour pieces
  // instead of O(S^2). A path between two points of one cell, or of two cells sharing a side
  // (their union is a rectangle), stays in those cells and inside E_h (convex), so only pieces
  // registered there (by their boxes, padded far beyond rounding) can cross it. Any decision too
  // close to call, and any point without a usable cell, takes the path from q0 with every piece.
  void build_grid() {
    const int nsc = ns - neh;
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
        G = std::max(2, std::min(kSilGridMax, int(std::ceil(std::sqrt(double(nsc))))));
        du = (umax - umin) / G, dv = (vmax - vmin) / G;
        gpad = 1e-9 * (umax - umin + vmax - vmin) + 64 * eps * scale;
        if (!(du > gpad && dv > gpad)) G = 0;
      }
    }
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
  }
  // C at m on the `from` side of piece `skip` (-1: none), from C at `from` and the crossings of
  // from -> m with the pieces registered in cells ca and cb (-1: none) but `skip2` (-1: none; a
  // piece `from` lies on, C at `from` taken on m's side of it). `at_ref`: `from` is ca's
  // reference point, `to_ref`: m is cb's (their pieces' sides of it are kept in gside, each
  // computed once).
  int cross_cells(V3<T> from, int cfrom, V3<T> m, int skip, int ca, int cb, bool at_ref = true, bool to_ref = false,
                  int skip2 = -1) {
    const V3<T> pqm = cross(from - p, m - p);
    const double pn = norm(pqm);
    const At af = at(from), am = at(m);
    int c = cfrom;
    stamp++;
    for (int cell : {ca, cb}) {
      if (cell < 0) continue;
      const bool cached = at_ref && cell == ca;
      for (int32_t k = gs[size_t(cell)]; k < gs[size_t(cell + 1)]; k++) {
        const int32_t i = gi[size_t(k)];
        if (i == skip || i == skip2 || stamp_of[size_t(i)] == stamp) continue;
        stamp_of[size_t(i)] = stamp;
        int sq;
        if (cached) {
          int8_t& g = w.gside[size_t(k)];
          if (g == 2) g = int8_t(side_of(af, segs[size_t(i)]));
          sq = g;
        } else {
          sq = side_of(af, segs[size_t(i)]);
        }
        int sm;
        if (to_ref && cell == cb) {
          int8_t& g = w.gside[size_t(k)];
          if (g == 2) g = int8_t(side_of(am, segs[size_t(i)]));
          sm = g;
        } else {
          sm = side_of(am, segs[size_t(i)]);
        }
        const int j = jump_from(segs[size_t(i)], sq, sm, pqm, pn);
        if (j == kNone) return kNone;
        c += j;
      }
    }
    return c;
  }
  // Reference points in the cells that hold pieces (the only cells queried): the cell's centre
  // when the cell lies inside E_h, else the mean of the vertices of the cell clipped to E_h, kept
  // when it is clear of E_h's edges by a thousandth of a cell. C there from the previous such cell
  // of its row (the cells between hold no piece), else from the row of such cells below: straight
  // up from the cell below when it has a reference, else through a point of that cell reached
  // along its row from the nearest cell holding pieces; else from q0. A cell's C is computed when
  // a query first needs it (grid_cov), with the cells it is computed from first: each value and
  // each decision is the one the same recurrence gives when every cell is computed in row order,
  // and most cells are never queried.
  void grid_references() {
    if (!G) return;
    w.gref.resize(size_t(G * G));
    w.gcov.assign(size_t(G * G), kNone);
    gscratch = &sil_grid_scratch<T>();
    SilGridScratch<T>& gsc = *gscratch;
    gsc.prev.resize(size_t(G * G));
    gsc.below.resize(size_t(G));
    int last_row = -1;  // the last row with a cell holding pieces
    for (int iy = 0; iy < G; iy++) {
      gsc.below[size_t(iy)] = last_row;
      int prev = -1;  // the previous cell of this row holding pieces
      for (int ix = 0; ix < G; ix++) {
        const int cell = iy * G + ix;
        if (!held(cell)) continue;
        gsc.prev[size_t(cell)] = prev;
        w.gcov[size_t(cell)] = kUnset;
        prev = cell;
      }
      if (prev >= 0) last_row = iy;
    }
    // Per E_h edge: its direction (eex, eey), the side E_h's centre lies on, and the margin
    // times its length.
    const double margin = 1e-3 * std::min(du, dv);
    for (int k = 0; k < neh; k++) {
      const int k1 = (k + 1) % neh;
      eex[k] = ehu[k1] - ehu[k], eey[k] = ehv[k1] - ehv[k];
      cside[k] = eex[k] * (0 - ehv[k]) - eey[k] * (0 - ehu[k]) > 0 ? 1.0 : -1.0;
      emarg[k] = margin * std::sqrt(eex[k] * eex[k] + eey[k] * eey[k]);
    }
  }
  bool held(int cell) const { return gs[size_t(cell + 1)] > gs[size_t(cell)]; }
  bool inside(double x, double y) const {  // clear of every E_h edge by the margin
    for (int k = 0; k < neh; k++)
      if (!(cside[k] * (eex[k] * (y - ehv[k]) - eey[k] * (x - ehu[k])) > emarg[k])) return false;
    return true;
  }
  // The reference point of cell (ix, iy); false: none.
  bool cell_point(int ix, int iy, V3<T>& r) const {
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
  }
  // C at cell's reference point (kNone: none, or a cell holding no piece), computed on first use
  // with the recurrence above; the cells it needs are computed first, through an explicit stack
  // (a chain of them can be as long as the grid has cells).
  int grid_cov(int cell) {
    if (!gscratch) grid_references();  // (made on the first use: most receivers never need them)
    if (w.gcov[size_t(cell)] != kUnset) return w.gcov[size_t(cell)];
    std::vector<SilGridFrame<T>>& stk = gscratch->frames;
    stk.clear();
    stk.push_back(SilGridFrame<T>{cell, 0, kNone, -1, -1, {}, {}});
    while (!stk.empty()) {
      const int dep = grid_step(stk.back());
      if (dep >= 0) {
        stk.push_back(SilGridFrame<T>{dep, 0, kNone, -1, -1, {}, {}});
      } else {
        stk.pop_back();
      }
    }
    return w.gcov[size_t(cell)];
  }
  // One step of cell f's recurrence (grid_references): -1 when its C is stored, else a cell
  // whose C it needs first (f keeps its state).
  int grid_step(SilGridFrame<T>& f) {
    const int ix = f.cell % G, iy = f.cell / G;
    const SilGridScratch<T>& gsc = *gscratch;
    const int before = gsc.prev[size_t(f.cell)], lr = gsc.below[size_t(iy)];
    const int below = lr >= 0 ? lr * G + ix : -1;
    auto need = [&](int cell) { return w.gcov[size_t(cell)] == kUnset; };
    for (;;) {
      switch (f.state) {
        case 0:  // the reference point, then the cell it is reached from
          if (!cell_point(ix, iy, f.r)) {
            w.gcov[size_t(f.cell)] = kNone;
            return -1;
          }
          w.gref[size_t(f.cell)] = f.r;
          if (before >= 0) {
            f.state = 1;
            if (need(before)) return before;
          } else if (lr >= 0) {
            f.state = 2;
            if (need(below)) return below;
          } else {
            f.state = 5;
          }
          break;
        case 1:  // from the previous cell of the row
          if (w.gcov[size_t(before)] != kNone) f.c = cross_cells(w.gref[size_t(before)], w.gcov[size_t(before)], f.r, -1, before, f.cell, true, true);
          f.state = 5;
          break;
        case 2:  // straight up from the cell below, else through it from its row
          if (w.gcov[size_t(below)] != kNone) {
            f.c = cross_cells(w.gref[size_t(below)], w.gcov[size_t(below)], f.r, -1, below, f.cell, true, true);
            f.state = 5;
          } else if (cell_point(ix, lr, f.sp)) {
            f.dir = -1;
            f.state = 3;
          } else {
            f.state = 5;
          }
          break;
        case 3: {  // the nearest cell holding pieces in the row below, in direction dir
          if (f.dir > 1 || f.c != kNone) {
            f.state = 5;
            break;
          }
          int k = ix + f.dir;
          while (k >= 0 && k < G && !held(lr * G + k)) k += f.dir;
          if (k < 0 || k >= G) {
            f.dir += 2;
            break;
          }
          f.from = lr * G + k;
          f.state = 4;
          if (need(f.from)) return f.from;
          break;
        }
        case 4:
          if (w.gcov[size_t(f.from)] != kNone) {
            const int c1 = cross_cells(w.gref[size_t(f.from)], w.gcov[size_t(f.from)], f.sp, -1, f.from, below);
            if (c1 != kNone) f.c = cross_cells(f.sp, c1, f.r, -1, below, f.cell, false, true);
          }
          f.dir += 2;
          f.state = 3;
          break;
        default:  // from q0 when no cell gave it
          if (f.c == kNone) f.c = coverage(f.r, -1);
          w.gcov[size_t(f.cell)] = f.c;
          return -1;
      }
    }
  }
  // C on q0's side of contour piece `skip` at point m on it: along q0 -> m through the grid, else
  // from m's cell's reference point, else from q0 with every piece.
  int coverage_at(V3<T> m, int skip) {
    if (G) {
      const int cp = coverage_path(m, skip);
      if (cp != kNone) return cp;
      double um, vm;
      uv(m, um, vm);
      if (um > umin - gpad && um < umin + G * du + gpad && vm > vmin - gpad && vm < vmin + G * dv + gpad) {
        const int cell = cell_of(vm, vmin, dv) * G + cell_of(um, umin, du);
        const int cc = grid_cov(cell);
        if (cc != kNone) {
          const SSeg<T>& s = segs[size_t(skip)];
          const V3<T> r = w.gref[size_t(cell)];
          const int rs = side_of(r, s), qs = s.q0s;
          if (rs != 0 && qs != 0) {
            const int c = cross_cells(r, cc, m, skip, cell, -1);
            if (c != kNone) return rs == qs ? c : (qs > 0 ? c + s.w : c - s.w);
          }
        }
      }
    }
    return coverage(m, skip);
  }
  // Whether (u, v) lies on the grid (its cell's pieces are the ones that can cross a path in it).
  bool on_grid(double u, double v) const {
    return u > umin - gpad && u < umin + G * du + gpad && v > vmin - gpad && v < vmin + G * dv + gpad;
  }
  // C on q0's side of contour piece `skip` at point m on it (skip = -1: C at a point m of E_h's
  // boundary, as coverage_eh), from a point `from` of another contour piece k (inside one of k's
  // pieces between breakpoints) where C on q0's side of k is ck: the crossings of from -> m with
  // the pieces registered in m's cell and from's cell when those are one cell, share a side, or
  // lie in one row with no piece registered in the cells between (the path stays in that row and
  // in E_h, convex, and no piece's padded box meets the cells between). kNone when the cells are
  // otherwise, a side is too close to call (m on k's line, `from` on skip's), or a crossing is;
  // the caller then asks coverage_at or coverage_eh.
  int coverage_from(V3<T> m, int skip, V3<T> from, int k, int ck) {
    if (!G) return kNone;
    double um, vm, uf, vf;
    uv(m, um, vm);
    uv(from, uf, vf);
    if (!on_grid(um, vm) || !on_grid(uf, vf)) return kNone;
    const int bx = cell_of(um, umin, du), by = cell_of(vm, vmin, dv);
    const int ax = cell_of(uf, umin, du), ay = cell_of(vf, vmin, dv);
    if (std::abs(ax - bx) + std::abs(ay - by) > 1) {  // else one row, the cells between holding none
      if (ay != by) return kNone;
      for (int x = std::min(ax, bx) + 1; x < std::max(ax, bx); x++)
        if (held(ay * G + x)) return kNone;
    }
    const SSeg<T>& sk = segs[size_t(k)];
    const int mk = side_of(m, sk);
    if (mk == 0 || sk.q0s == 0) return kNone;
    int rs = 0, qs = 0;
    if (skip >= 0) {
      rs = side_of(from, segs[size_t(skip)]), qs = segs[size_t(skip)].q0s;
      if (rs == 0 || qs == 0) return kNone;
    }
    const int cfrom = mk == sk.q0s ? ck : (mk > 0 ? ck + sk.w : ck - sk.w);  // C at `from` on m's side of k
    const int ca = ay * G + ax, cb = by * G + bx;
    const int c = cross_cells(from, cfrom, m, skip, ca, cb == ca ? -1 : cb, false, false, k);
    if (c == kNone || skip < 0) return c;
    const int w = segs[size_t(skip)].w;
    return rs == qs ? c : (qs > 0 ? c + w : c - w);
  }
  // C at a point m of E_h's boundary (inside E_h's side of every contour piece's plane test):
  // along q0 -> m through the grid (coverage_path), else
  // from the reference point of m's cell when the cell holds pieces, else of the nearest cell of
  // its row that does (the cells between hold none, and the path lies in E_h, convex, and in the
  // row); the pieces that can cross that path are the ones registered in that cell.
  int coverage_eh(V3<T> m) {
    if (G) {
      const int cp = coverage_path(m, -1);
      if (cp != kNone) return cp;
      double um, vm;
      uv(m, um, vm);
      if (um > umin - gpad && um < umin + G * du + gpad && vm > vmin - gpad && vm < vmin + G * dv + gpad) {
        const int iy = cell_of(vm, vmin, dv), ix = cell_of(um, umin, du);
        int from = -1;
        if (held(iy * G + ix)) {
          from = iy * G + ix;
        } else {
          int best = G + 1;
          for (int dir = -1; dir <= 1; dir += 2) {
            int k = ix + dir;
            while (k >= 0 && k < G && !held(iy * G + k)) k += dir;
            if (k < 0 || k >= G || std::abs(k - ix) >= best || grid_cov(iy * G + k) == kNone) continue;
            best = std::abs(k - ix);
            from = iy * G + k;
          }
        }
        if (from >= 0 && grid_cov(from) != kNone) {
          const int c = cross_cells(w.gref[size_t(from)], w.gcov[size_t(from)], m, -1, from, -1);
          if (c != kNone) return c;
        }
      }
    }
    return coverage(m, -1);
  }
};

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_SILHOUETTE_COVERAGE_H_
