// jaxshadow's shadow engine: polygon (part of `csrc/shadowc.cc`; see its header comment).
#ifndef JAXSHADOW_SHADOWC_POLYGON_H_
#define JAXSHADOW_SHADOWC_POLYGON_H_

#include "boundary.h"
#include "clear.h"
#include "silhouette.h"

namespace jaxshadow_engine {

// Output of one receiver: class and runs (appended to w.runs).
template <class T>
int32_t polygon_receiver(const PolyCall<T>& call, V3<T> p, V3<T> n, Work<T>& w) {
  w.n_candidates = 0;
  w.n_regions = 0;
  const int64_t K = call.L.K;
  const Occluders<T>& occ = call.occ;
  const T tol = T(kCollinearEps) * eps_of<T>();
  w.runs.clear();
  w.cand.clear();
  const double pd[3] = {double(p.x), double(p.y), double(p.z)};
  bool umbra_hit = false;  // inside a solid's umbra volume (umbra.h)

  // Emitter frame (_clip._emitter_frame).
  V3<T> e0 = call.L.v(0);
  V3<T> ne = call.ne_raw;
  T hp = dot(ne, p - e0);
  if (!(hp > 0)) return kZero;
  if (K > 64) return -1;
  // The silhouette path (silhouette.h) where every occluder vertex lies strictly between the
  // receiver's level and the emitter plane; the hierarchy's face query only if it falls back.
  const SilhouetteTree& sil = *call.sil;
  const bool try_sil = silhouette_serves(call, p, hp);
  const V3<T> ne_query = ne;

  // Candidate items: the hierarchy queried with the pyramid over the light (planes through p
  // and the light's edges, as plain cross products), the horizon and the emitter plane (the
  // pyramid lies on p's side of it). The pyramid over E_h lies inside. The margin bounds the
  // rounding of the planes and of the boxes' coordinates; it keeps touching items.
  auto query = [&]() {
    const V3<T> ne = ne_query;
    const int ne_edges = call.n_edges;
    auto make = [&](int j) -> HalfSpace { return pyramid_halfspace(call, p, n, ne, e0, j); };
    const double scale = std::max(double(absmax(p)), double(absmax(e0))) + 1.0;
    const double margin = 1e3 * double(eps_of<T>()) * scale + 64 * double(eps_of<T>()) * (call.item_extent + scale);
    w.cand.clear();
    if (!call.volume.outside(p)) {  // outside the root's occlusion volume the query returns nothing usable
      // The hierarchy's items in its depth-first order (from the receiver's group's list when there
      // is one), stopped at the first solid whose umbra volume holds p.
      const BVH& bv = *call.bvh;
      auto visit = [&](int32_t i) {
        const int32_t item = bv.items[i];
        w.cand.push_back({bv.key[i], item});
        umbra_hit = call.umbra.any && item < 0 && call.umbra.inside(-int64_t(item) - 1, pd, bv, occ.solid_faces);
        return !umbra_hit;
      };
      if (const std::vector<int32_t>* g = group_list(call, w.group))
        filter_lazy(bv, g->data(), g->size(), ne_edges + 2, margin, make, visit);
      else
        traverse_lazy(bv, ne_edges + 2, margin, make, visit);
      std::sort(w.cand.begin(), w.cand.end());
    }
  };
  if (!try_sil) query();
  if (!try_sil && w.cand.empty() && !w.lit_runs && call.n_edges > 0) {
    // Nothing can block: lit, or zero below the horizon. With the whole light above the horizon,
    // E_h is the light itself (a nonempty boundary: the light has an edge), as below.
    bool any_in = false, all_in = true;
    for (int64_t i = 0; i < K; i++) {
      const bool in = dot(call.L.v(i) - p, n) >= 0;
      any_in = any_in || in;
      all_in = all_in && in;
    }
    if (!any_in) return kZero;
    if (all_in) return kLit;
  }
  T esc = pow2_scale(absmax(ne));
  ne = esc * ne;
  hp = esc * hp;

  // E_h (horizon_clip_edges(p, n, E)): K + 1 edges with codes.
  w.edges.clear();
  w.planes.clear();
  w.prefs.clear();
  w.regions.clear();
  std::vector<V3<T>>& planes = w.planes;
  // Region 0 planes: the light's edge planes (v_{i+1} - p) x (v_i - p), then the horizon.
  for (int64_t i = 0; i < K; i++) {
    V3<T> a = call.L.v(i), b = call.L.v((i + 1) % K);
    V3<T> pl = same(a, b) ? V3<T>{0, 0, 0} : edge_plane(p, a, b);
    planes.push_back(rescale(pl));
    w.prefs.push_back(through(int32_t(i), int32_t((i + 1) % K)));
  }
  planes.push_back(rescale(n));
  w.prefs.push_back(PlaneRef{kHorizonPlane, 0, 0});
  const int np0 = int(K + 1);
  {
    Region<T> r0;
    r0.first = 0;
    r0.count = np0;
    r0.active = true;
    w.regions.push_back(r0);
  }
  T da[64], db[64];
  bool any_above = false;
  V3<T> exit_pt{}, entry_pt{};
  int32_t exit_i = -1, entry_i = -1;
  V3<T> ehv[130];  // E_h's vertices (for the umbra and box tests)
  int nehv = 0;
  for (int64_t i = 0; i < K; i++) {
    V3<T> a = call.L.v(i), b = call.L.v((i + 1) % K);
    da[i] = dot(a - p, n);
    db[i] = dot(b - p, n);
  }
  for (int64_t i = 0; i < K; i++) {
    V3<T> a = call.L.v(i), b = call.L.v((i + 1) % K);
    bool ain = da[i] >= 0, bin = db[i] >= 0;
    bool crossing = ain != bin;
    T t = crossing ? da[i] / (da[i] - db[i]) : T(0);
    V3<T> x = a + t * (b - a);
    if (ain) any_above = true;
    if (ain && !bin) {
      exit_pt = x;
      exit_i = int32_t(i);
    }
    if (!ain && bin) {
      entry_pt = x;
      entry_i = int32_t(i);
    }
    if (!(ain || bin)) continue;  // collapsed
    Edge<T> e;
    e.a = ain ? a : x;
    e.b = bin ? b : x;
    e.ca = ain ? code_point(kLightVertex, int32_t(i)) : code_point(kHorizon, int32_t(i));
    e.cb = bin ? code_point(kLightVertex, int32_t((i + 1) % K)) : code_point(kHorizon, int32_t(i));
    if (same(e.a, e.b)) continue;
    e.own = planes[i];
    e.own_ref = w.prefs[i];
    e.sigma = 1;
    e.region = 0;
    w.edges.push_back(e);
    ehv[nehv++] = e.a;
    ehv[nehv++] = e.b;
  }
  if (!any_above) return kZero;
  if (exit_i >= 0 && entry_i >= 0 && !same(exit_pt, entry_pt)) {
    Edge<T> e;
    e.a = exit_pt;
    e.b = entry_pt;
    e.ca = code_point(kHorizon, exit_i);
    e.cb = code_point(kHorizon, entry_i);
    e.own = planes[K];
    e.own_ref = w.prefs[K];
    e.sigma = 1;
    e.region = 0;
    w.edges.push_back(e);
  }
  const size_t n_eh_edges = w.edges.size();
  if (n_eh_edges == 0) return kZero;
  // E_h's box in the emitter plane.
  T ehlo[3], ehhi[3];
  for (int d = 0; d < 3; d++) {
    ehlo[d] = std::numeric_limits<T>::infinity();
    ehhi[d] = -std::numeric_limits<T>::infinity();
  }
  for (int i = 0; i < nehv; i++) {
    const T c[3] = {ehv[i].x, ehv[i].y, ehv[i].z};
    for (int d = 0; d < 3; d++) {
      ehlo[d] = std::min(ehlo[d], c[d]);
      ehhi[d] = std::max(ehhi[d], c[d]);
    }
  }
  for (int d = 0; d < 3; d++) {
    w.regions[0].lo[d] = ehlo[d];
    w.regions[0].hi[d] = ehhi[d];
  }

  if (try_sil) {
    const int32_t r = silhouette_receiver(call, sil, p, n, w.edges.data(), int(n_eh_edges), planes.data(), w.prefs.data(),
                                          np0, ne, hp, w);
    if (r != kFallback) return r;
    w.runs.clear();
    query();
  }
  if (w.cand.empty() && !w.lit_runs) return kLit;
  if (umbra_hit) {  // S hides all of the light, so all of E_h
    w.n_candidates = int32_t(w.cand.size());
    w.n_regions = int32_t(w.regions.size());
    return kUmbra;
  }

  // Per candidate: its region (planes through p) and candidate edges, or drop it.
  V3<T> cone[65];  // E_h's planes (a copy: `planes` grows below)
  T cnorm[65];
  for (int k = 0; k < np0; k++) {
    cone[k] = planes[k];
    cnorm[k] = norm(cone[k]);
  }
  // Where the plane through p with normal `own` crosses E_h's plane k.
  auto cone_crossing = [&](int k, V3<T> own) { return eh_crossing(call.L, w.prefs[size_t(k)], p, cone[k], own, ne, hp); };
  const T nenorm = norm(ne);

  // A region none of whose edges crosses E_h either misses E_h or contains all of it (both are
  // convex): E_h's centroid decides. Without this, a region that covers E_h with an edge exactly
  // on E_h's boundary (a receiver on an umbra boundary, an EV event) was taken for a miss and the
  // receiver came out fully lit.
  V3<T> eh_centre{0, 0, 0};
  for (int i = 0; i < nehv; i++) eh_centre = eh_centre + ehv[i];
  eh_centre = (T(1) / T(nehv > 0 ? nehv : 1)) * eh_centre;
  {  // Each E_h vertex once (consecutive edges share one) for the all-vertices tests below.
    int m = 0;
    for (int i = 0; i < nehv; i++) {
      bool dup = false;
      for (int j = 0; j < m && !dup; j++) dup = same(ehv[i], ehv[j]);
      if (!dup) ehv[m++] = ehv[i];
    }
    nehv = m;
    w.eh_margin = off_plane_margin(p, ehv, nehv, ne, hp);  // boundary_runs' boxes
  }
  auto covers_eh = [&](const V3<T>* pl, int np) -> bool {
    V3<T> r = eh_centre - p;
    for (int k = 0; k < np; k++)
      if (nonzero(pl[k]) && !(dot(r, pl[k]) >= 0)) return false;
    return true;
  };

  // An occluder region's planes are planes[first, first + np) and its candidate edges were pushed
  // after `before`: without any, it misses E_h (0, dropped) or covers all of it (2, umbra); else it
  // becomes a region (1).
  // `xlo`, `xhi`: the box of the region's interior edges' pieces (null: none).
  auto close_region = [&](int32_t first, int np, size_t before, bool touched, const T* xlo, const T* xhi) -> int {
    if (w.edges.size() == before && !touched) {
      const bool covers = covers_eh(planes.data() + first, np);
      planes.resize(first);
      w.prefs.resize(first);
      return covers ? 2 : 0;
    }
    Region<T> r;
    r.first = first;
    r.count = np;
    r.active = true;
    for (int d = 0; d < 3; d++) {
      r.xlo[d] = xlo ? xlo[d] : std::numeric_limits<T>::infinity();
      r.xhi[d] = xhi ? xhi[d] : -std::numeric_limits<T>::infinity();
    }
    w.regions.push_back(r);
    return 1;
  };

  // The tests that drop face f before its region is built (0), or its side (+1 / -1): the
  // face's plane separates it from the pyramid, all its vertices lie strictly outside one cone
  // plane or strictly behind the emitter plane, it blocks a zero solid angle, or it is a back
  // face of a closed mesh seen from outside its box. `fs` receives face_side's result.
  auto face_status = [&](int64_t f, bool closed_ok, FaceSide<T>& fs) -> int {
    const int64_t Ko = occ.Ko;
    if (Ko > 64) return 0;
    if (const int ls = call.light_side_of(f); ls != 0 && point_side(occ, f, p) == ls) return 0;
    // Cheap rejections first (_bsp.occluder_relevance): all vertices strictly outside one cone
    // plane, or strictly behind the emitter plane (|r|_1 >= |r|: a looser, still strict, test).
    for (int k = 0; k < np0; k++) {
      if (!nonzero(cone[k])) continue;
      bool all_out = true;
      for (int64_t i = 0; i < Ko && all_out; i++) {
        V3<T> r = occ.vert(f, i) - p;
        all_out = dot(r, cone[k]) < -tol * cnorm[k] * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z));
      }
      if (all_out) return 0;
    }
    {
      // Hugging the receiver's horizon: every point x of the face rises at most hmax (its highest
      // vertex) above the horizon plane and lies at least the distance d of the face's plane
      // from p, so its elevation is below asin(hmax / d). Within kHorizonBand the face blocks a
      // projected solid angle under pi * kHorizonBand^2 (a form factor below 1e-14) and clipping
      // it at the horizon is ill-conditioned (its projection runs along E_h's horizon edge): it
      // is dropped, as a face wholly at or below the horizon is (hmax <= 0).
      const V3<T>& hz = cone[np0 - 1];
      const double hn = norm(hz);
      if (hn > 0) {
        const V3<T> v0 = occ.vert(f, 0);
        double hmax = -std::numeric_limits<double>::infinity();
        double N[3] = {0, 0, 0};
        for (int64_t i = 0; i < Ko; i++) {
          hmax = std::max(hmax, double(dot(occ.vert(f, i) - p, hz)) / hn);
          const V3<T> a = occ.vert(f, i) - v0, b = occ.vert(f, (i + 1) % Ko) - v0;
          N[0] += double(a.y) * b.z - double(a.z) * b.y;
          N[1] += double(a.z) * b.x - double(a.x) * b.z;
          N[2] += double(a.x) * b.y - double(a.y) * b.x;
        }
        const double nn = std::sqrt(N[0] * N[0] + N[1] * N[1] + N[2] * N[2]);
        const double d = nn > 0 ? std::fabs((double(p.x) - v0.x) * N[0] + (double(p.y) - v0.y) * N[1] + (double(p.z) - v0.z) * N[2]) / nn : 0.0;
        if (hmax <= kHorizonBand * d) return 0;
      }
    }
    {
      bool all_behind = true;
      for (int64_t i = 0; i < Ko && all_behind; i++) {
        V3<T> r = occ.vert(f, i) - e0;
        all_behind = dot(r, ne) < -tol * nenorm * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z));
      }
      if (all_behind) return 0;
    }
    V3<T> rel[64];
    fs = face_side(occ, f, p, rel);
    if (fs.side == 0) return 0;  // inactive: blocks a zero solid angle (or not finite)
    if (closed_ok && fs.side < 0 && occ.face_closed && call.bvh->outside_mesh(occ.face_closed[f], pd)) return 0;  // back face
    return fs.side;
  };

  // Interior edges. Where face f and its twin g (PolyCall::twin) are both added and lie on
  // opposite sides of the plane through p and their shared edge (the same side for twins running
  // the edge in opposite directions, opposite sides otherwise), every point of the edge's relative
  // interior inside the pyramid lies inside the union of the two regions: each piece of it would
  // be blocked by the other region's collinear plane (the midpoint and tie tests of
  // boundary_runs), so it is left out. Only edges that bound the union (silhouette and boundary
  // edges, and interior edges of faces not both added) are split and tested; a region all of
  // whose edges inside the pyramid are interior is kept (it blocks the others' edges).
  bool any_interior = false;
  auto interior = [&](int64_t f, int64_t i, int s) -> bool {
    const int32_t t = call.twin()[size_t(f * occ.Ko + i)];
    if (t < 0) return false;
    const int g = w.fstat[size_t(t >> 1)];
    return g != 0 && ((t & 1) ? g == -s : g == s);
  };

  // `pre`: face_status's side and result when already computed (0: dropped).
  auto add_face = [&](int64_t f, bool closed_ok, const FaceSide<T>* pre) -> int {  // 0 dropped, 1 added, 2 umbra
    const int64_t Ko = occ.Ko;
    FaceSide<T> fs0;
    if (pre) {
      if (pre->side == 0) return 0;
      fs0 = *pre;
    } else if (face_status(f, closed_ok, fs0) == 0) {
      return 0;
    }
    const FaceSide<T>& fs = fs0;
    const T sigma = fs.scale, h0 = fs.h0, s = T(fs.side);
    const V3<T> no = fs.no;
    // Region planes: oriented edge planes, then the emitter-plane cut (_occluder_regions).
    const int32_t first = int32_t(planes.size());
    for (int64_t i = 0; i < Ko; i++) {
      V3<T> a = occ.vert(f, i), b = occ.vert(f, (i + 1) % Ko);
      V3<T> pl = same(a, b) ? V3<T>{0, 0, 0} : s * edge_plane(p, a, b);
      planes.push_back(pl);
      w.prefs.push_back(through(occ.ref(f, i), occ.ref(f, (i + 1) % Ko)));
    }
    V3<T> ncut = rescale((hp * sigma * -s) * no + std::fabs(h0) * ne);
    planes.push_back(ncut);
    w.prefs.push_back(PlaneRef{kCut, int32_t(f), 0});
    const int np = int(Ko + 1);
    const V3<T>* pl = planes.data() + first;
    // Umbra: every E_h vertex strictly inside all the region's planes.
    {
      T pn[65];  // the planes' norms, on first use
      for (int k = 0; k < np; k++) pn[k] = -1;
      bool all_in = true;
      for (int i = 0; i < nehv && all_in; i++) {
        V3<T> r = ehv[i] - p;
        T rn = norm(r);
        for (int k = 0; k < np && all_in; k++)
          if (nonzero(pl[k])) {
            if (pn[k] < 0) pn[k] = norm(pl[k]);
            all_in = dot(r, pl[k]) > tol * pn[k] * rn;
          }
      }
      if (all_in) return 2;
    }
    // Candidate edges: the effective blocker (horizon_clip_edges(e0, ne, occ)), each clipped to the
    // pyramid (p, E_h) and projected; reversed (R lies outside).
    T ha[64], hb[64];
    for (int64_t i = 0; i < Ko; i++) {
      ha[i] = dot(occ.vert(f, i) - e0, ne);
      hb[i] = dot(occ.vert(f, (i + 1) % Ko) - e0, ne);
    }
    const size_t before = w.edges.size();
    bool touched = false;  // an interior edge of this face meets the pyramid
    T xlo[3], xhi[3];  // the box of those pieces (boundary_runs' region boxes include it)
    for (int d = 0; d < 3; d++) {
      xlo[d] = std::numeric_limits<T>::infinity();
      xhi[d] = -std::numeric_limits<T>::infinity();
    }
    V3<T> bexit{}, bentry{};
    int64_t bexit_i = -1, bentry_i = -1;
    auto emit = [&](V3<T> a3, V3<T> b3, Code ca3, Code cb3, V3<T> own, PlaneRef oref, bool inner) {
      if (same(a3, b3)) return;
      T t0, t1;
      int i0, i1;
      if (!cyrus_beck(p, a3, b3, cone, np0, own, t0, t1, i0, i1)) return;
      V3<T> a2, b2;
      Code c2a, c2b;
      if (t0 > 0) {
        a2 = cone_crossing(i0, own);
        c2a = code_planes(w.prefs[i0], oref);
      } else {
        a2 = project(p, a3, ne, hp);
        c2a = ca3;
      }
      if (t1 < 1) {
        b2 = cone_crossing(i1, own);
        c2b = code_planes(w.prefs[i1], oref);
      } else {
        b2 = project(p, b3, ne, hp);
        c2b = cb3;
      }
      Edge<T> e;
      if (s > 0) {
        e.a = b2;
        e.b = a2;
        e.ca = c2b;
        e.cb = c2a;
      } else {
        e.a = a2;
        e.b = b2;
        e.ca = c2a;
        e.cb = c2b;
      }
      if (same(e.a, e.b)) return;
      if (inner) {
        touched = true;
        any_interior = true;
        const T ca[3] = {e.a.x, e.a.y, e.a.z}, cb[3] = {e.b.x, e.b.y, e.b.z};
        for (int d = 0; d < 3; d++) {
          xlo[d] = std::min(xlo[d], std::min(ca[d], cb[d]));
          xhi[d] = std::max(xhi[d], std::max(ca[d], cb[d]));
        }
        return;
      }
      e.own = own;
      e.own_ref = oref;
      e.sigma = -1;
      e.region = int32_t(w.regions.size());
      w.edges.push_back(e);
    };
    for (int64_t i = 0; i < Ko; i++) {
      V3<T> a = occ.vert(f, i), b = occ.vert(f, (i + 1) % Ko);
      bool ain = ha[i] >= 0, bin = hb[i] >= 0;
      bool crossing = ain != bin;
      T t = crossing ? ha[i] / (ha[i] - hb[i]) : T(0);
      V3<T> x = a + t * (b - a);
      Code cx = code_point(kEmitterCross, occ.ref(f, i), occ.ref(f, (i + 1) % Ko));
      if (ain && !bin) {
        bexit = x;
        bexit_i = i;
      }
      if (!ain && bin) {
        bentry = x;
        bentry_i = i;
      }
      if (!(ain || bin)) continue;
      V3<T> a3 = ain ? a : x, b3 = bin ? b : x;
      Code ca3 = ain ? code_point(kProjected, occ.ref(f, i)) : cx;
      Code cb3 = bin ? code_point(kProjected, occ.ref(f, (i + 1) % Ko)) : cx;
      if (same(a, b)) continue;
      emit(a3, b3, ca3, cb3, planes[first + i], w.prefs[first + i], interior(f, i, fs.side));
    }
    if (bexit_i >= 0 && bentry_i >= 0) {
      Code cx = code_point(kEmitterCross, occ.ref(f, bexit_i), occ.ref(f, (bexit_i + 1) % Ko));
      Code cy = code_point(kEmitterCross, occ.ref(f, bentry_i), occ.ref(f, (bentry_i + 1) % Ko));
      emit(bexit, bentry, cx, cy, planes[first + Ko], w.prefs[first + Ko], false);
    }
    return close_region(first, np, before, touched, xlo, xhi);  // its projection misses E_h, covers it, or bounds R
  };

  auto add_solid = [&](int64_t sidx) -> int {  // 0 dropped, 1 added, 2 umbra, 3 use its faces
    const int64_t f0 = occ.solid_faces[2 * sidx], f1 = occ.solid_faces[2 * sidx + 1];
    const BVH& bv = *call.bvh;
    const int32_t v0i = bv.solid_vert_off[sidx], v1i = bv.solid_vert_off[sidx + 1];
    uint8_t front[256];
    if (f1 - f0 > 256) return 3;
    // Strictly outside one cone plane: cannot block (its distinct vertices).
    for (int k = 0; k < np0; k++) {
      if (!nonzero(cone[k])) continue;
      bool all_out = true;
      for (int32_t q = v0i; q < v1i && all_out; q++) {
        V3<T> r = ld(occ.faces + 3 * int64_t(bv.solid_verts[q])) - p;
        all_out = dot(r, cone[k]) < -tol * cnorm[k] * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z));
      }
      if (all_out) return 0;
    }
    // The cone through the silhouette needs the solid strictly on p's side of the light's plane
    // and p strictly in front of at least one face (outside the solid); otherwise its faces are used.
    for (int32_t q = v0i; q < v1i; q++) {
      V3<T> r = ld(occ.faces + 3 * int64_t(bv.solid_verts[q])) - e0;
      if (!(dot(r, ne) > tol * nenorm * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z)))) return 3;
    }
    // Faces whose plane holds p (within the rounding bound `m`: a box resting on the floor, seen
    // from the floor) are taken as back faces. They are seen edge-on and block a zero solid
    // angle; the silhouette is then that of a point just behind their planes, whose edges all
    // border a strictly front face, so every silhouette plane's orientation is decided by a
    // strictly nonzero height. Where p is truly (by less than `m`) in front of such a face, the
    // cone leaves out that face's projection, a sliver of angular width O(m / |x - p|): round-off.
    bool any_front = false;
    for (int64_t f = f0; f < f1; f++) {
      const double* fp = bv.face_plane.data() + 6 * f;
      double rx = pd[0] - fp[3], ry = pd[1] - fp[4], rz = pd[2] - fp[5];
      double h = fp[0] * rx + fp[1] * ry + fp[2] * rz;
      double m = 1e3 * double(eps_of<T>()) * (std::fabs(rx) + std::fabs(ry) + std::fabs(rz) + std::fabs(fp[3]) +
                                              std::fabs(fp[4]) + std::fabs(fp[5]));
      const bool strict_front = h > m;
      // The on-surface rule (face_side) plays no part here: the device kernel drops a face within the
      // on-surface distance but keeps the solid's back faces, which every ray entering through it
      // leaves by, so the solid blocks its whole projection from p. Within
      // the rounding bound m, p in front (0 < h <= m) is too close to call: taken as a back face,
      // the cone would leave out the face's projection, a wedge of angular width h / d (d: p's
      // distance from the face's nearest edge; 4e-13 m off a box side, 1 um beside its corner, 7e-6
      // of the irradiance). The faces decide instead; p exactly in the plane leaves no wedge.
      if (!strict_front && h > 0) return 3;
      front[f - f0] = strict_front;
      any_front = any_front || strict_front;
      if (strict_front && call.light_side_of(f) > 0) return 0;  // the face's plane separates solid and pyramid
    }
    if (!any_front) return 3;  // p inside the solid or on its surface
    // Silhouette planes (through p and the edges between a front and a back face).
    const int32_t first = int32_t(planes.size());
    const size_t before = w.edges.size();
    const int32_t e0i = occ.solid_edge_off[sidx], e1i = occ.solid_edge_off[sidx + 1];
    struct SE {
      int32_t ra, rb;
    };
    SE sil[64];
    int nsil = 0;
    for (int32_t k = e0i; k < e1i; k++) {
      const int32_t* ed = occ.solid_edges + 4 * k;
      bool fl = front[ed[2] - f0], fr = front[ed[3] - f0];
      if (fl == fr) continue;
      if (nsil >= 16) {
        planes.resize(first);
        w.prefs.resize(first);
        return 3;
      }
      // In the front face's counter-clockwise order (seen from p) the edge runs ra -> rb.
      const int32_t ra = int32_t(occ.K) + ed[0], rb = int32_t(occ.K) + ed[1];  // flat face-vertex slots -> refs
      sil[nsil++] = fl ? SE{ra, rb} : SE{rb, ra};
    }
    if (nsil < 3) return 3;
    for (int k = 0; k < nsil; k++) {
      planes.push_back(edge_plane(p, occ.vref(sil[k].ra), occ.vref(sil[k].rb)));
      w.prefs.push_back(through(sil[k].ra, sil[k].rb));
    }
    const V3<T>* pl = planes.data() + first;
    T pn[64];
    for (int k = 0; k < nsil; k++) pn[k] = norm(pl[k]);
    for (int k = 0; k < nsil; k++) {  // E_h strictly outside one silhouette plane: disjoint cones
      bool all_out = true;
      for (int i = 0; i < nehv && all_out; i++) {
        V3<T> r = ehv[i] - p;
        all_out = dot(r, pl[k]) < -tol * pn[k] * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z));
      }
      if (all_out) {
        planes.resize(first);
        w.prefs.resize(first);
        return 0;
      }
    }
    {
      bool all_in = true;
      for (int i = 0; i < nehv && all_in; i++) {
        V3<T> r = ehv[i] - p;
        T rn = norm(r);
        for (int k = 0; k < nsil && all_in; k++) all_in = dot(r, pl[k]) > tol * pn[k] * rn;
      }
      if (all_in) return 2;
    }
    for (int k = 0; k < nsil; k++) {
      V3<T> a3 = occ.vref(sil[k].ra), b3 = occ.vref(sil[k].rb);
      T t0, t1;
      int i0, i1;
      if (!cyrus_beck(p, a3, b3, cone, np0, planes[first + k], t0, t1, i0, i1)) continue;
      V3<T> own = planes[first + k];
      PlaneRef oref = w.prefs[first + k];
      Edge<T> e;
      // Q's boundary runs a -> b counter-clockwise: R's edge is b -> a.
      if (t1 < 1) {
        e.a = cone_crossing(i1, own);
        e.ca = code_planes(w.prefs[i1], oref);
      } else {
        e.a = project(p, b3, ne, hp);
        e.ca = code_point(kProjected, sil[k].rb);
      }
      if (t0 > 0) {
        e.b = cone_crossing(i0, own);
        e.cb = code_planes(w.prefs[i0], oref);
      } else {
        e.b = project(p, a3, ne, hp);
        e.cb = code_point(kProjected, sil[k].ra);
      }
      if (same(e.a, e.b)) continue;
      e.own = own;
      e.own_ref = oref;
      e.sigma = -1;
      e.region = int32_t(w.regions.size());
      w.edges.push_back(e);
    }
    return close_region(first, nsil, before, false, nullptr, nullptr);  // its cone misses E_h, covers it, or bounds R
  };

  w.n_candidates = int32_t(w.cand.size());
  // The plain faces' sides first (interior edges need both faces' sides).
  if (w.fstat.size() != size_t(occ.M)) w.fstat.assign(size_t(occ.M), 0);
  std::vector<FaceSide<T>>& pre = w.pre;
  pre.resize(w.cand.size());
  // Back faces of a closed mesh are dropped seen from outside its box (face_status), except for
  // a mesh one of whose candidate faces p lies in the plane of (FaceSide::edge_on): that face is
  // dropped, and where p is in front of it by less than the on-surface distance (2e-6 m for a
  // mesh of float32 values 0.5 m across) only the back faces cover its wedge of shadow (5e-3 of
  // the irradiance 1e-6 m in front of an L-shaped prism's side). `keep`: such meshes.
  KeptMeshes keep;
  for (size_t c = 0; c < w.cand.size(); c++) {
    const int32_t item = w.cand[c].second;
    if (item < 0) continue;
    pre[c] = FaceSide<T>{};
    if (face_status(item, false, pre[c]) == 0) pre[c].side = 0;
    const int32_t mesh = occ.face_closed ? occ.face_closed[item] : -1;
    if (pre[c].edge_on && mesh >= 0) keep.add(mesh);
  }
  auto culled = [&](int32_t mesh) {  // back faces of closed mesh `mesh` (or -1) dropped from outside its box
    return mesh >= 0 && !keep.has(mesh) && call.bvh->outside_mesh(mesh, pd);
  };
  for (size_t c = 0; c < w.cand.size(); c++) {
    const int32_t item = w.cand[c].second;
    if (item < 0) continue;
    if (pre[c].side < 0 && occ.face_closed && culled(occ.face_closed[item])) pre[c].side = 0;  // back face
    const int st = pre[c].side;
    if (st != 0 && !call.twin().empty()) {
      w.fstat[size_t(item)] = int8_t(st);
      w.fstat_set.push_back(item);
    }
  }
  struct ResetStatus {  // every exit below leaves fstat all zero for the next receiver
    Work<T>& w;
    ~ResetStatus() {
      for (int32_t f : w.fstat_set) w.fstat[size_t(f)] = 0;
      w.fstat_set.clear();
    }
  } reset_status{w};
  for (size_t c = 0; c < w.cand.size(); c++) {
    int32_t item = w.cand[c].second;
    int res;
    if (item >= 0) {
      res = add_face(item, true, &pre[c]);
    } else {
      int64_t sidx = -int64_t(item) - 1;
      res = add_solid(sidx);
      if (res == 3) {
        res = 0;
        const int64_t f0 = occ.solid_faces[2 * sidx], f1 = occ.solid_faces[2 * sidx + 1];
        // Its back faces dropped only where p lies in none of its faces' planes (as above).
        bool cull = f1 > f0 && occ.face_closed && culled(occ.face_closed[f0]);
        for (int64_t f = f0; f < f1 && cull; f++) {
          FaceSide<T> fs;
          face_status(f, false, fs);
          cull = !fs.edge_on;
        }
        for (int64_t f = f0; f < f1; f++) {
          int r2 = add_face(f, cull, nullptr);
          if (r2 == 2) {
            res = 2;
            break;
          }
        }
      }
    }
    if (res == 2) {
      w.runs.clear();
      w.n_regions = int32_t(w.regions.size());
      return kUmbra;
    }
  }
  const int32_t n_regions = int32_t(w.regions.size());
  w.n_regions = n_regions - 1;
  if (any_interior && w.edges.size() == n_eh_edges) {
    // No edge bounds the union of the regions inside E_h: the union holds all of E_h's interior
    // or none of it, and E_h's centroid decides (umbra, or lit with E_h's own boundary).
    for (int32_t r = 1; r < n_regions; r++)
      if (covers_eh(planes.data() + w.regions[r].first, w.regions[r].count)) {
        w.runs.clear();
        return kUmbra;
      }
    for (size_t i = 0; i < w.edges.size(); i++) w.runs.push_back(Run{w.edges[i].ca, w.edges[i].cb});
    return kLit;
  }
  if (n_regions == 1) {
    for (size_t i = 0; i < w.edges.size(); i++) w.runs.push_back(Run{w.edges[i].ca, w.edges[i].cb});
    return kLit;
  }
  boundary_runs(occ, p, tol, ehv, nehv, w);
  return kPenumbra;
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_POLYGON_H_
