// jaxshadow's shadow engine: the silhouette path's hierarchy (part of `csrc/shadowc.cc`; see
// silhouette.h): the mesh's edges with their faces (T-junctions paired), a tree whose nodes bound
// their faces' planes (a box of the faces' vertices and a cone of their normals), built once per
// occluder set; the occluders' heights above the emitter plane per light; and the side tests of a
// face and of a node against a receiver.
#ifndef JAXSHADOW_SHADOWC_SILHOUETTE_TREE_H_
#define JAXSHADOW_SHADOWC_SILHOUETTE_TREE_H_

#include <array>
#include <map>

#include "polygon_types.h"

namespace jaxshadow_engine {

// T-junctions: edges without a twin that overlap along one line, such as an edge a -> c of one
// face and c -> b -> a of faces on the other side (coplanar merging leaves them where it drops a
// straight vertex of the merged face that a neighbour across a crease keeps). Such a group is
// cut at every end of its edges (each cut point within 1e-9 of the line's length of the line),
// and where every piece then runs against exactly one piece of another face, the pieces are
// paired as interior edges, as on a mesh without the junction, instead of boundary edges
// overlapping each other (collinear contour edges that no receiver can decide). Any other group
// is left as it is.
template <class T>
void resolve_t_junctions(const Occluders<T>& occ, std::vector<SEdge>& edges) {
  std::vector<int32_t> open;
  for (size_t k = 0; k < edges.size(); k++)
    if (edges[k].g < 0) open.push_back(int32_t(k));
  if (open.size() < 3) return;
  using Key = std::array<double, 3>;
  auto key = [&](int32_t r) {
    const V3<T> x = occ.vref(r);
    return Key{double(x.x), double(x.y), double(x.z)};
  };
  std::map<Key, std::vector<int32_t>> at;  // untwinned edges by the positions of their ends
  for (const int32_t k : open) {
    at[key(edges[size_t(k)].ra)].push_back(k);
    at[key(edges[size_t(k)].rb)].push_back(k);
  }
  std::vector<uint8_t> done(edges.size(), 0), used(edges.size(), 0);
  std::vector<SEdge> added;
  std::vector<int32_t> group, todo;
  struct Cut {
    double t;
    int32_t ref;
  };
  std::vector<Cut> cuts;
  for (const int32_t x : open) {
    if (done[size_t(x)]) continue;
    const V3<T> a = occ.vref(edges[size_t(x)].ra), ac = occ.vref(edges[size_t(x)].rb) - a;
    const double len2 = double(dot(ac, ac));
    done[size_t(x)] = 1;
    if (!(len2 > 0)) continue;
    auto param = [&](int32_t r, double& t) {  // r's position along a -> c; false: off the line
      const V3<T> ab = occ.vref(r) - a;
      t = double(dot(ab, ac)) / len2;
      const V3<T> off = ab - T(t) * ac;
      return double(dot(off, off)) < 1e-18 * len2;
    };
    // The group: untwinned edges on the line reached through shared end positions.
    group.assign(1, x);
    todo.assign(1, x);
    bool ok = true;
    while (!todo.empty() && ok) {
      const SEdge e = edges[size_t(todo.back())];
      todo.pop_back();
      for (const int32_t r : {e.ra, e.rb})
        for (const int32_t y : at[key(r)]) {
          if (done[size_t(y)]) continue;
          double ta, tb;
          if (!param(edges[size_t(y)].ra, ta) || !param(edges[size_t(y)].rb, tb)) continue;  // another line
          done[size_t(y)] = 1;
          group.push_back(y);
          todo.push_back(y);
          if (group.size() > 256) ok = false;
        }
    }
    if (!ok || group.size() < 3) continue;
    cuts.clear();
    for (const int32_t y : group)
      for (const int32_t r : {edges[size_t(y)].ra, edges[size_t(y)].rb}) {
        double t;
        param(r, t);
        cuts.push_back({t, r});
      }
    std::sort(cuts.begin(), cuts.end(), [](const Cut& u, const Cut& v) { return u.t < v.t; });
    // One cut per position (the first reference of it), all positions apart along the line.
    std::vector<Cut> pts;
    for (const Cut& u : cuts) {
      if (!pts.empty() && key(pts.back().ref) == key(u.ref)) continue;
      if (!pts.empty() && !(u.t > pts.back().t + 1e-9)) {
        ok = false;
        break;
      }
      pts.push_back(u);
    }
    if (!ok) continue;
    auto index_of = [&](int32_t r) {
      const Key kr = key(r);
      for (size_t i = 0; i < pts.size(); i++)
        if (key(pts[i].ref) == kr) return int(i);
      return -1;
    };
    // Per interval between consecutive cuts: the edge running along the line, the one against it.
    const int nI = int(pts.size()) - 1;
    std::vector<int32_t> fwd(size_t(nI), -1), bwd(size_t(nI), -1);
    for (const int32_t y : group) {
      const int ia = index_of(edges[size_t(y)].ra), ib = index_of(edges[size_t(y)].rb);
      if (ia < 0 || ib < 0 || ia == ib) ok = false;
      std::vector<int32_t>& side = ia < ib ? fwd : bwd;
      for (int i = std::min(ia, ib); ok && i < std::max(ia, ib); i++) {
        if (side[size_t(i)] >= 0) ok = false;
        side[size_t(i)] = y;
      }
      if (!ok) break;
    }
    for (int i = 0; ok && i < nI; i++)
      ok = fwd[size_t(i)] >= 0 && bwd[size_t(i)] >= 0 && edges[size_t(fwd[size_t(i)])].f != edges[size_t(bwd[size_t(i)])].f;
    if (!ok) continue;
    // Each interval an interior edge of the face running along the line and the one against it;
    // a piece's ends are its own edge's references where they are its ends.
    for (int i = 0; i < nI; i++) {
      const SEdge& ef = edges[size_t(fwd[size_t(i)])];
      const int32_t ra = index_of(ef.ra) == i ? ef.ra : pts[size_t(i)].ref;
      const int32_t rb = index_of(ef.rb) == i + 1 ? ef.rb : pts[size_t(i + 1)].ref;
      added.push_back(SEdge{ra, rb, ef.f, edges[size_t(bwd[size_t(i)])].f, int8_t(-1)});
    }
    for (const int32_t y : group) used[size_t(y)] = 1;
  }
  if (added.empty()) return;
  std::vector<SEdge> kept;
  kept.reserve(edges.size() + added.size());
  for (size_t k = 0; k < edges.size(); k++)
    if (!used[k]) kept.push_back(edges[k]);
  kept.insert(kept.end(), added.begin(), added.end());
  edges.swap(kept);
}

template <class T>
void build_silhouette_tree(const Occluders<T>& occ, const std::vector<int32_t>& twin, SilhouetteTree& st) {
  st = SilhouetteTree();
  const int64_t M = occ.M, Ko = occ.Ko;
  if (M < kSilhouetteMinFaces || Ko > 64 || twin.size() != size_t(M * Ko)) return;
  st.fn.assign(kFnStride * size_t(M), 0.0);
  for (int64_t f = 0; f < M; f++) {
    V3<T> o = occ.vert(f, 0), n{0, 0, 0};
    for (int64_t i = 0; i < Ko; i++) {
      const V3<T> x = occ.vert(f, i);
      n = n + cross(x - o, occ.vert(f, (i + 1) % Ko) - o);
      if (!(double(absmax(x)) < std::numeric_limits<double>::infinity())) return;
      st.scale = std::max(st.scale, double(absmax(x)));
    }
    const double nn = double(norm(n));
    if (!(nn > 0)) return;  // a degenerate face: the face path
    double* q = st.fn.data() + kFnStride * size_t(f);
    q[0] = n.x, q[1] = n.y, q[2] = n.z, q[3] = o.x, q[4] = o.y, q[5] = o.z;
    q[6] = n.x / nn, q[7] = n.y / nn, q[8] = n.z / nn;
    q[9] = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]);  // as sil_side would compute it
  }
  for (int64_t f = 0; f < M; f++)
    for (int64_t i = 0; i < Ko; i++) {
      if (same(occ.vert(f, i), occ.vert(f, (i + 1) % Ko))) continue;
      const int32_t t = twin[size_t(f * Ko + i)];
      SEdge e{occ.ref(f, i), occ.ref(f, (i + 1) % Ko), int32_t(f), -1, 0};
      if (t >= 0) {
        if ((t >> 1) < f) continue;  // recorded from the other face
        e.g = t >> 1;
        e.dg = (t & 1) ? int8_t(1) : int8_t(-1);
      }
      st.edges.push_back(e);
    }
  resolve_t_junctions(occ, st.edges);
  // Build: sort by the edge midpoints along the box's longest axis, split at the median.
  const int64_t E = int64_t(st.edges.size());
  std::vector<double> mid(size_t(3 * E));
  for (int64_t k = 0; k < E; k++) {
    const V3<T> a = occ.vref(st.edges[k].ra), b = occ.vref(st.edges[k].rb);
    mid[3 * k] = 0.5 * (double(a.x) + double(b.x));
    mid[3 * k + 1] = 0.5 * (double(a.y) + double(b.y));
    mid[3 * k + 2] = 0.5 * (double(a.z) + double(b.z));
  }
  // The edges grouped by connected component (faces joined through paired edges), components in
  // the order of their first edge, each keeping its edges' order: each component gets a subtree
  // of its own, built from its edges alone, and the components are joined above them by index
  // (not by position). A component's subtree, and the walk's order of its edges, then do not
  // depend on where the other components lie, so moving one object leaves every other object's
  // contour edges in the same order (ShadowCache.update equals a rebuild bit for bit).
  std::vector<int32_t> order(static_cast<size_t>(E));
  std::vector<int32_t> cstart;  // component c's edges: order[cstart[c] .. cstart[c + 1])
  {
    const std::vector<int32_t> root = face_components(st.edges, M);
    std::vector<int32_t> rank(static_cast<size_t>(M), -1), ecomp(static_cast<size_t>(E));
    for (int64_t k = 0; k < E; k++) {
      const int32_t r = root[size_t(st.edges[size_t(k)].f)];
      if (rank[size_t(r)] < 0) rank[size_t(r)] = int32_t(cstart.size()), cstart.push_back(0);
      ecomp[size_t(k)] = rank[size_t(r)];
      cstart[size_t(ecomp[size_t(k)])]++;
    }
    int32_t at = 0;
    for (int32_t& c : cstart) {
      const int32_t n = c;
      c = at;
      at += n;
    }
    cstart.push_back(at);
    std::vector<int32_t> fill_at(cstart.begin(), cstart.end() - 1);
    for (int64_t k = 0; k < E; k++) order[size_t(fill_at[size_t(ecomp[size_t(k)])]++)] = int32_t(k);
  }
  // Per edge: the box of its faces' vertices (a node's box is the min/max over its edges' boxes,
  // the same values as over their faces' vertices), read once instead of once per tree level.
  std::vector<double> ebox(size_t(6 * E));
  for (int64_t k = 0; k < E; k++) {
    double* b = ebox.data() + 6 * k;
    for (int d = 0; d < 3; d++) {
      b[d] = std::numeric_limits<double>::infinity();
      b[3 + d] = -std::numeric_limits<double>::infinity();
    }
    for (const int32_t f : {st.edges[size_t(k)].f, st.edges[size_t(k)].g}) {
      if (f < 0) continue;
      for (int64_t i = 0; i < Ko; i++) {
        const V3<T> x = occ.vert(f, i);
        const double c[3] = {double(x.x), double(x.y), double(x.z)};
        for (int d = 0; d < 3; d++) {
          b[d] = std::min(b[d], c[d]);
          b[3 + d] = std::max(b[3 + d], c[d]);
        }
      }
    }
  }
  auto fill = [&](SNode& nd) {  // box, cone and flag from the node's edges' faces
    for (int d = 0; d < 3; d++) {
      nd.box[d] = std::numeric_limits<double>::infinity();
      nd.box[3 + d] = -std::numeric_limits<double>::infinity();
    }
    double ax[3] = {0, 0, 0};
    nd.special = false;
    for (int32_t k = nd.start; k < nd.start + nd.count; k++) {
      const SEdge& e = st.edges[order[k]];
      const double* b = ebox.data() + 6 * size_t(order[k]);
      for (int d = 0; d < 3; d++) {
        nd.box[d] = std::min(nd.box[d], b[d]);
        nd.box[3 + d] = std::max(nd.box[3 + d], b[3 + d]);
      }
      for (int d = 0; d < 3; d++) ax[d] += st.fn[kFnStride * size_t(e.f) + 6 + d];
      if (e.g >= 0)
        for (int d = 0; d < 3; d++) ax[d] += st.fn[kFnStride * size_t(e.g) + 6 + d];
      nd.special = nd.special || e.g < 0 || e.dg > 0;
    }
    const double an = std::sqrt(ax[0] * ax[0] + ax[1] * ax[1] + ax[2] * ax[2]);
    nd.cosa = -1;
    nd.sina = 1;
    if (!(an > 0)) return;
    for (int d = 0; d < 3; d++) nd.axis[d] = ax[d] / an;
    double cmin = 1;
    auto cone = [&](int32_t f) {
      const double* u = st.fn.data() + kFnStride * size_t(f) + 6;
      cmin = std::min(cmin, u[0] * nd.axis[0] + u[1] * nd.axis[1] + u[2] * nd.axis[2]);
    };
    for (int32_t k = nd.start; k < nd.start + nd.count; k++) {
      cone(st.edges[order[k]].f);
      if (st.edges[order[k]].g >= 0) cone(st.edges[order[k]].g);
    }
    cmin = std::max(-1.0, std::min(1.0, cmin)) - 1e-12;  // rounding of the unit normals
    nd.cosa = cmin;
    nd.sina = std::sqrt(std::max(0.0, 1 - cmin * cmin)) + 1e-12;
    double h2 = 0;
    nd.arad = 0;
    for (int d = 0; d < 3; d++) {
      const double h = 0.5 * (nd.box[3 + d] - nd.box[d]);
      nd.arad += std::fabs(nd.axis[d]) * h;
      h2 += h * h;
    }
    nd.hrad = std::sqrt(h2);
  };
  st.nodes.reserve(size_t(2 * E / 4 + 2));
  struct Job {
    int32_t node, start, count, c0, c1;  // components [c0, c1) (one: split inside it)
  };
  std::vector<Job> jobs;
  st.nodes.push_back(SNode{});
  jobs.push_back({0, 0, int32_t(E), 0, int32_t(cstart.size()) - 1});
  while (!jobs.empty()) {
    const Job jb = jobs.back();
    jobs.pop_back();
    SNode nd{};
    nd.start = jb.start;
    nd.count = jb.count;
    nd.left = nd.right = -1;
    fill(nd);
    if (jb.c1 - jb.c0 > 1) {  // several components: split the list of them in the middle
      const int32_t cm = jb.c0 + (jb.c1 - jb.c0) / 2;
      nd.left = int32_t(st.nodes.size());
      st.nodes.push_back(SNode{});
      nd.right = int32_t(st.nodes.size());
      st.nodes.push_back(SNode{});
      jobs.push_back({nd.left, jb.start, cstart[size_t(cm)] - jb.start, jb.c0, cm});
      jobs.push_back({nd.right, cstart[size_t(cm)], jb.start + jb.count - cstart[size_t(cm)], cm, jb.c1});
    } else if (jb.count > 4) {
      int ax = 0;
      double ext = -1;
      for (int d = 0; d < 3; d++)
        if (nd.box[3 + d] - nd.box[d] > ext) ext = nd.box[3 + d] - nd.box[d], ax = d;
      const int32_t half = jb.count / 2;
      std::nth_element(order.begin() + jb.start, order.begin() + jb.start + half, order.begin() + jb.start + jb.count,
                       [&](int32_t x, int32_t y) { return mid[3 * size_t(x) + ax] < mid[3 * size_t(y) + ax]; });
      nd.left = int32_t(st.nodes.size());
      st.nodes.push_back(SNode{});
      nd.right = int32_t(st.nodes.size());
      st.nodes.push_back(SNode{});
      jobs.push_back({nd.left, jb.start, half, jb.c0, jb.c1});
      jobs.push_back({nd.right, jb.start + half, jb.count - half, jb.c0, jb.c1});
    }
    st.nodes[size_t(jb.node)] = nd;
  }
  std::vector<SEdge> sorted(static_cast<size_t>(E));
  for (int64_t k = 0; k < E; k++) sorted[k] = st.edges[order[k]];
  st.edges.swap(sorted);
  // The nodes in the order the walk visits them (right subtree first, as its stack pops them):
  // a walk reads them front to back.
  {
    std::vector<SNode> walk;
    walk.reserve(st.nodes.size());
    std::vector<int32_t> stk{0};
    std::vector<int32_t> where(st.nodes.size());
    while (!stk.empty()) {
      const int32_t k = stk.back();
      stk.pop_back();
      where[size_t(k)] = int32_t(walk.size());
      walk.push_back(st.nodes[size_t(k)]);
      if (st.nodes[size_t(k)].left >= 0) {
        stk.push_back(st.nodes[size_t(k)].left);
        stk.push_back(st.nodes[size_t(k)].right);
      }
    }
    for (SNode& nd : walk)
      if (nd.left >= 0) nd.left = where[size_t(nd.left)], nd.right = where[size_t(nd.right)];
    st.nodes.swap(walk);
  }
  std::vector<uint8_t> f32(static_cast<size_t>(M));
  for (int64_t f = 0; f < M; f++) f32[size_t(f)] = float32_face(occ, f);
  // Local face indices: in the order of the sorted edges, then the faces no edge names.
  st.floc.assign(size_t(M), -1);
  int32_t nl = 0;
  for (SEdge& e : st.edges)
    for (int32_t* f : {&e.f, &e.g}) {
      if (*f < 0) continue;
      if (st.floc[size_t(*f)] < 0) st.floc[size_t(*f)] = nl++;
      *f = st.floc[size_t(*f)];
    }
  for (int64_t f = 0; f < M; f++)
    if (st.floc[size_t(f)] < 0) st.floc[size_t(f)] = nl++;
  std::vector<double> fn(st.fn.size());
  st.f32.resize(size_t(M));
  st.fglob.resize(size_t(M));
  for (int64_t f = 0; f < M; f++) {
    const size_t l = size_t(st.floc[size_t(f)]);
    st.fglob[l] = int32_t(f);
    std::copy_n(st.fn.data() + kFnStride * size_t(f), kFnStride, fn.data() + kFnStride * l);
    st.f32[l] = f32[size_t(f)];
  }
  st.fn.swap(fn);
  st.ok = true;
}

// The occluders' heights above the emitter plane (ne . (x - e0)) for one light: whether the
// silhouette path may serve this call (`call.sil_ok`) and its bounds. `verts` (nullable): the
// distinct vertex slots of the faces, first occurrences in slot order (`distinct_vertices`), which
// give the same bounds as every slot.
template <class T>
void silhouette_heights(PolyCall<T>& call, const std::vector<int64_t>* verts = nullptr) {
  call.sil_ok = false;
  if (!call.sil || !call.sil->ok) return;
  // JAXSHADOW_SILHOUETTE=0 switches the path off (every receiver takes the face path): for
  // measuring one against the other, and for tests that compare them. Read per call (the
  // prepared data are cached across calls).
  const char* env = std::getenv("JAXSHADOW_SILHOUETTE");
  if (env && env[0] == '0') return;
  const Occluders<T>& occ = call.occ;
  const V3<T> ne = call.ne_raw, e0 = call.L.v(0);
  double lo = std::numeric_limits<double>::infinity(), hi = -lo;
  const int64_t n = verts ? int64_t(verts->size()) : occ.M * occ.Ko;
  for (int64_t j = 0; j < n; j++) {
    const int64_t k = verts ? (*verts)[size_t(j)] : j;
    const double h = double(dot(ne, ld(occ.faces + 3 * k) - e0));
    lo = std::min(lo, h);
    hi = std::max(hi, h);
  }
  call.sil_hmin = lo;
  call.sil_hmax = hi;
  call.sil_ok = std::isfinite(lo) && std::isfinite(hi);
}

// Which way face f (a local index: SilhouetteTree::floc) faces p: +1 when p is in front of its Newell normal... as face_side decides
// (+1: h0 = N . (v0 - p) < 0), 0 when p is within the rounding bound of its plane.
// Within the on-surface distance of the plane of a face of float32 values (kOnSurface of the
// scene's largest coordinate, at least face_side's own bound) it is 0 too: the face path then
// applies the on-surface rule.
// `S`: sil_scale(st, p), for callers that test many faces from one p.
inline double sil_scale(const SilhouetteTree& st, const double* p) {
  return std::max(st.scale, std::max(std::fabs(p[0]), std::max(std::fabs(p[1]), std::fabs(p[2]))));
}
inline int sil_side(const SilhouetteTree& st, int32_t f, const double* p, double S) {
  const double* q = st.fn.data() + kFnStride * size_t(f);
  const double r0 = q[3] - p[0], r1 = q[4] - p[1], r2 = q[5] - p[2];
  const double h = q[0] * r0 + q[1] * r1 + q[2] * r2;
  const double nn = q[9];
  const double m = std::max(1e4 * 2.220446049250313e-16 * (std::fabs(r0) + std::fabs(r1) + std::fabs(r2) + S),
                            st.f32[size_t(f)] ? 2 * kOnSurface * S : 0.0) * nn;
  return int(h < -m) - int(h > m);  // both comparisons, no branch
}
inline int sil_side(const SilhouetteTree& st, int32_t f, const double* p) { return sil_side(st, f, p, sil_scale(st, p)); }

// Where sil_side cannot tell (0) for face f (a local index) of float32 values: the face path's
// own decision, face_side's side (the on-surface rule included), in `side`: +1 / -1, or 0 where
// the face path drops the face (p within the on-surface distance of its plane, a normal its
// rounding leaves undetermined), which then covers nothing: C counts the faces the face path
// keeps. sil_side's band (twice the on-surface distance of the scene's largest coordinate, 1e4
// eps) holds face_side's, so elsewhere the two agree. A float32 mesh has its on-surface band
// (2^-17 S) across many faces' planes far from p, where the face path still decides every face.
// False for other faces (the caller falls back).
template <class T>
inline bool face_path_side(const Occluders<T>& occ, const SilhouetteTree& st, int32_t f, V3<T> p, int& side) {
  if (!st.f32[size_t(f)] || occ.Ko > 64) return false;
  V3<T> rel[64];
  side = face_side(occ, st.fglob[size_t(f)], p, rel).side;
  return true;
}

// +1 (-1): every face of the node faces p with side +1 (-1) by a clear margin; 0: not known.
inline int node_side(const SNode& nd, const double* p, double margin) {
  if (!(nd.cosa > 0)) return 0;
  // d = p - v over the box's points v = c + s (|s_i| <= h_i): a = axis . d lies within
  // axis . (p - c) -+ arad, and d's part across the axis, e = d - a axis, has |e| <= |e_c| + |h|.
  const double d[3] = {p[0] - 0.5 * (nd.box[0] + nd.box[3]), p[1] - 0.5 * (nd.box[1] + nd.box[4]),
                       p[2] - 0.5 * (nd.box[2] + nd.box[5])};
  const double a = d[0] * nd.axis[0] + d[1] * nd.axis[1] + d[2] * nd.axis[2];
  const double e[3] = {d[0] - a * nd.axis[0], d[1] - a * nd.axis[1], d[2] - a * nd.axis[2]};
  const double perp = std::sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2]) + nd.hrad;
  // n . d with n within the cone: n . d >= a cos - |e| sin. The bounds' rounding is far below
  // `margin` (beyond the on-surface distance).
  // side +1 <=> N . (v - p) < 0 <=> n . d > 0.
  if ((a - nd.arad) * nd.cosa - perp * nd.sina > margin) return 1;
  if ((a + nd.arad) * nd.cosa + perp * nd.sina < -margin) return -1;
  return 0;
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_SILHOUETTE_TREE_H_
