// jaxshadow's shadow engine: umbra receivers of large meshes recognised before the silhouette
// path's contour work (part of `csrc/shadowc.cc`; see its header comment and silhouette.h).
//
// Certificate. Let Z be the faces of one connected component of the mesh (connected through the
// silhouette hierarchy's paired edges) and D the cone from one point c (the mean of Z's boundary
// vertices) over Z's boundary and non-manifold edge slots (the SEdges with g < 0): the triangles
// (c, a, b). Every paired edge is two face edges over the same segment (T-junction pieces over
// the same line intervals), so modulo 2 the boundary of Z is the sum of the unpaired slots, each
// vertex of that 1-cycle has even degree, and Z + D is a closed 2-cycle modulo 2 (D's sides
// through c cancel in pairs). A point x off Z + D has a parity: the number of faces of Z + D a
// ray from x crosses, modulo 2, the same for every ray in general position; a segment from a
// point of parity 1 to a point of parity 0 meets Z + D. (For a closed component D is empty and
// parity 1 is "inside".)
//
// Bodies: in planes x_a = z0 (a = 0, 1, 2; z0 midway between consecutive vertex coordinates of Z
// and c, so no vertex lies on the plane and every face that crosses it cuts it in one segment),
// the cross-section of Z + D is a set of segments, and a point of the plane off them has the
// parity of a ray within the plane (its crossings with the segments). A grid of the plane over the
// component's box marks the cells that a segment comes within `pad` of (touched); the parity of
// an untouched cell is counted along the row through its centre (a row where a segment's end lies
// within rounding of that line is left unknown); two adjacent untouched cells must agree (their
// union meets no segment), else the section is dropped. The untouched cells of parity 1 (closed
// squares off Z + D, all of parity 1) are the section's body P, kept as a summed table: whether a
// box of cells is all body costs four reads.
//
// Receiver p, polygon light L (vertices v_i; h(x) = ne . (x - e0) the height above the emitter
// plane towards the receivers), a convex piece L' of L (L itself, or a triangle of a fan of it):
// p and every vertex of L' strictly on opposite sides of P's plane, and the box of the crossings
// b_i of the segments p -> v_i (v_i now L''s vertices) with that plane in P (section_shows), or
// their convex hull Q clear of every cut segment with a point of Q in P (section_shows_exact: Q
// is connected and meets no segment, so its points share that point's parity 1; P then stands
// for Q below). The central projection from p of the convex L' onto the plane is the convex hull
// of the b_i, inside their box: every q in L' is p + s (b(q) - p) with b(q) in P. The silhouette path serves p only when
// every mesh vertex lies strictly between the emitter plane and p's level, and P (parity 1:
// inside the convex hull of Z + D) lies there too, so for q in L 0 = h(q) < h(b(q)) < h(p) and
// s > 1: b(q) lies on the segment p -> q. The segment b(q) -> q runs from parity 1 to parity 0 (q
// lies on the emitter plane, beyond every vertex of Z + D, and a ray from q away from the
// receivers meets nothing), so it meets Z + D; it misses D when h(b(q)) < min h(D's vertices) (h
// decreases from b(q) to q, and D lies in the convex hull of its vertices), which the test asks
// of the b_i (h is linear and b(q) is in their convex hull). When pieces shown so (through any
// sections) cover L, every ray from p to L meets a face of Z: for q off the measure-zero set of
// rays through edges of Z, at a face's interior, and the depth complexity C(q) >= 1
// (silhouette.h). With every light vertex above p's horizon by more than 1e-6 rad, no face that
// blocks such a ray hugs the horizon (polygon.h drops faces within kHorizonBand = 1e-7 rad of
// it). So p is umbra: the exact path's answer (its face path, where the silhouette path falls
// back, reports a light covered by several faces and by no single one as penumbra with an empty
// boundary: the same value, 0), reached without the contour, the coverage or any region. These
// are C&F §3.1.3's umbra volumes of the bodies P, tested in their dual form (the light seen
// through P from p) and for non-convex, open meshes through the parity of Z + D. The cells'
// test costs four reads; the segments' test reaches the cross-section's outline itself, where
// receivers near the umbra's boundary see the light (the cells a segment touches are no body).
// What neither shows is the gap between a cross-section and the mesh's silhouette from p (rays
// that graze the mesh between two planes): those receivers take the silhouette path.
//
// Rounding: the plane level is at least 1e-9 of the scene's size from every vertex coordinate
// (sections with a smaller gap are not built); cells are untouched by a margin of 1e-7 of the
// component's size, far above the rounding of the cut points (a few eps of the scene's size); the
// receiver's test asks every crossing to lie inside P, every side and the heights to be clear, by
// 1e-9 of the scene's size (a crossing's rounding is a few eps of it; the crossings' box is
// widened by that much before it is looked up in cells). A receiver within that of deciding
// takes the silhouette path, which stays the reference.
#ifndef JAXSHADOW_SHADOWC_UMBRA_SECTIONS_H_
#define JAXSHADOW_SHADOWC_UMBRA_SECTIONS_H_

#include <algorithm>
#include <limits>
#include <numeric>

#include "silhouette_types.h"

namespace jaxshadow_engine {

constexpr int64_t kSectionMinFaces = 64;  // components with fewer faces get no sections
constexpr int kSectionComponents = 8;     // at most this many components (the largest) get sections
constexpr int kSectionLevels = 24;        // planes per axis and component
constexpr int kSectionGrid = 96;          // cells along a section's longer side
constexpr int kSectionFanDepth = 2;       // levels of fans of the light tried

// A section: the plane x_axis = level and its grid of cells [u0 + i h, u0 + (i + 1) h] x [w0 + j h,
// w0 + (j + 1) h] (u = x_b, w = x_c; b = (axis + 1) % 3, c = (axis + 2) % 3), i < gu, j < gw; `sat`
// indexes InteriorSections::sat, the table of sums of its cells that are not bodies:
// sat[(j' (gu + 1) + i')] = the count over cells i < i', j < j'.
// `coff` indexes InteriorSections::cell_off, the cells' lists of the cut segments that touch them
// (cell i + j gu: cell_seg[cell_off[coff + c] .. cell_off[coff + c + 1]), indices into seg).
struct Section {
  int32_t comp, axis;
  double level, u0, w0, h;
  int32_t gu, gw;
  int64_t sat, coff;
};
// The bodies of an occluder set (built once per set, prepared.h) and per component the vertices
// of its cap D (none: a closed component).
struct InteriorSections {
  std::vector<Section> sections;
  std::vector<int32_t> sat;
  std::vector<double> seg;          // (u0, w0, u1, w1) per cut segment of every section
  std::vector<int32_t> cell_off;    // per section: gu gw + 1 offsets into cell_seg
  std::vector<int32_t> cell_seg;    // per touched cell: the segments that touch it
  std::vector<double> cap;          // (x, y, z) per cap vertex: the boundary slots' ends and c
  std::vector<int32_t> cap_off;     // per component: its cap vertices [cap_off[k], cap_off[k + 1])
  std::vector<double> box;          // per component: the box of its vertices (lo, hi)
  double scale = 0;                 // the largest coordinate magnitude of the faces
  bool ok = false;
};

// The bodies usable with one polygon light: their indices, the light's vertices, the lowest cap
// height per component (infinity: closed).
struct SectionCall {
  const InteriorSections* sec = nullptr;
  std::vector<int32_t> use;
  std::vector<double> lv, hcap;
  double ne[3] = {0, 0, 0}, e0[3] = {0, 0, 0}, nn = 0;
  int64_t K = 0;
  bool any = false;
  bool exact = true;  // section_shows_exact where section_shows fails
};

namespace sections_detail {

struct Seg {
  double u0, w0, u1, w1;
};

// The bodies of one section: `segs` the cross-section (plane coordinates u = x_b, w = x_c), the
// grid over [u0, u0 + gu h] x [w0, w0 + gw h]. False: the parities disagree (no bodies).
inline bool section_bodies(const std::vector<Seg>& segs, double u0, double w0, double h, int gu, int gw, double pad,
                           double tiny, int32_t comp, int axis, double level, InteriorSections& sec) {
  const size_t nc = size_t(gu) * size_t(gw);
  std::vector<uint8_t> touched(nc, 0);
  std::vector<std::pair<int32_t, int32_t>> reg;  // (cell, segment) for every cell a segment touches
  auto cell_u = [&](double u) { return std::max(0, std::min(gu - 1, int(std::floor((u - u0) / h)))); };
  auto cell_w = [&](double w) { return std::max(0, std::min(gw - 1, int(std::floor((w - w0) / h)))); };
  for (size_t k = 0; k < segs.size(); k++) {
    const Seg& s = segs[k];
    const double wlo = std::min(s.w0, s.w1) - pad, whi = std::max(s.w0, s.w1) + pad;
    if (whi < w0 || wlo > w0 + gw * h) continue;
    const int j0 = cell_w(wlo), j1 = cell_w(whi);
    for (int j = j0; j <= j1; j++) {
      // The segment's part within the row (padded), its u-range padded.
      double ta = 0, tb = 1;
      const double dw = s.w1 - s.w0;
      if (dw != 0) {
        ta = (w0 + j * h - pad - s.w0) / dw, tb = (w0 + (j + 1) * h + pad - s.w0) / dw;
        if (ta > tb) std::swap(ta, tb);
        ta = std::max(0.0, ta), tb = std::min(1.0, tb);
        if (ta > tb) ta = tb = std::min(1.0, std::max(0.0, ta));
      }
      const double ua = s.u0 + ta * (s.u1 - s.u0), ub = s.u0 + tb * (s.u1 - s.u0);
      const int i0 = cell_u(std::min(ua, ub) - pad), i1 = cell_u(std::max(ua, ub) + pad);
      for (int i = i0; i <= i1; i++) {
        touched[size_t(j) * size_t(gu) + size_t(i)] = 1;
        reg.push_back({j * gu + i, int32_t(k)});
      }
    }
  }
  // Parity of the untouched cells, row by row (2: unknown): the segments that reach a row's
  // centre line (within `tiny`) listed per row first.
  std::vector<int32_t> roff(size_t(gw) + 1, 0), rseg;
  auto rows_of = [&](const Seg& s, int& j0, int& j1) {
    j0 = std::max(0, int(std::ceil((std::min(s.w0, s.w1) - tiny - w0) / h - 0.5)));
    j1 = std::min(gw - 1, int(std::floor((std::max(s.w0, s.w1) + tiny - w0) / h - 0.5)));
  };
  for (const Seg& s : segs) {
    int j0, j1;
    rows_of(s, j0, j1);
    for (int j = j0; j <= j1; j++) roff[size_t(j) + 1]++;
  }
  for (int j = 0; j < gw; j++) roff[size_t(j) + 1] += roff[size_t(j)];
  rseg.resize(size_t(roff[size_t(gw)]));
  {
    std::vector<int32_t> fill(roff.begin(), roff.end() - 1);
    for (size_t k = 0; k < segs.size(); k++) {
      int j0, j1;
      rows_of(segs[k], j0, j1);
      for (int j = j0; j <= j1; j++) rseg[size_t(fill[size_t(j)]++)] = int32_t(k);
    }
  }
  std::vector<uint8_t> par(nc, 2);
  std::vector<double> xs;
  for (int j = 0; j < gw; j++) {
    const double line = w0 + (j + 0.5) * h;
    xs.clear();
    bool known = true;
    for (int32_t k = roff[size_t(j)]; k < roff[size_t(j) + 1]; k++) {
      const Seg& s = segs[size_t(rseg[size_t(k)])];
      const double d0 = s.w0 - line, d1 = s.w1 - line;
      if (std::fabs(d0) <= tiny || std::fabs(d1) <= tiny) {
        known = false;
        break;
      }
      if ((d0 > 0) != (d1 > 0)) xs.push_back(s.u0 + d0 / (d0 - d1) * (s.u1 - s.u0));
    }
    if (!known) continue;
    std::sort(xs.begin(), xs.end());
    for (int i = 0; i < gu; i++) {
      const size_t c = size_t(j) * size_t(gu) + size_t(i);
      if (touched[c]) continue;
      const double x = u0 + (i + 0.5) * h;
      const size_t beyond = size_t(xs.end() - std::upper_bound(xs.begin(), xs.end(), x));
      par[c] = uint8_t(beyond & 1);
    }
  }
  for (int j = 0; j < gw; j++)
    for (int i = 0; i < gu; i++) {
      const size_t c = size_t(j) * size_t(gu) + size_t(i);
      if (par[c] == 2) continue;
      if (i + 1 < gu && par[c + 1] != 2 && par[c + 1] != par[c]) return false;
      if (j + 1 < gw && par[c + size_t(gu)] != 2 && par[c + size_t(gu)] != par[c]) return false;
    }
  // The body: the untouched cells of parity 1; the summed table of the other cells.
  Section q;
  q.comp = comp, q.axis = axis, q.level = level, q.u0 = u0, q.w0 = w0, q.h = h, q.gu = gu, q.gw = gw;
  q.sat = int64_t(sec.sat.size());
  const size_t W = size_t(gu) + 1;
  sec.sat.resize(sec.sat.size() + W * (size_t(gw) + 1), 0);
  int32_t* t = sec.sat.data() + q.sat;
  int64_t any = 0;
  for (int j = 0; j < gw; j++)
    for (int i = 0; i < gu; i++) {
      const int32_t out = par[size_t(j) * size_t(gu) + size_t(i)] == 1 ? 0 : 1;
      any += 1 - out;
      t[(size_t(j) + 1) * W + size_t(i) + 1] = out + t[size_t(j) * W + size_t(i) + 1] + t[(size_t(j) + 1) * W + size_t(i)] - t[size_t(j) * W + size_t(i)];
    }
  if (any < 4) {
    sec.sat.resize(size_t(q.sat));
    return true;
  }
  // The cut segments by cell (a cell's list in segment order).
  const int32_t s0 = int32_t(sec.seg.size() / 4);
  for (const Seg& s : segs) sec.seg.insert(sec.seg.end(), {s.u0, s.w0, s.u1, s.w1});
  q.coff = int64_t(sec.cell_off.size());
  std::stable_sort(reg.begin(), reg.end(), [](const auto& x, const auto& y) { return x.first < y.first; });
  reg.erase(std::unique(reg.begin(), reg.end()), reg.end());
  size_t r = 0;
  for (size_t c = 0; c <= nc; c++) {
    sec.cell_off.push_back(int32_t(sec.cell_seg.size()));
    for (; c < nc && r < reg.size() && size_t(reg[r].first) == c; r++) sec.cell_seg.push_back(s0 + reg[r].second);
  }
  sec.sections.push_back(q);
  return true;
}

}  // namespace sections_detail

// The bodies of `occ` (after build_silhouette_tree: its edges name their faces by local index).
template <class T>
void build_interior_sections(const Occluders<T>& occ, const SilhouetteTree& st, InteriorSections& out) {
  using sections_detail::Seg;
  out = InteriorSections();
  if (!st.ok) return;
  const int64_t M = occ.M, Ko = occ.Ko;
  std::vector<int32_t> glob(size_t(M), -1);  // local face index -> face
  for (int64_t f = 0; f < M; f++) glob[size_t(st.floc[size_t(f)])] = int32_t(f);
  // Components through paired edges (union-find over local faces).
  const std::vector<int32_t> comp = face_components(st.edges, M);
  auto find = [&](int32_t x) { return comp[size_t(x)]; };
  std::vector<int32_t> root_size(size_t(M), 0);
  for (int64_t f = 0; f < M; f++) root_size[size_t(find(int32_t(f)))]++;
  std::vector<int32_t> roots;
  for (int64_t f = 0; f < M; f++)
    if (comp[size_t(f)] == f && root_size[size_t(f)] >= kSectionMinFaces) roots.push_back(int32_t(f));
  std::stable_sort(roots.begin(), roots.end(), [&](int32_t x, int32_t y) { return root_size[size_t(x)] > root_size[size_t(y)]; });
  if (roots.size() > size_t(kSectionComponents)) roots.resize(size_t(kSectionComponents));
  if (roots.empty()) return;
  out.scale = st.scale;
  const double S = st.scale + 1e-300;
  auto pt = [&](int64_t f, int64_t i) {
    const V3<T> x = occ.vert(f, i);
    return V3<double>{double(x.x), double(x.y), double(x.z)};
  };
  auto coord = [](const V3<double>& x, int a) { return a == 0 ? x.x : (a == 1 ? x.y : x.z); };
  std::vector<int32_t> faces;
  std::vector<V3<double>> bnd;  // the component's unpaired slots' ends, two per slot
  std::vector<double> xs;
  out.cap_off.push_back(0);
  for (size_t k = 0; k < roots.size(); k++) {
    const int32_t root = roots[k];
    faces.clear();
    bnd.clear();
    for (int64_t l = 0; l < M; l++)
      if (find(int32_t(l)) == root) faces.push_back(glob[size_t(l)]);
    for (const SEdge& e : st.edges)
      if (e.g < 0 && find(e.f) == root) {
        const V3<T> a = occ.vref(e.ra), b = occ.vref(e.rb);
        bnd.push_back(V3<double>{double(a.x), double(a.y), double(a.z)});
        bnd.push_back(V3<double>{double(b.x), double(b.y), double(b.z)});
      }
    V3<double> c{0, 0, 0};
    for (const V3<double>& x : bnd) c = c + (1.0 / double(bnd.size())) * x;
    for (const V3<double>& x : bnd) out.cap.insert(out.cap.end(), {x.x, x.y, x.z});
    if (!bnd.empty()) out.cap.insert(out.cap.end(), {c.x, c.y, c.z});
    out.cap_off.push_back(int32_t(out.cap.size() / 3));
    double lo[3], hi[3];
    for (int d = 0; d < 3; d++) lo[d] = std::numeric_limits<double>::infinity(), hi[d] = -lo[d];
    for (const int32_t f : faces)
      for (int64_t i = 0; i < Ko; i++) {
        const V3<double> x = pt(f, i);
        for (int d = 0; d < 3; d++) lo[d] = std::min(lo[d], coord(x, d)), hi[d] = std::max(hi[d], coord(x, d));
      }
    out.box.insert(out.box.end(), {lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]});
    const double ext = std::max(hi[0] - lo[0], std::max(hi[1] - lo[1], hi[2] - lo[2]));
    if (!(ext > 1e-6 * S) || !std::isfinite(ext)) continue;
    const double pad = 1e-7 * ext + 1e3 * 2.220446049250313e-16 * S, tiny = 1e-10 * ext + 1e3 * 2.220446049250313e-16 * S;
    for (int a = 0; a < 3; a++) {
      const int b = (a + 1) % 3, cc = (a + 2) % 3;
      const double hcell = std::max(hi[b] - lo[b], hi[cc] - lo[cc]) / kSectionGrid;
      if (!(hcell > 0)) continue;
      const int gu = std::max(1, int(std::ceil((hi[b] - lo[b]) / hcell))), gw = std::max(1, int(std::ceil((hi[cc] - lo[cc]) / hcell)));
      // The levels: per target, the largest vertex coordinate (of Z and c) at or below it and the
      // smallest above it, from one pass that buckets each coordinate by the targets below it;
      // the level midway, where that gap is clear.
      constexpr int L = kSectionLevels;
      double tg[L], bmax[L + 1], bmin[L + 1];
      for (int l = 0; l < L; l++) tg[l] = lo[a] + (l + 0.5) / L * (hi[a] - lo[a]);
      for (int l = 0; l <= L; l++) bmax[l] = -std::numeric_limits<double>::infinity(), bmin[l] = std::numeric_limits<double>::infinity();
      auto note = [&](double x) {
        const int j = int(std::lower_bound(tg, tg + L, x) - tg);  // targets below x
        bmax[j] = std::max(bmax[j], x), bmin[j] = std::min(bmin[j], x);
      };
      for (const int32_t f : faces)
        for (int64_t i = 0; i < Ko; i++) note(coord(pt(f, i), a));
      if (!bnd.empty()) note(coord(c, a));
      double above[L + 1];
      above[L] = bmin[L];
      for (int l = L - 1; l >= 0; l--) above[l] = std::min(above[l + 1], bmin[l]);
      xs.clear();  // the levels, increasing
      double below = -std::numeric_limits<double>::infinity();
      for (int l = 0; l < L; l++) {
        below = std::max(below, bmax[l]);
        const double up = above[l + 1];
        if (!(std::isfinite(below) && std::isfinite(up))) continue;
        const double z0 = 0.5 * (below + up);
        if (up - z0 > 1e-9 * S && z0 - below > 1e-9 * S && (xs.empty() || z0 > xs.back())) xs.push_back(z0);
      }
      const size_t nl = xs.size();
      std::vector<std::vector<Seg>> lsegs(nl);
      std::vector<uint8_t> lok(nl, 1);
      // The cut of a face (or cap triangle) with every level between its lowest and highest
      // vertex: one segment per level, each cut point computed from the edge's ends in one order
      // (a shared edge cuts at the same point); more than two crossings drop the level.
      auto cut = [&](const V3<double>* v, int n) {
        double mn = std::numeric_limits<double>::infinity(), mx = -mn;
        for (int i = 0; i < n; i++) mn = std::min(mn, coord(v[i], a)), mx = std::max(mx, coord(v[i], a));
        const size_t l0 = size_t(std::upper_bound(xs.begin(), xs.end(), mn) - xs.begin());
        const size_t l1 = size_t(std::lower_bound(xs.begin(), xs.end(), mx) - xs.begin());
        for (size_t l = l0; l < l1; l++) {
          const double z0 = xs[l];
          double cu[2], cw[2];
          int m = 0;
          for (int i = 0; i < n; i++) {
            V3<double> x = v[i], y = v[(i + 1) % n];
            if (same(x, y) || (coord(x, a) > z0) == (coord(y, a) > z0)) continue;
            if (coord(x, a) > z0) std::swap(x, y);
            if (m == 2) {
              m = 3;
              break;
            }
            const double hx = coord(x, a) - z0, hy = coord(y, a) - z0, t = hx / (hx - hy);
            cu[m] = coord(x, b) + t * (coord(y, b) - coord(x, b));
            cw[m] = coord(x, cc) + t * (coord(y, cc) - coord(x, cc));
            m++;
          }
          if (m == 2)
            lsegs[l].push_back(Seg{cu[0], cw[0], cu[1], cw[1]});
          else if (m != 0)
            lok[l] = 0;
        }
      };
      V3<double> poly[64];
      for (const int32_t f : faces) {
        for (int64_t i = 0; i < Ko; i++) poly[i] = pt(f, i);
        cut(poly, int(Ko));
      }
      for (size_t s = 0; s + 1 < bnd.size(); s += 2) {
        const V3<double> tri[3] = {c, bnd[s], bnd[s + 1]};
        cut(tri, 3);
      }
      for (size_t l = 0; l < nl; l++)
        if (lok[l]) sections_detail::section_bodies(lsegs[l], lo[b], lo[cc], hcell, gu, gw, pad, tiny, int32_t(k), a, xs[l], out);
    }
  }
  out.ok = !out.sections.empty();
}

// The bodies usable with the light (`lv`: K vertices in double, `ne` its Newell normal towards
// the receivers): those whose plane has every light vertex clearly on one side.
inline void prepare_sections(SectionCall& sc, const InteriorSections* sec, const double* lv, int64_t K, const double* ne) {
  sc = SectionCall();
  if (!sec || !sec->ok || K < 3 || K > 64) return;
  sc.sec = sec;
  sc.K = K;
  sc.lv.assign(lv, lv + 3 * K);
  for (int d = 0; d < 3; d++) sc.ne[d] = ne[d], sc.e0[d] = lv[d];
  sc.nn = std::sqrt(ne[0] * ne[0] + ne[1] * ne[1] + ne[2] * ne[2]);
  double S = sec->scale;
  for (int64_t i = 0; i < 3 * K; i++) S = std::max(S, std::fabs(lv[i]));
  if (!(sc.nn > 0) || !std::isfinite(S)) return;
  const double m = 1e-9 * S;
  const size_t C = sec->cap_off.size() - 1;
  sc.hcap.assign(C, std::numeric_limits<double>::infinity());
  for (size_t k = 0; k < C; k++)
    for (int32_t v = sec->cap_off[k]; v < sec->cap_off[k + 1]; v++) {
      const double* x = sec->cap.data() + 3 * v;
      const double h = ne[0] * (x[0] - lv[0]) + ne[1] * (x[1] - lv[1]) + ne[2] * (x[2] - lv[2]);
      sc.hcap[k] = std::min(sc.hcap[k], h);
    }
  for (size_t j = 0; j < sec->sections.size(); j++) {
    const Section& r = sec->sections[j];
    bool pos = true, neg = true;
    for (int64_t i = 0; i < K; i++) {
      const double d = lv[3 * i + r.axis] - r.level;
      pos = pos && d > m;
      neg = neg && d < -m;
    }
    if (pos || neg) sc.use.push_back(int32_t(j));
  }
  sc.any = !sc.use.empty();
}

// The crossings b_i of section r's plane with the segments from p (`pd`) to the points of the
// convex polygon x (m points), for section_shows and section_shows_exact: false unless the
// polygon's points lie clearly (`mm`) on the far side of the plane from p and the b_i below the
// cap's lowest height by `mh`; else their box, widened by `mm`, in r's cell units (`f`: u0, u1,
// w0, w1), inside the grid. With `bu`, `bw` (m each): the b_i's coordinates and their centroid
// (`cu`, `cw`).
inline bool section_crossings(const SectionCall& sc, const Section& r, const double* pd, const double* x, int m, double mm,
                              double mh, double* f, double* bu = nullptr, double* bw = nullptr, double* cu = nullptr,
                              double* cw = nullptr) {
  const int a = r.axis, b = (a + 1) % 3, c = (a + 2) % 3;
  const double dp = pd[a] - r.level;
  const double dl = x[a] - r.level;
  if (!(dl > 0 ? dp < -mm : dp > mm)) return false;
  const double hcap = sc.hcap[size_t(r.comp)];
  const bool capped = hcap < std::numeric_limits<double>::infinity();
  double ulo = std::numeric_limits<double>::infinity(), uhi = -ulo, wlo = ulo, whi = -ulo, hmax = -ulo, su = 0, sw = 0;
  for (int i = 0; i < m; i++) {
    const double* v = x + 3 * i;
    const double dv = v[a] - r.level;
    if (!(dl > 0 ? dv > mm : dv < -mm)) return false;
    const double t = dp / (dp - dv);
    const double xb = pd[b] + t * (v[b] - pd[b]), xc = pd[c] + t * (v[c] - pd[c]);
    if (bu) bu[i] = xb, bw[i] = xc, su += xb / m, sw += xc / m;
    ulo = std::min(ulo, xb), uhi = std::max(uhi, xb), wlo = std::min(wlo, xc), whi = std::max(whi, xc);
    if (capped) {
      double y[3];
      y[a] = r.level, y[b] = xb, y[c] = xc;
      hmax = std::max(hmax, sc.ne[0] * (y[0] - sc.e0[0]) + sc.ne[1] * (y[1] - sc.e0[1]) + sc.ne[2] * (y[2] - sc.e0[2]));
    }
  }
  if (capped && !(hmax < hcap - mh)) return false;
  f[0] = (ulo - mm - r.u0) / r.h, f[1] = (uhi + mm - r.u0) / r.h;
  f[2] = (wlo - mm - r.w0) / r.h, f[3] = (whi + mm - r.w0) / r.h;
  if (cu) *cu = su, *cw = sw;
  return f[0] >= 0 && f[2] >= 0 && f[1] < r.gu && f[3] < r.gw;
}

// Whether section r shows every point q of the convex polygon x (m points) behind its body from p
// (the certificate above for the piece: q's vertices clearly on the light's side of the plane, p
// clearly on the other, their projections' box, widened by `mm`, in cells of parity 1, and below
// the cap's lowest height by `mh`).
inline bool section_shows(const SectionCall& sc, const Section& r, const double* pd, const double* x, int m, double mm,
                          double mh) {
  double f[4];
  if (!section_crossings(sc, r, pd, x, m, mm, mh, f)) return false;
  const size_t i0 = size_t(f[0]), i1 = size_t(f[1]) + 1, j0 = size_t(f[2]), j1 = size_t(f[3]) + 1, W = size_t(r.gu) + 1;
  const int32_t* t = sc.sec->sat.data() + r.sat;
  return t[j1 * W + i1] - t[j0 * W + i1] - t[j1 * W + i0] + t[j0 * W + i0] == 0;
}

// section_shows with the cut segments themselves in place of the touched cells: the hull Q of
// the crossings b_i meets no cut segment (each one near Q's box is listed in a cell of that box,
// and a separating axis -- a side of Q, the segment's normal or its direction -- keeps it clear
// by `mm`), so Q lies in one connected part of the plane off the cross-section, of one parity;
// the b_i's centroid (a point of Q, within rounding) and the square of side 2 mm around it lie
// in body cells, so that parity is 1. Then every point of Q is a point of parity 1 below the cap,
// which is all the certificate asks of the box of body cells.
inline bool section_shows_exact(const SectionCall& sc, const Section& r, const double* pd, const double* x, int m, double mm,
                                double mh) {
  double f[4], bu[64], bw[64], cu = 0, cw = 0;
  if (!section_crossings(sc, r, pd, x, m, mm, mh, f, bu, bw, &cu, &cw)) return false;
  const double fu0 = f[0], fu1 = f[1], fw0 = f[2], fw1 = f[3];
  const size_t W = size_t(r.gu) + 1;
  const int32_t* t = sc.sec->sat.data() + r.sat;
  const int32_t* off = sc.sec->cell_off.data() + r.coff;
  for (int i = 0; i < m; i++) {  // each b_i in a body cell or a touched one (else it is not of parity 1)
    const size_t ci = size_t((bu[i] - r.u0) / r.h), cj = size_t((bw[i] - r.w0) / r.h);
    if (ci >= size_t(r.gu) || cj >= size_t(r.gw)) continue;
    const size_t cl = cj * size_t(r.gu) + ci;
    if (t[(cj + 1) * W + ci + 1] - t[cj * W + ci + 1] - t[(cj + 1) * W + ci] + t[cj * W + ci] != 0 && off[cl + 1] == off[cl]) return false;
  }
  {  // the centroid's square in body cells
    const size_t i0 = size_t(std::max(0.0, (cu - mm - r.u0) / r.h)), j0 = size_t(std::max(0.0, (cw - mm - r.w0) / r.h));
    const size_t i1 = std::min(size_t(r.gu), size_t((cu + mm - r.u0) / r.h) + 1), j1 = std::min(size_t(r.gw), size_t((cw + mm - r.w0) / r.h) + 1);
    if (!(i0 < i1 && j0 < j1) || t[j1 * W + i1] - t[j0 * W + i1] - t[j1 * W + i0] + t[j0 * W + i0] != 0) return false;
  }
  // Q's sides as axes: normals (e_w, -e_u) of b_i -> b_{i+1}, with Q's extent along them.
  double ax[66][2], alo[66], ahi[66];
  int na = 0;
  for (int i = 0; i < m && m >= 2; i++) {
    const int j = (i + 1) % m;
    const double nu = bw[j] - bw[i], nw = bu[i] - bu[j];
    if (nu == 0 && nw == 0) continue;
    double lo = std::numeric_limits<double>::infinity(), hi = -lo;
    for (int k = 0; k < m; k++) lo = std::min(lo, nu * bu[k] + nw * bw[k]), hi = std::max(hi, nu * bu[k] + nw * bw[k]);
    const double g = mm * (std::fabs(nu) + std::fabs(nw));
    ax[na][0] = nu, ax[na][1] = nw, alo[na] = lo - g, ahi[na] = hi + g;
    na++;
  }
  auto clear_of = [&](const double* sg) {  // the segment (u0, w0, u1, w1) clear of Q by mm
    for (int k = 0; k < na; k++) {
      const double s0 = ax[k][0] * sg[0] + ax[k][1] * sg[1], s1 = ax[k][0] * sg[2] + ax[k][1] * sg[3];
      if (std::min(s0, s1) > ahi[k] || std::max(s0, s1) < alo[k]) return true;
    }
    const double du = sg[2] - sg[0], dw = sg[3] - sg[1];
    const double axes[2][2] = {{-dw, du}, {du, dw}};
    for (int e = 0; e < 2; e++) {
      const double nu = axes[e][0], nw = axes[e][1];
      if (nu == 0 && nw == 0) continue;
      const double s0 = nu * sg[0] + nw * sg[1], s1 = nu * sg[2] + nw * sg[3];
      const double g = mm * (std::fabs(nu) + std::fabs(nw));
      double lo = std::numeric_limits<double>::infinity(), hi = -lo;
      for (int k = 0; k < m; k++) lo = std::min(lo, nu * bu[k] + nw * bw[k]), hi = std::max(hi, nu * bu[k] + nw * bw[k]);
      if (std::min(s0, s1) > hi + g || std::max(s0, s1) < lo - g) return true;
    }
    return false;
  };
  const size_t i0 = size_t(fu0), i1 = size_t(fu1) + 1, j0 = size_t(fw0), j1 = size_t(fw1) + 1;
  for (size_t j = j0; j < j1; j++)
    for (size_t i = i0; i < i1; i++) {
      const size_t cl = j * size_t(r.gu) + i;
      for (int32_t k = off[cl]; k < off[cl + 1]; k++)
        if (!clear_of(sc.sec->seg.data() + 4 * size_t(sc.sec->cell_seg[size_t(k)]))) return false;
    }
  return true;
}

// Whether the certificate above shows receiver p (normal n) in umbra: the whole light through one
// section, else every triangle of the fan of the light from its centroid c, or of the fan of
// that triangle from its own centroid, through some section. A fan from any point covers its
// polygon (a point q of the polygon lies between the apex and where the ray from the apex through
// q leaves it), so rounding of the apexes leaves no gap.
template <class T>
bool section_umbra(const SectionCall& sc, V3<T> p, V3<T> n) {
  if (!sc.any) return false;
  const double pd[3] = {double(p.x), double(p.y), double(p.z)}, nd[3] = {double(n.x), double(n.y), double(n.z)};
  const int64_t K = sc.K;
  const double* lv = sc.lv.data();
  const double nrm = std::sqrt(nd[0] * nd[0] + nd[1] * nd[1] + nd[2] * nd[2]);
  double S = sc.sec->scale;
  for (int d = 0; d < 3; d++) S = std::max(S, std::fabs(pd[d]));
  for (int64_t i = 0; i < 3 * K; i++) S = std::max(S, std::fabs(lv[i]));
  if (!std::isfinite(S)) return false;
  double lc[3] = {0, 0, 0};
  for (int64_t i = 0; i < K; i++)
    for (int d = 0; d < 3; d++) lc[d] += lv[3 * i + d] / double(K);
  {  // the ray from p to the light's centroid meets a component's box (else no section can show it)
    bool meets = false;
    const double dd[3] = {lc[0] - pd[0], lc[1] - pd[1], lc[2] - pd[2]};
    for (size_t k = 0; k + 6 <= sc.sec->box.size() && !meets; k += 6) {
      const double* bx = sc.sec->box.data() + k;
      double ta = 0, tb = 1;
      for (int d = 0; d < 3 && ta <= tb; d++) {
        const double pad = 1e-6 * S;
        if (dd[d] == 0) {
          if (pd[d] < bx[d] - pad || pd[d] > bx[3 + d] + pad) ta = 2;
          continue;
        }
        double x = (bx[d] - pad - pd[d]) / dd[d], y = (bx[3 + d] + pad - pd[d]) / dd[d];
        if (x > y) std::swap(x, y);
        ta = std::max(ta, x), tb = std::min(tb, y);
      }
      meets = ta <= tb;
    }
    if (!meets) return false;
  }
  for (int64_t i = 0; i < K; i++) {  // every light vertex above the horizon by 1e-6 rad
    const double r[3] = {lv[3 * i] - pd[0], lv[3 * i + 1] - pd[1], lv[3 * i + 2] - pd[2]};
    const double up = r[0] * nd[0] + r[1] * nd[1] + r[2] * nd[2];
    if (!(up > 1e-6 * nrm * std::sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]))) return false;
  }
  const double mm = 1e-9 * S, mh = 1e-9 * S * sc.nn;
  static thread_local size_t last = 0;  // the section that showed the previous piece: tried first
  const size_t nu = sc.use.size();
  static thread_local size_t last_exact = 0;  // the same for the exact test
  auto shows = [&](const double* x, int m) {
    const size_t first = last < nu ? last : 0;
    for (size_t jj = 0; jj < nu; jj++) {
      const size_t ju = (first + jj) % nu;
      if (section_shows(sc, sc.sec->sections[size_t(sc.use[ju])], pd, x, m, mm, mh)) {
        last = ju;
        return true;
      }
    }
    // A point's square is in body cells (which no segment touches) for both tests alike.
    const size_t fe = last_exact < nu ? last_exact : 0;
    for (size_t jj = 0; jj < nu && sc.exact && m >= 2; jj++) {
      const size_t ju = (fe + jj) % nu;
      if (section_shows_exact(sc, sc.sec->sections[size_t(sc.use[ju])], pd, x, m, mm, mh)) {
        last_exact = ju;
        return true;
      }
    }
    return false;
  };
  if (!shows(lc, 1)) return false;  // the centroid's piece needs a section that shows it (first: lit receivers stop here)
  if (shows(lv, int(K))) return true;
  // A triangle of the fan at `depth`: shown, or each triangle of its fan from its centroid.
  auto fan_shows = [&](const double* tri, int depth, auto&& self) -> bool {
    if (shows(tri, 3)) return true;
    if (depth >= kSectionFanDepth) return false;
    double g[3];
    for (int d = 0; d < 3; d++) g[d] = (tri[d] + tri[3 + d] + tri[6 + d]) / 3;
    for (int e = 0; e < 3; e++) {
      const double* x = tri + 3 * e;
      const double* y = tri + 3 * ((e + 1) % 3);
      const double sub[9] = {g[0], g[1], g[2], x[0], x[1], x[2], y[0], y[1], y[2]};
      if (!self(sub, depth + 1, self)) return false;
    }
    return true;
  };
  for (int64_t i = 0; i < K; i++) {
    const double* va = lv + 3 * i;
    const double* vb = lv + 3 * ((i + 1) % K);
    if (va[0] == vb[0] && va[1] == vb[1] && va[2] == vb[2]) continue;
    const double tri[9] = {lc[0], lc[1], lc[2], va[0], va[1], va[2], vb[0], vb[1], vb[2]};
    if (!fan_shows(tri, 1, fan_shows)) return false;
  }
  return true;
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_UMBRA_SECTIONS_H_
