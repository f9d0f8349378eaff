// PyramidFilter(x [B, 3, H, W], head0 [B, L + k0^2, H, W], head_i [B, k_i^2, H/2^i, W/2^i] for
//   i = 1 .. L-1; attributes kernel_sizes, scale, has_scale) -> [B, 3, H, W] f32:
//   denoiser.nn.pyramid.PyramidFilter.forward (its module docstring is the definition): the
//   partition softmax, the parts [x, 1] * w_i average-pooled by 2^i, each level's kernel filter
//   (as KernelApply), the bilinear upsampling and sum from the coarsest level, and the division
//   by the filtered constant channel (x where it is <= 1e-30).
//
// Row by row as KernelApply (common.hpp's filter_row), with the sums and coarser parts kept in a
// scratch buffer reused between calls. Head 0 is read once: its partition logits and kernel logits
// in one pass over bands of rows, level 0's part kept in a ring of k0 rows (run_pyramid_filter).
// It is read through a provider of its rows, so that PyramidFilterHead (pyramid_filter_head.hpp)
// computes them instead of reading them.
#pragma once

#include "common.hpp"

namespace denoiser {

// The level-0 head's logits of one image row: channel c's row at data + c * plane.
struct Head0Rows {
    const float* data;
    int64_t plane;
};

// Head 0 as a planar input [B, L + k0^2, H, W]: rows are read in place.
struct PlanarHead0 {
    const float* H0;
    int64_t N0, H, W;
    static constexpr bool computes = false;
    int64_t scratch_floats(int64_t) const { return 0; }
    void load(int64_t, int64_t, float*) const {}
    // channels c0 .. c0 + n - 1 of row y of image b
    Head0Rows rows(int64_t b, int64_t y, int64_t c0, int64_t, float*) const {
        return {H0 + (b * N0 + c0) * H * W + y * W, H * W};
    }
};

// d[px] += sum over dx < f of w[px f + dx] * x[px f + dx] (x null: of w alone), px < wc: one
// row's share of an average pool by f, one sum per pooled pixel stored once. F: f at compile time
// (0: f at run time); the sums run in the same order either way.
template <int F>
static inline void pool_add_row(const float* __restrict w, const float* __restrict x, float* __restrict d, int64_t wc,
                                int64_t f_) {
    const int64_t f = F > 0 ? F : f_;
    if (x == nullptr) {
        for (int64_t px = 0; px < wc; ++px) {
            float a = 0.0f;
            for (int64_t dx = 0; dx < f; ++dx) a += w[px * f + dx];
            d[px] += a;
        }
        return;
    }
    for (int64_t px = 0; px < wc; ++px) {
        float a = 0.0f;
        for (int64_t dx = 0; dx < f; ++dx) a += w[px * f + dx] * x[px * f + dx];
        d[px] += a;
    }
}

// A thread's scratch, kept between calls (fresh pages would cost page faults on every band).
static float* thread_scratch(size_t floats) {
    static thread_local std::vector<float> buffer;
    if (buffer.size() < floats) buffer.resize(floats);
    return buffer.data();
}

// The pyramid filter (see the top of this file) of x [B, C, H, W] (shape xs) with head 0 from
// `head0` (PlanarHead0 or a provider that computes its rows: pyramid_filter_head.hpp) and the
// coarser heads heads[1 .. L-1] (inputs[first + i - 1] their tensors, for the shape check) -> O.
// scratch: the parts and sums, kept by the caller between calls (locked by it).
//
// Head 0 is read once, in one pass over bands of rows: each row's partition weights (level 0's
// part kept in a ring of k0 rows, the coarser parts pooled), and the level-0 filter of the row
// r0 = k0 / 2 above, whose source rows are then all in the ring. A provider is asked to load() a
// row, then for that row's partition logits and, r0 rows later, its kernel logits (rows()); a
// computing provider keeps r0 + 1 loaded rows.
template <class Head0>
static void run_pyramid_filter(const float* X, const ov::Shape& xs, const Head0& head0, const ov::TensorVector& inputs,
                               size_t first, const std::vector<const float*>& heads,
                               const std::vector<int64_t>& kernel_sizes, float scale, bool has_scale, float* O,
                               std::vector<float>& scratch) {
    const int64_t L = static_cast<int64_t>(kernel_sizes.size());
    const int64_t B = xs[0], C = xs[1], H = xs[2], W = xs[3], C1 = C + 1;
    std::vector<int64_t> hs(L), ws(L);
    for (int64_t i = 0; i < L; ++i) {
        hs[i] = H >> i, ws[i] = W >> i;  // avg_pool2d(2^i) floors
        const int64_t k = kernel_sizes[i];
        OPENVINO_ASSERT(k % 2 == 1 && k >= 1 && k <= MAX_K, "PyramidFilter: kernel size ", k,
                        " is not odd or above ", MAX_K);
        if (i == 0) continue;
        const auto& s = inputs[first + i - 1].get_shape();
        OPENVINO_ASSERT(s.size() == 4 && s[0] == xs[0] && s[1] == static_cast<size_t>(k * k) &&
                            s[2] == static_cast<size_t>(hs[i]) && s[3] == static_cast<size_t>(ws[i]),
                        "PyramidFilter: head ", i, " has shape ", s, " for x ", xs);
    }
    const int64_t HW = H * W, k0 = kernel_sizes[0], K0 = k0 * k0, r0 = k0 / 2, P = k0;
    // level i's filtered sum [B, C + 1, hs, ws]; levels >= 1 also their part (level 0's part lives
    // in the bands' rings). One allocation, kept between calls.
    std::vector<size_t> offsets{0};
    for (int64_t i = 0; i < L; ++i) {
        const size_t n = static_cast<size_t>(B * C1 * hs[i] * ws[i]);
        offsets.push_back(offsets.back() + n);
        if (i > 0) offsets.push_back(offsets.back() + n);
    }
    if (scratch.size() < offsets.back()) scratch.resize(offsets.back());
    std::vector<float*> parts(L, nullptr), accs(L);
    for (int64_t i = 0, o = 0; i < L; ++i) {
        accs[i] = scratch.data() + offsets[o++];
        if (i > 0) parts[i] = scratch.data() + offsets[o++];
    }
    // 1. in bands of rows, a multiple of 2^(L-1) high (a pooled row's source rows lie in one band,
    //    so each is written by one thread); a thread runs its consecutive bands of an image as one
    //    range of rows, and the r0 rows either side of that range are its neighbours', recomputed
    //    for their level-0 part only
    const int64_t G = int64_t(1) << (L - 1), band = G * std::max<int64_t>(1, 16 / G), bands = (H + band - 1) / band;
    const size_t head_floats = static_cast<size_t>(std::max(head0.scratch_floats(std::max(L, K0)), K0 * W));
    tbb::parallel_for(tbb::blocked_range<int64_t>(0, B * bands, 1), [&](const tbb::blocked_range<int64_t>& range) {
        // per thread: the head's rows, level 0's ring of parts, the partition's rows
        float* zbuf = thread_scratch(head_floats + static_cast<size_t>((P * C1 + 4 + L) * W));
        float* ring = zbuf + head_floats;  // P rows of [C + 1, W]: row yy in slot yy % P
        float *s = ring + P * C1 * W, *tmp = s + W, *m = tmp + W, *sum = m + W, *e = sum + W;
        for (int64_t first_band = range.begin(); first_band != range.end();) {
            const int64_t b = first_band / bands, last_band = std::min(range.end(), (b + 1) * bands);
            const int64_t y0 = (first_band % bands) * band, y1 = std::min(H, ((last_band - 1) % bands + 1) * band);
            first_band = last_band;
            for (int64_t yy = std::max<int64_t>(0, y0 - r0); yy < y1 + r0; ++yy) {
                if (yy < H) {  // row yy's partition
                    head0.load(b, yy, zbuf);
                    const Head0Rows zr = head0.rows(b, yy, 0, L, zbuf);
                    const float* z = zr.data;
                    const int64_t zp = zr.plane;
                    logit_scale_row(z, L, zp, W, scale, has_scale, s, tmp);
                    for (int64_t px = 0; px < W; ++px) m[px] = z[px] * s[px];
                    for (int64_t l = 1; l < L; ++l)
                        for (int64_t px = 0; px < W; ++px) m[px] = std::max(m[px], z[l * zp + px] * s[px]);
                    std::fill(sum, sum + W, 0.0f);
                    for (int64_t l = 0; l < L; ++l) {
                        int64_t px = 0;
                        for (; px + S <= W; px += S) {  // strips: the compilers leave this loop scalar
                            const Strip v = exp_bounded_strip(load_strip(z + l * zp + px) * load_strip(s + px) -
                                                              load_strip(m + px));
                            store_strip(e + l * W + px, v);
                            store_strip(sum + px, load_strip(sum + px) + v);
                        }
                        for (; px < W; ++px) {
                            e[l * W + px] = exp_bounded(z[l * zp + px] * s[px] - m[px]);
                            sum[px] += e[l * W + px];
                        }
                    }
                    for (int64_t px = 0; px < W; ++px) sum[px] = 1.0f / sum[px];
                    const bool own = yy >= y0 && yy < y1;  // pooled by this band
                    for (int64_t l = 0; l < L; ++l) {
                        float* w = e + l * W;
                        for (int64_t px = 0; px < W; ++px) w[px] *= sum[px];
                        const int64_t f = int64_t(1) << l, yc = yy >> l, wc = ws[l];
                        if (l == 0) {
                            float* dst = ring + (yy % P) * C1 * W;
                            for (int64_t c = 0; c < C; ++c) {
                                const float* xr = X + (b * C + c) * HW + yy * W;
                                for (int64_t px = 0; px < W; ++px) dst[c * W + px] = w[px] * xr[px];
                            }
                            std::memcpy(dst + C * W, w, W * sizeof(float));
                            continue;
                        }
                        if (!own || yc >= hs[l]) continue;  // a neighbour's row; rows a floor-sized pool leaves out
                        float* dst = parts[l] + b * C1 * hs[l] * wc + yc * wc;
                        const int64_t plane = hs[l] * wc;
                        if (yy % f == 0)
                            for (int64_t c = 0; c < C1; ++c) std::fill(dst + c * plane, dst + c * plane + wc, 0.0f);
                        for (int64_t c = 0; c < C1; ++c) {
                            float* d = dst + c * plane;
                            // c < C: w * x; the constant channel: the pooled weights
                            const float* xr = c < C ? X + (b * C + c) * HW + yy * W : nullptr;
                            switch (f) {  // the pool's width known to the compiler (the loops vectorise)
                                case 2: pool_add_row<2>(w, xr, d, wc, f); break;
                                case 4: pool_add_row<4>(w, xr, d, wc, f); break;
                                default: pool_add_row<0>(w, xr, d, wc, f);
                            }
                            if (yy % f == f - 1) {
                                const float norm = 1.0f / static_cast<float>(f * f);
                                for (int64_t px = 0; px < wc; ++px) d[px] *= norm;
                            }
                        }
                    }
                }
                const int64_t y = yy - r0;  // its source rows y - r0 .. y + r0 are in the ring
                if (y < y0 || y >= y1) continue;
                Head0Rows z = head0.rows(b, y, L, K0, zbuf);
                if (!Head0::computes) {  // a planar head's rows copied together (one compact block to read)
                    for (int64_t tap = 0; tap < K0; ++tap)
                        std::memcpy(zbuf + tap * W, z.data + tap * z.plane, W * sizeof(float));
                    z = Head0Rows{zbuf, W};
                }
                SourceRows src{{}, W};
                for (int64_t i = 0; i < k0; ++i)
                    src.rows[i] = y + i - r0 >= 0 && y + i - r0 < H ? ring + ((y + i - r0) % P) * C1 * W : nullptr;
                filter_row(src, C1, W, z.data, z.plane, k0, scale, has_scale, accs[0] + b * C1 * HW + y * W, HW);
            }
        }
    });
    // 2. the coarser levels, from the coarsest: acc_i = filter_i(part_i) + up(acc_{i+1})
    for (int64_t i = L - 1; i >= 1; --i) {
        const int64_t h = hs[i], w = ws[i], k = kernel_sizes[i], plane = h * w;
        std::vector<Lerp> ly, lx;
        if (i < L - 1) ly = bilinear_axis(hs[i + 1], h), lx = bilinear_axis(ws[i + 1], w);
        parallel_rows(B * h, [&](const tbb::blocked_range<int64_t>& rows) {
            std::vector<float> up_row(static_cast<size_t>(i < L - 1 ? ws[i + 1] : 0));
            std::vector<float> zbuf(static_cast<size_t>(k * k * w));
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / h, y = row % h;
                // this row's kernel logits copied together first (the filter then reads one
                // compact block, not k*k planes a frame apart: twice as fast at 1080p)
                const float* z = heads[i] + b * k * k * plane + y * w;
                for (int64_t tap = 0; tap < k * k; ++tap)
                    std::memcpy(zbuf.data() + tap * w, z + tap * plane, w * sizeof(float));
                float* acc = accs[i] + b * C1 * plane + y * w;
                filter_row(planar_rows(parts[i] + b * C1 * plane, h, w, k, y), C1, w, zbuf.data(), w, k, scale,
                           has_scale, acc, plane);
                if (i < L - 1)
                    add_upsampled_row(accs[i + 1] + b * C1 * hs[i + 1] * ws[i + 1], hs[i + 1], ws[i + 1], ly[y], lx,
                                      w, acc, plane, C1, up_row.data());
            }
        });
    }
    // 3. level 0: its filtered sum + up(acc_1), divided by the constant channel's
    std::vector<Lerp> ly, lx;
    if (L > 1) ly = bilinear_axis(hs[1], H), lx = bilinear_axis(ws[1], W);
    parallel_rows(B * H, [&](const tbb::blocked_range<int64_t>& rows) {
        std::vector<float> up_row(static_cast<size_t>(L > 1 ? ws[1] : 0));
        for (int64_t row = rows.begin(); row != rows.end(); ++row) {
            const int64_t b = row / H, y = row % H;
            float* acc = accs[0] + b * C1 * HW + y * W;
            if (L > 1) add_upsampled_row(accs[1] + b * C1 * hs[1] * ws[1], hs[1], ws[1], ly[y], lx, W, acc, HW, C1, up_row.data());
            const float* den = acc + C * HW;
            for (int64_t c = 0; c < C; ++c) {
                const float* a = acc + c * HW;
                const float* xr = X + (b * C + c) * HW + y * W;
                float* o = O + (b * C + c) * HW + y * W;
                for (int64_t px = 0; px < W; ++px)
                    o[px] = den[px] > NORM_EPS ? a[px] / std::max(den[px], NORM_EPS) : xr[px];
            }
        }
    });
}

class PyramidFilter : public ov::op::Op {
public:
    OPENVINO_OP("PyramidFilter", "denoiser");

    PyramidFilter() = default;
    PyramidFilter(const ov::OutputVector& args, std::vector<int64_t> kernel_sizes, float scale, bool has_scale)
        : Op(args), m_kernel_sizes(std::move(kernel_sizes)), m_scale(scale), m_has_scale(has_scale) {
        constructor_validate_and_infer_types();
    }

    void validate_and_infer_types() override {
        const int64_t L = static_cast<int64_t>(m_kernel_sizes.size());
        NODE_VALIDATION_CHECK(this, L >= 1 && static_cast<int64_t>(get_input_size()) == L + 1,
                              "PyramidFilter: needs x and one head per level (", L, " levels), got ",
                              get_input_size(), " inputs");
        for (size_t i = 0; i < get_input_size(); ++i)
            NODE_VALIDATION_CHECK(this, get_input_element_type(i) == ov::element::f32 &&
                                            get_input_partial_shape(i).rank().compatible(4),
                                  "PyramidFilter: 4-D f32 inputs only");
        set_output_type(0, ov::element::f32, get_input_partial_shape(0));
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<PyramidFilter>(args, m_kernel_sizes, m_scale, m_has_scale);
    }

    bool visit_attributes(ov::AttributeVisitor& visitor) override {
        visitor.on_attribute("kernel_sizes", m_kernel_sizes);
        visitor.on_attribute("scale", m_scale);
        visitor.on_attribute("has_scale", m_has_scale);
        return true;
    }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const int64_t L = static_cast<int64_t>(m_kernel_sizes.size());
        const auto& xs = inputs[0].get_shape();
        const int64_t H = xs[2], W = xs[3], K0 = m_kernel_sizes[0] * m_kernel_sizes[0];
        const auto& s0 = inputs[1].get_shape();
        OPENVINO_ASSERT(s0.size() == 4 && s0[0] == xs[0] && s0[1] == static_cast<size_t>(L + K0) &&
                            s0[2] == xs[2] && s0[3] == xs[3],
                        "PyramidFilter: head 0 has shape ", s0, " for x ", xs);
        outputs[0].set_shape(xs);
        std::vector<const float*> heads(L, nullptr);
        for (int64_t i = 1; i < L; ++i) heads[i] = inputs[i + 1].data<const float>();
        std::lock_guard<std::mutex> lock(m_mutex);
        run_pyramid_filter(inputs[0].data<const float>(), xs, PlanarHead0{inputs[1].data<const float>(), L + K0, H, W},
                           inputs, 2, heads, m_kernel_sizes, m_scale, m_has_scale, outputs[0].data<float>(), m_scratch);
        return true;
    }

private:
    std::vector<int64_t> m_kernel_sizes;
    float m_scale = 1.0f;
    bool m_has_scale = false;
    mutable std::mutex m_mutex;
    mutable std::vector<float> m_scratch;  // the parts and sums, reused between calls
};

}  // namespace denoiser
