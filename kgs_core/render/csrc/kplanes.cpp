// K-Planes feature sampling for the deformation field, forward and backward.
//
// The PyTorch path (six grid_sample calls per resolution, their products and the backward of
// each) was ~12 ms of a 66 ms training step on the panel scene and more for the D3DGS-like
// baseline; grid_sample's backward alone was 7 ms. Here one pass per resolution samples all
// six planes of a row with the channel vector contiguous ((H, W, F) layout), so a corner is a
// vector load and a product of planes is elementwise.
//
// Conventions (those of the PyTorch path, kgs_core/model/deformation.py): plane k of a
// resolution pairs the coordinates (0,1) (0,2) (0,3) (1,2) (1,3) (2,3) of (x, y, z, t); the
// first coordinate of a pair indexes the width, the second the height; bilinear,
// align_corners=True, border padding (coordinates arrive clamped to [-1, 1]). Spatial planes
// (no t) are sampled at the N points, time planes at each of the M N rows (row j = m N + n).
#include "kernels.h"

#include <omp.h>

#include <algorithm>
#include <type_traits>
#include <vector>

namespace kgs {
namespace {

constexpr int kPairs[6][2] = {{0, 1}, {0, 2}, {0, 3}, {1, 2}, {1, 3}, {2, 3}};

struct Tap {  // the four corners of a bilinear sample, and its weights
  int64_t i00, i10, i01, i11;  // offsets of the corners' channel vectors
  float fx, fy;
};

inline Tap tap(float u, float v, int64_t W, int64_t H, int64_t F) {
  float px = (u + 1.f) * 0.5f * float(W - 1);
  float py = (v + 1.f) * 0.5f * float(H - 1);
  px = std::min(std::max(px, 0.f), float(W - 1));
  py = std::min(std::max(py, 0.f), float(H - 1));
  const int64_t x0 = std::min<int64_t>(int64_t(px), W - 1), y0 = std::min<int64_t>(int64_t(py), H - 1);
  const int64_t x1 = std::min<int64_t>(x0 + 1, W - 1), y1 = std::min<int64_t>(y0 + 1, H - 1);
  return {(y0 * W + x0) * F, (y0 * W + x1) * F, (y1 * W + x0) * F, (y1 * W + x1) * F, px - float(x0), py - float(y0)};
}

// Plane k's tap for the point with coordinates xyz (3) at normalised time tj.
inline Tap tap_of(const float* xyz, float tj, int k, const KPlanes& p) {
  const float c[4] = {xyz[0], xyz[1], xyz[2], tj};
  return tap(c[kPairs[k][0]], c[kPairs[k][1]], p.W[k], p.H[k], p.F);
}

inline void sample(const float* g, const Tap& q, int64_t F, float* out) {
  const float w00 = (1 - q.fx) * (1 - q.fy), w10 = q.fx * (1 - q.fy), w01 = (1 - q.fx) * q.fy, w11 = q.fx * q.fy;
#pragma omp simd
  for (int64_t f = 0; f < F; ++f) out[f] = w00 * g[q.i00 + f] + w10 * g[q.i10 + f] + w01 * g[q.i01 + f] + w11 * g[q.i11 + f];
}

constexpr int64_t kMaxChannels = 256;  // per-row buffers live on the stack

// Calls run(std::integral_constant<int, FC>) with FC the channel count F when it is one the
// presets use (16: fast, 32: paper), 0 for any other F. With FC known every per-channel loop
// is a fixed run of vector operations; with a runtime count GCC kept them as loops with
// remainders (backward ~2x slower at the fast preset's size).
template <typename Run>
void with_channel_count(int64_t F, Run&& run) {
  switch (F) {
    case 16: run(std::integral_constant<int, 16>{}); break;
    case 32: run(std::integral_constant<int, 32>{}); break;
    default: run(std::integral_constant<int, 0>{});
  }
}

// FC: the channel count when known at compile time, 0 otherwise (with_channel_count).
template <int FC>
void forward_rows(int64_t N, int64_t rows, const float* x, const float* t, const KPlanes& p, float* out,
                  int64_t out_stride) {
  const int64_t F = FC > 0 ? FC : p.F;
#pragma omp parallel for schedule(static)
  for (int64_t j = 0; j < rows; ++j) {
    alignas(64) float acc[kMaxChannels], s[kMaxChannels];
    const float* xyz = x + (j % N) * 3;
    sample(p.data[0], tap_of(xyz, t[j], 0, p), F, acc);
    for (int k = 1; k < 6; ++k) {
      sample(p.data[k], tap_of(xyz, t[j], k, p), F, s);
#pragma omp simd
      for (int64_t f = 0; f < F; ++f) acc[f] *= s[f];
    }
    float* o = out + j * out_stride;
#pragma omp simd
    for (int64_t f = 0; f < F; ++f) o[f] = acc[f];
  }
}

// Rows j0 .. j1 of the backward, plane gradients into acc[k] (FC as in forward_rows).
template <int FC>
void backward_rows(int64_t j0, int64_t j1, int64_t N, const float* x, const float* t, const KPlanes& p,
                   const float* g_out, int64_t g_stride, float* const* acc, float* gr) {
  const int64_t F = FC > 0 ? FC : p.F;
  for (int64_t j = j0; j < j1; ++j) {
    alignas(64) float s[6][kMaxChannels], pre[kMaxChannels], gk[kMaxChannels];
    Tap q[6];
    const float* xyz = x + (j % N) * 3;
    for (int k = 0; k < 6; ++k) {
      q[k] = tap_of(xyz, t[j], k, p);
      sample(p.data[k], q[k], F, s[k]);
    }
    const float* go = g_out + j * g_stride;
    for (int64_t f = 0; f < F; ++f) pre[f] = go[f];
    for (int k = 0; k < 6; ++k) {
      // gradient of sample k: g_out * (product of the samples before k) * (those after k)
#pragma omp simd
      for (int64_t f = 0; f < F; ++f) gk[f] = pre[f];
      for (int k2 = k + 1; k2 < 6; ++k2)
#pragma omp simd
        for (int64_t f = 0; f < F; ++f) gk[f] *= s[k2][f];
#pragma omp simd
      for (int64_t f = 0; f < F; ++f) pre[f] *= s[k][f];
      const Tap& c = q[k];
      const float w00 = (1 - c.fx) * (1 - c.fy), w10 = c.fx * (1 - c.fy), w01 = (1 - c.fx) * c.fy, w11 = c.fx * c.fy;
      const float* g = p.data[k];
      float* a = acc[k];
      // Corners coincide at the border (x1 == x0): the four updates run one after another.
#pragma omp simd
      for (int64_t f = 0; f < F; ++f) a[c.i00 + f] += w00 * gk[f];
#pragma omp simd
      for (int64_t f = 0; f < F; ++f) a[c.i10 + f] += w10 * gk[f];
#pragma omp simd
      for (int64_t f = 0; f < F; ++f) a[c.i01 + f] += w01 * gk[f];
#pragma omp simd
      for (int64_t f = 0; f < F; ++f) a[c.i11 + f] += w11 * gk[f];
      if (gr == nullptr) continue;
      float du = 0.f, dv = 0.f;
#pragma omp simd reduction(+ : du, dv)
      for (int64_t f = 0; f < F; ++f) {
        const float g00 = g[c.i00 + f], g10 = g[c.i10 + f], g01 = g[c.i01 + f], g11 = g[c.i11 + f];
        du += gk[f] * ((1 - c.fy) * (g10 - g00) + c.fy * (g11 - g01));
        dv += gk[f] * ((1 - c.fx) * (g01 - g00) + c.fx * (g11 - g10));
      }
      // d pixel / d coordinate = (size - 1) / 2 (align_corners); a pair's first axis is spatial.
      gr[j * 3 + kPairs[k][0]] += du * 0.5f * float(p.W[k] - 1);
      if (kPairs[k][1] != 3) gr[j * 3 + kPairs[k][1]] += dv * 0.5f * float(p.H[k] - 1);
    }
  }
}

}  // namespace

void kplanes_forward(int64_t N, int64_t rows, const float* x, const float* t, const KPlanes& p, float* out,
                     int64_t out_stride) {
  with_channel_count(p.F, [&](auto fc) { forward_rows<decltype(fc)::value>(N, rows, x, t, p, out, out_stride); });
}

// One pass over the rows, split between the threads. Thread 0 accumulates the plane gradients
// in place, the others into private planes (kept across calls: no page faults) that are added
// in at the end; splitting channels instead puts two threads on one cache line (F = 16 is one
// line per corner).
void kplanes_backward(int64_t N, int64_t rows, const float* x, const float* t, const KPlanes& p, const float* g_out,
                      int64_t g_stride, float* g_x) {
  const int64_t F = p.F;
  int64_t offset[7] = {0};  // plane k's entries in a private copy: [offset[k], offset[k + 1])
  for (int k = 0; k < 6; ++k) offset[k + 1] = offset[k] + p.H[k] * p.W[k] * F;
  thread_local std::vector<float> row_grad;  // (rows, 3): each row written by one thread
  if (g_x != nullptr) row_grad.assign(size_t(rows) * 3, 0.f);
  float* gr = g_x != nullptr ? row_grad.data() : nullptr;
  std::vector<float*> copies(omp_get_max_threads(), nullptr);
#pragma omp parallel
  {
    const int nt = omp_get_num_threads(), tid = omp_get_thread_num();
    thread_local std::vector<float> own;
    float* acc[6];
    if (tid == 0) {
      for (int k = 0; k < 6; ++k) acc[k] = p.grad[k];
    } else {
      own.assign(size_t(offset[6]), 0.f);
      copies[tid] = own.data();
      for (int k = 0; k < 6; ++k) acc[k] = own.data() + offset[k];
    }
    const int64_t j0 = rows * tid / nt, j1 = rows * (tid + 1) / nt;
    with_channel_count(F, [&](auto fc) {
      backward_rows<decltype(fc)::value>(j0, j1, N, x, t, p, g_out, g_stride, acc, gr);
    });
#pragma omp barrier
    // The private copies into the planes, entries split between the threads.
    for (int k = 0; k < 6; ++k) {
      const int64_t size = offset[k + 1] - offset[k];
      float* dst = p.grad[k];
#pragma omp for schedule(static)
      for (int64_t i = 0; i < size; ++i) {
        float sum = 0.f;
        for (int other = 1; other < nt; ++other) sum += copies[other][offset[k] + i];
        dst[i] += sum;
      }
    }
  }
  if (g_x == nullptr) return;
  // g_x[n] = the sum over the point's M rows.
  for (int64_t m = 0; m < rows / N; ++m)
#pragma omp simd
    for (int64_t i = 0; i < N * 3; ++i) g_x[i] += gr[m * N * 3 + i];
}

}  // namespace kgs
