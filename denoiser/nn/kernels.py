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

Traced or exported (:func:`denoiser.nn.graph_mode.in_graph`, the graph of ``denoiser-export``,
ONNX Runtime and OpenVINO), the same sum is recorded as a few large ops
instead of k*k Python-level taps and the border masking's 2k slice assignments
(:func:`apply_kernels_graph`): the k*k shifted views are slices of one zero-padded copy, the
border mask is two small separable biases added to the logits (:func:`border_bias`: a row term
and a column term, 0 inside and -inf for taps outside), and the sum is k*k multiply-adds that an
inference engine fuses into elementwise kernels. In OpenVINO
at 1080p that is faster than gathering the views with a one-hot grouped convolution (im2col as
a convolution, which OpenVINO runs as a real k x k convolution, with reorders around it). Same numbers within float32 rounding (``tests/inference/test_export.py``); the training path
keeps the in-place loop with its hand-written backward.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from denoiser.nn.graph_mode import fused_kernels, in_graph, unfused
from denoiser.nn.graph_ops import graph_node, scale_attributes
from denoiser.nonfinite import nan_to_num


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
    The bound also limits how well a kernel can leave pixels out: to give ``m`` of ``n`` taps
    less weight than the others, the largest reachable gap between the two groups' logits is
    ``scale * n / sqrt(m (n - m))`` (two-valued logits; the spread is then set by ``m``). For
    the 3-level partition (two levels left out, ``m = 2``) that is ``2.12 scale``, for 6 taps of a 5x5 kernel
    ``2.34 scale``: at ``scale = 2.5`` a lamp 2500 times brighter than its surroundings kept
    1% of its partition weight on the coarse levels (0.6% and 0.4%) and spread into a glow (docs/results_log.md,
    "Small bright emitters"), which ``scale = 5`` removed.
    ``scale=None`` leaves the logits as they are (networks configured before this existed).
    Non-finite logits are replaced first (NaN -> 0, +-Inf -> +-1e4; float16 autocast can
    overflow a head). Traced or exported, that replacement is left out: a graph's inputs are
    sanitised once per frame, bounded by their transforms, and its weights are checked finite at
    export (:func:`denoiser.inference.step_graph.export_onnx`), so its logits are finite (a float32 or
    bfloat16 engine has float32's range); the replacement cost 3% of the demo student's time at
    1080p in OpenVINO. Computed in float32.
    """
    if in_graph():
        logits = logits.float()  # finite by construction (see above)
    else:
        logits = nan_to_num(logits.float(), nan=0.0, posinf=1e4, neginf=-1e4)
    if scale is None:
        return logits
    var = logits.var(dim=dim, unbiased=False, keepdim=True) if logits.shape[dim] > 1 else torch.zeros_like(logits)
    return logits * (scale * torch.rsqrt(var + 1.0))


def shifted_views(xp: torch.Tensor, k: int) -> list[torch.Tensor]:
    """The k*k views ``xp[:, :, i:i+H, j:j+W]`` of a ``[B, C, H+2r, W+2r]`` padded image, tap
    ``t = i*k + j`` at index t (each ``[B, C, H, W]``). The ends are constants relative to the
    padded size, so a trace records plain slices (no shape arithmetic) at any frame size."""
    r2 = k - 1

    def end(i: int) -> int | None:
        return i - r2 if i < r2 else None

    return [xp[:, :, i: end(i), j: end(j)] for i in range(k) for j in range(k)]


def _end(i: int, k: int) -> int | None:
    """End of the slice of tap offset ``i`` in a dimension padded by ``k - 1`` (None = to the end)."""
    return i - (k - 1) if i < k - 1 else None


def border_bias(logits: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Additive border masks of the taps, separable: ``(rows [B, k*k, H, 1], cols [B, k*k, 1, W])``,
    0 where tap ``t = i*k + j`` reads inside the image along that axis and ``-inf`` where it reads
    outside; ``logits + rows + cols`` masks exactly the taps :func:`mask_border_taps_` masks.

    Built from slices of a padded column and row of ones (O(k*k*(H + W)) values, not
    O(k*k*H*W)); logits: ``[B, k*k, H, W]`` (only its shape is used).
    """
    r = k // 2
    col = F.pad(torch.ones_like(logits[:, :1, :, :1]), (0, 0, r, r))  # [B, 1, H + 2r, 1]
    row = F.pad(torch.ones_like(logits[:, :1, :1, :]), (r, r, 0, 0))  # [B, 1, 1, W + 2r]
    ys = [col[:, :, i: _end(i, k), :] for i in range(k)]
    xs = [row[:, :, :, j: _end(j, k)] for j in range(k)]
    rows = torch.cat([ys[t // k] for t in range(k * k)], dim=1)
    cols = torch.cat([xs[t % k] for t in range(k * k)], dim=1)
    inf = torch.tensor(float("-inf"), dtype=logits.dtype)
    zero = torch.tensor(0.0, dtype=logits.dtype)
    return torch.where(rows > 0.5, zero, inf), torch.where(cols > 0.5, zero, inf)


def apply_kernels_graph(x: torch.Tensor, logits: torch.Tensor, scale: float | None = None) -> torch.Tensor:
    """:func:`apply_kernels` as plain slices, one softmax and multiply-adds (for tracing and
    export; no custom autograd).

    x: ``[B, C, H, W]``; logits: ``[B, k*k, H, W]`` -> ``[B, C, H, W]`` float32. The border
    taps are masked by two broadcast additions of :func:`border_bias` (no full-resolution mask).
    """
    if fused_kernels():
        with torch.autocast(device_type=x.device.type, enabled=False):
            return KernelApplyOp.apply(x.float(), logits.float(), scale)
    k = kernel_size_of(logits)
    r = k // 2
    with torch.autocast(device_type=x.device.type, enabled=False):
        x = x.float()
        logits = scale_logits(logits, scale)
        rows, cols = border_bias(logits, k)
        weights = torch.softmax(logits + rows + cols, dim=1)
        views = shifted_views(F.pad(x, (r, r, r, r)), k)
        out = weights[:, :1] * views[0]
        for t in range(1, k * k):
            out = out + weights[:, t: t + 1] * views[t]
        return out


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
    if in_graph():
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


# ----------------------------------------------------------------------------- export stub


class KernelApplyOp(torch.autograd.Function):
    """:func:`denoiser.nn.kernels.apply_kernels_graph` recorded as one ``denoiser::KernelApply`` node.

    forward(x ``[B, C, H, W]`` float32, logits ``[B, k*k, H, W]`` float32, scale float or None)
    -> ``[B, C, H, W]`` float32, computed by the plain graph.
    """

    @staticmethod
    def forward(ctx, x, logits, scale):
        return unfused(apply_kernels_graph, x, logits, scale)

    @staticmethod
    def symbolic(g, x, logits, scale):
        return graph_node(g, "KernelApply", x, logits, like=x, **scale_attributes(scale))
