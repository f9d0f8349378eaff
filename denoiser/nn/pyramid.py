"""PyramidFilter: partitioning pyramid of per-pixel kernels (after Balint et al. 2023).

With L levels and kernel sizes ``k_0..k_{L-1}`` (finest first), the network predicts at full
resolution L partition logits and the level-0 kernel logits, and at scale 1/2^i the level-i
kernel logits. For linear radiance ``x`` ``[B, 3, H, W]``:

    w       = softmax_L(norm(partition logits))                  (float32, sums to 1 per pixel)
    p_i     = avg_pool_{2^i}(w_i * [x, 1])                        partition i, [B, 4, H/2^i, W/2^i]
    y_i     = apply_kernels(p_i, norm(kernel logits of level i))  (softmax-normalised, float32)
    acc     = y_{L-1};  acc = up2_bilinear(acc) + y_i  for i = L-2 .. 0
    output  = acc[:, :3] / acc[:, 3:]    (x itself where acc[:, 3:] <= NORM_EPS)

``norm`` is the logit normalisation of :func:`~denoiser.nn.kernels.scale_logits` (``logit_scale``;
it keeps the softmaxes from saturating into a frozen state, e.g. the identity). The constant channel ``1`` travels through exactly the same non-negative linear operators as
``x``, and the division normalises the result: every output pixel is a convex combination of
input pixels, whatever the predicted weights and even next to the border (kernels renormalised
over in-image taps, clamping in the upsampling). The normaliser is a sum of positive float32
terms; only with extreme logits can it underflow, and there the input pixel is passed through. This normalisation is our addition to the cited method
(there the partitions preserve the image's total energy but not per-pixel convexity); it costs
one extra channel and guarantees the filter cannot create energy, NaN or overflow.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from denoiser.errors import ConfigError
from denoiser.nn.graph_mode import fused_kernels, unfused
from denoiser.nn.graph_ops import graph_node, scale_attributes
from denoiser.nn.kernels import apply_kernels, scale_logits
from denoiser.nn.parts import pointwise
from denoiser.nn.unet import FactoredHead

#: smallest normaliser used for division; below it the input pixel is passed through
NORM_EPS = 1e-30


def with_ones(x: torch.Tensor) -> torch.Tensor:
    """``[B, C, H, W]`` -> ``[B, C + 1, H, W]`` with a constant-1 channel appended (float32)."""
    x = x.float()
    return torch.cat([x, torch.ones_like(x[:, :1])], dim=1)


def normalize(acc: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
    """``[B, C + 1, H, W]`` filtered ``[x, 1]`` -> ``[B, C, H, W]`` = ``acc[:, :C] / acc[:, C]``,
    ``fallback [B, C, H, W]`` where ``acc[:, C] <= NORM_EPS``."""
    den = acc[:, -1:]
    return torch.where(den > NORM_EPS, acc[:, :-1] / den.clamp_min(NORM_EPS), fallback)


def partition_levels(x: torch.Tensor, head0: torch.Tensor, levels: int, logit_scale: float | None
                     ) -> tuple[torch.Tensor, torch.Tensor, list[torch.Tensor]]:
    """The partitioning step shared by the pyramid filters (float32, call without autocast).

    x: ``[B, 3, H, W]`` linear radiance; head0: ``[B, >= levels, H, W]`` whose first ``levels``
    channels are the partition logits. Returns ``(x1 [B, 4, H, W]`` = :func:`with_ones` of x,
    ``partition [B, L, H, W]`` softmax weights, ``parts``: level i's ``w_i * x1`` average-pooled
    to ``[B, 4, H/2^i, W/2^i]``).
    """
    x1 = with_ones(x)
    partition = torch.softmax(scale_logits(head0[:, :levels], logit_scale), dim=1)
    parts = []
    for i in range(levels):
        part = partition[:, i: i + 1] * x1
        parts.append(F.avg_pool2d(part, 2 ** i) if i > 0 else part)
    return x1, partition, parts


def check_kernel_sizes(kernel_sizes: Sequence[int]) -> list[int]:
    sizes = [int(k) for k in kernel_sizes]
    if not sizes or any(k < 1 or k % 2 == 0 for k in sizes):
        raise ConfigError(f"kernel.sizes: need one or more odd sizes >= 1, got {list(kernel_sizes)}")
    return sizes


class PyramidFilter(nn.Module):
    """Partitioning-pyramid kernel filter.

    Args:
        kernel_sizes: kernel size per level, finest first (``${kernel.sizes}``).
        logit_scale: sharpness of the partition and kernel softmaxes over scale-normalised
            logits (:func:`~denoiser.nn.kernels.scale_logits`); None = raw logits (configs from
            before it existed).

    ``head_channels[i]`` is what the U-Net head at scale 1/2^i must predict: level 0 has
    ``L + k_0^2`` channels (partition logits first), level i >= 1 ``k_i^2``.
    """

    #: heads[0] may be a :class:`~denoiser.nn.unet.FactoredHead` (exported graphs with matmul heads
    #: and the fused operations: one ``denoiser::PyramidFilterHead`` node computes its rows)
    reads_factored_head = True

    def __init__(self, kernel_sizes: Sequence[int], logit_scale: float | None = None):
        super().__init__()
        self.kernel_sizes = check_kernel_sizes(kernel_sizes)
        self.logit_scale = None if logit_scale is None else float(logit_scale)
        self.levels = len(self.kernel_sizes)
        self.head_channels = [self.levels + self.kernel_sizes[0] ** 2] + [
            k * k for k in self.kernel_sizes[1:]]
        self.multiple = 2 ** (self.levels - 1)

    def forward(self, x: torch.Tensor, heads: Sequence[torch.Tensor], scale: torch.Tensor
                ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """x: ``[B, 3, H, W]`` linear radiance (H, W multiples of 2^(L-1));
        heads[i]: ``[B, head_channels[i], H/2^i, W/2^i]`` (heads[0] also a
        :class:`~denoiser.nn.unet.FactoredHead`); scale: ``[B, 1, 1, 1]`` (unused).

        Returns ``(output [B, 3, H, W] float32, {"partition": [B, L, H, W]})``.
        """
        factored = isinstance(heads[0], FactoredHead)
        if fused_kernels():  # exported for OpenVINO with the project's extension: one node
            with torch.autocast(device_type=x.device.type, enabled=False):
                rest = [h.float() for h in heads[1:]]
                if factored:  # head 0 computed inside the node, never written (PyramidFilterHeadOp)
                    h0 = heads[0]
                    out = PyramidFilterHeadOp.apply(
                        x.float(), h0.skip0.float().permute(0, 2, 3, 1), h0.skip_weight.float(),
                        h0.upsampled_part().float(), tuple(self.kernel_sizes), self.logit_scale, h0.mode, h0.align,
                        *rest)
                else:
                    out = PyramidFilterOp.apply(x.float(), tuple(self.kernel_sizes), self.logit_scale,
                                                heads[0].float(), *rest)
            return out, {}
        if factored:
            heads = [heads[0].tensor()] + list(heads[1:])
        return pyramid_filter(x, heads, self.kernel_sizes, self.logit_scale)


def pyramid_filter(x: torch.Tensor, heads: Sequence[torch.Tensor], kernel_sizes: Sequence[int],
                   logit_scale: float | None) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """:meth:`PyramidFilter.forward` (same arguments and result; ``kernel_sizes``, ``logit_scale``
    as the module's)."""
    levels = len(kernel_sizes)
    with torch.autocast(device_type=x.device.type, enabled=False):
        head0 = heads[0].float()
        x1, partition, parts = partition_levels(x, head0, levels, logit_scale)
        logits = [head0[:, levels:]] + [heads[i].float() for i in range(1, levels)]
        filtered = [apply_kernels(part, logits[i], logit_scale) for i, part in enumerate(parts)]
        acc = filtered[-1]
        for i in range(levels - 2, -1, -1):
            acc = F.interpolate(acc, size=filtered[i].shape[-2:], mode="bilinear",
                                align_corners=False) + filtered[i]
        return normalize(acc, x1[:, :-1]), {"partition": partition}


# ----------------------------------------------------------------------------- export stubs


class PyramidFilterOp(torch.autograd.Function):
    """:meth:`denoiser.nn.pyramid.PyramidFilter.forward` recorded as one ``denoiser::PyramidFilter``
    node (inputs x and the L heads; attributes ``kernel_sizes``, ``scale``, ``has_scale``)."""

    @staticmethod
    def forward(ctx, x, kernel_sizes, scale, *heads):
        return unfused(pyramid_filter, x, heads, kernel_sizes, scale)[0]

    @staticmethod
    def symbolic(g, x, kernel_sizes, scale, *heads):
        return graph_node(g, "PyramidFilter", x, *heads, like=x, kernel_sizes=list(kernel_sizes),
                          **scale_attributes(scale))


class PyramidFilterHeadOp(torch.autograd.Function):
    """:meth:`denoiser.nn.pyramid.PyramidFilter.forward` with head 0 given by its factors
    (:class:`denoiser.nn.unet.FactoredHead`), recorded as one ``denoiser::PyramidFilterHead`` node:
    head 0 is ``weight @ skip + interpolate(z, (H, W), mode)``, computed row by row where the
    filter reads it instead of written at full resolution.

    forward(x ``[B, 3, H, W]``, skip ``[B, H, W, C_s]`` channels-last, weight ``[L + k0^2, C_s]``,
    z ``[B, L + k0^2, h, w]``, kernel_sizes, scale, mode, align, head_1 .. head_{L-1})
    -> ``[B, 3, H, W]`` float32, computed by the plain graph.
    """

    @staticmethod
    def forward(ctx, x, skip, weight, z, kernel_sizes, scale, mode, align, *heads):
        head0 = pointwise(weight, None, skip.permute(0, 3, 1, 2)) + F.interpolate(
            z, size=x.shape[-2:], mode=mode, align_corners=align)
        return unfused(pyramid_filter, x, (head0, *heads), kernel_sizes, scale)[0]

    @staticmethod
    def symbolic(g, x, skip, weight, z, kernel_sizes, scale, mode, align, *heads):
        return graph_node(g, "PyramidFilterHead", x, skip, weight, z, *heads, like=x,
                          kernel_sizes=list(kernel_sizes), mode=mode, **scale_attributes(scale))
