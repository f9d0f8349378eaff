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

#include "logit_stats.hpp"
#include "simd.hpp"


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

// exp_bounded of a strip, the same reduction lane by lane (n rounded by adding and subtracting
// 1.5 * 2^23, as nearbyint rounds; the fused multiply-adds the compiler's contractions): the
// compilers leave the scalar one's loops unvectorised on AVX2 (they see control flow in them).
static inline Strip exp_bounded_strip(Strip x) {
    x = x < -87.0f ? Strip{} - 87.0f : x;
    const Strip n = (x * 1.44269504088896341f + 12582912.0f) - 12582912.0f;
    Strip f = n * -0.693359375f + x;
    f = n * 2.12194440e-4f + f;
    Strip p = Strip{} + 1.9875691500e-4f;
    p = p * f + 1.3981999507e-3f;
    p = p * f + 8.3334519073e-3f;
    p = p * f + 4.1665795894e-2f;
    p = p * f + 1.6666665459e-1f;
    p = p * f + 5.0000001201e-1f;
    p = (p * f) * f + f + 1.0f;
    const IntStrip bits = (__builtin_convertvector(n, IntStrip) + 127) << 23;
    Strip scale;
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
                                     Strip s, Strip shift, float* acc_rows, int64_t acc_plane) {
    const int64_t r = k / 2, cs = X.cstride;
    const Strip sv = s * LOG2E, shv = shift * LOG2E;
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
                         int64_t px0, float scale, bool has_scale, const RowStats& stats, float* acc_rows,
                         int64_t acc_plane) {
    const int64_t C = NC > 0 ? NC : C_;
    const int64_t r = k / 2, K = k * k, cs = X.cstride;
    const int64_t n = EDGE ? std::min<int64_t>(S, W - px0) : S;
    if constexpr (!EDGE && NC > 0) {  // every tap inside (so a whole strip, px0 + S <= stats.n)
        // shifted by the mean (the exponents lie within scale sqrt(K) log2(e) <= 116 of 0): the
        // strip's statistics from the row's pass as vectors. (Copied into the arrays below, they were
        // stored in 16-byte pieces where S is 8, GCC's largest move for the AVX2 targets, and read
        // back whole: a load the stores cannot forward, which stalled for 15% of the AVX2 build's
        // samples in filter_row.)
        if (px0 + S <= stats.n && mean_shift_ok(K, scale, has_scale)) {
            const Strip sv = load_strip(stats.s + px0);
            filter_strip_taps<NC, false>(X, Z, plane, k, px0, sv, load_strip(stats.mean + px0) * sv, acc_rows,
                                         acc_plane);
            return;
        }
    }
    float mean[S] = {}, s[S], shift[S], sum[S] = {};
    float acc[NC > 0 ? NC : 8][S] = {};
    if (px0 + S <= stats.n) {  // a whole strip: its statistics from the row's pass (logit_stats_row)
        std::memcpy(mean, stats.mean + px0, sizeof(mean));
        std::memcpy(s, stats.s + px0, sizeof(s));
    } else {
        filter_strip_stats(Z, plane, K, n, px0, scale, has_scale, mean, s);
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
    if constexpr (!EDGE && NC > 0) {  // every tap inside, shifted by the maximum: the strip as vectors
        filter_strip_taps<NC, true>(X, Z, plane, k, px0, load_strip(s), load_strip(shift), acc_rows, acc_plane);
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
                         float scale, bool has_scale, const RowStats& stats, float* acc, int64_t acc_plane) {
    const int64_t r = k / 2;
    for (int64_t px0 = 0; px0 < W; px0 += S) {
        if (px0 >= r && px0 + S + r <= W)
            filter_strip<NC, false>(X, C, W, Z, plane, k, px0, scale, has_scale, stats, acc, acc_plane);
        else
            filter_strip<NC, true>(X, C, W, Z, plane, k, px0, scale, has_scale, stats, acc, acc_plane);
    }
}

// The kernel filter of a row: acc (C rows, acc_plane apart) = sum_t w_t * x[c, y + i - r, px + j - r]
// with the softmax weights w. X: the row's source rows (planar_rows, or a ring's); Z: k*k logit
// rows `plane` apart.
static void filter_row(const SourceRows& X, int64_t C, int64_t W, const float* Z, int64_t plane, int64_t k,
                       float scale, bool has_scale, float* acc, int64_t acc_plane) {
    static thread_local std::vector<float> stats_buffer;  // the row's means and scales, kept between rows
    if (stats_buffer.size() < static_cast<size_t>(2 * W)) stats_buffer.resize(static_cast<size_t>(2 * W));
    const RowStats stats =
        logit_stats_row(Z, plane, k * k, W, scale, has_scale, stats_buffer.data(), stats_buffer.data() + W);
    if (C == 3) return filter_row_c<3>(X, C, W, Z, plane, k, scale, has_scale, stats, acc, acc_plane);
    if (C == 4) return filter_row_c<4>(X, C, W, Z, plane, k, scale, has_scale, stats, acc, acc_plane);
    for (int64_t c0 = 0; c0 < C; c0 += 8) {  // other channel counts, 8 at a time
        const int64_t cn = std::min<int64_t>(8, C - c0);
        SourceRows part = X;
        for (int64_t i = 0; i < k; ++i)
            if (part.rows[i] != nullptr) part.rows[i] += c0 * X.cstride;
        filter_row_c<0>(part, cn, W, Z, plane, k, scale, has_scale, stats, acc + c0 * acc_plane, acc_plane);
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
