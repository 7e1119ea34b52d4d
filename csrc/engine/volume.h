// jaxshadow's shadow engine: occlusion volumes (part of `csrc/shadowc.cc`; see its header comment).
#ifndef JAXSHADOW_SHADOWC_VOLUME_H_
#define JAXSHADOW_SHADOWC_VOLUME_H_

#include "geometry.h"

namespace jaxshadow_engine {

// The occlusion volume of a box B under a convex polygon light L (Campbell & Fussell §3.1.2):
// the points p whose pyramid conv({p} ∪ L) meets B. It is convex -- it is the union over t >= 1
// of t B + (1 - t) L, and for convex L a combination of two such sets is again one -- and it is
// the intersection of the half-spaces on B's side of every plane that separates L from B: a
// receiver strictly on L's side of one separating plane sees all of L without B in the way
// (the plane separates its whole pyramid from B). The separating planes through an edge of one
// and a vertex of the other (the paper's minimum extremal planes, through the light's edges
// and the box's corners, and through the box's edges and the light's vertices) bound the volume
// exactly; any subset bounds a larger set, so a receiver outside one of the kept planes is
// outside the volume.
//
// Use: `outside` says that the hierarchy below B returns nothing for p. Rounding: a plane is
// kept only when B lies in front of the light's plane by a clear gap (`kGap` of the scene's
// size), and p must lie behind the plane by `kMargin` of |p| + the scene's size. Then the
// distance between p's pyramid and B is at least of order kGap * kMargin * size (near the light
// the pyramid is within the gap of the light's plane, farther away it is behind the plane),
// far above the hierarchy's rounding margin (~1e3 eps), so every item the hierarchy could
// return is disjoint from the pyramid and is dropped as having no boundary inside it: the
// class and boundary are the same with and without the test (the engine computes in double,
// float32 inputs widened).
struct OcclusionVolume {
  std::vector<double> planes;  // (n, 4): unit normal (B on its positive side), offset n . x0
  double scale = 0;            // the largest coordinate magnitude of B and L
  double margin = 0;           // relative margin for p

  template <class T>
  bool outside(V3<T> p) const {
    const size_t np = planes.size() / 4;
    if (np == 0) return false;
    const double px = double(p.x), py = double(p.y), pz = double(p.z);
    const double m = margin * (scale + std::max(std::fabs(px), std::max(std::fabs(py), std::fabs(pz))));
    for (size_t k = 0; k < np; k++) {
      const double* q = planes.data() + 4 * k;
      if (q[0] * px + q[1] * py + q[2] * pz - q[3] < -m) return true;
    }
    return false;
  }
};

// Corner c of the box [lo, hi]: bit d of c picks hi along axis d.
inline V3<double> box_corner(const double* lo, const double* hi, int c) {
  return V3<double>{(c & 1) ? hi[0] : lo[0], (c & 2) ? hi[1] : lo[1], (c & 4) ? hi[2] : lo[2]};
}

// The candidates for the extremal planes of a box [lo, hi] and a polygon light (C&F §3.1.2):
// `plane(a, b, c)` for the plane through each light edge a -> b (distinct ends) and each distinct
// box corner c, then through each box edge a -> b of positive length and each light vertex c. A
// flat box (zero extent along an axis) repeats no corner and has no zero-length edge.
template <class F>
void extremal_planes(const double* lo, const double* hi, const double* lv, int64_t K, F plane) {
  int flat = 0;
  for (int d = 0; d < 3; d++)
    if (!(hi[d] > lo[d])) flat |= 1 << d;
  V3<double> B[8];
  for (int c = 0; c < 8; c++) B[c] = box_corner(lo, hi, c);
  for (int64_t i = 0; i < K; i++) {
    const V3<double> a = ld(lv + 3 * i), b = ld(lv + 3 * ((i + 1) % K));
    if (same(a, b)) continue;
    for (int c = 0; c < 8; c++)
      if (!(c & flat)) plane(a, b, B[c]);
  }
  for (int c = 0; c < 8; c++)
    for (int d = 0; d < 3; d++) {
      if ((c & flat) || (c >> d & 1) || (flat >> d & 1)) continue;
      for (int64_t i = 0; i < K; i++) plane(B[c], B[c | (1 << d)], ld(lv + 3 * i));
    }
}

// `lv`: the light's K vertices (double, counter-clockwise seen from the lit side); `ne`: their
// Newell normal (unscaled, towards the lit side); `box`: lo[3], hi[3]; `eps`: the receivers'
// float type's epsilon.
inline OcclusionVolume occlusion_volume(const double* lv, int64_t K, const double* ne_, const double* box, double eps) {
  OcclusionVolume vol;
  constexpr double kGap = 1e11, kMargin = 1e10;  // times eps: 2.2e-5 and 2.2e-6 in float64
  vol.margin = kMargin * eps;
  if (K < 3 || K > 64 || !(vol.margin < 1e-3)) return vol;
  V3<double> B[8];
  for (int c = 0; c < 8; c++) B[c] = box_corner(box, box + 3, c);
  double scale = 0;
  for (int c = 0; c < 8; c++) scale = std::max(scale, absmax(B[c]));
  for (int64_t i = 0; i < K; i++) scale = std::max(scale, absmax(ld(lv + 3 * i)));
  if (!(scale > 0) || !std::isfinite(scale)) return vol;
  vol.scale = scale;
  // B strictly on the lit side of the light's plane, by the gap.
  const V3<double> ne = ld(ne_), l0 = ld(lv);
  const double nn = norm(ne);
  if (!(nn > 0)) return vol;
  for (int c = 0; c < 8; c++)
    if (!(dot(B[c] - l0, ne) > kGap * eps * scale * nn)) return vol;
  // A candidate plane through points a, b, c: kept (oriented with B positive) when it
  // separates L and B, within a rounding tolerance.
  const double tol = 64 * eps * scale;
  extremal_planes(box, box + 3, lv, K, [&](V3<double> a, V3<double> b, V3<double> c) {
    V3<double> n = cross(b - a, c - a);
    const double len = norm(n);
    if (!(len > 1e-9 * scale * scale)) return;
    n = V3<double>{n.x / len, n.y / len, n.z / len};
    const double off = dot(n, a);
    double bmin = std::numeric_limits<double>::infinity(), bmax = -bmin, lmin = bmin, lmax = -bmin;
    for (int q = 0; q < 8; q++) {
      const double h = dot(n, B[q]) - off;
      bmin = std::min(bmin, h);
      bmax = std::max(bmax, h);
    }
    for (int64_t q = 0; q < K; q++) {
      const double h = dot(n, ld(lv + 3 * q)) - off;
      lmin = std::min(lmin, h);
      lmax = std::max(lmax, h);
    }
    double s = 0;
    if (bmin >= -tol && lmax <= tol) s = 1;
    else if (bmax <= tol && lmin >= -tol) s = -1;
    if (s == 0) return;
    for (size_t k = 0; k + 4 <= vol.planes.size(); k += 4) {  // the same plane again
      const double* q = vol.planes.data() + k;
      if (std::fabs(q[0] - s * n.x) + std::fabs(q[1] - s * n.y) + std::fabs(q[2] - s * n.z) < 1e-12 &&
          std::fabs(q[3] - s * off) < 1e-12 * scale)
        return;
    }
    vol.planes.insert(vol.planes.end(), {s * n.x, s * n.y, s * n.z, s * off});
  });
  return vol;
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_VOLUME_H_
