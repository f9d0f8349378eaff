// ClampBlend(base [B, C, H, W], previous [B, C, H, W], weight [B, 1, H, W]; attribute k) -> [B, C, H, W] f32:
//   base + weight * (clamp(previous, mu - k sigma, mu + k sigma) - base), the mean mu and population
//   standard deviation sigma of base over each pixel's 3x3 neighbourhood, the edges replicated:
//   denoiser.nn.temporal.clamp_blend, the history clamp and blend of TemporalRecurrence (its module
//   docstring is the definition), in the same operation order as denoiser.nn.temporal.box_moments
//   (moments of the differences to the centre pixel, sigma = sqrt(var + 1e-12)).
//
// In the plain graph the 3x3 moments were eight full-resolution slices of a padded copy and five
// fused elementwise passes per blend; here each output row reads three rows of base once.
#pragma once

#include "common.hpp"

namespace denoiser {

// One row of one channel: out[px] for px in [0, W). r0, r1, r2: base rows y - 1, y, y + 1 (edges
// replicated), pixel px's three neighbours in each at px, px + 1, px + 2 (W + 2 floats: a row one
// pixel to the left of the output's, read in place, or a copy padded by its replicated ends).
// A strip of S pixels at a time (the compilers leave the pixel loop scalar), the same operations
// in the same order for the rest.
static inline void clamp_blend_row(const float* __restrict r0, const float* __restrict r1,
                                   const float* __restrict r2, const float* __restrict prev,
                                   const float* __restrict weight, float k, int64_t W, float* __restrict out) {
    int64_t px = 0;
    // four strips an iteration: their divisions and square roots overlap (5-7% at 1080p on one
    // thread, AVX2 and AVX-512 builds alike, on the AVX-512 AMD EPYC family 26)
#pragma GCC unroll 4
    for (; px + S <= W; px += S) {
        const Strip x = load_strip(r1 + px + 1);
        Strip total = {}, squares = {};
        // the neighbours in box_moments' order (rows, then columns; the centre left out)
        const Strip n[8] = {load_strip(r0 + px), load_strip(r0 + px + 1), load_strip(r0 + px + 2),
                            load_strip(r1 + px), load_strip(r1 + px + 2), load_strip(r2 + px),
                            load_strip(r2 + px + 1), load_strip(r2 + px + 2)};
        for (int t = 0; t < 8; ++t) {
            const Strip d = n[t] - x;
            total = total + d;
            squares = squares + d * d;
        }
        const Strip mean_d = total / 9.0f;
        const Strip var = max_strip(squares / 9.0f - mean_d * mean_d, Strip{});
        const Strip mean = x + mean_d;
        const Strip spread = k * sqrt_strip(var + 1e-12f);
        const Strip clamped = min_strip(max_strip(load_strip(prev + px), mean - spread), mean + spread);
        store_strip(out + px, x + load_strip(weight + px) * (clamped - x));
    }
    for (; px < W; ++px) {
        const float x = r1[px + 1];
        float total = 0.0f, squares = 0.0f;
        const float n[8] = {r0[px], r0[px + 1], r0[px + 2], r1[px], r1[px + 2], r2[px], r2[px + 1], r2[px + 2]};
        for (int t = 0; t < 8; ++t) {
            const float d = n[t] - x;
            total = total + d;
            squares = squares + d * d;
        }
        const float mean_d = total / 9.0f;
        const float var = std::max(squares / 9.0f - mean_d * mean_d, 0.0f);
        const float mean = x + mean_d;
        const float spread = k * std::sqrt(var + 1e-12f);
        const float clamped = std::min(std::max(prev[px], mean - spread), mean + spread);
        out[px] = x + weight[px] * (clamped - x);
    }
}

class ClampBlend : public ov::op::Op {
public:
    OPENVINO_OP("ClampBlend", "denoiser");

    ClampBlend() = default;
    ClampBlend(const ov::Output<ov::Node>& base, const ov::Output<ov::Node>& previous,
               const ov::Output<ov::Node>& weight, float k)
        : Op({base, previous, weight}), m_k(k) {
        constructor_validate_and_infer_types();
    }

    void validate_and_infer_types() override {
        for (size_t i = 0; i < 3; ++i)
            NODE_VALIDATION_CHECK(this, get_input_element_type(i) == ov::element::f32 &&
                                            get_input_partial_shape(i).rank().compatible(4),
                                  "ClampBlend: 4-D f32 inputs only");
        NODE_VALIDATION_CHECK(this, m_k > 0.0f, "ClampBlend: k must be > 0, got ", m_k);
        set_output_type(0, ov::element::f32, get_input_partial_shape(0));
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<ClampBlend>(args.at(0), args.at(1), args.at(2), m_k);
    }

    bool visit_attributes(ov::AttributeVisitor& visitor) override {
        visitor.on_attribute("k", m_k);
        return true;
    }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const auto& xs = inputs[0].get_shape();
        const auto& ps = inputs[1].get_shape();
        const auto& ws = inputs[2].get_shape();
        OPENVINO_ASSERT(xs.size() == 4 && ps == xs && ws.size() == 4 && ws[0] == xs[0] && ws[1] == 1 &&
                            ws[2] == xs[2] && ws[3] == xs[3],
                        "ClampBlend: base ", xs, ", previous ", ps, " and weight ", ws, " do not match");
        const int64_t B = xs[0], C = xs[1], H = xs[2], W = xs[3], HW = H * W;
        outputs[0].set_shape(xs);
        const float* X = inputs[0].data<const float>();
        const float* P = inputs[1].data<const float>();
        const float* A = inputs[2].data<const float>();
        float* O = outputs[0].data<float>();
        parallel_rows(B * H, [&](const tbb::blocked_range<int64_t>& rows) {
            float pad[3 * 4];  // an end pixel's 3 x 3 neighbourhood (W >= 3), or three padded rows (W + 2 <= 4)
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / H, y = row % H;
                for (int64_t c = 0; c < C; ++c) {
                    const float* plane = X + (b * C + c) * HW;
                    const float* src[3];  // rows y - 1, y, y + 1, replicated at the edges
                    for (int64_t i = 0; i < 3; ++i)
                        src[i] = plane + std::min(std::max(y + i - 1, int64_t(0)), H - 1) * W;
                    const int64_t o = (b * C + c) * HW + y * W;
                    if (W < 3) {  // both ends at once: the rows copied with their padding
                        for (int64_t i = 0; i < 3; ++i) {
                            float* p = pad + i * (W + 2);
                            std::memcpy(p + 1, src[i], W * sizeof(float));
                            p[0] = p[1], p[W + 1] = p[W];
                        }
                        clamp_blend_row(pad, pad + (W + 2), pad + 2 * (W + 2), P + o,
                                        A + b * HW + y * W, m_k, W, O + o);
                        continue;
                    }
                    // the inner pixels 1 .. W - 2 read the rows in place (pixel px + 1's neighbours
                    // at px .. px + 2); the two end pixels from their neighbourhoods, replicated
                    clamp_blend_row(src[0], src[1], src[2], P + o + 1, A + b * HW + y * W + 1, m_k, W - 2, O + o + 1);
                    for (const int64_t px : {int64_t(0), W - 1}) {
                        const int64_t l = std::max<int64_t>(px - 1, 0), r = std::min<int64_t>(px + 1, W - 1);
                        for (int64_t i = 0; i < 3; ++i)
                            pad[i * 3] = src[i][l], pad[i * 3 + 1] = src[i][px], pad[i * 3 + 2] = src[i][r];
                        clamp_blend_row(pad, pad + 3, pad + 6, P + o + px,
                                        A + b * HW + y * W + px, m_k, 1, O + o + px);
                    }
                }
            }
        });
        return true;
    }

private:
    float m_k = 1.0f;
};

}  // namespace denoiser
