// WarpHistory(motion [B, 2, H, W], keep [B, 1, 1, 1], buffer_0 [B, C_0, H, W], ..., buffer_{n-1};
//   attributes motion_limit, posinf, outside, cover_min, channels_last) -> n + 1 outputs f32: each
//   buffer warped, [B, C_i, H, W], or [B, H, W, C_i] where channels_last[i] is 1 (the layout the
//   convolution that reads it takes: no reorder at full resolution), then valid [B, 1, H, W]:
//   denoiser.nn.temporal.TemporalRecurrence.warp's sampling (its docstring and denoiser.nn.warp's
//   are the definition), before the gate:
//
//     m = clamp(sanitize(motion), -motion_limit * max(H, W), +...)  (NaN, -Inf -> 0, +Inf -> posinf)
//     sx = x + m_x (outside where keep is 0), sy = y + m_y
//     v_i = grid_sample(buffer_i, grid(sx, sy), bilinear, zeros, align_corners=False)
//     cover = coverage(sx, sy);  out_i = v_i / cover and valid = cover where cover > cover_min, else 0
//
// The plain graph built the grid with a dozen full-resolution elementwise passes, sampled each
// buffer with its own GridSample, divided and selected per buffer: here the sample positions,
// bilinear weights and coverage of a row are computed once, and every channel of every buffer is
// gathered from them (AVX-512: 16 pixels at a time, see gather_row). As torch's sampler, every in-image corner is
// read whatever its weight (a NaN there comes through), and the position goes through the grid's
// normalisation and back, so the weights are torch's.
#pragma once

#include "common.hpp"

namespace denoiser {

// One row's sampling: the north-west corner's index y0 * W + x0 (0 where no corner lies in the
// image; the other corners are +1, +W, +W + 1, each read only where it lies in the image), the four
// bilinear weights, which corners lie in the image (bit 0 nw, 1 ne, 2 sw, 3 se) and the coverage
// where it counts (> cover_min), else 0.
struct WarpRow {
    std::vector<int32_t> index;
    std::vector<float> nw, ne, sw, se, cover;
    std::vector<int32_t> inside;
    // per strip of 16 pixels (gather_row): the four corners' masks, and where the window starts (-1: gathers)
    std::vector<uint16_t> masks;
    std::vector<int32_t> start;
    explicit WarpRow(int64_t W)
        : index(W), nw(W), ne(W), sw(W), se(W), cover(W), inside(W), masks(W / 16 * 4), start(W / 16) {}
};

// coverage of one axis: (1 - f) [0 <= i < size] + f [0 <= i + 1 < size], i = floor(s)
static inline float axis_coverage(float s, int64_t size) {
    const float i = std::floor(s), f = s - i;
    return ((i >= 0.0f && i <= static_cast<float>(size - 1)) ? 1.0f - f : 0.0f) +
           ((i >= -1.0f && i <= static_cast<float>(size - 2)) ? f : 0.0f);
}

static inline float sanitized(float v, float posinf) {
    if (std::isnan(v)) return 0.0f;
    if (std::isinf(v)) return v > 0.0f ? posinf : 0.0f;
    return v;
}

class WarpHistory : public ov::op::Op {
public:
    OPENVINO_OP("WarpHistory", "denoiser");

    WarpHistory() = default;
    WarpHistory(const ov::OutputVector& args, float motion_limit, float posinf, float outside, float cover_min,
                std::vector<int64_t> channels_last)
        : Op(args), m_motion_limit(motion_limit), m_posinf(posinf), m_outside(outside), m_cover_min(cover_min),
          m_channels_last(std::move(channels_last)) {
        constructor_validate_and_infer_types();
    }

    // whether buffer i is written channels-last
    bool last(size_t i) const { return i < m_channels_last.size() && m_channels_last[i] != 0; }

    void validate_and_infer_types() override {
        const size_t n = get_input_size();
        NODE_VALIDATION_CHECK(this, n >= 3, "WarpHistory: needs motion, keep and at least one buffer, got ", n,
                              " inputs");
        for (size_t i = 0; i < n; ++i)
            NODE_VALIDATION_CHECK(this, get_input_element_type(i) == ov::element::f32 &&
                                            get_input_partial_shape(i).rank().compatible(4),
                                  "WarpHistory: 4-D f32 inputs only");
        NODE_VALIDATION_CHECK(this, m_channels_last.empty() || m_channels_last.size() == n - 2,
                              "WarpHistory: channels_last has ", m_channels_last.size(), " entries for ", n - 2,
                              " buffers");
        for (size_t i = 2; i < n; ++i) {
            auto shape = get_input_partial_shape(0);  // [B, C_i, H, W]: the motion's B, H, W
            const auto& buffer = get_input_partial_shape(i);
            if (shape.rank().is_static() && buffer.rank().is_static()) {
                shape[1] = buffer[1];
                if (last(i - 2)) shape = ov::PartialShape{shape[0], shape[2], shape[3], shape[1]};
            }
            set_output_type(i - 2, ov::element::f32, shape);
        }
        auto valid = get_input_partial_shape(0);
        if (valid.rank().is_static()) valid[1] = 1;
        set_output_type(n - 2, ov::element::f32, valid);
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<WarpHistory>(args, m_motion_limit, m_posinf, m_outside, m_cover_min, m_channels_last);
    }

    bool visit_attributes(ov::AttributeVisitor& visitor) override {
        visitor.on_attribute("motion_limit", m_motion_limit);
        visitor.on_attribute("posinf", m_posinf);
        visitor.on_attribute("outside", m_outside);
        visitor.on_attribute("cover_min", m_cover_min);
        visitor.on_attribute("channels_last", m_channels_last);
        return true;
    }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        const auto& ms = inputs[0].get_shape();
        OPENVINO_ASSERT(ms.size() == 4 && ms[1] == 2, "WarpHistory: motion has shape ", ms, ", expected [B, 2, H, W]");
        const int64_t B = ms[0], H = ms[2], W = ms[3], HW = H * W;
        OPENVINO_ASSERT(inputs[1].get_size() == static_cast<size_t>(B), "WarpHistory: keep has shape ",
                        inputs[1].get_shape(), ", expected one value per image (", B, ")");
        OPENVINO_ASSERT(HW < (int64_t(1) << 31) - 2 * W, "WarpHistory: a frame of ", H, "x", W, " is too large");
        const size_t n = inputs.size() - 2;
        std::vector<const float*> src(n);
        std::vector<float*> dst(n);
        std::vector<int64_t> channels(n);
        for (size_t i = 0; i < n; ++i) {
            const auto& s = inputs[i + 2].get_shape();
            OPENVINO_ASSERT(s.size() == 4 && s[0] == ms[0] && s[2] == ms[2] && s[3] == ms[3], "WarpHistory: buffer ",
                            i, " has shape ", s, " for motion ", ms);
            channels[i] = s[1];
            outputs[i].set_shape(last(i) ? ov::Shape{s[0], s[2], s[3], s[1]} : s);
            src[i] = inputs[i + 2].data<const float>();
            dst[i] = outputs[i].data<float>();
        }
        outputs[n].set_shape({ms[0], 1, ms[2], ms[3]});
        float* valid = outputs[n].data<float>();
        const float* M = inputs[0].data<const float>();
        const float* keep = inputs[1].data<const float>();
        const float limit = m_motion_limit * static_cast<float>(std::max(H, W));
        int64_t last_channels = 0;  // the channels-last buffers' rows are gathered planar first
        for (size_t i = 0; i < n; ++i) last_channels += last(i) ? channels[i] : 0;
        parallel_rows(B * H, [&](const tbb::blocked_range<int64_t>& rows) {
            WarpRow r(W);
            std::vector<const float*> planes;
            std::vector<float*> rows_out;
            std::vector<float> planar(static_cast<size_t>(last_channels * W));
            for (int64_t row = rows.begin(); row != rows.end(); ++row) {
                const int64_t b = row / H, y = row % H;
                const bool kept = keep[b] != 0.0f;
                const float* mx = M + (b * 2) * HW + y * W;
                const float* my = mx + HW;
                sample_row(mx, my, W, H, y, kept, limit, r, valid + b * HW + y * W);
                planes.clear(), rows_out.clear();
                for (size_t i = 0, p = 0; i < n; ++i)
                    for (int64_t c = 0; c < channels[i]; ++c) {
                        planes.push_back(src[i] + (b * channels[i] + c) * HW);
                        rows_out.push_back(last(i) ? planar.data() + (p++) * W : dst[i] + (b * channels[i] + c) * HW + y * W);
                    }
                gather_row(planes, HW, W, r, rows_out);
                for (size_t i = 0, p = 0; i < n; ++i)
                    if (last(i)) {
                        channels_last_from_planar(planar.data() + p * W, W, channels[i], W,
                                                  dst[i] + (b * H + y) * W * channels[i]);
                        p += channels[i];
                    }
            }
        });
        return true;
    }

private:
    // The sampling of row y (motion rows mx, my) into r, the coverage that counts into valid. Without
    // FMA contraction: the positions round as torch's separate multiplies and adds do (a fused
    // multiply-add moves a position by an ulp, which the division by a small coverage magnifies).
#if defined(__GNUC__) && !defined(__clang__)
    __attribute__((optimize("fp-contract=off")))
#endif
    void sample_row(const float* mx, const float* my, int64_t W, int64_t H, int64_t y, bool kept, float limit,
                    WarpRow& r, float* valid) const {
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
        const float fW = static_cast<float>(W), fH = static_cast<float>(H);
        const float halfW = fW / 2.0f, halfH = fH / 2.0f;
        // the grid's normalisation, as denoiser.nn.warp.grid_from_positions and torch's sampler
        const float gx_scale = 2.0f / fW, gy_scale = 2.0f / fH;
        int64_t px = 0;
#if defined(__AVX512F__)
        {  // 16 pixels at a time, the same operations in the same order as the loop below
            const __m512 zero = _mm512_setzero_ps(), onef = _mm512_set1_ps(1.0f), half = _mm512_set1_ps(0.5f);
            const __m512 lim = _mm512_set1_ps(limit), nlim = _mm512_set1_ps(-limit), pinf = _mm512_set1_ps(m_posinf);
            const __m512 inf = _mm512_set1_ps(std::numeric_limits<float>::infinity());
            const __m512 ninf = _mm512_set1_ps(-std::numeric_limits<float>::infinity());
            const __m512 wm1 = _mm512_set1_ps(fW - 1.0f), wm2 = _mm512_set1_ps(fW - 2.0f);
            const __m512 hm1 = _mm512_set1_ps(fH - 1.0f), hm2 = _mm512_set1_ps(fH - 2.0f), mone = _mm512_set1_ps(-1.0f);
            const __m512 gxs = _mm512_set1_ps(gx_scale), gys = _mm512_set1_ps(gy_scale);
            const __m512 hW = _mm512_set1_ps(halfW), hH = _mm512_set1_ps(halfH), cmin = _mm512_set1_ps(m_cover_min);
            const __m512 vy = _mm512_set1_ps(static_cast<float>(y)), outside = _mm512_set1_ps(m_outside);
            const __m512 lanes = _mm512_setr_ps(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
            const __m512i Wi = _mm512_set1_epi32(static_cast<int32_t>(W));
            auto clean = [&](__m512 v) {  // sanitised (NaN, -Inf -> 0, +Inf -> posinf), then clamped
                v = _mm512_mask_mov_ps(v, _mm512_cmp_ps_mask(v, v, _CMP_UNORD_Q) | _mm512_cmp_ps_mask(v, ninf, _CMP_EQ_OQ), zero);
                v = _mm512_mask_mov_ps(v, _mm512_cmp_ps_mask(v, inf, _CMP_EQ_OQ), pinf);
                return _mm512_min_ps(_mm512_max_ps(v, nlim), lim);
            };
            auto axis = [&](__m512 s, __m512 m1, __m512 m2) {  // axis_coverage
                const __m512 i = _mm512_roundscale_ps(s, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
                const __m512 f = _mm512_sub_ps(s, i);
                const __mmask16 a = _mm512_cmp_ps_mask(i, zero, _CMP_GE_OQ) & _mm512_cmp_ps_mask(i, m1, _CMP_LE_OQ);
                const __mmask16 b = _mm512_cmp_ps_mask(i, mone, _CMP_GE_OQ) & _mm512_cmp_ps_mask(i, m2, _CMP_LE_OQ);
                return _mm512_add_ps(_mm512_maskz_mov_ps(a, _mm512_sub_ps(onef, f)), _mm512_maskz_mov_ps(b, f));
            };
            for (; px + 16 <= W; px += 16) {
                const __m512 dx = clean(_mm512_loadu_ps(mx + px)), dy = clean(_mm512_loadu_ps(my + px));
                const __m512 sx = kept ? _mm512_add_ps(_mm512_add_ps(lanes, _mm512_set1_ps(static_cast<float>(px))), dx)
                                       : outside;
                const __m512 sy = _mm512_add_ps(vy, dy);
                const __m512 gx = _mm512_sub_ps(_mm512_mul_ps(_mm512_add_ps(sx, half), gxs), onef);
                const __m512 gy = _mm512_sub_ps(_mm512_mul_ps(_mm512_add_ps(sy, half), gys), onef);
                const __m512 ix = _mm512_sub_ps(_mm512_mul_ps(_mm512_add_ps(gx, onef), hW), half);
                const __m512 iy = _mm512_sub_ps(_mm512_mul_ps(_mm512_add_ps(gy, onef), hH), half);
                const __m512 x0 = _mm512_roundscale_ps(ix, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
                const __m512 y0 = _mm512_roundscale_ps(iy, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
                const __m512 e = _mm512_sub_ps(ix, x0), s = _mm512_sub_ps(iy, y0);
                const __m512 ce = _mm512_sub_ps(onef, e), cs = _mm512_sub_ps(onef, s);
                _mm512_storeu_ps(r.nw.data() + px, _mm512_mul_ps(ce, cs));
                _mm512_storeu_ps(r.ne.data() + px, _mm512_mul_ps(e, cs));
                _mm512_storeu_ps(r.sw.data() + px, _mm512_mul_ps(ce, s));
                _mm512_storeu_ps(r.se.data() + px, _mm512_mul_ps(e, s));
                const __mmask16 in_x0 = _mm512_cmp_ps_mask(x0, zero, _CMP_GE_OQ) & _mm512_cmp_ps_mask(x0, wm1, _CMP_LE_OQ);
                const __mmask16 in_x1 = _mm512_cmp_ps_mask(x0, mone, _CMP_GE_OQ) & _mm512_cmp_ps_mask(x0, wm2, _CMP_LE_OQ);
                const __mmask16 in_y0 = _mm512_cmp_ps_mask(y0, zero, _CMP_GE_OQ) & _mm512_cmp_ps_mask(y0, hm1, _CMP_LE_OQ);
                const __mmask16 in_y1 = _mm512_cmp_ps_mask(y0, mone, _CMP_GE_OQ) & _mm512_cmp_ps_mask(y0, hm2, _CMP_LE_OQ);
                __m512i bits = _mm512_maskz_mov_epi32(in_x0 & in_y0, _mm512_set1_epi32(1));
                bits = _mm512_mask_or_epi32(bits, in_x1 & in_y0, bits, _mm512_set1_epi32(2));
                bits = _mm512_mask_or_epi32(bits, in_x0 & in_y1, bits, _mm512_set1_epi32(4));
                bits = _mm512_mask_or_epi32(bits, in_x1 & in_y1, bits, _mm512_set1_epi32(8));
                _mm512_storeu_si512(r.inside.data() + px, bits);
                const __mmask16 any = _mm512_test_epi32_mask(bits, bits);
                // where no corner is inside, x0 and y0 may be far off: the index is 0 there
                const __m512i xi = _mm512_maskz_cvttps_epi32(any, x0), yi = _mm512_maskz_cvttps_epi32(any, y0);
                _mm512_storeu_si512(r.index.data() + px, _mm512_add_epi32(_mm512_mullo_epi32(yi, Wi), xi));
                const __m512 cover = _mm512_mul_ps(axis(sx, wm1, wm2), axis(sy, hm1, hm2));
                const __m512 counted = _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(cover, cmin, _CMP_GT_OQ), cover);
                _mm512_storeu_ps(r.cover.data() + px, counted);
                _mm512_storeu_ps(valid + px, counted);
            }
        }
#endif
        for (; px < W; ++px) {
            const float dx = std::min(std::max(sanitized(mx[px], m_posinf), -limit), limit);
            const float dy = std::min(std::max(sanitized(my[px], m_posinf), -limit), limit);
            const float sx = kept ? static_cast<float>(px) + dx : m_outside;
            const float sy = static_cast<float>(y) + dy;
            const float gx = (sx + 0.5f) * gx_scale - 1.0f, gy = (sy + 0.5f) * gy_scale - 1.0f;
            const float ix = (gx + 1.0f) * halfW - 0.5f, iy = (gy + 1.0f) * halfH - 0.5f;  // torch's CPU sampler
            const float x0 = std::floor(ix), y0 = std::floor(iy);
            const float e = ix - x0, s = iy - y0;
            r.nw[px] = (1.0f - e) * (1.0f - s);
            r.ne[px] = e * (1.0f - s);
            r.sw[px] = (1.0f - e) * s;
            r.se[px] = e * s;
            const bool in_x0 = x0 >= 0.0f && x0 <= fW - 1.0f, in_x1 = x0 >= -1.0f && x0 <= fW - 2.0f;
            const bool in_y0 = y0 >= 0.0f && y0 <= fH - 1.0f, in_y1 = y0 >= -1.0f && y0 <= fH - 2.0f;
            r.inside[px] = static_cast<int32_t>((in_x0 && in_y0) | ((in_x1 && in_y0) << 1) |
                                                 ((in_x0 && in_y1) << 2) | ((in_x1 && in_y1) << 3));
            r.index[px] = r.inside[px] ? static_cast<int32_t>(static_cast<int64_t>(y0) * W +
                                                              static_cast<int64_t>(x0))
                                       : 0;
            const float cover = axis_coverage(sx, W) * axis_coverage(sy, H);
            r.cover[px] = cover > m_cover_min ? cover : 0.0f;
            valid[px] = r.cover[px];
        }
    }

    // out[px] = (nw v_nw + ne v_ne + sw v_sw + se v_se) / cover where the coverage counts, else 0, for
    // each channel plane (HW floats; its output row in outs); a corner outside the image reads 0
    // (torch's order of the sum, unfused). AVX-512, 16 pixels at a time: where their corners lie
    // within 32 floats of one another (motion that varies by less than 15 pixels across them), the
    // two rows' 32-float windows are loaded once per plane and the corners picked from them
    // (vpermt2ps: a gather costs several times more); elsewhere, gathers.
#if defined(__GNUC__) && !defined(__clang__)
    __attribute__((optimize("fp-contract=off")))
#endif
    static void gather_row(const std::vector<const float*>& planes, int64_t HW, int64_t W, WarpRow& r,
                           const std::vector<float*>& outs) {
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
        const size_t np = planes.size();
        int64_t done = 0;  // pixels the vector loop covers
#if defined(__AVX512F__)
        // per strip of 16 pixels, once for every plane: the corners' masks and where their window starts
        const int64_t strips = W / 16;
        done = strips * 16;
        uint16_t* masks = r.masks.data();  // kept in r: no allocation per row
        int32_t* start = r.start.data();
        const __m512i one = _mm512_set1_epi32(1), right = _mm512_set1_epi32(static_cast<int32_t>(W)),
                      below = _mm512_set1_epi32(static_cast<int32_t>(W + 1));
        const __m512 zero = _mm512_setzero_ps();
        for (int64_t j = 0; j < strips; ++j) {
            const int64_t px = j * 16;
            const __mmask16 ok = _mm512_cmpneq_ps_mask(_mm512_loadu_ps(r.cover.data() + px), zero);
            const __m512i in = _mm512_loadu_si512(r.inside.data() + px);
            __mmask16* m = masks + j * 4;
            for (int corner = 0; corner < 4; ++corner)
                m[corner] = ok & _mm512_test_epi32_mask(in, _mm512_set1_epi32(1 << corner));
            const __mmask16 any = m[0] | m[1] | m[2] | m[3];
            const __m512i idx = _mm512_loadu_si512(r.index.data() + px);
            const int32_t lo = any ? _mm512_mask_reduce_min_epi32(any, idx) : 0;
            const int32_t hi = any ? _mm512_mask_reduce_max_epi32(any, idx) : 0;
            start[j] = hi - lo <= 30 && lo >= 0 && static_cast<int64_t>(lo) + W + 32 <= HW ? lo : -1;
        }
        // plane by plane (a few memory streams at a time, not two rows of every plane at once)
        for (size_t k = 0; k < np; ++k) {
            const float* plane = planes[k];
            float* out = outs[k];
            for (int64_t j = 0; j < strips; ++j) {
                const int64_t px = j * 16;
                const __mmask16* m = masks + j * 4;
                const __m512 cover = _mm512_loadu_ps(r.cover.data() + px);
                const __mmask16 ok = _mm512_cmpneq_ps_mask(cover, zero);
                if (ok == 0) {
                    _mm512_storeu_ps(out + px, zero);
                    continue;
                }
                const __m512i idx = _mm512_loadu_si512(r.index.data() + px);
                __m512 a, b, c, d;
                if (start[j] >= 0) {
                    const int32_t lo = start[j];
                    const __m512i rel = _mm512_sub_epi32(idx, _mm512_set1_epi32(lo)), rel1 = _mm512_add_epi32(rel, one);
                    const __m512 t0 = _mm512_loadu_ps(plane + lo), t1 = _mm512_loadu_ps(plane + lo + 16);
                    const __m512 b0 = _mm512_loadu_ps(plane + lo + W), b1 = _mm512_loadu_ps(plane + lo + W + 16);
                    a = _mm512_maskz_permutex2var_ps(m[0], t0, rel, t1);
                    b = _mm512_maskz_permutex2var_ps(m[1], t0, rel1, t1);
                    c = _mm512_maskz_permutex2var_ps(m[2], b0, rel, b1);
                    d = _mm512_maskz_permutex2var_ps(m[3], b0, rel1, b1);
                } else {
                    a = _mm512_mask_i32gather_ps(zero, m[0], idx, plane, 4);
                    b = _mm512_mask_i32gather_ps(zero, m[1], _mm512_add_epi32(idx, one), plane, 4);
                    c = _mm512_mask_i32gather_ps(zero, m[2], _mm512_add_epi32(idx, right), plane, 4);
                    d = _mm512_mask_i32gather_ps(zero, m[3], _mm512_add_epi32(idx, below), plane, 4);
                }
                __m512 v = _mm512_mul_ps(a, _mm512_loadu_ps(r.nw.data() + px));
                v = _mm512_add_ps(v, _mm512_mul_ps(b, _mm512_loadu_ps(r.ne.data() + px)));
                v = _mm512_add_ps(v, _mm512_mul_ps(c, _mm512_loadu_ps(r.sw.data() + px)));
                v = _mm512_add_ps(v, _mm512_mul_ps(d, _mm512_loadu_ps(r.se.data() + px)));
                _mm512_storeu_ps(out + px, _mm512_maskz_div_ps(ok, v, cover));
            }
        }
#endif
        for (int64_t px = done; px < W; ++px) {
            const float cover = r.cover[px];
            const int32_t in = r.inside[px];
            const int64_t i = r.index[px];
            for (size_t k = 0; k < np; ++k) {
                if (cover == 0.0f) {
                    outs[k][px] = 0.0f;
                    continue;
                }
                const float* plane = planes[k];
                const float a = (in & 1) ? plane[i] : 0.0f, b = (in & 2) ? plane[i + 1] : 0.0f;
                const float c = (in & 4) ? plane[i + W] : 0.0f, d = (in & 8) ? plane[i + W + 1] : 0.0f;
                outs[k][px] = (a * r.nw[px] + b * r.ne[px] + c * r.sw[px] + d * r.se[px]) / cover;
            }
        }
    }

    float m_motion_limit = 4.0f;
    float m_posinf = 65504.0f;
    float m_outside = -2.0f;
    float m_cover_min = 1e-4f;
    std::vector<int64_t> m_channels_last;  // per buffer, 1: its output channels-last (empty: none)
};

}  // namespace denoiser
