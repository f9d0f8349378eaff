// AddUpsampled(a [B, C, H, W], z [B, C, h, w]; attribute mode "bilinear" | "nearest") ->
// a + F.interpolate(z, size=(H, W), mode, align_corners=False) (torch's coordinates; nearest:
// floor(dst * h / H)), planar in and out: the level-0 head with its upsampled part multiplied
// at half resolution (denoiser.nn.unet.UNet.head0_before_upsampling). In the plain graph the
// upsampling's output came channels-last and the head's channel split then ran as a reference
// VariadicSplit.
#pragma once

#include "common.hpp"

namespace denoiser {

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
        const Upsampling up(h, w, H, W, m_mode == "bilinear");
        parallel_rows(B * H, [&](const tbb::blocked_range<int64_t>& rows) {
            std::vector<float> t(static_cast<size_t>(w));
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / H, y = row % H;
                float* o = O + (b * C * H + y) * W;
                up.row(Z + b * C * h * w, C, y, o, H * W, t.data());
                for (int64_t c = 0; c < C; ++c) {
                    const float* a = A + ((b * C + c) * H + y) * W;
                    for (int64_t px = 0; px < W; ++px) o[c * H * W + px] += a[px];
                }
            }
        });
        return true;
    }

private:
    std::string m_mode = "bilinear";
};

}  // namespace denoiser
