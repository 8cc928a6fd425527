// Tile rasteriser, forward and hand-written backward.
//
// Work is split over 16x16 tiles (OpenMP, dynamic schedule: tiles differ a lot in load).
// Inside a tile the loop is Gaussian-major: each Gaussian in depth order updates only the
// rows of its bounding box. A tile row is exactly one 16-lane vector (simd.h: an AVX-512
// register with predicate masks, two AVX2 registers, or vector extensions otherwise), so the
// per-pixel state of a tile is 16 vectors and every update is straight-line SIMD code. On
// AVX2 a pair whose box lies in one half of the tile runs on that register only.
//
// Each Gaussian's inputs are first packed into one 64-byte line (screen-space parameters,
// box, colour), so that a pair costs one cache miss, not one per input array, and the
// forward kernel prefetches the lines of the pairs a few steps ahead, where the misses hide
// behind the arithmetic. As it finishes a pair, the forward writes the pair's record for
// the backward (the line, with the box cut to the rows and lanes where the pair
// contributed, and its gradient slot), so the backward streams memory forward and never
// evaluates a row in which every lane failed the alpha test. (Copying the lines
// into records in a separate pass before the forward cost ~1 ms at 50k / 256²; reading the
// lines in the backward too cost it ~9 %.)
//
// The backward walks the same lists back to front, recovering each pixel's transmittance
// by division (alpha <= ALPHA_MAX keeps 1 - alpha >= 0.01), and writes one gradient slot
// per pair, id-major, so each Gaussian's slots are contiguous and summed in a fixed
// order: results do not depend on the thread count.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <new>
#include <type_traits>
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
static_assert(LINE_HEAD == 10 && RECORD_HEAD == 9, "read_pair, pack_gaussians and write_record spell out the heads");

// One (tile, Gaussian) pair as the kernels see it. The forward reads it from the Gaussian's
// packed line (mx, my, ca, cb, cc, opacity, depth, its box in pixels as four int16 (x0, y0 |
// x1, y1), the number of its first pair (id_start) as an int32, then the colour channels)
// and the box on this tile; it then writes the pair's record for the backward: the same
// seven parameters, the box cut to where the pair drew, the pair's gradient slot, the
// colour channels (write_record).
template <typename S>
struct PairRec {
  S mx, my, ca, cb, cc, op, z;
  int x0, x1, y0, y1;  // tile-relative, ends exclusive
  const S* col;
};

// A pair's box on a tile, as four bytes x0, x1, y0, y1 (tile-relative, ends exclusive; empty
// when y0 == y1).
inline uint32_t pack_box(int x0, int x1, int y0, int y1) {
  return uint32_t(x0) | uint32_t(x1) << 8 | uint32_t(y0) << 16 | uint32_t(y1) << 24;
}

// From a line (head = LINE_HEAD) or a record (head = RECORD_HEAD) and the pair's box.
template <typename S>
inline PairRec<S> read_pair(const S* src, uint32_t box, int head) {
  PairRec<S> p;
  p.mx = src[0]; p.my = src[1]; p.ca = src[2]; p.cb = src[3]; p.cc = src[4];
  p.op = src[5]; p.z = src[6];
  p.x0 = box & 0xff; p.x1 = box >> 8 & 0xff; p.y0 = box >> 16 & 0xff; p.y1 = box >> 24;
  p.col = src + head;
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

// Packs each Gaussian's inputs into one line of packed_stride(C) scalars, in id order.
template <typename S>
void pack_gaussians(int64_t n, int C, const S* means2d, const S* conics, const S* opac,
                    const S* colors, const S* depths, const int32_t* bbox,
                    const int32_t* id_start, S* packed) {
  const int P = packed_stride<S>(C);
#pragma omp parallel for schedule(static)
  for (int64_t g = 0; g < n; ++g) {
    S* d = packed + size_t(g) * P;
    d[0] = means2d[2 * g]; d[1] = means2d[2 * g + 1];
    d[2] = conics[3 * g]; d[3] = conics[3 * g + 1]; d[4] = conics[3 * g + 2];
    d[5] = opac[g]; d[6] = depths[g];
    int16_t box[4];
    for (int q = 0; q < 4; ++q) box[q] = int16_t(std::min(bbox[4 * g + q], 32767));
    std::memcpy(d + 7, box, 4);      // x0, y0
    std::memcpy(d + 8, box + 2, 4);  // x1, y1
    std::memcpy(d + 9, id_start + g, 4);
    for (int ch = 0; ch < C; ++ch) d[LINE_HEAD + ch] = colors[size_t(g) * C + ch];
    for (int q = LINE_HEAD + C; q < P; ++q) d[q] = S(0);
  }
}

// The pair lists as the forward walks them: the k-th pair's packed line, and the line a
// few pairs ahead brought toward the cache.
template <typename S>
struct PairLines {
  const S* packed;
  int stride;
  const int32_t* order;
  const int32_t* tile_ranks;
  static constexpr int AHEAD = 6;
  const S* line(int k) const { return packed + size_t(order[tile_ranks[k]]) * stride; }
  void prefetch(int k) const { __builtin_prefetch(line(k)); }
};

// A Gaussian's pixel box x0, y0, x1, y1 from its packed line.
template <typename S>
inline std::array<int16_t, 4> line_box(const S* line) {
  std::array<int16_t, 4> box;
  std::memcpy(box.data(), line + 7, 4);
  std::memcpy(box.data() + 2, line + 8, 4);
  return box;
}

// A Gaussian's pixel box clipped to a tile.
template <typename S>
inline uint32_t box_on_tile(const S* line, const TileGeom& t) {
  const auto box = line_box(line);
  return pack_box(std::clamp(box[0] - t.px0, 0, TILE), std::clamp(box[2] - t.px0, 0, TILE),
                  std::clamp(box[1] - t.py0, 0, TILE), std::clamp(box[3] - t.py0, 0, TILE));
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

// What a Gaussian's rows differ by: dy (pixel-centre y minus the mean's) and the quadratic
// term log2(e) cc dy^2 / 2, for tile row r, broadcast over the lane set Y. Formed per row in
// scalar code they put ~15 cycles of scalar steps at the head of every row's chain (dy ->
// power -> exp2 -> alpha -> the pixel update). The AVX-512 version below forms them for all
// 16 rows at once per pair and picks row r with one permute: forward -4 to -7 %
// (shortening the chain's tail, e.g. T - alpha T as one multiply-add, measured level). Both
// round exactly as the scalar forms do.
template <typename Y, typename S>
struct GaussRows {
  int py0;
  S my, half_cc;
  GaussRows(const TileGeom& t, const PairRec<S>& p, S half_cc_) : py0(t.py0), my(p.my), half_cc(half_cc_) {}
  S dy_s(int r) const { return S(py0 + r) + S(0.5) - my; }
  typename Y::V dy(int r) const { return Y::set1(dy_s(r)); }
  typename Y::V dy2(int r) const { const S d = dy_s(r); return Y::set1(d * d); }
  typename Y::V quad(int r) const { const S d = dy_s(r); return Y::set1(half_cc * d * d); }
};

#if defined(__AVX512F__)
template <>
struct GaussRows<Simd<float>, float> {
  __m512 dy_v, quad_v;  // lane r: row r's dy / quadratic term
  GaussRows(const TileGeom& t, const PairRec<float>& p, float half_cc) {
    const __m512i row = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    dy_v = _mm512_cvtepi32_ps(_mm512_add_epi32(row, _mm512_set1_epi32(t.py0))) + _mm512_set1_ps(0.5f) -
           _mm512_set1_ps(p.my);
    quad_v = _mm512_set1_ps(half_cc) * dy_v * dy_v;
  }
  static __m512 pick(__m512 v, int r) { return _mm512_permutexvar_ps(_mm512_set1_epi32(r), v); }
  __m512 dy(int r) const { return pick(dy_v, r); }
  __m512 dy2(int r) const { const __m512 d = dy(r); return d * d; }
  __m512 quad(int r) const { return pick(quad_v, r); }
  // Rows r and r + 1 in lanes 0-7 and 8-15 (TwoRows; index 16 wraps to row 0, in lanes
  // that a lone last row's masks leave out).
  static __m512 pick2(__m512 v, int r) {
    return _mm512_permutexvar_ps(_mm512_mask_set1_epi32(_mm512_set1_epi32(r), 0xFF00, r + 1), v);
  }
};
#endif

// The Gaussian at the lanes in_box, given each lane's dy and quadratic term (eval_row's
// broadcast row, or TwoRows' two rows).
template <typename X, typename S>
inline RowEval<X> eval_lanes(const GaussLanes<X, S>& gl, typename X::V dy, typename X::V quad,
                             typename X::M in_box) {
  RowEval<X> e;
  // (The product and the difference are independent: two steps deep, not three.)
  const auto power = dy * gl.p1 + (gl.p0 - quad);
  e.G = X::exp2(power);
  e.a_raw = X::set1(gl.op) * e.G;
  e.alpha = X::min(e.a_raw, X::set1(S(ALPHA_MAX)));
  e.ok = X::mand(in_box, X::mand(X::le(power, X::zero()), X::ge(e.alpha, X::set1(S(ALPHA_MIN)))));
  return e;
}

// The Gaussian on tile row r.
template <typename X, typename S>
inline RowEval<X> eval_row(const GaussLanes<X, S>& gl, const GaussRows<X, S>& rows, int r) {
  return eval_lanes(gl, rows.dy(r), rows.quad(r), gl.in_box);
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

// The span of the rows and lanes in which a pair contributed to some pixel (bit r of
// `rows`: row r; bit i of `lanes`: lane i) as a packed box; empty when it contributed
// nowhere.
inline uint32_t used_box(unsigned rows, unsigned lanes) {
  if (rows == 0 || lanes == 0) return 0;
  return pack_box(__builtin_ctz(lanes), 32 - __builtin_clz(lanes), __builtin_ctz(rows),
                  32 - __builtin_clz(rows));
}

// The gradient slot of a Gaussian's pair on a tile: the number of its first pair plus the
// tile's row-major place in the Gaussian's tile rectangle (the order binning numbers them in).
template <typename S>
inline int32_t pair_slot(const S* line, const TileGeom& t) {
  const auto box = line_box(line);
  int32_t first;
  std::memcpy(&first, line + 9, 4);
  const TileRect r = bin_tile_rect(box[0], box[1], box[2], box[3]);
  return first + (t.py0 / TILE - r.y0) * (r.x1 - r.x0) + (t.px0 / TILE - r.x0);
}

// A pair's record for the backward: the line's parameters and colour, its used box and its
// gradient slot. Written by the forward while the line is in L1, so the backward streams
// the records instead of missing the cache on a line per pair (reading the lines there
// cost the backward ~9 %).
// (A pair behind a finished tile gets only the head: an empty box and the slot to zero.)
template <typename S>
inline void write_record_head(S* rec, uint32_t box, int32_t slot) {
  std::memcpy(rec + 7, &box, 4);
  std::memcpy(rec + 8, &slot, 4);
}

template <typename S>
inline void write_record(S* rec, const S* line, uint32_t box, int32_t slot, int C) {
  for (int q = 0; q < 7; ++q) rec[q] = line[q];
  write_record_head(rec, box, slot);
  for (int ch = 0; ch < C; ++ch) rec[RECORD_HEAD + ch] = line[LINE_HEAD + ch];
}

// The record's box and slot, as write_record_head left them.
template <typename S>
inline void read_record_head(const S* rec, uint32_t& box, int32_t& slot) {
  std::memcpy(&box, rec + 7, 4);
  std::memcpy(&slot, rec + 8, 4);
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
// The tile and the pair lists come by value: through references the compiler reloaded
// their fields for every pair, since the record and pixel stores might alias them (the
// per-tile part of GaussRows then stays out of the pair loop: forward -3 %).
// Besides the pixels, the forward writes each pair's box cut to the rows and lanes where it
// contributed (used_box; pairs behind a finished tile: empty): the backward then
// skips the rows where every lane failed the alpha test (23 % of the box's rows on the
// benchmark scene: python -m kgs_app.bench.occupancy) without evaluating them. A lane that
// did not contribute adds exact zeros in the backward, so the gradients are unchanged.
template <typename S, int NC>
void forward_tile(const RasterShape& s, const TileGeom t, const PairLines<S> lines,
                  S* records, const S* background, S* image, S* alpha_out, S* depth_out,
                  S* t_final, int32_t* n_contrib, std::vector<typename Simd<S>::V>& acc_heap) {
  using X = Simd<S>;
  using V = typename X::V;
  using M = typename X::M;
  using Idx = typename X::Idx;
  const int C = NC > 0 ? NC : s.channels;
  V px = lane_px<S>(t);
  V T[TILE], dacc[TILE];
  Idx last[TILE];
  M done[TILE];
  // The colour sums: on the stack when C is known (through a heap pointer they cost a
  // reload of that pointer on every row, which the compiler cannot tell from the stores:
  // forward -2 to -9 %), else in the caller's buffer.
  V acc_local[NC > 0 ? NC * TILE : 1];
  V* acc = acc_local;
  if constexpr (NC == 0) {
    acc_heap.resize(size_t(C) * TILE);
    acc = acc_heap.data();
  }
  std::fill(acc, acc + size_t(C) * TILE, X::zero());
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
    if (k + lines.AHEAD < t.end) lines.prefetch(k + lines.AHEAD);
    const S* line = lines.line(k);
    const PairRec<S> p = read_pair(line, box_on_tile(line, t), LINE_HEAD);
    const S* col = p.col;
    unsigned used_rows = 0, used_lanes = 0;  // bit r: row r, bit i: lane i
    // Whether a pixel stopped (its transmittance fell below T_MIN) at this pair.
    const bool stopped = on_pair_lanes<X>(p, [&](auto lanes, auto part, int lane0) __attribute__((always_inline)) {
      using Y = decltype(lanes);
      using YM = typename Y::M;
      using YV = typename Y::V;
      const auto list_pos = Y::iset1(k - t.begin + 1);
      const GaussLanes<Y, S> gl(part(px), p, lane0);
      const GaussRows<Y, S> rows(t, p, gl.half_cc);
      const YV gz = Y::set1(p.z);
      YM any_term = Y::none(), any_use = Y::none();
      for (int r = p.y0; r < p.y1; ++r) {
        YM& done_r = part(done[r]);
        YV& T_r = part(T[r]);
        if (!Y::any(Y::mandnot(gl.in_box, done_r))) continue;  // row finished: skip the exp
        const RowEval<Y> e = eval_row(gl, rows, r);
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
    write_record(records + size_t(k) * (RECORD_HEAD + C), line, used_box(used_rows, used_lanes),
                 pair_slot(line, t), C);
    if (stopped) {
      n_done = 0;
      for (int r = 0; r < TILE; ++r) n_done += X::count(done[r]);
    }
  }
  for (; k < t.end; ++k) {  // behind a finished tile: an empty box and the slot to zero
    if (k + lines.AHEAD < t.end) lines.prefetch(k + lines.AHEAD);
    write_record_head(records + size_t(k) * (RECORD_HEAD + C), 0u, pair_slot(lines.line(k), t));
  }
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

// A pair's gradient sums over its pixels, per lane: the moments of gp = dL/dpower (sum gp
// dx, gp dy, gp dx^2, gp dx dy, gp dy^2), the opacity and depth terms, and (absgrad) the
// |dL/dmean2d| sums; both backward paths add to them and write them to the pair's slot.
template <typename Y, typename S>
struct PairSums {
  using V = typename Y::V;
  V m_x, m_y, m_xx, m_xy, m_yy, a_op, a_d, a_amx, a_amy;
  PairSums() { m_x = m_y = m_xx = m_xy = m_yy = a_op = a_d = a_amx = a_amy = Y::zero(); }
  // Through alpha = min(ALPHA_MAX, o * exp(power)) to the 2D Gaussian at the lanes `use`
  // (dy2 = dy^2, rounded as the caller forms it). Masked products: lanes that do not take
  // part contribute exact zeros, whatever their (unused) values are. Returns gp.
  V add(const RowEval<Y>& e, typename Y::M use, V dal, V dx, V dy, V dy2) {
    const auto live = Y::mand(use, Y::lt(e.a_raw, Y::set1(S(ALPHA_MAX))));
    const V gp = Y::keep(live, dal * e.a_raw);
    a_op += Y::keep(live, dal * e.G);
    const V gpdx = gp * dx;
    m_x += gpdx;
    m_y += gp * dy;
    m_xx += gpdx * dx;
    m_xy += gpdx * dy;
    m_yy += gp * dy2;
    return gp;
  }
  // Everything but the colour channels, which the caller sums.
  void write(S* slot, const PairRec<S>& p, bool abs) const {
    const S sx = Y::hsum(m_x), sy = Y::hsum(m_y);
    slot[MX] = p.ca * sx + p.cb * sy;
    slot[MY] = p.cb * sx + p.cc * sy;
    slot[CA] = S(-0.5) * Y::hsum(m_xx);
    slot[CB] = -Y::hsum(m_xy);
    slot[CC] = S(-0.5) * Y::hsum(m_yy);
    slot[OP] = Y::hsum(a_op);
    slot[DEPTH] = Y::hsum(a_d);
    slot[ABS_MX] = abs ? Y::hsum(a_amx) : S(0);
    slot[ABS_MY] = abs ? Y::hsum(a_amy) : S(0);
  }
};

#if defined(__AVX512F__)
// Two rows per 16-lane vector in the backward, for a pair whose used lanes span at most 8
// (at ~30 Gaussians per pixel a footprint draws ~4 of a row's 16 lanes): lanes 0-7 hold
// columns a .. a + 7 of row r, lanes 8-15 the same columns of row r + 1. The tile's
// per-pixel state stays in whole-row vectors; a pair gathers the values it reads with one
// two-source permute each and merges the two it changes back with masked permutes. Every
// lane computes exactly what the one-row path computes for its pixel (same operations,
// same rounding: the alpha test agrees with the forward's), so only the pair's lane sums
// add in another order. (The forward was tried the same way and lost ~15 %: all of its
// seven per-pixel values change per pair, and merging masks costs round trips through
// integer registers.)
struct TwoRows {
  using X = Simd<float>;
  int a;                      // first column of the window
  __m512i gather;             // lane j <- column of row r (index < 16) or row r + 1 (+ 16)
  __m512i back0, back1;       // row r's / row r + 1's column c <- lane c - a / c - a + 8
  __mmask16 window;           // the window's columns in a row vector
  __mmask16 in_cols;          // lanes whose column lies in the pair's box
  __m512 px;                  // pixel-centre x per lane
  TwoRows(const TileGeom& t, const PairRec<float>& p) {
    a = std::min(p.x0, 8);
    const __m512i lane = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    const __m512i col = _mm512_add_epi32(_mm512_set1_epi32(a), _mm512_and_si512(lane, _mm512_set1_epi32(7)));
    gather = _mm512_add_epi32(col, _mm512_slli_epi32(_mm512_srli_epi32(lane, 3), 4));
    back0 = _mm512_sub_epi32(lane, _mm512_set1_epi32(a));
    back1 = _mm512_add_epi32(back0, _mm512_set1_epi32(8));
    window = __mmask16(0xFFu << a);
    in_cols = __mmask16(_mm512_cmpge_epi32_mask(col, _mm512_set1_epi32(p.x0)) &
                        _mm512_cmplt_epi32_mask(col, _mm512_set1_epi32(p.x1)));
    // As lane_px: float(px0 + column) + 0.5.
    px = _mm512_cvtepi32_ps(_mm512_add_epi32(col, _mm512_set1_epi32(t.px0))) + X::set1(0.5f);
  }
  // The lanes of rows r and r1 as a mask (r1 == r: a lone last row; its upper half is off).
  static __mmask16 rows(int r, int r1) { return __mmask16(r1 != r ? 0xFFFFu : 0x00FFu); }
  __m512 get(const __m512* v, int r, int r1) const { return _mm512_permutex2var_ps(v[r], gather, v[r1]); }
  __m512i get(const __m512i* v, int r, int r1) const { return _mm512_permutex2var_epi32(v[r], gather, v[r1]); }
  // Writes the window of both rows back from `x` (constant masks: deriving the row masks
  // of only the changed lanes costs mask-register round trips through integer registers).
  void put(__m512* v, int r, int r1, __m512 x) const {
    v[r] = _mm512_mask_permutexvar_ps(v[r], window, back0, x);
    if (r1 != r) v[r1] = _mm512_mask_permutexvar_ps(v[r1], window, back1, x);
  }
};

// The backward of one pair on two rows at a time (see TwoRows): the same per-pixel updates
// as backward_tile's general path (the colour channels known at compile time, no absgrad).
template <int NC>
inline void backward_pair_two_rows(const TileGeom& t, const PairRec<float>& p, int list_pos_i,
                                   __m512* Tcur, __m512* Bg, const __m512* gAT, const __m512* gD,
                                   const __m512i* last, const __m512* gC, float* slot) {
  using X = Simd<float>;
  const TwoRows L(t, p);
  const GaussLanes<X, float> gl(L.px, p, 0);
  const GaussRows<X, float> rows(t, p, gl.half_cc);
  const __m512& dx = gl.dx;
  const __m512i list_pos = _mm512_set1_epi32(list_pos_i);
  const __m512 gz = X::set1(p.z), one = X::set1(1.0f);
  PairSums<X, float> sums;
  __m512 col_acc[NC];
  for (int ch = 0; ch < NC; ++ch) col_acc[ch] = X::zero();
  for (int r = p.y0; r < p.y1; r += 2) {
    const int r1 = r + 1 < p.y1 ? r + 1 : r;
    const __mmask16 in_box = L.in_cols & TwoRows::rows(r, r1);
    const __m512i last_2 = L.get(last, r, r1);
    // Pixels that stopped before this Gaussian: skip the rows before paying for the exp.
    if (!(in_box & _mm512_cmplt_epi32_mask(list_pos, last_2))) continue;
    const __m512 dy = GaussRows<X, float>::pick2(rows.dy_v, r);
    const RowEval<X> e = eval_lanes(gl, dy, GaussRows<X, float>::pick2(rows.quad_v, r), in_box);
    const __mmask16 use = e.ok & _mm512_cmplt_epi32_mask(list_pos, last_2);
    if (!use) continue;
    const __m512 T_2 = L.get(Tcur, r, r1);
    __m512 B = L.get(Bg, r, r1);
    const __m512 gd = L.get(gD, r, r1);
    const __m512 inv = X::rcp(one - e.alpha);
    const __m512 Ti = T_2 * inv;
    const __m512 w = X::keep(use, e.alpha * Ti);
    __m512 gcc = gd * gz;
    for (int ch = 0; ch < NC; ++ch) {
      const __m512 gc = L.get(gC + ch * TILE, r, r1);
      gcc += gc * X::set1(p.col[ch]);
      col_acc[ch] += w * gc;
    }
    const __m512 dal = inv * (L.get(gAT, r, r1) - B) + Ti * gcc;
    B += w * gcc;
    sums.a_d += w * gd;
    L.put(Tcur, r, r1, X::select(use, Ti, T_2));
    L.put(Bg, r, r1, B);
    sums.add(e, use, dal, dx, dy, dy * dy);
  }
  sums.write(slot, p, false);
  for (int ch = 0; ch < NC; ++ch) slot[COLOR0 + ch] = X::hsum(col_acc[ch]);
}
#endif

// How many pairs ahead the backward prefetches a pair's gradient slot (2 to 12 measured; 4
// was best by a little).
constexpr int SLOT_AHEAD = 4;

// ABS: also accumulate |dL/dmean2d| per pixel (AbsGS densification); without it the mean
// and conic gradients come from five moments of gp (per-Gaussian constants factored out
// of the row loop), which halves that part of the loop.
// NC: the channel count when known at compile time (3, the training render), 0 otherwise:
// with it the per-channel loops unroll and the pair's colour gradients stay in registers.
template <typename S, bool ABS, int NC>
void backward_tile(const RasterShape& s, const TileGeom& t, const S* records, const S* background, const S* t_final,
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
    const S* rec = records + size_t(k) * (RECORD_HEAD + C);
    uint32_t box;
    int32_t slot_index;
    // Slots are numbered id-major, so each pair writes its slot to a cache line nobody has
    // touched in this call: asking for ownership of that line a few pairs ahead hides the miss
    // (it stalled the store queue: backward -25 to -38 %).
    if (k - SLOT_AHEAD >= t.begin) {
      read_record_head(records + size_t(k - SLOT_AHEAD) * (RECORD_HEAD + C), box, slot_index);
      __builtin_prefetch(slots + size_t(slot_index) * stride, 1);
    }
    read_record_head(rec, box, slot_index);
    S* slot = slots + size_t(slot_index) * stride;  // id-major: summed sequentially
    if ((box >> 16 & 0xff) >= box >> 24) {  // contributed to no pixel in the forward
      std::fill(slot, slot + COLOR0 + C, S(0));
      continue;
    }
    const PairRec<S> p = read_pair(rec, box, RECORD_HEAD);
    const S* col = p.col;
#if defined(__AVX512F__)
    if constexpr (std::is_same_v<S, float> && NC > 0 && !ABS) {
      if (p.x1 - p.x0 <= 8 && p.y1 - p.y0 >= 2) {
        backward_pair_two_rows<NC>(t, p, k - t.begin, Tcur, Bg, gAT, gD, last, gC, slot);
        continue;
      }
    }
#endif
    on_pair_lanes<X>(p, [&](auto lanes, auto part, int lane0) __attribute__((always_inline)) {
      using Y = decltype(lanes);
      using YM = typename Y::M;
      using YV = typename Y::V;
      const auto list_pos = Y::iset1(k - t.begin);  // contributes where list_pos < last
      PairSums<Y, S> sums;
      // The pair's colour gradient per lane: locals when NC is known, else the scratch.
      YV col_local[NC > 0 ? NC : 1];
      auto col_acc = [&](int ch) -> YV& {
        if constexpr (NC > 0) return col_local[ch];
        else return part(s_col[ch]);
      };
      for (int ch = 0; ch < C; ++ch) col_acc(ch) = Y::zero();
      const GaussLanes<Y, S> gl(part(px), p, lane0);
      const GaussRows<Y, S> rows(t, p, gl.half_cc);
      const YV& dx = gl.dx;
      const YV gz = Y::set1(p.z), ca = Y::set1(p.ca), cb = Y::set1(p.cb), cc = Y::set1(p.cc);
      for (int r = p.y0; r < p.y1; ++r) {
        const auto& last_r = part(last[r]);
        // Pixels that stopped before this Gaussian: skip the row before paying for the exp.
        if (!Y::any(Y::mand(gl.in_box, Y::ilt(list_pos, last_r)))) continue;
        const RowEval<Y> e = eval_row(gl, rows, r);
        const YM use = Y::mand(e.ok, Y::ilt(list_pos, last_r));
        if (!Y::any(use)) continue;
        YV& Tcur_r = part(Tcur[r]);
        YV& Bg_r = part(Bg[r]);
        const YV gD_r = part(gD[r]);
        const YV dy = rows.dy(r);
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
        sums.a_d += w * gD_r;
        Tcur_r = Y::select(use, Ti, Tcur_r);
        const YV gp = sums.add(e, use, dal, dx, dy, rows.dy2(r));
        if constexpr (ABS) {
          sums.a_amx += Y::abs(gp * (ca * dx + cb * dy));
          sums.a_amy += Y::abs(gp * (cb * dx + cc * dy));
        }
      }
      sums.write(slot, p, ABS);
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
                    const S* background, S* records, S* image, S* alpha,
                    S* depth_acc, S* t_final, int32_t* n_contrib) {
  const int n_tiles = s.tiles_x * s.tiles_y;
  // The packed lines are work space, kept across calls (per calling thread): a fresh
  // buffer per call cost thousands of first-touch page faults at 200k Gaussians.
  thread_local std::vector<S, AlignedAllocator<S>> packed_buf;
  packed_buf.resize(size_t(n) * packed_stride<S>(s.channels));
  S* packed = packed_buf.data();
  pack_gaussians(n, s.channels, means2d, conics, opac, colors, depths, bbox, L.id_start, packed);
  const PairLines<S> lines{packed, packed_stride<S>(s.channels), L.order, L.tile_ranks};
#pragma omp parallel
  {
    std::vector<typename Simd<S>::V> acc;
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < n_tiles; ++tile) {
      const TileGeom t = tile_geom(s, L.tile_offsets, tile);
      if (s.channels == 3)
        forward_tile<S, 3>(s, t, lines, records, background, image, alpha, depth_acc, t_final, n_contrib, acc);
      else
        forward_tile<S, 0>(s, t, lines, records, background, image, alpha, depth_acc, t_final, n_contrib, acc);
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
