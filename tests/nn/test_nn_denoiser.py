"""Denoiser.step / forward: any size, hard inputs, autocast, bounds, temporal history, resets."""

import copy

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from denoiser.configs import build_net, compose_net_config
from denoiser.frames import random_frame
from denoiser.nn.inputs import guide_features, sanitize


def make_net(ablation="none", gain=1.0, seed=0):
    torch.manual_seed(seed)
    net = build_net(compose_net_config("tiny", ablation=ablation))
    if gain != 1.0:  # exaggerated weights make the heads produce extreme logits
        with torch.no_grad():
            for p in net.parameters():
                p.mul_(gain)
    return net


@pytest.fixture(autouse=True, scope="module")
def flush_denormals():
    """Extreme logits give denormal softmax weights, which are very slow on CPUs."""
    torch.set_flush_denormal(True)
    yield
    torch.set_flush_denormal(False)


@pytest.fixture(scope="module")
def net():
    return make_net()


@pytest.fixture(scope="module")
def wild():
    return make_net(gain=4.0, seed=1)


def channel_range(*tensors):
    lo = torch.stack([t.amin(dim=(2, 3)) for t in tensors]).amin(0)[..., None, None]
    hi = torch.stack([t.amax(dim=(2, 3)) for t in tensors]).amax(0)[..., None, None]
    return lo, hi


def assert_within(out, lo, hi):
    tol = 1e-5 * hi.abs().clamp_min(1.0)
    assert (out >= lo - tol).all() and (out <= hi + tol).all()


def hard_frame(kind, h, w, seed):
    f = random_frame(2, h, w, seed=seed)
    g = torch.Generator().manual_seed(seed)
    if kind == "black":
        f["color"].zero_()
    elif kind == "hdr":
        f["color"] = torch.rand(2, 3, h, w, generator=g) * 1e6
    elif kind == "fireflies":
        f["color"] = torch.rand(2, 3, h, w, generator=g) * 0.01
        f["color"][:, :, h // 2, w // 2] = 1e6
    elif kind == "nonfinite":
        f["color"][:, 0, 0, 0] = float("nan")
        f["color"][:, 1, -1, -1] = float("inf")
        f["depth"][:, :, h // 2] = float("inf")
        f["normal"][:, :, 0] = float("nan")
        f["motion"][:, :, -1] = float("nan")
    elif kind == "far_motion":
        f["motion"] = torch.randn(2, 2, h, w, generator=g) * 1e7
    return f


KINDS = ["plain", "black", "hdr", "fireflies", "nonfinite", "far_motion"]
SIZES = [(1, 1), (1, 9), (8, 3), (13, 21), (16, 16)]
DTYPES = [torch.float32, torch.bfloat16, torch.float16]


@settings(max_examples=12, deadline=None)
@given(kind=st.sampled_from(KINDS), size=st.sampled_from(SIZES), dtype=st.sampled_from(DTYPES),
       seed=st.integers(0, 2**16))
def test_hard_inputs_finite_and_bounded(wild, kind, size, dtype, seed):
    h, w = size
    f0, f1 = hard_frame(kind, h, w, seed), hard_frame(kind, h, w, seed + 1)
    f1["color"].requires_grad_(True)
    with torch.autocast("cpu", dtype=dtype, enabled=dtype != torch.float32):
        out0, state, _ = wild.step(f0, None)
        out1, _, _ = wild.step(f1, state)
    assert out0.shape == (2, 3, h, w) and out0.dtype == torch.float32
    assert torch.isfinite(out0).all() and torch.isfinite(out1).all()
    # no history: within the input's per-channel range
    assert_within(out0, *channel_range(sanitize(f0["color"])))
    # with history: within the range of the input and the (warped) history
    assert_within(out1, *channel_range(sanitize(f1["color"]), state["output"], state["color"]))
    # a training-style loss: SMAPE against a clean target, mean over pixels
    target = torch.rand(2, 3, h, w)
    loss = sum(((o - target).abs() / (o.abs() + target.abs() + 0.01)).mean() for o in (out0, out1))
    loss.backward()
    assert torch.isfinite(f1["color"].grad).all()
    assert all(torch.isfinite(p.grad).all() for p in wild.parameters() if p.grad is not None)
    wild.zero_grad(set_to_none=True)


@pytest.mark.parametrize("size", [(1, 1), (37, 53), (16, 8)])
def test_output_size_and_features(net, size):
    h, w = size
    out, state, extras = net.step(random_frame(1, h, w), None)
    assert out.shape == (1, 3, h, w)
    assert {k: v.shape[-2:] for k, v in state.items()} == {k: (h, w) for k in state}
    feats = extras["features"]
    assert [f.shape[1] for f in feats] == net.feature_channels
    ph = -(-h // net.multiple) * net.multiple
    assert [f.shape[-2] for f in feats] == [ph // 2**i for i in range(len(feats))]


def test_forward_equals_repeated_step(net):
    frames = {k: torch.stack([random_frame(1, 12, 10, seed=s)[k] for s in range(3)], 1)
              for k in random_frame(1, 1, 1)}
    outs, state, extras = net(frames)
    s = None
    for t in range(3):
        out, s, _ = net.step({k: v[:, t] for k, v in frames.items()}, s)
        assert torch.allclose(outs[:, t], out, atol=1e-6)
    assert torch.allclose(state["output"], s["output"]) and len(extras) == 3


def test_reset_forgets_previous_sequence(net):
    a0, a1 = random_frame(2, 16, 16, seed=1), random_frame(2, 16, 16, seed=2)
    x = random_frame(2, 16, 16, seed=3)
    x["motion"].zero_()
    _, state, _ = net.step(a0, None)
    _, state, _ = net.step(a1, state)
    fresh, _, _ = net.step(x, None)
    out, _, extras = net.step(x, state, reset=torch.tensor([True, False]))
    assert torch.equal(out[0], fresh[0])  # item 0 was reset: identical to a fresh start
    assert not torch.allclose(out[1], fresh[1])  # item 1 kept its history
    assert extras["weights"]["valid"][0].abs().max() == 0 and extras["weights"]["valid"][1].min() > 0
    # a different previous sequence gives the same result after the reset
    _, other, _ = net.step(random_frame(2, 16, 16, seed=9), None)
    other = {k: v * 1e6 for k, v in other.items()}
    out2, _, _ = net.step(x, other, reset=torch.tensor([True, True]))
    assert torch.equal(out2, fresh)
    # discarded history is never read: not even NaN or Inf in it reaches the output
    broken = {k: torch.full_like(v, float("nan")) for k, v in other.items()}
    broken["output"][:, :, ::2] = float("inf")
    out3, _, _ = net.step(x, broken, reset=torch.tensor([True, True]))
    assert torch.equal(out3, fresh)


def test_reset_from_batch_in_forward(net):
    frames = {k: torch.stack([random_frame(1, 8, 8, seed=s)[k] for s in (0, 1, 2)], 1)
              for k in random_frame(1, 1, 1)}
    frames["reset"] = torch.tensor([[True, False, True]])
    outs, _, _ = net(frames)
    fresh, _, _ = net.step({k: v[:, 2] for k, v in frames.items() if k != "reset"}, None)
    assert torch.equal(outs[:, 2], fresh)


def test_history_is_used_for_static_scene(net):
    f = random_frame(1, 16, 16)
    f["motion"].zero_()
    out0, state, _ = net.step(f, None)
    out1, _, extras = net.step(f, state)
    assert extras["weights"]["history_in"].min() > 0 and extras["weights"]["history_out"].min() > 0
    assert not torch.allclose(out0, out1)


def test_truncated_bptt_detaches_state(net):
    frames = {k: torch.stack([random_frame(1, 8, 8, seed=s)[k] for s in range(3)], 1)
              for k in random_frame(1, 1, 1)}
    for every, reaches_first in ((0, True), (1, False)):
        frames["color"] = frames["color"].detach().requires_grad_(True)
        outs, _, _ = net(frames, detach_every=every)
        outs[:, -1].sum().backward()
        grad_first = frames["color"].grad[:, 0].abs().sum().item()
        assert (grad_first > 0) == reaches_first
        net.zero_grad(set_to_none=True)


def test_identical_samples_equal_per_pixel_path(net):
    f = random_frame(1, 16, 16)
    g = dict(f, samples=f["color"].unsqueeze(1).repeat(1, 4, 1, 1, 1))
    assert torch.allclose(net.step(f, None)[0], net.step(g, None)[0], atol=1e-5)
    h = dict(f, samples=torch.rand(1, 4, 3, 16, 16) * 2)
    assert not torch.allclose(net.step(f, None)[0], net.step(h, None)[0])


@pytest.mark.parametrize("ablation", ["no_pyramid", "direct", "no_temporal"])
def test_ablations_run_and_stay_finite(ablation):
    net = make_net(ablation, gain=3.0)
    f = hard_frame("fireflies", 13, 11, 0)
    out0, state, extras = net.step(f, None)
    out1, state, _ = net.step(f, state)
    assert torch.isfinite(out1).all() and out1.shape == (2, 3, 13, 11)
    assert len(extras["features"]) == len(net.feature_channels)
    if ablation == "no_pyramid":
        assert_within(out0, *channel_range(sanitize(f["color"])))
    if ablation == "no_temporal":
        assert state == {} and torch.equal(out0, out1)


def test_copy_keeps_behaviour(net):
    """Deep copies (used for EMA / teacher init by the training code) behave identically."""
    f = random_frame(1, 8, 8)
    assert torch.equal(copy.deepcopy(net).step(f, None)[0], net.step(f, None)[0])


def test_unet_input_parts_equal_their_concatenation():
    """UNet(parts) (the exported graph's form: first convolution per part) equals UNet(cat(parts))."""
    from denoiser.nn.unet import UNet

    torch.manual_seed(0)
    unet = UNet(in_channels=7, encoder=[4, 8], bottleneck=8, decoder=[4], head_channels=[3, 2]).eval()
    parts = [torch.randn(2, 5, 8, 12), torch.randn(2, 2, 8, 12)]
    with torch.no_grad():
        heads, features = unet(torch.cat(parts, 1))
        heads_p, features_p = unet(parts)
    for a, b in zip(heads + features, heads_p + features_p):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_pointwise_of_parts_is_the_1x1_conv_of_the_concatenation():
    """pointwise_of_parts (the exported heads with heads=matmul) against a plain loop over
    pixels of the 1x1 convolution of the concatenated parts."""
    from denoiser.nn.parts import pointwise_of_parts

    torch.manual_seed(0)
    conv = torch.nn.Conv2d(7, 4, 1)
    parts = [torch.randn(2, 5, 3, 6), torch.randn(2, 2, 3, 6)]
    x = torch.cat(parts, 1)
    expected = torch.empty(2, 4, 3, 6)
    for b in range(2):
        for y in range(3):
            for xx in range(6):
                expected[b, :, y, xx] = conv.weight[:, :, 0, 0] @ x[b, :, y, xx] + conv.bias
    with torch.no_grad():
        got = pointwise_of_parts(conv, parts)
        torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(pointwise_of_parts(conv, [x]), expected, rtol=1e-5, atol=1e-5)


class _Heads(torch.nn.Module):
    def __init__(self, unet):
        super().__init__()
        self.unet = unet

    def forward(self, x):
        return tuple(self.unet(x)[0])


@pytest.mark.parametrize("upsample", ["bilinear", "nearest"])
def test_unet_matmul_heads_equal_conv_heads(upsample):
    """Traced with heads_as_matmul, the U-Net's heads are the same maps as its 1x1 convolutions
    (the level-0 head's upsampled part multiplied at half resolution, then upsampled:
    ``UNet.head0_before_upsampling``)."""
    from denoiser.nn.graph_mode import heads_as_matmul, matmul_heads
    from denoiser.nn.unet import UNet

    torch.manual_seed(0)
    unet = UNet(in_channels=7, encoder=[4, 8], bottleneck=8, decoder=[4], head_channels=[3, 2],
                upsample=upsample).eval()
    x = torch.randn(2, 7, 8, 12)
    with torch.no_grad():
        heads, _ = unet(x)
        with heads_as_matmul():
            assert matmul_heads()
            traced = torch.jit.trace(_Heads(unet), x, check_trace=False)
        assert not matmul_heads()
        graph_ops = [n.kind() for n in traced.inlined_graph.nodes()]
        assert "aten::matmul" in graph_ops
        # the bottleneck's and the head's: the full-resolution upsampled features are not computed
        assert graph_ops.count("aten::upsample_bilinear2d" if upsample == "bilinear" else "aten::upsample_nearest2d") == 2
        for a, b in zip(heads, traced(x)):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("upsample", ["bilinear", "nearest"])
def test_factored_head_is_the_level0_head(upsample):
    """``UNet.head0_before_upsampling`` (what graphs exported with matmul heads and the fused
    operations carry as heads[0]): its channels through :func:`head_channels` are those of the
    1x1 head of ``[skip0, up(half)]`` (the definition, a concatenation); a tensor head slices."""
    from denoiser.nn.unet import FactoredHead, UNet, head_channels

    torch.manual_seed(0)
    unet = UNet(in_channels=7, encoder=[4, 8], bottleneck=8, decoder=[4], head_channels=[6, 2],
                upsample=upsample).eval()
    skip0, half = torch.randn(2, 4, 8, 12), torch.randn(2, 4, 4, 6)
    up = F.interpolate(half, scale_factor=2, mode=upsample, align_corners=False if upsample == "bilinear" else None)
    want = unet.heads[0](torch.cat([skip0, up], 1))
    with torch.no_grad():
        factored = unet.head0_before_upsampling(skip0, half)
        assert isinstance(factored, FactoredHead)
        torch.testing.assert_close(head_channels(factored, 0, 6), want, rtol=1e-5, atol=1e-5)
        part = head_channels(factored, 2, 5, factored=True)
        assert isinstance(part, FactoredHead) and part.weight.shape == (3, 8)
        torch.testing.assert_close(part.tensor(), want[:, 2:5], rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(head_channels(want, 4), want[:, 4:])
        torch.testing.assert_close(head_channels(want, 1, 3, factored=True), want[:, 1:3])


def test_guide_input_off_leaves_the_guide_out_of_the_unet_input(tmp_path):
    """``net.temporal.guide_input=false``: the U-Net's first convolution reads 7 channels fewer
    (the warped history guide), the disocclusion gate still reads the guide (the state keeps it),
    steps stay finite over a reset, and the step graph exports."""
    from denoiser.inference.step_graph import export_onnx

    nets = {}
    for guide_input in (True, False):
        cfg = compose_net_config("tiny", overrides=["+net.temporal.reject_threshold=0.1"])
        cfg["temporal"]["guide_input"] = guide_input
        torch.manual_seed(0)
        nets[guide_input] = build_net(cfg).eval()
    first = {k: net.unet.encoder[0][0].in_channels for k, net in nets.items()}
    assert first[True] - first[False] == 7
    net = nets[False]
    assert [part for part, _ in net.temporal.input_layout] == ["output", "color", "features", "valid"]
    assert "guide" in net.temporal.state_channels()
    state = None
    with torch.no_grad():
        for t, reset in enumerate([True, False, False]):
            frame = random_frame(1, 20, 28, seed=t, kind="hard")
            out, state, _ = net.step(frame, state, torch.tensor([reset]))
            assert torch.isfinite(out).all() and state["guide"].shape[1] == 7
    export_onnx(net, tmp_path / "g.onnx", trace_size=(32, 32))


def test_embed_input_parts_equal_their_concatenation():
    """EmbedNet(parts) (the exported graph's form: first layer per part) equals EmbedNet(cat(parts))."""
    from denoiser.nn.embed import EmbedNet

    torch.manual_seed(0)
    embed = EmbedNet(in_channels=10, hidden=6, out_channels=5).eval()
    parts = [torch.randn(2, 3, 8, 12), torch.randn(2, 7, 8, 12)]
    with torch.no_grad():
        torch.testing.assert_close(embed(parts), embed(torch.cat(parts, 1)), rtol=1e-5, atol=1e-5)


def test_temporal_input_parts_follow_the_input_layout(net):
    """The history inputs, part by part, are the slices of their concatenation named by
    ``input_layout`` (what the exported graph feeds the U-Net's first convolution)."""
    temporal = net.temporal
    f = random_frame(2, 8, 8)
    _, state, _ = net.step(f, None)
    history = temporal.warp(state, f["motion"], None, like=f["color"], guide=guide_features(f))
    scale = torch.full((2, 1, 1, 1), 0.5)
    parts = dict(zip([name for name, _ in temporal.input_layout], temporal.input_parts(history, scale)))
    assert {k: p.shape[1] for k, p in parts.items()} == dict(temporal.input_layout)
    for name in ("guide", "features", "valid"):
        assert torch.equal(parts[name], history[name])
    for name in ("output", "color"):
        torch.testing.assert_close(parts[name], torch.log1p(history[name].clamp_min(0) / scale))
