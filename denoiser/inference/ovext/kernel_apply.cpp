// OpenVINO CPU extension: the kernel filters of denoiser.nn as single operations (domain "denoiser").
//
// KernelApply(x [B, C, H, W] f32, logits [B, k*k, H, W] f32; attributes scale, has_scale)
//   -> [B, C, H, W] f32: denoiser.nn.kernels.apply_kernels_graph. For every pixel p
//   (r = k / 2, tap t = i*k + j, i rows, j columns):
//
//   z_t   = logits[b, t, p] * s(p),  s(p) = scale / sqrt(var_t(logits[b, :, p]) + 1)  (has_scale)
//                                    s(p) = 1                                         (otherwise)
//   w     = softmax over the taps t that read inside the image of z
//   out_c = sum_t w_t * x[b, c, p + (i - r, j - r)]
//
// PyramidFilter(x [B, 3, H, W], head0 [B, L + k0^2, H, W], head_i [B, k_i^2, H/2^i, W/2^i] for
//   i = 1 .. L-1; attributes kernel_sizes, scale, has_scale) -> [B, 3, H, W] f32:
//   denoiser.nn.pyramid.PyramidFilter.forward (its module docstring is the definition): the
//   partition softmax, the parts [x, 1] * w_i average-pooled by 2^i, each level's kernel filter
//   (as KernelApply), the bilinear upsampling and sum from the coarsest level, and the division
//   by the filtered constant channel (x where it is <= 1e-30).
//
// Both run one image row at a time: the logits of a row are read from cache, the taps'
// exponentials are computed once and each input pixel of the k rows a tap needs is read once,
// instead of k*k materialised shifted copies and several passes over the weights in the plain
// graph. Rows run in parallel on the calling TBB arena (the CPU plugin's, so
// INFERENCE_NUM_THREADS holds); each row is computed by one thread in a fixed order, so results do
// not depend on the number of threads.
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

static std::unique_ptr<float[]> uninitialised(size_t n) { return std::unique_ptr<float[]>(new float[n]); }

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

// Scratch of one thread for rows of width W and C channels.
struct RowScratch {
    explicit RowScratch(int64_t W, int64_t C) : data(uninitialised(static_cast<size_t>(W) * C)) { acc = data.get(); }
    std::unique_ptr<float[]> data;
    float* acc;  // C rows of W: the filtered row
};

constexpr int64_t S = 16;  // pixels per strip: one AVX-512 register of floats

// Whether the softmax may be shifted by the logits' mean instead of their maximum: with the
// scale-normalised logits every centred, scaled logit lies within scale * sqrt(K) of it
// (|z_t - mean| <= sqrt(K var)), so exp stays finite and normal for scale * sqrt(K) <= 80.
static bool mean_shift_ok(int64_t K, float scale, bool has_scale) {
    return has_scale && scale * std::sqrt(static_cast<float>(K)) <= 80.0f;
}

// The kernel filter of pixels px0 .. px0 + S - 1 of row y, channels 0 .. C-1 (NC = C when known at
// compile time, else 0), into acc (C rows of W). EDGE: some of the strip's taps or pixels lie
// outside the row (checked per pixel); otherwise every tap column is inside. X: C planes of
// H x W; Z: k*k logit planes `plane` apart, offset to row y.
template <int NC, bool EDGE>
static void filter_strip(const float* X, int64_t C_, int64_t H, int64_t W, const float* Z, int64_t plane, int64_t k,
                         int64_t y, int64_t px0, float scale, bool has_scale, float* acc_rows) {
    const int64_t C = NC > 0 ? NC : C_;
    const int64_t r = k / 2, K = k * k, HW = H * W;
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
            if (y + i - r < 0 || y + i - r >= H) continue;
            for (int64_t j = 0; j < k; ++j) {
                const float* z = Z + (i * k + j) * plane + px0;
                for (int64_t l = 0; l < S; ++l) {
                    const int64_t q = px0 + l + j - r;
                    if (!EDGE || (l < n && q >= 0 && q < W)) shift[l] = std::max(shift[l], z[l] * s[l]);
                }
            }
        }
    }
    for (int64_t i = 0; i < k; ++i) {
        const int64_t yy = y + i - r;
        if (yy < 0 || yy >= H) continue;
        for (int64_t j = 0; j < k; ++j) {
            const int64_t d = j - r;
            const float* z = Z + (i * k + j) * plane + px0;
            const float* xr = X + yy * W + px0 + d;
            if (!EDGE) {
                for (int64_t l = 0; l < S; ++l) {
                    const float e = exp_bounded(z[l] * s[l] - shift[l]);
                    sum[l] += e;
                    for (int64_t c = 0; c < C; ++c) acc[c][l] += e * xr[c * HW + l];
                }
            } else {
                for (int64_t l = 0; l < n; ++l) {
                    const int64_t q = px0 + l + d;
                    if (q < 0 || q >= W) continue;
                    const float e = exp_bounded(z[l] * s[l] - shift[l]);
                    sum[l] += e;
                    for (int64_t c = 0; c < C; ++c) acc[c][l] += e * xr[c * HW + l];
                }
            }
        }
    }
    for (int64_t l = 0; l < S; ++l) sum[l] = 1.0f / sum[l];
    for (int64_t c = 0; c < C; ++c)
        for (int64_t l = 0; l < n; ++l) acc_rows[c * W + px0 + l] = acc[c][l] * sum[l];
}

template <int NC>
static void filter_row_c(const float* X, int64_t C, int64_t H, int64_t W, const float* Z, int64_t plane, int64_t k,
                         int64_t y, float scale, bool has_scale, float* acc) {
    const int64_t r = k / 2;
    for (int64_t px0 = 0; px0 < W; px0 += S) {
        if (px0 >= r && px0 + S + r <= W)
            filter_strip<NC, false>(X, C, H, W, Z, plane, k, y, px0, scale, has_scale, acc);
        else
            filter_strip<NC, true>(X, C, H, W, Z, plane, k, y, px0, scale, has_scale, acc);
    }
}

// The kernel filter of row y: t.acc (C rows of W) = sum_t w_t * x[c, y + i - r, px + j - r] with
// the softmax weights w. X: C planes of H x W; Z: k*k logit planes `plane` apart, offset to row y.
static void filter_row(const float* X, int64_t C, int64_t H, int64_t W, const float* Z, int64_t plane, int64_t k,
                       int64_t y, float scale, bool has_scale, RowScratch& t) {
    if (C == 3) return filter_row_c<3>(X, C, H, W, Z, plane, k, y, scale, has_scale, t.acc);
    if (C == 4) return filter_row_c<4>(X, C, H, W, Z, plane, k, y, scale, has_scale, t.acc);
    for (int64_t c0 = 0; c0 < C; c0 += 8) {  // other channel counts, 8 at a time
        const int64_t cn = std::min<int64_t>(8, C - c0);
        filter_row_c<0>(X + c0 * H * W, cn, H, W, Z, plane, k, y, scale, has_scale, t.acc + c0 * W);
    }
}

template <class F>
static void parallel_rows(int64_t rows, F&& body) {
    tbb::parallel_for(tbb::blocked_range<int64_t>(0, rows, 4), body);
}

static int64_t kernel_size_of(int64_t K) {
    const int64_t k = static_cast<int64_t>(std::lround(std::sqrt(static_cast<double>(K))));
    OPENVINO_ASSERT(k * k == K && k % 2 == 1, "kernel logits need k*k channels with odd k, got ", K);
    return k;
}

class KernelApply : public ov::op::Op {
public:
    OPENVINO_OP("KernelApply", "denoiser");

    KernelApply() = default;
    KernelApply(const ov::Output<ov::Node>& x, const ov::Output<ov::Node>& logits, float scale, bool has_scale)
        : Op({x, logits}), m_scale(scale), m_has_scale(has_scale) {
        constructor_validate_and_infer_types();
    }

    void validate_and_infer_types() override {
        const auto& xs = get_input_partial_shape(0);
        const auto& ls = get_input_partial_shape(1);
        NODE_VALIDATION_CHECK(this, xs.rank().compatible(4) && ls.rank().compatible(4),
                              "KernelApply: x and logits must be 4-D, got ", xs, " and ", ls);
        NODE_VALIDATION_CHECK(this, get_input_element_type(0) == ov::element::f32 &&
                                        get_input_element_type(1) == ov::element::f32,
                              "KernelApply: f32 inputs only");
        set_output_type(0, ov::element::f32, xs);
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<KernelApply>(args.at(0), args.at(1), m_scale, m_has_scale);
    }

    bool visit_attributes(ov::AttributeVisitor& visitor) override {
        visitor.on_attribute("scale", m_scale);
        visitor.on_attribute("has_scale", m_has_scale);
        return true;
    }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const auto& xs = inputs[0].get_shape();
        const auto& ls = inputs[1].get_shape();
        const int64_t B = xs[0], C = xs[1], H = xs[2], W = xs[3];
        const int64_t k = kernel_size_of(ls[1]);
        OPENVINO_ASSERT(ls[0] == xs[0] && ls[2] == xs[2] && ls[3] == xs[3], "KernelApply: logits ", ls,
                        " do not match x ", xs);
        outputs[0].set_shape(xs);
        const float* X = inputs[0].data<const float>();
        const float* L = inputs[1].data<const float>();
        float* O = outputs[0].data<float>();
        const int64_t HW = H * W;
        parallel_rows(B * H, [&](const tbb::blocked_range<int64_t>& rows) {
            RowScratch t(W, C);
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / H, y = row % H;
                filter_row(X + b * C * HW, C, H, W, L + b * k * k * HW + y * W, HW, k, y, m_scale, m_has_scale, t);
                for (int64_t c = 0; c < C; ++c) {
                    float* o = O + (b * C + c) * HW + y * W;
                    std::memcpy(o, t.acc + c * W, W * sizeof(float));
                }
            }
        });
        return true;
    }

private:
    float m_scale = 1.0f;
    bool m_has_scale = false;
};

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

// dst (4 planes h x w) += bilinear upsampling of src (4 planes hs x ws), row y only.
static void add_upsampled_row(const float* src, int64_t hs, int64_t ws, const Lerp& ly, const std::vector<Lerp>& lx,
                              int64_t w, float* dst_row, int64_t dst_plane, int64_t channels) {
    for (int64_t c = 0; c < channels; ++c) {
        const float* r0 = src + (c * hs + ly.i0) * ws;
        const float* r1 = src + (c * hs + ly.i1) * ws;
        float* o = dst_row + c * dst_plane;
        for (int64_t px = 0; px < w; ++px) {
            const Lerp& l = lx[px];
            o[px] += ly.l0 * (l.l0 * r0[l.i0] + l.l1 * r0[l.i1]) + ly.l1 * (l.l0 * r1[l.i0] + l.l1 * r1[l.i1]);
        }
    }
}

class PyramidFilter : public ov::op::Op {
public:
    OPENVINO_OP("PyramidFilter", "denoiser");

    PyramidFilter() = default;
    PyramidFilter(const ov::OutputVector& args, std::vector<int64_t> kernel_sizes, float scale, bool has_scale)
        : Op(args), m_kernel_sizes(std::move(kernel_sizes)), m_scale(scale), m_has_scale(has_scale) {
        constructor_validate_and_infer_types();
    }

    void validate_and_infer_types() override {
        const int64_t L = static_cast<int64_t>(m_kernel_sizes.size());
        NODE_VALIDATION_CHECK(this, L >= 1 && static_cast<int64_t>(get_input_size()) == L + 1,
                              "PyramidFilter: needs x and one head per level (", L, " levels), got ",
                              get_input_size(), " inputs");
        for (size_t i = 0; i < get_input_size(); ++i)
            NODE_VALIDATION_CHECK(this, get_input_element_type(i) == ov::element::f32 &&
                                            get_input_partial_shape(i).rank().compatible(4),
                                  "PyramidFilter: 4-D f32 inputs only");
        set_output_type(0, ov::element::f32, get_input_partial_shape(0));
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<PyramidFilter>(args, m_kernel_sizes, m_scale, m_has_scale);
    }

    bool visit_attributes(ov::AttributeVisitor& visitor) override {
        visitor.on_attribute("kernel_sizes", m_kernel_sizes);
        visitor.on_attribute("scale", m_scale);
        visitor.on_attribute("has_scale", m_has_scale);
        return true;
    }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const int64_t L = static_cast<int64_t>(m_kernel_sizes.size());
        const auto& xs = inputs[0].get_shape();
        const int64_t B = xs[0], C = xs[1], H = xs[2], W = xs[3], C1 = C + 1;
        std::vector<int64_t> hs(L), ws(L);
        for (int64_t i = 0; i < L; ++i) {
            hs[i] = H >> i, ws[i] = W >> i;  // avg_pool2d(2^i) floors
            const auto& s = inputs[i + 1].get_shape();
            const int64_t k = m_kernel_sizes[i];
            OPENVINO_ASSERT(k % 2 == 1 && k >= 1, "PyramidFilter: kernel size ", k, " is not odd");
            OPENVINO_ASSERT(s[0] == xs[0] && s[1] == static_cast<size_t>(k * k + (i == 0 ? L : 0)) &&
                                s[2] == static_cast<size_t>(hs[i]) && s[3] == static_cast<size_t>(ws[i]),
                            "PyramidFilter: head ", i, " has shape ", s, " for x ", xs);
        }
        outputs[0].set_shape(xs);
        const float* X = inputs[0].data<const float>();
        const float* H0 = inputs[1].data<const float>();
        float* O = outputs[0].data<float>();
        const int64_t HW = H * W, K0 = m_kernel_sizes[0] * m_kernel_sizes[0];
        // level i's part: [B, C + 1, hs, ws]; levels >= 1 also keep their filtered sum (acc).
        // One allocation, kept between calls (fresh pages cost page faults on every frame).
        std::lock_guard<std::mutex> lock(m_mutex);
        std::vector<size_t> offsets{0};
        for (int64_t i = 0; i < L; ++i) {
            const size_t n = static_cast<size_t>(B * C1 * hs[i] * ws[i]);
            offsets.push_back(offsets.back() + n);
            if (i > 0) offsets.push_back(offsets.back() + n);
        }
        if (m_scratch.size() < offsets.back()) m_scratch.resize(offsets.back());
        std::vector<float*> parts(L), accs(L, nullptr);
        for (int64_t i = 0, o = 0; i < L; ++i) {
            parts[i] = m_scratch.data() + offsets[o++];
            if (i > 0) accs[i] = m_scratch.data() + offsets[o++];
        }
        // 1. the partition weights, level 0's part at full resolution and the coarser parts
        //    (average pools of w_i * [x, 1] by 2^i), in groups of 2^(L-1) rows: a coarse row's
        //    source rows all lie in one group, so each is written by one thread
        const int64_t G = int64_t(1) << (L - 1), groups = (H + G - 1) / G;
        parallel_rows(B * groups, [&](const tbb::blocked_range<int64_t>& range) {
            std::vector<float> s(W), tmp(W), m(W), sum(W), e(static_cast<size_t>(L * W));
            for (int64_t group = range.begin(); group != range.end(); ++group) {
                const int64_t b = group / groups, y_end = std::min(H, (group % groups + 1) * G);
                for (int64_t y = (group % groups) * G; y < y_end; ++y) {
                    const float* z = H0 + b * (L + K0) * HW + y * W;
                    logit_scale_row(z, L, HW, W, m_scale, m_has_scale, s.data(), tmp.data());
                    for (int64_t px = 0; px < W; ++px) m[px] = z[px] * s[px];
                    for (int64_t l = 1; l < L; ++l)
                        for (int64_t px = 0; px < W; ++px) m[px] = std::max(m[px], z[l * HW + px] * s[px]);
                    std::fill(sum.begin(), sum.end(), 0.0f);
                    for (int64_t l = 0; l < L; ++l)
                        for (int64_t px = 0; px < W; ++px) {
                            e[l * W + px] = exp_bounded(z[l * HW + px] * s[px] - m[px]);
                            sum[px] += e[l * W + px];
                        }
                    for (int64_t px = 0; px < W; ++px) sum[px] = 1.0f / sum[px];
                    for (int64_t l = 0; l < L; ++l) {
                        float* w = e.data() + l * W;
                        for (int64_t px = 0; px < W; ++px) w[px] *= sum[px];
                        const int64_t f = int64_t(1) << l, yc = y >> l, wc = ws[l];
                        if (yc >= hs[l]) continue;  // rows a floor-sized pool leaves out
                        float* dst = parts[l] + b * C1 * hs[l] * wc + yc * wc;
                        const int64_t plane = hs[l] * wc;
                        if (l == 0) {
                            for (int64_t c = 0; c < C; ++c) {
                                const float* xr = X + (b * C + c) * HW + y * W;
                                for (int64_t px = 0; px < W; ++px) dst[c * plane + px] = w[px] * xr[px];
                            }
                            std::memcpy(dst + C * plane, w, W * sizeof(float));
                            continue;
                        }
                        if (y % f == 0)
                            for (int64_t c = 0; c < C1; ++c) std::fill(dst + c * plane, dst + c * plane + wc, 0.0f);
                        for (int64_t c = 0; c < C1; ++c) {
                            float* d = dst + c * plane;
                            if (c < C) {
                                const float* xr = X + (b * C + c) * HW + y * W;
                                for (int64_t px = 0; px < wc; ++px)
                                    for (int64_t dx = 0; dx < f; ++dx) d[px] += w[px * f + dx] * xr[px * f + dx];
                            } else {  // the constant channel: the pooled weights
                                for (int64_t px = 0; px < wc; ++px)
                                    for (int64_t dx = 0; dx < f; ++dx) d[px] += w[px * f + dx];
                            }
                            if (y % f == f - 1) {
                                const float norm = 1.0f / static_cast<float>(f * f);
                                for (int64_t px = 0; px < wc; ++px) d[px] *= norm;
                            }
                        }
                    }
                }
            }
        });
        // 3. from the coarsest level up: acc_i = filter_i(part_i) + up(acc_{i+1}); level 0 divides
        for (int64_t i = L - 1; i >= 0; --i) {
            const int64_t h = hs[i], w = ws[i], k = m_kernel_sizes[i], plane = h * w;
            const float* Z = i == 0 ? H0 + L * HW : inputs[i + 1].data<const float>();
            const int64_t zb = (i == 0 ? L + K0 : k * k) * plane;  // logits per image
            std::vector<Lerp> ly, lx;
            if (i < L - 1) ly = bilinear_axis(hs[i + 1], h), lx = bilinear_axis(ws[i + 1], w);
            parallel_rows(B * h, [&](const tbb::blocked_range<int64_t>& rows) {
                RowScratch t(w, C1);
                for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                    const int64_t b = row / h, y = row % h;
                    filter_row(parts[i] + b * C1 * plane, C1, h, w, Z + b * zb + y * w, plane, k, y, m_scale,
                               m_has_scale, t);
                    if (i < L - 1)
                        add_upsampled_row(accs[i + 1] + b * C1 * hs[i + 1] * ws[i + 1], hs[i + 1], ws[i + 1],
                                          ly[y], lx, w, t.acc, w, C1);
                    if (i > 0) {
                        for (int64_t c = 0; c < C1; ++c)
                            std::memcpy(accs[i] + (b * C1 + c) * plane + y * w, t.acc + c * w, w * sizeof(float));
                        continue;
                    }
                    const float* den = t.acc + C * w;
                    for (int64_t c = 0; c < C; ++c) {
                        const float* a = t.acc + c * w;
                        const float* xr = X + (b * C + c) * HW + y * W;
                        float* o = O + (b * C + c) * HW + y * W;
                        for (int64_t px = 0; px < w; ++px)
                            o[px] = den[px] > NORM_EPS ? a[px] / std::max(den[px], NORM_EPS) : xr[px];
                    }
                }
            });
        }
        return true;
    }

private:
    std::vector<int64_t> m_kernel_sizes;
    float m_scale = 1.0f;
    bool m_has_scale = false;
    mutable std::mutex m_mutex;
    mutable std::vector<float> m_scratch;  // the parts and sums, reused between calls
};

// log(1 + x) elementwise, as ONNX's Log(Add(x, 1)) computes it (the exported form of
// torch.log1p): Cephes' logf on u = 1 + x (at most 0.8 ulp on every 97th positive normal float),
// branch-free so the loop vectorises; u outside the normal positive finite floats (0, negative,
// subnormal, +inf, NaN) is redone by std::log in a second pass.
static inline float log_normal(float u) {
    int32_t bits;
    std::memcpy(&bits, &u, sizeof(bits));
    float e = static_cast<float>(((bits >> 23) & 0xff) - 126);
    bits = (bits & 0x807fffff) | 0x3f000000;  // mantissa in [0.5, 1)
    float m;
    std::memcpy(&m, &bits, sizeof(m));
    const float low = m < 0.707106781186547524f ? 1.0f : 0.0f;
    e -= low;
    const float f = m + low * m - 1.0f;
    const float z = f * f;
    float p = 7.0376836292e-2f;
    p = std::fma(p, f, -1.1514610310e-1f);
    p = std::fma(p, f, 1.1676998740e-1f);
    p = std::fma(p, f, -1.2420140846e-1f);
    p = std::fma(p, f, 1.4249322787e-1f);
    p = std::fma(p, f, -1.6668057665e-1f);
    p = std::fma(p, f, 2.0000714765e-1f);
    p = std::fma(p, f, -2.4999993993e-1f);
    p = std::fma(p, f, 3.3333331174e-1f);
    float y = f * z * p;
    y = std::fma(e, -2.12194440e-4f, y);
    y = std::fma(z, -0.5f, y);
    return std::fma(e, 0.693359375f, f + y);
}

static void log1p_range(const float* x, float* y, int64_t begin, int64_t end) {
    for (int64_t i = begin; i < end; ++i) y[i] = log_normal(1.0f + x[i]);
    for (int64_t i = begin; i < end; ++i) {
        const float u = 1.0f + x[i];
        if (!(u >= std::numeric_limits<float>::min() && u <= std::numeric_limits<float>::max())) y[i] = std::log(u);
    }
}

class Log1p : public ov::op::Op {
public:
    OPENVINO_OP("Log1p", "denoiser");

    Log1p() = default;
    explicit Log1p(const ov::Output<ov::Node>& x) : Op({x}) { constructor_validate_and_infer_types(); }

    void validate_and_infer_types() override {
        NODE_VALIDATION_CHECK(this, get_input_element_type(0) == ov::element::f32, "Log1p: f32 input only");
        set_output_type(0, ov::element::f32, get_input_partial_shape(0));
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<Log1p>(args.at(0));
    }

    bool visit_attributes(ov::AttributeVisitor&) override { return true; }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        outputs[0].set_shape(inputs[0].get_shape());
        const float* x = inputs[0].data<const float>();
        float* y = outputs[0].data<float>();
        const int64_t n = static_cast<int64_t>(inputs[0].get_size());
        tbb::parallel_for(tbb::blocked_range<int64_t>(0, n, 1 << 14), [&](const tbb::blocked_range<int64_t>& r) {
            log1p_range(x, y, r.begin(), r.end());
        });
        return true;
    }
};

// AddUpsampled(a [B, C, H, W], z [B, C, h, w]; attribute mode "bilinear" | "nearest") ->
// a + F.interpolate(z, size=(H, W), mode, align_corners=False) (torch's coordinates; nearest:
// floor(dst * h / H)), planar in and out: the level-0 head with its upsampled part multiplied
// at half resolution (denoiser.nn.unet.UNet.head0_before_upsampling). In the plain graph the
// upsampling's output came channels-last and the head's channel split then ran as a reference
// VariadicSplit.
class AddUpsampled : public ov::op::Op {
public:
    OPENVINO_OP("AddUpsampled", "denoiser");

    AddUpsampled() = default;
    AddUpsampled(const ov::Output<ov::Node>& a, const ov::Output<ov::Node>& z, std::string mode)
        : Op({a, z}), m_mode(std::move(mode)) {
        constructor_validate_and_infer_types();
    }

    void validate_and_infer_types() override {
        NODE_VALIDATION_CHECK(this, m_mode == "bilinear" || m_mode == "nearest",
                              "AddUpsampled: mode must be bilinear or nearest, got ", m_mode);
        NODE_VALIDATION_CHECK(this, get_input_element_type(0) == ov::element::f32 &&
                                        get_input_element_type(1) == ov::element::f32,
                              "AddUpsampled: f32 inputs only");
        set_output_type(0, ov::element::f32, get_input_partial_shape(0));
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<AddUpsampled>(args.at(0), args.at(1), m_mode);
    }

    bool visit_attributes(ov::AttributeVisitor& visitor) override {
        visitor.on_attribute("mode", m_mode);
        return true;
    }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const auto& as = inputs[0].get_shape();
        const auto& zs = inputs[1].get_shape();
        OPENVINO_ASSERT(as.size() == 4 && zs.size() == 4 && as[0] == zs[0] && as[1] == zs[1],
                        "AddUpsampled: ", as, " and ", zs, " do not match");
        const int64_t B = as[0], C = as[1], H = as[2], W = as[3], h = zs[2], w = zs[3];
        outputs[0].set_shape(as);
        const float* A = inputs[0].data<const float>();
        const float* Z = inputs[1].data<const float>();
        float* O = outputs[0].data<float>();
        const bool bilinear = m_mode == "bilinear";
        std::vector<Lerp> ly, lx;
        if (bilinear) {
            ly = bilinear_axis(h, H), lx = bilinear_axis(w, W);
        } else {  // nearest: one tap, weight 1
            const auto nearest = [](int64_t n_in, int64_t n_out) {
                std::vector<Lerp> out(static_cast<size_t>(n_out));
                const float ratio = static_cast<float>(n_in) / static_cast<float>(n_out);
                for (int64_t d = 0; d < n_out; ++d) {
                    const int64_t i = std::min<int64_t>(static_cast<int64_t>(std::floor(d * ratio)), n_in - 1);
                    out[d] = {i, i, 1.0f, 0.0f};
                }
                return out;
            };
            ly = nearest(h, H), lx = nearest(w, W);
        }
        const bool exact2x = bilinear && H == 2 * h && W == 2 * w && w >= 2;
        parallel_rows(B * H, [&](const tbb::blocked_range<int64_t>& rows) {
            std::vector<float> t(static_cast<size_t>(w)), even(static_cast<size_t>(w)), odd(static_cast<size_t>(w));
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / H, y = row % H;
                if (!exact2x) {
                    for (int64_t c = 0; c < C; ++c)
                        std::memcpy(O + ((b * C + c) * H + y) * W, A + ((b * C + c) * H + y) * W, W * sizeof(float));
                    add_upsampled_row(Z + b * C * h * w, h, w, ly[y], lx, W, O + (b * C * H + y) * W, H * W, C);
                    continue;
                }
                // exact 2x bilinear: the two source rows blended, then columns 2m and 2m + 1 at
                // 1/4 and 3/4 between source columns m - 1, m and m, m + 1 (the ends clamped)
                const Lerp& l = ly[y];
                for (int64_t c = 0; c < C; ++c) {
                    const float* z0 = Z + ((b * C + c) * h + l.i0) * w;
                    const float* z1 = Z + ((b * C + c) * h + l.i1) * w;
                    for (int64_t m = 0; m < w; ++m) t[m] = l.l0 * z0[m] + l.l1 * z1[m];
                    even[0] = t[0], odd[w - 1] = t[w - 1];
                    for (int64_t m = 1; m < w; ++m) {
                        even[m] = 0.25f * t[m - 1] + 0.75f * t[m];
                        odd[m - 1] = 0.75f * t[m - 1] + 0.25f * t[m];
                    }
                    const float* a = A + ((b * C + c) * H + y) * W;
                    float* o = O + ((b * C + c) * H + y) * W;
                    for (int64_t m = 0; m < w; ++m) {
                        o[2 * m] = a[2 * m] + even[m];
                        o[2 * m + 1] = a[2 * m + 1] + odd[m];
                    }
                }
            }
        });
        return true;
    }

private:
    std::string m_mode = "bilinear";
};

}  // namespace denoiser

OPENVINO_CREATE_EXTENSIONS(std::vector<ov::Extension::Ptr>({
    std::make_shared<ov::OpExtension<denoiser::KernelApply>>(),
    std::make_shared<ov::OpExtension<denoiser::PyramidFilter>>(),
    std::make_shared<ov::OpExtension<denoiser::Log1p>>(),
    std::make_shared<ov::OpExtension<denoiser::AddUpsampled>>(),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "AddUpsampled", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            return std::make_shared<denoiser::AddUpsampled>(ctx.get_input(0), ctx.get_input(1),
                                                            ctx.get_attribute<std::string>("mode"))->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "Log1p", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            return std::make_shared<denoiser::Log1p>(ctx.get_input(0))->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "KernelApply", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            const float scale = ctx.get_attribute<float>("scale", 1.0f);
            const int64_t has_scale = ctx.get_attribute<int64_t>("has_scale", 0);
            return std::make_shared<denoiser::KernelApply>(ctx.get_input(0), ctx.get_input(1), scale,
                                                           has_scale != 0)->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "PyramidFilter", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            ov::OutputVector args;
            for (size_t i = 0; i < ctx.get_input_size(); ++i) args.push_back(ctx.get_input(static_cast<int>(i)));
            const auto sizes = ctx.get_attribute<std::vector<int64_t>>("kernel_sizes");
            const float scale = ctx.get_attribute<float>("scale", 1.0f);
            const int64_t has_scale = ctx.get_attribute<int64_t>("has_scale", 0);
            return std::make_shared<denoiser::PyramidFilter>(args, sizes, scale, has_scale != 0)->outputs();
        }),
}));
