// OpenVINO CPU extension: the kernel filters of denoiser.nn as single operations (domain
// "denoiser"), one header per operation (their definitions at the top of each), registered here
// with the ONNX front end's conversions (the attributes of denoiser.nn.graph_ops.OPERATIONS;
// tests/test_ovext_schema.py checks both against it). The one file compiled; the headers are
// part of the build's cache key.
#include "clamp_blend.hpp"
#include "color_feature.hpp"
#include "embed_net.hpp"
#include "factored_head.hpp"
#include "guide_features.hpp"
#include "guide_gate.hpp"
#include "kernel_apply.hpp"
#include "log1p.hpp"
#include "pyramid_filter.hpp"
#include "pyramid_filter_head.hpp"
#include "warp_history.hpp"

// every input of a node that takes any number of them (the pyramid filters: one head per level)
static ov::OutputVector all_inputs(const ov::frontend::NodeContext& ctx) {
    ov::OutputVector args;
    for (size_t i = 0; i < ctx.get_input_size(); ++i) args.push_back(ctx.get_input(static_cast<int>(i)));
    return args;
}

OPENVINO_CREATE_EXTENSIONS(std::vector<ov::Extension::Ptr>({
    std::make_shared<ov::OpExtension<denoiser::KernelApply>>(),
    std::make_shared<ov::OpExtension<denoiser::PyramidFilter>>(),
    std::make_shared<ov::OpExtension<denoiser::PyramidFilterHead>>(),
    std::make_shared<ov::OpExtension<denoiser::Log1p>>(),
    std::make_shared<ov::OpExtension<denoiser::ClampBlend>>(),
    std::make_shared<ov::OpExtension<denoiser::GuideGate>>(),
    std::make_shared<ov::OpExtension<denoiser::EmbedNet>>(),
    std::make_shared<ov::OpExtension<denoiser::ColorFeature>>(),
    std::make_shared<ov::OpExtension<denoiser::GuideFeatures>>(),
    std::make_shared<ov::OpExtension<denoiser::FactoredHead>>(),
    std::make_shared<ov::OpExtension<denoiser::WarpHistory>>(),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "ClampBlend", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            return std::make_shared<denoiser::ClampBlend>(ctx.get_input(0), ctx.get_input(1), ctx.get_input(2),
                                                          ctx.get_attribute<float>("k"))->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "GuideGate", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            return std::make_shared<denoiser::GuideGate>(ctx.get_input(0), ctx.get_input(1),
                                                         ctx.get_attribute<float>("threshold"),
                                                         ctx.get_attribute<int64_t>("previous_channels_last", 0))
                ->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "EmbedNet", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            return std::make_shared<denoiser::EmbedNet>(all_inputs(ctx), ctx.get_attribute<float>("negative_slope"),
                                                        ctx.get_attribute<int64_t>("color_channels"))
                ->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "ColorFeature", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            return std::make_shared<denoiser::ColorFeature>(ctx.get_input(0), ctx.get_input(1))->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "FactoredHead", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            return std::make_shared<denoiser::FactoredHead>(ctx.get_input(0), ctx.get_input(1), ctx.get_input(2),
                                                            ctx.get_attribute<std::string>("mode"))->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "GuideFeatures", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            const ov::OutputVector args{ctx.get_input(0), ctx.get_input(1), ctx.get_input(2), ctx.get_input(3)};
            return std::make_shared<denoiser::GuideFeatures>(args, ctx.get_attribute<float>("albedo_max"),
                                                             ctx.get_attribute<float>("depth_far"),
                                                             ctx.get_attribute<float>("posinf"))->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "WarpHistory", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            const auto last = ctx.get_attribute<std::vector<int64_t>>("channels_last", std::vector<int64_t>{});
            return std::make_shared<denoiser::WarpHistory>(all_inputs(ctx), ctx.get_attribute<float>("motion_limit"),
                                                           ctx.get_attribute<float>("posinf"),
                                                           ctx.get_attribute<float>("outside"),
                                                           ctx.get_attribute<float>("cover_min"), last)->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "Log1p", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            return std::make_shared<denoiser::Log1p>(ctx.get_input(0))->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "KernelApply", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            const float scale = ctx.get_attribute<float>("scale", 1.0f);
            const int64_t has_scale = ctx.get_attribute<int64_t>("has_scale", 0);
            return std::make_shared<denoiser::KernelApply>(ctx.get_input(0), ctx.get_input(1), scale,
                                                           has_scale != 0)->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "PyramidFilter", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            const ov::OutputVector args = all_inputs(ctx);
            const auto sizes = ctx.get_attribute<std::vector<int64_t>>("kernel_sizes");
            const float scale = ctx.get_attribute<float>("scale", 1.0f);
            const int64_t has_scale = ctx.get_attribute<int64_t>("has_scale", 0);
            return std::make_shared<denoiser::PyramidFilter>(args, sizes, scale, has_scale != 0)->outputs();
        }),
    std::make_shared<ov::frontend::onnx::ConversionExtension>(
        "PyramidFilterHead", "denoiser",
        [](const ov::frontend::NodeContext& ctx) -> ov::OutputVector {
            const ov::OutputVector args = all_inputs(ctx);
            const auto sizes = ctx.get_attribute<std::vector<int64_t>>("kernel_sizes");
            const float scale = ctx.get_attribute<float>("scale", 1.0f);
            const int64_t has_scale = ctx.get_attribute<int64_t>("has_scale", 0);
            const auto mode = ctx.get_attribute<std::string>("mode");
            return std::make_shared<denoiser::PyramidFilterHead>(args, sizes, scale, has_scale != 0, mode)->outputs();
        }),
}));
