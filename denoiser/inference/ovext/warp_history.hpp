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
// gathered from them (a strip of S pixels at a time, see gather_row). As torch's sampler, every in-image corner is
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
    // per strip of S pixels (gather_row): twice where the corners' window starts, plus 1 where no
    // lane needs a select (-1: gathers, -2: nothing covered); a picked strip's index then holds its
    // lanes' offsets from that start
    std::vector<int64_t> start;
    explicit WarpRow(int64_t W) : index(W), nw(W), ne(W), sw(W), se(W), cover(W), inside(W), start(W / S) {}
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
        // the clamp at 2^30 (and the outside position's, a NaN one far outside as torch's sampler
        // takes it) moves no position into the image (W, H < 2^30 - 2 by the size check above)
        // and keeps every position below 2^31 for floor_strip
        constexpr float FAR = 1073741824.0f;
        const float limit = std::min(m_motion_limit * static_cast<float>(std::max(H, W)), FAR);
        const float outside = std::isnan(m_outside) ? -FAR : std::min(std::max(m_outside, -FAR), FAR);
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
                sample_row(mx, my, W, H, y, kept, limit, outside, r, valid + b * HW + y * W);
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
                    float outside, WarpRow& r, float* valid) const {
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
        const float fW = static_cast<float>(W), fH = static_cast<float>(H);
        const float halfW = fW / 2.0f, halfH = fH / 2.0f;
        // the grid's normalisation, as denoiser.nn.warp.grid_from_positions and torch's sampler
        const float gx_scale = 2.0f / fW, gy_scale = 2.0f / fH;
        int64_t px = 0;
        {  // a strip of S pixels at a time, the same operations in the same order as the loop below
            const Strip lanes = lane_index();
            const Strip inf = Strip{} + std::numeric_limits<float>::infinity();
            auto clean = [&](Strip v) {  // sanitised (NaN, -Inf -> 0, +Inf -> posinf), then clamped
                v = (v != v) | (v == -inf) ? Strip{} : v;
                v = v == inf ? Strip{} + m_posinf : v;
                v = v > -limit ? v : Strip{} - limit;
                return v < limit ? v : Strip{} + limit;
            };
            auto axis = [&](Strip s, float m1, float m2) {  // axis_coverage
                const Strip i = floor_strip(s), f = s - i;
                return ((i >= 0.0f) & (i <= m1) ? 1.0f - f : Strip{}) + ((i >= -1.0f) & (i <= m2) ? f : Strip{});
            };
            for (; px + S <= W; px += S) {
                const Strip dx = clean(load_strip(mx + px)), dy = clean(load_strip(my + px));
                const Strip sx = kept ? (lanes + static_cast<float>(px)) + dx : Strip{} + outside;
                const Strip sy = static_cast<float>(y) + dy;
                const Strip gx = (sx + 0.5f) * gx_scale - 1.0f, gy = (sy + 0.5f) * gy_scale - 1.0f;
                const Strip ix = (gx + 1.0f) * halfW - 0.5f, iy = (gy + 1.0f) * halfH - 0.5f;
                const Strip x0 = floor_strip(ix), y0 = floor_strip(iy);
                const Strip e = ix - x0, s = iy - y0;
                store_strip(r.nw.data() + px, (1.0f - e) * (1.0f - s));
                store_strip(r.ne.data() + px, e * (1.0f - s));
                store_strip(r.sw.data() + px, (1.0f - e) * s);
                store_strip(r.se.data() + px, e * s);
                const IntStrip in_x0 = (x0 >= 0.0f) & (x0 <= fW - 1.0f), in_x1 = (x0 >= -1.0f) & (x0 <= fW - 2.0f);
                const IntStrip in_y0 = (y0 >= 0.0f) & (y0 <= fH - 1.0f), in_y1 = (y0 >= -1.0f) & (y0 <= fH - 2.0f);
                const IntStrip bits = (in_x0 & in_y0 & 1) | (in_x1 & in_y0 & 2) | (in_x0 & in_y1 & 4) | (in_x1 & in_y1 & 8);
                store_int_strip(r.inside.data() + px, bits);
                // where no corner is inside, x0 and y0 may be far off: the index is 0 there
                const IntStrip xi = __builtin_convertvector(bits != 0 ? x0 : Strip{}, IntStrip);
                const IntStrip yi = __builtin_convertvector(bits != 0 ? y0 : Strip{}, IntStrip);
                store_int_strip(r.index.data() + px, yi * static_cast<int32_t>(W) + xi);
                const Strip cover = axis(sx, fW - 1.0f, fW - 2.0f) * axis(sy, fH - 1.0f, fH - 2.0f);
                const Strip counted = cover > m_cover_min ? cover : Strip{};
                store_strip(r.cover.data() + px, counted);
                store_strip(valid + px, counted);
            }
        }
        for (; px < W; ++px) {
            const float dx = std::min(std::max(sanitized(mx[px], m_posinf), -limit), limit);
            const float dy = std::min(std::max(sanitized(my[px], m_posinf), -limit), limit);
            const float sx = kept ? static_cast<float>(px) + dx : outside;
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
    // (torch's order of the sum, unfused). A strip of S pixels at a time: where their corners lie
    // within 2 S floats of one another (motion that varies by less than S - 1 pixels across them),
    // the two rows' windows of 2 S floats are loaded once per plane and the corners picked from
    // them (pick2: one or two permutes, where a gather costs several times more); elsewhere, and
    // without pick2, the corners are loaded one by one. What does not depend on the plane is
    // worked out once per strip: whether it is picked, and whether every pixel of it is covered
    // with its four corners in the image (then no lane needs a select: most strips of a frame).
#if defined(__GNUC__) && !defined(__clang__)
    __attribute__((optimize("fp-contract=off")))
#endif
    static void gather_row(const std::vector<const float*>& planes, int64_t HW, int64_t W, WarpRow& r,
                           const std::vector<float*>& outs) {
#if defined(__clang__)
#pragma clang fp contract(off)
#endif
        const size_t np = planes.size();
        const int64_t strips = W / S, done = strips * S;  // done: the pixels the vector loop covers
        int64_t* start = r.start.data();  // kept in r: no allocation per row
        int32_t* index = r.index.data();  // a picked strip's lanes: relative to its window's start
        constexpr int64_t NONE = -2;      // no pixel of the strip is covered: zeros
        for (int64_t j = 0; j < strips; ++j) {
            const int64_t px = j * S;
            const IntStrip ok = load_strip(r.cover.data() + px) != 0.0f;
            if (!any_lane(ok)) {
                start[j] = NONE;
                continue;
            }
            const IntStrip in = load_int_strip(r.inside.data() + px);
            const IntStrip used = ok & (in != 0);
            const IntStrip idx = load_int_strip(index + px);
            int32_t lo = lane_min(used != 0 ? idx : IntStrip{} + std::numeric_limits<int32_t>::max());
            int32_t hi = lane_max(used != 0 ? idx : IntStrip{} + std::numeric_limits<int32_t>::min());
            if (lo > hi) lo = hi = 0;
            const bool pick = PICK && hi - lo <= 2 * S - 2 && lo >= 0 && static_cast<int64_t>(lo) + W + 2 * S <= HW;
            if (!pick) {
                start[j] = -1;
                continue;
            }
            store_int_strip(index + px, idx - lo);
            // 2 lo + 1 >= 1: every lane covered, all four corners in the image; 2 lo >= 0: selects
            start[j] = 2 * static_cast<int64_t>(lo) + (any_lane(~(ok & (in == 15))) ? 0 : 1);
        }
        // plane by plane (a few memory streams at a time, not two rows of every plane at once)
        for (size_t k = 0; k < np; ++k) {
            const float* plane = planes[k];
            float* out = outs[k];
            for (int64_t j = 0; j < strips; ++j) {
                const int64_t px = j * S;
                const int64_t st = start[j];
                if (st == NONE) {
                    store_strip(out + px, Strip{});
                    continue;
                }
                const Strip cover = load_strip(r.cover.data() + px);
                const bool full = st >= 0 && (st & 1) != 0;
                Strip a, b, c, d;
                if (st >= 0) {  // the corners picked from two rows' windows of 2 S floats
                    const int64_t lo = st >> 1;
                    const IntStrip rel = load_int_strip(index + px), rel1 = rel + 1;
                    const Strip t0 = load_strip(plane + lo), t1 = load_strip(plane + lo + S);
                    const Strip b0 = load_strip(plane + lo + W), b1 = load_strip(plane + lo + W + S);
                    a = pick2(t0, t1, rel), b = pick2(t0, t1, rel1);
                    c = pick2(b0, b1, rel), d = pick2(b0, b1, rel1);
                    if (!full) {  // some corner outside the image, or some pixel not covered
                        const IntStrip in = load_int_strip(r.inside.data() + px);
                        a = (in & 1) != 0 ? a : Strip{};
                        b = (in & 2) != 0 ? b : Strip{};
                        c = (in & 4) != 0 ? c : Strip{};
                        d = (in & 8) != 0 ? d : Strip{};
                    }
                } else {
                    const IntStrip idx = load_int_strip(index + px);
                    const IntStrip in = load_int_strip(r.inside.data() + px);
                    for (int64_t l = 0; l < S; ++l) {
                        const int32_t i = idx[l], m = cover[l] != 0.0f ? in[l] : 0;
                        a[l] = (m & 1) ? plane[i] : 0.0f;
                        b[l] = (m & 2) ? plane[i + 1] : 0.0f;
                        c[l] = (m & 4) ? plane[i + W] : 0.0f;
                        d[l] = (m & 8) ? plane[i + W + 1] : 0.0f;
                    }
                }
                Strip v = a * load_strip(r.nw.data() + px);
                v = v + b * load_strip(r.ne.data() + px);
                v = v + c * load_strip(r.sw.data() + px);
                v = v + d * load_strip(r.se.data() + px);
                store_strip(out + px, full ? v / cover : cover != 0.0f ? v / cover : Strip{});
            }
        }
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
