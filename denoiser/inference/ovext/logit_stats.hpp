// The per-pixel statistics of a kernel's logits that its softmax is scaled and shifted by (the
// filters of common.hpp): the mean of a pixel's K logits and s = scale / sqrt(var + 1) (two-pass
// variance, as torch.var(unbiased=False); 1 without a scale), one strip at a time or a row's whole
// strips together, in the same operations and order (the same bits: tests/inference/ovext_simd_check.cpp).
#pragma once

#include <cmath>
#include <cstdint>
#include <type_traits>

#include "simd.hpp"

namespace denoiser {

// The mean of a strip's K logits and its softmax scale (scale / sqrt(var + 1), or 1), lanes past n
// taken as 0: the sums in order t = 0 .. K - 1, as logit_stats_row's.
static inline void filter_strip_stats(const float* Z, int64_t plane, int64_t K, int64_t n, int64_t px0, float scale,
                                      bool has_scale, float* mean, float* s) {
    for (int64_t l = 0; l < S; ++l) mean[l] = 0.0f;
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
}

// A row's per-pixel logit statistics for filter_strip: mean and s (as filter_strip_stats) of the
// pixels px < n, n the row's whole strips (W / S * S); the rest left to filter_strip.
struct RowStats {
    const float* mean;
    const float* s;
    int64_t n;
};

// RowStats of a row of K logit rows Z (`plane` apart, W pixels) into mean and s (W floats each):
// Q strips at a time, so that Q chains of K additions run side by side (within filter_strip each
// strip's two chains of K dependent operations waited on their latency, about a sixth of the
// level-0 filter's time on AVX2). The same operations in the same order as filter_strip_stats.
static RowStats logit_stats_row(const float* Z, int64_t plane, int64_t K, int64_t W, float scale, bool has_scale,
                                float* mean, float* s) {
    constexpr int64_t Q = 4;
    const int64_t n = W / S * S;
    const float invK = 1.0f / K;
    int64_t px0 = 0;
    auto block = [&](auto q_) {
        constexpr int64_t q = decltype(q_)::value;
        Strip m[q] = {}, v[q] = {};
        for (int64_t t = 0; t < K; ++t)
            for (int64_t j = 0; j < q; ++j) m[j] += load_strip(Z + t * plane + px0 + j * S);
        for (int64_t j = 0; j < q; ++j) m[j] *= invK;
        for (int64_t j = 0; j < q; ++j) store_strip(mean + px0 + j * S, m[j]);
        if (!has_scale) {
            for (int64_t j = 0; j < q; ++j) store_strip(s + px0 + j * S, Strip{} + 1.0f);
            return;
        }
        for (int64_t t = 0; t < K; ++t)
            for (int64_t j = 0; j < q; ++j) {
                const Strip d = load_strip(Z + t * plane + px0 + j * S) - m[j];
                v[j] += d * d;
            }
        for (int64_t j = 0; j < q; ++j) store_strip(s + px0 + j * S, scale / sqrt_strip(v[j] * invK + 1.0f));
    };
    for (; px0 + Q * S <= n; px0 += Q * S) block(std::integral_constant<int64_t, Q>{});
    for (; px0 < n; px0 += S) block(std::integral_constant<int64_t, 1>{});
    return {mean, s, n};
}

}  // namespace denoiser
