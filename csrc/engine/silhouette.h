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
#include <cstring>
#include <type_traits>

#include "silhouette_coverage.h"
#include "silhouette_tree.h"
#include "silhouette_walk.h"

namespace jaxshadow_engine {

// A slot of the table of contour segments' unclipped ends by position: the mesh vertex, the
// first two ends there (2 i + 0: segment i's end a, 2 i + 1: its end b) and how many (0: empty slot).
struct SilEnd {
  double x, y, z;
  int32_t e, e2, n;
};
// A segment's box in the emitter plane (lo, hi), in double (the exact values of T) as two-lane
// vectors for the box test: lxy = (lo.x, lo.y), hxy = (hi.x, hi.y), zh = (hi.z, -lo.z),
// zl = (lo.z, -hi.z). Boxes i and j are apart iff a lane of hxy_i < lxy_j, hxy_j < lxy_i or
// zh_i < zl_j holds (-lo_i.z < -hi_j.z is hi_j.z < lo_i.z; the negations are exact).
typedef double SilV2 __attribute__((vector_size(16)));
struct SilBox {
  SilV2 lxy, hxy, zh, zl;
};
inline bool sil_apart(const SilBox& a, const SilBox& b) {
  const auto m = (a.hxy < b.lxy) | (b.hxy < a.lxy) | (a.zh < b.zl);
  return (m[0] | m[1]) != 0;
}
// How many contour pieces of known C a coverage query tries (near, in silhouette_receiver) before
// the path from q0 through the grid (SilCoverage::coverage_at, coverage_eh).
constexpr int kSilNearTries = 4;
// The most ends of contour segments at one vertex whose rays silhouette_receiver sorts about it.
constexpr int kSilFan = 8;
// Per-thread scratch of silhouette_receiver's pieces (allocated once per thread).
struct SilPieces {
  std::vector<int32_t> boff, kf, kl, sj, sneg, cf, link, unpaired, succ, pred, todo;
  std::vector<double> pends;  // per contour segment: its first and last pieces' ends in t (4 values)
  std::vector<int32_t> eslot;  // per segment end: its slot in `ends` (-1: clipped)
  std::vector<int32_t> fan;    // the slots where 3 .. kSilFan ends meet
  std::vector<int32_t> fan_ends, fan_n;  // their ends (kSilFan per slot) and how many
  std::vector<int32_t> clipped;  // the contour segments with an end clipped at a cone plane
  std::vector<SilEnd> ends;     // all slots empty between receivers (the used ones are emptied after use)
  std::vector<int32_t> ends_used;  // the slots filled for this receiver (its first entries)
  // The grid's crossing candidates: per cell the first of its pieces not yet gathered from
  // (gpos). Per piece j the crossings found with pieces of lower index before j's turn, in
  // increasing order of those (a list from phead[j] through pnext, ptail[j] its last entry,
  // pnum[j] entries; an entry's t, code source and jump in pt, psrc, ptd).
  std::vector<int32_t> gpos, phead, ptail, pnum, psrc, ptd, pnext;
  std::vector<double> pt;
  std::vector<int32_t> all;  // 0 .. ns - 1 (the candidates of a piece off the grid)
  std::vector<int32_t> tsrc;  // per breakpoint: where its code comes from (silhouette_receiver)
};
inline std::vector<SilBox>& sil_boxes() {
  static thread_local std::vector<SilBox> boxes;
  return boxes;
}
template <class T>
inline std::vector<SilHot<T>>& sil_hot() {
  static thread_local std::vector<SilHot<T>> hot;
  return hot;
}
// Not inlined: the caller keeps the address, where an inlined thread-local would be looked up
// again (__tls_get_addr in a shared library) at every use in its loops.
__attribute__((noinline)) inline SilPieces& sil_pieces() {
  static thread_local SilPieces pieces;
  return pieces;
}

// The receiver through the silhouette path: its class with w.runs its boundary, or kFallback.
// `eh` are E_h's edges (polygon_receiver's first edges), `cone` / `prefs` E_h's planes.
template <class T>
int32_t silhouette_receiver(const PolyCall<T>& call, const SilhouetteTree& st, V3<T> p, V3<T> n,
                            const Edge<T>* eh, int neh, const V3<T>* cone, const PlaneRef* prefs, int np0,
                            V3<T> ne, double hp, Work<T>& w) {
  if (section_umbra(call.sections, p, n)) {  // umbra by a body inside the mesh (umbra_sections.h)
    w.n_candidates = 0;
    return kUmbra;
  }
  const double eps = 2.220446049250313e-16;
  const double tol = kCollinearEps * eps;
  const double scale = std::max(st.scale, double(absmax(p))) + 1e-300;
  std::vector<SSeg<T>>& segs = w.ssegs;
  segs.clear();
  for (int i = 0; i < neh; i++) {
    SSeg<T> s;
    s.a = eh[i].a, s.b = eh[i].b, s.own = eh[i].own, s.own_ref = eh[i].own_ref, s.ca = eh[i].ca, s.cb = eh[i].cb;
    s.w = 0, s.va = s.vb = -1, s.ia = s.ib = -1, s.on_a = s.on_b = -1, s.own_n = norm(s.own), s.q0s = 0;
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
  const int G = cov.G;
  const std::vector<int32_t>& gs = w.gstart;
  const std::vector<int32_t>& gi = w.gitems;
  std::vector<int32_t>& stamp_of = w.gstamp;
  int32_t& stamp = cov.stamp;

  // Pieces: every segment cut where another crosses it.
  w.runs.clear();
  bool eh_all = true, eh_any = false;
  std::vector<T>& ts = w.sts;
  // Per breakpoint: where its code comes from (tc_code below), the code made only for the ends of runs.
  std::vector<int32_t>& tc = sil_pieces().tsrc;
  // A breakpoint's code source: j >= 0 the crossing with contour piece j (code_planes of the two
  // planes), kSrcA / kSrcB the segment's end a / b (its ca / cb), kSrcClipped - 2 j - e contour
  // piece j's end e (0: a, 1: b) clipped at the plane of the E_h edge it is a breakpoint of.
  constexpr int32_t kSrcA = -1, kSrcB = -2, kSrcClipped = -3;
  auto tc_code = [&](const SSeg<T>& s, int32_t x) -> Code {
    const int32_t v = tc[size_t(x)];
    if (v >= 0) return code_planes(s.own_ref, segs[size_t(v)].own_ref);
    if (v == kSrcA) return s.ca;
    if (v == kSrcB) return s.cb;
    const int32_t q = kSrcClipped - v;
    const SSeg<T>& o = segs[size_t(q / 2)];
    return q % 2 ? o.cb : o.ca;
  };
  std::vector<int32_t>& td = w.std_;  // per breakpoint: the change of C crossing it along s
  // The segments' boxes in the emitter plane (crossing tests only between overlapping boxes).
  // Whether every contour piece has its mesh vertex and both ends' position ids (the tile's walk).
  bool all_ids = true, by_id = true;  // by_id: every contour piece has both ends' position ids
  for (int i = neh; i < ns; i++) {
    const bool ids = segs[size_t(i)].ia >= 0 && segs[size_t(i)].ib >= 0;
    by_id &= ids;
    all_ids &= ids && segs[size_t(i)].va >= 0;
  }
  std::vector<SilBox>& boxv = sil_boxes();
  if (boxv.size() < size_t(ns)) boxv.resize(2 * size_t(ns));
  SilBox* const bx = boxv.data();
  std::vector<SilHot<T>>& hotv = sil_hot<T>();
  if (hotv.size() < size_t(ns)) hotv.resize(2 * size_t(ns));
  SilHot<T>* const hot = hotv.data();
  cov.hot = hot;  // (filled below, before any coverage query)
  for (int i = 0; i < ns; i++) {
    const SSeg<T>& s = segs[size_t(i)];
    const typename Cov::At xa = cov.at(s.a), xb = cov.at(s.b);
    const V3<T> ap = xa.r, d = s.b - s.a;
    const double apn = std::fabs(ap.x) + std::fabs(ap.y) + std::fabs(ap.z) + std::fabs(d.x) + std::fabs(d.y) + std::fabs(d.z);
    hot[i] = SilHot<T>{s.own, xa.r, xb.r, d, s.own_n, xa.l1, xb.l1, apn, s.va, s.ia, s.ib};
    const T ca[3] = {segs[i].a.x, segs[i].a.y, segs[i].a.z}, cb[3] = {segs[i].b.x, segs[i].b.y, segs[i].b.z};
    double lo[3], hi[3];
    for (int k = 0; k < 3; k++) {
      lo[k] = double(std::min(ca[k], cb[k]) - T(1e-9) * T(scale));
      hi[k] = double(std::max(ca[k], cb[k]) + T(1e-9) * T(scale));
    }
    bx[i] = SilBox{SilV2{lo[0], lo[1]}, SilV2{hi[0], hi[1]}, SilV2{hi[2], -lo[2]}, SilV2{lo[2], -hi[2]}};
  }
  SilPieces& pc = sil_pieces();
  // The links between contour segments' ends at one vertex (C is carried along them below, after
  // the pieces; they are made first so that the crossing tests skip the pairs linked at their
  // common end).
  std::vector<int32_t>& link = pc.link;  // per segment end (2 i + 0: a, 2 i + 1: b): the other segment end at v, or -1
  link.assign(2 * size_t(ns), -1);
  // Per segment end, with every contour piece's ids (all_ids): the segment linked there when
  // the two share no other end (their crossing tests need not be made, below), else -1.
  std::vector<int32_t>& unpaired = pc.unpaired;
  if (all_ids) unpaired.assign(2 * size_t(ns), -1);
  std::vector<int32_t>& succ = pc.succ;  // per end at a vertex of k >= 3 rays: the next ray's end, or -1
  std::vector<int32_t>& pred = pc.pred;  // and the previous ray's end
  succ.assign(2 * size_t(ns), -1);
  pred.assign(2 * size_t(ns), -1);
  {
    // The unclipped ends by their mesh vertex's position, in an open-addressing table of
    // positions (nh slots, a power of two at least twice the ends): per slot the position, the
    // first end and how many ends are there (to 3).
    std::vector<SilEnd>& tab = pc.ends;
    // With every contour segment's position ids (the tile's walk, by_id), slot = id instead.
    size_t nh = 16;
    while (nh < 4 * size_t(ns - neh)) nh *= 2;
    if (by_id) nh = std::max(nh, size_t(w.sil_tile.nids));
    std::vector<int32_t>& used = pc.ends_used;
    if (tab.size() < nh) tab.resize(nh, SilEnd{0, 0, 0, -1, -1, 0});  // the first nh slots are used
    int32_t nused = 0;  // the filled slots: used[0 .. nused)
    if (used.size() < 2 * size_t(ns - neh)) used.resize(4 * size_t(ns - neh));
    std::vector<int32_t>& eslot = pc.eslot;
    eslot.assign(2 * size_t(ns), -1);
    auto bits = [](double x) {
      uint64_t u;
      x += 0.0;  // -0 as +0 (same() counts them equal)
      std::memcpy(&u, &x, sizeof(u));
      return u;
    };
    auto add = [&](V3<T> x3, int32_t id, int32_t e) {
      const double x = double(x3.x), y = double(x3.y), z = double(x3.z);
      if (by_id) {  // the slot's update by selects, not branches (the position is not read by id)
        SilEnd& t = tab[size_t(id)];
        eslot[size_t(e)] = id;
        const int32_t n0 = t.n;
        const bool first = n0 == 0;
        used[size_t(nused)] = id;
        nused += int32_t(first);
        t.e = first ? e : t.e;
        t.e2 = first ? -1 : (n0 == 1 ? e : t.e2);
        t.n = n0 + 1;
        return;
      }
      uint64_t h = bits(x) * 0x9E3779B97F4A7C15ull ^ bits(y) * 0xC2B2AE3D27D4EB4Full ^ bits(z) * 0x165667B19E3779F9ull;
      h ^= h >> 29;
      for (size_t k = size_t(h) & (nh - 1);; k = (k + 1) & (nh - 1)) {
        SilEnd& t = tab[k];
        if (t.n == 0) {
          t = SilEnd{x, y, z, e, -1, 1};
          used[size_t(nused++)] = int32_t(k);
          eslot[size_t(e)] = int32_t(k);
          return;
        }
        if (t.x == x && t.y == y && t.z == z) {
          if (t.n == 1) t.e2 = e;
          t.n++;
          eslot[size_t(e)] = int32_t(k);
          return;
        }
      }
    };
    for (int i = neh; i < ns; i++) {
      const SSeg<T>& s = segs[size_t(i)];
      if (s.on_a < 0) add(s.x3a, s.ia, 2 * i);
      if (s.on_b < 0) add(s.x3b, s.ib, 2 * i + 1);
    }
    // The filled slots only (each slot's links are its own: the order does not matter), each
    // emptied after (the slots of 3 .. kSilFan ends once their rays are linked below).
    std::vector<int32_t>& fan = pc.fan;
    fan.clear();
    for (int32_t q = 0; q < nused; q++) {
      SilEnd& t = tab[size_t(used[size_t(q)])];
      if (t.n == 2 && t.e / 2 != t.e2 / 2) {
        const int32_t ea = t.e, eb = t.e2;
        const SSeg<T>& sa = segs[size_t(ea / 2)];
        const SSeg<T>& sb = segs[size_t(eb / 2)];
        // Each far end clearly off the other's line.
        const SilHot<T>& ha = hot[ea / 2];
        const SilHot<T>& hb = hot[eb / 2];
        const typename Cov::At fa{ea % 2 ? ha.ra : ha.rb, ea % 2 ? ha.la : ha.lb};  // cov.at(sa's far end)
        const typename Cov::At fb{eb % 2 ? hb.ra : hb.rb, eb % 2 ? hb.la : hb.lb};
        if (cov.side_of(fa, sb) != 0 && cov.side_of(fb, sa) != 0) {
          link[size_t(ea)] = eb, link[size_t(eb)] = ea;
          if (all_ids) {
            const bool a_in_b = (ha.ia == hb.ia || ha.ia == hb.ib) && (ha.ib == hb.ia || ha.ib == hb.ib);
            const bool b_in_a = (hb.ia == ha.ia || hb.ia == ha.ib) && (hb.ib == ha.ia || hb.ib == ha.ib);
            if (!a_in_b && !b_in_a) unpaired[size_t(ea)] = eb / 2, unpaired[size_t(eb)] = ea / 2;
          }
        }
      }
      if (t.n >= 3 && t.n <= kSilFan) {
        t.e2 = int32_t(fan.size());  // the slot's number among the fans
        fan.push_back(used[size_t(q)]);
      } else {
        t.n = 0;
      }
    }
    if (!fan.empty()) {
      std::vector<int32_t>& fe = pc.fan_ends;
      std::vector<int32_t>& fn = pc.fan_n;
      fe.resize(fan.size() * kSilFan);
      fn.assign(fan.size(), 0);
      for (int32_t x = 2 * neh; x < 2 * ns; x++) {
        const int32_t sl = eslot[size_t(x)];
        if (sl < 0 || tab[size_t(sl)].n == 0) continue;
        const int32_t m = tab[size_t(sl)].e2;
        fe[size_t(m) * kSilFan + size_t(fn[size_t(m)]++)] = x;
      }
      // Whether ray y lies less than a half turn on from ray x about v - p (+1), more (-1), or
      // too close to call (0): the side of y's far end of n_x = -own_x at x's end a, +own_x at b.
      auto turn = [&](int32_t x, int32_t y) {
        const SSeg<T>& sy = segs[size_t(y / 2)];
        const int sd = cov.side_of(y % 2 ? sy.a : sy.b, segs[size_t(x / 2)]);
        return x % 2 ? sd : -sd;
      };
      for (size_t m = 0; m < fan.size(); m++) {
        int32_t* r = fe.data() + m * kSilFan;
        const int k = fn[m];
        tab[size_t(fan[m])].n = 0;
        // Ray r[0], then the rays less than a half turn on from it, then the others, each group
        // sorted by turn (insertion sort); every end a different segment's.
        int32_t up[kSilFan], lo[kSilFan];
        int nu = 0, nl = 0;
        bool ok = true;
        for (int a = 1; a < k && ok; a++) {
          for (int b = 0; b < a && ok; b++) ok = r[a] / 2 != r[b] / 2;
          const int o = turn(r[0], r[a]);
          ok = ok && o != 0;
          if (o > 0) up[nu++] = r[a];
          if (o < 0) lo[nl++] = r[a];
        }
        for (int g = 0; g < 2 && ok; g++) {
          int32_t* v = g == 0 ? up : lo;
          const int nv = g == 0 ? nu : nl;
          for (int a = 1; a < nv && ok; a++) {
            const int32_t x = v[a];
            int b = a - 1;
            for (; b >= 0; b--) {
              const int o = turn(v[b], x);
              if (o == 0) ok = false;
              if (o >= 0) break;
              v[b + 1] = v[b];
            }
            v[b + 1] = x;
          }
        }
        if (!ok) continue;
        int32_t seq[kSilFan];
        seq[0] = r[0];
        for (int a = 0; a < nu; a++) seq[1 + a] = up[a];
        for (int a = 0; a < nl; a++) seq[1 + nu + a] = lo[a];
        for (int a = 0; a < k; a++) {
          const int32_t x = seq[a], y = seq[(a + 1) % k];
          succ[size_t(x)] = y;
          pred[size_t(y)] = x;
        }
      }
    }
  }
  // Per contour segment: its first and last pieces of positive length (kf, kl, positions in
  // ord once its breakpoints are sorted; kf = -1: none, kUnsorted: not sorted yet), their ends
  // in t (pends: first piece's, then last piece's), the sum of the jumps of C from the first
  // to the last (sj) and of the negative ones among them (sneg).
  constexpr int32_t kUnsorted = -2;
  std::vector<int32_t>& kf = pc.kf;
  std::vector<int32_t>& kl = pc.kl;
  std::vector<int32_t>& sj = pc.sj;
  std::vector<int32_t>& sneg = pc.sneg;
  kf.assign(size_t(ns), -1);
  kl.assign(size_t(ns), -1);
  sj.assign(size_t(ns), 0);
  sneg.assign(size_t(ns), 0);
  if (pc.pends.size() < 4 * size_t(ns)) pc.pends.resize(8 * size_t(ns));
  double* const pends = pc.pends.data();
  // Every segment's breakpoints (its ends and its crossings, in w.sts / stc / std_ at
  // [boff[i], boff[i + 1])), in the order of their t in w.sord (indices into those arrays).
  std::vector<int32_t>& boff = pc.boff;
  std::vector<int32_t>& ord = w.sord;
  boff.assign(size_t(ns) + 1, 0);
  // The breakpoints in use are [0, nb) of ts, tc, td and ord, which are grown (never shrunk)
  // before each segment to hold its ends and one crossing per candidate.
  int32_t nb = 0;
  // An E_h edge is cut only where a contour segment was clipped at its plane: its crossing
  // candidates are those segments (in index order).
  pc.clipped.clear();
  for (int j = neh; j < ns; j++)
    if (segs[size_t(j)].on_a >= 0 || segs[size_t(j)].on_b >= 0) pc.clipped.push_back(j);
  int32_t npend = 0;  // pending crossings' entries in use
  if (G) {
    pc.gpos.assign(gs.begin(), gs.end() - 1);
    pc.phead.assign(size_t(ns), -1);
    pc.pnum.assign(size_t(ns), 0);
    pc.ptail.resize(size_t(ns));
    w.gcand.resize(size_t(ns));
  } else {
    pc.all.resize(size_t(ns));
    for (int j = 0; j < ns; j++) pc.all[size_t(j)] = j;
  }
  // The test of segment si against candidate j: false when the receiver falls back; a crossing
  // (a breakpoint of si) is handed to emit(t, code source, jump). `by_ids` (a std::true_type
  // or false_type): si and j are contour pieces and every contour piece has its mesh vertex
  // and its ends' position ids (the tests of va and ia below are known to pass).
  auto pair = [&](const int si, const int j, auto by_ids, auto emit) __attribute__((always_inline)) {
    const SSeg<T>& s = segs[size_t(si)];
    const SilHot<T>& hs = hot[si];
    const V3<T>& ap = hs.ra;  // s.a - p
    const V3<T>& d = hs.d;
    const double apn = hs.apn;
    const SSeg<T>& o = segs[size_t(j)];
    const SilHot<T>& ho = hot[j];
    if (decltype(by_ids)::value || (hs.va >= 0 && ho.va >= 0)) {
      // Common ends by their position ids where both have them (equal iff same()).
      const bool ids = decltype(by_ids)::value || (hs.ia >= 0 && ho.ia >= 0);
      const bool at_a = ids ? bool((hs.ia == ho.ia) | (hs.ia == ho.ib)) : (same(s.x3a, o.x3a) || same(s.x3a, o.x3b));
      const bool at_b = ids ? bool((hs.ib == ho.ia) | (hs.ib == ho.ib)) : (same(s.x3b, o.x3a) || same(s.x3b, o.x3b));
      if (at_a || at_b) {
        // Mesh edges with a common end meet there only, unless their projections overlap
        // along one line (p in the plane of both; or one edge twice, as at a non-manifold
        // edge): C beside them is then not what the crossings and the carry along chains
        // below make it. Too close to call.
        if (at_a && at_b) return false;
        const bool oa_at = ids ? ho.ia == (at_a ? hs.ia : hs.ib) : same(o.x3a, at_a ? s.x3a : s.x3b);
        // The ends picked by reference (an address select rather than a branch).
        const V3<T>& far = oa_at ? o.b : o.a;
        const V3<T>& at = at_a ? s.a : s.b;
        const V3<T>& other = at_a ? s.b : s.a;
        const typename Cov::At xf{oa_at ? ho.rb : ho.ra, oa_at ? ho.lb : ho.la};  // cov.at(far)
        if (cov.side_of(xf, s) == 0 && dot(far - at, other - at) > 0) return false;
        return true;
      }
    }
    if (!decltype(by_ids)::value && si < neh) {
      // An E_h edge: cut where a contour piece was clipped at its plane.
      const int pi = eh_plane[si];
      const bool at_a = o.on_a >= 0 && o.on_a == pi;
      const bool at_b = o.on_b >= 0 && o.on_b == pi;
      if (!at_a && !at_b) return true;
      const double g0 = dot(ap, ho.own), g1 = dot(d, ho.own);
      if (!(std::fabs(g1) > tol * ho.own_n * apn)) return false;
      const double t = -g0 / g1;
      if (!(t >= -1e-9 && t <= 1 + 1e-9)) return false;
      emit(T(std::min(1.0, std::max(0.0, t))), kSrcClipped - 2 * j - (at_a ? 0 : 1), g1 > 0 ? o.w : -o.w);
      return true;
    }
    if (!decltype(by_ids)::value && j < neh) return true;  // a contour piece ends on E_h's boundary, inside it otherwise
    const double on = ho.own_n * apn;
    const double g0 = dot(ap, ho.own), g1 = dot(d, ho.own);
    const double m = tol * on, g01 = g0 + g1;
    if ((g0 > m && g01 > m) || (g0 < -m && g01 < -m)) return true;  // s clearly on one side of o's plane
    const int s0 = Cov::sgn(g0, m), s1 = Cov::sgn(g01, m);
    if (s0 == 0 && s1 == 0) {
      // s along o's line (collinear contour edges, as on a straight crease): apart when o's
      // ends lie clearly beyond one end of s along it.
      const double dd = double(dot(d, d));
      const double ta = double(dot(o.a - s.a, d)) / dd, tb = double(dot(o.b - s.a, d)) / dd;
      return (ta < -1e-6 && tb < -1e-6) || (ta > 1 + 1e-6 && tb > 1 + 1e-6);
    }
    const int ca = cov.side_of(typename Cov::At{ho.ra, ho.la}, s), cb = cov.side_of(typename Cov::At{ho.rb, ho.lb}, s);
    if (ca == cb && ca != 0) return true;  // o on one side of s's line (s's end on o's line or not)
    if (s0 == 0 || s1 == 0) return false;
    if (ca == 0 || cb == 0) return false;
    emit(T(-g0 / g1), int32_t(j), s1 > 0 ? o.w : -o.w);  // into o's positive side: + W
    return true;
  };
  // Segment i's breakpoints [b0, b1) in the order of their t in ord. Up to 16 breakpoints
  // (nearly always) the insertion sort that std::sort runs on so few (the same comparisons, so
  // the same order for equal t), else std::sort.
  auto sort_breaks = [&](int32_t b0, int32_t b1) {
    const T* const tsp = ts.data();
    int32_t* const op = ord.data();
    for (int32_t k = b0; k < b1; k++) op[k] = k;
    if (b1 - b0 <= 16) {
      for (int32_t k = b0 + 1; k < b1; k++) {
        const int32_t v = op[k];
        const T tv = tsp[v];
        if (tv < tsp[op[b0]]) {
          for (int32_t x = k; x > b0; x--) op[x] = op[x - 1];
          op[b0] = v;
        } else {
          int32_t x = k;
          for (; tv < tsp[op[x - 1]]; x--) op[x] = op[x - 1];
          op[x] = v;
        }
      }
    } else {
      std::sort(op + b0, op + b1, [&](int32_t x, int32_t y) { return tsp[x] < tsp[y]; });
    }
  };
  // Contour segment i's first and last pieces of positive length from its sorted breakpoints.
  auto first_last = [&](int i, int32_t b0, int32_t b1) {
    const T* const tsp = ts.data();
    const int32_t* const tdp = td.data();
    const int32_t* const op = ord.data();
    int32_t f = -1, l = -1;
    for (int32_t k = b0; k + 1 < b1; k++) {
      if (!(tsp[op[k + 1]] > tsp[op[k]])) continue;
      if (f < 0) f = k;
      l = k;
    }
    int32_t sum = 0, neg = 0;
    for (int32_t k = f + 1; f >= 0 && k <= l; k++) sum += tdp[op[k]], neg += std::min(tdp[op[k]], 0);
    kf[size_t(i)] = f, kl[size_t(i)] = l, sj[size_t(i)] = sum, sneg[size_t(i)] = neg;
    if (f >= 0) {
      double* const pe = pends + 4 * i;
      pe[0] = double(tsp[op[f]]), pe[1] = double(tsp[op[f + 1]]), pe[2] = double(tsp[op[l]]), pe[3] = double(tsp[op[l + 1]]);
    }
  };
  for (int i = 0; i < ns; i++) {
    const int32_t b0 = nb;
    // Crossing candidates: every segment, or for a contour piece on the grid the pieces
    // registered in the cells its box meets whose boxes meet its box (in index order, as the
    // full loop visits them, and with the same box test).
    const bool listed = G && i >= neh;
    // Boxes apart: no crossing (tested first: the cheaper filter).
    const SilBox bi = bx[i];
    auto apart = [&](int j) { return sil_apart(bi, bx[j]); };
    if (listed) {
      // A pair is a candidate for both pieces (the relation is symmetric: a common cell, boxes
      // meeting), so each cell's pieces (in increasing order) are gathered from only past the
      // piece itself, and both tests of a pair are made at the turn of its lower piece i: i's
      // crossing is its breakpoint now, the higher piece j's waits in j's pending list (filled
      // in increasing order of i, as the pieces come). A piece's breakpoints are in the order
      // of its candidates (its ends, the pending ones, then the higher ones, gathered and sorted).
      int32_t* up = w.gcand.data();  // ns entries: each piece at most once
      int ncand = 0;
      stamp++;
      if (all_ids) {
        // The pieces linked to i at a common end (above): their boxes meet there, and both far
        // ends lie clearly off the other's line, so where they share no other end both crossing
        // tests of the pair return true without a breakpoint. They are not gathered.
        for (int e = 0; e < 2; e++) {
          const int32_t o = unpaired[size_t(2 * i + e)];
          if (o >= 0) stamp_of[size_t(o)] = stamp;
        }
      }
      const int32_t* r = w.gcells.data() + 4 * (i - neh);
      for (int iy = r[2]; iy <= r[3]; iy++)
        for (int ix = r[0]; ix <= r[1]; ix++) {
          const int cell = iy * G + ix;
          const int32_t e = gs[size_t(cell + 1)];
          // Every piece registered here visits this cell in increasing order, each moving gpos
          // past itself: gpos is at i.
          const int32_t k0 = pc.gpos[size_t(cell)] + 1;
          pc.gpos[size_t(cell)] = k0;
          int32_t k = k0;
          for (; k < e; k++) {  // kept: seen first here and boxes meeting (written, counted when kept)
            const int32_t j = gi[size_t(k)];
            if (stamp_of[size_t(j)] == stamp) continue;
            stamp_of[size_t(j)] = stamp;
            up[ncand] = j;
            ncand += int(!apart(j));
          }
        }
      // (distinct values: any sort gives this order; insertion sort for the few there nearly always are)
      if (ncand <= 16) {
        for (int x = 1; x < ncand; x++) {
          const int32_t v = up[x];
          int y = x;
          for (; y > 0 && up[y - 1] > v; y--) up[y] = up[y - 1];
          up[y] = v;
        }
      } else {
        std::sort(up, up + ncand);
      }
      const size_t need = size_t(nb) + 2 + size_t(pc.pnum[size_t(i)]) + size_t(ncand);
      if (ts.size() < need) {
        const size_t m = std::max(need, 2 * ts.size());
        ts.resize(m), tc.resize(m), td.resize(m), ord.resize(m);
      }
      if (pc.pt.size() < size_t(npend) + size_t(ncand)) {  // (grown by doubling)
        const size_t m = 2 * (size_t(npend) + size_t(ncand));
        pc.pt.resize(m), pc.psrc.resize(m), pc.ptd.resize(m), pc.pnext.resize(m);
      }
      T* const tsp = ts.data();
      int32_t* const tcp = tc.data();
      int32_t* const tdp = td.data();
      tsp[nb] = 0, tcp[nb] = kSrcA, tdp[nb] = 0, nb++;
      tsp[nb] = 1, tcp[nb] = kSrcB, tdp[nb] = 0, nb++;
      for (int32_t x = pc.phead[size_t(i)]; x >= 0; x = pc.pnext[size_t(x)])
        tsp[nb] = T(pc.pt[size_t(x)]), tcp[nb] = pc.psrc[size_t(x)], tdp[nb] = pc.ptd[size_t(x)], nb++;
      auto own = [&](T t, int32_t src, int32_t jump) { tsp[nb] = t, tcp[nb] = src, tdp[nb] = jump, nb++; };
      int32_t j = -1;
      auto pend = [&](T t, int32_t src, int32_t jump) {
        const int32_t x = npend++;
        pc.pt[size_t(x)] = double(t), pc.psrc[size_t(x)] = src, pc.ptd[size_t(x)] = jump, pc.pnext[size_t(x)] = -1;
        if (pc.phead[size_t(j)] < 0) {
          pc.phead[size_t(j)] = x;
        } else {
          pc.pnext[size_t(pc.ptail[size_t(j)])] = x;
        }
        pc.ptail[size_t(j)] = x;
        pc.pnum[size_t(j)]++;
      };
      if (all_ids) {
        for (int c = 0; c < ncand; c++) {
          j = up[c];
          if (!pair(i, j, std::true_type(), own) || !pair(j, i, std::true_type(), pend)) return kFallback;
        }
      } else {
        for (int c = 0; c < ncand; c++) {
          j = up[c];
          if (!pair(i, j, std::false_type(), own) || !pair(j, i, std::false_type(), pend)) return kFallback;
        }
      }
    } else {
      const int32_t* js = i < neh ? pc.clipped.data() : pc.all.data();
      const int nj = i < neh ? int(pc.clipped.size()) : ns;
      if (ts.size() < size_t(nb) + 2 + size_t(nj)) {
        const size_t m = std::max(size_t(nb) + 2 + size_t(nj), 2 * ts.size());
        ts.resize(m), tc.resize(m), td.resize(m), ord.resize(m);
      }
      T* const tsp = ts.data();
      int32_t* const tcp = tc.data();
      int32_t* const tdp = td.data();
      tsp[nb] = 0, tcp[nb] = kSrcA, tdp[nb] = 0, nb++;
      tsp[nb] = 1, tcp[nb] = kSrcB, tdp[nb] = 0, nb++;
      auto own = [&](T t, int32_t src, int32_t jump) { tsp[nb] = t, tcp[nb] = src, tdp[nb] = jump, nb++; };
      for (int jj = 0; jj < nj; jj++) {
        const int j = js[jj];
        if (j == i) continue;
        if (i < neh && j < neh) continue;  // E_h's edges meet at its vertices only
        if (i >= neh && j >= neh && apart(j)) continue;
        if (!pair(i, j, std::false_type(), own)) return kFallback;
      }
    }
    const T* const tsp = ts.data();
    const int32_t* const tdp = td.data();
    const int32_t b1 = nb;
    int32_t* const op = ord.data();
    boff[size_t(i) + 1] = b1;
    if (b1 - b0 == 2) {  // its ends only (t = 0, then 1): one piece, no jump
      op[b0] = b0, op[b0 + 1] = b0 + 1;
      if (i >= neh) {
        kf[size_t(i)] = kl[size_t(i)] = b0;
        double* const pe = pends + 4 * i;
        pe[0] = pe[2] = double(tsp[b0]), pe[1] = pe[3] = double(tsp[b0 + 1]);
      }
      continue;
    }
    if (i < neh) {
      sort_breaks(b0, b1);
      continue;
    }
    // A contour segment's crossings lie in [0, 1] (t = -g0 / g1 with g0 and g0 + g1 of opposite
    // signs), after its ends (t = 0, then 1): its first piece ends at the least t > 0, its last
    // starts at the greatest t < 1, and the jumps between them are those at 0 < t < 1, whatever
    // their order. The breakpoints are sorted only where the runs need them (below).
    T t2 = 1, tl = 0;
    int32_t sum = 0, neg = 0;
    bool in01 = true;
    for (int32_t k = b0 + 2; k < b1; k++) {
      const T t = tsp[k];
      in01 = in01 && t >= 0 && t <= 1;
      const bool inner = t > 0 && t < 1;
      const int32_t jump = inner ? tdp[k] : 0;
      sum += jump, neg += std::min(jump, 0);
      t2 = inner && t < t2 ? t : t2;
      tl = inner && t > tl ? t : tl;
    }
    if (in01) {
      kf[size_t(i)] = kl[size_t(i)] = kUnsorted;
      double* const pe = pends + 4 * i;
      pe[0] = 0, pe[1] = double(t2), pe[2] = double(tl), pe[3] = 1;
      sj[size_t(i)] = sum, sneg[size_t(i)] = neg;
    } else {  // (not met: every crossing's t is in [0, 1]) sorted now
      sort_breaks(b0, b1);
      first_last(i, b0, b1);
    }
  }
  // C beside every contour segment's first piece on q0's side (cf), from one coverage query per
  // chain of contour segments and carried along the chain. Where exactly two contour segments
  // meet at an unclipped end v (the projection of one mesh vertex; no other piece passes through
  // v, or a crossing test with it would have been too close to call), C near v is constant in
  // each of the two sectors the segments' rays r_i, r_j from v bound. With n_i the normal of the
  // plane through p, v and r_i's far end (n_i = cross(v - p, x_i - p)), the side just beyond r_i
  // in n_i's direction and the side just before r_j against n_j's are the same sector: seen
  // along v - p, turning from r_i in the positive sense enters the sector that turning from r_j
  // in the negative sense enters. own = edge_plane(p, a, b) points along -cross(a - p, b - p), so
  // n_i is -own_i when v is i's end a and +own_i when v is its end b: C on both sides of j near v
  // follows from C on both sides of i there without a geometric test. Both far ends clearly off
  // the other segment's line (the sectors not thin), both jumps consistent, and where a chain
  // closes the carried value equal to the one it meets; else the receiver falls back.
  // Where k = 3 .. kSilFan ends meet at v (the contour folding through v, common on scans), the
  // rays are sorted by angle about v - p (ray y lies less than a half turn on from ray x when y's
  // far end lies on n_x's positive side): the sector just beyond each ray along its n is the one
  // just before the next ray against the next one's n, so C on both sides of the next ray follows
  // from C beyond this one and the next one's own jump (+W across own, -W across n = -own), and
  // C on both sides of the previous ray from C before this one. Every far end clearly off the
  // first ray's line and every comparison of the sort clear, else these rays are not linked;
  // going round v the carried values must close (the jumps sum to 0), else the receiver falls back.
  std::vector<int32_t>& cf = pc.cf;
  cf.assign(size_t(ns), Cov::kNone);
  // C at point m of contour piece `skip` on q0's side of it (skip = -1: a point of E_h's boundary),
  // from a contour piece whose C is known already, registered in m's cell or in the nearest cells
  // of its row holding pieces (SilCoverage::coverage_from): from the midpoint of
  // its first or last piece, where C on its q0 side is cf or cf + sj (each a sum of all the jumps
  // before it, whatever the order of close breakpoints). kNone when none serves; the caller then
  // takes the path from q0 through the grid (SilCoverage::coverage_at, coverage_eh).
  auto near = [&](V3<T> m, int skip) -> int {
    if (!G) return Cov::kNone;
    double um, vm;
    cov.uv(m, um, vm);
    if (!cov.on_grid(um, vm)) return Cov::kNone;
    const int iy = cov.cell_of(vm, cov.vmin, cov.dv), ix = cov.cell_of(um, cov.umin, cov.du);
    int tries = 0;
    // The pieces of m's cell, then of the nearest cells of its row holding pieces.
    for (int dir = 0; dir < 3 && tries < kSilNearTries; dir++) {
      int kx = ix;
      if (dir > 0) {
        const int step = dir == 1 ? -1 : 1;
        for (kx = ix + step; kx >= 0 && kx < G && !cov.held(iy * G + kx); kx += step) {
        }
        if (kx < 0 || kx >= G) continue;
      }
      const int cell = iy * G + kx;
      for (int32_t x = gs[size_t(cell)]; x < gs[size_t(cell) + 1] && tries < kSilNearTries; x++) {
        const int k = gi[size_t(x)];
        if (k == skip || cf[size_t(k)] == Cov::kNone) continue;
        tries++;
        const SSeg<T>& sk = segs[size_t(k)];
        for (int e = 0; e < 2; e++) {
          const double ua = pends[4 * k + 2 * e], ub = pends[4 * k + 2 * e + 1];
          const V3<T> mk = sk.a + (0.5 * (ua + ub)) * (sk.b - sk.a);
          const int c = cov.coverage_from(m, skip, mk, k, e ? cf[size_t(k)] + sj[size_t(k)] : cf[size_t(k)]);
          if (c != Cov::kNone) return c;
        }
      }
    }
    return Cov::kNone;
  };
  {
    // The segments whose links are still to follow (each enters once: when its cf is set).
    if (pc.todo.size() < size_t(ns)) pc.todo.resize(2 * size_t(ns));
    int32_t* const todo = pc.todo.data();
    int ntodo = 0;
    for (int i0 = neh; i0 < ns; i0++) {
      if (kf[size_t(i0)] == -1 || cf[size_t(i0)] != Cov::kNone) continue;
      {
        // C at the midpoint of i0's first piece: from a known piece near it, else through the grid.
        const SSeg<T>& s = segs[size_t(i0)];
        const double ta = pends[4 * i0], tb = pends[4 * i0 + 1];
        const V3<T> m = s.a + (0.5 * (ta + tb)) * (s.b - s.a);
        int full = near(m, i0);
        if (full == Cov::kNone) full = cov.coverage_at(m, i0);
        if (full == Cov::kNone) return kFallback;
        cf[size_t(i0)] = full;
      }
      // C carried to segment j's reference point: taken (and j's links followed) the first time,
      // and equal to it every later time, else the receiver falls back.
      auto carry = [&](int j, int cj) {
        if (cf[size_t(j)] != Cov::kNone) return cf[size_t(j)] == cj;
        cf[size_t(j)] = cj;
        todo[ntodo++] = j;
        return true;
      };
      todo[ntodo++] = i0;
      while (ntodo) {
        const int i = todo[--ntodo];
        const SSeg<T>& s = segs[size_t(i)];
        for (int e = 0; e < 2; e++) {
          const int32_t o = link[size_t(2 * i + e)];
          if (o < 0 && succ[size_t(2 * i + e)] < 0) continue;
          // C on q0's side near v, on the positive and negative sides of i's own plane there.
          const int c = e == 0 ? cf[size_t(i)] : cf[size_t(i)] + sj[size_t(i)];
          // (The data-dependent choices below as integer arithmetic, not branches.)
          const int qi = int(s.q0s > 0);
          const int cpos = c + (1 - qi) * s.w, cneg = c - qi * s.w;  // s.q0s > 0 ? c : c + w, ? c - w : c
          const int ca = e == 0 ? cneg : cpos, cb = e == 0 ? cpos : cneg;  // C beyond r_i along n_i, and before it
          if (o < 0) {
            // The next ray (C beyond r_i is before it) and the previous one (C before r_i is beyond it).
            for (int g = 0; g < 2; g++) {
              const int32_t x = g == 0 ? succ[size_t(2 * i + e)] : pred[size_t(2 * i + e)];
              const int j = x / 2, ej = x % 2;
              const SSeg<T>& t = segs[size_t(j)];
              if (t.q0s == 0) return kFallback;
              const int jump = ej ? t.w : -t.w;  // C's jump across r_j along n_j
              const int cplus = g == 0 ? ca + jump : cb, cminus = g == 0 ? ca : cb - jump;  // along n_j, against it
              const int jpos = ej ? cplus : cminus, jneg = ej ? cminus : cplus;
              const int cv = t.q0s > 0 ? jpos : jneg;
              const int cj = cv - ej * sj[size_t(j)];
              if (!carry(j, cj)) return kFallback;
            }
            continue;
          }
          const int j = o / 2, ej = o % 2;
          const SSeg<T>& t = segs[size_t(j)];
          const int jpos = ca + ej * (cb - ca), jneg = cb + ej * (ca - cb);  // n_j = -own_j at j's end a (ej = 0)
          if (jpos - jneg != t.w || t.q0s == 0) return kFallback;
          const int cv = jneg + int(t.q0s > 0) * (jpos - jneg);  // t.q0s > 0 ? jpos : jneg
          const int cj = cv - ej * sj[size_t(j)];
          if (!carry(j, cj)) return kFallback;
        }
      }
    }
  }
  // The runs: every segment's pieces classified in index order; a kept piece extends the current run.
  bool contour_runs = false;
  for (int i = 0; i < ns; i++) {
    const SSeg<T>& s = segs[size_t(i)];
    if (i >= neh) {
      // A contour segment: its pieces from the first to the last of positive length (those
      // before and after have none), C from cf there; the open run's ends by breakpoint.
      if (kf[size_t(i)] == -1) continue;
      int c = cf[size_t(i)];
      if (c == Cov::kNone || s.q0s == 0) return kFallback;
      const int qi = int(s.q0s > 0);
      // C on s's lower side is c - lo at its first piece and never less than c + sneg - lo
      // after it: at least 1 there, every piece is covered on both sides (no run, and none
      // of the checks below can fail), and its breakpoints need no order.
      const int lo = qi ? std::max(0, s.w) : std::max(0, -s.w);
      if (c + sneg[size_t(i)] - lo >= 1) continue;
      if (kf[size_t(i)] == kUnsorted) {
        sort_breaks(boff[size_t(i)], boff[size_t(i) + 1]);
        first_last(i, boff[size_t(i)], boff[size_t(i) + 1]);
      }
      const int32_t f = kf[size_t(i)], l = kl[size_t(i)];
      if (f < 0) continue;
      int run_dir = 0;
      int32_t rs = 0, re = 0;
      for (int32_t k = f; k <= l; k++) {
        if (k > f) c += td[size_t(ord[size_t(k)])];
        if (!(ts[size_t(ord[size_t(k + 1)])] > ts[size_t(ord[size_t(k)])])) continue;
        const int cpos = c + (1 - qi) * s.w, cneg = c - qi * s.w;  // s.q0s > 0 ? c : c + w, ? c - w : c
        if (cpos < 0 || cneg < 0) return kFallback;
        int dir = 0;
        if ((cpos == 0) != (cneg == 0)) dir = cpos == 0 ? 1 : -1;  // R on the positive side: along own's edge
        if (dir != run_dir) {
          if (run_dir > 0) w.runs.push_back(Run{tc_code(s, rs), tc_code(s, re)});
          if (run_dir < 0) w.runs.push_back(Run{tc_code(s, re), tc_code(s, rs)});
          contour_runs = contour_runs || run_dir != 0;
          run_dir = dir;
          rs = ord[size_t(k)];
        }
        if (dir != 0) re = ord[size_t(k + 1)];
      }
      if (run_dir > 0) w.runs.push_back(Run{tc_code(s, rs), tc_code(s, re)});
      if (run_dir < 0) w.runs.push_back(Run{tc_code(s, re), tc_code(s, rs)});
      contour_runs = contour_runs || run_dir != 0;
      continue;
    }
    // An E_h edge.
    const int32_t b0 = boff[size_t(i)], b1 = boff[size_t(i) + 1];
    const V3<T> d = s.b - s.a;
    // Classify the pieces; a kept piece extends the current run.
    int run_dir = 0;  // +1: a run along s, -1: against it, 0: none open
    Code run_s{}, run_e{};
    auto close_run = [&]() {
      if (run_dir > 0) w.runs.push_back(Run{run_s, run_e});
      if (run_dir < 0) w.runs.push_back(Run{run_e, run_s});
      run_dir = 0;
    };
    // C beside s inside E_h: computed at the first piece, checked again at the last piece, and
    // carried across the breakpoints between.
    int c = Cov::kNone, last = -1;  // last: the last piece of positive length
    for (int32_t k = b0; k + 1 < b1; k++)
      if (ts[size_t(ord[size_t(k + 1)])] > ts[size_t(ord[size_t(k)])]) last = k;
    for (int32_t k = b0; k + 1 < b1; k++) {
      if (k > b0 && c != Cov::kNone) c += td[size_t(ord[size_t(k)])];
      const double ta = ts[size_t(ord[size_t(k)])], tb = ts[size_t(ord[size_t(k + 1)])];
      if (!(tb > ta)) continue;
      if (c == Cov::kNone || k == last) {
        const V3<T> m = s.a + (0.5 * (ta + tb)) * d;
        int full = near(m, -1);
        if (full == Cov::kNone) full = cov.coverage_eh(m);
        if (full == Cov::kNone || (c != Cov::kNone && full != c)) return kFallback;
        c = full;
      }
      if (c < 0) return kFallback;
      eh_any = eh_any || c == 0;
      eh_all = eh_all && c == 0;
      const int dir = c == 0 ? 1 : 0;
      if (dir != run_dir) {
        close_run();
        if (dir != 0) {
          run_dir = dir;
          run_s = tc_code(s, ord[size_t(k)]);
        }
      }
      if (dir != 0) run_e = tc_code(s, ord[size_t(k + 1)]);
    }
    close_run();
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
