// The OpenVINO extension's portable SIMD layer (denoiser/inference/ovext/simd.hpp) against plain
// loops, and a row's logit statistics (logit_stats.hpp) against a strip's, on whatever ISA this file is compiled for (tests/inference/test_ovext_simd.py builds it for
// the compiler's default target, -march=native and, where a cross compiler and QEMU are there,
// aarch64 NEON). Prints "ok S=<lanes>" and exits 0, or prints the first mismatch and exits 1.
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>
#include <vector>

#include "logit_stats.hpp"
#include "simd.hpp"

using namespace denoiser;

static int failures = 0;

static void expect(bool ok, const char* what, long a, long b, double got, double want) {
    if (!ok && failures++ == 0) std::printf("mismatch: %s at (%ld, %ld): %.9g, expected %.9g\n", what, a, b, got, want);
}

static bool same(float a, float b) { return std::memcmp(&a, &b, sizeof(a)) == 0; }

int main() {
    std::mt19937 rng(7);
    std::uniform_real_distribution<float> uni(-4.0f, 4.0f);

    // relayout both ways: n pixels (whole strips and a rest) x C channels (multiples of S and not)
    for (int64_t C : {1, 3, 4, 7, 8, 16, 17, 33})
        for (int64_t n : {S - 1, S, 3 * S + 5, 9 * S + 2}) {
            const int64_t stride = n + 3;
            // back: S floats past the row, which no store may reach
            std::vector<float> last(n * C), planar(C * stride, -9.0f), back(n * C + S, -9.0f);
            for (auto& v : last) v = uni(rng);
            planar_from_channels_last(last.data(), C, n, planar.data(), stride);
            for (int64_t p = 0; p < n; ++p)
                for (int64_t c = 0; c < C; ++c)
                    expect(same(planar[c * stride + p], last[p * C + c]), "planar_from_channels_last", C, p,
                           planar[c * stride + p], last[p * C + c]);
            for (int64_t c = 0; c < C; ++c)
                for (int64_t p = n; p < stride; ++p) expect(planar[c * stride + p] == -9.0f, "planar padding", c, p, 0, 0);
            channels_last_from_planar(planar.data(), stride, C, n, back.data());
            for (int64_t i = 0; i < n * C; ++i) expect(same(back[i], last[i]), "channels_last_from_planar", C, i, back[i], last[i]);
            for (int64_t i = n * C; i < n * C + S; ++i) expect(back[i] == -9.0f, "past the row", C, i, back[i], 0);
        }

    // a row's logit statistics (whole strips, several at a time) against one strip's, bit for bit
    for (int64_t K : {1, 9, 25})
        for (bool has_scale : {false, true})
            for (int64_t W : {S - 1, S, 5 * S + 3, 9 * S}) {
                const int64_t plane = W + 7;
                std::vector<float> Z(K * plane), mean(W, -9.0f), s(W, -9.0f);
                for (auto& v : Z) v = uni(rng);
                const RowStats st = logit_stats_row(Z.data(), plane, K, W, 5.0f, has_scale, mean.data(), s.data());
                expect(st.n == W / S * S, "logit_stats_row whole strips", W, 0, st.n, W / S * S);
                for (int64_t px0 = 0; px0 + S <= st.n; px0 += S) {
                    float m1[S], s1[S];
                    filter_strip_stats(Z.data(), plane, K, S, px0, 5.0f, has_scale, m1, s1);
                    for (int64_t l = 0; l < S; ++l) {
                        expect(same(mean[px0 + l], m1[l]), "logit_stats_row mean", K, px0 + l, mean[px0 + l], m1[l]);
                        expect(same(s[px0 + l], s1[l]), "logit_stats_row scale", K, px0 + l, s[px0 + l], s1[l]);
                    }
                }
                for (int64_t px = st.n; px < W; ++px) expect(mean[px] == -9.0f, "logit_stats_row past n", K, px, 0, 0);
            }

    // an S x S block transposed between strides
    std::vector<float> src(S * 21), dst(S * 19);
    for (auto& v : src) v = uni(rng);
    transpose_block(src.data(), 21, dst.data(), 19);
    for (int64_t i = 0; i < S; ++i)
        for (int64_t j = 0; j < S; ++j) expect(same(dst[j * 19 + i], src[i * 21 + j]), "transpose_block", i, j, dst[j * 19 + i], src[i * 21 + j]);

    // floor per lane, as std::floor for |x| < 2^31: fractions either side of 0, integers, 2^23 and
    // beyond (-0 may give +0: compared as values)
    const float specials[] = {-0.5f, 0.5f, -1.0f, 1.0f, -2.0f, 0.0f, -0.0f, 2.5f, -2.5f, 8388607.5f, -8388607.5f,
                              8388608.0f, -8388609.0f, 2.0e9f, -2.0e9f, -2147483648.0f, 2147483520.0f,
                              -1.0e-30f, 1.0e-30f, 7679.999f, -7680.5f};
    std::vector<float> xs(specials, specials + sizeof(specials) / sizeof(float));
    std::uniform_real_distribution<float> wide(-1.0e4f, 1.0e4f);
    for (int i = 0; i < 4000; ++i) xs.push_back(wide(rng));
    while (xs.size() % S) xs.push_back(0.25f);
    for (size_t i = 0; i < xs.size(); i += S) {
        const Strip f = floor_strip(load_strip(xs.data() + i));
        for (int64_t l = 0; l < S; ++l) {
            const float want = std::floor(xs[i + l]);
            expect(f[l] == want, "floor_strip", i, l, f[l], want);
        }
    }

    // 2^u within 2e-7 relative over [-126, 127] (CLAMP: below -126 as -126)
    for (int i = 0; i < 8000; i += S) {
        float u[S];
        for (int64_t l = 0; l < S; ++l) u[l] = -130.0f + 257.0f * static_cast<float>(i + l) / 8000.0f;
        const Strip e = exp2_strip<true>(load_strip(u));
        for (int64_t l = 0; l < S; ++l) {
            const double want = std::exp2(std::max<double>(u[l], -126.0));
            expect(std::fabs(e[l] - want) <= 2e-7 * want, "exp2_strip", i, l, e[l], want);
        }
    }

    // partial loads and stores: the rest of the lanes 0, the memory past n untouched
    for (int64_t n = 1; n < S; ++n) {
        float in[S], out[S + 1];
        for (int64_t l = 0; l < S; ++l) in[l] = uni(rng), out[l] = -7.0f;
        out[S] = -7.0f;
        const Strip v = load_part(in, n);
        for (int64_t l = 0; l < S; ++l) expect(same(v[l], l < n ? in[l] : 0.0f), "load_part", n, l, v[l], l < n ? in[l] : 0.0f);
        store_part(out, v, n);
        for (int64_t l = 0; l <= S; ++l) expect(same(out[l], l < n ? in[l] : -7.0f), "store_part", n, l, out[l], 0);
    }

    // lane_min, lane_max, any_lane: over every lane, extremes and one non-zero lane anywhere
    std::uniform_int_distribution<int32_t> ints(std::numeric_limits<int32_t>::min(), std::numeric_limits<int32_t>::max());
    for (int t = 0; t < 300; ++t) {
        IntStrip v;
        for (int64_t l = 0; l < S; ++l) v[l] = t % 3 == 0 ? ints(rng) % 1000 : ints(rng);
        int32_t lo = v[0], hi = v[0];
        for (int64_t l = 1; l < S; ++l) lo = std::min(lo, v[l]), hi = std::max(hi, v[l]);
        expect(lane_min(v) == lo, "lane_min", t, 0, lane_min(v), lo);
        expect(lane_max(v) == hi, "lane_max", t, 0, lane_max(v), hi);
        IntStrip one = {};
        one[t % S] = t % 2 ? -1 : 1 << (t % 31);
        expect(any_lane(one) && !any_lane(IntStrip{}), "any_lane", t, t % S, any_lane(one), 1);
    }

    // pick2: lane j of a then b by a variable selector (GCC); Clang has none (PICK false)
    if (PICK) {
        float ab[2 * S];
        for (auto& v : ab) v = uni(rng);
        std::uniform_int_distribution<int32_t> any(0, 2 * S - 1);
        for (int t = 0; t < 200; ++t) {
            IntStrip idx;
            for (int64_t l = 0; l < S; ++l) idx[l] = any(rng);
            const Strip v = pick2(load_strip(ab), load_strip(ab + S), idx);
            for (int64_t l = 0; l < S; ++l) expect(same(v[l], ab[idx[l]]), "pick2", t, l, v[l], ab[idx[l]]);
        }
    }

    if (failures) {
        std::printf("%d mismatches (S=%ld)\n", failures, static_cast<long>(S));
        return 1;
    }
    std::printf("ok S=%ld\n", static_cast<long>(S));
    return 0;
}
