// The OpenVINO extension's portable SIMD layer (common.hpp includes it; it includes no OpenVINO
// header, so tests/inference/ovext_simd_check.cpp checks it alone on each ISA against plain loops).
#pragma once

#include <algorithm>
#include <cstdint>
#include <cstring>
#include <utility>
#include <vector>

namespace denoiser {

// The kernels' vector code is written once, on the GCC/Clang vector extensions (no intrinsics):
// a Strip is S floats, S the lanes of the widest vector register the build's target has
// (-march=native: 16 with AVX-512, 8 with AVX2 or AVX, else 4: SSE2, NEON), so each Strip
// operation is one instruction on every ISA (a Strip wider than the registers would be kept in
// memory and its selects expanded lane by lane). Used where the compilers' own vectorisation
// leaves loops scalar: a strip's taps, the level-0 head's product, the transposes, the warp's
// sampling and gathers. Results do not depend on S (each pixel is computed alone).
#if defined(__AVX512F__)
constexpr int64_t S = 16;
#elif defined(__AVX__)
constexpr int64_t S = 8;
#else
constexpr int64_t S = 4;
#endif

#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic ignored "-Wpsabi"  // a Strip's argument passing differs between ISAs; none leaves the library
#endif
typedef float Strip __attribute__((vector_size(S * sizeof(float))));
typedef int32_t IntStrip __attribute__((vector_size(S * sizeof(int32_t))));
static inline Strip load_strip(const float* p) {
    Strip v;
    std::memcpy(&v, p, sizeof(v));
    return v;
}
static inline void store_strip(float* p, Strip v) { std::memcpy(p, &v, sizeof(v)); }
static inline IntStrip load_int_strip(const int32_t* p) {
    IntStrip v;
    std::memcpy(&v, p, sizeof(v));
    return v;
}
static inline void store_int_strip(int32_t* p, IntStrip v) { std::memcpy(p, &v, sizeof(v)); }

// The first n < S floats of p, the other lanes 0 (and their store): a row's last, partial strip.
static inline Strip load_part(const float* p, int64_t n) {
    float t[S] = {};
    std::memcpy(t, p, static_cast<size_t>(n) * sizeof(float));
    return load_strip(t);
}
static inline void store_part(float* p, Strip v, int64_t n) {
    float t[S];
    store_strip(t, v);
    std::memcpy(p, t, static_cast<size_t>(n) * sizeof(float));
}

// std::max and std::min per lane (a < b ? b : a and b < a ? b : a: a NaN in b gives a), and
// std::sqrt per lane (a loop the compilers make one square-root instruction of)
static inline Strip max_strip(Strip a, Strip b) { return a < b ? b : a; }
static inline Strip min_strip(Strip a, Strip b) { return b < a ? b : a; }
static inline Strip sqrt_strip(Strip v) {
    Strip r;
    for (int64_t l = 0; l < S; ++l) r[l] = __builtin_sqrtf(v[l]);
    return r;
}

// n floats each broadcast to a Strip (the weights of a product over strips: the multiply-add then
// reads its weight as a vector, where a weight broadcast in the loop costs an instruction of its own)
static inline std::vector<Strip> broadcast_strips(const float* w, int64_t n) {
    std::vector<Strip> out(static_cast<size_t>(n));
    for (int64_t i = 0; i < n; ++i) out[i] = Strip{} + w[i];
    return out;
}

// 0, 1, ..., S - 1
static inline Strip lane_index() {
    Strip v;
    for (int64_t l = 0; l < S; ++l) v[l] = static_cast<float>(l);
    return v;
}

// floor per lane, as std::floor, for |x| < 2^31 (the caller bounds x): t = trunc(x) through int32
// (exact there: integers above 2^23 too), minus 1 where that rounded up. -0 gives +0; NaN and
// |x| >= 2^31 are not handled (four instructions where the general floor takes ten).
static inline Strip floor_strip(Strip x) {
    const Strip t = __builtin_convertvector(__builtin_convertvector(x, IntStrip), Strip);
    return t > x ? t - 1.0f : t;
}

// Lane j of the result: lane j of a where bit D of j is clear, else lane j - D of b (HI: lane j + D
// of a where clear, else lane j of b): rows i and i + D of a block swap their off-diagonal D x D
// parts. The lane indices are constants, so each is one shuffle (or blend) of the ISA.
template <int64_t D, bool HI, size_t... J>
static inline Strip swap_halves(Strip a, Strip b, std::index_sequence<J...>) {
    return __builtin_shufflevector(a, b, (HI ? ((J & D) ? S + J : J + D) : ((J & D) ? S + J - D : J))...);
}

// r[i][j] <- r[j][i]: a block of S x S floats transposed in registers, log2(S) rounds of S
// shuffles (the off-diagonal halves swapped, then the quarters in each half, ...).
template <int64_t D = S / 2>
static inline void transpose_regs(Strip r[S]) {
    for (int64_t i = 0; i < S; ++i)
        if ((i & D) == 0) {
            const Strip lo = swap_halves<D, false>(r[i], r[i + D], std::make_index_sequence<S>{});
            const Strip hi = swap_halves<D, true>(r[i], r[i + D], std::make_index_sequence<S>{});
            r[i] = lo, r[i + D] = hi;
        }
    if constexpr (D > 1) transpose_regs<D / 2>(r);
}

// dst[c * dst_stride + p] = src[p * src_stride + c] for a block of S x S floats.
static inline void transpose_block(const float* src, int64_t src_stride, float* dst, int64_t dst_stride) {
    Strip r[S];
    for (int64_t i = 0; i < S; ++i) r[i] = load_strip(src + i * src_stride);
    transpose_regs(r);
    for (int64_t i = 0; i < S; ++i) store_strip(dst + i * dst_stride, r[i]);
}

// Rows of n pixels and C channels between channels-last (value px * C + c) and planar (c * stride
// + px): TO_PLANAR copies channels-last src into planar dst, else planar src into channels-last dst.
// S pixels and S channels at a time, transposed in registers. Where C < S a pixel's channels are
// read and written as whole strips all the same (its lanes past C are the next pixels' values:
// read and dropped, or written and then overwritten by those pixels' own stores, which come
// later), except where that strip would pass the row's end (partial loads or stores there, and
// where C > S is not a multiple of S).
template <bool TO_PLANAR>
static inline void relayout(const float* src, float* dst, int64_t C, int64_t n, int64_t stride) {
    int64_t done = 0;
    if (C % S == 0) {  // whole S x S blocks only (PyramidFilterHead's 16-channel skip): no per-lane tests
        for (; done + S <= n; done += S)
            for (int64_t c0 = 0; c0 < C; c0 += S) {
                if constexpr (TO_PLANAR)
                    transpose_block(src + done * C + c0, C, dst + c0 * stride + done, stride);
                else
                    transpose_block(src + c0 * stride + done, stride, dst + done * C + c0, C);
            }
    }
    if (C < S) {  // the blocks whose every pixel's strip lies within the row: no per-lane tests either
        // (a planar source's rows past C: its last row again, whose lanes are dropped or overwritten)
        const int64_t reach = (S + C - 1) / C;  // pixels one strip of channels-last floats spans
        for (; done + S - 1 + reach <= n; done += S) {
            Strip r[S];
            for (int64_t i = 0; i < S; ++i)
                r[i] = TO_PLANAR ? load_strip(src + (done + i) * C) : load_strip(src + std::min(i, C - 1) * stride + done);
            transpose_regs(r);
            for (int64_t i = 0; i < S; ++i) {
                if constexpr (TO_PLANAR) {
                    if (i < C) store_strip(dst + i * stride + done, r[i]);
                } else {
                    store_strip(dst + (done + i) * C, r[i]);
                }
            }
        }
    }
    for (; done + S <= n; done += S)
        for (int64_t c0 = 0; c0 < C; c0 += S) {
            const int64_t nc = std::min<int64_t>(S, C - c0);
            Strip r[S];
            // pixels below `whole` take a whole strip (C < S: within the row)
            const int64_t whole = nc == S ? S : C < S ? std::min<int64_t>(S, (n * C - S) / C - done + 1) : 0;
            for (int64_t i = 0; i < S; ++i) {
                if constexpr (TO_PLANAR)
                    r[i] = i < whole ? load_strip(src + (done + i) * C + c0) : load_part(src + (done + i) * C + c0, nc);
                else
                    r[i] = i < nc ? load_strip(src + (c0 + i) * stride + done) : Strip{};
            }
            transpose_regs(r);
            for (int64_t i = 0; i < S; ++i) {
                if constexpr (TO_PLANAR) {
                    if (i < nc) store_strip(dst + (c0 + i) * stride + done, r[i]);
                } else if (i < whole) {
                    store_strip(dst + (done + i) * C + c0, r[i]);
                } else {
                    store_part(dst + (done + i) * C + c0, r[i], nc);
                }
            }
        }
    for (int64_t px = done; px < n; ++px)
        for (int64_t c = 0; c < C; ++c) {
            if constexpr (TO_PLANAR)
                dst[c * stride + px] = src[px * C + c];
            else
                dst[px * C + c] = src[c * stride + px];
        }
}

// Channels-last to planar: dst[c * dst_stride + px] = src[px * C + c] for px < n, c < C.
static inline void planar_from_channels_last(const float* src, int64_t C, int64_t n, float* dst, int64_t dst_stride) {
    relayout<true>(src, dst, C, n, dst_stride);
}

// Planar to channels-last: dst[px * C + c] = src[c * src_stride + px] for px < n, c < C.
static inline void channels_last_from_planar(const float* src, int64_t src_stride, int64_t C, int64_t n, float* dst) {
    relayout<false>(src, dst, C, n, src_stride);
}

// 2^u of a strip, about 1 ulp past the rounding of u: u = n + f with n the nearest integer (adding
// and subtracting 1.5 * 2^23, exact for |u| < 2^22) and |f| <= 1/2, 2^f by a degree-6 polynomial
// (Chebyshev fit, relative error 1e-7), times 2^n built in the exponent bits (a NaN stays NaN).
// CLAMP: u below -126 taken as -126 (2^n would not be a normal float); without it u must lie in
// [-126, 127]. The kernel filters take exp(x) as 2^(x log2 e), log2 e folded into the softmax
// scale: 12 or 13 vector operations where the natural-base reduction takes 17.
template <bool CLAMP>
static inline Strip exp2_strip(Strip u) {
    if constexpr (CLAMP) u = u < -126.0f ? Strip{} - 126.0f : u;
    const Strip v = u + 12582912.0f;
    const Strip f = u - (v - 12582912.0f);
    Strip p = f * 1.546531857457012e-4f + 1.3395285932347178e-3f;
    p = p * f + 9.618040174245834e-3f;
    p = p * f + 5.550340563058853e-2f;
    p = p * f + 2.4022650718688965e-1f;
    p = p * f + 6.931471824645996e-1f;
    p = p * f + 1.0f;
    IntStrip bits;
    std::memcpy(&bits, &v, sizeof(bits));
    bits = (bits << 23) + (127 << 23);  // v's low mantissa bits hold n; its other bits shift out
    Strip scale;
    std::memcpy(&scale, &bits, sizeof(scale));
    return p * scale;
}

// lanes j and j + D (mod S) of v: the halving steps of a reduction over a strip's lanes
template <int64_t D, size_t... J>
static inline IntStrip rotate_lanes(IntStrip v, std::index_sequence<J...>) {
    return __builtin_shufflevector(v, v, ((J + D) % S)...);
}
// the smallest and the largest lane of v, and whether any lane is non-zero (log2 S shuffles each)
template <int64_t D = S / 2>
static inline int32_t lane_min(IntStrip v) {
    const IntStrip r = rotate_lanes<D>(v, std::make_index_sequence<S>{});
    v = r < v ? r : v;
    if constexpr (D > 1) return lane_min<D / 2>(v); else return v[0];
}
template <int64_t D = S / 2>
static inline int32_t lane_max(IntStrip v) {
    const IntStrip r = rotate_lanes<D>(v, std::make_index_sequence<S>{});
    v = r > v ? r : v;
    if constexpr (D > 1) return lane_max<D / 2>(v); else return v[0];
}
template <int64_t D = S / 2>
static inline bool any_lane(IntStrip v) {
    v = v | rotate_lanes<D>(v, std::make_index_sequence<S>{});
    if constexpr (D > 1) return any_lane<D / 2>(v); else return v[0] != 0;
}

#if defined(__GNUC__) && !defined(__clang__) && defined(__AVX2__)
constexpr bool PICK = true;
// lane j of the result: lane idx[j] of the 2 S lanes of a then b, idx[j] in [0, 2 S) (GCC's
// shuffle with a variable selector: vpermt2ps with AVX-512, two vpermps and a blend with AVX2)
static inline Strip pick2(Strip a, Strip b, IntStrip idx) { return __builtin_shuffle(a, b, idx); }
#else
// Clang's shuffles take constant selectors only, and GCC expands a variable one lane by lane
// without AVX2 (SSE, NEON): the warp's corners are loaded one by one there
constexpr bool PICK = false;
static inline Strip pick2(Strip a, Strip, IntStrip) { return a; }
#endif

}  // namespace denoiser
