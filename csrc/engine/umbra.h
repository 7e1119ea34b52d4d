// jaxshadow's shadow engine: umbra volumes of convex solids (part of `csrc/shadowc.cc`; see its header
// comment).
#ifndef JAXSHADOW_SHADOWC_UMBRA_H_
#define JAXSHADOW_SHADOWC_UMBRA_H_

#include "bvh.h"

namespace jaxshadow_engine {

// The umbra volume of a convex solid S under a polygon light L (Campbell & Fussell §3.1.3): the
// points p from which S hides all of L. From p, the points hidden by S form a convex set -- the
// union over t >= 1 of p + t (S - p), convex because S is -- so S hides L exactly when it hides
// L's vertices, and the volume is the intersection over the light's vertices v of the shadow
// of the point light v: the cone from v through S (the half-spaces through v and S's silhouette
// edges seen from v, the paper's maximum extremal planes) beyond S (behind every face of S that
// faces v: the ray from v enters S through its last front face). A receiver strictly inside it
// and strictly outside S gets exactly zero from L whatever its normal: it is umbra, with no
// region built.
//
// Rounding: a solid gets a volume only when it lies in front of the light's plane by a clear gap,
// no light vertex is within the gap of one of its face planes and no silhouette plane is near
// degenerate (`kBuild` of the scene's size); a receiver must be inside every plane, and outside
// S, by `kMargin` of |p| + the scene's size. The planes are computed in double from the same
// coordinates the rest of the engine reads, so their rounding (a few eps of the scene's size)
// is far below the margin: a receiver the test calls umbra is umbra in exact arithmetic, and
// the exact path would have found S covering all of its visible light (the same class). The
// others, near the volume's boundary or on S, take the exact path.
// Building them costs about one umbra receiver's exact path per solid, and about a third of the
// receivers of a scene of boxes are umbra: worth it for batches of a few hundred receivers.
constexpr int64_t kUmbraMinReceivers = 512;

struct UmbraVolumes {
  std::vector<int32_t> off;    // (S + 1): solid s's planes are [off[s], off[s + 1]); none: no volume
  std::vector<double> planes;  // (n, 4): unit normal (inside on its positive side), offset n . x0
  double scale = 0;            // the largest coordinate magnitude of the solids and the light
  double margin = 0;           // relative margin for p
  bool any = false;

  // p strictly inside solid s's umbra volume and strictly outside s (face planes from `bvh`).
  bool inside(int64_t s, const double* p, const BVH& bvh, const int32_t* solid_faces) const {
    const int32_t a = off[s], b = off[s + 1];
    if (a == b) return false;
    const double m = margin * (scale + std::max(std::fabs(p[0]), std::max(std::fabs(p[1]), std::fabs(p[2]))));
    for (int32_t k = a; k < b; k++) {
      const double* q = planes.data() + 4 * k;
      if (!(q[0] * p[0] + q[1] * p[1] + q[2] * p[2] - q[3] > m)) return false;
    }
    for (int64_t f = solid_faces[2 * s]; f < solid_faces[2 * s + 1]; f++) {
      const double* fp = bvh.face_plane.data() + 6 * f;
      if (fp[0] * (p[0] - fp[3]) + fp[1] * (p[1] - fp[4]) + fp[2] * (p[2] - fp[5]) > m) return true;
    }
    return false;  // on or inside S
  }
};

// `lv`: the light's K vertices (double); `ne`: their Newell normal (towards the lit side); `eps`:
// the receivers' float type's epsilon. Solids and their faces' planes (outward unit normals) from
// `occ` and `bvh` (after prepare_solids).
template <class T>
UmbraVolumes umbra_volumes(const Occluders<T>& occ, const BVH& bvh, const double* lv, int64_t K, const double* ne,
                           double eps) {
  constexpr double kBuild = 1e9, kMargin = 1e8;  // times eps: 2.2e-7 and 2.2e-8 in float64
  UmbraVolumes u;
  u.off.assign(occ.S + 1, 0);
  u.margin = kMargin * eps;
  if (occ.S == 0 || !occ.solid_faces || K < 3 || K > 64 || !(kBuild * eps < 1e-3)) return u;
  const double nn = std::sqrt(ne[0] * ne[0] + ne[1] * ne[1] + ne[2] * ne[2]);
  if (!(nn > 0)) return u;
  auto vert = [&](int32_t slot) { return occ.faces + 3 * int64_t(slot); };
  auto point = [&](int32_t slot) {
    const T* x = vert(slot);
    return V3<double>{double(x[0]), double(x[1]), double(x[2])};
  };
  double scale = 0;
  for (int64_t i = 0; i < 3 * K; i++) scale = std::max(scale, std::fabs(lv[i]));
  for (int32_t q : bvh.solid_verts) scale = std::max(scale, absmax(point(q)));
  if (!std::isfinite(scale)) return u;
  u.scale = scale;
  const double gap = kBuild * eps * (scale + 1e-300);
  std::vector<double> mine;
  std::vector<uint8_t> front, used;
  for (int64_t s = 0; s < occ.S; s++) {
    mine.clear();
    const int32_t f0 = occ.solid_faces[2 * s], f1 = occ.solid_faces[2 * s + 1];
    const int32_t v0 = bvh.solid_vert_off[s], v1 = bvh.solid_vert_off[s + 1];
    bool ok = f1 > f0 && v1 - v0 >= 4;
    double c[3] = {0, 0, 0};
    for (int32_t q = v0; q < v1 && ok; q++) {
      const T* x = vert(bvh.solid_verts[q]);
      double h = 0;
      for (int d = 0; d < 3; d++) {
        h += ne[d] * (double(x[d]) - lv[d]);
        c[d] += double(x[d]) / double(v1 - v0);
      }
      ok = h > gap * nn;  // strictly on the receivers' side of the light's plane
    }
    front.assign(f1 - f0, 0);
    used.assign(f1 - f0, 0);
    for (int64_t i = 0; i < K && ok; i++) {
      const double* v = lv + 3 * i;
      bool any_front = false;
      for (int32_t f = f0; f < f1 && ok; f++) {
        const double* fp = bvh.face_plane.data() + 6 * f;
        const double h = fp[0] * (v[0] - fp[3]) + fp[1] * (v[1] - fp[4]) + fp[2] * (v[2] - fp[5]);
        ok = std::fabs(h) > gap && (fp[0] != 0 || fp[1] != 0 || fp[2] != 0);
        front[f - f0] = h > 0;
        any_front = any_front || h > 0;
      }
      ok = ok && any_front;  // v outside S
      // Beyond S: behind every face v sees (each such plane once).
      for (int32_t f = f0; f < f1 && ok; f++) {
        if (!front[f - f0] || used[f - f0]) continue;
        used[f - f0] = 1;
        const double* fp = bvh.face_plane.data() + 6 * f;
        mine.insert(mine.end(), {-fp[0], -fp[1], -fp[2], -(fp[0] * fp[3] + fp[1] * fp[4] + fp[2] * fp[5])});
      }
      // The cone from v through S: planes through v and each silhouette edge, S on their positive side.
      for (int32_t k = occ.solid_edge_off[s]; k < occ.solid_edge_off[s + 1] && ok; k++) {
        const int32_t* ed = occ.solid_edges + 4 * k;
        if (front[ed[2] - f0] == front[ed[3] - f0]) continue;
        const V3<double> vv = ld(v), a = point(ed[0]) - vv, b = point(ed[1]) - vv;
        V3<double> n = cross(a, b);
        const double len = norm(n);
        ok = len > kBuild * eps * norm(a) * norm(b);  // v clearly off the edge's line
        if (!ok) break;
        n = V3<double>{n.x / len, n.y / len, n.z / len};
        const double hc = dot(n, ld(c) - vv);
        ok = std::fabs(hc) > gap;
        const double sg = hc > 0 ? 1.0 : -1.0;
        mine.insert(mine.end(), {sg * n.x, sg * n.y, sg * n.z, sg * dot(n, vv)});
      }
    }
    if (ok && !mine.empty()) {
      u.planes.insert(u.planes.end(), mine.begin(), mine.end());
      u.any = true;
    }
    u.off[s + 1] = int32_t(u.planes.size() / 4);
  }
  return u;
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_UMBRA_H_
