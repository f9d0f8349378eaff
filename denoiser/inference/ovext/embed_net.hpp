// EmbedNet(w0 [M, C], b0 [M], w1 [M, M], b1 [M], w2 [N, M], b2 [N], scale [B, 1, 1, 1],
//   part_0 .. part_{p-1} [B, C_i, H, W] with sum C_i = C; attributes negative_slope,
//   color_channels) -> [B, H, W, N] f32 channels-last: denoiser.nn.embed.EmbedNet's per-pixel
//   path on the parts' channel concatenation x,
//
//     y = lrelu(w2 lrelu(w1 lrelu(w0 x + b0) + b1) + b2),  lrelu(v) = v >= 0 ? v : slope v
//
//   where the first color_channels channels of x are linear colour, taken as their colour feature
//   log1p(max(x, 0) / scale) first (denoiser.nn.inputs.color_feature; the log1p as
//   denoiser::Log1p computes it: log1p.hpp); color_channels 0: x as given, scale unread.
//
//   per pixel, a strip of S pixels at a time (common.hpp) with the hidden values in registers. In the plain graph the
//   three 1x1 convolutions each wrote and read a full-resolution tensor (M = N = 16 channels for
//   the demo student: 133 MB at 1080p each, about 55 ms of its f32 step with the reorders of the
//   inputs into the first one). The output is channels-last, the layout the U-Net's first
//   convolution reads: the exported graph's transpose back to [B, N, H, W] costs nothing.
#pragma once

#include "common.hpp"
#include "log1p.hpp"

namespace denoiser {

class EmbedNet : public ov::op::Op {
public:
    OPENVINO_OP("EmbedNet", "denoiser");

    EmbedNet() = default;
    EmbedNet(const ov::OutputVector& args, float negative_slope, int64_t color_channels)
        : Op(args), m_slope(negative_slope), m_color(color_channels) {
        constructor_validate_and_infer_types();
    }

    void validate_and_infer_types() override {
        const size_t n = get_input_size();
        NODE_VALIDATION_CHECK(this, n >= 8, "EmbedNet: needs 6 weights and biases, the scale and at least one part, got ",
                              n, " inputs");
        for (size_t i = 0; i < n; ++i)
            NODE_VALIDATION_CHECK(this, get_input_element_type(i) == ov::element::f32, "EmbedNet: f32 inputs only");
        const auto& w2 = get_input_partial_shape(4);
        auto shape = get_input_partial_shape(7);
        if (shape.rank().is_static() && w2.rank().is_static()) {
            shape = ov::PartialShape{shape[0], shape[2], shape[3], w2[0]};
        } else {
            shape = ov::PartialShape::dynamic(4);
        }
        set_output_type(0, ov::element::f32, shape);
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<EmbedNet>(args, m_slope, m_color);
    }

    bool visit_attributes(ov::AttributeVisitor& visitor) override {
        visitor.on_attribute("negative_slope", m_slope);
        visitor.on_attribute("color_channels", m_color);
        return true;
    }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const auto& w0s = inputs[0].get_shape();
        const auto& w1s = inputs[2].get_shape();
        const auto& w2s = inputs[4].get_shape();
        const auto& ps = inputs[7].get_shape();
        OPENVINO_ASSERT(w0s.size() == 2 && w1s.size() == 2 && w2s.size() == 2 && w1s[0] == w0s[0] &&
                            w1s[1] == w0s[0] && w2s[1] == w0s[0] && inputs[1].get_size() == w0s[0] &&
                            inputs[3].get_size() == w0s[0] && inputs[5].get_size() == w2s[0],
                        "EmbedNet: weights ", w0s, ", ", w1s, ", ", w2s, " do not chain");
        const int64_t M = w0s[0], C = w0s[1], N = w2s[0];
        OPENVINO_ASSERT(ps.size() == 4, "EmbedNet: part 0 has shape ", ps);
        const int64_t B = ps[0], H = ps[2], W = ps[3], HW = H * W;
        std::vector<const float*> planes;  // the input channels, in the concatenation's order (image 0)
        std::vector<int64_t> per_image;    // each plane's distance to the next image's
        for (size_t i = 7; i < inputs.size(); ++i) {
            const auto& s = inputs[i].get_shape();
            OPENVINO_ASSERT(s.size() == 4 && s[0] == ps[0] && s[2] == ps[2] && s[3] == ps[3], "EmbedNet: part ",
                            i - 7, " has shape ", s, " for part 0 ", ps);
            for (size_t c = 0; c < s[1]; ++c) {
                planes.push_back(inputs[i].data<const float>() + c * HW);
                per_image.push_back(static_cast<int64_t>(s[1]) * HW);
            }
        }
        OPENVINO_ASSERT(static_cast<int64_t>(planes.size()) == C, "EmbedNet: the parts have ", planes.size(),
                        " channels, the first layer reads ", C);
        OPENVINO_ASSERT(m_color >= 0 && m_color <= C && (m_color == 0 || inputs[6].get_size() == ps[0]),
                        "EmbedNet: ", m_color, " colour channels of ", C, ", scale ", inputs[6].get_shape());
        const float* scale = inputs[6].data<const float>();
        outputs[0].set_shape({ps[0], ps[2], ps[3], w2s[0]});
        const float* w[3] = {inputs[0].data<const float>(), inputs[2].data<const float>(),
                             inputs[4].data<const float>()};
        const float* b[3] = {inputs[1].data<const float>(), inputs[3].data<const float>(),
                             inputs[5].data<const float>()};
        float* O = outputs[0].data<float>();
        // the demo student's widths: values in registers (mlp). Its weights and biases are read
        // broadcast from a table of strips (one vector read per multiply-add) where that table is
        // small: 704 strips, 22.5 KiB at S = 8, which stays in L1 beside the strips. At S = 16
        // (AVX-512) it would be 45 KiB, more than a 32 KiB L1, and the multiply-add reads a scalar
        // weight broadcast from memory ({1to16}) at no cost: on the AVX-512 AMD EPYC family 26
        // the table made the op 24% slower than the scalars (scripts/ovext_op_bench.cpp, 1 thread)
        const bool demo = C == 10 && M == 16 && N == 16;
        const bool table = demo && (C * M + M * M + N * M + 2 * M + N) * sizeof(Strip) <= 24 * 1024;
        std::vector<Strip> wide[3], bias[3];
        if (table)
            for (int i = 0; i < 3; ++i) {
                wide[i] = broadcast_strips(w[i], static_cast<int64_t>(inputs[2 * i].get_size()));
                bias[i] = broadcast_strips(b[i], static_cast<int64_t>(inputs[2 * i + 1].get_size()));
            }
        const Strip* const ws[3] = {wide[0].data(), wide[1].data(), wide[2].data()};
        const Strip* const bs[3] = {bias[0].data(), bias[1].data(), bias[2].data()};
        const int64_t strips = (W + S - 1) / S;
        // 0 <= slope <= 1: lrelu(v) = max(v, slope v), the same bits (v >= 0: v, also for -0; v < 0:
        // slope v; NaN: v) in two instructions, where the select takes three or four on AVX2
        const bool maxed = m_slope >= 0.0f && m_slope <= 1.0f;
        parallel_rows(B * H, [&](const tbb::blocked_range<int64_t>& rows) {
            std::vector<Strip> x(C), h1(M), h2(M), y(N);
            std::vector<const float*> src(C);
            float tile[S * 64];  // one strip's output, channels-last (N <= 64 here; else in pieces)
            // the row's colour feature, channel by channel, padded with 0 to whole strips (as each
            // strip's would be): log1p_range over the row at once, not once per strip
            const int64_t padded = strips * S;
            std::vector<float> urow(static_cast<size_t>(padded), 0.0f), frow(static_cast<size_t>(m_color * padded));
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t bi = row / H, yy = row % H;
                for (int64_t c = 0; c < C; ++c) src[c] = planes[c] + bi * per_image[c] + yy * W;
                float* orow = O + (bi * HW + yy * W) * N;
                for (int64_t c = 0; c < m_color; ++c) {
                    int64_t px = 0;
                    for (; px + S <= W; px += S)
                        store_strip(urow.data() + px, max_strip(load_strip(src[c] + px), Strip{}) / scale[bi]);
                    for (; px < W; ++px) urow[px] = std::max(src[c][px], 0.0f) / scale[bi];
                    log1p_range(urow.data(), frow.data() + c * padded, 0, padded);
                }
                for (int64_t s = 0; s < strips; ++s) {
                    const int64_t px0 = s * S, m = std::min<int64_t>(S, W - px0);
                    for (int64_t c = 0; c < C; ++c) {
                        if (c < m_color) {  // the colour feature of the strip (a partial strip's rest is 0)
                            x[c] = load_strip(frow.data() + c * padded + px0);
                        } else if (m == S) {
                            x[c] = load_strip(src[c] + px0);
                        } else {
                            float t[S] = {};
                            std::memcpy(t, src[c] + px0, m * sizeof(float));
                            x[c] = load_strip(t);
                        }
                    }
                    if (table && maxed) {
                        mlp<10, 16, 16, true>(ws, bs, x.data(), y.data());
                    } else if (table) {
                        mlp<10, 16, 16, false>(ws, bs, x.data(), y.data());
                    } else if (demo && maxed) {
                        mlp<10, 16, 16, true>(w, b, x.data(), y.data());
                    } else if (demo) {
                        mlp<10, 16, 16, false>(w, b, x.data(), y.data());
                    } else {
                        layer(w[0], b[0], x.data(), C, h1.data(), M);
                        layer(w[1], b[1], h1.data(), M, h2.data(), M);
                        layer(w[2], b[2], h2.data(), M, y.data(), N);
                    }
                    for (int64_t o0 = 0; o0 < N; o0 += 64) {  // channels-last: pixel p's N values together
                        const int64_t no = std::min<int64_t>(64, N - o0);
                        for (int64_t o = 0; o < no; ++o) store_strip(tile + o * S, y[o0 + o]);
                        if (m == S && no % S == 0) {  // S x S blocks transposed in registers
                            for (int64_t o = 0; o < no; o += S)
                                transpose_block(tile + o * S, S, orow + px0 * N + o0 + o, N);
                            continue;
                        }
                        for (int64_t p = 0; p < m; ++p)
                            for (int64_t o = 0; o < no; ++o) orow[(px0 + p) * N + o0 + o] = tile[o * S + p];
                    }
                }
            }
        });
        return true;
    }

private:
    // the three layers at compile-time widths (C inputs, M hidden, N outputs); Wt: Strip (the
    // broadcast table) or float (the weights as given); MAXED: lrelu as a maximum (0 <= slope <= 1)
    template <int C, int M, int N, bool MAXED, class Wt>
    void mlp(const Wt* const* w, const Wt* const* b, const Strip* x_in, Strip* y) const {
        Strip x[C], h1[M], h2[M];
        for (int c = 0; c < C; ++c) x[c] = x_in[c];
        dense<C, M, MAXED>(w[0], b[0], x, h1);
        dense<M, M, MAXED>(w[1], b[1], h1, h2);
        dense<M, N, MAXED>(w[2], b[2], h2, y);
    }

    // w, b: broadcast (broadcast_strips) or scalars. Q outputs at a time, each its own sum in the
    // same order (bias, then k = 0 .. NIN - 1): Q independent chains of multiply-adds, where one
    // output at a time waits on each multiply-add's latency
    template <int NIN, int NOUT, bool MAXED, class Wt>
    void dense(const Wt* w, const Wt* b, const Strip* in, Strip* out) const {
        // 8 on AVX2 (of its 16 vector registers: 8 sums, the input, the weights read as operands):
        // with the input loop unrolled, 0.85-0.93 of 4's time on the Intel Xeon with AMX (4 had been
        // faster than 1 or 8 while the loop stayed a loop); 1 at S = 16, where 4 chains were 6-9%
        // slower on the AVX-512 AMD EPYC family 26 (median ratios over 16 alternated rounds)
        constexpr int Q = NOUT % 8 == 0 && S < 16 ? 8 : NOUT % 4 == 0 && S < 16 ? 4 : 1;
        for (int j0 = 0; j0 < NOUT; j0 += Q) {
            Strip acc[Q];
            for (int q = 0; q < Q; ++q) acc[q] = Strip{} + b[j0 + q];
#pragma GCC unroll 16  // GCC kept this a loop at Q = 4 (AVX2); unrolled, 0.93-0.95 of its time
            for (int k = 0; k < NIN; ++k) {
                const Strip v = in[k];
                for (int q = 0; q < Q; ++q) acc[q] += w[(j0 + q) * NIN + k] * v;
            }
            for (int q = 0; q < Q; ++q)
                out[j0 + q] = MAXED ? max_strip(acc[q], acc[q] * m_slope) : acc[q] >= 0.0f ? acc[q] : acc[q] * m_slope;
        }
    }

    // out[j] = lrelu(b[j] + sum_k w[j, k] in[k]) for j < n_out (w: [n_out, n_in])
    void layer(const float* w, const float* b, const Strip* in, int64_t n_in, Strip* out, int64_t n_out) const {
        for (int64_t j = 0; j < n_out; ++j) {
            Strip acc = Strip{} + b[j];
            const float* wj = w + j * n_in;
            for (int64_t k = 0; k < n_in; ++k) acc += wj[k] * in[k];
            out[j] = acc >= 0.0f ? acc : acc * m_slope;
        }
    }

    float m_slope = 0.1f;
    int64_t m_color = 0;
};

}  // namespace denoiser
