// Tile rasteriser, forward and hand-written backward.
//
// Work is split over 16x16 tiles (OpenMP, dynamic schedule: tiles differ a lot in load).
// Inside a tile the loop is Gaussian-major: each Gaussian in depth order updates only the
// rows of its bounding box. A tile row is exactly one 16-lane vector (simd.h: an AVX-512
// register with predicate masks, two AVX2 registers, or vector extensions otherwise), so the
// per-pixel state of a tile is 16 vectors and every update is straight-line SIMD code. On
// AVX2 a pair whose box lies in one half of the tile runs on that register only.
//
// The forward first writes a compact record per (tile, Gaussian) pair in tile-list order
// (screen-space parameters, its box clipped to the tile, its colour), which the backward
// reuses: the kernels stream memory forward instead of missing the cache on a scene-wide
// array per pair (those misses were ~15 % of the forward). The forward kernel then cuts
// each record's box to the rows and lanes where the pair contributed, so the backward
// never evaluates a row in which every lane failed the alpha test.
//
// The backward walks the same lists back to front, recovering each pixel's transmittance
// by division (alpha <= ALPHA_MAX keeps 1 - alpha >= 0.01), and writes one gradient slot
// per pair, id-major, so each Gaussian's slots are contiguous and summed in a fixed
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
// (mx, my, ca, cb, cc, opacity, depth, the box clipped to the tile as four bytes (after the
// forward kernel: cut to where the pair contributed), the pair's slot in id-major order
// as an int32), then the colour channels.
template <typename S>
struct PairRec {
  S mx, my, ca, cb, cc, op, z;
  int x0, x1, y0, y1;  // tile-relative, ends exclusive
  int32_t slot_index;
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
  std::memcpy(&p.slot_index, rec + 8, 4);
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
    for (int64_t j = 0; j < L.n_pairs; ++j) slot_of[L.id_pairs[j]] = int32_t(j);
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

// What one Gaussian contributes along a tile row (or the part of it that the lane set X
// covers, starting at lane `lane0`), with everything that does not depend on the row
// hoisted out. The kernels evaluate the Gaussian as 2^(log2(e) power) (simd.h's exp2 is the
// shorter dependency chain), so the hoisted terms carry log2(e):
//   log2(e) power(dy) = p0 + dy * p1 - half_cc dy^2 per lane.
template <typename X, typename S>
struct GaussLanes {
  using V = typename X::V;
  using M = typename X::M;
  V dx, p0, p1;
  M in_box;  // lanes inside the Gaussian's bounding box
  S half_cc, op;
  GaussLanes(V px, const PairRec<S>& p, int lane0) {
    constexpr double LOG2E = 1.4426950408889634;
    dx = px - X::set1(p.mx);
    p0 = X::set1(S(-0.5 * LOG2E) * p.ca) * dx * dx;
    p1 = X::set1(-S(LOG2E) * p.cb) * dx;
    in_box = X::lanes_in(p.x0 - lane0, p.x1 - lane0);
    half_cc = S(0.5 * LOG2E) * p.cc;
    op = p.op;
  }
};

// The per-row evaluation both passes share: lanes where the Gaussian takes part (before
// the pixel's own cut-off, which the caller adds), its Gaussian value, raw and clamped alpha.
template <typename X>
struct RowEval {
  typename X::V G, a_raw, alpha;
  typename X::M ok;
};

template <typename X, typename S>
inline RowEval<X> eval_row(const GaussLanes<X, S>& gl, S dy) {
  RowEval<X> e;
  // (The product and the difference are independent: two steps deep, not three.)
  const auto power = X::set1(dy) * gl.p1 + (gl.p0 - X::set1(gl.half_cc * dy * dy));
  e.G = X::exp2(power);
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

// Which lanes of a tile row a pair's loop runs on. Kernels keep their per-pixel state as
// whole-row vectors; a part maps one of them to the vector its lane set works on.
struct WholeRow {
  template <typename T>
  T& operator()(T& v) const { return v; }
};
struct HalfRow {  // lanes 8h .. 8h + 7 (AVX2: one register of the two)
  int h;
  template <typename T>
  auto& operator()(T& v) const { return v.h[h]; }
};

// Calls run(X-or-half lane set, part, lane0) for a pair: on half a row when the lane set has
// half rows and the pair's box lies inside one half (at ~30 Gaussians per pixel a footprint
// is ~7 px across, so most boxes do: half the vector work for them), else on the whole row.
template <typename X, typename S, typename Run>
inline auto on_pair_lanes(const PairRec<S>& p, Run&& run) {
  if constexpr (has_half_rows<X>::value) {
    constexpr int HALF = LANES / 2;
    if (p.x1 <= HALF) return run(typename X::Half{}, HalfRow{0}, 0);
    if (p.x0 >= HALF) return run(typename X::Half{}, HalfRow{1}, HALF);
  }
  return run(X{}, WholeRow{}, 0);
}

// Overwrites a pair record's box with the span of the rows and lanes in which the pair
// contributed to some pixel (bit r of `rows`: row r; bit i of `lanes`: lane i), or with an
// empty box when it contributed nowhere.
template <typename S>
inline void write_used_box(S* rec, unsigned rows, unsigned lanes) {
  uint8_t clip[4];
  std::memcpy(clip, rec + 7, 4);
  if (rows == 0 || lanes == 0) {
    clip[3] = clip[2];  // no row
  } else {
    clip[0] = uint8_t(__builtin_ctz(lanes));
    clip[1] = uint8_t(32 - __builtin_clz(lanes));
    clip[2] = uint8_t(__builtin_ctz(rows));
    clip[3] = uint8_t(32 - __builtin_clz(rows));
  }
  std::memcpy(rec + 7, clip, 4);
}

// A pixel's expected depth: its alpha-weighted depth sum over its alpha, 0 where alpha <= 1e-6
// (as the PyTorch reference computes it; the backward of the division is in cpu_backend.py).
template <typename S>
inline typename Simd<S>::V expected_depth(typename Simd<S>::V depth_sum, typename Simd<S>::V alpha) {
  using X = Simd<S>;
  const auto eps = X::set1(S(1e-6));
  return X::keep(X::lt(eps, alpha), X::div(depth_sum, X::max(alpha, eps)));
}

// NC: the channel count when known at compile time (3, as in training), 0 otherwise.
// Besides the pixels, the forward cuts each pair's record to the rows and lanes where it
// contributed (write_used_box; pairs behind a finished tile to nothing): the backward then
// skips the rows where every lane failed the alpha test (23 % of the box's rows on the
// benchmark scene: python -m kgs_app.bench.occupancy) without evaluating them. A lane that
// did not contribute adds exact zeros in the backward, so the gradients are unchanged.
template <typename S, int NC>
void forward_tile(const RasterShape& s, const TileGeom& t, S* records,
                  const S* background, S* image, S* alpha_out, S* depth_out,
                  S* t_final, int32_t* n_contrib, std::vector<typename Simd<S>::V>& acc) {
  using X = Simd<S>;
  using V = typename X::V;
  using M = typename X::M;
  using Idx = typename X::Idx;
  const int C = NC > 0 ? NC : s.channels;
  V px = lane_px<S>(t);
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
  int k = t.begin;
  for (; k < t.end && n_done < TILE_PIXELS; ++k) {
    S* rec = records + size_t(k) * (RECORD_HEAD + C);
    const PairRec<S> p = read_pair(rec);
    const S* col = p.col;
    unsigned used_rows = 0, used_lanes = 0;  // bit r: row r, bit i: lane i
    // Whether a pixel stopped (its transmittance fell below T_MIN) at this pair.
    const bool stopped = on_pair_lanes<X>(p, [&](auto lanes, auto part, int lane0) __attribute__((always_inline)) {
      using Y = decltype(lanes);
      using YM = typename Y::M;
      using YV = typename Y::V;
      const auto list_pos = Y::iset1(k - t.begin + 1);
      const GaussLanes<Y, S> gl(part(px), p, lane0);
      const YV gz = Y::set1(p.z);
      YM any_term = Y::none(), any_use = Y::none();
      for (int r = p.y0; r < p.y1; ++r) {
        YM& done_r = part(done[r]);
        YV& T_r = part(T[r]);
        if (!Y::any(Y::mandnot(gl.in_box, done_r))) continue;  // row finished: skip the exp
        const RowEval<Y> e = eval_row(gl, S(t.py0 + r) + S(0.5) - p.my);
        const YM in = Y::mandnot(e.ok, done_r);
        const YV test_t = T_r * (Y::set1(S(1)) - e.alpha);
        const YM term = Y::mand(in, Y::lt(test_t, Y::set1(S(T_MIN))));
        const YM use = Y::mandnot(in, term);
        used_rows |= unsigned(Y::any(use)) << r;  // branch-free: the tests do not predict
        any_use = Y::mor(any_use, use);
        const YV w = Y::keep(use, e.alpha * T_r);
        T_r = Y::select(use, test_t, T_r);
        part(last[r]) = Y::iselect(use, list_pos, part(last[r]));
        done_r = Y::mor(done_r, term);
        any_term = Y::mor(any_term, term);
        part(dacc[r]) += w * gz;
        for (int ch = 0; ch < C; ++ch) part(acc[size_t(ch) * TILE + r]) += w * Y::set1(col[ch]);
      }
      used_lanes = Y::bits(any_use) << lane0;
      return Y::any(any_term);
    });
    write_used_box(rec, used_rows, used_lanes);
    if (stopped) {
      n_done = 0;
      for (int r = 0; r < TILE; ++r) n_done += X::count(done[r]);
    }
  }
  for (; k < t.end; ++k) write_used_box(records + size_t(k) * (RECORD_HEAD + C), 0u, 0u);
  S Tl[TILE], dl[TILE], cl[TILE];
  int32_t ll[TILE];
  for (int r = 0; r < t.h; ++r) {
    X::store(Tl, T[r]);
    const size_t row = size_t(t.py0 + r) * s.width + t.px0;
    if (t.w == TILE) {  // straight vector stores (the staging cost ~10 % at 256²)
      const V a = X::set1(S(1)) - T[r];
      X::store(alpha_out + row, a);
      X::store(depth_out + row, expected_depth<S>(dacc[r], a));
      X::store(t_final + row, T[r]);
      X::istore(n_contrib + row, last[r]);
    } else {
      X::istore(ll, last[r]);
      X::store(dl, expected_depth<S>(dacc[r], X::set1(S(1)) - T[r]));
      for (int i = 0; i < t.w; ++i) {
        alpha_out[row + i] = S(1) - Tl[i];
        depth_out[row + i] = dl[i];
        t_final[row + i] = Tl[i];
        n_contrib[row + i] = ll[i];
      }
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
// NC: the channel count when known at compile time (3, the training render), 0 otherwise:
// with it the per-channel loops unroll and the pair's colour gradients stay in registers.
template <typename S, bool ABS, int NC>
void backward_tile(const RasterShape& s, const TileGeom& t, const S* records,
                   const S* background, const S* t_final,
                   const int32_t* n_contrib, const S* g_image, const S* g_alpha,
                   const S* g_depth, S* slots, std::vector<typename Simd<S>::V>& scratch) {
  using X = Simd<S>;
  using V = typename X::V;
  using Idx = typename X::Idx;
  const int C = NC > 0 ? NC : s.channels;
  const int stride = slot_stride(C);
  V px = lane_px<S>(t);
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
      const size_t row = size_t(t.py0 + r) * s.width + t.px0;
      const bool whole_row = r < t.h && t.w == TILE;
      if (whole_row) {  // straight vector loads (the staging below cost ~10 % at 256²)
        Tcur[r] = X::load(t_final + row);
        gAT[r] = g_alpha ? X::load(g_alpha + row) * Tcur[r] : X::zero();
        gD[r] = g_depth ? X::load(g_depth + row) : X::zero();
        last[r] = X::iload(n_contrib + row);
      } else {  // edge tiles: outside pixels read as finished, with no gradient
        std::fill(tf, tf + TILE, S(1));
        std::fill(ga, ga + TILE, S(0));
        std::fill(gd, gd + TILE, S(0));
        std::fill(nc, nc + TILE, 0);
        if (r < t.h) {
          for (int i = 0; i < t.w; ++i) {
            tf[i] = t_final[row + i];
            ga[i] = g_alpha ? g_alpha[row + i] : S(0);
            gd[i] = g_depth ? g_depth[row + i] : S(0);
            nc[i] = n_contrib[row + i];
          }
        }
        Tcur[r] = X::load(tf);
        gAT[r] = X::load(ga) * Tcur[r];
        gD[r] = X::load(gd);
        last[r] = X::iload(nc);
      }
      const V Tfin = Tcur[r];
      Bg[r] = X::zero();
      for (int ch = 0; ch < C; ++ch) {
        if (whole_row) {
          for (int i = 0; i < TILE; ++i) gc[i] = g_image[(row + i) * C + ch];
        } else {
          std::fill(gc, gc + TILE, S(0));
          if (r < t.h)
            for (int i = 0; i < t.w; ++i) gc[i] = g_image[(row + i) * C + ch];
        }
        gC[size_t(ch) * TILE + r] = X::load(gc);
        Bg[r] += gC[size_t(ch) * TILE + r] * Tfin * X::set1(background[ch]);
      }
    }
  }
  for (int k = t.end - 1; k >= t.begin; --k) {
    const PairRec<S> p = read_pair(records + size_t(k) * (RECORD_HEAD + C));
    const S* col = p.col;
    S* slot = slots + size_t(p.slot_index) * stride;  // id-major: summed sequentially
    if (p.y0 >= p.y1) {  // contributed to no pixel in the forward
      std::fill(slot, slot + COLOR0 + C, S(0));
      continue;
    }
    on_pair_lanes<X>(p, [&](auto lanes, auto part, int lane0) __attribute__((always_inline)) {
      using Y = decltype(lanes);
      using YM = typename Y::M;
      using YV = typename Y::V;
      const auto list_pos = Y::iset1(k - t.begin);  // contributes where list_pos < last
      // Moments of gp = dL/dpower over the pixels: sum gp dx, gp dy, gp dx^2, gp dx dy, gp dy^2.
      YV m_x = Y::zero(), m_y = m_x, m_xx = m_x, m_xy = m_x, m_yy = m_x, a_op = m_x;
      YV a_d = m_x, a_amx = m_x, a_amy = m_x;
      // The pair's colour gradient per lane: locals when NC is known, else the scratch.
      YV col_local[NC > 0 ? NC : 1];
      auto col_acc = [&](int ch) -> YV& {
        if constexpr (NC > 0) return col_local[ch];
        else return part(s_col[ch]);
      };
      for (int ch = 0; ch < C; ++ch) col_acc(ch) = Y::zero();
      const GaussLanes<Y, S> gl(part(px), p, lane0);
      const YV& dx = gl.dx;
      const YV gz = Y::set1(p.z), ca = Y::set1(p.ca), cb = Y::set1(p.cb), cc = Y::set1(p.cc);
      for (int r = p.y0; r < p.y1; ++r) {
        const auto& last_r = part(last[r]);
        // Pixels that stopped before this Gaussian: skip the row before paying for the exp.
        if (!Y::any(Y::mand(gl.in_box, Y::ilt(list_pos, last_r)))) continue;
        const S dy_s = S(t.py0 + r) + S(0.5) - p.my;
        const RowEval<Y> e = eval_row(gl, dy_s);
        const YM use = Y::mand(e.ok, Y::ilt(list_pos, last_r));
        if (!Y::any(use)) continue;
        YV& Tcur_r = part(Tcur[r]);
        YV& Bg_r = part(Bg[r]);
        const YV gD_r = part(gD[r]);
        const YV dy = Y::set1(dy_s);
        const YV inv = Y::rcp(Y::set1(S(1)) - e.alpha);
        const YV Ti = Tcur_r * inv;  // transmittance in front of this Gaussian
        const YV w = Y::keep(use, e.alpha * Ti);
        YV gcc = gD_r * gz;
        for (int ch = 0; ch < C; ++ch) {
          const YV gc = part(gC[size_t(ch) * TILE + r]);
          gcc += gc * Y::set1(col[ch]);
          col_acc(ch) += w * gc;
        }
        const YV dal = inv * (part(gAT[r]) - Bg_r) + Ti * gcc;
        Bg_r += w * gcc;
        a_d += w * gD_r;
        Tcur_r = Y::select(use, Ti, Tcur_r);
        // Through alpha = min(ALPHA_MAX, o * exp(power)) to the 2D Gaussian.
        // Masked products: lanes that do not take part contribute exact zeros, whatever
        // their (unused) values are.
        const YM live = Y::mand(use, Y::lt(e.a_raw, Y::set1(S(ALPHA_MAX))));
        const YV gp = Y::keep(live, dal * e.a_raw);
        a_op += Y::keep(live, dal * e.G);
        const YV gpdx = gp * dx;
        m_x += gpdx;
        m_y += gp * dy;
        m_xx += gpdx * dx;
        m_xy += gpdx * dy;
        m_yy += gp * Y::set1(dy_s * dy_s);
        if constexpr (ABS) {
          a_amx += Y::abs(gp * (ca * dx + cb * dy));
          a_amy += Y::abs(gp * (cb * dx + cc * dy));
        }
      }
      const S sx = Y::hsum(m_x), sy = Y::hsum(m_y);
      slot[MX] = p.ca * sx + p.cb * sy;
      slot[MY] = p.cb * sx + p.cc * sy;
      slot[CA] = S(-0.5) * Y::hsum(m_xx);
      slot[CB] = -Y::hsum(m_xy);
      slot[CC] = S(-0.5) * Y::hsum(m_yy);
      slot[OP] = Y::hsum(a_op);
      slot[DEPTH] = Y::hsum(a_d);
      slot[ABS_MX] = ABS ? Y::hsum(a_amx) : S(0);
      slot[ABS_MY] = ABS ? Y::hsum(a_amy) : S(0);
      for (int ch = 0; ch < C; ++ch) slot[COLOR0 + ch] = Y::hsum(col_acc(ch));
    });
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
      const TileGeom t = tile_geom(s, L.tile_offsets, tile);
      if (s.channels == 3)
        forward_tile<S, 3>(s, t, records, background, image, alpha, depth_acc, t_final, n_contrib, acc);
      else
        forward_tile<S, 0>(s, t, records, background, image, alpha, depth_acc, t_final, n_contrib, acc);
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
        backward_tile<S, true, 0>(s, t, records, background, t_final, n_contrib, g_image, g_alpha,
                                  g_depth, slots.data(), scratch);
      else if (C == 3)
        backward_tile<S, false, 3>(s, t, records, background, t_final, n_contrib, g_image, g_alpha,
                                   g_depth, slots.data(), scratch);
      else
        backward_tile<S, false, 0>(s, t, records, background, t_final, n_contrib, g_image, g_alpha,
                                   g_depth, slots.data(), scratch);
    }
  }
  // Each Gaussian's slots are contiguous (id-major) and summed in list order straight into
  // its outputs: one sequential pass over the slots and the outputs. (A rank-major layout
  // needed a per-rank staging buffer and a gather by id: 1.1 ms at 50k / 256².)
  using X = Simd<S>;
  const int n_vec = stride / LANES;
  const S* slot_base = slots.data();
#pragma omp parallel
  {
    std::vector<typename X::V> acc(n_vec);
    std::vector<S> line(static_cast<size_t>(stride));  // one Gaussian's sums
    S* a = line.data();
#pragma omp for schedule(static)
    for (int64_t g = 0; g < n; ++g) {
      // An invisible Gaussian has no slots: its gradients are zero.
      for (auto& v : acc) v = X::zero();
      for (int32_t j = L.id_start[g]; j < L.id_start[g + 1]; ++j) {
        const S* slot = slot_base + size_t(j) * stride;
        for (int q = 0; q < n_vec; ++q) acc[q] += X::load(slot + q * LANES);
      }
      for (int q = 0; q < n_vec; ++q) X::store(a + q * LANES, acc[q]);
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
