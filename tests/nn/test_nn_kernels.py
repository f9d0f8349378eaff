"""Kernel application: fast accumulation vs a plain-loop reference, softmax in float32."""

import pytest
import torch
import torch.nn.functional as F
from helpers.kernels import reference_apply
from hypothesis import given, settings
from hypothesis import strategies as st

from denoiser.nn.kernels import apply_kernels, apply_kernels_graph, apply_kernels_unfold, kernel_weights


def assert_close_rel(a, b, tol=1e-5):
    scale = b.abs().amax().clamp_min(1.0)
    assert (a.double() - b).abs().max().item() <= tol * scale.item()


@settings(max_examples=12, deadline=None)
@given(h=st.integers(1, 7), w=st.integers(1, 7), k=st.sampled_from([1, 3, 5, 7]), c=st.integers(1, 4),
       magnitude=st.sampled_from([1.0, 1e3, 1e6]), logit_scale=st.sampled_from([0.1, 3.0, 60.0]),
       seed=st.integers(0, 2**16))
def test_fast_matches_plain_loop(h, w, k, c, magnitude, logit_scale, seed):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(2, c, h, w, generator=g) * magnitude
    logits = torch.randn(2, k * k, h, w, generator=g) * logit_scale
    ref = reference_apply(x, logits)
    assert_close_rel(apply_kernels(x, logits), ref)
    assert_close_rel(apply_kernels_unfold(x, logits), ref)
    assert_close_rel(apply_kernels_graph(x, logits), ref)


def test_tap_order_is_row_major_offsets():
    """Tap i*k + j reads the pixel at offset (dy, dx) = (i - r, j - r)."""
    x = torch.arange(25.0).view(1, 1, 5, 5)
    logits = torch.full((1, 9, 5, 5), -1e4)
    logits[:, 2 * 3 + 1] = 0.0  # i=2, j=1 -> one row down, same column
    logits[:, 1 * 3 + 1] = -40.0  # centre tap: wins only in the last row, where the other is outside
    out = apply_kernels(x, logits)
    assert torch.allclose(out[0, 0, :4], x[0, 0, 1:])
    assert torch.allclose(out[0, 0, 4], x[0, 0, 4])


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_softmax_in_float32_under_autocast(dtype):
    x = torch.rand(1, 3, 6, 6) * 1e5
    logits = (torch.randn(1, 25, 6, 6) * 30).to(dtype)
    with torch.autocast("cpu", dtype=dtype):
        w = kernel_weights(logits)
        out = apply_kernels(x, logits)
    assert w.dtype == torch.float32 and out.dtype == torch.float32
    assert torch.allclose(w.sum(1), torch.ones(1, 6, 6), atol=1e-6) and (w >= 0).all()
    assert_close_rel(out, reference_apply(x, logits.float()))


def test_no_unfold_of_the_image(monkeypatch):
    """The fast path accumulates shifted views; it must not materialise an unfold."""
    def forbidden(*args, **kwargs):
        raise AssertionError("apply_kernels called F.unfold")

    monkeypatch.setattr(F, "unfold", forbidden)
    monkeypatch.setattr(torch.Tensor, "unfold", forbidden)
    out = apply_kernels(torch.rand(1, 3, 8, 8), torch.randn(1, 25, 8, 8))
    assert out.shape == (1, 3, 8, 8)


def test_gradients_finite_with_extreme_logits():
    x = (torch.rand(1, 3, 8, 8) * 1e6).requires_grad_(True)
    logits = (torch.randn(1, 49, 8, 8) * 1e4).requires_grad_(True)
    apply_kernels(x, logits).sum().backward()
    assert torch.isfinite(x.grad).all() and torch.isfinite(logits.grad).all()


def test_kernels_renormalised_at_border():
    """A constant image stays constant up to the border, for any logits."""
    x = torch.full((1, 2, 4, 6), 5.0)
    out = apply_kernels(x, torch.randn(1, 49, 4, 6) * 10)
    assert torch.allclose(out, x, rtol=1e-6)


def test_backward_matches_autograd_reference():
    """The hand-written backward equals autograd through the unfold formulation (and gradcheck)."""
    g = torch.Generator().manual_seed(3)
    x = torch.rand(2, 3, 6, 5, generator=g, dtype=torch.float64, requires_grad=True)
    logits = torch.randn(2, 25, 6, 5, generator=g, dtype=torch.float64, requires_grad=True)
    from denoiser.nn.kernels import _ApplyWeights

    xp = torch.nn.functional.pad(x, (2, 2, 2, 2))
    weights = torch.softmax(logits, 1)
    assert torch.autograd.gradcheck(_ApplyWeights.apply, (xp, weights))
    grad = torch.rand(2, 3, 6, 5, generator=g, dtype=torch.float64)
    fast = torch.autograd.grad(apply_kernels(x.float(), logits.float()), (x, logits), grad.float())
    ref = torch.autograd.grad(apply_kernels_unfold(x, logits), (x, logits), grad)
    for a, b in zip(fast, ref):
        assert torch.allclose(a.double(), b, atol=1e-5)


@pytest.mark.filterwarnings("ignore::torch.jit.TracerWarning")
@pytest.mark.parametrize("scale", [None, 2.0])
def test_traced_graph_is_slices_and_multiply_adds(scale):
    """Traced, apply_kernels records out-of-place slices and multiply-adds: no convolution, no
    in-place op, no shape read (the slices' ends are constants), so the graph traced at one size
    gives the reference's numbers at another."""
    g = torch.Generator().manual_seed(3)
    x, logits = torch.rand(1, 4, 9, 11, generator=g) * 100, torch.randn(1, 25, 9, 11, generator=g) * 5
    with torch.no_grad():
        traced = torch.jit.trace(lambda a, b: apply_kernels(a, b, scale), (x, logits))
    kinds = [n.kind() for n in traced.graph.nodes()]
    assert not [k for k in kinds if k in ("aten::_convolution", "aten::size") or k.endswith("_")], kinds
    assert_close_rel(traced(x, logits), reference_apply(x, kernel_weights(logits, scale).log()), tol=1e-5)
    x2, logits2 = torch.rand(2, 4, 13, 7, generator=g) * 100, torch.randn(2, 25, 13, 7, generator=g) * 5
    assert_close_rel(traced(x2, logits2), reference_apply(x2, kernel_weights(logits2, scale).log()), tol=1e-5)


@pytest.mark.parametrize("k,h,w", [(3, 5, 7), (5, 4, 9), (5, 1, 1), (7, 3, 2)])
def test_border_bias_masks_exactly_the_taps_that_read_outside(k, h, w):
    """The separable row + column bias of the exported graph equals the in-place border mask."""
    from denoiser.nn.kernels import border_bias, mask_border_taps_

    logits = torch.zeros(2, k * k, h, w)
    rows, cols = border_bias(logits, k)
    assert rows.shape == (2, k * k, h, 1) and cols.shape == (2, k * k, 1, w)
    expected = mask_border_taps_(torch.zeros(2, k * k, h, w))
    assert torch.equal(logits + rows + cols, expected)
