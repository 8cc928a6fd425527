// Tile binning: each visible Gaussian is listed in every 16x16 tile its bounding box
// touches, in front-to-back order. One global stable depth sort, then a counting fill,
// leaves every tile's list sorted without per-tile sorts.
#include <algorithm>
#include <cstring>
#include <numeric>
#include <vector>

#include "kernels.h"

namespace kgs {
namespace {

struct TileRect {
  int x0, y0, x1, y1;  // tile indices, exclusive end
};

inline TileRect tile_rect(const int32_t* b) {
  return {b[0] / TILE, b[1] / TILE, (b[2] - 1) / TILE + 1, (b[3] - 1) / TILE + 1};
}

// Stable LSD radix sort of positive float keys (their bit patterns order like the values).
void sort_by_depth(const std::vector<int32_t>& ids, const float* depths, std::vector<int32_t>& out) {
  const size_t n = ids.size();
  std::vector<uint32_t> keys(n), keys_tmp(n);
  std::vector<int32_t> vals(ids), vals_tmp(n);
  for (size_t i = 0; i < n; ++i) std::memcpy(&keys[i], &depths[ids[i]], 4);
  constexpr int BITS = 11, BUCKETS = 1 << BITS;
  std::vector<uint32_t> count(BUCKETS);
  for (int shift = 0; shift < 32; shift += BITS) {
    std::fill(count.begin(), count.end(), 0u);
    for (size_t i = 0; i < n; ++i) ++count[(keys[i] >> shift) & (BUCKETS - 1)];
    uint32_t sum = 0;
    for (auto& c : count) { const uint32_t t = c; c = sum; sum += t; }
    for (size_t i = 0; i < n; ++i) {
      const uint32_t dst = count[(keys[i] >> shift) & (BUCKETS - 1)]++;
      keys_tmp[dst] = keys[i];
      vals_tmp[dst] = vals[i];
    }
    keys.swap(keys_tmp);
    vals.swap(vals_tmp);
  }
  out.swap(vals);
}

void sort_by_depth(const std::vector<int32_t>& ids, const double* depths, std::vector<int32_t>& out) {
  out = ids;
  std::stable_sort(out.begin(), out.end(),
                   [depths](int32_t a, int32_t b) { return depths[a] < depths[b]; });
}

}  // namespace

int64_t bin_count_pairs(int64_t n, const int32_t* bbox, const int32_t* radii, int width,
                        int height, int32_t* tile_offsets, int64_t* n_visible) {
  const int tiles_x = (width + TILE - 1) / TILE, tiles_y = (height + TILE - 1) / TILE;
  const int n_tiles = tiles_x * tiles_y;
  std::vector<int64_t> counts(n_tiles, 0);
  int64_t visible = 0;
#pragma omp parallel
  {
    std::vector<int64_t> local(n_tiles, 0);
    int64_t local_visible = 0;
#pragma omp for schedule(static) nowait
    for (int64_t i = 0; i < n; ++i) {
      if (radii[i] <= 0) continue;
      ++local_visible;
      const TileRect r = tile_rect(bbox + 4 * i);
      for (int ty = r.y0; ty < r.y1; ++ty)
        for (int tx = r.x0; tx < r.x1; ++tx) ++local[ty * tiles_x + tx];
    }
#pragma omp critical
    {
      for (int t = 0; t < n_tiles; ++t) counts[t] += local[t];
      visible += local_visible;
    }
  }
  int64_t total = 0;
  for (int t = 0; t < n_tiles; ++t) {
    tile_offsets[t] = int32_t(total);
    total += counts[t];
  }
  tile_offsets[n_tiles] = int32_t(total);
  *n_visible = visible;
  return total;
}

// The fill runs in parallel over contiguous chunks of ranks: each chunk starts its tile
// cursors after the pairs of the chunks before it, so every tile list still comes out in
// rank order, whatever the thread count.
template <typename S>
void bin_fill(int64_t n, const int32_t* bbox, const int32_t* radii, const S* depths,
              int width, int height, const int32_t* tile_offsets, int32_t* order,
              int32_t* tile_ranks, int32_t* rank_start, int32_t* rank_pairs) {
  const int tiles_x = (width + TILE - 1) / TILE, tiles_y = (height + TILE - 1) / TILE;
  const int n_tiles = tiles_x * tiles_y;
  std::vector<int32_t> visible;
  visible.reserve(size_t(n));
  for (int64_t i = 0; i < n; ++i)
    if (radii[i] > 0) visible.push_back(int32_t(i));
  std::vector<int32_t> sorted;
  sort_by_depth(visible, depths, sorted);
  const int64_t n_vis = int64_t(sorted.size());
  std::copy(sorted.begin(), sorted.end(), order);
  // Tile rectangles in depth order, gathered once by an independent loop (many cache
  // misses in flight); the counting passes below then read them sequentially.
  std::vector<TileRect> rects(static_cast<size_t>(n_vis));
#pragma omp parallel for schedule(static)
  for (int64_t rank = 0; rank < n_vis; ++rank) rects[rank] = tile_rect(bbox + 4 * sorted[rank]);
  constexpr int CHUNKS = 8;
  std::vector<int32_t> chunk_tiles(size_t(CHUNKS) * n_tiles, 0);
  std::vector<int32_t> per_rank(static_cast<size_t>(n_vis));
  auto chunk_begin = [&](int c) { return n_vis * c / CHUNKS; };
#pragma omp parallel for schedule(static)
  for (int c = 0; c < CHUNKS; ++c) {
    int32_t* cnt = chunk_tiles.data() + size_t(c) * n_tiles;
    for (int64_t rank = chunk_begin(c); rank < chunk_begin(c + 1); ++rank) {
      const TileRect& r = rects[rank];
      per_rank[rank] = (r.y1 - r.y0) * (r.x1 - r.x0);
      for (int ty = r.y0; ty < r.y1; ++ty)
        for (int tx = r.x0; tx < r.x1; ++tx) ++cnt[ty * tiles_x + tx];
    }
  }
  // Turn per-chunk counts into per-chunk cursors; rank_start is the prefix sum per rank.
  for (int t = 0; t < n_tiles; ++t) {
    int32_t cur = tile_offsets[t];
    for (int c = 0; c < CHUNKS; ++c) {
      int32_t& v = chunk_tiles[size_t(c) * n_tiles + t];
      const int32_t k = v;
      v = cur;
      cur += k;
    }
  }
  rank_start[0] = 0;
  for (int64_t rank = 0; rank < n_vis; ++rank) rank_start[rank + 1] = rank_start[rank] + per_rank[rank];
#pragma omp parallel for schedule(static)
  for (int c = 0; c < CHUNKS; ++c) {
    int32_t* cursor = chunk_tiles.data() + size_t(c) * n_tiles;
    for (int64_t rank = chunk_begin(c); rank < chunk_begin(c + 1); ++rank) {
      const TileRect& r = rects[rank];
      int32_t j = rank_start[rank];
      for (int ty = r.y0; ty < r.y1; ++ty)
        for (int tx = r.x0; tx < r.x1; ++tx) {
          const int32_t pos = cursor[ty * tiles_x + tx]++;
          tile_ranks[pos] = int32_t(rank);
          rank_pairs[j++] = pos;
        }
    }
  }
}

template void bin_fill<float>(int64_t, const int32_t*, const int32_t*, const float*, int, int,
                              const int32_t*, int32_t*, int32_t*, int32_t*, int32_t*);
template void bin_fill<double>(int64_t, const int32_t*, const int32_t*, const double*, int, int,
                              const int32_t*, int32_t*, int32_t*, int32_t*, int32_t*);

}  // namespace kgs
