// The OpenVINO extension's operations timed one by one (issue 66): each at the demo student's 1080p
// shapes and attributes (those of its fused f32 graph), inputs uniform random (the motion smooth, 1.2
// to 1.6 pixels, so the warp takes its window path as on rendered frames), evaluate() called directly
// in a TBB arena of THREADS threads, REPEATS calls; prints the smallest wall time and the smallest
// process CPU time of a call (less disturbed than the wall time where the machine is shared) and a
// checksum of the first output (equal across builds that compute the same bits, given the same
// NAMES). EXT_SOURCE: the extension compiled in (default: this checkout's; -DEXT_SOURCE=
// '"/path/extension.cpp"' another).
//
//   OV=$(.venv/bin/python -c 'import openvino, os; print(os.path.dirname(openvino.__file__))')
//   g++ -O3 -fno-math-errno -std=c++17 -march=native -I$OV/include scripts/ovext_op_bench.cpp \
//       -o /tmp/ovext_op_bench $OV/libs/libopenvino.so.* $OV/libs/libopenvino_onnx_frontend.so.* \
//       $OV/libs/libtbb.so.12 -Wl,-rpath,$OV/libs
//   /tmp/ovext_op_bench [THREADS=1] [REPEATS=5] [NAMES: e.g. "EmbedNet WarpHistory"; all when left out]
#ifndef EXT_SOURCE
#define EXT_SOURCE "../denoiser/inference/ovext/extension.cpp"
#endif
#include EXT_SOURCE
#include <openvino/op/parameter.hpp>
#include <tbb/task_arena.h>
#include <chrono>
#include <cstdio>
#include <random>
#include <ctime>
using namespace denoiser;
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
static void run(const char* name, std::shared_ptr<ov::Node> op, const ov::TensorVector& in, int threads, int reps) {
    ov::TensorVector out;
    for (size_t i = 0; i < op->get_output_size(); ++i) out.emplace_back(ov::element::f32, op->get_output_shape(i));
    tbb::task_arena arena(threads);
    double best = 1e30, cbest = 1e30;
    for (int r = 0; r < reps; ++r) {
        const double c0 = cpu_ms();
        const auto t0 = std::chrono::steady_clock::now();
        arena.execute([&] { op->evaluate(out, in); });
        const double ms = std::chrono::duration<double, std::milli>(std::chrono::steady_clock::now() - t0).count();
        const double c = cpu_ms() - c0;
        best = std::min(best, ms); cbest = std::min(cbest, c);
    }
    double sum = 0; const float* o = out[0].data<float>();
    for (size_t i = 0; i < out[0].get_size(); i += 997) sum += o[i];
    std::printf("%-20s threads %d  wall min %8.2f ms  cpu min %8.2f ms  (check %.6g)\n", name, threads, best, cbest,
                sum);
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
        run("PyramidFilterHead", std::make_shared<PyramidFilterHead>(params(in), sizes, 5.0f, true, "bilinear"), in,
            threads, reps);
    }
    if (want("EmbedNet")) {
        ov::TensorVector in{T({16, 10}, -.5f, .5f), T({16}), T({16, 16}, -.5f, .5f), T({16}),
                            T({16, 16}, -.5f, .5f), T({16}), T({1, 1, 1, 1}, 1, 2), T({1, 3, H, W}, 0, 4),
                            T({1, 7, H, W})};
        run("EmbedNet", std::make_shared<EmbedNet>(params(in), 0.1f, 3), in, threads, reps);
    }
    if (want("WarpHistory")) {
        ov::TensorVector in{T({1, 2, H, W}, 1.2f, 1.6f), T({1, 1, 1, 1}, 1, 1), T({1, 3, H, W}), T({1, 3, H, W}),
                            T({1, 4, H, W}), T({1, 7, H, W})};
        const std::vector<int64_t> last{0, 0, 1, 1};
        run("WarpHistory", std::make_shared<WarpHistory>(params(in), 4.0f, 65504.0f, -2.0f, 1e-4f, last), in, threads,
            reps);
    }
    if (want("GuideGate")) {
        ov::TensorVector in{T({1, H, W, 7}), T({1, 7, H, W})};
        auto p = params(in);
        run("GuideGate", std::make_shared<GuideGate>(p[0], p[1], 0.1f, 1), in, threads, reps);
    }
    if (want("ClampBlend")) {
        ov::TensorVector in{T({1, 3, H, W}), T({1, 3, H, W}), T({1, 1, H, W})};
        auto p = params(in);
        run("ClampBlend", std::make_shared<ClampBlend>(p[0], p[1], p[2], 1.0f), in, threads, reps);
    }
    if (want("GuideFeatures")) {
        ov::TensorVector in{T({1, 3, H, W}), T({1, 3, H, W}, -1, 1), T({1, 1, H, W}, 0, 10),
                            T({1, 1, 1, 1}, 1, 1)};
        run("GuideFeatures", std::make_shared<GuideFeatures>(params(in), 100.0f, 1e10f, 65504.0f), in, threads,
            reps);
    }
    if (want("FactoredHead")) {
        ov::TensorVector in{T({1, H, W, 16}, -1, 1), T({6, 16}, -.3f, .3f), T({1, 6, H / 2, W / 2})};
        auto p = params(in);
        run("FactoredHead", std::make_shared<FactoredHead>(p[0], p[1], p[2], "bilinear"), in, threads, reps);
    }
    if (want("ColorFeature")) {
        ov::TensorVector in{T({1, 3, H, W}, 0, 4), T({1, 1, 1, 1}, 1, 2)};
        auto p = params(in);
        run("ColorFeature", std::make_shared<ColorFeature>(p[0], p[1]), in, threads, reps);
    }
}
