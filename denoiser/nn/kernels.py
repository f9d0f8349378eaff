"""Per-pixel k x k kernels, normalised by a float32 softmax, applied to linear radiance.

``apply_kernels(x, logits)`` computes, for every pixel p,

    out[b, c, p] = sum_{i,j} softmax_k(logits[b, :, p])[i*k + j] * x[b, c, p + (i - r, j - r)]

with ``r = k // 2`` (i indexes rows/y, j columns/x) and zeros outside the image. The softmax
runs in float32 even under autocast, so the weights are positive and sum to one: each output
pixel is a convex combination of input pixels (zero-padded at the border).

Memory: the result is accumulated over the k*k shifted views of one zero-padded copy of x,
so besides the weights ``[B, k*k, H, W]`` only O(C*H*W) is allocated (an ``unfold`` would
allocate ``[B, C*k*k, H*W]``). :func:`apply_kernels_unfold` is that unfold formulation, kept
for the benchmark's comparison only.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def kernel_size_of(logits: torch.Tensor) -> int:
    """k such that ``logits.shape[1] == k*k`` (k odd)."""
    k = math.isqrt(logits.shape[1])
    if k * k != logits.shape[1] or k % 2 == 0:
        raise ValueError(f"kernel logits need k*k channels with odd k, got {logits.shape[1]}")
    return k


def kernel_weights(logits: torch.Tensor) -> torch.Tensor:
    """Softmax over the kernel taps in float32: ``[B, k*k, H, W]`` -> same shape, float32."""
    with torch.autocast(device_type=logits.device.type, enabled=False):
        return torch.softmax(logits.float(), dim=1)


def apply_kernels(x: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """Apply per-pixel kernels.

    x: ``[B, C, H, W]`` linear radiance; logits: ``[B, k*k, H, W]`` unnormalised kernel taps
    (any float dtype). Returns ``[B, C, H, W]`` float32.
    """
    k = kernel_size_of(logits)
    r = k // 2
    weights = kernel_weights(logits)
    with torch.autocast(device_type=x.device.type, enabled=False):
        x = x.float()
        h, w = x.shape[-2:]
        xp = F.pad(x, (r, r, r, r)) if r > 0 else x
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


def apply_kernels_unfold(x: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """Same result as :func:`apply_kernels` through ``F.unfold`` (O(C*k*k*H*W) memory).

    x: ``[B, C, H, W]``; logits: ``[B, k*k, H, W]`` -> ``[B, C, H, W]`` float32.
    """
    k = kernel_size_of(logits)
    b, c, h, w = x.shape
    weights = kernel_weights(logits)
    cols = F.unfold(x.float(), k, padding=k // 2).view(b, c, k * k, h, w)
    return (cols * weights.unsqueeze(1)).sum(dim=2)
