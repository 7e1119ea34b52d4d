// jaxshadow's shadow engine: occluder data prepared once per occluder set (part of
// `csrc/shadowc.cc`; see its header comment).
//
// The hierarchy of items (bvh.h), the faces' edge twins and the silhouette path's hierarchy of
// mesh edges depend on the occluders alone, and building them costs O(M log M) per call: 0.1 to
// 0.3 s for 70k to 80k faces, more than evaluating thousands of receivers. A small cache keyed by
// the occluder arrays' full contents (compared byte for byte, never by a hash alone) keeps the
// last few sets, so repeated calls on one scene (every light, every chunk of receivers, every
// `js.irradiance` call) build them once. Small sets are not cached: they build in microseconds.
#ifndef JAXSHADOW_SHADOWC_PREPARED_H_
#define JAXSHADOW_SHADOWC_PREPARED_H_

#include <cstring>
#include <memory>
#include <mutex>

#include "silhouette.h"

namespace jaxshadow_engine {

constexpr int64_t kCacheMinFaces = 1024;
constexpr size_t kCacheEntries = 4;

struct Prepared {
  std::vector<char> key;
  BVH bvh;
  std::vector<int32_t> twin;
  SilhouetteTree sil;  // without the light's heights (silhouette_heights)
  InteriorSections sections;  // bodies inside the mesh's components (umbra_sections.h)
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
    std::lock_guard<std::mutex> lock(mu);
    for (size_t i = 0; i < cache.size(); i++)
      if (key_matches(cache[i]->key, occ)) {
        auto hit = cache[i];
        cache.erase(cache.begin() + long(i));
        cache.push_back(hit);
        return hit;
      }
  }
  auto out = std::make_shared<Prepared>();
  out->bvh = build_bvh(occ);
  prepare_solids(occ, out->bvh);
  out->twin = edge_twins(occ);
  build_silhouette_tree(occ, out->twin, out->sil);
  build_interior_sections(occ, out->sil, out->sections);
  if (cached) {
    out->key = occluder_key(occ);
    std::lock_guard<std::mutex> lock(mu);
    cache.push_back(out);
    if (cache.size() > kCacheEntries) cache.erase(cache.begin());
  }
  return out;
}

// A polygon light's per-call data over prepared occluders (`prep` outlives `call`).
template <class T>
void bind_call(PolyCall<T>& call, const Prepared& prep) {
  prepare_call(call);
  call.twin_ptr = &prep.twin;
  call.sil = &prep.sil;
  silhouette_heights(call);
  // JAXSHADOW_UMBRA_SECTIONS=0: no early umbra test (for comparing it with the silhouette path);
  // =cells: the body cells' test alone (section_shows, not section_shows_exact).
  const char* env = std::getenv("JAXSHADOW_UMBRA_SECTIONS");
  if (call.sil_ok && !(env && env[0] == '0')) {
    const int64_t K = call.L.K;
    std::vector<double> lv(size_t(3 * K));
    for (int64_t i = 0; i < 3 * K; i++) lv[size_t(i)] = double(call.L.E[i]);
    const double ne[3] = {double(call.ne_raw.x), double(call.ne_raw.y), double(call.ne_raw.z)};
    prepare_sections(call.sections, &prep.sections, lv.data(), K, ne);
    call.sections.exact = !(env && std::strcmp(env, "cells") == 0);
  }
}

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_PREPARED_H_
