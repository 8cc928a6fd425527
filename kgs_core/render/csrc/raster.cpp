// Tile rasteriser, forward and hand-written backward.
//
// Work is split over 16x16 tiles (OpenMP, dynamic schedule: tiles differ a lot in load).
// Inside a tile the loop is Gaussian-major: each Gaussian in depth order updates only the
// rows of its bounding box. A tile row is exactly one 16-lane vector (GCC/Clang vector
// extensions, lowered to one AVX-512 or two AVX2 registers), so the per-pixel state of a
// tile is 16 vectors and every update is straight-line SIMD code. Auto-vectorisation of the
// equivalent scalar loop proved fragile (GCC 12 silently kept it scalar: 8x slower).
//
// The backward walks the same lists back to front, recovering each pixel's transmittance
// by division (alpha <= ALPHA_MAX keeps 1 - alpha >= 0.01), and writes one gradient slot
// per (tile, Gaussian) pair; the slots are summed per Gaussian in list order afterwards,
// which keeps results independent of the thread count.
#include <algorithm>
#include <cmath>
#include <cstring>
#include <type_traits>
#include <vector>

#include "kernels.h"

namespace kgs {
namespace {

static_assert(TILE == 16, "one tile row is one 16-lane vector");
constexpr int PREFETCH = 8;  // Gaussians ahead in a tile list

template <typename S>
struct Lanes;
template <>
struct Lanes<float> {
  typedef float V __attribute__((vector_size(64)));
  typedef int32_t M __attribute__((vector_size(64)));
};
template <>
struct Lanes<double> {
  typedef double V __attribute__((vector_size(128)));
  typedef int64_t M __attribute__((vector_size(128)));
};

// exp(x) for x <= 0 on 16 lanes (Cephes expf polynomial, ~2 ulp). Inputs below -40 give
// exp(-40) ~ 4e-18: far below any alpha threshold, and lanes outside a Gaussian's
// footprint stay out of denormal numbers, which cost ~100 cycles each.
inline Lanes<float>::V vexp(Lanes<float>::V x) {
  using V = Lanes<float>::V;
  using M = Lanes<float>::M;
  x = x < -40.0f ? V{} - 40.0f : x;
  x = x > 80.0f ? V{} + 80.0f : x;
  const V kt = x * 1.44269504088896341f + 0.5f;
  V kf = __builtin_convertvector(__builtin_convertvector(kt, M), V);
  kf = kf > kt ? kf - 1.0f : kf;  // floor
  V r = x - kf * 0.693359375f;
  r = r - kf * -2.12194440e-4f;
  const V z = r * r;
  V y = V{} + 1.9875691500e-4f;
  y = y * r + 1.3981999507e-3f;
  y = y * r + 8.3334519073e-3f;
  y = y * r + 4.1665795894e-2f;
  y = y * r + 1.6666665459e-1f;
  y = y * r + 5.0000001201e-1f;
  y = y * z + r + 1.0f;
  const M bits = (__builtin_convertvector(kf, M) + 127) << 23;
  return y * (V)bits;  // same-size vector cast = bit cast
}

// The float64 path serves gradcheck, not speed: exact exp per lane.
inline Lanes<double>::V vexp(Lanes<double>::V x) {
  Lanes<double>::V out;
  for (int i = 0; i < TILE; ++i) out[i] = std::exp(x[i]);
  return out;
}

template <typename V>
inline auto hsum(const V& v) -> std::remove_reference_t<decltype(v[0])> {
  std::remove_reference_t<decltype(v[0])> s = 0;
  for (int i = 0; i < TILE; ++i) s += v[i];
  return s;
}

template <typename M>
inline int count_set(const M& m) {
  int n = 0;
  for (int i = 0; i < TILE; ++i) n += m[i] != 0;
  return n;
}

struct TileGeom {
  int px0, py0;     // tile origin in pixels
  int w, h;         // tile extent inside the image
  int begin, end;   // range in tile_ranks
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

// A Gaussian's bounding box clipped to the tile: rows [y0, y1) in image coordinates,
// columns [x0, x1) relative to the tile origin.
struct Clip {
  int x0, x1, y0, y1;
  bool empty() const { return x0 >= x1 || y0 >= y1; }
};

inline Clip clip_to_tile(const int32_t* b, const TileGeom& t) {
  return {std::max(b[0], t.px0) - t.px0, std::min(b[2], t.px0 + TILE) - t.px0,
          std::max(b[1], t.py0), std::min(b[3], t.py0 + TILE)};
}

// A visible Gaussian's screen-space parameters, gathered in depth order so that every
// tile walks memory forward instead of jumping across the whole scene per Gaussian.
template <typename S>
struct Splat {
  S mx, my, ca, cb, cc, op, z;
  int32_t box[4];
};

template <typename S>
void gather_splats(int64_t n_visible, const int32_t* order, const S* means2d, const S* conics,
                   const S* opac, const S* colors, const S* depths, const int32_t* bbox, int C,
                   std::vector<Splat<S>>& splats, std::vector<S>& cols) {
  splats.resize(size_t(n_visible));
  cols.resize(size_t(n_visible) * C);
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n_visible; ++i) {
    const int32_t g = order[i];
    Splat<S>& sp = splats[i];
    sp.mx = means2d[2 * g]; sp.my = means2d[2 * g + 1];
    sp.ca = conics[3 * g]; sp.cb = conics[3 * g + 1]; sp.cc = conics[3 * g + 2];
    sp.op = opac[g]; sp.z = depths[g];
    for (int j = 0; j < 4; ++j) sp.box[j] = bbox[4 * g + j];
    for (int ch = 0; ch < C; ++ch) cols[size_t(i) * C + ch] = colors[size_t(g) * C + ch];
  }
}

// Lane constants shared by forward and backward for one tile.
template <typename S>
struct TileLanes {
  using V = typename Lanes<S>::V;
  using M = typename Lanes<S>::M;
  M lane;  // 0..15
  V px;    // pixel-centre x of each lane
  explicit TileLanes(const TileGeom& t) {
    for (int i = 0; i < TILE; ++i) {
      lane[i] = i;
      px[i] = S(t.px0 + i) + S(0.5);
    }
  }
};

// What one Gaussian contributes along a tile row, with everything that does not depend on
// the row hoisted out: power(dy) = p0 + dy * p1 - cc dy^2 / 2 per lane.
template <typename S>
struct GaussLanes {
  using V = typename Lanes<S>::V;
  using M = typename Lanes<S>::M;
  V dx, p0, p1;
  M in_box;  // lanes inside the Gaussian's bounding box
  S half_cc, op;
  GaussLanes(const TileLanes<S>& L, const Clip& c, S mx, S ca, S cb, S cc, S opacity) {
    dx = L.px - mx;
    p0 = S(-0.5) * ca * dx * dx;
    p1 = -cb * dx;
    in_box = (L.lane >= c.x0) & (L.lane < c.x1);
    half_cc = S(0.5) * cc;
    op = opacity;
  }
};

// The per-row evaluation both passes share: lanes where the Gaussian takes part (before
// the pixel's own cut-off, which the caller adds), its Gaussian value, raw and clamped alpha.
template <typename S>
struct RowEval {
  using V = typename Lanes<S>::V;
  using M = typename Lanes<S>::M;
  V G, a_raw, alpha;
  M ok;
};

template <typename S>
inline RowEval<S> eval_row(const GaussLanes<S>& gl, S dy) {
  RowEval<S> e;
  const auto power = gl.p0 + dy * gl.p1 - gl.half_cc * dy * dy;
  e.G = vexp(power);
  e.a_raw = gl.op * e.G;
  e.alpha = e.a_raw < S(ALPHA_MAX) ? e.a_raw : typename Lanes<S>::V{} + S(ALPHA_MAX);
  e.ok = gl.in_box & (power <= S(0)) & (e.alpha >= S(ALPHA_MIN));
  return e;
}

template <typename S>
void forward_tile(const RasterShape& s, const TileGeom& t, const Splat<S>* splats,
                  const S* colors, const S* background, const int32_t* tile_ranks, S* image,
                  S* alpha_out,
                  S* depth_out, S* t_final, int32_t* n_contrib,
                  std::vector<typename Lanes<S>::V>& acc) {
  using V = typename Lanes<S>::V;
  using M = typename Lanes<S>::M;
  const int C = s.channels;
  const TileLanes<S> L(t);
  V T[TILE], dacc[TILE];
  M last[TILE], done[TILE];
  acc.assign(size_t(C) * TILE, V{});
  int n_done = 0;
  for (int r = 0; r < TILE; ++r) {
    T[r] = V{} + S(1);
    dacc[r] = V{};
    last[r] = M{};
    // Pixels outside the image count as finished so that edge tiles can stop early.
    done[r] = (L.lane >= t.w) | (M{} + (r >= t.h ? -1 : 0));
    n_done += count_set(done[r]);
  }
  M any_term{};
  for (int k = t.begin; k < t.end; ++k) {
    // Counting finished pixels needs lane extraction: do it only after a pixel finished
    // and at most every 8 Gaussians.
    if (((k - t.begin) & 7) == 0 && count_set(any_term) > 0) {
      any_term = M{};
      n_done = 0;
      for (int r = 0; r < TILE; ++r) n_done += count_set(done[r]);
      if (n_done == TILE_PIXELS) break;
    }
    const int32_t g = tile_ranks[k];
    // Ranks in a tile are sparse in the scene-wide array: fetch a few Gaussians ahead.
    if (k + PREFETCH < t.end) {
      __builtin_prefetch(&splats[tile_ranks[k + PREFETCH]]);
      __builtin_prefetch(colors + size_t(tile_ranks[k + PREFETCH]) * C);
    }
    const Splat<S>& sp = splats[g];
    const Clip c = clip_to_tile(sp.box, t);
    if (c.empty()) continue;
    const S mx = sp.mx, my = sp.my, ca = sp.ca, cb = sp.cb, cc = sp.cc, op = sp.op, gz = sp.z;
    const S* col = colors + size_t(g) * C;
    const M list_pos = M{} + (k - t.begin + 1);
    const GaussLanes<S> gl(L, c, mx, ca, cb, cc, op);
    for (int y = c.y0; y < c.y1; ++y) {
      const int r = y - t.py0;
      const RowEval<S> e = eval_row(gl, S(y) + S(0.5) - my);
      const M in = e.ok & (done[r] == 0);
      const V test_t = T[r] * (S(1) - e.alpha);
      const M term = in & (test_t < S(T_MIN));
      const M use = in & ~term;
      const V w = use ? e.alpha * T[r] : V{};
      T[r] = use ? test_t : T[r];
      last[r] = use ? list_pos : last[r];
      done[r] |= term;
      any_term |= term;
      dacc[r] += w * gz;
      for (int ch = 0; ch < C; ++ch) acc[size_t(ch) * TILE + r] += w * col[ch];
    }
  }
  for (int r = 0; r < t.h; ++r) {
    for (int i = 0; i < t.w; ++i) {
      const size_t pix = size_t(t.py0 + r) * s.width + (t.px0 + i);
      for (int ch = 0; ch < C; ++ch)
        image[pix * C + ch] = acc[size_t(ch) * TILE + r][i] + T[r][i] * background[ch];
      alpha_out[pix] = S(1) - T[r][i];
      depth_out[pix] = dacc[r][i];
      t_final[pix] = T[r][i];
      n_contrib[pix] = int32_t(last[r][i]);
    }
  }
}

// Gradient slot layout per (tile, Gaussian) pair.
enum Slot { MX = 0, MY, CA, CB, CC, OP, DEPTH, ABS_MX, ABS_MY, COLOR0 };

template <typename S>
void backward_tile(const RasterShape& s, const TileGeom& t, const Splat<S>* splats,
                   const S* colors, const S* background, const int32_t* tile_ranks, const S* t_final,
                   const int32_t* n_contrib, const S* g_image, const S* g_alpha,
                   const S* g_depth, S* slots, std::vector<typename Lanes<S>::V>& scratch) {
  using V = typename Lanes<S>::V;
  using M = typename Lanes<S>::M;
  const int C = s.channels;
  const int stride = COLOR0 + C;
  const TileLanes<S> L(t);
  // Per-pixel state, channel-major: the image gradient and the colour accumulated behind
  // the current Gaussian (starting with the background seen through T_final).
  scratch.assign(size_t(2 * C + 1) * TILE, V{});
  V* gC = scratch.data();
  V* behind = gC + size_t(C) * TILE;
  V* s_col = behind + size_t(C) * TILE;  // per-Gaussian colour gradient, per lane
  V gA[TILE], gD[TILE], Tfin[TILE], Tcur[TILE], behind_d[TILE];
  M last[TILE];
  for (int r = 0; r < TILE; ++r) {
    gA[r] = gD[r] = behind_d[r] = V{};
    Tfin[r] = Tcur[r] = V{} + S(1);
    last[r] = M{};
  }
  for (int r = 0; r < t.h; ++r) {
    for (int i = 0; i < t.w; ++i) {
      const size_t pix = size_t(t.py0 + r) * s.width + (t.px0 + i);
      Tfin[r][i] = Tcur[r][i] = t_final[pix];
      last[r][i] = n_contrib[pix];
      gA[r][i] = g_alpha[pix];
      gD[r][i] = g_depth[pix];
      for (int ch = 0; ch < C; ++ch) {
        gC[size_t(ch) * TILE + r][i] = g_image[pix * C + ch];
        behind[size_t(ch) * TILE + r][i] = t_final[pix] * background[ch];
      }
    }
  }
  for (int k = t.end - 1; k >= t.begin; --k) {
    const int32_t g = tile_ranks[k];
    if (k - PREFETCH >= t.begin) {
      __builtin_prefetch(&splats[tile_ranks[k - PREFETCH]]);
      __builtin_prefetch(colors + size_t(tile_ranks[k - PREFETCH]) * C);
    }
    S* slot = slots + size_t(k) * stride;
    for (int j = 0; j < stride; ++j) slot[j] = S(0);
    const Splat<S>& sp = splats[g];
    const Clip c = clip_to_tile(sp.box, t);
    if (c.empty()) continue;
    const S mx = sp.mx, my = sp.my, ca = sp.ca, cb = sp.cb, cc = sp.cc, op = sp.op, gz = sp.z;
    const S* col = colors + size_t(g) * C;
    const M list_pos = M{} + (k - t.begin);  // contributes where list_pos < last
    V a_mx{}, a_my{}, a_ca{}, a_cb{}, a_cc{}, a_op{}, a_d{}, a_amx{}, a_amy{};
    for (int ch = 0; ch < C; ++ch) s_col[ch] = V{};
    const GaussLanes<S> gl(L, c, mx, ca, cb, cc, op);
    const V& dx = gl.dx;
    for (int y = c.y0; y < c.y1; ++y) {
      const int r = y - t.py0;
      const S dy = S(y) + S(0.5) - my;
      const RowEval<S> e = eval_row(gl, dy);
      const M use = e.ok & (list_pos < last[r]);
      const V inv = S(1) / (S(1) - e.alpha);
      const V Ti = Tcur[r] * inv;  // transmittance in front of this Gaussian
      const V w = use ? e.alpha * Ti : V{};
      // dL/dalpha = sum_c gC (c T_i - behind_c / (1 - alpha)) + the same for depth
      //             + gA T_final / (1 - alpha)
      V dal = gA[r] * Tfin[r] * inv + gD[r] * (gz * Ti - behind_d[r] * inv);
      for (int ch = 0; ch < C; ++ch) {
        const V gc = gC[size_t(ch) * TILE + r];
        V& bh = behind[size_t(ch) * TILE + r];
        dal += gc * (col[ch] * Ti - bh * inv);
        s_col[ch] += w * gc;
        bh += w * col[ch];
      }
      a_d += w * gD[r];
      behind_d[r] += w * gz;
      Tcur[r] = use ? Ti : Tcur[r];
      // Through alpha = min(ALPHA_MAX, o * exp(power)) to the 2D Gaussian.
      const V da = use & (e.a_raw < S(ALPHA_MAX)) ? dal : V{};
      const V gp = da * e.a_raw;
      a_op += da * e.G;
      const V gmx = gp * (ca * dx + cb * dy), gmy = gp * (cb * dx + cc * dy);
      a_mx += gmx;
      a_my += gmy;
      a_amx += gmx < S(0) ? -gmx : gmx;
      a_amy += gmy < S(0) ? -gmy : gmy;
      a_ca += S(-0.5) * gp * dx * dx;
      a_cb += -gp * dx * dy;
      a_cc += S(-0.5) * gp * (dy * dy);
    }
    slot[MX] = hsum(a_mx); slot[MY] = hsum(a_my);
    slot[CA] = hsum(a_ca); slot[CB] = hsum(a_cb); slot[CC] = hsum(a_cc);
    slot[OP] = hsum(a_op); slot[DEPTH] = hsum(a_d);
    slot[ABS_MX] = hsum(a_amx); slot[ABS_MY] = hsum(a_amy);
    for (int ch = 0; ch < C; ++ch) slot[COLOR0 + ch] = hsum(s_col[ch]);
  }
}

}  // namespace

template <typename S>
void raster_forward(const RasterShape& s, int64_t n_visible, const int32_t* order,
                    const S* means2d, const S* conics, const S* opac, const S* colors,
                    const S* depths, const int32_t* bbox, const S* background,
                    const int32_t* tile_offsets, const int32_t* tile_ranks, S* image, S* alpha,
                    S* depth_acc, S* t_final, int32_t* n_contrib) {
  const int n_tiles = s.tiles_x * s.tiles_y;
  std::vector<Splat<S>> splats;
  std::vector<S> cols;
  gather_splats(n_visible, order, means2d, conics, opac, colors, depths, bbox, s.channels,
                splats, cols);
#pragma omp parallel
  {
    std::vector<typename Lanes<S>::V> acc;
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < n_tiles; ++tile) {
      forward_tile(s, tile_geom(s, tile_offsets, tile), splats.data(), cols.data(), background,
                   tile_ranks, image, alpha, depth_acc, t_final, n_contrib, acc);
    }
  }
}

template <typename S>
void raster_backward(const RasterShape& s, int64_t n, int64_t n_visible, const int32_t* order,
                     const S* means2d, const S* conics, const S* opac, const S* colors,
                     const S* depths, const int32_t* bbox, const S* background,
                     const int32_t* tile_offsets, const int32_t* tile_ranks, const S* t_final,
                     const int32_t* n_contrib, const S* g_image, const S* g_alpha,
                     const S* g_depth, S* g_means2d, S* g_conics, S* g_opac, S* g_colors,
                     S* g_depths, S* abs_g_means2d) {
  const int n_tiles = s.tiles_x * s.tiles_y;
  const int C = s.channels;
  const int stride = COLOR0 + C;
  const int64_t n_pairs = tile_offsets[n_tiles];
  std::vector<Splat<S>> splats;
  std::vector<S> cols;
  gather_splats(n_visible, order, means2d, conics, opac, colors, depths, bbox, C, splats, cols);
  std::vector<S> slots(size_t(n_pairs) * stride);
#pragma omp parallel
  {
    std::vector<typename Lanes<S>::V> scratch;
#pragma omp for schedule(dynamic, 1)
    for (int tile = 0; tile < n_tiles; ++tile) {
      backward_tile(s, tile_geom(s, tile_offsets, tile), splats.data(), cols.data(), background,
                    tile_ranks, t_final, n_contrib, g_image, g_alpha, g_depth, slots.data(),
                    scratch);
    }
  }
  // Sum the pair slots per depth rank (in list order: deterministic), then scatter by id.
  std::vector<S> per_rank(size_t(n_visible) * stride, S(0));
  for (int64_t k = 0; k < n_pairs; ++k) {
    const S* slot = slots.data() + size_t(k) * stride;
    S* acc = per_rank.data() + size_t(tile_ranks[k]) * stride;
    for (int j = 0; j < stride; ++j) acc[j] += slot[j];
  }
  std::fill(g_means2d, g_means2d + 2 * n, S(0));
  std::fill(abs_g_means2d, abs_g_means2d + 2 * n, S(0));
  std::fill(g_conics, g_conics + 3 * n, S(0));
  std::fill(g_opac, g_opac + n, S(0));
  std::fill(g_depths, g_depths + n, S(0));
  std::fill(g_colors, g_colors + n * C, S(0));
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n_visible; ++i) {
    const int32_t g = order[i];
    const S* a = per_rank.data() + size_t(i) * stride;
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

#define KGS_INSTANTIATE(S)                                                                    \
  template void raster_forward<S>(const RasterShape&, int64_t, const int32_t*, const S*,      \
                                  const S*, const S*, const S*, const S*, const int32_t*,     \
                                  const S*, const int32_t*, const int32_t*, S*, S*, S*, S*,   \
                                  int32_t*);                                                  \
  template void raster_backward<S>(const RasterShape&, int64_t, int64_t, const int32_t*,      \
                                   const S*, const S*, const S*, const S*, const S*,          \
                                   const int32_t*, const S*, const int32_t*, const int32_t*,  \
                                   const S*, const int32_t*, const S*, const S*, const S*,    \
                                   S*, S*, S*, S*, S*, S*);
KGS_INSTANTIATE(float)
KGS_INSTANTIATE(double)
#undef KGS_INSTANTIATE

}  // namespace kgs
