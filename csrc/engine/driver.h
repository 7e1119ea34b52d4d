// jaxshadow's shadow engine: driver (part of `csrc/shadowc.cc`; see its header comment).
#ifndef JAXSHADOW_SHADOWC_DRIVER_H_
#define JAXSHADOW_SHADOWC_DRIVER_H_

#include "decode.h"
#include "groups.h"
#include "polygon.h"
#include "prepared.h"
#include "hard.h"

namespace jaxshadow_engine {

using jaxshadow_abi::kCodeWidth;
using jaxshadow_abi::kRunWidth;


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

// JAXSHADOW_SIL_TILES: 0 no tiles (each receiver walks the silhouette path's hierarchy alone), 1
// every run of receivers tiled; otherwise (the default) `tile_worth`. Read per call.
inline int sil_tiles_mode() {
  const char* env = std::getenv("JAXSHADOW_SIL_TILES");
  return env && env[0] == '0' ? 0 : env && env[0] == '1' ? 1 : 2;
}

// Whether receivers in the box [lo, hi] share one walk of the silhouette path's hierarchy, in a
// call whose occluders lie in the box `root` (lo[3], hi[3]); `mode` as sil_tiles_mode. A tile's
// walk keeps what any of its receivers may need, so it pays only where they see the occluders
// from nearly one direction: its box's diagonal at most kTileSpread times its gap to the
// occluders' box. Scattered receivers (60 fit targets on a 2 m floor) walked 4-25x slower in tiles
// than alone; floors of 2e5 receivers 1.3-1.8x faster (benchmarks/real_meshes), and they still
// are. Each receiver's result is the same either way.
constexpr double kTileSpread = 0.5;

inline bool tile_worth(int mode, const double* lo, const double* hi, const double* root) {
  if (mode != 2) return mode == 1;
  double diag = 0, gap = 0;
  for (int d = 0; d < 3; d++) {
    diag += (hi[d] - lo[d]) * (hi[d] - lo[d]);
    const double g = std::max({0.0, root[d] - hi[d], lo[d] - root[3 + d]});
    gap += g * g;
  }
  return std::sqrt(diag) <= kTileSpread * std::sqrt(gap);
}

constexpr int kSilTile = 16;  // receivers per tile of the silhouette path's walk
constexpr int kSilParent = 64;  // receivers per run of tiles whose walk the tiles' walks refine

// Morton order of receivers: codes over a box of the finite receivers (21 bits per axis).
struct MortonBox {
  double lo[3], hi[3];
  template <class T>
  MortonBox(int64_t N, const T* P) { finite_box(N, P, lo, hi); }
  static uint64_t spread(uint64_t v) {  // 21 bits to every third bit
    v &= 0x1fffff;
    v = (v | v << 32) & 0x1f00000000ffffull;
    v = (v | v << 16) & 0x1f0000ff0000ffull;
    v = (v | v << 8) & 0x100f00f00f00f00full;
    v = (v | v << 4) & 0x10c30c30c30c30c3ull;
    v = (v | v << 2) & 0x1249249249249249ull;
    return v;
  }
  // perm[a, b) in Morton order of the receivers' positions (ties by index).
  template <class T>
  void sort(const T* P, int64_t* perm, int64_t a, int64_t b, std::vector<std::pair<uint64_t, int64_t>>& key) const {
    key.clear();
    for (int64_t k = a; k < b; k++) {
      const int64_t i = perm[k];
      uint64_t code = 0;
      for (int d = 0; d < 3; d++) {
        const double x = double(P[3 * i + d]);
        double t = std::isfinite(x) && hi[d] > lo[d] ? (x - lo[d]) / (hi[d] - lo[d]) : 0.0;
        t = std::min(1.0, std::max(0.0, t));
        code |= spread(uint64_t(t * 2097151.0)) << d;
      }
      key.push_back({code, i});
    }
    std::sort(key.begin(), key.end());
    for (int64_t k = a; k < b; k++) perm[k] = key[size_t(k - a)].second;
  }
};

// Receiver i of a polygon light: its class, with `w.runs` its boundary; a light of more than 64
// vertices gives kZero and sets `err`.
template <class T>
JS_INLINE int32_t receiver_class(const PolyCall<T>& call, const T* P, const T* Nrm, int64_t i, Work<T>& w, std::atomic<int>& err) {
  const V3<T> p = ld(P + 3 * i), n = ld(Nrm + 3 * i);
  int32_t c = call.clear_ok ? clear_lit(call, p, n, w) : -1;  // clear.h
  if (c < 0) c = polygon_receiver(call, p, n, w);
  if (c < 0) {
    err = 1;
    c = kZero;
    w.runs.clear();
  }
  return c;
}

// Polygon plan, CSR output: classes (N), offsets (N + 1), runs (R, 2, 7) codes and/or (R, 2, 3) points
// (malloc'd, freed by the caller).
// `lambert` (N, nullable): per receiver the sum of lambert_term over its boundary (0 without
// one), for Lambert's integrand on the host path (the edges are decoded for it, also without
// `points_out`).
template <class T>
int poly_plan(int64_t N, const T* P, const T* Nrm, int64_t K, const T* E, const Occluders<T>& occ, int threads,
              int32_t* cls, int32_t* stats, int64_t* offsets, int32_t** runs_out, T** points_out, int64_t* nruns_out,
              T* lambert = nullptr) {
  const std::shared_ptr<const Prepared> prep = prepared(occ);
  const BVH& bvh = prep->bvh;
  PolyCall<T> call{Light<T>{K, E}, occ, &bvh, {}};
  bind_call(call, *prep, N);
  if (N >= kUmbraMinReceivers) prepare_umbra(call);
  call.clear_ok = call.sil_ok && clear_switch();
  threads = default_threads(threads);
  struct Block {
    int64_t s, e;
    std::vector<int32_t> codes;
    std::vector<T> pts;
  };
  std::vector<std::vector<Block>> per_thread(threads);
  std::vector<int32_t> counts(N, 0);
  std::atomic<int> err(0);
  // Receivers in groups of one grid cell that share one hierarchy query (groups.h); the blocks
  // then hold positions in that order.
  std::vector<int64_t> perm, cell;
  const bool grouped = int64_t(bvh.items.size()) >= kGroupMinItems && N >= 4 * kGroupSize;
  if (grouped) receiver_order(N, P, perm, cell);
  // The silhouette path's tiles: within each group (all receivers when there are none), receivers
  // in Morton order of their positions, and runs of at most kSilTile of one group share one walk
  // of the hierarchy (silhouette_walk.h). The groups keep their receivers.
  const int tiles_mode = sil_tiles_mode();
  const bool tiled = call.sil_ok && N >= 2 * kSilTile && tiles_mode != 0;
  const bool sorted = grouped || tiled;
  const MortonBox mbox(tiled ? N : 0, P);
  if (tiled && !grouped) {
    perm.resize(size_t(N));
    for (int64_t i = 0; i < N; i++) perm[size_t(i)] = i;
    std::vector<std::pair<uint64_t, int64_t>> key;
    mbox.sort(P, perm.data(), 0, N, key);
  }
  parallel_for(N, threads, [&](int t, int64_t s, int64_t e) {
    Work<T> w;
    w.lit_runs = false;
    Block blk;
    blk.s = s;
    blk.e = e;
    GroupList group;
    std::vector<std::pair<uint64_t, int64_t>> mkey;
    BoundaryEnds<T> ends;
    int64_t group_end = s, tile_end = s, parent_end = s;
    for (int64_t k = s; k < e; k++) {
      
      if (grouped && k == group_end) {  // the next group: positions [k, group_end) of one cell
        group_end = k + 1;
        while (group_end < e && group_end - k < kGroupSize && cell[group_end] == cell[k]) group_end++;
        double* lo = group.lo;
        double* hi = group.hi;
        for (int d = 0; d < 3; d++) {
          lo[d] = std::numeric_limits<double>::infinity();
          hi[d] = -std::numeric_limits<double>::infinity();
        }
        bool query = false;  // some receiver needs it (not outside the occlusion volume)
        for (int64_t q = k; q < group_end; q++) {
          const V3<T> x = ld(P + 3 * perm[q]);
          if (!(std::isfinite(double(x.x)) && std::isfinite(double(x.y)) && std::isfinite(double(x.z)))) continue;
          query = query || !call.volume.outside(x);
          const double c[3] = {double(x.x), double(x.y), double(x.z)};
          for (int d = 0; d < 3; d++) {
            lo[d] = std::min(lo[d], c[d]);
            hi[d] = std::max(hi[d], c[d]);
          }
        }
        if (tiled) mbox.sort(P, perm.data(), k, group_end, mkey);
        // Its items are listed when one of its receivers first queries the hierarchy (none: every
        // receiver outside the occlusion volume, the list stays empty).
        group.items.clear();
        group.listed = !query;
        w.group = &group;
      }
      const int64_t i = sorted ? perm[k] : k;
      if (tiled && k == parent_end) {  // the next run of tiles: positions [k, parent_end) of one group
        parent_end = k + 1;
        while (parent_end < (grouped ? group_end : e) && parent_end - k < kSilParent) parent_end++;
        w.tile.pid = -1;
        if (parent_end - k > kSilTile) {  // more than one tile
          w.tile.pid = k;
          for (int d = 0; d < 3; d++) {
            w.tile.plo[d] = std::numeric_limits<double>::infinity();
            w.tile.phi[d] = -std::numeric_limits<double>::infinity();
          }
          for (int64_t q = k; q < parent_end; q++)
            for (int d = 0; d < 3; d++) {
              const double x = double(P[3 * perm[q] + d]);
              if (!std::isfinite(x)) continue;
              w.tile.plo[d] = std::min(w.tile.plo[d], x);
              w.tile.phi[d] = std::max(w.tile.phi[d], x);
            }
          if (!tile_worth(tiles_mode, w.tile.plo, w.tile.phi, bvh.nodes[0].box)) w.tile.pid = -1;
        }
      }
      if (tiled && k == tile_end) {  // the next tile: positions [k, tile_end) of one group and run
        tile_end = k + 1;
        while (tile_end < parent_end && tile_end - k < kSilTile) tile_end++;
        w.tile.id = -1;
        if (tile_end - k >= 2) {
          w.tile.id = k;
          for (int d = 0; d < 3; d++) {
            w.tile.lo[d] = std::numeric_limits<double>::infinity();
            w.tile.hi[d] = -std::numeric_limits<double>::infinity();
          }
          w.tile.same_n = true;
          for (int d = 0; d < 3; d++) w.tile.n[d] = double(Nrm[3 * perm[k] + d]);
          for (int64_t q = k; q < tile_end; q++)
            for (int d = 0; d < 3; d++) {
              const double x = double(P[3 * perm[q] + d]);
              w.tile.same_n = w.tile.same_n && Nrm[3 * perm[q] + d] == Nrm[3 * perm[k] + d];
              if (!std::isfinite(x)) continue;
              w.tile.lo[d] = std::min(w.tile.lo[d], x);
              w.tile.hi[d] = std::max(w.tile.hi[d], x);
            }
          if (!tile_worth(tiles_mode, w.tile.lo, w.tile.hi, bvh.nodes[0].box)) w.tile.id = -1;
        }
      }
      const int32_t c = receiver_class(call, P, Nrm, i, w, err);
      cls[i] = c;
      // Only penumbra receivers are evaluated from their boundary: a lit receiver's would be
      // E_h's own edges (the unoccluded kernel evaluates it), so none are stored.
      if (c != kPenumbra) w.runs.clear();
      counts[i] = int32_t(w.runs.size());
      if (stats) {
        stats[2 * i] = w.n_candidates;
        stats[2 * i + 1] = w.n_regions;
      }
      if (runs_out)
        for (const Run& r : w.runs) {
          blk.codes.insert(blk.codes.end(), r.s.v, r.s.v + kCodeWidth);
          blk.codes.insert(blk.codes.end(), r.e.v, r.e.v + kCodeWidth);
        }
      if (lambert) lambert[i] = 0;
      if ((points_out || lambert) && !w.runs.empty()) {
        const size_t o = blk.pts.size();
        if (points_out) blk.pts.resize(o + 6 * w.runs.size());
        const T sum = decode_runs(call, ld(P + 3 * i), ld(Nrm + 3 * i), w.runs, ends, points_out ? blk.pts.data() + o : nullptr,
                                  lambert != nullptr);
        if (lambert) lambert[i] = sum;
      }
    }
    per_thread[t].push_back(std::move(blk));
  });
  offsets[0] = 0;
  for (int64_t i = 0; i < N; i++) offsets[i + 1] = offsets[i] + counts[i];
  int64_t total = offsets[N];
  *nruns_out = total;
  // A block's runs, receiver after receiver in its positions' order, to their CSR rows.
  auto scatter = [&](const Block& blk, auto* dst, const auto* src, int64_t width) {
    if (!sorted) {
      std::memcpy(dst + width * offsets[blk.s], src, sizeof(*src) * width * (offsets[blk.e] - offsets[blk.s]));
      return;
    }
    for (int64_t k = blk.s; k < blk.e; k++) {
      const int64_t i = perm[k], m = width * counts[i];
      if (m) std::memcpy(dst + width * offsets[i], src, sizeof(*src) * m);
      src += m;
    }
  };
  if (runs_out) {
    int32_t* runs = static_cast<int32_t*>(std::malloc(sizeof(int32_t) * kRunWidth * std::max<int64_t>(total, 1)));
    if (!runs) return 2;
    for (auto& blocks : per_thread)
      for (auto& blk : blocks)
        if (!blk.codes.empty()) scatter(blk, runs, blk.codes.data(), kRunWidth);
    *runs_out = runs;
  }
  if (points_out) {
    T* pts = static_cast<T*>(std::malloc(sizeof(T) * 6 * std::max<int64_t>(total, 1)));
    if (!pts) return 2;
    for (auto& blocks : per_thread)
      for (auto& blk : blocks)
        if (!blk.pts.empty()) scatter(blk, pts, blk.pts.data(), 6);
    *points_out = pts;
  }
  return err.load();
}

// Fixed-capacity variant (the FFI handler's layout): runs (N, cap, 2, 7), unused slots kUnused;
// `prep` is `occ`'s prepared data (`prepared(occ)`).
template <class T>
int poly_fixed(int64_t N, const T* P, const T* Nrm, int64_t K, const T* E, const Occluders<T>& occ,
               const Prepared& prep, int threads, int64_t cap, int32_t* cls, int32_t* counts, int32_t* runs) {
  const BVH& bvh = prep.bvh;
  PolyCall<T> call{Light<T>{K, E}, occ, &bvh, {}};
  bind_call(call, prep, N);
  std::atomic<int> err(0);
  parallel_for(N, default_threads(threads), [&](int, int64_t s, int64_t e) {
    Work<T> w;
    for (int64_t i = s; i < e; i++) {
      const int32_t c = receiver_class(call, P, Nrm, i, w, err);
      cls[i] = c;
      counts[i] = int32_t(w.runs.size());
      int32_t* out = runs + i * cap * kRunWidth;
      int64_t m = std::min<int64_t>(cap, int64_t(w.runs.size()));
      for (int64_t k = 0; k < m; k++) {
        std::memcpy(out + kRunWidth * k, w.runs[k].s.v, sizeof(w.runs[k].s.v));
        std::memcpy(out + kRunWidth * k + kCodeWidth, w.runs[k].e.v, sizeof(w.runs[k].e.v));
      }
      for (int64_t k = m; k < cap; k++)
        for (int q = 0; q < kRunWidth; q++) out[kRunWidth * k + q] = (q % kCodeWidth == 0) ? kUnused : 0;
    }
  });
  return err.load();
}

// Hard shadows: visible[i] 1 where the segment from P[i] to the point light X (is_point), or the
// ray from P[i] against the directional light's travel X, misses every occluder; `bvh` is `occ`'s
// hierarchy (`prepared(occ)->bvh`).
template <class T>
void hard_plan(int64_t N, const T* P, const T* X, int is_point, const Occluders<T>& occ, const BVH& bvh, int threads,
               uint8_t* visible) {
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
}

// Segment-light candidates of each receiver (segment_candidates) into `lists` (N); `bvh` as hard_plan's.
template <class T>
void segment_lists(int64_t N, const T* P, const T* A, const T* B, const Occluders<T>& occ, const BVH& bvh, int threads,
                   std::vector<std::vector<int32_t>>& lists) {
  V3<T> a = ld(A), b = ld(B);
  lists.resize(size_t(N));
  parallel_for(N, default_threads(threads), [&](int, int64_t s, int64_t e) {
    std::vector<std::pair<int32_t, int32_t>> cand;
    for (int64_t i = s; i < e; i++) segment_candidates(occ, bvh, ld(P + 3 * i), a, b, lists[i], cand);
  });
}

// The segment plan, CSR output: offsets (N + 1) and the candidate faces (malloc'd, freed by the caller).
template <class T>
int segment_plan(int64_t N, const T* P, const T* A, const T* B, const Occluders<T>& occ, int threads,
                 int64_t* offsets, int32_t** faces_out) {
  std::vector<std::vector<int32_t>> lists;
  segment_lists(N, P, A, B, occ, prepared(occ)->bvh, threads, lists);
  offsets[0] = 0;
  for (int64_t i = 0; i < N; i++) offsets[i + 1] = offsets[i] + int64_t(lists[i].size());
  int32_t* out = static_cast<int32_t*>(std::malloc(sizeof(int32_t) * std::max<int64_t>(offsets[N], 1)));
  if (!out) return 2;
  for (int64_t i = 0; i < N; i++)
    if (!lists[i].empty()) std::memcpy(out + offsets[i], lists[i].data(), sizeof(int32_t) * lists[i].size());
  *faces_out = out;
  return 0;
}


}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_DRIVER_H_
