// Projection of 3D Gaussians to screen-space ellipses (EWA splatting) and its backward.
// One Gaussian per loop iteration; OpenMP over Gaussians.
#include <algorithm>
#include <cmath>
#include <limits>

#include "kernels.h"
#include "parallel.h"

namespace kgs {
namespace {

// Largest half-extent we keep, in pixels: beyond this the bounding box is clipped to the
// image anyway, and the clamp keeps float -> int conversions defined.
constexpr double MAX_EXTENT = 1e7;

template <typename S>
struct Mat3 {
  S m[9];
  S operator()(int r, int c) const { return m[3 * r + c]; }
};

template <typename S>
struct CamS {
  Mat3<S> R;
  S t[3];
  S fx, fy, cx, cy;
  S lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;
  S near_plane, far_plane;
  explicit CamS(const Camera& c) {
    near_plane = S(c.near_plane);
    far_plane = S(c.far_plane);
    for (int r = 0; r < 3; ++r) {
      for (int k = 0; k < 3; ++k) R.m[3 * r + k] = S(c.viewmat[4 * r + k]);
      t[r] = S(c.viewmat[4 * r + 3]);
    }
    fx = S(c.fx); fy = S(c.fy); cx = S(c.cx); cy = S(c.cy);
    // Off-screen Gaussians use the Jacobian at a clamped direction (as 3DGS/gsplat do):
    // without it a Gaussian far outside the frustum gets an exploding 2D covariance.
    const S tan_fovx = S(0.5) * S(c.width) / fx, tan_fovy = S(0.5) * S(c.height) / fy;
    lim_x_pos = (S(c.width) - cx) / fx + S(0.3) * tan_fovx;
    lim_x_neg = cx / fx + S(0.3) * tan_fovx;
    lim_y_pos = (S(c.height) - cy) / fy + S(0.3) * tan_fovy;
    lim_y_neg = cy / fy + S(0.3) * tan_fovy;
  }
};

// Everything the forward computes for one Gaussian, recomputed by the backward.
template <typename S>
struct Projected {
  S p[3];           // camera-space mean
  S txz, tyz;       // clamped x/z, y/z used by the Jacobian
  bool clamp_x, clamp_y;
  S J[6];           // 2x3 Jacobian, row-major
  S sc[9];          // camera-space covariance
  S cov2d[3];       // undilated (xx, xy, yy)
  S det0, det1;     // determinants without / with dilation
  S comp;           // anti-aliasing opacity compensation (1 when off)
  S u, v;
};

template <typename S>
inline void unpack_cov(const S* c, S out[9]) {
  out[0] = c[0]; out[1] = c[1]; out[2] = c[2];
  out[3] = c[1]; out[4] = c[3]; out[5] = c[4];
  out[6] = c[2]; out[7] = c[4]; out[8] = c[5];
}

// Everything the projection computes for one Gaussian, with no early exit (so that the loops
// over Gaussians vectorise). Returns whether the Gaussian can be seen (inside near/far, not
// degenerate, finite); the fields are meaningless if not.
template <typename S>
__attribute__((always_inline)) inline bool project_math(const CamS<S>& cam, const S* mean,
                                                       const S* cov, S eps2d, bool antialiased,
                                                       Projected<S>& P) {
  const auto& R = cam.R;
  for (int r = 0; r < 3; ++r)
    P.p[r] = R(r, 0) * mean[0] + R(r, 1) * mean[1] + R(r, 2) * mean[2] + cam.t[r];
  const S z = P.p[2];
  // (& rather than &&: no conditional loads, which stop GCC vectorising the backward)
  const bool in_depth = (z >= cam.near_plane) & (z <= cam.far_plane);
  const S xz = P.p[0] / z, yz = P.p[1] / z;
  P.txz = std::min(cam.lim_x_pos, std::max(-cam.lim_x_neg, xz));
  P.tyz = std::min(cam.lim_y_pos, std::max(-cam.lim_y_neg, yz));
  P.clamp_x = P.txz != xz;
  P.clamp_y = P.tyz != yz;
  const S iz = S(1) / z;
  P.J[0] = cam.fx * iz; P.J[1] = 0; P.J[2] = -cam.fx * P.txz * iz;
  P.J[3] = 0; P.J[4] = cam.fy * iz; P.J[5] = -cam.fy * P.tyz * iz;
  S sw[9];
  unpack_cov(cov, sw);
  // sc = R sw R^T
  S tmp[9];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k)
      tmp[3 * r + k] = R(r, 0) * sw[k] + R(r, 1) * sw[3 + k] + R(r, 2) * sw[6 + k];
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k)
      P.sc[3 * r + k] = tmp[3 * r + 0] * R(k, 0) + tmp[3 * r + 1] * R(k, 1) + tmp[3 * r + 2] * R(k, 2);
  // cov2d = J sc J^T
  S T[6];
  for (int r = 0; r < 2; ++r)
    for (int k = 0; k < 3; ++k)
      T[3 * r + k] = P.J[3 * r] * P.sc[k] + P.J[3 * r + 1] * P.sc[3 + k] + P.J[3 * r + 2] * P.sc[6 + k];
  P.cov2d[0] = T[0] * P.J[0] + T[1] * P.J[1] + T[2] * P.J[2];
  P.cov2d[1] = T[0] * P.J[3] + T[1] * P.J[4] + T[2] * P.J[5];
  P.cov2d[2] = T[3] * P.J[3] + T[4] * P.J[4] + T[5] * P.J[5];
  const S p = P.cov2d[0], q = P.cov2d[1], r = P.cov2d[2];
  P.det0 = p * r - q * q;
  P.det1 = (p + eps2d) * (r + eps2d) - q * q;
  const bool det_ok = (P.det1 > S(0)) & (P.det1 <= std::numeric_limits<S>::max());
  P.comp = antialiased ? (P.det0 > S(0) ? std::sqrt(P.det0 / P.det1) : S(0)) : S(1);
  P.u = cam.fx * xz + cam.cx;
  P.v = cam.fy * yz + cam.cy;
  const S big = std::numeric_limits<S>::max();
  return in_depth & det_ok & (std::abs(P.u) <= big) & (std::abs(P.v) <= big);
}


}  // namespace

// The forward over Gaussians [begin, end), a block at a time in three loops, so that GCC
// vectorises the first and the last (see project_backward_range for why the restrict
// worker, the block buffers and the template flag): the projection, then the level
// 2 ln(o / ALPHA_MIN) in double (libm's log: scalar), then the box, in double as before.
template <typename S, bool antialiased>
__attribute__((noinline)) void project_forward_range(
    int64_t begin, int64_t end, const CamS<S>& cam, const Camera& c, const S* __restrict means,
    const S* __restrict covars, const S* __restrict opacities, S eps2d, S* __restrict means2d,
    S* __restrict conics, S* __restrict depths, S* __restrict opac_eff, int32_t* __restrict radii,
    int32_t* __restrict bbox) {
  constexpr int B = 128;
  alignas(64) S cov_in[6][B], opa[B], u_[B], v_[B], pd_[B], q_[B], rd_[B], det_[B], z_[B], o_[B];
  alignas(64) double level[B];
  alignas(64) int32_t ok[B];
  const double width = double(c.width), height = double(c.height);
  for (int64_t b0 = begin; b0 < end; b0 += B) {
    const int m = int(std::min<int64_t>(B, end - b0));
    for (int j = 0; j < m; ++j) {
      for (int k = 0; k < 6; ++k) cov_in[k][j] = covars[6 * (b0 + j) + k];
      opa[j] = opacities[b0 + j];
    }
#pragma GCC ivdep
    for (int j = 0; j < m; ++j) {
      const S cov[6] = {cov_in[0][j], cov_in[1][j], cov_in[2][j], cov_in[3][j], cov_in[4][j], cov_in[5][j]};
      Projected<S> P;
      const bool seen = project_math(cam, means + 3 * (b0 + j), cov, eps2d, antialiased, P);
      const S o = opa[j] * P.comp;
      // A Gaussian whose peak alpha is below ALPHA_MIN never touches a pixel.
      ok[j] = seen & (o >= S(ALPHA_MIN));
      u_[j] = P.u; v_[j] = P.v; z_[j] = P.p[2]; o_[j] = o; det_[j] = P.det1;
      pd_[j] = P.cov2d[0] + eps2d; q_[j] = P.cov2d[1]; rd_[j] = P.cov2d[2] + eps2d;
    }
    for (int j = 0; j < m; ++j)
      level[j] = ok[j] ? 2.0 * std::log(double(o_[j]) / double(ALPHA_MIN)) : 0.0;
#pragma GCC ivdep
    for (int j = 0; j < m; ++j) {
      const int64_t i = b0 + j;
      // Exact bounding box of the ellipse where o * exp(-d^2/2) >= ALPHA_MIN.
      const double rx = std::min(MAX_EXTENT, std::sqrt(std::max(0.0, level[j] * double(pd_[j]))));
      const double ry = std::min(MAX_EXTENT, std::sqrt(std::max(0.0, level[j] * double(rd_[j]))));
      const double u = std::clamp(double(u_[j]), -1e9, 1e9), v = std::clamp(double(v_[j]), -1e9, 1e9);
      const double x0 = std::max(0.0, std::floor(u - rx)), x1 = std::min(width, std::ceil(u + rx));
      const double y0 = std::max(0.0, std::floor(v - ry)), y1 = std::min(height, std::ceil(v + ry));
      const bool vis = (ok[j] != 0) & (x0 < x1) & (y0 < y1);
      // (Selected before the conversion: an invisible lane may hold NaN, and converting NaN
      // to an integer is undefined.)
      bbox[4 * i + 0] = int32_t(vis ? x0 : 0.0);
      bbox[4 * i + 1] = int32_t(vis ? y0 : 0.0);
      bbox[4 * i + 2] = int32_t(vis ? x1 : 0.0);
      bbox[4 * i + 3] = int32_t(vis ? y1 : 0.0);
      radii[i] = int32_t(vis ? std::max(1.0, std::ceil(std::max(rx, ry))) : 0.0);
      means2d[2 * i] = vis ? u_[j] : S(0);
      means2d[2 * i + 1] = vis ? v_[j] : S(0);
      const S det = det_[j];
      conics[3 * i] = vis ? rd_[j] / det : S(0);
      conics[3 * i + 1] = vis ? -q_[j] / det : S(0);
      conics[3 * i + 2] = vis ? pd_[j] / det : S(0);
      depths[i] = vis ? z_[j] : S(0);
      opac_eff[i] = vis ? o_[j] : S(0);
    }
  }
}

template <typename S>
void project_forward(int64_t n, const S* means, const S* covars, const S* opacities,
                     const Camera& c, S eps2d, bool antialiased, S* means2d, S* conics,
                     S* depths, S* opac_eff, int32_t* radii, int32_t* bbox) {
  const CamS<S> cam(c);
  with_constant(antialiased, [&](auto aa) {
    per_thread_share(n, [&](int64_t begin, int64_t end) {
      project_forward_range<S, decltype(aa)::value>(begin, end, cam, c, means, covars, opacities,
                                                    eps2d, means2d, conics, depths, opac_eff,
                                                    radii, bbox);
    });
  });
}

// The backward over Gaussians [begin, end). A function of its own so that its pointers stay
// __restrict (OpenMP's outlined loop bodies lose the qualifier, and GCC then gave up on
// vectorising behind 57 run-time alias checks), and branch-free (selects instead of ifs),
// so that GCC runs it over a vector of Gaussians (anti-aliasing is a template parameter for
// the same reason: a select on a run-time flag stopped it).
template <typename S, bool antialiased>
__attribute__((noinline)) void project_backward_range(
    int64_t begin, int64_t end, const CamS<S>& cam, const S* __restrict means,
    const S* __restrict covars, const S* __restrict opacities, S eps2d,
    const int32_t* __restrict radii, const S* __restrict g_means2d, const S* __restrict g_conics,
    const S* __restrict g_depths, const S* __restrict g_opac_eff, S* __restrict g_means,
    S* __restrict g_covars, S* __restrict g_opacities) {
  const auto& R = cam.R;
  // The per-Gaussian inputs pass through component-major buffers on the stack, a block at a
  // time: GCC does not vectorise a stride of 6 at all, and it moves reads under the
  // visibility select, which then need masked loads (none for strided data, none at all on
  // AVX2 here); a read from a local buffer cannot fault, so it needs no mask.
  constexpr int B = 128;
  alignas(64) S cov_in[6][B], cov_out[6][B], g2d[2][B], gcon[3][B], opa[B], gop[B], gdep[B];
  alignas(64) int32_t rad[B];
  for (int64_t b0 = begin; b0 < end; b0 += B) {
    const int m = int(std::min<int64_t>(B, end - b0));
    for (int j = 0; j < m; ++j) {
      const int64_t i = b0 + j;
      for (int k = 0; k < 6; ++k) cov_in[k][j] = covars[6 * i + k];
      for (int k = 0; k < 3; ++k) gcon[k][j] = g_conics[3 * i + k];
      for (int k = 0; k < 2; ++k) g2d[k][j] = g_means2d[2 * i + k];
      opa[j] = opacities[i];
      gop[j] = g_opac_eff[i];
      gdep[j] = g_depths[i];
      rad[j] = radii[i];
    }
#pragma GCC ivdep  // Gaussians are independent: no run-time alias checks
    for (int j = 0; j < m; ++j) {
      const int64_t i = b0 + j;
      const S cov[6] = {cov_in[0][j], cov_in[1][j], cov_in[2][j], cov_in[3][j], cov_in[4][j], cov_in[5][j]};
      Projected<S> P;
      const bool vis = project_math(cam, means + 3 * i, cov, eps2d, antialiased, P) & (rad[j] > 0);
      const S o = opa[j];
      const S go = gop[j];
      const S ga = gcon[0][j], gb = gcon[1][j], gc = gcon[2][j];
      const S gu = g2d[0][j], gv = g2d[1][j];
      const S gz = gdep[j];
      g_opacities[i] = vis ? go * P.comp : S(0);
      const S g_comp = go * o;

      // conic = inverse(cov2d + eps2d * I), written out per scalar (q appears twice).
      const S pd = P.cov2d[0] + eps2d, q = P.cov2d[1], rd = P.cov2d[2] + eps2d;
      const S det = P.det1, id2 = S(1) / (det * det);
      S gp = (-ga * rd * rd + gb * q * rd - gc * q * q) * id2;
      S gq = (S(2) * ga * q * rd - gb * (pd * rd + q * q) + S(2) * gc * pd * q) * id2;
      S gr = (-ga * q * q + gb * q * pd - gc * pd * pd) * id2;
      {
        const bool aa = antialiased & (P.det0 > S(0));
        const S k = g_comp * P.comp * S(0.5);
        const S p0 = P.cov2d[0], r0 = P.cov2d[2];
        gp = aa ? gp + k * (r0 / P.det0 - rd / P.det1) : gp;
        gq = aa ? gq + k * (-S(2) * q / P.det0 + S(2) * q / P.det1) : gq;
        gr = aa ? gr + k * (p0 / P.det0 - pd / P.det1) : gr;
      }
      // cov2d = J sc J^T with the symmetric matrix gradient G2.
      const S G2[4] = {gp, gq * S(0.5), gq * S(0.5), gr};
      const S (&J)[6] = P.J;
      S G2J[6];  // G2 (2x2) @ J (2x3)
      for (int r = 0; r < 2; ++r)
        for (int k = 0; k < 3; ++k) G2J[3 * r + k] = G2[2 * r] * J[k] + G2[2 * r + 1] * J[3 + k];
      S gsc[9];  // J^T G2 J
      for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k) gsc[3 * r + k] = J[r] * G2J[k] + J[3 + r] * G2J[3 + k];
      S gJ[6];  // 2 G2 J sc
      for (int r = 0; r < 2; ++r)
        for (int k = 0; k < 3; ++k)
          gJ[3 * r + k] = S(2) * (G2J[3 * r] * P.sc[k] + G2J[3 * r + 1] * P.sc[3 + k] +
                                  G2J[3 * r + 2] * P.sc[6 + k]);

      const S x = P.p[0], y = P.p[1], z = P.p[2], iz = S(1) / z, iz2 = iz * iz;
      S gpc[3] = {0, 0, 0};
      // J00 = fx/z, J11 = fy/z, J02 = -fx txz / z, J12 = -fy tyz / z.
      gpc[2] += -gJ[0] * cam.fx * iz2 - gJ[4] * cam.fy * iz2;
      gpc[0] += P.clamp_x ? S(0) : -gJ[2] * cam.fx * iz2;
      gpc[2] += P.clamp_x ? gJ[2] * cam.fx * P.txz * iz2 : gJ[2] * S(2) * cam.fx * x * iz2 * iz;
      gpc[1] += P.clamp_y ? S(0) : -gJ[5] * cam.fy * iz2;
      gpc[2] += P.clamp_y ? gJ[5] * cam.fy * P.tyz * iz2 : gJ[5] * S(2) * cam.fy * y * iz2 * iz;
      // means2d = (fx x/z + cx, fy y/z + cy)
      gpc[0] += gu * cam.fx * iz;
      gpc[1] += gv * cam.fy * iz;
      gpc[2] += -(gu * cam.fx * x + gv * cam.fy * y) * iz2;
      gpc[2] += gz;
      // p = R m + t
      for (int k = 0; k < 3; ++k)
        g_means[3 * i + k] = vis ? R(0, k) * gpc[0] + R(1, k) * gpc[1] + R(2, k) * gpc[2] : S(0);
      // sc = R sw R^T  ->  gsw = R^T gsc R
      S tmp[9], gsw[9];
      for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k)
          tmp[3 * r + k] = R(0, r) * gsc[k] + R(1, r) * gsc[3 + k] + R(2, r) * gsc[6 + k];
      for (int r = 0; r < 3; ++r)
        for (int k = 0; k < 3; ++k)
          gsw[3 * r + k] = tmp[3 * r] * R(0, k) + tmp[3 * r + 1] * R(1, k) + tmp[3 * r + 2] * R(2, k);
      cov_out[0][j] = vis ? gsw[0] : S(0);
      cov_out[1][j] = vis ? gsw[1] + gsw[3] : S(0);
      cov_out[2][j] = vis ? gsw[2] + gsw[6] : S(0);
      cov_out[3][j] = vis ? gsw[4] : S(0);
      cov_out[4][j] = vis ? gsw[5] + gsw[7] : S(0);
      cov_out[5][j] = vis ? gsw[8] : S(0);
    }
    for (int j = 0; j < m; ++j)
      for (int k = 0; k < 6; ++k) g_covars[6 * (b0 + j) + k] = cov_out[k][j];
  }
}

template <typename S>
void project_backward(int64_t n, const S* means, const S* covars, const S* opacities,
                      const Camera& c, S eps2d, bool antialiased, const int32_t* radii,
                      const S* g_means2d, const S* g_conics, const S* g_depths,
                      const S* g_opac_eff, S* g_means, S* g_covars, S* g_opacities) {
  const CamS<S> cam(c);
  with_constant(antialiased, [&](auto aa) {
    per_thread_share(n, [&](int64_t begin, int64_t end) {
      project_backward_range<S, decltype(aa)::value>(begin, end, cam, means, covars, opacities,
                                                     eps2d, radii, g_means2d, g_conics, g_depths,
                                                     g_opac_eff, g_means, g_covars, g_opacities);
    });
  });
}

// ---------------------------------------------------------------- motion-blur footprint
// The opacity factor that keeps a blurred splat's 2D mass (render/blur.py, whose PyTorch
// expression is the reference): sqrt(1 - s2^T Sigma2^-1 s2 / 12) with Sigma2 the screen-space
// blurred covariance (+ eps2d) and s2 the projected sweep, both through M = J R at the clamped
// direction, as in project_math. The factor hardly depends on the mean (s2 and Sigma2 scale
// together with depth), so M is held constant: gradients go to the covariance and the sweep.

namespace {

template <typename S>
struct BlurTerms {
  S m0[3], m1[3];     // rows of M
  S a, b, c, u, v;    // Sigma2 (with eps2d) and s2
  S det, q, inside;   // det Sigma2, s2^T Sigma2^-1 s2, 1 - q / 12
};

template <typename S>
inline void blur_terms(const CamS<S>& cam, const S* mean, const S* cov, const S* sweep, S eps2d,
                       BlurTerms<S>& B) {
  const auto& R = cam.R;
  S p[3];
  for (int r = 0; r < 3; ++r)
    p[r] = R(r, 0) * mean[0] + R(r, 1) * mean[1] + R(r, 2) * mean[2] + cam.t[r];
  const bool in_depth = (p[2] >= cam.near_plane) & (p[2] <= cam.far_plane);
  const S z = in_depth ? p[2] : S(1);
  const S txz = std::min(cam.lim_x_pos, std::max(-cam.lim_x_neg, p[0] / z));
  const S tyz = std::min(cam.lim_y_pos, std::max(-cam.lim_y_neg, p[1] / z));
  const S iz = S(1) / z;
  for (int k = 0; k < 3; ++k) {
    B.m0[k] = cam.fx * iz * (R(0, k) - txz * R(2, k));
    B.m1[k] = cam.fy * iz * (R(1, k) - tyz * R(2, k));
  }
  S sw[9];
  unpack_cov(cov, sw);
  S s0[3], s1[3];  // Sigma m0, Sigma m1
  for (int r = 0; r < 3; ++r) {
    s0[r] = sw[3 * r] * B.m0[0] + sw[3 * r + 1] * B.m0[1] + sw[3 * r + 2] * B.m0[2];
    s1[r] = sw[3 * r] * B.m1[0] + sw[3 * r + 1] * B.m1[1] + sw[3 * r + 2] * B.m1[2];
  }
  B.a = B.m0[0] * s0[0] + B.m0[1] * s0[1] + B.m0[2] * s0[2] + eps2d;
  B.b = B.m0[0] * s1[0] + B.m0[1] * s1[1] + B.m0[2] * s1[2];
  B.c = B.m1[0] * s1[0] + B.m1[1] * s1[1] + B.m1[2] * s1[2] + eps2d;
  B.u = B.m0[0] * sweep[0] + B.m0[1] * sweep[1] + B.m0[2] * sweep[2];
  B.v = B.m1[0] * sweep[0] + B.m1[1] * sweep[1] + B.m1[2] * sweep[2];
  B.det = std::max(B.a * B.c - B.b * B.b, S(1e-20));
  B.q = (B.c * B.u * B.u - S(2) * B.b * B.u * B.v + B.a * B.v * B.v) / B.det;
  B.inside = S(1) - B.q / S(12);
}

constexpr double BLUR_INSIDE_MIN = 1e-6;  // q / 12 < 1 exactly; this absorbs rounding

}  // namespace

template <typename S>
void blur_scale_forward(int64_t n, const S* means, const S* covars, const S* sweeps, const Camera& c,
                        S eps2d, S* scale) {
  const CamS<S> cam(c);
  per_thread_share(n, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      BlurTerms<S> B;
      blur_terms(cam, means + 3 * i, covars + 6 * i, sweeps + 3 * i, eps2d, B);
      scale[i] = std::sqrt(std::max(B.inside, S(BLUR_INSIDE_MIN)));
    }
  });
}

template <typename S>
void blur_scale_backward(int64_t n, const S* means, const S* covars, const S* sweeps, const Camera& c,
                         S eps2d, const S* g_scale, S* g_covars, S* g_sweeps) {
  const CamS<S> cam(c);
  // Packed entries xx, xy, xz, yy, yz, zz as (row, column).
  constexpr int I[6] = {0, 0, 0, 1, 1, 2}, J[6] = {0, 1, 2, 1, 2, 2};
  per_thread_share(n, [&](int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) {
      BlurTerms<S> B;
      blur_terms(cam, means + 3 * i, covars + 6 * i, sweeps + 3 * i, eps2d, B);
      const bool live = B.inside > S(BLUR_INSIDE_MIN);
      const S scale = std::sqrt(std::max(B.inside, S(BLUR_INSIDE_MIN)));
      const S gd = live ? -g_scale[i] / (S(24) * scale * B.det) : S(0);  // dL/dq / det
      const S ga = (B.v * B.v - B.q * B.c) * gd, gc = (B.u * B.u - B.q * B.a) * gd;
      const S gb = S(2) * (B.q * B.b - B.u * B.v) * gd;
      const S gu = S(2) * (B.c * B.u - B.b * B.v) * gd, gv = S(2) * (B.a * B.v - B.b * B.u) * gd;
      for (int k = 0; k < 6; ++k) {
        const int r = I[k], q = J[k];
        // x^T Sigma y over a packed entry: (x_r y_q + x_q y_r), halved on the diagonal.
        const S w = r == q ? S(0.5) : S(1);
        g_covars[6 * i + k] = w * (ga * S(2) * B.m0[r] * B.m0[q] + gc * S(2) * B.m1[r] * B.m1[q] +
                                   gb * (B.m0[r] * B.m1[q] + B.m0[q] * B.m1[r]));
      }
      for (int k = 0; k < 3; ++k) g_sweeps[3 * i + k] = gu * B.m0[k] + gv * B.m1[k];
    }
  });
}

#define KGS_INSTANTIATE(S)                                                                  \
  template void blur_scale_forward<S>(int64_t, const S*, const S*, const S*, const Camera&,  \
                                      S, S*);                                                \
  template void blur_scale_backward<S>(int64_t, const S*, const S*, const S*, const Camera&, \
                                       S, const S*, S*, S*);                                 \
  template void project_forward<S>(int64_t, const S*, const S*, const S*, const Camera&, S, \
                                   bool, S*, S*, S*, S*, int32_t*, int32_t*);               \
  template void project_backward<S>(int64_t, const S*, const S*, const S*, const Camera&,   \
                                    S, bool, const int32_t*, const S*, const S*, const S*,  \
                                    const S*, S*, S*, S*);
KGS_INSTANTIATE(float)
KGS_INSTANTIATE(double)
#undef KGS_INSTANTIATE

}  // namespace kgs
