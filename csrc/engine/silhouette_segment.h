// jaxshadow's shadow engine: the visible pieces of a segment light (part of `csrc/shadowc.cc`; see
// its header comment).
//
// Seen from a receiver p, the part of the segment light a -> b that a convex face hides is one
// interval of the parameter t of x(t) = a + t (b - a) (Poulin §4.2: the face cuts the light
// triangle (p, a, b) in a convex set): x(t) inside the cone of the face's edge planes through p,
// and beyond the face's plane. Each bound of that interval is the crossing of the segment with one
// plane: a plane through p and a face edge, or the face's own plane (a face the segment passes
// through). The hidden part of the segment is the union of the intervals of the faces that meet
// the light triangle (`segment_candidates`); its complement in [0, 1], the visible pieces, is
// bounded by the segment's ends and by crossings with planes through p and *contour* edges of the
// meshes: where two faces of a mesh share an edge and both hide the rays on either side of it,
// their intervals meet at that edge's crossing, computed from the same plane (`edge_plane` is
// bit-identical for the two faces, whichever way the edge runs), and the union closes over it.
// So a receiver's output is the list of visible pieces, each two endpoint codes, whatever the
// number of faces in its light triangle; the device computes each endpoint's t from the code (the
// same plane, differentiably) and integrates the segment's kernel over the pieces.
//
// The per-face interval is `_clip.blocked_intervals` test for test, in double (float32 inputs are
// exact in double): the face's side from `face_side` (the on-surface rule included; a face p lies
// in blocks nothing), the oriented edge planes s * edge_plane, an edge plane that is zero (a
// repeated vertex, an edge through p) ignored, and one parallel to the segment (d . plane = 0)
// hiding all or nothing by the sign of (a - p) . plane; then the interval clipped to [0, 1].
// Ties are decided as the device kernel decides them: intervals that touch (the end of one equal
// to the start of the next) leave no visible piece between them, and an interval clipped to zero
// length hides nothing.
//
// Endpoint codes (int32): kSegStart (t = 0), kSegEnd (t = 1), or f * (Ko + 1) + i: the plane
// through p and edge i -> i + 1 of face f (i < Ko), or face f's own plane (i = Ko).
#ifndef JAXSHADOW_SHADOWC_SILHOUETTE_SEGMENT_H_
#define JAXSHADOW_SHADOWC_SILHOUETTE_SEGMENT_H_

#include <algorithm>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <memory>
#include <vector>

#include "driver.h"

namespace jaxshadow_engine {

constexpr int32_t kSegStart = -1;
constexpr int32_t kSegEnd = -2;

// One face's hidden interval [lo, hi] of t and the codes of the planes that bound it.
struct SegmentBlock {
  double lo, hi;
  int32_t clo, chi;
};

// A receiver's scratch and result: its candidate faces, their intervals and the visible pieces
// (pairs of endpoint codes, in order along the segment).
struct SegmentWork {
  std::vector<int32_t> faces;
  std::vector<std::pair<int32_t, int32_t>> cand;
  std::vector<SegmentBlock> blocks;
  std::vector<int32_t> pieces;  // 2 codes per piece
};

// The interval of t that face f hides on a -> b (d = b - a) seen from p, clipped to [0, 1];
// false when it hides nothing there.
template <class T>
bool segment_block(const Occluders<T>& occ, int64_t f, V3<T> p, V3<T> a, V3<T> d, SegmentBlock& out) {
  const int64_t Ko = occ.Ko;
  if (Ko > 64) return false;
  V3<T> rel[64];
  const FaceSide<T> fs = face_side(occ, f, p, rel);
  if (fs.side == 0) return false;  // p in the face's plane: it blocks a zero solid angle
  const T s = T(fs.side);
  const int32_t base = int32_t(f * (Ko + 1));
  double lo = -std::numeric_limits<double>::infinity(), hi = std::numeric_limits<double>::infinity();
  int32_t clo = kSegStart, chi = kSegEnd;
  const V3<T> ap = a - p;
  for (int64_t i = 0; i < Ko; i++) {
    const V3<T> u = occ.vert(f, i), v = occ.vert(f, (i + 1) % Ko);
    if (same(u, v)) continue;
    const V3<T> pl = s * edge_plane(p, u, v);
    if (!nonzero(pl)) continue;
    const T g0 = dot(ap, pl), g1 = dot(d, pl);
    if (g1 > 0) {
      const double t = double(-g0 / g1);
      if (t > lo) lo = t, clo = base + int32_t(i);
    } else if (g1 < 0) {
      const double t = double(-g0 / g1);
      if (t < hi) hi = t, chi = base + int32_t(i);
    } else if (g0 < 0) {
      return false;
    }
  }
  // x(t) strictly beyond the face's plane seen from p: -s no . (x(t) - o_0) > 0.
  const T h0 = -s * dot(fs.no, a - occ.vert(f, 0)), h1 = -s * dot(fs.no, d);
  if (h1 > 0) {
    const double t = double(-h0 / h1);
    if (t > lo) lo = t, clo = base + int32_t(Ko);
  } else if (h1 < 0) {
    const double t = double(-h0 / h1);
    if (t < hi) hi = t, chi = base + int32_t(Ko);
  } else if (!(h0 > 0)) {
    return false;
  }
  if (!(lo > 0)) lo = 0, clo = kSegStart;
  if (!(hi < 1)) hi = 1, chi = kSegEnd;
  if (!(lo < hi)) return false;
  out = SegmentBlock{lo, hi, clo, chi};
  return true;
}

// The visible pieces of a -> b seen from p (`w.pieces`, two codes each) and the receiver's class:
// 1 (LIT: nothing hidden, no piece listed), 2 (UMBRA: all hidden) or 3 (PENUMBRA).
template <class T>
int32_t segment_pieces(const Occluders<T>& occ, const BVH& bvh, V3<T> p, V3<T> a, V3<T> b, SegmentWork& w) {
  w.pieces.clear();
  w.blocks.clear();
  segment_candidates(occ, bvh, p, a, b, w.faces, w.cand);
  const V3<T> d = b - a;
  for (int32_t f : w.faces) {
    SegmentBlock blk;
    if (segment_block(occ, f, p, a, d, blk)) w.blocks.push_back(blk);
  }
  if (w.blocks.empty()) return 1;
  std::sort(w.blocks.begin(), w.blocks.end(),
            [](const SegmentBlock& x, const SegmentBlock& y) { return x.lo < y.lo || (x.lo == y.lo && x.hi > y.hi); });
  double cur = 0;
  int32_t ccur = kSegStart;
  for (const SegmentBlock& blk : w.blocks) {
    if (blk.lo > cur) {
      w.pieces.push_back(ccur);
      w.pieces.push_back(blk.clo);
    }
    if (blk.hi > cur) cur = blk.hi, ccur = blk.chi;
  }
  if (cur < 1) {
    w.pieces.push_back(ccur);
    w.pieces.push_back(kSegEnd);
  }
  return w.pieces.empty() ? 2 : 3;
}

// Host plan: classes (N,), candidate faces per receiver (N,), offsets (N + 1,) into the pieces
// (R, 2) int32 (`*pieces_out`, malloc'ed; the caller frees it). Returns 0, or 2 out of memory.
template <class T>
int segment_pieces_plan(int64_t N, const T* P, const T* A, const T* B, const Occluders<T>& occ, int threads,
                        int32_t* cls, int32_t* kept, int64_t* offsets, int32_t** pieces_out) {
  const std::shared_ptr<const Prepared> prep = prepared(occ);  // the cached hierarchy
  const BVH& bvh = prep->bvh;
  const V3<T> a = ld(A), b = ld(B);
  std::vector<std::vector<int32_t>> lists(size_t(std::max<int64_t>(N, 0)));
  parallel_for(N, default_threads(threads), [&](int, int64_t s, int64_t e) {
    SegmentWork w;
    for (int64_t i = s; i < e; i++) {
      cls[i] = segment_pieces(occ, bvh, ld(P + 3 * i), a, b, w);
      kept[i] = int32_t(w.faces.size());
      lists[size_t(i)] = w.pieces;
    }
  });
  offsets[0] = 0;
  for (int64_t i = 0; i < N; i++) offsets[i + 1] = offsets[i] + int64_t(lists[size_t(i)].size() / 2);
  int32_t* out = static_cast<int32_t*>(std::malloc(sizeof(int32_t) * size_t(std::max<int64_t>(2 * offsets[N], 1))));
  if (!out) return 2;
  for (int64_t i = 0; i < N; i++)
    if (!lists[size_t(i)].empty())
      std::memcpy(out + 2 * offsets[i], lists[size_t(i)].data(), sizeof(int32_t) * lists[size_t(i)].size());
  *pieces_out = out;
  return 0;
}

// Fixed capacity (the FFI handler's layout): classes (N,), counts (N,) (pieces of a penumbra
// receiver, 0 for the others), pieces (N, cap, 2) with unused slots (kSegStart, kSegStart).
template <class T>
void segment_pieces_fixed(int64_t N, const T* P, const T* A, const T* B, const Occluders<T>& occ, const BVH& bvh,
                          int threads, int64_t cap, int32_t* cls, int32_t* counts, int32_t* pieces) {
  const V3<T> a = ld(A), b = ld(B);
  parallel_for(N, default_threads(threads), [&](int, int64_t s, int64_t e) {
    SegmentWork w;
    for (int64_t i = s; i < e; i++) {
      cls[i] = segment_pieces(occ, bvh, ld(P + 3 * i), a, b, w);
      const int64_t n = int64_t(w.pieces.size() / 2);
      counts[i] = int32_t(n);
      int32_t* out = pieces + i * cap * 2;
      for (int64_t k = 0; k < cap; k++) {
        out[2 * k] = k < n ? w.pieces[size_t(2 * k)] : kSegStart;
        out[2 * k + 1] = k < n ? w.pieces[size_t(2 * k + 1)] : kSegStart;
      }
    }
  });
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_SILHOUETTE_SEGMENT_H_
