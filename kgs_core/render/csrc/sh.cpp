// View-dependent colour from real spherical harmonics (degree 0..3), forward and backward,
// one Gaussian per loop iteration. In PyTorch the basis stack, the (N, 16, 3) product and
// their backward cost ~10 ms per 50k-Gaussian training step on two cores.
//
// Matches kgs_core/render/sh.py (the reference): direction = normalised (mean - camera
// centre), not differentiated; colour = max(sum_k basis_k coeff_k + 0.5, 0).
#include <algorithm>
#include <cmath>

#include "kernels.h"

namespace kgs {
namespace {

constexpr double C0 = 0.28209479177387814, C1 = 0.4886025119029199;
constexpr double C2[5] = {1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
                          -1.0925484305920792, 0.5462742152960396};
constexpr double C3[7] = {-0.5900435899266435, 2.890611442640554, -0.4570457994644658,
                          0.3731763325901154, -0.4570457994644658, 1.445305721320277,
                          -0.5900435899266435};

// Basis values for the unit direction from `center` to `mean`; returns how many.
template <typename S>
inline int basis(int degree, const S* mean, const S* center, S* b) {
  S x = mean[0] - center[0], y = mean[1] - center[1], z = mean[2] - center[2];
  const S inv = S(1) / std::max(std::sqrt(x * x + y * y + z * z), S(1e-12));
  x *= inv; y *= inv; z *= inv;
  b[0] = S(C0);
  if (degree < 1) return 1;
  b[1] = S(-C1) * y; b[2] = S(C1) * z; b[3] = S(-C1) * x;
  if (degree < 2) return 4;
  const S xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  b[4] = S(C2[0]) * xy; b[5] = S(C2[1]) * yz; b[6] = S(C2[2]) * (2 * zz - xx - yy);
  b[7] = S(C2[3]) * xz; b[8] = S(C2[4]) * (xx - yy);
  if (degree < 3) return 9;
  b[9] = S(C3[0]) * y * (3 * xx - yy);
  b[10] = S(C3[1]) * xy * z;
  b[11] = S(C3[2]) * y * (4 * zz - xx - yy);
  b[12] = S(C3[3]) * z * (2 * zz - 3 * xx - 3 * yy);
  b[13] = S(C3[4]) * x * (4 * zz - xx - yy);
  b[14] = S(C3[5]) * z * (xx - yy);
  b[15] = S(C3[6]) * x * (xx - 3 * yy);
  return 16;
}

// Colour before the clamp at 0: 0.5 + sum_k basis_k coeff_k.
template <typename S>
inline void raw_color(int degree, const S* c, const S* mean, const S* center, S* b, int* nb,
                      S acc[3]) {
  *nb = basis(degree, mean, center, b);
  acc[0] = acc[1] = acc[2] = S(0.5);
  for (int k = 0; k < *nb; ++k)
    for (int ch = 0; ch < 3; ++ch) acc[ch] += b[k] * c[3 * k + ch];
}

}  // namespace

template <typename S>
void sh_forward(int64_t n, int K, int degree, const S* coeffs, const S* means, const S* center,
                S* rgb) {
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    S b[16], acc[3];
    int nb;
    raw_color(degree, coeffs + size_t(i) * K * 3, means + 3 * i, center, b, &nb, acc);
    for (int ch = 0; ch < 3; ++ch) rgb[3 * i + ch] = std::max(acc[ch], S(0));
  }
}

template <typename S>
void sh_backward(int64_t n, int K, int degree, const S* coeffs, const S* means, const S* center,
                 const S* g_rgb, S* g_coeffs) {
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    S b[16], acc[3];
    int nb;
    raw_color(degree, coeffs + size_t(i) * K * 3, means + 3 * i, center, b, &nb, acc);
    S g[3];
    for (int ch = 0; ch < 3; ++ch) g[ch] = acc[ch] >= S(0) ? g_rgb[3 * i + ch] : S(0);  // clamp at 0
    S* gc = g_coeffs + size_t(i) * K * 3;
    for (int k = 0; k < K; ++k)
      for (int ch = 0; ch < 3; ++ch) gc[3 * k + ch] = k < nb ? b[k] * g[ch] : S(0);
  }
}

template void sh_forward<float>(int64_t, int, int, const float*, const float*, const float*, float*);
template void sh_forward<double>(int64_t, int, int, const double*, const double*, const double*, double*);
template void sh_backward<float>(int64_t, int, int, const float*, const float*, const float*,
                                 const float*, float*);
template void sh_backward<double>(int64_t, int, int, const double*, const double*, const double*,
                                  const double*, double*);

}  // namespace kgs
