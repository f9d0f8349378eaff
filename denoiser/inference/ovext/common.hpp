// Shared by the operations of the OpenVINO extension (one header per operation, extension.cpp
// registers them): the bounded exp, the per-pixel softmax scale, the row-wise kernel filter
// (KernelApply and PyramidFilter's levels), the row scheduler and torch's bilinear coordinates.
// Rows run in parallel on the calling TBB arena (the CPU plugin's, so INFERENCE_NUM_THREADS
// holds); each row is computed by one thread in a fixed order, so results do not depend on the
// number of threads.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <string>
#include <utility>
#include <limits>
#include <memory>
#include <mutex>
#include <vector>

#include <openvino/core/extension.hpp>
#include <openvino/core/op_extension.hpp>
#include <openvino/frontend/node_context.hpp>
#include <openvino/frontend/onnx/extension/conversion.hpp>
#include <openvino/op/op.hpp>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>


namespace denoiser {

constexpr float NORM_EPS = 1e-30f;  // denoiser.nn.pyramid.NORM_EPS

// exp(x) for x <= 88 (a softmax's shifted logits), about 2 ulp; 0 below -87.
// Cody-Waite reduction x = n ln2 + f, degree-6 polynomial on |f| <= ln2 / 2, 2^n by the exponent
// bits. Branch-free so the row loops vectorise.
static inline float exp_bounded(float x) {
    x = std::max(x, -87.0f);
    const float n = std::nearbyint(x * 1.44269504088896341f);
    float f = std::fma(n, -0.693359375f, x);
    f = std::fma(n, 2.12194440e-4f, f);
    float p = 1.9875691500e-4f;
    p = std::fma(p, f, 1.3981999507e-3f);
    p = std::fma(p, f, 8.3334519073e-3f);
    p = std::fma(p, f, 4.1665795894e-2f);
    p = std::fma(p, f, 1.6666665459e-1f);
    p = std::fma(p, f, 5.0000001201e-1f);
    p = std::fma(p * f, f, f) + 1.0f;
    const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
    float scale;
    std::memcpy(&scale, &bits, sizeof(scale));
    return p * scale;
}

// Softmax scale per pixel of a row: s[px] = scale / sqrt(var over the n planes + 1) (two-pass
// variance, as torch.var(unbiased=False)), or 1. z: n planes of W values, `plane` apart. tmp: W floats.
static void logit_scale_row(const float* z, int64_t n, int64_t plane, int64_t W, float scale, bool has_scale,
                            float* s, float* tmp) {
    if (!has_scale) {
        std::fill(s, s + W, 1.0f);
        return;
    }
    std::fill(tmp, tmp + W, 0.0f);
    for (int64_t t = 0; t < n; ++t)
        for (int64_t px = 0; px < W; ++px) tmp[px] += z[t * plane + px];
    for (int64_t px = 0; px < W; ++px) tmp[px] *= 1.0f / n;
    std::fill(s, s + W, 0.0f);
    for (int64_t t = 0; t < n; ++t)
        for (int64_t px = 0; px < W; ++px) {
            const float d = z[t * plane + px] - tmp[px];
            s[px] += d * d;
        }
    for (int64_t px = 0; px < W; ++px) s[px] = scale / std::sqrt(s[px] * (1.0f / n) + 1.0f);
}

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

// 0, 1, ..., S - 1
static inline Strip lane_index() {
    Strip v;
    for (int64_t l = 0; l < S; ++l) v[l] = static_cast<float>(l);
    return v;
}

// floor per lane (torch's and std::floor's): t = trunc(x) through int32 (exact for |x| < 2^23,
// where a float can have a fraction), minus 1 where that rounded up; |x| >= 2^23 and NaN unchanged.
static inline Strip floor_strip(Strip x) {
    const Strip t = __builtin_convertvector(__builtin_convertvector(x, IntStrip), Strip);
    const Strip fl = t > x ? t - 1.0f : t;
    const Strip ax = x < 0.0f ? -x : x;
    return ax < 8388608.0f ? fl : x;
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
// S pixels and S channels at a time, transposed in registers (partial loads or stores where C is
// not a multiple of S).
template <bool TO_PLANAR>
static inline void relayout(const float* src, float* dst, int64_t C, int64_t n, int64_t stride) {
    int64_t done = 0;
    for (; done + S <= n; done += S)
        for (int64_t c0 = 0; c0 < C; c0 += S) {
            const int64_t nc = std::min<int64_t>(S, C - c0);
            Strip r[S];
            for (int64_t i = 0; i < S; ++i) {
                if constexpr (TO_PLANAR)
                    r[i] = nc == S ? load_strip(src + (done + i) * C + c0) : load_part(src + (done + i) * C + c0, nc);
                else
                    r[i] = i < nc ? load_strip(src + (c0 + i) * stride + done) : Strip{};
            }
            transpose_regs(r);
            for (int64_t i = 0; i < S; ++i) {
                if constexpr (TO_PLANAR) {
                    if (i < nc) store_strip(dst + (c0 + i) * stride + done, r[i]);
                } else if (nc == S) {
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

constexpr float LOG2E = 1.44269504088896341f;

// Whether the softmax may be shifted by the logits' mean instead of their maximum: with the
// scale-normalised logits every centred, scaled logit lies within scale * sqrt(K) of it
// (|z_t - mean| <= sqrt(K var)), so exp stays finite and normal for scale * sqrt(K) <= 80.
static bool mean_shift_ok(int64_t K, float scale, bool has_scale) {
    return has_scale && scale * std::sqrt(static_cast<float>(K)) <= 80.0f;
}

constexpr int64_t MAX_K = 15;  // the largest kernel size the filters take

// The k source rows of a filtered row y: rows[i] is row y + i - r of x (channel c at
// rows[i] + c * cstride), null where that row lies outside the image. Planes of one tensor
// (cstride H * W) or rows kept in a ring (PyramidFilter's level 0, cstride W).
struct SourceRows {
    const float* rows[MAX_K];
    int64_t cstride;
};

// The source rows of row y of C planes X of H x W for a k x k filter.
static inline SourceRows planar_rows(const float* X, int64_t H, int64_t W, int64_t k, int64_t y) {
    SourceRows src{{}, H * W};
    for (int64_t i = 0, r = k / 2; i < k; ++i) src.rows[i] = y + i - r >= 0 && y + i - r < H ? X + (y + i - r) * W : nullptr;
    return src;
}

// The taps of filter_strip's vector path (every tap inside the row): acc (NC rows, acc_plane
// apart) at px0 .. px0 + S - 1 = sum_t e_t x_t / sum_t e_t, e_t = exp(z_t s - shift).
template <int NC, bool CLAMP>
static inline void filter_strip_taps(const SourceRows& X, const float* Z, int64_t plane, int64_t k, int64_t px0,
                                     const float* s, const float* shift, float* acc_rows, int64_t acc_plane) {
    const int64_t r = k / 2, cs = X.cstride;
    const Strip sv = load_strip(s) * LOG2E, shv = load_strip(shift) * LOG2E;
    Strip sumv = {}, accv[NC] = {};
    for (int64_t i = 0; i < k; ++i) {
        if (X.rows[i] == nullptr) continue;
        for (int64_t j = 0; j < k; ++j) {
            const Strip e = exp2_strip<CLAMP>(load_strip(Z + (i * k + j) * plane + px0) * sv - shv);
            const float* xr = X.rows[i] + px0 + j - r;
            sumv += e;
            for (int64_t c = 0; c < NC; ++c) accv[c] += e * load_strip(xr + c * cs);
        }
    }
    const Strip inv = 1.0f / sumv;
    for (int64_t c = 0; c < NC; ++c) store_strip(acc_rows + c * acc_plane + px0, accv[c] * inv);
}

// The kernel filter of pixels px0 .. px0 + S - 1 of a row, channels 0 .. C-1 (NC = C when known at
// compile time, else 0), into acc (C rows of W). EDGE: some of the strip's taps or pixels lie
// outside the row (checked per pixel); otherwise every tap column is inside. X: the row's source
// rows; Z: k*k logit rows `plane` apart.
template <int NC, bool EDGE>
static void filter_strip(const SourceRows& X, int64_t C_, int64_t W, const float* Z, int64_t plane, int64_t k,
                         int64_t px0, float scale, bool has_scale, float* acc_rows, int64_t acc_plane) {
    const int64_t C = NC > 0 ? NC : C_;
    const int64_t r = k / 2, K = k * k, cs = X.cstride;
    const int64_t n = EDGE ? std::min<int64_t>(S, W - px0) : S;
    float mean[S] = {}, s[S], shift[S], sum[S] = {};
    float acc[NC > 0 ? NC : 8][S] = {};
    for (int64_t t = 0; t < K; ++t) {
        const float* z = Z + t * plane + px0;
        for (int64_t l = 0; l < S; ++l) mean[l] += l < n ? z[l] : 0.0f;
    }
    for (int64_t l = 0; l < S; ++l) mean[l] *= 1.0f / K;
    if (has_scale) {
        float var[S] = {};
        for (int64_t t = 0; t < K; ++t) {
            const float* z = Z + t * plane + px0;
            for (int64_t l = 0; l < S; ++l) {
                const float d = (l < n ? z[l] : 0.0f) - mean[l];
                var[l] += d * d;
            }
        }
        for (int64_t l = 0; l < S; ++l) s[l] = scale / std::sqrt(var[l] * (1.0f / K) + 1.0f);
    } else {
        for (int64_t l = 0; l < S; ++l) s[l] = 1.0f;
    }
    if (mean_shift_ok(K, scale, has_scale)) {
        for (int64_t l = 0; l < S; ++l) shift[l] = mean[l] * s[l];
    } else {  // the largest in-image scaled logit; the centre tap always is in the image
        const float* zc = Z + (r * k + r) * plane + px0;
        for (int64_t l = 0; l < S; ++l) shift[l] = l < n ? zc[l] * s[l] : 0.0f;
        for (int64_t i = 0; i < k; ++i) {
            if (X.rows[i] == nullptr) continue;
            for (int64_t j = 0; j < k; ++j) {
                const float* z = Z + (i * k + j) * plane + px0;
                for (int64_t l = 0; l < S; ++l) {
                    const int64_t q = px0 + l + j - r;
                    if (!EDGE || (l < n && q >= 0 && q < W)) shift[l] = std::max(shift[l], z[l] * s[l]);
                }
            }
        }
    }
    if constexpr (!EDGE && NC > 0) {  // every tap inside: the strip as vectors (exp2_strip)
        // shifted by the mean, the exponents lie within scale sqrt(K) log2(e) <= 116 of 0
        if (mean_shift_ok(K, scale, has_scale))
            filter_strip_taps<NC, false>(X, Z, plane, k, px0, s, shift, acc_rows, acc_plane);
        else
            filter_strip_taps<NC, true>(X, Z, plane, k, px0, s, shift, acc_rows, acc_plane);
        return;
    }
    for (int64_t i = 0; i < k; ++i) {
        if (X.rows[i] == nullptr) continue;
        for (int64_t j = 0; j < k; ++j) {
            const int64_t d = j - r;
            const float* z = Z + (i * k + j) * plane + px0;
            const float* xr = X.rows[i] + px0 + d;
            if (!EDGE) {
                for (int64_t l = 0; l < S; ++l) {
                    const float e = exp_bounded(z[l] * s[l] - shift[l]);
                    sum[l] += e;
                    for (int64_t c = 0; c < C; ++c) acc[c][l] += e * xr[c * cs + l];
                }
            } else {
                for (int64_t l = 0; l < n; ++l) {
                    const int64_t q = px0 + l + d;
                    if (q < 0 || q >= W) continue;
                    const float e = exp_bounded(z[l] * s[l] - shift[l]);
                    sum[l] += e;
                    for (int64_t c = 0; c < C; ++c) acc[c][l] += e * xr[c * cs + l];
                }
            }
        }
    }
    for (int64_t l = 0; l < S; ++l) sum[l] = 1.0f / sum[l];
    for (int64_t c = 0; c < C; ++c)
        for (int64_t l = 0; l < n; ++l) acc_rows[c * acc_plane + px0 + l] = acc[c][l] * sum[l];
}

template <int NC>
static void filter_row_c(const SourceRows& X, int64_t C, int64_t W, const float* Z, int64_t plane, int64_t k,
                         float scale, bool has_scale, float* acc, int64_t acc_plane) {
    const int64_t r = k / 2;
    for (int64_t px0 = 0; px0 < W; px0 += S) {
        if (px0 >= r && px0 + S + r <= W)
            filter_strip<NC, false>(X, C, W, Z, plane, k, px0, scale, has_scale, acc, acc_plane);
        else
            filter_strip<NC, true>(X, C, W, Z, plane, k, px0, scale, has_scale, acc, acc_plane);
    }
}

// The kernel filter of a row: acc (C rows, acc_plane apart) = sum_t w_t * x[c, y + i - r, px + j - r]
// with the softmax weights w. X: the row's source rows (planar_rows, or a ring's); Z: k*k logit
// rows `plane` apart.
static void filter_row(const SourceRows& X, int64_t C, int64_t W, const float* Z, int64_t plane, int64_t k,
                       float scale, bool has_scale, float* acc, int64_t acc_plane) {
    if (C == 3) return filter_row_c<3>(X, C, W, Z, plane, k, scale, has_scale, acc, acc_plane);
    if (C == 4) return filter_row_c<4>(X, C, W, Z, plane, k, scale, has_scale, acc, acc_plane);
    for (int64_t c0 = 0; c0 < C; c0 += 8) {  // other channel counts, 8 at a time
        const int64_t cn = std::min<int64_t>(8, C - c0);
        SourceRows part = X;
        for (int64_t i = 0; i < k; ++i)
            if (part.rows[i] != nullptr) part.rows[i] += c0 * X.cstride;
        filter_row_c<0>(part, cn, W, Z, plane, k, scale, has_scale, acc + c0 * acc_plane, acc_plane);
    }
}

template <class F>
static void parallel_rows(int64_t rows, F&& body) {
    tbb::parallel_for(tbb::blocked_range<int64_t>(0, rows, 4), body);
}

static int64_t kernel_size_of(int64_t K) {
    const int64_t k = static_cast<int64_t>(std::lround(std::sqrt(static_cast<double>(K))));
    OPENVINO_ASSERT(k * k == K && k % 2 == 1 && k <= MAX_K, "kernel logits need k*k channels with odd k <= ", MAX_K,
                    ", got ", K);
    return k;
}

// One coordinate of torch's bilinear interpolation (align_corners=False) from n_in to n_out samples.
struct Lerp {
    int64_t i0, i1;
    float l0, l1;
};

static std::vector<Lerp> bilinear_axis(int64_t n_in, int64_t n_out) {
    std::vector<Lerp> out(static_cast<size_t>(n_out));
    const float ratio = static_cast<float>(n_in) / static_cast<float>(n_out);
    for (int64_t d = 0; d < n_out; ++d) {
        float src = ratio * (d + 0.5f) - 0.5f;
        src = std::max(src, 0.0f);
        const int64_t i0 = std::min<int64_t>(static_cast<int64_t>(src), n_in - 1);
        const int64_t i1 = i0 + (i0 < n_in - 1 ? 1 : 0);
        const float l1 = src - static_cast<float>(i0);
        out[d] = {i0, i1, 1.0f - l1, l1};
    }
    return out;
}

// Lerp tables of torch's nearest upsampling (floor(dst * n_in / n_out)): one tap, weight 1.
static std::vector<Lerp> nearest_axis(int64_t n_in, int64_t n_out) {
    std::vector<Lerp> out(static_cast<size_t>(n_out));
    const float ratio = static_cast<float>(n_in) / static_cast<float>(n_out);
    for (int64_t d = 0; d < n_out; ++d) {
        const int64_t i = std::min<int64_t>(static_cast<int64_t>(std::floor(d * ratio)), n_in - 1);
        out[d] = {i, i, 1.0f, 0.0f};
    }
    return out;
}

// The exact 2x bilinear upsampling (align_corners=False) of one row t[0 .. ws), ws >= 2, into
// o[0 .. 2 ws) (ADD: added to it): columns 2m and 2m + 1 at 1/4 and 3/4 between source columns
// m - 1, m and m, m + 1, the ends clamped (bilinear_axis(ws, 2 ws) in closed form; the loops
// vectorise, where the Lerp tables' gathers do not).
template <bool ADD>
static inline void upsample2x_row(const float* __restrict t, int64_t ws, float* __restrict o) {
    o[0] = (ADD ? o[0] : 0.0f) + t[0];
    o[2 * ws - 1] = (ADD ? o[2 * ws - 1] : 0.0f) + t[ws - 1];
    for (int64_t m = 1; m < ws; ++m) {
        o[2 * m] = (ADD ? o[2 * m] : 0.0f) + (0.25f * t[m - 1] + 0.75f * t[m]);
        o[2 * m - 1] = (ADD ? o[2 * m - 1] : 0.0f) + (0.75f * t[m - 1] + 0.25f * t[m]);
    }
}

// An upsampling of planes hs x ws to H x W (F.interpolate, align_corners=False), row by row.
struct Upsampling {
    Upsampling(int64_t hs_, int64_t ws_, int64_t H, int64_t W, bool bilinear)
        : hs(hs_), ws(ws_), w(W), ly(bilinear ? bilinear_axis(hs_, H) : nearest_axis(hs_, H)),
          lx(bilinear ? bilinear_axis(ws_, W) : nearest_axis(ws_, W)),
          exact2x(bilinear && H == 2 * hs_ && W == 2 * ws_ && ws_ >= 2) {}
    int64_t hs, ws, w;
    std::vector<Lerp> ly, lx;
    bool exact2x;

    // dst (channels rows of w, dst_plane apart) = row y of the upsampled src (channels planes of
    // hs x ws). t: ws floats.
    void row(const float* src, int64_t channels, int64_t y, float* dst, int64_t dst_plane, float* t) const {
        const Lerp& l = ly[y];
        for (int64_t c = 0; c < channels; ++c) {
            const float* z0 = src + (c * hs + l.i0) * ws;
            const float* z1 = src + (c * hs + l.i1) * ws;
            float* o = dst + c * dst_plane;
            if (!exact2x) {
                for (int64_t px = 0; px < w; ++px) {
                    const Lerp& m = lx[px];
                    o[px] = l.l0 * (m.l0 * z0[m.i0] + m.l1 * z0[m.i1]) + l.l1 * (m.l0 * z1[m.i0] + m.l1 * z1[m.i1]);
                }
                continue;
            }
            // exact 2x bilinear: the two source rows blended, then the row upsampled
            for (int64_t m = 0; m < ws; ++m) t[m] = l.l0 * z0[m] + l.l1 * z1[m];
            upsample2x_row<false>(t, ws, o);
        }
    }
};

// dst (channels planes h x w) += bilinear upsampling of src (channels planes hs x ws), row y
// only (ly: its row's Lerp). t: ws floats, used where w == 2 ws (the exact 2x columns).
static void add_upsampled_row(const float* src, int64_t hs, int64_t ws, const Lerp& ly, const std::vector<Lerp>& lx,
                              int64_t w, float* dst_row, int64_t dst_plane, int64_t channels, float* t) {
    for (int64_t c = 0; c < channels; ++c) {
        const float* r0 = src + (c * hs + ly.i0) * ws;
        const float* r1 = src + (c * hs + ly.i1) * ws;
        float* o = dst_row + c * dst_plane;
        if (w == 2 * ws && ws >= 2) {
            for (int64_t m = 0; m < ws; ++m) t[m] = ly.l0 * r0[m] + ly.l1 * r1[m];
            upsample2x_row<true>(t, ws, o);
            continue;
        }
        for (int64_t px = 0; px < w; ++px) {
            const Lerp& l = lx[px];
            o[px] += ly.l0 * (l.l0 * r0[l.i0] + l.l1 * r0[l.i1]) + ly.l1 * (l.l0 * r1[l.i0] + l.l1 * r1[l.i1]);
        }
    }
}

}  // namespace denoiser
