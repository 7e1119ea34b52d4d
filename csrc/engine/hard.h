// jaxshadow's shadow engine: hard (part of `csrc/shadowc.cc`; see its header comment).
#ifndef JAXSHADOW_SHADOWC_HARD_H_
#define JAXSHADOW_SHADOWC_HARD_H_

#include "bvh.h"

namespace jaxshadow_engine {


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
  const FaceSide<T> fs = face_side(occ, f, p, rel);
  if (fs.side == 0) return false;  // p in the face's plane: it blocks a zero solid angle
  const T s = T(fs.side);
  for (int64_t i = 0; i < Ko; i++) {
    V3<T> a = occ.vert(f, i), b = occ.vert(f, (i + 1) % Ko);
    if (same(a, b)) continue;
    V3<T> pl = s * edge_plane(p, a, b);
    if (!(dot(pl, r) > 0)) return false;
  }
  if (x) {
    // beyond: -s * no . (x - o_0) > 0, with no the scaled Newell normal (only its sign matters)
    if (!(-s * dot(fs.no, *x - occ.vert(f, 0)) > 0)) return false;
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
      double pad = 1e-9 * (std::fabs(nd.box[k]) + std::fabs(nd.box[3 + k]) + std::fabs(o[k]) + 1e-300);
      double lo = nd.box[k] - pad, hi = nd.box[3 + k] + pad;
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

// Whether face f has every vertex strictly on one side of the plane through p with normal nt
// (the light triangle's; a zero nt drops nothing), beyond the tolerance `tol` of its rounding.
template <class T>
bool off_triangle_plane(const Occluders<T>& occ, int64_t f, V3<T> p, V3<T> nt, T tol) {
  const T nn = norm(nt);
  bool pos = true, neg = true;
  for (int64_t i = 0; i < occ.Ko; i++) {
    const V3<T> r = occ.vert(f, i) - p;
    const T h = dot(r, nt);
    const T m = tol * nn * norm(r);
    if (!(h > m)) pos = false;
    if (!(h < -m)) neg = false;
  }
  return nonzero(nt) && (pos || neg);
}

// Whether p lies strictly behind face f (its Newell normal about p, beyond the tolerance `tol`):
// for an outward face of a closed mesh seen from outside its box, a front face of the same mesh
// blocks the same rays.
template <class T>
bool behind_face(const Occluders<T>& occ, int64_t f, V3<T> p, T tol) {
  const int64_t Ko = occ.Ko;
  V3<T> no{0, 0, 0};
  for (int64_t i = 0; i < Ko; i++) no = no + cross(occ.vert(f, i) - p, occ.vert(f, (i + 1) % Ko) - p);
  const T h0 = dot(no, occ.vert(f, 0) - p);
  T scl = 0;
  for (int64_t i = 0; i < Ko; i++) scl = std::max(scl, norm(occ.vert(f, i) - p));
  return h0 > tol * norm(no) * scl;
}

// Half-spaces bounding the light triangle (p, a, b): its two sides (the slab of its plane, as two
// half-spaces) and its three edge planes (in its plane, pointing inwards); none when the triangle
// is degenerate (nt = 0). Returns how many.
template <class T>
int segment_triangle_planes(V3<T> p, V3<T> a, V3<T> b, HalfSpace* hs) {
  const V3<T> nt = cross(a - p, b - p);
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
    add(cross(nt, a - p), p);  // inward of edge p->a
    add(cross(nt, b - a), a);  // inward of a->b
    add(cross(nt, p - b), b);  // inward of b->p
  }
  return nh;
}

// The box margin of the triangle's half-spaces (a bound on the rounding of the planes and the
// coordinates, so that touching faces are kept).
template <class T>
double segment_box_margin(V3<T> p, V3<T> a, V3<T> b) {
  const double scale = std::max(double(absmax(p)), std::max(double(absmax(a)), double(absmax(b)))) + 1.0;
  return 1e3 * double(eps_of<T>()) * scale;
}

// Faces that can block part of the segment light a -> b seen from p: the light triangle (p, a, b)
// meets them. Conservative: a box test, then the face's vertices not all strictly on one side of
// the triangle's plane or outside one of its edge planes. Back faces of closed meshes are dropped
// seen from outside the mesh's box, unless p lies in the plane of one of the mesh's listed faces.
template <class T>
void segment_candidates(const Occluders<T>& occ, const BVH& bvh, V3<T> p, V3<T> a, V3<T> b,
                        std::vector<int32_t>& out, std::vector<std::pair<int32_t, int32_t>>& cand) {
  out.clear();
  const V3<T> nt = cross(a - p, b - p);
  const T tol = T(kCollinearEps) * eps_of<T>();
  HalfSpace hs[5];
  const int nh = segment_triangle_planes(p, a, b, hs);
  query(bvh, hs, nh, segment_box_margin(p, a, b), cand);
  KeptMeshes keep;  // closed meshes that keep their back faces
  auto consider = [&](int64_t f) {
    if (off_triangle_plane(occ, f, p, nt, tol)) return;
    const double pd[3] = {double(p.x), double(p.y), double(p.z)};
    const int32_t mesh = occ.face_closed ? occ.face_closed[f] : -1;
    if (mesh >= 0 && bvh.outside_mesh(mesh, pd)) {
      // p in the face's plane (the evaluator drops the face, FaceSide::edge_on): the mesh keeps
      // its back faces, which alone cover the face's wedge where p is just in front of it.
      if (!keep.all() && near_face_plane(occ, f, p)) keep.add(mesh);
      if (behind_face(occ, f, p, tol)) {
        out.push_back(-int32_t(f) - 1);  // a back face, dropped below unless its mesh is kept
        return;
      }
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
  size_t m = 0;
  for (int32_t f : out) {
    if (f < 0) {
      f = -f - 1;
      if (!keep.has(occ.face_closed[f])) continue;
    }
    out[m++] = f;
  }
  out.resize(m);
  std::sort(out.begin(), out.end());
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_HARD_H_
