// 16-lane SIMD vocabulary of the tile rasteriser: one tile row is one vector.
//
// Two implementations behind one interface, so that the kernels are written once:
//  * Simd<float> on AVX-512: __m512 (whose arithmetic operators GCC/Clang provide) with
//    __mmask16 predicate registers: compares, selects and "any lane" tests cost one
//    instruction each, where integer-vector masks cost two or three.
//  * Simd<float> on AVX2 + FMA without AVX-512 (AMD Zen 2/3, older Intel): a pair of __m256
//    with float-vector masks (all-ones lanes), written with intrinsics. GCC's lowering of
//    the 64-byte generic vectors to AVX2 spilled lanes to the stack and ran the mask tests
//    lane by lane: 2.2x slower kernels on a Zen 3 (docs/rasterizer.md).
//  * the generic one (double, and float without either): GCC/Clang vector extensions with
//    integer-vector masks. Double exists for gradcheck, not for speed.
#pragma once
#include <cmath>
#include <cstdint>
#include <cstring>
#include <type_traits>

#if defined(__AVX512F__) || (defined(__AVX2__) && defined(__FMA__))
#include <immintrin.h>
#endif

namespace kgs {

constexpr int LANES = 16;

// Whether a lane set X also offers half rows (X::Half: LANES / 2 lanes, and X's vectors
// expose them as .h[0], .h[1]). Only the AVX2 path does: there a half row is one register.
// (AVX-512VL half rows, 256-bit ops with mask registers, were measured on a Zen 4, whose
// 512-bit ops occupy a 256-bit pipe twice: no gain, docs/rasterizer.md.)
template <class X, class = void>
struct has_half_rows : std::false_type {};
template <class X>
struct has_half_rows<X, std::void_t<typename X::Half>> : std::true_type {};

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
  static V max(V a, V b) { return a > b ? a : b; }
  static V div(V a, V b) { return a / b; }
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
  static unsigned bits(M m) {  // lane i -> bit i
    unsigned b = 0;
    for (int i = 0; i < LANES; ++i) b |= unsigned(m[i] != 0) << i;
    return b;
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
  // 2^x for the rasteriser's x <= 0: exact libm per lane (the float paths below are fast).
  static V exp2(V x) {
    V out;
    for (int i = 0; i < LANES; ++i) out[i] = std::exp2(x[i]);
    return out;
  }
};

// 2^x on float lanes, shared by every float path (the kernels evaluate the Gaussians in
// base 2: their per-pair constants carry the factor log2(e)). 2^x = 2^k 2^f with k =
// round(x) and f = x - k in [-1/2, 1/2], exact; 2^f ~ 1 + c1 f + ... + c6 f^6 with Cephes
// exp2f's coefficients (~2e-7 relative). The polynomial runs in Estrin's form, three
// multiply-adds deep where Horner's is six: the tile kernels are bound by the latency of
// this chain, not by its operation count (docs/rasterizer.md). Inputs are
// clamped to [-60, 120]: 2^-60 ~ 9e-19 is far below any alpha threshold, and lanes outside a
// Gaussian's footprint stay out of denormal numbers, which cost ~100 cycles each. AVX-512
// clamps only from below (one step off the chain): vscalefps is defined for any
// k (2^k overflows to inf), and the kernels' power <= 0 test leaves such lanes out; the
// other paths assemble 2^k from exponent bits, which needs k <= 127.
constexpr float EXP2_LO = -60.0f, EXP2_HI = 120.0f;
constexpr float EXP2_C[7] = {1.0f, 6.931472028550421e-1f, 2.402264791363012e-1f, 5.550332471162809e-2f,
                             9.618437357674640e-3f, 1.339887440266574e-3f, 1.535336188319500e-4f};
constexpr float LOG2E = 1.44269504088896341f;

// 2^f for f in [-1/2, 1/2], Estrin's form, through the ISA's multiply-add `fma(a, b, c)`.
template <typename V, typename Fma>
inline V exp2_poly(V f, Fma fma) {
  const auto c = [](float v) { return V{} + v; };  // broadcast
  const V f2 = f * f, f4 = f2 * f2;
  const V lo = fma(f2, fma(c(EXP2_C[3]), f, c(EXP2_C[2])), fma(c(EXP2_C[1]), f, c(EXP2_C[0])));
  const V hi = fma(c(EXP2_C[6]), f2, fma(c(EXP2_C[5]), f, c(EXP2_C[4])));
  return fma(f4, hi, lo);
}

// Each x86 ISA's overloads for exp2_x86 (multiply-add as an explicit intrinsic: -std=c++17
// turns off FMA contraction).
#if defined(__AVX512F__)
inline __m512 fmadd(__m512 a, __m512 b, __m512 c) { return _mm512_fmadd_ps(a, b, c); }
inline __m512 vmin(__m512 a, __m512 b) { return _mm512_min_ps(a, b); }
inline __m512 vmax(__m512 a, __m512 b) { return _mm512_max_ps(a, b); }
// vrndscaleps for the nearest integer k and vscalefps for p(f) * 2^k replace the emulated
// rounding and the exponent-bit assembly (7 instructions fewer in the kernels' hottest line).
inline __m512 round_nearest(__m512 x) { return _mm512_roundscale_ps(x, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC); }
inline __m512 times_pow2(__m512 y, __m512 k) { return _mm512_scalef_ps(y, k); }
#elif defined(__AVX2__) && defined(__FMA__)
inline __m256 fmadd(__m256 a, __m256 b, __m256 c) { return _mm256_fmadd_ps(a, b, c); }
inline __m256 vmin(__m256 a, __m256 b) { return _mm256_min_ps(a, b); }
inline __m256 vmax(__m256 a, __m256 b) { return _mm256_max_ps(a, b); }
// vroundps, and the exponent bits of 2^k added as integers.
inline __m256 round_nearest(__m256 x) { return _mm256_round_ps(x, _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC); }
inline __m256 times_pow2(__m256 y, __m256 k) {
  const __m256i e = _mm256_slli_epi32(_mm256_cvtps_epi32(k), 23);
  return _mm256_castsi256_ps(_mm256_add_epi32(_mm256_castps_si256(y), e));
}
#endif

#if defined(__AVX512F__) || (defined(__AVX2__) && defined(__FMA__))
template <typename V>
inline V exp2_x86(V x) {
  const auto c = [](float f) { return V{} + f; };  // broadcast
#if defined(__AVX512F__)
  x = vmax(x, c(EXP2_LO));
#else
  x = vmin(vmax(x, c(EXP2_LO)), c(EXP2_HI));
#endif
  const V k = round_nearest(x);
  return times_pow2(exp2_poly(x - k, [](V a, V b, V d) { return fmadd(a, b, d); }), k);
}
#endif

// 2^x on 16 float lanes of generic vectors (GCC vector extensions), as above.
template <typename V, typename IV>
inline V exp2_generic(V x) {
  x = x < EXP2_LO ? V{} + EXP2_LO : x;
  x = x > EXP2_HI ? V{} + EXP2_HI : x;
  const V kt = x + 0.5f;
  V k = __builtin_convertvector(__builtin_convertvector(kt, IV), V);
  k = k > kt ? k - 1.0f : k;  // floor(x + 1/2)
  const V y = exp2_poly(x - k, [](V a, V b, V d) { return a * b + d; });
  const IV bits = (__builtin_convertvector(k, IV) + 127) << 23;
  return y * (V)bits;  // same-size vector cast = bit cast
}

template <typename S>
struct Simd : SimdGeneric<S> {};

#if defined(__AVX512F__)
constexpr const char* SIMD_FLOAT = "avx512";

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
  static V max(V a, V b) { return _mm512_max_ps(a, b); }
  static V div(V a, V b) { return _mm512_div_ps(a, b); }
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
  static unsigned bits(M m) { return unsigned(m); }
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
  static V exp2(V x) { return exp2_x86(x); }
};
#elif defined(__AVX2__) && defined(__FMA__)
constexpr const char* SIMD_FLOAT = "avx2";

// Eight float lanes, one __m256 (whose arithmetic operators GCC/Clang provide), with
// all-ones float lanes as masks. Half a tile row: the kernels run a pair whose box lies in
// one half of the tile on this instead of the whole row (raster.cpp).
struct Simd8 {
  using V = __m256;
  using M = __m256;
  using Idx = __m256i;

  static V set1(float x) { return _mm256_set1_ps(x); }
  static V zero() { return _mm256_setzero_ps(); }
  static V min(V a, V b) { return _mm256_min_ps(a, b); }
  static V max(V a, V b) { return _mm256_max_ps(a, b); }
  static V div(V a, V b) { return _mm256_div_ps(a, b); }
  static M all() { return _mm256_castsi256_ps(_mm256_set1_epi32(-1)); }
  static M none() { return zero(); }
  static M lt(V a, V b) { return _mm256_cmp_ps(a, b, _CMP_LT_OQ); }
  static M le(V a, V b) { return _mm256_cmp_ps(a, b, _CMP_LE_OQ); }
  static M ge(V a, V b) { return _mm256_cmp_ps(a, b, _CMP_GE_OQ); }
  static M ilt(Idx a, Idx b) { return _mm256_castsi256_ps(_mm256_cmpgt_epi32(b, a)); }
  static M mand(M a, M b) { return _mm256_and_ps(a, b); }
  static M mor(M a, M b) { return _mm256_or_ps(a, b); }
  static M mandnot(M a, M b) { return _mm256_andnot_ps(b, a); }  // a and not b
  static M mnot(M a) { return mandnot(all(), a); }
  static unsigned bits(M m) { return unsigned(_mm256_movemask_ps(m)); }
  static bool any(M m) { return !_mm256_testz_ps(m, m); }
  static int count(M m) { return __builtin_popcount(unsigned(bits(m))); }
  static M lanes_in(int lo, int hi) {  // lanes lo <= i < hi
    const __m256i i = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
    return _mm256_castsi256_ps(_mm256_and_si256(_mm256_cmpgt_epi32(i, _mm256_set1_epi32(lo - 1)),
                                                _mm256_cmpgt_epi32(_mm256_set1_epi32(hi), i)));
  }
  static V select(M m, V a, V b) { return _mm256_blendv_ps(b, a, m); }
  static V keep(M m, V a) { return _mm256_and_ps(m, a); }  // a where m, else 0
  static Idx iset1(int x) { return _mm256_set1_epi32(x); }
  static Idx iselect(M m, Idx a, Idx b) {
    return _mm256_castps_si256(select(m, _mm256_castsi256_ps(a), _mm256_castsi256_ps(b)));
  }
  static V abs(V a) { return _mm256_andnot_ps(_mm256_set1_ps(-0.0f), a); }
  // 12-bit reciprocal estimate + one Newton step (~2 ulp) for the backward's 1 / (1 - alpha),
  // whose argument alpha <= 0.99 keeps in [0.01, 1]; vdivps costs several times more.
  static V rcp(V a) {
    const V r = _mm256_rcp_ps(a);
    return _mm256_mul_ps(r, _mm256_fnmadd_ps(a, r, _mm256_set1_ps(2.0f)));
  }
  static float hsum(V a) {
    __m128 q = _mm_add_ps(_mm256_castps256_ps128(a), _mm256_extractf128_ps(a, 1));
    q = _mm_add_ps(q, _mm_movehl_ps(q, q));
    q = _mm_add_ss(q, _mm_movehdup_ps(q));
    return _mm_cvtss_f32(q);
  }
  static V exp2(V x) { return exp2_x86(x); }
};

// Sixteen float lanes (a tile row) as two halves; h[0] holds lanes 0-7.
struct F32x16 {
  __m256 h[2];
};
struct I32x16 {
  __m256i h[2];
};
inline F32x16 operator+(F32x16 a, F32x16 b) { return {a.h[0] + b.h[0], a.h[1] + b.h[1]}; }
inline F32x16 operator-(F32x16 a, F32x16 b) { return {a.h[0] - b.h[0], a.h[1] - b.h[1]}; }
inline F32x16 operator*(F32x16 a, F32x16 b) { return {a.h[0] * b.h[0], a.h[1] * b.h[1]}; }
inline F32x16& operator+=(F32x16& a, F32x16 b) { return a = a + b; }
inline F32x16& operator-=(F32x16& a, F32x16 b) { return a = a - b; }
inline F32x16& operator*=(F32x16& a, F32x16 b) { return a = a * b; }

template <>
struct Simd<float> {
  using V = F32x16;
  using M = F32x16;  // all-ones lanes are true
  using Idx = I32x16;
  using Half = Simd8;  // the lane set of half a row (raster.cpp runs small boxes on it)
  using H = Half;

  static V set1(float x) { return {H::set1(x), H::set1(x)}; }
  static V zero() { return {H::zero(), H::zero()}; }
  static V load(const float* p) { return {_mm256_loadu_ps(p), _mm256_loadu_ps(p + 8)}; }
  static void store(float* p, V v) {
    _mm256_storeu_ps(p, v.h[0]);
    _mm256_storeu_ps(p + 8, v.h[1]);
  }
  static V min(V a, V b) { return {H::min(a.h[0], b.h[0]), H::min(a.h[1], b.h[1])}; }
  static V max(V a, V b) { return {H::max(a.h[0], b.h[0]), H::max(a.h[1], b.h[1])}; }
  static V div(V a, V b) { return {H::div(a.h[0], b.h[0]), H::div(a.h[1], b.h[1])}; }
  static void istore(int32_t* p, Idx v) {
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(p), v.h[0]);
    _mm256_storeu_si256(reinterpret_cast<__m256i*>(p + 8), v.h[1]);
  }
  static Idx iload(const int32_t* p) {
    return {_mm256_loadu_si256(reinterpret_cast<const __m256i*>(p)),
            _mm256_loadu_si256(reinterpret_cast<const __m256i*>(p + 8))};
  }
  static M all() { return {H::all(), H::all()}; }
  static M none() { return zero(); }
  static M lt(V a, V b) { return {H::lt(a.h[0], b.h[0]), H::lt(a.h[1], b.h[1])}; }
  static M le(V a, V b) { return {H::le(a.h[0], b.h[0]), H::le(a.h[1], b.h[1])}; }
  static M ge(V a, V b) { return {H::ge(a.h[0], b.h[0]), H::ge(a.h[1], b.h[1])}; }
  static M ilt(Idx a, Idx b) { return {H::ilt(a.h[0], b.h[0]), H::ilt(a.h[1], b.h[1])}; }
  static M mand(M a, M b) { return {H::mand(a.h[0], b.h[0]), H::mand(a.h[1], b.h[1])}; }
  static M mor(M a, M b) { return {H::mor(a.h[0], b.h[0]), H::mor(a.h[1], b.h[1])}; }
  static M mandnot(M a, M b) { return {H::mandnot(a.h[0], b.h[0]), H::mandnot(a.h[1], b.h[1])}; }
  static M mnot(M a) { return {H::mnot(a.h[0]), H::mnot(a.h[1])}; }
  static bool any(M m) { return H::any(H::mor(m.h[0], m.h[1])); }
  static int count(M m) { return H::count(m.h[0]) + H::count(m.h[1]); }
  static unsigned bits(M m) { return H::bits(m.h[0]) | H::bits(m.h[1]) << 8; }
  static bool get(M m, int i) { return (H::bits(m.h[i >> 3]) >> (i & 7)) & 1; }
  static M lanes_in(int lo, int hi) { return {H::lanes_in(lo, hi), H::lanes_in(lo - 8, hi - 8)}; }
  static V select(M m, V a, V b) { return {H::select(m.h[0], a.h[0], b.h[0]), H::select(m.h[1], a.h[1], b.h[1])}; }
  static V keep(M m, V a) { return {H::keep(m.h[0], a.h[0]), H::keep(m.h[1], a.h[1])}; }
  static Idx iset1(int x) { return {H::iset1(x), H::iset1(x)}; }
  static Idx iselect(M m, Idx a, Idx b) {
    return {H::iselect(m.h[0], a.h[0], b.h[0]), H::iselect(m.h[1], a.h[1], b.h[1])};
  }
  static V abs(V a) { return {H::abs(a.h[0]), H::abs(a.h[1])}; }
  static V rcp(V a) { return {H::rcp(a.h[0]), H::rcp(a.h[1])}; }
  static float hsum(V a) { return H::hsum(a.h[0] + a.h[1]); }
  static V exp2(V x) { return {H::exp2(x.h[0]), H::exp2(x.h[1])}; }
};
#else
constexpr const char* SIMD_FLOAT = "generic";

template <>
struct Simd<float> : SimdGeneric<float> {
  static V exp2(V x) { return exp2_generic<V, M>(x); }
};
#endif

}  // namespace kgs
