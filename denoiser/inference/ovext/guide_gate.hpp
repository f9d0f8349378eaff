// GuideGate(previous [B, 7, H, W] or, with previous_channels_last 1, [B, H, W, 7] (as WarpHistory
//   writes it for the convolution that also reads it), current [B, 7, H, W]; attributes threshold,
//   previous_channels_last) -> [B, 1, H, W] f32:
//   the disocclusion gate clamp(2 - D / threshold, 0, 1) of denoiser.nn.temporal.TemporalRecurrence.gate,
//   D = denoiser.nn.temporal.guide_disagreement of the warped and the current guide features
//   (albedo 3, normal 3, depth feature 1; its docstring and the module's are the definition):
//   the max of the albedo's excess over the current albedo's 3x3 [min, max] (edges replicated),
//   the normals' 1 - cos (1 where one normal is missing, 0 where both are) and the depth
//   features' absolute log ratio.
//
// In the plain graph the 3x3 min and max were twelve full-resolution slices and the rest a
// dozen elementwise passes; here each output row reads three rows of the current albedo once.
#pragma once

#include "common.hpp"
#include "log1p.hpp"

namespace denoiser {

constexpr float DEPTH_LOGIT_EPS = 1e-6f;  // denoiser.nn.temporal.DEPTH_LOGIT_EPS

class GuideGate : public ov::op::Op {
public:
    OPENVINO_OP("GuideGate", "denoiser");

    GuideGate() = default;
    GuideGate(const ov::Output<ov::Node>& previous, const ov::Output<ov::Node>& current, float threshold,
              int64_t previous_channels_last)
        : Op({previous, current}), m_threshold(threshold), m_previous_channels_last(previous_channels_last) {
        constructor_validate_and_infer_types();
    }

    void validate_and_infer_types() override {
        for (size_t i = 0; i < 2; ++i)
            NODE_VALIDATION_CHECK(this, get_input_element_type(i) == ov::element::f32 &&
                                            get_input_partial_shape(i).rank().compatible(4),
                                  "GuideGate: 4-D f32 inputs only");
        NODE_VALIDATION_CHECK(this, m_threshold > 0.0f, "GuideGate: threshold must be > 0, got ", m_threshold);
        auto shape = get_input_partial_shape(1);
        if (shape.rank().is_static()) shape[1] = 1;
        set_output_type(0, ov::element::f32, shape);
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<GuideGate>(args.at(0), args.at(1), m_threshold, m_previous_channels_last);
    }

    bool visit_attributes(ov::AttributeVisitor& visitor) override {
        visitor.on_attribute("threshold", m_threshold);
        visitor.on_attribute("previous_channels_last", m_previous_channels_last);
        return true;
    }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const bool last = m_previous_channels_last != 0;
        const auto& ps = inputs[0].get_shape();
        const auto& cs = inputs[1].get_shape();
        OPENVINO_ASSERT(cs.size() == 4 && cs[1] == 7 && ps.size() == 4 && ps[0] == cs[0] &&
                            (last ? ps[1] == cs[2] && ps[2] == cs[3] && ps[3] == 7 : ps == cs),
                        "GuideGate: previous ", ps, " and current ", cs, " must be ",
                        last ? "[B, H, W, 7] and [B, 7, H, W]" : "both [B, 7, H, W]");
        const int64_t B = cs[0], H = cs[2], W = cs[3], HW = H * W;
        outputs[0].set_shape({cs[0], 1, cs[2], cs[3]});
        const float* P = inputs[0].data<const float>();
        const float* X = inputs[1].data<const float>();
        float* O = outputs[0].data<float>();
        parallel_rows(B * H, [&](const tbb::blocked_range<int64_t>& rows) {
            std::vector<float> hmax(static_cast<size_t>(W + 2)), hmin(static_cast<size_t>(W + 2)),
                d(static_cast<size_t>(W)), prow(static_cast<size_t>(last ? 7 * W : 0));
            const int64_t pstride = last ? W : HW;  // the previous guide's plane stride as read below
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / H, y = row % H, y0 = std::max<int64_t>(y - 1, 0),
                              y2 = std::min<int64_t>(y + 1, H - 1);
                const float* p = P + b * 7 * HW + y * W;
                if (last) {  // this row of the previous guide made planar (7 rows of W)
                    planar_from_channels_last(P + (b * H + y) * W * 7, 7, W, prow.data(), W);
                    p = prow.data();
                }
                const float* x = X + b * 7 * HW + y * W;
                std::fill(d.begin(), d.end(), 0.0f);
                // albedo: how far the previous albedo lies outside the current 3x3 [min, max], max over channels
                for (int64_t c = 0; c < 3; ++c) {
                    const float* r0 = X + (b * 7 + c) * HW + y0 * W;
                    const float* r1 = X + (b * 7 + c) * HW + y * W;
                    const float* r2 = X + (b * 7 + c) * HW + y2 * W;
                    float* __restrict hi = hmax.data();
                    float* __restrict lo = hmin.data();
                    for (int64_t px = 0; px < W; ++px) {  // the column max and min, then across
                        hi[px + 1] = std::max(std::max(r0[px], r1[px]), r2[px]);
                        lo[px + 1] = std::min(std::min(r0[px], r1[px]), r2[px]);
                    }
                    hi[0] = hi[1], hi[W + 1] = hi[W], lo[0] = lo[1], lo[W + 1] = lo[W];
                    const float* pc = p + c * pstride;
                    float* __restrict dd = d.data();
                    for (int64_t px = 0; px < W; ++px) {
                        const float h = std::max(std::max(hi[px], hi[px + 1]), hi[px + 2]);
                        const float l = std::min(std::min(lo[px], lo[px + 1]), lo[px + 2]);
                        const float e = std::max(std::max(pc[px] - h, l - pc[px]), 0.0f);
                        dd[px] = std::max(dd[px], e);
                    }
                }
                float* __restrict o = O + b * HW + y * W;
                const float* __restrict d_ = d.data();
                int64_t px = 0;
                for (; px + S <= W; px += S) {  // strips (the compilers leave the pixel loop scalar), as below
                    const Strip p0 = load_strip(p + 3 * pstride + px), p1 = load_strip(p + 4 * pstride + px),
                                p2 = load_strip(p + 5 * pstride + px);
                    const Strip c0 = load_strip(x + 3 * HW + px), c1 = load_strip(x + 4 * HW + px),
                                c2 = load_strip(x + 5 * HW + px);
                    const Strip lp = sqrt_strip(p0 * p0 + p1 * p1 + p2 * p2);
                    const Strip lc = sqrt_strip(c0 * c0 + c1 * c1 + c2 * c2);
                    const IntStrip hp = lp > 0.5f, hc = lc > 0.5f;
                    const Strip cos = (p0 * c0 + p1 * c1 + p2 * c2) / max_strip(lp * lc, Strip{} + 1e-6f);
                    const Strip normal = (hp & hc) != 0 ? 1.0f - cos : (hp == hc ? Strip{} : Strip{} + 1.0f);
                    const Strip lo = Strip{} + DEPTH_LOGIT_EPS, hi = Strip{} + (1.0f - DEPTH_LOGIT_EPS);
                    const Strip pd = min_strip(max_strip(load_strip(p + 6 * pstride + px), lo), hi);
                    const Strip cd = min_strip(max_strip(load_strip(x + 6 * HW + px), lo), hi);
                    const Strip ratio = log_normal_strip((pd * (1.0f - cd)) / (cd * (1.0f - pd)));
                    IntStrip bits;
                    std::memcpy(&bits, &ratio, sizeof(bits));
                    bits &= 0x7fffffff;  // fabs
                    Strip depth;
                    std::memcpy(&depth, &bits, sizeof(depth));
                    const Strip D = max_strip(max_strip(load_strip(d_ + px), normal), depth);
                    store_strip(o + px, min_strip(max_strip(2.0f - D / m_threshold, Strip{}), Strip{} + 1.0f));
                }
                for (; px < W; ++px) {
                    // normals: 1 - cos where both are present (length > 0.5), 0 where neither, else 1
                    const float p0 = p[3 * pstride + px], p1 = p[4 * pstride + px], p2 = p[5 * pstride + px];
                    const float c0 = x[3 * HW + px], c1 = x[4 * HW + px], c2 = x[5 * HW + px];
                    const float lp = std::sqrt(p0 * p0 + p1 * p1 + p2 * p2);
                    const float lc = std::sqrt(c0 * c0 + c1 * c1 + c2 * c2);
                    const bool hp = lp > 0.5f, hc = lc > 0.5f;
                    const float cos = (p0 * c0 + p1 * c1 + p2 * c2) / std::max(lp * lc, 1e-6f);
                    const float normal = hp && hc ? 1.0f - cos : (hp == hc ? 0.0f : 1.0f);
                    // depth features: |log(p (1 - c) / (c (1 - p)))|, clamped to [eps, 1 - eps]
                    const float pd = std::min(std::max(p[6 * pstride + px], DEPTH_LOGIT_EPS), 1.0f - DEPTH_LOGIT_EPS);
                    const float cd = std::min(std::max(x[6 * HW + px], DEPTH_LOGIT_EPS), 1.0f - DEPTH_LOGIT_EPS);
                    const float depth = std::fabs(log_normal((pd * (1.0f - cd)) / (cd * (1.0f - pd))));
                    const float D = std::max(std::max(d_[px], normal), depth);
                    o[px] = std::min(std::max(2.0f - D / m_threshold, 0.0f), 1.0f);
                }
            }
        });
        return true;
    }

private:
    float m_threshold = 0.1f;
    int64_t m_previous_channels_last = 0;
};

}  // namespace denoiser
