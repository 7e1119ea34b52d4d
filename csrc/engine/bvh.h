// jaxshadow's shadow engine: bvh (part of `csrc/shadowc.cc`; see its header comment).
#ifndef JAXSHADOW_SHADOWC_BVH_H_
#define JAXSHADOW_SHADOWC_BVH_H_

#include "geometry.h"

namespace jaxshadow_engine {


// ----------------------------------------------------------------------------------------------
// Bounding-volume hierarchy over items (a face that is not part of a solid, or a solid)
// ----------------------------------------------------------------------------------------------

struct Node {
  double box[6];  // lo[3], hi[3]
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
      nd.box[d] = clo[d] = std::numeric_limits<double>::infinity();
      nd.box[3 + d] = chi[d] = -std::numeric_limits<double>::infinity();
    }
    for (int32_t i = t.start; i < t.start + t.count; i++)
      for (int d = 0; d < 3; d++) {
        nd.box[d] = std::min(nd.box[d], its[i].lo[d]);
        nd.box[3 + d] = std::max(nd.box[3 + d], its[i].hi[d]);
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
// -margin * |N|_1 (the margin, a bound on the rounding of the planes and the coordinates, keeps
// touching items).
struct HalfSpace {
  double n[3], q[3];
};

// A half-space prepared for box tests: the box's farthest corner along n is read as
// lo_hi[sel[d] + d] (lo at 0..2, hi at 3..5), rejected below `thr`.
struct BoxPlane {
  double n[3];
  int sel[3];
  double thr;  // n.q - margin |n|_1
};

inline int prepare_planes(const HalfSpace* hs, int nh, double margin, BoxPlane* out) {
  for (int i = 0; i < nh; i++) {
    double nq = 0, n1 = 0;
    for (int d = 0; d < 3; d++) {
      out[i].n[d] = hs[i].n[d];
      out[i].sel[d] = hs[i].n[d] >= 0 ? 3 : 0;
      nq += hs[i].n[d] * hs[i].q[d];
      n1 += std::fabs(hs[i].n[d]);
    }
    out[i].thr = nq - margin * n1;
  }
  return nh;
}

inline bool outside6(const double* lo_hi, const BoxPlane& b) {
  return b.n[0] * lo_hi[b.sel[0]] + b.n[1] * lo_hi[b.sel[1] + 1] + b.n[2] * lo_hi[b.sel[2] + 2] < b.thr;
}

// Depth-first over the hierarchy: `visit(item slot)` for every item no plane rejects; it returns
// false to stop. `make(i)` gives half-space i; each is prepared on first use only (a receiver whose
// pyramid misses the root's box is mostly rejected by its first plane or two). Which items are
// visited does not depend on the order in which planes are tested.
template <class Make, class F>
inline void traverse_lazy(const BVH& bvh, int nh, double margin, Make make, F visit) {
  if (bvh.nodes.empty()) return;
  BoxPlane bp[72];
  if (nh > 72) nh = 72;
  int ready = 0;
  auto plane = [&](int i) -> const BoxPlane& {
    while (ready <= i) {
      const HalfSpace h = make(ready);
      prepare_planes(&h, 1, margin, bp + ready);
      ready++;
    }
    return bp[i];
  };
  int32_t stack[256];  // median splits: depth ~ log2(M)
  int sp = 0;
  stack[sp++] = 0;
  while (sp) {
    const Node& nd = bvh.nodes[stack[--sp]];
    bool rej = false;
    for (int i = 0; i < nh && !rej; i++) rej = outside6(nd.box, plane(i));
    if (rej) continue;
    if (nd.left < 0) {
      for (int32_t i = nd.start; i < nd.start + nd.count; i++) {
        const double* b = bvh.ibox.data() + 6 * i;
        bool r2 = false;
        for (int k = 0; k < nh && !r2; k++) r2 = outside6(b, bp[k]);
        if (!r2 && !visit(i)) return;
      }
    } else {
      stack[sp++] = nd.left;
      stack[sp++] = nd.right;
    }
  }
}

// `visit(slot)` for the item slots of `slots` (in their order) that no half-space rejects: the
// leaf test of traverse_lazy on a ready list of items. With a list that holds every item
// traverse_lazy would visit, the same items in the same order.
template <class Make, class F>
inline void filter_lazy(const BVH& bvh, const int32_t* slots, size_t n, int nh, double margin, Make make, F visit) {
  BoxPlane bp[72];
  if (nh > 72) nh = 72;
  int ready = 0;
  for (size_t j = 0; j < n; j++) {
    const double* b = bvh.ibox.data() + 6 * slots[j];
    bool r = false;
    for (int k = 0; k < nh && !r; k++) {
      while (ready <= k) {
        const HalfSpace h = make(ready);
        prepare_planes(&h, 1, margin, bp + ready);
        ready++;
      }
      r = outside6(b, bp[k]);
    }
    if (!r && !visit(slots[j])) return;
  }
}

template <class Make>
inline void query_lazy(const BVH& bvh, int nh, double margin, Make make, std::vector<std::pair<int32_t, int32_t>>& out) {
  out.clear();
  traverse_lazy(bvh, nh, margin, make, [&](int32_t i) {
    out.push_back({bvh.key[i], bvh.items[i]});
    return true;
  });
  std::sort(out.begin(), out.end());
}

inline void query(const BVH& bvh, const HalfSpace* hs, int nh, double margin, std::vector<std::pair<int32_t, int32_t>>& out) {
  query_lazy(bvh, nh, margin, [hs](int i) { return hs[i]; }, out);
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_BVH_H_
