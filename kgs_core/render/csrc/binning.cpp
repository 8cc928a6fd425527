// Tile binning: each visible Gaussian is listed in every 16x16 tile its bounding box
// touches, in front-to-back order. One global stable depth sort, then a counting fill,
// leaves every tile's list sorted without per-tile sorts.
//
// Work buffers are kept across calls (per calling thread): at 50k Gaussians, fresh ones
// cost as much in first-touch page faults as the sort itself.
#include <algorithm>
#include <cstring>
#include <vector>

#include "kernels.h"

namespace kgs {
namespace {

inline TileRect tile_rect(const int32_t* b) { return bin_tile_rect(b[0], b[1], b[2], b[3]); }

// Nearly every box at ~30 Gaussians per pixel spans at most 2x2 tiles, with 1 or 2 in
// each direction at random, so loops over those spans mispredict their exits. A small box
// instead visits its four candidate tiles in row-major order without branches; the ones
// outside the box go to a discard counter at index n_tiles. (Counting 50k gathered boxes,
// alone in a loop: 0.49 -> 0.33 ms; inside the rendering pipeline the gain is in the noise.)
inline bool is_small(const TileRect& r) { return r.x1 - r.x0 <= 2 && r.y1 - r.y0 <= 2; }

// Calls visit(tile) for each tile of r in row-major order; for a small box, for its four
// candidate tiles, those outside the box as `discard`.
template <typename Visit>
inline void for_each_tile(const TileRect& r, int tiles_x, int discard, Visit&& visit) {
  if (is_small(r)) {
    const bool wide = r.x1 - r.x0 == 2, tall = r.y1 - r.y0 == 2;
    const int t = r.y0 * tiles_x + r.x0;
    visit(t);
    visit(wide ? t + 1 : discard);
    visit(tall ? t + tiles_x : discard);
    visit(wide && tall ? t + tiles_x + 1 : discard);
  } else {
    for (int ty = r.y0; ty < r.y1; ++ty)
      for (int tx = r.x0; tx < r.x1; ++tx) visit(ty * tiles_x + tx);
  }
}

template <typename T>
std::vector<T>& scratch(int which) {
  thread_local std::vector<T> buffers[4];
  return buffers[which];
}

// Stable LSD radix sort of the visible ids by positive float depth (their bit patterns
// order like the values): the three 11-bit digits' histograms in one pass, then three
// scatter passes.
void sort_by_depth(const float* depths, std::vector<int32_t>& ids) {
  const size_t n = ids.size();
  constexpr int BITS = 11, BUCKETS = 1 << BITS, PASSES = 3;
  auto& keys = scratch<uint32_t>(0);
  auto& keys_tmp = scratch<uint32_t>(1);
  auto& ids_tmp = scratch<int32_t>(2);
  keys.resize(n);
  keys_tmp.resize(n);
  ids_tmp.resize(n);
  uint32_t count[PASSES][BUCKETS] = {};
  for (size_t i = 0; i < n; ++i) {
    uint32_t k;
    std::memcpy(&k, &depths[ids[i]], 4);
    keys[i] = k;
    for (int p = 0; p < PASSES; ++p) ++count[p][(k >> (p * BITS)) & (BUCKETS - 1)];
  }
  for (int p = 0; p < PASSES; ++p) {
    uint32_t sum = 0;
    for (auto& c : count[p]) { const uint32_t t = c; c = sum; sum += t; }
    const int shift = p * BITS;
    for (size_t i = 0; i < n; ++i) {
      const uint32_t dst = count[p][(keys[i] >> shift) & (BUCKETS - 1)]++;
      keys_tmp[dst] = keys[i];
      ids_tmp[dst] = ids[i];
    }
    keys.swap(keys_tmp);
    ids.swap(ids_tmp);
  }
}

void sort_by_depth(const double* depths, std::vector<int32_t>& ids) {
  std::stable_sort(ids.begin(), ids.end(),
                   [depths](int32_t a, int32_t b) { return depths[a] < depths[b]; });
}

}  // namespace

// The fill runs in parallel over contiguous chunks of ranks: each chunk starts its tile
// cursors after the pairs of the chunks before it, so every tile list still comes out in
// rank order, whatever the thread count.
template <typename S>
void bin_gaussians(int64_t n, const int32_t* bbox, const int32_t* radii, const S* depths,
                   int width, int height, const std::function<BinOutputs(int64_t, int64_t)>& allocate) {
  const int tiles_x = (width + TILE - 1) / TILE, tiles_y = (height + TILE - 1) / TILE;
  const int n_tiles = tiles_x * tiles_y;
  auto& sorted = scratch<int32_t>(3);
  sorted.clear();
  for (int64_t i = 0; i < n; ++i)
    if (radii[i] > 0) sorted.push_back(int32_t(i));
  sort_by_depth(depths, sorted);
  const int64_t n_vis = int64_t(sorted.size());
  // Tile rectangles in depth order, gathered once by a loop of their own and read
  // sequentially by the counting and the fill. (Gathering inside the counting loop, whose
  // increments go through memory, left few misses in flight: binning +25 % at 50k / 256²,
  // +50 % at 200k / 512² in the rendering pipeline, where the boxes are no longer cached.)
  thread_local std::vector<TileRect> rects;
  thread_local std::vector<int32_t> per_rank, chunk_tiles;
  rects.resize(size_t(n_vis));
  per_rank.resize(size_t(n_vis));
  constexpr int CHUNKS = 8;
  const int stride = n_tiles + 1;  // each chunk's counters, plus the discard counter
  chunk_tiles.assign(size_t(CHUNKS) * stride, 0);
  auto chunk_begin = [n_vis](int c) { return n_vis * c / CHUNKS; };
  // (thread_local buffers are the calling thread's: inside the parallel regions they are
  // reached only through these pointers, never by name.)
  TileRect* rect = rects.data();
  int32_t* pairs_of = per_rank.data();
  int32_t* chunk_count = chunk_tiles.data();
  const int32_t* by_rank = sorted.data();
#pragma omp parallel
  {
    // Boxes read in depth order are random reads of memory the projection wrote long
    // before; fetching them GATHER_AHEAD ranks ahead keeps enough misses in flight (the
    // gather alone 0.55 -> 0.2-0.3 ms at 50k).
    constexpr int64_t GATHER_AHEAD = 32;
#pragma omp for schedule(static)
    for (int64_t rank = 0; rank < n_vis; ++rank) {
      if (rank + GATHER_AHEAD < n_vis) __builtin_prefetch(bbox + 4 * by_rank[rank + GATHER_AHEAD]);
      rect[rank] = tile_rect(bbox + 4 * by_rank[rank]);
    }
#pragma omp for schedule(static)
    for (int c = 0; c < CHUNKS; ++c) {
      int32_t* cnt = chunk_count + size_t(c) * stride;
      for (int64_t rank = chunk_begin(c); rank < chunk_begin(c + 1); ++rank) {
        const TileRect& r = rect[rank];
        pairs_of[rank] = (r.y1 - r.y0) * (r.x1 - r.x0);
        for_each_tile(r, tiles_x, n_tiles, [cnt](int tile) { ++cnt[tile]; });
      }
    }
  }
  int64_t n_pairs = 0;
  for (int t = 0; t < n_tiles; ++t)
    for (int c = 0; c < CHUNKS; ++c) n_pairs += chunk_count[size_t(c) * stride + t];
  const BinOutputs out = allocate(n_vis, n_pairs);
  std::copy(sorted.begin(), sorted.end(), out.order);
  // Per-chunk counts become per-chunk cursors; the tile offsets fall out on the way.
  int32_t cur = 0;
  for (int t = 0; t < n_tiles; ++t) {
    out.tile_offsets[t] = cur;
    for (int c = 0; c < CHUNKS; ++c) {
      int32_t& v = chunk_count[size_t(c) * stride + t];
      const int32_t k = v;
      v = cur;
      cur += k;
    }
  }
  out.tile_offsets[n_tiles] = cur;
  // Each Gaussian's pairs get a contiguous range of numbers in id order (the forward numbers
  // a pair by its tile's place in the Gaussian's rectangle): the backward sums them there
  // and writes its outputs in one sequential pass.
  int32_t* id_start = out.id_start;
  std::fill(id_start, id_start + n + 1, 0);
  for (int64_t rank = 0; rank < n_vis; ++rank) id_start[by_rank[rank] + 1] = pairs_of[rank];
  for (int64_t g = 0; g < n; ++g) id_start[g + 1] += id_start[g];
#pragma omp parallel for schedule(static)
  for (int c = 0; c < CHUNKS; ++c) {
    int32_t* cursor = chunk_count + size_t(c) * stride;
    for (int64_t rank = chunk_begin(c); rank < chunk_begin(c + 1); ++rank) {
      int32_t discarded;
      for_each_tile(rect[rank], tiles_x, n_tiles, [&](int tile) {
        const int32_t pos = cursor[tile]++;
        *(tile != n_tiles ? out.tile_ranks + pos : &discarded) = int32_t(rank);
      });
    }
  }
}

template void bin_gaussians<float>(int64_t, const int32_t*, const int32_t*, const float*, int, int,
                                   const std::function<BinOutputs(int64_t, int64_t)>&);
template void bin_gaussians<double>(int64_t, const int32_t*, const int32_t*, const double*, int, int,
                                    const std::function<BinOutputs(int64_t, int64_t)>&);

}  // namespace kgs
