// KernelApply(x [B, C, H, W] f32, logits [B, k*k, H, W] f32; attributes scale, has_scale)
//   -> [B, C, H, W] f32: denoiser.nn.kernels.apply_kernels_graph. For every pixel p
//   (r = k / 2, tap t = i*k + j, i rows, j columns):
//
//   z_t   = logits[b, t, p] * s(p),  s(p) = scale / sqrt(var_t(logits[b, :, p]) + 1)  (has_scale)
//                                    s(p) = 1                                         (otherwise)
//   w     = softmax over the taps t that read inside the image of z
//   out_c = sum_t w_t * x[b, c, p + (i - r, j - r)]
//
// One image row at a time: the logits of a row are read from cache, the taps' exponentials are
// computed once and each input pixel of the k rows a tap needs is read once, instead of k*k
// materialised shifted copies and several passes over the weights in the plain graph.
#pragma once

#include "common.hpp"

namespace denoiser {

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
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / H, y = row % H;
                filter_row(planar_rows(X + b * C * HW, H, W, k, y), C, W, L + b * k * k * HW + y * W, HW, k, m_scale,
                           m_has_scale, O + b * C * HW + y * W, HW);
            }
        });
        return true;
    }

private:
    float m_scale = 1.0f;
    bool m_has_scale = false;
};

}  // namespace denoiser
