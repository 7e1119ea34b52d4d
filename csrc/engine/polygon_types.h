// jaxshadow's shadow engine: polygon_types (part of `csrc/shadowc.cc`; see its header comment).
#ifndef JAXSHADOW_SHADOWC_POLYGON_TYPES_H_
#define JAXSHADOW_SHADOWC_POLYGON_TYPES_H_

#include "bvh.h"
#include "silhouette_types.h"
#include "umbra.h"
#include "umbra_sections.h"
#include "volume.h"

namespace jaxshadow_engine {


// ----------------------------------------------------------------------------------------------
// Polygon lights: one receiver
// ----------------------------------------------------------------------------------------------

template <class T>
struct Edge {
  V3<T> a, b;      // in the emitter plane
  V3<T> own;       // normal of the plane through p and the edge's line
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
  T xlo[3], xhi[3];  // box of its interior edges' pieces in the pyramid (not candidate edges)
};

struct Run {
  Code s, e;
};

// A group of receivers (groups.h): the box of their points and the items (slots, in the
// hierarchy's depth-first order) that may meet the pyramid of any of them, listed when a receiver
// of the group first queries the hierarchy (`group_list`; receivers on the silhouette path never do).
struct GroupList {
  double lo[3], hi[3];
  bool listed = false;
  std::vector<int32_t> items;
};

template <class T>
struct Work {  // per-thread scratch
  std::vector<std::pair<int32_t, int32_t>> cand;
  std::vector<V3<T>> planes;
  std::vector<T> pnorm;
  std::vector<T> pcond;  // per plane: through_condition (boundary.h)
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
  // Interior-edge culling (polygon_receiver): per face the side it is added with (+1 / -1, 0: not
  // added), set for the plain faces among the candidates and reset after each receiver.
  std::vector<int8_t> fstat;
  std::vector<int32_t> fstat_set;
  std::vector<FaceSide<T>> pre;  // per candidate: face_side of a plain face (side 0: dropped)
  // The silhouette path's scratch (silhouette.h).
  std::vector<SSeg<T>> ssegs;
  std::vector<T> sts;
  std::vector<int32_t> sord;
  std::vector<int32_t> std_;
  // Its grid of contour pieces in the emitter plane (silhouette_coverage.h, SilCoverage).
  std::vector<int32_t> gcells;   // per piece: the cells its box meets (ix0, ix1, iy0, iy1)
  std::vector<int32_t> gstart;   // per cell: first entry in gitems (CSR; G * G + 1)
  std::vector<int32_t> gitems;   // pieces by cell
  std::vector<V3<T>> gref;       // per cell: its reference point (inside E_h and the cell)
  std::vector<int32_t> gcov;     // per cell: C at the reference point (INT_MIN: none)
  std::vector<int32_t> gstamp;   // per piece: the last query that tested it
  std::vector<int32_t> gcand;    // one piece's crossing candidates
  std::vector<int8_t> gside;     // per entry of gitems: its piece's side of its cell's reference point (2: not yet)
  // off_plane_margin of the current receiver's E_h: boundary_runs widens its boxes by it.
  T eh_margin = 0;
  // Per receiver: the items the hierarchy returned (the silhouette path: contour edges in the
  // pyramid) and the occluder regions kept. A receiver of a group (groups.h) gets the items of its
  // group's list that pass its own box tests, so the count depends on the group's box: groups end
  // where the driver's blocks of receivers end, and blocks depend on the thread count. Classes and
  // boundaries do not (the exact tests drop the items that only a larger list holds).
  int32_t n_candidates = 0, n_regions = 0;
  // Whether a lit receiver's boundary (E_h's own edges) is wanted in `runs`: the fixed-capacity
  // (compiled) plan evaluates every receiver from its runs; the CSR plan evaluates lit receivers
  // with the unoccluded kernel, so a receiver that no item can block returns at once.
  bool lit_runs = true;
  // The current group of receivers (groups.h; null: the receiver queries the hierarchy itself).
  GroupList* group = nullptr;
  // The current receiver's tile (the driver's) and the contour walk's part of the hierarchy for
  // the last tile it served (silhouette_walk.h).
  SilTile tile;
  SilTileCache sil_tile;
  SilTileCache sil_parent;  // the walk of the tile's parent (SilTile::pid)
};

template <class T>
struct Light {
  int64_t K;
  const T* E;
  V3<T> v(int64_t i) const { return ld(E + 3 * i); }
};

// Cyrus-Beck of the segment a -> b against {x : (x - p).N >= 0} for the planes: (t0, t1, ok, i0, i1).
// `own`: the normal of the plane through p and the segment. A plane that holds the segment's line
// (its plane through p parallel to `own` within the collinear tolerance of boundary_runs, which
// decides with the same test) neither cuts nor drops it: its parameter there would be the ratio
// of two rounding errors, and the crossing point that of two coincident planes (a receiver on a
// face: the horizon holds the neighbouring faces' shared edges). boundary_runs' tie-break keeps
// one of the coincident edges (_clip._cyrus_beck).
template <class T>
inline bool cyrus_beck(V3<T> p, V3<T> a, V3<T> b, const V3<T>* pl, int np, V3<T> own, T& t0, T& t1, int& i0,
                       int& i1) {
  const T tol = T(kCollinearEps) * eps_of<T>();
  const V3<T> uo = normalize_safe(own);
  const T apn = norm(a - p) + norm(b - p);
  T tlo_best = -std::numeric_limits<T>::infinity(), thi_best = std::numeric_limits<T>::infinity();
  i0 = 0;
  i1 = 0;
  bool const_ok = true;
  T first_lo = 0, first_hi = 1;  // argmax/argmin over the full arrays (jnp semantics: first index)
  bool have_lo = false, have_hi = false;
  V3<T> ap = a - p, d = b - a;
  for (int k = 0; k < np; k++) {
    T g0 = dot(ap, pl[k]), g1 = dot(d, pl[k]);
    if (nonzero(pl[k])) {
      const T pn = norm(pl[k]);
      if (!(std::fabs(g0) > T(4) * tol * pn * apn) && !(std::fabs(g0 + g1) > T(4) * tol * pn * apn)) {
        const V3<T> cr = cross(uo, (T(1) / pn) * pl[k]);
        if (dot(cr, cr) <= tol * tol) g0 = g1 = 0;  // on the plane's line
      }
    }
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

// The largest coordinate distance between an E_h vertex and its central projection from p onto
// the emitter plane (through e0 with normal ne; hp = ne . (p - e0)). E_h's edges run between the
// light's own vertices, and a light that is planar only to rounding (float32 vertices of a tilted
// rectangle, or one vertex 1e-9 off: validation accepts both) has them off that plane, while the
// occluders' edges are projected onto it: boundary_runs compares their boxes, which must be
// widened by this much (a region otherwise missed an E_h edge by its 1e-9, and the edge was not
// split). Only the boxes: every membership test is made with planes through p.
template <class T>
inline T off_plane_margin(V3<T> p, const V3<T>* v, int n, V3<T> ne, T hp) {
  T m = 0;
  for (int i = 0; i < n; i++) m = std::max(m, absmax(project(p, v[i], ne, hp) - v[i]));
  return m == m ? m : std::numeric_limits<T>::infinity();
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

// Where the plane through p with normal m crosses light edge va vb's plane through p (normal c),
// met with the emitter plane. Planes within kNearPlanes of each other (sine of their angle: an
// occluder edge grazing the light edge's shadow line) are met along the edge: that point lies on
// the edge's line to rounding however nearly the planes coincide, where the cross product of
// their normals is off by eps over their angle (4e-6 U 1e-13 m off coincidence, light edges off
// the axes; `tests/test_exact_reference.py`). t is clamped to the edge, which a crossing of E_h's
// boundary leaves by rounding only. Others: the line common to the two planes.
constexpr double kNearPlanes = 1.0 / 1024;
// Whether the planes with normals c, m (x = c x m) are within kNearPlanes of each other.
template <class T>
inline bool near_planes(V3<T> x, V3<T> c, V3<T> m) {
  return dot(x, x) < T(kNearPlanes * kNearPlanes) * dot(c, c) * dot(m, m);
}
// Where the plane through p with normal m meets the segment va vb: va + t (vb - va),
// t = m.(va - p) / m.(va - vb) clamped to [0, 1].
template <class T>
inline V3<T> plane_meets_edge(V3<T> p, V3<T> va, V3<T> vb, V3<T> m) {
  const T da = dot(va - p, m), db = dot(vb - p, m);
  const T t = da != db ? std::min(std::max(da / (da - db), T(0)), T(1)) : T(0);
  return va + t * (vb - va);
}
template <class T>
inline V3<T> light_edge_crossing(V3<T> p, V3<T> va, V3<T> vb, V3<T> c, V3<T> m, V3<T> ne, T hp) {
  const V3<T> x = cross(c, m);
  if (!near_planes(x, c, m)) return crossing_point(p, x, ne, hp);
  return plane_meets_edge(p, va, vb, m);
}

// The sine of the angle the segment a b subtends at p (each difference brought to order one
// first, so that float32 neither under- nor overflows); NaN where an end is p.
template <class T>
inline T subtended_sine(V3<T> p, V3<T> a, V3<T> b) {
  V3<T> ra = a - p, rb = b - p;
  ra = (T(1) / absmax(ra)) * ra;
  rb = (T(1) / absmax(rb)) * rb;
  return norm(cross(ra, rb)) / (norm(ra) * norm(rb));
}

// Where the planes through p and two occluder edges a1 b1 (normal n1) and a2 b2 (normal n2)
// cross, met with the emitter plane, for planes within kNearPlanes of each other (two edges of
// different faces nearly in line as seen from p, their projections crossing at a small angle).
// The cross product of the normals is off by eps over the planes' angle, in a direction off
// both edges; here the vertex is where one edge's plane meets the other edge, projected from p:
// on that edge's line to rounding, and off the first edge's plane by that plane's own rounding
// only, eps times its conditioning (1 / the sine of the angle its edge subtends at p). So the
// plane is taken from the edge subtending the larger angle (the first on a tie) and the line
// from the other. The point is within the segment, as the crossing of two boundary pieces is.
template <class T>
inline V3<T> occluder_edges_crossing(V3<T> p, V3<T> a1, V3<T> b1, V3<T> n1, V3<T> a2, V3<T> b2, V3<T> n2, V3<T> ne,
                                     T hp) {
  const bool first_plane = !(subtended_sine(p, a1, b1) < subtended_sine(p, a2, b2));
  const V3<T> x = first_plane ? plane_meets_edge(p, a2, b2, n1) : plane_meets_edge(p, a1, b1, n2);
  return project(p, x, ne, hp);
}

// Where the plane through p with normal `own` crosses E_h's plane `r` (normal c), met with the
// emitter plane: a light edge's plane (light_edge_crossing) or the horizon's (the line common to
// the two planes). The clipped ends of occluder edges (polygon.h, silhouette_walk.h).
template <class T>
inline V3<T> eh_crossing(const Light<T>& L, const PlaneRef& r, V3<T> p, V3<T> c, V3<T> own, V3<T> ne, T hp) {
  if (r.t == kThrough) return light_edge_crossing(p, L.v(r.a), L.v(r.b), c, own, ne, hp);
  return crossing_point(p, cross(c, own), ne, hp);
}

template <class T>
struct PolyCall {
  Light<T> L;
  Occluders<T> occ;
  const BVH* bvh;
  // Per face, from the light alone (`light_side_of`): +1 all light vertices strictly in front of
  // the face's plane, -1 all strictly behind, 0 otherwise (a receiver strictly on that same side
  // cannot be shadowed by it: the plane separates the face from the receiver's pyramid). Computed
  // for every face by prepare_call for batches that test many faces, else per face when tested;
  // from the faces' Newell normals (`face_normal`: n (3) and |n| per face, `face_normals`).
  std::vector<int8_t> light_side;
  const double* face_normal = nullptr;
  int light_side_of(int64_t f) const;
  // The light's Newell normal (unscaled) and the largest coordinate magnitude of the hierarchy's
  // items (bounds rounding in quick_class).
  V3<T> ne_raw{0, 0, 0};
  double item_extent = 0;
  // The light's edges with distinct ends (their indices i: v_i -> v_{i+1}), in order.
  int32_t edge_index[64];
  int n_edges = 0;
  // The occlusion volume of the hierarchy's root box: a receiver outside it needs no query.
  OcclusionVolume volume;
  // Umbra volumes of the convex solids (prepare_umbra; none: not built): a receiver inside one is
  // umbra without building regions.
  UmbraVolumes umbra;
  // Per face edge slot f * Ko + i (the edge v_i -> v_{i+1}): 2 g + d when exactly one other face g
  // has an edge with the same two endpoints (exactly equal coordinates) and no third face does,
  // d = 1 when g runs it in the same direction; -1 otherwise. (The face path uses it for plain
  // faces only: a solid's faces have no side in Work::fstat.)
  const std::vector<int32_t>* twin_ptr = nullptr;
  const std::vector<int32_t>& twin() const { return *twin_ptr; }
  // The silhouette path's hierarchy of mesh edges (silhouette_tree.h; prepared.h) and the occluders'
  // heights above the emitter plane for this light (silhouette_heights); `sil_ok` false: not used.
  const SilhouetteTree* sil = nullptr;
  double sil_hmin = 0, sil_hmax = 0;
  bool sil_ok = false;
  // The interior sections' bodies usable with this light (umbra_sections.h; prepared.h).
  SectionCall sections;
  // Receivers that see all of the light decided before E_h (clear.h; set by the CSR plan where the
  // silhouette path may serve).
  bool clear_ok = false;
};

// The faces' edge twins (PolyCall::twin, prepared.h): one sort of the edge slots by their endpoints'
// coordinates (the lower endpoint first, lexicographically), O(M Ko log(M Ko)) per call.
template <class T>
std::vector<int32_t> edge_twins(const Occluders<T>& occ) {
  const int64_t M = occ.M, Ko = occ.Ko;
  std::vector<int32_t> twin(size_t(M * Ko), -1);
  if (M < 2) return twin;
  struct Key {
    T k[6];
    int32_t slot;
    int8_t fwd;
  };
  std::vector<Key> keys;
  keys.reserve(size_t(M * Ko));
  for (int64_t f = 0; f < M; f++) {
    for (int64_t i = 0; i < Ko; i++) {
      const V3<T> a = occ.vert(f, i), b = occ.vert(f, (i + 1) % Ko);
      if (same(a, b)) continue;
      const T ca[3] = {a.x, a.y, a.z}, cb[3] = {b.x, b.y, b.z};
      const bool fwd = std::lexicographical_compare(ca, ca + 3, cb, cb + 3);
      Key key;
      for (int d = 0; d < 3; d++) {
        key.k[d] = fwd ? ca[d] : cb[d];
        key.k[3 + d] = fwd ? cb[d] : ca[d];
      }
      key.slot = int32_t(f * Ko + i);
      key.fwd = int8_t(fwd);
      keys.push_back(key);
    }
  }
  auto less = [](const Key& x, const Key& y) {
    for (int d = 0; d < 6; d++)
      if (x.k[d] != y.k[d]) return x.k[d] < y.k[d];
    return x.slot < y.slot;
  };
  std::sort(keys.begin(), keys.end(), less);
  auto eq = [](const Key& x, const Key& y) {
    for (int d = 0; d < 6; d++)
      if (!(x.k[d] == y.k[d])) return false;
    return true;
  };
  for (size_t s = 0; s < keys.size();) {
    size_t e = s + 1;
    while (e < keys.size() && eq(keys[s], keys[e])) e++;
    if (e - s == 2) {
      const Key &x = keys[s], &y = keys[s + 1];
      const int32_t fx = int32_t(x.slot / Ko), fy = int32_t(y.slot / Ko);
      if (fx != fy) {
        const int32_t d = x.fwd == y.fwd ? 1 : 0;
        twin[size_t(x.slot)] = 2 * fy + d;
        twin[size_t(y.slot)] = 2 * fx + d;
      }
    }
    s = e;
  }
  return twin;
}

// Per face its Newell normal about its first vertex and that normal's length (M, 4): what
// `light_side_of` reads, from the occluders alone (prepared.h keeps it with the occluder set).
template <class T>
std::vector<double> face_normals(const Occluders<T>& occ) {
  std::vector<double> out(size_t(4 * occ.M));
  for (int64_t f = 0; f < occ.M; f++) {
    V3<T> o = occ.vert(f, 0), n{0, 0, 0};
    for (int64_t i = 0; i < occ.Ko; i++) n = n + cross(occ.vert(f, i) - o, occ.vert(f, (i + 1) % occ.Ko) - o);
    double* q = out.data() + 4 * f;
    q[0] = double(n.x), q[1] = double(n.y), q[2] = double(n.z), q[3] = double(norm(n));
  }
  return out;
}

template <class T>
int PolyCall<T>::light_side_of(int64_t f) const {
  if (!light_side.empty()) return light_side[size_t(f)];
  const double* q = face_normal + 4 * f;
  const V3<T> o = occ.vert(f, 0), n{T(q[0]), T(q[1]), T(q[2])};
  const T nn = T(q[3]);
  if (!(nn > 0)) return 0;
  bool pos = true, neg = true;
  for (int64_t i = 0; i < L.K; i++) {
    V3<T> r = L.v(i) - o;
    T h = dot(r, n), m = T(1e3) * eps_of<T>() * nn * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z) + absmax(o));
    pos = pos && h > m;
    neg = neg && h < -m;
  }
  return pos ? 1 : (neg ? -1 : 0);
}

// Per-call data of the light and the occluders (`ne_raw`, `edge_index`, `item_extent`, and
// `light_side` for every face when `every_side`: a batch whose receivers test more faces than
// there are; otherwise each face's side is computed when a receiver tests it). `call.face_normal`
// must be set (`face_normals`).
template <class T>
void prepare_call(PolyCall<T>& call, bool every_side) {
  const int64_t K = call.L.K;
  call.ne_raw = V3<T>{0, 0, 0};
  for (int64_t i = 0; i < K; i++) call.ne_raw = call.ne_raw + cross(call.L.v(i), call.L.v((i + 1) % K));
  call.n_edges = 0;
  for (int64_t i = 0; i < K && i < 64; i++)
    if (!same(call.L.v(i), call.L.v((i + 1) % K))) call.edge_index[call.n_edges++] = int32_t(i);
  call.item_extent = 0;
  if (!call.bvh->nodes.empty()) {
    for (int d = 0; d < 3; d++)
      call.item_extent = std::max(call.item_extent, std::max(std::fabs(call.bvh->nodes[0].box[d]), std::fabs(call.bvh->nodes[0].box[3 + d])));
    std::vector<double> lv(3 * K);
    for (int64_t i = 0; i < 3 * K; i++) lv[i] = double(call.L.E[i]);
    const double ne[3] = {double(call.ne_raw.x), double(call.ne_raw.y), double(call.ne_raw.z)};
    call.volume = occlusion_volume(lv.data(), K, ne, call.bvh->nodes[0].box, double(eps_of<T>()));
  }
  call.light_side.clear();
  if (!every_side) return;
  std::vector<int8_t> side(size_t(call.occ.M));
  for (int64_t f = 0; f < call.occ.M; f++) side[size_t(f)] = int8_t(call.light_side_of(f));
  call.light_side.swap(side);
}

// The solids' umbra volumes for `call` (after prepare_call), for batches of at least
// kUmbraMinReceivers receivers.
template <class T>
void prepare_umbra(PolyCall<T>& call) {
  if (call.bvh->nodes.empty()) return;
  const int64_t K = call.L.K;
  std::vector<double> lv(3 * K);
  for (int64_t i = 0; i < 3 * K; i++) lv[i] = double(call.L.E[i]);
  const double ne[3] = {double(call.ne_raw.x), double(call.ne_raw.y), double(call.ne_raw.z)};
  call.umbra = umbra_volumes(call.occ, *call.bvh, lv.data(), K, ne, double(eps_of<T>()));
}

// Side of p against face f's plane (+1 / -1 strictly, 0 too close to tell), measured as prepare_call measures the light's vertices.
template <class T>
inline int point_side(const Occluders<T>& occ, int64_t f, V3<T> p) {
  V3<T> o = occ.vert(f, 0), n{0, 0, 0};
  for (int64_t i = 0; i < occ.Ko; i++) n = n + cross(occ.vert(f, i) - o, occ.vert(f, (i + 1) % occ.Ko) - o);
  V3<T> r = p - o;
  T h = dot(r, n), m = T(1e3) * eps_of<T>() * norm(n) * (std::fabs(r.x) + std::fabs(r.y) + std::fabs(r.z) + absmax(o));
  return h > m ? 1 : (h < -m ? -1 : 0);
}


}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_POLYGON_TYPES_H_
