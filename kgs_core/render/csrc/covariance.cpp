// Covariance from (quaternion, scale): Sigma = R S S^T R^T, packed upper-triangular, and
// its backward. Saves ~40 small torch ops per render on the common static-Gaussian path.
#include <algorithm>
#include <cmath>

#include "kernels.h"
#include "parallel.h"

namespace kgs {
namespace {

template <typename S>
struct UnitQuat {
  S w, x, y, z, norm;
  bool zero;  // a zero quaternion means the identity rotation (and gets no gradient)
};

template <typename S>
inline UnitQuat<S> unit_quat(const S* q) {
  const S n = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (!(n >= S(1e-12))) return {S(1), S(0), S(0), S(0), n, true};
  return {q[0] / n, q[1] / n, q[2] / n, q[3] / n, n, false};
}

template <typename S>
inline void rotmat(const UnitQuat<S>& u, S R[9]) {
  const S w = u.w, x = u.x, y = u.y, z = u.z;
  R[0] = 1 - 2 * (y * y + z * z); R[1] = 2 * (x * y - w * z); R[2] = 2 * (x * z + w * y);
  R[3] = 2 * (x * y + w * z); R[4] = 1 - 2 * (x * x + z * z); R[5] = 2 * (y * z - w * x);
  R[6] = 2 * (x * z - w * y); R[7] = 2 * (y * z + w * x); R[8] = 1 - 2 * (x * x + y * y);
}

}  // namespace

template <typename S>
void covar_forward(int64_t n, const S* quats, const S* scales, S* cov6) {
#pragma omp parallel for schedule(static)
  for (int64_t i = 0; i < n; ++i) {
    S R[9], M[9];
    rotmat(unit_quat(quats + 4 * i), R);
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c) M[3 * r + c] = R[3 * r + c] * scales[3 * i + c];
    S* o = cov6 + 6 * i;
    const int rows[6] = {0, 0, 0, 1, 1, 2}, cols[6] = {0, 1, 2, 1, 2, 2};
    for (int k = 0; k < 6; ++k) {
      const S* a = M + 3 * rows[k];
      const S* b = M + 3 * cols[k];
      o[k] = a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    }
  }
}

// The backward over Gaussians [begin, end): a function of its own so that its pointers stay
// __restrict, branch-free, and reading the stride-6 gradient through a component-major
// block buffer, so that GCC vectorises it over Gaussians (as project.cpp's backward).
template <typename S>
__attribute__((noinline)) void covar_backward_range(int64_t begin, int64_t end,
                                                    const S* __restrict quats,
                                                    const S* __restrict scales,
                                                    const S* __restrict g_cov6,
                                                    S* __restrict g_quats, S* __restrict g_scales) {
  constexpr int B = 128;
  alignas(64) S g_in[6][B];
  for (int64_t b0 = begin; b0 < end; b0 += B) {
    const int m = int(std::min<int64_t>(B, end - b0));
    for (int j = 0; j < m; ++j)
      for (int k = 0; k < 6; ++k) g_in[k][j] = g_cov6[6 * (b0 + j) + k];
#pragma GCC ivdep  // Gaussians are independent: no run-time alias checks
    for (int j = 0; j < m; ++j) {
      const int64_t i = b0 + j;
      const UnitQuat<S> u = unit_quat(quats + 4 * i);
      S R[9], M[9];
      rotmat(u, R);
      const S* s = scales + 3 * i;
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c) M[3 * r + c] = R[3 * r + c] * s[c];
      // Sigma = M M^T with packed output: dL/dM = Gs M, Gs the symmetric matrix with 2 g on
      // the diagonal and g off it.
      const S g[6] = {g_in[0][j], g_in[1][j], g_in[2][j], g_in[3][j], g_in[4][j], g_in[5][j]};
      const S Gs[9] = {2 * g[0], g[1], g[2], g[1], 2 * g[3], g[4], g[2], g[4], 2 * g[5]};
      S gM[9];
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
          gM[3 * r + c] = Gs[3 * r] * M[c] + Gs[3 * r + 1] * M[3 + c] + Gs[3 * r + 2] * M[6 + c];
      S gR[9];
      for (int c = 0; c < 3; ++c) {
        S gs = 0;
        for (int r = 0; r < 3; ++r) {
          gR[3 * r + c] = gM[3 * r + c] * s[c];
          gs += gM[3 * r + c] * R[3 * r + c];
        }
        g_scales[3 * i + c] = gs;
      }
      const S w = u.w, x = u.x, y = u.y, z = u.z;
      const S gw = 2 * (-z * gR[1] + y * gR[2] + z * gR[3] - x * gR[5] - y * gR[6] + x * gR[7]);
      const S gx = 2 * (y * gR[1] + z * gR[2] + y * gR[3] - 2 * x * gR[4] - w * gR[5] +
                        z * gR[6] + w * gR[7] - 2 * x * gR[8]);
      const S gy = 2 * (-2 * y * gR[0] + x * gR[1] + w * gR[2] + x * gR[3] + z * gR[5] -
                        w * gR[6] + z * gR[7] - 2 * y * gR[8]);
      const S gz = 2 * (-2 * z * gR[0] - w * gR[1] + x * gR[2] + w * gR[3] - 2 * z * gR[4] +
                        y * gR[5] + x * gR[6] + y * gR[7]);
      // Through q / |q|: remove the radial component and divide by |q| (a zero quaternion,
      // the identity, gets no gradient).
      const S dot = gw * w + gx * x + gy * y + gz * z;
      S* gq = g_quats + 4 * i;
      gq[0] = u.zero ? S(0) : (gw - dot * w) / u.norm;
      gq[1] = u.zero ? S(0) : (gx - dot * x) / u.norm;
      gq[2] = u.zero ? S(0) : (gy - dot * y) / u.norm;
      gq[3] = u.zero ? S(0) : (gz - dot * z) / u.norm;
    }
  }
}

template <typename S>
void covar_backward(int64_t n, const S* quats, const S* scales, const S* g_cov6, S* g_quats,
                    S* g_scales) {
  per_thread_share(n, [&](int64_t begin, int64_t end) {
    covar_backward_range(begin, end, quats, scales, g_cov6, g_quats, g_scales);
  });
}

template void covar_forward<float>(int64_t, const float*, const float*, float*);
template void covar_forward<double>(int64_t, const double*, const double*, double*);
template void covar_backward<float>(int64_t, const float*, const float*, const float*, float*, float*);
template void covar_backward<double>(int64_t, const double*, const double*, const double*, double*, double*);

}  // namespace kgs
