"""Baseline filters NPPD (learned upsampling pyramid) and WS (weight-sharing kernels): the fast
paths against plain loops over pixels, convexity on hard inputs, and their net configs end to end
(build, recurrent forward with a reset, gradients, a few training steps, export)."""

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from denoiser.buffers import FRAME_INPUTS
from denoiser.configs import build_net, compose_net_config
from denoiser.frames import random_frame
from denoiser.measure import count_flops
from denoiser.nn.inputs import sanitize
from denoiser.nn.kernels import scale_logits
from denoiser.nn.nppd import LearnedUpsamplingPyramid, bilinear_splat_logits, splat_upsample
from denoiser.nn.pyramid import PyramidFilter
from denoiser.nn.ws import WeightSharingFilter, box_sum

# (net config, kernel group, ablation): the CPU-width baselines and our net with learned upsampling
NETS = [("nppd_demo", None, "none"), ("ws_demo", None, "none"), ("tiny", None, "learned_upsampling")]


@pytest.fixture(autouse=True, scope="module")
def flush_denormals():
    """Extreme logits give denormal softmax weights, which are very slow on CPUs."""
    torch.set_flush_denormal(True)
    yield
    torch.set_flush_denormal(False)


def random_heads(filt, b, h, w, scale, g):
    return [torch.randn(b, n, h // 2**i, w // 2**i, generator=g) * scale
            for i, n in enumerate(filt.head_channels)]


def assert_within_input_range(out, x):
    lo, hi = x.amin(dim=(2, 3), keepdim=True), x.amax(dim=(2, 3), keepdim=True)
    tol = 1e-5 * hi.abs().clamp_min(1.0)
    assert torch.isfinite(out).all()
    assert (out >= lo - tol).all() and (out <= hi + tol).all()


# ----------------------------------------------------------------------------- NPPD: learned upsampling


def splat_loop(coarse: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Reference: every coarse pixel (Y, X) adds ``weights[a*4+b] * value`` to fine (2Y-1+a, 2X-1+b)."""
    b, c, h, w = coarse.shape
    out = torch.zeros(b, c, 2 * h, 2 * w, dtype=coarse.dtype)
    for y in range(h):
        for x in range(w):
            for a in range(4):
                for t in range(4):
                    fy, fx = 2 * y - 1 + a, 2 * x - 1 + t
                    if 0 <= fy < 2 * h and 0 <= fx < 2 * w:
                        out[:, :, fy, fx] += weights[:, a * 4 + t, y, x, None] * coarse[:, :, y, x]
    return out


@pytest.mark.parametrize("size", [(1, 1), (3, 5), (4, 4)])
def test_splat_upsample_matches_pixel_loop(size):
    g = torch.Generator().manual_seed(sum(size))
    coarse = torch.rand(2, 4, *size, generator=g, dtype=torch.float64)
    weights = torch.rand(2, 16, *size, generator=g, dtype=torch.float64)
    torch.testing.assert_close(splat_upsample(coarse, weights), splat_loop(coarse, weights))


def test_bilinear_splat_weights_are_bilinear_upsampling_inside():
    """The prior's weights (times 4) are bilinear 2x upsampling away from the border (where
    bilinear clamps and the splat drops the weight, which the normalisation makes up for)."""
    coarse = torch.rand(1, 3, 6, 7, dtype=torch.float64)
    weights = torch.from_numpy(4 * np.exp(bilinear_splat_logits())).double().view(1, 16, 1, 1).expand(1, 16, 6, 7)
    assert float(weights[0, :, 0, 0].sum()) == pytest.approx(4.0)
    expected = F.interpolate(coarse, scale_factor=2, mode="bilinear", align_corners=False)
    torch.testing.assert_close(splat_upsample(coarse, weights)[..., 1:-1, 1:-1], expected[..., 1:-1, 1:-1])


def test_learned_pyramid_with_bilinear_prior_starts_at_our_pyramid():
    """Zero upsampling logits + bilinear prior = PyramidFilter, away from the border."""
    g = torch.Generator().manual_seed(3)
    ours = PyramidFilter([5, 3, 3], logit_scale=2.5)
    learned = LearnedUpsamplingPyramid([5, 3, 3], logit_scale=2.5, bilinear_prior=True)
    x = torch.rand(1, 3, 32, 32, generator=g) * 10
    heads = random_heads(ours, 1, 32, 32, 3.0, g)
    padded = [heads[0]] + [torch.cat([hd, torch.zeros(1, 16, *hd.shape[-2:])], 1) for hd in heads[1:]]
    a, _ = ours(x, heads, torch.ones(1, 1, 1, 1))
    b, _ = learned(x, padded, torch.ones(1, 1, 1, 1))
    torch.testing.assert_close(b[..., 6:-6, 6:-6], a[..., 6:-6, 6:-6], rtol=1e-5, atol=1e-5)


def test_learned_upsampling_weights_change_the_output():
    g = torch.Generator().manual_seed(4)
    filt = LearnedUpsamplingPyramid([3, 3], logit_scale=2.5)
    assert filt.head_channels == [2 + 9, 9 + 16]
    x = torch.rand(1, 3, 8, 8, generator=g)
    heads = random_heads(filt, 1, 8, 8, 1.0, g)
    part = torch.full((1, 2, 8, 8), -1e4)
    part[:, 1] = 0  # everything through level 1
    heads[0] = torch.cat([part, heads[0][:, 2:]], 1)
    out1, _ = filt(x, heads, torch.ones(1, 1, 1, 1))
    heads[1] = heads[1].clone()
    heads[1][:, 9:] = torch.randn(1, 16, 4, 4, generator=g) * 5
    out2, _ = filt(x, heads, torch.ones(1, 1, 1, 1))
    assert not torch.allclose(out1, out2)


@pytest.mark.parametrize("logit_scale, prior", [(None, False), (2.5, False), (20.0, True)])
@pytest.mark.parametrize("magnitude", [0.0, 1.0, 1e6])
def test_learned_pyramid_output_within_input_range(logit_scale, prior, magnitude):
    g = torch.Generator().manual_seed(int(magnitude) % 97)
    filt = LearnedUpsamplingPyramid([5, 3, 3], logit_scale=logit_scale, bilinear_prior=prior)
    x = torch.rand(2, 3, 20, 12, generator=g) * magnitude
    x[:, :, 10, 6] = 1e6  # firefly
    heads = random_heads(filt, 2, 20, 12, 30.0, g)
    heads[1][0, 0, 0, 0] = float("nan")
    heads[2][1, -1, 0, 0] = float("inf")
    out, weights = filt(x, heads, torch.ones(2, 1, 1, 1))
    assert out.shape == x.shape
    assert_within_input_range(out, x)
    torch.testing.assert_close(weights["partition"].sum(1), torch.ones(2, 20, 12))


def test_learned_pyramid_keeps_a_constant_image():
    filt = LearnedUpsamplingPyramid([5, 5, 5])
    x = torch.full((1, 3, 16, 24), 3.5)
    out, _ = filt(x, random_heads(filt, 1, 16, 24, 5.0, torch.Generator().manual_seed(0)), torch.ones(1, 1, 1, 1))
    torch.testing.assert_close(out, x)


# ----------------------------------------------------------------------------- WS: weight-sharing kernels


def ws_loop(x, head, sizes, dilations, logit_scale, max_log):
    """Reference in float64: per pixel, each kernel's sum of s(q) x(q) / sum of s(q) over its
    in-image window, fused by the softmax of the normalised fusion logits."""
    n = len(sizes)
    x, head = x.double(), head.double()
    shared = torch.exp(max_log * torch.tanh(head[:, :n] / max_log))
    fusion = torch.softmax(scale_logits(head[:, n:], logit_scale).double(), dim=1)
    b, c, h, w = x.shape
    out = torch.zeros(b, c, h, w, dtype=torch.float64)
    for y in range(h):
        for xx in range(w):
            for j, (k, d) in enumerate(zip(sizes, dilations)):
                num, den = torch.zeros(b, c, dtype=torch.float64), torch.zeros(b, 1, dtype=torch.float64)
                for i in range(-(k // 2), k // 2 + 1):
                    for t in range(-(k // 2), k // 2 + 1):
                        qy, qx = y + d * i, xx + d * t
                        if 0 <= qy < h and 0 <= qx < w:
                            num += shared[:, j, qy, qx, None] * x[:, :, qy, qx]
                            den += shared[:, j, qy, qx, None]
                out[:, :, y, xx] += fusion[:, j, y, xx, None] * num / den
    return out


@pytest.mark.parametrize("size", [(7, 9), (1, 1), (2, 5)])
def test_weight_sharing_filter_matches_pixel_loop(size):
    g = torch.Generator().manual_seed(size[0])
    sizes, dilations = [1, 3, 5], [1, 1, 2]
    filt = WeightSharingFilter(sizes, dilations, logit_scale=2.5, max_log_weight=4.0)
    x = torch.rand(2, 3, *size, generator=g) * 10
    head = torch.randn(2, 6, *size, generator=g) * 3
    out, weights = filt(x, [head], torch.ones(2, 1, 1, 1))
    torch.testing.assert_close(out.double(), ws_loop(x, head, sizes, dilations, 2.5, 4.0), rtol=1e-5, atol=1e-5)
    assert weights["fusion"].shape == (2, 3, *size)


def test_box_sum_matches_loop_with_dilation():
    x = torch.rand(1, 2, 6, 11, dtype=torch.float64)
    got = box_sum(x, 3, 3)
    expected = torch.zeros_like(x)
    for y in range(6):
        for xx in range(11):
            for i in (-3, 0, 3):
                for t in (-3, 0, 3):
                    if 0 <= y + i < 6 and 0 <= xx + t < 11:
                        expected[:, :, y, xx] += x[:, :, y + i, xx + t]
    torch.testing.assert_close(got, expected)


@pytest.mark.parametrize("logit_magnitude", [1.0, 1e6])
@pytest.mark.parametrize("kind", ["fireflies", "black", "hdr"])
def test_weight_sharing_filter_output_within_input_range(logit_magnitude, kind):
    g = torch.Generator().manual_seed(5)
    filt = WeightSharingFilter([1, 3, 7, 13], [1, 1, 1, 2], logit_scale=2.5)
    x = {"fireflies": torch.rand(2, 3, 17, 23, generator=g) * 0.01,
         "black": torch.zeros(2, 3, 17, 23), "hdr": torch.rand(2, 3, 17, 23, generator=g) * 1e6}[kind]
    if kind == "fireflies":
        x[:, :, 8, 11] = 1e6
    head = torch.randn(2, 8, 17, 23, generator=g) * logit_magnitude
    head[0, 0, 0, 0], head[1, 5, 3, 3], head[0, 2, 1, 1] = float("nan"), float("inf"), float("-inf")
    out, weights = filt(x, [head], torch.ones(2, 1, 1, 1))
    assert_within_input_range(out, x)
    torch.testing.assert_close(weights["fusion"].sum(1), torch.ones(2, 17, 23))


def test_weight_sharing_shared_weights_are_bounded_and_keep_a_gradient():
    filt = WeightSharingFilter([3], max_log_weight=8.0)
    z = torch.tensor([-1e6, -10.0, 0.0, 10.0, 1e6], requires_grad=True)
    s = filt.shared_weights(z.view(1, 1, 1, 5))
    assert float(s.detach().min()) >= math.exp(-8.0) * (1 - 1e-6) and float(s.detach().max()) <= math.exp(8.0) * (1 + 1e-6)
    s.sum().backward()
    assert (z.grad[1:4] > 0).all()


def test_weight_sharing_config_mistakes():
    from denoiser.errors import ConfigError

    with pytest.raises(ConfigError, match="dilations"):
        WeightSharingFilter([1, 3], [1])
    with pytest.raises(ConfigError, match="kernel.sizes"):
        WeightSharingFilter([2, 3])


# ----------------------------------------------------------------------------- the nets end to end


def window(b, h, w, seed, kind="plain"):
    frames = [random_frame(b, h, w, seed=seed + t, kind=kind) for t in range(3)]
    return {k: torch.stack([f[k] for f in frames], dim=1) for k in FRAME_INPUTS}


def make_net(name, kernel, ablation, seed=0):
    torch.manual_seed(seed)
    return build_net(compose_net_config(name, kernel, ablation=ablation))


def test_configs_build_the_baseline_filters():
    assert isinstance(make_net("nppd_demo", None, "none").filter, LearnedUpsamplingPyramid)
    ws = make_net("ws_demo", None, "none")
    assert isinstance(ws.filter, WeightSharingFilter) and ws.unet.head_channels[0] == 8 + ws.temporal.head_channels
    ablated = make_net("tiny", "teacher", "learned_upsampling")
    assert isinstance(ablated.filter, LearnedUpsamplingPyramid) and ablated.filter.bilinear_prior
    assert ablated.filter.kernel_sizes == [5, 7, 9] and ablated.filter.logit_scale == 2.5


def test_nppd_gpu_config_has_five_levels_and_runs():
    cfg = compose_net_config("nppd")  # kernel group nppd by name: five 5x5 levels
    assert cfg["unet"]["encoder"] == [96, 128, 192, 256, 384] and cfg["embed"]["hidden"] == 32
    net = build_net(cfg)
    assert net.filter.levels == 5 and net.multiple == 32
    assert net.unet.head_channels[1:] == [25 + 16] * 4
    with torch.no_grad():
        out, _, _ = net(window(1, 16, 24, 0))
    assert out.shape == (1, 3, 3, 16, 24) and torch.isfinite(out).all()


@pytest.mark.parametrize("name, kernel, ablation", NETS)
def test_forward_with_reset_gradients_and_training(name, kernel, ablation):
    net = make_net(name, kernel, ablation)
    frames = window(2, 17, 23, 1, kind="hard")
    frames["color"][0, 1, 0, 0, 0] = float("nan")
    frames["color"][1, 2, 1, 3, 3] = float("inf")
    frames["color"][:, 2, :, 8, 11] = 1e6  # firefly
    frames["color"].requires_grad_(True)
    reset = torch.tensor([[True, False, True], [True, False, False]])
    outs, _state, extras = net(frames, reset=reset)
    assert outs.shape == (2, 3, 3, 17, 23) and torch.isfinite(outs).all() and len(extras) == 3
    # a reset frame has no history: within the range of its own (sanitised) input
    first = sanitize(frames["color"][:, 0].detach())
    assert_within_input_range(outs[:, 0], first)
    target = torch.rand_like(outs)
    ((outs - target).abs() / (outs.abs() + target.abs() + 0.01)).mean().backward()
    grads = [p.grad for p in net.parameters() if p.grad is not None]
    assert grads and all(torch.isfinite(gr).all() for gr in grads)
    assert torch.isfinite(frames["color"].grad).all()
    # reset at frame 2 of item 0: the same as a fresh start on that frame alone
    with torch.no_grad():
        single = {k: v[:1, 2:] for k, v in frames.items()}
        fresh, _, _ = net(single)
        torch.testing.assert_close(outs[:1, 2].detach(), fresh[:, 0])


@pytest.mark.parametrize("name, kernel, ablation", NETS)
def test_a_few_training_steps_reduce_the_loss(name, kernel, ablation):
    net = make_net(name, kernel, ablation, seed=1)
    frames = window(1, 16, 16, 5)
    frames["motion"].zero_()
    # a learnable target: the 5x5 box blur of the noisy frames
    target = F.avg_pool2d(frames["color"].flatten(0, 1), 5, stride=1, padding=2,
                          count_include_pad=False).view_as(frames["color"])
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)

    def loss_now():
        outs, _, _ = net(frames)
        return (outs - target).abs().mean()

    losses = []
    for _ in range(8):
        loss = loss_now()
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(float(loss.detach()))
    with torch.no_grad():
        final = float(loss_now())
    assert math.isfinite(final) and final < 0.9 * losses[0], losses + [final]


@pytest.mark.parametrize("name, kernel, ablation", NETS)
@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_autocast_outputs_are_float32_and_bounded(name, kernel, ablation, dtype):
    net = make_net(name, kernel, ablation)
    frames = window(1, 17, 23, 2, kind="hard")
    with torch.no_grad(), torch.autocast("cpu", dtype=dtype):
        outs, _, _ = net(frames)
    assert outs.dtype == torch.float32 and torch.isfinite(outs).all()
    assert_within_input_range(outs[:, 0], sanitize(frames["color"][:, 0]))


@pytest.mark.parametrize("name", ["nppd_demo", "ws_demo"])
def test_flops_are_counted(name):
    net = make_net(name, None, "none")
    assert count_flops(net, 32, 32) > 2 * net.num_parameters() * 32 * 32 / 64


@pytest.mark.parametrize("name", ["nppd_demo", "ws_demo"])
def test_onnx_export_matches_pytorch(name, tmp_path):
    pytest.importorskip("onnxruntime")
    from denoiser.inference.step_graph import check_export, export_onnx

    net = make_net(name, None, "none").eval()
    path = export_onnx(net, tmp_path / f"{name}.onnx", trace_size=(13, 21))
    errors = check_export(net, path, size=(20, 28), steps=2, threads=1)
    assert all(err <= 1e-4 * max(1.0, scale) for err, scale in errors.values()), errors


def test_nppd_demo_encodes_samples_per_sample():
    """NPPD's per-sample encoder is our EmbedNet over ``samples``: they change the output."""
    from denoiser.buffers import NETWORK_INPUTS

    net = make_net("nppd_demo", None, "none")
    frames = [random_frame(1, 16, 16, seed=t, samples=3) for t in range(2)]
    with_samples = {k: torch.stack([f[k] for f in frames], dim=1) for k in NETWORK_INPUTS if k in frames[0]}
    assert with_samples["samples"].shape == (1, 2, 3, 3, 16, 16)
    without = {k: v for k, v in with_samples.items() if k != "samples"}
    with torch.no_grad():
        a, _, _ = net(with_samples)
        b, _, _ = net(without)
    assert torch.isfinite(a).all() and not torch.allclose(a, b)
