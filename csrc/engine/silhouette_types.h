// jaxshadow's shadow engine: the silhouette path's data (part of `csrc/shadowc.cc`; see
// silhouette.h).
#ifndef JAXSHADOW_SHADOWC_SILHOUETTE_TYPES_H_
#define JAXSHADOW_SHADOWC_SILHOUETTE_TYPES_H_

#include "geometry.h"

namespace jaxshadow_engine {

constexpr int64_t kSilhouetteMinFaces = 256;  // fewer faces: the face path is as fast
constexpr int32_t kFallback = -2;
// Contour pieces from which the arrangement uses a grid of the emitter plane (fewer: every pair
// and every path from q0 is as fast), and the grid's largest side in cells.
constexpr int kSilGridMin = 32;
constexpr int kSilGridMax = 128;
constexpr size_t kFnStride = 10;  // doubles per face in SilhouetteTree::fn

struct SEdge {
  int32_t ra, rb;  // vertex refs (K + f * Ko + i), the edge running ra -> rb in face f
  int32_t f, g;    // its faces (g = -1: a boundary or non-manifold edge slot; local indices once built)
  int8_t dg;       // +1: g runs it ra -> rb too (inconsistent orientation), -1: rb -> ra
};

// Each face's component through paired edges (`g >= 0`): a union-find over the `M` local
// faces; entry f is its component's root, the component's smallest face index.
inline std::vector<int32_t> face_components(const std::vector<SEdge>& edges, int64_t M) {
  std::vector<int32_t> up(static_cast<size_t>(M));
  for (int64_t f = 0; f < M; f++) up[size_t(f)] = int32_t(f);
  auto find = [&](int32_t x) {
    while (up[size_t(x)] != x) x = up[size_t(x)] = up[size_t(up[size_t(x)])];
    return x;
  };
  for (const SEdge& e : edges)
    if (e.g >= 0) {
      const int32_t a = find(e.f), b = find(e.g);
      if (a != b) up[size_t(std::max(a, b))] = std::min(a, b);
    }
  for (int64_t f = 0; f < M; f++) up[size_t(f)] = find(int32_t(f));
  return up;
}

struct alignas(64) SNode {  // two cache lines
  double box[6];               // the faces' vertices (lo, hi)
  double axis[3], cosa, sina;  // cone of the faces' unit normals (cosa < 0: no cone)
  double arad, hrad;           // the box's half extents h: sum |axis_i| h_i, and |h|
  int32_t left, right, start, count;  // nodes in the walk's order: right = this node + 1
  bool special;  // holds an edge with g < 0 or dg > 0
};

struct SilhouetteTree {
  std::vector<SEdge> edges;
  std::vector<SNode> nodes;
  // Faces in the order the tree's edges (leaf after leaf) first name them, so that a walk reads
  // them nearly front to back: SEdge::f and g, fn and f32 use these local indices; floc maps a
  // face of the occluders to its local index.
  std::vector<double> fn;  // per face (kFnStride): Newell normal (3), first vertex (3), unit normal (3), |Newell normal|
  std::vector<int32_t> floc;
  std::vector<int32_t> fglob;  // the inverse of floc: per local index, the face of the occluders
  double scale = 0;           // largest coordinate magnitude
  std::vector<uint8_t> f32;   // per face: every coordinate a float32 value (the on-surface rule)
  bool ok = false;
};

// A tile of receivers: the driver hands out consecutive receivers in spatial order in tiles of a
// few, with their box, so that the contour walk (silhouette_walk.h) walks the hierarchy once per
// tile. `id` < 0: no tile (each receiver walks the hierarchy).
struct SilTile {
  int64_t id = -1;
  double lo[3] = {0, 0, 0}, hi[3] = {0, 0, 0};  // the box of the tile's receivers
  bool same_n = false;  // every receiver of the tile has the normal n (bit for bit)
  double n[3] = {0, 0, 0};
  // The tile's parent: a run of a few consecutive tiles (pid < 0: none) whose walk of the
  // hierarchy the tile's own walk refines (silhouette_walk.h), with the box of its receivers.
  int64_t pid = -1;
  double plo[3] = {0, 0, 0}, phi[3] = {0, 0, 0};
};

// One entry of a tile's part of the hierarchy: a node that the tile's walk did not prune, in the
// walk's order (preorder, right subtree first; in the walk of a tile its receivers read, inner
// nodes with `sure` are left out); `skip` is the first entry after its subtree; for a
// leaf, its kept edges [e0, e1) in SilTileCache::edges; `sure`: no receiver of the tile prunes
// it (its tests are skipped). Otherwise `planes` holds the pyramid's planes that some receiver's
// test may prune it by (bit k: the receiver's cone plane k, bit K + 1 the emitter plane, K the
// light's vertex count; the others hold it inside for every receiver) and `side` whether its
// faces' sides may (node_side).
struct STEntry {
  int32_t node, skip, e0, e1;
  bool sure, side;
  uint64_t planes;
};

// A kept edge: its SEdge, its ends (the occluders' values), its coverage jump W when every
// receiver of the tile sees both faces on known sides (0: decided per receiver), `inm`: the
// pyramid's planes (STEntry::planes' bits) that both ends lie inside of for every receiver by a
// margin far above rounding (the receiver's clipping keeps the whole edge by those planes and its
// ends are clear of E_h's boundary along them), and `in`: every plane is such.
// `ia`, `ib`: the ends' position ids (equal iff the positions are equal, within one tile walk and
// the walks refining it: SilTileCache::nids of them).
// `fwd`, `dir`: whether a precedes b lexicographically and rescale(hi - lo) of the ends in that
// order (lo, hi), in the call's float type: the part of edge_plane that does not depend on the
// receiver. `lf`, `lg`: where W is 0, the faces' slots in SilTileCache::faces (lg -1 without g).
struct STEdge {
  SEdge e;
  int8_t w;
  bool in;
  bool fwd;
  int32_t ia, ib;
  int32_t lf, lg;
  uint64_t inm;
  double a[3], b[3];
  double dir[3];
};

// The hierarchy as seen from a whole tile (silhouette_walk.h, tile_walk): the nodes no receiver
// of the tile can prune, and the edges of their leaves that can be a contour edge of some
// receiver of the tile or make it fall back, with the coverage jump W where every receiver of the
// tile sees both faces on known sides (0: decided per receiver).
struct SilTileCache {
  int64_t id = -1;
  const void* tree = nullptr;
  bool ok = false;
  std::vector<STEntry> entries;
  std::vector<STEdge> edges;
  int32_t nids = 0;  // the edges' position ids are 0 .. nids - 1
  // The table of positions by their bits that assigns the ids (tile_walk; open addressing).
  struct Slot {
    double x, y, z;
    int32_t id;
  };
  std::vector<Slot> idtab;
  // The faces whose side some receiver of the tile decides itself (the edges' lf, lg), as
  // structure of arrays of their SilhouetteTree::fn records for the per-receiver side test:
  // Newell normal (fq[0..2]), first vertex (fq[3..5]), |Newell normal| (fnn), and whether the
  // face is of float32 values (f32: 1, else 0; the on-surface rule). `side`: their sides from the current
  // receiver (sil_side's +1, -1, 0). `slot`: per face of the tree its slot (-1: none; reset by
  // the next walk).
  std::vector<int32_t> faces;
  std::vector<double> fq[6], fnn, f32;
  std::vector<double> side;
  std::vector<int32_t> slot;
  std::vector<int8_t> pos_in;    // tile_walk's scratch: per position id, whether pos_m is set
  std::vector<uint64_t> pos_m;   // and its end test (end_planes)
  std::vector<int32_t> remap;  // tile_walk's scratch: entries' new indices
  // tile_walk's scratch: per face of the tree, its side over the tile (tile_side; 2: not yet
  // computed), and the faces set.
  std::vector<int8_t> fside;
  std::vector<int32_t> fside_set;
};

template <class T>
struct SSeg {
  SSeg() {}  // members unset: contour_edges builds each segment in place in Work::ssegs
  V3<T> a, b;  // in the emitter plane (clipped to E_h)
  V3<T> own;   // edge_plane(p, ., .) of the edge, canonical direction
  T own_n;     // norm(own)
  int q0s;     // side_of(q0, own) once q0 is chosen
  PlaneRef own_ref;
  Code ca, cb;
  int32_t w;            // coverage jump across it (positive side minus negative side); 0: an E_h edge
  int32_t va, vb;       // vertex refs of the mesh edge (-1 for E_h edges)
  int32_t ia, ib;       // position ids of x3a, x3b (STEdge::ia, ib; -1: none, positions compared)
  V3<T> x3a, x3b;       // the mesh edge's ends
  int32_t on_a, on_b;   // the cone plane an end was clipped at (-1: none)
};

}  // namespace jaxshadow_engine

#endif  // JAXSHADOW_SHADOWC_SILHOUETTE_TYPES_H_
