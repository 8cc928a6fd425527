// 16-lane SIMD vocabulary of the tile rasteriser: one tile row is one vector.
//
// Two implementations behind one interface, so that the kernels are written once:
//  * Simd<float> on AVX-512: __m512 (whose arithmetic operators GCC/Clang provide) with
//    __mmask16 predicate registers: compares, selects and "any lane" tests cost one
//    instruction each, where integer-vector masks cost two or three.
//  * the generic one (double, and float without AVX-512): GCC/Clang vector extensions with
//    integer-vector masks. Double exists for gradcheck, not for speed.
#pragma once
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>

#if defined(__AVX512F__)
#include <immintrin.h>
#endif

namespace kgs {

constexpr int LANES = 16;

template <typename S>
struct SimdGeneric {
  using I = std::conditional_t<sizeof(S) == 4, int32_t, int64_t>;
  typedef S V __attribute__((vector_size(LANES * sizeof(S))));
  typedef I M __attribute__((vector_size(LANES * sizeof(S))));  // all-ones lanes are true
  using Idx = M;                                                 // per-lane integers

  static V set1(S x) { return V{} + x; }
  static V zero() { return V{}; }
  static V load(const S* p) {
    V v;
    std::memcpy(&v, p, sizeof(V));
    return v;
  }
  static void store(S* p, V v) { std::memcpy(p, &v, sizeof(V)); }
  static V min(V a, V b) { return a < b ? a : b; }
  static void istore(int32_t* p, Idx v) {
    for (int i = 0; i < LANES; ++i) p[i] = int32_t(v[i]);
  }
  static Idx iload(const int32_t* p) {
    Idx v;
    for (int i = 0; i < LANES; ++i) v[i] = I(p[i]);
    return v;
  }
  static M all() { return M{} - 1; }
  static M none() { return M{}; }
  static M lt(V a, V b) { return a < b; }
  static M le(V a, V b) { return a <= b; }
  static M ge(V a, V b) { return a >= b; }
  static M ilt(Idx a, Idx b) { return a < b; }
  static M mand(M a, M b) { return a & b; }
  static M mor(M a, M b) { return a | b; }
  static M mandnot(M a, M b) { return a & ~b; }  // a and not b
  static M mnot(M a) { return ~a; }
  static bool any(M m) {
    for (int i = 0; i < LANES; ++i)
      if (m[i]) return true;
    return false;
  }
  static int count(M m) {
    int n = 0;
    for (int i = 0; i < LANES; ++i) n += m[i] != 0;
    return n;
  }
  static bool get(M m, int i) { return m[i] != 0; }
  static M lanes_in(int lo, int hi) {  // lanes lo <= i < hi
    M m;
    for (int i = 0; i < LANES; ++i) m[i] = (i >= lo && i < hi) ? I(-1) : I(0);
    return m;
  }
  static V select(M m, V a, V b) { return m ? a : b; }
  static V keep(M m, V a) { return m ? a : V{}; }  // a where m, else 0
  static Idx iset1(int x) { return Idx{} + I(x); }
  static Idx iselect(M m, Idx a, Idx b) { return m ? a : b; }
  static V abs(V a) { return a < S(0) ? -a : a; }
  static V rcp(V a) { return S(1) / a; }
  static S hsum(V a) {
    S s = 0;
    for (int i = 0; i < LANES; ++i) s += a[i];
    return s;
  }
  // exp(x) for the rasteriser's x <= 0: exact libm per lane (the float path below is fast).
  static V exp(V x) {
    V out;
    for (int i = 0; i < LANES; ++i) out[i] = std::exp(x[i]);
    return out;
  }
};

// exp(x) for x <= 0 on 16 float lanes (Cephes expf polynomial, ~2 ulp). Inputs below -40
// give exp(-40) ~ 4e-18: far below any alpha threshold, and lanes outside a Gaussian's
// footprint stay out of denormal numbers, which cost ~100 cycles each.
template <typename V, typename IV>
inline V cephes_expf(V x) {
  x = x < -40.0f ? V{} - 40.0f : x;
  x = x > 80.0f ? V{} + 80.0f : x;
  const V kt = x * 1.44269504088896341f + 0.5f;
  V kf = __builtin_convertvector(__builtin_convertvector(kt, IV), V);
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
  const IV bits = (__builtin_convertvector(kf, IV) + 127) << 23;
  return y * (V)bits;  // same-size vector cast = bit cast
}

template <typename S>
struct Simd : SimdGeneric<S> {};

#if defined(__AVX512F__)
template <>
struct Simd<float> {
  using V = __m512;
  using M = __mmask16;
  using Idx = __m512i;
  typedef int32_t IV __attribute__((vector_size(64)));

  static V set1(float x) { return _mm512_set1_ps(x); }
  static V zero() { return _mm512_setzero_ps(); }
  static V load(const float* p) { return _mm512_loadu_ps(p); }
  static void store(float* p, V v) { _mm512_storeu_ps(p, v); }
  static V min(V a, V b) { return _mm512_min_ps(a, b); }
  static void istore(int32_t* p, Idx v) { _mm512_storeu_si512(p, v); }
  static Idx iload(const int32_t* p) { return _mm512_loadu_si512(p); }
  static M all() { return M(0xFFFF); }
  static M none() { return M(0); }
  static M lt(V a, V b) { return _mm512_cmp_ps_mask(a, b, _CMP_LT_OQ); }
  static M le(V a, V b) { return _mm512_cmp_ps_mask(a, b, _CMP_LE_OQ); }
  static M ge(V a, V b) { return _mm512_cmp_ps_mask(a, b, _CMP_GE_OQ); }
  static M ilt(Idx a, Idx b) { return _mm512_cmplt_epi32_mask(a, b); }
  static M mand(M a, M b) { return M(a & b); }
  static M mor(M a, M b) { return M(a | b); }
  static M mandnot(M a, M b) { return M(a & ~b); }
  static M mnot(M a) { return M(~a); }
  static bool any(M m) { return m != 0; }
  static int count(M m) { return __builtin_popcount(unsigned(m)); }
  static bool get(M m, int i) { return (m >> i) & 1; }
  static M lanes_in(int lo, int hi) {
    return hi <= lo ? M(0) : M(((1u << hi) - 1u) & ~((1u << lo) - 1u));
  }
  static V select(M m, V a, V b) { return _mm512_mask_blend_ps(m, b, a); }
  static V keep(M m, V a) { return _mm512_maskz_mov_ps(m, a); }
  static Idx iset1(int x) { return _mm512_set1_epi32(x); }
  static Idx iselect(M m, Idx a, Idx b) { return _mm512_mask_blend_epi32(m, b, a); }
  static V abs(V a) { return _mm512_abs_ps(a); }
  // 14-bit reciprocal estimate + one Newton step: ~1 ulp for the 1 / (1 - alpha) of the
  // backward, where alpha <= 0.99 keeps the argument in [0.01, 1]; vdivps costs ~10x more.
  static V rcp(V a) {
    const V r = _mm512_rcp14_ps(a);
    return r * (2.0f - a * r);
  }
  static float hsum(V a) { return _mm512_reduce_add_ps(a); }
  // The same polynomial as cephes_expf, with AVX-512's rounding and exponent instructions:
  // vrndscaleps for the nearest integer k and vscalefps for p(r) * 2^k replace the emulated
  // floor and the bit assembly (7 instructions fewer in the kernels' hottest line).
  static V exp(V x) {
    x = _mm512_min_ps(_mm512_max_ps(x, set1(-40.0f)), set1(80.0f));
    const V k = _mm512_roundscale_ps(x * set1(1.44269504088896341f),
                                     _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
    V r = _mm512_fnmadd_ps(k, set1(0.693359375f), x);
    r = _mm512_fnmadd_ps(k, set1(-2.12194440e-4f), r);
    V y = set1(1.9875691500e-4f);
    y = _mm512_fmadd_ps(y, r, set1(1.3981999507e-3f));
    y = _mm512_fmadd_ps(y, r, set1(8.3334519073e-3f));
    y = _mm512_fmadd_ps(y, r, set1(4.1665795894e-2f));
    y = _mm512_fmadd_ps(y, r, set1(1.6666665459e-1f));
    y = _mm512_fmadd_ps(y, r, set1(5.0000001201e-1f));
    y = _mm512_fmadd_ps(y, r * r, r + set1(1.0f));
    return _mm512_scalef_ps(y, k);
  }
};
#else
template <>
struct Simd<float> : SimdGeneric<float> {
  static V exp(V x) { return cephes_expf<V, M>(x); }
};
#endif

}  // namespace kgs
