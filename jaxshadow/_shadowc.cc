// The host side of jaxshadow's exact shadows: per receiver, which occluders can block the light
// (a bounding-volume hierarchy queried with the receiver's illumination pyramid) and the
// combinatorics of the visible region's boundary, as integer endpoint codes that the JAX side turns
// into points (and differentiates): `jaxshadow/_visibility.py`.
//
// Polygon lights (Campbell & Fussell §3.1, §4.2-4.3). For a receiver p with normal n the visible
// region is R = E_h \ U_j Q_j in the emitter plane: E_h the light clipped to p's horizon, Q_j the
// central projection of what occluder j blocks. Every region is an intersection of half-spaces
// bounded by planes through p, and R's boundary consists of pieces of the regions' edges. An
// occluder j can block part of the light seen from p iff the pyramid conv(p, E_h) meets it, i.e.
// iff p lies in the occlusion volume of (E, j) (C&F Theorem 2, evaluated here in that dual form);
// p is in the umbra of j iff E_h lies inside Q_j (C&F Theorem 3's volume, same duality). So each
// receiver is classified
//   LIT       no occluder meets the pyramid: the unoccluded form factor is exact;
//   UMBRA     one occluder (a face, or a convex solid through its silhouette) hides all of E_h: 0;
//   PENUMBRA  the boundary of R is computed from the candidates only;
// and the hierarchy makes the candidate search O(log M + k) instead of O(M).
//
// The combinatorics follow `jaxshadow._clip` (the device kernel) test for test: candidate edges
// (E_h's, and each occluder's effective-blocker edges clipped in 3-D to the pyramid and projected),
// cut at the parameters where they enter and leave every other region, pieces kept by a one-sided
// midpoint test with the coincident-edge tie-break (emitter first, then occluders in index order),
// kept pieces merged into runs. Regions whose bounding boxes in the emitter plane do not meet an
// edge are skipped (they cannot contain any of it). A convex closed mesh ("solid") strictly on the
// receiver's side of the emitter plane, with p strictly outside it, is one region: the planes
// through p and its silhouette edges (the cone it blocks), so that a box costs one hexagon.
//
// Point and directional lights: hard-shadow ray tests against the hierarchy. Segment lights: the
// occluders that meet the light triangle (p, a, b) (Poulin §4.2), for the device kernel to clip.
//
// Build: plain C++17, no dependencies; IEEE arithmetic without contraction into fused
// multiply-adds (setup.py passes -ffp-contract=off), so that the decisions round as NumPy's do.
// With JAXSHADOW_FFI (setup.py defines it when jaxlib's XLA FFI headers are found) the polygon
// combinatorics are also exported as an XLA FFI handler, for programs that compute them inside a
// compiled computation (traced receivers, light fits); otherwise only the C entry points exist
// (called through ctypes, before any compiled computation).

#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <thread>
#include <vector>

namespace {

constexpr double kCollinearEps = 64.0;  // _clip.COLLINEAR_EPS

enum Class : int32_t { kZero = 0, kLit = 1, kUmbra = 2, kPenumbra = 3 };

// Endpoint codes (7 int32 each), decoded by `_visibility._decode_endpoints`.
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
  int32_t v[7];
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
inline double pow2_scale(double mag) {
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
inline float pow2_scale(float mag) {
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
inline V3<T> rescale(V3<T> a) { return pow2_scale(absmax(a)) * a; }

template <class T>
inline bool lex_less(V3<T> a, V3<T> b) {
  if (a.x != b.x) return a.x < b.x;
  if (a.y != b.y) return a.y < b.y;
  return a.z < b.z;
}

// The plane through p and the edge a -> b, (b - p) x (a - p) up to a positive factor, computed from the
// two endpoints in lexicographic order: the same edge gives bit-identical normals (up to an exact
// sign) whichever face or light it comes from and in which direction it runs, so that coincident
// boundary lines (two faces of a mesh sharing an edge) are recognised exactly, not within a
// tolerance that rounding (or a compiler's fused multiply-adds) can defeat.
template <class T>
inline V3<T> edge_plane(V3<T> p, V3<T> a, V3<T> b) {
  if (lex_less(a, b)) return rescale(cross(rescale(b - p), rescale(a - p)));
  V3<T> c = rescale(cross(rescale(a - p), rescale(b - p)));
  return V3<T>{-c.x, -c.y, -c.z};
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

// ----------------------------------------------------------------------------------------------
// Bounding-volume hierarchy over items (a face that is not part of a solid, or a solid)
// ----------------------------------------------------------------------------------------------

struct Node {
  double lo[3], hi[3];
  int32_t left, right;  // children, or -1
  int32_t start, count;  // item range for leaves
};

struct BVH {
  std::vector<Node> nodes;
  std::vector<int32_t> items;  // item id: >= 0 face, < 0 solid -(s + 1)
  std::vector<int32_t> key;    // sort key per item slot: its first face index (priority order)
  std::vector<double> ibox;    // per item slot: lo[3], hi[3]
  // Per face: outward unit normal and first vertex (double), for the cheap side tests of solids.
  std::vector<double> face_plane;  // (M, 6)
  // Per solid: its distinct vertices (face-vertex slots), for the cheap rejections.
  std::vector<int32_t> solid_vert_off, solid_verts;
  std::vector<double> mesh_box;  // per closed mesh: lo[3], hi[3]
  // Strictly outside closed mesh `id`'s box (with a rounding margin): back faces may be dropped.
  bool outside_mesh(int32_t id, const double* p) const {
    if (id < 0 || size_t(6 * id + 6) > mesh_box.size()) return false;
    const double* b = mesh_box.data() + 6 * id;
    for (int d = 0; d < 3; d++) {
      double pad = 1e-9 * (std::fabs(b[d]) + std::fabs(b[3 + d]) + std::fabs(p[d]));
      if (p[d] < b[d] - pad || p[d] > b[3 + d] + pad) return true;
    }
    return false;
  }
};

template <class T>
BVH build_bvh(const Occluders<T>& occ) {
  struct Item {
    int32_t id, key;
    double lo[3], hi[3], c[3];
  };
  std::vector<Item> its;
  auto box_faces = [&](int64_t f0, int64_t f1, Item& it) {
    for (int d = 0; d < 3; d++) {
      it.lo[d] = std::numeric_limits<double>::infinity();
      it.hi[d] = -std::numeric_limits<double>::infinity();
    }
    for (int64_t f = f0; f < f1; f++)
      for (int64_t i = 0; i < occ.Ko; i++) {
        const T* v = occ.faces + 3 * (f * occ.Ko + i);
        for (int d = 0; d < 3; d++) {
          double x = double(v[d]);
          it.lo[d] = std::min(it.lo[d], x);
          it.hi[d] = std::max(it.hi[d], x);
        }
      }
    for (int d = 0; d < 3; d++) it.c[d] = 0.5 * (it.lo[d] + it.hi[d]);
  };
  for (int64_t f = 0; f < occ.M; f++) {
    if (occ.face_solid && occ.face_solid[f] >= 0) continue;
    Item it;
    it.id = int32_t(f);
    it.key = int32_t(f);
    box_faces(f, f + 1, it);
    its.push_back(it);
  }
  for (int64_t s = 0; s < occ.S; s++) {
    Item it;
    it.id = -int32_t(s) - 1;
    it.key = occ.solid_faces[2 * s];
    box_faces(occ.solid_faces[2 * s], occ.solid_faces[2 * s + 1], it);
    its.push_back(it);
  }
  BVH bvh;
  if (occ.face_closed) {
    for (int64_t f = 0; f < occ.M; f++) {
      int32_t id = occ.face_closed[f];
      if (id < 0) continue;
      if (bvh.mesh_box.size() < size_t(6 * id + 6)) {
        size_t old = bvh.mesh_box.size() / 6;
        bvh.mesh_box.resize(6 * (id + 1));
        for (size_t j = old; j < size_t(id + 1); j++)
          for (int d = 0; d < 3; d++) {
            bvh.mesh_box[6 * j + d] = std::numeric_limits<double>::infinity();
            bvh.mesh_box[6 * j + 3 + d] = -std::numeric_limits<double>::infinity();
          }
      }
      for (int64_t i = 0; i < occ.Ko; i++)
        for (int d = 0; d < 3; d++) {
          double x = double(occ.faces[3 * (f * occ.Ko + i) + d]);
          bvh.mesh_box[6 * id + d] = std::min(bvh.mesh_box[6 * id + d], x);
          bvh.mesh_box[6 * id + 3 + d] = std::max(bvh.mesh_box[6 * id + 3 + d], x);
        }
    }
  }
  if (its.empty()) return bvh;
  bvh.nodes.reserve(2 * its.size());
  // Iterative top-down build: median split of the centroids on the widest axis, leaves of <= 4.
  struct Task {
    int32_t node, start, count;
  };
  std::vector<Task> stack;
  bvh.nodes.push_back(Node{});
  stack.push_back({0, 0, int32_t(its.size())});
  while (!stack.empty()) {
    Task t = stack.back();
    stack.pop_back();
    Node nd;
    double clo[3], chi[3];
    for (int d = 0; d < 3; d++) {
      nd.lo[d] = clo[d] = std::numeric_limits<double>::infinity();
      nd.hi[d] = chi[d] = -std::numeric_limits<double>::infinity();
    }
    for (int32_t i = t.start; i < t.start + t.count; i++)
      for (int d = 0; d < 3; d++) {
        nd.lo[d] = std::min(nd.lo[d], its[i].lo[d]);
        nd.hi[d] = std::max(nd.hi[d], its[i].hi[d]);
        clo[d] = std::min(clo[d], its[i].c[d]);
        chi[d] = std::max(chi[d], its[i].c[d]);
      }
    nd.left = nd.right = -1;
    nd.start = t.start;
    nd.count = t.count;
    if (t.count > 4) {
      int ax = 0;
      for (int d = 1; d < 3; d++)
        if (chi[d] - clo[d] > chi[ax] - clo[ax]) ax = d;
      int32_t mid = t.start + t.count / 2;
      std::nth_element(its.begin() + t.start, its.begin() + mid, its.begin() + t.start + t.count,
                       [ax](const Item& a, const Item& b) { return a.c[ax] < b.c[ax]; });
      nd.left = int32_t(bvh.nodes.size());
      bvh.nodes.push_back(Node{});
      nd.right = int32_t(bvh.nodes.size());
      bvh.nodes.push_back(Node{});
      stack.push_back({nd.left, t.start, mid - t.start});
      stack.push_back({nd.right, mid, t.start + t.count - mid});
      nd.count = 0;
    }
    bvh.nodes[t.node] = nd;
  }
  bvh.items.resize(its.size());
  bvh.key.resize(its.size());
  bvh.ibox.resize(6 * its.size());
  for (size_t i = 0; i < its.size(); i++) {
    bvh.items[i] = its[i].id;
    bvh.key[i] = its[i].key;
    for (int d = 0; d < 3; d++) {
      bvh.ibox[6 * i + d] = its[i].lo[d];
      bvh.ibox[6 * i + 3 + d] = its[i].hi[d];
    }
  }
  return bvh;
}

// Per-call data of the solids: face planes and distinct vertices.
template <class T>
void prepare_solids(const Occluders<T>& occ, BVH& bvh) {
  bvh.face_plane.assign(6 * occ.M, 0.0);
  for (int64_t f = 0; f < occ.M; f++) {
    if (!occ.face_solid || occ.face_solid[f] < 0) continue;
    const T* v0 = occ.faces + 3 * (f * occ.Ko);
    double n[3] = {0, 0, 0};
    for (int64_t i = 0; i < occ.Ko; i++) {
      const T* a = occ.faces + 3 * (f * occ.Ko + i);
      const T* b = occ.faces + 3 * (f * occ.Ko + (i + 1) % occ.Ko);
      double ax = double(a[0]) - v0[0], ay = double(a[1]) - v0[1], az = double(a[2]) - v0[2];
      double bx = double(b[0]) - v0[0], by = double(b[1]) - v0[1], bz = double(b[2]) - v0[2];
      n[0] += ay * bz - az * by;
      n[1] += az * bx - ax * bz;
      n[2] += ax * by - ay * bx;
    }
    double nn = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    for (int d = 0; d < 3; d++) {
      bvh.face_plane[6 * f + d] = nn > 0 ? n[d] / nn : 0.0;
      bvh.face_plane[6 * f + 3 + d] = double(v0[d]);
    }
  }
  bvh.solid_vert_off.assign(1, 0);
  bvh.solid_verts.clear();
  for (int64_t s = 0; s < occ.S; s++) {
    std::vector<int32_t> vs;
    for (int32_t k = occ.solid_edge_off[s]; k < occ.solid_edge_off[s + 1]; k++)
      for (int q = 0; q < 2; q++) {
        int32_t slot = occ.solid_edges[4 * k + q];
        const T* x = occ.faces + 3 * int64_t(slot);
        bool dup = false;
        for (int32_t o : vs) {
          const T* y = occ.faces + 3 * int64_t(o);
          if (x[0] == y[0] && x[1] == y[1] && x[2] == y[2]) {
            dup = true;
            break;
          }
        }
        if (!dup) vs.push_back(slot);
      }
    bvh.solid_verts.insert(bvh.solid_verts.end(), vs.begin(), vs.end());
    bvh.solid_vert_off.push_back(int32_t(bvh.solid_verts.size()));
  }
}

// Items whose boxes are not strictly outside any of the half-spaces {x : N.(x - q) >= 0}.
// `planes` holds (N, q) pairs; a box is rejected when its farthest corner along N is below
// -margin * |N| (the margin, a bound on the rounding of the coordinates, keeps touching items).
struct HalfSpace {
  double n[3], q[3];
};

inline bool box_outside(const Node& nd, const HalfSpace& h, double margin) {
  double best = 0;
  double nn = 0;
  for (int d = 0; d < 3; d++) {
    double c = h.n[d] >= 0 ? nd.hi[d] : nd.lo[d];
    best += h.n[d] * (c - h.q[d]);
    nn += std::fabs(h.n[d]);
  }
  return best < -margin * nn;
}

inline bool ibox_outside(const BVH& bvh, int32_t i, const HalfSpace& h, double margin) {
  const double* b = bvh.ibox.data() + 6 * i;
  double best = 0, nn = 0;
  for (int d = 0; d < 3; d++) {
    double c = h.n[d] >= 0 ? b[3 + d] : b[d];
    best += h.n[d] * (c - h.q[d]);
    nn += std::fabs(h.n[d]);
  }
  return best < -margin * nn;
}

inline void query(const BVH& bvh, const HalfSpace* hs, int nh, double margin, std::vector<std::pair<int32_t, int32_t>>& out) {
  out.clear();
  if (bvh.nodes.empty()) return;
  int32_t stack[256];  // median splits: depth ~ log2(M)
  int sp = 0;
  stack[sp++] = 0;
  while (sp) {
    const Node& nd = bvh.nodes[stack[--sp]];
    bool rej = false;
    for (int i = 0; i < nh && !rej; i++) rej = box_outside(nd, hs[i], margin);
    if (rej) continue;
    if (nd.left < 0) {
      for (int32_t i = nd.start; i < nd.start + nd.count; i++) {
        bool r2 = false;
        for (int k = 0; k < nh && !r2; k++) r2 = ibox_outside(bvh, i, hs[k], margin);
        if (!r2) out.push_back({bvh.key[i], bvh.items[i]});
      }
    } else {
      stack[sp++] = nd.left;
      stack[sp++] = nd.right;
    }
  }
  std::sort(out.begin(), out.end());
}

// ----------------------------------------------------------------------------------------------
// Polygon lights: one receiver
// ----------------------------------------------------------------------------------------------

template <class T>
struct Edge {
  V3<T> a, b;      // in the emitter plane
  V3<T> own;       // normal of the plane through p and the edge's line
  V3<T> uo;        // its unit vector
  PlaneRef own_ref;
  Code ca, cb;     // endpoint codes of a and b
  T sigma;         // +1: R on the interior side of `own` (E_h), -1: outside (occluders)
  int32_t region;
  T lo[3], hi[3];  // bounding box
};

template <class T>
struct Region {
  int32_t first, count;  // planes in the receiver's plane table
  bool active;
  T lo[3], hi[3];  // box of region ∩ E_h, in the emitter plane
};

struct Run {
  Code s, e;
};

template <class T>
struct Work {  // per-thread scratch
  std::vector<std::pair<int32_t, int32_t>> cand;
  std::vector<V3<T>> planes, unit;
  std::vector<T> pnorm;
  std::vector<PlaneRef> prefs;
  std::vector<Region<T>> regions;
  std::vector<Edge<T>> edges;
  std::vector<Run> runs;
  std::vector<T> ts;
  std::vector<Code> tcodes;
  std::vector<int32_t> order;
  std::vector<T> rlo, rhi;
  std::vector<uint8_t> rnc, rc, rany, rlive;
  std::vector<int32_t> rilo, rihi;
  std::vector<int32_t> live;
  std::vector<uint8_t> free;
  int32_t n_candidates = 0, n_regions = 0;  // items the hierarchy returned; occluder regions kept
};

template <class T>
struct Light {
  int64_t K;
  const T* E;
  V3<T> v(int64_t i) const { return ld(E + 3 * i); }
};

// Cyrus-Beck of the segment a -> b against {x : (x - p).N >= 0} for the planes: (t0, t1, ok, i0, i1).
template <class T>
inline bool cyrus_beck(V3<T> p, V3<T> a, V3<T> b, const V3<T>* pl, int np, T& t0, T& t1, int& i0, int& i1) {
  T tlo_best = -std::numeric_limits<T>::infinity(), thi_best = std::numeric_limits<T>::infinity();
  i0 = 0;
  i1 = 0;
  bool const_ok = true;
  T first_lo = 0, first_hi = 1;  // argmax/argmin over the full arrays (jnp semantics: first index)
  bool have_lo = false, have_hi = false;
  V3<T> ap = a - p, d = b - a;
  for (int k = 0; k < np; k++) {
    T g0 = dot(ap, pl[k]), g1 = dot(d, pl[k]);
    T tc = g1 != 0 ? -g0 / g1 : T(0);
    T tl = g1 > 0 ? tc : T(0);  // t_lo = where(pos, tc, 0)
    T th = g1 < 0 ? tc : T(1);  // t_hi = where(neg, tc, 1)
    if (!have_lo || tl > first_lo) {
      first_lo = tl;
      i0 = k;
      have_lo = true;
    }
    if (!have_hi || th < first_hi) {
      first_hi = th;
      i1 = k;
      have_hi = true;
    }
    if (!(g1 != 0 || g0 >= 0)) const_ok = false;
  }
  (void)tlo_best;
  (void)thi_best;
  t0 = std::max(have_lo ? first_lo : T(0), T(0));
  t1 = std::min(have_hi ? first_hi : T(1), T(1));
  return const_ok && t1 > t0;
}

// _clip._project: central projection from p of x onto the emitter plane.
template <class T>
inline V3<T> project(V3<T> p, V3<T> x, V3<T> ne, T hp) {
  V3<T> r = x - p;
  T w = -dot(r, ne);
  T s = w > 0 ? hp / w : T(0);
  return p + s * r;
}

// _clip._crossing_point.
template <class T>
inline V3<T> crossing_point(V3<T> p, V3<T> c, V3<T> ne, T hp) {
  c = rescale(c);
  T den = -dot(c, ne);
  T e = eps_of<T>();
  bool ok = std::fabs(den) > e * e * absmax(c) * absmax(ne);
  return p + (ok ? hp / den : T(0)) * c;
}

template <class T>
struct PolyCall {
  Light<T> L;
  Occluders<T> occ;
  const BVH* bvh;
  // Per face, from the light alone: +1 all light vertices strictly in front of the face's plane,
  // -1 all strictly behind, 0 otherwise (a receiver strictly on that same side cannot be shadowed by
  // it: the plane separates the face from the receiver's pyramid).
  std::vector<int8_t> light_side;
};

template <class T>
void light_sides(PolyCall<T>& call) {
  const Occluders<T>& occ = call.occ;
  call.light_side.assign(occ.M, 0);
  for (int64_t f = 0; f < occ.M; f++) {
    V3<T> o = occ.vert(f, 0), n{0, 0, 0};
    for (int64_t i = 0; i < occ.Ko; i++) n = n + cross(occ.vert(f, i) - o, occ.vert(f, (i + 1) % occ.Ko) - o);
    T nn = norm(n);
    if (!(nn > 0)) continue;
    bool pos = true, neg = true;
    for (int64_t i = 0; i < call.L.K; i++) {
      V3<T> r = call.L.v(i) - o;
      T h = dot(r, n), m = T(1e3) * eps_of<T>() * nn * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z) + absmax(o));
      pos = pos && h > m;
      neg = neg && h < -m;
    }
    call.light_side[f] = pos ? 1 : (neg ? -1 : 0);
  }
}

// Side of p against face f's plane (+1 / -1 strictly, 0 too close to tell), as light_sides measures it.
template <class T>
inline int point_side(const Occluders<T>& occ, int64_t f, V3<T> p) {
  V3<T> o = occ.vert(f, 0), n{0, 0, 0};
  for (int64_t i = 0; i < occ.Ko; i++) n = n + cross(occ.vert(f, i) - o, occ.vert(f, (i + 1) % occ.Ko) - o);
  V3<T> r = p - o;
  T h = dot(r, n), m = T(1e3) * eps_of<T>() * norm(n) * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z) + absmax(o));
  return h > m ? 1 : (h < -m ? -1 : 0);
}

// Output of one receiver: class and runs (appended to w.runs).
template <class T>
int32_t polygon_receiver(const PolyCall<T>& call, V3<T> p, V3<T> n, Work<T>& w) {
  w.n_candidates = 0;
  w.n_regions = 0;
  const int64_t K = call.L.K;
  const Occluders<T>& occ = call.occ;
  const T tol = T(kCollinearEps) * eps_of<T>();
  w.runs.clear();
  const double pd[3] = {double(p.x), double(p.y), double(p.z)};

  // Emitter frame (_clip._emitter_frame).
  V3<T> e0 = call.L.v(0);
  V3<T> ne{0, 0, 0};
  for (int64_t i = 0; i < K; i++) ne = ne + cross(call.L.v(i), call.L.v((i + 1) % K));
  T hp = dot(ne, p - e0);
  if (!(hp > 0)) return kZero;
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
  if (K > 64) return -1;
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

  // Candidate items: the hierarchy queried with the pyramid's planes (through p and E_h's edges)
  // and the emitter plane (the pyramid lies on p's side of it).
  HalfSpace hs[70];
  int nh = 0;
  for (int k = 0; k < np0; k++) {
    if (!nonzero(planes[k])) continue;
    hs[nh].n[0] = double(planes[k].x);
    hs[nh].n[1] = double(planes[k].y);
    hs[nh].n[2] = double(planes[k].z);
    hs[nh].q[0] = double(p.x);
    hs[nh].q[1] = double(p.y);
    hs[nh].q[2] = double(p.z);
    nh++;
  }
  hs[nh].n[0] = double(ne.x);
  hs[nh].n[1] = double(ne.y);
  hs[nh].n[2] = double(ne.z);
  hs[nh].q[0] = double(e0.x);
  hs[nh].q[1] = double(e0.y);
  hs[nh].q[2] = double(e0.z);
  nh++;
  double scale = std::max(double(absmax(p)), double(absmax(e0))) + 1.0;
  double margin = 1e3 * double(eps_of<T>()) * scale;
  // Items are boxes in float64 of T's values; a T-rounding margin keeps touching ones.
  query(*call.bvh, hs, nh, margin, w.cand);

  // Per candidate: its region (planes through p) and candidate edges, or drop it.
  V3<T> cone[65];  // E_h's planes (a copy: `planes` grows below)
  T cnorm[65];
  for (int k = 0; k < np0; k++) {
    cone[k] = planes[k];
    cnorm[k] = norm(cone[k]);
  }
  const T nenorm = norm(ne);

  auto add_face = [&](int64_t f, bool closed_ok) -> int {  // 0 dropped, 1 added, 2 umbra
    const int64_t Ko = occ.Ko;
    if (Ko > 64) return 0;
    if (call.light_side[f] != 0 && point_side(occ, f, p) == call.light_side[f]) return 0;
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
      bool all_behind = true;
      for (int64_t i = 0; i < Ko && all_behind; i++) {
        V3<T> r = occ.vert(f, i) - e0;
        all_behind = dot(r, ne) < -tol * nenorm * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z));
      }
      if (all_behind) return 0;
    }
    V3<T> rel[64];
    T mx = 0;
    for (int64_t i = 0; i < Ko; i++) {
      rel[i] = occ.vert(f, i) - p;
      mx = std::max(mx, absmax(rel[i]));
    }
    if (!(mx == mx)) return 0;
    T sigma = pow2_scale(mx);
    for (int64_t i = 0; i < Ko; i++) rel[i] = sigma * rel[i];
    // _occluder_sides.
    V3<T> no{0, 0, 0}, bnd{0, 0, 0};
    for (int64_t i = 0; i < Ko; i++) {
      V3<T> a = rel[i], b = rel[(i + 1) % Ko];
      no = no + cross(a, b);
      V3<T> aa{std::fabs(a.x), std::fabs(a.y), std::fabs(a.z)}, bb{std::fabs(b.x), std::fabs(b.y), std::fabs(b.z)};
      bnd = bnd + V3<T>{aa.y * bb.z + aa.z * bb.y, aa.z * bb.x + aa.x * bb.z, aa.x * bb.y + aa.y * bb.x};
    }
    T h0 = dot(no, rel[0]);
    T s = h0 < 0 ? T(1) : T(-1);
    T boundf = T(Ko + 8) / T(2) * eps_of<T>();
    for (int64_t i = 0; i < Ko; i++) {
      T h = dot(no, rel[i]);
      V3<T> ar{std::fabs(rel[i].x), std::fabs(rel[i].y), std::fabs(rel[i].z)};
      if (!(-s * h > boundf * dot(bnd, ar))) return 0;  // inactive: blocks a zero solid angle
    }
    if (closed_ok && s < 0 && occ.face_closed && call.bvh->outside_mesh(occ.face_closed[f], pd)) return 0;  // back face
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
      bool all_in = true;
      for (int i = 0; i < nehv && all_in; i++) {
        V3<T> r = ehv[i] - p;
        T rn = norm(r);
        for (int k = 0; k < np && all_in; k++)
          if (nonzero(pl[k])) all_in = dot(r, pl[k]) > tol * norm(pl[k]) * rn;
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
    V3<T> bexit{}, bentry{};
    int64_t bexit_i = -1, bentry_i = -1;
    auto emit = [&](V3<T> a3, V3<T> b3, Code ca3, Code cb3, V3<T> own, PlaneRef oref) {
      if (same(a3, b3)) return;
      T t0, t1;
      int i0, i1;
      if (!cyrus_beck(p, a3, b3, cone, np0, t0, t1, i0, i1)) return;
      V3<T> a2, b2;
      Code c2a, c2b;
      if (t0 > 0) {
        a2 = crossing_point(p, cross(cone[i0], own), ne, hp);
        c2a = code_planes(w.prefs[i0], oref);
      } else {
        a2 = project(p, a3, ne, hp);
        c2a = ca3;
      }
      if (t1 < 1) {
        b2 = crossing_point(p, cross(cone[i1], own), ne, hp);
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
      emit(a3, b3, ca3, cb3, planes[first + i], w.prefs[first + i]);
    }
    if (bexit_i >= 0 && bentry_i >= 0) {
      Code cx = code_point(kEmitterCross, occ.ref(f, bexit_i), occ.ref(f, (bexit_i + 1) % Ko));
      Code cy = code_point(kEmitterCross, occ.ref(f, bentry_i), occ.ref(f, (bentry_i + 1) % Ko));
      emit(bexit, bentry, cx, cy, planes[first + Ko], w.prefs[first + Ko]);
    }
    if (w.edges.size() == before) {  // its projection misses E_h
      planes.resize(first);
      w.prefs.resize(first);
      return 0;
    }
    Region<T> r;
    r.first = first;
    r.count = np;
    r.active = true;
    w.regions.push_back(r);
    return 1;
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
    // and p strictly off every face plane (front or back); otherwise its faces are used.
    for (int32_t q = v0i; q < v1i; q++) {
      V3<T> r = ld(occ.faces + 3 * int64_t(bv.solid_verts[q])) - e0;
      if (!(dot(r, ne) > tol * nenorm * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z)))) return 3;
    }
    bool any_front = false;
    for (int64_t f = f0; f < f1; f++) {
      const double* fp = bv.face_plane.data() + 6 * f;
      double rx = pd[0] - fp[3], ry = pd[1] - fp[4], rz = pd[2] - fp[5];
      double h = fp[0] * rx + fp[1] * ry + fp[2] * rz;
      double m = 1e3 * double(eps_of<T>()) * (std::fabs(rx) + std::fabs(ry) + std::fabs(rz) + std::fabs(fp[3]) +
                                              std::fabs(fp[4]) + std::fabs(fp[5]));
      if (!(std::fabs(h) > m)) return 3;
      front[f - f0] = h > 0;
      any_front = any_front || h > 0;
      if (h > 0 && call.light_side[f] > 0) return 0;  // the face's plane separates solid and pyramid
    }
    if (!any_front) return 3;  // p inside the solid
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
    for (int k = 0; k < nsil; k++) {  // E_h strictly outside one silhouette plane: disjoint cones
      T pn = norm(pl[k]);
      bool all_out = true;
      for (int i = 0; i < nehv && all_out; i++) {
        V3<T> r = ehv[i] - p;
        all_out = dot(r, pl[k]) < -tol * pn * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z));
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
        for (int k = 0; k < nsil && all_in; k++) all_in = dot(r, pl[k]) > tol * norm(pl[k]) * rn;
      }
      if (all_in) return 2;
    }
    for (int k = 0; k < nsil; k++) {
      V3<T> a3 = occ.vref(sil[k].ra), b3 = occ.vref(sil[k].rb);
      T t0, t1;
      int i0, i1;
      if (!cyrus_beck(p, a3, b3, cone, np0, t0, t1, i0, i1)) continue;
      V3<T> own = planes[first + k];
      PlaneRef oref = w.prefs[first + k];
      Edge<T> e;
      // Q's boundary runs a -> b counter-clockwise: R's edge is b -> a.
      if (t1 < 1) {
        e.a = crossing_point(p, cross(cone[i1], own), ne, hp);
        e.ca = code_planes(w.prefs[i1], oref);
      } else {
        e.a = project(p, b3, ne, hp);
        e.ca = code_point(kProjected, sil[k].rb);
      }
      if (t0 > 0) {
        e.b = crossing_point(p, cross(cone[i0], own), ne, hp);
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
    if (w.edges.size() == before) {
      planes.resize(first);
      w.prefs.resize(first);
      return 0;
    }
    Region<T> r;
    r.first = first;
    r.count = nsil;
    r.active = true;
    w.regions.push_back(r);
    return 1;
  };

  w.n_candidates = int32_t(w.cand.size());
  for (const auto& kv : w.cand) {
    int32_t item = kv.second;
    int res;
    if (item >= 0) {
      res = add_face(item, true);
    } else {
      int64_t sidx = -int64_t(item) - 1;
      res = add_solid(sidx);
      if (res == 3) {
        res = 0;
        for (int64_t f = occ.solid_faces[2 * sidx]; f < occ.solid_faces[2 * sidx + 1]; f++) {
          int r2 = add_face(f, true);
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
  if (n_regions == 1) {
    for (size_t i = 0; i < w.edges.size(); i++) w.runs.push_back(Run{w.edges[i].ca, w.edges[i].cb});
    return kLit;
  }

  // Unit normals and norms of all planes; regions' boxes (their candidate edges' ends and the
  // E_h vertices inside them).
  const size_t npl = planes.size();
  w.unit.resize(npl);
  w.pnorm.resize(npl);
  for (size_t k = 0; k < npl; k++) {
    w.unit[k] = normalize_safe(planes[k]);
    w.pnorm[k] = norm(planes[k]);
  }
  for (int32_t r = 1; r < n_regions; r++)
    for (int d = 0; d < 3; d++) {
      w.regions[r].lo[d] = std::numeric_limits<T>::infinity();
      w.regions[r].hi[d] = -std::numeric_limits<T>::infinity();
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
    e.uo = normalize_safe(e.own);
  }
  for (int i = 0; i < nehv; i++) {
    V3<T> r = ehv[i] - p;
    for (int32_t j = 1; j < n_regions; j++) {
      const Region<T>& R = w.regions[j];
      bool in = true;
      for (int k = 0; k < R.count && in; k++) in = dot(r, planes[R.first + k]) >= 0;
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
  for (const Edge<T>& e : w.edges) {
    V3<T> ap = e.a - p, d = e.b - e.a;
    T apn = norm(ap) + norm(e.b - p);
    T ext = 0;
    for (int dd = 0; dd < 3; dd++) ext = std::max(ext, std::max(std::fabs(e.lo[dd]), std::fabs(e.hi[dd])));
    T bmargin = T(1e3) * eps_of<T>() * (ext + absmax(p));
    w.live.clear();
    for (int32_t j = 0; j < n_regions; j++) {
      if (j == e.region) continue;
      const Region<T>& R = w.regions[j];
      bool overlap = true;
      const T elo[3] = {e.lo[0], e.lo[1], e.lo[2]}, ehi[3] = {e.hi[0], e.hi[1], e.hi[2]};
      for (int dd = 0; dd < 3 && overlap; dd++)
        overlap = !(ehi[dd] < R.lo[dd] - bmargin || R.hi[dd] < elo[dd] - bmargin);
      if (overlap) w.live.push_back(j);
    }
    const int nl = int(w.live.size());
    w.rlo.resize(nl);
    w.rhi.resize(nl);
    w.rnc.resize(nl);
    w.rc.resize(nl);
    w.rany.resize(nl);
    w.rilo.resize(nl);
    w.rihi.resize(nl);
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
            V3<T> cr = cross(e.uo, w.unit[pk]);
            collinear = dot(cr, cr) <= tol * tol;
          }
        }
        bool side_ok = e.sigma * dot(w.unit[pk], e.uo) > 0;
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
        if (collinear && !side_ok) c_c = false;
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
    std::stable_sort(w.order.begin(), w.order.end(), [&](int32_t x, int32_t y) { return w.ts[x] < w.ts[y]; });
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
  return kPenumbra;
}

// ----------------------------------------------------------------------------------------------
// Hard shadows (point and directional lights) and segment-light candidates
// ----------------------------------------------------------------------------------------------

// _clip._ray_blocked for one face: the ray p + t r (t > 0) strictly inside the cone of the face's
// edge planes, the face active, and (with a limit point x) x strictly beyond the face's plane.
template <class T>
bool face_blocks_ray(const Occluders<T>& occ, int64_t f, V3<T> p, V3<T> r, const V3<T>* x) {
  const int64_t Ko = occ.Ko;
  V3<T> rel[64];
  if (Ko > 64) return false;
  T mx = 0;
  for (int64_t i = 0; i < Ko; i++) {
    rel[i] = occ.vert(f, i) - p;
    mx = std::max(mx, absmax(rel[i]));
  }
  T sg = pow2_scale(mx);
  for (int64_t i = 0; i < Ko; i++) rel[i] = sg * rel[i];
  V3<T> no{0, 0, 0}, bnd{0, 0, 0};
  for (int64_t i = 0; i < Ko; i++) {
    V3<T> a = rel[i], b = rel[(i + 1) % Ko];
    no = no + cross(a, b);
    V3<T> aa{std::fabs(a.x), std::fabs(a.y), std::fabs(a.z)}, bb{std::fabs(b.x), std::fabs(b.y), std::fabs(b.z)};
    bnd = bnd + V3<T>{aa.y * bb.z + aa.z * bb.y, aa.z * bb.x + aa.x * bb.z, aa.x * bb.y + aa.y * bb.x};
  }
  T h0 = dot(no, rel[0]);
  T s = h0 < 0 ? T(1) : T(-1);
  T boundf = T(Ko + 8) / T(2) * eps_of<T>();
  for (int64_t i = 0; i < Ko; i++) {
    T h = dot(no, rel[i]);
    V3<T> ar{std::fabs(rel[i].x), std::fabs(rel[i].y), std::fabs(rel[i].z)};
    if (!(-s * h > boundf * dot(bnd, ar))) return false;
  }
  for (int64_t i = 0; i < Ko; i++) {
    V3<T> a = occ.vert(f, i), b = occ.vert(f, (i + 1) % Ko);
    if (same(a, b)) continue;
    V3<T> pl = s * edge_plane(p, a, b);
    if (!(dot(pl, r) > 0)) return false;
  }
  if (x) {
    V3<T> nraw{0, 0, 0};
    for (int64_t i = 0; i < Ko; i++) nraw = nraw + cross(rel[i], rel[(i + 1) % Ko]);
    // beyond: -s * no . (x - o_0) > 0, with no the sigma-scaled Newell normal (only its sign matters)
    if (!(-s * dot(nraw, *x - occ.vert(f, 0)) > 0)) return false;
  }
  return true;
}

template <class T>
bool ray_blocked(const Occluders<T>& occ, const BVH& bvh, V3<T> p, V3<T> r, const V3<T>* x,
                 std::vector<std::pair<int32_t, int32_t>>& cand) {
  // Items whose boxes the segment (or ray, clipped to a far distance) meets: slab test per node.
  cand.clear();
  if (bvh.nodes.empty()) return false;
  double o[3] = {double(p.x), double(p.y), double(p.z)};
  double dd[3] = {double(r.x), double(r.y), double(r.z)};
  double tmax = x ? 1.0 : std::numeric_limits<double>::infinity();
  int32_t stack[128];
  int sp = 0;
  stack[sp++] = 0;
  auto hits = [&](const Node& nd) {
    double t0 = 0, t1 = tmax;
    for (int k = 0; k < 3; k++) {
      double pad = 1e-9 * (std::fabs(nd.lo[k]) + std::fabs(nd.hi[k]) + std::fabs(o[k]) + 1e-300);
      double lo = nd.lo[k] - pad, hi = nd.hi[k] + pad;
      if (dd[k] == 0) {
        if (o[k] < lo || o[k] > hi) return false;
        continue;
      }
      double a = (lo - o[k]) / dd[k], b = (hi - o[k]) / dd[k];
      if (a > b) std::swap(a, b);
      t0 = std::max(t0, a);
      t1 = std::min(t1, b);
      if (t0 > t1) return false;
    }
    return true;
  };
  while (sp) {
    const Node& nd = bvh.nodes[stack[--sp]];
    if (!hits(nd)) continue;
    if (nd.left < 0) {
      for (int32_t i = nd.start; i < nd.start + nd.count; i++) {
        int32_t item = bvh.items[i];
        if (item >= 0) {
          if (face_blocks_ray(occ, item, p, r, x)) return true;
        } else {
          int64_t s = -int64_t(item) - 1;
          for (int64_t f = occ.solid_faces[2 * s]; f < occ.solid_faces[2 * s + 1]; f++)
            if (face_blocks_ray(occ, f, p, r, x)) return true;
        }
      }
    } else if (sp + 2 <= 128) {
      stack[sp++] = nd.left;
      stack[sp++] = nd.right;
    } else {
      for (int32_t i = nd.start; i < nd.start + nd.count; i++) {
        int32_t item = bvh.items[i];
        if (item >= 0 && face_blocks_ray(occ, item, p, r, x)) return true;
        if (item < 0) {
          int64_t s = -int64_t(item) - 1;
          for (int64_t f = occ.solid_faces[2 * s]; f < occ.solid_faces[2 * s + 1]; f++)
            if (face_blocks_ray(occ, f, p, r, x)) return true;
        }
      }
    }
  }
  return false;
}

// Faces that can block part of the segment light a -> b seen from p: the light triangle (p, a, b)
// meets them. Conservative: a box test, then the face's vertices not all strictly on one side of
// the triangle's plane or outside one of its edge planes. Back faces of closed meshes are dropped.
template <class T>
void segment_candidates(const Occluders<T>& occ, const BVH& bvh, V3<T> p, V3<T> a, V3<T> b,
                        std::vector<int32_t>& out, std::vector<std::pair<int32_t, int32_t>>& cand) {
  out.clear();
  // Half-spaces bounding the triangle: its two sides (slab of the plane, as two half-spaces), and
  // the three edge planes (in the triangle's plane, pointing inwards).
  V3<T> nt = cross(a - p, b - p);
  T tol = T(kCollinearEps) * eps_of<T>();
  HalfSpace hs[5];
  int nh = 0;
  auto add = [&](V3<T> nrm, V3<T> q) {
    hs[nh].n[0] = double(nrm.x);
    hs[nh].n[1] = double(nrm.y);
    hs[nh].n[2] = double(nrm.z);
    hs[nh].q[0] = double(q.x);
    hs[nh].q[1] = double(q.y);
    hs[nh].q[2] = double(q.z);
    nh++;
  };
  if (nonzero(nt)) {
    add(nt, p);
    add(T(-1) * nt, p);
    add(cross(nt, a - p), p);   // inward of edge p->a
    add(cross(nt, b - a), a);   // inward of a->b
    add(cross(nt, p - b), b);   // inward of b->p
  }
  double scale = std::max(double(absmax(p)), std::max(double(absmax(a)), double(absmax(b)))) + 1.0;
  query(bvh, hs, nh, 1e3 * double(eps_of<T>()) * scale, cand);
  auto consider = [&](int64_t f) {
    const int64_t Ko = occ.Ko;
    // Drop faces with every vertex strictly on one side of the triangle's plane.
    T nn = norm(nt);
    bool pos = true, neg = true;
    for (int64_t i = 0; i < Ko; i++) {
      V3<T> r = occ.vert(f, i) - p;
      T h = dot(r, nt);
      T m = tol * nn * norm(r);
      if (!(h > m)) pos = false;
      if (!(h < -m)) neg = false;
    }
    if (nonzero(nt) && (pos || neg)) return;
    const double pd[3] = {double(p.x), double(p.y), double(p.z)};
    if (occ.face_closed && bvh.outside_mesh(occ.face_closed[f], pd)) {
      V3<T> no{0, 0, 0};
      for (int64_t i = 0; i < Ko; i++) no = no + cross(occ.vert(f, i) - p, occ.vert(f, (i + 1) % Ko) - p);
      T h0 = dot(no, occ.vert(f, 0) - p);
      // p strictly behind an outward face: a front face of the same mesh blocks the same rays.
      T scl = 0;
      for (int64_t i = 0; i < Ko; i++) scl = std::max(scl, norm(occ.vert(f, i) - p));
      if (h0 > tol * norm(no) * scl) return;
    }
    out.push_back(int32_t(f));
  };
  for (const auto& kv : cand) {
    int32_t item = kv.second;
    if (item >= 0) {
      consider(item);
    } else {
      int64_t s = -int64_t(item) - 1;
      for (int64_t f = occ.solid_faces[2 * s]; f < occ.solid_faces[2 * s + 1]; f++) consider(f);
    }
  }
  std::sort(out.begin(), out.end());
}

// ----------------------------------------------------------------------------------------------
// Parallel driver
// ----------------------------------------------------------------------------------------------

template <class F>
void parallel_for(int64_t n, int threads, F fn) {
  if (threads <= 1 || n < 64) {
    fn(0, 0, n);
    return;
  }
  std::vector<std::thread> pool;
  std::atomic<int64_t> next(0);
  const int64_t block = std::max<int64_t>(64, n / (threads * 16));
  for (int t = 0; t < threads; t++)
    pool.emplace_back([&, t]() {
      for (;;) {
        int64_t s = next.fetch_add(block);
        if (s >= n) break;
        fn(t, s, std::min(n, s + block));
      }
    });
  for (auto& th : pool) th.join();
}

int default_threads(int requested) {
  if (requested > 0) return requested;
  unsigned hc = std::thread::hardware_concurrency();
  return hc ? int(std::min(hc, 64u)) : 1;
}

template <class T>
Occluders<T> make_occ(int64_t K, int64_t M, int64_t Ko, const T* faces, const int32_t* face_solid,
                      const int32_t* face_closed, int64_t S, const int32_t* solid_faces,
                      const int32_t* solid_edge_off, const int32_t* solid_edges) {
  Occluders<T> occ;
  occ.K = K;
  occ.M = M;
  occ.Ko = Ko;
  occ.faces = faces;
  occ.face_solid = face_solid;
  occ.face_closed = face_closed;
  occ.S = S;
  occ.solid_faces = solid_faces;
  occ.solid_edge_off = solid_edge_off;
  occ.solid_edges = solid_edges;
  return occ;
}

// The points of endpoint codes, as `_visibility.decode_endpoints` computes them (the same formulas
// in the same order): for evaluations that are not differentiated, the JAX side then only
// integrates over ready-made edges.
template <class T>
struct Decoder {
  const PolyCall<T>& call;
  V3<T> p, n, e0, ne;
  T hp;
  Decoder(const PolyCall<T>& c, V3<T> p_, V3<T> n_) : call(c), p(p_), n(n_) {
    const int64_t K = c.L.K;
    e0 = c.L.v(0);
    ne = V3<T>{0, 0, 0};
    for (int64_t i = 0; i < K; i++) ne = ne + cross(c.L.v(i), c.L.v((i + 1) % K));
    ne = pow2_scale(absmax(ne)) * ne;
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
        V3<T> n1 = plane(c.v[1], c.v[2], c.v[3]), n2 = plane(c.v[4], c.v[5], c.v[6]);
        return crossing_point(p, cross(n1, n2), ne, hp);
      }
      default:
        return e0;
    }
  }
};

// Polygon plan, CSR output: classes (N), offsets (N + 1), runs (R, 2, 7) codes and/or (R, 2, 3) points
// (malloc'd, freed by the caller).
template <class T>
int poly_plan(int64_t N, const T* P, const T* Nrm, int64_t K, const T* E, const Occluders<T>& occ, int threads,
              int32_t* cls, int32_t* stats, int64_t* offsets, int32_t** runs_out, T** points_out, int64_t* nruns_out) {
  BVH bvh = build_bvh(occ);
  prepare_solids(occ, bvh);
  PolyCall<T> call{Light<T>{K, E}, occ, &bvh, {}};
  light_sides(call);
  threads = default_threads(threads);
  struct Block {
    int64_t s, e;
    std::vector<int32_t> codes;
    std::vector<T> pts;
  };
  std::vector<std::vector<Block>> per_thread(threads);
  std::vector<int32_t> counts(N, 0);
  std::atomic<int> err(0);
  parallel_for(N, threads, [&](int t, int64_t s, int64_t e) {
    Work<T> w;
    Block blk;
    blk.s = s;
    blk.e = e;
    for (int64_t i = s; i < e; i++) {
      int32_t c = polygon_receiver(call, ld(P + 3 * i), ld(Nrm + 3 * i), w);
      if (c < 0) {
        err = 1;
        c = kZero;
        w.runs.clear();
      }
      cls[i] = c;
      counts[i] = int32_t(w.runs.size());
      if (stats) {
        stats[2 * i] = w.n_candidates;
        stats[2 * i + 1] = w.n_regions;
      }
      if (runs_out)
        for (const Run& r : w.runs) {
          blk.codes.insert(blk.codes.end(), r.s.v, r.s.v + 7);
          blk.codes.insert(blk.codes.end(), r.e.v, r.e.v + 7);
        }
      if (points_out && !w.runs.empty()) {
        Decoder<T> dec(call, ld(P + 3 * i), ld(Nrm + 3 * i));
        for (const Run& r : w.runs) {
          V3<T> a = dec.point(r.s), b = dec.point(r.e);
          const T q[6] = {a.x, a.y, a.z, b.x, b.y, b.z};
          blk.pts.insert(blk.pts.end(), q, q + 6);
        }
      }
    }
    per_thread[t].push_back(std::move(blk));
  });
  offsets[0] = 0;
  for (int64_t i = 0; i < N; i++) offsets[i + 1] = offsets[i] + counts[i];
  int64_t total = offsets[N];
  *nruns_out = total;
  if (runs_out) {
    int32_t* runs = static_cast<int32_t*>(std::malloc(sizeof(int32_t) * 14 * std::max<int64_t>(total, 1)));
    if (!runs) return 2;
    for (auto& blocks : per_thread)
      for (auto& blk : blocks)
        if (!blk.codes.empty()) std::memcpy(runs + 14 * offsets[blk.s], blk.codes.data(), sizeof(int32_t) * blk.codes.size());
    *runs_out = runs;
  }
  if (points_out) {
    T* pts = static_cast<T*>(std::malloc(sizeof(T) * 6 * std::max<int64_t>(total, 1)));
    if (!pts) return 2;
    for (auto& blocks : per_thread)
      for (auto& blk : blocks)
        if (!blk.pts.empty()) std::memcpy(pts + 6 * offsets[blk.s], blk.pts.data(), sizeof(T) * blk.pts.size());
    *points_out = pts;
  }
  return err.load();
}

// Fixed-capacity variant (the FFI handler's layout): runs (N, cap, 2, 7), unused slots kUnused.
template <class T>
int poly_fixed(int64_t N, const T* P, const T* Nrm, int64_t K, const T* E, const Occluders<T>& occ, int threads,
               int64_t cap, int32_t* cls, int32_t* counts, int32_t* runs) {
  BVH bvh = build_bvh(occ);
  prepare_solids(occ, bvh);
  PolyCall<T> call{Light<T>{K, E}, occ, &bvh, {}};
  light_sides(call);
  std::atomic<int> err(0);
  parallel_for(N, default_threads(threads), [&](int, int64_t s, int64_t e) {
    Work<T> w;
    for (int64_t i = s; i < e; i++) {
      int32_t c = polygon_receiver(call, ld(P + 3 * i), ld(Nrm + 3 * i), w);
      if (c < 0) {
        err = 1;
        c = kZero;
        w.runs.clear();
      }
      cls[i] = c;
      counts[i] = int32_t(w.runs.size());
      int32_t* out = runs + i * cap * 14;
      int64_t m = std::min<int64_t>(cap, int64_t(w.runs.size()));
      for (int64_t k = 0; k < m; k++) {
        std::memcpy(out + 14 * k, w.runs[k].s.v, 7 * sizeof(int32_t));
        std::memcpy(out + 14 * k + 7, w.runs[k].e.v, 7 * sizeof(int32_t));
      }
      for (int64_t k = m; k < cap; k++)
        for (int q = 0; q < 14; q++) out[14 * k + q] = (q % 7 == 0) ? kUnused : 0;
    }
  });
  return err.load();
}

template <class T>
int hard_plan(int64_t N, const T* P, const T* X, int is_point, const Occluders<T>& occ, int threads, uint8_t* visible) {
  BVH bvh = build_bvh(occ);
  V3<T> x = ld(X);
  parallel_for(N, default_threads(threads), [&](int, int64_t s, int64_t e) {
    std::vector<std::pair<int32_t, int32_t>> cand;
    for (int64_t i = s; i < e; i++) {
      V3<T> p = ld(P + 3 * i);
      bool blocked = is_point ? ray_blocked(occ, bvh, p, x - p, &x, cand)
                              : ray_blocked(occ, bvh, p, T(-1) * x, static_cast<const V3<T>*>(nullptr), cand);
      visible[i] = blocked ? 0 : 1;
    }
  });
  return 0;
}

template <class T>
int segment_plan(int64_t N, const T* P, const T* A, const T* B, const Occluders<T>& occ, int threads,
                 int64_t* offsets, int32_t** faces_out) {
  BVH bvh = build_bvh(occ);
  V3<T> a = ld(A), b = ld(B);
  std::vector<std::vector<int32_t>> lists(N);
  parallel_for(N, default_threads(threads), [&](int, int64_t s, int64_t e) {
    std::vector<std::pair<int32_t, int32_t>> cand;
    for (int64_t i = s; i < e; i++) segment_candidates(occ, bvh, ld(P + 3 * i), a, b, lists[i], cand);
  });
  offsets[0] = 0;
  for (int64_t i = 0; i < N; i++) offsets[i + 1] = offsets[i] + int64_t(lists[i].size());
  int32_t* out = static_cast<int32_t*>(std::malloc(sizeof(int32_t) * std::max<int64_t>(offsets[N], 1)));
  if (!out) return 2;
  for (int64_t i = 0; i < N; i++)
    if (!lists[i].empty()) std::memcpy(out + offsets[i], lists[i].data(), sizeof(int32_t) * lists[i].size());
  *faces_out = out;
  return 0;
}

}  // namespace

// ----------------------------------------------------------------------------------------------
// C entry points (ctypes)
// ----------------------------------------------------------------------------------------------

#define JS_OCC_ARGS                                                                                           \
  int64_t M, int64_t Ko, const void *faces, const int32_t *face_solid, const int32_t *face_closed, int64_t S, \
      const int32_t *solid_faces, const int32_t *solid_edge_off, const int32_t *solid_edges

extern "C" {

int jaxshadow_shadowc_abi(void) { return 1; }

void jaxshadow_free(void* p) { std::free(p); }

int jaxshadow_poly_plan(int is_f64, int64_t N, const void* P, const void* Nrm, int64_t K, const void* E, JS_OCC_ARGS,
                        int threads, int32_t* cls, int32_t* stats, int64_t* offsets, int32_t** runs, void** points,
                        int64_t* nruns) {
  if (is_f64) {
    auto occ = make_occ<double>(K, M, Ko, static_cast<const double*>(faces), face_solid, face_closed, S, solid_faces,
                                solid_edge_off, solid_edges);
    return poly_plan<double>(N, static_cast<const double*>(P), static_cast<const double*>(Nrm), K,
                             static_cast<const double*>(E), occ, threads, cls, stats, offsets, runs,
                             reinterpret_cast<double**>(points), nruns);
  }
  auto occ = make_occ<float>(K, M, Ko, static_cast<const float*>(faces), face_solid, face_closed, S, solid_faces,
                             solid_edge_off, solid_edges);
  return poly_plan<float>(N, static_cast<const float*>(P), static_cast<const float*>(Nrm), K,
                          static_cast<const float*>(E), occ, threads, cls, stats, offsets, runs,
                          reinterpret_cast<float**>(points), nruns);
}

int jaxshadow_poly_fixed(int is_f64, int64_t N, const void* P, const void* Nrm, int64_t K, const void* E, JS_OCC_ARGS,
                         int threads, int64_t cap, int32_t* cls, int32_t* counts, int32_t* runs) {
  if (is_f64) {
    auto occ = make_occ<double>(K, M, Ko, static_cast<const double*>(faces), face_solid, face_closed, S, solid_faces,
                                solid_edge_off, solid_edges);
    return poly_fixed<double>(N, static_cast<const double*>(P), static_cast<const double*>(Nrm), K,
                              static_cast<const double*>(E), occ, threads, cap, cls, counts, runs);
  }
  auto occ = make_occ<float>(K, M, Ko, static_cast<const float*>(faces), face_solid, face_closed, S, solid_faces,
                             solid_edge_off, solid_edges);
  return poly_fixed<float>(N, static_cast<const float*>(P), static_cast<const float*>(Nrm), K,
                           static_cast<const float*>(E), occ, threads, cap, cls, counts, runs);
}

int jaxshadow_hard_plan(int is_f64, int64_t N, const void* P, const void* X, int is_point, int64_t K_unused,
                        JS_OCC_ARGS, int threads, uint8_t* visible) {
  (void)K_unused;
  if (is_f64) {
    auto occ = make_occ<double>(0, M, Ko, static_cast<const double*>(faces), face_solid, face_closed, S, solid_faces,
                                solid_edge_off, solid_edges);
    return hard_plan<double>(N, static_cast<const double*>(P), static_cast<const double*>(X), is_point, occ, threads,
                             visible);
  }
  auto occ = make_occ<float>(0, M, Ko, static_cast<const float*>(faces), face_solid, face_closed, S, solid_faces,
                             solid_edge_off, solid_edges);
  return hard_plan<float>(N, static_cast<const float*>(P), static_cast<const float*>(X), is_point, occ, threads,
                          visible);
}

int jaxshadow_segment_plan(int is_f64, int64_t N, const void* P, const void* A, const void* B, JS_OCC_ARGS,
                           int threads, int64_t* offsets, int32_t** faces_out) {
  if (is_f64) {
    auto occ = make_occ<double>(0, M, Ko, static_cast<const double*>(faces), face_solid, face_closed, S, solid_faces,
                                solid_edge_off, solid_edges);
    return segment_plan<double>(N, static_cast<const double*>(P), static_cast<const double*>(A),
                                static_cast<const double*>(B), occ, threads, offsets, faces_out);
  }
  auto occ = make_occ<float>(0, M, Ko, static_cast<const float*>(faces), face_solid, face_closed, S, solid_faces,
                             solid_edge_off, solid_edges);
  return segment_plan<float>(N, static_cast<const float*>(P), static_cast<const float*>(A),
                             static_cast<const float*>(B), occ, threads, offsets, faces_out);
}

}  // extern "C"

// ----------------------------------------------------------------------------------------------
// XLA FFI handler: the polygon combinatorics inside a compiled computation
// ----------------------------------------------------------------------------------------------
#ifdef JAXSHADOW_FFI
#include "xla/ffi/api/ffi.h"

namespace ffi = xla::ffi;

namespace {

// Inputs with a common leading batch shape (vmap_method="broadcast_all"): points (..., N, 3),
// normals (..., N, 3), light (..., K, 3), faces (..., M, Ko, 3), and the occluder topology
// (int32, batched alike). Outputs: classes (..., N), counts (..., N), runs (..., N, cap, 2, 7).
template <class T>
ffi::Error poly_ffi_typed(ffi::AnyBuffer points, ffi::AnyBuffer normals, ffi::AnyBuffer light, ffi::AnyBuffer faces,
                          ffi::Buffer<ffi::S32> face_solid, ffi::Buffer<ffi::S32> face_closed,
                          ffi::Buffer<ffi::S32> solid_faces, ffi::Buffer<ffi::S32> solid_edge_off,
                          ffi::Buffer<ffi::S32> solid_edges, int64_t cap, int64_t threads,
                          ffi::Result<ffi::Buffer<ffi::S32>> cls, ffi::Result<ffi::Buffer<ffi::S32>> counts,
                          ffi::Result<ffi::Buffer<ffi::S32>> runs) {
  auto pd = points.dimensions();
  auto ld_ = light.dimensions();
  auto fd = faces.dimensions();
  if (pd.size() < 2 || ld_.size() < 2 || fd.size() < 3) return ffi::Error::InvalidArgument("jaxshadow_poly_codes: bad ranks");
  const size_t nb = pd.size() - 2;
  if (ld_.size() != nb + 2 || fd.size() != nb + 3) return ffi::Error::InvalidArgument("jaxshadow_poly_codes: batch ranks differ");
  int64_t B = 1;
  for (size_t i = 0; i < nb; i++) B *= pd[i];
  const int64_t N = pd[nb], K = ld_[nb], M = fd[nb], Ko = fd[nb + 1];
  auto sd = solid_faces.dimensions();
  const int64_t S = sd[sd.size() - 2];
  auto ed = solid_edges.dimensions();
  const int64_t NE = ed[ed.size() - 2];
  const T* P = reinterpret_cast<const T*>(points.untyped_data());
  const T* Nr = reinterpret_cast<const T*>(normals.untyped_data());
  const T* E = reinterpret_cast<const T*>(light.untyped_data());
  const T* F = reinterpret_cast<const T*>(faces.untyped_data());
  for (int64_t b = 0; b < B; b++) {
    auto occ = make_occ<T>(K, M, Ko, F + b * M * Ko * 3, face_solid.typed_data() + b * M, face_closed.typed_data() + b * M,
                           S, solid_faces.typed_data() + b * 2 * S, solid_edge_off.typed_data() + b * (S + 1),
                           solid_edges.typed_data() + b * 4 * NE);
    int rc = poly_fixed<T>(N, P + b * N * 3, Nr + b * N * 3, K, E + b * K * 3, occ, int(threads), cap,
                           cls->typed_data() + b * N, counts->typed_data() + b * N, runs->typed_data() + b * N * cap * 14);
    if (rc) return ffi::Error::InvalidArgument("jaxshadow_poly_codes: light with more than 64 vertices");
  }
  return ffi::Error::Success();
}

ffi::Error poly_ffi(ffi::AnyBuffer points, ffi::AnyBuffer normals, ffi::AnyBuffer light, ffi::AnyBuffer faces,
                    ffi::Buffer<ffi::S32> face_solid, ffi::Buffer<ffi::S32> face_closed,
                    ffi::Buffer<ffi::S32> solid_faces, ffi::Buffer<ffi::S32> solid_edge_off,
                    ffi::Buffer<ffi::S32> solid_edges, int64_t cap, int64_t threads,
                    ffi::Result<ffi::Buffer<ffi::S32>> cls, ffi::Result<ffi::Buffer<ffi::S32>> counts,
                    ffi::Result<ffi::Buffer<ffi::S32>> runs) {
  if (points.element_type() == ffi::F64)
    return poly_ffi_typed<double>(points, normals, light, faces, face_solid, face_closed, solid_faces, solid_edge_off,
                                  solid_edges, cap, threads, cls, counts, runs);
  if (points.element_type() == ffi::F32)
    return poly_ffi_typed<float>(points, normals, light, faces, face_solid, face_closed, solid_faces, solid_edge_off,
                                 solid_edges, cap, threads, cls, counts, runs);
  return ffi::Error::InvalidArgument("jaxshadow_poly_codes: float32 or float64 only");
}

}  // namespace

XLA_FFI_DEFINE_HANDLER_SYMBOL(JaxshadowPolyCodes, poly_ffi,
                              ffi::Ffi::Bind()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::AnyBuffer>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Arg<ffi::Buffer<ffi::S32>>()
                                  .Attr<int64_t>("cap")
                                  .Attr<int64_t>("threads")
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>()
                                  .Ret<ffi::Buffer<ffi::S32>>());

extern "C" int jaxshadow_has_ffi(void) { return 1; }
#else
extern "C" int jaxshadow_has_ffi(void) { return 0; }
#endif

// An importable (empty) module, so that the package can locate the shared library.
static struct PyModuleDef shadowc_module = {PyModuleDef_HEAD_INIT, "_shadowc",
                                            "jaxshadow's shadow engine (ctypes and XLA FFI entry points).", -1,
                                            nullptr, nullptr, nullptr, nullptr, nullptr};
PyMODINIT_FUNC PyInit__shadowc(void) { return PyModule_Create(&shadowc_module); }
