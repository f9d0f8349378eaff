"""A plain-loop reference of the per-pixel kernel filter (:func:`denoiser.nn.kernels.apply_kernels`)."""

import math

import torch


def reference_apply(x: torch.Tensor, logits: torch.Tensor) -> torch.Tensor:
    """Plain loops over pixels and taps, float64; softmax over the in-image taps only."""
    b, c, h, w = x.shape
    k = math.isqrt(logits.shape[1])
    r = k // 2
    xd, ld = x.double(), logits.double()
    out = torch.zeros(b, c, h, w, dtype=torch.float64)
    for y in range(h):
        for xx in range(w):
            taps = [(i, j) for i in range(k) for j in range(k)
                    if 0 <= y + i - r < h and 0 <= xx + j - r < w]
            weights = torch.softmax(torch.stack([ld[:, i * k + j, y, xx] for i, j in taps], 1), dim=1)
            for t, (i, j) in enumerate(taps):
                out[:, :, y, xx] += weights[:, t, None] * xd[:, :, y + i - r, xx + j - r]
    return out
