"""Ablation filters selected by config in place of :class:`~denoiser.nn.pyramid.PyramidFilter`.

Both take the same ``kernel_sizes`` argument as the pyramid so that an ablation config only
swaps ``_target_`` (``conf/ablation/no_pyramid.yaml``, ``conf/ablation/direct.yaml``).

* :class:`SingleKernelFilter` (``no_pyramid``): one full-resolution per-pixel kernel of size
  ``max(kernel_sizes)`` (softmax-normalised, so every output pixel is a convex combination of
  input pixels).
* :class:`DirectColor` (``direct``): the U-Net predicts the color itself, in the input's
  log space: ``output = expm1(min(softplus(h), MAX_LOG)) * scale`` with ``scale`` the color
  scale of :func:`~denoiser.nn.inputs.color_scale` and ``MAX_LOG = log1p(65504 / 1e-3)``, the
  largest value the input transform can produce; the output is finite and >= 0 by construction.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from denoiser.nn.graph_mode import in_graph
from denoiser.nn.inputs import COLOR_EPS, POSINF
from denoiser.nn.kernels import apply_kernels
from denoiser.nn.pyramid import check_kernel_sizes

MAX_LOG = math.log1p(POSINF / COLOR_EPS)


class SingleKernelFilter(nn.Module):
    """One full-resolution kernel of size ``max(kernel_sizes)`` (the ``no_pyramid`` ablation);
    ``logit_scale`` as in :class:`~denoiser.nn.pyramid.PyramidFilter`."""

    def __init__(self, kernel_sizes: Sequence[int], logit_scale: float | None = None):
        super().__init__()
        self.kernel_size = max(check_kernel_sizes(kernel_sizes))
        self.logit_scale = None if logit_scale is None else float(logit_scale)
        self.head_channels = [self.kernel_size ** 2]
        self.multiple = 1

    def forward(self, x: torch.Tensor, heads: Sequence[torch.Tensor], scale: torch.Tensor
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """x: ``[B, 3, H, W]`` linear; heads[0]: ``[B, k*k, H, W]`` -> ``([B, 3, H, W], {})``."""
        with torch.autocast(device_type=x.device.type, enabled=False):
            return apply_kernels(x.float(), heads[0], self.logit_scale), {}


class DirectColor(nn.Module):
    """Direct color prediction (the ``direct`` ablation); ``kernel_sizes`` and ``logit_scale`` are
    accepted (the net config's filter keys) and unused."""

    def __init__(self, kernel_sizes: Sequence[int] | None = None, logit_scale: float | None = None):
        super().__init__()
        self.head_channels = [3]
        self.multiple = 1

    def forward(self, x: torch.Tensor, heads: Sequence[torch.Tensor], scale: torch.Tensor
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """x: ``[B, 3, H, W]`` (unused); heads[0]: ``[B, 3, H, W]``; scale ``[B, 1, 1, 1]``.

        Returns ``([B, 3, H, W] float32 >= 0, {})``.
        """
        with torch.autocast(device_type=x.device.type, enabled=False):
            log = F.softplus(heads[0].float()).clamp_max(MAX_LOG)
            # ONNX has no Expm1: a graph spells it exp - 1 (off by under 1.2e-7 absolute, times the scale)
            return (torch.exp(log) - 1.0 if in_graph() else torch.expm1(log)) * scale, {}
