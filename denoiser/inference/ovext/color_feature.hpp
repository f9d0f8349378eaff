// ColorFeature(x [B, C, H, W], scale [B, 1, 1, 1]) -> [B, H, W, C] f32 channels-last:
//   log1p(max(x, 0) / scale), denoiser.nn.inputs.color_feature (max keeps NaN, as clamp_min
//   does; the quotient a division, the log1p as denoiser::Log1p computes it: log1p.hpp).
//
// The history's color parts of the U-Net's input (its warped output and color) in the layout the
// U-Net's first convolution reads: the exported graph's transpose back to [B, C, H, W] costs
// nothing. In the plain graph they were a Clip-and-Divide pass, a Log1p pass and a reorder into
// the convolution, each reading and writing the part at full resolution (about 10 ms of the demo
// student's f32 1080p step per part).
#pragma once

#include "common.hpp"
#include "log1p.hpp"

namespace denoiser {

// dst[3 p + c] = src[c * plane + p] for p < n, c < 3: a loop the compilers vectorise with the
// ISA's two-source permutes (three vectors of pixels in, three interleaved out).
static inline void interleave3(const float* __restrict src, int64_t plane, int64_t n, float* __restrict dst) {
    const float *c0 = src, *c1 = src + plane, *c2 = src + 2 * plane;
    for (int64_t p = 0; p < n; ++p) {
        dst[3 * p] = c0[p];
        dst[3 * p + 1] = c1[p];
        dst[3 * p + 2] = c2[p];
    }
}

class ColorFeature : public ov::op::Op {
public:
    OPENVINO_OP("ColorFeature", "denoiser");

    ColorFeature() = default;
    ColorFeature(const ov::Output<ov::Node>& x, const ov::Output<ov::Node>& scale) : Op({x, scale}) {
        constructor_validate_and_infer_types();
    }

    void validate_and_infer_types() override {
        NODE_VALIDATION_CHECK(this, get_input_element_type(0) == ov::element::f32 &&
                                        get_input_element_type(1) == ov::element::f32,
                              "ColorFeature: f32 inputs only");
        auto shape = get_input_partial_shape(0);
        if (shape.rank().is_static()) {
            NODE_VALIDATION_CHECK(this, shape.rank().get_length() == 4, "ColorFeature: x must be [B, C, H, W]");
            shape = ov::PartialShape{shape[0], shape[2], shape[3], shape[1]};
        } else {
            shape = ov::PartialShape::dynamic(4);
        }
        set_output_type(0, ov::element::f32, shape);
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<ColorFeature>(args.at(0), args.at(1));
    }

    bool visit_attributes(ov::AttributeVisitor&) override { return true; }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const auto& xs = inputs[0].get_shape();
        OPENVINO_ASSERT(xs.size() == 4, "ColorFeature: x has shape ", xs);
        OPENVINO_ASSERT(inputs[1].get_size() == xs[0], "ColorFeature: scale has shape ", inputs[1].get_shape(),
                        " for x ", xs);
        const int64_t B = xs[0], C = xs[1], H = xs[2], W = xs[3];
        outputs[0].set_shape({xs[0], xs[2], xs[3], xs[1]});
        const float* X = inputs[0].data<const float>();
        const float* scale = inputs[1].data<const float>();
        float* O = outputs[0].data<float>();
        parallel_rows(B * H, [&](const tbb::blocked_range<int64_t>& rows) {
            std::vector<float> u(static_cast<size_t>(C * W)), y(static_cast<size_t>(C * W));
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / H, yy = row % H;
                const float s = scale[b];
                for (int64_t c = 0; c < C; ++c) {
                    const float* xr = X + ((b * C + c) * H + yy) * W;
                    float* ur = u.data() + c * W;
                    for (int64_t px = 0; px < W; ++px) ur[px] = std::max(xr[px], 0.0f) / s;
                }
                log1p_range(u.data(), y.data(), 0, C * W);
                float* orow = O + (b * H + yy) * W * C;
                if (C == 3) {  // the three channels interleaved by vector permutes
                    interleave3(y.data(), W, W, orow);
                    continue;
                }
                for (int64_t px = 0; px < W; ++px)
                    for (int64_t c = 0; c < C; ++c) orow[px * C + c] = y[c * W + px];
            }
        });
        return true;
    }
};

}  // namespace denoiser
