// jaxshadow's shadow engine: occlusion volumes (part of `_shadowc.cc`; see its header comment).
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

// `lv`: the light's K vertices (double, counter-clockwise seen from the lit side); `ne`: their
// Newell normal (unscaled, towards the lit side); `box`: lo[3], hi[3]; `eps`: the receivers'
// float type's epsilon.
inline OcclusionVolume occlusion_volume(const double* lv, int64_t K, const double* ne, const double* box, double eps) {
  OcclusionVolume vol;
  constexpr double kGap = 1e11, kMargin = 1e10;  // times eps: 2.2e-5 and 2.2e-6 in float64
  vol.margin = kMargin * eps;
  if (K < 3 || K > 64 || !(vol.margin < 1e-3)) return vol;
  double B[8][3];
  for (int c = 0; c < 8; c++)
    for (int d = 0; d < 3; d++) B[c][d] = box[(c >> d & 1) ? 3 + d : d];
  double scale = 0;
  for (int c = 0; c < 8; c++)
    for (int d = 0; d < 3; d++) scale = std::max(scale, std::fabs(B[c][d]));
  for (int64_t i = 0; i < K; i++)
    for (int d = 0; d < 3; d++) scale = std::max(scale, std::fabs(lv[3 * i + d]));
  if (!(scale > 0) || !std::isfinite(scale)) return vol;
  vol.scale = scale;
  auto sub = [](const double* a, const double* b, double* o) {
    for (int d = 0; d < 3; d++) o[d] = a[d] - b[d];
  };
  auto crs = [](const double* a, const double* b, double* o) {
    o[0] = a[1] * b[2] - a[2] * b[1];
    o[1] = a[2] * b[0] - a[0] * b[2];
    o[2] = a[0] * b[1] - a[1] * b[0];
  };
  auto dt = [](const double* a, const double* b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; };
  // B strictly on the lit side of the light's plane, by the gap.
  const double nn = std::sqrt(dt(ne, ne));
  if (!(nn > 0)) return vol;
  for (int c = 0; c < 8; c++) {
    double r[3];
    sub(B[c], lv, r);
    if (!(dt(r, ne) > kGap * eps * scale * nn)) return vol;
  }
  // A candidate plane through points a, b, c: kept (oriented with B positive) when it
  // separates L and B, within a rounding tolerance.
  const double tol = 64 * eps * scale;
  auto consider = [&](const double* a, const double* b, const double* c) {
    double u[3], v[3], n[3];
    sub(b, a, u);
    sub(c, a, v);
    crs(u, v, n);
    const double len = std::sqrt(dt(n, n));
    if (!(len > 1e-9 * scale * scale)) return;
    for (int d = 0; d < 3; d++) n[d] /= len;
    const double off = dt(n, a);
    double bmin = std::numeric_limits<double>::infinity(), bmax = -bmin, lmin = bmin, lmax = -bmin;
    for (int q = 0; q < 8; q++) {
      const double h = dt(n, B[q]) - off;
      bmin = std::min(bmin, h);
      bmax = std::max(bmax, h);
    }
    for (int64_t q = 0; q < K; q++) {
      const double h = dt(n, lv + 3 * q) - off;
      lmin = std::min(lmin, h);
      lmax = std::max(lmax, h);
    }
    double s = 0;
    if (bmin >= -tol && lmax <= tol) s = 1;
    else if (bmax <= tol && lmin >= -tol) s = -1;
    if (s == 0) return;
    for (size_t k = 0; k + 4 <= vol.planes.size(); k += 4) {  // the same plane again (a flat box)
      const double* q = vol.planes.data() + k;
      if (std::fabs(q[0] - s * n[0]) + std::fabs(q[1] - s * n[1]) + std::fabs(q[2] - s * n[2]) < 1e-12 &&
          std::fabs(q[3] - s * off) < 1e-12 * scale)
        return;
    }
    vol.planes.insert(vol.planes.end(), {s * n[0], s * n[1], s * n[2], s * off});
  };
  static const int kEdges[12][2] = {{0, 1}, {2, 3}, {4, 5}, {6, 7}, {0, 2}, {1, 3},
                                    {4, 6}, {5, 7}, {0, 4}, {1, 5}, {2, 6}, {3, 7}};
  for (int64_t i = 0; i < K; i++) {
    const double *a = lv + 3 * i, *b = lv + 3 * ((i + 1) % K);
    if (a[0] == b[0] && a[1] == b[1] && a[2] == b[2]) continue;
    for (int c = 0; c < 8; c++) consider(a, b, B[c]);
  }
  for (const auto& e : kEdges)
    for (int64_t i = 0; i < K; i++) consider(B[e[0]], B[e[1]], lv + 3 * i);
  return vol;
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_VOLUME_H_
