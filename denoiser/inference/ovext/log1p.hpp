// Log1p(x [any shape] f32) -> [same] f32: the input transforms' log1p as one operation
// (OpenVINO's own Log is a reference implementation on the CPU).
#pragma once

#include "common.hpp"

namespace denoiser {

// log(1 + x) elementwise, as ONNX's Log(Add(x, 1)) computes it (the exported form of
// torch.log1p): Cephes' logf on u = 1 + x (at most 0.8 ulp on every 97th positive normal float),
// branch-free so the loop vectorises; u outside the normal positive finite floats (0, negative,
// subnormal, +inf, NaN) is redone by std::log in a second pass (only over a range that has one).
static inline float log_normal(float u) {
    int32_t bits;
    std::memcpy(&bits, &u, sizeof(bits));
    float e = static_cast<float>(((bits >> 23) & 0xff) - 126);
    bits = (bits & 0x807fffff) | 0x3f000000;  // mantissa in [0.5, 1)
    float m;
    std::memcpy(&m, &bits, sizeof(m));
    const float low = m < 0.707106781186547524f ? 1.0f : 0.0f;
    e -= low;
    const float f = m + low * m - 1.0f;
    const float z = f * f;
    float p = 7.0376836292e-2f;
    p = std::fma(p, f, -1.1514610310e-1f);
    p = std::fma(p, f, 1.1676998740e-1f);
    p = std::fma(p, f, -1.2420140846e-1f);
    p = std::fma(p, f, 1.4249322787e-1f);
    p = std::fma(p, f, -1.6668057665e-1f);
    p = std::fma(p, f, 2.0000714765e-1f);
    p = std::fma(p, f, -2.4999993993e-1f);
    p = std::fma(p, f, 3.3333331174e-1f);
    float y = f * z * p;
    y = std::fma(e, -2.12194440e-4f, y);
    y = std::fma(z, -0.5f, y);
    return std::fma(e, 0.693359375f, f + y);
}

// log_normal of a strip, the same operations lane by lane (the fused multiply-adds are the
// compiler's contractions: one instruction with FMA, a multiply and an add without). The
// compilers leave the scalar loop unvectorised (they see control flow in it).
static inline Strip log_normal_strip(Strip u) {
    IntStrip bits;
    std::memcpy(&bits, &u, sizeof(bits));
    Strip e = __builtin_convertvector(((bits >> 23) & 0xff) - 126, Strip);
    bits = (bits & static_cast<int32_t>(0x807fffff)) | 0x3f000000;  // mantissa in [0.5, 1)
    Strip m;
    std::memcpy(&m, &bits, sizeof(m));
    const Strip low = m < 0.707106781186547524f ? Strip{} + 1.0f : Strip{};
    e -= low;
    const Strip f = m + low * m - 1.0f;
    const Strip z = f * f;
    Strip p = Strip{} + 7.0376836292e-2f;
    p = p * f + -1.1514610310e-1f;
    p = p * f + 1.1676998740e-1f;
    p = p * f + -1.2420140846e-1f;
    p = p * f + 1.4249322787e-1f;
    p = p * f + -1.6668057665e-1f;
    p = p * f + 2.0000714765e-1f;
    p = p * f + -2.4999993993e-1f;
    p = p * f + 3.3333331174e-1f;
    Strip y = f * z * p;
    y = e * -2.12194440e-4f + y;
    y = z * -0.5f + y;
    return e * 0.693359375f + (f + y);
}

static void log1p_range(const float* x, float* y, int64_t begin, int64_t end) {
    // the second pass only where some u lies outside the normal positive finite floats
    const float lo = std::numeric_limits<float>::min(), hi = std::numeric_limits<float>::max();
    bool outside = false;
    int64_t i = begin;
    IntStrip bad = {};
    for (; i + S <= end; i += S) {  // ordered compares: false for NaN
        const Strip u = 1.0f + load_strip(x + i);
        bad |= ~((u >= lo) & (u <= hi));
        store_strip(y + i, log_normal_strip(u));
    }
    outside = any_lane(bad);
    for (; i < end; ++i) {
        const float u = 1.0f + x[i];
        y[i] = log_normal(u);
        outside = outside || !(u >= lo && u <= hi);
    }
    if (!outside) return;
    for (i = begin; i < end; ++i) {
        const float u = 1.0f + x[i];
        if (!(u >= lo && u <= hi)) y[i] = std::log(u);
    }
}

class Log1p : public ov::op::Op {
public:
    OPENVINO_OP("Log1p", "denoiser");

    Log1p() = default;
    explicit Log1p(const ov::Output<ov::Node>& x) : Op({x}) { constructor_validate_and_infer_types(); }

    void validate_and_infer_types() override {
        NODE_VALIDATION_CHECK(this, get_input_element_type(0) == ov::element::f32, "Log1p: f32 input only");
        set_output_type(0, ov::element::f32, get_input_partial_shape(0));
    }

    std::shared_ptr<ov::Node> clone_with_new_inputs(const ov::OutputVector& args) const override {
        return std::make_shared<Log1p>(args.at(0));
    }

    bool visit_attributes(ov::AttributeVisitor&) override { return true; }

    bool has_evaluate() const override { return true; }

    bool evaluate(ov::TensorVector& outputs, const ov::TensorVector& inputs) const override {
        outputs[0].set_shape(inputs[0].get_shape());
        const float* x = inputs[0].data<const float>();
        float* y = outputs[0].data<float>();
        const int64_t n = static_cast<int64_t>(inputs[0].get_size());
        tbb::parallel_for(tbb::blocked_range<int64_t>(0, n, 1 << 14), [&](const tbb::blocked_range<int64_t>& r) {
            log1p_range(x, y, r.begin(), r.end());
        });
        return true;
    }
};

}  // namespace denoiser
