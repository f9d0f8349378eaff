// The OpenVINO extension's operations timed one by one (issue 66): each at the demo student's 1080p
// shapes and attributes (those of its fused f32 graph), inputs uniform random (the motion smooth, 1.2
// to 1.6 pixels, so the warp takes its window path as on rendered frames), evaluate() called directly
// in a TBB arena of THREADS threads, REPEATS calls; prints the smallest wall time and the smallest
// process CPU time of a call (less disturbed than the wall time where the machine is shared) and a
// checksum of the first output (equal across builds that compute the same bits, given the same
// NAMES). EXT_SOURCE: the extension compiled in (default: this checkout's; -DEXT_SOURCE=
// '"/path/extension.cpp"' another).
//
// Paired (-DEXT_B='"/path/extension.cpp"'): a second extension compiled in beside the first (each in
// a namespace of its own), both run on the same inputs, alternated A B B A ... REPEATS times; prints
// each build's smallest wall time, the median and range of the ratios B / A of the pairs and how many
// output values differ in their bits between the builds. Where
// two processes are compared, the time of an operation can move by half between processes on one VM
// (the same binary: 35 or 53 ms for EmbedNet, steady within a process, on either vCPU and with huge
// pages too; the cause is not known); in one process both builds meet the same conditions.
//
//   OV=$(.venv/bin/python -c 'import openvino, os; print(os.path.dirname(openvino.__file__))')
//   g++ -O3 -fno-math-errno -std=c++17 -march=native -I$OV/include scripts/ovext_op_bench.cpp \
//       -o /tmp/ovext_op_bench $OV/libs/libopenvino.so.* $OV/libs/libopenvino_onnx_frontend.so.* \
//       $OV/libs/libtbb.so.12 -Wl,-rpath,$OV/libs
//   /tmp/ovext_op_bench [THREADS=1] [REPEATS=5] [NAMES: e.g. "EmbedNet WarpHistory"; all when left out]
#include <openvino/core/extension.hpp>
#undef OPENVINO_CREATE_EXTENSIONS
#define OPENVINO_CREATE_EXTENSIONS(...)  // the extensions' entry points are not needed here (and would clash)

#ifndef EXT_SOURCE
#define EXT_SOURCE "../denoiser/inference/ovext/extension.cpp"
#endif
#define denoiser ext_a
#define all_inputs all_inputs_a
#include EXT_SOURCE
#undef denoiser
#undef all_inputs
#ifdef EXT_B
#define denoiser ext_b
#define all_inputs all_inputs_b
#include EXT_B
#undef denoiser
#undef all_inputs
#endif
#include <openvino/op/parameter.hpp>
#include <tbb/task_arena.h>
#include <algorithm>
#include <chrono>
#include <cstdio>
#include <random>
#include <ctime>
namespace ext_a {}
namespace ext_b {}
// the operations of each build, by name: A::EmbedNet(args...) makes ext_a's
#define OP(ns, name) \
    template <class... X> static auto name(X&&... x) { return std::make_shared<ns::name>(x...); }
#define OPS(ns) \
    OP(ns, PyramidFilterHead) OP(ns, EmbedNet) OP(ns, WarpHistory) OP(ns, GuideGate) OP(ns, ClampBlend) \
    OP(ns, GuideFeatures) OP(ns, FactoredHead) OP(ns, ColorFeature)
struct A { OPS(ext_a) };
#ifdef EXT_B
struct B { OPS(ext_b) };
#endif
static std::mt19937 rng(1);
static ov::Tensor T(ov::Shape s, float lo = 0.f, float hi = 1.f) {
    ov::Tensor t(ov::element::f32, s);
    std::uniform_real_distribution<float> d(lo, hi);
    float* p = t.data<float>();
    const size_t n = t.get_size();
    for (size_t i = 0; i < n; ++i) p[i] = d(rng);
    return t;
}
static ov::OutputVector params(const ov::TensorVector& in) {
    ov::OutputVector v;
    for (auto& t : in) v.push_back(std::make_shared<ov::op::v0::Parameter>(ov::element::f32, t.get_shape()));
    return v;
}
static double cpu_ms() {
    timespec ts;
    clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
    return ts.tv_sec * 1e3 + ts.tv_nsec * 1e-6;
}
static double checksum(const ov::TensorVector& out) {
    double sum = 0;
    const float* o = out[0].data<float>();
    for (size_t i = 0; i < out[0].get_size(); i += 997) sum += o[i];
    return sum;
}
static ov::TensorVector outputs_of(const std::shared_ptr<ov::Node>& op) {
    ov::TensorVector out;
    for (size_t i = 0; i < op->get_output_size(); ++i) out.emplace_back(ov::element::f32, op->get_output_shape(i));
    return out;
}
// one call of op, timed: {wall ms, process CPU ms}
static std::pair<double, double> call(const std::shared_ptr<ov::Node>& op, ov::TensorVector& out,
                                      const ov::TensorVector& in, tbb::task_arena& arena) {
    const double c0 = cpu_ms();
    const auto t0 = std::chrono::steady_clock::now();
    arena.execute([&] { op->evaluate(out, in); });
    const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
    return {ms, cpu_ms() - c0};
}
// make(ns): the operation of build ns (A, or B where compiled in) on `in`
template <class Make>
static void run(const char* name, Make make, const ov::TensorVector& in, int threads, int reps) {
    tbb::task_arena arena(threads);
    const auto op = make(A{});
    ov::TensorVector out = outputs_of(op);
#ifndef EXT_B
    double best = 1e30, cbest = 1e30;
    for (int r = 0; r < reps; ++r) {
        const auto [ms, c] = call(op, out, in, arena);
        best = std::min(best, ms), cbest = std::min(cbest, c);
    }
    std::printf("%-20s threads %d  wall min %8.2f ms  cpu min %8.2f ms  (check %.6g)\n", name, threads, best, cbest,
                checksum(out));
#else
    const auto op_b = make(B{});
    ov::TensorVector out_b = outputs_of(op_b);
    call(op, out, in, arena), call(op_b, out_b, in, arena);  // warm-up: scratch buffers, pages
    std::vector<double> ratios;
    double best_a = 1e30, best_b = 1e30;
    for (int r = 0; r < reps; ++r) {  // A B, then B A
        double a, b;
        if (r % 2 == 0) a = call(op, out, in, arena).first, b = call(op_b, out_b, in, arena).first;
        else b = call(op_b, out_b, in, arena).first, a = call(op, out, in, arena).first;
        best_a = std::min(best_a, a), best_b = std::min(best_b, b);
        ratios.push_back(b / a);
    }
    std::sort(ratios.begin(), ratios.end());
    const size_t n = ratios.size();
    const double median = n % 2 ? ratios[n / 2] : 0.5 * (ratios[n / 2 - 1] + ratios[n / 2]);
    size_t differ = 0, total = 0;  // the two builds' outputs compared value by value (bits)
    for (size_t i = 0; i < out.size(); ++i) {
        const float *x = out[i].data<float>(), *y = out_b[i].data<float>();
        for (size_t j = 0; j < out[i].get_size(); ++j) differ += std::memcmp(x + j, y + j, sizeof(float)) != 0;
        total += out[i].get_size();
    }
    std::printf("%-20s threads %d  A min %8.2f ms  B min %8.2f ms  B/A median %.3f (%.3f-%.3f, %zu pairs)  %zu of %zu "
                "output values differ\n",
                name, threads, best_a, best_b, median, ratios.front(), ratios.back(), n, differ, total);
#endif
}
int main(int argc, char** argv) {
    const int64_t H = 1080, W = 1920;
    const int threads = argc > 1 ? std::atoi(argv[1]) : 1, reps = argc > 2 ? std::atoi(argv[2]) : 5;
    const std::string only = argc > 3 ? argv[3] : "";
    auto want = [&](const char* n) { return only.empty() || only.find(n) != std::string::npos; };
    if (want("PyramidFilterHead")) {
        ov::TensorVector in{T({1, 3, H, W}), T({1, H, W, 16}, -1, 1), T({28, 16}, -0.3f, 0.3f),
                            T({1, 28, H / 2, W / 2}, -2, 2), T({1, 25, H / 2, W / 2}, -2, 2),
                            T({1, 25, H / 4, W / 4}, -2, 2)};
        const std::vector<int64_t> sizes{5, 5, 5};
        run("PyramidFilterHead", [&](auto ns) { return ns.PyramidFilterHead(params(in), sizes, 5.0f, true, "bilinear"); }, in,
            threads, reps);
    }
    if (want("EmbedNet")) {
        ov::TensorVector in{T({16, 10}, -.5f, .5f), T({16}), T({16, 16}, -.5f, .5f), T({16}),
                            T({16, 16}, -.5f, .5f), T({16}), T({1, 1, 1, 1}, 1, 2), T({1, 3, H, W}, 0, 4),
                            T({1, 7, H, W})};
        run("EmbedNet", [&](auto ns) { return ns.EmbedNet(params(in), 0.1f, 3); }, in, threads, reps);
    }
    if (want("WarpHistory")) {
        ov::TensorVector in{T({1, 2, H, W}, 1.2f, 1.6f), T({1, 1, 1, 1}, 1, 1), T({1, 3, H, W}), T({1, 3, H, W}),
                            T({1, 4, H, W}), T({1, 7, H, W})};
        const std::vector<int64_t> last{0, 0, 1, 1};
        run("WarpHistory", [&](auto ns) { return ns.WarpHistory(params(in), 4.0f, 65504.0f, -2.0f, 1e-4f, last); }, in, threads,
            reps);
    }
    if (want("GuideGate")) {
        ov::TensorVector in{T({1, H, W, 7}), T({1, 7, H, W})};
        auto p = params(in);
        run("GuideGate", [&](auto ns) { return ns.GuideGate(p[0], p[1], 0.1f, 1); }, in, threads, reps);
    }
    if (want("ClampBlend")) {
        ov::TensorVector in{T({1, 3, H, W}), T({1, 3, H, W}), T({1, 1, H, W})};
        auto p = params(in);
        run("ClampBlend", [&](auto ns) { return ns.ClampBlend(p[0], p[1], p[2], 1.0f); }, in, threads, reps);
    }
    if (want("GuideFeatures")) {
        ov::TensorVector in{T({1, 3, H, W}), T({1, 3, H, W}, -1, 1), T({1, 1, H, W}, 0, 10),
                            T({1, 1, 1, 1}, 1, 1)};
        run("GuideFeatures", [&](auto ns) { return ns.GuideFeatures(params(in), 100.0f, 1e10f, 65504.0f); }, in, threads,
            reps);
    }
    if (want("FactoredHead")) {
        ov::TensorVector in{T({1, H, W, 16}, -1, 1), T({6, 16}, -.3f, .3f), T({1, 6, H / 2, W / 2})};
        auto p = params(in);
        run("FactoredHead", [&](auto ns) { return ns.FactoredHead(p[0], p[1], p[2], "bilinear"); }, in, threads, reps);
    }
    if (want("ColorFeature")) {
        ov::TensorVector in{T({1, 3, H, W}, 0, 4), T({1, 1, 1, 1}, 1, 2)};
        auto p = params(in);
        run("ColorFeature", [&](auto ns) { return ns.ColorFeature(p[0], p[1]); }, in, threads, reps);
    }
}
