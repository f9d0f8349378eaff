"""The OpenVINO extension (denoiser.inference.ovext): each operation against what it replaces.

``denoiser::KernelApply`` against a plain loop over pixels (the definition in
``denoiser/nn/kernels.py``) and eager :func:`~denoiser.nn.kernels.apply_kernels`, at odd sizes,
kernels larger than the image, extreme logits and fireflies; ``denoiser::PyramidFilter`` against
:class:`~denoiser.nn.pyramid.PyramidFilter`; ``denoiser::Log1p`` against the exact log;
``denoiser::FactoredHead`` against its product and ``F.interpolate``, and the f32 graph's input
operations against PyTorch: these need the built extension and skip,
naming why, without it (they fail instead under ``DENOISER_REQUIRE_OVEXT=1``, tests/conftest.py).
Then the build's failure modes and the cache's trust rules, with fake compilers (shell scripts):
these need the ``openvino`` package only. Whole exported networks run the fused graph's parity
over a sequence in tests/inference/test_openvino.py.
"""

import hashlib
import math
import os
import platform
import stat
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers.ovext import extension_or_skip

from denoiser.errors import UserError
from denoiser.inference import ovext
from denoiser.nn.graph_mode import kernels_as_op
from denoiser.nn.kernels import apply_kernels
from denoiser.nn.pyramid import PyramidFilter


@pytest.fixture
def extension():
    """The built extension (the tests that run its operations, through ONNX graphs)."""
    pytest.importorskip("onnx", reason="onnx is not installed (the export needs it)")
    return extension_or_skip()


needs_extension = pytest.mark.usefixtures("extension")


class Filter(torch.nn.Module):
    def __init__(self, scale):
        super().__init__()
        self.scale = scale

    def forward(self, x, logits):
        return apply_kernels(x, logits, self.scale)


def export_filter(path, scale, x, logits):
    """A graph of one ``denoiser::KernelApply`` (x ``[B, C, H, W]``, logits ``[B, k*k, H, W]``)."""
    dynamic = {"x": {2: "h", 3: "w"}, "logits": {2: "h", 3: "w"}}
    with kernels_as_op(True), torch.no_grad():
        torch.onnx.export(Filter(scale), (x, logits), str(path), input_names=["x", "logits"], output_names=["y"],
                          dynamic_axes=dynamic, opset_version=17, dynamo=False, custom_opsets={"denoiser": 1})
    return path


def run_openvino(path, x, logits, threads=1, precision="f32"):
    """The graph at ``path`` on inputs ``x`` and ``logits`` (a tensor, or a list named h0, h1, ...)."""
    import openvino as ov

    core = ov.Core()
    ovext.load_into(core, path)
    hint = {"f32": "f32", "bf16": "bf16"}[precision]
    compiled = core.compile_model(core.read_model(str(path)), "CPU",
                                  {"INFERENCE_NUM_THREADS": threads, "INFERENCE_PRECISION_HINT": hint})
    feed = {"x": x.numpy()}
    if isinstance(logits, dict):
        pass
    elif isinstance(logits, torch.Tensor):
        feed["logits"] = logits.numpy()
    else:
        feed.update({f"h{i}": h.numpy() for i, h in enumerate(logits)})
    return compiled(feed)[compiled.output(0)]


def f32_graph_outputs(path, module, inputs: dict, op: str) -> list[np.ndarray]:
    """``module`` exported to ``path`` as the f32 graph (matmul heads, the fused operations) with
    ``inputs`` (name -> tensor) as its inputs; checks that its only extension node is ``op`` and
    returns its output run by OpenVINO f32 on 1 and on 2 threads."""
    import onnx
    import openvino as ov

    from denoiser.nn.graph_mode import heads_as_matmul

    names = list(inputs)
    with heads_as_matmul(True), kernels_as_op(True), torch.no_grad():
        torch.onnx.export(module, tuple(inputs.values()), str(path), input_names=names, output_names=["y"],
                          opset_version=17, dynamo=False, custom_opsets={"denoiser": 1})
    assert [n.op_type for n in onnx.load(str(path)).graph.node if n.domain == "denoiser"] == [op]
    core = ov.Core()
    ovext.load_into(core, path)
    got = []
    for threads in (1, 2):
        compiled = core.compile_model(core.read_model(str(path)), "CPU",
                                      {"INFERENCE_NUM_THREADS": threads, "INFERENCE_PRECISION_HINT": "f32"})
        read = set().union(*(port.get_names() for port in compiled.inputs))  # an unread input is not one
        got.append(compiled({name: t.numpy() for name, t in inputs.items() if name in read})[compiled.output(0)])
    return got


class Pyramid(torch.nn.Module):
    def __init__(self, sizes, scale):
        super().__init__()
        self.filter = PyramidFilter(sizes, scale)

    def forward(self, x, *heads):
        return self.filter(x, list(heads), None)[0]


def export_pyramid(path, module, x, heads):
    """A graph of one ``denoiser::PyramidFilter`` (x, then heads h0 .. h{L-1})."""
    names = [f"h{i}" for i in range(len(heads))]
    with kernels_as_op(True), torch.no_grad():
        torch.onnx.export(module, (x, *heads), str(path), input_names=["x", *names], output_names=["y"],
                          opset_version=17, dynamo=False, custom_opsets={"denoiser": 1})
    return path


def pyramid_inputs(sizes, b, h, w, seed, spread=3.0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(b, 3, h, w, generator=g) * 10
    heads = [torch.randn(b, len(sizes) + sizes[0] ** 2, h, w, generator=g) * spread]
    heads += [torch.randn(b, k * k, h >> i, w >> i, generator=g) * spread for i, k in enumerate(sizes) if i > 0]
    return x, heads


def loop_reference(x, logits, scale):
    """The definition, one pixel at a time (float64)."""
    x, logits = x.double().numpy(), logits.double().numpy()
    n, _, h, w = x.shape
    k = math.isqrt(logits.shape[1])
    r = k // 2
    out = np.zeros_like(x)
    for b in range(n):
        for y in range(h):
            for px in range(w):
                z = logits[b, :, y, px]
                if scale is not None:
                    z = z * scale / np.sqrt(z.var() + 1.0)
                taps = [(t, y + t // k - r, px + t % k - r) for t in range(k * k)]
                taps = [(t, yy, xx) for t, yy, xx in taps if 0 <= yy < h and 0 <= xx < w]
                zs = np.array([z[t] for t, _, _ in taps])
                e = np.exp(zs - zs.max())
                wts = e / e.sum()
                for wt, (_, yy, xx) in zip(wts, taps):
                    out[b, :, y, px] += wt * x[b, :, yy, xx]
    return out


@needs_extension
@pytest.mark.parametrize("k", [1, 3, 5, 7])
@pytest.mark.parametrize("scale", [None, 2.5])
def test_kernel_apply_matches_the_loop_over_pixels(tmp_path, k, scale):
    """Odd sizes (5 x 9: a 7 x 7 kernel is taller than the image), two images, four channels."""
    g = torch.Generator().manual_seed(k)
    x = torch.rand(2, 4, 5, 9, generator=g) * 10
    logits = torch.randn(2, k * k, 5, 9, generator=g) * 3
    path = export_filter(tmp_path / "f.onnx", scale, x, logits)
    got = run_openvino(path, x, logits)
    want = loop_reference(x, logits, scale)
    np.testing.assert_allclose(got, want, rtol=2e-5, atol=2e-5)
    np.testing.assert_allclose(got, apply_kernels(x, logits, scale).numpy(), rtol=2e-5, atol=2e-5)


@needs_extension
def test_kernel_apply_hard_values_and_threads(tmp_path):
    """Fireflies, black pixels, logits at +-1e4 (saturated softmaxes: one-hot kernels), and a
    row split across threads: equal to eager within float32 rounding, finite, and the same bits
    with 1 and 2 threads (each row is computed by one thread in a fixed order)."""
    g = torch.Generator().manual_seed(3)
    h, w = 37, 61
    x = torch.rand(1, 4, h, w, generator=g)
    x[:, :3, ::7, ::5] = 5e4  # fireflies
    x[:, :3, 10:20] = 0.0  # black
    logits = torch.randn(1, 25, h, w, generator=g) * 4
    logits[:, :, ::3] = 1e4 * torch.sign(torch.randn(1, 25, 1, w, generator=g))
    for scale in (None, 5.0, 15.0, 30.0):  # 15 * sqrt(25) = 75: shifted by the mean, near its bound; 30: by the max
        path = export_filter(tmp_path / f"h{scale}.onnx", scale, x, logits)
        one = run_openvino(path, x, logits, threads=1)
        two = run_openvino(path, x, logits, threads=2)
        want = apply_kernels(x, logits, scale).numpy()
        assert np.isfinite(one).all()
        np.testing.assert_array_equal(one, two)
        np.testing.assert_allclose(one, want, rtol=1e-5, atol=1e-5 * float(np.abs(want).max()))


@needs_extension
def test_kernel_apply_in_bf16_inference(tmp_path):
    """Under ``INFERENCE_PRECISION_HINT=bf16`` the operation still runs in float32 (its inputs
    arrive converted): the same numbers as f32."""
    import openvino as ov

    if "BF16" not in ov.Core().get_property("CPU", "OPTIMIZATION_CAPABILITIES"):
        pytest.skip("the CPU has no bf16")
    g = torch.Generator().manual_seed(4)
    x, logits = torch.rand(1, 4, 12, 20, generator=g), torch.randn(1, 25, 12, 20, generator=g)
    path = export_filter(tmp_path / "b.onnx", 2.5, x, logits)
    np.testing.assert_allclose(run_openvino(path, x, logits, precision="bf16"), run_openvino(path, x, logits),
                               rtol=1e-6, atol=1e-6)


@needs_extension
@pytest.mark.parametrize(("sizes", "scale", "hw"), [
    ([5, 5, 5], 2.5, (20, 28)),  # the student's pyramid
    ([5, 5, 5], None, (21, 30)),  # sizes that are not multiples of 4: floored pools, upsampling to size
    ([3, 1], 5.0, (9, 14)),
    ([7], 2.5, (6, 5)),  # one level, a kernel larger than the image
    ([5, 5, 5], 2.5, (12, 72)),  # strips with every tap inside (the vector path) on levels 0 and 1
    ([3, 3], None, (8, 70)),  # the same with the softmax shifted by its maximum
    ([5, 5, 5], 2.5, (70, 36)),  # five bands of 16 rows: the rows either side of a thread's bands recomputed
])
def test_pyramid_filter_matches_the_module(tmp_path, sizes, scale, hw):
    """``denoiser::PyramidFilter`` against :class:`~denoiser.nn.pyramid.PyramidFilter` (eager:
    partition softmax, pooled parts, per-level kernels, bilinear upsampling, normalisation)."""
    module = Pyramid(sizes, scale).eval()
    x, heads = pyramid_inputs(sizes, 2, *hw, seed=len(sizes))
    path = export_pyramid(tmp_path / "p.onnx", module, x, heads)
    want = module(x, *heads).detach().numpy()
    got = run_openvino(path, x, heads)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    for threads in (2, 3):  # the threads' shares of the bands do not change a value
        assert np.array_equal(run_openvino(path, x, heads, threads=threads), got)


class FactoredPyramid(torch.nn.Module):
    """A PyramidFilter reading head 0 as a :class:`~denoiser.nn.unet.FactoredHead` of ``skip0`` and
    ``half`` (exported: one ``denoiser::PyramidFilterHead``)."""

    def __init__(self, sizes, scale, mode, weight, bias):
        super().__init__()
        self.filter, self.mode = PyramidFilter(sizes, scale), mode
        self.register_buffer("weight", weight)
        self.register_buffer("bias", bias)

    def forward(self, x, skip0, half, *heads):
        from denoiser.nn.unet import FactoredHead

        head0 = FactoredHead(skip0, half, self.weight, self.bias, self.mode, False if self.mode == "bilinear" else None)
        return self.filter(x, [head0, *heads], None)[0]


@needs_extension
@pytest.mark.parametrize(("skip", "hw", "mode"), [
    (16, (20, 44), "bilinear"),  # the demo student's 16 channels (blocks transposed in registers), a partial strip
    (32, (12, 16), "bilinear"),  # the teacher's width
    (5, (10, 14), "nearest"),  # any other width, nearest upsampling
    (16, (70, 40), "bilinear"),  # five bands of 16 rows, split between the threads
])
def test_pyramid_filter_head_matches_the_module(tmp_path, skip, hw, mode):
    """``denoiser::PyramidFilterHead`` against the eager PyramidFilter on head 0 computed as its
    definition: the 1x1 convolution of ``[skip0, interpolate(half)]`` (a concatenation), not the
    factored form; two images, one, two and three threads alike."""
    import openvino as ov

    from denoiser.nn.graph_ops import OPERATIONS

    sizes, scale = [5, 5, 5], 2.5
    n0, (h, w) = len(sizes) + sizes[0] ** 2, hw
    g = torch.Generator().manual_seed(skip)
    x = torch.rand(2, 3, h, w, generator=g) * 10
    skip0, half = torch.randn(2, skip, h, w, generator=g), torch.randn(2, 7, h // 2, w // 2, generator=g)
    weight, bias = torch.randn(n0, skip + 7, generator=g) * 0.5, torch.randn(n0, generator=g)
    heads = [torch.randn(2, k * k, h >> i, w >> i, generator=g) * 3 for i, k in enumerate(sizes) if i > 0]
    module = FactoredPyramid(sizes, scale, mode, weight, bias).eval()
    up = torch.nn.functional.interpolate(half, size=hw, mode=mode, align_corners=False if mode == "bilinear" else None)
    head0 = torch.nn.functional.conv2d(torch.cat([skip0, up], 1), weight[:, :, None, None], bias)
    want = Pyramid(sizes, scale).eval()(x, head0, *heads).detach().numpy()
    names = ["x", "skip", "half", "h1", "h2"]
    with kernels_as_op(True), torch.no_grad():
        torch.onnx.export(module, (x, skip0, half, *heads), str(tmp_path / "f.onnx"), input_names=names,
                          output_names=["y"], opset_version=17, dynamo=False, custom_opsets={"denoiser": 1})
    import onnx

    ops = [n.op_type for n in onnx.load(str(tmp_path / "f.onnx")).graph.node if n.domain == "denoiser"]
    assert ops == ["PyramidFilterHead"] and "PyramidFilterHead" in OPERATIONS
    core = ov.Core()
    ovext.load_into(core, tmp_path / "f.onnx")
    feed = dict(zip(names, (t.numpy() for t in (x, skip0, half, *heads))))
    got = []
    for threads in (3, 2, 1):  # the split ones first: their bands' edge rows are not left from an earlier run
        compiled = core.compile_model(core.read_model(str(tmp_path / "f.onnx")), "CPU",
                                      {"INFERENCE_NUM_THREADS": threads, "INFERENCE_PRECISION_HINT": "f32"})
        got.append(compiled(feed)[compiled.output(0)])
    np.testing.assert_allclose(got[0], want, rtol=1e-4, atol=1e-4)
    assert np.array_equal(got[0], got[1]) and np.array_equal(got[0], got[2])


@needs_extension
@pytest.mark.parametrize(("parts", "hidden", "out", "hw", "color", "slope"), [
    ((3, 7), 16, 16, (5, 37), True, 0.1),  # the demo student's widths (the register path), a partial strip
    ((3, 7), 16, 16, (3, 32), True, 0.1),  # whole strips: the channels-last store through 16 x 16 blocks
    ((3, 7), 16, 16, (3, 32), False, 0.1),  # the parts as given
    ((3, 7), 16, 16, (3, 32), True, 1.5),  # a slope above 1: the select, not the maximum
    ((2, 4), 6, 5, (4, 19), False, 0.1),  # any other widths
])
def test_embed_net_matches_the_module(tmp_path, parts, hidden, out, hw, color, slope):
    """``denoiser::EmbedNet`` (the f32 graph's EmbedNet on its input parts, channels-last out)
    against the eager :class:`~denoiser.nn.embed.EmbedNet` on the parts' concatenation, with
    negative values through every LeakyReLU; with ``color`` the first part is linear colour whose
    feature the node takes (per image scale; negative values, a NaN kept as clamp_min keeps it
    would poison the pixel, so none here); two images; 1 and 2 threads alike."""
    from denoiser.nn.embed import EmbedNet
    from denoiser.nn.inputs import color_feature

    torch.manual_seed(len(parts) + hidden)
    embed = EmbedNet(sum(parts), hidden, out, negative_slope=slope).eval()
    xs = [torch.randn(2, c, *hw) * 2 for c in parts]
    scale = torch.tensor([0.5, 4.0]).view(2, 1, 1, 1)

    class Embed(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.embed = embed

        def forward(self, scale, *parts):
            return self.embed(list(parts), color_scale=scale if color else None)

    first = color_feature(xs[0], scale) if color else xs[0]
    want = embed(torch.cat([first, *xs[1:]], 1)).detach().numpy()
    got = f32_graph_outputs(tmp_path / "e.onnx", Embed(), {"scale": scale, **{f"p{i}": x for i, x in enumerate(xs)}},
                            "EmbedNet")
    assert (want < 0).any()
    np.testing.assert_allclose(got[0], want, rtol=1e-5, atol=1e-5)
    assert np.array_equal(got[0], got[1])
    eager = Embed()(scale, *xs).detach().numpy()  # the module's own path on parts, outside a graph
    np.testing.assert_allclose(eager, want, rtol=1e-5, atol=1e-5)


@needs_extension
@pytest.mark.parametrize(("channels", "hw"), [
    (3, (3, 40)),  # the history's colour parts: two whole 16-pixel blocks interleaved in registers, and a rest
    (3, (2, 16)),  # exactly one block per row
    (2, (4, 7)),  # any other channel count: the plain loop
])
def test_color_feature_matches_torch_channels_last(tmp_path, channels, hw):
    """``denoiser::ColorFeature`` (the f32 graph's colour feature of a U-Net input part, written
    channels-last and permuted back) within 1 ulp of ``log(1 + max(x, 0) / scale)`` (the quotient
    and ``1 +`` in float32, as the graph's Log1p), and of the eager ``log1p``, per image
    scale, with negative values (clamped to 0), a NaN (kept: clamp_min keeps it), +inf and zero;
    1 and 2 threads alike; the exported graph holds one such node per part and no Log1p."""

    from denoiser.nn.inputs import color_feature_part

    class Part(torch.nn.Module):
        def forward(self, x, scale):
            return color_feature_part(x, scale)

    torch.manual_seed(channels)
    x = torch.randn(2, channels, *hw) * 3
    x[0, 0, 0, :4] = torch.tensor([float("nan"), float("inf"), 0.0, -5.0])
    scale = torch.tensor([0.7, 3.0]).view(2, 1, 1, 1)
    got = f32_graph_outputs(tmp_path / "c.onnx", Part(), {"x": x, "scale": scale}, "ColorFeature")
    u = x.clamp_min(0) / scale  # float32, then log(1 + u) with 1 + u in float32 (as denoiser::Log1p)
    want = torch.log((1.0 + u).double()).float().numpy()
    assert got[0].shape == want.shape
    assert np.isnan(got[0][0, 0, 0, 0]) and got[0][0, 0, 0, 1] == np.inf and got[0][0, 0, 0, 2:4].tolist() == [0, 0]
    np.testing.assert_allclose(got[0], want, rtol=1.2e-7, atol=0)
    np.testing.assert_allclose(got[0], torch.log1p(u).numpy(), rtol=2.4e-7, atol=1.2e-7)  # the eager feature
    np.testing.assert_array_equal(got[0], got[1])


@needs_extension
@pytest.mark.parametrize("hw", [(3, 37), (2, 5)])
def test_guide_features_match_the_plain_features(tmp_path, hw):
    """``denoiser::GuideFeatures`` (the f32 graph's auxiliary-buffer features in one pass) against
    :func:`~denoiser.nn.inputs.guide_features` in PyTorch: NaN, +-inf and out-of-range values in
    every buffer (sanitised, then clamped), depth beyond the far plane, an image without a hit (its
    mean depth 1); two images; 1 and 2 threads alike."""

    from denoiser.nn.inputs import DEPTH_FAR, guide_features

    class Guide(torch.nn.Module):
        def forward(self, albedo, normal, depth):
            return guide_features({"albedo": albedo, "normal": normal, "depth": depth})

    torch.manual_seed(hw[1])
    albedo = torch.rand(2, 3, *hw) * 3 - 0.5
    normal = torch.randn(2, 3, *hw) * 1.5
    depth = torch.rand(2, 1, *hw) * 20
    hard = torch.tensor([float("nan"), float("inf"), -float("inf"), 1e6, -3.0])
    for x in (albedo, normal, depth):
        x[0, 0, 0, :5] = hard
    depth[1] = DEPTH_FAR * 10  # no hit in the second image
    got = f32_graph_outputs(tmp_path / "g.onnx", Guide(), {"albedo": albedo, "normal": normal, "depth": depth},
                            "GuideFeatures")
    want = guide_features({"albedo": albedo, "normal": normal, "depth": depth}).numpy()
    assert np.isfinite(want).all()
    assert got[0].shape == want.shape == (2, 7, *hw)
    np.testing.assert_allclose(got[0], want, rtol=2.4e-7, atol=1.2e-7)
    np.testing.assert_array_equal(got[0], got[1])


def one_hot(taps, k: int = 5) -> torch.Tensor:
    """Logits ``[1, k*k, H, W]``: +1e4 at tap ``taps[y]`` of row y, -1e4 elsewhere (saturated)."""
    logits = torch.full((1, k * k, len(taps), 1), -1e4)
    for y, t in enumerate(taps):
        logits[0, t, y] = 1e4
    return logits


@needs_extension
def test_pyramid_filter_hard_values(tmp_path):
    """Saturated softmaxes (logits at +-1e4: one-hot weights) built so that every level's kernel
    reads only pixels whose partition weight is 0: the normaliser is exactly 0 below the first
    two rows and the input pixel is passed through there, as in eager. With fireflies and a
    black band; finite, and equal to eager."""
    h, w = 24, 36
    g = torch.Generator().manual_seed(7)
    x = torch.rand(1, 3, h, w, generator=g)
    x[:, :, ::5, ::7] = 6e4
    x[:, :, 8:12] = 0.0
    top = [y % 4 < 2 for y in range(h)]  # rows 0, 1 mod 4 belong to level 0, rows 2, 3 to level 1
    partition = torch.full((1, 3, h, 1), -1e4)
    for y, level0 in enumerate(top):
        partition[0, 0 if level0 else 1, y] = 1e4
    # level 0 reads two rows up from its own rows (level 1's rows), its own pixel elsewhere;
    # level 1 (coarse rows 2y' hold nothing of it) reads its own pixel on even coarse rows and
    # the row above on odd ones; level 2 holds nothing
    k0 = one_hot([2 if level0 else 12 for level0 in top])
    k1 = one_hot([12 if y % 2 == 0 else 7 for y in range(h // 2)])
    heads = [torch.cat([partition, k0], 1).expand(1, 28, h, w).contiguous(), k1.expand(1, 25, h // 2, w // 2).contiguous(),
             torch.zeros(1, 25, h // 4, w // 4)]
    module = Pyramid([5, 5, 5], None).eval()
    want = module(x, *heads).detach().numpy()
    assert np.array_equal(want[:, :, 2:], x[:, :, 2:].numpy())  # the fallback, below the top rows
    path = export_pyramid(tmp_path / "h.onnx", module, x, heads)
    got = run_openvino(path, x, heads)
    assert np.isfinite(got).all()
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(np.abs(want).max()))


@needs_extension
def test_log1p_matches_torch(tmp_path):
    """``denoiser::Log1p`` (the exported ``torch.log1p`` of the input transforms, ONNX's
    ``Log(1 + x)`` with ``1 + x`` in float32) within 1 ulp of the exact log of that ``1 + x``, over
    values from 1e-12 to 1e30, and the special values: -1 -> -inf, below -1 -> NaN, +inf ->
    +inf, NaN -> NaN, and 1 + x subnormal-free but tiny (2^-24)."""
    from denoiser.nn.inputs import log1p

    class Log(torch.nn.Module):
        def forward(self, x):
            return log1p(x)

    x = torch.cat([torch.logspace(-12, 30, 4000), torch.rand(1000) * 5, torch.tensor([0.0, 1e-8, 65504.0])])
    specials = torch.tensor([-1.0, -2.0, float("inf"), float("nan"), -1.0 + 2.0 ** -24])
    x = torch.cat([x, specials]).view(1, 1, 1, -1)
    with kernels_as_op(True), torch.no_grad():
        torch.onnx.export(Log(), (x,), str(tmp_path / "l.onnx"), input_names=["x"], output_names=["y"],
                          opset_version=17, dynamo=False, custom_opsets={"denoiser": 1})
    import onnx

    assert [n.op_type for n in onnx.load(str(tmp_path / "l.onnx")).graph.node] == ["Log1p"]
    got = run_openvino(tmp_path / "l.onnx", x, {}).ravel()
    want = torch.log((1.0 + x).ravel().double()).float().numpy()  # the graph's Log(1 + x), 1 + x in float32
    finite = np.isfinite(want)
    np.testing.assert_allclose(got[finite], want[finite], rtol=1.2e-7, atol=0)
    n = len(specials)
    assert got[-n] == -np.inf and np.isnan(got[-n + 1]) and got[-n + 2] == np.inf and np.isnan(got[-n + 3])
    np.testing.assert_allclose(got[-1], np.log(2.0 ** -24), rtol=1e-6)


@needs_extension
@pytest.mark.parametrize(("mode", "hw", "half", "skip"), [
    ("bilinear", (12, 20), (6, 10), 16),  # the exact 2x of the level-0 head, the unrolled width (16 x 16 blocks)
    ("bilinear", (9, 14), (4, 7), 16),  # any other size: the general upsampling, a partial block
    ("nearest", (12, 20), (6, 10), 5),  # any other width
])
def test_factored_head_matches_its_product(tmp_path, mode, hw, half, skip):
    """``denoiser::FactoredHead`` (the level-0 head's channels from its factors: ``weight @ skip +
    F.interpolate(z)``, align_corners False, planar out) against that computation in PyTorch; two
    images; 1 and 2 threads alike."""
    from denoiser.nn.unet import FactoredHeadOp

    align = False if mode == "bilinear" else None

    class Head(torch.nn.Module):
        def forward(self, skip, weight, z):
            return FactoredHeadOp.apply(skip, weight, z, mode, align)

    g = torch.Generator().manual_seed(5)
    s = torch.randn(2, *hw, skip, generator=g)  # channels-last
    weight, z = torch.randn(6, skip, generator=g), torch.randn(2, 6, *half, generator=g) * 100
    got = f32_graph_outputs(tmp_path / "h.onnx", Head(), {"skip": s, "weight": weight, "z": z}, "FactoredHead")
    want = (torch.einsum("bhwc,tc->bthw", s, weight) + torch.nn.functional.interpolate(
        z, size=hw, mode=mode, align_corners=align)).numpy()
    np.testing.assert_allclose(got[0], want, rtol=1e-5, atol=1e-4)
    np.testing.assert_array_equal(got[0], got[1])


def clamp_blend_loop(base, previous, weight, k: float) -> np.ndarray:
    """The history clamp and blend, a plain loop over pixels (float64): ``base + weight * (clamp(
    previous, mu - k sigma, mu + k sigma) - base)`` with the 3x3 mean and population deviation of
    ``base``, edges replicated."""
    x, p, a = (t.double().numpy() for t in (base, previous, weight))
    b_, c_, h, w = x.shape
    out = np.zeros_like(x)
    for b in range(b_):
        for c in range(c_):
            for y in range(h):
                for px in range(w):
                    box = [x[b, c, min(max(y + i, 0), h - 1), min(max(px + j, 0), w - 1)]
                           for i in (-1, 0, 1) for j in (-1, 0, 1)]
                    mu, sd = np.mean(box), np.sqrt(np.var(box) + 1e-12)
                    clamped = min(max(p[b, c, y, px], mu - k * sd), mu + k * sd)
                    out[b, c, y, px] = x[b, c, y, px] + a[b, 0, y, px] * (clamped - x[b, c, y, px])
    return out


def run_clamp_blend(path, base, previous, weight, threads: int = 2) -> np.ndarray:
    import openvino as ov

    core = ov.Core()
    ovext.load_into(core, path)
    compiled = core.compile_model(core.read_model(str(path)), "CPU", {"INFERENCE_NUM_THREADS": threads})
    return compiled({"base": base.numpy(), "previous": previous.numpy(), "weight": weight.numpy()})[compiled.output(0)]


def export_clamp_blend(path, k: float, *inputs):
    from denoiser.nn.temporal import ClampBlendOp

    class Blend(torch.nn.Module):
        def forward(self, base, previous, weight):
            return ClampBlendOp.apply(base, previous, weight, k)

    with torch.no_grad():
        torch.onnx.export(Blend(), inputs, str(path), input_names=["base", "previous", "weight"], output_names=["y"],
                          opset_version=17, dynamo=False, custom_opsets={"denoiser": 1})
    return path


@needs_extension
@pytest.mark.parametrize(("hw", "k"), [((7, 11), 1.0), ((1, 5), 0.5), ((4, 1), 2.0), ((3, 2), 1.0), ((2, 3), 1.5), ((33, 47), 1.0)])
def test_clamp_blend_matches_the_loop_over_pixels(tmp_path, hw, k):
    """``denoiser::ClampBlend`` (the history clamp and blend of
    :class:`~denoiser.nn.temporal.TemporalRecurrence`) against a loop over pixels and against
    :func:`denoiser.nn.temporal.clamp_blend`, at odd sizes (a single row, a single column: every
    neighbourhood replicated), two images, three channels; the same bits with 1 and 2 threads."""
    from denoiser.nn.temporal import clamp_blend

    g = torch.Generator().manual_seed(hw[0])
    base = torch.rand(2, 3, *hw, generator=g) * 4
    previous = base + torch.randn(2, 3, *hw, generator=g)
    weight = torch.rand(2, 1, *hw, generator=g)
    path = export_clamp_blend(tmp_path / "c.onnx", k, base, previous, weight)
    got = run_clamp_blend(path, base, previous, weight)
    np.testing.assert_allclose(got, clamp_blend_loop(base, previous, weight, k), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(got, clamp_blend(base, previous, weight, k).numpy(), rtol=1e-6, atol=1e-6)
    assert np.array_equal(run_clamp_blend(path, base, previous, weight, threads=1), got)


@needs_extension
def test_clamp_blend_hard_values(tmp_path):
    """Fireflies (6e4) beside black pixels, a flat neighbourhood (sigma 0: the history snaps to the
    mean), weights 0 and 1, history far outside: finite and equal to eager within float32 rounding."""
    from denoiser.nn.temporal import clamp_blend

    g = torch.Generator().manual_seed(11)
    h, w = 19, 23
    base = torch.rand(1, 3, h, w, generator=g)
    base[:, :, ::4, ::5] = 6e4
    base[:, :, 10:14] = 0.0
    previous = torch.rand(1, 3, h, w, generator=g) * 1e5
    weight = torch.rand(1, 1, h, w, generator=g)
    weight[..., :, :3] = 0.0
    weight[..., :, -3:] = 1.0
    path = export_clamp_blend(tmp_path / "h.onnx", 1.0, base, previous, weight)
    got = run_clamp_blend(path, base, previous, weight)
    want = clamp_blend(base, previous, weight, 1.0).numpy()
    assert np.isfinite(got).all()
    np.testing.assert_array_equal(got[..., :3], base.numpy()[..., :3])  # weight 0: the current frame
    # black and flat: the history snaps to 0, within k * sqrt(1e-12) (the epsilon under the root)
    assert np.abs(got[:, :, 11:13, 4:-4]).max() <= 1e-6
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5 * float(np.abs(want).max()))


def guide_gate_loop(previous, current, t: float) -> np.ndarray:
    """The disocclusion gate, a plain loop over pixels (float64): ``clamp(2 - D / t, 0, 1)``, D the
    max of the albedo's excess over the current 3x3 [min, max] (edges replicated, max over
    channels), the normals' ``1 - cos`` (1 where one is missing, 0 where both are) and the depth
    features' absolute log ratio (clamped to [1e-6, 1 - 1e-6])."""
    p, x = previous.double().numpy(), current.double().numpy()
    b_, _, h, w = x.shape
    out = np.zeros((b_, 1, h, w))
    for b in range(b_):
        for y in range(h):
            for px in range(w):
                box = [(min(max(y + i, 0), h - 1), min(max(px + j, 0), w - 1)) for i in (-1, 0, 1) for j in (-1, 0, 1)]
                albedo = max(max(p[b, c, y, px] - max(x[b, c, yy, xx] for yy, xx in box),
                                 min(x[b, c, yy, xx] for yy, xx in box) - p[b, c, y, px], 0.0) for c in range(3))
                pn, cn = p[b, 3:6, y, px], x[b, 3:6, y, px]
                lp, lc = np.linalg.norm(pn), np.linalg.norm(cn)
                if lp > 0.5 and lc > 0.5:
                    normal = 1.0 - pn @ cn / max(lp * lc, 1e-6)
                else:
                    normal = 0.0 if (lp > 0.5) == (lc > 0.5) else 1.0
                pd, cd = (min(max(v, 1e-6), 1 - 1e-6) for v in (p[b, 6, y, px], x[b, 6, y, px]))
                depth = abs(np.log(pd * (1 - cd) / (cd * (1 - pd))))
                out[b, 0, y, px] = min(max(2.0 - max(albedo, normal, depth) / t, 0.0), 1.0)
    return out


def guide_pair(b: int, h: int, w: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Warped and current guides ``[B, 7, H, W]``: albedo, unit normals (some missing: zero), depth
    features in [0, 1] (some 0 and 1: the clamp), the previous a perturbed copy of the current."""
    g = torch.Generator().manual_seed(seed)
    current = torch.rand(b, 7, h, w, generator=g)
    current[:, 3:6] = torch.nn.functional.normalize(torch.randn(b, 3, h, w, generator=g), dim=1)
    current[:, 3:6, ::3, ::4] = 0.0
    current[:, 6, ::5] = 0.0
    current[:, 6, 1::7] = 1.0
    previous = current + 0.3 * torch.randn(b, 7, h, w, generator=g)
    previous[:, 3:6, ::2, ::3] = 0.0
    previous[:, 6] = previous[:, 6].clamp(0, 1)
    return previous, current


@needs_extension
@pytest.mark.parametrize(("hw", "t", "last"), [((7, 11), 0.1, True), ((1, 6), 0.6, True), ((5, 1), 0.6, True),
                                               ((29, 41), 0.6, True), ((29, 41), 0.6, False)])
def test_guide_gate_matches_the_loop_over_pixels(tmp_path, hw, t, last):
    """``denoiser::GuideGate`` (the disocclusion gate of
    :class:`~denoiser.nn.temporal.TemporalRecurrence`) against a loop over pixels and against
    eager, at odd sizes (a single row or column; 41 columns: 16-pixel blocks and the rest), with
    missing normals and depth features at 0 and 1, the previous guide channels-last as exported
    and planar (``previous_channels_last`` 0: a graph exported before the attribute existed); the
    same bits with 1 and 2 threads."""
    import onnx

    from denoiser.nn.temporal import GuideGateOp, TemporalRecurrence

    class Gate(torch.nn.Module):
        def forward(self, previous, current):
            return GuideGateOp.apply(previous, current, t)

    previous, current = guide_pair(2, *hw, seed=hw[1])
    previous_last = previous.permute(0, 2, 3, 1).contiguous()
    with torch.no_grad():
        torch.onnx.export(Gate(), (previous_last, current), str(tmp_path / "g.onnx"), input_names=["p", "c"],
                          output_names=["y"], opset_version=17, dynamo=False, custom_opsets={"denoiser": 1})
    model = onnx.load(str(tmp_path / "g.onnx"))
    (node,) = [n for n in model.graph.node if n.op_type == "GuideGate"]
    (attribute,) = [a for a in node.attribute if a.name == "previous_channels_last"]
    assert attribute.i == 1
    if not last:  # the attribute as an older graph has it (absent: 0), the previous guide planar
        node.attribute.remove(attribute)
        model.graph.input[0].type.tensor_type.shape.dim[1].dim_value = 7
        model.graph.input[0].type.tensor_type.shape.dim[2].dim_value = hw[0]
        model.graph.input[0].type.tensor_type.shape.dim[3].dim_value = hw[1]
        onnx.save(model, str(tmp_path / "g.onnx"))
    import openvino as ov

    core = ov.Core()
    ovext.load_into(core, tmp_path / "g.onnx")

    def run(threads):
        compiled = core.compile_model(core.read_model(str(tmp_path / "g.onnx")), "CPU", {"INFERENCE_NUM_THREADS": threads})
        fed = previous_last if last else previous
        return compiled({"p": fed.numpy(), "c": current.numpy()})[compiled.output(0)]

    got = run(2)
    assert got.shape == (2, 1, *hw)
    if t > 0.5 and got.size >= 100:  # not saturated everywhere: the comparison sees D, not only its clamp
        assert ((got > 0.05) & (got < 0.95)).mean() > 0.1
    np.testing.assert_allclose(got, guide_gate_loop(previous, current, t), atol=2e-5)
    eager = TemporalRecurrence(state_features=4, reject_threshold=t).gate(previous, current)
    np.testing.assert_allclose(got, eager.numpy(), atol=2e-5)
    assert np.array_equal(run(1), got)


def test_missing_extension_is_one_clear_line(tmp_path, monkeypatch):
    pytest.importorskip("onnx", reason="onnx is not installed (the export needs it)")
    pytest.importorskip("openvino", reason="openvino is not installed (pip install .[openvino])")
    from denoiser.inference.step_graph import OpenVinoStep

    x, logits = torch.rand(1, 4, 8, 8), torch.randn(1, 9, 8, 8)
    path = export_filter(tmp_path / "m.onnx", None, x, logits)
    monkeypatch.setattr(ovext, "_status", lambda: (None, "no C++ compiler ($CXX, g++ or c++) to build it"))
    with pytest.raises(UserError, match=r"m\.onnx: uses denoiser::KernelApply.*no C\+\+ compiler"):
        OpenVinoStep(path)


class FakeBuild:
    """A private cache (``$DENOISER_CACHE``) and a shell script as ``$CXX``: the build's failure
    modes and the cache's rules without a real compiler. Each run of the script appends its
    arguments to ``log``; :meth:`status` is what a new process would get."""

    def __init__(self, tmp_path, monkeypatch):
        self.tmp, self.monkeypatch = tmp_path, monkeypatch
        self.cache = tmp_path / "cache"
        self.log = tmp_path / "cxx.log"
        monkeypatch.setenv("DENOISER_CACHE", str(self.cache))
        monkeypatch.delenv(ovext.MARCH_ENV, raising=False)  # the native build, whatever the caller's target

    def compiler(self, body: str, name: str = "fake-cxx"):
        """``$CXX`` becomes a script that logs its arguments, sets ``$OUT`` to its ``-o`` path, then runs ``body``."""
        script = self.tmp / name
        script.write_text(f'#!/bin/sh\necho "$@" >> "{self.log}"\n'
                          'while [ $# -gt 0 ]; do [ "$1" = "-o" ] && OUT="$2"; shift; done\n' + body + "\n")
        script.chmod(script.stat().st_mode | stat.S_IEXEC)
        self.monkeypatch.setenv("CXX", str(script))

    def runs(self) -> list[str]:
        """The builds the script ran (not the queries of its target macros, ``-dM -E``)."""
        lines = self.log.read_text().splitlines() if self.log.exists() else []
        return [line for line in lines if "-dM" not in line.split()]

    def status(self):
        ovext._status.cache_clear()
        return ovext.kernel_extension(), ovext.unavailable_reason()


@pytest.fixture
def fake(tmp_path, monkeypatch):
    pytest.importorskip("openvino", reason="openvino is not installed (pip install .[openvino])")
    try:
        yield FakeBuild(tmp_path, monkeypatch)
    finally:
        ovext._status.cache_clear()  # the next use builds again under the restored environment


FAILS = "echo 'extension.cpp:1:1: error: simulated failure' >&2\nexit 1"
BUILDS = "printf 'built by the fake compiler\\n' > \"$OUT\""


def test_failed_build_leaves_no_library_and_says_why(fake):
    """A compiler error becomes the reason (one line); no library is left in the cache, only the
    remembered reason."""
    fake.compiler(FAILS)
    path, reason = fake.status()
    assert path is None and "simulated failure" in reason and "\n" not in reason
    left = [p for p in fake.cache.rglob("*") if p.is_file()]
    assert [p.name for p in left] == [ovext.FAILED], left
    assert "simulated failure" in left[0].read_text()


def test_a_failed_build_is_remembered(fake):
    """The next process says the remembered reason without compiling; deleting the marker retries."""
    fake.compiler(FAILS)
    first = fake.status()[1]
    path, reason = fake.status()
    assert path is None and len(fake.runs()) == 1
    assert reason.startswith(first) and "remembered" in reason
    marker = next(fake.cache.rglob(ovext.FAILED))
    assert str(marker) in reason
    marker.unlink()
    fake.compiler(BUILDS)  # the same script path: the same cache key
    path, reason = fake.status()
    assert reason is None and path.read_text() == "built by the fake compiler\n" and len(fake.runs()) == 2


def test_a_compiler_that_hangs_is_stopped(fake, monkeypatch):
    """A compiler past ``$DENOISER_OVEXT_TIMEOUT`` is killed with its children (the shell's
    ``sleep`` holds the output pipes) and the build fails with the reason, remembered."""
    monkeypatch.setenv(ovext.TIMEOUT_ENV, "0.5")
    fake.compiler("sleep 60\n" + BUILDS)
    start = time.monotonic()
    path, reason = fake.status()
    assert time.monotonic() - start < 20
    assert path is None and "took longer than 0.5 s" in reason and ovext.TIMEOUT_ENV in reason
    assert not list(fake.cache.rglob("*.so")) and len(list(fake.cache.rglob(ovext.FAILED))) == 1


def test_a_bad_timeout_is_a_reason_not_a_failed_build(fake, monkeypatch):
    monkeypatch.setenv(ovext.TIMEOUT_ENV, "soon")
    fake.compiler(BUILDS)
    path, reason = fake.status()
    assert path is None and reason == f"${ovext.TIMEOUT_ENV}='soon': not a positive number of seconds"
    assert fake.runs() == [] and not list(fake.cache.rglob(ovext.FAILED))


def test_a_foreign_library_is_not_loaded(fake, capfd):
    """A real shared library (OpenVINO's TBB) planted at the exact path the cache loads from is
    refused: by :func:`~denoiser.inference.ovext.load_into` in the process that checked the build, and by the
    next process, which builds the library again; likewise with the recorded hash removed."""
    import openvino as ov

    fake.compiler(BUILDS)
    path, _ = fake.status()
    digest = ovext._hash_file(path).read_text().strip()
    assert digest == hashlib.sha256(b"built by the fake compiler\n").hexdigest()
    foreign = ovext._openvino_libs(Path(ov.__file__).parent)[-1].read_bytes()  # libtbb.so
    path.write_bytes(foreign)
    with pytest.raises(UserError, match="SHA-256 is not the one recorded"):
        ovext.load_into(ov.Core())
    capfd.readouterr()
    again, reason = fake.status()
    assert again == path and reason is None and len(fake.runs()) == 2
    assert path.read_text() == "built by the fake compiler\n"
    assert "not the one recorded after its build; not loading it, building it again" in capfd.readouterr().err
    path.write_bytes(foreign)
    ovext._hash_file(path).unlink()
    again, reason = fake.status()
    assert again == path and reason is None and len(fake.runs()) == 3
    assert path.read_text() == "built by the fake compiler\n" and ovext._hash_file(path).read_text().strip() == digest
    assert "no SHA-256 recorded beside it" in capfd.readouterr().err


def test_cache_folders_are_private(fake):
    fake.compiler(BUILDS)
    path, _ = fake.status()
    for folder in (fake.cache, fake.cache / "ovext", path.parent):
        assert stat.S_IMODE(folder.stat().st_mode) == 0o700, folder


@pytest.mark.parametrize("problem", ["group-writable root", "world-writable ovext", "ovext of another user",
                                     "ovext a link"])
def test_an_untrusted_cache_folder_is_refused(fake, problem):
    """The cache root or ``ovext/`` writable by others, owned by another user, or a link: the
    reason names the folder and the problem, and nothing is compiled or loaded there."""
    ovdir = fake.cache / "ovext"
    if problem == "ovext a link":
        elsewhere = fake.tmp / "elsewhere"
        elsewhere.mkdir(mode=0o700)
        fake.cache.mkdir(mode=0o700)
        ovdir.symlink_to(elsewhere)
    else:
        ovdir.mkdir(parents=True, mode=0o700)
    if problem == "group-writable root":
        fake.cache.chmod(0o770)
    elif problem == "world-writable ovext":
        ovdir.chmod(0o702)
    elif problem == "ovext of another user":
        if os.getuid() != 0:
            pytest.skip("giving a folder to another user needs root")
        os.chown(ovdir, 65534, 65534)
    fake.compiler(BUILDS)
    path, reason = fake.status()
    assert path is None and fake.runs() == []
    folder = fake.cache if problem.endswith("root") else ovdir
    expect = {"group-writable root": "writable by group or others (mode 0770)",
              "world-writable ovext": "writable by group or others (mode 0702)",
              "ovext of another user": "owned by user id 65534", "ovext a link": "not a folder"}[problem]
    assert reason.startswith(f"{folder}: {expect}"), reason


@pytest.mark.parametrize("cpuinfo", ["flags", "no flags line", "missing"])
def test_march_native_only_where_the_cpu_flags_are_known(fake, monkeypatch, cpuinfo):
    """Without a ``flags`` line in /proc/cpuinfo the CPU cannot be told apart from another, so the
    cached library is built for the compiler's default target, under its own key."""
    info = fake.tmp / "cpuinfo"
    if cpuinfo != "missing":
        info.write_text("processor\t: 0\nmodel name\t: test\n" + ("flags\t\t: fpu sse2 avx2\n" if cpuinfo == "flags" else ""))
    monkeypatch.setattr(ovext, "CPUINFO", info)
    fake.compiler(BUILDS)
    path, reason = fake.status()
    assert reason is None and path.exists()
    assert (ovext.NATIVE in fake.runs()[0].split()) == (cpuinfo == "flags")
    monkeypatch.setattr(ovext, "CPUINFO", fake.tmp / "other")
    (fake.tmp / "other").write_text("flags\t\t: fpu sse2\n")
    assert fake.status()[0].parent != path.parent  # another CPU: another key


def test_the_cache_key_holds_the_dispatch_targets(fake, monkeypatch):
    """The vector ISAs the compiler targets are part of the key: the same compiler, flags and CPU
    flags with another target (a compiler upgrade that resolves -march=native differently) is
    another build, not the cached library."""
    fake.compiler(BUILDS)
    monkeypatch.setattr(ovext, "dispatch_targets", lambda cxx, flags: "avx2 avx fma sse2")
    path, reason = fake.status()
    assert reason is None and len(fake.runs()) == 1
    assert fake.status()[0] == path and len(fake.runs()) == 1  # the same targets: the cached library
    monkeypatch.setattr(ovext, "dispatch_targets", lambda cxx, flags: "avx512f avx512bw avx512vl avx2 avx fma sse2")
    other, reason = fake.status()
    assert reason is None and other.parent != path.parent and len(fake.runs()) == 2


def test_dispatch_targets_are_the_widest_the_cpu_has():
    """With -march=native the compiler targets the CPU's widest vector ISA (what the kernels'
    strips are as wide as: common.hpp), read from its own macros; an unknown compiler says nothing."""
    cxx = ovext.compiler()
    if cxx is None or ovext._cpu_flags() is None:
        pytest.skip("no C++ compiler, or no CPU flags in /proc/cpuinfo")
    cpu = set(ovext._cpu_flags().split(":", 1)[1].split())
    native = ovext.dispatch_targets(cxx, (*ovext.FLAGS, ovext.NATIVE)).split()
    for isa in ("avx512f", "avx2", "fma", "sse2"):
        if isa in cpu:
            assert isa in native, (isa, native)
    if "avx512f" not in cpu:
        assert "avx512f" not in native
    assert "avx512f" not in ovext.dispatch_targets(cxx, ovext.FLAGS).split()  # the default target: portable
    assert ovext.dispatch_targets(str(Path(cxx).with_name("no-such-compiler")), ovext.FLAGS) == ""


def _real_compiler_and_cpu():
    cxx = ovext.compiler()
    if cxx is None or ovext._cpu_flags() is None or platform.machine() != "x86_64":
        pytest.skip("needs a C++ compiler and an x86-64 CPU whose flags /proc/cpuinfo names")
    return cxx, set(ovext._cpu_flags().split(":", 1)[1].split())


def test_march_from_the_environment_is_its_own_build(fake, monkeypatch):
    """$DENOISER_OVEXT_MARCH builds for that target in place of -march=native, under another key
    than the native library; unset again, the native library is the one found."""
    cxx, _cpu = _real_compiler_and_cpu()
    fake.compiler(BUILDS)
    real = ovext._defined_macros  # the target's macros from the real compiler, the builds by the fake one
    monkeypatch.setattr(ovext, "_defined_macros", lambda c, flags: real(cxx, flags))
    native, reason = fake.status()
    assert reason is None and ovext.NATIVE in fake.runs()[0].split()
    monkeypatch.setenv(ovext.MARCH_ENV, "x86-64")  # SSE2: every x86-64 CPU has it
    other, reason = fake.status()
    assert reason is None and other.parent != native.parent
    assert "-march=x86-64" in fake.runs()[1].split() and ovext.NATIVE not in fake.runs()[1].split()
    monkeypatch.delenv(ovext.MARCH_ENV)
    assert fake.status()[0] == native and len(fake.runs()) == 2


@pytest.mark.parametrize("march", ["not a target", "no-such-cpu-name", "a wider CPU"])
def test_a_march_this_cpu_cannot_run_is_refused(fake, monkeypatch, march):
    """A malformed or unknown target, or one that enables an ISA -march=native does not (an
    AVX-512 build on an AVX2 CPU, AVX512-FP16 and AMX on a CPU without them), is refused in one
    line naming the variable, and nothing is compiled."""
    cxx, cpu = _real_compiler_and_cpu()
    fake.compiler(BUILDS)
    real = ovext._defined_macros  # the target's macros from the real compiler, the builds by the fake one
    monkeypatch.setattr(ovext, "_defined_macros", lambda c, flags: real(cxx, flags))
    if march == "a wider CPU":
        macros = real(cxx, ("-march=sapphirerapids",))
        if macros is None:
            pytest.skip(f"{cxx} does not know -march=sapphirerapids")
        if not any(ovext.ISA_MACRO.fullmatch(m) for m in macros - (real(cxx, ("-march=native",)) or macros)):
            pytest.skip("this CPU has every ISA of sapphirerapids")
        march = "sapphirerapids"
    monkeypatch.setenv(ovext.MARCH_ENV, march)
    path, reason = fake.status()
    assert path is None and fake.runs() == [] and "\n" not in reason
    assert reason.startswith(f"${ovext.MARCH_ENV}={march!r}"), reason
    expect = {"not a target": "not a -march= target name", "no-such-cpu-name": "does not know that target",
              "sapphirerapids": "which this CPU lacks"}[march]
    assert expect in reason, reason
    if march == "sapphirerapids":  # it names ISAs, and only ones this CPU's flags lack (which they are varies:
        # AVX512-FP16 and AMX on most CPUs; AVX512-VP2INTERSECT, ENQCMD, ... on an Intel Xeon that has those two)
        named = reason.split(" enables ", 1)[1].split(", which", 1)[0].split(", ")
        flags = {f.replace("_", "") for f in cpu}
        assert named and not any(n.replace("_", "") in flags for n in named), reason


def warp_history_loop(motion, keep, buffers, cover_min=1e-4):
    """The history's sampling, a plain loop over pixels (float64): motion sanitised (NaN, -Inf -> 0,
    +Inf -> 65504) and clamped to 4 frame sizes, the position p + motion (x off the image at -2 where
    the item is not kept), each buffer read bilinearly with zeros outside (every in-image corner read,
    whatever its weight), divided by the in-image share of the footprint (the coverage) where that
    exceeds cover_min, else 0; and valid, the coverage there."""
    m = np.nan_to_num(motion.double().numpy(), nan=0.0, posinf=65504.0, neginf=0.0)
    xs = [b.double().numpy() for b in buffers]
    n, _, h, w = m.shape
    limit = 4.0 * max(h, w)
    outs = [np.zeros_like(x) for x in xs]
    valid = np.zeros((n, 1, h, w))
    for b in range(n):
        for y in range(h):
            for px in range(w):
                sx = px + min(max(m[b, 0, y, px], -limit), limit) if keep[b] else -2.0
                sy = y + min(max(m[b, 1, y, px], -limit), limit)
                x0, y0 = math.floor(sx), math.floor(sy)
                fx, fy = sx - x0, sy - y0
                corners = [(y0, x0, (1 - fx) * (1 - fy)), (y0, x0 + 1, fx * (1 - fy)),
                           (y0 + 1, x0, (1 - fx) * fy), (y0 + 1, x0 + 1, fx * fy)]
                inside = [(yy, xx, wt) for yy, xx, wt in corners if 0 <= yy < h and 0 <= xx < w]
                cover = sum(wt for _, _, wt in inside)
                if cover <= cover_min:
                    continue
                valid[b, 0, y, px] = cover
                for x, out in zip(xs, outs):
                    out[b, :, y, px] = sum(wt * x[b, :, yy, xx] for yy, xx, wt in inside) / cover
    return outs, valid


def warp_inputs(b: int, h: int, w: int, seed: int, channels=(3, 3, 4, 7)):
    """Motion ``[B, 2, H, W]`` of a few pixels, random in the upper half (whole-pixel steps: half the
    footprint off the image) and smooth in the lower, with huge values (clamped), NaN and infinities;
    the state buffers; keep: the last item reset."""
    g = torch.Generator().manual_seed(seed)
    motion = torch.randn(b, 2, h, w, generator=g) * 3.0
    motion[:, :, ::3, ::2] = motion[:, :, ::3, ::2].round()  # whole pixels: one footprint column on the edge
    xs = torch.arange(w, dtype=torch.float32)
    motion[:, 0, h // 2:] = 0.7 + 2.0 * torch.sin(xs / 5.0)   # smooth in the lower half, as rendered motion is:
    motion[:, 1, h // 2:] = -0.4                              # a row's corners lie close together
    motion[:, 0, ::5, 1::4] = 1e7                             # clamped to 4 frame widths: off the image
    motion[:, 1, 1::6, ::3] = float("nan")                    # no motion
    motion[:, 0, 2::7, 2::5] = float("inf")
    motion[:, 1, 3::7, ::4] = float("-inf")
    buffers = [torch.rand(b, c, h, w, generator=g) * 4.0 - 1.0 for c in channels]
    keep = torch.ones(b, dtype=torch.bool)
    keep[-1] = False
    return motion, keep, buffers


@needs_extension
@pytest.mark.parametrize(("hw", "last"), [((7, 11), (0, 0, 1, 1)), ((1, 6), (0, 0, 1, 1)), ((5, 1), (0, 0, 1, 1)),
                                          ((29, 41), (0, 0, 1, 1)), ((29, 41), (0, 0, 0, 0)), ((7, 40), (1, 0, 1, 0))])
def test_warp_history_matches_the_loop_over_pixels(tmp_path, hw, last):
    """``denoiser::WarpHistory`` (the sampling of :meth:`~denoiser.nn.temporal.TemporalRecurrence.warp`)
    against a loop over pixels and against eager, at odd sizes (a single row or column; 41 columns:
    the 16-pixel gathers and the rest), with huge, NaN and infinite motion and a reset item (whose
    NaN state is never read), buffers written planar and channels-last (``last``; the exported
    graphs': the last two); the same bits with 1 and 2 threads."""
    import openvino as ov

    from denoiser.nn.warp import WarpHistoryOp

    class Warp(torch.nn.Module):
        def forward(self, motion, keep, a, b, c, d):
            return WarpHistoryOp.apply(motion, keep.view(-1, 1, 1, 1), 1e-4, tuple(map(bool, last)), a, b, c, d)

    motion, keep, buffers = warp_inputs(2, *hw, seed=hw[1])
    buffers[2][-1] = float("nan")  # the reset item's state
    names = ["motion", "keep", "a", "b", "c", "d"]
    with torch.no_grad(), kernels_as_op(True):
        torch.onnx.export(Warp(), (motion, keep, *buffers), str(tmp_path / "w.onnx"), input_names=names,
                          output_names=["oa", "ob", "oc", "od", "valid"], opset_version=17, dynamo=False,
                          custom_opsets={"denoiser": 1})
    core = ov.Core()
    ovext.load_into(core, tmp_path / "w.onnx")

    def run(threads):
        compiled = core.compile_model(core.read_model(str(tmp_path / "w.onnx")), "CPU", {"INFERENCE_NUM_THREADS": threads})
        result = compiled(dict(zip(names, [t.numpy() for t in (motion, keep, *buffers)])))
        return [result[compiled.output(i)] for i in range(5)]

    got = run(2)
    assert [g.shape for g in got] == [(2, *hw, c) if l else (2, c, *hw) for c, l in zip((3, 3, 4, 7, 1), (*last, 0))]
    got = [g.transpose(0, 3, 1, 2) if l else g for g, l in zip(got, (*last, 0))]  # all [B, C, H, W] from here
    outs, valid = warp_history_loop(motion, keep, buffers)
    assert (valid[-1] == 0).all()  # the reset item reads nothing
    if min(hw) > 1:  # not a single row or column, which motion of a few pixels leaves: the comparison sees samples
        assert (valid[0] > 0).mean() > 0.3 and ((valid[0] > 0) & (valid[0] < 1)).any()
    np.testing.assert_allclose(got[-1], valid, atol=2e-6)
    for g, want in zip(got, outs):  # the samples before the division: a small coverage magnifies float32 rounding
        assert np.isfinite(g).all()
        np.testing.assert_allclose(g * got[-1], want * valid, atol=2e-5)
    with torch.no_grad():
        eager = Warp()(motion, keep, *buffers)
    for g, want, l in zip(got, eager, (*last, 0)):
        np.testing.assert_allclose(g, (want.permute(0, 3, 1, 2) if l else want).numpy(), atol=2e-5)
    got_one = [g.transpose(0, 3, 1, 2) if l else g for g, l in zip(run(1), (*last, 0))]
    assert all(np.array_equal(a, b) for a, b in zip(got_one, got))
