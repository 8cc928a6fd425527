// Fused SSIM (Wang et al. 2004) with a separable window over valid pixels, forward and
// backward, for `(H, W, C)` images. In PyTorch the five depthwise convolutions and their
// backward took ~45 ms per 256x256 training step on two cores, more than the rasteriser.
//
// Rows are treated as flat arrays of W*C scalars, so a horizontal tap is an offset of C and
// a vertical tap an offset of one row: every inner loop is a contiguous, vectorisable axpy.
#include <algorithm>
#include <vector>

#include "kernels.h"

namespace kgs {
namespace {

constexpr double C1 = 0.01 * 0.01, C2 = 0.03 * 0.03;

// out (Ho x Wo*C) = vertical(horizontal(in (H x W*C))), valid part only.
template <typename S>
void blur_valid(const S* in, int H, int W, int C, const S* w, int k, S* tmp, S* out) {
  const int Ho = H - k + 1, Wo = W - k + 1;
  const int rin = W * C, rout = Wo * C;
#pragma omp parallel for schedule(static)
  for (int h = 0; h < H; ++h) {
    S* o = tmp + size_t(h) * rout;
    const S* r = in + size_t(h) * rin;
    std::fill(o, o + rout, S(0));
    for (int t = 0; t < k; ++t) {
      const S wt = w[t];
      const S* src = r + t * C;
      for (int q = 0; q < rout; ++q) o[q] += wt * src[q];
    }
  }
#pragma omp parallel for schedule(static)
  for (int i = 0; i < Ho; ++i) {
    S* o = out + size_t(i) * rout;
    std::fill(o, o + rout, S(0));
    for (int t = 0; t < k; ++t) {
      const S wt = w[t];
      const S* src = tmp + size_t(i + t) * rout;
      for (int q = 0; q < rout; ++q) o[q] += wt * src[q];
    }
  }
}

// The adjoint of blur_valid: out (H x W*C) = horizontal^T(vertical^T(in (Ho x Wo*C))).
template <typename S>
void blur_adjoint(const S* in, int H, int W, int C, const S* w, int k, S* tmp, S* out) {
  const int Ho = H - k + 1;
  const int rin = (W - k + 1) * C, rout = W * C;
#pragma omp parallel for schedule(static)
  for (int h = 0; h < H; ++h) {  // tmp[h] = sum_t w[t] in[h - t]
    S* o = tmp + size_t(h) * rin;
    std::fill(o, o + rin, S(0));
    for (int t = std::max(0, h - Ho + 1); t <= std::min(k - 1, h); ++t) {
      const S wt = w[t];
      const S* src = in + size_t(h - t) * rin;
      for (int q = 0; q < rin; ++q) o[q] += wt * src[q];
    }
  }
#pragma omp parallel for schedule(static)
  for (int h = 0; h < H; ++h) {  // out[h][q + t C] += w[t] tmp[h][q]
    S* o = out + size_t(h) * rout;
    const S* src = tmp + size_t(h) * rin;
    std::fill(o, o + rout, S(0));
    for (int t = 0; t < k; ++t) {
      const S wt = w[t];
      S* dst = o + t * C;
      for (int q = 0; q < rin; ++q) dst[q] += wt * src[q];
    }
  }
}

}  // namespace

template <typename S>
S ssim_forward(const S* x, const S* y, int H, int W, int C, const S* w, int k, S* maps) {
  const size_t n_in = size_t(H) * W * C;
  const int Ho = H - k + 1, Wo = W - k + 1;
  const size_t n_out = size_t(Ho) * Wo * C;
  std::vector<S> prod(n_in), tmp(size_t(H) * Wo * C);
  // maps: mu_x, mu_y, E[xx], E[yy], E[xy], each Ho x Wo x C.
  for (int m = 0; m < 5; ++m) {
    const S* src = m == 0 ? x : m == 1 ? y : prod.data();
    if (m >= 2) {
      const S* a = m == 3 ? y : x;
      const S* b = m == 2 ? x : y;
#pragma omp parallel for schedule(static)
      for (size_t i = 0; i < n_in; ++i) prod[i] = a[i] * b[i];
    }
    blur_valid(src, H, W, C, w, k, tmp.data(), maps + m * n_out);
  }
  const S *mx = maps, *my = maps + n_out, *exx = maps + 2 * n_out, *eyy = maps + 3 * n_out,
          *exy = maps + 4 * n_out;
  double total = 0;
#pragma omp parallel for schedule(static) reduction(+ : total)
  for (size_t i = 0; i < n_out; ++i) {
    const double a = mx[i], b = my[i];
    const double sxx = exx[i] - a * a, syy = eyy[i] - b * b, sxy = exy[i] - a * b;
    total += ((2 * a * b + C1) * (2 * sxy + C2)) / ((a * a + b * b + C1) * (sxx + syy + C2));
  }
  return S(total / double(n_out));
}

template <typename S>
void ssim_backward(const S* x, const S* y, int H, int W, int C, const S* w, int k,
                   const S* maps, S grad, S* g_x) {
  const size_t n_in = size_t(H) * W * C;
  const int Ho = H - k + 1, Wo = W - k + 1;
  const size_t n_out = size_t(Ho) * Wo * C;
  const S *mx = maps, *my = maps + n_out, *exx = maps + 2 * n_out, *eyy = maps + 3 * n_out,
          *exy = maps + 4 * n_out;
  // dL/d(mu_x), dL/dE[xx], dL/dE[xy] per output pixel, for L = grad * mean(SSIM map).
  std::vector<S> g(3 * n_out);
  S *g_mx = g.data(), *g_exx = g_mx + n_out, *g_exy = g_exx + n_out;
  const S scale = grad / S(n_out);
#pragma omp parallel for schedule(static)
  for (size_t i = 0; i < n_out; ++i) {
    const S a = mx[i], b = my[i];
    const S A1 = 2 * a * b + S(C1), A2 = 2 * (exy[i] - a * b) + S(C2);
    const S B1 = a * a + b * b + S(C1), B2 = (exx[i] - a * a) + (eyy[i] - b * b) + S(C2);
    // S = A1 A2 / D with D = B1 B2 >= C1 C2 > 0; only D is divided by (A2 = 2 sxy + C2 can
    // be zero or negative, so S / A2 would be 0 / 0 where the images are anti-correlated).
    const S inv_d = S(1) / (B1 * B2);
    const S s = A1 * A2 * inv_d;
    g_mx[i] = scale * inv_d * (2 * b * (A2 - A1) - s * 2 * a * (B2 - B1));
    g_exx[i] = -scale * s * B1 * inv_d;
    g_exy[i] = scale * 2 * A1 * inv_d;
  }
  std::vector<S> tmp(size_t(H) * Wo * C), back(3 * n_in);
  for (int m = 0; m < 3; ++m)
    blur_adjoint(g.data() + m * n_out, H, W, C, w, k, tmp.data(), back.data() + m * n_in);
  const S *b_mx = back.data(), *b_exx = b_mx + n_in, *b_exy = b_exx + n_in;
#pragma omp parallel for schedule(static)
  for (size_t i = 0; i < n_in; ++i) g_x[i] = b_mx[i] + 2 * x[i] * b_exx[i] + y[i] * b_exy[i];
}

template float ssim_forward<float>(const float*, const float*, int, int, int, const float*, int, float*);
template double ssim_forward<double>(const double*, const double*, int, int, int, const double*, int, double*);
template void ssim_backward<float>(const float*, const float*, int, int, int, const float*, int,
                                   const float*, float, float*);
template void ssim_backward<double>(const double*, const double*, int, int, int, const double*, int,
                                    const double*, double, double*);

}  // namespace kgs
