// Tile rasteriser, forward and hand-written backward.
//
// Work is split over 16x16 tiles (OpenMP, dynamic schedule: tiles differ a lot in load).
// Inside a tile the loop is Gaussian-major: each Gaussian in depth order updates only the
// rows of its bounding box. A tile row is exactly one 16-lane vector (simd.h: AVX-512
// registers with predicate masks for float, vector extensions otherwise), so the per-pixel
// state of a tile is 16 vectors and every update is straight-line SIMD code.
//
// The forward first writes a compact record per (tile, Gaussian) pair in tile-list order
// (screen-space parameters, its box clipped to the tile, its colour), which the backward
// reuses: the kernels stream memory forward instead of missing the cache on a scene-wide
// array per pair (those misses were ~15 % of the forward).
//
// The backward walks the same lists back to front, recovering each pixel's transmittance
// by division (alpha <= ALPHA_MAX keeps 1 - alpha >= 0.01), and writes one gradient slot
// per pair, rank-major, so each Gaussian's slots are contiguous and summed in a fixed
// order: results do not depend on the thread count.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <new>
#include <vector>

#include "kernels.h"
#include "simd.h"

namespace kgs {
namespace {

// Cache-line aligned storage for the packed per-Gaussian lines.
template <typename T>
struct AlignedAllocator {
  using value_type = T;
  AlignedAllocator() = default;
  template <typename U>
  AlignedAllocator(const AlignedAllocator<U>&) {}
  T* allocate(size_t n) { return static_cast<T*>(::operator new(n * sizeof(T), std::align_val_t(64))); }
  void deallocate(T* p, size_t) { ::operator delete(p, std::align_val_t(64)); }
  bool operator==(const AlignedAllocator&) const { return true; }
  bool operator!=(const AlignedAllocator&) const { return false; }
};

static_assert(TILE == LANES, "one tile row is one 16-lane vector");
static_assert(RECORD_HEAD == 9, "read_pair and build_pairs spell out the record head");

// One (tile, Gaussian) pair as the kernels read it from its record: RECORD_HEAD scalars
// (mx, my, ca, cb, cc, opacity, depth, the box clipped to the tile as four bytes, the
// pair's index in rank-major order as an int32), then the colour channels.
template <typename S>
struct PairRec {
  S mx, my, ca, cb, cc, op, z;
  int x0, x1, y0, y1;  // tile-relative, ends exclusive
  int32_t rank_slot;
  const S* col;
};

template <typename S>
inline PairRec<S> read_pair(const S* rec) {
  PairRec<S> p;
  p.mx = rec[0]; p.my = rec[1]; p.ca = rec[2]; p.cb = rec[3]; p.cc = rec[4];
  p.op = rec[5]; p.z = rec[6];
  uint8_t clip[4];
  std::memcpy(clip, rec + 7, 4);
  p.x0 = clip[0]; p.x1 = clip[1]; p.y0 = clip[2]; p.y1 = clip[3];
  std::memcpy(&p.rank_slot, rec + 8, 4);
  p.col = rec + RECORD_HEAD;
  return p;
}

struct TileGeom {
  int px0, py0;     // tile origin in pixels
  int w, h;         // tile extent inside the image
  int begin, end;   // range in the pair lists
};

inline TileGeom tile_geom(const RasterShape& s, const int32_t* tile_offsets, int tile) {
  TileGeom g;
  g.px0 = (tile % s.tiles_x) * TILE;
  g.py0 = (tile / s.tiles_x) * TILE;
  g.w = std::min(TILE, s.width - g.px0);
  g.h = std::min(TILE, s.height - g.py0);
  g.begin = tile_offsets[tile];
  g.end = tile_offsets[tile + 1];
  return g;
}

// Writes every pair's record in tile-list order (sequential writes). Depth order is random
// in memory, so each pair's inputs cost cache misses: they are first packed per Gaussian,
// in id order, into one 64-byte line (mx, my, ca, cb, cc, opacity, depth, box as 4 int16,
// colour), which makes it one miss per pair instead of one per input array (gathering the
// seven arrays in depth order took as long as the forward kernel).
template <typename S>
void build_pairs(const RasterShape& s, const TileLists& L, int64_t n, const S* means2d,
                 const S* conics, const S* opac, const S* colors, const S* depths,
                 const int32_t* bbox, S* records) {
  const int C = s.channels;
  const int R = RECORD_HEAD + C;
  constexpr int LINE = 64 / sizeof(S);
  const int P = (R + LINE - 1) / LINE * LINE;  // packed stride, whole cache lines
  const int n_tiles = s.tiles_x * s.tiles_y;
  thread_local std::vector<S, AlignedAllocator<S>> packed;
  thread_local std::vector<int32_t> pair_slot;
  packed.resize(size_t(n) * P);
  pair_slot.resize(size_t(L.n_pairs));
  S* G = packed.data();
  int32_t* slot_of = pair_slot.data();
#pragma omp parallel
  {
#pragma omp for schedule(static) nowait
    for (int64_t g = 0; g < n; ++g) {
      S* d = G + size_t(g) * P;
      d[0] = means2d[2 * g]; d[1] = means2d[2 * g + 1];
      d[2] = conics[3 * g]; d[3] = conics[3 * g + 1]; d[4] = conics[3 * g + 2];
      d[5] = opac[g]; d[6] = depths[g];
      int16_t box[4];
      for (int q = 0; q < 4; ++q) box[q] = int16_t(std::min(bbox[4 * g + q], 32767));
      std::memcpy(d + 7, box, 4);      // x0, y0
      std::memcpy(d + 8, box + 2, 4);  // x1, y1
      for (int ch = 0; ch < C; ++ch) d[RECORD_HEAD + ch] = colors[size_t(g) * C + ch];
    }
#pragma omp for schedule(static)
    for (int64_t j = 0; j < L.n_pairs; ++j) slot_of[L.rank_pairs[j]] = int32_t(j);
#pragma omp for schedule(dynamic, 4)
    for (int tile = 0; tile < n_tiles; ++tile) {
      const TileGeom t = tile_geom(s, L.tile_offsets, tile);
      for (int k = t.begin; k < t.end; ++k) {
        if (k + 8 < t.end) __builtin_prefetch(G + size_t(L.order[L.tile_ranks[k + 8]]) * P);
        const S* src = G + size_t(L.order[L.tile_ranks[k]]) * P;
        S* rec = records + size_t(k) * R;
        int16_t box[4];
        std::memcpy(box, src + 7, 4);
        std::memcpy(box + 2, src + 8, 4);
        const uint8_t clip[4] = {uint8_t(std::clamp(box[0] - t.px0, 0, TILE)),
                                 uint8_t(std::clamp(box[2] - t.px0, 0, TILE)),
                                 uint8_t(std::clamp(box[1] - t.py0, 0, TILE)),
                                 uint8_t(std::clamp(box[3] - t.py0, 0, TILE))};
        for (int q = 0; q < 7; ++q) rec[q] = src[q];
        std::memcpy(rec + 7, clip, 4);
        std::memcpy(rec + 8, slot_of + k, 4);
        for (int ch = 0; ch < C; ++ch) rec[RECORD_HEAD + ch] = src[RECORD_HEAD + ch];
      }
    }
  }
}

// What one Gaussian contributes along a tile row, with everything that does not depend on
// the row hoisted out: power(dy) = p0 + dy * p1 - cc dy^2 / 2 per lane.
template <typename S>
struct GaussLanes {
  using X = Simd<S>;
  using V = typename X::V;
  using M = typename X::M;
  V dx, p0, p1;
  M in_box;  // lanes inside the Gaussian's bounding box
  S half_cc, op;
  GaussLanes(V px, const PairRec<S>& p) {
    dx = px - X::set1(p.mx);
    p0 = X::set1(S(-0.5) * p.ca) * dx * dx;
    p1 = X::set1(-p.cb) * dx;
    in_box = X::lanes_in(p.x0, p.x1);
    half_cc = S(0.5) * p.cc;
    op = p.op;
  }
};

// The per-row evaluation both passes share: lanes where the Gaussian takes part (before
// the pixel's own cut-off, which the caller adds), its Gaussian value, raw and clamped alpha.
template <typename S>
struct RowEval {
  typename Simd<S>::V G, a_raw, alpha;
  typename Simd<S>::M ok;
};

template <typename S>
inline RowEval<S> eval_row(const GaussLanes<S>& gl, S dy) {
  using X = Simd<S>;
  RowEval<S> e;
  const auto power = gl.p0 + X::set1(dy) * gl.p1 - X::set1(gl.half_cc * dy * dy);
  e.G = X::exp(power);
  e.a_raw = X::set1(gl.op) * e.G;
  e.alpha = X::min(e.a_raw, X::set1(S(ALPHA_MAX)));
  e.ok = X::mand(gl.in_box, X::mand(X::le(power, X::zero()), X::ge(e.alpha, X::set1(S(ALPHA_MIN)))));
  return e;
}

// Pixel-centre x of each lane of a tile.
template <typename S>
typename Simd<S>::V lane_px(const TileGeom& t) {
  S px[TILE];
  for (int i = 0; i < TILE; ++i) px[i] = S(t.px0 + i) + S(0.5);
  return Simd<S>::load(px);
}

template <typename S>
void forward_tile(const RasterShape& s, const TileGeom& t, const S* records,
                  const S* background, S* image, S* alpha_out, S* depth_out,
                  S* t_final, int32_t* n_contrib, std::vector<typename Simd<S>::V>& acc) {
  using X = Simd<S>;
  using V = typename X::V;
  using M = typename X::M;
  using Idx = typename X::Idx;
  const int C = s.channels;
  const V px = lane_px<S>(t);
  V T[TILE], dacc[TILE];
  Idx last[TILE];
  M done[TILE];
  acc.assign(size_t(C) * TILE, X::zero());
  int n_done = 0;
  for (int r = 0; r < TILE; ++r) {
    T[r] = X::set1(S(1));
    dacc[r] = X::zero();
    last[r] = X::iset1(0);
    // Pixels outside the image count as finished so that edge tiles can stop early.
    done[r] = r < t.h ? X::mnot(X::lanes_in(0, t.w)) : X::all();
    n_done += X::count(done[r]);
  }
  for (int k = t.begin; k < t.end && n_done < TILE_PIXELS; ++k) {
    const PairRec<S> p = read_pair(records + size_t(k) * (RECORD_HEAD + C));
    const S* col = p.col;
    const Idx list_pos = X::iset1(k - t.begin + 1);
    const GaussLanes<S> gl(px, p);
    const V gz = X::set1(p.z);
    M any_term = X::none();
    for (int r = p.y0; r < p.y1; ++r) {
      if (!X::any(X::mandnot(gl.in_box, done[r]))) continue;  // row finished: skip the exp
      const RowEval<S> e = eval_row(gl, S(t.py0 + r) + S(0.5) - p.my);
      const M in = X::mandnot(e.ok, done[r]);
      const V test_t = T[r] * (X::set1(S(1)) - e.alpha);
      const M term = X::mand(in, X::lt(test_t, X::set1(S(T_MIN))));
      const M use = X::mandnot(in, term);
      const V w = X::keep(use, e.alpha * T[r]);
      T[r] = X::select(use, test_t, T[r]);
      last[r] = X::iselect(use, list_pos, last[r]);
      done[r] = X::mor(done[r], term);
      any_term = X::mor(any_term, term);
      dacc[r] += w * gz;
      for (int ch = 0; ch < C; ++ch) acc[size_t(ch) * TILE + r] += w * X::set1(col[ch]);
    }
    if (X::any(any_term)) {
      n_done = 0;
      for (int r = 0; r < TILE; ++r) n_done += X::count(done[r]);
    }
  }
  S Tl[TILE], dl[TILE], cl[TILE];
  int32_t ll[TILE];
  for (int r = 0; r < t.h; ++r) {
    X::store(Tl, T[r]);
    X::store(dl, dacc[r]);
    X::istore(ll, last[r]);
    const size_t row = size_t(t.py0 + r) * s.width + t.px0;
    for (int i = 0; i < t.w; ++i) {
      alpha_out[row + i] = S(1) - Tl[i];
      depth_out[row + i] = dl[i];
      t_final[row + i] = Tl[i];
      n_contrib[row + i] = ll[i];
    }
    for (int ch = 0; ch < C; ++ch) {
      X::store(cl, acc[size_t(ch) * TILE + r]);
      for (int i = 0; i < t.w; ++i) image[(row + i) * C + ch] = cl[i] + Tl[i] * background[ch];
    }
  }
}

// Gradient slot layout per (tile, Gaussian) pair, padded to whole 16-lane vectors so that
// the per-Gaussian sums are vector adds (a scalar loop over 12 values cost 12 % of the
// backward).
enum Slot { MX = 0, MY, CA, CB, CC, OP, DEPTH, ABS_MX, ABS_MY, COLOR0 };
inline int slot_stride(int channels) { return (COLOR0 + channels + LANES - 1) / LANES * LANES; }

// ABS: also accumulate |dL/dmean2d| per pixel (AbsGS densification); without it the mean
// and conic gradients come from five moments of gp (per-Gaussian constants factored out
// of the row loop), which halves that part of the loop.
template <typename S, bool ABS>
void backward_tile(const RasterShape& s, const TileGeom& t, const S* records,
                   const S* background, const S* t_final,
                   const int32_t* n_contrib, const S* g_image, const S* g_alpha,
                   const S* g_depth, S* slots, std::vector<typename Simd<S>::V>& scratch) {
  using X = Simd<S>;
  using V = typename X::V;
  using M = typename X::M;
  using Idx = typename X::Idx;
  const int C = s.channels;
  const int stride = slot_stride(C);
  const V px = lane_px<S>(t);
  // Per-pixel state. dL/dalpha of a Gaussian at a pixel is
  //   gA T_final / (1 - a) + sum_c gC_c (c_c T_i - behind_c / (1 - a)) + (same for depth)
  // = (gAT - Bg) / (1 - a) + T_i gcc,
  // with gAT = gA T_final, gcc = sum_c gC_c c_c + gD z (this Gaussian's colour and depth
  // seen through the image gradient) and Bg = sum_c gC_c behind_c + gD behind_depth (what
  // lies behind it, seen the same way): one running value per pixel instead of one per
  // channel, which halves the row loop's work.
  scratch.assign(size_t(2 * C) * TILE, X::zero());
  V* gC = scratch.data();              // image gradient, channel-major
  V* s_col = gC + size_t(C) * TILE;   // per-Gaussian colour gradient, per lane
  V gAT[TILE], gD[TILE], Tcur[TILE], Bg[TILE];
  Idx last[TILE];
  {
    S tf[TILE], ga[TILE], gd[TILE], gc[TILE];
    int32_t nc[TILE];
    for (int r = 0; r < TILE; ++r) {
      std::fill(tf, tf + TILE, S(1));
      std::fill(ga, ga + TILE, S(0));
      std::fill(gd, gd + TILE, S(0));
      std::fill(nc, nc + TILE, 0);
      const size_t row = size_t(t.py0 + r) * s.width + t.px0;
      if (r < t.h) {
        for (int i = 0; i < t.w; ++i) {
          tf[i] = t_final[row + i];
          ga[i] = g_alpha[row + i];
          gd[i] = g_depth[row + i];
          nc[i] = n_contrib[row + i];
        }
      }
      const V Tfin = X::load(tf);
      Tcur[r] = Tfin;
      gAT[r] = X::load(ga) * Tfin;
      gD[r] = X::load(gd);
      last[r] = X::iload(nc);
      Bg[r] = X::zero();
      for (int ch = 0; ch < C; ++ch) {
        std::fill(gc, gc + TILE, S(0));
        if (r < t.h)
          for (int i = 0; i < t.w; ++i) gc[i] = g_image[(row + i) * C + ch];
        gC[size_t(ch) * TILE + r] = X::load(gc);
        Bg[r] += gC[size_t(ch) * TILE + r] * Tfin * X::set1(background[ch]);
      }
    }
  }
  for (int k = t.end - 1; k >= t.begin; --k) {
    const PairRec<S> p = read_pair(records + size_t(k) * (RECORD_HEAD + C));
    const S* col = p.col;
    S* slot = slots + size_t(p.rank_slot) * stride;  // rank-major: summed sequentially
    const Idx list_pos = X::iset1(k - t.begin);  // contributes where list_pos < last
    // Moments of gp = dL/dpower over the pixels: sum gp dx, gp dy, gp dx^2, gp dx dy, gp dy^2.
    V m_x = X::zero(), m_y = m_x, m_xx = m_x, m_xy = m_x, m_yy = m_x, a_op = m_x;
    V a_d = m_x, a_amx = m_x, a_amy = m_x;
    for (int ch = 0; ch < C; ++ch) s_col[ch] = X::zero();
    const GaussLanes<S> gl(px, p);
    const V& dx = gl.dx;
    const V gz = X::set1(p.z), ca = X::set1(p.ca), cb = X::set1(p.cb), cc = X::set1(p.cc);
    for (int r = p.y0; r < p.y1; ++r) {
      // Pixels that stopped before this Gaussian: skip the row before paying for the exp.
      if (!X::any(X::mand(gl.in_box, X::ilt(list_pos, last[r])))) continue;
      const S dy_s = S(t.py0 + r) + S(0.5) - p.my;
      const RowEval<S> e = eval_row(gl, dy_s);
      const M use = X::mand(e.ok, X::ilt(list_pos, last[r]));
      if (!X::any(use)) continue;
      const V dy = X::set1(dy_s);
      const V inv = X::rcp(X::set1(S(1)) - e.alpha);
      const V Ti = Tcur[r] * inv;  // transmittance in front of this Gaussian
      const V w = X::keep(use, e.alpha * Ti);
      V gcc = gD[r] * gz;
      for (int ch = 0; ch < C; ++ch) {
        const V gc = gC[size_t(ch) * TILE + r];
        gcc += gc * X::set1(col[ch]);
        s_col[ch] += w * gc;
      }
      const V dal = inv * (gAT[r] - Bg[r]) + Ti * gcc;
      Bg[r] += w * gcc;
      a_d += w * gD[r];
      Tcur[r] = X::select(use, Ti, Tcur[r]);
      // Through alpha = min(ALPHA_MAX, o * exp(power)) to the 2D Gaussian.
      // Masked products: lanes that do not take part contribute exact zeros, whatever
      // their (unused) values are.
      const M live = X::mand(use, X::lt(e.a_raw, X::set1(S(ALPHA_MAX))));
      const V gp = X::keep(live, dal * e.a_raw);
      a_op += X::keep(live, dal * e.G);
      const V gpdx = gp * dx;
      m_x += gpdx;
      m_y += gp * dy;
      m_xx += gpdx * dx;
      m_xy += gpdx * dy;
      m_yy += gp * X::set1(dy_s * dy_s);
      if constexpr (ABS) {
        a_amx += X::abs(gp * (ca * dx + cb * dy));
        a_amy += X::abs(gp * (cb * dx + cc * dy));
      }
    }
    const S sx = X::hsum(m_x), sy = X::hsum(m_y);
    slot[MX] = p.ca * sx + p.cb * sy;
    slot[MY] = p.cb * sx + p.cc * sy;
    slot[CA] = S(-0.5) * X::hsum(m_xx);
    slot[CB] = -X::hsum(m_xy);
    slot[CC] = S(-0.5) * X::hsum(m_yy);
    slot[OP] = X::hsum(a_op);
    slot[DEPTH] = X::hsum(a_d);
    slot[ABS_MX] = ABS ? X::hsum(a_amx) : S(0);
    slot[ABS_MY] = ABS ? X::hsum(a_amy) : S(0);
    for (int ch = 0; ch < C; ++ch) slot[COLOR0 + ch] = X::hsum(s_col[ch]);
  }
}

// The backward's gradient slots, kept across calls (per calling thread): a fresh
// multi-megabyte vector per call costs page faults on every first touch (~7 % of the
// backward). It keeps n_pairs * slot_stride(channels) scalars of the largest call so far, per
// calling thread, until the thread ends.
template <typename T>
std::vector<T>& reusable_slots() {
  thread_local std::vector<T> slots;
  return slots;
}

}  // namespace

template <typename S>
void raster_forward(const RasterShape& s, const TileLists& L, int64_t n, const S* means2d,
                    const S* conics, const S* opac, const S* colors, const S* depths, const int32_t* bbox,
                    const S* background, S* records, S* image, S* alpha, S* depth_acc,
                    S* t_final, int32_t* n_contrib) {
  const int n_tiles = s.tiles_x * s.tiles_y;
  build_pairs(s, L, n, means2d, conics, opac, colors, depths, bbox, records);
#pragma omp parallel
  {
    std::vector<typename Simd<S>::V> acc;
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < n_tiles; ++tile) {
      forward_tile(s, tile_geom(s, L.tile_offsets, tile), records, background, image, alpha,
                   depth_acc, t_final, n_contrib, acc);
    }
  }
}

template <typename S>
void raster_backward(const RasterShape& s, const TileLists& L, int64_t n, const S* records,
                     const S* background, const S* t_final, const int32_t* n_contrib,
                     const S* g_image, const S* g_alpha, const S* g_depth, S* g_means2d,
                     S* g_conics, S* g_opac, S* g_colors, S* g_depths, S* abs_g_means2d,
                     bool absgrad) {
  const int n_tiles = s.tiles_x * s.tiles_y;
  const int C = s.channels;
  const int stride = slot_stride(C);
  auto& slots = reusable_slots<S>();
  slots.resize(size_t(L.n_pairs) * stride);
#pragma omp parallel
  {
    std::vector<typename Simd<S>::V> scratch;
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < n_tiles; ++tile) {
      const TileGeom t = tile_geom(s, L.tile_offsets, tile);
      if (absgrad)
        backward_tile<S, true>(s, t, records, background, t_final, n_contrib, g_image, g_alpha,
                               g_depth, slots.data(), scratch);
      else
        backward_tile<S, false>(s, t, records, background, t_final, n_contrib, g_image, g_alpha,
                                g_depth, slots.data(), scratch);
    }
  }
  // Each Gaussian's slots are contiguous (rank-major) and summed in list order, into one
  // line per rank; the outputs are then written in id order, reading each Gaussian's line
  // once (scattering six output arrays by depth order missed the cache on every store).
  using X = Simd<S>;
  const int n_vec = stride / LANES;
  // (thread_local buffers are the calling thread's: inside the parallel regions below they
  // are reached only through these pointers, never by name.)
  thread_local std::vector<S, AlignedAllocator<S>> per_rank_buf;
  thread_local std::vector<int32_t> rank_of_buf;
  per_rank_buf.resize(size_t(L.n_visible) * stride);
  rank_of_buf.assign(size_t(n), -1);
  S* per_rank = per_rank_buf.data();
  int32_t* rank_of = rank_of_buf.data();
#pragma omp parallel
  {
    std::vector<typename X::V> acc(n_vec);
#pragma omp for schedule(static) nowait
    for (int64_t i = 0; i < L.n_visible; ++i) {
      for (auto& v : acc) v = X::zero();
      for (int32_t j = L.rank_start[i]; j < L.rank_start[i + 1]; ++j) {
        const S* slot = slots.data() + size_t(j) * stride;
        for (int q = 0; q < n_vec; ++q) acc[q] += X::load(slot + q * LANES);
      }
      for (int q = 0; q < n_vec; ++q) X::store(per_rank + size_t(i) * stride + q * LANES, acc[q]);
    }
#pragma omp for schedule(static)
    for (int64_t i = 0; i < L.n_visible; ++i) rank_of[L.order[i]] = int32_t(i);
#pragma omp for schedule(static)
    for (int64_t g = 0; g < n; ++g) {
      const int32_t r = rank_of[g];
      if (r < 0) {  // not visible: no gradient
        g_means2d[2 * g] = g_means2d[2 * g + 1] = S(0);
        abs_g_means2d[2 * g] = abs_g_means2d[2 * g + 1] = S(0);
        g_conics[3 * g] = g_conics[3 * g + 1] = g_conics[3 * g + 2] = S(0);
        g_opac[g] = g_depths[g] = S(0);
        for (int ch = 0; ch < C; ++ch) g_colors[size_t(g) * C + ch] = S(0);
        continue;
      }
      const S* a = per_rank + size_t(r) * stride;
      g_means2d[2 * g] = a[MX];
      g_means2d[2 * g + 1] = a[MY];
      abs_g_means2d[2 * g] = a[ABS_MX];
      abs_g_means2d[2 * g + 1] = a[ABS_MY];
      g_conics[3 * g] = a[CA];
      g_conics[3 * g + 1] = a[CB];
      g_conics[3 * g + 2] = a[CC];
      g_opac[g] = a[OP];
      g_depths[g] = a[DEPTH];
      for (int ch = 0; ch < C; ++ch) g_colors[size_t(g) * C + ch] = a[COLOR0 + ch];
    }
  }
}

#define KGS_INSTANTIATE(S)                                                                     \
  template void raster_forward<S>(const RasterShape&, const TileLists&, int64_t, const S*,     \
                                  const S*,                                                    \
                                  const S*, const S*, const S*, const int32_t*, const S*, S*,  \
                                  S*, S*, S*, S*, int32_t*);                                   \
  template void raster_backward<S>(const RasterShape&, const TileLists&, int64_t, const S*,    \
                                   const S*, const S*, const int32_t*, const S*, const S*,     \
                                   const S*, S*, S*, S*, S*, S*, S*, bool);
KGS_INSTANTIATE(float)
KGS_INSTANTIATE(double)
#undef KGS_INSTANTIATE

}  // namespace kgs
