// jaxshadow's shadow engine: occluder data prepared once per occluder set (part of
// `csrc/shadowc.cc`; see its header comment).
//
// The hierarchy of items (bvh.h), the faces' edge twins and the silhouette path's hierarchy of
// mesh edges depend on the occluders alone, and building them costs O(M log M) per call: 0.1 to
// 0.3 s for 70k to 80k faces, more than evaluating thousands of receivers. A small cache keyed by
// the occluder arrays' full contents (compared byte for byte, never by a hash alone) keeps the
// last few sets, so repeated calls on one scene (every light, every chunk of receivers, every
// `js.irradiance` call) build them once. Small sets are not cached: they build in microseconds.
// Every light kind reads the hierarchy; what only polygon lights read (`PolygonParts`) is built
// when the first polygon light needs it, so that point, directional and segment lights share
// the cache without paying for it.
#ifndef JAXSHADOW_SHADOWC_PREPARED_H_
#define JAXSHADOW_SHADOWC_PREPARED_H_

#include <algorithm>
#include <atomic>
#include <cstring>
#include <memory>
#include <mutex>
#include <vector>

#include "silhouette.h"

namespace jaxshadow_engine {

constexpr int64_t kCacheMinFaces = 1024;
constexpr size_t kCacheEntries = 4;
// Faces a receiver is taken to test (bind_call's choice of computing every face's light side).
constexpr int64_t kSideTestsPerReceiver = 64;

// What polygon lights read besides the hierarchy: the faces' edge twins, the silhouette path's
// hierarchy of mesh edges (without the light's heights: silhouette_heights), the bodies inside the
// mesh components (umbra_sections.h), the faces' Newell normals (`face_normals`) and their
// distinct vertices (`distinct_vertices`).
struct PolygonParts {
  std::vector<int32_t> twin;
  SilhouetteTree sil;
  InteriorSections sections;
  std::vector<double> face_normal;
  std::vector<int64_t> verts;
};

// Whether faces f and g have an edge with the same two end positions (`same`), either way.
template <class T>
bool share_edge(const Occluders<T>& occ, int64_t f, int64_t g) {
  for (int64_t i = 0; i < occ.Ko; i++) {
    const V3<T> u = occ.vert(f, i), v = occ.vert(f, (i + 1) % occ.Ko);
    if (same(u, v)) continue;
    for (int64_t j = 0; j < occ.Ko; j++) {
      const V3<T> x = occ.vert(g, j), y = occ.vert(g, (j + 1) % occ.Ko);
      if ((same(u, x) && same(v, y)) || (same(u, y) && same(v, x))) return true;
    }
  }
  return false;
}

// What the segment lights' contour path (silhouette_segment.h) reads besides the polygon parts,
// over their silhouette hierarchy: per edge slot, whether its two faces have the edge in common
// (`share_edge`; 0 for a slot without a second face), and per node, whether its subtree holds a
// pair of faces that do not (a T-junction's pair: their intervals need not meet bit for bit).
struct SegmentParts {
  std::vector<uint8_t> shared;    // per SilhouetteTree::edges
  std::vector<uint8_t> unshared;  // per SilhouetteTree::nodes
};

template <class T>
void build_segment_parts(const Occluders<T>& occ, const SilhouetteTree& st, SegmentParts& out) {
  out.shared.assign(st.edges.size(), 0);
  out.unshared.assign(st.nodes.size(), 0);
  if (!st.ok || st.fglob.size() != size_t(occ.M)) return;
  for (size_t j = 0; j < st.edges.size(); j++) {
    const SEdge& e = st.edges[j];
    if (e.g >= 0) out.shared[j] = share_edge(occ, st.fglob[size_t(e.f)], st.fglob[size_t(e.g)]) ? 1 : 0;
  }
  for (size_t k = st.nodes.size(); k-- > 0;) {  // children follow their parent
    const SNode& nd = st.nodes[k];
    if (nd.left >= 0) {
      out.unshared[k] = out.unshared[size_t(nd.left)] | out.unshared[size_t(nd.right)];
      continue;
    }
    for (int32_t j = nd.start; j < nd.start + nd.count && !out.unshared[k]; j++)
      if (st.edges[size_t(j)].g >= 0 && !out.shared[size_t(j)]) out.unshared[k] = 1;
  }
}

// The faces' vertex slots (f * Ko + i) whose coordinates (bit for bit) no earlier slot has, in slot
// order: a mesh's vertex is in about six faces, so a per-light pass over the vertices (the light's
// heights) reads a sixth as much; a minimum or maximum over them is that over every slot (a later
// repeat of a value never changes either).
template <class T>
std::vector<int64_t> distinct_vertices(const Occluders<T>& occ) {
  const int64_t n = occ.M * occ.Ko;
  std::vector<int64_t> order(static_cast<size_t>(n));
  for (int64_t k = 0; k < n; k++) order[size_t(k)] = k;
  auto bits = [&](int64_t k) { return occ.faces + 3 * k; };
  std::stable_sort(order.begin(), order.end(), [&](int64_t a, int64_t b) {
    return std::memcmp(bits(a), bits(b), 3 * sizeof(T)) < 0;
  });
  std::vector<uint8_t> first(size_t(n), 0);
  for (size_t j = 0; j < order.size(); j++)
    if (j == 0 || std::memcmp(bits(order[j - 1]), bits(order[j]), 3 * sizeof(T)) != 0) first[size_t(order[j])] = 1;
  std::vector<int64_t> out;
  for (int64_t k = 0; k < n; k++)
    if (first[size_t(k)]) out.push_back(k);
  return out;
}

// Counts of the cache's work since the process started (`prepared_stats`, for tests): lookups of
// a cached-size set, those found, hierarchies built (any size) and polygon parts built.
struct PreparedStats {
  std::atomic<int64_t> lookups{0}, hits{0}, builds{0}, polygon_builds{0};
};

inline PreparedStats& prepared_stats() {
  static PreparedStats stats;
  return stats;
}

struct Prepared {
  std::vector<char> key;
  BVH bvh;

  // The polygon lights' parts of `occ` (this set's occluders), built on the first call of a light
  // with occ.K vertices (once, whichever thread asks first; the others wait for it). One per K:
  // the parts hold vertex references (Occluders::ref), which are offset by the light's vertex
  // count, so a triangle light must not read the parts a quad light built.
  template <class T>
  const PolygonParts& polygon(const Occluders<T>& occ) const {
    PolygonEntry* e = entry(occ.K);
    std::call_once(e->once, [&]() {
      prepared_stats().polygon_builds++;
      PolygonParts& parts = e->parts;
      parts.twin = edge_twins(occ);
      build_silhouette_tree(occ, parts.twin, parts.sil);
      build_interior_sections(occ, parts.sil, parts.sections);
      parts.face_normal = face_normals(occ);
      parts.verts = distinct_vertices(occ);
    });
    return e->parts;
  }

  // The segment lights' parts over `polygon(occ)`'s silhouette hierarchy, built on the first
  // segment light's contour path (once, as the polygon parts; they depend on the occluders alone).
  template <class T>
  const SegmentParts& segment(const Occluders<T>& occ) const {
    const PolygonParts& parts = polygon(occ);
    PolygonEntry* e = entry(occ.K);
    std::call_once(e->segment_once, [&]() { build_segment_parts(occ, parts.sil, e->segment); });
    return e->segment;
  }

 private:
  struct PolygonEntry {
    int64_t K = 0;
    std::once_flag once, segment_once;
    PolygonParts parts;
    SegmentParts segment;
  };
  mutable std::mutex polygon_mu_;
  mutable std::vector<std::unique_ptr<PolygonEntry>> polygon_;  // one per light vertex count

  // The entry for light vertex count K, made on first use (entries are never removed, so the
  // pointer stays valid after the lock is released).
  PolygonEntry* entry(int64_t K) const {
    std::lock_guard<std::mutex> lock(polygon_mu_);
    for (const auto& x : polygon_)
      if (x->K == K) return x.get();
    polygon_.push_back(std::make_unique<PolygonEntry>());
    polygon_.back()->K = K;
    return polygon_.back().get();
  }
};

// Calls `put(pointer, bytes)` on each piece of `occ`'s key, in the key's order.
template <class T, class Put>
void occluder_key_pieces(const Occluders<T>& occ, Put&& put) {
  const int64_t head[3] = {occ.M, occ.Ko, occ.S};
  put(head, sizeof(head));
  put(occ.faces, sizeof(T) * size_t(occ.M * occ.Ko * 3));
  if (occ.face_solid) put(occ.face_solid, sizeof(int32_t) * size_t(occ.M));
  if (occ.face_closed) put(occ.face_closed, sizeof(int32_t) * size_t(occ.M));
  if (occ.S > 0) {
    put(occ.solid_faces, sizeof(int32_t) * size_t(2 * occ.S));
    put(occ.solid_edge_off, sizeof(int32_t) * size_t(occ.S + 1));
    put(occ.solid_edges, sizeof(int32_t) * size_t(4 * occ.solid_edge_off[occ.S]));
  }
}

template <class T>
std::vector<char> occluder_key(const Occluders<T>& occ) {
  std::vector<char> k;
  occluder_key_pieces(occ, [&](const void* p, size_t n) {
    const char* c = static_cast<const char*>(p);
    k.insert(k.end(), c, c + n);
  });
  return k;
}

// Whether `key` is `occ`'s key, compared piece by piece in place: a lookup reads each byte once
// and allocates nothing (building the key first cost an allocation and a copy of the occluders on
// every call, which a fit makes per iteration and per batch element).
template <class T>
bool key_matches(const std::vector<char>& key, const Occluders<T>& occ) {
  size_t at = 0;
  bool same = true;
  occluder_key_pieces(occ, [&](const void* p, size_t n) {
    if (!same) return;
    if (at + n > key.size() || std::memcmp(key.data() + at, p, n) != 0) same = false;
    at += n;
  });
  return same && at == key.size();
}

// The prepared data of `occ` (built now, or found in the cache).
template <class T>
std::shared_ptr<const Prepared> prepared(const Occluders<T>& occ) {
  static std::mutex mu;
  static std::vector<std::shared_ptr<const Prepared>> cache;  // most recent last
  const bool cached = occ.M >= kCacheMinFaces;
  if (cached) {
    prepared_stats().lookups++;
    std::lock_guard<std::mutex> lock(mu);
    for (size_t i = 0; i < cache.size(); i++)
      if (key_matches(cache[i]->key, occ)) {
        auto hit = cache[i];
        cache.erase(cache.begin() + long(i));
        cache.push_back(hit);
        prepared_stats().hits++;
        return hit;
      }
  }
  prepared_stats().builds++;
  auto out = std::make_shared<Prepared>();
  out->bvh = build_bvh(occ);
  prepare_solids(occ, out->bvh);
  if (cached) {
    out->key = occluder_key(occ);
    std::lock_guard<std::mutex> lock(mu);
    cache.push_back(out);
    if (cache.size() > kCacheEntries) cache.erase(cache.begin());
  }
  return out;
}

// A polygon light's per-call data over prepared occluders (`prep` outlives `call`), for a call of
// N receivers.
template <class T>
void bind_call(PolyCall<T>& call, const Prepared& prep, int64_t N) {
  const PolygonParts& parts = prep.polygon(call.occ);
  call.face_normal = parts.face_normal.data();
  // Every face's side of the light when the receivers are likely to test more faces than there
  // are (a face-path receiver tests tens to hundreds), else each when tested: the same values.
  prepare_call(call, N * kSideTestsPerReceiver >= call.occ.M);
  call.twin_ptr = &parts.twin;
  call.sil = &parts.sil;
  silhouette_heights(call, &parts.verts);
  // JAXSHADOW_UMBRA_SECTIONS=0: no early umbra test (for comparing it with the silhouette path);
  // =cells: the body cells' test alone (section_shows, not section_shows_exact).
  const char* env = std::getenv("JAXSHADOW_UMBRA_SECTIONS");
  if (call.sil_ok && !(env && env[0] == '0')) {
    const int64_t K = call.L.K;
    std::vector<double> lv(size_t(3 * K));
    for (int64_t i = 0; i < 3 * K; i++) lv[size_t(i)] = double(call.L.E[i]);
    const double ne[3] = {double(call.ne_raw.x), double(call.ne_raw.y), double(call.ne_raw.z)};
    prepare_sections(call.sections, &parts.sections, lv.data(), K, ne);
    call.sections.exact = !(env && std::strcmp(env, "cells") == 0);
  }
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_PREPARED_H_
