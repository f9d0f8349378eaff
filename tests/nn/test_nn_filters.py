"""PyramidFilter and the ablation filters: convexity, identity cases, level recombination."""

import pytest
import torch
import torch.nn.functional as F
from hypothesis import given, settings
from hypothesis import strategies as st

from denoiser.nn.filters import DirectColor, SingleKernelFilter
from denoiser.nn.pyramid import PyramidFilter


def random_heads(filt, b, h, w, scale, g):
    return [torch.randn(b, n, h // 2**i, w // 2**i, generator=g) * scale
            for i, n in enumerate(filt.head_channels)]


def delta_logits(k, b, h, w):
    logits = torch.full((b, k * k, h, w), -1e4)
    logits[:, (k * k) // 2] = 0.0
    return logits


@settings(max_examples=10, deadline=None)
@given(sizes=st.sampled_from([[5, 5, 5], [5, 7, 9], [3], [3, 3]]), hq=st.integers(1, 5), wq=st.integers(1, 5),
       magnitude=st.sampled_from([0.0, 1.0, 1e6]), logit_scale=st.sampled_from([0.5, 20.0]),
       seed=st.integers(0, 2**16))
def test_pyramid_output_within_input_range(sizes, hq, wq, magnitude, logit_scale, seed):
    g = torch.Generator().manual_seed(seed)
    filt = PyramidFilter(sizes)
    h, w = hq * filt.multiple, wq * filt.multiple
    x = torch.rand(2, 3, h, w, generator=g) * magnitude
    x[:, :, h // 2, w // 2] = 1e6  # firefly
    out, weights = filt(x, random_heads(filt, 2, h, w, logit_scale, g), torch.ones(2, 1, 1, 1))
    assert out.shape == x.shape and torch.isfinite(out).all()
    lo, hi = x.amin(dim=(2, 3), keepdim=True), x.amax(dim=(2, 3), keepdim=True)
    tol = 1e-5 * hi.clamp_min(1.0)
    assert (out >= lo - tol).all() and (out <= hi + tol).all()
    assert torch.allclose(weights["partition"].sum(1), torch.ones(2, h, w), atol=1e-5)


def test_pyramid_preserves_constant_image_at_borders():
    filt = PyramidFilter([5, 7, 9])
    x = torch.full((1, 3, 16, 24), 3.5)
    out, _ = filt(x, random_heads(filt, 1, 16, 24, 5.0, torch.Generator().manual_seed(0)), torch.ones(1, 1, 1, 1))
    assert torch.allclose(out, x, rtol=1e-5)


def test_pyramid_level0_delta_is_identity():
    filt = PyramidFilter([5, 5, 5])
    x = torch.rand(1, 3, 16, 16) * 100
    part = torch.full((1, 3, 16, 16), -1e4)
    part[:, 0] = 0
    heads = [torch.cat([part, delta_logits(5, 1, 16, 16)], 1), delta_logits(5, 1, 8, 8), delta_logits(5, 1, 4, 4)]
    out, _ = filt(x, heads, torch.ones(1, 1, 1, 1))
    assert torch.allclose(out, x, rtol=1e-5)


def test_pyramid_level1_is_bilinear_upsampled_average_pool():
    """All weight on level 1 with delta kernels: avg_pool 2x2, then bilinear 2x upsampling."""
    filt = PyramidFilter([3, 3])
    x = torch.rand(1, 3, 8, 12) * 10
    part = torch.full((1, 2, 8, 12), -1e4)
    part[:, 1] = 0
    heads = [torch.cat([part, delta_logits(3, 1, 8, 12)], 1), delta_logits(3, 1, 4, 6)]
    out, _ = filt(x, heads, torch.ones(1, 1, 1, 1))
    expected = F.interpolate(F.avg_pool2d(x, 2), scale_factor=2, mode="bilinear", align_corners=False)
    assert torch.allclose(out, expected, rtol=1e-5, atol=1e-6)


def test_single_kernel_filter_range_and_size():
    filt = SingleKernelFilter([5, 7, 9])
    assert filt.kernel_size == 9 and filt.head_channels == [81]
    g = torch.Generator().manual_seed(1)
    x = torch.rand(1, 3, 7, 5, generator=g) * 1e6
    out, _ = filt(x, random_heads(filt, 1, 7, 5, 30.0, g), torch.ones(1, 1, 1, 1))
    lo, hi = x.amin(dim=(2, 3), keepdim=True), x.amax(dim=(2, 3), keepdim=True)
    tol = 1e-5 * hi
    assert (out >= lo - tol).all() and (out <= hi + tol).all()


@pytest.mark.parametrize("value", [-1e9, 0.0, 1e9])
def test_direct_color_is_finite_and_nonnegative(value):
    filt = DirectColor([5, 5, 5])
    heads = [torch.full((1, 3, 4, 4), value, requires_grad=True)]
    out, _ = filt(torch.zeros(1, 3, 4, 4), heads, torch.full((1, 1, 1, 1), 2.0))
    out.sum().backward()
    assert torch.isfinite(out).all() and (out >= 0).all() and torch.isfinite(heads[0].grad).all()


def identity_like_heads(filt, b, h, w, gap):
    """Heads at a saturated identity: partition on level 0 and every kernel on its centre tap,
    ``gap`` logits above everything else (the frozen state of the collapsed demo teacher)."""
    heads = [torch.zeros(b, n, h // 2**i, w // 2**i) for i, n in enumerate(filt.head_channels)]
    heads[0][:, 0] = gap
    for i, k in enumerate(filt.kernel_sizes):
        offset = filt.levels if i == 0 else 0
        heads[i][:, offset + (k * k) // 2] = gap
    return [hd.requires_grad_() for hd in heads]


@pytest.mark.parametrize("gap", [200.0, 1e6])
def test_identity_like_state_keeps_a_gradient_with_scaled_logits(gap):
    """With raw logits a saturated identity has an exactly-zero gradient (float32 softmax
    underflows to one-hot), so training can never leave it; normalised logits keep it alive."""
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 3, 16, 16, generator=g)
    target = F.avg_pool2d(x, 5, stride=1, padding=2)  # any target other than the input
    grads = {}
    for scale in (None, 2.5):
        filt = PyramidFilter([5, 7, 9], logit_scale=scale)
        heads = identity_like_heads(filt, 1, 16, 16, gap)
        out, _ = filt(x, heads, torch.ones(1, 1, 1, 1))
        (out - target).abs().mean().backward()
        grads[scale] = max(float(hd.grad.abs().max()) for hd in heads)
    assert grads[None] == 0.0
    assert grads[2.5] > 0.0


def test_scaled_logits_keep_every_kernel_weight_above_the_floor():
    from denoiser.nn.kernels import kernel_weights

    logits = torch.zeros(1, 25, 8, 8)
    logits[:, 12] = 1e30
    logits[:, 3] = float("inf")
    logits[:, 7] = float("nan")
    w = kernel_weights(logits, scale=2.5)
    inside = w[..., 4, 4]  # an interior pixel: every tap is in the image
    floor = float(torch.exp(torch.tensor(-2.5 * 50**0.5)) / 25)  # exp(-scale * sqrt(2 n)) / n
    assert torch.isfinite(w).all() and float(inside.min()) >= floor
    torch.testing.assert_close(w.sum(1), torch.ones(1, 8, 8))
