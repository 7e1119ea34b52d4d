// jaxshadow's shadow engine: geometry helpers and the occluder layout (see `csrc/shadowc.cc`).
#ifndef JAXSHADOW_SHADOWC_GEOMETRY_H_
#define JAXSHADOW_SHADOWC_GEOMETRY_H_

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <thread>
#include <vector>

#include "../abi.h"

namespace jaxshadow_engine {


constexpr double kCollinearEps = 64.0;  // _clip.COLLINEAR_EPS
constexpr double kHorizonBand = 1e-7;  // polygon.h face_status: faces this close to the horizon (rad) block nothing
// _clip.ON_SURFACE: a receiver closer to a face's plane than kOnSurface times S (the largest
// coordinate magnitude of the face's vertices and the receiver) lies on that face: 32 float32
// epsilons (2^-18, about 3.8e-6) of S, whatever the float type, because scene data are float32
// (OBJ, PLY, Mitsuba) far more often than not, and a face built from float32-rounded vertices
// is planar, and a point computed on it lies in its plane, only to a few float32 roundings.
constexpr double kOnSurface = 1.0 / 262144.0;
// The same rule for faces of other doubles: 256 double epsilons (2^-44, about 5.7e-14) of S. A
// point computed on such a face (barycentric coordinates, a transform applied to the face and
// the point alike) lies in its plane to a few roundings of S, not of the face's size, which is
// what face_side's rounding bound follows: a receiver on a small face far from the origin was
// behind its own face and self-shadowed. The face dropped seen from closer than this blocks a
// sliver of angular width below 2^-44 S / distance: far below the double results' accuracy.
constexpr double kOnSurface64 = 1.0 / 17592186044416.0;

enum Class : int32_t { kZero = 0, kLit = 1, kUmbra = 2, kPenumbra = 3 };

// Endpoint codes (kCodeWidth int32 each, `csrc/abi.h`), decoded by `_shadows.binding.decode_endpoints`.
enum Kind : int32_t {
  kUnused = -1,
  kLightVertex = 0,    // a: light vertex index
  kHorizon = 1,        // a: light edge i, its crossing with the receiver's horizon
  kProjected = 2,      // a: global vertex ref, projected from p onto the emitter plane
  kEmitterCross = 3,   // a, b: global refs of an occluder edge; its crossing with the emitter plane, projected
  kPlanes = 4,         // (t1, a1, b1), (t2, a2, b2): the line common to two planes through p, met with the emitter plane
};
enum PlaneType : int32_t { kThrough = 0, kHorizonPlane = 1, kCut = 2 };

struct PlaneRef {
  int32_t t, a, b;
};
inline bool operator<(const PlaneRef& x, const PlaneRef& y) {
  if (x.t != y.t) return x.t < y.t;
  if (x.a != y.a) return x.a < y.a;
  return x.b < y.b;
}
inline PlaneRef through(int32_t a, int32_t b) { return a < b ? PlaneRef{kThrough, a, b} : PlaneRef{kThrough, b, a}; }

struct Code {
  int32_t v[jaxshadow_abi::kCodeWidth];
};
inline Code code_point(int32_t kind, int32_t a, int32_t b = 0) { return Code{{kind, a, b, 0, 0, 0, 0}}; }
inline Code code_planes(PlaneRef x, PlaneRef y) {
  if (y < x) std::swap(x, y);
  return Code{{kPlanes, x.t, x.a, x.b, y.t, y.a, y.b}};
}
inline Code code_unused() { return Code{{kUnused, 0, 0, 0, 0, 0, 0}}; }

// ----------------------------------------------------------------------------------------------
// Small vector helpers
// ----------------------------------------------------------------------------------------------

template <class T>
struct V3 {
  T x, y, z;
};
template <class T>
inline V3<T> ld(const T* a) { return V3<T>{a[0], a[1], a[2]}; }
template <class T>
inline V3<T> operator-(V3<T> a, V3<T> b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
template <class T>
inline V3<T> operator+(V3<T> a, V3<T> b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
template <class T>
inline V3<T> operator*(T s, V3<T> a) { return {s * a.x, s * a.y, s * a.z}; }
template <class T>
inline T dot(V3<T> a, V3<T> b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
template <class T>
inline V3<T> cross(V3<T> a, V3<T> b) {
  return {a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x};
}
template <class T>
inline bool same(V3<T> a, V3<T> b) { return a.x == b.x && a.y == b.y && a.z == b.z; }
template <class T>
inline bool nonzero(V3<T> a) { return a.x != 0 || a.y != 0 || a.z != 0; }
template <class T>
inline T absmax(V3<T> a) { return std::max(std::fabs(a.x), std::max(std::fabs(a.y), std::fabs(a.z))); }
template <class T>
inline T norm(V3<T> a) { return std::sqrt(dot(a, a)); }

template <class T>
inline T eps_of() { return std::numeric_limits<T>::epsilon(); }

// _clip._pow2_scale: 2^-e with mag * 2^-e in [0.5, 1) (1/2 for 0 or non-finite), clamped to the
// normal range; read from the exponent bits (frexp's exponent), as the JAX version does.
#define JS_INLINE inline __attribute__((always_inline))

JS_INLINE double pow2_scale(double mag) {
  uint64_t bits;
  bool ok = mag > 0 && std::isfinite(mag);
  double m = ok ? mag : 1.0;
  std::memcpy(&bits, &m, 8);
  int e = int((bits >> 52) & 0x7ff) - 1022;  // frexp exponent (subnormals read as the smallest normal's)
  int k = -e;
  if (k < 2 - 1023) k = 2 - 1023;
  if (k > 1022) k = 1022;
  uint64_t out = uint64_t(k + 1023) << 52;
  double r;
  std::memcpy(&r, &out, 8);
  return r;
}
JS_INLINE float pow2_scale(float mag) {
  uint32_t bits;
  bool ok = mag > 0 && std::isfinite(mag);
  float m = ok ? mag : 1.0f;
  std::memcpy(&bits, &m, 4);
  int e = int((bits >> 23) & 0xff) - 126;
  int k = -e;
  if (k < 2 - 127) k = 2 - 127;
  if (k > 126) k = 126;
  uint32_t out = uint32_t(k + 127) << 23;
  float r;
  std::memcpy(&r, &out, 4);
  return r;
}
template <class T>
JS_INLINE V3<T> rescale(V3<T> a) { return pow2_scale(absmax(a)) * a; }

template <class T>
inline bool lex_less(V3<T> a, V3<T> b) {
  if (a.x != b.x) return a.x < b.x;
  if (a.y != b.y) return a.y < b.y;
  return a.z < b.z;
}

// The plane through p and the edge a -> b, (b - p) x (a - p) up to a positive factor, computed from the
// two endpoints in lexicographic order (lo, hi): the same edge gives bit-identical normals (up to an
// exact sign) whichever face or light it comes from and in which direction it runs, so that
// coincident boundary lines (two faces of a mesh sharing an edge) are recognised exactly, not
// within a tolerance that rounding (or a compiler's fused multiply-adds) can defeat. Computed as
// (hi - lo) x (x - p), x the endpoint nearer p (the same vector): (hi - p) x (lo - p) cancels for an
// edge short beside its distance (its relative rounding is about eps |a - p| |b - p| / |(b - p) x
// (a - p)|, through_condition's eps), this form's at most twice that and smaller by |b - a| over the
// farther endpoint's distance. A far short edge's plane was off by 400 eps on a mesh seen at a
// grazing angle, and the crossing of two such planes (a boundary vertex) by 1e-10 of its distance.
template <class T>
JS_INLINE V3<T> edge_plane(V3<T> p, V3<T> a, V3<T> b) {
  const bool fwd = lex_less(a, b);
  const V3<T> lo = fwd ? a : b, hi = fwd ? b : a;
  const V3<T> rl = lo - p, rh = hi - p;
  const V3<T> c = rescale(cross(rescale(hi - lo), rescale(dot(rh, rh) < dot(rl, rl) ? rh : rl)));
  return fwd ? c : V3<T>{-c.x, -c.y, -c.z};
}

template <class T>
inline V3<T> normalize_safe(V3<T> a) {
  T n2 = dot(a, a);
  if (!(n2 > 0)) return V3<T>{0, 0, 0};
  T inv = T(1) / std::sqrt(n2);
  return inv * a;
}

// ----------------------------------------------------------------------------------------------
// Inputs
// ----------------------------------------------------------------------------------------------

// Occluders: M padded convex faces (M, Ko, 3); solids are convex closed meshes made of a
// contiguous range of faces with their edge list (ref_a, ref_b, f_left, f_right): global vertex
// face-vertex slots (f * Ko + i) of the edge's ends as it runs in f_left's (outward, counter-clockwise) order, and the two
// faces. `face_solid[f]` is the solid of face f or -1; `face_closed[f]` is the index of the closed,
// outward-oriented mesh face f belongs to, or -1. A receiver outside a closed mesh sees the same
// blockers without the mesh's back faces; that is used only where the receiver is strictly outside
// the mesh's bounding box (inside it, a receiver might be inside the mesh, where back faces block).
template <class T>
struct Occluders {
  int64_t M = 0, Ko = 0, K = 0;  // K: light vertices, the offset of face refs
  const T* faces = nullptr;
  const int32_t* face_solid = nullptr;
  const int32_t* face_closed = nullptr;
  int64_t S = 0;
  const int32_t* solid_faces = nullptr;  // (S, 2) [first, last) face
  const int32_t* solid_edge_off = nullptr;  // (S + 1)
  const int32_t* solid_edges = nullptr;  // (E, 4)
  V3<T> vert(int64_t f, int64_t i) const { return ld(faces + 3 * (f * Ko + i)); }
  int32_t ref(int64_t f, int64_t i) const { return int32_t(K + f * Ko + i); }
  V3<T> vref(int32_t r) const { return ld(faces + 3 * (int64_t(r) - K)); }
};

// _clip._occluder_sides for face f seen from p: its vertices relative to p, scaled by the power of
// two `scale` into `rel` (Ko <= 64 slots), their Newell normal `no` and h0 = no . rel[0]; `side`
// is +1 when p is behind `no` (h0 < 0), -1 in front, 0 when p cannot be told apart from the face's
// plane within the heights' rounding bounds or lies on the face (closer to its plane than
// kOnSurface S for a face of float32 values, kOnSurface64 S for other faces; the face then blocks
// a zero solid angle, and so does every face coplanar with it) or a vertex is not finite.
// Whether every coordinate of face f is a float32 value (data read from files or Mitsuba).
template <class T>
inline bool float32_face(const Occluders<T>& occ, int64_t f) {
  for (int64_t k = 0; k < 3 * occ.Ko; k++) {
    const double x = double(occ.faces[3 * f * occ.Ko + k]);
    if (double(float(x)) != x) return false;
  }
  return true;
}

// `edge_on`: side is 0 because p lies in the face's plane within the heights' rounding bounds or
// the on-surface distance (the face's vertices finite), on its front side. Such a face is dropped;
// where p is in fact (by less than that distance) in front of it, the face's projection, a wedge, is then
// blocked only by the mesh's other faces behind it, so a closed mesh keeps its back faces
// (polygon.h, hard.h). The device kernel does the same: it drops the face and keeps the rest.
template <class T>
struct FaceSide {
  int side = 0;
  bool edge_on = false;
  T scale = 0, h0 = 0;
  V3<T> no{0, 0, 0};
};

template <class T>
FaceSide<T> face_side(const Occluders<T>& occ, int64_t f, V3<T> p, V3<T>* rel) {
  const int64_t Ko = occ.Ko;
  FaceSide<T> out;
  T mx = 0;
  for (int64_t i = 0; i < Ko; i++) {
    rel[i] = occ.vert(f, i) - p;
    mx = std::max(mx, absmax(rel[i]));
  }
  if (!(mx == mx)) return out;
  out.scale = pow2_scale(mx);
  for (int64_t i = 0; i < Ko; i++) rel[i] = out.scale * rel[i];
  V3<T> no{0, 0, 0}, bnd{0, 0, 0};
  for (int64_t i = 0; i < Ko; i++) {
    V3<T> a = rel[i], b = rel[(i + 1) % Ko];
    no = no + cross(a, b);
    V3<T> aa{std::fabs(a.x), std::fabs(a.y), std::fabs(a.z)}, bb{std::fabs(b.x), std::fabs(b.y), std::fabs(b.z)};
    bnd = bnd + V3<T>{aa.y * bb.z + aa.z * bb.y, aa.z * bb.x + aa.x * bb.z, aa.x * bb.y + aa.y * bb.x};
  }
  const T h0 = dot(no, rel[0]);
  const T s = h0 < 0 ? T(1) : T(-1);
  const T boundf = T(Ko + 8) / T(2) * eps_of<T>();
  // On the face (kOnSurface): every height must also exceed kOnSurface S |no| (scaled frame).
  T S = absmax(p);
  for (int64_t i = 0; i < Ko; i++) S = std::max(S, absmax(occ.vert(f, i)));
  // kOnSurface for faces made of float32 values (meshes from files, Mitsuba); a face of other
  // doubles is planar to double rounding, and takes the double rounding of S (kOnSurface64).
  const T dtol = T(float32_face(occ, f) ? kOnSurface : kOnSurface64) * S * out.scale * norm(no);
  for (int64_t i = 0; i < Ko; i++) {
    T h = dot(no, rel[i]);
    V3<T> ar{std::fabs(rel[i].x), std::fabs(rel[i].y), std::fabs(rel[i].z)};
    if (!(-s * h > boundf * dot(bnd, ar)) || !(-s * h > dtol)) {
      // Only with p on the face's front side (h0 < 0; exactly in its plane, or behind it, p sees
      // no wedge), and not for a face whose normal its rounding does not determine (collinear
      // vertices, a sliver): it blocks a solid angle of the order of that rounding.
      out.edge_on = h0 < 0 && norm(no) > T(16) * boundf * norm(bnd);
      return out;
    }
  }
  out.side = h0 < 0 ? 1 : -1;
  out.h0 = h0;
  out.no = no;
  return out;
}

// The closed meshes that keep their back faces for one receiver (FaceSide::edge_on): at most
// kMax listed; past that, every mesh keeps them.
struct KeptMeshes {
  static constexpr int kMax = 8;
  int32_t id[kMax];
  int n = 0;
  bool all() const { return n > kMax; }
  bool has(int32_t mesh) const {
    if (all()) return true;
    for (int k = 0; k < n; k++)
      if (id[k] == mesh) return true;
    return false;
  }
  void add(int32_t mesh) {
    if (has(mesh)) return;
    if (n < kMax) id[n] = mesh;
    n++;  // kMax + 1: all of them
  }
};

// Whether p lies in the plane of face f, on its front side, as face_side decides (edge_on), or
// within twice the on-surface distance in front of it (in double): a rule applied elsewhere to
// the same face and point (the JAX kernels' _occluder_sides, with their own roundings) drops the
// face at most there. Faces whose normal is not determined to 2^-30 of their edges' products
// (slivers) never are.
template <class T>
bool near_face_plane(const Occluders<T>& occ, int64_t f, V3<T> p) {
  if (occ.Ko > 64) return false;
  V3<T> rel[64];
  if (face_side(occ, f, p, rel).edge_on) return true;
  const V3<T> v0 = occ.vert(f, 0);
  double N[3] = {0, 0, 0}, B = 0, S = double(absmax(p));
  for (int64_t i = 0; i < occ.Ko; i++) {
    const V3<T> vi = occ.vert(f, i), vj = occ.vert(f, (i + 1) % occ.Ko);
    S = std::max(S, double(absmax(vi)));
    const double a[3] = {double(vi.x) - v0.x, double(vi.y) - v0.y, double(vi.z) - v0.z};
    const double b[3] = {double(vj.x) - v0.x, double(vj.y) - v0.y, double(vj.z) - v0.z};
    N[0] += a[1] * b[2] - a[2] * b[1];
    N[1] += a[2] * b[0] - a[0] * b[2];
    N[2] += a[0] * b[1] - a[1] * b[0];
    B += std::sqrt((a[0] * a[0] + a[1] * a[1] + a[2] * a[2]) * (b[0] * b[0] + b[1] * b[1] + b[2] * b[2]));
  }
  const double nn = std::sqrt(N[0] * N[0] + N[1] * N[1] + N[2] * N[2]);
  if (!(nn > 0x1p-30 * B)) return false;  // a sliver or collinear vertices (as edge_on)
  const double h = (double(p.x) - v0.x) * N[0] + (double(p.y) - v0.y) * N[1] + (double(p.z) - v0.z) * N[2];
  const double dtol = 2 * (float32_face(occ, f) ? kOnSurface : kOnSurface64) * S;
  return h > 0 && h <= dtol * nn;  // in front (as edge_on)
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_GEOMETRY_H_
