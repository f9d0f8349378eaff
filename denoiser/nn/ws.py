"""WeightSharingFilter: the WS baseline's filter (our reading of a paper without public code).

Baseline after Fan, Wang, Huo, Bao, "Real-time Monte Carlo Denoising with the Weight Sharing
Kernel Prediction Network" (EGSR 2021, CGF 40(4)). **Taken from the paper:** instead of a full
k x k kernel per *output* pixel (k^2 channels per pixel), the network predicts a compact encoding
of the kernel map, one weight per *source* pixel, and every kernel that covers a pixel uses that
same weight (the kernels are "decoded" by unfolding the weight map); several such kernels are
fused with predicted per-pixel weights ("kernel fusion"), which lets the filter scale to large
footprints at the cost of a few channels.

**Our decisions** (the paper's exact encoding, kernel set and fusion are not reproduced here):

* one weight map per kernel j (not one for all), positive and bounded:
  ``s_j(q) = exp(M * tanh(z_j(q) / M))`` with ``M = max_log_weight`` (ratio of two weights at
  most ``exp(2M)``; the gradient never vanishes exactly, unlike a hard clamp);
* kernel j is a (dilated) k_j x k_j box over source pixels weighted by ``s_j``, normalised over
  the in-image taps; with ``x1 = [x, 1]`` the weighted box sum of ``s_j * x1`` divided by its
  last channel is (for a pixel p, window N_j(p) of size k_j and dilation d_j)::

      y_j(p) = sum_{q in N_j(p)} s_j(q) x(q) / sum_{q in N_j(p)} s_j(q)

  computed as two separable depthwise convolutions with a ones filter (O(k) per pixel, not
  O(k^2); zero padding, so taps outside the image carry no weight);
* fusion: ``output = sum_j softmax_j(norm(f))_j * y_j`` with the fusion logits ``f`` normalised
  by :func:`~denoiser.nn.kernels.scale_logits` (``logit_scale``). Each y_j is a convex
  combination of input pixels and so is their convex fusion: the output stays within the
  input's range, finite whatever the logits. A size-1 kernel in ``kernel_sizes`` is the identity
  (the noisy pixel itself), so the fusion can keep detail;
* full resolution only (no pyramid), all heads at level 0: ``head_channels = [2 * n]`` for n
  kernels (the n weight maps, then the n fusion logits). Temporal blending stays
  :class:`~denoiser.nn.temporal.TemporalRecurrence`'s.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from denoiser.errors import ConfigError
from denoiser.nn.kernels import scale_logits
from denoiser.nn.pyramid import check_kernel_sizes, normalize, with_ones
from denoiser.nonfinite import nan_to_num


def box_sum(x: torch.Tensor, size: int, dilation: int = 1) -> torch.Tensor:
    """Sum over the dilated ``size x size`` window centred on each pixel, zeros outside.

    x: ``[B, C, H, W]`` float32 -> ``[B, C, H, W]``: ``out[p] = sum_{|i|,|j| <= size//2} x[p + d*(i, j)]``.
    Two depthwise convolutions with a ones filter (rows, then columns); the filter is built
    from NumPy, so a trace records a constant of known shape (the ONNX exporter needs one).
    """
    if size == 1:
        return x
    c = x.shape[1]
    pad = dilation * (size // 2)
    ones = torch.from_numpy(np.ones((int(c), 1, size, 1), np.float32)).to(device=x.device, dtype=x.dtype)
    x = F.conv2d(x, ones, padding=(pad, 0), dilation=(dilation, 1), groups=c)
    return F.conv2d(x, ones.transpose(2, 3), padding=(0, pad), dilation=(1, dilation), groups=c)


class WeightSharingFilter(nn.Module):
    """Fusion of weight-sharing kernels (the WS baseline; module docstring for the reading).

    Args:
        kernel_sizes: odd window size per kernel (1 = identity), e.g. ``[1, 3, 5, 9]``.
        dilations: dilation per kernel (None = all 1); a size-k kernel of dilation d spans
            ``d*(k-1)+1`` pixels.
        logit_scale: sharpness of the fusion softmax over scale-normalised logits (None = raw).
        max_log_weight: bound M of the log shared weights (``exp(M * tanh(z / M))``).

    ``head_channels = [2 * len(kernel_sizes)]``: shared-weight logits, then fusion logits.
    """

    def __init__(self, kernel_sizes: Sequence[int], dilations: Sequence[int] | None = None,
                 logit_scale: float | None = None, max_log_weight: float = 8.0):
        super().__init__()
        self.kernel_sizes = check_kernel_sizes(kernel_sizes)
        self.dilations = [1] * len(self.kernel_sizes) if dilations is None else [int(d) for d in dilations]
        if len(self.dilations) != len(self.kernel_sizes) or any(d < 1 for d in self.dilations):
            raise ConfigError(f"net.filter.dilations: need one dilation >= 1 per kernel size "
                              f"{self.kernel_sizes}, got {list(dilations or [])}")
        if not max_log_weight > 0:
            raise ConfigError(f"net.filter.max_log_weight: must be > 0, got {max_log_weight}")
        self.logit_scale = None if logit_scale is None else float(logit_scale)
        self.max_log_weight = float(max_log_weight)
        self.kernels = len(self.kernel_sizes)
        self.head_channels = [2 * self.kernels]
        self.multiple = 1

    def shared_weights(self, logits: torch.Tensor) -> torch.Tensor:
        """``[B, n, H, W]`` weight logits -> positive shared weights ``[B, n, H, W]`` float32 in
        ``[exp(-M), exp(M)]`` (non-finite logits replaced first)."""
        z = nan_to_num(logits.float(), nan=0.0, posinf=1e4, neginf=-1e4)
        m = self.max_log_weight
        return torch.exp(m * torch.tanh(z / m))

    def forward(self, x: torch.Tensor, heads: Sequence[torch.Tensor], scale: torch.Tensor
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """x: ``[B, 3, H, W]`` linear radiance; heads[0]: ``[B, 2n, H, W]``; scale: ``[B, 1, 1, 1]`` (unused).

        Returns ``(output [B, 3, H, W] float32, {"fusion": [B, n, H, W]})``.
        """
        with torch.autocast(device_type=x.device.type, enabled=False):
            x1 = with_ones(x)
            head = heads[0].float()
            shared = self.shared_weights(head[:, : self.kernels])
            fusion = torch.softmax(scale_logits(head[:, self.kernels:], self.logit_scale), dim=1)
            output = None
            for j, (size, dilation) in enumerate(zip(self.kernel_sizes, self.dilations)):
                y = normalize(box_sum(shared[:, j: j + 1] * x1, size, dilation), x1[:, :-1])
                term = fusion[:, j: j + 1] * y
                output = term if output is None else output + term
            return output, {"fusion": fusion}
