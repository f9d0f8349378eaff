"""Per-pixel k x k kernels, normalised by a float32 softmax, applied to linear radiance.

``apply_kernels(x, logits)`` computes, for every pixel p,

    out[b, c, p] = sum_{i,j} softmax_k(logits[b, :, p] + border(p))[i*k + j] * x[b, c, p + (i - r, j - r)]

with ``r = k // 2`` (i indexes rows/y, j columns/x). ``border(p)`` is ``-inf`` for taps that
fall outside the image and 0 otherwise, so the softmax runs over the in-image taps only (the
centre tap always is): the kernel is renormalised at the border instead of reading zeros.
The softmax runs in float32 even under autocast, so the weights are non-negative and sum to
one: each output pixel is a convex combination of input pixels.

Memory: the result is accumulated over the k*k shifted views of one zero-padded copy of x,
so besides the weights ``[B, k*k, H, W]`` only O(C*H*W) is allocated (an ``unfold`` would
allocate ``[B, C*k*k, H*W]``). :func:`apply_kernels_unfold` is that unfold formulation, kept
for the benchmark's comparison only.

Traced or exported (``torch.jit.is_tracing()`` / ``torch.onnx.is_in_onnx_export()``, the graph
of ``denoiser-export``, ONNX Runtime and OpenVINO), the same sum is recorded as a few large ops
instead of k*k Python-level taps and the border masking's 2k slice assignments
(:func:`apply_kernels_graph`): one grouped convolution with one-hot k x k filters gathers the
k*k shifted views (im2col as a convolution, zero padding included), one multiply by the
weights repeated over the channels, one grouped 1x1 convolution sums the taps; the border mask
is the same one-hot convolution of a ones image (1 inside, 0 for taps outside). Same numbers
within float32 rounding of the sum's order (``tests/test_export.py``); the training path keeps
the shifted-view loop with its hand-written backward.
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F


def kernel_size_of(logits: torch.Tensor) -> int:
    """k such that ``logits.shape[1] == k*k`` (k odd)."""
    k = math.isqrt(logits.shape[1])
    if k * k != logits.shape[1] or k % 2 == 0:
        raise ValueError(f"kernel logits need k*k channels with odd k, got {logits.shape[1]}")
    return k


def mask_border_taps_(logits: torch.Tensor) -> torch.Tensor:
    """Set, in place, the logits of taps that read outside the image to ``-inf``.

    logits: ``[B, k*k, H, W]`` float32. Tap (i, j) at pixel (y, x) reads (y + i - r, x + j - r);
    only border strips are written (2k slice assignments), so the cost is O(k*k*r*(H+W)).
    """
    k = kernel_size_of(logits)
    r = k // 2
    h, w = logits.shape[-2:]
    for d in range(-r, r + 1):
        rows = slice(0, min(-d, h)) if d < 0 else slice(max(h - d, 0), h)
        cols = slice(0, min(-d, w)) if d < 0 else slice(max(w - d, 0), w)
        if d != 0:
            logits[:, (d + r) * k: (d + r + 1) * k, rows] = float("-inf")  # taps with row offset d
            logits[:, d + r:: k, :, cols] = float("-inf")  # taps with column offset d
    return logits


def scale_logits(logits: torch.Tensor, scale: float | None, dim: int = 1) -> torch.Tensor:
    """Scale-normalised softmax logits: ``scale * z / sqrt(var_dim(z) + 1)``; any shape.

    Why: with raw logits the softmax can only sharpen by growing the logits, and Adam keeps
    growing them until float32 ``softmax`` returns exactly one-hot; its gradient is then exactly
    0 and the weights never move again (the demo teacher froze that way into the identity
    kernel, partition 100% on level 0). Divided by their spread over the taps (levels), the
    logits' sharpness is set by their *shape*, not their scale: near zero the map is about
    ``scale * z`` (an untrained head still gives smooth kernels), and however large ``z``
    grows, the logits of ``n`` entries stay within ``scale * sqrt(2 n)`` of each other, so every
    weight stays above ``exp(-scale * sqrt(2 n)) / n`` and a gradient always flows (the same
    remedy as normalised attention logits against attention-entropy collapse).
    ``scale=None`` leaves the logits as they are (networks configured before this existed).
    Non-finite logits are replaced first (NaN -> 0, +-Inf -> +-1e4). Computed in float32.
    """
    logits = torch.nan_to_num(logits.float(), nan=0.0, posinf=1e4, neginf=-1e4)
    if scale is None:
        return logits
    var = logits.var(dim=dim, unbiased=False, keepdim=True) if logits.shape[dim] > 1 else torch.zeros_like(logits)
    return logits * (scale * torch.rsqrt(var + 1.0))


def tap_filters(k: int, channels: int, like: torch.Tensor) -> torch.Tensor:
    """One-hot ``[channels * k*k, 1, k, k]`` filters: output channel ``c*k*k + i*k + j`` of a
    grouped (``groups=channels``) convolution with padding ``k // 2`` is channel c shifted by
    tap (i, j): ``x[c, y + i - r, x + j - r]`` (0 outside). Built from NumPy, so a trace
    records a constant of known shape (the ONNX exporter needs one for a convolution)."""
    eye = np.tile(np.eye(k * k, dtype=np.float32).reshape(k * k, 1, k, k), (int(channels), 1, 1, 1))
    return torch.from_numpy(eye).to(device=like.device, dtype=like.dtype)


def apply_kernels_graph(x: torch.Tensor, logits: torch.Tensor, scale: float | None = None) -> torch.Tensor:
    """:func:`apply_kernels` as a few large ops (for tracing and export; no custom autograd).

    x: ``[B, C, H, W]``; logits: ``[B, k*k, H, W]`` -> ``[B, C, H, W]`` float32.
    """
    k = kernel_size_of(logits)
    r = k // 2
    c = x.shape[1]
    with torch.autocast(device_type=x.device.type, enabled=False):
        x = x.float()
        logits = scale_logits(logits, scale)
        inside = F.conv2d(torch.ones_like(logits[:, :1]), tap_filters(k, 1, logits), padding=r)
        weights = torch.softmax(torch.where(inside > 0.5, logits, float("-inf")), dim=1)
        views = F.conv2d(x, tap_filters(k, c, x), padding=r, groups=c)  # [B, C*k*k, H, W]
        summed = torch.from_numpy(np.ones((int(c), k * k, 1, 1), np.float32)).to(x.device)
        return F.conv2d(views * weights.repeat(1, c, 1, 1), summed, groups=c)


def kernel_weights(logits: torch.Tensor, scale: float | None = None) -> torch.Tensor:
    """Softmax over the in-image kernel taps in float32: ``[B, k*k, H, W]`` -> same shape, float32.

    Logits pass :func:`scale_logits` first (non-finite values replaced, optional normalisation).
    """
    with torch.autocast(device_type=logits.device.type, enabled=False):
        return torch.softmax(mask_border_taps_(scale_logits(logits, scale)), dim=1)


def _accumulate(xp: torch.Tensor, weights: torch.Tensor, k: int, h: int, w: int) -> torch.Tensor:
    """``sum_t weights[:, t] * xp[:, :, i:i+h, j:j+w]`` over taps ``t = i*k + j`` (no autograd)."""
    out = None
    for i in range(k):
        for j in range(k):
            tap = weights[:, i * k + j: i * k + j + 1]
            view = xp[:, :, i: i + h, j: j + w]
            if out is None:
                out = tap * view
            else:
                out.addcmul_(tap, view)
    return out


class _ApplyWeights(torch.autograd.Function):
    """Per-pixel weighted sum of shifted views with a hand-written backward.

    forward(xp ``[B, C, H+2r, W+2r]`` zero-padded image, weights ``[B, k*k, H, W]``) ->
    ``[B, C, H, W]``. backward: ``grad_weights[:, t] = sum_c grad * view_t`` and
    ``grad_xp[view_t] += grad * weights[:, t]``, accumulated in place (autograd on the loop
    would keep k*k intermediate graphs and allocate a gradient per view).
    """

    @staticmethod
    def forward(ctx, xp, weights):
        k = kernel_size_of(weights)
        h, w = weights.shape[-2:]
        ctx.save_for_backward(xp, weights)
        ctx.k = k
        return _accumulate(xp, weights, k, h, w)

    @staticmethod
    def backward(ctx, grad):
        xp, weights = ctx.saved_tensors
        k = ctx.k
        h, w = weights.shape[-2:]
        grad = grad.contiguous()
        grad_xp = torch.zeros_like(xp) if ctx.needs_input_grad[0] else None
        grad_w = torch.empty_like(weights) if ctx.needs_input_grad[1] else None
        for i in range(k):
            for j in range(k):
                t = i * k + j
                view = xp[:, :, i: i + h, j: j + w]
                if grad_w is not None:
                    torch.sum(grad * view, dim=1, keepdim=True, out=grad_w[:, t: t + 1])
                if grad_xp is not None:
                    grad_xp[:, :, i: i + h, j: j + w].addcmul_(grad, weights[:, t: t + 1])
        return grad_xp, grad_w


def apply_kernels(x: torch.Tensor, logits: torch.Tensor, scale: float | None = None) -> torch.Tensor:
    """Apply per-pixel kernels.

    x: ``[B, C, H, W]`` linear radiance; logits: ``[B, k*k, H, W]`` unnormalised kernel taps
    (any float dtype); scale: logit normalisation (:func:`scale_logits`). Returns ``[B, C, H, W]`` float32.
    """
    if torch.jit.is_tracing() or torch.onnx.is_in_onnx_export():
        return apply_kernels_graph(x, logits, scale)
    k = kernel_size_of(logits)
    r = k // 2
    weights = kernel_weights(logits, scale)
    with torch.autocast(device_type=x.device.type, enabled=False):
        x = x.float()
        xp = F.pad(x, (r, r, r, r)) if r > 0 else x  # zeros, which get zero weight
        if torch.is_grad_enabled() and (xp.requires_grad or weights.requires_grad):
            return _ApplyWeights.apply(xp, weights)  # training: hand-written backward
        return _accumulate(xp, weights, k, *x.shape[-2:])


def apply_kernels_unfold(x: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """Same result as :func:`apply_kernels` through ``F.unfold`` (O(C*k*k*H*W) memory).

    x: ``[B, C, H, W]``; logits: ``[B, k*k, H, W]`` -> ``[B, C, H, W]`` float32.
    """
    k = kernel_size_of(logits)
    b, c, h, w = x.shape
    weights = kernel_weights(logits)
    cols = F.unfold(x.float(), k, padding=k // 2).view(b, c, k * k, h, w)
    return (cols * weights.unsqueeze(1)).sum(dim=2)
