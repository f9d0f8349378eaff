// OpenVINO CPU extension: the per-pixel kernel filter of denoiser.nn.kernels as one operation.
//
// KernelApply(x [B, C, H, W] f32, logits [B, k*k, H, W] f32; attributes scale, has_scale)
//   -> [B, C, H, W] f32, with, for every pixel p (r = k / 2, tap t = i*k + j, i rows, j columns):
//
//   z_t   = logits[b, t, p] * s(p),  s(p) = scale / sqrt(var_t(logits[b, :, p]) + 1)  (has_scale)
//                                    s(p) = 1                                         (otherwise)
//   w     = softmax over the taps t that read inside the image of z
//   out_c = sum_t w_t * x[b, c, p + (i - r, j - r)]
//
// the same function as denoiser.nn.kernels.apply_kernels_graph (its docstring is the reference).
// One pass per image row: the logits of a row are read from cache, the taps' exponentials are
// computed once and each input pixel of the k rows it needs is read once per tap, instead of
// k*k materialised shifted copies and several passes over the weights in the plain graph.
// Rows run in parallel on the calling TBB arena (the CPU plugin's, so INFERENCE_NUM_THREADS holds).
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include <openvino/core/extension.hpp>
#include <openvino/core/op_extension.hpp>
#include <openvino/frontend/onnx/extension/conversion.hpp>
#include <openvino/frontend/node_context.hpp>
#include <openvino/op/op.hpp>
#include <tbb/blocked_range.h>
#include <tbb/parallel_for.h>

namespace denoiser {

// exp(x) for x <= 0 (a softmax's centred logits), about 2 ulp; 0 below -87.
// Cody-Waite reduction x = n ln2 + f, degree-6 polynomial on |f| <= ln2 / 2, 2^n by the exponent
// bits. Branch-free so the row loops vectorise.
static inline float exp_nonpositive(float x) {
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
        const int64_t B = xs[0], C = xs[1], H = xs[2], W = xs[3], K = ls[1];
        const int64_t k = static_cast<int64_t>(std::lround(std::sqrt(static_cast<double>(K))));
        OPENVINO_ASSERT(k * k == K && k % 2 == 1 && ls[0] == xs[0] && ls[2] == xs[2] && ls[3] == xs[3],
                        "KernelApply: logits ", ls, " do not match x ", xs);
        outputs[0].set_shape(xs);
        const float* X = inputs[0].data<const float>();
        const float* L = inputs[1].data<const float>();
        float* O = outputs[0].data<float>();
        const int64_t r = k / 2;
        const float scale = m_scale;
        const bool has_scale = m_has_scale;
        tbb::parallel_for(tbb::blocked_range<int64_t>(0, B * H, 4), [&](const tbb::blocked_range<int64_t>& rows) {
            std::vector<float> buf(static_cast<size_t>(W) * (4 + C));
            float* s = buf.data();
            float* m = s + W;
            float* sum = m + W;
            float* e = sum + W;
            float* acc = e + W;
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / H, y = row % H;
                const float* Lb = L + b * K * H * W + y * W;  // tap t's row at Lb + t*H*W
                const float* Xb = X + b * C * H * W;
                // the logits' scale per pixel (two-pass variance over the taps, as torch.var)
                if (has_scale) {
                    std::fill(m, m + W, 0.0f);
                    for (int64_t t = 0; t < K; ++t) {
                        const float* z = Lb + t * H * W;
                        for (int64_t px = 0; px < W; ++px) m[px] += z[px];
                    }
                    for (int64_t px = 0; px < W; ++px) m[px] *= 1.0f / K;
                    std::fill(sum, sum + W, 0.0f);
                    for (int64_t t = 0; t < K; ++t) {
                        const float* z = Lb + t * H * W;
                        for (int64_t px = 0; px < W; ++px) {
                            const float d = z[px] - m[px];
                            sum[px] += d * d;
                        }
                    }
                    for (int64_t px = 0; px < W; ++px) s[px] = scale / std::sqrt(sum[px] * (1.0f / K) + 1.0f);
                } else {
                    std::fill(s, s + W, 1.0f);
                }
                // the largest in-image scaled logit; the centre tap is always in the image
                {
                    const float* z = Lb + (r * k + r) * H * W;
                    for (int64_t px = 0; px < W; ++px) m[px] = z[px] * s[px];
                }
                for (int64_t i = 0; i < k; ++i) {
                    const int64_t yy = y + i - r;
                    if (yy < 0 || yy >= H) continue;
                    for (int64_t j = 0; j < k; ++j) {
                        const int64_t d = j - r, x0 = std::max<int64_t>(0, -d), x1 = std::min<int64_t>(W, W - d);
                        const float* z = Lb + (i * k + j) * H * W;
                        for (int64_t px = x0; px < x1; ++px) m[px] = std::max(m[px], z[px] * s[px]);
                    }
                }
                std::fill(sum, sum + W, 0.0f);
                std::fill(acc, acc + C * W, 0.0f);
                for (int64_t i = 0; i < k; ++i) {
                    const int64_t yy = y + i - r;
                    if (yy < 0 || yy >= H) continue;
                    for (int64_t j = 0; j < k; ++j) {
                        const int64_t d = j - r, x0 = std::max<int64_t>(0, -d), x1 = std::min<int64_t>(W, W - d);
                        const float* z = Lb + (i * k + j) * H * W;
                        for (int64_t px = x0; px < x1; ++px) {
                            e[px] = exp_nonpositive(z[px] * s[px] - m[px]);
                            sum[px] += e[px];
                        }
                        for (int64_t c = 0; c < C; ++c) {
                            const float* xr = Xb + (c * H + yy) * W + d;
                            float* a = acc + c * W;
                            for (int64_t px = x0; px < x1; ++px) a[px] += e[px] * xr[px];
                        }
                    }
                }
                for (int64_t px = 0; px < W; ++px) sum[px] = 1.0f / sum[px];
                for (int64_t c = 0; c < C; ++c) {
                    float* o = O + ((b * C + c) * H + y) * W;
                    const float* a = acc + c * W;
                    for (int64_t px = 0; px < W; ++px) o[px] = a[px] * sum[px];
                }
            }
        });
        return true;
    }

private:
    float m_scale = 1.0f;
    bool m_has_scale = false;
};

}  // namespace denoiser

OPENVINO_CREATE_EXTENSIONS(std::vector<ov::Extension::Ptr>({
    std::make_shared<ov::OpExtension<denoiser::KernelApply>>(),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "KernelApply", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            const float scale = ctx.get_attribute<float>("scale", 1.0f);
            const int64_t has_scale = ctx.get_attribute<int64_t>("has_scale", 0);
            return std::make_shared<denoiser::KernelApply>(ctx.get_input(0), ctx.get_input(1), scale,
                                                           has_scale != 0)->outputs();
        }),
}));
