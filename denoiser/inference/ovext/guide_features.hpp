// GuideFeatures(albedo [B, 3, H, W], normal [B, 3, H, W], depth [B, 1, H, W], mean [B, 1, 1, 1];
//   attributes albedo_max, depth_far, posinf) -> [B, 7, H, W] f32: denoiser.nn.inputs.guide_features,
//   the auxiliary buffers' features in one pass, each value first sanitised as
//   denoiser.nonfinite says (NaN and -inf -> 0, +inf -> posinf):
//
//     channels 0-2  log1p(clamp(albedo, 0, albedo_max))   (the log1p as denoiser::Log1p: log1p.hpp)
//     channels 3-5  clamp(normal, -1, 1)
//     channel  6    d / (d + mean),  d = clamp(depth, 0, depth_far)
//
//   mean: the image's mean hit depth plus its epsilon (denoiser.nn.inputs.depth_mean, a reduction
//   the graph computes). In the plain graph these were a sanitising and clamping pass per buffer,
//   a Log1p pass, the depth's division and a concatenation, each at full resolution.
#pragma once

#include "common.hpp"
#include "log1p.hpp"

namespace denoiser {

class GuideFeatures : public ov::op::Op {
public:
    OPENVINO_OP("GuideFeatures", "denoiser");

    GuideFeatures() = default;
    GuideFeatures(const ov::OutputVector& args, float albedo_max, float depth_far, float posinf)
        : Op(args), m_albedo_max(albedo_max), m_depth_far(depth_far), m_posinf(posinf) {
        constructor_validate_and_infer_types();
    }

    void validate_and_infer_types() override {
        NODE_VALIDATION_CHECK(this, get_input_size() == 4, "GuideFeatures: needs albedo, normal, depth and mean");
        for (size_t i = 0; i < 4; ++i)
            NODE_VALIDATION_CHECK(this, get_input_element_type(i) == ov::element::f32, "GuideFeatures: f32 inputs only");
        auto shape = get_input_partial_shape(0);
        if (shape.rank().is_static()) {
            NODE_VALIDATION_CHECK(this, shape.rank().get_length() == 4, "GuideFeatures: albedo must be [B, 3, H, W]");
            shape[1] = 7;
        } else {
            shape = ov::PartialShape::dynamic(4);
        }
        set_output_type(0, ov::element::f32, shape);
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<GuideFeatures>(args, m_albedo_max, m_depth_far, m_posinf);
    }

    bool visit_attributes(ov::AttributeVisitor& visitor) override {
        visitor.on_attribute("albedo_max", m_albedo_max);
        visitor.on_attribute("depth_far", m_depth_far);
        visitor.on_attribute("posinf", m_posinf);
        return true;
    }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const auto& as = inputs[0].get_shape();
        OPENVINO_ASSERT(as.size() == 4 && as[1] == 3, "GuideFeatures: albedo has shape ", as);
        const auto& ns = inputs[1].get_shape();
        const auto& ds = inputs[2].get_shape();
        OPENVINO_ASSERT(ns == as && ds.size() == 4 && ds[0] == as[0] && ds[1] == 1 && ds[2] == as[2] &&
                            ds[3] == as[3] && inputs[3].get_size() == as[0],
                        "GuideFeatures: normal ", ns, ", depth ", ds, " and mean ", inputs[3].get_shape(),
                        " for albedo ", as);
        const int64_t B = as[0], H = as[2], W = as[3], HW = H * W;
        outputs[0].set_shape({as[0], 7, as[2], as[3]});
        const float* A = inputs[0].data<const float>();
        const float* N = inputs[1].data<const float>();
        const float* D = inputs[2].data<const float>();
        const float* mean = inputs[3].data<const float>();
        float* O = outputs[0].data<float>();
        const float inf = std::numeric_limits<float>::infinity(), posinf = m_posinf;
        // the rule of denoiser.nonfinite (the comparisons are false for NaN)
        auto sanitized = [inf, posinf](float v) { return v == inf ? posinf : (v > -inf ? v : 0.0f); };
        parallel_rows(B * H, [&](const tbb::blocked_range<int64_t>& rows) {
            std::vector<float> u(static_cast<size_t>(3 * W));
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / H, y = row % H;
                float* o = O + b * 7 * HW + y * W;
                for (int64_t c = 0; c < 3; ++c) {
                    const float* a = A + (b * 3 + c) * HW + y * W;
                    const float* n = N + (b * 3 + c) * HW + y * W;
                    float* on = o + (3 + c) * HW;
                    for (int64_t px = 0; px < W; ++px) {
                        u[c * W + px] = std::min(std::max(sanitized(a[px]), 0.0f), m_albedo_max);
                        on[px] = std::min(std::max(sanitized(n[px]), -1.0f), 1.0f);
                    }
                }
                for (int64_t c = 0; c < 3; ++c) log1p_range(u.data() + c * W, o + c * HW, 0, W);
                const float* d = D + b * HW + y * W;
                float* od = o + 6 * HW;
                const float mb = mean[b];
                for (int64_t px = 0; px < W; ++px) {
                    const float v = std::min(std::max(sanitized(d[px]), 0.0f), m_depth_far);
                    od[px] = v / (v + mb);
                }
            }
        });
        return true;
    }

private:
    float m_albedo_max = 100.0f;
    float m_depth_far = 1e10f;
    float m_posinf = 65504.0f;
};

}  // namespace denoiser
