// Kinematics-GS CPU rasteriser: kernels on raw pointers, no torch headers, so that the
// heavy translation units compile quickly and the math stays readable.
//
// Conventions (match kgs_core/render/torch_backend.py, the test oracle):
//  * OpenCV pinhole camera, world-to-camera viewmat (row-major 4x4), K row-major 3x3.
//  * Pixel (row i, col j) has its centre at (j + 0.5, i + 0.5) (COLMAP convention).
//  * Covariances are packed upper-triangular: (xx, xy, xz, yy, yz, zz).
//  * Conics are packed (a, b, c) for the inverse 2D covariance [[a, b], [b, c]].
//  * A Gaussian contributes alpha = min(ALPHA_MAX, o * exp(power)) to a pixel when
//    power <= 0 and alpha >= ALPHA_MIN; a pixel stops (excluding that Gaussian) as soon as
//    its transmittance would fall below T_MIN. Forward and backward share these rules.
#pragma once
#include <cstdint>
#include <functional>

namespace kgs {

constexpr int TILE = 16;
constexpr int TILE_PIXELS = TILE * TILE;
constexpr float ALPHA_MIN = 1.0f / 255.0f;
constexpr float ALPHA_MAX = 0.99f;
constexpr float T_MIN = 1e-4f;

struct Camera {
  double viewmat[16];  // world-to-camera, row-major
  double fx, fy, cx, cy;
  int width, height;
  double near_plane, far_plane;
};

// Sigma = R(q) diag(s)^2 R(q)^T, packed; q need not be normalised (zero -> identity).
template <typename S>
void covar_forward(int64_t n, const S* quats, const S* scales, S* cov6);
template <typename S>
void covar_backward(int64_t n, const S* quats, const S* scales, const S* g_cov6, S* g_quats,
                    S* g_scales);

// Opacity factor that keeps a motion-blurred splat's 2D mass, and its gradients with respect
// to the packed blurred covariances and the sweeps (project.cpp; render/blur.py).
template <typename S>
void blur_scale_forward(int64_t n, const S* means, const S* covars, const S* sweeps, const Camera& c,
                        S eps2d, S* scale);
template <typename S>
void blur_scale_backward(int64_t n, const S* means, const S* covars, const S* sweeps, const Camera& c,
                         S eps2d, const S* g_scale, S* g_covars, S* g_sweeps);

template <typename S>
void project_forward(int64_t n, const S* means, const S* covars, const S* opacities,
                     const Camera& cam, S eps2d, bool antialiased,
                     S* means2d, S* conics, S* depths, S* opac_eff, int32_t* radii,
                     int32_t* bbox);

template <typename S>
void project_backward(int64_t n, const S* means, const S* covars, const S* opacities,
                      const Camera& cam, S eps2d, bool antialiased, const int32_t* radii,
                      const S* g_means2d, const S* g_conics, const S* g_depths,
                      const S* g_opac_eff, S* g_means, S* g_covars, S* g_opacities);

// Where bin_gaussians writes the depth-sorted tile lists (see there).
struct BinOutputs {
  int32_t* tile_offsets;  // (n_tiles + 1,)
  int32_t* order;         // (n_visible,)
  int32_t* tile_ranks;    // (n_pairs,)
  int32_t* id_start;      // (n + 1,)
};

// Depth-sorted tile lists of the visible Gaussians (radii > 0). Once it knows their sizes,
// it calls allocate(n_visible, n_pairs) for the output arrays, then writes `tile_offsets`
// (each tile's range in the pair lists), `order` (visible ids, front to back: rank -> id),
// `tile_ranks` (per tile, ranks in increasing depth: the pair lists) and `id_start`, an
// id-major numbering of the same pairs: Gaussian g's pairs are numbered id_start[g] ..
// id_start[g + 1] - 1 (an invisible Gaussian's range is empty), in the row-major order of
// the tiles of its rectangle (bin_tile_rect). The backward writes each pair's gradients to
// the slot of its number and sums every Gaussian's contiguous slots in one sequential pass.
template <typename S>
void bin_gaussians(int64_t n, const int32_t* bbox, const int32_t* radii, const S* depths,
                   int width, int height, const std::function<BinOutputs(int64_t, int64_t)>& allocate);

struct RasterShape {
  int width, height, channels;
  int tiles_x, tiles_y;
};

// Tile lists as binning left them.
struct TileLists {
  int64_t n_visible, n_pairs;
  const int32_t* order;        // (n_visible,) rank -> Gaussian id
  const int32_t* tile_offsets; // (n_tiles + 1,)
  const int32_t* tile_ranks;   // (n_pairs,)
  const int32_t* id_start;     // (n + 1,)
};

// The tiles [x0, x1) x [y0, y1) that a Gaussian's pixel box [b0, b2) x [b1, b3) touches.
struct TileRect {
  int16_t x0, y0, x1, y1;  // exclusive ends (boxes lie inside the image)
};
inline TileRect bin_tile_rect(int b0, int b1, int b2, int b3) {
  return {int16_t(b0 / TILE), int16_t(b1 / TILE), int16_t((b2 - 1) / TILE + 1),
          int16_t((b3 - 1) / TILE + 1)};
}

// The kernels read each Gaussian's inputs from one packed line (see raster.cpp): LINE_HEAD
// scalars, then the colour channels, padded to whole 64-byte cache lines. The forward
// writes per pair a record for the backward: RECORD_HEAD scalars, then the colour channels.
constexpr int LINE_HEAD = 10;
constexpr int RECORD_HEAD = 9;
template <typename S>
constexpr int packed_stride(int channels) {
  constexpr int PER_LINE = 64 / sizeof(S);
  return (LINE_HEAD + channels + PER_LINE - 1) / PER_LINE * PER_LINE;
}

// The forward packs the inputs into lines of packed_stride(channels) scalars (work space)
// and writes `records` (n_pairs * (RECORD_HEAD + channels) scalars: each pair's
// parameters, colour, box cut to where it drew and gradient slot, in list order), which the
// backward reads instead of the per-Gaussian inputs.
template <typename S>
void raster_forward(const RasterShape& shape, const TileLists& lists, int64_t n, const S* means2d,
                    const S* conics, const S* opac, const S* colors, const S* depths,
                    const int32_t* bbox, const S* background, S* records,
                    S* image, S* alpha, S* depth_acc, S* t_final, int32_t* n_contrib);

template <typename S>
void raster_backward(const RasterShape& shape, const TileLists& lists, int64_t n,
                     const S* records, const S* background, const S* t_final,
                     const int32_t* n_contrib, const S* g_image, const S* g_alpha,
                     const S* g_depth, S* g_means2d, S* g_conics, S* g_opac, S* g_colors,
                     S* g_depths, S* abs_g_means2d, bool absgrad);

// Colours (N, 3) from SH coefficients (N, K, 3), degree 0..3, seen from `center` (3):
// max(sum_k basis_k(normalised mean - center) coeff_k + 0.5, 0). The backward gives the
// coefficients' gradient (the direction is not differentiated, as in the reference).
template <typename S>
void sh_forward(int64_t n, int K, int degree, const S* coeffs, const S* means, const S* center,
                S* rgb);
template <typename S>
void sh_backward(int64_t n, int K, int degree, const S* coeffs, const S* means, const S* center,
                 const S* g_rgb, S* g_coeffs);

// Fused SSIM over valid pixels of (H, W, C) images with a separable window w (k taps).
// The forward returns the mean and fills `maps` (5 x (H-k+1) x (W-k+1) x C: mu_x, mu_y,
// E[xx], E[yy], E[xy]); the backward writes d(grad * mean)/dx.
template <typename S>
S ssim_forward(const S* x, const S* y, int H, int W, int C, const S* w, int k, S* maps);
template <typename S>
void ssim_backward(const S* x, const S* y, int H, int W, int C, const S* w, int k,
                   const S* maps, S grad, S* g_x);

// K-Planes features of the deformation field, one resolution (six planes) at a time
// (kplanes.cpp). Planes are channels-last (H, W, F); `grad` planes are accumulated into
// (zeroed by the caller). Row j of the M N rows is point j mod N at time t[j].
struct KPlanes {
  const float* data[6];
  float* grad[6];
  int64_t H[6], W[6];
  int64_t F;
};
// out[j * out_stride + f] = prod_k sample_k(j)[f].
void kplanes_forward(int64_t N, int64_t rows, const float* x, const float* t, const KPlanes& p, float* out,
                     int64_t out_stride);
// F <= 256. g_x (N, 3): the points' coordinate gradient (summed over their M rows),
// accumulated into, or null (not needed).
void kplanes_backward(int64_t N, int64_t rows, const float* x, const float* t, const KPlanes& p, const float* g_out,
                      int64_t g_stride, float* g_x);

}  // namespace kgs
