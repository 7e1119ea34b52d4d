// jaxshadow's shadow engine: a receiver's boundary decoded on the host, and Lambert's edge terms
// over it (part of `csrc/shadowc.cc`; see its header comment).
#ifndef JAXSHADOW_SHADOWC_DECODE_H_
#define JAXSHADOW_SHADOWC_DECODE_H_

#include <cstring>

#include "polygon_types.h"

namespace jaxshadow_engine {

// The points of endpoint codes, as `_shadows.binding.decode_endpoints` computes them (the same formulas
// in the same order): for evaluations that are not differentiated, the JAX side then only
// integrates over ready-made edges.
template <class T>
struct Decoder {
  const PolyCall<T>& call;
  V3<T> p, n, e0, ne;
  T hp;
  Decoder(const PolyCall<T>& c, V3<T> p_, V3<T> n_) : call(c), p(p_), n(n_) {
    e0 = c.L.v(0);
    ne = pow2_scale(absmax(c.ne_raw)) * c.ne_raw;
    hp = dot(ne, p - e0);
  }
  V3<T> V(int32_t r) const { return r < call.L.K ? call.L.v(r) : call.occ.vref(r); }
  V3<T> face_normal(int32_t f) const {
    const Occluders<T>& o = call.occ;
    V3<T> v0 = o.vert(f, 0), acc{0, 0, 0};
    for (int64_t i = 0; i < o.Ko; i++) acc = acc + cross(o.vert(f, i) - v0, o.vert(f, (i + 1) % o.Ko) - v0);
    return acc;
  }
  V3<T> plane(int32_t t, int32_t a, int32_t b) const {
    V3<T> out;
    if (t == kThrough) {
      out = edge_plane(p, V(a), V(b));
    } else if (t == kHorizonPlane) {
      out = n;
    } else {
      V3<T> fn = face_normal(a), f0 = call.occ.vert(a, 0);
      T d = dot(fn, f0 - p);
      T sg = d > 0 ? T(1) : (d < 0 ? T(-1) : T(0));
      out = (hp * sg) * fn + std::fabs(d) * ne;
    }
    return rescale(out);
  }
  V3<T> point(const Code& c) const {
    const int32_t kind = c.v[0];
    switch (kind) {
      case kLightVertex:
        return V(c.v[1]);
      case kHorizon: {
        V3<T> va = V(c.v[1]), vb = V(int32_t((c.v[1] + 1) % call.L.K));
        T da = dot(va - p, n), db = dot(vb - p, n);
        T t = da != db ? da / (da - db) : T(0);
        return va + t * (vb - va);
      }
      case kProjected:
        return project(p, V(c.v[1]), ne, hp);
      case kEmitterCross: {
        V3<T> va = V(c.v[1]), vb = V(c.v[2]);
        T da = dot(va - e0, ne), db = dot(vb - e0, ne);
        T t = da != db ? da / (da - db) : T(0);
        return project(p, va + t * (vb - va), ne, hp);
      }
      case kPlanes: {
        // Two planes through p and occluder edges with one common end: they cross on the line
        // from p through it, which their normals' cross product finds only to eps over their angle.
        if (c.v[1] == kThrough && c.v[4] == kThrough) {
          const V3<T> a1 = V(c.v[2]), b1 = V(c.v[3]), a2 = V(c.v[5]), b2 = V(c.v[6]);
          auto eq = [](V3<T> u, V3<T> v) { return u.x == v.x && u.y == v.y && u.z == v.z; };
          const bool aa = eq(a1, a2), ab = eq(a1, b2), ba = eq(b1, a2), bb = eq(b1, b2);
          if (int(aa) + int(ab) + int(ba) + int(bb) == 1) return crossing_point(p, (aa || ab ? a1 : b1) - p, ne, hp);
        }
        V3<T> n1 = plane(c.v[1], c.v[2], c.v[3]), n2 = plane(c.v[4], c.v[5], c.v[6]);
        // A light edge's plane through p (the first of the two: code_planes sorts them) and another.
        if (c.v[1] == kThrough && c.v[3] < call.L.K) return light_edge_crossing(p, V(c.v[2]), V(c.v[3]), n1, n2, ne, hp);
        const V3<T> x = cross(n1, n2);
        // Two occluder edges' planes through p, nearly coincident: on one edge's line
        // (occluder_edges_crossing).
        const int32_t K = call.L.K;
        if (c.v[1] == kThrough && c.v[4] == kThrough && c.v[2] >= K && c.v[3] >= K && c.v[5] >= K && c.v[6] >= K &&
            near_planes(x, n1, n2))
          return occluder_edges_crossing(p, V(c.v[2]), V(c.v[3]), n1, V(c.v[5]), V(c.v[6]), n2, ne, hp);
        return crossing_point(p, x, ne, hp);
      }
      default:
        return e0;
    }
  }
};

// v / |v| computed as `_polygon.edge_term` does (scaled by its largest component first); zero for
// a zero vector.
template <class T>
inline V3<T> unit_scaled(V3<T> v) {
  const T s = absmax(v);
  if (!(s > 0)) return V3<T>{0, 0, 0};
  v = V3<T>{v.x / s, v.y / s, v.z / s};
  const T r = std::sqrt(dot(v, v));
  return V3<T>{v.x / r, v.y / r, v.z / r};
}

// Lambert's term theta (n . Gamma) of a boundary edge whose ends seen from p are the unit vectors
// A and B (`unit_scaled(a - p)`, `unit_scaled(b - p)`; `_polygon.edge_term`: theta =
// atan2(|A x B|, A . B); zero for a zero-length edge and for p on the edge). Its sum over a
// receiver's boundary is -2 pi times the form factor.
template <class T>
inline T lambert_term(V3<T> n, V3<T> A, V3<T> B) {
  const V3<T> c = cross(A, B);
  const T s2 = dot(c, c);
  if (!(s2 > 0)) return T(0);
  const T sn = std::sqrt(s2);
  return std::atan2(sn, dot(A, B)) / sn * dot(n, c);
}

// The rounding bound of an edge's Lambert term from its ends' rounding: a decoded point is within
// kCollinearEps eps S of the exact one (S the largest coordinate magnitude `sa`, `sb` of the ends
// and `sp` of p), which moves the angle the edge subtends by at most that over its distance from p
// (`da`, `db`: the ends' distances from p).
template <class T>
inline T lambert_term_bound(T da, T db, T sa, T sb, T sp) {
  if (!(da > 0) || !(db > 0)) return T(0);
  const T S = std::max(std::max(sa, sb), sp);
  return T(kCollinearEps) * eps_of<T>() * S * (T(1) / da + T(1) / db);
}

// A visible region's form factor is never negative: Lambert's sum over its boundary (-2 pi F)
// is not positive. An all-but-empty region (its boundary's runs nearly zero-length: a receiver
// at an umbra's vertex) sums to +-1e-16 of rounding, relatively large against its tiny terms; a
// positive sum within the terms' rounding bound is that region's value, 0. A larger one is
// kept: a genuine error stays visible. (_clip.masked_contour_form_factor does the same.)
template <class T>
inline T lambert_rounded(T sum, T bound) {
  return sum > 0 && sum <= bound ? T(0) : sum;
}

// A decoded boundary vertex: its code, its point x, and what Lambert's terms read of it (the unit
// vector from p, its distance from p, its largest coordinate magnitude).
template <class T>
struct BoundaryEnd {
  Code c;
  V3<T> x, u;
  T d, s;
};

// Scratch of `decode_runs` (per thread): the decoded vertices and a hash table of their codes.
template <class T>
struct BoundaryEnds {
  std::vector<BoundaryEnd<T>> ends;
  std::vector<int32_t> table;  // open addressing: index into `ends`, -1 empty
};

constexpr size_t kLinearEnds = 8;  // runs up to which decode_runs searches its vertices linearly

inline uint32_t code_hash(const Code& c) {
  uint32_t h = 2166136261u;
  for (int k = 0; k < jaxshadow_abi::kCodeWidth; k++) h = (h ^ uint32_t(c.v[k])) * 16777619u;
  return h ^ (h >> 15);
}

// Receiver p's boundary `runs` decoded (`Decoder`): their points appended to `pts` (nullable; 6
// per run: start, end) and, with `lambert`, Lambert's sum over them (`lambert_rounded`; else 0). A
// vertex ends one run and starts another under the same code (the same point bit for bit), so each
// is decoded once (found again by its code).
template <class T>
T decode_runs(const PolyCall<T>& call, V3<T> p, V3<T> n, const std::vector<Run>& runs, BoundaryEnds<T>& scratch,
              T* pts, bool lambert) {
  const Decoder<T> dec(call, p, n);
  std::vector<BoundaryEnd<T>>& ends = scratch.ends;
  std::vector<int32_t>& table = scratch.table;
  ends.clear();
  // Few runs: the latest vertices searched first (consecutive runs share one); more: a hash table.
  const bool hashed = runs.size() > kLinearEnds;
  size_t size = 16;
  while (hashed && size < 4 * runs.size()) size *= 2;
  if (hashed) table.assign(size, -1);
  const size_t mask = size - 1;
  auto end = [&](const Code& c) -> size_t {
    size_t h = 0;
    if (hashed) {
      for (h = code_hash(c) & mask; table[h] >= 0; h = (h + 1) & mask)
        if (std::memcmp(ends[size_t(table[h])].c.v, c.v, sizeof(c.v)) == 0) return size_t(table[h]);
    } else {
      for (size_t k = ends.size(); k-- > 0;)
        if (std::memcmp(ends[k].c.v, c.v, sizeof(c.v)) == 0) return k;
    }
    BoundaryEnd<T> e;
    e.c = c;
    e.x = dec.point(c);
    if (lambert) {
      e.u = unit_scaled(e.x - p);
      e.d = norm(e.x - p);
      e.s = absmax(e.x);
    }
    if (hashed) table[h] = int32_t(ends.size());
    ends.push_back(e);
    return ends.size() - 1;
  };
  const T sp = absmax(p);
  T sum = 0, bound = 0;
  for (const Run& r : runs) {
    const size_t ka = end(r.s), kb = end(r.e);
    const BoundaryEnd<T>& a = ends[ka];
    const BoundaryEnd<T>& b = ends[kb];
    if (pts) {
      pts[0] = a.x.x, pts[1] = a.x.y, pts[2] = a.x.z, pts[3] = b.x.x, pts[4] = b.x.y, pts[5] = b.x.z;
      pts += 6;
    }
    if (lambert) {
      sum += lambert_term(n, a.u, b.u);
      bound += lambert_term_bound(a.d, b.d, a.s, b.s, sp);
    }
  }
  return lambert ? lambert_rounded(sum, bound) : T(0);
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_DECODE_H_
