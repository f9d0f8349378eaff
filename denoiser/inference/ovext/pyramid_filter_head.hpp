// PyramidFilterHead(x [B, 3, H, W], skip [B, H, W, Cs] channels-last, weight [L + k0^2, Cs],
//   z [B, L + k0^2, h, w], head_i [B, k_i^2, H/2^i, W/2^i] for i = 1 .. L-1; attributes
//   kernel_sizes, scale, has_scale, mode "bilinear" | "nearest") -> [B, 3, H, W] f32:
//   PyramidFilter (pyramid_filter.hpp) with head 0 given by its factors,
//
//     head0[t, p] = sum_c weight[t, c] * skip[p, c] + F.interpolate(z, (H, W), mode)[t, p]
//
//   (denoiser.nn.unet.FactoredHead: the level-0 1x1 head of [skip0, up(half)] with the product
//   of the upsampled part taken at half resolution and the bias in z). Each row of head 0 is
//   computed where the filter reads it and never written out: the L + k0^2 full-resolution
//   planes (28 for the demo student, 232 MB at 1080p) are not stored by a matrix product, read
//   and written again by AddUpsampled and read by the filter. skip is read channels-last, the
//   layout the convolution that makes it writes (the exported graph's transpose of it costs
//   nothing), once: each row is transposed to planar into a ring that serves both the partition
//   logits and, r0 rows later, the kernel logits (133 MB at 1080p for the demo student's 16
//   channels; it was read and transposed twice).
#pragma once

#include "pyramid_filter.hpp"


namespace denoiser {


// Head 0 from its factors, one row at a time (see the top of this file). load() transposes a row
// of skip to planar into a ring of `ring` rows (the filter asks for a row's kernel logits r0 rows
// after its partition logits, so ring = r0 + 1): skip is read and transposed once.
struct FactoredHead0 {
    const float* skip;    // [B, H, W, Cs]
    const float* weight;  // [N0, Cs]
    const float* z;       // [B, N0, h, w]
    int64_t N0, Cs, H, W, h, w, ring;
    const Upsampling* up;
    static constexpr bool computes = true;

    int64_t padded() const { return (W + S - 1) / S * S; }

    // floats of `buf` that load() and rows(..., n, buf) need: the ring of planar skip rows, n rows
    // (padded to whole strips) and a row of z
    int64_t scratch_floats(int64_t n) const { return (ring * Cs + n) * padded() + w; }

    // row y of image b's skip, planar, into its slot of the ring in buf
    void load(int64_t b, int64_t y, float* buf) const {
        const int64_t Wp = padded();
        float* planar = buf + (y % ring) * Cs * Wp;
        planar_from_channels_last(skip + (b * H + y) * W * Cs, Cs, W, planar, Wp);
        for (int64_t c = 0; c < Cs; ++c) std::fill(planar + c * Wp + W, planar + (c + 1) * Wp, 0.0f);
    }

    // channels c0 .. c0 + n - 1 of head 0's row y of image b (loaded at most ring - 1 rows ago),
    // planes padded() apart in buf
    Head0Rows rows(int64_t b, int64_t y, int64_t c0, int64_t n, float* buf) const {
        switch (Cs) {  // the channel loops unrolled for the shipped widths (a third faster)
            case 16: return rows_of<16>(b, y, c0, n, buf);
            case 32: return rows_of<32>(b, y, c0, n, buf);
            default: return rows_of<0>(b, y, c0, n, buf);
        }
    }

    template <int NC>
    Head0Rows rows_of(int64_t b, int64_t y, int64_t c0, int64_t n, float* buf) const {
        const int64_t C = NC > 0 ? NC : Cs, Wp = padded();
        const float* planar = buf + (y % ring) * C * Wp;  // C rows of Wp: this row of skip, channel by channel
        float* out = buf + ring * C * Wp;
        up->row(z + (b * N0 + c0) * h * w, n, y, out, Wp, out + n * Wp);
        for (int64_t t = 0; t < n; ++t) std::fill(out + t * Wp + W, out + (t + 1) * Wp, 0.0f);
        if constexpr (NC > 0) {  // strip by strip, G of the strip's skip channels in registers at a time:
            // all NC, but 8 on AVX2, whose 16 registers do not hold NC = 16 and the sums (each sum then
            // goes through memory between the groups: the same adds in the same order)
            constexpr int64_t G = S < 16 && NC % 8 == 0 ? 8 : NC;
            for (int64_t px0 = 0; px0 < Wp; px0 += S) {
                for (int64_t g = 0; g < NC; g += G) {
                    Strip col[G];
                    for (int64_t c = 0; c < G; ++c) col[c] = load_strip(planar + (g + c) * Wp + px0);
                    for (int64_t t = 0; t < n; ++t) {
                        const float* wt = weight + (c0 + t) * NC + g;
                        Strip acc = load_strip(out + t * Wp + px0);
                        for (int64_t c = 0; c < G; ++c) acc += wt[c] * col[c];
                        store_strip(out + t * Wp + px0, acc);
                    }
                }
            }
        } else {
            for (int64_t t = 0; t < n; ++t) {
                const float* wt = weight + (c0 + t) * C;
                for (int64_t px0 = 0; px0 < Wp; px0 += S) {
                    Strip acc = load_strip(out + t * Wp + px0);
                    for (int64_t c = 0; c < C; ++c) acc += wt[c] * load_strip(planar + c * Wp + px0);
                    store_strip(out + t * Wp + px0, acc);
                }
            }
        }
        return {out, Wp};
    }
};

class PyramidFilterHead : public ov::op::Op {
public:
    OPENVINO_OP("PyramidFilterHead", "denoiser");

    PyramidFilterHead() = default;
    PyramidFilterHead(const ov::OutputVector& args, std::vector<int64_t> kernel_sizes, float scale, bool has_scale,
                      std::string mode)
        : Op(args), m_kernel_sizes(std::move(kernel_sizes)), m_scale(scale), m_has_scale(has_scale),
          m_mode(std::move(mode)) {
        constructor_validate_and_infer_types();
    }

    void validate_and_infer_types() override {
        const int64_t L = static_cast<int64_t>(m_kernel_sizes.size());
        NODE_VALIDATION_CHECK(this, L >= 1 && static_cast<int64_t>(get_input_size()) == L + 3,
                              "PyramidFilterHead: needs x, skip, weight, z and one head per coarser level (", L,
                              " levels), got ", get_input_size(), " inputs");
        NODE_VALIDATION_CHECK(this, m_mode == "bilinear" || m_mode == "nearest",
                              "PyramidFilterHead: mode must be bilinear or nearest, got ", m_mode);
        for (size_t i = 0; i < get_input_size(); ++i)
            NODE_VALIDATION_CHECK(this, get_input_element_type(i) == ov::element::f32 &&
                                            get_input_partial_shape(i).rank().compatible(i == 2 ? 2 : 4),
                                  "PyramidFilterHead: f32 inputs only, weight 2-D and the others 4-D");
        set_output_type(0, ov::element::f32, get_input_partial_shape(0));
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<PyramidFilterHead>(args, m_kernel_sizes, m_scale, m_has_scale, m_mode);
    }

    bool visit_attributes(ov::AttributeVisitor& visitor) override {
        visitor.on_attribute("kernel_sizes", m_kernel_sizes);
        visitor.on_attribute("scale", m_scale);
        visitor.on_attribute("has_scale", m_has_scale);
        visitor.on_attribute("mode", m_mode);
        return true;
    }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const int64_t L = static_cast<int64_t>(m_kernel_sizes.size());
        const auto& xs = inputs[0].get_shape();
        const auto& ss = inputs[1].get_shape();
        const auto& wshape = inputs[2].get_shape();
        const auto& zs = inputs[3].get_shape();
        const int64_t N0 = L + m_kernel_sizes[0] * m_kernel_sizes[0];
        OPENVINO_ASSERT(xs.size() == 4 && ss.size() == 4 && ss[0] == xs[0] && ss[1] == xs[2] && ss[2] == xs[3],
                        "PyramidFilterHead: skip has shape ", ss, " for x ", xs, " (channels-last expected)");
        OPENVINO_ASSERT(wshape.size() == 2 && wshape[0] == static_cast<size_t>(N0) && wshape[1] == ss[3],
                        "PyramidFilterHead: weight has shape ", wshape, ", expected [", N0, ", ", ss[3], "]");
        OPENVINO_ASSERT(zs.size() == 4 && zs[0] == xs[0] && zs[1] == static_cast<size_t>(N0) && zs[2] >= 1 &&
                            zs[3] >= 1,
                        "PyramidFilterHead: z has shape ", zs, ", expected [", xs[0], ", ", N0, ", h, w]");
        const int64_t H = xs[2], W = xs[3];
        outputs[0].set_shape(xs);
        std::vector<const float*> heads(L, nullptr);
        for (int64_t i = 1; i < L; ++i) heads[i] = inputs[i + 3].data<const float>();
        std::lock_guard<std::mutex> lock(m_mutex);
        const Upsampling up(zs[2], zs[3], H, W, m_mode == "bilinear");
        const FactoredHead0 head0{inputs[1].data<const float>(), inputs[2].data<const float>(),
                                  inputs[3].data<const float>(), N0, static_cast<int64_t>(ss[3]), H, W,
                                  static_cast<int64_t>(zs[2]), static_cast<int64_t>(zs[3]),
                                  m_kernel_sizes[0] / 2 + 1, &up};
        run_pyramid_filter(inputs[0].data<const float>(), xs, head0, inputs, 4, heads, m_kernel_sizes, m_scale,
                           m_has_scale, outputs[0].data<float>(), m_scratch);
        return true;
    }

private:
    std::vector<int64_t> m_kernel_sizes;
    float m_scale = 1.0f;
    bool m_has_scale = false;
    std::string m_mode = "bilinear";
    mutable std::mutex m_mutex;
    mutable std::vector<float> m_scratch;  // the parts and sums, reused between calls
};

}  // namespace denoiser
