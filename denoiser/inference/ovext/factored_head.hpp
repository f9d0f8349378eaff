// FactoredHead(skip [B, H, W, Cs] channels-last, weight [N, Cs], z [B, N, h, w]; attribute mode
//   "bilinear" | "nearest") -> [B, N, H, W] f32 planar:
//
//     head[t, p] = sum_c weight[t, c] * skip[p, c] + F.interpolate(z, (H, W), mode)[t, p]
//
//   denoiser.nn.unet.FactoredHead.tensor: a 1x1 head of [skip0, up(half)] from its factors (the
//   upsampled part's product taken at half resolution, the bias in z), row by row as
//   PyramidFilterHead computes its head (FactoredHead0, pyramid_filter_head.hpp). In the plain
//   graph it was a matrix product over skip's channels-last rows (written planar) and an
//   AddUpsampled pass reading and writing the head again: the temporal head's 6 channels of the
//   demo student, about 17-21 ms of its f32 1080p step.
#pragma once

#include "pyramid_filter_head.hpp"

namespace denoiser {

class FactoredHead : public ov::op::Op {
public:
    OPENVINO_OP("FactoredHead", "denoiser");

    FactoredHead() = default;
    FactoredHead(const ov::Output<ov::Node>& skip, const ov::Output<ov::Node>& weight, const ov::Output<ov::Node>& z,
                 std::string mode)
        : Op({skip, weight, z}), m_mode(std::move(mode)) {
        constructor_validate_and_infer_types();
    }

    void validate_and_infer_types() override {
        NODE_VALIDATION_CHECK(this, m_mode == "bilinear" || m_mode == "nearest",
                              "FactoredHead: mode must be bilinear or nearest, got ", m_mode);
        for (size_t i = 0; i < 3; ++i)
            NODE_VALIDATION_CHECK(this, get_input_element_type(i) == ov::element::f32, "FactoredHead: f32 inputs only");
        const auto& s = get_input_partial_shape(0);
        const auto& z = get_input_partial_shape(2);
        if (s.rank().is_static() && z.rank().is_static()) {
            set_output_type(0, ov::element::f32, ov::PartialShape{s[0], z[1], s[1], s[2]});
        } else {
            set_output_type(0, ov::element::f32, ov::PartialShape::dynamic(4));
        }
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<FactoredHead>(args.at(0), args.at(1), args.at(2), m_mode);
    }

    bool visit_attributes(ov::AttributeVisitor& visitor) override {
        visitor.on_attribute("mode", m_mode);
        return true;
    }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const auto& ss = inputs[0].get_shape();
        const auto& ws = inputs[1].get_shape();
        const auto& zs = inputs[2].get_shape();
        OPENVINO_ASSERT(ss.size() == 4 && ws.size() == 2 && ws[1] == ss[3] && zs.size() == 4 && zs[0] == ss[0] &&
                            zs[1] == ws[0] && zs[2] >= 1 && zs[3] >= 1,
                        "FactoredHead: skip ", ss, " (channels-last), weight ", ws, " and z ", zs, " do not match");
        const int64_t B = ss[0], H = ss[1], W = ss[2], N = ws[0];
        outputs[0].set_shape({ss[0], ws[0], ss[1], ss[2]});
        const Upsampling up(zs[2], zs[3], H, W, m_mode == "bilinear");
        const FactoredHead0 head{inputs[0].data<const float>(), inputs[1].data<const float>(),
                                 inputs[2].data<const float>(), N, static_cast<int64_t>(ss[3]), H, W,
                                 static_cast<int64_t>(zs[2]), static_cast<int64_t>(zs[3]), 1, &up};
        float* O = outputs[0].data<float>();
        parallel_rows(B * H, [&](const tbb::blocked_range<int64_t>& rows) {
            std::vector<float> buf(static_cast<size_t>(head.scratch_floats(N)));
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / H, y = row % H;
                head.load(b, y, buf.data());
                const Head0Rows r = head.rows(b, y, 0, N, buf.data());
                for (int64_t t = 0; t < N; ++t)
                    std::memcpy(O + ((b * N + t) * H + y) * W, r.data + t * r.plane, W * sizeof(float));
            }
        });
        return true;
    }

private:
    std::string m_mode = "bilinear";
};

}  // namespace denoiser
